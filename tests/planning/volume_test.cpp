// Tests of ImageGeometry (planning/volume.hpp): index <-> physical with a rotated, reflected and
// anisotropic grid, nearest voxel lookup, validation messages, grid comparison.
#include "planning/imaging/volume.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <random>

#include <Eigen/Geometry>
#include <cmath>
#include <limits>
#include <string>

#include "tests/support/errors.hpp"
#include "tests/support/grids.hpp"

namespace crepuscular::planning {
namespace {

using test::expect_error_containing;
using test::oblique_geometry;

// Exact arithmetic up to rounding of a handful of products: 1e-12 mm on values below 100 mm.
constexpr double kRoundingTol = 1e-12;

TEST(ImageGeometry, IndexToPhysicalIsOriginPlusDirectionColumnsScaledBySpacing) {
  const ImageGeometry g = oblique_geometry();
  // By the definition in volume.hpp: p = origin + sum_a index[a] * spacing[a] * direction.col(a).
  const Eigen::Vector3d expected = g.origin + 2.0 * 0.8 * g.direction.col(0) +
                                   3.0 * 1.3 * g.direction.col(1) + 1.0 * 2.1 * g.direction.col(2);
  EXPECT_TRUE(g.index_to_physical(2, 3, 1).isApprox(expected, kRoundingTol))
      << g.index_to_physical(2, 3, 1).transpose() << " vs " << expected.transpose();
  EXPECT_TRUE(g.index_to_physical(0, 0, 0).isApprox(g.origin, kRoundingTol));
  // One step along an index axis moves by that axis' spacing, in that axis' direction.
  for (int a = 0; a < 3; ++a) {
    Eigen::Vector3d step = Eigen::Vector3d::Zero();
    step[a] = 1.0;
    const Eigen::Vector3d moved = g.index_to_physical(step) - g.origin;
    EXPECT_NEAR(moved.norm(), g.spacing[a], kRoundingTol) << "axis " << a;
    EXPECT_NEAR(moved.normalized().dot(g.direction.col(a)), 1.0, kRoundingTol) << "axis " << a;
  }
}

TEST(ImageGeometry, PhysicalToIndexInvertsIndexToPhysicalForRotationAndReflection) {
  ImageGeometry rotated = oblique_geometry();
  ImageGeometry reflected = oblique_geometry();
  reflected.direction.col(2) *= -1.0;  // determinant -1
  ASSERT_NEAR(reflected.direction.determinant(), -1.0, 1e-12);
  for (const ImageGeometry& g : {rotated, reflected}) {
    for (const Eigen::Vector3d& index :
         {Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(6, 4, 3), Eigen::Vector3d(2.25, -1.5, 7.75)}) {
      const Eigen::Vector3d back = g.physical_to_index(g.index_to_physical(index));
      EXPECT_LT((back - index).cwiseAbs().maxCoeff(), kRoundingTol)
          << "index " << index.transpose() << " came back as " << back.transpose();
    }
  }
}

TEST(ImageGeometry, NearestIndexRoundsEachAxisToTheClosestVoxelCentre) {
  const ImageGeometry g = oblique_geometry();
  // Continuous index (2.4, 2.6, -0.4): nearest centres are 2, 3 and 0 along the three axes.
  EXPECT_EQ(g.nearest_index(g.index_to_physical(Eigen::Vector3d(2.4, 2.6, -0.4))),
            (Index3{2, 3, 0}));
  EXPECT_EQ(g.nearest_index(g.index_to_physical(Eigen::Vector3d(6.0, 4.0, 3.0))),
            (Index3{6, 4, 3}));
}

TEST(ImageGeometry, NearestIndexOfAPointOutsideTheGridIsOutsideTheGrid) {
  const ImageGeometry g = oblique_geometry();
  const Index3 below = g.nearest_index(g.index_to_physical(Eigen::Vector3d(-3.2, 1.0, 1.0)));
  EXPECT_EQ(below, (Index3{-3, 1, 1}));
  EXPECT_FALSE(g.contains(below[0], below[1], below[2]));
  const Index3 above = g.nearest_index(g.index_to_physical(Eigen::Vector3d(1.0, 1.0, 4.2)));
  EXPECT_EQ(above, (Index3{1, 1, 4}));
  EXPECT_FALSE(g.contains(above[0], above[1], above[2]));
  EXPECT_TRUE(g.contains(6, 4, 3));
}

TEST(ImageGeometry, OffsetRunsFastestAlongTheFirstIndexAndInvertsExactly) {
  const ImageGeometry g = oblique_geometry();
  EXPECT_EQ(g.voxel_count(), 7 * 5 * 4);
  EXPECT_NEAR(g.voxel_volume_mm3(), 0.8 * 1.3 * 2.1, 1e-12);
  EXPECT_EQ(g.offset(1, 0, 0), 1);
  EXPECT_EQ(g.offset(0, 1, 0), 7);
  EXPECT_EQ(g.offset(0, 0, 1), 35);
  for (int64_t offset = 0; offset < g.voxel_count(); ++offset) {
    const Index3 ijk = g.index_of_offset(offset);
    ASSERT_EQ(g.offset(ijk[0], ijk[1], ijk[2]), offset);
  }
}

TEST(ImageGeometry, ValidateAcceptsARotationAndAReflection) {
  ImageGeometry g = oblique_geometry();
  EXPECT_NO_THROW(g.validate("ct.nii.gz"));
  g.direction.col(0) *= -1.0;
  EXPECT_NO_THROW(g.validate("ct.nii.gz"));
}

TEST(ImageGeometry, ValidateRejectsAnEmptyDimensionNamingIt) {
  ImageGeometry g = oblique_geometry();
  g.dims[1] = 0;
  expect_error_containing([&] { g.validate("ct.nii.gz"); }, {"ct.nii.gz", "dimension 1", "0"});
}

TEST(ImageGeometry, ValidateRejectsZeroNegativeAndNonFiniteSpacing) {
  for (const double bad : {0.0, -1.5, std::numeric_limits<double>::quiet_NaN(),
                           std::numeric_limits<double>::infinity()}) {
    ImageGeometry g = oblique_geometry();
    g.spacing[2] = bad;
    expect_error_containing([&] { g.validate("mask.nrrd"); }, {"mask.nrrd", "spacing", "axis 2"});
  }
}

TEST(ImageGeometry, ValidateRejectsANonFiniteOrigin) {
  ImageGeometry g = oblique_geometry();
  g.origin[0] = std::numeric_limits<double>::quiet_NaN();
  expect_error_containing([&] { g.validate("ct.mha"); }, {"ct.mha", "origin"});
}

TEST(ImageGeometry, ValidateRejectsSingularAndScaledDirections) {
  ImageGeometry singular = oblique_geometry();
  singular.direction.col(2) = singular.direction.col(0);  // two equal axes: determinant 0
  expect_error_containing([&] { singular.validate("ct.nii"); }, {"ct.nii", "direction"});

  ImageGeometry scaled = oblique_geometry();
  scaled.direction *= 2.0;  // determinant 8
  expect_error_containing([&] { scaled.validate("ct.nii"); }, {"ct.nii", "direction"});
}

TEST(ImageGeometry, SameGridComparesDimsAndGeometryWithinTolerance) {
  const ImageGeometry a = oblique_geometry();
  ImageGeometry b = a;
  EXPECT_TRUE(a.same_grid(b));

  b.origin.x() += 1e-7;  // below the default tolerance 1e-6
  EXPECT_TRUE(a.same_grid(b));
  b.origin.x() += 1e-5;
  EXPECT_FALSE(a.same_grid(b));
  EXPECT_TRUE(a.same_grid(b, 1e-3));

  ImageGeometry other_dims = a;
  other_dims.dims[0] += 1;
  EXPECT_FALSE(a.same_grid(other_dims, 1.0));

  ImageGeometry other_spacing = a;
  other_spacing.spacing[1] *= 1.01;
  EXPECT_FALSE(a.same_grid(other_spacing));

  ImageGeometry other_direction = a;
  other_direction.direction.col(2) *= -1.0;
  EXPECT_FALSE(a.same_grid(other_direction));
}

}  // namespace
}  // namespace crepuscular::planning

namespace crepuscular::planning {
namespace {

// nonzero_box against a voxel-by-voxel search: rows of lengths around the 8-byte words, voxels at
// the rows' ends and at the grid's faces, a single voxel, and an empty mask.
TEST(NonzeroBox, IsTheSmallestBoxHoldingEveryVoxelThatIsNotZero) {
  std::mt19937 rng(7);
  for (const Index3 dims : {Index3{1, 1, 1}, Index3{7, 3, 2}, Index3{8, 5, 4}, Index3{9, 2, 3},
                            Index3{17, 6, 5}, Index3{33, 4, 7}}) {
    for (int trial = 0; trial < 40; ++trial) {
      ImageGeometry g;
      g.dims = dims;
      Volume<uint8_t> mask(g, 0);
      const int voxels = trial % 5;  // 0: empty
      for (int n = 0; n < voxels; ++n) {
        const int64_t i = trial % 3 == 0 ? (n % 2 ? dims[0] - 1 : 0)
                                         : int64_t(rng() % uint64_t(dims[0]));
        mask(i, int64_t(rng() % uint64_t(dims[1])), int64_t(rng() % uint64_t(dims[2]))) =
            uint8_t(1 + rng() % 255);
      }
      VoxelBox expected;
      expected.lo = dims;
      for (int64_t k = 0; k < dims[2]; ++k) {
        for (int64_t j = 0; j < dims[1]; ++j) {
          for (int64_t i = 0; i < dims[0]; ++i) {
            if (!mask(i, j, k)) continue;
            expected.lo = {std::min(expected.lo[0], i), std::min(expected.lo[1], j),
                           std::min(expected.lo[2], k)};
            expected.hi = {std::max(expected.hi[0], i), std::max(expected.hi[1], j),
                           std::max(expected.hi[2], k)};
          }
        }
      }
      const VoxelBox box = nonzero_box(mask);
      if (voxels == 0) {
        EXPECT_TRUE(box.empty());
        continue;
      }
      EXPECT_FALSE(box.empty());
      EXPECT_EQ(box.lo, expected.lo) << dims[0] << " trial " << trial;
      EXPECT_EQ(box.hi, expected.hi) << dims[0] << " trial " << trial;
    }
  }
}

}  // namespace
}  // namespace crepuscular::planning
