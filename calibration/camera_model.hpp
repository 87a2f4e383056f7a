// Pinhole camera with Brown-Conrady distortion (k1 k2 p1 p2 k3) or an equidistant fisheye lens
// (k1..k4, cv::fisheye's model = Kalibr's "equidistant"), as OpenCV defines them.
// Coordinates: camera frame in mm (x right, y down, z forward), pixels with (0,0) at the centre of
// the top-left pixel (OpenCV's convention).
#pragma once

#include <Eigen/Core>
#include <array>
#include <cmath>
#include <functional>
#include <opencv2/core.hpp>
#include <string>

namespace crepuscular::calibration {

// The lens distortion models. brown_conrady: OpenCV's default model (k1 k2 p1 p2 k3), ROS's
// "plumb_bob". equidistant: cv::fisheye's model (ROS and Kalibr "equidistant"): a ray at angle
// theta from the optical axis lands at radius theta_d = theta (1 + k1 th^2 + k2 th^4 + k3 th^6 +
// k4 th^8) in normalised units.
enum class DistortionModel { brown_conrady, equidistant };

// The model's name in camera.yaml (distortion_model: "plumb_bob" or "equidistant").
const char* distortion_model_name(DistortionModel model);
// The model of a name (also "brown_conrady", "pinhole", "fisheye"); throws Error naming `what`,
// the value and the accepted names otherwise.
DistortionModel parse_distortion_model(const std::string& name, const std::string& what);

struct CameraModel {
  int width = 0;
  int height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;
  DistortionModel model = DistortionModel::brown_conrady;
  // brown_conrady: k1 k2 p1 p2 k3. equidistant: k1 k2 k3 k4, and the last entry 0.
  std::array<double, 5> distortion{0, 0, 0, 0, 0};

  // Point in the camera frame -> pixel (distortion applied). z must be > 0.
  Eigen::Vector2d project(const Eigen::Vector3d& p_cam) const;
  // Pixel -> normalised, undistorted image point (x/z, y/z): the exact inverse of project() (to
  // 1e-12 in normalised units) wherever the distortion is invertible. NaN where it is not (an
  // equidistant lens: rays at 90 degrees or more off axis, or past the angle where theta_d stops
  // growing with theta).
  Eigen::Vector2d unproject(const Eigen::Vector2d& pixel) const;
  // The same, by Newton's method from `guess` (a normalised point near the answer, e.g.
  // interpolated from neighbouring pixels): faster when many nearby pixels are unprojected. An
  // equidistant lens has a one-dimensional inverse and ignores `guess`.
  Eigen::Vector2d unproject(const Eigen::Vector2d& pixel, const Eigen::Vector2d& guess) const;

  // Undistorted normalised point (x/z, y/z) -> distorted normalised point (OpenCV's model).
  Eigen::Vector2d distort(const Eigen::Vector2d& xy) const;
  // Undistorted normalised point -> pixel.
  Eigen::Vector2d normalized_to_pixel(const Eigen::Vector2d& xy) const;

  // OpenCV's matrices: 3x3 CV_64F camera matrix and CV_64F distortion coefficients, 1x5 for
  // brown_conrady (cv::undistortPoints etc.), 1x4 for equidistant (cv::fisheye::*).
  cv::Mat camera_matrix() const;
  cv::Mat distortion_coefficients() const;
  // From OpenCV's matrices. brown_conrady: distortion with 4, 5 or more entries (entries past k3
  // must be 0); equidistant: 4 entries k1..k4. Throws Error naming `what` when they do not fit.
  static CameraModel from_opencv(const cv::Mat& camera_matrix, const cv::Mat& distortion, int width,
                                 int height, const std::string& what = "camera model",
                                 DistortionModel model = DistortionModel::brown_conrady);

  // Throws Error naming `what` when the model is unusable (sizes, focal lengths, non-finite, an
  // equidistant lens with a non-zero fifth coefficient).
  void validate(const std::string& what) const;

  // OpenCV FileStorage YAML: camera_matrix, distortion_coefficients, image_width, image_height and
  // distortion_model ("plumb_bob" when absent, or "equidistant"). Errors name the file and the
  // field. write_yaml writes a temporary sibling and renames it.
  static CameraModel read_yaml(const std::string& path);
  void write_yaml(const std::string& path) const;

  // The projection of project() with the intrinsics as parameters, for Ceres autodiff (T = double
  // or ceres::Jet); the one definition of the lens math. intrinsics = {fx, fy, cx, cy},
  // distortion = the five entries of CameraModel::distortion for `model`.
  template <typename T>
  static void project_generic(DistortionModel model, const T* intrinsics, const T* distortion,
                              const T* p_cam, T* pixel) {
    using std::atan;
    using std::sqrt;
    const T x = p_cam[0] / p_cam[2];
    const T y = p_cam[1] / p_cam[2];
    const T r2 = x * x + y * y;
    T xd, yd;
    if (model == DistortionModel::equidistant) {
      // theta_d / r, and its limit 1 on the axis (as cv::fisheye does below r = 1e-8).
      T scale = T(1);
      if (r2 > T(1e-16)) {
        const T r = sqrt(r2);
        const T theta = atan(r);
        const T t2 = theta * theta;
        const T theta_d =
            theta *
            (T(1) + t2 * (distortion[0] +
                          t2 * (distortion[1] + t2 * (distortion[2] + t2 * distortion[3]))));
        scale = theta_d / r;
      }
      xd = x * scale;
      yd = y * scale;
    } else {
      const T radial = T(1) + r2 * (distortion[0] + r2 * (distortion[1] + r2 * distortion[4]));
      xd = x * radial + T(2) * distortion[2] * x * y + distortion[3] * (r2 + T(2) * x * x);
      yd = y * radial + distortion[2] * (r2 + T(2) * y * y) + T(2) * distortion[3] * x * y;
    }
    pixel[0] = intrinsics[0] * xd + intrinsics[2];
    pixel[1] = intrinsics[1] * yd + intrinsics[3];
  }

  // project_generic with this camera's numbers and a point of type T (for Ceres autodiff over the
  // point or a pose).
  template <typename T>
  void project_point(const T* p_cam, T* pixel) const {
    const T intrinsics[4] = {T(fx), T(fy), T(cx), T(cy)};
    const T d[5] = {T(distortion[0]), T(distortion[1]), T(distortion[2]), T(distortion[3]),
                    T(distortion[4])};
    project_generic(model, intrinsics, d, p_cam, pixel);
  }
};

// Opens an OpenCV FileStorage file (YAML; XML or JSON by extension) for reading. OpenCV's parser
// hangs or reads out of bounds on some malformed files (found by fuzzing), so the text is parsed
// first in a child process under a deadline: a file the parser fails on there is refused with
// Error "PATH: ..." and never parsed here. Also refuses a top level without named fields.
void open_file_storage(cv::FileStorage& storage, const std::string& path);

// An "!!opencv-matrix" node read as cv::Mat after checking what OpenCV would trust (rows, cols,
// dt, and as many data values as they announce: OpenCV allocates from rows and cols first).
// Throws Error "PATH: field FIELD ..." otherwise.
cv::Mat read_opencv_matrix(const cv::FileNode& node, const std::string& path,
                           const std::string& field);

// Writes an OpenCV FileStorage file through a temporary sibling (foundation's atomic output):
// `body` writes the fields. format: cv::FileStorage::FORMAT_AUTO (from the extension) or
// FORMAT_YAML, ... Throws Error "PATH: cannot be written (reason)"; nothing is left behind then.
void write_file_storage(const std::string& path, const std::function<void(cv::FileStorage&)>& body,
                        int format = cv::FileStorage::FORMAT_AUTO);

}  // namespace crepuscular::calibration
