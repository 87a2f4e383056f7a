// Test scenes for tracking: AprilTag boards rendered with OpenCV alone (an independent renderer:
// tag bitmaps from libapriltag, geometry from the pinhole matrix, distortion through
// cv::undistortPoints), with exact corner projections from cv::projectPoints as truth.
#pragma once

#include <apriltag.h>
#include <tag36h11.h>

#include <Eigen/Geometry>
#include <array>
#include <cmath>
#include <cstdlib>
#include <map>
#include <memory>
#include <opencv2/calib3d.hpp>
#include <opencv2/core/eigen.hpp>
#include <opencv2/imgproc.hpp>
#include <random>
#include <vector>

#include "calibration/camera_model.hpp"
#include "tracking/board.hpp"

namespace crepuscular::tracking::testing {

// A 1280x720 camera with a 70 degree horizontal field of view and mild barrel distortion.
inline calibration::CameraModel hd_camera(bool distorted = true, int width = 1280,
                                          int height = 720) {
  calibration::CameraModel cam;
  cam.width = width;
  cam.height = height;
  cam.fx = cam.fy = 914.0 * width / 1280.0;
  cam.cx = 0.5 * (width - 1) + 3.2;
  cam.cy = 0.5 * (height - 1) - 2.7;
  if (distorted) cam.distortion = {-0.12, 0.05, 0.0007, -0.0004, 0.0};
  return cam;
}

inline cv::Mat camera_matrix(const calibration::CameraModel& cam) {
  return (cv::Mat_<double>(3, 3) << cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1);
}
inline cv::Mat distortion(const calibration::CameraModel& cam) {
  return (cv::Mat_<double>(1, 5) << cam.distortion[0], cam.distortion[1], cam.distortion[2],
          cam.distortion[3], cam.distortion[4]);
}

// Exact corners of all tags of a board (cv::projectPoints), per tag id, in p order.
inline std::map<int, std::array<Eigen::Vector2d, 4>> project_corners(
    const calibration::CameraModel& cam, const Board& board, const Eigen::Isometry3d& T_cam_board) {
  std::map<int, std::array<Eigen::Vector2d, 4>> out;
  cv::Mat R;
  cv::eigen2cv(Eigen::Matrix3d(T_cam_board.linear()), R);
  cv::Mat rvec, tvec;
  cv::Rodrigues(R, rvec);
  tvec = (cv::Mat_<double>(3, 1) << T_cam_board.translation().x(), T_cam_board.translation().y(),
          T_cam_board.translation().z());
  for (const BoardTag& t : board.tags) {
    std::vector<cv::Point3d> obj;
    for (const Eigen::Vector3d& c : t.corners) obj.emplace_back(c.x(), c.y(), c.z());
    std::vector<cv::Point2d> img;
    cv::projectPoints(obj, rvec, tvec, camera_matrix(cam), distortion(cam), img);
    std::array<Eigen::Vector2d, 4> a;
    for (int k = 0; k < 4; ++k) a[k] = Eigen::Vector2d(img[k].x, img[k].y);
    out[t.id] = a;
  }
  return out;
}

struct RenderOptions {
  double background = 150;    // grey level around the tags
  double noise_sigma = 0;     // Gaussian pixel noise (grey levels)
  double blur_sigma = 0;      // Gaussian blur (px)
  int supersample = 4;
  unsigned seed = 1;
  std::vector<int> hidden_ids;  // tags left out (occlusion)
};

struct PlacedBoard {
  const Board* board;
  Eigen::Isometry3d T_cam_board;
};

// Renders boards as seen by cam, BGR 8-bit. Each tag is its libapriltag bitmap (with its one-cell
// white quiet zone) mapped onto the board plane; distortion is applied by resampling the ideal
// pinhole image at cv::undistortPoints of every pixel.
class SceneRenderer {
 public:
  explicit SceneRenderer(const calibration::CameraModel& cam) : cam_(cam) {
    family_ = tag36h11_create();
    const bool distorted = cam.distortion != std::array<double, 5>{0, 0, 0, 0, 0};
    if (distorted) {
      std::vector<cv::Point2f> px;
      px.reserve(size_t(cam.width) * cam.height);
      for (int y = 0; y < cam.height; ++y)
        for (int x = 0; x < cam.width; ++x) px.emplace_back(float(x), float(y));
      std::vector<cv::Point2f> ideal;
      cv::undistortPoints(px, ideal, camera_matrix(cam), distortion(cam), cv::noArray(),
                          camera_matrix(cam),
                          cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 50,
                                           1e-9));
      map_x_.create(cam.height, cam.width, CV_32F);
      map_y_.create(cam.height, cam.width, CV_32F);
      for (int y = 0; y < cam.height; ++y)
        for (int x = 0; x < cam.width; ++x) {
          map_x_.at<float>(y, x) = ideal[size_t(y) * cam.width + x].x;
          map_y_.at<float>(y, x) = ideal[size_t(y) * cam.width + x].y;
        }
    }
  }
  ~SceneRenderer() { tag36h11_destroy(family_); }
  SceneRenderer(const SceneRenderer&) = delete;
  SceneRenderer& operator=(const SceneRenderer&) = delete;

  cv::Mat render(const std::vector<PlacedBoard>& boards, const RenderOptions& o = {}) {
    const int S = o.supersample;
    // Ideal pinhole image, rendered S times larger, with a margin so that distortion can pull
    // in content from outside the frame.
    const int margin = map_x_.empty() ? 0 : 64;
    const int W = (cam_.width + 2 * margin) * S, H = (cam_.height + 2 * margin) * S;
    cv::Mat hi(H, W, CV_8UC1, cv::Scalar(o.background));
    // low-res pixel (x, y) -> hi-res pixel: S * (x + margin + 0.5) - 0.5
    Eigen::Matrix3d A;
    A << S, 0, S * (margin + 0.5) - 0.5, 0, S, S * (margin + 0.5) - 0.5, 0, 0, 1;
    Eigen::Matrix3d K;
    K << cam_.fx, 0, cam_.cx, 0, cam_.fy, cam_.cy, 0, 0, 1;
    for (const PlacedBoard& pb : boards) {
      for (const BoardTag& t : pb.board->tags) {
        if (std::find(o.hidden_ids.begin(), o.hidden_ids.end(), t.id) != o.hidden_ids.end())
          continue;
        const cv::Mat& bmp = bitmap(t.id);
        const double cells = family_->width_at_border;  // black border edge to edge
        const double border = (bmp.cols - cells) / 2.0;  // quiet zone cells each side
        // Board point of bitmap coordinates (u, v) in cells: X = a u + b v + c.
        const Eigen::Vector3d& p0 = t.corners[0];
        const Eigen::Vector3d& p2 = t.corners[2];
        const Eigen::Vector3d& p3 = t.corners[3];
        const Eigen::Vector3d a = (p2 - p3) / cells, b = (p0 - p3) / cells;
        const Eigen::Vector3d c = p3 - a * border - b * border;
        Eigen::Matrix3d M;
        M.col(0) = pb.T_cam_board.linear() * a;
        M.col(1) = pb.T_cam_board.linear() * b;
        M.col(2) = pb.T_cam_board.linear() * c + pb.T_cam_board.translation();
        // bitmap pixel index (i, j) has its centre at cell (i + 0.5, j + 0.5)
        Eigen::Matrix3d Tc;
        Tc << 1, 0, 0.5, 0, 1, 0.5, 0, 0, 1;
        Eigen::Matrix3d Hm = A * K * M * Tc;  // bitmap pixel -> hi-res pixel
        // bounding box in hi-res pixels
        std::vector<cv::Point2f> quad;
        for (double u : {-0.5, bmp.cols - 0.5})
          for (double v : {-0.5, bmp.rows - 0.5}) {
            Eigen::Vector3d q = Hm * Eigen::Vector3d(u, v, 1);
            quad.emplace_back(float(q.x() / q.z()), float(q.y() / q.z()));
          }
        cv::Rect box = cv::boundingRect(quad);
        box.x -= 2;
        box.y -= 2;
        box.width += 4;
        box.height += 4;
        box &= cv::Rect(0, 0, W, H);
        if (box.area() <= 0) continue;
        Eigen::Matrix3d shift;
        shift << 1, 0, -box.x, 0, 1, -box.y, 0, 0, 1;
        Eigen::Matrix3d Hb = shift * Hm;
        cv::Mat Hcv;
        cv::eigen2cv(Hb, Hcv);
        cv::Mat dst = hi(box);
        cv::warpPerspective(bmp, dst, Hcv, dst.size(), cv::INTER_NEAREST, cv::BORDER_TRANSPARENT);
      }
    }
    cv::Mat ideal;
    cv::resize(hi, ideal, cv::Size(W / S, H / S), 0, 0, cv::INTER_AREA);
    cv::Mat grey;
    if (map_x_.empty()) {
      grey = ideal;
    } else {
      cv::Mat mx = map_x_ + float(margin), my = map_y_ + float(margin);
      cv::remap(ideal, grey, mx, my, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
    }
    cv::Mat f;
    grey.convertTo(f, CV_32F);
    if (o.blur_sigma > 0) cv::GaussianBlur(f, f, cv::Size(0, 0), o.blur_sigma);
    if (o.noise_sigma > 0) {
      std::mt19937 rng(o.seed);
      std::normal_distribution<float> n(0.f, float(o.noise_sigma));
      for (int y = 0; y < f.rows; ++y) {
        float* row = f.ptr<float>(y);
        for (int x = 0; x < f.cols; ++x) row[x] += n(rng);
      }
    }
    cv::Mat out8, bgr;
    f.convertTo(out8, CV_8U);
    cv::cvtColor(out8, bgr, cv::COLOR_GRAY2BGR);
    return bgr;
  }

  double white = 235, black = 25;  // grey levels of the tags' cells

 private:
  const cv::Mat& bitmap(int id) {
    auto it = bitmaps_.find(id);
    if (it != bitmaps_.end()) return it->second;
    image_u8_t* im = apriltag_to_image(family_, id);
    cv::Mat m(im->height, im->width, CV_8UC1);
    for (int y = 0; y < im->height; ++y)
      for (int x = 0; x < im->width; ++x)
        m.at<uint8_t>(y, x) = im->buf[y * im->stride + x] ? uint8_t(white) : uint8_t(black);
    // image_u8_destroy is not exported by the shared library; image_u8_create used calloc.
    free(im->buf);
    free(im);
    return bitmaps_[id] = m;
  }

  calibration::CameraModel cam_;
  apriltag_family_t* family_ = nullptr;
  std::map<int, cv::Mat> bitmaps_;
  cv::Mat map_x_, map_y_;
};

// T_cam_board looking at the board from distance_mm, tilted by the given angles (degrees).
inline Eigen::Isometry3d look_at_board(double x_mm, double y_mm, double distance_mm,
                                       double tilt_x_deg, double tilt_y_deg, double roll_deg) {
  const double d2r = M_PI / 180.0;
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = (Eigen::AngleAxisd(roll_deg * d2r, Eigen::Vector3d::UnitZ()) *
                Eigen::AngleAxisd(tilt_y_deg * d2r, Eigen::Vector3d::UnitY()) *
                Eigen::AngleAxisd(tilt_x_deg * d2r, Eigen::Vector3d::UnitX()))
                   .toRotationMatrix();
  T.translation() = Eigen::Vector3d(x_mm, y_mm, distance_mm);
  return T;
}

}  // namespace crepuscular::tracking::testing
