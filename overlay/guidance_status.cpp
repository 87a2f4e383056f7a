// Layer 6 "status": the tracking state of both boards, frame rate, latency, and the warnings.
#include "overlay/guidance_drawing.hpp"

#include <fmt/format.h>

namespace crepuscular::overlay {

void GuidanceOverlay::draw_status(OverlayRenderer& renderer, const GuidanceFrameInfo& info,
                                  const GuidanceTiming& timing) {
  const auto& cam = renderer.camera();
  const cv::Size frame(cam.width, cam.height);
  const cv::Scalar ok(120, 230, 120), bad(60, 60, 255);
  std::vector<TextLine> lines;
  auto board_line = [&](const char* name, bool tracked, double age) {
    lines.push_back({tracked ? fmt::format("{} marker: tracked ({:.0f} ms)", name, age)
                             : fmt::format("{} marker: LOST", name),
                     tracked ? ok : bad});
  };
  board_line("patient", info.patient_tracked, info.patient_age_ms);
  board_line("needle", info.needle_tracked, info.needle_age_ms);
  lines.push_back({fmt::format("{:.1f} fps, frame {}", timing.fps, (long long)info.frame)});
  if (timing.latency_ms >= 0) {
    lines.push_back({fmt::format("latency {:.0f} ms ({})", timing.latency_ms,
                                 timing.latency_from_capture ? "from capture"
                                                             : "from frame arrival")});
  }
  if (info.breathing) {
    const planning::PhaseEstimate& e = info.breathing->estimate;
    lines.push_back({e.known ? fmt::format("breathing: {} ({:.1f} mm above end-exhale)",
                                           breathing_->names[size_t(e.phase)], e.displacement_mm)
                             : e.reason});
  }
  if (visible(GuidanceLayer::kStatus)) {
    cv::Point origin;
    const cv::Mat panel = text_panel(lines, cv::Point(10, 10), false, frame, &origin);
    renderer.add_layer_image("status", panel, origin);
  }
  // Warnings: large, red, at the top centre.
  int y = 20;
  for (const auto& w : info.warnings) {
    int base = 0;
    const cv::Size s = cv::getTextSize(w, cv::FONT_HERSHEY_SIMPLEX, 1.0, 2, &base);
    const cv::Rect box =
        cv::Rect(std::max(0, (cam.width - s.width) / 2 - 12), y, s.width + 24, s.height + base + 16) &
        cv::Rect(0, 0, cam.width, cam.height);
    if (box.empty()) break;
    cv::Mat banner(box.size(), CV_8UC4, cv::Scalar(0, 0, 160, 200));
    cv::putText(banner, w, cv::Point(12, s.height + 8), cv::FONT_HERSHEY_SIMPLEX, 1.0,
                cv::Scalar(255, 255, 255, 255), 2, cv::LINE_AA);
    renderer.add_layer_image("status", banner, box.tl());
    y += box.height + 8;
  }
}

}  // namespace crepuscular::overlay
