// `crepuscular track`: marker-board poses for every frame of a camera, recording or synthetic
// scene, written as a poses CSV.
#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "apps/commands.hpp"
#include "calibration/camera_model.hpp"
#include "kernels/error.hpp"
#include "tracking/board.hpp"
#include "tracking/frame_source.hpp"
#include "tracking/poses_csv.hpp"
#include "tracking/tracker.hpp"

namespace crepuscular::apps {

namespace {

struct TrackArgs {
  std::string source;
  std::string boards;
  std::string camera;
  std::string out = "poses.csv";
  double max_age_ms = 100.0;
  double decimate = 2.0;
  int threads = 2;
  int full_search_interval = 15;
  bool no_smoothing = false;
  std::string family = "tag36h11";
};

double median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

void run_track(const TrackArgs& a) {
  std::unique_ptr<tracking::FrameSource> source = tracking::open_frame_source(a.source);

  // Boards and camera: given, or the recording's own.
  std::string recording_dir;
  if (a.source.rfind("recording:", 0) == 0) {
    recording_dir = tracking::parse_source_uri(a.source).path;
  }
  std::string boards_path = a.boards;
  if (boards_path.empty() && !recording_dir.empty() &&
      std::filesystem::exists(recording_dir + "/boards.json")) {
    boards_path = recording_dir + "/boards.json";
  }
  if (boards_path.empty()) {
    throw Error("track: --boards is required (the source " + a.source + " brings no boards.json)");
  }
  const std::vector<tracking::Board> boards = tracking::read_boards(boards_path);

  calibration::CameraModel camera;
  if (!a.camera.empty()) {
    camera = calibration::CameraModel::read_yaml(a.camera);
  } else if (auto c = source->camera()) {
    camera = *c;
  } else {
    throw Error("track: --camera is required (the source " + a.source +
                " brings no camera model)");
  }

  tracking::TrackerOptions o;
  o.detector.family = a.family;
  o.detector.decimate = a.decimate;
  o.detector.threads = a.threads;
  o.max_age_ms = a.max_age_ms;
  o.full_search_interval = a.full_search_interval;
  o.smoothing = !a.no_smoothing;
  tracking::Tracker tracker(camera, boards, o);
  spdlog::info("track: {} board(s) from {}, camera {}x{} f={:.1f} px, source {}", boards.size(),
               boards_path, camera.width, camera.height, camera.fx, source->describe());

  tracking::PosesCsvWriter writer(a.out);
  std::map<std::string, int64_t> tracked, measured;
  std::map<std::string, std::vector<double>> err_mm, err_deg;
  int64_t frames = 0, dropped = 0, problems = 0;
  double busy_s = 0;
  const auto start = std::chrono::steady_clock::now();
  while (std::optional<tracking::Frame> frame = source->next()) {
    const auto t0 = std::chrono::steady_clock::now();
    const tracking::TrackResult r = tracker.process(*frame);
    busy_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    writer.write(r);
    ++frames;
    if (r.dropped > 0) {
      dropped += r.dropped;
      spdlog::warn("frame {}: {} frame(s) dropped before it", r.frame, r.dropped);
    }
    if (!r.problem.empty()) {
      ++problems;
      spdlog::warn("frame {}: {}", r.frame, r.problem);
    }
    for (const tracking::BoardStatus& s : r.boards) {
      if (s.tracked) ++tracked[s.board];
      if (s.measured) ++measured[s.board];
      for (const tracking::TruePose& t : frame->truth) {
        if (t.board != s.board || !s.tracked) continue;
        err_mm[s.board].push_back((s.T_cam_board.translation() - t.T_cam_board.translation()).norm());
        err_deg[s.board].push_back(
            Eigen::AngleAxisd(s.T_cam_board.linear().transpose() * t.T_cam_board.linear()).angle() *
            180.0 / 3.14159265358979323846);
      }
    }
    if (frames % 100 == 0) {
      spdlog::info("track: {} frames, {:.1f} ms per frame", frames, 1e3 * busy_s / double(frames));
    }
  }
  writer.finish();
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  spdlog::info("track: {} frames in {:.2f} s ({:.1f} ms per frame tracking), {} dropped, {} with a "
               "problem, {} full-frame searches; poses in {}",
               frames, wall, frames ? 1e3 * busy_s / double(frames) : 0.0, dropped, problems,
               tracker.full_searches(), a.out);
  for (const tracking::Board& b : boards) {
    spdlog::info("track: {}: tracked in {} of {} frames (measured in {})", b.name, tracked[b.name],
                 frames, measured[b.name]);
    if (!err_mm[b.name].empty()) {
      spdlog::info("track: {}: against ground truth: median {:.3f} mm, {:.3f} deg", b.name,
                   median(err_mm[b.name]), median(err_deg[b.name]));
    }
  }
}

}  // namespace

void add_track_command(CLI::App& app) {
  auto a = std::make_shared<TrackArgs>();
  CLI::App* cmd = app.add_subcommand(
      "track",
      "Find the marker boards in every frame and write their poses (T_cam_board, mm) as CSV:\n"
      "frame,timestamp_ns,board,state,tx,ty,tz,qw,qx,qy,qz,rms_px, state tracked or lost.\n"
      "A board not seen for longer than --max-age-ms is reported lost, never held longer.");
  cmd->add_option("--source", a->source,
                  "Frames: recording:DIR, synthetic:SCENE.json, synthetic:builtin or "
                  "v4l2:/dev/video0?width=1280&height=720&fps=60")
      ->required();
  cmd->add_option("--boards", a->boards,
                  "Marker boards (boards.json); default: the recording's boards.json");
  cmd->add_option("--camera", a->camera,
                  "Camera model (OpenCV YAML); default: the source's own (a recording's "
                  "camera.yaml, a synthetic scene's camera)");
  cmd->add_option("--out", a->out, "Poses CSV to write (complete or not at all)")
      ->capture_default_str();
  cmd->add_option("--max-age-ms", a->max_age_ms,
                  "Longest time a board's last pose is still reported while the board is not "
                  "seen; older poses are reported lost")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  cmd->add_option("--decimate", a->decimate,
                  "AprilTag quad detection on the image decimated by this factor (1 = full "
                  "resolution: smaller tags, slower)")
      ->capture_default_str()
      ->check(CLI::Range(1.0, 8.0));
  cmd->add_option("--threads", a->threads, "Worker threads of the AprilTag detector")
      ->capture_default_str()
      ->check(CLI::Range(1, 64));
  cmd->add_option("--full-search-every", a->full_search_interval,
                  "Search the whole frame at least every this many frames while all boards are "
                  "tracked (in between only where their poses predict the tags); 0 = every frame")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--family", a->family, "AprilTag family of the boards")->capture_default_str();
  cmd->add_flag("--no-smoothing", a->no_smoothing,
                "Report each frame's measured pose without the temporal filter");
  cmd->callback([a] { run_track(*a); });
}

}  // namespace crepuscular::apps
