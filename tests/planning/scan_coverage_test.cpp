// The scan's mask on an output grid (ScanCoverage::mask) against the definition voxel by voxel:
// a voxel is covered when its centre lies within half a voxel of the outer voxel centres of every
// input grid, each centre mapped to the input's index space through physical space.
#include "planning/imaging/scan_coverage.hpp"

#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include <cmath>
#include <random>

#include "planning/imaging/sampling.hpp"

namespace crepuscular::planning {
namespace {

ImageGeometry grid_of(Index3 dims, Eigen::Vector3d spacing, Eigen::Vector3d origin,
                      const Eigen::Matrix3d& direction) {
  ImageGeometry g;
  g.dims = dims;
  g.spacing = spacing;
  g.origin = origin;
  g.direction = direction;
  return g;
}

// How far q lies from the nearest face of g's extent, in voxels (negative: outside).
double margin_inside(const ImageGeometry& g, const Eigen::Vector3d& q) {
  double m = INFINITY;
  for (int a = 0; a < 3; ++a) m = std::min({m, q[a] + 0.5, double(g.dims[a]) - 0.5 - q[a]});
  return m;
}

TEST(ScanCoverage, MaskIsTheDefinitionVoxelByVoxelOnObliqueAndAlignedGrids) {
  // The output grid, axis-aligned, and three inputs: a thin slab of a CT on the same axes, a
  // label map tilted about two axes, and a grid whose faces lie on the output's voxel centres
  // (rows along a face, where rounding decides).
  const ImageGeometry out = grid_of({61, 47, 39}, {1.0, 1.0, 1.0}, {-30.0, -23.0, -19.0},
                                    Eigen::Matrix3d::Identity());
  const ImageGeometry slab = grid_of({80, 70, 9}, {0.8, 0.8, 3.0}, {-32.0, -28.0, -10.0},
                                     Eigen::Matrix3d::Identity());
  const Eigen::Matrix3d tilt =
      (Eigen::AngleAxisd(0.35, Eigen::Vector3d::UnitZ()) * Eigen::AngleAxisd(-0.2, Eigen::Vector3d::UnitX()))
          .toRotationMatrix();
  const ImageGeometry tilted = grid_of({50, 45, 40}, {0.9, 0.9, 1.1}, {-18.0, -30.0, -25.0}, tilt);
  // Its low x face (index -0.5: x = -20 mm) passes through a plane of output voxel centres.
  const ImageGeometry on_faces = grid_of({30, 60, 60}, {1.0, 1.0, 1.0}, {-19.5, -40.0, -40.0},
                                         Eigen::Matrix3d::Identity());
  int64_t checked = 0;
  for (const auto& inputs : std::vector<std::vector<ImageGeometry>>{
           {slab}, {tilted}, {slab, tilted}, {on_faces}, {tilted, on_faces}}) {
    ScanCoverage coverage;
    for (const ImageGeometry& g : inputs) coverage.add(g, "input");
    const Volume<uint8_t> mask = coverage.mask(out);
    int64_t covered = 0, uncovered = 0, differ = 0;
    for (int64_t k = 0; k < out.dims[2]; ++k)
      for (int64_t j = 0; j < out.dims[1]; ++j)
        for (int64_t i = 0; i < out.dims[0]; ++i) {
          const Eigen::Vector3d p = out.index_to_physical(i, j, k);
          bool inside = true;
          double nearest_face = INFINITY;
          for (const ImageGeometry& g : inputs) {
            const Eigen::Vector3d q = g.physical_to_index(p);
            inside = inside && within_extent(g, q);
            nearest_face = std::min(nearest_face, std::abs(margin_inside(g, q)));
          }
          // On a face (within rounding) either answer is the definition's.
          if (nearest_face < 1e-9) continue;
          ++checked;
          covered += inside;
          uncovered += !inside;
          differ += (mask(i, j, k) != 0) != inside;
        }
    EXPECT_EQ(differ, 0) << inputs.size() << " inputs";
    EXPECT_GT(covered, 1000);
    EXPECT_GT(uncovered, 1000);
  }
  EXPECT_GT(checked, 5 * 100000);
}

TEST(ScanCoverage, RowsOnAFaceAreDecidedAsVoxelByVoxel) {
  // An input whose low face along y lies exactly on a row of output voxel centres (-0.5 voxel in
  // its index space): the mask takes the voxel-by-voxel answer along the whole row, never half.
  const ImageGeometry out = grid_of({21, 21, 21}, {1.0, 1.0, 1.0}, {0.0, 0.0, 0.0},
                                    Eigen::Matrix3d::Identity());
  const ImageGeometry input = grid_of({40, 10, 40}, {1.0, 1.0, 1.0}, {-5.0, 5.5, -5.0},
                                      Eigen::Matrix3d::Identity());
  ScanCoverage coverage;
  coverage.add(input, "input");
  const Volume<uint8_t> mask = coverage.mask(out);
  for (int64_t i = 0; i < 21; ++i) {
    EXPECT_EQ(mask(i, 5, 10), 1) << i;  // y = 5: index -0.5, on the face: inside
    EXPECT_EQ(mask(i, 4, 10), 0) << i;
    EXPECT_EQ(mask(i, 15, 10), 1) << i;  // y = 15: index 9.5, on the high face: inside
    EXPECT_EQ(mask(i, 16, 10), 0) << i;
  }
}

}  // namespace
}  // namespace crepuscular::planning
