// Paired-point rigid registration of the patient marker board to the CT: correspondence found from
// the board's known fiducial layout (no manual ordering), closed-form fit (Umeyama/Horn without
// scale), Ceres refinement with a robust loss, FRE per fiducial and the expected TRE at a target
// (Fitzpatrick, West & Maurer 1998). Mirrored and degenerate configurations are refused.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <string>
#include <vector>

namespace crepuscular::calibration {

struct RegistrationOptions {
  double distance_tolerance_mm = 2.0;  // pairwise distances must agree this well to pair points
  double inlier_mm = 2.0;              // a fiducial matches a CT point within this distance
  int min_matches = 3;
  double robust_scale_mm = 1.0;        // Cauchy loss of the refinement
  double min_spread_ratio = 0.05;      // 2nd / 1st principal extent below this: collinear
};

struct RegistrationResult {
  Eigen::Isometry3d T_ct_patient = Eigen::Isometry3d::Identity();  // board frame -> CT (LPS mm)
  std::vector<int> match;       // per board fiducial: index of its CT fiducial, -1 if not found
  std::vector<double> fre_mm;   // per board fiducial: |T p - q| after the fit; -1 if unmatched
  std::vector<int> unmatched_ct;  // CT fiducials matched to no board fiducial (extra beads)
  int matched = 0;
  double fre_rms_mm = 0;
  double fle_mm = 0;            // estimated: FRE^2 = (1 - 2/N) FLE^2 (0 when N <= 2)
  std::string solver_report;
};

// Closed-form rigid fit T with to_i ~ T from_i (same order, no scale). Throws Error when fewer
// than 3 points, collinear points, or when only a mirror image (determinant -1) fits.
Eigen::Isometry3d rigid_fit_closed_form(const std::vector<Eigen::Vector3d>& from,
                                        const std::vector<Eigen::Vector3d>& to,
                                        const RegistrationOptions& options = {});

// Registration with known correspondence (from[i] <-> to[i]): closed form, then Ceres with a robust
// loss. `from` are board-frame fiducials, `to` CT fiducials.
RegistrationResult register_paired_points(const std::vector<Eigen::Vector3d>& from,
                                          const std::vector<Eigen::Vector3d>& to,
                                          const RegistrationOptions& options = {});

// Registration with unknown correspondence: CT fiducials may come in any order, some board
// fiducials may be missing from the CT and the CT may hold extra bright spots. Pairs are found by
// matching the layout's pairwise distances and verified by the fit. Throws Error (with advice) when
// fewer than min_matches pair up, when the CT points are a mirror image of the layout, when the
// layout is symmetric so that two assignments fit equally, or when the matched points are collinear.
RegistrationResult register_fiducials(const std::vector<Eigen::Vector3d>& board_fiducials,
                                      const std::vector<Eigen::Vector3d>& ct_fiducials,
                                      const RegistrationOptions& options = {});

// Expected target registration error at `target` (same frame as `fiducials`, the matched
// fiducials): TRE^2 = FLE^2 / N (1 + 1/3 sum_k d_k^2 / f_k^2), d_k the target's distance from the
// k-th principal axis of the fiducials, f_k the fiducials' RMS distance from that axis.
double expected_tre_mm(const std::vector<Eigen::Vector3d>& fiducials, const Eigen::Vector3d& target,
                       double fle_mm);

}  // namespace crepuscular::calibration
