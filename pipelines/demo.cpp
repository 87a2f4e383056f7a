// The demo job: phantom -> plan -> slices -> 3D views -> guidance scenario and its synthetic recording ->
// guidance, headless -> report.md, all under one staged folder.
#include "pipelines/demo.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <optional>
#include <opencv2/imgcodecs.hpp>

#include "foundation/log.hpp"
#include "foundation/output_files.hpp"
#include "pipelines/demo_report.hpp"
#include "pipelines/demo_scenario.hpp"
#include "pipelines/guide.hpp"
#include "pipelines/job_inputs.hpp"
#include "pipelines/plan.hpp"
#include "pipelines/registration.hpp"
#include "pipelines/render.hpp"
#include "pipelines/slices.hpp"
#include "planning/simulation/phantom.hpp"
#include "tracking/board.hpp"
#include "tracking/frame_source.hpp"
#include "tracking/synthetic.hpp"

namespace fs = std::filesystem;

namespace crepuscular::pipelines {

namespace {

// A file of the planning scan: the phantom at rest, or with breathing its first phase (end-exhale,
// the same anatomy).
std::string phantom_file(const DemoRequest& a, const std::string& dir, const std::string& name) {
  return dir + (a.breathing_phases > 0 ? "/phantom/phase00/" : "/phantom/") + name;
}

void make_plan(const DemoRequest& a, const std::string& dir) {
  PlanRequest req;
  if (a.breathing_phases > 0) {
    req.phases = dir + "/phantom/phases.json";
    req.per_phase = true;
    // Ten plans instead of one: SVV alone (what guidance and the scenario read first), and a
    // smaller exact check of fast mode per phase, keep the breathing demo within minutes.
    req.path_safety.values = kernels::kSvv;
    req.path_safety.fast.check_voxels = 200;
  } else {
    req.labels = {dir + "/phantom/labels.nii.gz"};
    req.tumor = dir + "/phantom/tumor.nii.gz";
    // Recorded in plan.json (the CT lies on the label map's grid: the plan is the same), so that
    // `view` and `render` find it.
    req.ct = dir + "/phantom/ct.nii.gz";
    req.vulnerability = dir + "/phantom/vulnerability.json";
  }
  req.path_safety.device = a.device;
  req.path_safety.mode = a.mode;
  req.path_safety.radius_mm = a.radius_mm;
  req.out_dir = dir + "/plan";
  spdlog::info("demo [2/8]: planning path safety and area safety (radius {} mm, {} mode)",
               a.radius_mm, planning::mode_name(a.mode));
  run_plan(req);
}

// Slice views through the largest safe region.
void make_slices(const DemoRequest& a, const std::string& dir) {
  spdlog::info("demo [3/8]: slice views");
  SlicesRequest sr;
  sr.plan_dir = dir + "/plan";
  sr.ct = phantom_file(a, dir, "ct.nii.gz");
  sr.region = 0;
  sr.planes = {planning::SlicePlaneKind::kAxial, planning::SlicePlaneKind::kCoronal,
               planning::SlicePlaneKind::kSagittal, planning::SlicePlaneKind::kOblique};
  sr.out_dir = dir + "/slices";
  run_slices(sr);
}

// The 3D planning view from four sides (`render`), dangerous hidden as `view` and `render` start.
void make_3d(const DemoRequest& a, const std::string& dir) {
  spdlog::info("demo [4/8]: 3D views of the plan");
  const ViewInputs inputs =
      load_view_inputs(dir + "/plan", phantom_file(a, dir, "ct.nii.gz"), "", {}, "");
  overlay::PlanViewOptions options;
  options.hidden[size_t(planning::SafetyClass::kDangerous)] = true;
  overlay::PlanView3D view(inputs.plan, &inputs.ct, options);
  StagedDirectory out(dir + "/3d");
  for (const auto& [name, angles] : std::vector<std::pair<std::string, std::string>>{
           {"anterior", "anterior"}, {"anterior_left", "30,20"}, {"left", "left"},
           {"from_feet", "inferior"}}) {
    const cv::Mat image = render_plan_view(view, overlay::parse_view_angles(angles), 1280, 960);
    const std::string path = out.file(name + ".png");
    write_file_atomically(path, [&](const std::string& tmp) {
      if (!cv::imwrite(tmp, image)) throw Error(path + ": cannot write the PNG");
    });
  }
  out.commit();
}

// The breathing recording's ground truth per frame: the true phase, the breath's fraction, the
// skin's rise under the patient board and the needle's true tip and axis in the CT.
void write_breathing_truth(const GuidanceScenario& scenario, const std::string& path) {
  std::string text;
  for (int64_t f = 0; f < scenario.scene.frame_count; ++f) {
    const double t = double(f) / scenario.scene.fps;
    const Eigen::Isometry3d T = scenario.T_ct_needle_at(t);
    const Eigen::Vector3d tip = T * tracking::kNeedleTipInNeedle;
    const Eigen::Vector3d axis = T.linear().col(2);
    const double cycle = t / scenario.breathing_period_s - std::floor(t / scenario.breathing_period_s);
    text += fmt::format("{},{},{},{:.4f},{:.3f},{:.3f},{:.3f},{:.3f},{:.6f},{:.6f},{:.6f}\n", f,
                        int64_t(std::llround(t * 1e9)), scenario.breathing_phase_at(t), cycle,
                        scenario.skin_displacement_at(t).norm(), tip.x(), tip.y(), tip.z(),
                        axis.x(), axis.y(), axis.z());
  }
  PendingTextFile file(path, "breathing ground truth",
                       "frame,timestamp_ns,phase,cycle_fraction,skin_rise_mm,tip_x_mm,tip_y_mm,"
                       "tip_z_mm,axis_x,axis_y,axis_z");
  file.write(text);
  file.commit();
}

// The guidance scenario, its calibration files in setup/ and its synthetic recording.
GuidanceScenario record_scenario(const DemoRequest& a, const planning::PlanData& plan,
                                 const std::string& dir) {
  spdlog::info("demo [5/8]: choosing a safe and a vessel-crossing approach, scripting the scene");
  GuidanceScenario scenario;
  GuidanceScenarioOptions options;
  if (a.breathing_phases > 0) {
    // The patient breathes 15 times a minute; 3 s before and after the approaches let the phase
    // be found from the board's motion before the needle comes.
    options.breaths_per_minute = 15;
    options.breathing_amplitude_mm = a.breathing_amplitude_mm;
    options.breathing_phases = a.breathing_phases;
    options.hold_s = 3.0;
  }
  try {
    scenario = make_guidance_scenario(plan, options);
  } catch (const Error& e) {
    // A plan whose safe region is narrow (over a breathing cycle, say) may have no vessel-crossing
    // approach 15-35 deg from a safe one; a wider separation still shows both.
    GuidanceScenarioOptions wide = options;
    wide.min_separation_deg = 10;
    wide.max_separation_deg = 60;
    spdlog::info("demo: {}; looking 10 to 60 deg from the safe approach", e.what());
    scenario = make_guidance_scenario(plan, wide);
  }
  write_guidance_setup(scenario, dir + "/setup");
  spdlog::info("demo [6/8]: rendering the synthetic recording ({} frames)",
               scenario.scene.frame_count);
  tracking::RecordOptions ro;
  std::vector<tracking::Board> boards;
  for (const auto& b : scenario.scene.boards) boards.push_back(b.board);
  ro.boards_json = tracking::boards_json_text(boards);
  ro.plan = dir + "/plan";
  auto source = tracking::make_synthetic_source(scenario.scene, "synthetic: demo scenario");
  tracking::record_to_folder(*source, dir + "/recording", ro);
  if (scenario.breathing_period_s > 0) write_breathing_truth(scenario, dir + "/recording/breathing_truth.csv");
  return scenario;
}

// `register` on the phantom CT: the beads found, paired with the board's layout and fitted; the
// guidance then uses this registration, not the scenario's truth. Its error against the truth
// at the tumor goes into the report.
std::string register_board(const DemoRequest& a, const GuidanceScenario& scenario,
                           const std::string& dir) {
  const std::string ct = phantom_file(a, dir, "ct.nii.gz");
  spdlog::info("demo [7/8]: registering the patient board to the CT by its beads (register)");
  std::string md = "\n## Registration\n\n";
  try {
    const int beads = paint_board_beads(scenario, ct);
    RegistrationRequest rr;
    rr.ct = ct;
    rr.boards = dir + "/setup/boards.json";
    rr.board_name = "patient";
    rr.tumor = phantom_file(a, dir, "tumor.nii.gz");
    rr.out = dir + "/setup/registration.yaml";
    const calibration::RegistrationRecord r = run_registration(rr);
    const Eigen::Vector3d c = scenario.target_ct;
    const double error = (r.T_ct_patient * (scenario.T_ct_patient.inverse() * c) - c).norm();
    md += fmt::format(
        "`crepuscular register` found the patient board's beads in the CT ({} of {} painted, "
        "3 mm radius) and paired {} with the board's layout: FRE {:.2f} mm (RMS), expected TRE "
        "at the tumor {:.2f} mm. Against the scenario's true registration the error at the tumor "
        "centroid is **{:.2f} mm**. Guidance below uses this registration "
        "(`setup/registration.yaml`).\n",
        r.fiducials_in_ct, beads, r.board_fiducials.size(), r.fre_rms_mm, r.expected_tre_mm,
        error);
    spdlog::info("demo: registration error at the tumor {:.2f} mm (FRE {:.2f} mm)", error,
                 r.fre_rms_mm);
  } catch (const Error& e) {
    // The scenario's true registration stays in setup/registration.yaml; the report says why.
    spdlog::warn("demo: registration not performed: {}", e.what());
    md += "Registration not performed (" + std::string(e.what()) +
          "); guidance uses the scenario's true registration.\n";
  }
  return md;
}

// Guidance, headless, from the recording and the calibration files; snapshots at the end of and
// midway through each approach.
GuideSummary guide(const planning::PlanData& plan, const GuidanceScenario& scenario,
                   const std::string& dir) {
  spdlog::info("demo [8/8]: guidance on the recording (headless)");
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
  // The demo's phantom/, plan/ and slices/ are those commands' folders: each may replace its own.
  std::optional<OutputCommandScope> made_by;
  made_by.emplace("phantom");
  planning::PhantomOptions po;
  po.spacing_mm = a.spacing_mm;
  po.amplitude_mm = a.breathing_amplitude_mm;
  if (a.breathing_phases > 0) {
    spdlog::info("demo [1/8]: building the breathing phantom ({} mm, {} phases, {} mm at the "
                 "dome)", a.spacing_mm, a.breathing_phases, a.breathing_amplitude_mm);
    planning::write_breathing_phantom(po, a.breathing_phases, dir + "/phantom");
  } else {
    spdlog::info("demo [1/8]: building the phantom ({} mm)", a.spacing_mm);
    planning::write_phantom(planning::make_phantom(po), dir + "/phantom");
  }
  times["phantom_s"] = seconds_since(t);

  t = Clock::now();
  made_by.emplace("plan");
  make_plan(a, dir);
  times["plan_s"] = seconds_since(t);

  t = Clock::now();
  made_by.emplace("slices");
  make_slices(a, dir);
  times["slices_s"] = seconds_since(t);
  t = Clock::now();
  made_by.emplace("render");
  make_3d(a, dir);
  times["3d_s"] = seconds_since(t);
  made_by.reset();

  const planning::PlanData plan = planning::load_plan(dir + "/plan");
  std::string report = demo_plan_report(plan, a.spacing_mm, planning::mode_name(a.mode),
                                        times["plan_s"].get<double>());
  if (a.guidance) {
    t = Clock::now();
    const GuidanceScenario scenario = record_scenario(a, plan, dir);
    times["recording_s"] = seconds_since(t);
    t = Clock::now();
    const std::string registration = register_board(a, scenario, dir);
    times["registration_s"] = seconds_since(t);
    t = Clock::now();
    const GuideSummary g = guide(plan, scenario, dir);
    times["guide_s"] = seconds_since(t);
    report += registration + demo_guidance_report(scenario, g);
    if (a.breathing_phases > 0) report += demo_breathing_report(plan, scenario, g);
  }
  times["total_s"] = seconds_since(t_start);
  report += demo_files_report(a.guidance, times["total_s"].get<double>());
  write_text_file(dir + "/report.md", report);
  write_text_file(dir + "/times.json", times.dump(2) + "\n");
  staged.commit();
  spdlog::info(
      "demo: done in {:.0f} s. Outputs in {}/: report.md, overlay.mp4, snapshots/, "
      "slices/, 3d/, plan/, phantom/",
      times["total_s"].get<double>(), a.out_dir);
}

}  // namespace crepuscular::pipelines
