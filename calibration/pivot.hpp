// Needle calibration from tracked needle-board poses T_cam_needle:
// - pivot: the tip rests in a divot while the needle pivots; solves the tip in the needle frame and
//   the pivot point in the camera frame with the tip's uncertainty (least squares, with a robust
//   pass that leaves out poses where the tip slipped);
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
  // Cauchy loss scale of the robust pass: at least this, else the robust 3D RMS of the
  // least-squares residuals.
  double robust_scale_mm = 1.0;
  // Poses whose residual after the robust pass exceeds max(this, 3 x the robust 3D RMS) are
  // outliers: reported and left out of the final least squares.
  double outlier_mm = 2.0;
  // Refuse a tip whose 3D standard deviation (square root of the trace of its covariance: the RMS
  // 3D tip error to expect, which the largest axis would understate) is larger. 0.5 mm passes
  // 1000-1151 hand-held poses at 3-3.2 mm residual RMS (0.22 mm) and refuses 40 such poses
  // (1.0 mm).
  double max_tip_stddev_mm = 0.5;
  double warn_rms_mm = 2.0;   // a larger inlier residual RMS is logged as a warning, not refused
  double max_tip_mm = 500.0;  // refuse a tip farther than this from the needle board
};

struct PivotResult {
  Eigen::Vector3d tip_needle = Eigen::Vector3d::Zero();  // tip in the needle frame (mm)
  Eigen::Vector3d pivot_cam = Eigen::Vector3d::Zero();   // pivot point in the camera frame (mm)
  // Covariance of the tip (mm^2, needle frame): sigma^2 (A^T A)^-1 of the inliers' linear system
  // [R_i -I][t; p] = -t_i restricted to the tip, sigma^2 = inlier sum of squares / (3 n - 6).
  // It assumes independent poses: frames of a fast camera that share their error make it low.
  Eigen::Matrix3d tip_covariance_mm2 = Eigen::Matrix3d::Zero();
  Eigen::Vector3d tip_stddev_mm = Eigen::Vector3d::Zero();  // per axis, needle frame
  double tip_stddev_3d_mm = 0;  // sqrt(trace of the covariance): the RMS 3D tip error expected
  double rms_mm = 0;            // RMS of |R_i t + t_i - p| over the inlier poses
  Eigen::Vector3d rms_axis_mm = Eigen::Vector3d::Zero();  // the same per camera axis
  double rms_all_mm = 0;                                  // the 3D RMS over all poses
  std::vector<double> residual_mm;   // per pose, |R_i t + t_i - p| of the final tip and pivot
  std::vector<bool> outlier;         // per pose
  std::vector<int> outlier_indices;  // indices of the outlier poses, ascending
  int inliers = 0;
  double rotation_spread_deg = 0;  // largest angle between two poses
  double axis_spread_deg = 0;      // spread about the least excited axis
  Eigen::Vector3d linear_tip_needle = Eigen::Vector3d::Zero();  // least squares over all poses
  std::vector<std::string> warnings;  // what was logged as a warning (large residual RMS)
  std::string solver_report;          // of the robust pass
};

// Tip and pivot point from poses of a needle pivoting about its tip: least squares over all
// poses, a robust pass (Ceres, Cauchy loss) that finds the poses which disagree, then least
// squares over the others. Logs the result (tip, its standard deviation, residuals, motion,
// outliers) and a warning when the inlier RMS is above warn_rms_mm. Throws Error with advice when
// there are too few poses, a pose is implausible (> 10 m away), the motion does not determine
// the tip (too small, or about one axis only), fewer than min_poses poses agree, the tip's 3D
// standard deviation is above max_tip_stddev_mm, or the tip is more than max_tip_mm from the board.
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
