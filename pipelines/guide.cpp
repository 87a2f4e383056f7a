// The guide job: frames -> GuideLoop (tracking, overlay, drawing) -> window, video, snapshots,
// per-frame log and a recording of the frames; timing statistics in the summary.
#include "pipelines/guide.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <cctype>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <memory>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/videoio.hpp>
#include <optional>
#include <sstream>

#include "calibration/calibration_files.hpp"
#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "foundation/output_files.hpp"
#include "pipelines/guide_loop.hpp"
#include "pipelines/guide_igtl.hpp"
#include "recordings/plus_sequence.hpp"
#include "tracking/board.hpp"
#include "tracking/frame_source.hpp"

namespace crepuscular::pipelines {

using namespace overlay;  // NOLINT: the pipeline drives the overlay module throughout

namespace fs = std::filesystem;

namespace {

using Clock = std::chrono::steady_clock;

std::string csv_field(std::string s) {
  if (s.find_first_of(",\"\n") == std::string::npos) return s;
  std::string out = "\"";
  for (char c : s) {
    if (c == '"') out += '"';
    out += c == '\n' ? ' ' : c;
  }
  return out + "\"";
}

// Writes an image through a temporary sibling; throws Error naming the path on failure.
void write_png(const std::string& path, const cv::Mat& image) {
  write_file_atomically(path, [&](const std::string& temporary) {
    if (!cv::imwrite(temporary, image)) throw Error(path + ": cannot write the snapshot");
  });
}

// `path`, its folder created.
const std::string& in_made_folder(const std::string& path) {
  const fs::path parent = fs::path(path).parent_path();
  if (!parent.empty()) fs::create_directories(parent);
  return path;
}

// A video written under a temporary name and renamed when complete.
class VideoOutput {
 public:
  VideoOutput(const std::string& path, const cv::Size& size, double fps)
      : file_(in_made_folder(path)) {
    const std::string ext = fs::path(path).extension().string();
    int fourcc = 0;
    if (ext == ".mp4" || ext == ".m4v" || ext == ".mov") {
      fourcc = cv::VideoWriter::fourcc('m', 'p', '4', 'v');
    } else if (ext == ".avi") {
      fourcc = cv::VideoWriter::fourcc('M', 'J', 'P', 'G');
    } else {
      throw Error(path + ": unknown video type '" + ext + "', use .mp4 or .avi");
    }
    if (!writer_.open(file_.temporary(), fourcc, fps, size, true)) {
      throw Error(path + ": cannot open a video writer (OpenCV without a video encoder for '" +
                  ext + "'?)");
    }
  }
  void write(const cv::Mat& bgr) { writer_.write(bgr); }
  void commit() {
    writer_.release();
    file_.commit();
  }

 private:
  PendingFile file_;  // declared first: removed after the writer has closed it
  cv::VideoWriter writer_;
};

// The per-frame CSV log, written under a temporary name and renamed when complete.
class LogOutput {
 public:
  explicit LogOutput(const std::string& path)
      : file_(in_made_folder(path), "log", guide_log_header()) {}
  void write(const std::string& row) { file_.write(row + "\n"); }
  void commit() { file_.commit(); }

 private:
  PendingTextFile file_;
};

// Everything a guidance run writes besides the window: the video, snapshots, the per-frame log
// and a recording of the incoming frames. Each appears complete or not at all.
class GuideOutputs {
 public:
  GuideOutputs(const GuideRequest& request, const std::string& source_description)
      : request_(request), source_description_(source_description) {
    snapshot_dir_ = request.snapshot_dir;
    if (snapshot_dir_.empty()) {
      snapshot_dir_ = request.video.empty() ? "." : fs::path(request.video).parent_path().string();
      if (snapshot_dir_.empty()) snapshot_dir_ = ".";
    }
    pending_snapshots_ = request.snapshots;
    std::sort(pending_snapshots_.begin(), pending_snapshots_.end());
    if (!request.log.empty()) log_.emplace(request.log);
    record_options_.boards_json = tracking::boards_json_text(request.boards);
    record_options_.camera = request.setup.camera;
  }

  // Whether the overlay image must be read back for these outputs.
  bool need_image() const {
    return !request_.video.empty() || !pending_snapshots_.empty() || request_.snapshot_every > 0;
  }
  const std::string& snapshot_dir() const { return snapshot_dir_; }

  // The recording, the video, the snapshots due at this frame (given frames, every N-th of the
  // `shown` frames so far) and the log row of one frame.
  void add(const tracking::Frame& frame, const GuideFrameResult& r, int64_t shown) {
    last_frame_ = frame.index;
    if (!request_.record.empty()) {
      if (!recorder_) {
        recorder_ = std::make_unique<tracking::FrameRecorder>(
            request_.record, source_description_, request_.setup.camera, record_options_,
            !frame.truth.empty());
      }
      recorder_->add(frame);
    }
    if (!request_.video.empty()) {
      if (!video_) video_.emplace(request_.video, r.image.size(), request_.video_fps);
      video_->write(r.image);
    }
    while (!pending_snapshots_.empty() && pending_snapshots_.front().first <= frame.index) {
      snapshot(pending_snapshots_.front().second, r.image);
      pending_snapshots_.erase(pending_snapshots_.begin());
    }
    if (request_.snapshot_every > 0 && shown % request_.snapshot_every == 0) {
      snapshot(fmt::format("frame_{:06d}.png", frame.index), r.image);
    }
    if (log_) log_->write(guide_log_row(r.info, r.latency_ms, r.render_ms));
    if (!request_.record_poses.empty()) poses_.frames.push_back(pose_frame(frame, r));
  }

  // One frame of the poses' sequence file.
  static recordings::PlusFrame pose_frame(const tracking::Frame& frame, const GuideFrameResult& r) {
    recordings::PlusFrame f;
    f.fields.emplace_back("FrameNumber", std::to_string(frame.index));
    f.fields.emplace_back("Timestamp", fmt::format("{:.6f}", double(frame.timestamp_ns) * 1e-9));
    f.fields.emplace_back("ImageStatus", "INVALID");  // poses only, no image frames
    for (const tracking::BoardStatus& b : r.boards) {
      const std::string name = recordings::plus_tool_name(b.board);
      f.fields.emplace_back(name + "ToCameraTransform",
                            recordings::plus_matrix_text(b.tracked ? b.T_cam_board.matrix()
                                                                   : Eigen::Matrix4d::Identity()));
      f.fields.emplace_back(name + "ToCameraTransformStatus", b.tracked ? "OK" : "INVALID");
    }
    const bool needle = r.info.needle.has_value();
    f.fields.emplace_back("NeedleToCTTransform",
                          recordings::plus_matrix_text(needle ? r.info.needle->T_ct_needle.matrix()
                                                              : Eigen::Matrix4d::Identity()));
    f.fields.emplace_back("NeedleToCTTransformStatus", needle ? "OK" : "INVALID");
    if (needle) {
      f.fields.emplace_back("NeedleSafety", planning::needle_safety_name(r.info.needle->state.safety));
    }
    return f;
  }

  void snapshot(const std::string& name, const cv::Mat& image) {
    const std::string path = (fs::path(snapshot_dir_) / name).string();  // absolute names stay
    write_png(path, image);
    snapshots_written_.push_back(path);
  }

  // Video, recording and log take their final names.
  void commit(GuideSummary& summary) {
    if (video_) {
      video_->commit();
      summary.video = request_.video;
    }
    if (recorder_) {
      const tracking::RecordSummary rs = recorder_->finish();
      spdlog::info("guide: {} frames recorded in {}", rs.frames, rs.path);
    }
    if (log_) log_->commit();
    if (!request_.record_poses.empty()) {
      poses_.header = {{"AnatomicalOrientation", "RAI"},
                       {"Kinds", "domain domain list"},
                       {"ElementSpacing", "1 1 1"},
                       {"Offset", "0 0 0"},
                       {"TransformMatrix", "1 0 0 0 1 0 0 0 1"},
                       {"UltrasoundImageOrientation", "MF"}};
      recordings::write_plus_sequence(request_.record_poses, poses_);
      spdlog::info("guide: the poses of {} frames written to {}", poses_.frames.size(),
                   request_.record_poses);
    }
    summary.snapshots_written = snapshots_written_;
    // Snapshots asked for beyond the frames shown are said, not passed over.
    for (const auto& [frame, name] : pending_snapshots_) {
      const std::string why =
          last_frame_ < 0 ? "no frame was shown"
                          : fmt::format("the frames shown ended at frame {}", last_frame_);
      spdlog::warn("guide: snapshot {} at frame {} not taken: {}", name, frame, why);
      summary.snapshots_not_taken.push_back(fmt::format("{} (frame {})", name, frame));
    }
  }

 private:
  const GuideRequest& request_;
  std::string source_description_;
  std::string snapshot_dir_;
  std::vector<std::pair<int64_t, std::string>> pending_snapshots_;
  std::optional<VideoOutput> video_;
  std::optional<LogOutput> log_;
  std::unique_ptr<tracking::FrameRecorder> recorder_;
  tracking::RecordOptions record_options_;
  std::vector<std::string> snapshots_written_;
  recordings::PlusSequence poses_;  // --record-poses
  int64_t last_frame_ = -1;
};

// Window keys: 1-7 toggle layers, C palette, S snapshot, Q or Esc quit. Returns true to quit.
bool handle_keys(GuideLoop& loop, GuideOutputs& outputs, const cv::Mat& image,
                 int& manual_snapshots) {
  OverlayRenderer& renderer = loop.renderer();
  GuidanceOverlay& overlay = loop.overlay();
  bool quit = false;
  for (int key : renderer.poll_keys()) {
    if (key >= '1' && key < '1' + kGuidanceLayerCount) {
      const auto layer = static_cast<GuidanceLayer>(key - '1');
      overlay.toggle(layer);
      spdlog::info("guide: layer {} {}", guidance_layer_name(layer),
                   overlay.visible(layer) ? "on" : "off");
    } else if (key == 'C') {
      overlay.set_palette(overlay.palette() == planning::Palette::kDefault
                              ? planning::Palette::kColorblind
                              : planning::Palette::kDefault);
    } else if (key == 'S') {
      const std::string name = fmt::format("snapshot_{:03d}.png", ++manual_snapshots);
      outputs.snapshot(name, image.empty() ? renderer.render() : image);
      spdlog::info("guide: snapshot {}/{}", outputs.snapshot_dir(), name);
    } else if (key == 'Q' || key == 256 /* Escape */) {
      quit = true;
    }
  }
  return quit;
}

// Per-frame times, summarised at the end.
struct Timings {
  std::vector<double> latency, track, overlay, render;

  void add(const GuideFrameResult& r) {
    latency.push_back(r.latency_ms);
    track.push_back(r.track_ms);
    overlay.push_back(r.overlay_ms);
    render.push_back(r.render_ms);
  }
  void summarise(GuideSummary& s) const {
    s.latency_median_ms = percentile(latency, 50);
    s.latency_p95_ms = percentile(latency, 95);
    s.latency_max_ms = latency.empty() ? 0 : *std::max_element(latency.begin(), latency.end());
    s.track_median_ms = percentile(track, 50);
    s.overlay_median_ms = percentile(overlay, 50);
    s.render_median_ms = percentile(render, 50);
    s.render_p95_ms = percentile(render, 95);
  }
};

void count_frame(GuideSummary& summary, GuideFrameResult& r) {
  ++summary.frames;
  summary.dropped += r.dropped;
  if (!r.info.image) ++summary.frames_without_image;
  if (r.info.anatomy_drawn) ++summary.patient_tracked;
  if (r.info.needle) {
    ++summary.needle_evaluated;
    switch (r.info.needle->state.safety) {
      case planning::NeedleSafety::kSafe:
        ++summary.needle_safe;
        break;
      case planning::NeedleSafety::kMedium:
        ++summary.needle_medium;
        break;
      case planning::NeedleSafety::kDangerous:
        ++summary.needle_dangerous;
        break;
      case planning::NeedleSafety::kUnknown:
        ++summary.needle_unknown;
        break;
    }
  }
  summary.latency_from_capture = r.latency_from_capture;
  summary.frame_infos.push_back(std::move(r.info));
}

void log_summary(const GuideSummary& summary) {
  spdlog::info(
      "guide: {} frames in {:.1f} s ({:.1f} fps); latency median {:.1f} ms, p95 {:.1f} ms ({}); "
      "tracking {:.1f} ms, overlay {:.1f} ms, rendering {:.1f} ms (medians)",
      summary.frames, summary.seconds, summary.fps, summary.latency_median_ms,
      summary.latency_p95_ms, summary.latency_from_capture ? "from capture" : "from frame arrival",
      summary.track_median_ms, summary.overlay_median_ms, summary.render_median_ms);
  spdlog::info(
      "guide: anatomy shown in {} frames, needle evaluated in {} (safe {}, medium {}, "
      "dangerous {}), {} without image, {} dropped",
      summary.patient_tracked, summary.needle_evaluated, summary.needle_safe, summary.needle_medium,
      summary.needle_dangerous, summary.frames_without_image, summary.dropped);
}

// Refuses a source whose frames do not match the camera calibration.
void check_source(const tracking::FrameSource& source, const GuideRequest& request) {
  const auto c = source.camera();
  const calibration::CameraModel& camera = request.setup.camera;
  if (c && (c->width != camera.width || c->height != camera.height)) {
    throw Error("guide: the source " + request.source + " delivers " + std::to_string(c->width) +
                "x" + std::to_string(c->height) + " frames but the camera calibration is " +
                std::to_string(camera.width) + "x" + std::to_string(camera.height));
  }
}

// Boards for a session whose poses come over OpenIGTLink: named as the setup's, never detected.
std::vector<tracking::Board> placeholder_boards(const overlay::GuidanceSetup& setup) {
  std::vector<tracking::Board> boards(2);
  boards[0].name = setup.patient_board;
  boards[1].name = setup.needle_board;
  for (size_t b = 0; b < 2; ++b) {
    tracking::BoardTag tag;
    tag.id = int(b);
    tag.corners = {Eigen::Vector3d(-5, 5, 0), Eigen::Vector3d(5, 5, 0), Eigen::Vector3d(5, -5, 0),
                   Eigen::Vector3d(-5, -5, 0)};
    boards[b].tags = {tag};
  }
  return boards;
}

}  // namespace

planning::NeedleUncertaintySources calibration_uncertainty(
    const calibration::NeedleCalibration& needle, const calibration::RegistrationRecord& reg) {
  planning::NeedleUncertaintySources u;
  if (needle.tip_stddev_mm.squaredNorm() > 0) {
    u.tip_mm2 = needle.tip_stddev_mm.cwiseAbs2().asDiagonal();
  } else {
    u.tip_mm2 = Eigen::Matrix3d::Identity() * (needle.tip_stddev_3d_mm * needle.tip_stddev_3d_mm / 3.0);
  }
  u.axis_from_tip = !needle.axis_needle;
  u.axis_stddev_rad = needle.axis_needle ? needle.axis_rms_deg * M_PI / 180.0 : 0.0;
  u.registration_tre_mm = reg.expected_tre_mm > 0 ? reg.expected_tre_mm : reg.fre_rms_mm;
  return u;
}

GuidanceSetup read_guidance_setup(const std::string& camera_yaml,
                                  const std::string& registration_yaml,
                                  const std::string& needle_yaml) {
  GuidanceSetup setup;
  if (camera_yaml.empty()) {
    // No camera (poses over OpenIGTLink): the virtual camera, 1280x720, 1000 px focal length.
    setup.camera.width = 1280;
    setup.camera.height = 720;
    setup.camera.fx = setup.camera.fy = 1000.0;
    setup.camera.cx = 639.5;
    setup.camera.cy = 359.5;
  } else {
    setup.camera = calibration::CameraModel::read_yaml(camera_yaml);
  }
  const calibration::RegistrationRecord reg = calibration::read_registration(registration_yaml);
  setup.T_ct_patient = reg.T_ct_patient;
  if (!reg.board.empty()) setup.patient_board = reg.board;
  const calibration::NeedleCalibration needle = calibration::read_needle_calibration(needle_yaml);
  if (!needle.board.empty()) setup.needle_board = needle.board;
  setup.tip_in_needle = needle.tip_needle;
  Eigen::Vector3d axis = needle.axis_needle ? *needle.axis_needle : needle.tip_needle;
  if (!(axis.norm() > 1e-9)) {
    throw Error(needle_yaml +
                ": the needle has no axis: no spin axis and the tip lies at the "
                "board origin");
  }
  axis.normalize();
  if (axis.dot(needle.tip_needle) < 0) axis = -axis;  // from the hub toward the tip
  setup.axis_in_needle = axis;
  setup.uncertainty = calibration_uncertainty(needle, reg);
  if (setup.patient_board == setup.needle_board) {
    throw Error(needle_yaml + ": the needle board '" + setup.needle_board +
                "' is also the patient board of " + registration_yaml);
  }
  return setup;
}

std::pair<int64_t, std::string> parse_snapshot(const std::string& spec) {
  const auto colon = spec.find(':');
  const std::string frame = spec.substr(0, colon);
  try {
    size_t used = 0;
    const int64_t index = std::stoll(frame, &used);
    return {index, colon == std::string::npos ? "frame_" + frame + ".png" : spec.substr(colon + 1)};
  } catch (const std::exception&) {
    throw Error("guide: snapshot '" + spec + "': expected FRAME or FRAME:NAME.png");
  }
}

std::string guide_log_header() {
  return "frame,timestamp_ns,image,problem,patient_tracked,patient_age_ms,needle_tracked,"
         "needle_age_ms,anatomy_drawn,needle_safety,line_integral,clear,tip_class,"
         "tip_to_target_mm,miss_mm,hits_tumor,angle_to_safe_deg,structures,uncertainty_95_mm,"
         "uncertainty_95_minor_mm,worst_in_95,uncertain,pose_covariance_known,breathing_phase,"
         "breathing_displacement_mm,safe_phases,latency_ms,render_ms,warnings";
}

std::string guide_log_row(const GuidanceFrameInfo& i, double latency_ms, double render_ms) {
  std::ostringstream o;
  o.precision(6);
  o << i.frame << ',' << i.timestamp_ns << ',' << (i.image ? 1 : 0) << ',' << csv_field(i.problem)
    << ',' << (i.patient_tracked ? 1 : 0) << ',';
  if (i.patient_tracked) o << i.patient_age_ms;
  o << ',' << (i.needle_tracked ? 1 : 0) << ',';
  if (i.needle_tracked) o << i.needle_age_ms;
  o << ',' << (i.anatomy_drawn ? 1 : 0) << ',';
  if (i.needle) {
    const auto& s = i.needle->state;
    std::string structures;
    for (const auto& t : needle_text(s)) structures += (structures.empty() ? "" : "; ") + t;
    o << planning::needle_safety_name(s.safety) << ',' << s.evaluation.line_integral << ','
      << (s.clear ? 1 : 0) << ',' << s.tip_class << ',' << s.tip_to_centroid_mm << ','
      << s.miss_distance_mm << ',' << (s.hits_tumor ? 1 : 0) << ',' << s.angle_to_safe_deg << ','
      << csv_field(structures) << ',';
    const auto& n = *i.needle;
    if (n.uncertainty.valid) o << n.uncertainty.major95_mm << ',' << n.uncertainty.minor95_mm;
    else o << ',';
    o << ',' << planning::needle_safety_name(n.region.worst) << ',' << (n.region.uncertain() ? 1 : 0)
      << ',' << (n.pose_covariance_known ? 1 : 0);
  } else {
    o << ",,,,,,,,,,,,,";
  }
  // Breathing plans: the phase (empty until known), the board's rise from end-exhale, and the
  // phases in which the needle's line is safe.
  o << ',';
  if (i.breathing && i.breathing->estimate.known) o << i.breathing->estimate.phase;
  o << ',';
  if (i.breathing && i.breathing->estimate.known) o << i.breathing->estimate.displacement_mm;
  std::string safe;
  if (i.breathing) {
    for (size_t k = 0; k < i.breathing->phase_safety.size(); ++k) {
      if (i.breathing->phase_safety[k] == planning::NeedleSafety::kSafe) {
        safe += (safe.empty() ? "" : " ") + std::to_string(k);
      }
    }
  }
  o << ',' << csv_field(safe);
  std::string warnings;
  for (const auto& w : i.warnings) warnings += (warnings.empty() ? "" : "; ") + w;
  o << ',' << latency_ms << ',' << render_ms << ',' << csv_field(warnings);
  return o.str();
}

GuideSummary run_guide(const planning::PlanData& plan, const GuideRequest& request) {
  if (!request.window && request.video.empty() && request.snapshots.empty() &&
      request.snapshot_every <= 0 && request.log.empty() && request.record_poses.empty()) {
    throw Error("guide: nothing to show: open a window, or give a video, snapshots or a log");
  }
  std::unique_ptr<PoseInput> pose_input;
  std::unique_ptr<tracking::FrameSource> source;
  std::vector<tracking::Board> boards = request.boards;
  if (!request.poses.empty()) {
    pose_input = std::make_unique<PoseInput>(request.poses, request.poses_needle,
                                             request.poses_patient, request.tracker.max_age_ms,
                                             request.setup, plan.tumor_centre);
  }
  if (pose_input && pose_input->sequence() && !request.source.empty()) {
    throw Error("guide: --poses " + request.poses + " replays a PLUS sequence file with the "
                "virtual camera; give no --source with it");
  }
  if (pose_input && request.source.empty()) {
    source = pose_input->sequence()
                 ? plus_frames_source(request.setup.camera, *pose_input->sequence(),
                                      request.poses_fps, plus_poses_address(request.poses)->second)
                 : virtual_camera_source(request.setup.camera, request.poses_fps);
    if (boards.empty()) boards = placeholder_boards(request.setup);
  } else {
    source = tracking::open_frame_source(request.source);
    check_source(*source, request);
  }
  RendererOptions ro = request.renderer;
  ro.visible = request.window;
  tracking::TrackerOptions to = request.tracker;
  if (request.full_search_mode) {
    to.full_search_mode = *request.full_search_mode;
  } else {
    const bool live = request.source.rfind("v4l2:", 0) == 0 ||
                      request.source.find("realtime=1") != std::string::npos;
    to.full_search_mode = live ? tracking::FullSearchMode::kBackground
                               : tracking::FullSearchMode::kBackgroundWait;
  }
  GuideLoop loop(plan, request.setup, boards, request.options, to, ro);
  if (pose_input) loop.set_pose_input(pose_input.get(), request.source.empty());
  std::unique_ptr<GuidanceBroadcast> broadcast;
  if (request.igtl_port >= 0) {
    igtlink::Server::Options io;
    io.port = request.igtl_port;
    broadcast = std::make_unique<GuidanceBroadcast>(io, plan, request.setup);
    loop.set_broadcast(broadcast.get());
  }

  GuideSummary summary;
  summary.gl = loop.renderer().gl_description();
  spdlog::info("guide: {} -> {}{}; OpenGL: {}", source->describe(),
               request.window ? "window" : "headless",
               request.video.empty() ? "" : ", video " + request.video, summary.gl);
  GuideOutputs outputs(request, source->describe());
  Timings timings;
  const auto t0 = Clock::now();
  auto last_progress = t0;
  int manual_snapshots = 0;
  bool quit = false;
  while (!quit) {
    if (request.stop && request.stop->load()) break;
    if (request.max_frames >= 0 && summary.frames >= request.max_frames) break;
    std::optional<tracking::Frame> frame = source->next();
    if (!frame) break;
    const auto arrival = Clock::now();
    if (!frame->note.empty()) spdlog::info("guide: frame {}: {}", frame->index, frame->note);
    GuideFrameResult r = loop.process(*frame, arrival, outputs.need_image());
    if (loop.window_closed()) quit = true;
    timings.add(r);
    outputs.add(*frame, r, summary.frames);
    if (request.window && handle_keys(loop, outputs, r.image, manual_snapshots)) quit = true;
    count_frame(summary, r);
    const auto now = Clock::now();
    if (now - last_progress > std::chrono::seconds(2)) {
      last_progress = now;
      spdlog::info("guide: {} frames, latency {:.0f} ms (median so far)", summary.frames,
                   percentile(timings.latency, 50));
    }
  }
  summary.seconds = std::chrono::duration<double>(Clock::now() - t0).count();
  if (pose_input && pose_input->receiver()) {
    const igtlink::PoseReceiver::Stats st = pose_input->receiver()->stats();
    spdlog::info("guide: OpenIGTLink poses: {} connection(s), {} messages, {} poses, {} skipped, "
                 "{} dropped{}",
                 st.connections, st.messages, st.poses, st.skipped, st.dropped,
                 st.last_problem.empty() ? "" : " (last: " + st.last_problem + ")");
  }
  if (broadcast) {
    const igtlink::Server::Stats st = broadcast->server().stats();
    summary.igtl_connections = st.connections;
    summary.igtl_messages = st.messages_sent;
    summary.igtl_latency_median_ms = st.latency_median_ms;
    summary.igtl_latency_p95_ms = st.latency_p95_ms;
    spdlog::info("guide: OpenIGTLink: {} client(s) served, {} messages, pose to socket {:.3f} ms "
                 "median, {:.3f} ms p95; {} dropped",
                 st.connections, st.messages_sent, st.latency_median_ms, st.latency_p95_ms,
                 st.dropped);
  }
  summary.fps = summary.seconds > 0 ? double(summary.frames) / summary.seconds : 0;
  timings.summarise(summary);
  outputs.commit(summary);
  log_summary(summary);
  return summary;
}

GuideSummary run_guide(const std::string& plan_dir, const GuideRequest& request) {
  planning::PlanLoadOptions lo;
  lo.blocking = true;
  spdlog::info("guide: loading the plan {}", plan_dir);
  const planning::PlanData plan = planning::load_plan(plan_dir, lo);
  const GuideSummary s = run_guide(plan, request);
  if (!s.video.empty()) spdlog::info("guide: overlay video {}", s.video);
  if (!request.log.empty()) spdlog::info("guide: per-frame log {}", request.log);
  return s;
}

}  // namespace crepuscular::pipelines
