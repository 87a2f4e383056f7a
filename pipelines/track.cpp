// The track job: frames -> Tracker -> poses CSV, with counts and ground-truth errors.
#include "pipelines/track.hpp"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <memory>
#include <vector>

#include "pipelines/session_inputs.hpp"
#include "tracking/board.hpp"
#include "tracking/frame_source.hpp"
#include "tracking/poses_csv.hpp"
#include "tracking/tracker.hpp"

namespace crepuscular::pipelines {

namespace {

using Clock = std::chrono::steady_clock;

double median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

// Errors of the tracked poses against a synthetic frame's ground truth, per board.
struct TruthErrors {
  std::map<std::string, std::vector<double>> mm, deg;

  void add(const tracking::Frame& frame, const tracking::BoardStatus& s) {
    for (const tracking::TruePose& t : frame.truth) {
      if (t.board != s.board || !s.tracked) continue;
      mm[s.board].push_back((s.T_cam_board.translation() - t.T_cam_board.translation()).norm());
      deg[s.board].push_back(
          Eigen::AngleAxisd(s.T_cam_board.linear().transpose() * t.T_cam_board.linear()).angle() *
          180.0 / 3.14159265358979323846);
    }
  }
};

void log_summary(const TrackSummary& s, const std::vector<tracking::Board>& boards,
                 int64_t full_searches, const std::string& out) {
  spdlog::info(
      "track: {} frames in {:.2f} s ({:.1f} ms per frame tracking), {} dropped, {} with a "
      "problem, {} full-frame searches; poses in {}",
      s.frames, s.seconds, s.tracking_ms, s.dropped, s.problems, full_searches, out);
  for (const tracking::Board& b : boards) {
    const auto count = [&](const std::map<std::string, int64_t>& m) {
      const auto it = m.find(b.name);
      return it == m.end() ? int64_t(0) : it->second;
    };
    spdlog::info("track: {}: tracked in {} of {} frames (measured in {})", b.name, count(s.tracked),
                 s.frames, count(s.measured));
    if (s.median_error_mm.count(b.name)) {
      spdlog::info("track: {}: against ground truth: median {:.3f} mm, {:.3f} deg", b.name,
                   s.median_error_mm.at(b.name), s.median_error_deg.at(b.name));
    }
  }
}

}  // namespace

TrackSummary run_track(const TrackRequest& a) {
  std::unique_ptr<tracking::FrameSource> source = tracking::open_frame_source(a.source);
  const std::string boards_path = session_boards_file(a.boards, a.source, "track");
  const std::vector<tracking::Board> boards = tracking::read_boards(boards_path);
  const calibration::CameraModel camera = session_camera(a.camera, *source, "track");

  tracking::TrackerOptions o;
  o.detector.family = a.family.empty() ? boards.front().family : a.family;
  o.detector.decimate = a.decimate;
  o.detector.threads = a.threads;
  o.max_age_ms = a.max_age_ms;
  o.full_search_interval = a.full_search_interval;
  o.smoothing = a.smoothing;
  tracking::Tracker tracker(camera, boards, o);
  spdlog::info("track: {} board(s) from {}, camera {}x{} f={:.1f} px, source {}", boards.size(),
               boards_path, camera.width, camera.height, camera.fx, source->describe());

  tracking::PosesCsvWriter writer(a.out);
  TrackSummary s;
  TruthErrors errors;
  double busy_s = 0;
  const auto start = Clock::now();
  while (std::optional<tracking::Frame> frame = source->next()) {
    const auto t0 = Clock::now();
    const tracking::TrackResult r = tracker.process(*frame);
    busy_s += std::chrono::duration<double>(Clock::now() - t0).count();
    writer.write(r);
    ++s.frames;
    if (r.dropped > 0) {
      s.dropped += r.dropped;
      spdlog::warn("frame {}: {} frame(s) dropped before it", r.frame, r.dropped);
    }
    if (!r.problem.empty()) {
      ++s.problems;
      spdlog::warn("frame {}: {}", r.frame, r.problem);
    }
    for (const tracking::BoardStatus& b : r.boards) {
      if (b.tracked) ++s.tracked[b.board];
      if (b.measured) ++s.measured[b.board];
      errors.add(*frame, b);
    }
    if (s.frames % 100 == 0) {
      spdlog::info("track: {} frames, {:.1f} ms per frame", s.frames,
                   1e3 * busy_s / double(s.frames));
    }
  }
  writer.finish();
  s.seconds = std::chrono::duration<double>(Clock::now() - start).count();
  s.tracking_ms = s.frames ? 1e3 * busy_s / double(s.frames) : 0.0;
  for (const auto& [board, mm] : errors.mm) {
    s.median_error_mm[board] = median(mm);
    s.median_error_deg[board] = median(errors.deg[board]);
  }
  log_summary(s, boards, tracker.full_searches(), a.out);
  return s;
}

}  // namespace crepuscular::pipelines
