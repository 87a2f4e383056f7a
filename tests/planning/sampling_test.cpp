// Tests of volume sampling (planning/imaging/sampling.hpp) and rays through a label map
// (planning/imaging/ray_march.hpp) on analytic cases: a linear field, voxel centres, NaN holes,
// a box-shaped body.
#include "planning/imaging/sampling.hpp"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>
#include <limits>

#include "planning/imaging/ray_march.hpp"
#include "tests/support/grids.hpp"

namespace crepuscular::planning {
namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();

// f(i, j, k) = 3 + 2 i - 0.5 j + 1.25 k: trilinear interpolation reproduces a linear field exactly.
double linear_field(const Eigen::Vector3d& q) {
  return 3.0 + 2.0 * q.x() - 0.5 * q.y() + 1.25 * q.z();
}

Volume<float> linear_volume() {
  Volume<float> v(test::oblique_geometry());
  const auto& d = v.dims();
  for (int64_t k = 0; k < d[2]; ++k)
    for (int64_t j = 0; j < d[1]; ++j)
      for (int64_t i = 0; i < d[0]; ++i)
        v(i, j, k) = float(linear_field(Eigen::Vector3d(double(i), double(j), double(k))));
  return v;
}

// Values are exact in float (multiples of 1/4 below 2^20); the interpolation adds a few roundings.
constexpr double kTol = 1e-9;

TEST(Sampling, PhysicalToIndexAffineMatchesImageGeometry) {
  const ImageGeometry g = test::oblique_geometry();
  const kernels::Affine<double> a = physical_to_index_affine(g);
  for (const Eigen::Vector3d& q : {Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(2.5, 1.25, 3.0),
                                   Eigen::Vector3d(-1.0, 7.0, 0.5)}) {
    const Eigen::Vector3d p = g.index_to_physical(q);
    const kernels::Vec3<double> r = a.apply({p.x(), p.y(), p.z()});
    EXPECT_NEAR(r.x, q.x(), 1e-12);
    EXPECT_NEAR(r.y, q.y(), 1e-12);
    EXPECT_NEAR(r.z, q.z(), 1e-12);
  }
}

TEST(Sampling, TrilinearOfLinearFieldIsExactInsideTheGrid) {
  const Volume<float> v = linear_volume();
  for (const Eigen::Vector3d& q :
       {Eigen::Vector3d(0.3, 0.7, 0.1), Eigen::Vector3d(2.5, 3.25, 1.75),
        Eigen::Vector3d(4.99, 3.5, 2.0), Eigen::Vector3d(1.0, 2.0, 3.0)}) {
    EXPECT_NEAR(trilinear(v, q), linear_field(q), kTol) << q.transpose();
    EXPECT_NEAR(trilinear_finite(v, q), linear_field(q), kTol) << q.transpose();
    ASSERT_TRUE(trilinear_clamped(v, q).has_value());
    EXPECT_NEAR(*trilinear_clamped(v, q), linear_field(q), kTol) << q.transpose();
    // The kernels' definition (zero outside) agrees inside the grid.
    const kernels::BlockingGrid<double> grid = blocking_grid(v);
    EXPECT_NEAR(kernels::sample_blocking(grid, kernels::Vec3<double>{q.x(), q.y(), q.z()}),
                linear_field(q), 1e-6);
  }
}

TEST(Sampling, OutsideTheGridTrilinearFadesToZeroAndClampedHoldsTheEdge) {
  const Volume<float> v = linear_volume();
  // Half-way past the last x centre: half of the edge value (the other half is outside).
  const Eigen::Vector3d q(6.5, 2.0, 1.0);
  const double edge = linear_field(Eigen::Vector3d(6.0, 2.0, 1.0));
  EXPECT_NEAR(trilinear(v, q), 0.5 * edge, kTol);
  // NaN-skipping renormalises over the corners in the grid: the edge value.
  EXPECT_NEAR(trilinear_finite(v, q), edge, kTol);
  // Clamped: the edge voxel extends to the grid's extent, and nothing beyond it.
  ASSERT_TRUE(trilinear_clamped(v, q).has_value());
  EXPECT_NEAR(*trilinear_clamped(v, q), edge, kTol);
  EXPECT_FALSE(trilinear_clamped(v, Eigen::Vector3d(6.51, 2.0, 1.0)).has_value());
  EXPECT_FALSE(within_extent(v.geometry(), Eigen::Vector3d(1.0, -0.51, 1.0)));
  EXPECT_TRUE(within_extent(v.geometry(), Eigen::Vector3d(1.0, -0.5, 1.0)));
  // Wholly outside: 0, and NaN for the NaN-skipping sampler.
  EXPECT_EQ(trilinear(v, Eigen::Vector3d(9.0, 2.0, 1.0)), 0.0);
  EXPECT_TRUE(std::isnan(trilinear_finite(v, Eigen::Vector3d(9.0, 2.0, 1.0))));
}

TEST(Sampling, NanVoxelsAreSkippedAndTheRestRenormalised) {
  Volume<float> v(test::oblique_geometry(), 0.0f);
  // Corners of the cell at (1, 1, 1): x = 1 holds 10, x = 2 holds NaN.
  for (int64_t k = 1; k <= 2; ++k)
    for (int64_t j = 1; j <= 2; ++j) {
      v(1, j, k) = 10.0f;
      v(2, j, k) = kNaN;
    }
  // Whatever the weights, only finite corners count: their weighted mean, 10.
  EXPECT_NEAR(trilinear_finite(v, Eigen::Vector3d(1.3, 1.6, 1.2)), 10.0, kTol);
  // At the NaN corners only (weight of the finite ones 0): NaN.
  EXPECT_TRUE(std::isnan(trilinear_finite(v, Eigen::Vector3d(2.0, 1.5, 1.5))));
  // The plain sampler propagates the NaN.
  EXPECT_TRUE(std::isnan(trilinear(v, Eigen::Vector3d(1.3, 1.6, 1.2))));
}

TEST(Sampling, NearestVoxelAtCentresAndBeyondTheGrid) {
  Volume<int32_t> v(test::oblique_geometry(), 0);
  const auto& d = v.dims();
  for (int64_t k = 0; k < d[2]; ++k)
    for (int64_t j = 0; j < d[1]; ++j)
      for (int64_t i = 0; i < d[0]; ++i) v(i, j, k) = int32_t(100 * k + 10 * j + i);
  const ImageGeometry& g = v.geometry();
  // At a voxel centre, and within 0.4 voxel of it, that voxel.
  EXPECT_EQ(nearest_voxel(v, g.index_to_physical(3, 2, 1)), std::optional<int32_t>(123));
  EXPECT_EQ(nearest_voxel_or(v, g.index_to_physical(Eigen::Vector3d(3.4, 1.6, 0.7)), -1), 123);
  // Beyond the last centre by more than half a voxel: outside.
  EXPECT_FALSE(nearest_voxel(v, g.index_to_physical(Eigen::Vector3d(6.6, 0, 0))).has_value());
  EXPECT_EQ(nearest_voxel_or(v, g.index_to_physical(Eigen::Vector3d(0, -0.6, 0)), -1), -1);
  EXPECT_FALSE(nearest_voxel(Volume<int32_t>(), Eigen::Vector3d::Zero()).has_value());
}

// A body of label 1 filling x in [10, 20] mm of a 1 mm grid 0..29 along x (3 voxels across y, z).
Volume<int32_t> slab_body() {
  ImageGeometry g;
  g.dims = {30, 3, 3};
  Volume<int32_t> v(g, 0);
  for (int64_t k = 0; k < 3; ++k)
    for (int64_t j = 0; j < 3; ++j)
      for (int64_t i = 10; i <= 20; ++i) v(i, j, k) = 1;
  return v;
}

TEST(RayMarch, FirstBodyExitIsTheFirstOutsideSampleAfterTheBody) {
  const Volume<int32_t> body = slab_body();
  const Eigen::Vector3d x = Eigen::Vector3d::UnitX();
  // From x = 0 (outside) in steps of 0.5 mm: inside from x = 9.5 (nearest voxel 10) to 20.0;
  // x = 20.5 rounds half away from zero to voxel 21, outside.
  const auto e = first_body_exit(body, Eigen::Vector3d(0, 1, 1), x, 0.5, 40.0);
  ASSERT_TRUE(e.has_value());
  EXPECT_DOUBLE_EQ(e->last_inside_s, 20.0);
  EXPECT_DOUBLE_EQ(e->first_outside_s, 20.5);
  EXPECT_TRUE(e->last_inside.isApprox(Eigen::Vector3d(20.0, 1, 1)));
  // Not left by max_s, or a `within` bound reached first: none.
  EXPECT_FALSE(first_body_exit(body, Eigen::Vector3d(0, 1, 1), x, 0.5, 15.0).has_value());
  EXPECT_FALSE(
      first_body_exit(body, Eigen::Vector3d(0, 1, 1), x, 0.5, 40.0, [](const Eigen::Vector3d& p) {
        return p.x() <= 18.0;
      }).has_value());
  EXPECT_TRUE(in_body(body, Eigen::Vector3d(15, 1, 1)));
  EXPECT_FALSE(in_body(body, Eigen::Vector3d(15, 5, 1)));  // outside the grid
  // Along +y the body fills the grid to its edge (y = 2.5): the skin is not in the scan, so no
  // exit (the edge of the scan is not a skin entry).
  EXPECT_FALSE(first_body_exit(body, Eigen::Vector3d(15, 0, 1), Eigen::Vector3d::UnitY(), 0.5,
                               40.0).has_value());
}

TEST(RayMarch, FirstEntryBracketsTheBoundaryToTheTolerance) {
  const Volume<int32_t> body = slab_body();
  const auto inside = [&](const Eigen::Vector3d& p) { return in_body(body, p); };
  // Nearest-voxel body from x = 9.5 (llround rounds half away from zero): the boundary.
  const auto c = first_entry(Eigen::Vector3d(0, 1, 1), Eigen::Vector3d::UnitX(), 1.0, 40.0, inside);
  ASSERT_TRUE(c.has_value());
  EXPECT_LE(c->inside_s - c->outside_s, 1e-3);
  EXPECT_LT(c->outside_s, 9.5);
  EXPECT_GE(c->inside_s, 9.5);
  // Starting inside: both 0.
  const auto at =
      first_entry(Eigen::Vector3d(15, 1, 1), Eigen::Vector3d::UnitX(), 1.0, 40.0, inside);
  ASSERT_TRUE(at.has_value());
  EXPECT_EQ(at->outside_s, 0.0);
  EXPECT_EQ(at->inside_s, 0.0);
  // The smooth skin (body fraction 0.5) lies half-way between the last outside and first inside
  // voxel centres, at x = 9.5 and 20.5.
  EXPECT_NEAR(body_fraction(body, Eigen::Vector3d(9.5, 1, 1)), 0.5, 1e-12);
  EXPECT_NEAR(body_fraction(body, Eigen::Vector3d(20.5, 1, 1)), 0.5, 1e-12);
  EXPECT_NEAR(body_fraction(body, Eigen::Vector3d(15.0, 1, 1)), 1.0, 1e-12);
}

TEST(RayMarch, OutermostExitIsOutsideTheFarSideOfTheBody) {
  const Volume<int32_t> body = slab_body();
  // From inside the body along +x: the body ends at voxel 20, i.e. x = 20.5 by nearest voxel.
  const auto e = outermost_body_exit(body, Eigen::Vector3d(15, 1, 1), Eigen::Vector3d::UnitX());
  ASSERT_TRUE(e.has_value());
  EXPECT_NEAR(e->x(), 20.5, 1e-3);
  EXPECT_FALSE(in_body(body, *e));
  // A line that misses the body (x = 5 is outside it): none.
  EXPECT_FALSE(
      outermost_body_exit(body, Eigen::Vector3d(5, 1, 1), Eigen::Vector3d::UnitY()).has_value());
  // The body reaching the grid's edge along +y: no skin seen there.
  EXPECT_FALSE(
      outermost_body_exit(body, Eigen::Vector3d(15, 1, 1), Eigen::Vector3d::UnitY()).has_value());
}

TEST(RayMarch, FibonacciSphereIsUnitAndBalanced) {
  const int n = 200;
  const std::vector<Eigen::Vector3d> dirs = fibonacci_sphere(n);
  ASSERT_EQ(dirs.size(), size_t(n));
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  for (const auto& d : dirs) {
    EXPECT_NEAR(d.norm(), 1.0, 1e-12);
    sum += d;
  }
  // Evenly spread: the mean direction is near 0 (z is exactly balanced, x and y nearly).
  EXPECT_NEAR(sum.z() / n, 0.0, 1e-12);
  EXPECT_LT(sum.norm() / n, 0.02);
  EXPECT_NEAR(dirs.front().z(), 1.0 - 1.0 / n, 1e-12);
  EXPECT_NEAR(dirs.back().z(), -1.0 + 1.0 / n, 1e-12);
}

}  // namespace
}  // namespace crepuscular::planning
