// Camera intrinsic calibration from views of a planar target: Zhang's homography start, then a
// Ceres bundle adjustment of fx fy cx cy and the lens (k1 k2 p1 p2 k3, or k1..k4 of an
// equidistant fisheye) and every view's pose with a robust loss,
// outlier view rejection, per-parameter standard deviations, and a refusal (with advice on what to
// capture next) when the views cannot determine the parameters.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <vector>

#include "calibration/camera_model.hpp"

namespace crepuscular::calibration {

// One image of a planar target: corners in the target frame (mm, all with z = 0) and where they
// were detected (pixels, OpenCV convention).
struct CalibrationView {
  std::string name;  // image file or frame number, for messages and reports
  std::vector<Eigen::Vector3d> object_points;
  std::vector<Eigen::Vector2d> image_points;
};

struct IntrinsicsOptions {
  int min_views = 4;                  // fewer usable views are refused
  int min_points_per_view = 6;        // views with fewer corners are skipped
  double min_tilt_spread_deg = 10.0;  // largest angle between two views' target normals
  double min_coverage = 0.4;          // fraction of the 4 x 4 image cells that hold a corner
  double huber_px = 1.0;              // robust loss: quadratic up to this residual
  double outlier_view_factor = 3.0;   // a view whose RMS exceeds factor x median RMS is dropped...
  double outlier_view_min_px = 0.5;   // ...unless its RMS is below this
  bool fix_k3 = false;                // keep k3 at 0 (narrow lenses; Brown-Conrady only)
  // The lens model to calibrate: brown_conrady (pinhole lenses) or equidistant (fisheye).
  DistortionModel model = DistortionModel::brown_conrady;
  int max_iterations = 200;
};

struct ViewReport {
  std::string name;
  int points = 0;
  double rms_px = 0;      // reprojection RMS with the final intrinsics
  double tilt_deg = 0;    // angle between the target normal and the optical axis
  bool rejected = false;  // dropped as an outlier view (not used in the final solution)
  Eigen::Isometry3d T_cam_target = Eigen::Isometry3d::Identity();
};

struct IntrinsicsResult {
  CameraModel camera;
  // Standard deviations of fx fy cx cy (px) and k1 k2 p1 p2 k3 (equidistant: k1 k2 k3 k4 and a
  // last 0), from the Ceres covariance scaled by the residual variance (as OpenCV's
  // stdDeviationsIntrinsics).
  std::array<double, 9> stddev{};
  double rms_px = 0;  // over all corners of the views kept
  int views_used = 0;
  int points_used = 0;
  double coverage = 0;            // fraction of 4 x 4 image cells holding a corner
  double tilt_spread_deg = 0;     // largest angle between two target normals
  std::vector<ViewReport> views;  // one per input view, in input order (skipped ones have 0 points)
  std::string solver_report;      // Ceres BriefReport of the last solve
};

// Names of the model's parameters in the order of IntrinsicsResult::stddev (nine for
// brown_conrady, eight for equidistant).
const std::vector<std::string>& intrinsic_parameter_names(
    DistortionModel model = DistortionModel::brown_conrady);

// Calibrates a camera of width x height pixels. Throws Error with advice (what to capture next)
// when the views cannot determine the parameters: too few views, all nearly parallel to each other
// (e.g. all fronto-parallel), or corners that leave most of the image empty.
IntrinsicsResult calibrate_intrinsics(const std::vector<CalibrationView>& views, int width,
                                      int height, const IntrinsicsOptions& options = {});

// Fraction of the cells of a cells x cells grid over the image that contain at least one corner.
double corner_coverage(const std::vector<CalibrationView>& views, int width, int height,
                       int cells = 4);

// Picks at most max_views views, greedily the ones that add the most uncovered cells of a 10 x 10
// grid over the image, then evenly spaced ones; returns indices into `views` in ascending order.
std::vector<size_t> select_views_for_coverage(const std::vector<CalibrationView>& views, int width,
                                              int height, size_t max_views);

// "chessboard:COLSxROWS:SQUARE_MM": inner corners counted as OpenCV does (9x6 for a board of
// 10 x 7 squares).
struct ChessboardSpec {
  int cols = 0;
  int rows = 0;
  double square_mm = 0;
};
// Parses the spec; throws Error naming the text when it is malformed. Returns nullopt when the
// text does not start with "chessboard:".
std::optional<ChessboardSpec> parse_chessboard_spec(const std::string& text);

// Finds the inner corners of a chessboard (cv::findChessboardCorners + cv::cornerSubPix). Returns
// nullopt when the whole board is not found. Object points are in the board frame, z = 0, row by
// row as OpenCV orders them.
std::optional<CalibrationView> detect_chessboard(const cv::Mat& image, const ChessboardSpec& spec,
                                                 const std::string& name);

}  // namespace crepuscular::calibration
