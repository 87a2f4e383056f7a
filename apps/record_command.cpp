// `crepuscular record`: records any frame source (camera, recording, synthetic scene) into a
// recording folder.
#include "apps/commands.hpp"
#include "pipelines/record.hpp"

namespace crepuscular::apps {

void add_record_command(CLI::App& app) {
  auto args = std::make_shared<pipelines::RecordRequest>();
  CLI::App* cmd = app.add_subcommand(
      "record",
      "Record frames from a source into a recording folder, which `crepuscular track` and the\n"
      "training simulators replay. It holds frames/, frames.csv with capture timestamps,\n"
      "camera.yaml, session.json, and ground_truth.csv when the source has truth.\n"
      "\n"
      "Sources:\n"
      "  v4l2:/dev/video0?width=1280&height=720&fps=60[&format=mjpeg|yuyv]   a camera (MJPEG\n"
      "      frames are stored as received, corrupt ones included; the camera is reopened if it\n"
      "      disappears, and the gap shows as missing frame numbers)\n"
      "  recording:DIR[?realtime=1&loop=1]   another recording (copy, cut with "
      "--frames/--seconds)\n"
      "  synthetic:SCENE.json | synthetic:builtin   rendered frames with ground truth\n"
      "  plus:FILE.igs.mha[?realtime=1]   a PLUS sequence file's image frames (.igs.mha, .seq.mha,\n"
      "      .igs.nrrd), its transforms kept as the frames' poses\n"
      "\n"
      "The recording is written frame by frame into DIR.partial and renamed to DIR when it ends\n"
      "(--frames or --seconds reached, the source ended, or Ctrl-C). If the recorder is killed,\n"
      "DIR.partial stays and replays up to its last complete frame:\n"
      "  crepuscular track --source recording:DIR.partial ...");
  cmd->add_option("--source", args->source, "Frame source URI (see above)")->required();
  cmd->add_option("--out", args->out,
                  "Output recording folder (DIR); must not exist. With --format plus: the "
                  "sequence file (FILE.igs.mha)")
      ->required();
  cmd->add_option("--frames", args->frames, "Stop after this many frames (default: no limit)")
      ->check(in_range(1, 1e9, true));
  cmd->add_option("--seconds", args->seconds,
                  "Stop after this much capture time in seconds (default: no limit)")
      ->check(in_range(0.001, 86400));
  cmd->add_option("--format", args->format,
                  "Frame image format: jpg (camera MJPEG stored as received), png (lossless), or "
                  "plus: one PLUS sequence file (.igs.mha) that 3D Slicer's Sequences module and "
                  "PLUS replay: RGB frames, timestamps, the frames' poses as <Board>ToCamera "
                  "transforms")
      ->capture_default_str()
      ->check(CLI::IsMember({"jpg", "png", "plus"}));
  cmd->add_option("--quality", args->quality, "JPEG quality for frames that are encoded here")
      ->capture_default_str()
      ->check(in_range(1, 100, true));
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
    claim_run_paths({"record",
                     {{"--source", source_path(args->source)},
                      {"--boards", args->boards},
                      {"--camera", args->camera},
                      {"--plan", args->plan}},
                     {{"--out", args->out,
                       args->format == "plus" ? OutputKind::kFile : OutputKind::kFolder}}});
    args->stop = stop_on_signals();
    pipelines::run_record(*args);
  });
}

}  // namespace crepuscular::apps
