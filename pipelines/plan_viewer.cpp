// The view job: plan + CT -> a window with the 3D view and three slices -> trial paths evaluated
// live and saved as markups.
#include "pipelines/plan_viewer.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>
#include <thread>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "foundation/output_files.hpp"
#include "planning/imaging/scan_coverage.hpp"
#include "planning/trajectories/markups.hpp"

namespace fs = std::filesystem;

namespace crepuscular::pipelines {

namespace {

// GLFW key codes the viewer uses (letters and digits are their ASCII upper-case codes).
constexpr int kKeyEscape = 256, kKeyTab = 258, kKeyBackspace = 259, kKeyRight = 262,
              kKeyLeft = 263, kKeyDown = 264, kKeyUp = 265, kKeyEqual = 61, kKeyMinus = 45,
              kKeyPadAdd = 334, kKeyPadSubtract = 333;
constexpr int kModShift = 1;
constexpr double kDragPx = 3;           // a press that moves less than this is a click
constexpr double kDegreesPerPx = 0.4;   // rotation by dragging in the 3D view
constexpr double kDegreesPerKey = 15;   // rotation by the arrow keys

planning::SlicePlaneKind plane_kind(ViewPanel panel) {
  switch (panel) {
    case ViewPanel::kAxial: return planning::SlicePlaneKind::kAxial;
    case ViewPanel::kCoronal: return planning::SlicePlaneKind::kCoronal;
    default: return planning::SlicePlaneKind::kSagittal;
  }
}

cv::Scalar class_bgr(const std::string& safety_class, planning::Palette palette) {
  const auto colours = planning::class_colours(palette);
  const char* names[3] = {"safe", "medium", "dangerous"};
  for (size_t c = 0; c < 3; ++c) {
    if (safety_class == names[c]) return cv::Scalar(colours[c][2], colours[c][1], colours[c][0]);
  }
  return cv::Scalar(overlay::kUnknownGrey[2], overlay::kUnknownGrey[1], overlay::kUnknownGrey[0]);
}

// Text lines on a translucent dark panel (BGRA).
cv::Mat text_panel(const std::vector<std::string>& lines, int width, double scale = 0.45,
                   int alpha = 190) {
  const int line = int(std::lround(40 * scale));
  cv::Mat panel(int(lines.size()) * line + line / 2, width, CV_8UC4, cv::Scalar(20, 20, 20, alpha));
  for (size_t i = 0; i < lines.size(); ++i) {
    cv::putText(panel, lines[i], {8, int(i + 1) * line - line / 4}, cv::FONT_HERSHEY_SIMPLEX,
                scale, cv::Scalar(235, 235, 235, 255), 1, cv::LINE_AA);
  }
  return panel;
}

std::vector<std::string> split_lines(const std::string& text) {
  std::vector<std::string> lines;
  std::stringstream in(text);
  std::string l;
  while (std::getline(in, l)) lines.push_back(l);
  return lines;
}

// The next free "<plan>-<what>-NN<extension>" beside the plan folder.
std::string next_path_beside(const std::string& plan_dir, const std::string& what,
                             const std::string& extension) {
  fs::path plan = fs::path(plan_dir).lexically_normal();
  if (plan.filename().empty()) plan = plan.parent_path();
  for (int n = 1; n < 10000; ++n) {
    const fs::path p = plan.parent_path() / fmt::format("{}-{}-{:02d}{}", plan.filename().string(),
                                                        what, n, extension);
    std::error_code ec;
    if (!fs::exists(p, ec)) return p.string();
  }
  throw Error(plan_dir + ": no free " + what + " file name beside the plan");
}

}  // namespace

const std::vector<std::string>& viewer_key_help() {
  static const std::vector<std::string> help = {
      "click on the skin    entry of a trial path (to the tumor centre)",
      "Shift+click          target of the trial path",
      "Backspace            clear the trial path",
      "M                    save the trial path as a Slicer line markup",
      "P                    save a picture of the window;  E: hide/show the evaluation",
      "drag in 3D / arrows  rotate;  wheel in 3D: zoom",
      "wheel on a slice     move its plane;  drag on a slice: move the other planes there",
      "Tab                  next path safety value",
      "1 2 3 4              hide/show safe, medium, dangerous, unknown",
      "S B T G              hide/show skin, bone, tumor, structures",
      "A                    area safety mesh (leeway colours)",
      "+ -                  more/less opaque classes",
      "C                    colour-blind palette",
      "O                    oblique plane (along the trial path or the largest safe region)",
      "L                    layout: 2x2, 3D only, slices only",
      "R                    reset the view;  H: this help;  Esc: quit"};
  return help;
}

PlanViewer::PlanViewer(const ViewInputs& inputs, ViewerOptions options,
                       std::future<planning::PlanData> full,
                       std::future<planning::Volume<float>> ct)
    : inputs_(inputs), options_(std::move(options)), full_future_(std::move(full)),
      ct_future_(std::move(ct)), layout_(options_.layout) {
  if (!inputs_.ct.empty()) ct_ = &inputs_.ct;
  // A CT read by now is taken before the 3D view's anatomy is made, not after.
  receive_ct();
  if (options_.width < 320 || options_.height < 240) {
    throw Error(fmt::format("view: window {}x{} (expected at least 320x240)", options_.width,
                            options_.height));
  }
  view_ = std::make_unique<overlay::PlanView3D>(inputs_.plan, ct_, options_.view);
  calibration::CameraModel window_camera;
  window_camera.width = options_.width;
  window_camera.height = options_.height;
  window_camera.fx = window_camera.fy = 1000;
  window_camera.cx = 0.5 * (options_.width - 1);
  window_camera.cy = 0.5 * (options_.height - 1);
  window_camera.distortion = {0, 0, 0, 0, 0};
  overlay::RendererOptions ro;
  ro.visible = options_.window;
  renderer_ = std::make_unique<overlay::OverlayRenderer>(window_camera, ro);
  const std::string gl = renderer_->gl_description();
  software_ = gl.find("llvmpipe") != std::string::npos || gl.find("softpipe") != std::string::npos;
  spdlog::info("view: OpenGL {}", gl);
  for (const char* layer : {"3d", "mesh", "slices", "marks", "text"}) renderer_->clear_layer(layer);
  renderer_->set_layer_draw("3d", [this](const overlay::DrawContext& c) {
    const cv::Rect r = panels_[size_t(ViewPanel::k3d)];
    if (r.empty()) return;
    view_->draw(c, r, camera3d(), orbit_.pose(), software_, moving_);
  });
  cursor_ = inputs_.plan.tumor_centre;
  target_ = inputs_.plan.tumor_centre;
  slice_options_ = options_.slices;
  place_panels();
  orbit_ = view_->default_camera(options_.angles, double(panels_[0].width) / panels_[0].height);
  text_revision_ = overlay::OverlayRenderer::new_image_revision();
}

PlanViewer::~PlanViewer() {
  try {
    renderer_->clear_layer("3d");
    renderer_->draw();  // the context current, to free the rendering's objects in it
    view_->release_gl();
  } catch (const std::exception&) {
  }
}

void PlanViewer::place_panels() {
  const int w = options_.width, h = options_.height;
  panels_ = {};
  switch (layout_) {
    case ViewLayout::kQuad:
      panels_[0] = {0, 0, w / 2, h / 2};
      panels_[1] = {w / 2, 0, w - w / 2, h / 2};
      panels_[2] = {0, h / 2, w / 2, h - h / 2};
      panels_[3] = {w / 2, h / 2, w - w / 2, h - h / 2};
      break;
    case ViewLayout::k3d: panels_[0] = {0, 0, w, h}; break;
    case ViewLayout::kSlices:
      for (int p = 1; p < kViewPanels; ++p) panels_[size_t(p)] = {(p - 1) * w / 3, 0, w / 3, h};
      break;
  }
  // One pixel size for the three slices, the finest at which each fits its panel.
  if (ct_ && layout_ != ViewLayout::k3d) {
    const auto& g = ct_->geometry();
    double pixel_mm = 0;
    for (int p = 1; p < kViewPanels; ++p) {
      const planning::SlicePlane plane =
          planning::make_slice_plane(plane_kind(ViewPanel(p)), cursor_);
      double lo[2] = {1e300, 1e300}, hi[2] = {-1e300, -1e300};
      for (int c = 0; c < 8; ++c) {
        const Eigen::Vector3d q = g.index_to_physical(
            Eigen::Vector3d((c & 1) ? g.dims[0] - 0.5 : -0.5, (c & 2) ? g.dims[1] - 0.5 : -0.5,
                            (c & 4) ? g.dims[2] - 0.5 : -0.5));
        const double a[2] = {q.dot(plane.right), q.dot(plane.down)};
        for (int i = 0; i < 2; ++i) {
          lo[i] = std::min(lo[i], a[i]);
          hi[i] = std::max(hi[i], a[i]);
        }
      }
      const cv::Rect& r = panels_[size_t(p)];
      pixel_mm = std::max({pixel_mm, (hi[0] - lo[0]) / (r.width - 2), (hi[1] - lo[1]) / (r.height - 2)});
    }
    slice_options_.pixel_mm = pixel_mm;
  }
  update_slices(true);
  dirty_ = true;
}

calibration::CameraModel PlanViewer::camera3d() const {
  const cv::Rect& r = panels_[size_t(ViewPanel::k3d)];
  return orbit_.camera(std::max(1, r.width), std::max(1, r.height));
}

cv::Rect PlanViewer::panel_rect(ViewPanel panel) const { return panels_[size_t(panel)]; }

cv::Point PlanViewer::slice_origin(ViewPanel panel) const {
  const cv::Rect& r = panels_[size_t(panel)];
  const auto& s = slices_[size_t(panel)];
  return {r.x + std::max(0, (r.width - s.view_width) / 2),
          r.y + std::max(0, (r.height - s.view_height) / 2)};
}

void PlanViewer::update_slices(bool all) {
  if (!ct_) return;
  planning::SliceScene scene;
  scene.ct = ct_;
  const auto& plan = inputs_.plan;
  scene.path_safety = &view_->volume();
  scene.region_state = plan.region.empty() ? nullptr : &plan.region;
  scene.value_name = view_->value();
  scene.classes = view_->classes();
  scene.labels = plan.labels.empty() ? nullptr : &plan.labels;
  scene.table = plan.table ? &*plan.table : nullptr;
  scene.tumor = plan.tumor.empty() ? nullptr : &plan.tumor;
  scene.area = plan.area ? &*plan.area : nullptr;
  // A view grows beyond the CT where unknown voxels lie: then a coarser pixel for all three.
  for (int attempt = 0; attempt < 4; ++attempt) {
    render_slices(scene, all);
    double over = 1;
    for (int p = 1; p < kViewPanels; ++p) {
      const cv::Rect& r = panels_[size_t(p)];
      const auto& v = slices_[size_t(p)];
      if (r.empty() || v.view_width == 0) continue;
      over = std::max({over, double(v.view_width) / r.width, double(v.view_height) / r.height});
    }
    if (over <= 1) break;
    slice_options_.pixel_mm *= over * 1.01;
    all = true;
  }
  dirty_ = true;
}

void PlanViewer::render_slices(const planning::SliceScene& scene, bool all) {
  const auto& plan = inputs_.plan;
  planning::SliceOptions o = slice_options_;
  o.palette = view_->options().palette;
  for (size_t c = 0; c < 3; ++c) o.hidden[c] = view_->options().hidden[c];
  for (int p = 1; p < kViewPanels; ++p) {
    if (panels_[size_t(p)].empty()) continue;
    if (!all && p != kViewPanels - 1) continue;
    planning::SlicePlane plane = planning::make_slice_plane(plane_kind(ViewPanel(p)), cursor_);
    if (p == kViewPanels - 1 && oblique_) {
      Eigen::Vector3d axis = Eigen::Vector3d::Zero();
      if (entry_) {
        axis = (target_ - *entry_).normalized();
      } else if (plan.area && !plan.area->regions.empty()) {
        axis = plan.area->regions[0].main_axis;
      }
      if (axis.squaredNorm() > 0) {
        plane = planning::make_slice_plane(planning::SlicePlaneKind::kOblique, plan.tumor_centre, axis);
      }
    }
    slices_[size_t(p)] = planning::render_slice(scene, plane, o);
    slice_revisions_[size_t(p)] = overlay::OverlayRenderer::new_image_revision();
    // The window's picture of it, made once: the view part, within its panel, BGRA.
    const auto& v = slices_[size_t(p)];
    const cv::Rect& panel = panels_[size_t(p)];
    cv::Mat rgb(v.image.height, v.image.width, CV_8UC3, const_cast<uint8_t*>(v.image.rgb.data()));
    cv::cvtColor(rgb(cv::Rect(0, 0, std::min(v.view_width, panel.width),
                              std::min(v.view_height, panel.height))),
                 slice_pictures_[size_t(p)], cv::COLOR_RGB2BGRA);
  }
}

std::string PlanViewer::evaluation_text() const {
  return evaluation_ ? planning::evaluation_text(*evaluation_) : std::string();
}

void PlanViewer::evaluate() {
  evaluation_.reset();
  if (!entry_) return;
  try {
    planning::Trajectory t;
    t.name = "trial";
    t.entry = *entry_;
    t.target = target_;
    // Made at the first path: it ranks every value's region of interest once.
    take_full_plan(true);
    if (!full_) throw Error("the plan with its blocking volume could not be read");
    if (!evaluator_) evaluator_ = std::make_unique<planning::TrajectoryEvaluator>(*full_);
    evaluation_ = evaluator_->evaluate(t);
  } catch (const Error& e) {
    spdlog::warn("view: {}", e.what());
  }
  if (oblique_) update_slices(false);
  dirty_ = true;
}

void PlanViewer::take_full_plan(bool wait) {
  if (full_ || !full_future_.valid()) return;
  if (!wait && full_future_.wait_for(std::chrono::seconds(0)) != std::future_status::ready) return;
  try {
    full_ = std::make_unique<planning::PlanData>(full_future_.get());
    view_->add_values(*full_);
    dirty_ = true;
  } catch (const Error& e) {
    spdlog::error("view: {}", e.what());
  }
}

bool PlanViewer::receive_ct() {
  if (!ct_future_.valid() ||
      ct_future_.wait_for(std::chrono::seconds(0)) != std::future_status::ready) {
    return false;
  }
  try {
    late_ct_ = std::make_unique<planning::Volume<float>>(ct_future_.get());
    planning::require_overlap_with_plan(late_ct_->geometry(), inputs_.plan.grid, inputs_.ct_path,
                                        "the CT");
    ct_ = late_ct_.get();
    return true;
  } catch (const Error& e) {
    late_ct_.reset();
    ct_problem_ = e.what();
    spdlog::error("view: {}", ct_problem_);
    return false;
  }
}

void PlanViewer::take_ct() {
  if (!ct_future_.valid() ||
      ct_future_.wait_for(std::chrono::seconds(0)) != std::future_status::ready) {
    return;
  }
  if (receive_ct()) {
    view_->set_ct(ct_);
    place_panels();
  }
  dirty_ = true;
}

void PlanViewer::set_entry(const Eigen::Vector3d& entry) {
  entry_ = entry;
  spdlog::info("view: entry ({:.1f}, {:.1f}, {:.1f}) LPS mm", entry.x(), entry.y(), entry.z());
  evaluate();
}

void PlanViewer::set_target(const Eigen::Vector3d& target) {
  target_ = target;
  spdlog::info("view: target ({:.1f}, {:.1f}, {:.1f}) LPS mm", target.x(), target.y(), target.z());
  evaluate();
}

void PlanViewer::save_picture() {
  const std::string path = next_path_beside(inputs_.plan.dir, "view", ".png");
  const cv::Mat image = picture();
  write_file_atomically(path, [&](const std::string& tmp) {
    if (!cv::imwrite(tmp, image)) throw Error(path + ": cannot write the PNG");
  });
  saved_picture_ = path;
  spdlog::info("view: picture saved as {}", path);
  dirty_ = true;
}

void PlanViewer::save_markup() {
  if (!entry_) {
    spdlog::warn("view: no trial path to save (click on the skin first)");
    return;
  }
  const std::string path = next_path_beside(inputs_.plan.dir, "trajectory", ".mrk.json");
  planning::LineMarkup line;
  line.name = fs::path(path).stem().stem().string();
  line.first = *entry_;
  line.second = target_;
  line.first_label = "entry";
  line.second_label = "target";
  planning::write_line_markup(path, line, "LPS");
  saved_markup_ = path;
  spdlog::info("view: trial path saved as {}", path);
  dirty_ = true;
}

std::optional<ViewPanel> PlanViewer::panel_at(double x, double y) const {
  for (int p = 0; p < kViewPanels; ++p) {
    const cv::Rect& r = panels_[size_t(p)];
    if (!r.empty() && x >= r.x - 0.5 && x < r.x + r.width - 0.5 && y >= r.y - 0.5 &&
        y < r.y + r.height - 0.5) {
      return ViewPanel(p);
    }
  }
  return std::nullopt;
}

std::optional<Eigen::Vector3d> PlanViewer::point_at(ViewPanel panel, double x, double y) const {
  const cv::Rect& r = panels_[size_t(panel)];
  if (panel == ViewPanel::k3d) {
    return view_->pick_skin(camera3d(), orbit_.pose(), x - r.x, y - r.y);
  }
  const auto& s = slices_[size_t(panel)];
  if (s.view_width == 0) return std::nullopt;
  const cv::Point o = slice_origin(panel);
  const double sx = x - o.x, sy = y - o.y;
  if (sx < -0.5 || sy < -0.5 || sx > s.view_width - 0.5 || sy > s.view_height - 0.5) {
    return std::nullopt;
  }
  return s.point_of(sx, sy);
}

void PlanViewer::handle(const overlay::InputEvent& e) {
  using Kind = overlay::InputEvent::Kind;
  overlay::PlanViewOptions o = view_->options();
  bool options_changed = false, slices_changed = false;
  switch (e.kind) {
    case Kind::kPress:
      held_button_ = e.key;
      held_mods_ = e.mods;
      held_panel_ = panel_at(e.x, e.y);
      press_at_ = last_at_ = {e.x, e.y};
      dragged_ = false;
      return;
    case Kind::kMove: {
      if (held_button_ < 0 || !held_panel_) return;
      const Eigen::Vector2d at(e.x, e.y);
      if ((at - press_at_).norm() >= kDragPx) dragged_ = true;
      const Eigen::Vector2d d = at - last_at_;
      last_at_ = at;
      if (!dragged_) return;
      if (*held_panel_ == ViewPanel::k3d) {
        orbit_.angles.azimuth_deg -= d.x() * kDegreesPerPx;
        orbit_.angles.elevation_deg =
            std::clamp(orbit_.angles.elevation_deg + d.y() * kDegreesPerPx, -89.0, 89.0);
        dirty_ = true;
      } else if (const auto p = point_at(*held_panel_, e.x, e.y)) {
        cursor_ = *p;
        update_slices(true);
      }
      return;
    }
    case Kind::kRelease: {
      const bool click = held_button_ == 0 && !dragged_ && held_panel_;
      const auto panel = held_panel_;
      const int mods = held_mods_;
      held_button_ = -1;
      held_panel_.reset();
      if (!click) return;
      const auto p = point_at(*panel, e.x, e.y);
      if (!p) return;
      if (mods & kModShift) {
        set_target(*p);
      } else {
        set_entry(*p);
      }
      return;
    }
    case Kind::kScroll: {
      const auto panel = panel_at(e.x, e.y);
      if (!panel) return;
      if (*panel == ViewPanel::k3d) {
        orbit_.distance_mm *= std::pow(0.9, e.scroll);
        dirty_ = true;
      } else {
        const auto& s = slices_[size_t(*panel)];
        const double step = inputs_.plan.grid.spacing.minCoeff();
        cursor_ += s.plane.normal() * step * e.scroll;
        update_slices(true);
      }
      return;
    }
    case Kind::kKey: break;
  }
  const int key = e.key;
  if (key >= '1' && key <= '4') {
    o.hidden[size_t(key - '1')] = !o.hidden[size_t(key - '1')];
    options_changed = slices_changed = true;
  }
  const auto toggle_surface = [&](uint32_t bits) {
    o.hidden_surfaces = (o.hidden_surfaces & bits) ? (o.hidden_surfaces & ~bits)
                                                   : (o.hidden_surfaces | bits);
    options_changed = true;
  };
  switch (key) {
    case kKeyEscape:
    case 'Q': open_ = false; break;
    case kKeyTab:
      take_full_plan(true);
      view_->next_value();
      slices_changed = true;
      if (entry_) evaluate();
      break;
    case 'S': toggle_surface(1u << overlay::kSkin); break;
    case 'B': toggle_surface(1u << overlay::kBone); break;
    case 'T': toggle_surface(1u << overlay::kTumor); break;
    case 'G': toggle_surface(~0u << overlay::kStructureKind); break;
    case 'A': o.area_mesh = !o.area_mesh; options_changed = true; break;
    case 'C':
      o.palette = o.palette == planning::Palette::kDefault ? planning::Palette::kColorblind
                                                           : planning::Palette::kDefault;
      options_changed = slices_changed = true;
      break;
    case kKeyEqual:
    case kKeyPadAdd: o.opacity_scale *= 1.5; options_changed = true; break;
    case kKeyMinus:
    case kKeyPadSubtract: o.opacity_scale /= 1.5; options_changed = true; break;
    case kKeyLeft: orbit_.angles.azimuth_deg += kDegreesPerKey; dirty_ = true; break;
    case kKeyRight: orbit_.angles.azimuth_deg -= kDegreesPerKey; dirty_ = true; break;
    case kKeyUp:
      orbit_.angles.elevation_deg = std::min(89.0, orbit_.angles.elevation_deg + kDegreesPerKey);
      dirty_ = true;
      break;
    case kKeyDown:
      orbit_.angles.elevation_deg = std::max(-89.0, orbit_.angles.elevation_deg - kDegreesPerKey);
      dirty_ = true;
      break;
    case 'O': oblique_ = !oblique_; update_slices(false); break;
    case 'L':
      layout_ = layout_ == ViewLayout::kQuad ? ViewLayout::k3d
                : layout_ == ViewLayout::k3d ? ViewLayout::kSlices
                                             : ViewLayout::kQuad;
      place_panels();
      if (!panels_[0].empty()) {
        orbit_.distance_mm =
            view_->default_camera(orbit_.angles, double(panels_[0].width) / panels_[0].height)
                .distance_mm;
      }
      break;
    case 'R':
      orbit_ = view_->default_camera(options_.angles,
                                     panels_[0].empty() ? 16.0 / 9.0
                                                        : double(panels_[0].width) / panels_[0].height);
      cursor_ = inputs_.plan.tumor_centre;
      slices_changed = true;
      break;
    case kKeyBackspace:
      entry_.reset();
      target_ = inputs_.plan.tumor_centre;
      evaluate();
      break;
    case 'M':
    case 'P':
      // A file that cannot be written (a read-only folder, a full disk) is said in the window and
      // the log; the view goes on.
      try {
        save_problem_.clear();
        key == 'M' ? save_markup() : save_picture();
      } catch (const Error& e) {
        save_problem_ = e.what();
        spdlog::error("view: {}", save_problem_);
        dirty_ = true;
      }
      break;
    case 'H': help_ = !help_; dirty_ = true; break;
    case 'E': show_evaluation_ = !show_evaluation_; dirty_ = true; break;
    default: break;
  }
  if (options_changed) {
    view_->set_options(o);
    dirty_ = true;
  }
  if (slices_changed) update_slices(true);
}

void PlanViewer::update_layers() {
  overlay::OverlayRenderer& r = *renderer_;
  const planning::Palette palette = view_->options().palette;
  // Slices, at their size (pixel for pixel as `slices` draws them).
  r.clear_layer("slices");
  for (int p = 1; p < kViewPanels; ++p) {
    const auto& s = slices_[size_t(p)];
    if (panels_[size_t(p)].empty() || s.view_width == 0) continue;
    r.add_layer_image("slices", slice_pictures_[size_t(p)], slice_origin(ViewPanel(p)),
                      slice_revisions_[size_t(p)]);
  }
  // The trial path: its line in every panel, coloured by the class of its entry.
  r.clear_layer("marks");
  r.clear_layer("mesh");
  const cv::Rect& r3 = panels_[size_t(ViewPanel::k3d)];
  if (!r3.empty() && view_->options().area_mesh) {
    cv::Mat mesh(r3.height, r3.width, CV_8UC4, cv::Scalar(0, 0, 0, 0));
    const calibration::CameraModel cam = camera3d();
    for (const auto& [p, colour] : view_->mesh_points(orbit_.pose())) {
      if (p.z() <= 1) continue;
      const Eigen::Vector2d px = cam.project(p);
      cv::circle(mesh, cv::Point(int(std::lround(px.x())), int(std::lround(px.y()))), 1,
                 cv::Scalar(colour[0], colour[1], colour[2], 255), cv::FILLED);
    }
    r.add_layer_image("mesh", mesh, r3.tl());
  }
  if (entry_) {
    const std::string cls = evaluation_ && !evaluation_->values.empty()
                                ? evaluation_->values.front().safety_class
                                : std::string("unknown");
    const cv::Scalar colour = class_bgr(cls, palette);
    if (!r3.empty()) {
      const calibration::CameraModel cam = camera3d();
      const Eigen::Isometry3d pose = orbit_.pose();
      std::vector<Eigen::Vector2d> line;
      for (const Eigen::Vector3d& p : {*entry_, target_}) {
        const Eigen::Vector2d px = cam.project(pose * p);
        line.push_back(px + Eigen::Vector2d(r3.x, r3.y));
      }
      r.add_polyline_px("marks", line, colour, 3);
      r.add_polyline_px("marks", {line[0] + Eigen::Vector2d(-5, -5), line[0] + Eigen::Vector2d(5, -5),
                                  line[0] + Eigen::Vector2d(5, 5), line[0] + Eigen::Vector2d(-5, 5)},
                        cv::Scalar(255, 255, 255), 2, true);
    }
    for (int p = 1; p < kViewPanels; ++p) {
      const auto& s = slices_[size_t(p)];
      if (panels_[size_t(p)].empty() || s.view_width == 0) continue;
      const cv::Point o = slice_origin(ViewPanel(p));
      const Eigen::Vector2d a = s.pixel_of(*entry_) + Eigen::Vector2d(o.x, o.y);
      const Eigen::Vector2d b = s.pixel_of(target_) + Eigen::Vector2d(o.x, o.y);
      r.add_polyline_px("marks", {a, b}, colour, 2);
      r.add_polyline_px("marks", {a + Eigen::Vector2d(-4, -4), a + Eigen::Vector2d(4, -4),
                                  a + Eigen::Vector2d(4, 4), a + Eigen::Vector2d(-4, 4)},
                        cv::Scalar(255, 255, 255), 2, true);
    }
  }
  // Text: the help and the evaluation over the 3D panel (else over the first slice), the status.
  r.clear_layer("text");
  const cv::Rect& host = !r3.empty() ? r3 : panels_[1];
  const int width = std::min(host.width, 560);
  int y = host.y;
  const auto& o = view_->options();
  std::string hidden;
  const char* classes[4] = {"safe", "medium", "dangerous", "unknown"};
  for (size_t c = 0; c < 4; ++c)
    if (o.hidden[c]) hidden += std::string(hidden.empty() ? "" : ",") + classes[c];
  std::vector<std::string> status = {fmt::format(
      "{}  |  hidden: {}  |  {}  |  H: keys", view_->value(), hidden.empty() ? "none" : hidden,
      o.palette == planning::Palette::kColorblind ? "colour-blind palette" : "default palette")};
  if (ct_future_.valid()) status.push_back("reading the CT " + inputs_.ct_path + " ...");
  if (!ct_problem_.empty()) status.push_back("no CT: " + ct_problem_);
  if (!save_problem_.empty()) status.push_back("NOT SAVED: " + save_problem_);
  if (!saved_markup_.empty()) status.push_back("saved " + saved_markup_);
  if (!saved_picture_.empty()) status.push_back("saved " + saved_picture_);
  if (full_) {
    for (const auto& c : full_->changed_inputs) status.push_back("WARNING: " + c.message);
  }
  const cv::Mat status_panel = text_panel(status, width);
  r.add_layer_image("text", status_panel, {host.x, y}, 0);
  y += status_panel.rows;
  if (help_) {
    if (help_picture_.cols != width) help_picture_ = text_panel(viewer_key_help(), width, 0.4);
    const cv::Mat& help = help_picture_;
    if (y + help.rows <= host.y + host.height) {
      r.add_layer_image("text", help, {host.x, y}, text_revision_);
      y += help.rows;
    }
  }
  if (evaluation_ && show_evaluation_) {
    std::vector<std::string> lines = split_lines(evaluation_text());
    const int max_lines = std::max(1, (host.y + host.height - y) / 16 - 1);
    if (int(lines.size()) > max_lines) lines.resize(size_t(max_lines));
    const cv::Mat eval = text_panel(lines, width, 0.38, 140);
    const int at = std::max(y, host.y + host.height - eval.rows);
    if (at + eval.rows <= options_.height) r.add_layer_image("text", eval, {host.x, at}, 0);
  }
}

bool PlanViewer::frame(bool force) {
  take_full_plan(false);
  take_ct();
  for (const auto& e : renderer_->poll_events()) handle(e);
  if (!open_ || !renderer_->window_open()) return false;
  if (!dirty_ && !force) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
    return true;
  }
  // While the camera moves the 3D view may be drawn coarser (PlanViewOptions::resolution_scale);
  // the frame after it stopped draws it again in full.
  const Eigen::Isometry3d pose = orbit_.pose();
  moving_ = !pose.isApprox(drawn_pose_, 1e-12) && drawn_once_;
  update_layers();
  renderer_->draw();
  drawn_pose_ = pose;
  drawn_once_ = true;
  dirty_ = moving_;
  return renderer_->present();
}

cv::Mat PlanViewer::picture() {
  update_layers();
  return renderer_->render();
}

void run_view(const ViewRequest& req) {
  const auto t0 = std::chrono::steady_clock::now();
  ViewStart start = start_view_inputs(req.plan_dir, req.ct, req.labels, req.series,
                                     req.options.view.value, false);
  PlanViewer viewer(start.inputs, req.options,
                    std::async(std::launch::async, load_full_plan, req.plan_dir, req.labels,
                               req.series),
                    std::move(start.ct));
  viewer.frame(true);
  spdlog::info("view: first picture after {:.2f} s; H lists the keys, Esc quits",
               std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  while (viewer.frame()) {
    if (req.stop && req.stop->load()) break;
  }
}

}  // namespace crepuscular::pipelines
