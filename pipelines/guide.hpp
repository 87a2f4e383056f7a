// `crepuscular guide`: frames from a camera, recording or synthetic scene -> marker tracking ->
// guidance overlay -> a window (live) and/or a video file and PNG snapshots (headless). The same
// renderer and overlay code serve both targets.
//
// Latency: for every frame shown, the time from its capture (the camera's monotonic timestamp,
// when the source gives one on this machine's clock) or else from its arrival (the moment the
// source handed it over: recordings and synthetic scenes) to the moment the image is complete
// (window: after the buffer swap; headless: after the read-back). Shown on screen one frame late.
#pragma once

#include <atomic>
#include <cstdint>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "calibration/calibration_files.hpp"
#include "overlay/guidance.hpp"
#include "overlay/renderer.hpp"
#include "planning/plan_folder/plan_folder.hpp"
#include "tracking/board.hpp"
#include "tracking/tracker.hpp"

namespace crepuscular::pipelines {

struct GuideRequest {
  overlay::GuidanceSetup setup;
  std::vector<tracking::Board> boards;  // must include setup.patient_board and setup.needle_board
  std::string source;                   // open_frame_source URI
  bool window = false;                  // show a GLFW window (keys: 1-7 layers, C palette,
                                        // S snapshot, Q or Esc quit)
  std::string video;                    // overlay video to write (.mp4 or .avi); "" = none
  double video_fps = 30;                // frame rate written into the video
  std::string snapshot_dir;             // PNG snapshots go here ("" = beside the video or ".")
  // Snapshots of given frames: (frame index, file name). A dropped frame's snapshot is taken at
  // the next frame shown.
  std::vector<std::pair<int64_t, std::string>> snapshots;
  int snapshot_every = 0;  // also every N-th frame (0 = never)
  std::string log;         // per-frame CSV log ("" = none)
  // Also record the incoming frames, as received, to this recording folder ("" = none); written
  // as FOLDER.partial while guiding (replayable at any moment), renamed at the end.
  std::string record;
  // Also write the session's poses as a PLUS sequence file (.igs.mha; "" = none), for 3D
  // Slicer's Sequences module and PLUS: per frame each board's pose in the camera
  // (<Board>ToCameraTransform, INVALID while lost), the needle in the CT (NeedleToCTTransform) and
  // its class (NeedleSafety), with the frame's timestamp. Written at the end, complete or not at all.
  std::string record_poses;
  int64_t max_frames = -1;
  // OpenIGTLink server port for the operating room's tools (guide_igtl.hpp); -1: none.
  int igtl_port = -1;
  // OpenIGTLink in (guide_igtl.hpp): "igtl://HOST:PORT" or "igtl-server:PORT" gives the poses
  // instead of the camera (then without video: source empty, the virtual camera's frames).
  std::string poses;
  std::string poses_needle = "NeedleToTracker";
  std::string poses_patient = "ReferenceToTracker";  // "": the tracker's frame is the patient's
  double poses_fps = 30;
  overlay::GuidanceOptions options;
  // Tag outlines found at half resolution: 4.2x less CPU per 720p frame than full resolution
  // (bench/RESULTS.md, 2026-12-07, real cameras and real trackers), for boards whose tags are
  // 25 px or more across, as in the operating room; --decimate 1 finds smaller ones.
  tracking::TrackerOptions tracker = [] {
    tracking::TrackerOptions o;
    o.detector.decimate = 2.0;
    return o;
  }();
  // Where full-frame tag searches run (tracker.full_search_mode is not used): unset, on a worker
  // that no frame waits for when the source is live (a camera, a realtime replay), and on the
  // worker with the next frame waiting for it when frames are replayed as fast as they come (the
  // same overlay on every run).
  std::optional<tracking::FullSearchMode> full_search_mode;
  overlay::RendererOptions renderer;
  const std::atomic<bool>* stop = nullptr;  // set (e.g. by Ctrl-C) to end cleanly
};

struct GuideSummary {
  int64_t frames = 0;  // frames shown
  int64_t frames_without_image = 0;
  int64_t dropped = 0;           // frames the source skipped
  int64_t patient_tracked = 0;   // frames with the anatomy drawn
  int64_t needle_evaluated = 0;  // frames with a needle reading
  int64_t needle_safe = 0, needle_medium = 0, needle_dangerous = 0, needle_unknown = 0;
  double seconds = 0;  // wall time
  double fps = 0;      // frames shown per wall second
  double latency_median_ms = 0, latency_p95_ms = 0, latency_max_ms = 0;
  bool latency_from_capture = false;
  double track_median_ms = 0, overlay_median_ms = 0, render_median_ms = 0, render_p95_ms = 0;
  std::string gl;                                       // the OpenGL implementation
  // OpenIGTLink (with igtl_port): clients served, and publish-to-socket latency of the poses.
  int64_t igtl_connections = 0, igtl_messages = 0;
  double igtl_latency_median_ms = 0, igtl_latency_p95_ms = 0;
  std::vector<overlay::GuidanceFrameInfo> frame_infos;  // one per frame shown
  std::vector<std::string> snapshots_written;
  std::vector<std::string> snapshots_not_taken;  // "NAME (frame N)": asked for beyond the frames
  std::string video;  // the video written, if any
};

// Runs the loop until the source ends, max_frames, the window is closed, or *stop. Outputs (video,
// log, snapshots, recording) appear complete or not at all. Throws Error naming the input and the
// problem for unusable inputs; tracking loss, dropped and corrupt frames are shown and logged, and
// the loop goes on.
GuideSummary run_guide(const planning::PlanData& plan, const GuideRequest& request);

// The same with the plan folder read first (planning::load_plan with the blocking volume).
GuideSummary run_guide(const std::string& plan_dir, const GuideRequest& request);

// A snapshot request "FRAME" or "FRAME:NAME.png" (FRAME alone: frame_FRAME.png); throws Error
// naming the text otherwise.
std::pair<int64_t, std::string> parse_snapshot(const std::string& spec);

// What the needle calibration and the registration say of their own errors: the tip's per-axis
// standard deviations (else its 3D one spread alike over the axes), the spin axis's residual angle
// (else the axis follows the tip), the registration's expected TRE at the tumor (else its FRE).
planning::NeedleUncertaintySources calibration_uncertainty(
    const calibration::NeedleCalibration& needle, const calibration::RegistrationRecord& reg);

// The calibration files of a session: camera.yaml (intrinsics), registration.yaml (T_ct_patient and
// the patient board's name) and needle.yaml (tip, and the axis when spin calibration was done).
// The needle axis points from the hub toward the tip; without a spin axis it is the direction
// from the board origin to the tip. Throws Error naming the file and the problem.
overlay::GuidanceSetup read_guidance_setup(const std::string& camera_yaml,
                                           const std::string& registration_yaml,
                                           const std::string& needle_yaml);

// The per-frame log's header and one row (CSV).
std::string guide_log_header();
std::string guide_log_row(const overlay::GuidanceFrameInfo& info, double latency_ms,
                          double render_ms);

}  // namespace crepuscular::pipelines
