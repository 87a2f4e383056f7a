// Fast mode (coarse to fine) against exact mode on random vessel scenes: safety class agreement
// (the requirement: the same class on at least 99.5 % of the region of interest, on every scene)
// and relative L2.
#include <gtest/gtest.h>

#include <cmath>
#include <functional>
#include <random>
#include <string>

#include "planning/safety/path_safety.hpp"
#include "planning/safety/safety_classes.hpp"

namespace crepuscular::planning {
namespace {

// Vessel-like tubes (impassable and high-risk), smoothed like a 4 mm safety margin, around an
// ellipsoid tumor; fixed seed.
struct Scene {
  Volume<float> blocking;
  Volume<uint8_t> tumor;
};

Scene vessel_scene(uint32_t seed) {
  const int n = 72;
  const double s = 2.0;
  ImageGeometry g;
  g.dims = {n, n, n};
  g.spacing = Eigen::Vector3d::Constant(s);
  g.origin = Eigen::Vector3d::Constant(-(n - 1) / 2.0 * s);
  Scene scene{Volume<float>(g, 0.0f), Volume<uint8_t>(g, 0)};
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  for (int t = 0; t < 12; ++t) {
    const Eigen::Vector3d a(140 * (u(rng) - .5), 140 * (u(rng) - .5), 140 * (u(rng) - .5));
    const Eigen::Vector3d d =
        Eigen::Vector3d(u(rng) - .5, u(rng) - .5, u(rng) - .5).normalized();
    const double r = 1.5 + 3.0 * u(rng), beta = t < 4 ? 100.0 : 1.0, sigma = 1.7;
    if (a.norm() < 20) continue;
    for (int64_t k = 0; k < n; ++k)
      for (int64_t j = 0; j < n; ++j)
        for (int64_t i = 0; i < n; ++i) {
          const Eigen::Vector3d p = g.index_to_physical(i, j, k) - a;
          const double dist = (p - p.dot(d) * d).norm();
          const double v = dist < r ? beta : beta * std::exp(-0.5 * std::pow((dist - r) / sigma, 2));
          scene.blocking(i, j, k) = std::max(scene.blocking(i, j, k), float(v));
        }
  }
  for (int k = -6; k <= 6; ++k)
    for (int j = -6; j <= 6; ++j)
      for (int i = -6; i <= 6; ++i)
        if (i * i / 25.0 + j * j / 9.0 + k * k / 16.0 <= 1) scene.tumor(36 + i, 36 + j, 36 + k) = 1;
  return scene;
}

// The requirement: fast mode gives exact mode's safety class on >= 99.5 % of the voxels.
constexpr double kRequiredAgreement = 0.995;

// Fast mode against exact mode on the scene of `seed`: relative L2 (<= 0.075, 0.05 for svv) and
// class agreement >= kRequiredAgreement for every value, and its own check (300 voxels recomputed
// exactly) agrees.
void expect_fast_agrees_with_exact(uint32_t seed) {
  const Scene s = vessel_scene(seed);
  PathSafetyOptions o;
  o.radius_mm = 50.0;
  o.eps = 0.5;
  o.device = Device::kCpu;
  const PathSafetyResult exact = compute_path_safety(s.blocking, s.tumor, o);
  {
    const Mode mode = Mode::kFast;
    o.mode = mode;
    o.fast.check_voxels = 300;
    const PathSafetyResult fast = compute_path_safety(s.blocking, s.tumor, o);
    const ModeDifference d = compare_volumes(exact.volumes, fast.volumes, kernels::kAllValues);
    EXPECT_EQ(d.voxels, exact.grid.roi_voxels);
    for (int v = 0; v < kernels::kValueCount; ++v) {
      const std::string name = std::string(mode_name(mode)) + " " + value_name(1u << v);
      const double agreement = d.class_agreement[size_t(v)];
      std::printf("seed %u %s: relative L2 %.3e, class agreement %.4f (check at %lld voxels: "
                  "%.3e, %.4f)\n",
                  seed, name.c_str(), d.relative_l2[size_t(v)], agreement,
                  (long long)fast.fast.check_voxels, fast.fast.check_relative_l2[size_t(v)],
                  fast.fast.check_class_agreement[size_t(v)]);
      // Fast mode interpolates inside regions of one class, where the blocking values of the
      // dangerous class vary steeply (beside impassable tubes): its values are near, its
      // classes agree. (The level of stride 2 point by point interpolates across 4 voxels
      // where 2 were computed before: scene 3's ISBV 0.059 -> 0.068, IVBV 0.053 -> 0.062, the
      // classes unchanged.)
      const double l2_bound = v == 0 ? 0.05 : 0.075;
      EXPECT_LE(d.relative_l2[size_t(v)], l2_bound) << name;
      EXPECT_GE(agreement, kRequiredAgreement) << name;
      EXPECT_GE(fast.fast.check_class_agreement[size_t(v)], 0.99) << name;
    }
    EXPECT_EQ(fast.fast.check_voxels, 300);
    {
      // Coarse to fine fills part of the region by interpolation (in these small, dense scenes
      // it computes about as many points as exact mode; on a real grid a small fraction).
      std::printf("seed %u fast: %lld points exact, %lld interpolated of %lld\n", seed,
                  (long long)fast.fast.evaluated_points, (long long)fast.fast.interpolated_voxels,
                  (long long)fast.grid.roi_voxels);
      EXPECT_GT(fast.fast.interpolated_voxels, fast.grid.roi_voxels / 20);
    }
  }
}

// The harshest scenes of the first 16 seeds: impassable tubes close to the tumor.
TEST(PathSafetyFast, SafetyClassAgreesWithExactModeOnScene3) { expect_fast_agrees_with_exact(3); }

TEST(PathSafetyFast, SafetyClassAgreesWithExactModeOnScene11) { expect_fast_agrees_with_exact(11); }

// The scene of seed 3 planned at 1 mm output spacing (its tumor resampled to 1 mm, R 34 mm) in
// exact mode, once for the tests that hold fast mode's choices on finer grids against it.
struct FineScene {
  Scene scene;
  PathSafetyOptions options;
  PathSafetyResult exact;
};

const FineScene& fine_scene() {
  static const FineScene fine = [] {
    FineScene f{vessel_scene(3), PathSafetyOptions{}, PathSafetyResult{}};
    f.options.radius_mm = 34.0;
    f.options.spacing_mm = 1.0;
    f.options.eps = 0.5;
    f.options.device = Device::kCpu;
    f.exact = compute_path_safety(f.scene.blocking, f.scene.tumor, f.options);
    return f;
  }();
  return fine;
}

// Fast mode on the 1 mm scene (no self-check), `adjust` applied to its options, with every value
// in exact mode's class on >= 99.5 % of the region's voxels.
PathSafetyResult fast_on_fine_scene(const std::string& label,
                                    const std::function<void(PathSafetyOptions&)>& adjust) {
  const FineScene& f = fine_scene();
  PathSafetyOptions o = f.options;
  o.mode = Mode::kFast;
  o.fast.check_voxels = 0;
  adjust(o);
  PathSafetyResult fast = compute_path_safety(f.scene.blocking, f.scene.tumor, o);
  const ModeDifference d = compare_volumes(f.exact.volumes, fast.volumes, kernels::kAllValues);
  EXPECT_EQ(d.voxels, f.exact.grid.roi_voxels);
  for (int v = 0; v < kernels::kValueCount; ++v) {
    std::printf("1 mm, %s, %s: relative L2 %.3e, class agreement %.4f\n", label.c_str(),
                value_name(1u << v), d.relative_l2[size_t(v)], d.class_agreement[size_t(v)]);
    EXPECT_GE(d.class_agreement[size_t(v)], kRequiredAgreement) << label << " " << value_name(1u << v);
  }
  return fast;
}

// Finer grids start from a coarser lattice in voxels (coarsest_stride: every 8th voxel at 1 mm,
// every 4th at 2 mm; never more than 8 mm nor a quarter of the region's radius apart), and the
// finest level computes only points whose neighbours differ in a class. The 1 mm scene keeps
// exact mode's class on >= 99.5 % of the voxels.
TEST(PathSafetyFast, AutomaticStrideOnAFinerGridAgreesWithExactMode) {
  EXPECT_EQ(coarsest_stride(2.0, 100.0), 4);
  EXPECT_EQ(coarsest_stride(3.0, 100.0), 4);
  EXPECT_EQ(coarsest_stride(1.0, 100.0), 8);
  EXPECT_EQ(coarsest_stride(0.7, 179.2), 8);
  EXPECT_EQ(coarsest_stride(0.5, 100.0), 16);
  EXPECT_EQ(coarsest_stride(0.7, 12.0), 4);  // a small region: four cells across its radius
  EXPECT_EQ(coarsest_stride(1.0, 30.0), 4);
  const PathSafetyResult fast = fast_on_fine_scene("automatic stride", [](PathSafetyOptions&) {});
  EXPECT_EQ(fast.fast.coarsest_stride, 8);
  std::printf("1 mm: %lld points exact, %lld interpolated of %lld\n",
              (long long)fast.fast.evaluated_points, (long long)fast.fast.interpolated_voxels,
              (long long)fast.grid.roi_voxels);
  EXPECT_GT(fast.fast.interpolated_voxels, fast.grid.roi_voxels / 4);
  EXPECT_EQ(fast.fast.ray_stride, 2);  // automatic at 1 mm over 2 mm voxels: runs of 1 mm
}

// Runs of blocking samples taken at their midpoints (fast mode's quadrature, --fast-ray-stride):
// automatic from the output spacing and the blocking volume's (runs of at most 1.05 mm and at
// most 1.5 blocking voxels), and on the 1 mm scene with runs of three samples (1.5 mm, beyond the
// automatic choice) still exact mode's class on >= 99.5 % of the voxels. Runs of 2 mm on the 2 mm
// scenes keep only 99.0 % (seed 11, isbv): the automatic choice never takes them.
TEST(PathSafetyFast, RunsOfSamplesAtTheirMidpointsAgreeWithExactMode) {
  EXPECT_EQ(automatic_ray_stride(0.7, 0.7), 3);   // 1.05 mm
  EXPECT_EQ(automatic_ray_stride(0.7, double(0.7f)), 3);  // a spacing stored as float
  EXPECT_EQ(automatic_ray_stride(0.75, 0.7), 2);  // three would be 1.125 mm
  EXPECT_EQ(automatic_ray_stride(0.7, 0.5), 2);   // three would span 2.1 blocking voxels
  EXPECT_EQ(automatic_ray_stride(1.0, 1.0), 2);
  EXPECT_EQ(automatic_ray_stride(1.4, 0.7), 1);
  EXPECT_EQ(automatic_ray_stride(2.0, 1.0), 1);
  EXPECT_EQ(automatic_ray_stride(0.5, 0.5), 3);   // 0.75 mm, 1.5 voxels
  EXPECT_EQ(automatic_ray_stride(0.3, 1.0), 4);   // at most 4
  EXPECT_EQ(automatic_ray_stride(0.3, 0.3), 3);
  const PathSafetyResult fast = fast_on_fine_scene(
      "runs of 3 samples", [](PathSafetyOptions& o) { o.fast.ray_stride = 3; });
  EXPECT_EQ(fast.fast.ray_stride, 3);
}

// --fast-surface-block 2: one ray per block of 2^3 tumor voxels, counted once for each surface
// point of its block. The values keep their size (a weightless quarter of the rays would give
// blocking sums ~3.5x too small), and the classes stay close to exact mode's; the self-check
// compares with exact mode's every ray. Measured here: relative L2 3.6 % (svv) to 9.8 % (ivbv),
// classes 99.5-99.8 %.
TEST(PathSafetyFast, SurfaceBlocksStandForTheirPointsWithTheirWeight) {
  const Scene s = vessel_scene(3);
  PathSafetyOptions o;
  o.radius_mm = 50.0;
  o.device = Device::kCpu;
  const PathSafetyResult exact = compute_path_safety(s.blocking, s.tumor, o);
  o.mode = Mode::kFast;
  o.fast.surface_block = 2;
  o.fast.check_voxels = 300;
  const PathSafetyResult fast = compute_path_safety(s.blocking, s.tumor, o);
  EXPECT_EQ(fast.surface_points, exact.surface_points);
  EXPECT_GT(fast.fast.surface_points, exact.surface_points / 5);
  EXPECT_LT(fast.fast.surface_points, exact.surface_points / 2);
  const ModeDifference d = compare_volumes(exact.volumes, fast.volumes, kernels::kAllValues);
  for (int v = 0; v < kernels::kValueCount; ++v) {
    std::printf("surface blocks %s: relative L2 %.3e, class agreement %.4f\n",
                value_name(1u << v), d.relative_l2[size_t(v)], d.class_agreement[size_t(v)]);
    EXPECT_LE(d.relative_l2[size_t(v)], 0.2) << value_name(1u << v);
    EXPECT_GE(d.class_agreement[size_t(v)], 0.97) << value_name(1u << v);
  }
  EXPECT_EQ(fast.fast.check_voxels, 300);
}

}  // namespace
}  // namespace crepuscular::planning
