// End-to-end latency of the guidance loop on the demo's recording: the built-in phantom is planned
// (fast mode), the demo's guidance scenario (a needle on a safe, then a vessel-crossing path) is
// rendered into memory, and every frame goes through tracking, the overlay's layers and rendering
// with read-back (what `crepuscular guide --headless` does per frame, without the video encoder).
// Frames are handed over back to back; latency counts from the hand-over to the finished image.
//
// Prints one JSON line per image size and volume-layer setting: latency median / p95 / max, the
// medians of tracking, overlay and rendering, and the OpenGL implementation. `--full-search`
// picks where full-frame tag searches run (default: on a worker, as `guide` with a camera).
#include <CLI/CLI.hpp>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <string>
#include <vector>

#include <unistd.h>

#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include "foundation/error.hpp"
#include "pipelines/demo_scenario.hpp"
#include "pipelines/guide.hpp"
#include "pipelines/guide_loop.hpp"
#include "planning/trajectories/evaluate.hpp"
#include "planning/simulation/phantom.hpp"
#include "pipelines/plan.hpp"
#include "tracking/synthetic.hpp"

namespace fs = std::filesystem;
using namespace crepuscular;

int main(int argc, char** argv) {
  CLI::App app{"End-to-end latency of the guidance loop (tracking + overlay + rendering)"};
  double spacing = 3.0;
  int frames = 120;
  std::vector<std::string> sizes = {"1280x720", "1920x1080"};
  std::string backend = "auto";
  std::string device = "auto";
  double volume_scale = 0;
  std::string full_search = "background";
  std::string plan_dir;
  std::string volume_layer = "both";
  bool anatomy_ahead = true;
  app.add_option("--spacing", spacing, "Phantom voxel size, mm")->capture_default_str();
  app.add_option("--frames", frames, "Frames per configuration (the first 5 are warm-up)")
      ->capture_default_str();
  app.add_option("--size", sizes, "Image sizes")->capture_default_str();
  app.add_option("--backend", backend, "auto, egl or glfw")->capture_default_str();
  app.add_option("--device", device, "Path safety device for the plan: auto, cpu or cuda")
      ->capture_default_str();
  app.add_option("--volume-scale", volume_scale,
                 "Volume rendering resolution (0: automatic, 1 on a GPU, 0.25 on Mesa)")
      ->capture_default_str();
  app.add_option("--full-search", full_search,
                 "Where full-frame tag searches run: background (a worker no frame waits for, "
                 "as `guide` with a camera), wait (the worker, the next frame waiting) or "
                 "in-frame (the frame that needs one waits for it)")
      ->check(CLI::IsMember({"background", "wait", "in-frame"}))
      ->capture_default_str();
  app.add_option("--volume-layer", volume_layer,
                 "Volume layer settings to measure: off, on or both")
      ->check(CLI::IsMember({"off", "on", "both"}))
      ->capture_default_str();
  app.add_option("--anatomy-ahead", anatomy_ahead,
                 "Anatomy pictures placed by an affine map and drawn ahead on another thread "
                 "(false: drawn in the frame whenever the board moved)")
      ->capture_default_str();
  app.add_option("--plan", plan_dir,
                 "Plan folder of the phantom to reuse (made there when it holds no plan.json yet; "
                 "kept afterwards)");
  CLI11_PARSE(app, argc, argv);
  spdlog::set_level(std::getenv("GUIDE_BENCH_DEBUG") ? spdlog::level::debug : spdlog::level::warn);
  try {
    const fs::path dir = fs::temp_directory_path() / ("crepuscular_guide_bench_" +
                                                      std::to_string(::getpid()));
    fs::remove_all(dir);
    pipelines::PlanRequest req;
    req.out_dir = plan_dir.empty() ? (dir / "plan").string() : plan_dir;
    if (plan_dir.empty() || !fs::exists(fs::path(plan_dir) / "plan.json")) {
      // A kept plan keeps its phantom beside it: the scenario reads its label map.
      const fs::path phantom =
          plan_dir.empty() ? dir / "phantom" : fs::path(plan_dir).parent_path() / "phantom";
      planning::PhantomOptions po;
      po.spacing_mm = spacing;
      planning::write_phantom(planning::make_phantom(po), phantom.string());
      req.labels = {(phantom / "labels.nii.gz").string()};
      req.tumor = (phantom / "tumor.nii.gz").string();
      req.vulnerability = (phantom / "vulnerability.json").string();
      req.path_safety.mode = planning::Mode::kFast;
      req.path_safety.device = planning::parse_device(device);
      req.path_safety.radius_mm = 120;
      const auto t_plan = std::chrono::steady_clock::now();
      pipelines::run_plan(req);
      std::cerr << "plan: "
                << std::chrono::duration<double>(std::chrono::steady_clock::now() - t_plan).count()
                << " s\n";
    }
    const planning::PlanData plan = planning::load_plan(req.out_dir);
    const pipelines::GuidanceScenario scenario = pipelines::make_guidance_scenario(plan);
    std::vector<tracking::Board> boards;
    for (const auto& b : scenario.scene.boards) boards.push_back(b.board);

    for (const std::string& size : sizes) {
      int w = 0, h = 0, used = 0;
      if (std::sscanf(size.c_str(), "%dx%d%n", &w, &h, &used) != 2 || w <= 0 || h <= 0 ||
          used != int(size.size())) {
        throw Error("--size " + size + ": expected WIDTHxHEIGHT (several sizes: separated by spaces)");
      }
      // The same view at another resolution: the camera's intrinsics scaled.
      tracking::SyntheticScene scene = scenario.scene;
      const double s = double(w) / scene.camera.width;
      scene.camera.fx *= s;
      scene.camera.fy *= s;
      scene.camera.cx = (scene.camera.cx + 0.5) * s - 0.5;
      scene.camera.cy = (scene.camera.cy + 0.5) * s - 0.5;
      scene.camera.width = w;
      scene.camera.height = h;
      tracking::SyntheticRenderer renderer(scene);
      std::vector<tracking::Frame> video;
      const int64_t n = std::min<int64_t>(frames, scene.frame_count);
      for (int64_t f = 0; f < n; ++f) {
        // Spread over the whole recording: both approaches.
        const int64_t index = f * scene.frame_count / n;
        tracking::Frame frame;
        frame.index = index;
        frame.timestamp_ns = renderer.timestamp_ns_of(index);
        frame.image = renderer.render(index);
        video.push_back(std::move(frame));
      }
      overlay::GuidanceSetup setup;
      setup.camera = scene.camera;
      setup.T_ct_patient = scenario.T_ct_patient;
      setup.tip_in_needle = scenario.needle.tip_needle;
      setup.axis_in_needle =
          scenario.needle.axis_needle ? *scenario.needle.axis_needle : Eigen::Vector3d::UnitZ();
      // A registration known to 1.5 mm at the tumor, as in patients.
      calibration::RegistrationRecord registration;
      registration.expected_tre_mm = 1.5;
      setup.uncertainty = pipelines::calibration_uncertainty(scenario.needle, registration);
      for (bool volume : {false, true}) {
        if (volume_layer != "both" && volume != (volume_layer == "on")) continue;
        overlay::GuidanceOptions go;
        go.visible[size_t(overlay::GuidanceLayer::kVolume)] = volume;
        go.volume_resolution_scale = volume_scale;
        go.anatomy_ahead = anatomy_ahead;
        tracking::TrackerOptions to;
        // Frames are spread over the recording: allow the gaps between them.
        to.max_age_ms = 1000;
        to.full_search_mode = full_search == "in-frame" ? tracking::FullSearchMode::kInFrame
                              : full_search == "wait"   ? tracking::FullSearchMode::kBackgroundWait
                                                        : tracking::FullSearchMode::kBackground;
        overlay::RendererOptions ro;
        ro.backend = backend == "egl"    ? overlay::RendererBackend::kEgl
                     : backend == "glfw" ? overlay::RendererBackend::kGlfw
                                         : overlay::RendererBackend::kAuto;
        pipelines::GuideLoop loop(plan, setup, boards, go, to, ro);
        std::vector<double> latency, track, over, render, upload, anatomy, needle_ms, status;
        std::vector<double> evaluate_ms, targeting_ms, panel_ms, uncertainty_ms;
        int64_t needle = 0;
        for (size_t i = 0; i < video.size(); ++i) {
          const auto arrival = std::chrono::steady_clock::now();
          const pipelines::GuideFrameResult r = loop.process(video[i], arrival, true);
          if (i < 5) continue;
          latency.push_back(r.latency_ms);
          track.push_back(r.track_ms);
          over.push_back(r.overlay_ms);
          render.push_back(r.render_ms);
          upload.push_back(r.info.upload_ms);
          anatomy.push_back(r.info.anatomy_ms);
          needle_ms.push_back(r.info.needle_ms);
          status.push_back(r.info.status_ms);
          if (r.info.needle) {
            evaluate_ms.push_back(r.info.needle_evaluate_ms);
            targeting_ms.push_back(r.info.targeting_ms);
            panel_ms.push_back(r.info.needle_panel_ms);
            uncertainty_ms.push_back(r.info.uncertainty_ms);
          }
          needle += r.info.needle ? 1 : 0;
        }
        nlohmann::json j;
        j["bench"] = "guide";
        j["size"] = size;
        j["volume_layer"] = volume;
        j["full_search"] = full_search;
        j["anatomy_ahead"] = anatomy_ahead;
        j["frames"] = latency.size();
        j["needle_evaluated"] = needle;
        j["latency_median_ms"] = pipelines::percentile(latency, 50);
        j["latency_p95_ms"] = pipelines::percentile(latency, 95);
        j["latency_max_ms"] = pipelines::percentile(latency, 100);
        j["track_median_ms"] = pipelines::percentile(track, 50);
        j["overlay_median_ms"] = pipelines::percentile(over, 50);
        j["render_median_ms"] = pipelines::percentile(render, 50);
        j["overlay_parts_median_ms"] = {{"upload", pipelines::percentile(upload, 50)},
                                        {"anatomy", pipelines::percentile(anatomy, 50)},
                                        {"needle", pipelines::percentile(needle_ms, 50)},
                                        {"status", pipelines::percentile(status, 50)},
                                        {"needle_evaluate", pipelines::percentile(evaluate_ms, 50)},
                                        {"targeting_view", pipelines::percentile(targeting_ms, 50)},
                                        {"needle_panel", pipelines::percentile(panel_ms, 50)},
                                        {"uncertainty", pipelines::percentile(uncertainty_ms, 50)}};
        j["overlay_parts_p95_ms"] = {{"anatomy", pipelines::percentile(anatomy, 95)},
                                     {"needle", pipelines::percentile(needle_ms, 95)},
                                     {"uncertainty", pipelines::percentile(uncertainty_ms, 95)}};
        j["render_p95_ms"] = pipelines::percentile(render, 95);
        j["anatomy_pictures"] = {{"drawn", loop.overlay().anatomy_pictures_drawn()},
                                 {"placed", loop.overlay().anatomy_pictures_warped()},
                                 {"waited_for", loop.overlay().anatomy_pictures_waited()}};
        j["gl"] = loop.renderer().gl_description();
        std::cout << j.dump() << std::endl;
      }
    }
    fs::remove_all(dir);
  } catch (const std::exception& e) {
    std::cerr << "guide_bench: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
