// The render job: plan (+ CT) -> the 3D planning view from one side -> PNG.
#include "pipelines/render.hpp"

#include <fmt/format.h>

#include <chrono>
#include <cstring>
#include <fstream>
#include <future>
#include <sstream>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "foundation/output_files.hpp"
#include "overlay/renderer.hpp"
#include "planning/imaging/scan_coverage.hpp"
#include "planning/imaging/volume_io.hpp"

namespace fs = std::filesystem;

namespace crepuscular::pipelines {

ViewStart start_view_inputs(const std::string& plan_dir, const std::string& ct,
                            const std::string& labels, const std::vector<std::string>& series,
                            const std::string& value, bool check_inputs) {
  ViewStart start;
  planning::PlanLoadOptions load;
  load.blocking = false;
  load.only_value = value.empty() ? planning::plan_default_value(plan_dir) : value;
  load.labels_override = labels;
  load.series = series;
  load.check_inputs = check_inputs;
  // The CT's path needs plan.json only.
  std::string ct_path = ct;
  if (ct_path.empty()) {
    planning::PlanData json_only;
    json_only.dir = plan_dir;
    std::ifstream j((fs::path(plan_dir) / "plan.json").string());
    try {
      j >> json_only.json;
      ct_path = planning::plan_input_path(json_only, "ct");
    } catch (const std::exception&) {
      ct_path.clear();  // load_plan reports what is wrong with plan.json
    }
    std::error_code ec;
    if (!ct_path.empty() && !fs::exists(ct_path, ec)) {
      spdlog::warn("{}: the plan's CT {} is gone; the view shows no bone and no slices (give --ct)",
                   plan_dir, ct_path);
      ct_path.clear();
    }
  }
  if (!ct_path.empty()) {
    spdlog::info("reading CT {}", ct_path);
    start.ct = std::async(std::launch::async, [ct_path, series] {
      return planning::read_volume<float>(ct_path, {series});
    });
    start.inputs.ct_path = ct_path;
  }
  spdlog::info("reading plan {}", plan_dir);
  try {
    start.inputs.plan = planning::load_plan(plan_dir, load);
  } catch (...) {
    if (start.ct.valid()) start.ct.wait();  // the CT's reader stops before the error goes up
    throw;
  }
  return start;
}

ViewInputs load_view_inputs(const std::string& plan_dir, const std::string& ct,
                            const std::string& labels, const std::vector<std::string>& series,
                            const std::string& value, bool check_inputs) {
  ViewStart start = start_view_inputs(plan_dir, ct, labels, series, value, check_inputs);
  ViewInputs in = std::move(start.inputs);
  if (start.ct.valid()) {
    in.ct = start.ct.get();
    planning::require_overlap_with_plan(in.ct.geometry(), in.plan.grid, in.ct_path, "the CT");
  }
  return in;
}

planning::PlanData load_full_plan(const std::string& plan_dir, const std::string& labels,
                                  const std::vector<std::string>& series) {
  planning::PlanLoadOptions load;
  load.labels_override = labels;
  load.series = series;
  return planning::load_plan(plan_dir, load);
}

namespace {

cv::Scalar bgr(const planning::Rgb& c) { return cv::Scalar(c[2], c[1], c[0]); }

void text(cv::Mat& image, const std::string& s, cv::Point at, const cv::Scalar& colour,
          double scale) {
  cv::putText(image, s, at, cv::FONT_HERSHEY_SIMPLEX, scale, cv::Scalar(0, 0, 0), 4, cv::LINE_AA);
  cv::putText(image, s, at, cv::FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv::LINE_AA);
}

}  // namespace

void draw_view_legend(cv::Mat& bgr_image, const overlay::PlanView3D& view,
                      const overlay::ViewAngles& angles) {
  const double scale = std::clamp(bgr_image.rows / 1000.0, 0.4, 1.0);
  const int line = int(std::lround(30 * scale));
  int y = line;
  const int x = int(std::lround(12 * scale));
  text(bgr_image,
       fmt::format("path safety: {}   view from azimuth {:.0f}, elevation {:.0f} deg", view.value(),
                   angles.azimuth_deg, angles.elevation_deg),
       {x, y}, cv::Scalar(255, 255, 255), 0.7 * scale);
  y += line;
  const auto colours = planning::class_colours(view.options().palette);
  const char* names[4] = {"safe", "medium", "dangerous", "unknown"};
  int cx = x;
  for (int c = 0; c < 4; ++c) {
    if (view.options().hidden[size_t(c)]) continue;
    const cv::Scalar colour = c < 3 ? bgr(colours[size_t(c)]) : bgr(overlay::kUnknownGrey);
    cv::rectangle(bgr_image, cv::Rect(cx, y - int(16 * scale), int(16 * scale), int(16 * scale)),
                  colour, cv::FILLED);
    text(bgr_image, names[c], {cx + int(22 * scale), y}, cv::Scalar(255, 255, 255), 0.6 * scale);
    cx += int(std::lround((30 + 14 * std::strlen(names[c])) * scale));
  }
  if (view.options().context) {
    y += line;
    cx = x;
    const auto& surfaces = view.context().surfaces;
    for (size_t k = 1; k < surfaces.size(); ++k) {
      if ((view.options().hidden_surfaces >> k) & 1u) continue;
      const std::string& name = surfaces[k].name;
      const int width = int(std::lround((30 + 12 * name.size()) * scale));
      if (cx + width > bgr_image.cols) {
        y += line;
        cx = x;
      }
      cv::circle(bgr_image, {cx + int(8 * scale), y - int(6 * scale)}, int(7 * scale),
                 bgr(surfaces[k].colour), cv::FILLED, cv::LINE_AA);
      text(bgr_image, name, {cx + int(22 * scale), y}, cv::Scalar(230, 230, 230), 0.5 * scale);
      cx += width;
    }
  }
}

cv::Mat render_plan_view(overlay::PlanView3D& view, const overlay::ViewAngles& angles, int width,
                         int height) {
  const overlay::OrbitCamera orbit = view.default_camera(angles, double(width) / height);
  const calibration::CameraModel camera = orbit.camera(width, height);
  overlay::OverlayRenderer renderer(camera, {});
  const bool software = renderer.gl_description().find("llvmpipe") != std::string::npos ||
                        renderer.gl_description().find("softpipe") != std::string::npos;
  renderer.set_frame(cv::Mat(height, width, CV_8UC3, cv::Scalar(30, 24, 20)));
  const Eigen::Isometry3d pose = orbit.pose();
  renderer.set_layer_draw("3d", [&](const overlay::DrawContext& c) {
    view.draw(c, cv::Rect(0, 0, width, height), camera, pose, software);
  });
  for (const auto& [p, colour] : view.mesh_points(pose)) renderer.add_points("mesh", {p}, colour);
  cv::Mat image = renderer.render();
  view.release_gl();
  draw_view_legend(image, view, angles);
  return image;
}

void apply_hidden(const std::string& list, overlay::PlanViewOptions& options) {
  std::stringstream in(list);
  std::string word;
  while (std::getline(in, word, ',')) {
    word.erase(0, word.find_first_not_of(' '));
    word.erase(word.find_last_not_of(' ') + 1);
    const char* classes[4] = {"safe", "medium", "dangerous", "unknown"};
    bool known = false;
    for (size_t c = 0; c < 4; ++c) {
      if (word == classes[c]) options.hidden[c] = known = true;
    }
    if (word == "skin") options.hidden_surfaces |= 1u << overlay::kSkin;
    if (word == "bone") options.hidden_surfaces |= 1u << overlay::kBone;
    if (word == "tumor") options.hidden_surfaces |= 1u << overlay::kTumor;
    if (word == "structures") options.hidden_surfaces |= ~0u << overlay::kStructureKind;
    if (word == "anatomy") options.context = false;
    known = known || word == "skin" || word == "bone" || word == "tumor" || word == "structures" ||
            word == "anatomy";
    if (!known && !word.empty()) {
      throw Error("--hide: '" + word +
                  "' is neither a class (safe, medium, dangerous, unknown) nor a surface (skin, "
                  "bone, tumor, structures, anatomy)");
    }
  }
}

void run_render(const RenderRequest& req) {
  const auto t0 = std::chrono::steady_clock::now();
  if (req.out.empty()) throw Error("render: --out is required");
  if (req.width < 16 || req.height < 16 || req.width > 8192 || req.height > 8192) {
    throw Error(fmt::format("render: size {}x{} (expected 16 to 8192 pixels per side)", req.width,
                            req.height));
  }
  const overlay::ViewAngles angles = overlay::parse_view_angles(req.view);
  const std::string lower = fs::path(req.out).extension().string();
  if (lower != ".png" && lower != ".PNG") {
    throw Error(req.out + ": expected a .png file");
  }
  const ViewInputs in =
      load_view_inputs(req.plan_dir, req.ct, req.labels, req.series, req.options.value);
  overlay::PlanView3D view(in.plan, in.ct.empty() ? nullptr : &in.ct, req.options);
  const auto t_loaded = std::chrono::steady_clock::now();
  const cv::Mat image = render_plan_view(view, angles, req.width, req.height);
  const auto t_drawn = std::chrono::steady_clock::now();
  write_file_atomically(req.out, [&](const std::string& tmp) {
    if (!cv::imwrite(tmp, image)) throw Error(req.out + ": cannot write the PNG");
  });
  const auto seconds = [](auto a, auto b) { return std::chrono::duration<double>(b - a).count(); };
  spdlog::info("{}: {} seen from {} ({}x{}); read {:.2f} s, drawn {:.2f} s", req.out, view.value(),
               req.view, req.width, req.height, seconds(t0, t_loaded), seconds(t_loaded, t_drawn));
}

}  // namespace crepuscular::pipelines
