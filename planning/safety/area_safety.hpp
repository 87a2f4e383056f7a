// Area safety geometry (paper section 3.3, docs/ARCHITECTURE.md §6): a tessellated PCA ellipsoid of
// the tumor, every vertex extruded along its normal until the maximum distance or an unsafe point;
// connected safe regions; each region's size by the divergence theorem; every vertex weighted by
// its region's size (its leeway).
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <functional>
#include <limits>
#include <nlohmann/json_fwd.hpp>
#include <string>
#include <vector>

#include "planning/safety/path_safety.hpp"
#include "planning/imaging/volume.hpp"

namespace crepuscular::planning {

// Ellipsoid from the PCA of the tumor's voxel centres (LPS mm).
struct Ellipsoid {
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  Eigen::Matrix3d axes = Eigen::Matrix3d::Identity();  // columns: unit main axes, largest first
  Eigen::Vector3d radii = Eigen::Vector3d::Ones();     // mm, largest first
};

// One connected safe region of the extruded surface.
struct AreaRegion {
  int id = 0;           // 0, 1, ... by decreasing size
  double size_mm3 = 0;  // mass by the divergence theorem
  // LPS mm, centre of its extruded vertices (each weighted by its share of the ellipsoid's area,
  // so that the denser vertices near the poles of the spherical grid do not pull it).
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  Eigen::Vector3d main_axis = Eigen::Vector3d::Zero();  // unit, from the tumor centre outward
  double leeway = 0;                                    // size relative to the largest region, 0..1
  int vertex_count = 0;
};

struct AreaSafetyGeometry {
  Ellipsoid ellipsoid;
  std::vector<Eigen::Vector3d> base;          // vertex on the ellipsoid (LPS mm)
  std::vector<Eigen::Vector3d> normals;       // unit outward normal at the base vertex
  std::vector<Eigen::Vector3d> vertices;      // extruded vertex (LPS mm)
  std::vector<std::array<int, 3>> triangles;  // outward-facing, closed surface
  std::vector<uint8_t> safe;                  // 1 where the extrusion reached its distance (the
                                              // maximum distance or the outer edge of the
                                              // region of interest) through computed, safe
                                              // values inside the scan; 0 everywhere else
  std::vector<int> region;                    // region id per vertex, -1 where unsafe
  std::vector<float> leeway;                  // per vertex: its region's leeway, 0 where unsafe
  std::vector<AreaRegion> regions;            // by decreasing size

  // --- Added fields --------------------------------------------------------------------------
  std::vector<float> extrusion;  // per vertex: distance extruded along the normal, mm
  int rings = 0;                 // spherical grid: rings of latitude (poles excluded) + 1
  int segments = 0;              // spherical grid: vertices per ring of latitude
  double max_distance_mm = 0;    // the extrusion's maximum distance
  double step_mm = 0;            // sampling step along the normals
  double spacing_mm = 0;         // h: the output spacing
  double edge_bound_mm = 0;      // the edge bound the tessellation was refined for
  double angular_step_deg = 0;   // AreaSafetyOptions::angular_step_deg
  std::string criterion;         // how "unsafe" was decided, in words (for area_safety_json)
  int64_t unknown_vertex_count = 0;  // extrusions stopped at the unknown (outside the scan)
  // Extrusions stopped at points with no value before their distance (a region of interest that
  // does not reach the vertex, voxels cropped away): not safe.
  int64_t uncomputed_vertex_count = 0;
  double threshold = 0;          // the unsafe threshold of that criterion
};

// --- Ellipsoid ----------------------------------------------------------------------------------

// PCA of the centres of the voxels > 0 (LPS mm). Radii are scaled so that a uniform solid
// ellipsoid gives back its own radii: the variance along a main axis of a solid ellipsoid is r^2/5,
// and voxel centres miss the variance of the voxel cube itself (s^2/12 along that axis), so
// r = sqrt(5 (eigenvalue + s^2/12)). Axes: columns largest radius first, right-handed.
// Throws Error naming `source` when the mask is empty.
Ellipsoid fit_tumor_ellipsoid(const Volume<uint8_t>& tumor,
                              const std::string& source = "tumor mask");

// --- Tessellation -------------------------------------------------------------------------------

// The ellipsoid tessellated on a regular spherical grid (equal angular steps in latitude and
// longitude, pi / rings): rings - 1 rings of `2 * rings` vertices plus one vertex at each pole,
// the pole on the ellipsoid's largest axis. Fills base, normals (outward ellipsoid normals),
// triangles (closed, consistently outward), vertices = base, extrusion = 0, rings, segments.
AreaSafetyGeometry tessellate_ellipsoid(const Ellipsoid& ellipsoid, int rings);

// Longest edge of the mesh with every vertex at base + distance * normal (mm).
double max_edge_length(const AreaSafetyGeometry& geometry, double distance_mm);
// Longest edge of the mesh as extruded (geometry.vertices), mm.
double max_edge_length(const AreaSafetyGeometry& geometry);

// The smallest `rings` (refined by doubling, then bisected) for which, with every vertex extruded
// to `max_distance_mm`, no edge is longer than `spacing_mm`. Throws Error when that needs more
// than `max_vertices` vertices.
int rings_for_edge_bound(const Ellipsoid& ellipsoid, double max_distance_mm, double spacing_mm,
                         int64_t max_vertices);

// --- Unsafe criterion ---------------------------------------------------------------------------

enum class PointSafety { kSafe, kUnsafe, kBeyond, kOutside, kUnknown };

// The unsafe criterion at one point (LPS mm):
// - kSafe, kUnsafe: a known value on either side of the threshold;
// - kBeyond: past the outer edge of the region of interest, where the extrusion has reached its
//   distance; the vertex is safe when every sample before was safe and there was at least one;
// - kOutside: no value although inside the region (a region of interest that does not reach
//   there, voxels cropped to the scan, a hole): the extrusion stops, the vertex is NOT safe;
// - kUnknown: outside the scan (planning/safety/unknown.hpp): the extrusion stops, the vertex is
//   NOT safe (unknown is never safe).
// Must be callable from several threads at once.
using SafetyTest = std::function<PointSafety(const Eigen::Vector3d& point)>;

// Preview (§3.3 "fast preview"): unsafe where the blocking volume (trilinear) is >= threshold
// (risk per mm); kUnknown beyond the extent of its grid (the scan: nothing is known there).
// `blocking` must outlive the returned test.
SafetyTest blocking_safety_test(const Volume<float>& blocking, double threshold);

// Path safety: unsafe where the value (trilinear over the computed voxels; NaN voxels are left out
// and their weight renormalised) is past the threshold: value > threshold, or value < threshold
// when higher_is_safer (SVV). kBeyond outside the region of interest, the ball of
// `roi_radius_mm` around the grid's centre voxel (the plan's output grid); no ball (0): nothing
// is beyond. kUnknown where the nearest voxel of `region_state` (RegionState, roi.nii.gz;
// optional) is unknown, before the value is looked at (the interpolation would borrow computed
// neighbours). kOutside inside the ball where no corner of the interpolation cell was computed.
// `path_safety` and `region_state` must outlive the returned test.
SafetyTest path_safety_test(const Volume<float>& path_safety, bool higher_is_safer,
                            double threshold, double roi_radius_mm,
                            const Volume<uint8_t>* region_state = nullptr);

// --- The geometry -------------------------------------------------------------------------------

struct AreaSafetyOptions {
  double spacing_mm = 0;           // h: the finest edge bound; required > 0
  // Directions the mesh resolves, degrees: after full extrusion no edge is longer than
  // max(h, max_distance x this angle). 1 degree is 1.7 mm per 100 mm, about a needle's width
  // (14-17 G): a safe region narrower than that holds no needle path. 0: edges within h
  // everywhere (the paper's rule; 2.9 M vertices for R = 179 mm at h = 0.7 mm).
  double angular_step_deg = 1.0;
  double max_distance_mm = 0;      // extrusion limit; required > 0 (the plan uses R)
  double step_mm = 0;              // sampling step along each normal; 0 or more than h/2: h/2
  int64_t max_vertices = 4000000;  // refuse a finer mesh (memory, file size)
  int threads = 0;                 // 0: all cores
};

// Tessellates (rings_for_edge_bound), extrudes every vertex along its normal in steps of at most
// h/2 from distance 0 up to max_distance_mm, stopping at the first sample that is not kSafe: at a
// kUnsafe one (the vertex is placed there, unsafe); at a kBeyond one (placed at the last sample
// before it, safe when there was one, else not safe and counted in uncomputed_vertex_count); at a
// kOutside one (placed at the last sample before it, not safe, counted in
// uncomputed_vertex_count); at a kUnknown one (the same, counted in unknown_vertex_count);
// classifies; finds connected safe regions over the mesh edges; measures them
// (measure_regions). Throws Error on bad options.
AreaSafetyGeometry compute_area_safety(const Ellipsoid& ellipsoid, const SafetyTest& test,
                                       const AreaSafetyOptions& options);

// From geometry.vertices, triangles and safe: connected safe regions over the mesh edges
// (union-find), their sizes, centres, main axes and leeways, and the per-vertex region and
// leeway. Size (§3.3, Alyassin et al.): the divergence theorem on the closed extruded surface,
// tetrahedra from the ellipsoid centre, (1/6) (v0 - c) x (v1 - c) . (v2 - c) per triangle; a
// triangle counts a third for each of its vertices in the region, so triangles inside a region
// count fully, border triangles (some vertices unsafe) partly, and the sizes of all regions plus
// the unsafe share add up to the enclosed volume. Regions are numbered by decreasing size.
void measure_regions(AreaSafetyGeometry& geometry);

// Enclosed volume of the closed mesh (sum of all signed tetrahedra), mm^3.
double enclosed_volume(const AreaSafetyGeometry& geometry);

// --- Files --------------------------------------------------------------------------------------

// VTK legacy POLYDATA, BINARY (big-endian, as VTK and 3D Slicer read it), LPS mm (title line
// carries "SPACE=LPS" for 3D Slicer): POINTS, POLYGONS, POINT_DATA with NORMALS (base normals) and
// scalars leeway, safe, region, extrusion_mm, leeway first so that it is the active scalar in 3D
// Slicer and ParaView; FIELD data with the ellipsoid and the regions. Written atomically
// (output_files.hpp).
void write_area_safety_vtk(const std::string& path, const AreaSafetyGeometry& geometry);

// Reads what write_area_safety_vtk wrote (BINARY, and ASCII as earlier versions wrote it; the
// scalars in any order): vertices, triangles, normals, safe, region, leeway, extrusion (base =
// vertex - extrusion * normal), ellipsoid, regions and max distance. Throws Error naming the file
// and the section when it is not such a file.
AreaSafetyGeometry read_area_safety_vtk(const std::string& path);

// The plan.json / area.json section: criterion, threshold, distances, counts and regions.
nlohmann::json area_safety_json(const AreaSafetyGeometry& geometry);

// Area safety inside the plan job (after path safety, for the first computed value).
struct AreaSafetyPlanOptions {
  bool enabled = true;
  std::string unsafe_class = "dangerous";  // "dangerous" or "medium" (medium and dangerous)
  double threshold = std::numeric_limits<double>::quiet_NaN();  // NaN: from the classes
  double max_distance_mm = 0;  // 0: the plan's region of interest radius R
  double angular_step_deg = 1.0;  // AreaSafetyOptions::angular_step_deg
};

// The plan's area safety step: for the first value computed in `result`, unsafe past the class
// threshold of options.unsafe_class (default_classes of that volume) or options.threshold; maximum
// distance R; edge bound h. `region_state`: the voxel states of the plan (extrusions stop unsafe
// at unknown voxels). Writes the mesh to `vtk_path` and returns plan.json's "area_safety".
// `geometry`, when given, receives the mesh as written.
nlohmann::json plan_area_safety(const Volume<uint8_t>& tumor, const PathSafetyResult& result,
                                const AreaSafetyPlanOptions& options, const std::string& vtk_path,
                                const Volume<uint8_t>* region_state = nullptr,
                                AreaSafetyGeometry* geometry = nullptr);

}  // namespace crepuscular::planning
