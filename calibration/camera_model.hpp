// Pinhole camera with Brown-Conrady distortion (k1 k2 p1 p2 k3), as OpenCV defines it.
// Coordinates: camera frame in mm (x right, y down, z forward), pixels with (0,0) at the centre of
// the top-left pixel (OpenCV's convention).
#pragma once

#include <Eigen/Core>
#include <array>
#include <string>

namespace crepuscular::calibration {

struct CameraModel {
  int width = 0;
  int height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;
  std::array<double, 5> distortion{0, 0, 0, 0, 0};  // k1 k2 p1 p2 k3

  // Point in the camera frame -> pixel (distortion applied). z must be > 0.
  Eigen::Vector2d project(const Eigen::Vector3d& p_cam) const;
  // Pixel -> normalised, undistorted image point (x/z, y/z).
  Eigen::Vector2d unproject(const Eigen::Vector2d& pixel) const;

  // OpenCV FileStorage YAML: camera_matrix, distortion_coefficients, image_width, image_height.
  // Errors name the file and the field.
  static CameraModel read_yaml(const std::string& path);
  void write_yaml(const std::string& path) const;
};

}  // namespace crepuscular::calibration
