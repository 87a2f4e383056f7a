// Timings on a plan folder (e.g. the demo's: `crepuscular demo --mode fast`), moved here from the
// test suite, where they checked nothing:
// - needle --plan DIR: live needle guidance, time per call (target: under 1 ms);
// - volume --plan DIR [--png PREFIX]: draw time of the safety volume rendering layer at 1280x720
//   and 1920x1080, resolution scales 1, 0.5 and 0.25;
// - scenario --plan DIR --out DIR: time to load the plan and build the demo's guidance scenario;
//   prints the scenario and writes its setup and two frames into DIR.
#include <spdlog/spdlog.h>

#include <CLI/CLI.hpp>
#include <Eigen/Geometry>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <random>
#include <string>
#include <utility>
#include <vector>

#include "foundation/error.hpp"
#include "overlay/renderer.hpp"
#include "overlay/volume_rendering.hpp"
#include "pipelines/demo_scenario.hpp"
#include "planning/plan_folder/plan_folder.hpp"
#include "planning/trajectories/needle_guidance.hpp"
#include "tracking/synthetic.hpp"

using namespace crepuscular;
using Clock = std::chrono::steady_clock;

namespace {

double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

// `calls` needles of 80 mm aimed at the tumor centre from random directions, one call each.
void needle_bench(const std::string& plan_dir, int calls) {
  const planning::NeedleGuide guide(plan_dir);
  const Eigen::Vector3d c = guide.plan().tumor_centre;
  std::mt19937 rng(3);
  std::normal_distribution<double> normal;
  std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3d>> needles;
  for (int n = 0; n < calls; ++n) {
    const Eigen::Vector3d u = Eigen::Vector3d(normal(rng), normal(rng), normal(rng)).normalized();
    needles.emplace_back(c + 80.0 * u + Eigen::Vector3d(normal(rng), normal(rng), 0), -u);
  }
  double integral = 0;
  const auto t0 = Clock::now();
  for (const auto& [tip, axis] : needles) {
    integral += guide.evaluate(Eigen::Isometry3d::Identity(), tip, axis).evaluation.line_integral;
  }
  const double ms = ms_since(t0) / calls;
  std::printf(
      "needle guidance: %.4f ms per call (%d calls, 80 mm needles, %zu safe vertices, "
      "sum of line integrals %.3f); target under 1 ms: %s\n",
      ms, calls, guide.safe_directions().size(), integral, ms < 1.0 ? "met" : "NOT met");
}

// T_cam_ct of a camera at `eye` (LPS mm) looking at `target`, with `up_hint` roughly image-up.
Eigen::Isometry3d look_at(const Eigen::Vector3d& eye, const Eigen::Vector3d& target,
                          const Eigen::Vector3d& up_hint) {
  const Eigen::Vector3d z = (target - eye).normalized();
  const Eigen::Vector3d x = (-up_hint).cross(z).normalized();  // image y points down
  Eigen::Isometry3d T_ct_cam = Eigen::Isometry3d::Identity();
  T_ct_cam.linear().col(0) = x;
  T_ct_cam.linear().col(1) = z.cross(x);
  T_ct_cam.linear().col(2) = z;
  T_ct_cam.translation() = eye;
  return T_ct_cam.inverse();
}

// Frame time with and without the volume layer (5 frames each), 50 cm in front of the tumor.
void volume_bench(const std::string& plan_dir, const std::string& png_prefix) {
  planning::PlanLoadOptions load;
  load.blocking = false;
  load.labels = false;
  load.tumor = false;
  load.area_safety = false;
  load.only_value = "svv";
  const planning::PlanData plan = planning::load_plan(plan_dir, load);
  const auto& svv = plan.path_safety.at("svv");
  // Camera 50 cm in front of the tumor (anterior, -P), looking at it, head up.
  const Eigen::Isometry3d pose = look_at(plan.tumor_centre + Eigen::Vector3d(0, -500, 0),
                                         plan.tumor_centre, Eigen::Vector3d(0, 0, 1));
  for (const auto& size : {std::pair<int, int>(1280, 720), std::pair<int, int>(1920, 1080)}) {
    calibration::CameraModel cam;
    cam.width = size.first;
    cam.height = size.second;
    cam.fx = cam.fy = 0.9 * size.first;
    cam.cx = size.first / 2.0 - 0.5;
    cam.cy = size.second / 2.0 - 0.5;
    cam.distortion = {-0.1, 0.02, 0, 0, 0};
    overlay::OverlayRenderer renderer(cam);
    std::cout << renderer.gl_description() << "\n";
    cv::Mat frame(cam.height, cam.width, CV_8UC3);
    cv::RNG(1).fill(frame, cv::RNG::UNIFORM, 0, 256);
    for (const double scale : {1.0, 0.5, 0.25}) {
      overlay::VolumeRenderingOptions options;
      options.resolution_scale = scale;
      overlay::SafetyVolumeRendering rendering(svv, plan.classes.at("svv"), options);
      rendering.set_pose(pose);
      renderer.set_frame(frame);
      renderer.set_layer_draw("volume",
                              [&rendering](const overlay::DrawContext& c) { rendering.draw(c); });
      const cv::Mat first = renderer.render();  // makes the GL objects and the rays
      renderer.set_layer_visible("volume", false);
      const int n = 5;
      auto t0 = Clock::now();
      for (int i = 0; i < n; ++i) renderer.render();
      const double bare = ms_since(t0) / n;
      renderer.set_layer_visible("volume", true);
      t0 = Clock::now();
      for (int i = 0; i < n; ++i) renderer.render();
      const double with = ms_since(t0) / n;
      std::printf(
          "%dx%d scale %.2f: frame %.2f ms with the volume layer, %.2f ms without: layer "
          "%.2f ms\n",
          cam.width, cam.height, scale, with, bare, with - bare);
      if (!png_prefix.empty()) {
        cv::imwrite(png_prefix + "_" + std::to_string(cam.width) + "_" +
                        std::to_string(int(scale * 100)) + ".png",
                    first);
      }
    }
  }
}

// The demo's scenario on the plan: its approaches, the needle's safety along the recording, the
// setup files and one frame of each approach in `out_dir`.
void scenario_bench(const std::string& plan_dir, const std::string& out_dir) {
  spdlog::set_level(spdlog::level::debug);
  const auto t0 = Clock::now();
  const planning::PlanData plan = planning::load_plan(plan_dir);
  const double load_ms = ms_since(t0);
  const auto t1 = Clock::now();
  const pipelines::GuidanceScenario sc = pipelines::make_guidance_scenario(plan);
  std::printf("load %.2f s, scenario %.2f s\n", load_ms / 1000, ms_since(t1) / 1000);
  for (const pipelines::GuidanceApproach* a : {&sc.safe, &sc.dangerous}) {
    const planning::NeedleState& s = a->state;
    std::printf(
        "%s: direction %s, entry %s, %.1f deg from anterior, %.1f deg from the view axis, "
        "%.2f..%.2f s\n  line integral %.4f (eps %.2f), clear %d, tip class %s, safety %s, "
        "angle to safe %.1f deg, tip to centroid %.1f mm\n",
        a->name.c_str(),
        nlohmann::json({a->direction_ct.x(), a->direction_ct.y(), a->direction_ct.z()})
            .dump()
            .c_str(),
        nlohmann::json({a->entry_ct.x(), a->entry_ct.y(), a->entry_ct.z()}).dump().c_str(),
        a->angle_from_anterior_deg, a->angle_to_view_axis_deg, a->start_s, a->end_s,
        s.evaluation.line_integral, s.eps, int(s.clear), s.tip_class.c_str(),
        planning::needle_safety_name(s.safety), s.angle_to_safe_deg, s.tip_to_centroid_mm);
    for (const planning::StructureHit& h : s.evaluation.structures) {
      std::printf("    %s (label %d, %s): depth %.1f mm, length %.1f mm\n", h.name.c_str(), h.label,
                  h.level_name.c_str(), h.depth_mm, h.length_mm);
    }
  }
  std::printf("angle between approaches %.1f deg\n",
              std::acos(sc.safe.direction_ct.dot(sc.dangerous.direction_ct)) * 180 / M_PI);
  std::cout << "T_ct_patient\n" << sc.T_ct_patient.matrix() << "\n";
  // The needle's safety along the recording (ground-truth poses).
  const planning::NeedleGuide guide(plan);
  for (int64_t f = 0; f < sc.scene.frame_count; f += 6) {
    const double t = double(f) / sc.scene.fps;
    const planning::NeedleState s = guide.evaluate(
        sc.T_ct_needle_at(t), tracking::kNeedleTipInNeedle, Eigen::Vector3d::UnitZ());
    std::printf(
        "t %.2f s: %s, line integral %.3f, tip class %s, tip to centroid %.1f mm, miss "
        "%.1f mm\n",
        t, planning::needle_safety_name(s.safety), s.evaluation.line_integral, s.tip_class.c_str(),
        s.tip_to_centroid_mm, s.miss_distance_mm);
  }
  pipelines::write_guidance_setup(sc, out_dir);
  tracking::SyntheticRenderer renderer(sc.scene);
  for (double t : {0.5 * (sc.safe.start_s + sc.safe.end_s),
                   0.5 * (sc.dangerous.start_s + sc.dangerous.end_s)}) {
    const int64_t f = int64_t(t * sc.scene.fps);
    cv::imwrite(out_dir + "/frame_" + std::to_string(f) + ".png", renderer.render(f));
  }
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Timings on a plan folder: needle guidance, volume rendering, the demo's scenario"};
  app.require_subcommand(1);
  std::string plan_dir, png_prefix, out_dir;
  int calls = 2000;
  CLI::App* needle = app.add_subcommand("needle", "Live needle guidance: time per call");
  needle->add_option("--plan", plan_dir, "Plan folder")->required();
  needle->add_option("--calls", calls, "Needles evaluated")->capture_default_str();
  CLI::App* volume = app.add_subcommand("volume", "Safety volume rendering layer: draw time");
  volume->add_option("--plan", plan_dir, "Plan folder")->required();
  volume->add_option("--png", png_prefix, "Write the first frame of each setting to PREFIX_*.png");
  CLI::App* scenario = app.add_subcommand("scenario", "The demo's guidance scenario: build time");
  scenario->add_option("--plan", plan_dir, "Plan folder")->required();
  scenario->add_option("--out", out_dir, "Folder for the setup files and two frames")->required();
  CLI11_PARSE(app, argc, argv);
  try {
    if (*needle) needle_bench(plan_dir, calls);
    if (*volume) volume_bench(plan_dir, png_prefix);
    if (*scenario) scenario_bench(plan_dir, out_dir);
  } catch (const Error& e) {
    spdlog::error("{}", e.what());
    return 1;
  }
  return 0;
}
