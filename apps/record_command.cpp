// `crepuscular record`: records any frame source (camera, recording, synthetic scene) into a
// recording folder.
#include <spdlog/spdlog.h>

#include <atomic>
#include <csignal>
#include <fstream>
#include <memory>
#include <sstream>
#include <string>

#include "apps/commands.hpp"
#include "calibration/camera_model.hpp"
#include "kernels/error.hpp"
#include "tracking/board.hpp"
#include "tracking/frame_source.hpp"

namespace crepuscular::apps {

namespace {

struct RecordArgs {
  std::string source;
  std::string out;
  int64_t frames = -1;
  double seconds = -1;
  std::string format = "jpg";
  int quality = 95;
  std::string boards;
  std::string camera;
  std::string plan;
};

std::atomic<bool> g_stop{false};

extern "C" void on_interrupt(int) { g_stop.store(true); }

}  // namespace

void add_record_command(CLI::App& app) {
  auto args = std::make_shared<RecordArgs>();
  CLI::App* cmd = app.add_subcommand(
      "record",
      "Record frames from a source into a recording folder that `crepuscular track` and the\n"
      "training simulators replay (DESIGN.md section 8: frames/, frames.csv with capture\n"
      "timestamps, camera.yaml, session.json, and ground_truth.csv when the source has truth).\n"
      "\n"
      "Sources:\n"
      "  v4l2:/dev/video0?width=1280&height=720&fps=60[&format=mjpeg|yuyv]   a camera (MJPEG\n"
      "      frames are stored as received, corrupt ones included; the camera is reopened if it\n"
      "      disappears, and the gap shows as missing frame numbers)\n"
      "  recording:DIR[?realtime=1&loop=1]   another recording (copy, cut with --frames/--seconds)\n"
      "  synthetic:SCENE.json | synthetic:builtin   rendered frames with ground truth\n"
      "\n"
      "The recording is written frame by frame into DIR.partial and renamed to DIR when it ends\n"
      "(--frames or --seconds reached, the source ended, or Ctrl-C). If the recorder is killed,\n"
      "DIR.partial stays and replays up to its last complete frame:\n"
      "  crepuscular track --source recording:DIR.partial ...");
  cmd->add_option("--source", args->source, "Frame source URI (see above)")->required();
  cmd->add_option("--out", args->out, "Output recording folder (DIR); must not exist")->required();
  cmd->add_option("--frames", args->frames, "Stop after this many frames (default: no limit)")
      ->check(CLI::PositiveNumber);
  cmd->add_option("--seconds", args->seconds,
                  "Stop after this much capture time in seconds (default: no limit)")
      ->check(CLI::PositiveNumber);
  cmd->add_option("--format", args->format,
                  "Frame image format: jpg (camera MJPEG stored as received) or png (lossless)")
      ->capture_default_str()
      ->check(CLI::IsMember({"jpg", "png"}));
  cmd->add_option("--quality", args->quality, "JPEG quality for frames that are encoded here")
      ->capture_default_str()
      ->check(CLI::Range(1, 100));
  cmd->add_option("--boards", args->boards,
                  "boards.json of the marker boards in view, stored with the recording "
                  "(default: none)")
      ->check(CLI::ExistingFile);
  cmd->add_option("--camera", args->camera,
                  "camera.yaml to store with the recording (default: the source's own camera "
                  "model when it has one: synthetic scenes, recordings)")
      ->check(CLI::ExistingFile);
  cmd->add_option("--plan", args->plan, "Plan folder this session belongs to (default: none)");
  cmd->callback([args] {
    tracking::RecordOptions options;
    options.max_frames = args->frames;
    options.max_seconds = args->seconds;
    options.image_format = args->format;
    options.jpeg_quality = args->quality;
    options.plan = args->plan;
    if (!args->boards.empty()) {
      // Checked and normalised: grids expanded, as tracking reads them.
      options.boards_json = tracking::boards_json_text(tracking::read_boards(args->boards));
    }
    if (!args->camera.empty()) options.camera = calibration::CameraModel::read_yaml(args->camera);
    auto source = tracking::open_frame_source(args->source);
    if (args->frames < 0 && args->seconds < 0 && args->source.rfind("v4l2:", 0) == 0) {
      spdlog::info("record: no --frames or --seconds: recording until Ctrl-C");
    }
    g_stop.store(false);
    options.stop = &g_stop;
    auto previous = std::signal(SIGINT, on_interrupt);
    tracking::RecordSummary s;
    try {
      s = tracking::record_to_folder(*source, args->out, options);
    } catch (...) {
      std::signal(SIGINT, previous);
      throw;
    }
    std::signal(SIGINT, previous);
    spdlog::info("record: wrote {} frames to {} in {:.1f} s ({} without image data skipped, {} "
                 "with a problem{})",
                 s.frames, s.path, s.seconds, s.skipped, s.problems,
                 s.truth_rows > 0 ? ", " + std::to_string(s.truth_rows) + " ground-truth rows" : "");
  });
}

}  // namespace crepuscular::apps
