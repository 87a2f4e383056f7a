// `crepuscular calibrate camera` (intrinsics from images or a recording of a chessboard or an
// AprilTag grid board) and `crepuscular calibrate pivot` (needle tip and axis from needle poses).
#include <spdlog/spdlog.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "apps/commands.hpp"
#include "calibration/calibration_files.hpp"
#include "calibration/camera_model.hpp"
#include "calibration/intrinsics.hpp"
#include "calibration/pivot.hpp"
#include "kernels/error.hpp"
#include "recordings/recording.hpp"
#include "tracking/board.hpp"
#include "tracking/detector.hpp"
#include "tracking/frame_source.hpp"
#include "tracking/pose.hpp"
#include "tracking/poses_csv.hpp"
#include "tracking/tracker.hpp"

namespace crepuscular::apps {

namespace {

namespace fs = std::filesystem;

struct CameraArgs {
  std::string images;
  std::string recording;
  std::string board;
  std::string board_name;
  std::string out = "camera.yaml";
  int max_views = 40;
  int min_views = 4;
  bool fix_k3 = false;
  double decimate = 1.0;
};

// Image files of a quoted glob ('DIR/*.png') or of a folder (png, jpg, jpeg, bmp, tif, tiff).
std::vector<std::string> list_images(const std::string& spec) {
  std::vector<std::string> files;
  if (fs::is_directory(spec)) {
    for (const auto& entry : fs::directory_iterator(spec)) {
      std::string ext = entry.path().extension().string();
      std::transform(ext.begin(), ext.end(), ext.begin(), ::tolower);
      if (entry.is_regular_file() && (ext == ".png" || ext == ".jpg" || ext == ".jpeg" ||
                                      ext == ".bmp" || ext == ".tif" || ext == ".tiff")) {
        files.push_back(entry.path().string());
      }
    }
  } else {
    std::vector<cv::String> found;
    try {
      cv::glob(spec, found, false);
    } catch (const cv::Exception&) {
      found.clear();
    }
    for (const auto& f : found) files.push_back(f);
  }
  std::sort(files.begin(), files.end());
  if (files.empty()) {
    throw Error("calibrate camera: --images " + spec +
                ": no image files (give a folder or a quoted glob such as 'shots/*.png')");
  }
  return files;
}

// Finds the target in one image: a chessboard, or the tags of an AprilTag board.
class TargetFinder {
 public:
  explicit TargetFinder(const CameraArgs& a) {
    chessboard_ = calibration::parse_chessboard_spec(a.board);
    if (chessboard_) {
      description_ = a.board;
      return;
    }
    const std::vector<tracking::Board> boards = tracking::read_boards(a.board);
    const tracking::Board* chosen = nullptr;
    for (const auto& b : boards) {
      if (!a.board_name.empty() ? b.name == a.board_name
                                : (!chosen || b.tags.size() > chosen->tags.size())) {
        chosen = &b;
      }
    }
    if (!chosen) {
      throw Error(a.board + ": no board named \"" + a.board_name + "\" (--board-name)");
    }
    board_ = *chosen;
    for (const auto& t : board_.tags) {
      for (const auto& c : t.corners) {
        if (std::abs(c.z()) > 1e-6) {
          throw Error(a.board + ": board \"" + board_.name +
                      "\" is not planar in its z = 0 plane (camera calibration needs a flat "
                      "target)");
        }
      }
    }
    tracking::DetectorOptions o;
    o.family = board_.family;
    o.decimate = a.decimate;
    detector_ = std::make_unique<tracking::TagDetector>(o);
    description_ = a.board + " (board " + board_.name + ", " + std::to_string(board_.tags.size()) +
                   " tags)";
  }

  std::optional<calibration::CalibrationView> find(const cv::Mat& image, const std::string& name) {
    if (chessboard_) return calibration::detect_chessboard(image, *chessboard_, name);
    const auto corners = tracking::match_board_corners(board_, detector_->detect(image));
    if (corners.board_mm.size() < 8) return std::nullopt;  // at least two tags
    calibration::CalibrationView v;
    v.name = name;
    v.object_points = corners.board_mm;
    v.image_points = corners.pixels;
    return v;
  }
  const std::string& description() const { return description_; }

 private:
  std::optional<calibration::ChessboardSpec> chessboard_;
  tracking::Board board_;
  std::unique_ptr<tracking::TagDetector> detector_;
  std::string description_;
};

void run_calibrate_camera(const CameraArgs& a) {
  if (a.images.empty() == a.recording.empty()) {
    throw Error("calibrate camera: give either --images or --recording");
  }
  TargetFinder finder(a);
  std::vector<calibration::CalibrationView> views;
  std::vector<std::string> inputs;
  int width = 0, height = 0;
  auto check_size = [&](const cv::Mat& image, const std::string& name) {
    if (width == 0) {
      width = image.cols;
      height = image.rows;
    } else if (image.cols != width || image.rows != height) {
      throw Error("calibrate camera: " + name + " is " + std::to_string(image.cols) + " x " +
                  std::to_string(image.rows) + " pixels, the first image " + std::to_string(width) +
                  " x " + std::to_string(height) + " (one camera, one resolution)");
    }
  };
  if (!a.images.empty()) {
    const std::vector<std::string> files = list_images(a.images);
    inputs.push_back(a.images);
    for (size_t i = 0; i < files.size(); ++i) {
      const cv::Mat image = cv::imread(files[i], cv::IMREAD_COLOR);
      if (image.empty()) {
        spdlog::warn("calibrate camera: {} cannot be read as an image; skipped", files[i]);
        continue;
      }
      check_size(image, files[i]);
      auto v = finder.find(image, fs::path(files[i]).filename().string());
      spdlog::info("calibrate camera: {} ({}/{}): {}", files[i], i + 1, files.size(),
                   v ? std::to_string(v->image_points.size()) + " corners" : "target not found");
      if (v) views.push_back(std::move(*v));
    }
  } else {
    recordings::RecordingReader reader(a.recording);
    inputs.push_back(a.recording);
    const size_t n = reader.entries().size();
    // Look at up to 6 frames per wanted view, spread over the recording.
    const size_t step = std::max<size_t>(1, n / size_t(std::max(1, 6 * a.max_views)));
    for (size_t i = 0; i < n; i += step) {
      const auto loaded = reader.load(i);
      if (loaded.image.empty()) {
        spdlog::warn("calibrate camera: frame {}: {}", reader.entries()[i].frame, loaded.problem);
        continue;
      }
      check_size(loaded.image, reader.entries()[i].file);
      auto v = finder.find(loaded.image, "frame " + std::to_string(reader.entries()[i].frame));
      if (v) views.push_back(std::move(*v));
      if ((i / step) % 20 == 0) {
        spdlog::info("calibrate camera: frame {}/{}: target in {} frames so far", i + 1, n,
                     views.size());
      }
    }
    if (views.size() > size_t(a.max_views)) {
      const auto picked =
          calibration::select_views_for_coverage(views, width, height, size_t(a.max_views));
      std::vector<calibration::CalibrationView> chosen;
      for (size_t k : picked) chosen.push_back(views[k]);
      spdlog::info("calibrate camera: {} of {} frames with the target picked for coverage",
                   chosen.size(), views.size());
      views = std::move(chosen);
    }
  }
  if (width == 0) throw Error("calibrate camera: no readable image");
  calibration::IntrinsicsOptions o;
  o.min_views = a.min_views;
  o.fix_k3 = a.fix_k3;
  const calibration::IntrinsicsResult r = calibration::calibrate_intrinsics(views, width, height, o);
  calibration::write_camera_calibration(a.out, r, finder.description(), inputs);
  const auto& names = calibration::intrinsic_parameter_names();
  const std::array<double, 9> values = {r.camera.fx, r.camera.fy, r.camera.cx, r.camera.cy,
                                        r.camera.distortion[0], r.camera.distortion[1],
                                        r.camera.distortion[2], r.camera.distortion[3],
                                        r.camera.distortion[4]};
  for (size_t p = 0; p < 9; ++p) {
    spdlog::info("  {:>2} = {:>12.6f} +- {:.6f}", names[p], values[p], r.stddev[p]);
  }
  for (const auto& v : r.views) {
    if (v.points == 0) continue;
    spdlog::info("  view {:<24} {:>4} corners  RMS {:.3f} px  tilt {:5.1f} deg{}", v.name, v.points,
                 v.rms_px, v.tilt_deg, v.rejected ? "  REJECTED" : "");
  }
  spdlog::info("calibrate camera: RMS reprojection error {:.3f} px over {} views; {} written",
               r.rms_px, r.views_used, a.out);
}

struct PivotArgs {
  std::string poses;
  std::string recording;
  std::string boards;
  std::string camera;
  std::string board_name = "needle";
  std::string spin_poses;
  std::string spin_recording;
  std::string out = "needle.yaml";
  double min_rotation_deg = 15.0;
};

// The needle board's measured poses from a poses CSV (tracked rows only).
std::vector<Eigen::Isometry3d> poses_from_csv(const std::string& path, const std::string& board) {
  std::vector<Eigen::Isometry3d> out;
  for (const auto& r : tracking::read_poses_csv(path)) {
    if (r.board == board && r.tracked) out.push_back(r.T_cam_board);
  }
  if (out.empty()) {
    throw Error(path + ": no tracked rows for board \"" + board + "\" (--board-name)");
  }
  return out;
}

// The board's pose measured in every frame of a recording (no smoothing, no prediction).
std::vector<Eigen::Isometry3d> poses_from_recording(const std::string& dir,
                                                    const std::string& boards_arg,
                                                    const std::string& camera_arg,
                                                    const std::string& board) {
  std::unique_ptr<tracking::FrameSource> source = tracking::open_frame_source("recording:" + dir);
  std::string boards_path = boards_arg;
  if (boards_path.empty() && fs::exists(dir + "/boards.json")) boards_path = dir + "/boards.json";
  if (boards_path.empty()) {
    throw Error("--boards is required (the recording " + dir + " brings no boards.json)");
  }
  calibration::CameraModel camera;
  if (!camera_arg.empty()) {
    camera = calibration::CameraModel::read_yaml(camera_arg);
  } else if (auto c = source->camera()) {
    camera = *c;
  } else {
    throw Error("--camera is required (the recording " + dir + " brings no camera.yaml)");
  }
  std::vector<tracking::Board> boards;
  for (const auto& b : tracking::read_boards(boards_path)) {
    if (b.name == board) boards.push_back(b);
  }
  if (boards.empty()) throw Error(boards_path + ": no board named \"" + board + "\"");
  tracking::TrackerOptions o;
  o.detector.family = boards.front().family;
  o.smoothing = false;
  tracking::Tracker tracker(camera, boards, o);
  std::vector<Eigen::Isometry3d> out;
  int64_t frames = 0;
  while (auto frame = source->next()) {
    const tracking::TrackResult r = tracker.process(*frame);
    for (const auto& s : r.boards) {
      if (s.measured) out.push_back(s.T_measured);
    }
    if (++frames % 100 == 0) spdlog::info("{}: {} frames, board measured in {}", dir, frames, out.size());
  }
  spdlog::info("{}: board \"{}\" measured in {} of {} frames", dir, board, out.size(), frames);
  return out;
}

void run_calibrate_pivot(const PivotArgs& a) {
  if (a.poses.empty() == a.recording.empty()) {
    throw Error("calibrate pivot: give either --poses or --recording");
  }
  if (!a.spin_poses.empty() && !a.spin_recording.empty()) {
    throw Error("calibrate pivot: give at most one of --spin-poses and --spin-recording");
  }
  const std::vector<Eigen::Isometry3d> poses =
      !a.poses.empty() ? poses_from_csv(a.poses, a.board_name)
                       : poses_from_recording(a.recording, a.boards, a.camera, a.board_name);
  calibration::PivotOptions po;
  po.min_rotation_spread_deg = a.min_rotation_deg;
  const calibration::PivotResult p = calibration::calibrate_pivot(poses, po);
  calibration::NeedleCalibration n;
  n.date = calibration::utc_timestamp();
  n.inputs.push_back(!a.poses.empty() ? a.poses : a.recording);
  n.board = a.board_name;
  n.tip_needle = p.tip_needle;
  n.tip_stddev_mm = p.tip_stddev_mm;
  n.pivot_rms_mm = p.rms_mm;
  n.poses_used = p.inliers;
  n.poses_total = int(poses.size());
  n.rotation_spread_deg = p.rotation_spread_deg;
  if (!a.spin_poses.empty() || !a.spin_recording.empty()) {
    const std::vector<Eigen::Isometry3d> spin =
        !a.spin_poses.empty()
            ? poses_from_csv(a.spin_poses, a.board_name)
            : poses_from_recording(a.spin_recording, a.boards, a.camera, a.board_name);
    const calibration::SpinResult s = calibration::calibrate_spin(spin, p.tip_needle);
    n.inputs.push_back(!a.spin_poses.empty() ? a.spin_poses : a.spin_recording);
    n.axis_needle = s.axis_needle;
    n.axis_rms_deg = s.axis_rms_deg;
    n.tip_to_axis_mm = s.tip_to_axis_mm.value_or(0.0);
    spdlog::info("calibrate pivot: axis ({:.4f}, {:.4f}, {:.4f}), tip {:.2f} mm from the axis",
                 s.axis_needle.x(), s.axis_needle.y(), s.axis_needle.z(), n.tip_to_axis_mm);
  }
  calibration::write_needle_calibration(a.out, n);
  spdlog::info("calibrate pivot: tip ({:.3f}, {:.3f}, {:.3f}) mm +- ({:.3f}, {:.3f}, {:.3f}) in the "
               "needle frame; RMS {:.3f} mm over {} of {} poses; {} written",
               p.tip_needle.x(), p.tip_needle.y(), p.tip_needle.z(), p.tip_stddev_mm.x(),
               p.tip_stddev_mm.y(), p.tip_stddev_mm.z(), p.rms_mm, p.inliers, poses.size(), a.out);
}

}  // namespace

void add_calibrate_command(CLI::App& app) {
  CLI::App* cmd = app.add_subcommand(
      "calibrate", "Calibrate the camera (intrinsics) or the needle (tip by pivoting, axis by "
                   "spinning). Each writes a file that `crepuscular guide` reads, with the date, "
                   "the inputs and the errors.");
  cmd->require_subcommand(1);

  auto c = std::make_shared<CameraArgs>();
  CLI::App* camera = cmd->add_subcommand(
      "camera",
      "Camera intrinsics (fx fy cx cy k1 k2 p1 p2 k3) from 10-25 views of a flat target,\n"
      "tilted by 20-45 degrees in different directions and reaching every image corner.\n"
      "Refuses, saying what to capture next, when the views cannot determine the parameters.");
  camera->add_option("--images", c->images,
                     "Images of the target: a folder or a quoted glob such as 'shots/*.png'");
  camera->add_option("--recording", c->recording,
                     "A recording folder; frames are picked for coverage of the image");
  camera
      ->add_option("--board", c->board,
                   "The target: boards.json of an AprilTag grid board, or "
                   "chessboard:COLSxROWS:SQUARE_MM counting inner corners as OpenCV does "
                   "(chessboard:9x6:25 for a board of 10 x 7 squares of 25 mm)")
      ->required();
  camera->add_option("--board-name", c->board_name,
                     "Which board of boards.json (default: the one with the most tags)");
  camera->add_option("--out", c->out, "Camera file to write (OpenCV YAML)")
      ->capture_default_str();
  camera->add_option("--max-views", c->max_views, "Views kept from a recording")
      ->capture_default_str()
      ->check(CLI::Range(4, 500));
  camera->add_option("--min-views", c->min_views, "Fewer usable views are refused")
      ->capture_default_str()
      ->check(CLI::Range(3, 100));
  camera->add_flag("--fix-k3", c->fix_k3,
                   "Keep k3 at 0 (narrow lenses, or few views near the image corners)");
  camera->add_option("--decimate", c->decimate,
                     "AprilTag quad detection on an image decimated by this factor")
      ->capture_default_str()
      ->check(CLI::Range(1.0, 4.0));
  camera->callback([c] { run_calibrate_camera(*c); });

  auto p = std::make_shared<PivotArgs>();
  CLI::App* pivot = cmd->add_subcommand(
      "pivot",
      "Needle tip in the needle board frame: rest the tip in a divot and pivot the needle in a\n"
      "cone of 20-40 degrees for 10-20 s while the camera records. Optionally the needle axis:\n"
      "turn the needle about its own axis in a second capture (--spin-poses/--spin-recording).");
  pivot->add_option("--poses", p->poses,
                    "Poses CSV of the pivoting (from `crepuscular track --out`)");
  pivot->add_option("--recording", p->recording, "Recording of the pivoting");
  pivot->add_option("--boards", p->boards,
                    "Marker boards (boards.json); default: the recording's boards.json");
  pivot->add_option("--camera", p->camera,
                    "Camera model (OpenCV YAML); default: the recording's camera.yaml");
  pivot->add_option("--board-name", p->board_name, "The needle board's name")
      ->capture_default_str();
  pivot->add_option("--spin-poses", p->spin_poses,
                    "Poses CSV of the needle turning about its own axis (spin calibration)");
  pivot->add_option("--spin-recording", p->spin_recording,
                    "Recording of the needle turning about its own axis (spin calibration)");
  pivot->add_option("--min-rotation-deg", p->min_rotation_deg,
                    "Refuse when the needle turned less than this")
      ->capture_default_str();
  pivot->add_option("--out", p->out, "Needle file to write (YAML)")->capture_default_str();
  pivot->callback([p] { run_calibrate_pivot(*p); });
}

}  // namespace crepuscular::apps
