// `crepuscular synth`: renders a synthetic recording with ground truth (a scene file, or the
// built-in guidance scene).
#include "apps/commands.hpp"
#include "pipelines/record.hpp"

namespace crepuscular::apps {

void add_synth_command(CLI::App& app) {
  auto args = std::make_shared<pipelines::SynthRequest>();
  CLI::App* cmd = app.add_subcommand(
      "synth",
      "Render synthetic camera frames of marker boards at known poses, as a recording. It replays\n"
      "with `crepuscular track --source recording:DIR`, and its ground truth measures tracking\n"
      "accuracy in millimetres. Boards are drawn at scripted poses through the camera\n"
      "model (distortion included) onto a background, with optional noise, blur, lighting,\n"
      "occlusions, dropped and corrupt frames; tag corners land where the camera model projects\n"
      "them (sub-pixel, anti-aliased).\n"
      "\n"
      "Without --scene it renders the built-in guidance scene: the patient board (2 x 3 tags of\n"
      "40 mm, tag36h11 ids 0-5, with 4 CT fiducials at its corners) 50 to 58 cm from a 1280 x 720\n"
      "camera, and the needle board (2 x 2 tags of 20 mm, ids 10-13) whose needle tip moves "
      "toward\n"
      "the phantom's tumor over 3 s at 30 fps.\n"
      "\n"
      "Writes the recording folder DIR (docs/ARCHITECTURE.md §8):\n"
      "  frames/000000.jpg ...  the frames (gaps in the numbers are dropped frames)\n"
      "  frames.csv             frame,timestamp_ns,file\n"
      "  ground_truth.csv       frame,timestamp_ns,board,state,tx,ty,tz,qw,qx,qy,qz,rms_px\n"
      "                         (T_cam_board in mm, the format `crepuscular track --out` writes)\n"
      "  boards.json            the boards, for `crepuscular track --boards`\n"
      "  camera.yaml            the camera model (OpenCV FileStorage YAML)\n"
      "  session.json           source, date, boards, frame count\n"
      "While it renders, the folder is DIR.partial (already replayable); it is renamed at the "
      "end.\n"
      "The scene file format is described in tracking/synthetic.hpp (read_scene). Next step:\n"
      "  crepuscular track --source recording:DIR --boards DIR/boards.json --out poses.csv");
  cmd->add_option("--scene", args->scene,
                  "Scene JSON (camera, background, boards, pose keyframes, frames, noise, blur, "
                  "lighting, occlusions, dropped and corrupt frames); default: the built-in scene")
      ->check(CLI::ExistingFile);
  cmd->add_option("--out", args->out, "Output recording folder (DIR); must not exist")->required();
  cmd->add_option("--format", args->format, "Frame image format: jpg or png (lossless)")
      ->capture_default_str()
      ->check(CLI::IsMember({"jpg", "png"}));
  cmd->add_option("--quality", args->quality, "JPEG quality, 1 to 100")
      ->capture_default_str()
      ->check(in_range(1, 100, true));
  cmd->add_option("--frames", args->frames,
                  "Render at most this many frames (default: all frames of the scene)")
      ->check(in_range(1, 1e7, true));
  cmd->add_option("--breathing", args->breaths_per_minute,
                  "A breathing patient: the patient board rises and falls this many times a "
                  "minute (12-20 at rest), off the skin toward the camera; writes breathing.csv "
                  "(frame, timestamp_ns, cycle_fraction, rise_mm) beside the ground truth")
      ->check(in_range(1, 60, true));
  cmd->add_option("--rise", args->rise_mm,
                  "How far the board rises at end-inhale, mm (the anterior abdominal wall: 5-15)")
      ->capture_default_str()
      ->check(in_range(0.1, 50, true));
  cmd->callback([args] {
    claim_run_paths({"synth", {{"--scene", args->scene}}, {{"--out", args->out, OutputKind::kFolder}}});
    pipelines::run_synth(*args);
  });
}

}  // namespace crepuscular::apps
