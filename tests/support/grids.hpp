// Image grids the planning tests build their scenes on.
#pragma once

#include <Eigen/Core>

#include "planning/imaging/volume.hpp"
#include "planning/safety/output_grid.hpp"

namespace crepuscular::test {

// n^3 voxels of `spacing` mm, identity direction, voxel (0, 0, 0) at `origin`.
planning::ImageGeometry cube_grid(int n, double spacing,
                                  const Eigen::Vector3d& origin = Eigen::Vector3d::Zero());

// n^3 voxels of `spacing` mm, identity direction, centred on `centre` (a voxel centre when n is
// odd, a voxel corner when it is even).
planning::ImageGeometry centred_cube_grid(int n, double spacing,
                                          const Eigen::Vector3d& centre = Eigen::Vector3d::Zero());

// 7 x 5 x 4 voxels (distinct sizes catch swapped axes), anisotropic spacing (0.8, 1.3, 2.1) mm,
// origin (-12.5, 40.25, 7.75) and a rotation of 30 degrees about the oblique axis (1, 2, 3).
planning::ImageGeometry oblique_geometry();

// The output grid of 2 half + 1 voxels of 1 mm a side, the centre voxel at the origin, the region
// of interest the ball of radius `half` voxels around it (as fast mode's sampler sees a plan).
planning::OutputGrid ball_grid(int half);

}  // namespace crepuscular::test
