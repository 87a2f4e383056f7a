// The demo job: phantom -> plan -> slices -> guidance scenario and its synthetic recording ->
// guidance, headless -> report.md, all under one staged folder.
#include "pipelines/demo.hpp"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <nlohmann/json.hpp>

#include "foundation/output_files.hpp"
#include "pipelines/demo_report.hpp"
#include "pipelines/demo_scenario.hpp"
#include "pipelines/guide.hpp"
#include "pipelines/job_inputs.hpp"
#include "pipelines/plan.hpp"
#include "pipelines/slices.hpp"
#include "planning/simulation/phantom.hpp"
#include "tracking/board.hpp"
#include "tracking/frame_source.hpp"
#include "tracking/synthetic.hpp"

namespace fs = std::filesystem;

namespace crepuscular::pipelines {

namespace {

void make_plan(const DemoRequest& a, const std::string& dir) {
  PlanRequest req;
  req.labels = {dir + "/phantom/labels.nii.gz"};
  req.tumor = dir + "/phantom/tumor.nii.gz";
  req.vulnerability = dir + "/phantom/vulnerability.json";
  req.path_safety.device = a.device;
  req.path_safety.mode = a.mode;
  req.path_safety.radius_mm = a.radius_mm;
  req.out_dir = dir + "/plan";
  spdlog::info("demo [2/6]: planning path safety and area safety (radius {} mm, {} mode)",
               a.radius_mm, planning::mode_name(a.mode));
  run_plan(req);
}

// Slice views through the largest safe region.
void make_slices(const std::string& dir) {
  spdlog::info("demo [3/6]: slice views");
  SlicesRequest sr;
  sr.plan_dir = dir + "/plan";
  sr.ct = dir + "/phantom/ct.nii.gz";
  sr.region = 0;
  sr.planes = {planning::SlicePlaneKind::kAxial, planning::SlicePlaneKind::kCoronal,
               planning::SlicePlaneKind::kSagittal, planning::SlicePlaneKind::kOblique};
  sr.out_dir = dir + "/slices";
  run_slices(sr);
}

// The guidance scenario, its calibration files in setup/ and its synthetic recording.
GuidanceScenario record_scenario(const planning::PlanData& plan, const std::string& dir) {
  spdlog::info("demo [4/6]: choosing a safe and a vessel-crossing approach, scripting the scene");
  GuidanceScenario scenario = make_guidance_scenario(plan);
  write_guidance_setup(scenario, dir + "/setup");
  spdlog::info("demo [5/6]: rendering the synthetic recording ({} frames)",
               scenario.scene.frame_count);
  tracking::RecordOptions ro;
  std::vector<tracking::Board> boards;
  for (const auto& b : scenario.scene.boards) boards.push_back(b.board);
  ro.boards_json = tracking::boards_json_text(boards);
  ro.plan = dir + "/plan";
  auto source = tracking::make_synthetic_source(scenario.scene, "synthetic: demo scenario");
  tracking::record_to_folder(*source, dir + "/recording", ro);
  return scenario;
}

// Guidance, headless, from the recording and the calibration files; snapshots at the end of and
// midway through each approach.
GuideSummary guide(const planning::PlanData& plan, const GuidanceScenario& scenario,
                   const std::string& dir) {
  spdlog::info("demo [6/6]: guidance on the recording (headless)");
  GuideRequest gr;
  gr.setup = read_guidance_setup(dir + "/setup/camera.yaml", dir + "/setup/registration.yaml",
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
  const GuidanceApproach& safe = scenario.safe;
  const GuidanceApproach& dangerous = scenario.dangerous;
  gr.snapshots = {
      {frame_at(safe.end_s), "safe_path.png"},
      {frame_at(dangerous.end_s), "dangerous_path.png"},
      {frame_at(0.5 * (safe.start_s + safe.end_s)), "safe_path_midway.png"},
      {frame_at(0.5 * (dangerous.start_s + dangerous.end_s)), "dangerous_path_midway.png"}};
  return run_guide(plan, gr);
}

}  // namespace

void run_demo(const DemoRequest& a) {
  const auto t_start = Clock::now();
  StagedDirectory staged(a.out_dir);
  const std::string dir = staged.path();
  nlohmann::json times;

  auto t = Clock::now();
  planning::PhantomOptions po;
  po.spacing_mm = a.spacing_mm;
  spdlog::info("demo [1/6]: building the phantom ({} mm)", a.spacing_mm);
  planning::write_phantom(planning::make_phantom(po), dir + "/phantom");
  times["phantom_s"] = seconds_since(t);

  t = Clock::now();
  make_plan(a, dir);
  times["plan_s"] = seconds_since(t);

  t = Clock::now();
  make_slices(dir);
  times["slices_s"] = seconds_since(t);

  const planning::PlanData plan = planning::load_plan(dir + "/plan");
  std::string report = demo_plan_report(plan, a.spacing_mm, planning::mode_name(a.mode),
                                        times["plan_s"].get<double>());
  if (a.guidance) {
    t = Clock::now();
    const GuidanceScenario scenario = record_scenario(plan, dir);
    times["recording_s"] = seconds_since(t);
    t = Clock::now();
    const GuideSummary g = guide(plan, scenario, dir);
    times["guide_s"] = seconds_since(t);
    report += demo_guidance_report(scenario, g);
  }
  times["total_s"] = seconds_since(t_start);
  report += demo_files_report(a.guidance, times["total_s"].get<double>());
  write_text_file(dir + "/report.md", report);
  write_text_file(dir + "/times.json", times.dump(2) + "\n");
  staged.commit();
  spdlog::info(
      "demo: done in {:.0f} s. Outputs in {}/: report.md, overlay.mp4, snapshots/, "
      "slices/, plan/, phantom/",
      times["total_s"].get<double>(), a.out_dir);
}

}  // namespace crepuscular::pipelines
