// The targeting view's geometry (overlay layer "target"): a view looking down the tracked
// needle's axis at the plane through the tumor centroid perpendicular to it, as navigation systems
// show for needle alignment. It holds the tumor's outline projected onto that plane, the point
// where the extended needle meets the plane, and a polar map of path safety: for needle directions
// tilted from the current axis about the needle's skin entry, the class of each straight path,
// evaluated as the live needle is (NeedleGuide::evaluate). No rendering.
#pragma once

#include <Eigen/Core>
#include <limits>
#include <optional>
#include <vector>

#include "planning/trajectories/needle_guidance.hpp"

namespace crepuscular::planning {

struct TargetingOptions {
  int size_px = 300;            // the view is size_px x size_px pixels
  double half_extent_mm = 0;    // half the view's width in the target plane; 0: automatic
  int rings = 5;                // tilt rings of the polar map: ring r covers tilts
  double max_tilt_deg = 12.5;   //   [r, r + 1) * max_tilt_deg / rings, r = 0 .. rings - 1
  int sectors = 16;             // sectors around the axis; sector s is centred at s * 360 / sectors
  // The CT direction shown to the right of the view (projected onto the plane; when it is nearly
  // parallel to the needle another direction is used). The overlay passes the camera's x axis, so
  // right in the view is right in the video.
  Eigen::Vector3d right_hint = Eigen::Vector3d::UnitX();
};

// One cell of the polar map, classified at its centre direction.
struct PolarCell {
  int ring = 0, sector = 0;
  double tilt_deg = 0;     // centre tilt from the needle axis: (ring + 0.5) * max_tilt / rings
  double azimuth_deg = 0;  // centre azimuth: sector * 360 / sectors, from the view's right (u)
                           // toward its down (v)
  Eigen::Vector3d direction = Eigen::Vector3d::UnitZ();  // unit, into the body (CT)
  NeedleSafety safety = NeedleSafety::kUnknown;
};

// All points CT LPS mm; pixels: (0,0) is the centre of the view's top-left pixel.
struct TargetingGeometry {
  bool valid = false;  // false when the needle points away from the tumor (nothing to target)
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();  // tumor centroid: the plane's point, view centre
  Eigen::Vector3d axis = Eigen::Vector3d::UnitZ();   // needle axis, unit, into the body (plane normal)
  Eigen::Vector3d u = Eigen::Vector3d::UnitX();      // view right, unit, in the plane
  Eigen::Vector3d v = Eigen::Vector3d::UnitY();      // view down, unit: axis x u
  // The pivot the polar map tilts the needle about: just outside the body where the needle's
  // line enters it (the tip itself without a label map, or when the line never meets the body
  // before the target). The polar map's paths start here, as the live needle's line does.
  Eigen::Vector3d pivot = Eigen::Vector3d::Zero();
  double pivot_to_plane_mm = 0;  // (centre - pivot) . axis
  int size_px = 0;
  double mm_per_px = 1;
  Eigen::Vector2d centre_px = Eigen::Vector2d::Zero();  // ((size - 1) / 2, (size - 1) / 2)
  Eigen::Vector3d crossing = Eigen::Vector3d::Zero();   // extended needle x plane
  Eigen::Vector2d crossing_px = Eigen::Vector2d::Zero();
  std::vector<Eigen::Vector2d> tumor_px;  // tumor surface points projected along the axis
  double tumor_point_radius_px = 1;       // half a tumor voxel, in pixels
  std::vector<PolarCell> cells;           // rings x sectors, ring-major
  int rings = 0, sectors = 0;
  double max_tilt_deg = 0;
  // The nearest safe direction (NeedleState): the tilt to it (NaN without one) and its azimuth.
  double nearest_safe_deg = std::numeric_limits<double>::quiet_NaN();
  double nearest_safe_azimuth_deg = 0;

  // Pixel of a point, projected along the axis onto the plane.
  Eigen::Vector2d to_px(const Eigen::Vector3d& p) const;
  // Where the needle tilted by tilt_deg toward azimuth_deg (about the pivot) meets the plane, in
  // pixels: crossing + D tan(tilt) (cos az u + sin az v) / mm_per_px, D = pivot_to_plane_mm.
  Eigen::Vector2d tilt_px(double tilt_deg, double azimuth_deg) const;
  // The unit direction tilted by tilt_deg toward azimuth_deg.
  Eigen::Vector3d tilted(double tilt_deg, double azimuth_deg) const;
};

// The targeting view of the needle `needle` (as NeedleGuide::evaluate gave it) against the plan of
// `guide`. `tumor_surface` (LPS mm, voxels of `tumor_voxel_mm`) is projected for the outline.
// Automatic extent: the tumor outline (1.6 x its farthest point) and the polar map around the
// crossing both fit, rounded up to 5 mm, at least 15 mm. Throws Error on options out of range.
TargetingGeometry targeting_geometry(const NeedleGuide& guide, const NeedleState& needle,
                                     const std::vector<Eigen::Vector3d>& tumor_surface,
                                     double tumor_voxel_mm, const TargetingOptions& options = {});

// How far a needle line is from a reference line (e.g. the nearest safe direction, or the planned
// trajectory), both given by a point on the skin and a unit direction into the body.
struct Deviation {
  double entry_mm = 0;   // distance between the two skin entry points
  double angle_deg = 0;  // angle between the two directions
};
Deviation line_deviation(const Eigen::Vector3d& entry, const Eigen::Vector3d& axis,
                         const Eigen::Vector3d& reference_entry,
                         const Eigen::Vector3d& reference_axis);

// Where the line `from + s axis` (s >= 0, unit axis) first enters the body of `labels`: the last
// sample outside it (steps of half the finest spacing, bisected to 0.01 mm), within max_s mm.
// nullopt without a label map or when it never does.
std::optional<Eigen::Vector3d> body_entry_along(const Volume<int32_t>& labels,
                                                const Eigen::Vector3d& from,
                                                const Eigen::Vector3d& axis, double max_s);

}  // namespace crepuscular::planning
