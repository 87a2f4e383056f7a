// Rays through a label map: the body, its first and outermost exits, the Fibonacci sphere.
#include "planning/imaging/ray_march.hpp"

#include <algorithm>
#include <cmath>

#include "planning/imaging/sampling.hpp"

namespace crepuscular::planning {

bool in_body(const Volume<int32_t>& labels, const Eigen::Vector3d& p) {
  return nearest_voxel_or<int32_t>(labels, p, 0) > 0;
}

double body_fraction(const Volume<int32_t>& labels, const Eigen::Vector3d& p) {
  return trilinear(labels, labels.physical_to_index(p),
                   [](int32_t label) { return label > 0 ? 1.0 : 0.0; });
}

std::optional<BodyExit> first_body_exit(const Volume<int32_t>& labels, const Eigen::Vector3d& start,
                                        const Eigen::Vector3d& dir, double step_mm, double max_s,
                                        const std::function<bool(const Eigen::Vector3d&)>& within) {
  std::optional<double> last_inside;
  bool left_within = false;
  const std::optional<double> s =
      march_until(start, dir, step_mm, max_s, [&](const Eigen::Vector3d& p, double at) {
        if (within && !within(p)) {
          left_within = true;
          return true;
        }
        if (in_body(labels, p)) {
          last_inside = at;
          return false;
        }
        return last_inside.has_value();
      });
  if (!s || left_within) return std::nullopt;
  // The body reaching beyond the label map is no exit: its skin is not in the scan.
  if (!nearest_voxel(labels, start + *s * dir)) return std::nullopt;
  BodyExit e;
  e.last_inside_s = *last_inside;
  e.first_outside_s = *s;
  e.last_inside = start + e.last_inside_s * dir;
  e.first_outside = start + e.first_outside_s * dir;
  return e;
}

std::optional<Eigen::Vector3d> outermost_body_exit(const Volume<int32_t>& labels,
                                                   const Eigen::Vector3d& from,
                                                   const Eigen::Vector3d& u) {
  const ImageGeometry& g = labels.geometry();
  // Far enough to be outside the grid along any direction.
  const Eigen::Vector3d extent =
      g.index_to_physical_matrix().cwiseAbs() *
      Eigen::Vector3d(double(g.dims[0]), double(g.dims[1]), double(g.dims[2]));
  const double far = extent.norm() + (from - g.origin).norm();
  const double step = 0.25 * g.spacing.minCoeff();
  const std::optional<Crossing> c =
      first_entry(from + far * u, -u, step, far + 1e-9,
                  [&](const Eigen::Vector3d& p) { return in_body(labels, p); });
  if (!c) return std::nullopt;
  const Eigen::Vector3d outside(from + (far - c->outside_s) * u);
  // The body reaching the label map's edge: its skin there is not in the scan.
  if (!nearest_voxel(labels, outside)) return std::nullopt;
  return outside;
}

std::vector<Eigen::Vector3d> fibonacci_sphere(int n) {
  std::vector<Eigen::Vector3d> dirs;
  dirs.reserve(size_t(std::max(n, 0)));
  const double golden = M_PI * (3.0 - std::sqrt(5.0));
  for (int i = 0; i < n; ++i) {
    const double z = 1.0 - (2.0 * i + 1.0) / n;
    const double r = std::sqrt(std::max(0.0, 1.0 - z * z));
    dirs.emplace_back(r * std::cos(golden * i), r * std::sin(golden * i), z);
  }
  return dirs;
}

}  // namespace crepuscular::planning
