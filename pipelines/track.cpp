// The track job: frames -> Tracker -> poses CSV, with counts and ground-truth errors.
#include "pipelines/track.hpp"

#include <algorithm>
#include <chrono>
#include <memory>
#include <set>
#include <vector>

#include "foundation/log.hpp"
#include "pipelines/session_inputs.hpp"
#include "tracking/board.hpp"
#include "tracking/details_csv.hpp"
#include "tracking/detector.hpp"
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

// Says when and why a board is lost: a warning when a board goes from measured to not measured,
// or its reason changes, and a note at the end for boards never measured. Where no tag of a
// board's family was found, the other families are tried on that frame (at most every 30 frames)
// so that a board described in the wrong family says so.
class LossReporter {
 public:
  explicit LossReporter(const std::vector<tracking::Board>& boards)
      : boards_(boards), state_(boards.size()) {}

  void report(const tracking::Frame& frame, tracking::TrackResult& r) {
    for (size_t b = 0; b < r.boards.size() && b < boards_.size(); ++b) {
      tracking::BoardStatus& s = r.boards[b];
      if (s.measured) {
        state_[b].clear();
        continue;
      }
      if (s.problem.rfind("no tag of the board's family", 0) == 0) {
        s.problem += other_families(frame, boards_[b].family);
      }
      if (s.problem == state_[b]) continue;
      state_[b] = s.problem;
      last_problem_[s.board] = s.problem;
      spdlog::warn("frame {}: {}: not measured: {}", r.frame, s.board, s.problem);
    }
  }

  const std::map<std::string, std::string>& last_problem() const { return last_problem_; }

 private:
  // "; tags of family F seen (ids ...): is the board's family right?" when the frame shows tags of
  // a family other than `family`; the tags of the last search within 30 frames are reused.
  std::string other_families(const tracking::Frame& frame, const std::string& family) {
    if (frame.image.empty()) return "";
    if (probed_ < 0 || frame.index - probed_ >= 30) {
      probed_ = frame.index;
      seen_.clear();
      for (const auto& d : tracking::detect_families(frame.image, tracking::tag_family_names())) {
        seen_[d.family].insert(d.id);
      }
    }
    std::string text;
    for (const auto& [other, ids] : seen_) {
      if (other == family) continue;
      std::string list;
      for (int id : ids) list += (list.empty() ? "" : " ") + std::to_string(id);
      text += "; tags of family " + other + " seen (ids " + list + ")";
    }
    return text.empty() ? text : text + ": is the board's family right?";
  }

  const std::vector<tracking::Board>& boards_;
  std::vector<std::string> state_;  // per board: the reason last reported; empty while measured
  std::map<std::string, std::string> last_problem_;
  int64_t probed_ = -1;
  std::map<std::string, std::set<int>> seen_;  // family -> ids of the last search
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
  o.detector = a.detector;
  o.max_age_ms = a.max_age_ms;
  o.full_search_interval = a.full_search_interval;
  o.smoothing = a.smoothing;
  tracking::Tracker tracker(camera, boards, o);
  spdlog::info("track: {} board(s) from {}, camera {}x{} f={:.1f} px, source {}", boards.size(),
               boards_path, camera.width, camera.height, camera.fx, source->describe());
  spdlog::info("track: tag detection at decimate {}, edge refinement {}, sharpening {}, blur {} px",
               a.detector.decimate, a.detector.refine_edges ? "on" : "off",
               a.detector.sharpening, a.detector.blur_sigma);

  tracking::PosesCsvWriter writer(a.out);
  std::unique_ptr<tracking::DetailsCsvWriter> details;
  if (!a.details.empty()) details = std::make_unique<tracking::DetailsCsvWriter>(a.details);
  LossReporter losses(boards);
  TrackSummary s;
  TruthErrors errors;
  double busy_s = 0;
  const auto start = Clock::now();
  while (std::optional<tracking::Frame> frame = source->next()) {
    const auto t0 = Clock::now();
    tracking::TrackResult r = tracker.process(*frame);
    busy_s += std::chrono::duration<double>(Clock::now() - t0).count();
    writer.write(r);
    losses.report(*frame, r);
    if (details) details->write(r, tracker.boards());
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
  if (details) details->finish();
  s.last_problem = losses.last_problem();
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
