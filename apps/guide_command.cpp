// `crepuscular guide`: the AR needle guidance on live video, a recording or a synthetic scene.
#include <spdlog/spdlog.h>

#include <atomic>
#include <csignal>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "apps/commands.hpp"
#include "kernels/error.hpp"
#include "overlay/guide.hpp"
#include "planning/evaluate.hpp"
#include "planning/slices.hpp"
#include "tracking/board.hpp"
#include "tracking/frame_source.hpp"

namespace crepuscular::apps {

namespace {

std::atomic<bool> g_stop{false};
void on_signal(int) { g_stop = true; }

struct GuideArgs {
  std::string plan, camera, registration, needle, boards, source;
  bool headless = false;
  std::string out;
  std::string snapshots_dir;
  std::vector<std::string> snapshot_at;
  int snapshot_every = 0;
  std::string log;
  std::string record;
  std::vector<std::string> hide, show;
  std::string palette = "default";
  std::string volume_classes = "safe,medium";
  std::string value;
  double max_age_ms = 100;
  int64_t max_frames = -1;
  double video_fps = 30;
  int rays = 3000;
};

void run(const GuideArgs& a) {
  overlay::GuideRequest req;
  req.setup = overlay::read_guidance_setup(a.camera, a.registration, a.needle);
  std::string boards_path = a.boards;
  const std::string recording_prefix = "recording:";
  if (boards_path.empty() && a.source.rfind(recording_prefix, 0) == 0) {
    const std::string dir = tracking::parse_source_uri(a.source).path;
    if (std::filesystem::exists(dir + "/boards.json")) boards_path = dir + "/boards.json";
  }
  if (boards_path.empty()) {
    throw Error("guide: --boards is required (the source " + a.source + " brings no boards.json)");
  }
  req.boards = tracking::read_boards(boards_path);
  req.source = a.source;
  req.window = !a.headless;
  req.video = a.out;
  req.video_fps = a.video_fps;
  req.snapshot_dir = a.snapshots_dir;
  for (const std::string& s : a.snapshot_at) {
    const auto colon = s.find(':');
    try {
      const int64_t frame = std::stoll(s.substr(0, colon));
      const std::string name = colon == std::string::npos ? "frame_" + s.substr(0, colon) + ".png"
                                                          : s.substr(colon + 1);
      req.snapshots.emplace_back(frame, name);
    } catch (const std::exception&) {
      throw Error("guide: --snapshot-at '" + s + "': expected FRAME or FRAME:NAME.png");
    }
  }
  req.snapshot_every = a.snapshot_every;
  req.log = a.log;
  req.record = a.record;
  if (req.log.empty() && !a.out.empty()) {
    req.log = std::filesystem::path(a.out).replace_extension(".csv").string();
  }
  req.max_frames = a.max_frames;
  req.options.value = a.value;
  req.options.palette = planning::parse_palette(a.palette);
  {
    // parse_hidden_classes takes the classes to hide; the option names those to show.
    const auto shown = planning::parse_hidden_classes(a.volume_classes);
    for (size_t c = 0; c < 3; ++c) req.options.volume_classes[c] = shown[c];
  }
  req.options.ray_directions = a.rays;
  for (const auto& l : a.hide) req.options.visible[size_t(overlay::parse_guidance_layer(l))] = false;
  for (const auto& l : a.show) req.options.visible[size_t(overlay::parse_guidance_layer(l))] = true;
  req.tracker.max_age_ms = a.max_age_ms;
  if (a.headless && req.video.empty() && req.snapshots.empty() && req.snapshot_every <= 0) {
    throw Error("guide: --headless needs an output: --out overlay.mp4, --snapshot-at or "
                "--snapshot-every");
  }
  g_stop = false;
  std::signal(SIGINT, on_signal);
  std::signal(SIGTERM, on_signal);
  req.stop = &g_stop;

  planning::PlanLoadOptions lo;
  lo.blocking = true;
  spdlog::info("guide: loading the plan {}", a.plan);
  const planning::PlanData plan = planning::load_plan(a.plan, lo);
  const overlay::GuideSummary s = overlay::run_guide(plan, req);
  if (!s.video.empty()) spdlog::info("guide: overlay video {}", s.video);
  if (!req.log.empty()) spdlog::info("guide: per-frame log {}", req.log);
}

}  // namespace

void add_guide_command(CLI::App& app) {
  auto a = std::make_shared<GuideArgs>();
  CLI::App* cmd = app.add_subcommand(
      "guide",
      "Needle guidance on the video: tracks the patient and needle boards and draws, with the\n"
      "calibrated camera, (1) safe ray bundles, (2) a volume rendering of path safety, (3) entry\n"
      "areas on the skin with their leeway, (4) the tumor outline, (5) the needle, its line to\n"
      "the tumor coloured by its live safety, the structures it crosses and the angle to the\n"
      "nearest safe direction, (6) tracking state, frame rate and latency. Nothing is drawn from\n"
      "a pose older than --max-age-ms: a lost marker or a corrupt frame is said on screen.\n"
      "Window keys: 1-6 toggle layers, C colour-blind palette, S snapshot, Q or Esc quit.\n"
      "Example: crepuscular guide --plan demo/plan --camera demo/setup/camera.yaml\n"
      "  --registration demo/setup/registration.yaml --needle demo/setup/needle.yaml\n"
      "  --source recording:demo/recording --headless --out demo/overlay.mp4");
  cmd->add_option("--plan", a->plan, "Plan folder (crepuscular plan)")->required();
  cmd->add_option("--camera", a->camera, "Camera calibration (camera.yaml)")->required();
  cmd->add_option("--registration", a->registration,
                  "Patient registration (registration.yaml from crepuscular register)")
      ->required();
  cmd->add_option("--needle", a->needle, "Needle calibration (needle.yaml from calibrate pivot)")
      ->required();
  cmd->add_option("--boards", a->boards,
                  "Marker boards (boards.json); default: the recording's boards.json");
  cmd->add_option("--source", a->source,
                  "Frames: v4l2:/dev/video0?width=1280&height=720&fps=60, recording:DIR[?realtime=1],"
                  " synthetic:SCENE.json")
      ->required();
  cmd->add_flag("--headless", a->headless,
                "No window: write the overlay to --out and snapshots only (no display needed "
                "where EGL is available; else run under xvfb-run -a)");
  cmd->add_option("--out", a->out, "Overlay video to write (.mp4 or .avi), complete or not at all");
  cmd->add_option("--snapshots", a->snapshots_dir,
                  "Folder for PNG snapshots (default: the video's folder, else .)");
  cmd->add_option("--snapshot-at", a->snapshot_at,
                  "Snapshot of a frame: FRAME or FRAME:NAME.png (repeatable)");
  cmd->add_option("--snapshot-every", a->snapshot_every, "Snapshot every N-th frame (0: never)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--log", a->log,
                  "Per-frame CSV (tracking, needle safety, latency); default: the video's name "
                  "with .csv");
  cmd->add_option("--record", a->record,
                  "Also record the incoming frames to this recording folder (replay it later "
                  "with --source recording:DIR)");
  cmd->add_option("--hide", a->hide, "Layers to start hidden: rays, volume, entry, tumor, needle, "
                                     "status (or 1-6)");
  cmd->add_option("--show", a->show, "Layers to start shown (the volume rendering starts hidden)");
  cmd->add_option("--palette", a->palette, "default or colorblind")->capture_default_str();
  cmd->add_option("--volume-classes", a->volume_classes,
                  "Classes the volume rendering shows: any of safe,medium,dangerous")
      ->capture_default_str();
  cmd->add_option("--value", a->value,
                  "Path safety value of the ray bundles (svv, isbv, ivbv, bvv); default: the "
                  "plan's first");
  cmd->add_option("--rays", a->rays, "Directions sampled around the tumor for the ray bundles")
      ->capture_default_str()
      ->check(CLI::Range(1, 200000));
  cmd->add_option("--max-age-ms", a->max_age_ms,
                  "A marker pose older than this is lost: nothing is drawn from it")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  cmd->add_option("--max-frames", a->max_frames, "Stop after this many frames (-1: the whole source)")
      ->capture_default_str();
  cmd->add_option("--video-fps", a->video_fps, "Frame rate written into the video")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  cmd->callback([a] { run(*a); });
}

}  // namespace crepuscular::apps
