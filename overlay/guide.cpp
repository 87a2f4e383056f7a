#include "overlay/guide.hpp"

#include "overlay/guide_loop.hpp"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <optional>
#include <sstream>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/videoio.hpp>
#include <spdlog/spdlog.h>

#include "calibration/calibration_files.hpp"
#include "kernels/error.hpp"
#include "planning/output_files.hpp"
#include "tracking/board.hpp"
#include "tracking/frame_source.hpp"

namespace crepuscular::overlay {

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
  const std::string tmp = planning::temporary_sibling(path);
  if (!cv::imwrite(tmp, image)) {
    fs::remove(tmp);
    throw Error(path + ": cannot write the snapshot");
  }
  planning::commit_file(tmp, path);
}

// A video written under a temporary name and renamed when complete.
class VideoOutput {
 public:
  VideoOutput(const std::string& path, const cv::Size& size, double fps) : path_(path) {
    const std::string ext = fs::path(path).extension().string();
    int fourcc = 0;
    if (ext == ".mp4" || ext == ".m4v" || ext == ".mov") {
      fourcc = cv::VideoWriter::fourcc('m', 'p', '4', 'v');
    } else if (ext == ".avi") {
      fourcc = cv::VideoWriter::fourcc('M', 'J', 'P', 'G');
    } else {
      throw Error(path + ": unknown video type '" + ext + "', use .mp4 or .avi");
    }
    const fs::path parent = fs::path(path).parent_path();
    if (!parent.empty()) fs::create_directories(parent);
    tmp_ = planning::temporary_sibling(path);
    if (!writer_.open(tmp_, fourcc, fps, size, true)) {
      throw Error(path + ": cannot open a video writer (OpenCV without a video encoder for '" +
                  ext + "'?)");
    }
  }
  ~VideoOutput() {
    if (!committed_) {
      writer_.release();
      std::error_code ec;
      fs::remove(tmp_, ec);
    }
  }
  void write(const cv::Mat& bgr) { writer_.write(bgr); }
  void commit() {
    writer_.release();
    planning::commit_file(tmp_, path_);
    committed_ = true;
  }

 private:
  std::string path_, tmp_;
  cv::VideoWriter writer_;
  bool committed_ = false;
};


}  // namespace

GuidanceSetup read_guidance_setup(const std::string& camera_yaml,
                                  const std::string& registration_yaml,
                                  const std::string& needle_yaml) {
  GuidanceSetup setup;
  setup.camera = calibration::CameraModel::read_yaml(camera_yaml);
  const calibration::RegistrationRecord reg = calibration::read_registration(registration_yaml);
  setup.T_ct_patient = reg.T_ct_patient;
  if (!reg.board.empty()) setup.patient_board = reg.board;
  const calibration::NeedleCalibration needle = calibration::read_needle_calibration(needle_yaml);
  if (!needle.board.empty()) setup.needle_board = needle.board;
  setup.tip_in_needle = needle.tip_needle;
  Eigen::Vector3d axis = needle.axis_needle ? *needle.axis_needle : needle.tip_needle;
  if (!(axis.norm() > 1e-9)) {
    throw Error(needle_yaml + ": the needle has no axis: no spin axis and the tip lies at the "
                              "board origin");
  }
  axis.normalize();
  if (axis.dot(needle.tip_needle) < 0) axis = -axis;  // from the hub toward the tip
  setup.axis_in_needle = axis;
  if (setup.patient_board == setup.needle_board) {
    throw Error(needle_yaml + ": the needle board '" + setup.needle_board +
                "' is also the patient board of " + registration_yaml);
  }
  return setup;
}

std::string guide_log_header() {
  return "frame,timestamp_ns,image,problem,patient_tracked,patient_age_ms,needle_tracked,"
         "needle_age_ms,anatomy_drawn,needle_safety,line_integral,clear,tip_class,"
         "tip_to_target_mm,miss_mm,hits_tumor,angle_to_safe_deg,structures,latency_ms,render_ms,"
         "warnings";
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
      << csv_field(structures);
  } else {
    o << ",,,,,,,,";
  }
  std::string warnings;
  for (const auto& w : i.warnings) warnings += (warnings.empty() ? "" : "; ") + w;
  o << ',' << latency_ms << ',' << render_ms << ',' << csv_field(warnings);
  return o.str();
}

GuideSummary run_guide(const planning::PlanData& plan, const GuideRequest& request) {
  const GuidanceSetup& setup = request.setup;
  if (!request.window && request.video.empty() && request.snapshots.empty() &&
      request.snapshot_every <= 0 && request.log.empty()) {
    throw Error("guide: nothing to show: open a window, or give a video, snapshots or a log");
  }

  std::unique_ptr<tracking::FrameSource> source = tracking::open_frame_source(request.source);
  if (auto c = source->camera()) {
    if (c->width != setup.camera.width || c->height != setup.camera.height) {
      throw Error("guide: the source " + request.source + " delivers " + std::to_string(c->width) +
                  "x" + std::to_string(c->height) + " frames but the camera calibration is " +
                  std::to_string(setup.camera.width) + "x" + std::to_string(setup.camera.height));
    }
  }
  RendererOptions ro = request.renderer;
  ro.visible = request.window;
  GuideLoop loop(plan, setup, request.boards, request.options, request.tracker, ro);
  OverlayRenderer& renderer = loop.renderer();
  GuidanceOverlay& overlay = loop.overlay();

  GuideSummary summary;
  summary.gl = renderer.gl_description();
  spdlog::info("guide: {} -> {}{}; OpenGL: {}", source->describe(),
               request.window ? "window" : "headless",
               request.video.empty() ? "" : ", video " + request.video, summary.gl);

  std::string snapshot_dir = request.snapshot_dir;
  if (snapshot_dir.empty()) {
    snapshot_dir = request.video.empty() ? "." : fs::path(request.video).parent_path().string();
    if (snapshot_dir.empty()) snapshot_dir = ".";
  }
  auto pending_snapshots = request.snapshots;
  std::sort(pending_snapshots.begin(), pending_snapshots.end());
  const bool need_image = !request.video.empty() || !pending_snapshots.empty() ||
                          request.snapshot_every > 0;

  std::optional<VideoOutput> video;
  std::string log_tmp;
  std::FILE* log = nullptr;
  if (!request.log.empty()) {
    const fs::path parent = fs::path(request.log).parent_path();
    if (!parent.empty()) fs::create_directories(parent);
    log_tmp = planning::temporary_sibling(request.log);
    log = std::fopen(log_tmp.c_str(), "w");
    if (!log) throw Error(request.log + ": cannot write the log");
    std::fprintf(log, "%s\n", guide_log_header().c_str());
  }
  struct LogCloser {
    std::FILE*& f;
    std::string& tmp;
    ~LogCloser() {
      if (f) {
        std::fclose(f);
        std::error_code ec;
        fs::remove(tmp, ec);
      }
    }
  } log_closer{log, log_tmp};

  std::unique_ptr<tracking::FrameRecorder> recorder;
  tracking::RecordOptions record_options;
  record_options.boards_json = tracking::boards_json_text(request.boards);
  record_options.camera = setup.camera;

  std::vector<double> latencies, track_ms, overlay_ms, render_ms;
  const auto t0 = Clock::now();
  auto last_progress = t0;
  int manual_snapshots = 0;
  bool quit = false;
  auto snapshot = [&](const std::string& name, const cv::Mat& image) {
    const std::string path = (fs::path(snapshot_dir) / name).string();  // absolute names stay
    write_png(path, image);
    summary.snapshots_written.push_back(path);
  };

  while (!quit) {
    if (request.stop && request.stop->load()) break;
    if (request.max_frames >= 0 && summary.frames >= request.max_frames) break;
    std::optional<tracking::Frame> frame = source->next();
    if (!frame) break;
    const auto arrival = Clock::now();
    if (!frame->note.empty()) spdlog::info("guide: frame {}: {}", frame->index, frame->note);
    GuideFrameResult r = loop.process(*frame, arrival, need_image);
    if (loop.window_closed()) quit = true;
    if (!request.record.empty()) {
      if (!recorder) {
        recorder = std::make_unique<tracking::FrameRecorder>(
            request.record, source->describe(), setup.camera, record_options,
            !frame->truth.empty());
      }
      recorder->add(*frame);
    }
    latencies.push_back(r.latency_ms);
    track_ms.push_back(r.track_ms);
    overlay_ms.push_back(r.overlay_ms);
    render_ms.push_back(r.render_ms);

    if (!request.video.empty()) {
      if (!video) video.emplace(request.video, r.image.size(), request.video_fps);
      video->write(r.image);
    }
    while (!pending_snapshots.empty() && pending_snapshots.front().first <= frame->index) {
      snapshot(pending_snapshots.front().second, r.image);
      pending_snapshots.erase(pending_snapshots.begin());
    }
    if (request.snapshot_every > 0 && summary.frames % request.snapshot_every == 0) {
      char name[64];
      std::snprintf(name, sizeof(name), "frame_%06lld.png", (long long)frame->index);
      snapshot(name, r.image);
    }
    if (request.window) {
      for (int key : renderer.poll_keys()) {
        if (key >= '1' && key <= '6') {
          const auto layer = static_cast<GuidanceLayer>(key - '1');
          overlay.toggle(layer);
          spdlog::info("guide: layer {} {}", guidance_layer_name(layer),
                       overlay.visible(layer) ? "on" : "off");
        } else if (key == 'C') {
          overlay.set_palette(overlay.palette() == planning::Palette::kDefault
                                  ? planning::Palette::kColorblind
                                  : planning::Palette::kDefault);
        } else if (key == 'S') {
          char name[64];
          std::snprintf(name, sizeof(name), "snapshot_%03d.png", ++manual_snapshots);
          snapshot(name, r.image.empty() ? renderer.render() : r.image);
          spdlog::info("guide: snapshot {}/{}", snapshot_dir, name);
        } else if (key == 'Q' || key == 256 /* Escape */) {
          quit = true;
        }
      }
    }

    if (log) {
      std::fprintf(log, "%s\n", guide_log_row(r.info, r.latency_ms, r.render_ms).c_str());
    }
    ++summary.frames;
    summary.dropped += r.dropped;
    if (!r.info.image) ++summary.frames_without_image;
    if (r.info.anatomy_drawn) ++summary.patient_tracked;
    if (r.info.needle) {
      ++summary.needle_evaluated;
      switch (r.info.needle->state.safety) {
        case planning::NeedleSafety::kSafe: ++summary.needle_safe; break;
        case planning::NeedleSafety::kMedium: ++summary.needle_medium; break;
        case planning::NeedleSafety::kDangerous: ++summary.needle_dangerous; break;
      }
    }
    summary.latency_from_capture = r.latency_from_capture;
    summary.frame_infos.push_back(std::move(r.info));

    const auto now = Clock::now();
    if (now - last_progress > std::chrono::seconds(2)) {
      last_progress = now;
      spdlog::info("guide: {} frames, latency {:.0f} ms (median so far)", summary.frames,
                   percentile(latencies, 50));
    }
  }

  summary.seconds = std::chrono::duration<double>(Clock::now() - t0).count();
  summary.fps = summary.seconds > 0 ? double(summary.frames) / summary.seconds : 0;
  summary.latency_median_ms = percentile(latencies, 50);
  summary.latency_p95_ms = percentile(latencies, 95);
  summary.latency_max_ms =
      latencies.empty() ? 0 : *std::max_element(latencies.begin(), latencies.end());
  summary.track_median_ms = percentile(track_ms, 50);
  summary.overlay_median_ms = percentile(overlay_ms, 50);
  summary.render_median_ms = percentile(render_ms, 50);
  summary.render_p95_ms = percentile(render_ms, 95);

  if (video) {
    video->commit();
    summary.video = request.video;
  }
  if (recorder) {
    const tracking::RecordSummary rs = recorder->finish();
    spdlog::info("guide: {} frames recorded in {}", rs.frames, rs.path);
  }
  if (log) {
    std::fclose(log);
    log = nullptr;
    planning::commit_file(log_tmp, request.log);
  }
  spdlog::info(
      "guide: {} frames in {:.1f} s ({:.1f} fps); latency median {:.1f} ms, p95 {:.1f} ms ({}); "
      "tracking {:.1f} ms, overlay {:.1f} ms, rendering {:.1f} ms (medians)",
      summary.frames, summary.seconds, summary.fps, summary.latency_median_ms,
      summary.latency_p95_ms, summary.latency_from_capture ? "from capture" : "from frame arrival",
      summary.track_median_ms, summary.overlay_median_ms, summary.render_median_ms);
  spdlog::info("guide: anatomy shown in {} frames, needle evaluated in {} (safe {}, medium {}, "
               "dangerous {}), {} without image, {} dropped",
               summary.patient_tracked, summary.needle_evaluated, summary.needle_safe,
               summary.needle_medium, summary.needle_dangerous, summary.frames_without_image,
               summary.dropped);
  return summary;
}

}  // namespace crepuscular::overlay
