// Pivot and spin calibration of the needle (see pivot.hpp).
#include "calibration/pivot.hpp"

#include <fmt/format.h>

#include <ceres/ceres.h>
#include <spdlog/spdlog.h>

#include <Eigen/Eigenvalues>
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <numeric>
#include <sstream>

#include "foundation/error.hpp"

namespace crepuscular::calibration {
namespace {

constexpr double kPi = 3.14159265358979323846;

double rotation_angle_deg(const Eigen::Matrix3d& R) {
  return Eigen::AngleAxisd(R).angle() * 180.0 / kPi;
}

double max_pairwise_angle_deg(const std::vector<Eigen::Isometry3d>& poses) {
  double spread = 0;
  for (size_t a = 0; a < poses.size(); ++a) {
    for (size_t b = a + 1; b < poses.size(); ++b) {
      spread = std::max(spread,
                        rotation_angle_deg(poses[a].linear().transpose() * poses[b].linear()));
    }
  }
  return spread;
}

// Residual R_i t + t_i - p (mm) of one pose; parameters tip t (needle frame), pivot p (camera).
struct PivotCost {
  explicit PivotCost(const Eigen::Isometry3d& T) : R_(T.linear()), t_(T.translation()) {}
  template <typename T>
  bool operator()(const T* tip, const T* pivot, T* residual) const {
    for (int r = 0; r < 3; ++r) {
      residual[r] = T(R_(r, 0)) * tip[0] + T(R_(r, 1)) * tip[1] + T(R_(r, 2)) * tip[2] +
                    T(t_(r)) - pivot[r];
    }
    return true;
  }
  static ceres::CostFunction* Create(const Eigen::Isometry3d& T) {
    return new ceres::AutoDiffCostFunction<PivotCost, 3, 3, 3>(new PivotCost(T));
  }
  Eigen::Matrix3d R_;
  Eigen::Vector3d t_;
};

void check_poses(const std::vector<Eigen::Isometry3d>& poses, const char* what) {
  for (size_t i = 0; i < poses.size(); ++i) {
    const Eigen::Matrix3d& R = poses[i].linear();
    if (!poses[i].matrix().allFinite() ||
        (R.transpose() * R - Eigen::Matrix3d::Identity()).norm() > 1e-6 || R.determinant() < 0) {
      throw Error(std::string(what) + ": pose " + std::to_string(i) +
                  " is not a rigid transform (rotation not orthonormal or not finite)");
    }
    // A tracked board farther than 10 m from the camera is not a measurement.
    if (poses[i].translation().norm() > 10000.0) {
      throw Error(std::string(what) + ": pose " + std::to_string(i) + " puts the needle board " +
                  fmt::format("{:.3g}", poses[i].translation().norm()) +
                  " mm from the camera (at most 10 m is plausible); remove that row");
    }
  }
}

void check_pivot_pose_count(int n, const PivotOptions& options) {
  if (n < options.min_poses) {
    throw Error("pivot calibration: " + std::to_string(n) + " needle poses (at least " +
                std::to_string(options.min_poses) +
                " needed). Record the needle board while pivoting the needle about its resting "
                "tip for 10-20 s.");
  }
}

// Spread about the least excited axis (degrees): smallest singular value of the stacked
// R_i - mean(R).
double least_axis_spread_deg(const std::vector<Eigen::Isometry3d>& T_cam_needle) {
  const int n = int(T_cam_needle.size());
  Eigen::Matrix3d mean = Eigen::Matrix3d::Zero();
  for (const auto& T : T_cam_needle) mean += T.linear();
  mean /= n;
  Eigen::MatrixXd D(3 * n, 3);
  for (int i = 0; i < n; ++i) D.block<3, 3>(3 * i, 0) = T_cam_needle[size_t(i)].linear() - mean;
  const double smin = Eigen::JacobiSVD<Eigen::MatrixXd>(D).singularValues()(2);
  return std::asin(std::min(1.0, smin / std::sqrt(double(n)))) * 180.0 / kPi;
}

// Throws Error with advice when the spreads of `result` are below the options' minimums.
void check_pivot_motion(const PivotResult& result, const PivotOptions& options) {
  if (result.rotation_spread_deg < options.min_rotation_spread_deg ||
      result.axis_spread_deg < options.min_axis_spread_deg) {
    std::ostringstream msg;
    msg.precision(1);
    msg << std::fixed << "pivot calibration: the pivoting motion is too small to determine the tip "
        << "(largest turn " << result.rotation_spread_deg << " degrees, at least "
        << options.min_rotation_spread_deg << " needed; tilt about the least moved axis "
        << result.axis_spread_deg << " degrees, at least " << options.min_axis_spread_deg
        << " needed). Keep the tip in the divot and pivot the needle in a cone of 20-40 degrees: "
           "forward, backward, left and right. Turning it about its own axis or along one line "
           "only leaves the tip undetermined.";
    throw Error(msg.str());
  }
}

// The linear system [R_i  -I] [t; p] = -t_i of all poses (3 rows per pose).
struct PivotSystem {
  Eigen::MatrixXd A;
  Eigen::VectorXd b;
};

PivotSystem linear_pivot_system(const std::vector<Eigen::Isometry3d>& T_cam_needle) {
  const int n = int(T_cam_needle.size());
  PivotSystem system{Eigen::MatrixXd(3 * n, 6), Eigen::VectorXd(3 * n)};
  for (int i = 0; i < n; ++i) {
    system.A.block<3, 3>(3 * i, 0) = T_cam_needle[size_t(i)].linear();
    system.A.block<3, 3>(3 * i, 3) = -Eigen::Matrix3d::Identity();
    system.b.segment<3>(3 * i) = -T_cam_needle[size_t(i)].translation();
  }
  return system;
}

// Robust refinement of tip and pivot (in place) over the poses `rows`: a Cauchy loss bounds the
// pull of poses where the tip slipped or the board was mis-detected.
ceres::Solver::Summary solve_robust(const std::vector<Eigen::Isometry3d>& T_cam_needle,
                                    const std::vector<int>& rows, double robust_scale_mm,
                                    double* tip, double* pivot) {
  ceres::Problem problem;
  for (int i : rows) {
    problem.AddResidualBlock(PivotCost::Create(T_cam_needle[size_t(i)]),
                             new ceres::CauchyLoss(robust_scale_mm), tip, pivot);
  }
  ceres::Solver::Options solver_options;
  solver_options.linear_solver_type = ceres::DENSE_QR;
  solver_options.max_num_iterations = 100;
  ceres::Solver::Summary summary;
  ceres::Solve(solver_options, &problem, &summary);
  return summary;
}

// |T_i tip - pivot| of every pose (mm).
std::vector<double> pivot_residuals(const std::vector<Eigen::Isometry3d>& T_cam_needle,
                                    const Eigen::Vector3d& tip, const Eigen::Vector3d& pivot) {
  std::vector<double> r;
  for (const auto& T : T_cam_needle) r.push_back((T * tip - pivot).norm());
  return r;
}

// Marks as outliers the residuals above max(outlier_mm, 3 x robust RMS), the robust RMS being
// 1.4826 x the median residual (per axis, as a 3D RMS); counts the inliers and returns their rows.
std::vector<int> mark_outliers(PivotResult& result, const PivotOptions& options) {
  const std::vector<double>& r = result.residual_mm;
  const int n = int(r.size());
  std::vector<double> sorted = r;
  std::nth_element(sorted.begin(), sorted.begin() + n / 2, sorted.end());
  const double robust_rms = 1.4826 * sorted[size_t(n / 2)];
  const double limit = std::max(options.outlier_mm, 3.0 * robust_rms);
  result.outlier.assign(size_t(n), false);
  std::vector<int> in_rows;
  for (int i = 0; i < n; ++i) {
    if (r[size_t(i)] > limit) {
      result.outlier[size_t(i)] = true;
    } else {
      ++result.inliers;
      in_rows.push_back(i);
    }
  }
  return in_rows;
}

// Sum of the squared residuals, over the inliers only when `inliers_only`.
double sum_of_squares(const PivotResult& result, bool inliers_only) {
  double sum = 0;
  for (size_t i = 0; i < result.residual_mm.size(); ++i) {
    if (inliers_only && result.outlier[i]) continue;
    sum += result.residual_mm[i] * result.residual_mm[i];
  }
  return sum;
}

// Standard deviation of the tip: sigma^2 (A^T A)^-1 over the inlier rows of the linear system,
// sigma^2 per coordinate from the inliers' sum of squared residuals.
Eigen::Vector3d tip_stddev_mm(const Eigen::MatrixXd& A, const std::vector<int>& in_rows,
                              double sum_in) {
  const int inliers = int(in_rows.size());
  Eigen::MatrixXd Ai(3 * inliers, 6);
  for (size_t k = 0; k < in_rows.size(); ++k) {
    Ai.middleRows<3>(Eigen::Index(3 * k)) = A.middleRows<3>(3 * in_rows[k]);
  }
  const double sigma2 = sum_in / std::max(1, 3 * inliers - 6);
  const Eigen::Matrix<double, 6, 6> cov = sigma2 * (Ai.transpose() * Ai).inverse();
  return cov.diagonal().head<3>().cwiseSqrt();
}

}  // namespace

PivotResult calibrate_pivot(const std::vector<Eigen::Isometry3d>& T_cam_needle,
                            const PivotOptions& options) {
  const int n = int(T_cam_needle.size());
  check_pivot_pose_count(n, options);
  check_poses(T_cam_needle, "pivot calibration");
  PivotResult result;
  result.rotation_spread_deg = max_pairwise_angle_deg(T_cam_needle);
  result.axis_spread_deg = least_axis_spread_deg(T_cam_needle);
  check_pivot_motion(result, options);

  // Closed form in the least-squares sense, the start of the robust solve.
  const PivotSystem linear = linear_pivot_system(T_cam_needle);
  const Eigen::VectorXd x = linear.A.colPivHouseholderQr().solve(linear.b);
  double tip[3] = {x(0), x(1), x(2)};
  double pivot[3] = {x(3), x(4), x(5)};
  result.linear_tip_needle = x.head<3>();

  std::vector<int> all_rows(T_cam_needle.size());
  std::iota(all_rows.begin(), all_rows.end(), 0);
  const ceres::Solver::Summary summary =
      solve_robust(T_cam_needle, all_rows, options.robust_scale_mm, tip, pivot);
  result.solver_report = summary.BriefReport();
  if (!summary.IsSolutionUsable()) {
    throw Error("pivot calibration: the robust solve failed (" + summary.BriefReport() + ")");
  }
  result.tip_needle = Eigen::Vector3d(tip[0], tip[1], tip[2]);
  result.pivot_cam = Eigen::Vector3d(pivot[0], pivot[1], pivot[2]);
  result.residual_mm = pivot_residuals(T_cam_needle, result.tip_needle, result.pivot_cam);
  const double sum_all = sum_of_squares(result, false);
  const std::vector<int> in_rows = mark_outliers(result, options);

  // Without the outliers, solved again (their pull under the Cauchy loss is small, not zero).
  if (result.inliers < n && result.inliers >= options.min_poses) {
    result.solver_report =
        solve_robust(T_cam_needle, in_rows, options.robust_scale_mm, tip, pivot).BriefReport();
    result.tip_needle = Eigen::Vector3d(tip[0], tip[1], tip[2]);
    result.pivot_cam = Eigen::Vector3d(pivot[0], pivot[1], pivot[2]);
    result.residual_mm = pivot_residuals(T_cam_needle, result.tip_needle, result.pivot_cam);
  }
  const double sum_in = sum_of_squares(result, true);
  result.rms_mm = result.inliers > 0 ? std::sqrt(sum_in / result.inliers) : 0.0;
  result.rms_all_mm = std::sqrt(sum_all / n);
  if (result.inliers > 2) result.tip_stddev_mm = tip_stddev_mm(linear.A, in_rows, sum_in);
  // Quality gates: a tip far from its board, or poses that do not agree on one pivot point, are
  // refused with the reason rather than written for guidance to trust.
  if (!result.tip_needle.allFinite() || result.tip_needle.norm() > options.max_tip_mm) {
    throw Error(fmt::format("pivot calibration: the tip comes out {:.4g} mm from the needle board "
                            "(at most {:.0f} mm is plausible): the poses do not describe a "
                            "needle pivoting about its tip",
                            result.tip_needle.norm(), options.max_tip_mm));
  }
  if (!(result.rms_mm <= options.max_rms_mm)) {
    throw Error(fmt::format("pivot calibration: RMS {:.3g} mm over {} inlier poses (at most {:.2g} "
                            "mm accepted): the tip slipped in the divot or the board was tracked "
                            "poorly; record again",
                            result.rms_mm, result.inliers, options.max_rms_mm));
  }
  spdlog::info("pivot calibration: tip ({:.2f}, {:.2f}, {:.2f}) mm in the needle frame, RMS {:.3f} "
               "mm over {} of {} poses, rotation spread {:.1f} deg",
               tip[0], tip[1], tip[2], result.rms_mm, result.inliers, n,
               result.rotation_spread_deg);
  return result;
}

SpinResult calibrate_spin(const std::vector<Eigen::Isometry3d>& T_cam_needle,
                          const std::optional<Eigen::Vector3d>& tip_needle,
                          const SpinOptions& options) {
  const int n = int(T_cam_needle.size());
  if (n < options.min_poses) {
    throw Error("spin calibration: " + std::to_string(n) + " needle poses (at least " +
                std::to_string(options.min_poses) +
                " needed). Record the needle board while turning the needle about its own axis.");
  }
  check_poses(T_cam_needle, "spin calibration");
  SpinResult result;
  result.rotation_range_deg = max_pairwise_angle_deg(T_cam_needle);
  if (result.rotation_range_deg < options.min_rotation_deg) {
    std::ostringstream msg;
    msg.precision(1);
    msg << std::fixed << "spin calibration: the needle turned by at most "
        << result.rotation_range_deg << " degrees (at least " << options.min_rotation_deg
        << " needed). Turn the needle about its own axis by 90 degrees or more, in a guide or "
           "between two fingers, keeping the board in view.";
    throw Error(msg.str());
  }
  // Relative motions in the needle frame, each against every other pose: T_j^-1 T_i.
  std::vector<Eigen::Isometry3d> rel;
  for (int j = 0; j < n; ++j) {
    for (int i = j + 1; i < n; ++i) {
      rel.push_back(T_cam_needle[size_t(j)].inverse() * T_cam_needle[size_t(i)]);
    }
  }
  // Axis: the direction every relative rotation leaves unchanged, (R - I) a = 0 least squares.
  Eigen::Matrix3d M = Eigen::Matrix3d::Zero();
  for (const auto& T : rel) {
    const Eigen::Matrix3d E = T.linear() - Eigen::Matrix3d::Identity();
    M += E.transpose() * E;
  }
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(M);
  Eigen::Vector3d a = eig.eigenvectors().col(0).normalized();
  if (tip_needle && a.dot(*tip_needle) < 0) a = -a;
  if (!tip_needle && a.z() < 0) a = -a;
  result.axis_needle = a;
  // Point on the axis: P (R - I) c = -P t for every relative motion (P removes sliding along a).
  // The position along the axis is free: c = (a . anchor) a + B y with B spanning the plane
  // normal to a, anchor = the tip (when given) or the origin.
  const Eigen::Matrix3d P = Eigen::Matrix3d::Identity() - a * a.transpose();
  Eigen::Matrix<double, 3, 2> B;
  B.col(0) = a.unitOrthogonal();
  B.col(1) = a.cross(B.col(0));
  const Eigen::Vector3d anchor = tip_needle ? *tip_needle : Eigen::Vector3d::Zero();
  const Eigen::Vector3d c0 = a.dot(anchor) * a;
  Eigen::MatrixXd A(3 * rel.size(), 2);
  Eigen::VectorXd b(3 * rel.size());
  for (size_t k = 0; k < rel.size(); ++k) {
    const Eigen::Matrix3d E = P * (rel[k].linear() - Eigen::Matrix3d::Identity());
    A.middleRows<3>(Eigen::Index(3 * k)) = E * B;
    b.segment<3>(Eigen::Index(3 * k)) = -P * rel[k].translation() - E * c0;
  }
  const Eigen::Vector2d y = A.colPivHouseholderQr().solve(b);
  const Eigen::Vector3d c = c0 + B * y;
  result.point_needle = c;
  double sum_angle = 0, sum_move = 0;
  int counted = 0;
  for (const auto& T : rel) {
    const Eigen::AngleAxisd aa(T.linear());
    if (aa.angle() > 5.0 * kPi / 180.0) {
      const double cosang = std::min(1.0, std::abs(aa.axis().dot(a)));
      const double ang = std::acos(cosang) * 180.0 / kPi;
      sum_angle += ang * ang;
      ++counted;
    }
    const Eigen::Vector3d moved = P * (T * c - c);
    sum_move += moved.squaredNorm();
  }
  result.axis_rms_deg = counted > 0 ? std::sqrt(sum_angle / counted) : 0.0;
  result.rms_mm = std::sqrt(sum_move / double(rel.size()));
  if (tip_needle) {
    result.tip_to_axis_mm = (P * (*tip_needle - c)).norm();
  }
  spdlog::info("spin calibration: axis ({:.4f}, {:.4f}, {:.4f}) in the needle frame, axis RMS "
               "{:.2f} deg, rotation range {:.1f} deg",
               a.x(), a.y(), a.z(), result.axis_rms_deg, result.rotation_range_deg);
  return result;
}

}  // namespace crepuscular::calibration
