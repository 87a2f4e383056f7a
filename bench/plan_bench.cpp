// `crepuscular plan` end to end as a user runs it (read, preprocess, path safety, scan coverage,
// write, area safety), phase by phase: the built-in phantom at a given spacing with a ball tumor of
// a given diameter segmented at a given spacing, or (--phases N) the breathing phantom's N phases
// with their own tumors, planned over the cycle. The phantom is written first (not timed); the
// plan's own timings (plan.json "timings") and the wall time are printed as one JSON line.
#include <execinfo.h>
#include <sys/resource.h>
#include <unistd.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <csignal>

#include <CLI/CLI.hpp>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "foundation/error.hpp"
#include "pipelines/plan.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/simulation/phantom.hpp"

using namespace crepuscular;
using namespace crepuscular::planning;

namespace {

// A ball of `diameter_mm` centred on `c` (LPS mm), on an isotropic grid of `spacing_mm` with the
// axes `direction`.
Volume<uint8_t> ball_at(const Eigen::Vector3d& c, const Eigen::Matrix3d& direction,
                        double diameter_mm, double spacing_mm) {
  const double r = 0.5 * diameter_mm;
  const int64_t half = int64_t(std::ceil(r / spacing_mm)) + 2;
  ImageGeometry g;
  g.dims = {2 * half + 1, 2 * half + 1, 2 * half + 1};
  g.spacing = Eigen::Vector3d::Constant(spacing_mm);
  g.direction = direction;
  g.origin = c - g.index_to_physical_matrix() * Eigen::Vector3d::Constant(double(half));
  Volume<uint8_t> t(g, 0);
  for (int64_t k = 0; k < g.dims[2]; ++k)
    for (int64_t j = 0; j < g.dims[1]; ++j)
      for (int64_t i = 0; i < g.dims[0]; ++i)
        t(i, j, k) = (g.index_to_physical(i, j, k) - c).norm() <= r;
  return t;
}

// A ball of `diameter_mm` at the phantom tumor's centroid, on an isotropic grid of `spacing_mm`.
Volume<uint8_t> ball_tumor(const Volume<uint8_t>& phantom_tumor, double diameter_mm,
                           double spacing_mm) {
  Eigen::Vector3d c = Eigen::Vector3d::Zero();
  int64_t n = 0;
  const ImageGeometry& g0 = phantom_tumor.geometry();
  for (int64_t k = 0; k < g0.dims[2]; ++k)
    for (int64_t j = 0; j < g0.dims[1]; ++j)
      for (int64_t i = 0; i < g0.dims[0]; ++i)
        if (phantom_tumor(i, j, k)) {
          c += g0.index_to_physical(i, j, k);
          ++n;
        }
  c /= double(n);
  return ball_at(c, g0.direction, diameter_mm, spacing_mm);
}

// The breathing phantom's list with each phase's tumor replaced by a ball of `diameter_mm` at that
// phase's tumor centroid (the headline's tumor, moving as the phantom's does), written beside the
// list as ballD/phaseKK.nii.gz and phases_ballD.json; returns the new list's path.
std::string phases_with_ball_tumors(const std::string& list, double diameter_mm,
                                    double spacing_mm) {
  namespace fs = std::filesystem;
  nlohmann::json doc = nlohmann::json::parse(std::ifstream(list));
  const fs::path dir = fs::path(list).parent_path();
  const std::string tag = "ball" + std::to_string(int(std::lround(diameter_mm)));
  fs::create_directories(dir / tag);
  for (auto& phase : doc.at("phases")) {
    const auto c = phase.at("tumor_centroid_lps_mm").get<std::vector<double>>();
    const ImageGeometry g0 =
        read_volume_geometry((dir / phase.at("tumor").get<std::string>()).string());
    const std::string name = tag + "/" + phase.at("name").get<std::string>() + ".nii.gz";
    write_volume(ball_at({c[0], c[1], c[2]}, g0.direction, diameter_mm, spacing_mm),
                 (dir / name).string());
    phase["tumor"] = name;
  }
  const std::string out = (dir / ("phases_" + tag + ".json")).string();
  std::ofstream(out) << doc.dump(2);
  return out;
}

}  // namespace

// The process's use of the cores and of memory pages so far (getrusage).
struct CpuUse {
  double user_s = 0.0, system_s = 0.0;
  long minor_faults = 0, involuntary_switches = 0;
};
CpuUse cpu_use() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  const auto seconds = [](const timeval& t) { return double(t.tv_sec) + 1e-6 * double(t.tv_usec); };
  return {seconds(usage.ru_utime), seconds(usage.ru_stime), usage.ru_minflt, usage.ru_nivcsw};
}

double peak_rss_gib() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return double(usage.ru_maxrss) / (1024.0 * 1024.0);  // KiB on Linux
}

int bench_plan(int argc, char** argv) {
  CLI::App app{"crepuscular plan end to end, phase by phase"};
  double phantom_spacing = 1.0, tumor_diameter = 30.0, tumor_spacing = 1.0, spacing = 2.0;
  double radius = 100.0;
  std::string mode = "fast", device = "auto", work = "/tmp/crepuscular_plan_bench", values = "all";
  bool keep = false;
  int phases = 0;
  app.add_option("--phantom-spacing", phantom_spacing, "phantom voxel size, mm");
  app.add_option("--tumor-diameter", tumor_diameter, "ball tumor diameter, mm");
  app.add_option("--tumor-spacing", tumor_spacing, "tumor mask voxel size, mm");
  app.add_option("--spacing", spacing, "output spacing h, mm (0: the smallest input spacing)");
  app.add_option("--radius", radius, "region of interest R, mm");
  app.add_option("--mode", mode, "exact or fast");
  FastModeOptions fast;
  app.add_option("--fast-surface-block", fast.surface_block,
                 "fast mode: one ray per block of this many tumor voxels a side");
  app.add_option("--fast-ray-stride", fast.ray_stride,
                 "fast mode: blocking samples per quadrature point along a ray");
  app.add_option("--check-voxels", fast.check_voxels, "fast mode: voxels of the self-check");
  app.add_option("--device", device, "auto, cpu or cuda");
  app.add_option("--value", values, "values (svv,isbv,ivbv,bvv or all)");
  double phase_tumor_diameter = 0.0;
  app.add_option("--phase-tumor-diameter", phase_tumor_diameter,
                 "breathing: each phase's tumor a ball of this diameter (mm, at --tumor-spacing) "
                 "at that phase's tumor centroid, as the headline's (0: the phantom's own tumor)");
  app.add_option("--phases", phases,
                 "breathing: plan the breathing phantom's phases (their own tumors; "
                 "--tumor-diameter and --tumor-spacing do not apply)");
  bool per_phase = false;
  app.add_flag("--per-phase", per_phase,
               "breathing: write every phase's volumes (every phase refined everywhere)");
  int phases_at_once = 0;
  app.add_option("--phases-at-once", phases_at_once,
                 "breathing: phases computed at once (0: the plan's default)");
  app.add_option("--work", work, "working folder (phantom and plan)");
  app.add_flag("--keep", keep, "keep the working folder");
  bool reuse_phantom = false;
  app.add_flag("--reuse-phantom", reuse_phantom,
               "keep the phantom in the working folder for the next run, and plan one found there "
               "(runs with the same phantom options)");
  bool verbose = false;
  app.add_flag("--verbose", verbose, "log the plan's progress (info) instead of warnings only");
  CLI11_PARSE(app, argc, argv);
  // The log on stderr: stdout holds the one JSON line a script reads.
  spdlog::set_default_logger(spdlog::stderr_color_mt("bench_plan"));
  spdlog::set_level(verbose ? spdlog::level::info : spdlog::level::warn);
  // A crash on the GPU machine (no debugger there) leaves its call stack on stderr: a segmentation
  // fault, or an abort (the C library's on a corrupted heap). backtrace() is called once here,
  // so that the handler does not load its library (and allocate) on a broken heap.
  void* first[1];
  (void)backtrace(first, 1);
  const auto crashed = [](int sig) {
    void* frames[64];
    const int n = backtrace(frames, 64);
    backtrace_symbols_fd(frames, n, 2);
    std::signal(sig, SIG_DFL);
    std::raise(sig);
  };
  std::signal(SIGSEGV, crashed);
  std::signal(SIGABRT, crashed);
  namespace fs = std::filesystem;
  const bool reuse = reuse_phantom && fs::exists(work + (phases > 0 ? "/cycle/phases.json"
                                                                    : "/phantom/labels.nii.gz"));
  if (reuse) {
    fs::remove_all(work + "/plan");
  } else {
    fs::remove_all(work);
  }
  fs::create_directories(work);

  PhantomOptions po;
  po.spacing_mm = phantom_spacing;
  const auto t_setup = std::chrono::steady_clock::now();
  pipelines::PlanRequest req;
  if (phases > 0) {
    if (!reuse) write_breathing_phantom(po, phases, work + "/cycle");
    req.phases = work + "/cycle/phases.json";
    if (phase_tumor_diameter > 0.0) {
      req.phases = phases_with_ball_tumors(req.phases, phase_tumor_diameter, tumor_spacing);
    }
  } else {
    if (!reuse) {
      const Phantom phantom = make_phantom(po);
      write_phantom(phantom, work + "/phantom");
      write_volume(ball_tumor(phantom.tumor, tumor_diameter, tumor_spacing),
                   work + "/tumor.nii.gz");
    }
    req.labels = {work + "/phantom/labels.nii.gz"};
    req.tumor = work + "/tumor.nii.gz";
  }
  // The phantom's files on the disk before the plan is timed: a plan reads a scan that is there
  // already, and the writeback of a fresh phantom's few GB held up the first timed plan after it
  // by seconds (bench/RESULTS.md, 2026-11-29).
  if (!reuse) sync();
  const double setup_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t_setup).count();

  req.preset = "phantom";
  req.path_safety.values = parse_value_set(values);
  req.path_safety.mode = parse_mode(mode);
  req.path_safety.device = parse_device(device);
  req.path_safety.spacing_mm = spacing;
  req.path_safety.radius_mm = radius;
  req.path_safety.fast = fast;
  req.per_phase = per_phase;
  req.phases_at_once = phases_at_once;
  req.out_dir = work + "/plan";
  const CpuUse before = cpu_use();
  const auto t0 = std::chrono::steady_clock::now();
  const nlohmann::json plan = pipelines::run_plan(req);
  const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const CpuUse after = cpu_use();

  uintmax_t bytes = 0;
  for (const auto& e : fs::directory_iterator(req.out_dir)) bytes += e.file_size();
  nlohmann::json line = {{"phantom_spacing_mm", phantom_spacing},
                         {"tumor_diameter_mm", tumor_diameter},
                         {"phase_tumor_diameter_mm", phase_tumor_diameter},
                         {"tumor_spacing_mm", tumor_spacing},
                         {"spacing_mm", plan["parameters"]["spacing_mm"]},
                         {"radius_mm", plan["parameters"]["radius_mm"]},
                         {"grid", plan["grid"]["dims"]},
                         {"phases", phases},
                         {"breathing", phases > 0 ? plan["breathing"] : nlohmann::json()},
                         {"surface_points", plan.contains("tumor") ? plan["tumor"].value("surface_points", nlohmann::json())
                                                               : nlohmann::json()},
                         {"mode", mode},
                         {"fast_surface_block", fast.surface_block},
                         {"fast_ray_stride", fast.ray_stride},
                         {"per_phase", per_phase},
                         {"phases_at_once", phases_at_once},
                         {"fast_vs_exact", plan.value("fast_mode_vs_exact", nlohmann::json())},
                         {"device", plan["parameters"]["device"]},
                         {"setup_s_not_counted", setup_s},
                         {"wall_s", wall_s},
                         {"timings", plan["timings"]},
                         {"plan_bytes", bytes},
                         // The plan's own use of the cores: where a slow machine loses its time
                         // (page faults show in the system time).
                         {"cpu",
                          {{"user_s", after.user_s - before.user_s},
                           {"system_s", after.system_s - before.system_s},
                           {"minor_faults", after.minor_faults - before.minor_faults},
                           {"involuntary_switches",
                            after.involuntary_switches - before.involuntary_switches}}},
                         // The process's peak resident memory: the plan's alone where the
                         // phantom was reused, else making the phantom's too.
                         {"peak_rss_gib", peak_rss_gib()},
                         {"phantom_made_in_process", !reuse}};
  std::printf("%s\n", line.dump().c_str());
  if (reuse_phantom) {
    if (!keep) fs::remove_all(work + "/plan");  // the phantom stays for the next run
  } else if (!keep) {
    fs::remove_all(work);
  }
  return 0;
}

// A failed plan (no CUDA device, a phantom that cannot be written) is an error line, not an abort.
int main(int argc, char** argv) {
  try {
    return bench_plan(argc, argv);
  } catch (const crepuscular::Error& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  }
}
