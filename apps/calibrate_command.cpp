// `crepuscular calibrate camera` (intrinsics from images or a recording of a chessboard, a ChArUco
// board or a marker board) and `crepuscular calibrate pivot` (needle tip and axis from needle poses).
#include "apps/commands.hpp"
#include "pipelines/calibration.hpp"

namespace crepuscular::apps {

void add_calibrate_command(CLI::App& app) {
  CLI::App* cmd = app.add_subcommand(
      "calibrate",
      "Calibrate the camera (intrinsics) or the needle (tip by pivoting, axis by "
      "spinning). Each writes a file that `crepuscular guide` reads, with the date, "
      "the inputs and the errors.");
  cmd->require_subcommand(1);

  auto c = std::make_shared<pipelines::CameraCalibrationRequest>();
  CLI::App* camera = cmd->add_subcommand(
      "camera",
      "Camera intrinsics (fx fy cx cy k1 k2 p1 p2 k3, or k1..k4 of a fisheye lens with\n"
      "--lens fisheye) from 10-25 views of a flat target,\n"
      "tilted by 20-45 degrees in different directions and reaching every image corner.\n"
      "Refuses, saying what to capture next, when the views cannot determine the parameters.");
  camera->add_option("--images", c->images,
                     "Images of the target: a folder or a quoted glob such as 'shots/*.png'");
  camera->add_option("--recording", c->recording,
                     "A recording folder; frames are picked for coverage of the image");
  camera
      ->add_option("--board", c->board,
                   "The target: boards.json of a marker board (AprilTag or ArUco markers), "
                   "Kalibr's aprilgrid target yaml, "
                   "chessboard:COLSxROWS:SQUARE_MM counting inner corners as OpenCV does "
                   "(chessboard:9x6:25 for a board of 10 x 7 squares of 25 mm), or "
                   "charuco:SQUARES_XxSQUARES_Y:SQUARE_MM:MARKER_MM:DICT counting squares as "
                   "cv::aruco::CharucoBoard does, markers from id 0 "
                   "(charuco:5x7:40:30:DICT_6X6_250); its chessboard corners are used")
      ->required();
  camera->add_option("--board-name", c->board_name,
                     "Which board of boards.json (default: the one with the most tags)");
  camera->add_option("--out", c->out, "Camera file to write (OpenCV YAML)")->capture_default_str();
  camera->add_option("--max-views", c->max_views, "Views kept from a recording")
      ->capture_default_str()
      ->check(in_range(4, 500, true));
  camera->add_option("--min-views", c->min_views, "Fewer usable views are refused")
      ->capture_default_str()
      ->check(in_range(3, 100, true));
  camera->add_flag("--fix-k3", c->fix_k3,
                   "Keep k3 at 0 (narrow lenses, or few views near the image corners)");
  auto lens = std::make_shared<std::string>("pinhole");
  camera
      ->add_option("--lens", *lens,
                   "Lens model: pinhole (Brown-Conrady k1 k2 p1 p2 k3, OpenCV's default) or "
                   "fisheye (equidistant k1..k4, as cv::fisheye and Kalibr; wide-angle lenses "
                   "of 120 degrees or more)")
      ->capture_default_str()
      ->check(CLI::IsMember({"pinhole", "fisheye"}));
  add_detector_options(camera, c->detector);
  camera->callback([c, lens] {
    c->fisheye = *lens == "fisheye";
    claim_run_paths({"calibrate camera",
                     {{"--images", c->images}, {"--recording", c->recording}, {"--board", c->board}},
                     {{"--out", c->out}}});
    pipelines::run_camera_calibration(*c);
  });

  auto p = std::make_shared<pipelines::PivotCalibrationRequest>();
  CLI::App* pivot = cmd->add_subcommand(
      "pivot",
      "Needle tip in the needle board frame: rest the tip in a divot and pivot the needle in a\n"
      "cone of 20-40 degrees for 10-20 s while the camera records. Optionally the needle axis:\n"
      "turn the needle about its own axis in a second capture (--spin-poses/--spin-recording).");
  pivot->add_option("--poses", p->poses,
                    "Poses of the pivoting: a poses CSV (from `crepuscular track --out`) or a PLUS "
                    "sequence file (.igs.mha, .seq.mha, .igs.nrrd; the tracker's frame plays the "
                    "camera's, INVALID transforms are left out)");
  pivot->add_option("--tool", p->tool,
                    "The needle's transform in a PLUS sequence file, e.g. StylusToTracker "
                    "(default: the file's only transform)");
  pivot->add_option("--recording", p->recording, "Recording of the pivoting");
  pivot->add_option("--boards", p->boards,
                    "Marker boards (boards.json); default: the recording's boards.json");
  pivot->add_option("--camera", p->camera,
                    "Camera model (OpenCV YAML); default: the recording's camera.yaml");
  pivot->add_option("--board-name", p->board_name, "The needle board's name")
      ->capture_default_str();
  pivot->add_option("--spin-poses", p->spin_poses,
                    "Poses of the needle turning about its own axis (spin calibration): a poses "
                    "CSV or a PLUS sequence file (--tool names its transform)");
  pivot->add_option("--spin-recording", p->spin_recording,
                    "Recording of the needle turning about its own axis (spin calibration)");
  pivot
      ->add_option("--min-rotation-deg", p->min_rotation_deg,
                   "Refuse when the needle turned less than this")
      ->capture_default_str();
  pivot
      ->add_option("--max-tip-stddev-mm", p->max_tip_stddev_mm,
                   "Refuse a tip whose 3D standard deviation from the fit (square root of the\n"
                   "trace of its covariance: the RMS tip error to expect) is larger")
      ->capture_default_str();
  pivot
      ->add_option("--warn-rms-mm", p->warn_rms_mm,
                   "Warn (not refuse) when the residual RMS of the poses is larger: a noisy\n"
                   "recording is usable when the tip's standard deviation passes")
      ->capture_default_str();
  pivot->add_option("--out", p->out, "Needle file to write (YAML)")->capture_default_str();
  pivot->callback([p] {
    claim_run_paths({"calibrate pivot",
                     {{"--poses", p->poses},
                      {"--recording", p->recording},
                      {"--boards", p->boards},
                      {"--camera", p->camera},
                      {"--spin-poses", p->spin_poses},
                      {"--spin-recording", p->spin_recording}},
                     {{"--out", p->out}}});
    pipelines::run_pivot_calibration(*p);
  });
}

}  // namespace crepuscular::apps
