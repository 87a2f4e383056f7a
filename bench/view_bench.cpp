// `crepuscular view` as a user sees it, without a window (EGL: the GPU's, or Mesa's): the time from
// the start to the first picture, phase by phase (reading the plan and CT, the 3D view's anatomy,
// the window with its slices, the first frame drawn), then frames per second while the 3D view
// turns (2 degrees of azimuth per frame), in the 3D-only layout and in the 2x2 layout. One JSON
// line on stdout. The full plan (every value, the blocking volume) is read beside the first picture,
// as `view` reads it; the first trial path waits for it.
#include <CLI/CLI.hpp>
#include <chrono>
#include <cstdio>
#include <future>
#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include "foundation/error.hpp"
#include "pipelines/plan_viewer.hpp"

using namespace crepuscular;

namespace {

double since(std::chrono::steady_clock::time_point t) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
}

// Frames per second over `frames` frames turning the camera, after 5 frames not counted.
double turning_fps(pipelines::PlanViewer& viewer, int frames) {
  for (int f = 0; f < 5; ++f) {
    viewer.orbit().angles.azimuth_deg += 2;
    viewer.frame(true);
  }
  viewer.renderer().finish();
  const auto t = std::chrono::steady_clock::now();
  for (int f = 0; f < frames; ++f) {
    viewer.orbit().angles.azimuth_deg += 2;
    viewer.frame(true);
  }
  viewer.renderer().finish();
  return frames / since(t);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app("3D planning view: first picture and frames per second (no window)");
  std::string plan, ct, size = "1920x1080";
  int frames = 120;
  app.add_option("--plan", plan, "plan folder")->required();
  app.add_option("--ct", ct, "CT (default: the plan's)");
  app.add_option("--size", size, "window size WxH")->capture_default_str();
  app.add_option("--frames", frames, "frames timed per layout")->capture_default_str();
  double scale = 0;
  bool no_anatomy = false;
  app.add_option("--resolution-scale", scale, "rays per pixel (0: the view's automatic choice)");
  app.add_flag("--no-anatomy", no_anatomy, "without the anatomy surfaces");
  CLI11_PARSE(app, argc, argv);
  spdlog::set_level(spdlog::level::warn);
  try {
    pipelines::ViewerOptions o;
    o.window = false;
    o.width = std::stoi(size.substr(0, size.find('x')));
    o.height = std::stoi(size.substr(size.find('x') + 1));
    o.view.hidden[2] = true;  // the command's default: dangerous hidden
    o.view.resolution_scale = scale;
    o.view.context = !no_anatomy;
    nlohmann::json j;
    const auto t0 = std::chrono::steady_clock::now();
    auto t = t0;
    pipelines::ViewStart start = pipelines::start_view_inputs(plan, ct, "", {}, "", false);
    const pipelines::ViewInputs& inputs = start.inputs;
    j["read_s"] = since(t);
    t = std::chrono::steady_clock::now();
    // As `view` does: every value and the blocking volume read meanwhile.
    const auto t_full = std::chrono::steady_clock::now();
    double full_s = 0;
    pipelines::PlanViewer viewer(inputs, o, std::async(std::launch::async, [&] {
                                   auto p = pipelines::load_full_plan(plan, "", {});
                                   full_s = since(t_full);
                                   return p;
                                 }),
                                 std::move(start.ct));
    j["window_and_slices_s"] = since(t);
    t = std::chrono::steady_clock::now();
    viewer.frame(true);
    viewer.renderer().finish();
    j["first_frame_s"] = since(t);
    j["first_picture_s"] = since(t0);
    // The CT's arrival: bone in the 3D view and the slices (the frames until then show the plan).
    while (viewer.slice(pipelines::ViewPanel::kAxial).view_width == 0 && since(t0) < 120) {
      viewer.frame(true);
    }
    viewer.renderer().finish();
    j["with_ct_s"] = since(t0);
    j["gl"] = viewer.renderer().gl_description();
    j["grid"] = {inputs.plan.grid.dims[0], inputs.plan.grid.dims[1], inputs.plan.grid.dims[2]};
    j["size"] = size;
    // The first path waits for the full plan.
    viewer.set_entry(inputs.plan.tumor_centre + Eigen::Vector3d(0, -60, 0));
    j["full_plan_s"] = full_s;
    j["first_path_s"] = since(t0);
    viewer.handle({overlay::InputEvent::Kind::kKey, 'L'});  // 2x2 -> 3D only
    j["fps_3d"] = turning_fps(viewer, frames);
    viewer.handle({overlay::InputEvent::Kind::kKey, 'L'});  // -> slices only
    viewer.handle({overlay::InputEvent::Kind::kKey, 'L'});  // -> 2x2
    j["fps_2x2"] = turning_fps(viewer, frames);
    std::printf("%s\n", j.dump().c_str());
  } catch (const std::exception& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  }
  return 0;
}
