// Analytic cases of the path safety values (docs/ARCHITECTURE.md §4) and the input checks of the planner.
#include "planning/safety/path_safety.hpp"
#include "planning/safety/path_safety_scene.hpp"
#include "planning/safety/safety_classes.hpp"
#include "planning/safety/unknown.hpp"

#include <gtest/gtest.h>
#include <omp.h>

#include <Eigen/Geometry>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <random>

#include "foundation/error.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/grids.hpp"

namespace crepuscular::planning {
namespace {

using test::centred_cube_grid;
using test::expect_error_containing;

using kernels::kAllValues;
using kernels::kBvv;
using kernels::kIsbv;
using kernels::kIvbv;
using kernels::kSvv;

// Iterates the region of interest of a result: f(i, j, k, p) for every voxel inside the ball.
template <typename F>
void for_roi(const PathSafetyResult& r, F&& f) {
  const auto& g = r.grid.geometry;
  for (int64_t k = 0; k < g.dims[2]; ++k) {
    for (int64_t j = 0; j < g.dims[1]; ++j) {
      for (int64_t i = 0; i < g.dims[0]; ++i) {
        const Eigen::Vector3d p = g.index_to_physical(i, j, k);
        if (!r.grid.in_roi(i, j, k)) continue;
        EXPECT_LE((p - r.grid.centre).norm(), r.grid.radius_mm + 1e-6);
        f(i, j, k, p);
      }
    }
  }
}

TEST(PathSafety, NoBlockingMeansFullVisibilityAndZeroBlocking) {
  // Nothing blocks: every visible surface point is clear (SVV 100 %) and every sum of line
  // integrals is exactly 0.
  Volume<float> blocking(centred_cube_grid(21, 2.0), 0.0f);
  Volume<uint8_t> tumor(centred_cube_grid(21, 2.0), 0);
  for (int k = 9; k <= 11; ++k)
    for (int j = 9; j <= 11; ++j)
      for (int i = 9; i <= 11; ++i) tumor(i, j, k) = 1;
  PathSafetyOptions o;
  o.radius_mm = 12.0;
  const PathSafetyResult r = compute_path_safety(blocking, tumor, o);
  int64_t n = 0;
  for_roi(r, [&](int64_t i, int64_t j, int64_t k, const Eigen::Vector3d&) {
    ++n;
    EXPECT_EQ(r.volumes[0](i, j, k), 100.0f);
    EXPECT_EQ(r.volumes[1](i, j, k), 0.0f);
    EXPECT_EQ(r.volumes[2](i, j, k), 0.0f);
    EXPECT_EQ(r.volumes[3](i, j, k), 0.0f);
  });
  EXPECT_EQ(n, r.grid.roi_voxels);
  EXPECT_GT(n, 800);  // a ball of 6 voxels radius: about 4/3 pi 6^3 = 905 voxels
  // Outside the ball: not computed.
  EXPECT_TRUE(std::isnan(r.volumes[0](0, 0, 0)));
}

TEST(PathSafety, NoBlockingWithoutRadiusIsRefused) {
  Volume<float> blocking(centred_cube_grid(11, 2.0), 0.0f);
  Volume<uint8_t> tumor(centred_cube_grid(11, 2.0), 0);
  tumor(5, 5, 5) = 1;
  EXPECT_THROW(compute_path_safety(blocking, tumor, PathSafetyOptions{}), Error);
}

TEST(PathSafety, UniformBlockingSingleVoxelTumorGivesDistanceTimesBeta) {
  // One tumor voxel t, uniform b = beta: L(p,t) = beta |p - t| (every sample is beta), the single
  // surface point is always front-facing, so ISBV(p) = beta |p - t| s_T^2.
  const double beta = 0.7, s = 1.5;
  Volume<float> blocking(centred_cube_grid(41, s), float(beta));
  ImageGeometry tg = centred_cube_grid(41, s);
  Volume<uint8_t> tumor(tg, 0);
  tumor(20, 20, 20) = 1;
  const Eigen::Vector3d t = tg.index_to_physical(20, 20, 20);
  PathSafetyOptions o;
  o.values = kIsbv | kSvv;
  o.radius_mm = 12.0;
  o.eps = 1e9;
  const PathSafetyResult r = compute_path_safety(blocking, tumor, o);
  const double s2 = std::pow(s * s * s, 2.0 / 3.0);
  EXPECT_NEAR(r.s2_mm2, s2, 1e-12);
  double worst = 0.0;
  for_roi(r, [&](int64_t i, int64_t j, int64_t k, const Eigen::Vector3d& p) {
    const double expected = beta * (p - t).norm() * s2;
    const double got = r.volumes[1](i, j, k);
    // Results are stored as float32: 1e-6 relative is the storage precision (2^-24 ~ 6e-8) with
    // room for the sum of N equal terms in double.
    const double tol = 1e-6 * std::max(expected, 1e-12);
    if (std::abs(got - expected) > tol) {
      ADD_FAILURE() << "ISBV at (" << i << "," << j << "," << k << ") = " << got << ", expected "
                    << expected;
    }
    worst = std::max(worst, std::abs(got - expected) / std::max(expected, 1e-12));
    EXPECT_EQ(r.volumes[0](i, j, k), 100.0f);
  });
  RecordProperty("worst_relative_error", std::to_string(worst));
}

TEST(PathSafety, SlabLineIntegralIsBetaTimesThicknessOverCos) {
  // A slab of blocking beta, w = 8 voxels of 1 mm thick (z in [-13.5, -5.5] mm around index
  // centres), one tumor voxel at the origin. For p below the slab, the path crosses the whole slab:
  // L = beta w / |cos theta| with cos theta = (t_z - p_z) / |t - p|. Trilinear interpolation keeps
  // the integral of the profile across the slab (ramps of one voxel at each face), and the sums
  // with step <= 0.25 mm err by far less than 0.3 %.
  const double beta = 2.0;
  ImageGeometry g = centred_cube_grid(61, 1.0);
  Volume<float> blocking(g, 0.0f);
  for (int k = 17; k <= 24; ++k)  // z = k - 30: -13 .. -6
    for (int j = 0; j < 61; ++j)
      for (int i = 0; i < 61; ++i) blocking(i, j, k) = float(beta);
  const double w = 8.0;
  Volume<uint8_t> tumor(g, 0);
  tumor(30, 30, 30) = 1;
  const Eigen::Vector3d t = g.index_to_physical(30, 30, 30);
  PathSafetyOptions o;
  o.values = kIsbv;
  o.radius_mm = 25.0;
  o.spacing_mm = 0.5;
  const PathSafetyResult r = compute_path_safety(blocking, tumor, o);
  int checked = 0;
  for_roi(r, [&](int64_t i, int64_t j, int64_t k, const Eigen::Vector3d& p) {
    if (p.z() > -16.0) return;  // p must lie below the slab and its ramp
    const double cos_theta = (t.z() - p.z()) / (t - p).norm();
    const double expected = beta * w / cos_theta * r.s2_mm2;
    EXPECT_NEAR(r.volumes[1](i, j, k), expected, 3e-3 * expected)
        << "at p = " << p.transpose() << ", cos theta = " << cos_theta;
    ++checked;
  });
  EXPECT_GT(checked, 500);
}

Volume<uint8_t> cube_tumor(const ImageGeometry& g, int lo, int hi) {
  Volume<uint8_t> tumor(g, 0);
  for (int k = lo; k <= hi; ++k)
    for (int j = lo; j <= hi; ++j)
      for (int i = lo; i <= hi; ++i) tumor(i, j, k) = 1;
  return tumor;
}

// Tumor sampling (docs/ARCHITECTURE.md §4): a fine mask of a ball of 10 mm radius resampled to 2 mm holds the
// voxels whose centres lie in the ball, up to the fine mask's own half voxel at its boundary.
TEST(TumorSampling, ResampledBallHasTheBallsVoxelsAtTheNewSpacing) {
  const double radius = 10.0;
  Volume<uint8_t> fine(centred_cube_grid(61, 0.5, Eigen::Vector3d(3.0, -2.0, 1.0)), 0);
  const ImageGeometry& fg = fine.geometry();
  for (int64_t k = 0; k < 61; ++k)
    for (int64_t j = 0; j < 61; ++j)
      for (int64_t i = 0; i < 61; ++i)
        fine(i, j, k) = (fg.index_to_physical(i, j, k) - Eigen::Vector3d(3.0, -2.0, 1.0)).norm() <=
                        radius;
  const TumorSurface surface = extract_tumor_surface(fine, "ball");
  Volume<float> blocking(centred_cube_grid(31, 2.0, Eigen::Vector3d(3.0, -2.0, 1.0)), 0.0f);
  PathSafetyOptions o;
  o.spacing_mm = 2.0;
  o.radius_mm = 20.0;
  const OutputGrid grid = make_output_grid(blocking, fine, surface, o);
  const Volume<uint8_t> coarse = resample_tumor(fine, surface, grid, 2.0);
  const ImageGeometry& cg = coarse.geometry();
  EXPECT_EQ(cg.spacing, Eigen::Vector3d::Constant(2.0));
  int64_t tumor = 0;
  for (int64_t k = 0; k < cg.dims[2]; ++k) {
    for (int64_t j = 0; j < cg.dims[1]; ++j) {
      for (int64_t i = 0; i < cg.dims[0]; ++i) {
        const Eigen::Vector3d p = cg.index_to_physical(i, j, k);
        // The lattice is the output grid's: every centre is a centre of Θ.
        const Eigen::Vector3d q = grid.geometry.physical_to_index(p);
        ASSERT_NEAR((q - q.array().round().matrix()).norm(), 0.0, 1e-9);
        const double r = (p - Eigen::Vector3d(3.0, -2.0, 1.0)).norm();
        if (r < radius - 0.45) {
          EXPECT_EQ(coarse(i, j, k), 1) << r;
        }
        if (r > radius + 0.45) {
          EXPECT_EQ(coarse(i, j, k), 0) << r;
        }
        tumor += coarse(i, j, k);
      }
    }
  }
  // 4/3 pi 10^3 = 4189 mm^3 = 524 voxels of 8 mm^3.
  EXPECT_NEAR(double(tumor) * 8.0, 4.0 / 3.0 * M_PI * radius * radius * radius, 0.08 * 4189.0);
  // The grid covers the ball with a voxel to spare on every side.
  for (int a = 0; a < 3; ++a) EXPECT_GE(cg.dims[a], 11);
}

// A mask at 0.5 mm that is exactly a 2 mm mask on the output lattice plans exactly like that 2 mm
// mask: same surface points, same values, at a sixteenth of the rays.
TEST(TumorSampling, FineMaskPlansLikeTheCoarseMaskItResamplesTo) {
  const ImageGeometry coarse_grid = centred_cube_grid(21, 2.0);
  Volume<uint8_t> coarse(coarse_grid, 0);
  for (int k = 0; k < 21; ++k)
    for (int j = 0; j < 21; ++j)
      for (int i = 0; i < 21; ++i)
        coarse(i, j, k) = (i - 10) * (i - 10) + (j - 10) * (j - 10) + (k - 10) * (k - 10) <= 6;
  // Each coarse voxel split into 4^3 fine ones (centred_cube_grid of an even size: the fine
  // voxels' faces include every coarse face).
  Volume<uint8_t> fine(centred_cube_grid(84, 0.5), 0);
  for (int k = 0; k < 84; ++k)
    for (int j = 0; j < 84; ++j)
      for (int i = 0; i < 84; ++i) fine(i, j, k) = coarse(i / 4, j / 4, k / 4);
  Volume<float> blocking(coarse_grid, 0.02f);
  for (int k = 0; k < 21; ++k)
    for (int j = 0; j < 21; ++j) blocking(15, j, k) = blocking(j, 4, k) = 1.0f;
  PathSafetyOptions o;
  o.spacing_mm = 2.0;
  o.radius_mm = 14.0;
  const PathSafetyResult from_coarse = compute_path_safety(blocking, coarse, o);
  const PathSafetyResult from_fine = compute_path_safety(blocking, fine, o);
  EXPECT_FALSE(from_coarse.tumor_resampled);
  EXPECT_TRUE(from_fine.tumor_resampled);
  EXPECT_EQ(from_fine.tumor_spacing_mm, 2.0);
  EXPECT_EQ(from_fine.surface_points, from_coarse.surface_points);
  EXPECT_GT(from_fine.mask_surface_points, 10 * from_fine.surface_points);
  EXPECT_DOUBLE_EQ(from_fine.s2_mm2, 4.0);
  int64_t compared = 0;
  for_roi(from_coarse, [&](int64_t i, int64_t j, int64_t k, const Eigen::Vector3d&) {
    for (int v = 0; v < kernels::kValueCount; ++v) {
      ASSERT_NEAR(from_fine.volumes[size_t(v)](i, j, k), from_coarse.volumes[size_t(v)](i, j, k),
                  1e-4 * (1.0 + std::fabs(from_coarse.volumes[size_t(v)](i, j, k))))
          << "value " << v << " at " << i << "," << j << "," << k;
    }
    ++compared;
  });
  EXPECT_GT(compared, 1000);
  // --tumor-spacing 1 keeps more of the mask: four times the surface points, about.
  o.tumor_spacing_mm = 1.0;
  const PathSafetyResult at_1mm = compute_path_safety(blocking, fine, o);
  EXPECT_EQ(at_1mm.tumor_spacing_mm, 1.0);
  EXPECT_GT(at_1mm.surface_points, 3 * from_fine.surface_points);
}

// Uniform bricks: a sample whose lower corner lies in one is the brick's value without reading
// the volume. On a volume of constant organs, empty space, a smooth margin and values up to its
// last voxel, every sample equals the sample taken without bricks, bit for bit, and the bricks
// that are uniform are found (inside the organ, in the empty corner), those at the grid's far
// edge holding a nonzero value are not (beyond the edge is 0).
TEST(PathSafety, UniformBricksGiveTheSamplesOfTheVolume) {
  ImageGeometry g;
  g.dims = {37, 29, 23};
  g.spacing = Eigen::Vector3d(1.0, 1.2, 0.9);
  Volume<float> blocking(g, 0.0f);
  for (int64_t k = 0; k < 23; ++k)
    for (int64_t j = 0; j < 29; ++j)
      for (int64_t i = 0; i < 37; ++i) {
        float v = 0.0f;
        if (i >= 8) v = 0.1f;                                // an organ up to the far edge
        if (i >= 20 && j >= 10) v = 1.0f;                    // a higher-risk organ
        if (i >= 14 && i < 18) v = 0.1f + 0.05f * float(j);  // a margin, smooth across
        blocking(i, j, k) = v;
      }
  const std::vector<float> bricks = blocking_bricks(blocking);
  const int bx = kernels::bricks_along(37), by = kernels::bricks_along(29);
  const auto brick = [&](int x, int y, int z) { return bricks[size_t((z * by + y) * bx + x)]; };
  EXPECT_EQ(brick(0, 0, 0), 0.0f);   // voxels 0..4 along i: empty
  EXPECT_EQ(brick(2, 0, 0), 0.1f);   // voxels 8..12: the organ
  EXPECT_EQ(brick(6, 3, 1), 1.0f);   // i 24..28, j 12..16: the higher-risk organ
  EXPECT_EQ(brick(1, 0, 0), -1.0f);  // i 4..8: the organ's edge
  EXPECT_EQ(brick(3, 0, 0), -1.0f);  // the margin
  EXPECT_EQ(brick(9, 3, 1), -1.0f);  // i 36..: the next voxel lies beyond the grid (0)
  EXPECT_EQ(brick(6, 3, 5), -1.0f);  // k 20..22 + 1: beyond the grid

  const Volume<uint8_t> tumor(g, 0);
  const TumorSurface none;
  const auto with = make_scene(blocking, tumor, none, 0.5, 0.0, bricks);
  const auto without = make_scene(blocking, tumor, none, 0.5, 0.0);
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> x(-1.5, 37.5), y(-1.5, 29.5), z(-1.5, 23.5);
  int64_t uniform_samples = 0;
  for (int n = 0; n < 200000; ++n) {
    const kernels::Vec3<double> q{x(rng), y(rng), z(rng)};
    const double a = kernels::sample_blocking(with.blocking, q);
    const double b = kernels::sample_blocking(without.blocking, q);
    ASSERT_EQ(a, b) << q.x << "," << q.y << "," << q.z;
    uniform_samples += kernels::uniform_brick(with.blocking, int(std::floor(q.x)),
                                              int(std::floor(q.y)), int(std::floor(q.z))) >= 0.0f;
  }
  EXPECT_GT(uniform_samples, 40000);
}

// Empty bricks far from anything that blocks hold their Chebyshev distance to it (in bricks), so
// rays leap over them; checked against a brute-force search over every brick.
TEST(PathSafety, EmptyBricksHoldTheirDistanceToBlocking) {
  ImageGeometry g;
  g.dims = {150, 97, 61};  // 38 x 25 x 16 bricks, the last ones partial
  Volume<float> blocking(g, 0.0f);
  std::mt19937 rng(11);
  std::uniform_int_distribution<int> x(0, 149), y(0, 96), z(0, 60);
  for (int blob = 0; blob < 6; ++blob) {  // small cubes of blocking
    const int cx = x(rng), cy = y(rng), cz = z(rng);
    for (int k = std::max(0, cz - 2); k <= std::min(60, cz + 2); ++k)
      for (int j = std::max(0, cy - 2); j <= std::min(96, cy + 2); ++j)
        for (int i = std::max(0, cx - 2); i <= std::min(149, cx + 2); ++i) blocking(i, j, k) = 0.5f;
  }
  const std::vector<float> bricks = blocking_bricks(blocking);
  const int n[3] = {kernels::bricks_along(150), kernels::bricks_along(97), kernels::bricks_along(61)};
  const auto code = [&](int bx, int by, int bz) {
    return bricks[size_t((int64_t(bz) * n[1] + by) * n[0] + bx)];
  };
  // Truth: a brick is empty when all voxels of it and its trilinear support are 0.
  const auto empty = [&](int bx, int by, int bz) {
    for (int k = bz * 4; k <= std::min(bz * 4 + 4, 60); ++k)
      for (int j = by * 4; j <= std::min(by * 4 + 4, 96); ++j)
        for (int i = bx * 4; i <= std::min(bx * 4 + 4, 149); ++i)
          if (blocking(i, j, k) != 0.0f) return false;
    return true;
  };
  std::vector<uint8_t> is_empty(size_t(n[0]) * n[1] * n[2]);
  for (int bz = 0; bz < n[2]; ++bz)
    for (int by = 0; by < n[1]; ++by)
      for (int bx = 0; bx < n[0]; ++bx)
        is_empty[size_t((int64_t(bz) * n[1] + by) * n[0] + bx)] = empty(bx, by, bz);
  int leaping = 0, far = 0;
  for (int bz = 0; bz < n[2]; ++bz)
    for (int by = 0; by < n[1]; ++by)
      for (int bx = 0; bx < n[0]; ++bx) {
        const float c = code(bx, by, bz);
        if (!is_empty[size_t((int64_t(bz) * n[1] + by) * n[0] + bx)]) {
          EXPECT_GE(c, -1.0f);
          EXPECT_NE(c, 0.0f);
          continue;
        }
        // Distance to the nearest brick that is not empty, the bricks beyond the grid included.
        int d = std::min({bx + 1, by + 1, bz + 1, n[0] - bx, n[1] - by, n[2] - bz});
        for (int cz = 0; cz < n[2]; ++cz)
          for (int cy = 0; cy < n[1]; ++cy)
            for (int cx = 0; cx < n[0]; ++cx)
              if (!is_empty[size_t((int64_t(cz) * n[1] + cy) * n[0] + cx)])
                d = std::min(d, std::max({std::abs(cx - bx), std::abs(cy - by), std::abs(cz - bz)}));
        d = std::min(d, kernels::kMaxEmptyRun);
        ASSERT_EQ(c, d >= 2 ? -float(d) : 0.0f) << bx << "," << by << "," << bz;
        leaping += d >= 2;
        far += d >= 5;
      }
  EXPECT_GT(leaping, 1000);  // the test has cubes to leap through
  EXPECT_GT(far, 50);
}

// Leaping over empty bricks changes no value, bit for bit: rays through wide empty space to a
// tumor among a few blocking structures, with and without the bricks.
TEST(PathSafety, LeapingOverEmptyBricksChangesNoValue) {
  const ImageGeometry g = centred_cube_grid(81, 1.0);
  Volume<float> blocking(g, 0.0f);
  Volume<uint8_t> tumor(g, 0);
  for (int64_t k = 0; k < 81; ++k)
    for (int64_t j = 0; j < 81; ++j)
      for (int64_t i = 0; i < 81; ++i) {
        const Eigen::Vector3d p = g.index_to_physical(i, j, k);
        if (p.norm() <= 4.0) tumor(i, j, k) = 1;
        if ((p - Eigen::Vector3d(14, 3, -2)).norm() <= 5.0) blocking(i, j, k) = 0.8f;  // an organ
        if (std::abs(p.x() + 12) < 1.5 && std::abs(p.z() - 6) < 1.5) {               // a vessel
          blocking(i, j, k) = 1.0f + 0.01f * float(j);
        }
      }
  const TumorSurface surface = extract_tumor_surface(tumor, "ball");
  const std::vector<float> bricks = blocking_bricks(blocking);
  int64_t leaping = 0;
  for (float c : bricks) leaping += c < kernels::kEmptyRunBelow;
  ASSERT_GT(leaping, 500);
  const auto with = make_scene(blocking, tumor, surface, 0.5, 0.01, bricks);
  const auto without = make_scene(blocking, tumor, surface, 0.5, 0.01);
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-39.0, 39.0);
  int blocked = 0;
  for (int n = 0; n < 300; ++n) {
    const kernels::Vec3<double> p{u(rng), u(rng), u(rng)};
    float a[4] = {-1, -1, -1, -1}, b[4] = {-2, -2, -2, -2}, c[4] = {-3, -3, -3, -3};
    kernels::path_safety_at<double, kAllValues>(with, p, a);
    kernels::path_safety_at<double, kAllValues>(without, p, b);
    // The march that samples every step (the GPU point kernel's) reads the same codes as 0.
    kernels::path_safety_at<double, kAllValues, kernels::GridSampler<double>,
                            kernels::kMarchEverySample>(with, p, c,
                                                        kernels::GridSampler<double>{with.blocking});
    for (int v = 0; v < 4; ++v) {
      ASSERT_EQ(a[v], b[v]) << "value " << v << " at sample " << n;
      ASSERT_EQ(c[v], b[v]) << "value " << v << " at sample " << n;
    }
    blocked += b[1] > 0.0f;
  }
  EXPECT_GT(blocked, 20);  // some rays cross the organ or the vessel
}

// A tumor that is not convex, on an anisotropic grid turned against the blocking volume's: two
// overlapping balls with a hollow in one and a third ball apart (several pieces, a cavity).
Volume<uint8_t> lumpy_tumor(ImageGeometry& g) {
  g.dims = {40, 34, 27};
  g.spacing = Eigen::Vector3d(0.7, 0.9, 1.3);
  g.direction = Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  g.origin = -g.direction * (Eigen::Vector3d(20 * 0.7, 17 * 0.9, 13 * 1.3));
  Volume<uint8_t> tumor(g, 0);
  for (int64_t k = 0; k < 27; ++k)
    for (int64_t j = 0; j < 34; ++j)
      for (int64_t i = 0; i < 40; ++i) {
        const Eigen::Vector3d p = g.index_to_physical(i, j, k);
        const bool a = (p - Eigen::Vector3d(-2, 1, 0)).norm() <= 6.5;
        const bool hollow = (p - Eigen::Vector3d(-3, 1, 0)).norm() <= 2.5;
        const bool b = (p - Eigen::Vector3d(5, -2, 3)).norm() <= 4.0;
        const bool c = (p - Eigen::Vector3d(2, 8, -8)).norm() <= 2.2;
        tumor(i, j, k) = ((a && !hollow) || b || c) ? 1 : 0;
      }
  return tumor;
}

// The tumor's leaps against a brute-force search: each voxel of the box holds its kind and its
// Chebyshev distance to the nearest voxel of the other kind, voxels beyond the box not tumor.
TEST(PathSafety, TumorLeapsHoldTheChebyshevDistanceToTheOtherKind) {
  ImageGeometry g;
  const Volume<uint8_t> tumor = lumpy_tumor(g);
  const TumorSurface surface = extract_tumor_surface(tumor, "lumpy");
  const std::vector<uint8_t> leaps = tumor_leaps(tumor, surface.lo, surface.hi);
  const int m[3] = {surface.hi[0] - surface.lo[0] + 1, surface.hi[1] - surface.lo[1] + 1,
                    surface.hi[2] - surface.lo[2] + 1};
  ASSERT_EQ(leaps.size(), size_t(m[0]) * m[1] * m[2]);
  const auto in = [&](int i, int j, int k) {  // box indices; beyond the box: not tumor
    return i >= 0 && j >= 0 && k >= 0 && i < m[0] && j < m[1] && k < m[2] &&
           tumor(surface.lo[0] + i, surface.lo[1] + j, surface.lo[2] + k) != 0;
  };
  std::array<int, 8> histogram{};
  for (int k = 0; k < m[2]; ++k)
    for (int j = 0; j < m[1]; ++j)
      for (int i = 0; i < m[0]; ++i) {
        const bool kind = in(i, j, k);
        int d = 1;  // grow the cube until it holds a voxel of the other kind
        for (bool found = false; !found; ++d) {
          for (int c = k - d; c <= k + d && !found; ++c)
            for (int b = j - d; b <= j + d && !found; ++b)
              for (int a = i - d; a <= i + d && !found; ++a) found = in(a, b, c) != kind;
          if (found) break;
        }
        const uint8_t code = leaps[size_t((k * m[1] + j) * m[0] + i)];
        ASSERT_EQ((code & kernels::kTumorLeapInside) != 0, kind) << i << "," << j << "," << k;
        ASSERT_EQ(code & kernels::kMaxTumorLeap, std::min(d, kernels::kMaxTumorLeap))
            << i << "," << j << "," << k;
        ++histogram[size_t(std::min(d, 7))];
      }
  EXPECT_GT(histogram[3] + histogram[4], 500) << histogram[3] << " " << histogram[4];
  EXPECT_GT(histogram[5], 0);  // deep enough to leap inside and outside
}

// Walking over the leaps finds the tumor's occupancy of every sample: front- and back-facing and
// the samples inside, ray by ray, for points far, near, inside the tumor's box and within a
// hundredth of a voxel of t (the walk's tiny steps), against the walk that looks at every sample;
// and the four values bit for bit.
TEST(PathSafety, TumorLeapsGiveTheWalkOfEverySample) {
  ImageGeometry tg;
  const Volume<uint8_t> tumor = lumpy_tumor(tg);
  const TumorSurface surface = extract_tumor_surface(tumor, "lumpy");
  const std::vector<uint8_t> leaps = tumor_leaps(tumor, surface.lo, surface.hi);
  const ImageGeometry g = centred_cube_grid(61, 1.0);
  Volume<float> blocking(g, 0.0f);
  for (int64_t k = 0; k < 61; ++k)
    for (int64_t j = 0; j < 61; ++j)
      for (int64_t i = 0; i < 61; ++i) {
        const Eigen::Vector3d p = g.index_to_physical(i, j, k);
        if ((p - Eigen::Vector3d(14, 3, -2)).norm() <= 5.0) blocking(i, j, k) = 0.8f;
      }
  const auto with = make_scene(blocking, tumor, surface, 0.35, 0.01, {}, leaps);
  const auto without = make_scene(blocking, tumor, surface, 0.35, 0.01);
  ASSERT_NE(with.tumor.leap, nullptr);
  ASSERT_EQ(without.tumor.leap, nullptr);
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> far(-29.0, 29.0), near(-9.0, 9.0), tiny(-0.004, 0.004);
  std::uniform_int_distribution<size_t> pick(0, surface.points.size() - 1);
  int64_t rays = 0, front = 0, back = 0, chords = 0;
  for (int n = 0; n < 3000; ++n) {
    const auto& t = surface.points[pick(rng)];
    kernels::Vec3<double> p;
    if (n % 3 == 0) {
      p = {far(rng), far(rng), far(rng)};
    } else if (n % 3 == 1) {
      p = {near(rng), near(rng), near(rng)};
    } else {  // within a hundredth of a voxel of t, or on it
      p = {t.position.x + tiny(rng), t.position.y + tiny(rng), t.position.z + tiny(rng)};
      if (n % 30 == 2) p = t.position;
    }
    const auto ray_with = kernels::make_ray(with, p, t);
    const auto ray_without = kernels::make_ray(without, p, t);
    const auto a = kernels::cross_tumor(with.tumor, ray_with, t.offset, true);
    const auto b = kernels::cross_tumor(without.tumor, ray_without, t.offset, true);
    ASSERT_EQ(a.front_facing, b.front_facing) << "ray " << n;
    ASSERT_EQ(a.back_facing, b.back_facing) << "ray " << n;
    ASSERT_EQ(a.samples_in_tumor, b.samples_in_tumor) << "ray " << n;
    ++rays;
    front += b.front_facing;
    back += b.back_facing;
    chords += b.samples_in_tumor > 20;
  }
  // Every kind of ray was walked: seen, seen through, and crossing the tumor.
  EXPECT_GT(front, 300);
  EXPECT_GT(back, 300);
  EXPECT_LT(front + back, 2 * rays);
  EXPECT_GT(chords, 100);
  for (int n = 0; n < 60; ++n) {
    const kernels::Vec3<double> p{far(rng), far(rng), near(rng)};
    float x[4] = {-1, -1, -1, -1}, y[4] = {-2, -2, -2, -2};
    kernels::path_safety_at<double, kAllValues>(with, p, x);
    kernels::path_safety_at<double, kAllValues>(without, p, y);
    for (int v = 0; v < 4; ++v) ASSERT_EQ(x[v], y[v]) << "value " << v << " at point " << n;
  }
}

// The tumor walk stops early only where nothing more of it is used: against a walk that looks at
// every sample toward p (k = 1..N) and beyond t to the tumor's box, front- and back-facing agree on
// every ray, and the samples inside the tumor wherever t is back-facing (the chord IVBV uses).
TEST(PathSafety, TumorWalkStopsOnlyWhereNothingMoreIsUsed) {
  ImageGeometry tg;
  const Volume<uint8_t> tumor = lumpy_tumor(tg);
  const TumorSurface surface = extract_tumor_surface(tumor, "lumpy");
  const std::vector<uint8_t> leaps = tumor_leaps(tumor, surface.lo, surface.hi);
  const Volume<float> blocking(centred_cube_grid(41, 1.0), 0.0f);
  for (const bool leaping : {true, false}) {
    const auto scene = leaping ? make_scene(blocking, tumor, surface, 0.35, 0.01, {}, leaps)
                               : make_scene(blocking, tumor, surface, 0.35, 0.01);
    std::mt19937 rng(9);
    std::uniform_real_distribution<double> far(-29.0, 29.0), near(-9.0, 9.0);
    std::uniform_int_distribution<size_t> pick(0, surface.points.size() - 1);
    int neither = 0, back_chords = 0;
    for (int n = 0; n < 3000; ++n) {
      const auto& t = surface.points[pick(rng)];
      const kernels::Vec3<double> p = n % 2 ? kernels::Vec3<double>{far(rng), far(rng), far(rng)}
                                            : kernels::Vec3<double>{near(rng), near(rng), near(rng)};
      const auto d = p - t.position;
      if (kernels::dot(d, d) < 0.05 * 0.05) continue;  // tiny steps: the leap test's case
      const auto ray = kernels::make_ray(scene, p, t);
      const auto walked = kernels::cross_tumor(scene.tumor, ray, t.offset, true);
      // Every sample, from the definition: x_k = p + k (t - p) / N, nearest voxel.
      const kernels::Vec3<double> r0 = kernels::shift_for_ties(ray.r0);
      bool front = true, back = true;
      int inside = 0;
      for (int k = 1; k <= ray.n; ++k) {
        const int off =
            kernels::tumor_offset_at_shifted(scene.tumor, kernels::along_rn(r0, ray.dr, double(k)));
        if (off < 0) continue;
        ++inside;
        if (off != t.offset && k < ray.n) front = false;
      }
      double k_in, k_out;
      kernels::box_range(ray.r0, ray.dr, scene.tumor.lo, scene.tumor.hi, k_in, k_out);
      for (double k = double(ray.n) + 1.0; k <= k_out; k = kernels::add_rn(k, 1.0)) {
        const int off = kernels::tumor_offset_at_shifted(scene.tumor, kernels::along_rn(r0, ray.dr, k));
        if (off >= 0 && off != t.offset) back = false;
      }
      ASSERT_EQ(walked.front_facing, front) << "ray " << n;
      ASSERT_EQ(walked.back_facing, back) << "ray " << n;
      if (back) {
        ASSERT_EQ(walked.samples_in_tumor, inside) << "ray " << n;
        back_chords += inside > 20;
      }
      neither += !front && !back;
    }
    EXPECT_GT(neither, 200) << leaping;      // walks that stop early
    EXPECT_GT(back_chords, 100) << leaping;  // whole chords through the tumor
  }
}

// A sampler that counts its samples (the march's cost) and reads the grid.
struct CountingSampler {
  kernels::GridSampler<double> grid;
  int64_t* samples;
  double operator()(kernels::Vec3<double> q) const {
    ++*samples;
    return grid(q);
  }
  double mixed(kernels::Vec3<double> q) const {
    ++*samples;
    return grid.mixed(q);
  }
};

// Fast mode's quadrature (blocking_stride 2) against the definition, one ray at a time, in a
// blocking volume that is linear in space: trilinear interpolation of a linear field is that
// field, and the midpoint of a run of two samples is their mean, so the line integral of every
// ray is the definition's (SVV, ISBV, IVBV) and BVV's sum of b_k k^2 differs by exactly
// f''(k_c) / 4 per run, f(k) = b(x_k) k^2 (a cubic in k). Half the samples are read.
TEST(PathSafety, RaysTakenInRunsOfTwoSamplesKeepTheLineIntegralOfALinearField) {
  const ImageGeometry g = centred_cube_grid(61, 1.0);
  Volume<float> blocking(g, 0.0f);
  Volume<uint8_t> tumor(g, 0);
  const Eigen::Vector3d grad(0.004, -0.003, 0.002);
  const auto field = [&](const Eigen::Vector3d& x) { return 0.3 + grad.dot(x); };
  for (int64_t k = 0; k < 61; ++k)
    for (int64_t j = 0; j < 61; ++j)
      for (int64_t i = 0; i < 61; ++i) {
        const Eigen::Vector3d p = g.index_to_physical(i, j, k);
        blocking(i, j, k) = float(field(p));
        if (p.norm() <= 3.5) tumor(i, j, k) = 1;
      }
  const TumorSurface surface = extract_tumor_surface(tumor, "ball");
  auto exact = make_scene(blocking, tumor, surface, 0.5, 5.0);
  auto runs = exact;
  runs.blocking_stride = 2;
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> u(-25.0, 25.0);
  int rays = 0;
  for (int n = 0; n < 40; ++n) {
    const kernels::Vec3<double> p{u(rng), u(rng), u(rng)};
    if (std::sqrt(kernels::dot(p, p)) < 6.0) continue;
    for (size_t t = 0; t < surface.points.size(); t += 7) {
      const auto& target = surface.points[t];
      const auto ray = kernels::make_ray(exact, p, target);
      const auto crossing = kernels::cross_tumor(exact.tumor, ray, target.offset, true);
      if (!crossing.front_facing && !crossing.back_facing) continue;
      int64_t samples_exact = 0, samples_runs = 0;
      kernels::VoxelState<double> a, b;
      kernels::combine_ray<double, kAllValues, CountingSampler, kernels::kMarchEverySample>(
          a, exact, p, target, CountingSampler{{exact.blocking}, &samples_exact});
      kernels::combine_ray<double, kAllValues, CountingSampler, kernels::kMarchEverySample>(
          b, runs, p, target, CountingSampler{{runs.blocking}, &samples_runs});
      ASSERT_EQ(samples_exact, ray.n);
      ASSERT_EQ(samples_runs, ray.n / 2 + ray.n % 2);
      ASSERT_GT(a.isbv.sum + a.ivbv.sum, 0.0);
      EXPECT_NEAR(b.isbv.sum, a.isbv.sum, 1e-6 * a.isbv.sum);  // float texels
      EXPECT_NEAR(b.ivbv.sum, a.ivbv.sum, 1e-6 * a.ivbv.sum);
      EXPECT_EQ(b.svv.visible, a.svv.visible);
      EXPECT_EQ(b.svv.clear, a.svv.clear);
      // BVV: the runs' midpoints k_c = 2 j - 1/2, j = 1..N/2; f''(k) = 2 b(x_k) + 4 k b' + ...
      // for b(x_k) = b0 + beta k: f''(k) = 2 b0 + 6 beta k.
      const Eigen::Vector3d pe(p.x, p.y, p.z), te(target.position.x, target.position.y,
                                                  target.position.z);
      const double b0 = field(pe), beta = grad.dot(te - pe) / ray.n;
      double correction = 0.0;
      for (int j = 1; j <= ray.n / 2; ++j) {
        const double kc = 2.0 * j - 0.5;
        correction += (2.0 * b0 + 6.0 * beta * kc) / 4.0;
      }
      const double scale = (crossing.back_facing ? ray.cos_alpha : 0.0) * double(ray.step) / (double(ray.n) * ray.n);
      EXPECT_NEAR(a.bvv.sum - b.bvv.sum, correction * scale, 1e-6 * a.bvv.sum);
      if (crossing.back_facing) {
        EXPECT_GT(std::abs(correction * scale), 2e-5 * a.bvv.sum);  // the difference is seen
      }
      ++rays;
    }
  }
  EXPECT_GT(rays, 100);
}

// Front- and back-facing sets of the surface seen from p.
void facing_sets(const Volume<float>& blocking, const Volume<uint8_t>& tumor,
                 const Eigen::Vector3d& p, std::vector<Index3>& front, std::vector<Index3>& back) {
  const TumorSurface surface = extract_tumor_surface(tumor, "cube");
  const auto scene = make_scene(blocking, tumor, surface, 0.5, 0.0);
  for (const auto& sp : surface.points) {
    const auto ray = kernels::make_ray(scene, {p.x(), p.y(), p.z()}, sp);
    const auto c = kernels::cross_tumor(scene.tumor, ray, sp.offset, true);
    const Index3 idx = tumor.geometry().index_of_offset(sp.offset);
    if (c.front_facing) front.push_back(idx);
    if (c.back_facing) back.push_back(idx);
  }
}

TEST(PathSafety, FrontFacingSetOfCubeIsNearFace) {
  // A 5x5x5 cube seen from 30 mm above its centre along +z: the front-facing set is exactly the
  // 25 voxels of the top face, the back-facing set exactly the 25 of the bottom face.
  const ImageGeometry g = centred_cube_grid(41, 1.0);
  const Volume<float> blocking(g, 0.0f);
  const Volume<uint8_t> tumor = cube_tumor(g, 18, 22);
  std::vector<Index3> front, back;
  facing_sets(blocking, tumor, Eigen::Vector3d(0, 0, 30), front, back);
  ASSERT_EQ(front.size(), 25u);
  for (const auto& f : front) EXPECT_EQ(f[2], 22);
  ASSERT_EQ(back.size(), 25u);
  for (const auto& b : back) EXPECT_EQ(b[2], 18);
  // Seen from the opposite side: mirrored.
  front.clear();
  back.clear();
  facing_sets(blocking, tumor, Eigen::Vector3d(0, 0, -30), front, back);
  ASSERT_EQ(front.size(), 25u);
  for (const auto& f : front) EXPECT_EQ(f[2], 18);
  ASSERT_EQ(back.size(), 25u);
  for (const auto& b : back) EXPECT_EQ(b[2], 22);
}

TEST(PathSafety, DefaultClassesOfAVolumeAreThoseOfItsPositiveValues) {
  // The volume's thresholds (found from a histogram of the values' bits) against nth_element over
  // a copy of its positive finite values: equal, bit for bit, for values with ties, NaN (unknown),
  // infinities, zeros and negatives among them, and for one of 0.6 M voxels.
  std::mt19937 rng(5);
  for (int64_t side : {1, 7, 23, 85}) {
    Volume<float> v(centred_cube_grid(side, 1.0), 0.0f);
    std::lognormal_distribution<float> size(0.0f, 1.0f);
    std::uniform_int_distribution<int> kind(0, 19);
    for (float& x : v.values()) {
      const int k = kind(rng);
      x = k == 0 ? std::numeric_limits<float>::quiet_NaN()
        : k == 1 ? std::numeric_limits<float>::infinity()
        : k == 2 ? -size(rng)
        : k <= 5 ? 0.0f
        : k <= 7 ? 2.5f  // ties
                 : size(rng);
    }
    // The statistics of the same pass: the finite values (infinities and NaN left out).
    ValueStatistics truth;
    for (const float x : v.values()) {
      if (!std::isfinite(x)) continue;
      ++truth.voxels;
      truth.min = std::min(truth.min, double(x));
      truth.max = std::max(truth.max, double(x));
      truth.sum += x;
    }
    for (unsigned bit : {kernels::kIsbv, kernels::kIvbv, kernels::kBvv, kernels::kSvv}) {
      std::vector<float> copy(v.values().begin(), v.values().end());
      const SafetyClasses want = default_classes_of(bit, copy);
      ValueStatistics statistics;
      const SafetyClasses got = default_classes(bit, v, &statistics);
      EXPECT_EQ(statistics.voxels, truth.voxels) << "side " << side;
      EXPECT_EQ(statistics.min, truth.min) << "side " << side;
      EXPECT_EQ(statistics.max, truth.max) << "side " << side;
      EXPECT_NEAR(statistics.sum, truth.sum, 1e-9 * std::abs(truth.sum)) << "side " << side;
      // The sum's chunks are added in order: the same bits on one thread as on several.
      const int threads = omp_get_max_threads();
      omp_set_num_threads(1);
      const ValueStatistics alone = value_statistics(v);
      omp_set_num_threads(threads);
      EXPECT_EQ(alone.sum, statistics.sum) << "side " << side;
      EXPECT_EQ(alone.voxels, statistics.voxels) << "side " << side;
      EXPECT_EQ(got.safe, want.safe) << "side " << side << " value " << bit;
      EXPECT_EQ(got.dangerous, want.dangerous) << "side " << side << " value " << bit;
      EXPECT_EQ(got.higher_is_safer, want.higher_is_safer);
      if (side > 1 && bit != kernels::kSvv) {
        EXPECT_LT(got.safe, got.dangerous);
      }
    }
  }
  // Nothing positive: both thresholds 0.
  const Volume<float> empty(centred_cube_grid(5, 1.0), 0.0f);
  EXPECT_EQ(default_classes(kernels::kBvv, empty).safe, 0.0);
  EXPECT_EQ(default_classes(kernels::kBvv, empty).dangerous, 0.0);
}

TEST(PathSafety, MirroredSceneGivesMirroredVolume) {
  // Blocking symmetric under z -> -z about the cube tumor's centre (a blob above and its mirror
  // image below, plus an asymmetric blob in x so the test is not trivially symmetric in x): every
  // value at (i, j, k) equals the value at (i, j, n-1-k).
  const ImageGeometry g = centred_cube_grid(31, 1.0);
  Volume<float> blocking(g, 0.0f);
  for (int k = 0; k < 31; ++k)
    for (int j = 0; j < 31; ++j)
      for (int i = 0; i < 31; ++i) {
        const Eigen::Vector3d p = g.index_to_physical(i, j, k);
        const double a = std::exp(-(p - Eigen::Vector3d(3, 1, 8)).squaredNorm() / 8.0);
        const double b = std::exp(-(p - Eigen::Vector3d(3, 1, -8)).squaredNorm() / 8.0);
        const double c = std::exp(-(p - Eigen::Vector3d(-9, 0, 0)).squaredNorm() / 4.0);
        blocking(i, j, k) = float(a + b + 0.5 * c);
      }
  const Volume<uint8_t> tumor = cube_tumor(g, 14, 16);
  PathSafetyOptions o;
  o.radius_mm = 12.0;
  o.eps = 0.3;
  // A spacing incommensurate with the voxels keeps samples off exact nearest-voxel ties (x.5),
  // which round the same way on both sides and would break the symmetry by one voxel.
  o.spacing_mm = 0.6180339887;
  const PathSafetyResult r = compute_path_safety(blocking, tumor, o);
  const int64_t n = r.grid.geometry.dims[2];
  double max_value[4] = {0, 0, 0, 0};
  for_roi(r, [&](int64_t i, int64_t j, int64_t k, const Eigen::Vector3d&) {
    for (int v = 0; v < 4; ++v) {
      const double a = r.volumes[size_t(v)](i, j, k), b = r.volumes[size_t(v)](i, j, n - 1 - k);
      max_value[v] = std::max(max_value[v], std::abs(a));
      EXPECT_NEAR(a, b, 1e-5 * std::max(1.0, std::abs(a))) << "value " << v << " at " << i << ","
                                                             << j << "," << k;
    }
  });
  for (int v = 1; v < 4; ++v) EXPECT_GT(max_value[v], 0.0) << "value " << v << " is all zero";
}

// --- Input checks ------------------------------------------------------------------------------

struct SmallScene {
  Volume<float> blocking{centred_cube_grid(11, 2.0), 1.0f};
  Volume<uint8_t> tumor{centred_cube_grid(11, 2.0), 0};
  SmallScene() { tumor(5, 5, 5) = 1; }
};

TEST(PathSafetyInput, EmptyTumorMaskIsRefused) {
  SmallScene s;
  s.tumor(5, 5, 5) = 0;
  expect_error_containing([&] { compute_path_safety(s.blocking, s.tumor, {}, "b", "tum.nii"); },
                          "tum.nii: tumor mask is empty");
}

TEST(PathSafetyInput, TumorOutsideBlockingVolumeIsRefused) {
  SmallScene s;
  ImageGeometry far = s.tumor.geometry();
  far.origin += Eigen::Vector3d(100, 0, 0);
  Volume<uint8_t> tumor(far, 0);
  tumor(5, 5, 5) = 1;
  expect_error_containing([&] { compute_path_safety(s.blocking, tumor, {}, "b", "tum.nii"); },
                          "outside the blocking volume");
}

TEST(PathSafetyInput, NegativeOrNanBlockingIsRefused) {
  SmallScene s;
  s.blocking(1, 2, 3) = -0.5f;
  expect_error_containing([&] { compute_path_safety(s.blocking, s.tumor, {}, "blk.nii", "t"); },
                          "blk.nii");
  s.blocking(1, 2, 3) = std::numeric_limits<float>::quiet_NaN();
  expect_error_containing([&] { compute_path_safety(s.blocking, s.tumor, {}, "blk.nii", "t"); },
                          "blk.nii");
}

TEST(PathSafetyInput, ZeroOrNegativeSpacingIsRefused) {
  SmallScene s;
  ImageGeometry bad = s.blocking.geometry();
  bad.spacing.y() = 0.0;
  Volume<float> blocking(bad, 1.0f);
  expect_error_containing([&] { compute_path_safety(blocking, s.tumor, {}, "blk.nii", "t"); },
                          "spacing");
  PathSafetyOptions o;
  o.spacing_mm = -1.0;
  expect_error_containing([&] { compute_path_safety(s.blocking, s.tumor, o); }, "output spacing");
}

TEST(PathSafetyInput, RegionTooLargeForMemoryIsRefusedBeforeAllocating) {
  SmallScene s;
  PathSafetyOptions o;
  o.radius_mm = 2000.0;  // 4001^3 voxels would be needed at 1 mm
  o.spacing_mm = 1.0;
  expect_error_containing([&] { compute_path_safety(s.blocking, s.tumor, o); }, "too large");
  o.radius_mm = 100.0;  // 201^3 x 4 values x 4 bytes = 130 MB > 1 MB limit
  o.memory_limit_bytes = 1 << 20;
  expect_error_containing([&] { compute_path_safety(s.blocking, s.tumor, o); },
                          "too large for memory");
}

// --spacing 1e9 or --radius 1 would leave one voxel and "every vertex safe": refused.
TEST(PathSafetyInput, RegionOfASingleVoxelIsRefused) {
  Volume<float> blocking(centred_cube_grid(11, 2.0), 0.1f);
  Volume<uint8_t> tumor(centred_cube_grid(11, 2.0), 0);
  tumor(5, 5, 5) = 1;
  PathSafetyOptions o;
  o.radius_mm = 1.0;
  expect_error_containing([&] { compute_path_safety(blocking, tumor, o); },
                          {"region of interest", "single voxel"});
  o.radius_mm = 8.0;
  o.spacing_mm = 1e9;
  expect_error_containing([&] { compute_path_safety(blocking, tumor, o); }, {"single voxel"});
}

TEST(PathSafetyInput, ValueNamesParse) {
  EXPECT_EQ(parse_value_set("svv,bvv"), kSvv | kBvv);
  EXPECT_EQ(parse_value_set("all"), kAllValues);
  EXPECT_EQ(parse_value_set(" IVBV , isbv"), kIvbv | kIsbv);
  EXPECT_THROW(parse_value_set("svv,foo"), Error);
  EXPECT_THROW(parse_value_set(""), Error);
}

// A volume read over the runs of its region (a ball, NaN beyond it) gives the classes and the
// statistics of every voxel, bit for bit (the sum's chunks span rows cut by the runs), and the
// runs are what is read: a finite value left beyond them is not counted.
TEST(PathSafety, ClassesOverTheRegionsRunsAreThoseOfEveryVoxel) {
  const int64_t side = 85;  // 614 125 voxels: the sum's chunks of 2^18 end inside rows
  OutputGrid grid;
  grid.geometry = centred_cube_grid(side, 1.0);
  grid.half = side / 2;
  grid.max_sq = 40 * 40;
  Volume<float> v(grid.geometry, std::numeric_limits<float>::quiet_NaN());
  std::mt19937 rng(11);
  std::lognormal_distribution<float> size(0.0f, 1.0f);
  for (int64_t k = 0; k < side; ++k)
    for (int64_t j = 0; j < side; ++j)
      for (int64_t i = 0; i < side; ++i) {
        if (!grid.in_roi(i, j, k)) continue;
        ++grid.roi_voxels;
        v(i, j, k) = (i + j) % 5 == 0 ? 0.0f : size(rng);
      }
  const RowRun runs = roi_runs(grid, v);
  ASSERT_TRUE(runs);
  for (unsigned bit : {kernels::kIsbv, kernels::kSvv}) {
    ValueStatistics all, in_runs;
    const SafetyClasses a = default_classes(bit, v, &all);
    const SafetyClasses b = default_classes(bit, v, &in_runs, runs);
    EXPECT_EQ(a.safe, b.safe);
    EXPECT_EQ(a.dangerous, b.dangerous);
    EXPECT_EQ(in_runs.voxels, grid.roi_voxels);
    EXPECT_EQ(all.voxels, in_runs.voxels);
    EXPECT_EQ(all.min, in_runs.min);
    EXPECT_EQ(all.max, in_runs.max);
    EXPECT_EQ(all.sum, in_runs.sum) << "the same chunks, added in the same order";
  }
  // A corner voxel (outside the ball) given a value: every voxel counts it, the runs do not.
  v(0, 0, 0) = 1e6f;
  EXPECT_EQ(value_statistics(v).voxels, grid.roi_voxels + 1);
  EXPECT_EQ(value_statistics(v, runs).voxels, grid.roi_voxels);
  EXPECT_LT(value_statistics(v, runs).max, 1e6);
  // A volume of another grid is read whole.
  const Volume<float> other(centred_cube_grid(side - 1, 1.0), 1.0f);
  EXPECT_FALSE(roi_runs(grid, other));
}

// The classes the self-check and the plan take once (PathSafetyResult::classes) are the
// volume's default_classes, and are dropped when the scan's coverage turns computed voxels
// unknown (their percentiles change); a coverage that changes no value keeps them.
TEST(PathSafety, ClassesTakenOnceFollowTheVolumeThroughTheScanCoverage) {
  const ImageGeometry g = centred_cube_grid(25, 2.0);
  Volume<float> blocking(g, 0.0f);
  Volume<uint8_t> tumor(g, 0);
  for (int k = 11; k <= 13; ++k)
    for (int j = 11; j <= 13; ++j)
      for (int i = 11; i <= 13; ++i) tumor(i, j, k) = 1;
  for (int k = 0; k < 25; ++k)
    for (int j = 0; j < 25; ++j)
      for (int i = 16; i <= 17; ++i) blocking(i, j, k) = float(0.1 + 0.05 * j);
  PathSafetyOptions o;
  o.radius_mm = 20.0;
  o.values = kIsbv | kBvv;
  PathSafetyResult r = compute_path_safety(blocking, tumor, o);
  const SafetyClasses before = classes_of(r, kIsbv);
  const SafetyClasses reference = default_classes(kIsbv, r.volumes[1]);
  EXPECT_EQ(before.safe, reference.safe);
  EXPECT_EQ(before.dangerous, reference.dangerous);
  ASSERT_TRUE(r.classes[1].has_value());
  ASSERT_TRUE(r.statistics[1].has_value()) << "taken in the classes' pass";
  EXPECT_EQ(statistics_of(r, kIsbv).max, value_statistics(r.volumes[1]).max);
  EXPECT_EQ(statistics_of(r, kIsbv).voxels, value_statistics(r.volumes[1]).voxels);
  EXPECT_GT(before.dangerous, before.safe);

  // A scan covering the whole grid changes nothing: the classes stay.
  ScanCoverage everything;
  everything.add(g, "scan");
  apply_scan_coverage(r, everything, tumor, CoverageOptions{}, nullptr);
  EXPECT_TRUE(r.classes[1].has_value());
  const int64_t before_voxels = statistics_of(r, kIsbv).voxels;

  // A scan ending at the grid's middle slab along x: half the region becomes unknown.
  ImageGeometry half = g;
  half.dims[0] = 13;
  ScanCoverage partial;
  partial.add(half, "scan");
  apply_scan_coverage(r, partial, tumor, CoverageOptions{}, nullptr);
  EXPECT_FALSE(r.classes[1].has_value());
  EXPECT_FALSE(r.statistics[1].has_value());
  EXPECT_EQ(statistics_of(r, kIsbv).voxels, value_statistics(r.volumes[1]).voxels);
  EXPECT_LT(statistics_of(r, kIsbv).voxels, before_voxels);
  const SafetyClasses after = classes_of(r, kIsbv);
  const SafetyClasses now = default_classes(kIsbv, r.volumes[1]);
  EXPECT_EQ(after.safe, now.safe);
  EXPECT_EQ(after.dangerous, now.dangerous);
  // The shadow behind the slab lay in the half now unknown: the thresholds moved.
  EXPECT_NE(after.dangerous, before.dangerous);
}

}  // namespace
}  // namespace crepuscular::planning
