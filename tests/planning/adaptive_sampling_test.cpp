// Coarse-to-fine sampling of fast mode against fields known in closed form: where the sampler
// interpolates, where it computes, and that it never computes nor interpolates the unknown.
#include <gtest/gtest.h>

#include <cstring>

#include <chrono>
#include <cmath>
#include <set>
#include <string>
#include <thread>
#include <tuple>

#include "foundation/error.hpp"
#include "planning/safety/adaptive_sampling.hpp"

namespace crepuscular::planning {
namespace {

OutputGrid ball_grid(int half) {
  OutputGrid g;
  const int n = 2 * half + 1;
  g.geometry.dims = {n, n, n};
  g.geometry.spacing = Eigen::Vector3d::Ones();
  g.geometry.origin = Eigen::Vector3d::Constant(-half);
  g.half = half;
  g.max_sq = int64_t(half) * half;
  for (int k = 0; k < n; ++k)
    for (int j = 0; j < n; ++j)
      for (int i = 0; i < n; ++i) g.roi_voxels += g.in_roi(i, j, k);
  g.radius_mm = half;
  return g;
}

// SVV of a scene with one shadow: 20 % inside a ball of radius 7 voxels centred at (8, 0, 0)
// from the centre, 95 % elsewhere (two classes, a sharp boundary).
float shadow_svv(int64_t i, int64_t j, int64_t k, int half) {
  const double x = double(i - half) - 8.0, y = double(j - half), z = double(k - half);
  return x * x + y * y + z * z <= 49.0 ? 20.0f : 95.0f;
}

struct Sampled {
  std::vector<float> svv;
  std::set<std::tuple<int, int, int>> evaluated;
  AdaptiveReport report;
};

Sampled sample(const OutputGrid& g, const AdaptiveOptions& o) {
  Sampled run;
  const int64_t n = g.geometry.dims[0];
  run.svv.assign(size_t(n * n * n), std::nanf(""));
  float* out[kernels::kValueCount] = {run.svv.data(), nullptr, nullptr, nullptr};
  const int half = int(g.half);
  const PointEvaluator evaluate = [&](const std::vector<GridPoint>& points,
                                      std::vector<float>& values) {
    for (size_t p = 0; p < points.size(); ++p) {
      const auto key = std::make_tuple(points[p].i, points[p].j, points[p].k);
      EXPECT_TRUE(run.evaluated.insert(key).second) << "a point computed twice";
      values[p * kernels::kValueCount] = shadow_svv(points[p].i, points[p].j, points[p].k, half);
    }
  };
  run.report = sample_adaptively(g, o, evaluate, out);
  return run;
}

TEST(AdaptiveSampling, EveryVoxelHasTheClassOfTheFieldAndMostAreInterpolated) {
  const OutputGrid g = ball_grid(24);
  AdaptiveOptions o;
  o.values = kernels::kSvv;
  const Sampled run = sample(g, o);
  const int64_t n = g.geometry.dims[0];
  int64_t wrong = 0, exact = 0;
  for (int64_t k = 0; k < n; ++k)
    for (int64_t j = 0; j < n; ++j)
      for (int64_t i = 0; i < n; ++i) {
        const float v = run.svv[size_t((k * n + j) * n + i)];
        if (!g.in_roi(i, j, k)) {
          EXPECT_TRUE(std::isnan(v)) << "outside the region: " << i << "," << j << "," << k;
          continue;
        }
        // A constant field inside each class: interpolation between corners of one class is
        // exact, so every voxel must hold the field's value.
        wrong += v != shadow_svv(i, j, k, int(g.half));
        exact += run.evaluated.count({int(i), int(j), int(k)});
      }
  EXPECT_EQ(wrong, 0);
  EXPECT_EQ(run.report.interpolated + exact, g.roi_voxels);
  // The shadow's surface, not the region's volume, is computed voxel by voxel.
  EXPECT_LT(run.report.evaluated, g.roi_voxels / 3);
  EXPECT_GT(run.report.interpolated, g.roi_voxels / 2);
  ASSERT_EQ(run.report.levels.size(), 3u);  // strides 4, 2, 1
  EXPECT_EQ(run.report.levels[0].first, 4);
}

// The finest level point by point: inside a refined cell of edge 2 only the points whose own
// corners differ are computed; the same field is right at every voxel either way, with fewer
// points computed than when every voxel of a refined cell is.
TEST(AdaptiveSampling, FinestLevelComputesOnlyBetweenCornersThatDiffer) {
  const OutputGrid g = ball_grid(24);
  AdaptiveOptions o;
  o.values = kernels::kSvv;
  o.pointwise_finest = false;
  const Sampled cellwise = sample(g, o);
  o.pointwise_finest = true;
  const Sampled pointwise = sample(g, o);
  const int64_t n = g.geometry.dims[0];
  int64_t wrong = 0;
  for (int64_t k = 0; k < n; ++k)
    for (int64_t j = 0; j < n; ++j)
      for (int64_t i = 0; i < n; ++i) {
        if (!g.in_roi(i, j, k)) continue;
        wrong += pointwise.svv[size_t((k * n + j) * n + i)] != shadow_svv(i, j, k, int(g.half));
      }
  EXPECT_EQ(wrong, 0);
  ASSERT_EQ(cellwise.report.levels.size(), 3u);
  ASSERT_EQ(pointwise.report.levels.size(), 3u);
  EXPECT_EQ(cellwise.report.levels[2].first, 1);
  EXPECT_EQ(pointwise.report.levels[2].first, 0);  // the point-by-point level
  const int64_t cell_finest = cellwise.report.levels[2].second;
  const int64_t point_finest = pointwise.report.levels[2].second;
  EXPECT_GT(cell_finest, 0);
  EXPECT_LT(point_finest, cell_finest * 3 / 4) << point_finest << " vs " << cell_finest;
  // Every point computed at the finest level lies next to the shadow's boundary: some voxel
  // within one step along each axis belongs to the other class.
  for (const auto& [i, j, k] : pointwise.evaluated) {
    if ((i - g.half) % 2 == 0 && (j - g.half) % 2 == 0 && (k - g.half) % 2 == 0) continue;
    const float here = shadow_svv(i, j, k, int(g.half));
    bool boundary = false;
    for (int d = 0; d < 27; ++d) {
      boundary |= shadow_svv(i + d % 3 - 1, j + (d / 3) % 3 - 1, k + d / 9 - 1, int(g.half)) != here;
    }
    EXPECT_TRUE(boundary) << "computed away from the boundary: " << i << "," << j << "," << k;
  }
}

// The host's steps beside the evaluator (overlap_host_steps, as for the GPU): the finest level
// gathered in pieces, each computed while the next is gathered, and each level's fill beside the
// next level's evaluation: the same points computed, none twice, the same values, in or out of a
// scan that cuts the region.
TEST(AdaptiveSampling, HostStepsBesideTheEvaluatorComputeTheSamePoints) {
  const OutputGrid g = ball_grid(24);
  for (const int stride : {4, 8}) {
    for (const bool cut : {false, true}) {
      for (const int pieces : {2, 3, 7}) {
        SCOPED_TRACE(::testing::Message() << "stride " << stride << (cut ? ", scan cut" : "")
                                          << ", " << pieces << " pieces");
        AdaptiveOptions o;
        o.values = kernels::kSvv;
        o.stride = stride;
        if (cut) o.known = [edge = g.half - 5](int64_t i, int64_t, int64_t) { return i >= edge; };
        const Sampled one = sample(g, o);
        o.overlap_host_steps = true;
        o.overlap_finest_from = 2;
        o.finest_pieces = pieces;
        const Sampled beside = sample(g, o);
        EXPECT_EQ(beside.evaluated, one.evaluated);
        ASSERT_EQ(beside.svv.size(), one.svv.size());
        EXPECT_EQ(0, std::memcmp(beside.svv.data(), one.svv.data(), one.svv.size() * sizeof(float)));
        EXPECT_EQ(beside.report.interpolated, one.report.interpolated);
        ASSERT_EQ(one.report.levels.size(), stride == 4 ? 3u : 4u);
        EXPECT_GT(one.report.levels.back().second, 100);  // a finest level worth splitting
      }
    }
  }
}

// Outside the scan nothing is reported: every voxel there is NaN, every voxel inside has the
// field's value. Outside it only the corners of cells that reach into the scan are computed (the
// supports of those cells), none farther than a coarsest cell; the scan's edge is sampled as any
// class boundary, so no level splits cells down to single voxels.
TEST(AdaptiveSampling, UnknownVoxelsAreNeverReportedAndOnlyCornersNearTheScanAreComputed) {
  const OutputGrid g = ball_grid(24);
  AdaptiveOptions o;
  o.values = kernels::kSvv;
  // The scan ends 5 voxels left of the centre (as a slab scan's last slice would).
  const int64_t edge = g.half - 5;
  o.known = [edge](int64_t i, int64_t, int64_t) { return i >= edge; };
  const Sampled run = sample(g, o);
  int64_t supports = 0;
  for (const auto& [i, j, k] : run.evaluated) {
    if (i >= edge) continue;
    ++supports;
    EXPECT_GE(i, edge - o.stride) << "computed far outside the scan";
    const bool corner = (i - g.half) % 2 == 0 && (j - g.half) % 2 == 0 && (k - g.half) % 2 == 0;
    EXPECT_TRUE(corner) << "computed an unknown point that is no lattice corner: " << i << ","
                        << j << "," << k;
  }
  EXPECT_GT(supports, 0);
  for (const auto& [stride, count] : run.report.levels) EXPECT_NE(stride, 1) << count;
  const int64_t n = g.geometry.dims[0];
  int64_t unknown_nan = 0, unknown = 0, known_wrong = 0;
  for (int64_t k = 0; k < n; ++k)
    for (int64_t j = 0; j < n; ++j)
      for (int64_t i = 0; i < n; ++i) {
        if (!g.in_roi(i, j, k)) continue;
        const float v = run.svv[size_t((k * n + j) * n + i)];
        if (i < edge) {
          ++unknown;
          unknown_nan += std::isnan(v);
        } else {
          known_wrong += v != shadow_svv(i, j, k, int(g.half));
        }
      }
  EXPECT_GT(unknown, 1000);
  EXPECT_EQ(unknown_nan, unknown);
  EXPECT_EQ(known_wrong, 0);
}

// Progress follows the work: each level weighs four times the one before, the finest level
// (its points gathered in one pass) reports when they are computed, and the fraction only grows
// to 1.
TEST(AdaptiveSampling, ProgressGrowsWithTheLevelsToOne) {
  const OutputGrid g = ball_grid(24);
  AdaptiveOptions o;
  o.values = kernels::kSvv;
  std::vector<double> reported;
  o.progress = [&](double f) { reported.push_back(f); };
  sample(g, o);
  ASSERT_EQ(reported.size(), 3u);
  for (size_t r = 1; r < reported.size(); ++r) EXPECT_GT(reported[r], reported[r - 1]);
  EXPECT_NEAR(reported.front(), 1.0 / 21.0, 1e-12);  // the coarsest of three levels: 1 of 1+4+16
  EXPECT_NEAR(reported[1], 5.0 / 21.0, 1e-12);       // the second level done
  EXPECT_EQ(reported.back(), 1.0);                   // the finest level done
}

// The sampler's steps are reported by name, in order, and they account for its wall time: an
// evaluator that takes 20 ms a call shows as at least that much in "sampler_evaluate", and the
// steps together never exceed the wall time of the whole call.
TEST(AdaptiveSampling, StepsReportTheirWallTime) {
  const OutputGrid g = ball_grid(12);
  AdaptiveOptions o;
  o.values = kernels::kSvv;
  const int64_t n = g.geometry.dims[0];
  std::vector<float> svv(size_t(n * n * n), std::nanf(""));
  float* out[kernels::kValueCount] = {svv.data(), nullptr, nullptr, nullptr};
  int calls = 0;
  const PointEvaluator evaluate = [&](const std::vector<GridPoint>& points,
                                      std::vector<float>& values) {
    ++calls;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    for (size_t p = 0; p < points.size(); ++p) {
      values[p * kernels::kValueCount] = shadow_svv(points[p].i, points[p].j, points[p].k, 12);
    }
  };
  const auto t0 = std::chrono::steady_clock::now();
  const AdaptiveReport report = sample_adaptively(g, o, evaluate, out);
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const std::vector<std::string> names = {
      "sampler_cells",  "sampler_requests", "sampler_finest_requests", "sampler_store",
      "sampler_refine", "sampler_fill",     "sampler_finish",          "sampler_evaluate"};
  ASSERT_EQ(report.seconds.size(), names.size());
  double sum = 0.0;
  for (size_t s = 0; s < names.size(); ++s) {
    EXPECT_EQ(report.seconds[s].first, names[s]);
    EXPECT_GE(report.seconds[s].second, 0.0);
    sum += report.seconds[s].second;
  }
  ASSERT_GE(calls, 3);  // the levels and the finest level
  EXPECT_GE(report.seconds.back().second, 0.020 * calls);
  EXPECT_LE(sum, wall + 1e-6);
}

TEST(AdaptiveSampling, RefusesAStrideThatIsNotAPowerOfTwo) {
  const OutputGrid g = ball_grid(8);
  AdaptiveOptions o;
  o.stride = 3;
  float* out[kernels::kValueCount] = {};
  EXPECT_THROW(sample_adaptively(g, o, [](const auto&, auto&) {}, out), Error);
}

}  // namespace
}  // namespace crepuscular::planning
