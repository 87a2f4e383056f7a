// How well the tracked needle's line is known (overlay layers "needle" and "target"): the
// covariances of both boards' poses, of the needle's tip and axis (its calibration) and the
// registration's expected error at the tumor, carried to the needle's line in CT by first-order
// propagation (a Jacobian by central differences of the exact chain T_ct_patient T_cam_patient^-1
// T_cam_needle). The line is described by where it crosses two planes across the nominal axis: the
// plane through the nominal tip and a plane at least 10 mm beyond it (the tumor's plane when that
// lies farther); its 95 % region is the ellipsoid of those four offsets at the chi-square 95 %
// point of 4 degrees of freedom. At the plane through the tumor centre across the axis the
// uncertainty is an ellipse (95 %: chi-square of 2 degrees of freedom). No rendering.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <utility>
#include <vector>

#include "planning/trajectories/needle_guidance.hpp"

namespace crepuscular::planning {

using Matrix6d = Eigen::Matrix<double, 6, 6>;

// One standard deviation of each source; zero: that source is exact.
struct NeedleUncertaintySources {
  // Covariances of the boards' poses T_cam_patient and T_cam_needle, [w (rad), t (mm)] as the
  // tracker reports them: w a small rotation applied in the camera frame (R <- exp(w) R), t added
  // to the translation.
  Matrix6d patient_pose = Matrix6d::Zero();
  Matrix6d needle_pose = Matrix6d::Zero();
  Eigen::Matrix3d tip_mm2 = Eigen::Matrix3d::Zero();  // of the tip, needle frame (pivot calibration)
  // Of each of the axis's two components across it (needle frame, rad), for a spin-calibrated
  // axis. axis_from_tip: the axis is the direction from the needle frame's origin to the tip, so
  // it moves with the tip's error.
  double axis_stddev_rad = 0;
  bool axis_from_tip = false;
  // The registration's expected target registration error at the tumor (RMS, 3D, mm), taken as
  // an isotropic error of every registered point near the tumor: TRE^2 / 3 per axis.
  double registration_tre_mm = 0;
};

// chi-square 95 % points.
constexpr double kChi2_95_2dof = 5.991464547107979;
constexpr double kChi2_95_4dof = 9.487729036781154;

struct LineUncertainty {
  bool valid = false;  // false: the axis is zero or the chain not finite
  Eigen::Vector3d tip = Eigen::Vector3d::Zero();    // nominal tip, CT
  Eigen::Vector3d axis = Eigen::Vector3d::UnitZ();  // nominal unit axis, into the body
  Eigen::Vector3d e1 = Eigen::Vector3d::UnitX(), e2 = Eigen::Vector3d::UnitY();  // across the axis
  double far_depth_mm = 10;  // the second plane's distance from the tip along the axis
  // Covariance (mm^2) of the line's offsets along e1, e2 at the tip's plane and at the far plane.
  Eigen::Matrix4d covariance = Eigen::Matrix4d::Zero();
  // At the plane through the tumor centre across the axis: the nominal crossing, its depth from
  // the tip, the crossing's covariance (e1, e2; mm^2) and its 95 % ellipse (semi-axes, mm; the
  // major one along major_direction, CT).
  Eigen::Vector3d tumor_crossing = Eigen::Vector3d::Zero();
  double tumor_depth_mm = 0;
  Eigen::Matrix2d at_tumor = Eigen::Matrix2d::Zero();
  double major95_mm = 0, minor95_mm = 0;
  Eigen::Vector3d major_direction = Eigen::Vector3d::UnitX();

  // The offsets [tip plane e1, e2, far plane e1, e2] of the line tip + s axis (axis need not be
  // unit); NaN when it runs along the planes.
  Eigen::Vector4d offsets(const Eigen::Vector3d& tip, const Eigen::Vector3d& axis) const;
  // Squared Mahalanobis distance of a line from the nominal one (a covariance without spread in
  // some direction counts a tenth of a micrometre there).
  double distance2(const Eigen::Vector3d& tip, const Eigen::Vector3d& axis) const;
  bool inside95(const Eigen::Vector3d& tip, const Eigen::Vector3d& axis) const {
    return distance2(tip, axis) <= kChi2_95_4dof;
  }
  // Lines of the 95 % region (tip, unit axis): along each principal direction of the covariance
  // both ways and along the diagonals of the two largest pairs, each at a third, two thirds and
  // the whole of the region's extent (48 lines, none when the covariance is zero).
  std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3d>> region_lines() const;
  // n points of the 95 % ellipse at the tumor's plane (CT).
  std::vector<Eigen::Vector3d> ellipse_at_tumor(int n) const;
};

// The uncertainty of the line of a needle whose boards the camera sees at T_cam_patient and
// T_cam_needle, registered by T_ct_patient, tip and axis in the needle frame, against the tumor
// centre (CT).
LineUncertainty needle_line_uncertainty(const Eigen::Isometry3d& T_ct_patient,
                                        const Eigen::Isometry3d& T_cam_patient,
                                        const Eigen::Isometry3d& T_cam_needle,
                                        const Eigen::Vector3d& tip_in_needle,
                                        const Eigen::Vector3d& axis_in_needle,
                                        const Eigen::Vector3d& tumor_centre,
                                        const NeedleUncertaintySources& sources);

// Safe < medium < unknown < dangerous.
int needle_safety_severity(NeedleSafety s);

// The worst class (NeedleGuide::line_safety) over the lines of the 95 % region, and the nominal
// line's own class; uncertain when a line of the region is worse than the nominal one.
struct RegionSafety {
  NeedleSafety nominal = NeedleSafety::kUnknown;
  NeedleSafety worst = NeedleSafety::kUnknown;
  int lines = 0;  // lines of the region evaluated
  bool uncertain() const { return needle_safety_severity(worst) > needle_safety_severity(nominal); }
};
RegionSafety region_safety(const NeedleGuide& guide, const LineUncertainty& line,
                           NeedleSafety nominal);

}  // namespace crepuscular::planning
