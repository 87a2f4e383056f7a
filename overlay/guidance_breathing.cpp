// Guidance over the breathing cycle: the phase from the patient board's motion, the registration
// moved with the skin, the needle in the current phase and in every phase (the gating bar, drawn
// in layer 5 "needle"), the current phase's tumor.
#include "overlay/guidance_drawing.hpp"

#include <fmt/format.h>

#include "foundation/error.hpp"

namespace crepuscular::overlay {

void GuidanceOverlay::set_breathing(std::unique_ptr<BreathingPhases> phases) {
  breathing_.reset();
  phase_guides_.clear();
  phase_estimator_.reset();
  phase_patches_.clear();
  phase_shown_ = PhaseShown{};
  tumor_centre_shown_ = plan_.tumor_centre;
  if (!phases) return;
  if (phases->plans.size() < 2 || phases->names.size() != phases->plans.size() ||
      phases->skin.displacement_mm.size() != phases->plans.size()) {
    throw Error(plan_.dir + ": breathing guidance needs at least two phases, each with its plan "
                "and the skin's motion");
  }
  for (const auto& plan : phases->plans) {
    phase_guides_.push_back(std::make_unique<planning::NeedleGuide>(*plan));
    phase_patches_.push_back(entry_patches_of(*plan));
  }
  phase_estimator_ = std::make_unique<planning::RespiratoryPhaseEstimator>(phases->skin);
  breathing_ = std::move(phases);
}

const planning::NeedleGuide* GuidanceOverlay::read_breathing(const tracking::Frame& frame,
                                                             const tracking::BoardStatus& patient,
                                                             Eigen::Isometry3d& T_ct_patient,
                                                             BreathingReading& reading) {
  const planning::SkinMotion& skin = breathing_->skin;
  // The skin's outward direction in the camera, through the registration; the board's position
  // along it is the respiratory signal.
  const Eigen::Vector3d outward_cam =
      patient.T_cam_board.linear() * setup_.T_ct_patient.linear().transpose() * skin.direction;
  reading.estimate = phase_estimator_->update(frame.timestamp_ns,
                                              patient.T_cam_board.translation().dot(outward_cam));
  phase_shown_ = PhaseShown{};
  tumor_centre_shown_ = plan_.tumor_centre;
  if (!reading.estimate.known) return guide_.get();
  const size_t k = size_t(reading.estimate.phase);
  // The board lies on the skin, which has risen from its end-exhale place, where the
  // registration holds: the board's pose in the CT moves with it.
  T_ct_patient.pretranslate(reading.estimate.displacement_mm * skin.direction);
  const planning::PlanData& phase = *breathing_->plans[k];
  tumor_centre_shown_ = phase.tumor_centre;
  phase_shown_.tumor_shift = phase.tumor_centre - breathing_->plans.front()->tumor_centre;
  // The phase's own cones and entry patches where its plan has area safety, else the plan's.
  phase_shown_.phase = phase.area ? int(k) : -1;
  return phase_guides_[k].get();
}

void GuidanceOverlay::draw_gating_bar(LayerCalls& renderer, const BreathingReading& reading) const {
  const auto& e = reading.estimate;
  const int n = int(breathing_->names.size());
  const int box = 30, gap = 4, width = std::max(n * (box + gap) + 16, 330), height = 84;
  cv::Mat bar(height, width, CV_8UC4, cv::Scalar(20, 20, 20, 170));
  const cv::Scalar white(255, 255, 255, 255), grey(150, 150, 150, 255);
  std::string title;
  if (e.known) {
    title = fmt::format("BREATHING: {} ({})", breathing_->names[size_t(e.phase)],
                        e.motion > 0 ? "inhaling" : e.motion < 0 ? "exhaling" : "at rest");
  } else {
    title = "BREATHING: phase not known yet";
  }
  cv::putText(bar, title, cv::Point(8, 20), cv::FONT_HERSHEY_SIMPLEX, 0.5, white, 1, cv::LINE_AA);
  int safe = 0;
  for (int k = 0; k < n; ++k) {
    const cv::Rect r(8 + k * (box + gap), 30, box, 24);
    const bool known = size_t(k) < reading.phase_safety.size();
    const planning::NeedleSafety s = known ? reading.phase_safety[size_t(k)] : planning::NeedleSafety::kUnknown;
    safe += known && s == planning::NeedleSafety::kSafe;
    const cv::Scalar c = safety_bgr(options_.palette, s);
    cv::rectangle(bar, r, cv::Scalar(c[0], c[1], c[2], 255), cv::FILLED);
    if (e.known && e.phase == k) cv::rectangle(bar, r, white, 3);
    cv::putText(bar, fmt::format("{}", k), cv::Point(r.x + 9, r.y + 17), cv::FONT_HERSHEY_SIMPLEX,
                0.45, cv::Scalar(20, 20, 20, 255), 1, cv::LINE_AA);
  }
  const std::string line =
      reading.phase_safety.empty()
          ? std::string("the needle's line in each phase")
          : fmt::format("line safe in {} of {} phases", safe, n);
  cv::putText(bar, line, cv::Point(8, 74), cv::FONT_HERSHEY_SIMPLEX, 0.45, grey, 1, cv::LINE_AA);
  renderer.add_layer_image("needle", bar, cv::Point(10, 150));  // below the status panel
}

}  // namespace crepuscular::overlay
