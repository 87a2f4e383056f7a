#include "planning/trajectories/needle_uncertainty.hpp"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>

namespace crepuscular::planning {

namespace {

// The perturbations of the chain, in order: patient pose [w, t], needle pose [w, t], tip, the
// axis's two components across it, the registration's translation at the tumor.
constexpr int kParameters = 20;
using Parameters = Eigen::Matrix<double, kParameters, 1>;

Eigen::Matrix3d exp_so3(const Eigen::Vector3d& w) {
  const double angle = w.norm();
  if (!(angle > 0)) return Eigen::Matrix3d::Identity();
  return Eigen::AngleAxisd(angle, w / angle).toRotationMatrix();
}

// A pose moved by [w, t] as the tracker's covariance describes it.
Eigen::Isometry3d perturbed(const Eigen::Isometry3d& T, const Eigen::Ref<const Eigen::VectorXd>& d) {
  Eigen::Isometry3d out = T;
  out.linear() = exp_so3(d.head<3>()) * T.linear();
  out.translation() = T.translation() + d.tail<3>();
  return out;
}

struct Chain {
  Eigen::Isometry3d T_ct_patient, T_cam_patient, T_cam_needle;
  Eigen::Vector3d tip, axis, across1, across2;
  bool axis_from_tip = false;

  // The needle's tip and unit axis in CT under the perturbation x.
  std::pair<Eigen::Vector3d, Eigen::Vector3d> line(const Parameters& x) const {
    Eigen::Isometry3d T_ct = T_ct_patient;
    T_ct.translation() += x.segment<3>(17);
    const Eigen::Isometry3d T_ct_needle = T_ct * perturbed(T_cam_patient, x.segment<6>(0)).inverse() *
                                          perturbed(T_cam_needle, x.segment<6>(6));
    const Eigen::Vector3d tip_n = tip + x.segment<3>(12);
    Eigen::Vector3d axis_n = axis_from_tip ? Eigen::Vector3d(tip_n)
                                           : Eigen::Vector3d(axis + x(15) * across1 + x(16) * across2);
    axis_n.normalize();
    return {T_ct_needle * tip_n, T_ct_needle.linear() * axis_n};
  }
};

// Where the line p + s d crosses the plane through q across `normal`, as offsets along e1, e2.
Eigen::Vector2d plane_offsets(const Eigen::Vector3d& p, const Eigen::Vector3d& d,
                              const Eigen::Vector3d& q, const Eigen::Vector3d& normal,
                              const Eigen::Vector3d& e1, const Eigen::Vector3d& e2) {
  const double along = d.dot(normal);
  if (!(std::abs(along) > 1e-12)) return Eigen::Vector2d::Constant(std::nan(""));
  const Eigen::Vector3d x = p + d * ((q - p).dot(normal) / along);
  return {(x - q).dot(e1), (x - q).dot(e2)};
}

}  // namespace

Eigen::Vector4d LineUncertainty::offsets(const Eigen::Vector3d& p, const Eigen::Vector3d& d) const {
  Eigen::Vector4d o;
  o.head<2>() = plane_offsets(p, d, tip, axis, e1, e2);
  o.tail<2>() = plane_offsets(p, d, tip + far_depth_mm * axis, axis, e1, e2);
  return o;
}

double LineUncertainty::distance2(const Eigen::Vector3d& p, const Eigen::Vector3d& d) const {
  const Eigen::Vector4d o = offsets(p, d);
  if (!o.allFinite()) return std::numeric_limits<double>::infinity();
  const Eigen::Matrix4d c = covariance + 1e-8 * Eigen::Matrix4d::Identity();
  return o.dot(c.ldlt().solve(o));
}

std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3d>> LineUncertainty::region_lines() const {
  std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3d>> lines;
  if (!valid) return lines;
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix4d> eig(covariance);
  std::array<Eigen::Vector4d, 4> d;  // semi-axes of the 95 % ellipsoid, smallest first
  for (int i = 0; i < 4; ++i) {
    d[size_t(i)] = std::sqrt(kChi2_95_4dof * std::max(0.0, eig.eigenvalues()(i))) *
                   eig.eigenvectors().col(i);
  }
  std::vector<Eigen::Vector4d> directions;
  for (const auto& v : d) {
    directions.push_back(v);
    directions.push_back(-v);
  }
  for (const auto& [a, b] : {std::pair<int, int>{3, 2}, {1, 0}}) {
    for (const double sa : {1.0, -1.0})
      for (const double sb : {1.0, -1.0})
        directions.push_back((sa * d[size_t(a)] + sb * d[size_t(b)]) / std::sqrt(2.0));
  }
  for (const double scale : {1.0 / 3.0, 2.0 / 3.0, 1.0}) {
    for (const Eigen::Vector4d& o : directions) {
      if (!(o.norm() > 1e-6)) continue;  // no spread that way
      const Eigen::Vector3d p = tip + scale * (o(0) * e1 + o(1) * e2);
      const Eigen::Vector3d far = tip + far_depth_mm * axis + scale * (o(2) * e1 + o(3) * e2);
      lines.emplace_back(p, (far - p).normalized());
    }
  }
  return lines;
}

std::vector<Eigen::Vector3d> LineUncertainty::ellipse_at_tumor(int n) const {
  std::vector<Eigen::Vector3d> points;
  if (!valid || n < 1) return points;
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> eig(at_tumor);
  const double r = std::sqrt(kChi2_95_2dof);
  const Eigen::Vector2d a = r * std::sqrt(std::max(0.0, eig.eigenvalues()(1))) * eig.eigenvectors().col(1);
  const Eigen::Vector2d b = r * std::sqrt(std::max(0.0, eig.eigenvalues()(0))) * eig.eigenvectors().col(0);
  for (int k = 0; k < n; ++k) {
    const double t = 2 * M_PI * k / n;
    const Eigen::Vector2d o = std::cos(t) * a + std::sin(t) * b;
    points.push_back(tumor_crossing + o(0) * e1 + o(1) * e2);
  }
  return points;
}

LineUncertainty needle_line_uncertainty(const Eigen::Isometry3d& T_ct_patient,
                                        const Eigen::Isometry3d& T_cam_patient,
                                        const Eigen::Isometry3d& T_cam_needle,
                                        const Eigen::Vector3d& tip_in_needle,
                                        const Eigen::Vector3d& axis_in_needle,
                                        const Eigen::Vector3d& tumor_centre,
                                        const NeedleUncertaintySources& sources) {
  LineUncertainty u;
  const Eigen::Vector3d axis_n = sources.axis_from_tip ? tip_in_needle : axis_in_needle;
  if (!(axis_n.norm() > 1e-9) || !axis_n.allFinite()) return u;
  Chain chain{T_ct_patient, T_cam_patient, T_cam_needle, tip_in_needle, axis_n.normalized(),
              Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero(), sources.axis_from_tip};
  chain.across1 = chain.axis.unitOrthogonal();
  chain.across2 = chain.axis.cross(chain.across1);
  const auto [tip, axis] = chain.line(Parameters::Zero());
  if (!tip.allFinite() || !axis.allFinite()) return u;
  u.tip = tip;
  u.axis = axis;
  u.e1 = axis.unitOrthogonal();
  u.e2 = axis.cross(u.e1);
  u.tumor_depth_mm = (tumor_centre - tip).dot(axis);
  u.tumor_crossing = tip + u.tumor_depth_mm * axis;
  u.far_depth_mm = std::max(10.0, u.tumor_depth_mm);

  // Offsets at the tip's plane, the far plane and the tumor's plane.
  const auto outputs = [&](const Parameters& x) {
    const auto [p, d] = chain.line(x);
    Eigen::Matrix<double, 6, 1> y;
    y.head<4>() = u.offsets(p, d);
    y.tail<2>() = plane_offsets(p, d, u.tumor_crossing, u.axis, u.e1, u.e2);
    return y;
  };
  Eigen::Matrix<double, kParameters, kParameters> sigma =
      Eigen::Matrix<double, kParameters, kParameters>::Zero();
  sigma.block<6, 6>(0, 0) = sources.patient_pose;
  sigma.block<6, 6>(6, 6) = sources.needle_pose;
  sigma.block<3, 3>(12, 12) = sources.tip_mm2;
  if (!sources.axis_from_tip) {
    sigma(15, 15) = sigma(16, 16) = sources.axis_stddev_rad * sources.axis_stddev_rad;
  }
  const double reg = sources.registration_tre_mm * sources.registration_tre_mm / 3.0;
  sigma.block<3, 3>(17, 17) = reg * Eigen::Matrix3d::Identity();

  Eigen::Matrix<double, 6, kParameters> J;
  for (int i = 0; i < kParameters; ++i) {
    // Radians for rotations and the axis, millimetres for the rest.
    const bool angle = i < 3 || (i >= 6 && i < 9) || i == 15 || i == 16;
    const double h = angle ? 1e-6 : 1e-4;
    Parameters x = Parameters::Zero();
    x(i) = h;
    const Eigen::Matrix<double, 6, 1> plus = outputs(x);
    x(i) = -h;
    J.col(i) = (plus - outputs(x)) / (2 * h);
  }
  if (!J.allFinite()) return u;
  const Eigen::Matrix<double, 6, 6> out = J * sigma * J.transpose();
  u.covariance = out.topLeftCorner<4, 4>();
  u.at_tumor = out.bottomRightCorner<2, 2>();
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> eig(u.at_tumor);
  const double r = std::sqrt(kChi2_95_2dof);
  u.major95_mm = r * std::sqrt(std::max(0.0, eig.eigenvalues()(1)));
  u.minor95_mm = r * std::sqrt(std::max(0.0, eig.eigenvalues()(0)));
  const Eigen::Vector2d m = eig.eigenvectors().col(1);
  u.major_direction = (m(0) * u.e1 + m(1) * u.e2).normalized();
  u.valid = true;
  return u;
}

int needle_safety_severity(NeedleSafety s) {
  switch (s) {
    case NeedleSafety::kSafe: return 0;
    case NeedleSafety::kMedium: return 1;
    case NeedleSafety::kUnknown: return 2;
    case NeedleSafety::kDangerous: return 3;
  }
  return 3;
}

RegionSafety region_safety(const NeedleGuide& guide, const LineUncertainty& line,
                           NeedleSafety nominal) {
  RegionSafety r;
  r.nominal = nominal;
  r.worst = nominal;
  for (const auto& [tip, axis] : line.region_lines()) {
    ++r.lines;
    const NeedleSafety s = guide.line_safety(tip, axis);
    if (needle_safety_severity(s) > needle_safety_severity(r.worst)) r.worst = s;
    if (r.worst == NeedleSafety::kDangerous) break;  // nothing is worse
  }
  return r;
}

}  // namespace crepuscular::planning
