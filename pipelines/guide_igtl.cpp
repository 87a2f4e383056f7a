#include "pipelines/guide_igtl.hpp"

#include <fmt/format.h>
#include <spdlog/spdlog.h>

#include <filesystem>

#include "foundation/error.hpp"
#include "planning/trajectories/markups.hpp"

namespace crepuscular::pipelines {

namespace fs = std::filesystem;

std::vector<igtlink::Message> on_connect_messages(const planning::PlanData& plan,
                                                  const overlay::GuidanceSetup& setup) {
  std::vector<igtlink::Message> messages;
  Eigen::Isometry3d tip = Eigen::Isometry3d::Identity();
  tip.translation() = setup.tip_in_needle;
  messages.push_back(igtlink::transform_message("NeedleTipToNeedle", tip, 0));
  messages.push_back(igtlink::point_message("Target", "tumor centre", plan.tumor_centre, 0));
  const fs::path planned = fs::path(plan.dir) / "trajectories.mrk.json";
  std::error_code ec;
  if (fs::exists(planned, ec)) {
    try {
      const planning::LineMarkup line = planning::read_line_markup(planned.string());
      messages.push_back(igtlink::trajectory_message(
          "PlannedTrajectory", line.name.empty() ? "planned" : line.name, line.first,
          line.second, 0));
    } catch (const Error& e) {
      spdlog::warn("OpenIGTLink: no planned trajectory sent: {}", e.what());
    }
  }
  return messages;
}

GuidanceBroadcast::GuidanceBroadcast(const igtlink::Server::Options& options,
                                     const planning::PlanData& plan,
                                     const overlay::GuidanceSetup& setup)
    : setup_(setup), server_(options, on_connect_messages(plan, setup)) {}

void GuidanceBroadcast::poses(const tracking::Frame& frame, const tracking::TrackResult& track) {
  const tracking::BoardStatus* patient = nullptr;
  const tracking::BoardStatus* needle = nullptr;
  for (const auto& b : track.boards) {
    if (b.board == setup_.patient_board && b.tracked) patient = &b;
    if (b.board == setup_.needle_board && b.tracked) needle = &b;
  }
  const int64_t t = frame.timestamp_ns;
  std::vector<igtlink::Message> messages;
  if (patient) {
    messages.push_back(igtlink::transform_message("PatientToCT", setup_.T_ct_patient, t));
  } else {
    messages.push_back(igtlink::status_message("PatientToCT", igtlink::kStatusNotFound,
                                               "patient marker lost: no pose in the CT", t));
  }
  if (patient && needle) {
    const Eigen::Isometry3d T_ct_needle =
        setup_.T_ct_patient * patient->T_cam_board.inverse() * needle->T_cam_board;
    messages.push_back(igtlink::transform_message("NeedleToCT", T_ct_needle, t));
  } else {
    messages.push_back(igtlink::status_message(
        "NeedleToCT", igtlink::kStatusNotFound,
        needle ? "patient marker lost: the needle has no pose in the CT" : "needle marker lost",
        t));
  }
  server_.publish(std::move(messages));
}

void GuidanceBroadcast::safety(const overlay::GuidanceFrameInfo& info) {
  std::string text;
  if (!info.needle) {
    text = "no needle reading";
  } else {
    const planning::NeedleState& s = info.needle->state;
    text = fmt::format("{}; line integral {:.3g}", planning::needle_safety_name(s.safety),
                       s.evaluation.line_integral);
    for (const std::string& line : overlay::needle_text(s)) text += "; " + line;
  }
  server_.publish({igtlink::string_message("NeedleSafety", text, info.timestamp_ns)});
}

}  // namespace crepuscular::pipelines
