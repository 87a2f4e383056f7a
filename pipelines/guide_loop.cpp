#include "pipelines/guide_loop.hpp"

#include "pipelines/guide_breathing.hpp"

#include <time.h>

#include <algorithm>
#include <future>

#include "foundation/error.hpp"
#include "pipelines/guide_igtl.hpp"

namespace crepuscular::pipelines {

using namespace overlay;  // NOLINT: the pipeline drives the overlay module throughout

namespace {

double ms_between(GuideLoop::Clock::time_point a, GuideLoop::Clock::time_point b) {
  return std::chrono::duration<double, std::milli>(b - a).count();
}

int64_t monotonic_now_ns() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return int64_t(ts.tv_sec) * 1000000000LL + ts.tv_nsec;
}

const std::vector<tracking::Board>& checked(const std::vector<tracking::Board>& boards,
                                            const GuidanceSetup& setup) {
  bool has_patient = false, has_needle = false;
  for (const auto& b : boards) {
    has_patient |= b.name == setup.patient_board;
    has_needle |= b.name == setup.needle_board;
  }
  if (!has_patient || !has_needle) {
    throw Error("guide: the boards must include the patient board '" + setup.patient_board +
                "' and the needle board '" + setup.needle_board + "'");
  }
  return boards;
}

}  // namespace

double percentile(std::vector<double> v, double p) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  const size_t i = std::min(v.size() - 1, size_t(p / 100.0 * double(v.size() - 1) + 0.5));
  return v[i];
}

GuideLoop::GuideLoop(const planning::PlanData& plan, const GuidanceSetup& setup,
                     const std::vector<tracking::Board>& boards, const GuidanceOptions& options,
                     const tracking::TrackerOptions& tracker, const RendererOptions& renderer)
    : tracker_(setup.camera, checked(boards, setup), tracker),
      overlay_(plan, setup, options),
      renderer_(setup.camera, renderer) {
  overlay_.set_breathing(load_breathing_phases(plan, setup.T_ct_patient));
}

GuideFrameResult GuideLoop::process(const tracking::Frame& frame, Clock::time_point arrival,
                                    bool want_image) {
  GuideFrameResult r;
  // A camera timestamp on this machine's monotonic clock (V4L2) measures from capture; other
  // sources (recordings, synthetic scenes) from the moment the frame was handed over.
  const int64_t capture_offset_ns =
      monotonic_now_ns() - frame.timestamp_ns - int64_t(ms_between(arrival, Clock::now()) * 1e6);
  r.latency_from_capture = capture_offset_ns >= 0 && capture_offset_ns < 2000000000LL;

  // Tracking runs on another thread while this one uploads the video frame to the GPU (the
  // upload needs no pose; the OpenGL context stays on this thread).
  std::future<tracking::TrackResult> tracking =
      pose_input_ && virtual_camera_
          ? std::async(std::launch::deferred, [this, &frame] { return pose_input_->track(frame); })
          : std::async(std::launch::async, [this, &frame] {
              tracking::TrackResult r = tracker_.process(frame);
              if (pose_input_) pose_input_->replace_needle(r);  // over the video
              return r;
            });
  // A frame of another size than the camera's is no picture of this camera: not shown (the
  // overlay says so), never an end of the session.
  const calibration::CameraModel& camera = renderer_.camera();
  const bool uploaded = !frame.image.empty() && frame.image.cols == camera.width &&
                        frame.image.rows == camera.height && frame.image.type() == CV_8UC3;
  if (uploaded) renderer_.set_frame(frame.image);
  const tracking::TrackResult track = tracking.get();
  if (broadcast_) broadcast_->poses(frame, track);
  r.dropped = track.dropped;
  r.boards = track.boards;
  const auto tracked = Clock::now();
  timing_.track_ms = ms_between(arrival, tracked);
  r.info = overlay_.update(renderer_, frame, track, timing_, uploaded);
  if (broadcast_) broadcast_->safety(r.info);
  const auto overlaid = Clock::now();
  if (want_image) {
    r.image = renderer_.render();
  } else {
    renderer_.draw();
    if (!renderer_.visible()) renderer_.finish();
  }
  if (renderer_.visible() && !renderer_.present()) window_closed_ = true;
  const auto done = Clock::now();

  r.track_ms = timing_.track_ms;
  r.overlay_ms = ms_between(tracked, overlaid);
  r.render_ms = ms_between(overlaid, done);
  r.latency_ms =
      ms_between(arrival, done) + (r.latency_from_capture ? double(capture_offset_ns) * 1e-6 : 0.0);
  // Shown on the next frame: this one's image is already finished.
  timing_.latency_ms = r.latency_ms;
  timing_.latency_from_capture = r.latency_from_capture;
  shown_.push_back(done);
  while (shown_.size() > 1 && shown_.back() - shown_.front() > std::chrono::seconds(1)) {
    shown_.pop_front();
  }
  timing_.fps =
      shown_.size() > 1
          ? double(shown_.size() - 1) /
                std::chrono::duration<double>(shown_.back() - shown_.front()).count()
          : 0.0;
  return r;
}

}  // namespace crepuscular::pipelines
