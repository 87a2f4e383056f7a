// The targeting view's geometry: the plane through the tumor centroid across the needle, the
// needle's crossing, the tumor's outline and the polar map of tilted paths.
#include "planning/trajectories/targeting.hpp"

#include <algorithm>
#include <cmath>

#include "foundation/error.hpp"
#include "planning/imaging/ray_march.hpp"

namespace crepuscular::planning {

namespace {
constexpr double kDeg = M_PI / 180.0;
}  // namespace

Eigen::Vector2d TargetingGeometry::to_px(const Eigen::Vector3d& p) const {
  const Eigen::Vector3d d = p - centre;
  return centre_px + Eigen::Vector2d(d.dot(u), d.dot(v)) / mm_per_px;
}

Eigen::Vector3d TargetingGeometry::tilted(double tilt_deg, double azimuth_deg) const {
  const double t = tilt_deg * kDeg, a = azimuth_deg * kDeg;
  return (std::cos(t) * axis + std::sin(t) * (std::cos(a) * u + std::sin(a) * v)).normalized();
}

Eigen::Vector2d TargetingGeometry::tilt_px(double tilt_deg, double azimuth_deg) const {
  const double r = pivot_to_plane_mm * std::tan(tilt_deg * kDeg) / mm_per_px;
  const double a = azimuth_deg * kDeg;
  return crossing_px + r * Eigen::Vector2d(std::cos(a), std::sin(a));
}

std::optional<Eigen::Vector3d> body_entry_along(const Volume<int32_t>& labels,
                                                const Eigen::Vector3d& from,
                                                const Eigen::Vector3d& axis, double max_s) {
  if (labels.empty()) return std::nullopt;
  const double step = 0.5 * labels.geometry().spacing.minCoeff();
  const auto c = first_entry(
      from, axis, step, max_s, [&](const Eigen::Vector3d& p) { return in_body(labels, p); }, 0.01);
  if (!c) return std::nullopt;
  return Eigen::Vector3d(from + c->outside_s * axis);
}

Deviation line_deviation(const Eigen::Vector3d& entry, const Eigen::Vector3d& axis,
                         const Eigen::Vector3d& reference_entry,
                         const Eigen::Vector3d& reference_axis) {
  Deviation d;
  d.entry_mm = (entry - reference_entry).norm();
  const double c = axis.normalized().dot(reference_axis.normalized());
  d.angle_deg = std::acos(std::clamp(c, -1.0, 1.0)) / kDeg;
  return d;
}

TargetingGeometry targeting_geometry(const NeedleGuide& guide, const NeedleState& needle,
                                     const std::vector<Eigen::Vector3d>& tumor_surface,
                                     double tumor_voxel_mm, const TargetingOptions& options) {
  if (options.size_px < 32 || options.size_px > 4096) {
    throw Error("targeting view: size must be 32 to 4096 pixels");
  }
  if (options.rings < 1 || options.rings > 100 || options.sectors < 4 || options.sectors > 360) {
    throw Error("targeting view: 1 to 100 rings and 4 to 360 sectors");
  }
  if (!(options.max_tilt_deg > 0 && options.max_tilt_deg < 60)) {
    throw Error("targeting view: the largest tilt must lie between 0 and 60 degrees");
  }
  if (!(options.half_extent_mm >= 0) || !std::isfinite(options.half_extent_mm)) {
    throw Error("targeting view: the extent must be 0 (automatic) or positive");
  }
  const PlanData& plan = guide.plan();
  TargetingGeometry g;
  g.size_px = options.size_px;
  g.rings = options.rings;
  g.sectors = options.sectors;
  g.max_tilt_deg = options.max_tilt_deg;
  g.centre = plan.tumor_centre;
  g.axis = needle.axis.normalized();
  g.centre_px = Eigen::Vector2d::Constant(0.5 * (options.size_px - 1));
  // View axes: the hint projected onto the plane (another axis when it is nearly parallel).
  Eigen::Vector3d right = options.right_hint - options.right_hint.dot(g.axis) * g.axis;
  if (!(right.norm() > 0.1 * options.right_hint.norm()) || !right.allFinite()) {
    right = g.axis.unitOrthogonal();
  }
  g.u = right.normalized();
  g.v = g.axis.cross(g.u);
  if (needle.points_away) return g;
  g.valid = true;

  // Pivot: just outside the body where the needle's line enters it.
  g.pivot = needle.line_start;
  if (!needle.tip_in_body) {
    if (auto e = body_entry_along(plan.labels, needle.tip, g.axis, needle.along_axis_mm)) {
      g.pivot = *e;
    }
  }
  g.pivot_to_plane_mm = (g.centre - g.pivot).dot(g.axis);
  // Crossing of the extended needle with the plane: tip + s axis, (p - centre) . axis = 0.
  g.crossing = needle.tip + (g.centre - needle.tip).dot(g.axis) * g.axis;

  // Extent: the tumor outline and the polar map around the crossing fit.
  double tumor_r = 0;
  for (const auto& p : tumor_surface) {
    const Eigen::Vector3d d = p - g.centre;
    tumor_r = std::max(tumor_r, (d - d.dot(g.axis) * g.axis).norm() + 0.5 * tumor_voxel_mm);
  }
  double half = options.half_extent_mm;
  if (!(half > 0)) {
    const double polar = std::abs(g.pivot_to_plane_mm) * std::tan(options.max_tilt_deg * kDeg);
    half = std::max({15.0, 1.6 * tumor_r, 1.1 * ((g.crossing - g.centre).norm() + polar)});
    half = 5.0 * std::ceil(half / 5.0);
  }
  g.mm_per_px = half / (0.5 * options.size_px);
  g.crossing_px = g.to_px(g.crossing);
  g.tumor_point_radius_px = std::max(1.0, 0.6 * tumor_voxel_mm / g.mm_per_px);
  g.tumor_px.reserve(tumor_surface.size());
  for (const auto& p : tumor_surface) g.tumor_px.push_back(g.to_px(p));

  if (std::isfinite(needle.angle_to_safe_deg)) {
    const Eigen::Vector3d in = -needle.nearest_safe_direction;  // into the body
    g.nearest_safe_deg = needle.angle_to_safe_deg;
    g.nearest_safe_azimuth_deg = std::atan2(in.dot(g.v), in.dot(g.u)) / kDeg;
  }
  // Polar map: the needle tilted about the pivot, each cell's centre direction evaluated as the
  // live needle is (its tip at the pivot).
  const double ring_deg = options.max_tilt_deg / options.rings;
  for (int r = 0; r < options.rings; ++r) {
    for (int s = 0; s < options.sectors; ++s) {
      PolarCell c;
      c.ring = r;
      c.sector = s;
      c.tilt_deg = (r + 0.5) * ring_deg;
      c.azimuth_deg = s * 360.0 / options.sectors;
      c.direction = g.tilted(c.tilt_deg, c.azimuth_deg);
      c.safety = guide.line_safety(g.pivot, c.direction);  // kUnknown where it points away
      g.cells.push_back(c);
    }
  }
  return g;
}

}  // namespace crepuscular::planning
