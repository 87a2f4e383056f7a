// Pinhole camera with Brown-Conrady distortion (k1 k2 p1 p2 k3), as OpenCV defines it.
// Coordinates: camera frame in mm (x right, y down, z forward), pixels with (0,0) at the centre of
// the top-left pixel (OpenCV's convention).
#pragma once

#include <Eigen/Core>
#include <array>
#include <functional>
#include <string>

#include <opencv2/core.hpp>

namespace crepuscular::calibration {

struct CameraModel {
  int width = 0;
  int height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;
  std::array<double, 5> distortion{0, 0, 0, 0, 0};  // k1 k2 p1 p2 k3

  // Point in the camera frame -> pixel (distortion applied). z must be > 0.
  Eigen::Vector2d project(const Eigen::Vector3d& p_cam) const;
  // Pixel -> normalised, undistorted image point (x/z, y/z): the exact inverse of project() (to
  // 1e-12 in normalised units) wherever the distortion is invertible.
  Eigen::Vector2d unproject(const Eigen::Vector2d& pixel) const;
  // The same, by Newton's method from `guess` (a normalised point near the answer, e.g.
  // interpolated from neighbouring pixels): faster when many nearby pixels are unprojected.
  Eigen::Vector2d unproject(const Eigen::Vector2d& pixel, const Eigen::Vector2d& guess) const;

  // Undistorted normalised point (x/z, y/z) -> distorted normalised point (OpenCV's model).
  Eigen::Vector2d distort(const Eigen::Vector2d& xy) const;
  // Undistorted normalised point -> pixel.
  Eigen::Vector2d normalized_to_pixel(const Eigen::Vector2d& xy) const;

  // OpenCV's matrices: 3x3 CV_64F camera matrix and 1x5 CV_64F distortion coefficients.
  cv::Mat camera_matrix() const;
  cv::Mat distortion_coefficients() const;
  // From OpenCV's matrices (distortion with 4, 5 or more entries; entries past k3 must be 0).
  // Throws Error naming `what` when they do not fit this model.
  static CameraModel from_opencv(const cv::Mat& camera_matrix, const cv::Mat& distortion,
                                 int width, int height, const std::string& what = "camera model");

  // Throws Error naming `what` when the model is unusable (sizes, focal lengths, non-finite).
  void validate(const std::string& what) const;

  // OpenCV FileStorage YAML: camera_matrix, distortion_coefficients, image_width, image_height.
  // Errors name the file and the field. write_yaml writes a temporary sibling and renames it.
  static CameraModel read_yaml(const std::string& path);
  void write_yaml(const std::string& path) const;

  // The projection of project() with the intrinsics as parameters, for Ceres autodiff (T = double
  // or ceres::Jet). intrinsics = {fx, fy, cx, cy}, distortion = {k1, k2, p1, p2, k3}.
  template <typename T>
  static void project_generic(const T* intrinsics, const T* distortion, const T* p_cam,
                              T* pixel) {
    const T x = p_cam[0] / p_cam[2];
    const T y = p_cam[1] / p_cam[2];
    const T r2 = x * x + y * y;
    const T radial =
        T(1) + r2 * (distortion[0] + r2 * (distortion[1] + r2 * distortion[4]));
    const T xd = x * radial + T(2) * distortion[2] * x * y + distortion[3] * (r2 + T(2) * x * x);
    const T yd = y * radial + distortion[2] * (r2 + T(2) * y * y) + T(2) * distortion[3] * x * y;
    pixel[0] = intrinsics[0] * xd + intrinsics[2];
    pixel[1] = intrinsics[1] * yd + intrinsics[3];
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
