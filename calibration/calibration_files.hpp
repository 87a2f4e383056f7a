// Calibration result files that `crepuscular guide` reads: camera.yaml (intrinsics), needle.yaml
// (pivot and spin) and registration.yaml (T_ct_patient). OpenCV FileStorage YAML, each with the
// date, the inputs and the errors of the calibration that made it. Written through a temporary
// file and a rename: a failed run leaves no half-written file.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "calibration/intrinsics.hpp"

namespace crepuscular::calibration {

// Current UTC time as ISO 8601, e.g. "2026-11-23T10:38:10Z" (foundation's utc_now_iso8601).
std::string utc_timestamp();

// camera.yaml: camera_matrix, distortion_coefficients, image_width, image_height (read by
// CameraModel::read_yaml, OpenCV and ROS tools) plus calibration_date, inputs, board, rms_px,
// per-view errors and the standard deviation of every parameter.
void write_camera_calibration(const std::string& path, const IntrinsicsResult& result,
                              const std::string& board, const std::vector<std::string>& inputs);

struct NeedleCalibration {
  std::string date;                                      // ISO 8601 UTC
  std::vector<std::string> inputs;                       // files the calibration was computed from
  std::string board;                                     // needle board name
  Eigen::Vector3d tip_needle = Eigen::Vector3d::Zero();  // mm, needle frame
  Eigen::Vector3d tip_stddev_mm = Eigen::Vector3d::Zero();  // per axis
  double tip_stddev_3d_mm = 0;  // sqrt of the trace of the tip's covariance (0: not recorded)
  Eigen::Vector3d pivot_cam = Eigen::Vector3d::Zero();          // pivot point, camera frame (mm)
  double pivot_rms_mm = 0;                                      // inlier residual RMS, 3D
  Eigen::Vector3d pivot_rms_axis_mm = Eigen::Vector3d::Zero();  // the same per camera axis
  double pivot_rms_all_mm = 0;                                  // 3D RMS over all poses
  int poses_used = 0;
  int poses_total = 0;
  double rotation_spread_deg = 0;  // largest angle between two poses
  double least_axis_tilt_deg = 0;  // tilt about the least moved rotation axis
  // Frame numbers of the input (poses CSV frame column, recording frame index) of the poses left
  // out as outliers; their count is written as `outliers`.
  std::vector<int64_t> outlier_frames;
  // From spin calibration, when it was done: unit axis direction (needle frame), its fit quality.
  std::optional<Eigen::Vector3d> axis_needle;
  double axis_rms_deg = 0;
  double tip_to_axis_mm = 0;
};
void write_needle_calibration(const std::string& path, const NeedleCalibration& needle);
// Throws Error naming the file and the field when it is missing or malformed.
NeedleCalibration read_needle_calibration(const std::string& path);

struct RegistrationRecord {
  std::string date;
  std::vector<std::string> inputs;
  std::string board;  // patient board name
  Eigen::Isometry3d T_ct_patient = Eigen::Isometry3d::Identity();
  std::vector<Eigen::Vector3d> board_fiducials;  // patient frame, as paired (unmatched ones left out)
  std::vector<Eigen::Vector3d> ct_fiducials;     // CT LPS mm, same order
  std::vector<double> fre_mm;                    // per pair
  double fre_rms_mm = 0;
  double fle_mm = 0;
  int fiducials_in_board = 0;
  int fiducials_in_ct = 0;
  std::optional<Eigen::Vector3d> target_ct;  // where the expected TRE was evaluated (tumor centroid)
  double expected_tre_mm = 0;
};
void write_registration(const std::string& path, const RegistrationRecord& record);
RegistrationRecord read_registration(const std::string& path);

}  // namespace crepuscular::calibration
