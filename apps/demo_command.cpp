// `crepuscular demo`: the whole job on the built-in data, written under demo/: phantom -> plan
// (path safety, area safety) -> slice views -> a synthetic recording of a needle approaching the
// tumor along a safe path and then along one that crosses a vessel -> guidance, headless -> the
// overlay video, snapshots of both moments and a short report.
#include <spdlog/spdlog.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <memory>
#include <sstream>
#include <string>

#include <nlohmann/json.hpp>

#include "apps/commands.hpp"
#include "kernels/error.hpp"
#include "overlay/guidance_scene.hpp"
#include "overlay/guide.hpp"
#include "planning/evaluate.hpp"
#include "planning/output_files.hpp"
#include "planning/phantom.hpp"
#include "planning/plan.hpp"
#include "planning/slices.hpp"
#include "tracking/board.hpp"
#include "tracking/frame_source.hpp"
#include "tracking/synthetic.hpp"

namespace crepuscular::apps {

namespace fs = std::filesystem;

namespace {

struct DemoArgs {
  std::string out = "demo";
  double spacing = 3.0;
  std::string device = "auto";
  std::string mode = "exact";
  double radius = 120.0;
  bool no_guidance = false;
};

using Clock = std::chrono::steady_clock;
double seconds_since(Clock::time_point t) {
  return std::chrono::duration<double>(Clock::now() - t).count();
}

std::string fmt3(const Eigen::Vector3d& v) {
  char buf[96];
  std::snprintf(buf, sizeof(buf), "(%.1f, %.1f, %.1f)", v.x(), v.y(), v.z());
  return buf;
}

std::string approach_text(const overlay::GuidanceApproach& a) {
  std::ostringstream o;
  const auto& s = a.state;
  char buf[256];
  std::snprintf(buf, sizeof(buf),
                "- **%s path**: entry %s mm (LPS), %.0f deg from straight anterior; line integral "
                "%.2f (insignificant <= %.2f), path safety at the entry: %s; "
                "tip to target %.1f mm.\n",
                a.name.c_str(), fmt3(a.entry_ct).c_str(), a.angle_from_anterior_deg,
                s.evaluation.line_integral, s.eps, s.tip_class.c_str(), s.tip_to_centroid_mm);
  o << buf;
  const auto lines = overlay::needle_text(s);
  if (lines.empty()) {
    o << "  It crosses no structure that carries risk.\n";
  } else {
    o << "  It crosses:";
    for (const auto& l : lines) o << " " << l << ";";
    o << "\n";
  }
  return o.str();
}

// Share of region-of-interest voxels in each class, for the report.
std::array<double, 3> class_shares(const planning::Volume<float>& v,
                                   const planning::SafetyClasses& c) {
  std::array<double, 3> n{0, 0, 0};
  double total = 0;
  for (float x : v.values()) {
    if (!std::isfinite(x)) continue;
    n[size_t(c.classify(x))] += 1;
    total += 1;
  }
  for (double& s : n) s = total > 0 ? 100.0 * s / total : 0.0;
  return n;
}

void run_demo(const DemoArgs& a) {
  const auto t_start = Clock::now();
  planning::StagedDirectory staged(a.out);
  const std::string dir = staged.path();
  nlohmann::json times;

  // 1. Phantom.
  auto t = Clock::now();
  planning::PhantomOptions po;
  po.spacing_mm = a.spacing;
  spdlog::info("demo [1/6]: building the phantom ({} mm)", a.spacing);
  planning::write_phantom(planning::make_phantom(po), dir + "/phantom");
  times["phantom_s"] = seconds_since(t);

  // 2. Plan.
  t = Clock::now();
  planning::PlanRequest req;
  req.labels = dir + "/phantom/labels.nii.gz";
  req.tumor = dir + "/phantom/tumor.nii.gz";
  req.vulnerability = dir + "/phantom/vulnerability.json";
  req.path_safety.device = planning::parse_device(a.device);
  req.path_safety.mode = planning::parse_mode(a.mode);
  req.path_safety.radius_mm = a.radius;
  req.out_dir = dir + "/plan";
  spdlog::info("demo [2/6]: planning path safety and area safety (radius {} mm, {} mode)",
               a.radius, a.mode);
  const nlohmann::json plan_json = planning::run_plan(req);
  times["plan_s"] = seconds_since(t);

  // 3. Slice views through the largest safe region.
  t = Clock::now();
  spdlog::info("demo [3/6]: slice views");
  planning::SlicesRequest sr;
  sr.plan_dir = dir + "/plan";
  sr.ct = dir + "/phantom/ct.nii.gz";
  sr.region = 0;
  sr.planes = planning::parse_planes("axial,coronal,sagittal,oblique");
  sr.out_dir = dir + "/slices";
  planning::run_slices(sr);
  times["slices_s"] = seconds_since(t);

  std::ostringstream report;
  report << "# Crepuscular demo report\n\n"
         << "Built-in phantom abdomen (" << a.spacing << " mm voxels) with a liver tumor.\n\n";
  planning::PlanLoadOptions lo;
  const planning::PlanData plan = planning::load_plan(dir + "/plan", lo);
  report << "## Plan\n\n"
         << "Tumor centre " << fmt3(plan.tumor_centre) << " mm (LPS); region of interest "
         << plan.radius_mm << " mm around it; " << a.mode << " mode, computed in "
         << times["plan_s"].get<double>() << " s.\n\n"
         << "| value | safe | medium | dangerous | (share of the region's voxels) |\n"
         << "|---|---|---|---|---|\n";
  for (const auto& v : plan.values) {
    const auto s = class_shares(plan.path_safety.at(v), plan.classes.at(v));
    char buf[160];
    std::snprintf(buf, sizeof(buf), "| %s | %.1f %% | %.1f %% | %.1f %% | |\n", v.c_str(), s[0],
                  s[1], s[2]);
    report << buf;
  }
  if (plan.area) {
    report << "\nArea safety: " << plan.area->regions.size() << " safe region(s)";
    if (!plan.area->regions.empty()) {
      char buf[160];
      std::snprintf(buf, sizeof(buf), "; the largest is %.1f cm3 around %s mm",
                    plan.area->regions[0].size_mm3 / 1000.0,
                    fmt3(plan.area->regions[0].centre).c_str());
      report << buf;
    }
    report << ".\n";
  }

  if (!a.no_guidance) {
    // 4. The guidance scenario and its synthetic recording.
    t = Clock::now();
    spdlog::info("demo [4/6]: choosing a safe and a vessel-crossing approach, scripting the scene");
    const overlay::GuidanceScenario scenario = overlay::make_guidance_scenario(plan);
    overlay::write_guidance_setup(scenario, dir + "/setup");
    spdlog::info("demo [5/6]: rendering the synthetic recording ({} frames)",
                 scenario.scene.frame_count);
    tracking::RecordOptions ro;
    std::vector<tracking::Board> boards;
    for (const auto& b : scenario.scene.boards) boards.push_back(b.board);
    ro.boards_json = tracking::boards_json_text(boards);
    ro.plan = dir + "/plan";
    auto source = tracking::make_synthetic_source(scenario.scene, "synthetic: demo scenario");
    tracking::record_to_folder(*source, dir + "/recording", ro);
    times["recording_s"] = seconds_since(t);

    // 5. Guidance, headless, from the recording and the calibration files.
    t = Clock::now();
    spdlog::info("demo [6/6]: guidance on the recording (headless)");
    overlay::GuideRequest gr;
    gr.setup = overlay::read_guidance_setup(dir + "/setup/camera.yaml",
                                            dir + "/setup/registration.yaml",
                                            dir + "/setup/needle.yaml");
    gr.boards = tracking::read_boards(dir + "/recording/boards.json");
    gr.source = "recording:" + dir + "/recording";
    gr.video = dir + "/overlay.mp4";
    gr.video_fps = scenario.scene.fps;
    gr.log = dir + "/overlay.csv";
    gr.snapshot_dir = dir + "/snapshots";
    fs::create_directories(gr.snapshot_dir);
    const auto frame_at = [&](double s) {
      return std::min<int64_t>(scenario.scene.frame_count - 1,
                               int64_t(std::floor(s * scenario.scene.fps)));
    };
    gr.snapshots = {{frame_at(scenario.safe.end_s), "safe_path.png"},
                    {frame_at(scenario.dangerous.end_s), "dangerous_path.png"},
                    {frame_at(0.5 * (scenario.safe.start_s + scenario.safe.end_s)),
                     "safe_path_midway.png"},
                    {frame_at(0.5 * (scenario.dangerous.start_s + scenario.dangerous.end_s)),
                     "dangerous_path_midway.png"}};
    const overlay::GuideSummary g = overlay::run_guide(plan, gr);
    times["guide_s"] = seconds_since(t);

    // Needle safety per phase of the recording.
    struct Phase {
      const overlay::GuidanceApproach* approach;
      int64_t safe = 0, medium = 0, dangerous = 0, lost = 0;
      double first_dangerous_s = -1;
    };
    Phase phases[2] = {{&scenario.safe}, {&scenario.dangerous}};
    for (const auto& info : g.frame_infos) {
      const double time_s = double(info.frame) / scenario.scene.fps;
      for (Phase& p : phases) {
        if (time_s < p.approach->start_s || time_s > p.approach->end_s) continue;
        if (!info.needle) {
          ++p.lost;
          continue;
        }
        switch (info.needle->state.safety) {
          case planning::NeedleSafety::kSafe: ++p.safe; break;
          case planning::NeedleSafety::kMedium: ++p.medium; break;
          case planning::NeedleSafety::kDangerous:
            ++p.dangerous;
            if (p.first_dangerous_s < 0) p.first_dangerous_s = time_s;
            break;
        }
      }
    }
    report << "\n## The needle along the recording\n\n"
           << "A synthetic camera recording (" << g.frames << " frames at " << scenario.scene.fps
           << " fps, 1280x720) of the patient board on the skin and a tracked needle, guided "
              "headless with the calibration files in setup/.\n\n";
    report << approach_text(scenario.safe) << approach_text(scenario.dangerous) << "\n";
    report << "| approach | time | frames safe | medium | dangerous | needle not tracked |\n"
           << "|---|---|---|---|---|---|\n";
    for (const Phase& p : phases) {
      char buf[200];
      std::snprintf(buf, sizeof(buf), "| %s | %.1f-%.1f s | %lld | %lld | %lld | %lld |\n",
                    p.approach->name.c_str(), p.approach->start_s, p.approach->end_s,
                    (long long)p.safe, (long long)p.medium, (long long)p.dangerous,
                    (long long)p.lost);
      report << buf;
    }
    char buf[512];
    std::snprintf(buf, sizeof(buf),
                  "\nAnatomy shown in %lld of %lld frames (patient board tracked); needle evaluated "
                  "in %lld. Latency from frame arrival to finished overlay: median %.1f ms, p95 "
                  "%.1f ms (tracking %.1f ms, overlay %.1f ms, rendering %.1f ms; %s).\n",
                  (long long)g.patient_tracked, (long long)g.frames,
                  (long long)g.needle_evaluated, g.latency_median_ms, g.latency_p95_ms,
                  g.track_median_ms, g.overlay_median_ms, g.render_median_ms, g.gl.c_str());
    report << buf;
    report << "\nSnapshots: snapshots/safe_path.png and snapshots/dangerous_path.png (end of each "
              "approach), and midway through each.\n";
  }

  report << "\n## Files\n\n"
         << "- phantom/: ct.nii.gz, labels.nii.gz, tumor.nii.gz, vulnerability.json\n"
         << "- plan/: path_safety_*.nii.gz (NaN outside the region), blocking.nii.gz, "
            "area_safety.vtk, plan.json: open with the CT in 3D Slicer\n"
         << "- slices/: axial, coronal, sagittal and oblique views through the largest safe "
            "region\n";
  if (!a.no_guidance) {
    report << "- setup/: camera.yaml, registration.yaml, needle.yaml, boards.json, scene.json\n"
           << "- recording/: the synthetic camera recording with its ground truth\n"
           << "- overlay.mp4, overlay.csv (per frame: tracking, needle safety, latency), "
              "snapshots/\n";
  }
  times["total_s"] = seconds_since(t_start);
  char buf[128];
  std::snprintf(buf, sizeof(buf), "\nThe demo took %.0f s.\n", times["total_s"].get<double>());
  report << buf;
  planning::write_text_file(dir + "/report.md", report.str());
  planning::write_text_file(dir + "/times.json", times.dump(2) + "\n");
  staged.commit();
  spdlog::info("demo: done in {:.0f} s. Outputs in {}/: report.md, overlay.mp4, snapshots/, "
               "slices/, plan/, phantom/",
               times["total_s"].get<double>(), a.out);
}

}  // namespace

void add_demo_command(CLI::App& app) {
  auto a = std::make_shared<DemoArgs>();
  CLI::App* cmd = app.add_subcommand(
      "demo",
      "Run Crepuscular end to end on the built-in data: build the phantom abdomen, plan all four\n"
      "path safety values and the area safety around its liver tumor, draw slice views, script a\n"
      "synthetic camera recording in which a tracked needle approaches the tumor first along a\n"
      "safe path and then along one that crosses a vessel, and guide it headless. DIR holds\n"
      "report.md, overlay.mp4, snapshots/, slices/, plan/ and phantom/ (open\n"
      "DIR/phantom/ct.nii.gz with DIR/plan/path_safety_svv.nii.gz in 3D Slicer).");
  cmd->add_option("--out", a->out, "Output folder (replaced only when the demo completes)")
      ->capture_default_str();
  cmd->add_option("--spacing", a->spacing, "Phantom voxel size in mm")->capture_default_str();
  cmd->add_option("--device", a->device, "auto, cpu or cuda")->capture_default_str();
  cmd->add_option("--mode", a->mode, "exact or fast (see `crepuscular plan --help`)")
      ->capture_default_str();
  cmd->add_option("--radius", a->radius,
                  "Region of interest around the tumor, mm: the reach of a long needle. (The "
                  "plan's own default, the farthest voxel with any blocking, spans the whole "
                  "body here because muscle carries a low risk.)")
      ->capture_default_str();
  cmd->add_flag("--no-guidance", a->no_guidance,
                "Stop after the plan and the slice views (no recording, no overlay)");
  cmd->callback([a] { run_demo(*a); });
}

}  // namespace crepuscular::apps
