// One frame of guidance: tracking, the overlay's layers, drawing (and read-back or display), with
// the time each step took and the latency. Shared by `crepuscular guide` (pipelines/guide.hpp) and
// the latency benchmark; it needs no video or image codecs.
#pragma once

#include <chrono>
#include <deque>
#include <memory>
#include <vector>

#include <opencv2/core.hpp>

#include "overlay/guidance.hpp"
#include "overlay/renderer.hpp"
#include "tracking/board.hpp"
#include "tracking/frame_source.hpp"
#include "tracking/tracker.hpp"

namespace crepuscular::pipelines {

class GuidanceBroadcast;
class PoseInput;

struct GuideFrameResult {
  overlay::GuidanceFrameInfo info;
  cv::Mat image;  // the overlay image (when asked for), CV_8UC3 BGR
  // From arrival (or capture, see latency_from_capture) to the finished image (read back, or
  // swapped to the window).
  double latency_ms = 0;
  bool latency_from_capture = false;
  // track_ms: tracking, with the video frame's upload to the GPU done meanwhile on this thread.
  double track_ms = 0, overlay_ms = 0, render_ms = 0;
  int64_t dropped = 0;  // frames the source skipped before this one
  std::vector<tracking::BoardStatus> boards;  // the frame's tracking, board by board
};

class GuideLoop {
 public:
  using Clock = std::chrono::steady_clock;
  // Throws Error when the boards lack the setup's patient or needle board, or no OpenGL context
  // can be made.
  GuideLoop(const planning::PlanData& plan, const overlay::GuidanceSetup& setup,
            const std::vector<tracking::Board>& boards, const overlay::GuidanceOptions& options,
            const tracking::TrackerOptions& tracker, const overlay::RendererOptions& renderer);

  // Processes a frame that the source handed over at `arrival`. want_image: read the image back
  // (video, snapshots); a visible renderer also shows it in its window.
  GuideFrameResult process(const tracking::Frame& frame, Clock::time_point arrival,
                           bool want_image);

  overlay::GuidanceOverlay& overlay() { return overlay_; }
  overlay::OverlayRenderer& renderer() { return renderer_; }
  bool window_closed() const { return window_closed_; }
  // OpenIGTLink out (guide_igtl.hpp): poses right after tracking, safety after the overlay.
  void set_broadcast(GuidanceBroadcast* broadcast) { broadcast_ = broadcast; }
  // OpenIGTLink in (guide_igtl.hpp): the boards' poses come from a tracking server instead of
  // the camera; frames are then the virtual camera's (no video).
  void set_pose_input(const PoseInput* input, bool virtual_camera) {
    pose_input_ = input;
    virtual_camera_ = virtual_camera;
  }

 private:
  tracking::Tracker tracker_;
  overlay::GuidanceOverlay overlay_;
  overlay::OverlayRenderer renderer_;
  overlay::GuidanceTiming timing_;
  std::deque<Clock::time_point> shown_;
  bool window_closed_ = false;
  GuidanceBroadcast* broadcast_ = nullptr;
  const PoseInput* pose_input_ = nullptr;
  bool virtual_camera_ = false;
};

// Nearest-rank percentile (p in 0..100) of the values; 0 for none.
double percentile(std::vector<double> values, double p);

}  // namespace crepuscular::pipelines
