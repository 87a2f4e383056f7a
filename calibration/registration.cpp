// Paired-point rigid registration with correspondence search (see registration.hpp).
#include "calibration/registration.hpp"

#include <ceres/ceres.h>
#include <ceres/rotation.h>

#include <Eigen/Eigenvalues>
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <sstream>

#include "foundation/error.hpp"
#include "foundation/log.hpp"

namespace crepuscular::calibration {
namespace {

Eigen::Vector3d centroid(const std::vector<Eigen::Vector3d>& p) {
  Eigen::Vector3d c = Eigen::Vector3d::Zero();
  for (const auto& x : p) c += x;
  return c / double(p.size());
}

// Singular values of the centred points (extent along the principal axes, descending).
Eigen::Vector3d principal_extents(const std::vector<Eigen::Vector3d>& p) {
  const Eigen::Vector3d c = centroid(p);
  Eigen::MatrixXd A(p.size(), 3);
  for (size_t i = 0; i < p.size(); ++i) A.row(Eigen::Index(i)) = (p[i] - c).transpose();
  return Eigen::JacobiSVD<Eigen::MatrixXd>(A).singularValues();
}

struct Procrustes {
  Eigen::Isometry3d rigid = Eigen::Isometry3d::Identity();
  double rigid_rms = 0;
  bool reflection_preferred = false;  // the best orthogonal fit has determinant -1
  double reflection_rms = 0;
};

// Orthogonal Procrustes (Horn/Umeyama without scale), and the unconstrained fit for comparison.
Procrustes procrustes(const std::vector<Eigen::Vector3d>& from,
                      const std::vector<Eigen::Vector3d>& to) {
  const Eigen::Vector3d a = centroid(from), b = centroid(to);
  Eigen::Matrix3d H = Eigen::Matrix3d::Zero();
  for (size_t i = 0; i < from.size(); ++i) H += (to[i] - b) * (from[i] - a).transpose();
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(H, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Matrix3d U = svd.matrixU(), V = svd.matrixV();
  const double d = (U * V.transpose()).determinant() < 0 ? -1.0 : 1.0;
  Procrustes out;
  const Eigen::Matrix3d R = U * Eigen::Vector3d(1, 1, d).asDiagonal() * V.transpose();
  out.rigid.linear() = R;
  out.rigid.translation() = b - R * a;
  const Eigen::Matrix3d M = U * V.transpose();
  out.reflection_preferred = d < 0;
  double s_rigid = 0, s_refl = 0;
  for (size_t i = 0; i < from.size(); ++i) {
    s_rigid += (out.rigid * from[i] - to[i]).squaredNorm();
    s_refl += (M * (from[i] - a) + b - to[i]).squaredNorm();
  }
  out.rigid_rms = std::sqrt(s_rigid / double(from.size()));
  out.reflection_rms = std::sqrt(s_refl / double(from.size()));
  return out;
}

// Residual R(w) (R0 p) + t - q, rotation as an angle-axis update of a start rotation R0.
struct PairedPointCost {
  PairedPointCost(const Eigen::Vector3d& rotated_from, const Eigen::Vector3d& to)
      : p_(rotated_from), q_(to) {}
  template <typename T>
  bool operator()(const T* w, const T* t, T* residual) const {
    const T p[3] = {T(p_.x()), T(p_.y()), T(p_.z())};
    T r[3];
    ceres::AngleAxisRotatePoint(w, p, r);
    for (int k = 0; k < 3; ++k) residual[k] = r[k] + t[k] - T(q_(k));
    return true;
  }
  static ceres::CostFunction* Create(const Eigen::Vector3d& p, const Eigen::Vector3d& q) {
    return new ceres::AutoDiffCostFunction<PairedPointCost, 3, 3, 3>(new PairedPointCost(p, q));
  }
  Eigen::Vector3d p_, q_;
};

// Each board point to its nearest CT point within `inlier_mm`, one-to-one (closest pairs first).
std::vector<int> assign(const std::vector<Eigen::Vector3d>& board,
                        const std::vector<Eigen::Vector3d>& ct, const Eigen::Isometry3d& T,
                        double inlier_mm) {
  struct Pair {
    double d;
    int i, j;
  };
  std::vector<Pair> pairs;
  for (size_t i = 0; i < board.size(); ++i) {
    const Eigen::Vector3d p = T * board[i];
    for (size_t j = 0; j < ct.size(); ++j) {
      const double d = (p - ct[j]).norm();
      if (d <= inlier_mm) pairs.push_back({d, int(i), int(j)});
    }
  }
  std::sort(pairs.begin(), pairs.end(), [](const Pair& x, const Pair& y) { return x.d < y.d; });
  std::vector<int> match(board.size(), -1);
  std::vector<char> used(ct.size(), 0);
  for (const auto& p : pairs) {
    if (match[size_t(p.i)] >= 0 || used[size_t(p.j)]) continue;
    match[size_t(p.i)] = p.j;
    used[size_t(p.j)] = 1;
  }
  return match;
}

struct Hypothesis {
  std::vector<int> match;
  int count = 0;
  double rms = 0;
};

// Fits the matched pairs and re-assigns until the assignment stops changing.
Hypothesis polish(const std::vector<Eigen::Vector3d>& board, const std::vector<Eigen::Vector3d>& ct,
                  std::vector<int> match, double inlier_mm) {
  Hypothesis h;
  for (int iteration = 0; iteration < 5; ++iteration) {
    std::vector<Eigen::Vector3d> f, t;
    for (size_t i = 0; i < board.size(); ++i) {
      if (match[i] >= 0) {
        f.push_back(board[i]);
        t.push_back(ct[size_t(match[i])]);
      }
    }
    if (f.size() < 3) break;
    const Procrustes fit = procrustes(f, t);
    std::vector<int> next = assign(board, ct, fit.rigid, inlier_mm);
    h.match = match;
    h.count = int(f.size());
    h.rms = fit.rigid_rms;
    if (next == match) break;
    match = next;
  }
  return h;
}

// All assignments supported by some congruent triple, best first (more pairs, then lower RMS).
std::vector<Hypothesis> search(const std::vector<Eigen::Vector3d>& board,
                               const std::vector<Eigen::Vector3d>& ct,
                               const RegistrationOptions& options) {
  const size_t n = board.size(), m = ct.size();
  const double tol = options.distance_tolerance_mm;
  std::map<std::vector<int>, Hypothesis> found;
  auto dist = [](const Eigen::Vector3d& x, const Eigen::Vector3d& y) { return (x - y).norm(); };
  for (size_t i = 0; i < n; ++i) {
    for (size_t j = i + 1; j < n; ++j) {
      for (size_t k = j + 1; k < n; ++k) {
        const double dij = dist(board[i], board[j]), dik = dist(board[i], board[k]),
                     djk = dist(board[j], board[k]);
        // Skip nearly collinear triples: they do not fix a rotation.
        const double area2 = (board[j] - board[i]).cross(board[k] - board[i]).norm();
        if (area2 < 0.05 * std::max({dij, dik, djk}) * std::max({dij, dik, djk})) continue;
        for (size_t a = 0; a < m; ++a) {
          for (size_t b = 0; b < m; ++b) {
            if (b == a || std::abs(dist(ct[a], ct[b]) - dij) > tol) continue;
            for (size_t c = 0; c < m; ++c) {
              if (c == a || c == b) continue;
              if (std::abs(dist(ct[a], ct[c]) - dik) > tol) continue;
              if (std::abs(dist(ct[b], ct[c]) - djk) > tol) continue;
              const Procrustes fit =
                  procrustes({board[i], board[j], board[k]}, {ct[a], ct[b], ct[c]});
              std::vector<int> match = assign(board, ct, fit.rigid, options.inlier_mm);
              if (found.count(match)) continue;
              Hypothesis h = polish(board, ct, match, options.inlier_mm);
              if (h.count >= 3) found.emplace(match, h);
            }
          }
        }
      }
    }
  }
  // Distinct final assignments only.
  std::map<std::vector<int>, Hypothesis> distinct;
  for (auto& [start, h] : found) distinct.emplace(h.match, h);
  std::vector<Hypothesis> out;
  for (auto& [match, h] : distinct) out.push_back(h);
  std::sort(out.begin(), out.end(), [](const Hypothesis& x, const Hypothesis& y) {
    return x.count != y.count ? x.count > y.count : x.rms < y.rms;
  });
  return out;
}

}  // namespace

Eigen::Isometry3d rigid_fit_closed_form(const std::vector<Eigen::Vector3d>& from,
                                        const std::vector<Eigen::Vector3d>& to,
                                        const RegistrationOptions& options) {
  if (from.size() != to.size()) {
    throw Error("registration: " + std::to_string(from.size()) + " board points but " +
                std::to_string(to.size()) + " CT points (expected pairs)");
  }
  if (from.size() < 3) {
    throw Error("registration: " + std::to_string(from.size()) +
                " point pair(s) (at least 3 non-collinear fiducials needed)");
  }
  const Eigen::Vector3d s = principal_extents(from);
  const Eigen::Vector3d t = principal_extents(to);
  if (s(0) <= 0 || s(1) < options.min_spread_ratio * s(0) || t(1) < options.min_spread_ratio * t(0)) {
    throw Error(
        "registration: the paired fiducials are (nearly) collinear, which leaves the rotation "
        "about their line undetermined. Use at least 3 fiducials spread over the board, not in "
        "one row.");
  }
  const Procrustes fit = procrustes(from, to);
  if (fit.reflection_preferred && fit.rigid_rms > options.inlier_mm &&
      fit.reflection_rms < 0.5 * fit.rigid_rms) {
    std::ostringstream msg;
    msg.precision(2);
    msg << std::fixed
        << "registration: the CT fiducials are a mirror image of the board's layout (a reflection "
           "fits with RMS "
        << fit.reflection_rms << " mm, a rigid motion only with " << fit.rigid_rms
        << " mm). Check the CT's orientation (LPS vs RAS, a flipped axis) and the board "
           "definition.";
    throw Error(msg.str());
  }
  return fit.rigid;
}

RegistrationResult register_paired_points(const std::vector<Eigen::Vector3d>& from,
                                          const std::vector<Eigen::Vector3d>& to,
                                          const RegistrationOptions& options) {
  const Eigen::Isometry3d T0 = rigid_fit_closed_form(from, to, options);
  const Eigen::Vector3d e = principal_extents(from);
  if (e(2) < options.min_spread_ratio * e(0)) {
    spdlog::warn("registration: the fiducials are (nearly) coplanar, so a mirrored CT (LPS/RAS "
                 "confusion) cannot be detected from them; check the CT's orientation");
  }
  double w[3] = {0, 0, 0};
  double t[3] = {T0.translation().x(), T0.translation().y(), T0.translation().z()};
  ceres::Problem problem;
  for (size_t i = 0; i < from.size(); ++i) {
    problem.AddResidualBlock(PairedPointCost::Create(T0.linear() * from[i], to[i]),
                             new ceres::CauchyLoss(options.robust_scale_mm), w, t);
  }
  ceres::Solver::Options solver_options;
  solver_options.linear_solver_type = ceres::DENSE_QR;
  solver_options.function_tolerance = 1e-14;
  solver_options.parameter_tolerance = 1e-14;
  ceres::Solver::Summary summary;
  ceres::Solve(solver_options, &problem, &summary);
  RegistrationResult result;
  result.solver_report = summary.BriefReport();
  const Eigen::Vector3d wv(w[0], w[1], w[2]);
  Eigen::Matrix3d dR = Eigen::Matrix3d::Identity();
  if (wv.norm() > 0) dR = Eigen::AngleAxisd(wv.norm(), wv.normalized()).toRotationMatrix();
  result.T_ct_patient.linear() = dR * T0.linear();
  result.T_ct_patient.translation() = Eigen::Vector3d(t[0], t[1], t[2]);
  result.match.resize(from.size());
  double sum = 0;
  for (size_t i = 0; i < from.size(); ++i) {
    result.match[i] = int(i);
    const double d = (result.T_ct_patient * from[i] - to[i]).norm();
    result.fre_mm.push_back(d);
    sum += d * d;
  }
  const int n = int(from.size());
  result.matched = n;
  result.fre_rms_mm = std::sqrt(sum / n);
  result.fle_mm = n > 2 ? result.fre_rms_mm * std::sqrt(double(n) / double(n - 2)) : 0.0;
  return result;
}

RegistrationResult register_fiducials(const std::vector<Eigen::Vector3d>& board_fiducials,
                                      const std::vector<Eigen::Vector3d>& ct_fiducials,
                                      const RegistrationOptions& options) {
  const size_t n = board_fiducials.size(), m = ct_fiducials.size();
  if (n < 3) {
    throw Error("registration: the board defines " + std::to_string(n) +
                " fiducial(s); at least 3 (better 4-6, not in one plane) are needed");
  }
  if (m < 3) {
    throw Error("registration: " + std::to_string(m) +
                " fiducial(s) found in the CT; at least 3 are needed. Check the CT fiducial file, "
                "or the threshold of the automatic bead detection.");
  }
  const std::vector<Hypothesis> hyps = search(board_fiducials, ct_fiducials, options);
  const int best_count = hyps.empty() ? 0 : hyps.front().count;
  // The mirror image of the layout: does it fit better than the layout itself?
  std::vector<Eigen::Vector3d> mirrored = board_fiducials;
  for (auto& p : mirrored) p.x() = -p.x();
  const std::vector<Hypothesis> mirror_hyps = search(mirrored, ct_fiducials, options);
  const int mirror_count = mirror_hyps.empty() ? 0 : mirror_hyps.front().count;
  if (mirror_count >= 4 && mirror_count > best_count) {
    std::ostringstream msg;
    msg << "registration: the CT fiducials match the mirror image of the board's layout ("
        << mirror_count << " fiducials pair up mirrored, only " << best_count
        << " as a rigid motion). Check the CT's orientation (LPS vs RAS, a flipped axis) and the "
           "board definition.";
    throw Error(msg.str());
  }
  if (best_count < options.min_matches) {
    std::ostringstream msg;
    msg << "registration: only " << best_count << " of the board's " << n
        << " fiducials could be paired with the " << m
        << " CT fiducials (pairwise distances agreeing within " << options.distance_tolerance_mm
        << " mm; at least " << options.min_matches
        << " needed). Check the board definition's fiducial positions, the CT fiducials, and that "
           "the CT's spacing is right.";
    throw Error(msg.str());
  }
  const Hypothesis& best = hyps.front();
  if (hyps.size() > 1 && hyps[1].count == best.count && hyps[1].rms < options.inlier_mm) {
    std::ostringstream msg;
    msg.precision(2);
    msg << std::fixed << "registration: the fiducial layout is symmetric: two different pairings "
        << "of " << best.count << " fiducials fit (RMS " << best.rms << " and " << hyps[1].rms
        << " mm). Use a board whose fiducials have distinct mutual distances, or list the CT "
           "fiducials in the board's order and pair them by order.";
    throw Error(msg.str());
  }
  std::vector<Eigen::Vector3d> f, t;
  for (size_t i = 0; i < n; ++i) {
    if (best.match[i] >= 0) {
      f.push_back(board_fiducials[i]);
      t.push_back(ct_fiducials[size_t(best.match[i])]);
    }
  }
  RegistrationResult paired = register_paired_points(f, t, options);
  RegistrationResult result;
  result.T_ct_patient = paired.T_ct_patient;
  result.solver_report = paired.solver_report;
  result.match = best.match;
  result.matched = best.count;
  result.fre_rms_mm = paired.fre_rms_mm;
  result.fle_mm = paired.fle_mm;
  std::vector<char> used(m, 0);
  for (size_t i = 0; i < n; ++i) {
    if (best.match[i] < 0) {
      result.fre_mm.push_back(-1.0);
      spdlog::warn("registration: board fiducial {} was not found in the CT", i);
      continue;
    }
    used[size_t(best.match[i])] = 1;
    result.fre_mm.push_back(
        (result.T_ct_patient * board_fiducials[i] - ct_fiducials[size_t(best.match[i])]).norm());
  }
  for (size_t j = 0; j < m; ++j) {
    if (!used[j]) result.unmatched_ct.push_back(int(j));
  }
  spdlog::info("registration: {} of {} board fiducials paired with {} CT fiducials, FRE RMS {:.3f} "
               "mm",
               result.matched, n, m, result.fre_rms_mm);
  return result;
}

double expected_tre_mm(const std::vector<Eigen::Vector3d>& fiducials, const Eigen::Vector3d& target,
                       double fle_mm) {
  const size_t n = fiducials.size();
  if (n < 3) return std::numeric_limits<double>::infinity();
  const Eigen::Vector3d c = centroid(fiducials);
  Eigen::Matrix3d S = Eigen::Matrix3d::Zero();
  for (const auto& p : fiducials) S += (p - c) * (p - c).transpose();
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(S);
  const Eigen::Vector3d r = target - c;
  double sum = 0;
  for (int k = 0; k < 3; ++k) {
    const Eigen::Vector3d u = eig.eigenvectors().col(k);
    double f2 = 0;
    for (const auto& p : fiducials) {
      const Eigen::Vector3d x = p - c;
      f2 += x.squaredNorm() - std::pow(x.dot(u), 2);
    }
    f2 /= double(n);
    const double d2 = r.squaredNorm() - std::pow(r.dot(u), 2);
    if (f2 <= 0) return std::numeric_limits<double>::infinity();
    sum += d2 / f2;
  }
  return std::sqrt(fle_mm * fle_mm / double(n) * (1.0 + sum / 3.0));
}

}  // namespace crepuscular::calibration
