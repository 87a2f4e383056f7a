// Rays through a label map: marching along a ray, the body (label > 0) and where a ray enters or
// leaves it, and evenly spread directions to cast rays in. Points are LPS mm.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <functional>
#include <optional>
#include <vector>

#include "planning/imaging/volume.hpp"

namespace crepuscular::planning {

// Samples start + s dir at s = 0, step_mm, 2 step_mm, ... (s accumulated by adding step_mm) while
// s <= max_s, and returns the first s at which stop(point, s) holds; nullopt when none does.
// step_mm > 0.
template <typename Stop>
std::optional<double> march_until(const Eigen::Vector3d& start, const Eigen::Vector3d& dir,
                                  double step_mm, double max_s, Stop&& stop) {
  for (double s = 0; s <= max_s; s += step_mm) {
    if (stop(Eigen::Vector3d(start + s * dir), s)) return s;
  }
  return std::nullopt;
}

// Two positions along a ray on either side of a region's boundary.
struct Crossing {
  double outside_s = 0;  // last position outside the region
  double inside_s = 0;   // first position inside it
};

// Where a march (as march_until) first enters the region where inside(point) holds: the sample
// before and the first sample inside, bisected until at most tol_mm apart. Both 0 when start is
// inside; nullopt when no sample up to max_s is.
template <typename Inside>
std::optional<Crossing> first_entry(const Eigen::Vector3d& start, const Eigen::Vector3d& dir,
                                    double step_mm, double max_s, Inside&& inside,
                                    double tol_mm = 1e-3) {
  double before = 0;
  const std::optional<double> hit =
      march_until(start, dir, step_mm, max_s, [&](const Eigen::Vector3d& p, double s) {
        if (inside(p)) return true;
        before = s;
        return false;
      });
  if (!hit) return std::nullopt;
  Crossing c{before, *hit};
  while (c.inside_s - c.outside_s > tol_mm) {
    const double mid = 0.5 * (c.outside_s + c.inside_s);
    (inside(Eigen::Vector3d(start + mid * dir)) ? c.inside_s : c.outside_s) = mid;
  }
  return c;
}

// The body: label > 0 at the voxel nearest to p; outside the grid is outside the body.
bool in_body(const Volume<int32_t>& labels, const Eigen::Vector3d& p);

// Trilinear interpolation of the body indicator (label > 0) at p: 0 outside, 1 inside, 0 outside
// the grid. The skin is its 0.5 level, a smooth surface through the label map's voxel faces.
double body_fraction(const Volume<int32_t>& labels, const Eigen::Vector3d& p);

// The first exit from the body along a march (as march_until): the last sample inside the body
// and the first sample outside it after that (a march that starts outside enters first).
struct BodyExit {
  double last_inside_s = 0, first_outside_s = 0;
  Eigen::Vector3d last_inside = Eigen::Vector3d::Zero(), first_outside = Eigen::Vector3d::Zero();
};
// nullopt when the march has not left the body by max_s, reaches a sample where `within` (when
// given) is false before it does, or leaves the label map while still in the body (the skin
// there is not in the scan: unknown, never an entry point).
std::optional<BodyExit> first_body_exit(
    const Volume<int32_t>& labels, const Eigen::Vector3d& start, const Eigen::Vector3d& dir,
    double step_mm, double max_s,
    const std::function<bool(const Eigen::Vector3d&)>& within = nullptr);

// Where the line from `from` along unit u finally leaves the body: the outermost crossing, on its
// outside (within 0.001 mm of the body, by the nearest voxel), found by marching inward from
// beyond the grid in steps of a quarter of the finest spacing. nullopt when the line never meets
// the body, or meets it at the label map's edge (the skin there is not in the scan).
std::optional<Eigen::Vector3d> outermost_body_exit(const Volume<int32_t>& labels,
                                                   const Eigen::Vector3d& from,
                                                   const Eigen::Vector3d& u);

// n unit directions spread evenly over the sphere (Fibonacci sphere): z from 1 - 1/n down to
// -1 + 1/n in equal steps, successive points turned by the golden angle.
std::vector<Eigen::Vector3d> fibonacci_sphere(int n);

}  // namespace crepuscular::planning
