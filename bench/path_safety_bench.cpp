// Path safety benchmark: the demo phantom plan, and the paper's headline case (512^3 output grid,
// a 508-voxel tumor of about 2 cm, blocking at 0.7 mm). Prints one JSON line per run.
#include <spdlog/spdlog.h>

#include <CLI/CLI.hpp>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <nlohmann/json.hpp>
#include <random>

#include "planning/preprocessing/blocking.hpp"
#include "planning/safety/path_safety.hpp"
#include "planning/safety/path_safety_scene.hpp"
#include "planning/simulation/phantom.hpp"
#include "planning/safety/safety_classes.hpp"
#include "planning/preprocessing/vulnerability.hpp"

using namespace crepuscular;
using namespace crepuscular::planning;

namespace {

// Samples the exact mode marches (rays in F(p) or B(p) as the value set needs, N samples each),
// estimated from `probe` random voxels of the region of interest.
double estimate_samples(const Volume<float>& blocking, const Volume<uint8_t>& tumor,
                        const PathSafetyResult& r, unsigned values, int probe) {
  const TumorSurface surface = extract_tumor_surface(tumor, "tumor");
  const auto scene = make_scene(blocking, tumor, surface, r.gamma_mm, r.eps);
  const bool front = values & (kernels::kSvv | kernels::kIsbv);
  const bool back = values & (kernels::kIvbv | kernels::kBvv);
  std::mt19937_64 rng(7);
  const int64_t n = r.grid.geometry.dims[0];
  std::uniform_int_distribution<int64_t> u(0, n - 1);
  double sum = 0.0;
  int got = 0;
  while (got < probe) {
    const int64_t i = u(rng), j = u(rng), k = u(rng);
    if (!r.grid.in_roi(i, j, k)) continue;
    const Eigen::Vector3d p = r.grid.geometry.index_to_physical(i, j, k);
    for (const auto& t : surface.points) {
      const auto ray = kernels::make_ray(scene, {p.x(), p.y(), p.z()}, t);
      const auto c = kernels::cross_tumor(scene.tumor, ray, t.offset, back);
      if ((front && c.front_facing) || (back && c.back_facing)) sum += ray.n;
    }
    ++got;
  }
  return sum / probe * double(r.grid.roi_voxels);
}

// A ball of about `voxels` voxels at `spacing_mm`, centred at `centre` (LPS mm).
Volume<uint8_t> ball_tumor(const Eigen::Vector3d& centre, double spacing_mm, int voxels) {
  ImageGeometry g;
  g.dims = {21, 21, 21};
  g.spacing = Eigen::Vector3d::Constant(spacing_mm);
  g.origin = centre - Eigen::Vector3d::Constant(10 * spacing_mm);
  // Smallest radius (in voxels) whose ball holds >= `voxels` voxels.
  double best_r = 1.0;
  for (double r = 1.0; r < 10.0; r += 0.005) {
    int count = 0;
    for (int k = -10; k <= 10; ++k)
      for (int j = -10; j <= 10; ++j)
        for (int i = -10; i <= 10; ++i) count += (i * i + j * j + k * k) <= r * r;
    if (count >= voxels) {
      best_r = r;
      break;
    }
  }
  Volume<uint8_t> t(g, 0);
  for (int k = -10; k <= 10; ++k)
    for (int j = -10; j <= 10; ++j)
      for (int i = -10; i <= 10; ++i)
        if ((i * i + j * j + k * k) <= best_r * best_r) t(i + 10, j + 10, k + 10) = 1;
  return t;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Path safety benchmark (see bench/RESULTS.md)"};
  std::string which = "phantom", device = "cpu", values_text = "all";
  double spacing = 3.0, radius = 150.0;
  int grid = 513, threads = 0, probe = 2000, tumor_voxels = 508, gpus = 0;
  bool each_value = false;
  std::string mode = "exact";
  app.add_option("--case", which, "phantom (demo plan) or headline (512^3, 508-voxel tumor)");
  app.add_option("--device", device, "cpu or cuda");
  app.add_option("--value", values_text, "values (svv,isbv,ivbv,bvv or all)");
  app.add_flag("--each-value", each_value, "time each value in a run of its own");
  app.add_option("--spacing", spacing, "phantom spacing in mm (phantom case)");
  app.add_option("--radius", radius, "region of interest in mm (phantom case; 0: the plan default)");
  app.add_option("--grid", grid, "output voxels per axis (headline case)");
  app.add_option("--tumor-voxels", tumor_voxels, "tumor size in voxels (headline case)");
  app.add_option("--threads", threads, "CPU threads (0: all)");
  app.add_option("--gpus", gpus, "CUDA devices (0: all visible)");
  app.add_option("--probe", probe, "ROI voxels probed to count samples");
  app.add_option("--mode", mode, "exact, fast, or both (fast compared with exact in full)");
  CLI11_PARSE(app, argc, argv);
  spdlog::set_level(spdlog::level::warn);

  const auto t0 = std::chrono::steady_clock::now();
  PhantomOptions po;
  Volume<float> blocking;
  Volume<uint8_t> tumor;
  PathSafetyOptions o;
  o.device = parse_device(device);
  o.threads = threads;
  o.max_gpus = gpus;
  if (which == "phantom") {
    po.spacing_mm = spacing;
    Phantom ph = make_phantom(po);
    Volume<int32_t> labels(ph.labels.geometry());
    for (int64_t i = 0; i < labels.voxel_count(); ++i) labels[i] = ph.labels[i];
    blocking = blocking_from_labels(labels, VulnerabilityTable::from_json(ph.vulnerability, "phantom"),
                                    MarginOptions{}, "phantom");
    tumor = ph.tumor;
    o.radius_mm = radius;
  } else if (which == "headline") {
    po.spacing_mm = 0.7;  // vessels and bone at 0.7 mm
    Phantom ph = make_phantom(po);
    Volume<int32_t> labels(ph.labels.geometry());
    for (int64_t i = 0; i < labels.voxel_count(); ++i) labels[i] = ph.labels[i];
    blocking = blocking_from_labels(labels, VulnerabilityTable::from_json(ph.vulnerability, "phantom"),
                                    MarginOptions{}, "phantom");
    const TumorSurface s = extract_tumor_surface(ph.tumor, "phantom tumor");
    tumor = ball_tumor(s.centroid, 2.0, tumor_voxels);
    o.spacing_mm = 0.7;
    o.radius_mm = 0.7 * ((grid - 1) / 2);  // 2 ceil(R/h) + 1 = grid (odd) voxels per axis
  } else {
    std::fprintf(stderr, "error: unknown --case %s\n", which.c_str());
    return 1;
  }
  const double setup_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();

  std::vector<unsigned> runs;
  const unsigned all = parse_value_set(values_text);
  if (each_value) {
    for (unsigned bit = 1; bit <= 8; bit <<= 1)
      if (all & bit) runs.push_back(bit);
  } else {
    runs.push_back(all);
  }
  const auto report = [&](const PathSafetyResult& r, unsigned values, const char* mode_text,
                          const PathSafetyResult* exact) {
    const double samples =
        mode_text == std::string("exact") ? estimate_samples(blocking, tumor, r, values, probe) : 0.0;
    std::string names;
    for (unsigned bit = 1; bit <= 8; bit <<= 1)
      if (values & bit) names += std::string(names.empty() ? "" : ",") + value_name(bit);
    nlohmann::json j = {{"case", which},
                        {"values", names},
                        {"mode", mode_text},
                        {"device", r.device},
                        {"threads", r.threads},
                        {"grid", r.grid.geometry.dims[0]},
                        {"spacing_mm", r.grid.geometry.spacing[0]},
                        {"radius_mm", r.grid.radius_mm},
                        {"roi_voxels", r.grid.roi_voxels},
                        {"tumor_voxels", r.tumor_voxels},
                        {"surface_points", r.surface_points},
                        {"rays", r.rays},
                        {"seconds", r.seconds},
                        {"setup_seconds", setup_s},
                        {"speedup_vs_paper_300s", 300.0 / r.seconds}};
    if (samples > 0) {
      j["samples_estimated"] = samples;
      j["samples_per_second"] = samples / r.seconds;
    }
    for (const auto& [phase, s] : r.phases) j["phases"][phase] = s;
    if (r.mode == Mode::kFast) {
      j["points_computed_exactly"] = r.fast.evaluated_points;
      j["coarsest_stride"] = r.fast.coarsest_stride;
    }
    if (exact) {
      const ModeDifference d = compare_volumes(exact->volumes, r.volumes, values);
      for (unsigned bit = 1; bit <= 8; bit <<= 1) {
        if (!(values & bit)) continue;
        const int v = kernels::value_slot(bit);
        j["vs_exact"][value_name(bit)] = {{"relative_l2", d.relative_l2[size_t(v)]},
                                          {"class_agreement", d.class_agreement[size_t(v)]}};
      }
      j["speedup_vs_exact"] = exact->seconds / r.seconds;
    }
    std::printf("%s\n", j.dump().c_str());
    std::fflush(stdout);
  };
  o.fast.check_voxels = 0;
  for (unsigned values : runs) {
    o.values = values;
    if (mode == "exact" || mode == "both") {
      o.mode = Mode::kExact;
      const PathSafetyResult exact = compute_path_safety(blocking, tumor, o);
      report(exact, values, "exact", nullptr);
      if (mode == "both") {
        o.mode = Mode::kFast;
        report(compute_path_safety(blocking, tumor, o), values, "fast", &exact);
      }
    } else {
      o.mode = Mode::kFast;
      report(compute_path_safety(blocking, tumor, o), values, "fast", nullptr);
    }
  }
  return 0;
}
