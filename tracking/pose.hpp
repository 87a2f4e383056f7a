// Pose of a marker board from the detected corners of its tags (docs/ARCHITECTURE.md §7): a planar
// PnP start (IPPE, both solutions when a single tag is ambiguous), then Ceres refinement of the
// reprojection error through the full camera model (distortion included) with a robust loss, and
// the covariance of the six pose parameters.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <vector>

#include "calibration/camera_model.hpp"
#include "tracking/board.hpp"
#include "tracking/detector.hpp"

namespace crepuscular::tracking {

struct PoseOptions {
  double huber_px = 1.0;    // Huber loss scale: residuals beyond this many pixels weigh less
  int max_iterations = 30;  // Levenberg-Marquardt iterations
  bool covariance = true;   // compute the 6x6 covariance (ceres::Covariance)
  // Two IPPE solutions whose refined RMS errors differ by less than this factor are ambiguous;
  // then the previous pose (when given) decides, else the lower error.
  double ambiguity_ratio = 3.0;
  double max_rms_px = 3.0;  // a refined pose with a larger RMS error is rejected
};

// Corners of one board matched to detections (same order in both vectors).
struct BoardCorners {
  std::vector<Eigen::Vector3d> board_mm;  // corner in the board frame
  std::vector<Eigen::Vector2d> pixels;    // detected corner
  std::vector<int> tag_ids;               // the tag of each group of four corners
};

// The corners of `board`'s tags among `detections` (tags of other boards, and detections naming
// another family than the board's, are ignored; a tag detected twice keeps the detection with the
// larger decision margin).
BoardCorners match_board_corners(const Board& board, const std::vector<Detection>& detections);

// Whether a detection is one of `board`'s tags: its id is on the board, and its family is the
// board's (a detection naming no family counts as the board's).
bool belongs_to(const Board& board, const Detection& detection);

struct BoardPose {
  bool valid = false;
  Eigen::Isometry3d T_cam_board = Eigen::Isometry3d::Identity();
  double rms_px = 0;  // RMS reprojection error over all corners (pixels)
  // Covariance of [w (rad), t (mm)]: w the rotation vector of a small rotation applied in the
  // camera frame (R_cam_board <- exp(w) R_cam_board), t the translation of T_cam_board. From
  // ceres::Covariance, scaled by the residual variance sigma^2 = sum(r^2) / (2 n - 6), floored at
  // (0.05 px)^2.
  Eigen::Matrix<double, 6, 6> covariance = Eigen::Matrix<double, 6, 6>::Zero();
  bool covariance_valid = false;
  int tags = 0;
  int corners = 0;
  bool ambiguous = false;  // two solutions explained the corners about equally well
  std::string problem;     // why the pose is not valid
};

// Pose of one board from its matched corners. `previous` (may be null) is the board's last pose,
// used to choose between the two IPPE solutions when they are ambiguous. Needs at least one tag
// (four corners).
BoardPose estimate_board_pose(const calibration::CameraModel& camera, const BoardCorners& corners,
                              const Eigen::Isometry3d* previous, const PoseOptions& options = {});

// Pixel of a board point through the camera model (its lens model included); templated so that
// Ceres differentiates it. calibration::CameraModel::project_generic's math.
template <typename T>
void project_with_distortion(const calibration::CameraModel& cam, const T p[3], T pixel[2]) {
  cam.project_point(p, pixel);
}

}  // namespace crepuscular::tracking
