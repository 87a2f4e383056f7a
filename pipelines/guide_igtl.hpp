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

#include "igtl/pose_receiver.hpp"
#include "igtl/server.hpp"
#include "overlay/guidance.hpp"
#include "recordings/plus_sequence.hpp"
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

// OpenIGTLink in: the boards' poses from a tracking server (PLUS, ...), as the camera tracker
// would report them. Without video, seen by a virtual camera 400 mm anterior of the tumor centre
// looking posterior (patient's left on the right, head up). Over the video, the camera tracks
// the patient board and the patient reference is that board (or the tracker's frame is, with
// patient ""): the needle is placed by T_cam_needle = T_cam_patient T_tracker_patient^-1
// T_tracker_needle, so no separate tracker-to-camera calibration is needed.
//   needle: the needle tool's device name (e.g. NeedleToTracker); patient: the patient
//   reference's (e.g. ReferenceToTracker), "" when the tracker's frame is the patient board's.
// A pose older than max_age_ms (by its arrival here) is lost, as for the camera.
// `plus:FILE.igs.mha` instead of an OpenIGTLink address replays a PLUS sequence file: the
// virtual camera shows one frame per sequence frame (plus_frames_source), whose transforms are
// that frame's poses; an INVALID transform is a lost tool.
class PoseInput {
 public:
  PoseInput(const std::string& uri, std::string needle, std::string patient, double max_age_ms,
            const overlay::GuidanceSetup& setup, const Eigen::Vector3d& tumor_centre);

  tracking::TrackResult track(const tracking::Frame& frame) const;
  // Over the video: the camera's result with its needle replaced by the tracker's.
  void replace_needle(tracking::TrackResult& camera) const;
  // Over OpenIGTLink; null when replaying a sequence file.
  igtlink::PoseReceiver* receiver() { return receiver_.get(); }
  // The sequence file replayed; null over OpenIGTLink.
  const recordings::PlusSequence* sequence() const { return sequence_.get(); }
  // The virtual camera's view of the CT (LPS mm to camera).
  const Eigen::Isometry3d& T_cam_ct() const { return T_cam_ct_; }

 private:
  // The latest pose of `device` and its age (by its arrival here); true when not older than
  // max_age_ms.
  // From a sequence file: the pose in the frame of that index.
  bool current_pose(const std::string& device, int64_t frame, Eigen::Isometry3d* T,
                    double* age_ms) const;
  std::string where() const;

  std::unique_ptr<igtlink::PoseReceiver> receiver_;
  std::unique_ptr<recordings::PlusSequence> sequence_;
  std::string sequence_path_;
  std::string needle_, patient_;
  double max_age_ms_;
  overlay::GuidanceSetup setup_;
  Eigen::Isometry3d T_cam_ct_;
};

// The virtual camera's frames for a PLUS sequence file's poses: one per sequence frame, stamped
// with the sequence's timestamps (the frame rate where a frame has none), paced as recorded when
// `realtime`, else as fast as they are taken.
std::unique_ptr<tracking::FrameSource> plus_frames_source(const calibration::CameraModel& camera,
                                                          const recordings::PlusSequence& sequence,
                                                          double fps, bool realtime);
// "plus:FILE[?realtime=1]": the file and whether to pace it; nullopt for other addresses.
std::optional<std::pair<std::string, bool>> plus_poses_address(const std::string& uri);

// Frames of the virtual camera: a dark picture at `fps`, paced in real time.
std::unique_ptr<tracking::FrameSource> virtual_camera_source(const calibration::CameraModel& camera,
                                                             double fps);

// The on-connect messages: NeedleTipToNeedle, Target, and PlannedTrajectory when `plan_dir`
// holds trajectories.mrk.json.
std::vector<igtlink::Message> on_connect_messages(const planning::PlanData& plan,
                                                  const overlay::GuidanceSetup& setup);

}  // namespace crepuscular::pipelines
