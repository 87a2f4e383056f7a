// Camera and needle calibration from captured data: finding the target in images or recording
// frames, picking frames, measuring the needle board's poses, and writing the calibration files.
#include "pipelines/calibration.hpp"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <memory>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <optional>
#include <vector>

#include "calibration/aruco.hpp"
#include "calibration/pivot.hpp"
#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "pipelines/session_inputs.hpp"
#include "recordings/recording.hpp"
#include "tracking/board.hpp"
#include "tracking/detector.hpp"
#include "tracking/frame_source.hpp"
#include "tracking/pose.hpp"
#include "recordings/plus_sequence.hpp"
#include "tracking/poses_csv.hpp"
#include "tracking/tracker.hpp"

namespace fs = std::filesystem;

namespace crepuscular::pipelines {

namespace {

// Image files of a glob ('DIR/*.png') or of a folder (png, jpg, jpeg, bmp, tif, tiff).
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
    throw Error("calibrate camera: images " + spec +
                ": no image files (give a folder or a quoted glob such as 'shots/*.png')");
  }
  return files;
}

// Finds the target in one image: a chessboard, a ChArUco board, or the tags of a marker board.
class TargetFinder {
 public:
  explicit TargetFinder(const CameraCalibrationRequest& a) {
    chessboard_ = calibration::parse_chessboard_spec(a.board);
    charuco_ = calibration::parse_charuco_spec(a.board);
    if (chessboard_ || charuco_) {
      description_ = a.board;
      return;
    }
    board_ = choose_board(a.board, a.board_name);
    tracking::DetectorOptions o = a.detector;
    o.family = board_.family;
    detector_ = std::make_unique<tracking::TagDetector>(o);
    description_ =
        a.board + " (board " + board_.name + ", " + std::to_string(board_.tags.size()) + " tags)";
  }

  std::optional<calibration::CalibrationView> find(const cv::Mat& image, const std::string& name) {
    if (chessboard_) return calibration::detect_chessboard(image, *chessboard_, name);
    if (charuco_) return calibration::detect_charuco(image, *charuco_, name);
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
  // The board named, else the one with the most tags; it must be flat (z = 0).
  static tracking::Board choose_board(const std::string& file, const std::string& name) {
    const std::vector<tracking::Board> boards = tracking::read_boards(file);
    const tracking::Board* chosen = nullptr;
    for (const auto& b : boards) {
      if (!name.empty() ? b.name == name : (!chosen || b.tags.size() > chosen->tags.size())) {
        chosen = &b;
      }
    }
    if (!chosen) throw Error(file + ": no board named \"" + name + "\"");
    for (const auto& t : chosen->tags) {
      for (const auto& c : t.corners) {
        if (std::abs(c.z()) > 1e-6) {
          throw Error(file + ": board \"" + chosen->name +
                      "\" is not planar in its z = 0 plane (camera calibration needs a flat "
                      "target)");
        }
      }
    }
    return *chosen;
  }

  std::optional<calibration::ChessboardSpec> chessboard_;
  std::optional<calibration::CharucoSpec> charuco_;
  tracking::Board board_;
  std::unique_ptr<tracking::TagDetector> detector_;
  std::string description_;
};

// The views found and the image size they share (one camera, one resolution).
struct Views {
  std::vector<calibration::CalibrationView> views;
  int width = 0, height = 0;

  void check_size(const cv::Mat& image, const std::string& name) {
    if (width == 0) {
      width = image.cols;
      height = image.rows;
    } else if (image.cols != width || image.rows != height) {
      throw Error("calibrate camera: " + name + " is " + std::to_string(image.cols) + " x " +
                  std::to_string(image.rows) + " pixels, the first image " + std::to_string(width) +
                  " x " + std::to_string(height) + " (one camera, one resolution)");
    }
  }
};

Views views_from_images(const std::string& spec, TargetFinder& finder) {
  Views out;
  const std::vector<std::string> files = list_images(spec);
  for (size_t i = 0; i < files.size(); ++i) {
    const cv::Mat image =
        recordings::to_8bit_by_range(cv::imread(files[i], cv::IMREAD_COLOR | cv::IMREAD_ANYDEPTH));
    if (image.empty()) {
      spdlog::warn("calibrate camera: {} cannot be read as an image; skipped", files[i]);
      continue;
    }
    out.check_size(image, files[i]);
    auto v = finder.find(image, fs::path(files[i]).filename().string());
    spdlog::info("calibrate camera: {} ({}/{}): {}", files[i], i + 1, files.size(),
                 v ? std::to_string(v->image_points.size()) + " corners" : "target not found");
    if (v) out.views.push_back(std::move(*v));
  }
  return out;
}

// Frame selection: up to 6 frames per wanted view, spread over the recording, then max_views of
// those with the target picked for coverage of the image.
Views views_from_recording(const std::string& dir, int max_views, TargetFinder& finder) {
  Views out;
  recordings::RecordingReader reader(dir);
  const size_t n = reader.entries().size();
  const size_t step = std::max<size_t>(1, n / size_t(std::max(1, 6 * max_views)));
  for (size_t i = 0; i < n; i += step) {
    const auto loaded = reader.load(i);
    if (loaded.image.empty()) {
      spdlog::warn("calibrate camera: frame {}: {}", reader.entries()[i].frame, loaded.problem);
      continue;
    }
    out.check_size(loaded.image, reader.entries()[i].file);
    auto v = finder.find(loaded.image, "frame " + std::to_string(reader.entries()[i].frame));
    if (v) out.views.push_back(std::move(*v));
    if ((i / step) % 20 == 0) {
      spdlog::info("calibrate camera: frame {}/{}: target in {} frames so far", i + 1, n,
                   out.views.size());
    }
  }
  if (out.views.size() > size_t(max_views)) {
    const auto picked =
        calibration::select_views_for_coverage(out.views, out.width, out.height, size_t(max_views));
    std::vector<calibration::CalibrationView> chosen;
    for (size_t k : picked) chosen.push_back(out.views[k]);
    spdlog::info("calibrate camera: {} of {} frames with the target picked for coverage",
                 chosen.size(), out.views.size());
    out.views = std::move(chosen);
  }
  return out;
}

void log_intrinsics(const calibration::IntrinsicsResult& r, const std::string& out) {
  const auto& names = calibration::intrinsic_parameter_names(r.camera.model);
  const auto& d = r.camera.distortion;
  const std::array<double, 9> values = {r.camera.fx, r.camera.fy, r.camera.cx, r.camera.cy, d[0],
                                        d[1],        d[2],        d[3],        d[4]};
  spdlog::info("  lens model {}", calibration::distortion_model_name(r.camera.model));
  for (size_t p = 0; p < names.size(); ++p) {
    spdlog::info("  {:>2} = {:>12.6f} +- {:.6f}", names[p], values[p], r.stddev[p]);
  }
  for (const auto& v : r.views) {
    if (v.points == 0) continue;
    spdlog::info("  view {:<24} {:>4} corners  RMS {:.3f} px  tilt {:5.1f} deg{}", v.name, v.points,
                 v.rms_px, v.tilt_deg, v.rejected ? "  REJECTED" : "");
  }
  spdlog::info("calibrate camera: RMS reprojection error {:.3f} px over {} views; {} written",
               r.rms_px, r.views_used, out);
}

// The needle board's measured poses and their frame numbers.
struct NeedlePoses {
  std::vector<Eigen::Isometry3d> T_cam_needle;
  std::vector<int64_t> frames;
};

// The needle board's measured poses from a poses CSV (tracked rows only).
NeedlePoses poses_from_csv(const std::string& path, const std::string& board) {
  NeedlePoses out;
  for (const auto& r : tracking::read_poses_csv(path)) {
    if (r.board == board && r.tracked) {
      out.T_cam_needle.push_back(r.T_cam_board);
      out.frames.push_back(r.frame);
    }
  }
  if (out.T_cam_needle.empty()) throw Error(path + ": no tracked rows for board \"" + board + "\"");
  return out;
}

// The board's pose measured in every frame of a recording (no smoothing, no prediction).
NeedlePoses poses_from_recording(const std::string& dir, const PivotCalibrationRequest& a) {
  const std::string uri = "recording:" + dir;
  std::unique_ptr<tracking::FrameSource> source = tracking::open_frame_source(uri);
  const std::string boards_path = session_boards_file(a.boards, uri, "calibrate pivot");
  const calibration::CameraModel camera = session_camera(a.camera, *source, "calibrate pivot");
  std::vector<tracking::Board> boards;
  for (const auto& b : tracking::read_boards(boards_path)) {
    if (b.name == a.board_name) boards.push_back(b);
  }
  if (boards.empty()) throw Error(boards_path + ": no board named \"" + a.board_name + "\"");
  tracking::TrackerOptions o;
  o.detector.family = boards.front().family;
  o.smoothing = false;
  tracking::Tracker tracker(camera, boards, o);
  NeedlePoses out;
  int64_t frames = 0;
  while (auto frame = source->next()) {
    const tracking::TrackResult r = tracker.process(*frame);
    for (const auto& s : r.boards) {
      if (s.measured) {
        out.T_cam_needle.push_back(s.T_measured);
        out.frames.push_back(r.frame);
      }
    }
    if (++frames % 100 == 0) {
      spdlog::info("{}: {} frames, board measured in {}", dir, frames, out.T_cam_needle.size());
    }
  }
  spdlog::info("{}: board \"{}\" measured in {} of {} frames", dir, a.board_name,
               out.T_cam_needle.size(), frames);
  return out;
}

// The tool's valid poses in a PLUS sequence file (INVALID ones: the tool was lost), by frame.
NeedlePoses poses_from_plus(const std::string& path, std::string tool) {
  const recordings::PlusSequence s = recordings::read_plus_sequence(path);
  const std::vector<std::string> names = s.transform_names();
  std::string listed;
  for (const auto& n : names) listed += (listed.empty() ? "" : ", ") + n;
  if (tool.empty()) {
    if (names.size() != 1) {
      throw Error(path + ": holds the transforms " + (listed.empty() ? "(none)" : listed) +
                  ": name the needle's with --tool");
    }
    tool = names.front();
  }
  NeedlePoses out;
  int64_t invalid = 0;
  for (size_t f = 0; f < s.frames.size(); ++f) {
    const auto it = s.frames[f].transforms.find(tool);
    if (it == s.frames[f].transforms.end()) continue;
    if (!it->second.valid) {
      ++invalid;
      continue;
    }
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.matrix() = it->second.matrix;
    out.T_cam_needle.push_back(T);
    out.frames.push_back(int64_t(f));
  }
  if (out.T_cam_needle.empty()) {
    throw Error(path + ": no valid " + tool + "Transform (the sequence holds " +
                (listed.empty() ? std::string("none") : listed) + ")");
  }
  spdlog::info("{}: {} poses of {} ({} frames where it was lost)", path, out.T_cam_needle.size(),
               tool, invalid);
  return out;
}

bool is_plus_sequence(const std::string& path) {
  for (const char* ext : {".mha", ".nrrd"}) {
    const std::string e = ext;
    if (path.size() > e.size() && path.compare(path.size() - e.size(), e.size(), e) == 0) return true;
  }
  return false;
}

NeedlePoses needle_poses(const std::string& poses, const std::string& recording,
                         const PivotCalibrationRequest& a) {
  if (!poses.empty() && is_plus_sequence(poses)) return poses_from_plus(poses, a.tool);
  return !poses.empty() ? poses_from_csv(poses, a.board_name) : poses_from_recording(recording, a);
}

}  // namespace

calibration::IntrinsicsResult run_camera_calibration(const CameraCalibrationRequest& a) {
  if (a.images.empty() == a.recording.empty()) {
    throw Error("calibrate camera: give either images or a recording");
  }
  TargetFinder finder(a);
  const Views found = !a.images.empty() ? views_from_images(a.images, finder)
                                        : views_from_recording(a.recording, a.max_views, finder);
  if (found.width == 0) throw Error("calibrate camera: no readable image");
  calibration::IntrinsicsOptions o;
  o.min_views = a.min_views;
  o.fix_k3 = a.fix_k3;
  o.model = a.fisheye ? calibration::DistortionModel::equidistant
                      : calibration::DistortionModel::brown_conrady;
  const calibration::IntrinsicsResult r =
      calibration::calibrate_intrinsics(found.views, found.width, found.height, o);
  calibration::write_camera_calibration(a.out, r, finder.description(),
                                        {!a.images.empty() ? a.images : a.recording});
  log_intrinsics(r, a.out);
  return r;
}

calibration::NeedleCalibration run_pivot_calibration(const PivotCalibrationRequest& a) {
  if (a.poses.empty() == a.recording.empty()) {
    throw Error("calibrate pivot: give either a poses CSV or a recording of the pivoting");
  }
  if (!a.spin_poses.empty() && !a.spin_recording.empty()) {
    throw Error("calibrate pivot: give at most one spin capture (poses CSV or recording)");
  }
  const NeedlePoses poses = needle_poses(a.poses, a.recording, a);
  calibration::PivotOptions po;
  po.min_rotation_spread_deg = a.min_rotation_deg;
  po.max_tip_stddev_mm = a.max_tip_stddev_mm;
  po.warn_rms_mm = a.warn_rms_mm;
  const calibration::PivotResult p = calibration::calibrate_pivot(poses.T_cam_needle, po);
  calibration::NeedleCalibration n;
  n.date = calibration::utc_timestamp();
  n.inputs.push_back(!a.poses.empty() ? a.poses : a.recording);
  n.board = a.board_name;
  n.tip_needle = p.tip_needle;
  n.tip_stddev_mm = p.tip_stddev_mm;
  n.tip_stddev_3d_mm = p.tip_stddev_3d_mm;
  n.pivot_cam = p.pivot_cam;
  n.pivot_rms_mm = p.rms_mm;
  n.pivot_rms_axis_mm = p.rms_axis_mm;
  n.pivot_rms_all_mm = p.rms_all_mm;
  n.poses_used = p.inliers;
  n.poses_total = int(poses.T_cam_needle.size());
  n.rotation_spread_deg = p.rotation_spread_deg;
  n.least_axis_tilt_deg = p.axis_spread_deg;
  for (int i : p.outlier_indices) n.outlier_frames.push_back(poses.frames[size_t(i)]);
  if (!n.outlier_frames.empty()) {
    std::string list;
    for (size_t k = 0; k < n.outlier_frames.size() && k < 50; ++k) {
      list += (k ? ", " : "") + std::to_string(n.outlier_frames[k]);
    }
    if (n.outlier_frames.size() > 50) list += ", ...";
    spdlog::info("calibrate pivot: {} outlier poses left out, frames {}", n.outlier_frames.size(),
                 list);
  }
  if (!a.spin_poses.empty() || !a.spin_recording.empty()) {
    const calibration::SpinResult s = calibration::calibrate_spin(
        needle_poses(a.spin_poses, a.spin_recording, a).T_cam_needle, p.tip_needle);
    n.inputs.push_back(!a.spin_poses.empty() ? a.spin_poses : a.spin_recording);
    n.axis_needle = s.axis_needle;
    n.axis_rms_deg = s.axis_rms_deg;
    n.tip_to_axis_mm = s.tip_to_axis_mm.value_or(0.0);
    spdlog::info("calibrate pivot: axis ({:.4f}, {:.4f}, {:.4f}), tip {:.2f} mm from the axis",
                 s.axis_needle.x(), s.axis_needle.y(), s.axis_needle.z(), n.tip_to_axis_mm);
  }
  calibration::write_needle_calibration(a.out, n);
  spdlog::info(
      "calibrate pivot: tip ({:.3f}, {:.3f}, {:.3f}) mm +- {:.3f} mm (3D) in the needle frame; "
      "RMS {:.3f} mm over {} of {} poses; {} written",
      p.tip_needle.x(), p.tip_needle.y(), p.tip_needle.z(), p.tip_stddev_3d_mm, p.rms_mm, p.inliers,
      poses.T_cam_needle.size(), a.out);
  return n;
}

}  // namespace crepuscular::pipelines
