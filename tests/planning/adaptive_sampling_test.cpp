// Coarse-to-fine sampling of fast mode against fields known in closed form: where the sampler
// interpolates, where it computes, and that it never computes nor interpolates the unknown.
#include <gtest/gtest.h>
#include <omp.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstring>
#include <functional>
#include <set>
#include <string>
#include <thread>
#include <tuple>

#include "foundation/error.hpp"
#include "planning/safety/adaptive_sampling.hpp"
#include "tests/support/grids.hpp"

namespace crepuscular::planning {
namespace {

using test::ball_grid;

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

// Voxels of the region whose sampled SVV is not the field's.
int64_t voxels_unlike_the_field(const OutputGrid& g, const Sampled& run) {
  const int64_t n = g.geometry.dims[0];
  int64_t wrong = 0;
  for (int64_t k = 0; k < n; ++k)
    for (int64_t j = 0; j < n; ++j)
      for (int64_t i = 0; i < n; ++i) {
        if (!g.in_roi(i, j, k)) continue;
        wrong += run.svv[size_t((k * n + j) * n + i)] != shadow_svv(i, j, k, int(g.half));
      }
  return wrong;
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
// corners differ are computed; the field is right at every voxel.
TEST(AdaptiveSampling, FinestLevelComputesOnlyBetweenCornersThatDiffer) {
  const OutputGrid g = ball_grid(24);
  AdaptiveOptions o;
  o.values = kernels::kSvv;
  const Sampled pointwise = sample(g, o);
  EXPECT_EQ(voxels_unlike_the_field(g, pointwise), 0);
  ASSERT_EQ(pointwise.report.levels.size(), 3u);
  EXPECT_EQ(pointwise.report.levels[2].first, 0);  // the point-by-point level
  EXPECT_GT(pointwise.report.levels[2].second, 0);
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

// The level above the finest point by point too: inside a refined cell of edge 4 only the points
// of stride 2 whose own corners differ are computed; the field is still right at every voxel, and
// each point of stride 2 computed lies beside the boundary.
TEST(AdaptiveSampling, HalvesComputeOnlyBetweenCornersThatDiffer) {
  const OutputGrid g = ball_grid(32);
  AdaptiveOptions o;
  o.values = kernels::kSvv;
  o.stride = 8;
  const Sampled halves = sample(g, o);
  EXPECT_EQ(voxels_unlike_the_field(g, halves), 0);
  // Every point of stride 2 (not of stride 4) computed lies beside the boundary: some voxel
  // within two steps along each axis belongs to the other class.
  int64_t on_halves = 0;
  for (const auto& [i, j, k] : halves.evaluated) {
    const int64_t a = i - g.half, b = j - g.half, c = k - g.half;
    if (a % 2 != 0 || b % 2 != 0 || c % 2 != 0) continue;        // a finest point
    if (a % 4 == 0 && b % 4 == 0 && c % 4 == 0) continue;        // a corner of stride 4
    ++on_halves;
    const float here = shadow_svv(i, j, k, int(g.half));
    bool boundary = false;
    for (int d = 0; d < 125; ++d) {
      boundary |= shadow_svv(i + d % 5 - 2, j + (d / 5) % 5 - 2, k + d / 25 - 2, int(g.half)) != here;
    }
    EXPECT_TRUE(boundary) << "computed away from the boundary: " << i << "," << j << "," << k;
  }
  EXPECT_GT(on_halves, 0);
}

// The host's steps beside the evaluator (overlap_host_steps, as for the GPU): the finest level
// gathered in pieces, each computed while the next is gathered, and each level's fill beside the
// next level's evaluation: the same points computed, none twice, the same values, in or out of a
// scan that cuts the region.
TEST(AdaptiveSampling, HostStepsBesideTheEvaluatorComputeTheSamePoints) {
  const OutputGrid g = ball_grid(24);
  for (const int stride : {4, 8}) {
    for (const bool cut : {false, true}) {
      {
        SCOPED_TRACE(::testing::Message() << "stride " << stride << (cut ? ", scan cut" : ""));
        AdaptiveOptions o;
        o.values = kernels::kSvv;
        o.stride = stride;
        if (cut) o.known = [edge = g.half - 5](int64_t i, int64_t, int64_t) { return i >= edge; };
        const Sampled one = sample(g, o);
        o.overlap_host_steps = true;
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

// A uniform cell's voxels take the trilinear interpolation of its corners, each written by one
// cell even where cells share a face, an edge or a corner: with a field linear outside a shadow
// (its interpolation exact up to rounding), every voxel of the region holds the field's value,
// the voxels interpolated and computed add up to the region, and the volume is the same bits
// whatever the number of threads (a voxel written by two cells in turn would depend on their
// order), with the fills beside the evaluator or not.
TEST(AdaptiveSampling, UniformCellsFillEachVoxelOnceWithTheirTrilinearValues) {
  const OutputGrid g = ball_grid(24);
  const int half = int(g.half);
  const auto field = [half](int64_t i, int64_t j, int64_t k) {
    if (shadow_svv(i, j, k, half) < 50.0f) return 20.0f;
    return float(96.0 + 0.05 * double(i - half) + 0.03 * double(j - half) -
                 0.02 * double(k - half));
  };
  const int64_t n = g.geometry.dims[0];
  const auto run = [&](int threads, bool beside, int64_t& computed, int64_t& interpolated) {
    std::vector<float> svv(size_t(n * n * n), std::nanf(""));
    float* out[kernels::kValueCount] = {svv.data(), nullptr, nullptr, nullptr};
    AdaptiveOptions o;
    o.values = kernels::kSvv;
    o.stride = 8;
    o.overlap_host_steps = beside;
    const PointEvaluator evaluate = [&](const std::vector<GridPoint>& points,
                                        std::vector<float>& values) {
      for (size_t p = 0; p < points.size(); ++p) {
        values[p * kernels::kValueCount] = field(points[p].i, points[p].j, points[p].k);
      }
    };
    const int before = omp_get_max_threads();
    omp_set_num_threads(threads);
    const AdaptiveReport report = sample_adaptively(g, o, evaluate, out);
    omp_set_num_threads(before);
    computed = report.evaluated;
    interpolated = report.interpolated;
    return svv;
  };
  int64_t computed = 0, interpolated = 0;
  const std::vector<float> one = run(1, false, computed, interpolated);
  int64_t far = 0;
  for (int64_t k = 0; k < n; ++k)
    for (int64_t j = 0; j < n; ++j)
      for (int64_t i = 0; i < n; ++i) {
        const float v = one[size_t((k * n + j) * n + i)];
        if (!g.in_roi(i, j, k)) continue;
        far += !(std::abs(v - field(i, j, k)) <= 1e-4f);
      }
  EXPECT_EQ(far, 0);
  // Computed points include corners beyond the grid's edge; the region's voxels are each either
  // computed or interpolated.
  EXPECT_GT(interpolated, g.roi_voxels / 2);
  EXPECT_GE(interpolated + computed, g.roi_voxels);
  for (const int threads : {2, 5}) {
    for (const bool beside : {false, true}) {
      SCOPED_TRACE(::testing::Message() << threads << " threads" << (beside ? ", beside" : ""));
      int64_t c = 0, f = 0;
      const std::vector<float> other = run(threads, beside, c, f);
      EXPECT_EQ(0, std::memcmp(other.data(), one.data(), one.size() * sizeof(float)));
      EXPECT_EQ(c, computed);
      EXPECT_EQ(f, interpolated);
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
      "sampler_refine", "sampler_fill",     "sampler_finish",          "sampler_evaluate",
      "sampler_combination_wait"};
  ASSERT_EQ(report.seconds.size(), names.size());
  double sum = 0.0;
  for (size_t s = 0; s < names.size(); ++s) {
    EXPECT_EQ(report.seconds[s].first, names[s]);
    EXPECT_GE(report.seconds[s].second, 0.0);
    sum += report.seconds[s].second;
  }
  ASSERT_GE(calls, 3);  // the levels and the finest level
  EXPECT_GE(report.seconds[7].second, 0.020 * calls);  // the evaluator's calls
  EXPECT_EQ(report.seconds[8].second, 0.0);  // no phases before to wait for
  EXPECT_LE(sum, wall + 1e-6);
}

// --- Breathing: refinement left to the phases computed before (AdaptiveOptions::combination)

// SVV of a shadow whose value rises with the distance d (voxels) from its centre: 20 % up to
// d = 5, then 15 points per voxel up to 95 %: dangerous (< 50 %) for d < 7, medium up to
// d = 9.67, safe beyond. Three classes, boundaries at known distances.
float ramp_shadow(double x, double y, double z, double cx, double cy, double cz) {
  const double d = std::sqrt((x - cx) * (x - cx) + (y - cy) * (y - cy) + (z - cz) * (z - cz));
  return float(std::clamp(20.0 + 15.0 * (d - 5.0), 20.0, 95.0));
}

using Field = std::function<float(int64_t, int64_t, int64_t)>;

struct Phase {
  std::vector<float> svv;
  int64_t evaluated = 0;
  AdaptiveReport report;
};

// One phase sampled, after `before` (the phases combined so far; empty: none).
// `pending`: a phase not folded into `newer` yet, read through it (CombinedVolumes::pending).
Phase sample_phase(const OutputGrid& g, const Field& field, const std::vector<float>& before,
                   int stride = 8, const std::vector<float>* newer = nullptr,
                   int newer_from_level = 1, const std::vector<float>* pending = nullptr) {
  Phase run;
  const int64_t n = g.geometry.dims[0];
  run.svv.assign(size_t(n * n * n), std::nanf(""));
  float* out[kernels::kValueCount] = {run.svv.data(), nullptr, nullptr, nullptr};
  AdaptiveOptions o;
  o.values = kernels::kSvv;
  o.stride = stride;
  if (!before.empty()) {
    o.combination.so_far = [&before] {
      return std::array<const float*, kernels::kValueCount>{before.data(), nullptr, nullptr,
                                                            nullptr};
    };
  }
  if (newer) {
    o.combination.newer = [newer, pending] {
      CombinedVolumes v = std::array<const float*, kernels::kValueCount>{newer->data(), nullptr,
                                                                         nullptr, nullptr};
      if (pending) v.pending[0] = pending->data();
      return v;
    };
    o.combination.newer_from_level = newer_from_level;
  }
  const PointEvaluator evaluate = [&](const std::vector<GridPoint>& points,
                                      std::vector<float>& values) {
    run.evaluated += int64_t(points.size());
    for (size_t p = 0; p < points.size(); ++p) {
      values[p * kernels::kValueCount] = field(points[p].i, points[p].j, points[p].k);
    }
  };
  run.report = sample_adaptively(g, o, evaluate, out);
  return run;
}

std::vector<float> minimum(const std::vector<float>& a, const std::vector<float>& b) {
  std::vector<float> m(a.size());
  for (size_t v = 0; v < a.size(); ++v) m[v] = std::min(a[v], b[v]);
  return m;
}

// The two phases below: one shadow 8 voxels from the centre; in the second it has moved by 3
// voxels, and a second shadow, far from the first, appears.
Field first_phase_field(const OutputGrid& g) {
  const double h = double(g.half);
  return [h](int64_t i, int64_t j, int64_t k) {
    return ramp_shadow(double(i), double(j), double(k), h + 8.0, h, h);
  };
}
Field second_phase_field(const OutputGrid& g) {
  const double h = double(g.half);
  return [h](int64_t i, int64_t j, int64_t k) {
    return std::min(ramp_shadow(double(i), double(j), double(k), h + 11.0, h, h),
                    ramp_shadow(double(i), double(j), double(k), h - 16.0, h, h));
  };
}

// Two phases: in the second the first's shadow has moved by 3 voxels, and a second shadow,
// far from the first, appears. Left to the combination, the second phase computes fewer points,
// the combination has every voxel in the same class as with every boundary refined (and as
// the fields' own minimum), and around the new shadow, which the first phase does not cover,
// the second phase's values are those of a phase refined everywhere, bit for bit.
TEST(AdaptiveSampling, APhaseLeavesToTheCombinationOnlyWhatItCannotChange) {
  const OutputGrid g = ball_grid(32);
  const double h = double(g.half);
  const Field first = first_phase_field(g), second = second_phase_field(g);
  const Phase a = sample_phase(g, first, {});
  const Phase whole = sample_phase(g, second, {});
  const Phase left = sample_phase(g, second, a.svv);
  EXPECT_LT(left.evaluated, whole.evaluated * 19 / 20) << left.evaluated << " vs " << whole.evaluated;
  // Each point left is one the phase refined everywhere computes, counted once however many
  // cells share it: they cannot outnumber the points saved (counted once per cell, they did).
  EXPECT_LE(left.report.points_left_to_combination, whole.evaluated - left.evaluated)
      << left.report.points_left_to_combination << " points left";
  EXPECT_GT(left.report.cells_left_to_combination + left.report.points_left_to_combination, 0);
  EXPECT_EQ(whole.report.cells_left_to_combination + whole.report.points_left_to_combination, 0);
  const std::vector<float> with_whole = minimum(a.svv, whole.svv);
  const std::vector<float> with_left = minimum(a.svv, left.svv);
  const SafetyClasses& classes = left.report.classes[0];
  const int64_t n = g.geometry.dims[0];
  int64_t differ = 0, wrong_whole = 0, wrong_left = 0, near_new = 0, near_new_differ = 0;
  int64_t changed = 0, changed_where_first_safe = 0;
  for (int64_t k = 0; k < n; ++k)
    for (int64_t j = 0; j < n; ++j)
      for (int64_t i = 0; i < n; ++i) {
        if (!g.in_roi(i, j, k)) continue;
        const size_t v = size_t((k * n + j) * n + i);
        const SafetyClass truth = classes.classify(std::min(first(i, j, k), second(i, j, k)));
        differ += classes.classify(with_left[v]) != classes.classify(with_whole[v]);
        wrong_whole += classes.classify(with_whole[v]) != truth;
        wrong_left += classes.classify(with_left[v]) != truth;
        // Left to the combination only where the phases before are not safe: a voxel whose value
        // this phase did not refine is never one the first phase calls safe.
        if (left.svv[v] != whole.svv[v]) {
          ++changed;
          changed_where_first_safe += classes.classify(a.svv[v]) == SafetyClass::kSafe;
        }
        const double x = double(i) - (h - 16.0), y = double(j) - h, z = double(k) - h;
        if (x * x + y * y + z * z <= 14.0 * 14.0) {  // the new shadow and a margin around it
          ++near_new;
          near_new_differ += left.svv[v] != whole.svv[v];
        }
      }
  EXPECT_EQ(differ, 0);
  EXPECT_GT(changed, 100);
  EXPECT_EQ(changed_where_first_safe, 0);
  EXPECT_EQ(wrong_left, wrong_whole);
  EXPECT_LE(wrong_whole, g.roi_voxels / 1000);
  EXPECT_GT(near_new, 1000);
  EXPECT_EQ(near_new_differ, 0);
}

// A later combination (CombinationSource::newer) decides from its level on. After a
// combination safe everywhere, which leaves nothing, the first phase's from the second level on
// leaves cells to it, and the combination has the classes it has with every boundary refined,
// never leaving where the first phase is safe. The same combination given as both is that
// combination alone, bit for bit; from level 0 the later one is never asked for.
TEST(AdaptiveSampling, ALaterCombinationDecidesFromItsLevelOn) {
  const OutputGrid g = ball_grid(32);
  const Field first = first_phase_field(g), second = second_phase_field(g);
  const int64_t n = g.geometry.dims[0];
  const Phase a = sample_phase(g, first, {});
  const Phase whole = sample_phase(g, second, {});
  const Phase left = sample_phase(g, second, a.svv);
  const std::vector<float> safe(size_t(n * n * n), 95.0f);
  const Phase same = sample_phase(g, second, a.svv, 8, &a.svv);
  EXPECT_EQ(same.evaluated, left.evaluated);
  EXPECT_EQ(0, std::memcmp(same.svv.data(), left.svv.data(), left.svv.size() * 4));
  const Phase later = sample_phase(g, second, safe, 8, &a.svv);
  EXPECT_GT(later.report.cells_left_to_combination + later.report.points_left_to_combination, 0);
  EXPECT_LT(later.evaluated, whole.evaluated);
  // Level 0: never asked for; the safe combination alone leaves nothing.
  const Phase never = sample_phase(g, second, safe, 8, &a.svv, 0);
  EXPECT_EQ(never.evaluated, whole.evaluated);
  EXPECT_EQ(0, std::memcmp(never.svv.data(), whole.svv.data(), whole.svv.size() * 4));
  const std::vector<float> with_whole = minimum(a.svv, whole.svv);
  const std::vector<float> with_later = minimum(a.svv, later.svv);
  const SafetyClasses& classes = later.report.classes[0];
  int64_t differ = 0, changed_where_first_safe = 0;
  for (int64_t v = 0; v < n * n * n; ++v) {
    const int64_t i = v % n, j = (v / n) % n, k = v / (n * n);
    if (!g.in_roi(i, j, k)) continue;
    differ += classes.classify(with_later[size_t(v)]) != classes.classify(with_whole[size_t(v)]);
    if (later.svv[size_t(v)] != whole.svv[size_t(v)]) {
      changed_where_first_safe += classes.classify(a.svv[size_t(v)]) == SafetyClass::kSafe;
    }
  }
  EXPECT_EQ(differ, 0);
  EXPECT_EQ(changed_where_first_safe, 0);
}

// A later combination read through a phase not folded into it yet (CombinedVolumes::pending)
// is that phase folded in: the same points and values, bit for bit, with unknown voxels (NaN)
// in either; and the pending phase is read: the combination alone decides otherwise.
TEST(AdaptiveSampling, APhaseReadThroughTheCombinationIsItsFold) {
  const OutputGrid g = ball_grid(32);
  const double h = double(g.half);
  const int64_t n = g.geometry.dims[0];
  const Field first = first_phase_field(g), second = second_phase_field(g);
  const Field third = [h](int64_t i, int64_t j, int64_t k) {
    return ramp_shadow(double(i), double(j), double(k), h + 5.0, h, h);
  };
  Phase a = sample_phase(g, first, {});
  Phase c = sample_phase(g, third, {});
  std::vector<float> folded(a.svv.size());
  int64_t unknown = 0;
  for (int64_t v = 0; v < n * n * n; ++v) {
    const int64_t i = v % n, j = (v / n) % n;
    if (double(i) < h - 20.0) a.svv[size_t(v)] = std::nanf("");  // unknown in one phase
    if (double(j) > h + 20.0) c.svv[size_t(v)] = std::nanf("");  // and in the other
    const float x = a.svv[size_t(v)], y = c.svv[size_t(v)];
    folded[size_t(v)] = std::isnan(x) || std::isnan(y) ? std::nanf("") : std::min(x, y);
    unknown += std::isnan(folded[size_t(v)]) && g.in_roi(i, j, v / (n * n));
  }
  EXPECT_GT(unknown, 1000);
  const std::vector<float> safe(size_t(n * n * n), 95.0f);
  const Phase materialized = sample_phase(g, second, safe, 8, &folded);
  const Phase read_through = sample_phase(g, second, safe, 8, &a.svv, 1, &c.svv);
  EXPECT_GT(materialized.report.cells_left_to_combination +
                materialized.report.points_left_to_combination,
            0);
  EXPECT_EQ(read_through.evaluated, materialized.evaluated);
  EXPECT_EQ(read_through.report.cells_left_to_combination,
            materialized.report.cells_left_to_combination);
  EXPECT_EQ(0, std::memcmp(read_through.svv.data(), materialized.svv.data(),
                           materialized.svv.size() * 4));
  const Phase without = sample_phase(g, second, safe, 8, &a.svv);
  EXPECT_NE(without.evaluated, materialized.evaluated);
}

// A combination that is safe everywhere decides nothing: the phase is sampled as on its own,
// bit for bit. One unknown everywhere (NaN: unknown in an earlier phase) decides everything:
// whatever this phase says, the combination is unknown, so only the coarsest lattice is
// computed.
// One shadow beside the centre of `g`, and a combination of one value everywhere.
Field one_shadow(const OutputGrid& g) {
  const double h = double(g.half);
  return [h](int64_t i, int64_t j, int64_t k) {
    return ramp_shadow(double(i), double(j), double(k), h + 6.0, h, h);
  };
}
std::vector<float> everywhere(const OutputGrid& g, float value) {
  const int64_t n = g.geometry.dims[0];
  return std::vector<float>(size_t(n * n * n), value);
}

TEST(AdaptiveSampling, ACombinationSafeEverywhereLeavesNothingAndOneUnknownLeavesAll) {
  const OutputGrid g = ball_grid(24);
  const Field field = one_shadow(g);
  const Phase alone = sample_phase(g, field, {}, 4);
  const Phase after_safe = sample_phase(g, field, everywhere(g, 95.0f), 4);
  EXPECT_EQ(after_safe.evaluated, alone.evaluated);
  EXPECT_EQ(0, std::memcmp(after_safe.svv.data(), alone.svv.data(), alone.svv.size() * 4));
  EXPECT_EQ(after_safe.report.cells_left_to_combination, 0);
  EXPECT_EQ(after_safe.report.points_left_to_combination, 0);
  const Phase after_unknown = sample_phase(g, field, everywhere(g, std::nanf("")), 4);
  ASSERT_FALSE(alone.report.levels.empty());
  EXPECT_EQ(after_unknown.evaluated, alone.report.levels.front().second);
  EXPECT_GT(alone.evaluated, 2 * alone.report.levels.front().second);
}

// SVV's thresholds are fixed, so the combination needs no margin of its own: one dangerous by a
// single point everywhere (49 %, within the 3-point margin of 50 %) is dangerous whatever this
// phase holds, and every class boundary of the phase is left to it after the coarsest level;
// the combined classes are the truth's, dangerous throughout. Just above the threshold (51 %),
// the phase's boundaries between dangerous and medium are refined as before.
TEST(AdaptiveSampling, ACombinationDangerousByOnePointIsLeftTheBoundariesItDecides) {
  const OutputGrid g = ball_grid(24);
  const Field field = one_shadow(g);
  const int64_t n = g.geometry.dims[0];
  const Phase alone = sample_phase(g, field, {}, 4);
  const Phase after_49 = sample_phase(g, field, everywhere(g, 49.0f), 4);
  const Phase after_51 = sample_phase(g, field, everywhere(g, 51.0f), 4);
  ASSERT_FALSE(alone.report.levels.empty());
  EXPECT_EQ(after_49.evaluated, alone.report.levels.front().second);
  EXPECT_GT(alone.evaluated, 2 * alone.report.levels.front().second);
  EXPECT_GT(after_51.evaluated, alone.report.levels.front().second);
  const SafetyClasses& classes = after_49.report.classes[0];
  int64_t dangerous = 0, voxels = 0;
  for (int64_t v = 0; v < n * n * n; ++v) {
    const int64_t i = v % n, j = (v / n) % n, k = v / (n * n);
    if (!g.in_roi(i, j, k)) continue;
    ++voxels;
    dangerous += classes.classify(std::min(49.0f, after_49.svv[size_t(v)])) ==
                 SafetyClass::kDangerous;
  }
  EXPECT_EQ(dangerous, voxels);
}

// The thresholds are the combination's: the coarsest samples combined with the phases before.
// Blocking values have relative thresholds; a phase whose combination so far is twice its own
// values refines with the classes of a phase of twice its values.
TEST(AdaptiveSampling, ThresholdsAreTakenOfTheCoarsestSamplesCombinedWithThePhasesBefore) {
  const OutputGrid g = ball_grid(24);
  const int64_t n = g.geometry.dims[0];
  const auto blocking = [&](int64_t i, int64_t j, int64_t k, float scale) {
    return scale * float(1 + (i * 7 + j * 3 + k) % 50);
  };
  std::vector<float> before(size_t(n * n * n));
  for (int64_t k = 0; k < n; ++k)
    for (int64_t j = 0; j < n; ++j)
      for (int64_t i = 0; i < n; ++i) before[size_t((k * n + j) * n + i)] = blocking(i, j, k, 2.0f);
  std::array<SafetyClasses, 2> classes;
  for (int run = 0; run < 2; ++run) {
    std::vector<float> isbv(size_t(n * n * n), std::nanf(""));
    float* out[kernels::kValueCount] = {nullptr, isbv.data(), nullptr, nullptr};
    AdaptiveOptions o;
    o.values = kernels::kIsbv;
    if (run == 1) {
      o.combination.so_far = [&before] {
        return std::array<const float*, kernels::kValueCount>{nullptr, before.data(), nullptr,
                                                              nullptr};
      };
    }
    const float scale = run == 0 ? 2.0f : 1.0f;
    const PointEvaluator evaluate = [&](const std::vector<GridPoint>& points,
                                        std::vector<float>& values) {
      for (size_t p = 0; p < points.size(); ++p) {
        values[p * kernels::kValueCount + 1] =
            blocking(points[p].i, points[p].j, points[p].k, scale);
      }
    };
    classes[size_t(run)] = sample_adaptively(g, o, evaluate, out).classes[1];
  }
  EXPECT_GT(classes[0].safe, 0.0);
  EXPECT_EQ(classes[1].safe, classes[0].safe);
  EXPECT_EQ(classes[1].dangerous, classes[0].dangerous);
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
