// Test frames of a Kalibr aprilgrid as Kalibr prints it (tag36h11 with a 2-cell black border,
// black corner squares of side tagSpacing * tagSize in every gap where tags meet and along the
// outer rows and columns, white paper around), seen by a pinhole (OpenCV radial-tangential) or an
// equidistant fisheye camera, in 8 or 16 bits, sharp or blurred, with noise. Every pixel is
// traced back to the board (3 x 3 samples per pixel), so the truth is the projection of Kalibr's
// corner positions, pixel centres at integer coordinates (OpenCV's convention).
#pragma once

#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <cmath>
#include <map>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <vector>

#include "calibration/camera_model.hpp"
#include "tracking/board.hpp"

namespace crepuscular::tracking::testing {

// A camera: pinhole with OpenCV's k1 k2 p1 p2 k3 (through calibration::CameraModel) or equidistant
// fisheye (Kalibr's "equidistant", OpenCV's cv::fisheye: theta_d = theta (1 + k1 theta^2 + k2
// theta^4 + k3 theta^6 + k4 theta^8)), its own formula here.
struct KalibrTestCamera {
  int width = 0, height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;
  bool fisheye = false;
  std::array<double, 5> d{0, 0, 0, 0, 0};

  calibration::CameraModel pinhole() const {
    calibration::CameraModel m;
    m.width = width;
    m.height = height;
    m.fx = fx;
    m.fy = fy;
    m.cx = cx;
    m.cy = cy;
    m.distortion = d;
    return m;
  }
  double theta_d(double theta) const {
    const double t2 = theta * theta;
    return theta * (1 + t2 * (d[0] + t2 * (d[1] + t2 * (d[2] + t2 * d[3]))));
  }
  Eigen::Vector2d project(const Eigen::Vector3d& p) const {
    if (!fisheye) return pinhole().project(p);
    const double r = std::hypot(p.x(), p.y());
    const double theta = std::atan2(r, p.z());
    const double s = r > 1e-12 ? theta_d(theta) / r : 1.0 / p.z();
    return {fx * s * p.x() + cx, fy * s * p.y() + cy};
  }
  // Direction of the ray through pixel (u, v); z <= 0 when no ray of the model reaches it.
  Eigen::Vector3d ray(double u, double v, const calibration::CameraModel& model) const {
    if (!fisheye) {
      const Eigen::Vector2d xy = model.unproject(Eigen::Vector2d(u, v));
      return {xy.x(), xy.y(), 1.0};
    }
    const double xd = (u - cx) / fx, yd = (v - cy) / fy;
    const double td = std::hypot(xd, yd);
    if (td < 1e-12) return {0, 0, 1};
    double theta = td;
    for (int i = 0; i < 30; ++i) {
      const double t2 = theta * theta;
      const double f = theta_d(theta) - td;
      const double df = 1 + t2 * (3 * d[0] + t2 * (5 * d[1] + t2 * (7 * d[2] + t2 * 9 * d[3])));
      theta -= f / df;
    }
    if (!(theta < M_PI / 2 - 1e-3)) return {0, 0, -1};
    return {std::sin(theta) * xd / td, std::sin(theta) * yd / td, std::cos(theta)};
  }
};

// EuRoC MAV cam0 (752 x 480, radial-tangential) as Kalibr calibrated it.
inline KalibrTestCamera euroc_camera() {
  KalibrTestCamera c;
  c.width = 752;
  c.height = 480;
  c.fx = 458.654;
  c.fy = 457.296;
  c.cx = 367.215;
  c.cy = 248.375;
  c.d = {-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0};
  return c;
}

// TUM VI cam0 (512 x 512, equidistant fisheye, about 190 degrees) as its authors calibrated it.
inline KalibrTestCamera tumvi_camera() {
  KalibrTestCamera c;
  c.width = c.height = 512;
  c.fx = 190.978;
  c.fy = 190.973;
  c.cx = 254.932;
  c.cy = 256.897;
  c.fisheye = true;
  c.d = {0.00348238, 0.000715034, -0.00205323, 0.000202936, 0.0};
  return c;
}

struct KalibrGridSpec {
  int rows = 6, cols = 6;
  double tag_mm = 88, spacing = 0.3;
  double margin_mm = 40;  // white paper beyond the outer corner squares
  double gap_mm() const { return spacing * tag_mm; }
  double pitch_mm() const { return (1 + spacing) * tag_mm; }
  // The printed pattern's extent in Kalibr's frame: [-gap, cols * pitch] x [-gap, rows * pitch].
  Eigen::Vector2d low() const { return {-gap_mm(), -gap_mm()}; }
  Eigen::Vector2d high() const { return {cols * pitch_mm(), rows * pitch_mm()}; }
};

struct KalibrFrameOptions {
  double blur_sigma = 0;   // Gaussian blur (px)
  double noise_sigma = 0;  // Gaussian noise (8-bit grey levels)
  int depth = CV_8U;       // CV_8U or CV_16U
  double scale16 = 257;    // 16-bit: value = 8-bit level * scale16 (257: full range; 16: 12 bits)
  double ink = 30, paper = 220;  // 8-bit levels of black and white
  uint64_t seed = 1;
};

// Renders a Kalibr aprilgrid at poses T_cam_board (board = Kalibr's target frame, mm).
class KalibrGridRenderer {
 public:
  static constexpr int kSamples = 3;  // per pixel and axis

  KalibrGridRenderer(const KalibrTestCamera& camera, const KalibrGridSpec& grid)
      : camera_(camera), grid_(grid) {
    for (int id = 0; id < grid.rows * grid.cols; ++id) {
      patterns_.push_back(tag_pattern("tag36h11b2", id));
    }
    const calibration::CameraModel model = camera.pinhole();
    rays_.create(camera.height * kSamples, camera.width * kSamples, CV_32FC3);
    for (int y = 0; y < rays_.rows; ++y) {
      for (int x = 0; x < rays_.cols; ++x) {
        const double u = (x + 0.5) / kSamples - 0.5, v = (y + 0.5) / kSamples - 0.5;
        const Eigen::Vector3d r = camera.ray(u, v, model);
        rays_.at<cv::Vec3f>(y, x) = cv::Vec3f(float(r.x()), float(r.y()), float(r.z()));
      }
    }
  }

  const KalibrTestCamera& camera() const { return camera_; }
  const KalibrGridSpec& grid() const { return grid_; }

  // 8-bit level of the print (or of the background) at board point (x, y) mm.
  double level(double x, double y, const KalibrFrameOptions& o) const {
    const KalibrGridSpec& g = grid_;
    const Eigen::Vector2d lo = g.low(), hi = g.high();
    if (x < lo.x() - g.margin_mm || y < lo.y() - g.margin_mm || x > hi.x() + g.margin_mm ||
        y > hi.y() + g.margin_mm) {
      return -1;  // off the paper
    }
    const double p = g.pitch_mm(), gap = g.gap_mm(), t = g.tag_mm;
    const auto in_square = [&](double v, int n) {
      const int k = int(std::floor((v + gap) / p));
      return k >= 0 && k <= n && v + gap - k * p < gap;
    };
    if (in_square(x, g.cols) && in_square(y, g.rows)) return o.ink;
    const int c = int(std::floor(x / p)), r = int(std::floor(y / p));
    const double lx = x - c * p, ly = y - r * p;
    if (c >= 0 && c < g.cols && r >= 0 && r < g.rows && lx < t && ly < t) {
      const TagPattern& pat = patterns_[size_t(r * g.cols + c)];
      const int w = pat.width_at_border;
      const int col = std::clamp(int(lx / t * w), 0, w - 1);
      const int row = std::clamp(int((t - ly) / t * w), 0, w - 1);  // row 0 at the printed top
      const uint8_t v = pat.cells.at<uint8_t>(pat.border_start() + row, pat.border_start() + col);
      return v ? o.paper : o.ink;
    }
    return o.paper;
  }

  cv::Mat render(const Eigen::Isometry3d& T_cam_board, const KalibrFrameOptions& o) const {
    const Eigen::Matrix3d R = T_cam_board.linear();
    const Eigen::Vector3d t = T_cam_board.translation();
    const Eigen::Vector3d n = R.col(2);
    const double nt = n.dot(t);
    cv::Mat image(camera_.height, camera_.width, CV_64F);
    for (int y = 0; y < camera_.height; ++y) {
      for (int x = 0; x < camera_.width; ++x) {
        double sum = 0;
        for (int sy = 0; sy < kSamples; ++sy) {
          for (int sx = 0; sx < kSamples; ++sx) {
            const cv::Vec3f rv = rays_.at<cv::Vec3f>(y * kSamples + sy, x * kSamples + sx);
            const Eigen::Vector3d ray(rv[0], rv[1], rv[2]);
            double v = -1;
            const double nr = n.dot(ray);
            if (rv[2] > 0 && std::abs(nr) > 1e-12 && nt / nr > 0) {
              const Eigen::Vector3d pb = R.transpose() * (nt / nr * ray - t);
              v = level(pb.x(), pb.y(), o);
            }
            // Background: a smooth grey gradient.
            if (v < 0) v = 90 + 40 * std::sin(0.011 * x + 0.007 * y);
            sum += v;
          }
        }
        image.at<double>(y, x) = sum / (kSamples * kSamples);
      }
    }
    if (o.blur_sigma > 0) cv::GaussianBlur(image, image, cv::Size(0, 0), o.blur_sigma);
    if (o.noise_sigma > 0) {
      cv::Mat noise(image.size(), CV_64F);
      cv::RNG rng(o.seed);
      rng.fill(noise, cv::RNG::NORMAL, 0.0, o.noise_sigma);
      image += noise;
    }
    cv::Mat out;
    if (o.depth == CV_16U) {
      image.convertTo(out, CV_16U, o.scale16);
    } else {
      image.convertTo(out, CV_8U);
    }
    return out;
  }

  // Pixels of the board's tag corners (Kalibr's frame through the camera), by tag id.
  std::map<int, std::array<Eigen::Vector2d, 4>> truth(const Board& board,
                                                      const Eigen::Isometry3d& T) const {
    std::map<int, std::array<Eigen::Vector2d, 4>> out;
    for (const BoardTag& tag : board.tags) {
      std::array<Eigen::Vector2d, 4> px;
      for (int k = 0; k < 4; ++k) px[k] = camera_.project(T * tag.corners[k]);
      out[tag.id] = px;
    }
    return out;
  }

  // Whether all four corners of the tag lie in front of the camera, `margin` px inside the image.
  bool visible(const BoardTag& tag, const Eigen::Isometry3d& T, double margin = 4) const {
    for (const Eigen::Vector3d& c : tag.corners) {
      const Eigen::Vector3d pc = T * c;
      if (pc.z() <= 0) return false;
      const Eigen::Vector2d px = camera_.project(pc);
      if (px.x() < margin || px.y() < margin || px.x() > camera_.width - 1 - margin ||
          px.y() > camera_.height - 1 - margin) {
        return false;
      }
    }
    return true;
  }

  // Fraction of the image area inside the bounding box of the printed pattern's projection.
  double fill(const Eigen::Isometry3d& T) const {
    const Eigen::Vector2d lo = grid_.low(), hi = grid_.high();
    double x0 = 1e30, y0 = 1e30, x1 = -1e30, y1 = -1e30;
    for (int i = 0; i <= 40; ++i) {
      const double a = i / 40.0;
      for (const Eigen::Vector2d& q : {Eigen::Vector2d(lo.x() + a * (hi.x() - lo.x()), lo.y()),
                                       Eigen::Vector2d(lo.x() + a * (hi.x() - lo.x()), hi.y()),
                                       Eigen::Vector2d(lo.x(), lo.y() + a * (hi.y() - lo.y())),
                                       Eigen::Vector2d(hi.x(), lo.y() + a * (hi.y() - lo.y()))}) {
        const Eigen::Vector2d px = camera_.project(T * Eigen::Vector3d(q.x(), q.y(), 0));
        x0 = std::min(x0, px.x());
        y0 = std::min(y0, px.y());
        x1 = std::max(x1, px.x());
        y1 = std::max(y1, px.y());
      }
    }
    x0 = std::max(x0, 0.0);
    y0 = std::max(y0, 0.0);
    x1 = std::min(x1, camera_.width - 1.0);
    y1 = std::min(y1, camera_.height - 1.0);
    return std::max(0.0, x1 - x0) * std::max(0.0, y1 - y0) / (camera_.width * camera_.height);
  }

  // A pose that shows the printed face tilted by tilt_deg about an in-image axis at axis_deg from
  // the image x axis, the pattern's centre seen at pixel offset (dx, dy) from the principal point,
  // at the distance where the pattern's bounding box covers `fill_fraction` of the image.
  Eigen::Isometry3d pose(double tilt_deg, double axis_deg, double fill_fraction, double dx = 0,
                         double dy = 0) const {
    const double a = axis_deg * M_PI / 180;
    Eigen::Matrix3d flip = Eigen::Vector3d(1, -1, -1).asDiagonal();  // Kalibr's z faces the camera
    const Eigen::Matrix3d R =
        Eigen::AngleAxisd(tilt_deg * M_PI / 180, Eigen::Vector3d(std::cos(a), std::sin(a), 0))
            .toRotationMatrix() *
        flip;
    const Eigen::Vector3d centre(0.5 * (grid_.low() + grid_.high()).x(),
                                 0.5 * (grid_.low() + grid_.high()).y(), 0);
    Eigen::Vector3d dir = camera_.ray(camera_.cx + dx, camera_.cy + dy, camera_.pinhole());
    dir /= dir.z();
    const auto at = [&](double z) {
      Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
      T.linear() = R;
      T.translation() = z * dir - R * centre;
      return T;
    };
    double near = 50, far = 50000;
    for (int i = 0; i < 60; ++i) {
      const double mid = std::sqrt(near * far);
      (fill(at(mid)) > fill_fraction ? near : far) = mid;
    }
    return at(far);
  }

 private:
  KalibrTestCamera camera_;
  KalibrGridSpec grid_;
  std::vector<TagPattern> patterns_;
  cv::Mat rays_;
};

}  // namespace crepuscular::tracking::testing
