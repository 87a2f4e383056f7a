// The host's share of fast mode: coarse-to-fine sampling of the headline grid (513^3 voxels, the
// ball of the region of interest, a plane cutting off part of it as outside the scan) with the
// values of an analytic field instead of marched rays, so that what is timed is the sampler
// alone: requests, refinement, interpolation. `bench_adaptive [--half 256] [--shadows 400]`.
#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include <chrono>
#include <cmath>
#include <iostream>
#include <random>
#include <vector>

#include "planning/safety/adaptive_sampling.hpp"

using namespace crepuscular;
using namespace crepuscular::planning;

namespace {

struct Shadow {
  double x, y, z, r2, svv, blocking;
};

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"fast mode's coarse-to-fine sampler on an analytic field, timed"};
  int half = 256, shadows = 400;
  app.add_option("--half", half, "grid half width in voxels (the grid is 2 half + 1 a side)");
  app.add_option("--shadows", shadows, "balls of lower SVV and higher blocking in the field");
  CLI11_PARSE(app, argc, argv);

  OutputGrid g;
  const int n = 2 * half + 1;
  g.geometry.dims = {n, n, n};
  g.geometry.spacing = Eigen::Vector3d::Ones();
  g.geometry.origin = Eigen::Vector3d::Constant(-half);
  g.half = half;
  g.max_sq = int64_t(half) * half;
  g.radius_mm = half;
  g.roi_voxels = int64_t(4.0 / 3.0 * M_PI * half * half * half);

  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-1.0, 1.0), r(2.0, 0.06 * half);
  std::vector<Shadow> field;
  for (int s = 0; s < shadows; ++s) {
    const double rr = r(rng);
    field.push_back({u(rng) * half, u(rng) * half, u(rng) * half, rr * rr, 40.0 + 40.0 * u(rng),
                     8.0 + 4.0 * u(rng)});
  }
  const auto field_at = [&](int64_t i, int64_t j, int64_t k, float* values) {
    const double x = double(i - half), y = double(j - half), z = double(k - half);
    // Away from the shadows: SVV 100, blocking growing smoothly with the distance.
    const double d = std::sqrt(x * x + y * y + z * z) / half;
    double svv = 100.0, blocking = std::exp(3.0 * d);
    for (const Shadow& s : field) {
      const double d2 = (x - s.x) * (x - s.x) + (y - s.y) * (y - s.y) + (z - s.z) * (z - s.z);
      if (d2 <= s.r2) svv = std::min(svv, s.svv), blocking += s.blocking;
    }
    for (int v = 0; v < kernels::kValueCount; ++v) {
      values[v] = float(v == 0 ? svv : blocking * (1.0 + 0.3 * v));
    }
  };
  // The field tabulated beforehand (not timed), so that the evaluator costs a copy.
  std::vector<float> table(size_t(n) * n * n * kernels::kValueCount);
#pragma omp parallel for schedule(dynamic, 1)
  for (int64_t k = 0; k < n; ++k)
    for (int64_t j = 0; j < n; ++j)
      for (int64_t i = 0; i < n; ++i) {
        field_at(i, j, k, &table[size_t(((k * n + j) * n + i) * kernels::kValueCount)]);
      }
  int64_t evaluated = 0;
  const PointEvaluator evaluate = [&](const std::vector<GridPoint>& points,
                                      std::vector<float>& values) {
    evaluated += int64_t(points.size());
#pragma omp parallel for schedule(static)
    for (int64_t p = 0; p < int64_t(points.size()); ++p) {
      const GridPoint& g = points[size_t(p)];
      float* v = &values[size_t(p) * kernels::kValueCount];
      if (g.i >= 0 && g.j >= 0 && g.k >= 0 && g.i < n && g.j < n && g.k < n) {
        const float* t = &table[size_t(((int64_t(g.k) * n + g.j) * n + g.i) * kernels::kValueCount)];
        std::copy(t, t + kernels::kValueCount, v);
      } else {
        field_at(g.i, g.j, g.k, v);
      }
    }
  };
  std::vector<std::vector<float>> volumes(kernels::kValueCount,
                                          std::vector<float>(size_t(n) * n * n, NAN));
  float* out[kernels::kValueCount];
  for (int v = 0; v < kernels::kValueCount; ++v) out[v] = volumes[size_t(v)].data();
  // The plan's coarsest stride and margins.
  AdaptiveOptions o;
  o.stride = coarsest_stride(g.geometry.spacing[0], g.radius_mm);
  // 60 % of the ball in the scan: a plane at 0.3 R.
  o.known = [half](int64_t i, int64_t, int64_t) { return double(i - half) < 0.3 * half; };
  std::vector<uint8_t> known_mask(size_t(n) * n * n);
  for (size_t v = 0; v < known_mask.size(); ++v) known_mask[v] = o.known(int64_t(v % size_t(n)), 0, 0);
  o.known_mask = known_mask.data();  // as plan passes the scan's mask

  const auto t0 = std::chrono::steady_clock::now();
  const AdaptiveReport report = sample_adaptively(g, o, evaluate, out);
  const double total = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  nlohmann::json levels = nlohmann::json::array();
  for (const auto& [stride, count] : report.levels) levels.push_back({stride, count});
  nlohmann::json steps = nlohmann::json::object();
  for (const auto& [name, seconds] : report.seconds) steps[name] = seconds;
  std::cout << nlohmann::json{{"grid", n},
                              {"steps_s", steps},
                              {"coarsest_stride", o.stride},
                              {"evaluated", report.evaluated},
                              {"interpolated", report.interpolated},
                              {"levels", levels},
                              {"sampler_s", total}}
                   .dump()
            << "\n";
  return 0;
}
