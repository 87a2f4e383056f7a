// The CUDA backend against the CPU backend on random scenes (skips where no GPU is found).
#include "kernels/path_safety_cuda.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>

#include "kernels/path_safety_math.hpp"
#include "planning/safety/path_safety.hpp"
#include "planning/safety/path_safety_scene.hpp"
#include "planning/safety/safety_classes.hpp"

namespace crepuscular::planning {
namespace {

struct Scene {
  Volume<float> blocking;
  Volume<uint8_t> tumor;
};

ImageGeometry grid(int n, double spacing) {
  ImageGeometry g;
  g.dims = {n, n, n};
  g.spacing = Eigen::Vector3d::Constant(spacing);
  g.origin = Eigen::Vector3d::Constant(-(n - 1) / 2.0 * spacing);
  return g;
}

// Random blobs of blocking (0..3 per mm) and a tumor of the given shape near the centre.
Scene random_scene(uint32_t seed, const std::string& shape, bool aligned) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  ImageGeometry bg = grid(48, 1.3);
  Volume<float> blocking(bg, 0.0f);
  for (int b = 0; b < 12; ++b) {
    const Eigen::Vector3d c(60 * (u(rng) - 0.5), 60 * (u(rng) - 0.5), 60 * (u(rng) - 0.5));
    if (c.norm() < 9.0) continue;
    const double r = 1.5 + 5.0 * u(rng), a = 3.0 * u(rng);
    for (int64_t k = 0; k < 48; ++k)
      for (int64_t j = 0; j < 48; ++j)
        for (int64_t i = 0; i < 48; ++i) {
          const double d2 = (bg.index_to_physical(i, j, k) - c).squaredNorm();
          blocking(i, j, k) += float(a * std::exp(-d2 / (2 * r * r)));
        }
  }
  // The tumor on its own grid, aligned with the output grid or shifted by a fraction of a voxel.
  // Aligned, with the output grid centred on the tumor centroid, many samples lie exactly half-way
  // between two tumor voxels (nearest-voxel ties): both backends must resolve them alike.
  ImageGeometry tg = grid(24, 1.1);
  if (!aligned) tg.origin += Eigen::Vector3d(0.3719, 0.2113, 0.1361);
  Volume<uint8_t> tumor(tg, 0);
  for (int64_t k = 0; k < 24; ++k)
    for (int64_t j = 0; j < 24; ++j)
      for (int64_t i = 0; i < 24; ++i) {
        const Eigen::Vector3d p = tg.index_to_physical(i, j, k);
        bool in = false;
        if (shape == "sphere") in = p.norm() < 5.0;
        if (shape == "ellipsoid") in = std::pow(p.x() / 8, 2) + std::pow(p.y() / 3, 2) +
                                           std::pow(p.z() / 4, 2) < 1.0;
        if (shape == "l-shape") in = (std::abs(p.x()) < 6 && std::abs(p.y()) < 2 &&
                                      std::abs(p.z()) < 2) ||
                                     (std::abs(p.x() - 4) < 2 && std::abs(p.y()) < 2 &&
                                      p.z() > -2 && p.z() < 7);
        if (shape == "two-blobs") in = (p - Eigen::Vector3d(-5, 0, 0)).norm() < 3.0 ||
                                       (p - Eigen::Vector3d(5, 1, 0)).norm() < 3.0;
        tumor(i, j, k) = in ? 1 : 0;
      }
  return {blocking, tumor};
}

class CudaVersusCpu : public ::testing::TestWithParam<std::string> {};

// "shape" or "shape/aligned".
Scene scene_of(const std::string& param, uint32_t& seed) {
  const size_t slash = param.find('/');
  const std::string shape = param.substr(0, slash);
  seed = 1234u + uint32_t(shape.size());
  return random_scene(seed, shape, slash != std::string::npos);
}

TEST_P(CudaVersusCpu, AllValuesAgree) {
  if (kernels::cuda_device_count() == 0) GTEST_SKIP() << "no CUDA device";
  uint32_t seed = 0;
  const Scene s = scene_of(GetParam(), seed);
  SCOPED_TRACE("seed " + std::to_string(seed) + ", tumor " + GetParam());
  PathSafetyOptions o;
  o.radius_mm = 28.0;
  o.eps = 0.4;
  o.device = Device::kCpu;
  const PathSafetyResult cpu = compute_path_safety(s.blocking, s.tumor, o);
  o.device = Device::kCuda;
  const PathSafetyResult gpu = compute_path_safety(s.blocking, s.tumor, o);
  for (int v = 0; v < 4; ++v) {
    double diff2 = 0, ref2 = 0;
    int64_t n = 0, equal = 0, mismatched_nan = 0;
    const auto& a = cpu.volumes[size_t(v)].values();
    const auto& b = gpu.volumes[size_t(v)].values();
    for (size_t i = 0; i < a.size(); ++i) {
      if (std::isnan(a[i]) != std::isnan(b[i])) ++mismatched_nan;
      if (std::isnan(a[i])) continue;
      ++n;
      diff2 += double(a[i] - b[i]) * (a[i] - b[i]);
      ref2 += double(a[i]) * a[i];
      equal += a[i] == b[i];
    }
    EXPECT_EQ(mismatched_nan, 0) << "value " << v << ": region of interest differs";
    ASSERT_GT(ref2, 0.0) << "value " << v << " is all zero: the scene tests nothing";
    const double rel = std::sqrt(diff2 / ref2);
    std::printf("[ %-9s ] %s: relative L2 cpu-vs-cuda %.2e, equal %.4f %%\n",
                GetParam().c_str(), value_name(1u << v), rel, 100.0 * equal / n);
    EXPECT_LE(rel, 1e-3) << "value " << value_name(1u << v);
    if (v == 0) {
      EXPECT_GE(double(equal) / n, 0.999) << "SVV counts differ";
    }
  }
}

// Fast mode on the GPU (float rays through a texture of halves) and on the CPU (double rays in
// global memory): which cells are refined depends on values that float and double may decide
// differently, so the backends are not compared with each other but both with exact mode on the
// CPU (the reference): the GPU's fast result must be about as close to it as the CPU's and give
// the same safety class on >= 98.5 % of the voxels of these small, dense scenes.
TEST_P(CudaVersusCpu, FastModeAgrees) {
  if (kernels::cuda_device_count() == 0) GTEST_SKIP() << "no CUDA device";
  uint32_t seed = 0;
  const Scene s = scene_of(GetParam(), seed);
  SCOPED_TRACE("seed " + std::to_string(seed) + ", tumor " + GetParam());
  PathSafetyOptions o;
  o.radius_mm = 28.0;
  o.eps = 0.4;
  o.device = Device::kCpu;
  const PathSafetyResult exact = compute_path_safety(s.blocking, s.tumor, o);
  o.mode = Mode::kFast;
  o.fast.check_voxels = 0;
  const PathSafetyResult cpu = compute_path_safety(s.blocking, s.tumor, o);
  o.device = Device::kCuda;
  const PathSafetyResult gpu = compute_path_safety(s.blocking, s.tumor, o);
  const ModeDifference d_cpu = compare_volumes(exact.volumes, cpu.volumes, kernels::kAllValues);
  const ModeDifference d_gpu = compare_volumes(exact.volumes, gpu.volumes, kernels::kAllValues);
  EXPECT_EQ(d_gpu.voxels, exact.grid.roi_voxels) << "region of interest differs";
  for (int v = 0; v < 4; ++v) {
    std::printf("[ %-9s ] fast %s vs exact: relative L2 cpu %.2e cuda %.2e, same class cpu "
                "%.4f cuda %.4f\n",
                GetParam().c_str(), value_name(1u << v), d_cpu.relative_l2[size_t(v)],
                d_gpu.relative_l2[size_t(v)], d_cpu.class_agreement[size_t(v)],
                d_gpu.class_agreement[size_t(v)]);
    EXPECT_LE(d_gpu.relative_l2[size_t(v)], std::max(2.0 * d_cpu.relative_l2[size_t(v)], 2.5e-2))
        << "value " << value_name(1u << v);
    EXPECT_GE(d_gpu.class_agreement[size_t(v)], 0.985) << "value " << value_name(1u << v);
  }
}

INSTANTIATE_TEST_SUITE_P(Shapes, CudaVersusCpu,
                         ::testing::Values("sphere", "ellipsoid", "l-shape", "two-blobs",
                                           "sphere/aligned", "l-shape/aligned"),
                         [](const ::testing::TestParamInfo<std::string>& info) {
                           std::string name = info.param;
                           for (char& c : name)
                             if (c == '-' || c == '/') c = '_';
                           return name;
                         });

// Fast mode's check compared later (as plan asks, compare_check_later): its exact values are taken
// on the GPU, nothing is recomputed on the cores, and finish_fast_check gives the comparison an
// immediate check gives.
TEST(CudaFastCheck, LeftForLaterGivesTheImmediateChecksNumbers) {
  if (kernels::cuda_device_count() == 0) GTEST_SKIP() << "no CUDA device";
  uint32_t seed = 0;
  const Scene s = scene_of("sphere", seed);
  PathSafetyOptions o;
  o.radius_mm = 28.0;
  o.eps = 0.4;
  o.device = Device::kCuda;
  o.mode = Mode::kFast;
  o.fast.check_voxels = 500;
  const PathSafetyResult now = compute_path_safety(s.blocking, s.tumor, o);
  o.compare_check_later = true;
  PathSafetyResult later = compute_path_safety(s.blocking, s.tumor, o);
  EXPECT_EQ(now.fast.check_voxels, 500);
  EXPECT_FALSE(now.pending_check);
  ASSERT_TRUE(later.pending_check);
  EXPECT_EQ(later.fast.check_voxels, 0);  // not compared yet, and not recomputed on the cores
  finish_fast_check(later);
  EXPECT_FALSE(later.pending_check);
  EXPECT_EQ(later.fast.check_voxels, now.fast.check_voxels);
  for (int v = 0; v < 4; ++v) {
    EXPECT_EQ(later.fast.check_relative_l2[size_t(v)], now.fast.check_relative_l2[size_t(v)]) << v;
    EXPECT_EQ(later.fast.check_class_agreement[size_t(v)], now.fast.check_class_agreement[size_t(v)]) << v;
  }
}

// After the warm-up, a thread waiting for a device sleeps rather than spins (the cores stay free
// for the host steps of the phases beside it); the launches still give the definition's values
// (the tests after this one).
TEST(CudaWarmUp, WaitingThreadsSleep) {
  if (kernels::cuda_device_count() == 0) GTEST_SKIP() << "no CUDA device";
  EXPECT_GT(kernels::cuda_warm_up(), 0);
  EXPECT_TRUE(kernels::cuda_waits_sleep());
}

// Fast mode's point kernel (one thread per point, every sample marched, uniform bricks read from
// their codes) against the definition in double on the cores, at points side by side and
// scattered, in a large empty volume with an organ, a vessel and a tumor: a sample that took a
// wrong value would change a crossing ray's integral by tenths.
TEST(CudaPointKernel, ValuesOfTheDefinitionAtNeighboursAndScatteredPoints) {
  if (kernels::cuda_device_count() == 0) GTEST_SKIP() << "no CUDA device";
  ImageGeometry g = grid(121, 1.0);
  Volume<float> blocking(g, 0.0f);
  Volume<uint8_t> tumor(g, 0);
  for (int64_t k = 0; k < 121; ++k)
    for (int64_t j = 0; j < 121; ++j)
      for (int64_t i = 0; i < 121; ++i) {
        const Eigen::Vector3d p = g.index_to_physical(i, j, k);
        if (p.norm() <= 4.0) tumor(i, j, k) = 1;
        if ((p - Eigen::Vector3d(24, 3, -2)).norm() <= 7.0) blocking(i, j, k) = 0.8f;  // an organ
        if (std::abs(p.x() + 20) < 1.5 && std::abs(p.z() - 9) < 1.5) {                 // a vessel
          blocking(i, j, k) = 1.0f + 0.01f * float(j);
        }
      }
  const TumorSurface surface = extract_tumor_surface(tumor, "ball");
  const std::vector<float> bricks = blocking_bricks(blocking);
  int64_t empty_runs = 0;  // bricks whose codes say "empty around here": read as 0
  for (const float c : bricks) empty_runs += c < kernels::kEmptyRunBelow;
  ASSERT_GT(empty_runs, 5000);
  const kernels::PathSafetyScene<double> scene =
      make_scene(blocking, tumor, surface, 0.5, 0.05, bricks);
  kernels::OutputGridDesc desc{};
  for (int a = 0; a < 3; ++a) {
    desc.origin[a] = g.origin[a];
    for (int b = 0; b < 3; ++b) desc.axes[a][b] = a == b ? 1.0 : 0.0;
  }
  desc.n = 121;
  desc.half = 60;
  desc.max_sq = 3 * 60 * 60;
  // 16384 points (the one-thread-per-point kernel): rows of neighbours, then scattered points.
  std::mt19937 rng(11);
  std::uniform_int_distribution<int> u(0, 120);
  std::vector<int32_t> ijk;
  while (ijk.size() < 3 * 8192) {
    const int j = u(rng), k = u(rng);
    for (int i = 0; i < 121 && ijk.size() < 3 * 8192; ++i) ijk.insert(ijk.end(), {i, j, k});
  }
  while (ijk.size() < 3 * 16384) ijk.insert(ijk.end(), {u(rng), u(rng), u(rng)});
  const int64_t count = int64_t(ijk.size() / 3);
  std::vector<float> gpu(size_t(count) * kernels::kValueCount);
  {
    kernels::CudaPointEvaluator evaluator(scene, desc, kernels::kAllValues,
                                          kernels::BlockingStorage::kGlobal, 1);
    evaluator.evaluate(ijk.data(), count, gpu.data());
  }
  double diff2[4] = {}, ref2[4] = {};
  int64_t svv_same = 0, compared = 0, blocked = 0;
  for (int64_t p = 0; p < count; p += 7) {
    const kernels::Vec3<double> x = kernels::grid_point(desc.origin, desc.axes, ijk[3 * p],
                                                        ijk[3 * p + 1], ijk[3 * p + 2]);
    float ref[4] = {};
    kernels::path_safety_at<double, kernels::kAllValues>(scene, x, ref);
    for (int v = 0; v < 4; ++v) {
      const double d = double(gpu[size_t(p) * 4 + size_t(v)]) - ref[v];
      diff2[v] += d * d;
      ref2[v] += double(ref[v]) * ref[v];
    }
    svv_same += std::abs(gpu[size_t(p) * 4] - ref[0]) < 1e-3f;
    blocked += ref[1] > 0.0f;
    ++compared;
  }
  EXPECT_GT(blocked, compared / 20) << "few rays cross the organ or the vessel: tests little";
  EXPECT_GE(double(svv_same) / double(compared), 0.995);
  for (int v = 0; v < 4; ++v) {
    ASSERT_GT(ref2[v], 0.0) << value_name(1u << v);
    const double rel = std::sqrt(diff2[v] / ref2[v]);
    std::printf("[ points   ] %s: relative L2 cuda points vs cpu double %.2e\n",
                value_name(1u << v), rel);
    EXPECT_LE(rel, 1e-4) << value_name(1u << v);
  }

  // Through the texture (fast mode's storage, of floats and of halves): the kernel's own bricks
  // at texture coordinates (MarchTextureSampler) against the scene's bricks (TextureSampler),
  // which a call takes when one of its points lies beyond the reach of the kernel's bricks. The
  // same hardware filtering, so they differ only by rounding; a brick that stood for the wrong
  // value would move a crossing ray's integral by tenths.
  const auto relative_l2 = [&](const std::vector<float>& a, const std::vector<float>& b, int v,
                               int64_t every) {
    double d2 = 0.0, r2 = 0.0;
    for (int64_t p = 0; p < count; p += every) {
      const double x = a[size_t(p) * 4 + size_t(v)], y = b[size_t(p) * 4 + size_t(v)];
      d2 += (x - y) * (x - y);
      r2 += y * y;
    }
    EXPECT_GT(r2, 0.0) << value_name(1u << v);
    return r2 > 0.0 ? std::sqrt(d2 / r2) : 1.0;
  };
  std::vector<float> texture_floats;
  for (const kernels::BlockingStorage storage :
       {kernels::BlockingStorage::kTexture, kernels::BlockingStorage::kTextureHalf}) {
    const bool half = storage == kernels::BlockingStorage::kTextureHalf;
    std::vector<float> march(size_t(count) * kernels::kValueCount);
    std::vector<float> scene_bricks(size_t(count + 1) * kernels::kValueCount);
    {
      kernels::CudaPointEvaluator evaluator(scene, desc, kernels::kAllValues, storage, 1);
      evaluator.evaluate(ijk.data(), count, march.data());
      std::vector<int32_t> beyond = ijk;
      beyond.insert(beyond.end(), {desc.n + 70, desc.half, desc.half});  // past the 64 of reach
      evaluator.evaluate(beyond.data(), count + 1, scene_bricks.data());
    }
    for (int v = 0; v < 4; ++v) {
      const double bricks = relative_l2(march, scene_bricks, v, 1);
      std::printf("[ points   ] %s: relative L2 march vs scene bricks (texture of %s) %.2e\n",
                  value_name(1u << v), half ? "halves" : "floats", bricks);
      EXPECT_LE(bricks, 1e-3) << value_name(1u << v);
      EXPECT_LE(relative_l2(march, gpu, v, 7), 5e-2) << value_name(1u << v) << ": texture far off";
      if (half) {
        // Halves round each voxel by at most 2^-12 of its value; a texture read with the wrong
        // layout or format would be off by whole values.
        const double floats = relative_l2(march, texture_floats, v, 1);
        std::printf("[ points   ] %s: relative L2 texture of halves vs of floats %.2e\n",
                    value_name(1u << v), floats);
        EXPECT_LE(floats, 2e-3) << value_name(1u << v);
      }
    }
    if (!half) texture_floats = march;
  }
}

}  // namespace
}  // namespace crepuscular::planning
