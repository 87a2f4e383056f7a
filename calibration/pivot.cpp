// Pivot and spin calibration of the needle (see pivot.hpp).
#include "calibration/pivot.hpp"

#include <fmt/format.h>

#include <ceres/ceres.h>

#include <Eigen/Eigenvalues>
#include <Eigen/QR>
#include <algorithm>
#include <cmath>
#include <numeric>
#include <sstream>

#include "foundation/error.hpp"
#include "foundation/log.hpp"

namespace crepuscular::calibration {
namespace {

constexpr double kPi = 3.14159265358979323846;

// Largest angle between the orientations of two poses (degrees): 2 acos of the smallest |q_a . q_b|
// of their unit quaternions.
double max_pairwise_angle_deg(const std::vector<Eigen::Isometry3d>& poses) {
  std::vector<Eigen::Vector4d> q;
  q.reserve(poses.size());
  for (const auto& T : poses) q.push_back(Eigen::Quaterniond(T.linear()).normalized().coeffs());
  double min_dot = 1.0;
  for (size_t a = 0; a < q.size(); ++a) {
    for (size_t b = a + 1; b < q.size(); ++b) min_dot = std::min(min_dot, std::abs(q[a].dot(q[b])));
  }
  return 2.0 * std::acos(std::min(1.0, min_dot)) * 180.0 / kPi;
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
  Eigen::Matrix3d DtD = Eigen::Matrix3d::Zero();
  for (const auto& T : T_cam_needle) {
    const Eigen::Matrix3d D = T.linear() - mean;
    DtD += D.transpose() * D;
  }
  const double smin = std::sqrt(
      std::max(0.0, Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(DtD).eigenvalues()(0)));
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

// Least squares of the linear system [R_i  -I] [t; p] = -t_i over the poses `rows` (3 rows per
// pose), solved through its 6 x 6 normal equations; also returns (A^T A)^-1.
struct LinearPivot {
  Eigen::Vector3d tip = Eigen::Vector3d::Zero();
  Eigen::Vector3d pivot = Eigen::Vector3d::Zero();
  Eigen::Matrix<double, 6, 6> normal_inverse = Eigen::Matrix<double, 6, 6>::Zero();
};

LinearPivot solve_linear(const std::vector<Eigen::Isometry3d>& T_cam_needle,
                         const std::vector<int>& rows) {
  Eigen::Matrix<double, 6, 6> AtA = Eigen::Matrix<double, 6, 6>::Zero();
  Eigen::Matrix<double, 6, 1> Atb = Eigen::Matrix<double, 6, 1>::Zero();
  Eigen::Matrix<double, 3, 6> A;
  A.rightCols<3>() = -Eigen::Matrix3d::Identity();
  for (int i : rows) {
    A.leftCols<3>() = T_cam_needle[size_t(i)].linear();
    AtA += A.transpose() * A;
    Atb -= A.transpose() * T_cam_needle[size_t(i)].translation();
  }
  // The motion checks make A^T A well conditioned; the QR copes with what is left.
  const Eigen::ColPivHouseholderQR<Eigen::Matrix<double, 6, 6>> qr(AtA);
  const Eigen::Matrix<double, 6, 1> x = qr.solve(Atb);
  LinearPivot out;
  out.tip = x.head<3>();
  out.pivot = x.tail<3>();
  out.normal_inverse = qr.inverse();
  return out;
}

// Robust refinement of tip and pivot (in place) over all poses: a Cauchy loss of scale
// `scale_mm` bounds the pull of poses where the tip slipped or the board was mis-detected.
ceres::Solver::Summary solve_robust(const std::vector<Eigen::Isometry3d>& T_cam_needle,
                                    double scale_mm, double* tip, double* pivot) {
  ceres::Problem problem;
  for (const auto& T : T_cam_needle) {
    problem.AddResidualBlock(PivotCost::Create(T), new ceres::CauchyLoss(scale_mm), tip, pivot);
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
  r.reserve(T_cam_needle.size());
  for (const auto& T : T_cam_needle) r.push_back((T * tip - pivot).norm());
  return r;
}

// 3D RMS of residual norms estimated from their median, which a minority of wild poses does not
// move: for isotropic Gaussian errors of sigma per axis the median norm is 1.5382 sigma and the
// 3D RMS sqrt(3) sigma.
double robust_rms_mm(std::vector<double> r) {
  const size_t mid = r.size() / 2;
  std::nth_element(r.begin(), r.begin() + std::ptrdiff_t(mid), r.end());
  return r[mid] * std::sqrt(3.0) / 1.5382;
}

// Up to `most` numbers of `values`, comma separated, then "..." when there are more.
template <typename T>
std::string list_some(const std::vector<T>& values, size_t most = 20) {
  std::string s;
  for (size_t k = 0; k < values.size() && k < most; ++k) {
    s += (k ? ", " : "") + fmt::format("{}", values[k]);
  }
  if (values.size() > most) s += fmt::format(", ... ({} in all)", values.size());
  return s;
}

void log_pivot(const PivotResult& r, const PivotOptions& options) {
  const int n = int(r.residual_mm.size());
  spdlog::info("pivot calibration over {} poses ({} used, {} outliers):", n, r.inliers,
               r.outlier_indices.size());
  spdlog::info("  tip (needle frame)   ({:8.3f}, {:8.3f}, {:8.3f}) mm", r.tip_needle.x(),
               r.tip_needle.y(), r.tip_needle.z());
  spdlog::info(
      "  tip std deviation    ({:8.3f}, {:8.3f}, {:8.3f}) mm per axis, {:.3f} mm 3D "
      "(at most {:.2f} mm accepted)",
      r.tip_stddev_mm.x(), r.tip_stddev_mm.y(), r.tip_stddev_mm.z(), r.tip_stddev_3d_mm,
      options.max_tip_stddev_mm);
  spdlog::info("  pivot (camera frame) ({:8.2f}, {:8.2f}, {:8.2f}) mm", r.pivot_cam.x(),
               r.pivot_cam.y(), r.pivot_cam.z());
  spdlog::info(
      "  residual RMS         {:.3f} mm 3D, ({:.3f}, {:.3f}, {:.3f}) mm per camera axis; "
      "{:.3f} mm 3D over all poses",
      r.rms_mm, r.rms_axis_mm.x(), r.rms_axis_mm.y(), r.rms_axis_mm.z(), r.rms_all_mm);
  spdlog::info(
      "  motion               largest turn between two poses {:.1f} deg, tilt about the "
      "least moved axis {:.1f} deg",
      r.rotation_spread_deg, r.axis_spread_deg);
  if (!r.outlier_indices.empty()) {
    std::vector<std::string> items;
    for (int i : r.outlier_indices) {
      items.push_back(fmt::format("{} ({:.1f} mm)", i, r.residual_mm[size_t(i)]));
    }
    spdlog::info("  outlier poses        {} (pose index from 0, residual)", list_some(items));
  }
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

  // Least squares over all poses: the start of the robust pass.
  std::vector<int> all_rows(T_cam_needle.size());
  std::iota(all_rows.begin(), all_rows.end(), 0);
  const LinearPivot start = solve_linear(T_cam_needle, all_rows);
  result.linear_tip_needle = start.tip;

  // Robust pass, its Cauchy scale matched to the noise so that ordinary poses keep their weight.
  const double scale_mm =
      std::max(options.robust_scale_mm,
               robust_rms_mm(pivot_residuals(T_cam_needle, start.tip, start.pivot)));
  double tip[3] = {start.tip.x(), start.tip.y(), start.tip.z()};
  double pivot[3] = {start.pivot.x(), start.pivot.y(), start.pivot.z()};
  const ceres::Solver::Summary summary = solve_robust(T_cam_needle, scale_mm, tip, pivot);
  result.solver_report = summary.BriefReport();
  if (!summary.IsSolutionUsable()) {
    throw Error("pivot calibration: the robust solve failed (" + summary.BriefReport() + ")");
  }

  // Outliers: residuals of the robust solution above max(outlier_mm, 3 x robust 3D RMS).
  const std::vector<double> robust_residuals =
      pivot_residuals(T_cam_needle, Eigen::Vector3d(tip[0], tip[1], tip[2]),
                      Eigen::Vector3d(pivot[0], pivot[1], pivot[2]));
  const double limit = std::max(options.outlier_mm, 3.0 * robust_rms_mm(robust_residuals));
  result.outlier.assign(size_t(n), false);
  std::vector<int> in_rows;
  for (int i = 0; i < n; ++i) {
    if (robust_residuals[size_t(i)] > limit) {
      result.outlier[size_t(i)] = true;
      result.outlier_indices.push_back(i);
    } else {
      in_rows.push_back(i);
    }
  }
  result.inliers = int(in_rows.size());
  if (result.inliers < options.min_poses) {
    throw Error(fmt::format(
        "pivot calibration: only {} of {} poses agree on one pivot point (at least {} needed; the "
        "others are more than {:.2f} mm off): the tip slipped out of the divot or the board was "
        "mis-detected in most frames. Record again with the tip held firmly in the divot.",
        result.inliers, n, options.min_poses, limit));
  }

  // Least squares over the inliers: the tip, the pivot and the covariance that belongs to them.
  const LinearPivot final_fit = solve_linear(T_cam_needle, in_rows);
  result.tip_needle = final_fit.tip;
  result.pivot_cam = final_fit.pivot;
  result.residual_mm = pivot_residuals(T_cam_needle, result.tip_needle, result.pivot_cam);
  double sum_in = 0, sum_all = 0;
  Eigen::Vector3d sum_axis = Eigen::Vector3d::Zero();
  for (int i = 0; i < n; ++i) {
    const double r2 = result.residual_mm[size_t(i)] * result.residual_mm[size_t(i)];
    sum_all += r2;
    if (result.outlier[size_t(i)]) continue;
    sum_in += r2;
    sum_axis += (T_cam_needle[size_t(i)] * result.tip_needle - result.pivot_cam).cwiseAbs2();
  }
  result.rms_mm = std::sqrt(sum_in / result.inliers);
  result.rms_axis_mm = (sum_axis / result.inliers).cwiseSqrt();
  result.rms_all_mm = std::sqrt(sum_all / n);
  const double sigma2 = sum_in / double(3 * result.inliers - 6);
  result.tip_covariance_mm2 = sigma2 * final_fit.normal_inverse.topLeftCorner<3, 3>();
  result.tip_stddev_mm = result.tip_covariance_mm2.diagonal().cwiseMax(0.0).cwiseSqrt();
  result.tip_stddev_3d_mm = std::sqrt(std::max(0.0, result.tip_covariance_mm2.trace()));
  log_pivot(result, options);

  // Gates: what makes the tip unusable is its own uncertainty (or a tip far from its board),
  // not a large residual, which only says the recording was noisy.
  if (!result.tip_needle.allFinite() || result.tip_needle.norm() > options.max_tip_mm) {
    throw Error(
        fmt::format("pivot calibration: the tip comes out {:.4g} mm from the needle board "
                    "(at most {:.0f} mm is plausible): the poses do not describe a "
                    "needle pivoting about its tip; record the pivoting again",
                    result.tip_needle.norm(), options.max_tip_mm));
  }
  if (!(result.tip_stddev_3d_mm <= options.max_tip_stddev_mm)) {
    throw Error(fmt::format(
        "pivot calibration: the tip is uncertain by {:.3g} mm (3D standard deviation from the "
        "fit of {} poses at {:.3g} mm residual RMS; at most {:.3g} mm accepted). Record longer "
        "(more poses) while pivoting in a wider cone of 20-40 degrees with the tip held in the "
        "divot and the board well in view; raise --max-tip-stddev-mm only if a tip this "
        "uncertain is acceptable.",
        result.tip_stddev_3d_mm, result.inliers, result.rms_mm, options.max_tip_stddev_mm));
  }
  if (result.rms_mm > options.warn_rms_mm) {
    result.warnings.push_back(fmt::format(
        "pivot calibration: residual RMS {:.3g} mm over {} poses is above {:.3g} mm: the board "
        "was tracked noisily or the tip moved in the divot. The tip is kept, its 3D standard "
        "deviation {:.3g} mm being within {:.3g} mm; a steadier recording gives a tighter tip.",
        result.rms_mm, result.inliers, options.warn_rms_mm, result.tip_stddev_3d_mm,
        options.max_tip_stddev_mm));
    spdlog::warn("{}", result.warnings.back());
  }
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
