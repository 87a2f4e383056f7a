#include "overlay/guidance.hpp"

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <future>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "overlay/guidance_drawing.hpp"
#include "overlay/volume_rendering.hpp"
#include "planning/imaging/ray_march.hpp"

namespace crepuscular::overlay {

namespace {

constexpr std::array<const char*, kGuidanceLayerCount> kLayerNames = {
    "rays", "volume", "entry", "tumor", "needle", "status", "target"};

}  // namespace

const char* guidance_layer_name(GuidanceLayer layer) { return kLayerNames[size_t(layer)]; }

GuidanceLayer parse_guidance_layer(const std::string& text) {
  for (int i = 0; i < kGuidanceLayerCount; ++i) {
    if (text == kLayerNames[size_t(i)] || text == std::to_string(i + 1)) {
      return static_cast<GuidanceLayer>(i);
    }
  }
  throw Error("unknown overlay layer '" + text +
              "', expected rays, volume, entry, tumor, needle, status or target (or 1-7)");
}

GuidanceOverlay::GuidanceOverlay(const planning::PlanData& plan, GuidanceSetup setup,
                                 GuidanceOptions options)
    : plan_(plan), setup_(std::move(setup)), options_(std::move(options)) {
  if (plan_.values.empty() || plan_.path_safety.empty()) {
    throw Error(plan_.dir + "/plan.json: the plan has no path safety volume to guide with");
  }
  value_ = options_.value.empty() ? plan_.values.front() : options_.value;
  if (!plan_.path_safety.count(value_) || !plan_.classes.count(value_)) {
    throw Error(plan_.dir + "/plan.json: no path safety volume '" + value_ + "' in the plan");
  }
  if (!(setup_.axis_in_needle.norm() > 0)) throw Error("guidance: the needle axis is zero");
  setup_.axis_in_needle.normalize();
  if (options_.ray_directions < 1 || options_.ray_directions > 200000) {
    throw Error("guidance: ray directions must be 1 to 200000");
  }
  guide_ = std::make_unique<planning::NeedleGuide>(plan_);
  tumor_centre_shown_ = plan_.tumor_centre;
  current_guide_ = guide_.get();
  build_tumor_surface();
  build_rays();
  build_entry_contours();
  patches_ = entry_patches_of(plan_);
  if (plan_.area) {
    const auto planned = planning::region_trajectories(*plan_.area, plan_.tumor_centre,
                                                       plan_.labels, plan_.path_safety.at(value_),
                                                       plan_.radius_mm);
    if (!planned.empty()) planned_ = planned.front();
  }
  // The box around everything the anatomy pictures show (the ring of the planned entry: 5 mm).
  Eigen::AlignedBox3d box(plan_.tumor_centre);
  for (const auto& p : tumor_surface_) box.extend(p);
  for (const Patch& patch : patches_)
    for (const auto& p : patch.points) box.extend(p);
  if (planned_) {
    box.extend(planned_->entry);
    box.extend(planned_->target);
  }
  box.min() -= Eigen::Vector3d::Constant(std::max(5.0, tumor_voxel_mm_));
  box.max() += Eigen::Vector3d::Constant(std::max(5.0, tumor_voxel_mm_));
  for (int i = 0; i < 8; ++i) {
    anatomy_box_[size_t(i)] = box.corner(static_cast<Eigen::AlignedBox3d::CornerType>(i));
  }
  // Points of everything the pictures show, for the placed pictures' error: patch points, cone
  // lines half-way to the tumor, tumor surface points, the planned trajectory (about 150 in all).
  const auto every = [](size_t n, size_t want) { return std::max<size_t>(1, n / want); };
  size_t patch_points = 0;
  for (const Patch& patch : patches_) patch_points += patch.points.size();
  anatomy_anchors_.push_back(plan_.tumor_centre);
  for (const Patch& patch : patches_) {
    const size_t step = every(patch_points, 60);
    for (size_t i = 0; i < patch.points.size(); i += step) {
      anatomy_anchors_.push_back(patch.points[i]);
      anatomy_anchors_.push_back(0.5 * (patch.points[i] + plan_.tumor_centre));
    }
  }
  for (size_t i = 0; i < tumor_surface_.size(); i += every(tumor_surface_.size(), 30)) {
    anatomy_anchors_.push_back(tumor_surface_[i]);
  }
  if (planned_) {
    anatomy_anchors_.push_back(planned_->entry);
    anatomy_anchors_.push_back(planned_->target);
  }
  // A plan without these still gets a placement only where its box moves as one.
  if (anatomy_anchors_.size() < 8) {
    anatomy_anchors_.insert(anatomy_anchors_.end(), anatomy_box_.begin(), anatomy_box_.end());
  }
  spdlog::info("guidance: {} safe or medium rays of {} ({} not drawn: they reach the unknown "
               "outside the scan), {} entry contours, {} tumor surface points",
               rays_.size(), options_.ray_directions, unknown_rays_, contours_.size(),
               tumor_surface_.size());
}

GuidanceOverlay::~GuidanceOverlay() = default;

void GuidanceOverlay::set_visible(GuidanceLayer layer, bool visible) {
  options_.visible[size_t(layer)] = visible;
}
bool GuidanceOverlay::visible(GuidanceLayer layer) const {
  return options_.visible[size_t(layer)];
}
void GuidanceOverlay::set_palette(planning::Palette palette) {
  options_.palette = palette;
  if (volume_) {
    VolumeRenderingOptions vo = volume_->options();
    vo.palette = palette;
    volume_->set_options(vo);
  }
}

bool GuidanceOverlay::inside_body(const Eigen::Vector3d& p) const {
  return planning::in_body(plan_.labels, p);
}

std::optional<Eigen::Vector3d> GuidanceOverlay::skin_exit(const Eigen::Vector3d& from,
                                                          const Eigen::Vector3d& dir) const {
  return skin_exit_in(plan_, from, dir);
}

std::optional<Eigen::Vector3d> GuidanceOverlay::skin_exit_in(const planning::PlanData& plan,
                                                             const Eigen::Vector3d& from,
                                                             const Eigen::Vector3d& dir) {
  const double step = 0.5 * plan.grid.spacing.minCoeff();
  const double reach = plan.radius_mm > 0 ? plan.radius_mm : 200.0;
  if (plan.labels.empty()) return from + dir * reach;  // no body outline: the region's edge
  const Eigen::Vector3d& centre = plan.tumor_centre;
  // None when still inside the body at the region's edge.
  const auto exit = planning::first_body_exit(
      plan.labels, from, dir, step, 2 * reach,
      [&](const Eigen::Vector3d& p) { return (p - centre).norm() <= reach; });
  if (!exit) return std::nullopt;
  return exit->last_inside;
}

GuidanceFrameInfo GuidanceOverlay::update(OverlayRenderer& renderer, const tracking::Frame& frame,
                                          const tracking::TrackResult& track,
                                          const GuidanceTiming& timing, bool frame_uploaded) {
  const calibration::CameraModel& cam = renderer.camera();
  GuidanceFrameInfo info;
  info.frame = frame.index;
  info.timestamp_ns = frame.timestamp_ns;
  info.problem = frame.problem.empty() ? track.problem : frame.problem;
  // A frame of another size (or kind) than the camera's cannot be shown under this overlay.
  const bool fits = frame.image.cols == cam.width && frame.image.rows == cam.height &&
                    frame.image.type() == CV_8UC3;
  info.image = !frame.image.empty() && fits;
  if (!frame.image.empty() && !fits && info.problem.empty()) {
    info.problem = "frame " + std::to_string(frame.index) + " is " +
                   std::to_string(frame.image.cols) + "x" + std::to_string(frame.image.rows) +
                   ", not the camera's " + std::to_string(cam.width) + "x" +
                   std::to_string(cam.height) + ": skipped";
  }

  for (int i = 0; i < kGuidanceLayerCount; ++i) {
    const char* name = kLayerNames[size_t(i)];
    renderer.clear_layer(name);
    renderer.set_layer_visible(name, options_.visible[size_t(i)]);
  }

  const tracking::BoardStatus* patient = nullptr;
  const tracking::BoardStatus* needle = nullptr;
  for (const auto& b : track.boards) {
    if (b.board == setup_.patient_board) patient = &b;
    if (b.board == setup_.needle_board) needle = &b;
  }
  info.patient_tracked = patient && patient->tracked;
  info.needle_tracked = needle && needle->tracked;
  if (info.patient_tracked) info.patient_age_ms = patient->age_ms;
  if (info.needle_tracked) info.needle_age_ms = needle->age_ms;

  using Clock = std::chrono::steady_clock;
  const auto ms_since = [](Clock::time_point t) {
    return std::chrono::duration<double, std::milli>(Clock::now() - t).count();
  };
  auto t = Clock::now();
  if (info.image) {
    if (!frame_uploaded) renderer.set_frame(frame.image);
  } else {
    // No picture: a dark frame, no overlay, and the reason.
    renderer.set_frame(cv::Mat(cam.height, cam.width, CV_8UC3, cv::Scalar(40, 40, 40)));
    info.warnings.push_back("NO CAMERA IMAGE" +
                            (info.problem.empty() ? std::string() : ": " + info.problem));
  }
  if (track.dropped > 0) {
    info.warnings.push_back(std::to_string(track.dropped) + " FRAME(S) DROPPED");
  }
  // A plan whose inputs changed since planning is shown as such on every frame.
  for (const planning::ChangedInput& c : plan_.changed_inputs) {
    info.warnings.push_back("PLAN INPUT CHANGED: " +
                            std::filesystem::path(c.path).filename().string() + " (" + c.role +
                            "), RE-PLAN");
  }

  info.upload_ms = ms_since(t);
  if (info.image && info.patient_tracked) {
    // Breathing plans: the phase, the registration moved with the skin, the phase's guide.
    Eigen::Isometry3d T_ct_patient = setup_.T_ct_patient;
    const planning::NeedleGuide* guide = guide_.get();
    if (breathing_) {
      info.breathing.emplace();
      guide = read_breathing(frame, *patient, T_ct_patient, *info.breathing);
    }
    current_guide_ = guide;
    const Eigen::Isometry3d T_cam_ct = patient->T_cam_board * T_ct_patient.inverse();
    info.anatomy_drawn = true;
    // The needle's reading and drawing run beside the anatomy's: they share only what neither
    // changes (plan, setup, options; each keeps its own pictures). Their renderer calls are
    // recorded and made here afterwards, so the layers are the same as drawn one after the other.
    struct NeedlePart {
      NeedleReading reading;
      LayerCalls calls;
      double ms = 0.0, evaluate_ms = 0.0, uncertainty_ms = 0.0;
      std::vector<planning::NeedleSafety> phase_safety;
    };
    std::future<NeedlePart> needle_part;
    if (info.needle_tracked) {
      const Eigen::Isometry3d T_cam_needle = needle->T_cam_board;
      const Eigen::Isometry3d T_ct_needle =
          T_ct_patient * patient->T_cam_board.inverse() * T_cam_needle;
      const BreathingReading* breathing = info.breathing ? &*info.breathing : nullptr;
      needle_part = std::async(std::launch::async, [this, &renderer, T_cam_ct, T_cam_needle,
                                                    T_ct_needle, T_ct_patient, patient, needle,
                                                    guide, breathing] {
        const auto t0 = Clock::now();
        NeedlePart part{NeedleReading{}, LayerCalls(renderer.camera())};
        part.reading.T_ct_needle = T_ct_needle;
        part.reading.state =
            guide->evaluate(T_ct_needle, setup_.tip_in_needle, setup_.axis_in_needle);
        part.evaluate_ms =
            std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
        const auto t1 = Clock::now();
        read_uncertainty(part.reading, *guide, T_ct_patient, *patient, *needle);
        if (breathing) {
          // The line in every phase (the gating bar), read beside the anatomy's drawing.
          for (const auto& g : phase_guides_) {
            part.phase_safety.push_back(
                part.reading.state.points_away
                    ? planning::NeedleSafety::kUnknown
                    : g->line_safety(part.reading.state.tip, part.reading.state.axis));
          }
        }
        part.uncertainty_ms = std::chrono::duration<double, std::milli>(Clock::now() - t1).count();
        if (visible(GuidanceLayer::kNeedle) || visible(GuidanceLayer::kTarget)) {
          BreathingReading shown;
          if (breathing) {
            shown.estimate = breathing->estimate;
            shown.phase_safety = part.phase_safety;
          }
          draw_needle(part.calls, T_cam_ct, T_cam_needle, part.reading,
                      breathing ? &shown : nullptr);
        }
        part.ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
        return part;
      });
    }
    t = Clock::now();
    draw_anatomy(renderer, T_cam_ct);
    info.anatomy_ms = ms_since(t);
    if (needle_part.valid()) {
      NeedlePart part = needle_part.get();  // rethrows what the needle's part threw
      part.calls.replay(renderer);
      info.needle = std::move(part.reading);
      info.needle_ms = part.ms;
      info.needle_evaluate_ms = part.evaluate_ms;
      info.uncertainty_ms = part.uncertainty_ms;
      if (info.breathing) info.breathing->phase_safety = std::move(part.phase_safety);
      info.targeting_ms = targeting_ms_;
      info.needle_panel_ms = needle_panel_ms_;
    }
  }
  if (info.image && !info.patient_tracked) {
    info.warnings.push_back("PATIENT MARKER LOST: NO GUIDANCE SHOWN");
  } else if (info.image && !info.needle_tracked) {
    info.warnings.push_back("NEEDLE MARKER LOST");
  }
  // Warnings always show: hiding the status layer hides only its panel.
  t = Clock::now();
  draw_status(renderer, info, timing);
  info.status_ms = ms_since(t);
  renderer.set_layer_visible("status", true);
  return info;
}

}  // namespace crepuscular::overlay
