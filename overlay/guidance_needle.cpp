// Layer 5 "needle": the tracked needle, its line to the tumor coloured by its live safety, where it
// enters the skin, the nearest safe direction and the text panel.
#include "overlay/guidance_drawing.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <future>

#include <fmt/format.h>

#include "planning/imaging/ray_march.hpp"

namespace crepuscular::overlay {

std::vector<std::string> needle_text(const planning::NeedleState& s) {
  std::vector<std::string> out;
  for (const auto& hit : s.evaluation.structures) {
    if (hit.blocking_per_mm <= 0) continue;
    out.push_back(fmt::format("{} ({}) at {:.0f} mm, {:.1f} mm long", hit.name,
                              hit.level_name.empty() ? "?" : hit.level_name, hit.depth_mm,
                              hit.length_mm));
  }
  return out;
}

std::optional<Eigen::Vector3d> GuidanceOverlay::needle_skin_entry(
    const planning::NeedleState& s) const {
  if (s.points_away) return std::nullopt;
  if (s.tip_in_body) return s.line_start;
  return planning::body_entry_along(plan_.labels, s.tip, s.axis, s.along_axis_mm);
}

void GuidanceOverlay::read_uncertainty(NeedleReading& reading, const planning::NeedleGuide& guide,
                                       const Eigen::Isometry3d& T_ct_patient,
                                       const tracking::BoardStatus& patient,
                                       const tracking::BoardStatus& needle) const {
  planning::NeedleUncertaintySources sources = setup_.uncertainty;
  reading.pose_covariance_known = patient.covariance_valid && needle.covariance_valid;
  if (patient.covariance_valid) sources.patient_pose = patient.pose_covariance;
  if (needle.covariance_valid) sources.needle_pose = needle.pose_covariance;
  reading.uncertainty = planning::needle_line_uncertainty(
      T_ct_patient, patient.T_cam_board, needle.T_cam_board, setup_.tip_in_needle,
      setup_.axis_in_needle, guide.plan().tumor_centre, sources);
  reading.region.nominal = reading.region.worst = reading.state.safety;
  if (!reading.state.points_away && reading.uncertainty.valid) {
    reading.region = planning::region_safety(guide, reading.uncertainty, reading.state.safety);
  }
}

void GuidanceOverlay::draw_needle(LayerCalls& renderer, const Eigen::Isometry3d& T_cam_ct,
                                  const Eigen::Isometry3d& T_cam_needle,
                                  const NeedleReading& reading,
                                  const BreathingReading* breathing) {
  const auto& s = reading.state;
  const auto palette = options_.palette;
  const cv::Scalar colour = safety_bgr(palette, s.safety);
  const Eigen::Vector3d tip = T_cam_needle * setup_.tip_in_needle;
  // The shaft: from the hub (the board origin's foot on the axis) to the tip.
  const double length = setup_.tip_in_needle.dot(setup_.axis_in_needle);
  const Eigen::Vector3d hub = T_cam_needle * (setup_.tip_in_needle - length * setup_.axis_in_needle);
  // Drawn first, under the needle and its extension.
  const std::optional<Eigen::Vector3d> entry = needle_skin_entry(s);
  if (entry) {
    // Where the needle's line enters the skin: a ring of 4 mm radius across the needle.
    const Eigen::Vector3d e1 = s.axis.unitOrthogonal(), e2 = s.axis.cross(e1);
    Polyline ring;
    for (int k = 0; k < 32; ++k) {
      const double t = 2 * M_PI * k / 32;
      ring.points_cam.push_back(T_cam_ct * (*entry + 4.0 * (std::cos(t) * e1 + std::sin(t) * e2)));
    }
    ring.closed = true;
    ring.colour = cv::Scalar(30, 30, 30);  // a dark rim, so that the ring reads on the patches
    ring.width_px = 5;
    renderer.add_polyline("needle", ring);
    ring.colour = colour;
    ring.width_px = 2.5;
    renderer.add_polyline("needle", ring);
  }
  Polyline shaft;
  shaft.points_cam = {hub, tip};
  shaft.colour = cv::Scalar(255, 255, 255);
  shaft.width_px = 3;
  renderer.add_polyline("needle", shaft);
  if (!s.points_away) {
    Polyline ext;
    ext.points_cam = {tip, T_cam_ct * s.target};
    ext.colour = colour;
    ext.width_px = 3;
    renderer.add_polyline("needle", ext);
  }
  if (s.nearest_safe_vertex >= 0 && s.safety != planning::NeedleSafety::kSafe) {
    // The nearest safe direction, from the tumor out: where to turn the needle.
    Polyline dir;
    const Eigen::Vector3d c = plan_.tumor_centre;
    for (int k = 0; k < 12; k += 2) {
      Polyline dash;
      dash.points_cam = {T_cam_ct * (c + (10.0 + 8.0 * k) * s.nearest_safe_direction),
                         T_cam_ct * (c + (10.0 + 8.0 * (k + 1)) * s.nearest_safe_direction)};
      dash.colour = class_bgr(palette, planning::SafetyClass::kSafe);
      dash.width_px = 2;
      renderer.add_polyline("needle", dash);
    }
  }

  // Text panel, bottom left.
  std::vector<TextLine> lines;
  std::string headline = std::string("NEEDLE PATH: ") + planning::needle_safety_name(s.safety);
  std::transform(headline.begin(), headline.end(), headline.begin(), ::toupper);
  if (breathing && breathing->estimate.known) {
    headline += " IN " + breathing_->names[size_t(breathing->estimate.phase)];
  } else if (breathing) {
    headline += " (ALL PHASES)";
  }
  if (breathing) draw_gating_bar(renderer, *breathing);
  lines.push_back({headline, colour, 0.8});
  const planning::LineUncertainty& u = reading.uncertainty;
  if (reading.region.uncertain()) {
    // A line of the 95 % region is worse than the needle's own: say which, and how far it reaches.
    std::string worst = planning::needle_safety_name(reading.region.worst);
    std::transform(worst.begin(), worst.end(), worst.begin(), ::toupper);
    lines.push_back({fmt::format("UNCERTAIN: {} within {:.1f} mm (95 %)", worst, u.major95_mm),
                     safety_bgr(palette, reading.region.worst), 0.7});
  }
  if (!s.points_away && u.valid) {
    lines.push_back({fmt::format("uncertainty at the tumor {:.1f} x {:.1f} mm (95 %)", u.major95_mm,
                                 u.minor95_mm)});
    if (!reading.pose_covariance_known) lines.push_back({"(the tracker gave no pose errors)"});
  }
  if (s.points_away) {
    lines.push_back({"needle points away from the tumor"});
  } else {
    lines.push_back({fmt::format("line integral {:.2f} (insignificant <= {:.2f})",
                                 s.evaluation.line_integral, s.eps)});
    for (const auto& t : needle_text(s)) lines.push_back({"crosses " + t, colour, 0.5});
    lines.push_back({fmt::format("tip to target {:.1f} mm, passes {:.1f} mm from the centre",
                                 s.tip_to_centroid_mm, s.miss_distance_mm)});
  }
  // Deviations: between the skin entries (mm) and the directions (degrees).
  if (std::isfinite(s.angle_to_safe_deg)) {
    const Eigen::Vector3d dir = s.nearest_safe_direction;
    const auto safe_entry = skin_exit(plan_.tumor_centre, dir);
    if (entry && safe_entry) {
      const planning::Deviation d = planning::line_deviation(*entry, s.axis, *safe_entry, -dir);
      lines.push_back({fmt::format("to nearest safe direction: {:.0f} mm at the skin, {:.1f} deg",
                                   d.entry_mm, s.angle_to_safe_deg)});
    } else {
      lines.push_back({fmt::format("to nearest safe direction: {:.1f} deg", s.angle_to_safe_deg)});
    }
  }
  if (planned_ && entry && !s.points_away) {
    const planning::Deviation d = planning::line_deviation(
        *entry, s.axis, planned_->entry, (planned_->target - planned_->entry).normalized());
    lines.push_back({fmt::format("to planned trajectory: {:.0f} mm at the skin, {:.1f} deg",
                                 d.entry_mm, d.angle_deg)});
  }

  // The panel's text is drawn beside the targeting view (layers keep their own order).
  const cv::Size frame(renderer.camera().width, renderer.camera().height);
  std::future<Picture> panel =
      std::async(std::launch::async, [this, lines = std::move(lines), frame] {
        const auto t0 = std::chrono::steady_clock::now();
        Picture p;
        p.bgra = text_panel(lines, cv::Point(10, frame.height - 10), true, frame, &p.origin);
        needle_panel_ms_ = std::chrono::duration<double, std::milli>(
                               std::chrono::steady_clock::now() - t0).count();
        return p;
      });
  draw_targeting(renderer, T_cam_ct, reading);
  const Picture p = panel.get();
  renderer.add_layer_image("needle", p.bgra, p.origin);
}

}  // namespace crepuscular::overlay
