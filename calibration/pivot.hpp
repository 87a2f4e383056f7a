// Needle calibration from tracked needle-board poses T_cam_needle:
// - pivot: the tip rests in a divot while the needle pivots; solves the tip in the needle frame and
//   the pivot point in the camera frame (linear least squares, then Ceres with a robust loss);
// - spin: the needle turns about its own axis; gives the axis direction in the needle frame.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <optional>
#include <string>
#include <vector>

namespace crepuscular::calibration {

struct PivotOptions {
  int min_poses = 8;
  double min_rotation_spread_deg = 15.0;  // largest angle between two poses' orientations
  double min_axis_spread_deg = 8.0;       // tilt about the least moved rotation axis
  double robust_scale_mm = 1.0;           // Cauchy loss scale
  double outlier_mm = 2.0;  // residuals above max(this, 3 x robust RMS) are reported as outliers
  double max_rms_mm = 2.0;  // refuse a result whose inlier RMS is larger
  double max_tip_mm = 500.0;  // refuse a tip farther than this from the needle board
};

struct PivotResult {
  Eigen::Vector3d tip_needle = Eigen::Vector3d::Zero();  // tip in the needle frame (mm)
  Eigen::Vector3d pivot_cam = Eigen::Vector3d::Zero();   // pivot point in the camera frame (mm)
  Eigen::Vector3d tip_stddev_mm = Eigen::Vector3d::Zero();  // per axis, needle frame
  double rms_mm = 0;         // RMS of |R_i t + t_i - p| over the inlier poses
  double rms_all_mm = 0;     // the same over all poses
  std::vector<double> residual_mm;  // per pose
  std::vector<bool> outlier;        // per pose
  int inliers = 0;
  double rotation_spread_deg = 0;  // largest angle between two poses
  double axis_spread_deg = 0;      // spread about the least excited axis
  Eigen::Vector3d linear_tip_needle = Eigen::Vector3d::Zero();  // closed-form start
  std::string solver_report;
};

// Throws Error with advice when there are too few poses, a pose is implausible (> 10 m away), the
// motion does not determine the tip (too small, or about one axis only), or the result fails the
// quality gates (inlier RMS > max_rms_mm, tip > max_tip_mm from the board).
PivotResult calibrate_pivot(const std::vector<Eigen::Isometry3d>& T_cam_needle,
                            const PivotOptions& options = {});

struct SpinOptions {
  int min_poses = 6;
  double min_rotation_deg = 30.0;  // the needle must turn at least this far about its axis
};

struct SpinResult {
  Eigen::Vector3d axis_needle = Eigen::Vector3d::UnitZ();  // unit direction, needle frame
  Eigen::Vector3d point_needle = Eigen::Vector3d::Zero();  // a point on the axis, needle frame
  double rotation_range_deg = 0;  // largest rotation between two poses
  double axis_rms_deg = 0;        // angle between each relative rotation's axis and the fit (RMS)
  double rms_mm = 0;              // how far points on the fitted axis move, RMS over poses
  std::optional<double> tip_to_axis_mm;  // distance of the pivot-calibrated tip from the axis
};

// Axis of the relative rotations (least squares). When `tip_needle` is given the direction points
// from the needle frame's origin toward the tip and the point on the axis is the one nearest the
// tip; otherwise the point is nearest the origin. Throws Error with advice on too little rotation.
SpinResult calibrate_spin(const std::vector<Eigen::Isometry3d>& T_cam_needle,
                          const std::optional<Eigen::Vector3d>& tip_needle = std::nullopt,
                          const SpinOptions& options = {});

}  // namespace crepuscular::calibration
