// Test scenes of OpenCV ChArUco boards (header only): the board image of
// cv::aruco::CharucoBoard::draw seen through a camera with distortion, and its corners' true
// pixels.
#pragma once

#include <Eigen/Geometry>
#include <opencv2/aruco/charuco.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/core/eigen.hpp>
#include <opencv2/imgproc.hpp>
#include <random>
#include <vector>

#include "calibration/camera_model.hpp"

namespace crepuscular::test {

inline cv::Mat camera_matrix_of(const calibration::CameraModel& cam) {
  return (cv::Mat_<double>(3, 3) << cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1);
}
inline cv::Mat distortion_of(const calibration::CameraModel& cam) {
  return (cv::Mat_<double>(1, 5) << cam.distortion[0], cam.distortion[1], cam.distortion[2],
          cam.distortion[3], cam.distortion[4]);
}

// rvec and tvec of T_cam_board, as cv::projectPoints and cv::aruco take them.
inline void rvec_tvec(const Eigen::Isometry3d& T, cv::Vec3d& rvec, cv::Vec3d& tvec) {
  cv::Mat R;
  cv::eigen2cv(Eigen::Matrix3d(T.linear()), R);
  cv::Rodrigues(R, rvec);
  tvec = cv::Vec3d(T.translation().x(), T.translation().y(), T.translation().z());
}

// Exact pixels of board points (mm) through the camera (cv::projectPoints).
inline std::vector<Eigen::Vector2d> project_points(const calibration::CameraModel& cam,
                                                   const Eigen::Isometry3d& T_cam_board,
                                                   const std::vector<cv::Point3f>& points) {
  cv::Vec3d rvec, tvec;
  rvec_tvec(T_cam_board, rvec, tvec);
  std::vector<cv::Point3d> in(points.begin(), points.end());
  std::vector<cv::Point2d> px;
  cv::projectPoints(in, rvec, tvec, camera_matrix_of(cam), distortion_of(cam), px);
  std::vector<Eigen::Vector2d> out;
  for (const cv::Point2d& p : px) out.emplace_back(p.x, p.y);
  return out;
}

// Renders a ChArUco board: each pixel is the mean of 3 x 3 samples, each sample's ray
// (cv::undistortPoints, so distortion is exact) meets the board plane and reads the board image
// of CharucoBoard::draw at px_per_mm (squares of a whole number of pixels). Paper outside the
// board is `paper`; black 25, white 230 grey levels.
class CharucoRenderer {
 public:
  CharucoRenderer(const calibration::CameraModel& cam,
                  const cv::Ptr<cv::aruco::CharucoBoard>& board, double px_per_mm = 4.0)
      : cam_(cam), ppm_(px_per_mm) {
    const cv::Size2f size = board->getChessboardSize();
    const float square = board->getSquareLength();
    board->draw(cv::Size(int(std::lround(size.width * square * ppm_)),
                         int(std::lround(size.height * square * ppm_))),
                board_image_, 0, 1);
    std::vector<cv::Point2f> px;
    px.reserve(size_t(cam.width) * cam.height * 9);
    for (int v = 0; v < cam.height; ++v)
      for (int u = 0; u < cam.width; ++u)
        for (int a = -1; a <= 1; ++a)
          for (int b = -1; b <= 1; ++b) px.emplace_back(u + b / 3.0f, v + a / 3.0f);
    cv::undistortPoints(
        px, rays_, camera_matrix_of(cam), distortion_of(cam), cv::noArray(), cv::noArray(),
        cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 30, 1e-10));
  }

  // Grey 8-bit image of the board at T_cam_board, blurred (px) and with Gaussian noise.
  cv::Mat render(const Eigen::Isometry3d& T_cam_board, double blur_sigma = 0.0,
                 double noise_sigma = 0.0, unsigned seed = 1, double paper = 200.0) const {
    const Eigen::Vector3d n = T_cam_board.linear().col(2);
    const Eigen::Vector3d t = T_cam_board.translation();
    const Eigen::Matrix3d Rt = T_cam_board.linear().transpose();
    cv::Mat f(cam_.height, cam_.width, CV_32F);
    size_t k = 0;
    for (int v = 0; v < cam_.height; ++v) {
      float* row = f.ptr<float>(v);
      for (int u = 0; u < cam_.width; ++u) {
        double sum = 0;
        for (int s = 0; s < 9; ++s, ++k) {
          const Eigen::Vector3d d(rays_[k].x, rays_[k].y, 1.0);
          const double depth = n.dot(t) / n.dot(d);
          double value = paper;
          if (depth > 0) {
            const Eigen::Vector3d X = Rt * (depth * d - t);
            const int i = int(std::floor(X.x() * ppm_)), j = int(std::floor(X.y() * ppm_));
            if (i >= 0 && j >= 0 && i < board_image_.cols && j < board_image_.rows) {
              value = board_image_.at<uint8_t>(j, i) ? 230.0 : 25.0;
            }
          }
          sum += value;
        }
        row[u] = float(sum / 9.0);
      }
    }
    if (blur_sigma > 0) cv::GaussianBlur(f, f, cv::Size(0, 0), blur_sigma);
    if (noise_sigma > 0) {
      std::mt19937 rng(seed);
      std::normal_distribution<float> noise(0.f, float(noise_sigma));
      for (int v = 0; v < f.rows; ++v) {
        float* row = f.ptr<float>(v);
        for (int u = 0; u < f.cols; ++u) row[u] += noise(rng);
      }
    }
    cv::Mat out;
    f.convertTo(out, CV_8U);
    return out;
  }

 private:
  calibration::CameraModel cam_;
  double ppm_;
  cv::Mat board_image_;
  std::vector<cv::Point2f> rays_;  // normalised image coordinates of every sample
};

}  // namespace crepuscular::test
