// `crepuscular guide`: the AR needle guidance on live video, a recording or a synthetic scene.
#include <filesystem>

#include "apps/commands.hpp"
#include "apps/enum_names.hpp"
#include "foundation/error.hpp"
#include "pipelines/guide.hpp"
#include "pipelines/session_inputs.hpp"
#include "planning/views/slices.hpp"

namespace crepuscular::apps {

namespace {

struct GuideArgs {
  pipelines::GuideRequest req;  // the flags that map one to one
  std::string plan, camera, registration, needle, boards, volume_classes = "safe,medium";
  bool headless = false;
  std::vector<overlay::GuidanceLayer> hide, show;
};

void run(GuideArgs& a) {
  pipelines::GuideRequest& req = a.req;
  if (req.source.empty() && req.poses.empty()) {
    throw Error("guide: give --source (video; the camera tracks the markers), --poses (a "
                "tracking server's poses over OpenIGTLink, drawn from a virtual camera) or both");
  }
  if (!req.source.empty() && a.camera.empty()) throw Error("guide: --camera is required with --source");
  if (req.log.empty() && !req.video.empty()) {
    req.log = std::filesystem::path(req.video).replace_extension(".csv").string();
  }
  claim_run_paths({"guide",
                   {{"--plan", a.plan},
                    {"--camera", a.camera},
                    {"--registration", a.registration},
                    {"--needle", a.needle},
                    {"--boards", a.boards},
                    {"--source", source_path(req.source)}},
                   {{"--out", req.video},
                    {"--log", req.log},
                    {"--snapshots", req.snapshot_dir, OutputKind::kFilesInFolder},
                    {"--record", req.record, OutputKind::kFolder},
                    {"--record-poses", req.record_poses}}});
  req.setup = pipelines::read_guidance_setup(a.camera, a.registration, a.needle);
  if (!req.source.empty() || !a.boards.empty()) {
    req.boards = tracking::read_boards(pipelines::session_boards_file(a.boards, req.source, "guide"));
  }
  req.window = !a.headless;
  // parse_hidden_classes takes the classes to hide; the option names those to show.
  const auto shown = planning::parse_hidden_classes(a.volume_classes);
  for (size_t c = 0; c < 3; ++c) req.options.volume_classes[c] = shown[c];
  for (const auto l : a.hide) req.options.visible[size_t(l)] = false;
  for (const auto l : a.show) req.options.visible[size_t(l)] = true;
  if (a.headless && req.video.empty() && req.snapshots.empty() && req.snapshot_every <= 0) {
    throw Error(
        "guide: --headless needs an output: --out overlay.mp4, --snapshot-at or --snapshot-every");
  }
  req.stop = stop_on_signals();
  pipelines::run_guide(a.plan, req);
}

}  // namespace

void add_guide_command(CLI::App& app) {
  auto a = std::make_shared<GuideArgs>();
  pipelines::GuideRequest& r = a->req;
  CLI::App* cmd = app.add_subcommand(
      "guide",
      "Needle guidance on the video: tracks the patient and needle boards and draws, with the\n"
      "calibrated camera, (1) safe ray bundles, (2) a volume rendering of path safety, (3) entry\n"
      "areas on the skin with their leeway, (4) the tumor outline, (5) the needle, its line to\n"
      "the tumor coloured by its live safety, the structures it crosses and the angle to the\n"
      "nearest safe direction, (6) tracking state, frame rate and latency, (7) the targeting view:\n"
      "a picture-in-picture looking down the needle at the tumor, with a cross where the\n"
      "extended needle meets the plane through the tumor centre and, around it, the safety of\n"
      "the paths the needle takes when tilted by up to 12.5 deg about its skin entry (green:\n"
      "safe, yellow: medium, red: dangerous, grey: unknown): tilt toward green. Nothing is drawn from\n"
      "a pose older than --max-age-ms: a lost marker or a corrupt frame is said on screen.\n"
      "The needle's line comes with its 95 % uncertainty (the boards' pose errors, the needle\n"
      "calibration's and the registration's expected TRE): its size at the tumor in the panel,\n"
      "its ellipse in the targeting view, and UNCERTAIN when a line within it is less safe.\n"
      "A plan made over a breathing cycle with --per-phase is guided phase by phase: the phase\n"
      "from the patient board's rise and fall on the skin, a gating bar of the needle line's\n"
      "class in every phase, the tumor where it is in the current phase.\n"
      "Window keys: 1-7 toggle layers, C colour-blind palette, S snapshot, Q or Esc quit.\n"
      "Example: crepuscular guide --plan demo/plan --camera demo/setup/camera.yaml\n"
      "  --registration demo/setup/registration.yaml --needle demo/setup/needle.yaml\n"
      "  --source recording:demo/recording --headless --out demo/overlay.mp4");
  cmd->add_option("--plan", a->plan, "Plan folder (crepuscular plan)")->required();
  cmd->add_option("--camera", a->camera,
                  "Camera calibration (camera.yaml); with --poses: the virtual camera's (default "
                  "1280x720, 1000 px focal length)");
  cmd->add_option("--registration", a->registration,
                  "Patient registration (registration.yaml from crepuscular register)")
      ->required();
  cmd->add_option("--needle", a->needle, "Needle calibration (needle.yaml from calibrate pivot)")
      ->required();
  cmd->add_option("--boards", a->boards,
                  "Marker boards (boards.json); default: the recording's boards.json");
  cmd->add_option("--source", r.source,
                  "Frames: v4l2:/dev/video0?width=1280&height=720&fps=60, "
                  "recording:DIR[?realtime=1], synthetic:SCENE.json, plus:FILE.igs.mha[?realtime=1] "
                  "(a PLUS sequence file's image frames) (or --poses instead)");
  cmd->add_flag("--headless", a->headless,
                "No window: write the overlay to --out and snapshots only (no display needed "
                "where EGL is available; else run under xvfb-run -a)");
  cmd->add_option("--out", r.video,
                  "Overlay video to write (.mp4 or .avi), complete or not at all");
  cmd->add_option("--snapshots", r.snapshot_dir,
                  "Folder for PNG snapshots (default: the video's folder, else .)");
  cmd->add_option("--snapshot-at", "Snapshot of a frame: FRAME or FRAME:NAME.png (repeatable)")
      ->multi_option_policy(CLI::MultiOptionPolicy::TakeAll)
      ->each([&r](const std::string& s) { r.snapshots.push_back(pipelines::parse_snapshot(s)); });
  cmd->add_option("--snapshot-every", r.snapshot_every, "Snapshot every N-th frame (0: never)")
      ->capture_default_str()
      ->check(in_range(0, 1e9, true));
  cmd->add_option("--log", r.log,
                  "Per-frame CSV (tracking, needle safety, latency); default: the video's name "
                  "with .csv");
  cmd->add_option("--poses", r.poses,
                  "Take the needle and patient poses from a tracking server (PLUS, ...) over "
                  "OpenIGTLink instead of the camera: igtl://HOST:PORT connects to it, "
                  "igtl-server:PORT lets it connect; TRANSFORM or TDATA. Without --source: no "
                  "video, a virtual camera looks at the plan from the front. With --source: the "
                  "camera tracks the patient board, the tracker the needle relative to it. "
                  "plus:FILE.igs.mha replays a PLUS sequence file instead (3D Slicer's and PLUS's "
                  "recordings; ?realtime=1 at its recorded pace, else as fast as possible), one "
                  "virtual camera frame per sequence frame, INVALID transforms lost");
  cmd->add_option("--poses-needle", r.poses_needle, "Device name of the needle's pose")
      ->capture_default_str();
  cmd->add_option("--poses-patient", r.poses_patient,
                  "Device name of the patient reference's pose (\"\": the tracker's frame is the "
                  "patient board's)")
      ->capture_default_str();
  cmd->add_option("--poses-fps", r.poses_fps, "Frame rate of the virtual camera")
      ->check(in_range(1, 240))
      ->capture_default_str();
  cmd->add_option("--igtl-server", r.igtl_port,
                  "Serve OpenIGTLink on this TCP port (Slicer's default: 18944) to 3D Slicer's "
                  "OpenIGTLinkIF and other clients: NeedleToCT, PatientToCT, NeedleTipToNeedle "
                  "(TRANSFORM), NeedleSafety and, for breathing plans, BreathingPhase (STRING), Target "
                  "(POINT), PlannedTrajectory (TRAJ), STATUS for a lost marker; 0: any free port")
      ->check(in_range(0, 65535, true));
  cmd->add_option("--record", r.record,
                  "Also record the incoming frames to this recording folder (replay it later "
                  "with --source recording:DIR)");
  cmd->add_option("--record-poses", r.record_poses,
                  "Also write the session's poses as a PLUS sequence file (FILE.igs.mha) that 3D "
                  "Slicer's Sequences module and PLUS replay: each board in the camera "
                  "(PatientToCamera, NeedleToCamera; INVALID while lost), the needle in the CT "
                  "(NeedleToCT), its class and the frame's timestamp");
  cmd->add_option("--hide", a->hide,
                  "Layers to start hidden: rays, volume, entry, tumor, needle, status, target (or 1-7)")
      ->transform(enum_names(guidance_layer_names()));
  cmd->add_option("--show", a->show, "Layers to start shown (the volume rendering starts hidden)")
      ->transform(enum_names(guidance_layer_names()));
  cmd->add_option("--palette", r.options.palette, "default or colorblind")
      ->transform(enum_names(palette_names()))
      ->default_str("default");
  cmd->add_option("--volume-classes", a->volume_classes,
                  "Classes the volume rendering shows: any of safe,medium,dangerous")
      ->check(safety_class_list())
      ->capture_default_str();
  cmd->add_option("--value", r.options.value,
                  "Path safety value of the ray bundles (svv, isbv, ivbv, bvv); default: the "
                  "plan's first");
  cmd->add_option("--rays", r.options.ray_directions,
                  "Directions sampled around the tumor for the ray bundles")
      ->capture_default_str()
      ->check(in_range(1, 200000, true));
  cmd->add_option("--max-age-ms", r.tracker.max_age_ms,
                  "A marker pose older than this is lost: nothing is drawn from it")
      ->capture_default_str()
      ->check(in_range(1, 10000));
  add_detector_options(cmd, r.tracker.detector);
  cmd->add_option("--max-frames", r.max_frames,
                  "Stop after this many frames (-1: the whole source)")
      ->capture_default_str();
  cmd->add_option("--video-fps", r.video_fps, "Frame rate written into the video")
      ->capture_default_str()
      ->check(in_range(1, 240));
  cmd->callback([a] { run(*a); });
}

}  // namespace crepuscular::apps
