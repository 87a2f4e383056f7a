// What guidance tells the operating room's tools over OpenIGTLink (igtl/server.hpp), per frame:
// right after tracking, the needle and patient board in the CT frame (TRANSFORM NeedleToCT and
// PatientToCT, or a STATUS for a marker that is lost); after the needle's evaluation, its safety
// (STRING NeedleSafety: class, line integral, structures crossed). A client that connects gets
// first NeedleTipToNeedle (the tip calibration), the target (POINT Target: the tumor centre) and
// the planned trajectory (TRAJ PlannedTrajectory: the plan's trajectories.mrk.json, first line),
// where the plan has one. In 3D Slicer's OpenIGTLinkIF the needle then moves in the CT live.
#pragma once

#include <memory>
#include <optional>

#include "igtl/server.hpp"
#include "overlay/guidance.hpp"
#include "planning/plan_folder/plan_folder.hpp"
#include "tracking/frame_source.hpp"
#include "tracking/tracker.hpp"

namespace crepuscular::pipelines {

class GuidanceBroadcast {
 public:
  GuidanceBroadcast(const igtlink::Server::Options& options, const planning::PlanData& plan,
                    const overlay::GuidanceSetup& setup);

  void poses(const tracking::Frame& frame, const tracking::TrackResult& track);
  void safety(const overlay::GuidanceFrameInfo& info);

  igtlink::Server& server() { return server_; }

 private:
  overlay::GuidanceSetup setup_;
  igtlink::Server server_;
};

// The on-connect messages: NeedleTipToNeedle, Target, and PlannedTrajectory when `plan_dir`
// holds trajectories.mrk.json.
std::vector<igtlink::Message> on_connect_messages(const planning::PlanData& plan,
                                                  const overlay::GuidanceSetup& setup);

}  // namespace crepuscular::pipelines
