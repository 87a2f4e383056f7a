// What path safety builds from its inputs before a ray is cast: the tumor's surface, the output
// grid, the tumor resampled for the rays, the blocking volume's bricks and the tumor's leaps, and
// the scene the kernels read. For the planner's own modules (planning/), their tests and
// benchmarks; a caller of path safety needs path_safety.hpp alone.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "kernels/path_safety_math.hpp"
#include "planning/imaging/volume.hpp"
#include "planning/safety/output_grid.hpp"
#include "planning/safety/path_safety.hpp"

namespace crepuscular::planning {

// Tumor surface for the rays: surface voxels with centres and outward normals.
struct TumorSurface {
  std::vector<kernels::SurfacePoint<double>> points;
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();  // mean of tumor voxel centres, LPS mm
  int64_t tumor_voxels = 0;
  double s2_mm2 = 0.0;  // (voxel volume)^(2/3)
  int lo[3] = {0, 0, 0}, hi[3] = {0, 0, 0};  // index bounding box of the tumor voxels
};

// Extracts surface voxels (6-neighbourhood) and their normals: the negative gradient of the mask
// smoothed with a Gaussian of sigma = 1 voxel. Throws Error when the mask is empty.
TumorSurface extract_tumor_surface(const Volume<uint8_t>& tumor, const std::string& source);

// The output grid (output_grid.hpp) of `options`' spacing, radius and centre. Throws Error when
// the region of interest lies inside the tumor (a ball around a centre in the tumor that does not
// reach its surface).
OutputGrid make_output_grid(const Volume<float>& blocking, const Volume<uint8_t>& tumor,
                            const TumorSurface& surface, const PathSafetyOptions& options);
// The tumor mask on an isotropic grid of `spacing` with the axes of the output grid and a lattice
// through its centre (docs/ARCHITECTURE.md §4, tumor sampling): a voxel is tumor when its centre
// lies in a tumor voxel of the mask (nearest voxel). Covers the mask's tumor voxels with one voxel
// to spare. `surface` is the mask's own (its index bounding box is used).
Volume<uint8_t> resample_tumor(const Volume<uint8_t>& tumor, const TumorSurface& surface,
                               const OutputGrid& grid, double spacing);

// The blocking volume's bricks (kernels::kBrickShift, kernels::brick_code): the value every
// sample whose lower corner lies in the brick takes where that is one value (0 in empty space),
// else -1; an empty brick at Chebyshev distance d >= 2 bricks from the nearest brick that is not
// empty holds -d (capped at kernels::kMaxEmptyRun), so rays leap over the cube of empty bricks.
std::vector<float> blocking_bricks(const Volume<float>& blocking);

// The tumor's leaps (kernels::TumorGrid::leap) over its index box [lo, hi]: one byte per voxel,
// kernels::kTumorLeapInside for tumor plus the Chebyshev distance (capped at
// kernels::kMaxTumorLeap) to the nearest voxel of the other kind, voxels beyond the box counting
// as not tumor. Empty when the box is.
std::vector<uint8_t> tumor_leaps(const Volume<uint8_t>& tumor, const int lo[3], const int hi[3]);

// Builds the scene the kernels read. The returned views point into `blocking`, `tumor`,
// `surface`, `bricks` (may be empty: no uniform-space skipping) and `leaps` (tumor_leaps of the
// surface's box; may be empty: every sample of a ray's tumor walk looked up), which must outlive
// them.
kernels::PathSafetyScene<double> make_scene(const Volume<float>& blocking,
                                            const Volume<uint8_t>& tumor,
                                            const TumorSurface& surface, double gamma_mm,
                                            double eps,
                                            const std::vector<float>& bricks = {},
                                            const std::vector<uint8_t>& leaps = {});

}  // namespace crepuscular::planning
