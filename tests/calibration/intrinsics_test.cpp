// Tests of calibration/intrinsics: synthetic views projected with cv::projectPoints from known
// intrinsics plus 0.2 px noise (every parameter within its reported 3 sigma, fx and fy within
// 0.2 %), agreement with cv::calibrateCamera on the same detections, outlier view rejection,
// refusals with advice, and chessboard detection on rendered images.
#include "calibration/intrinsics.hpp"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <initializer_list>
#include <iterator>
#include <opencv2/calib3d.hpp>
#include <opencv2/core/persistence.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <random>
#include <string>
#include <vector>

#include "foundation/error.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/temporary_folder.hpp"
#include "tracking/board.hpp"
#include "tracking/detector.hpp"
#include "tracking/pose.hpp"
#include "tracking/synthetic.hpp"

namespace crepuscular::calibration {
namespace {

using test::expect_error_containing;

constexpr double kPi = 3.14159265358979323846;
constexpr int kWidth = 1280;
constexpr int kHeight = 720;

// The camera the synthetic views are taken with.
struct TrueCamera {
  double fx = 910.0, fy = 905.0, cx = 652.0, cy = 351.0;
  double k1 = -0.21, k2 = 0.09, p1 = 0.0012, p2 = -0.0009, k3 = -0.015;
  cv::Matx33d K() const { return {fx, 0, cx, 0, fy, cy, 0, 0, 1}; }
  std::vector<double> dist() const { return {k1, k2, p1, p2, k3}; }
  std::array<double, 9> params() const { return {fx, fy, cx, cy, k1, k2, p1, p2, k3}; }
};

// A grid target of cols x rows corners, spacing_mm apart, in its z = 0 plane.
std::vector<Eigen::Vector3d> grid_points(int cols, int rows, double spacing_mm) {
  std::vector<Eigen::Vector3d> points;
  for (int r = 0; r < rows; ++r) {
    for (int c = 0; c < cols; ++c) points.emplace_back(c * spacing_mm, r * spacing_mm, 0.0);
  }
  return points;
}

std::vector<Eigen::Vector2d> project(const TrueCamera& cam, const Eigen::Isometry3d& T_cam_target,
                                     const std::vector<Eigen::Vector3d>& points) {
  std::vector<cv::Point3d> in;
  for (const auto& p : points) {
    const Eigen::Vector3d q = T_cam_target * p;
    in.emplace_back(q.x(), q.y(), q.z());
  }
  std::vector<cv::Point2d> out;
  cv::projectPoints(in, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), cam.K(), cam.dist(), out);
  std::vector<Eigen::Vector2d> pixels;
  for (const auto& p : out) pixels.emplace_back(p.x, p.y);
  return pixels;
}

struct ViewSpec {
  double max_tilt_deg = 40.0;
  double min_depth_mm = 380.0, max_depth_mm = 750.0;
  double centre_lo = 0.0, centre_hi = 1.0;  // where the target centre lands (fraction of image)
};

// `count` views of the grid with random tilts and positions that keep every corner in the image,
// with Gaussian pixel noise of noise_px (seeded, reproducible).
std::vector<CalibrationView> synthetic_views(const TrueCamera& cam, int count, double noise_px,
                                             unsigned seed, const ViewSpec& spec = {}) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> uni(0.0, 1.0);
  std::normal_distribution<double> noise(0.0, noise_px);
  const auto target = grid_points(10, 7, 30.0);
  const Eigen::Vector3d centre(135.0, 90.0, 0.0);
  std::vector<CalibrationView> views;
  int attempts = 0;
  while (int(views.size()) < count && attempts++ < 100000) {
    const double ax = (2 * uni(rng) - 1) * spec.max_tilt_deg * kPi / 180.0;
    const double ay = (2 * uni(rng) - 1) * spec.max_tilt_deg * kPi / 180.0;
    const double az = (2 * uni(rng) - 1) * 20.0 * kPi / 180.0;
    const double depth = spec.min_depth_mm + uni(rng) * (spec.max_depth_mm - spec.min_depth_mm);
    const double u = (spec.centre_lo + uni(rng) * (spec.centre_hi - spec.centre_lo)) * kWidth;
    const double v = (spec.centre_lo + uni(rng) * (spec.centre_hi - spec.centre_lo)) * kHeight;
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = (Eigen::AngleAxisd(ax, Eigen::Vector3d::UnitX()) *
                  Eigen::AngleAxisd(ay, Eigen::Vector3d::UnitY()) *
                  Eigen::AngleAxisd(az, Eigen::Vector3d::UnitZ()))
                     .toRotationMatrix();
    const Eigen::Vector3d c_cam((u - cam.cx) / cam.fx * depth, (v - cam.cy) / cam.fy * depth,
                                depth);
    T.translation() = c_cam - T.linear() * centre;
    bool inside = true;
    for (const auto& p : target) inside = inside && (T * p).z() > 100.0;
    if (!inside) continue;
    const auto pixels = project(cam, T, target);
    for (const auto& p : pixels) {
      inside = inside && p.x() > 10 && p.y() > 10 && p.x() < kWidth - 10 && p.y() < kHeight - 10;
    }
    if (!inside) continue;
    CalibrationView view;
    view.name = "view" + std::to_string(views.size());
    view.object_points = target;
    for (const auto& p : pixels)
      view.image_points.push_back(p + Eigen::Vector2d(noise(rng), noise(rng)));
    views.push_back(std::move(view));
  }
  return views;
}

TEST(Intrinsics, RecoversKnownCameraWithinReportedThreeSigma) {
  const TrueCamera truth;
  const auto views = synthetic_views(truth, 20, 0.2, 1234);
  ASSERT_EQ(views.size(), 20u);
  const auto t0 = std::chrono::steady_clock::now();
  const IntrinsicsResult r = calibrate_intrinsics(views, kWidth, kHeight);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const std::array<double, 9> est = {r.camera.fx,
                                     r.camera.fy,
                                     r.camera.cx,
                                     r.camera.cy,
                                     r.camera.distortion[0],
                                     r.camera.distortion[1],
                                     r.camera.distortion[2],
                                     r.camera.distortion[3],
                                     r.camera.distortion[4]};
  const auto want = truth.params();
  for (size_t p = 0; p < 9; ++p) {
    EXPECT_GT(r.stddev[p], 0.0) << intrinsic_parameter_names()[p];
    EXPECT_NEAR(est[p], want[p], 3.0 * r.stddev[p])
        << intrinsic_parameter_names()[p] << " sigma " << r.stddev[p];
  }
  EXPECT_NEAR(r.camera.fx, truth.fx, 0.002 * truth.fx);
  EXPECT_NEAR(r.camera.fy, truth.fy, 0.002 * truth.fy);
  // 0.2 px per coordinate: the 2D residual RMS is about 0.2 * sqrt(2) = 0.28 px.
  EXPECT_GT(r.rms_px, 0.2);
  EXPECT_LT(r.rms_px, 0.34);
  EXPECT_EQ(r.views_used, 20);
  for (const auto& v : r.views) EXPECT_FALSE(v.rejected) << v.name;
  EXPECT_LT(seconds, 20.0);
  std::printf(
      "fx %.3f +- %.3f  fy %.3f +- %.3f  cx %.3f +- %.3f  cy %.3f +- %.3f  rms %.3f px  "
      "%.2f s\n",
      r.camera.fx, r.stddev[0], r.camera.fy, r.stddev[1], r.camera.cx, r.stddev[2], r.camera.cy,
      r.stddev[3], r.rms_px, seconds);
}

TEST(Intrinsics, AgreesWithOpenCvCalibrateCamera) {
  const TrueCamera truth;
  const auto views = synthetic_views(truth, 15, 0.2, 99);
  ASSERT_EQ(views.size(), 15u);
  const IntrinsicsResult r = calibrate_intrinsics(views, kWidth, kHeight);
  std::vector<std::vector<cv::Point3f>> obj;
  std::vector<std::vector<cv::Point2f>> img;
  for (const auto& v : views) {
    obj.emplace_back();
    img.emplace_back();
    for (size_t k = 0; k < v.object_points.size(); ++k) {
      obj.back().emplace_back(float(v.object_points[k].x()), float(v.object_points[k].y()), 0.f);
      img.back().emplace_back(float(v.image_points[k].x()), float(v.image_points[k].y()));
    }
  }
  cv::Mat K, dist;
  std::vector<cv::Mat> rvecs, tvecs;
  const double cv_rms = cv::calibrateCamera(
      obj, img, cv::Size(kWidth, kHeight), K, dist, rvecs, tvecs, 0,
      cv::TermCriteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, 200, 1e-12));
  EXPECT_NEAR(r.camera.fx, K.at<double>(0, 0), 0.005 * K.at<double>(0, 0));
  EXPECT_NEAR(r.camera.fy, K.at<double>(1, 1), 0.005 * K.at<double>(1, 1));
  EXPECT_NEAR(r.camera.cx, K.at<double>(0, 2), 0.005 * K.at<double>(0, 2));
  EXPECT_NEAR(r.camera.cy, K.at<double>(1, 2), 0.005 * K.at<double>(1, 2));
  // OpenCV's RMS is per coordinate pair as well (sqrt(sum |r|^2 / N)).
  EXPECT_NEAR(r.rms_px, cv_rms, 0.02);
  // Distortion compared where it matters: the pixel displacement it causes across the image.
  double worst = 0;
  for (double x = -0.6; x <= 0.6; x += 0.1) {
    for (double y = -0.35; y <= 0.35; y += 0.07) {
      std::vector<cv::Point3d> p = {{x, y, 1.0}};
      std::vector<cv::Point2d> a, b;
      cv::projectPoints(p, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), K, dist, a);
      const cv::Matx33d K2(r.camera.fx, 0, r.camera.cx, 0, r.camera.fy, r.camera.cy, 0, 0, 1);
      std::vector<double> d2(r.camera.distortion.begin(), r.camera.distortion.end());
      cv::projectPoints(p, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), K2, d2, b);
      worst = std::max(worst, cv::norm(a[0] - b[0]));
    }
  }
  EXPECT_LT(worst, 0.5) << "largest pixel difference between the two calibrations";
  std::printf(
      "Ceres fx %.3f fy %.3f cx %.3f cy %.3f | OpenCV fx %.3f fy %.3f cx %.3f cy %.3f | "
      "max pixel difference %.3f\n",
      r.camera.fx, r.camera.fy, r.camera.cx, r.camera.cy, K.at<double>(0, 0), K.at<double>(1, 1),
      K.at<double>(0, 2), K.at<double>(1, 2), worst);
}

// A TUM VI-like fisheye (512 x 512, f 191 px, Kalibr's equidistant coefficients of its cam0).
struct TrueFisheye {
  double fx = 190.97847715128717, fy = 190.9733070521226, cx = 254.93170605935475,
         cy = 256.8974428996504;
  cv::Vec4d k{0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202,
              0.00020293673591811182};
  cv::Matx33d K() const { return {fx, 0, cx, 0, fy, cy, 0, 0, 1}; }
};

// `count` views of a 10 x 7 grid of 30 mm seen through the fisheye (cv::fisheye::projectPoints),
// every corner inside the 512 x 512 image and under 80 degrees off axis, with Gaussian noise.
std::vector<CalibrationView> fisheye_views(const TrueFisheye& cam, int count, double noise_px,
                                           unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> uni(0.0, 1.0);
  std::normal_distribution<double> noise(0.0, noise_px);
  const auto target = grid_points(10, 7, 30.0);
  const Eigen::Vector3d centre(135.0, 90.0, 0.0);
  std::vector<CalibrationView> views;
  int attempts = 0;
  while (int(views.size()) < count && attempts++ < 100000) {
    // Target centre 0-65 degrees off axis, 200-450 mm away, turned towards the camera +- 45.
    const double off = uni(rng) * 65.0 * kPi / 180.0, az = (2 * uni(rng) - 1) * kPi;
    const double depth = 200.0 + uni(rng) * 250.0;
    const Eigen::Vector3d dir(std::sin(off) * std::cos(az), std::sin(off) * std::sin(az),
                              std::cos(off));
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() =
        (Eigen::AngleAxisd((2 * uni(rng) - 1) * 45.0 * kPi / 180.0, Eigen::Vector3d::UnitX()) *
         Eigen::AngleAxisd((2 * uni(rng) - 1) * 45.0 * kPi / 180.0, Eigen::Vector3d::UnitY()) *
         Eigen::AngleAxisd((2 * uni(rng) - 1) * kPi, Eigen::Vector3d::UnitZ()))
            .toRotationMatrix();
    T.translation() = depth * dir - T.linear() * centre;
    std::vector<cv::Point3d> in;
    bool inside = true;
    for (const auto& p : target) {
      const Eigen::Vector3d q = T * p;
      inside = inside && q.z() > 0 && std::atan2(q.head<2>().norm(), q.z()) < 80.0 * kPi / 180.0;
      in.emplace_back(q.x(), q.y(), q.z());
    }
    if (!inside) continue;
    std::vector<cv::Point2d> out;
    cv::fisheye::projectPoints(in, out, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), cam.K(), cam.k);
    for (const auto& p : out) inside = inside && p.x > 5 && p.y > 5 && p.x < 506 && p.y < 506;
    if (!inside) continue;
    CalibrationView view;
    view.name = "fisheye" + std::to_string(views.size());
    view.object_points = target;
    for (const auto& p : out) view.image_points.emplace_back(p.x + noise(rng), p.y + noise(rng));
    views.push_back(std::move(view));
  }
  return views;
}

// The equidistant calibration on synthetic fisheye corners agrees with cv::fisheye::calibrate on
// the same corners (fx fy cx cy within 0.1 %), and both find the true camera.
TEST(Intrinsics, FisheyeAgreesWithOpenCvFisheyeCalibrate) {
  const TrueFisheye truth;
  const auto views = fisheye_views(truth, 20, 0.2, 2024);
  ASSERT_EQ(views.size(), 20u);
  IntrinsicsOptions options;
  options.model = DistortionModel::equidistant;
  const auto t0 = std::chrono::steady_clock::now();
  const IntrinsicsResult r = calibrate_intrinsics(views, 512, 512, options);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  EXPECT_EQ(r.camera.model, DistortionModel::equidistant);
  EXPECT_EQ(r.camera.distortion[4], 0.0);
  EXPECT_EQ(r.stddev[8], 0.0);
  ASSERT_EQ(intrinsic_parameter_names(DistortionModel::equidistant).size(), 8u);

  std::vector<std::vector<cv::Point3d>> obj;
  std::vector<std::vector<cv::Point2d>> img;
  for (const auto& v : views) {
    obj.emplace_back();
    img.emplace_back();
    for (size_t k = 0; k < v.object_points.size(); ++k) {
      obj.back().emplace_back(v.object_points[k].x(), v.object_points[k].y(), 0.0);
      img.back().emplace_back(v.image_points[k].x(), v.image_points[k].y());
    }
  }
  cv::Matx33d K;
  cv::Vec4d D;
  std::vector<cv::Vec3d> rvecs, tvecs;
  const double cv_rms = cv::fisheye::calibrate(
      obj, img, cv::Size(512, 512), K, D, rvecs, tvecs,
      cv::fisheye::CALIB_RECOMPUTE_EXTRINSIC | cv::fisheye::CALIB_FIX_SKEW,
      cv::TermCriteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, 200, 1e-14));
  const double ours[4] = {r.camera.fx, r.camera.fy, r.camera.cx, r.camera.cy};
  const double opencv[4] = {K(0, 0), K(1, 1), K(0, 2), K(1, 2)};
  const double want[4] = {truth.fx, truth.fy, truth.cx, truth.cy};
  for (int p = 0; p < 4; ++p) {
    EXPECT_NEAR(ours[p], opencv[p], 0.001 * opencv[p]) << intrinsic_parameter_names()[size_t(p)];
    EXPECT_NEAR(ours[p], want[p], 0.005 * want[p]) << intrinsic_parameter_names()[size_t(p)];
    EXPECT_NEAR(opencv[p], want[p], 0.005 * want[p]) << intrinsic_parameter_names()[size_t(p)];
    EXPECT_NEAR(ours[p], want[p], 4.0 * r.stddev[size_t(p)])
        << intrinsic_parameter_names()[size_t(p)];
  }
  for (int i = 0; i < 4; ++i) {
    EXPECT_GT(r.stddev[size_t(4 + i)], 0.0);
    EXPECT_NEAR(r.camera.distortion[size_t(i)], truth.k[i], 4.0 * r.stddev[size_t(4 + i)])
        << "k" << i + 1;
  }
  // OpenCV's RMS is per coordinate pair too; 0.2 px per coordinate gives about 0.28 px.
  EXPECT_NEAR(r.rms_px, cv_rms, 0.01);
  EXPECT_GT(r.rms_px, 0.2);
  EXPECT_LT(r.rms_px, 0.34);
  // The two lenses image every ray out to 80 degrees at nearly the same pixel.
  CameraModel theirs = CameraModel::from_opencv(cv::Mat(K), cv::Mat(D), 512, 512, "OpenCV",
                                                DistortionModel::equidistant);
  double worst = 0;
  for (double t = 0; t <= 80.0; t += 5.0) {
    for (double a = 0; a < 360.0; a += 30.0) {
      const Eigen::Vector3d ray(std::sin(t * kPi / 180) * std::cos(a * kPi / 180),
                                std::sin(t * kPi / 180) * std::sin(a * kPi / 180),
                                std::cos(t * kPi / 180));
      worst = std::max(worst, (r.camera.project(ray) - theirs.project(ray)).norm());
    }
  }
  EXPECT_LT(worst, 0.3);
  EXPECT_LT(seconds, 20.0);
  // k3 of Brown-Conrady cannot be kept at 0 on a fisheye.
  options.fix_k3 = true;
  expect_error_containing([&] { calibrate_intrinsics(views, 512, 512, options); },
                          {"fix-k3", "fisheye", "--lens pinhole"});
  std::printf(
      "fisheye Ceres fx %.3f fy %.3f cx %.3f cy %.3f (sigma fx %.3f) | OpenCV fx %.3f fy "
      "%.3f cx %.3f cy %.3f | truth fx %.3f | rms %.4f vs %.4f px | max pixel difference "
      "%.3f | %.2f s\n",
      r.camera.fx, r.camera.fy, r.camera.cx, r.camera.cy, r.stddev[0], K(0, 0), K(1, 1), K(0, 2),
      K(1, 2), truth.fx, r.rms_px, cv_rms, worst, seconds);
}

// End to end through the command line: `synth` renders a fisheye recording of an AprilTag grid,
// `calibrate camera --lens fisheye` finds the camera and writes an equidistant camera.yaml.
TEST(Intrinsics, CalibrateCameraCommandWithFisheyeLens) {
  namespace fs = std::filesystem;
  const test::TemporaryFolder dir;
  const TrueFisheye truth;
  const tracking::Board grid = tracking::make_grid_board("calib", 4, 5, 30.0, 8.0, 0);
  std::vector<cv::Point3d> corners;
  for (const auto& t : grid.tags) {
    for (const auto& c : t.corners) corners.emplace_back(c.x(), c.y(), c.z());
  }
  std::mt19937 rng(77);
  std::uniform_real_distribution<double> uni(0.0, 1.0);
  std::string poses;
  int kept = 0, attempts = 0;
  while (kept < 14 && attempts++ < 100000) {
    const double off = uni(rng) * 50.0 * kPi / 180.0, az = (2 * uni(rng) - 1) * kPi;
    const double depth = 170.0 + uni(rng) * 120.0;
    const Eigen::Vector3d rotvec((2 * uni(rng) - 1) * 35.0, (2 * uni(rng) - 1) * 35.0,
                                 (2 * uni(rng) - 1) * 30.0);
    const Eigen::Matrix3d R =
        Eigen::AngleAxisd(rotvec.norm() * kPi / 180.0, rotvec.normalized()).toRotationMatrix();
    const Eigen::Vector3d t = depth * Eigen::Vector3d(std::sin(off) * std::cos(az),
                                                      std::sin(off) * std::sin(az), std::cos(off)) -
                              R * Eigen::Vector3d(95.0, 76.0, 0.0);
    cv::Matx33d Rcv;
    for (int i = 0; i < 9; ++i) Rcv(i / 3, i % 3) = R(i / 3, i % 3);
    cv::Vec3d rvec;
    cv::Rodrigues(Rcv, rvec);
    std::vector<cv::Point2d> px;
    cv::fisheye::projectPoints(corners, px, rvec, cv::Vec3d(t.x(), t.y(), t.z()), truth.K(),
                               truth.k);
    bool inside = true;
    for (const auto& c : corners)
      inside = inside && (R * Eigen::Vector3d(c.x, c.y, 0) + t).z() > 50;
    for (const auto& p : px) inside = inside && p.x > 20 && p.y > 20 && p.x < 491 && p.y < 491;
    if (!inside) continue;
    char line[200];
    std::snprintf(line, sizeof line,
                  "%s{\"t\": %d, \"translation_mm\": [%.6f, %.6f, %.6f], \"rotvec_deg\": [%.6f, "
                  "%.6f, %.6f]}",
                  kept ? ", " : "", kept, t.x(), t.y(), t.z(), rotvec.x(), rotvec.y(), rotvec.z());
    poses += line;
    ++kept;
  }
  ASSERT_EQ(kept, 14);
  char camera[400];
  std::snprintf(camera, sizeof camera,
                "{\"width\": 512, \"height\": 512, \"fx\": %.12g, \"fy\": %.12g, \"cx\": %.12g, "
                "\"cy\": %.12g, \"distortion_model\": \"equidistant\", \"distortion\": [%.12g, "
                "%.12g, %.12g, %.12g]}",
                truth.fx, truth.fy, truth.cx, truth.cy, truth.k[0], truth.k[1], truth.k[2],
                truth.k[3]);
  tracking::write_boards((dir / "boards.json").string(), {grid});
  std::ofstream(dir / "scene.json") << "{\"camera\": " << camera
                                    << ", \"background\": \"plain\", \"boards\": \"boards.json\", "
                                       "\"fps\": 1, \"frames\": 14, \"noise_sigma\": 2, "
                                       "\"poses\": {\"calib\": ["
                                    << poses << "]}}";
  const std::string bin = CREPUSCULAR_BINARY;
  const std::string log = (dir / "log.txt").string();
  const std::string synth = bin + " synth --scene " + (dir / "scene.json").string() + " --out " +
                            (dir / "rec").string() + " > " + log + " 2>&1";
  ASSERT_EQ(std::system(synth.c_str()), 0) << synth;
  const std::string out = (dir / "camera.yaml").string();
  const std::string calibrate = bin + " calibrate camera --recording " + (dir / "rec").string() +
                                " --board " + (dir / "boards.json").string() +
                                " --lens fisheye --out " + out + " >> " + log + " 2>&1";
  ASSERT_EQ(std::system(calibrate.c_str()), 0) << calibrate;
  const CameraModel cam = CameraModel::read_yaml(out);
  EXPECT_EQ(cam.model, DistortionModel::equidistant);
  EXPECT_NEAR(cam.fx, truth.fx, 0.01 * truth.fx);
  EXPECT_NEAR(cam.fy, truth.fy, 0.01 * truth.fy);
  EXPECT_NEAR(cam.cx, truth.cx, 0.01 * truth.cx);
  EXPECT_NEAR(cam.cy, truth.cy, 0.01 * truth.cy);
  cv::FileStorage in(out, cv::FileStorage::READ);
  EXPECT_EQ(std::string(in["distortion_model"]), "equidistant");
  EXPECT_FALSE(in["parameter_stddev"]["k4"].empty());
  std::printf(
      "fisheye from a rendered recording: fx %.2f fy %.2f cx %.2f cy %.2f (truth %.2f "
      "%.2f %.2f %.2f), RMS %.3f px\n",
      cam.fx, cam.fy, cam.cx, cam.cy, truth.fx, truth.fy, truth.cx, truth.cy,
      double(in["rms_reprojection_error_px"]));
  // The lens flag is explained in --help and checked.
  const std::string help = bin + " calibrate camera --help > " + log + " 2>&1";
  ASSERT_EQ(std::system(help.c_str()), 0);
  std::ifstream help_text(log);
  const std::string text((std::istreambuf_iterator<char>(help_text)),
                         std::istreambuf_iterator<char>());
  EXPECT_NE(text.find("--lens"), std::string::npos) << text;
  EXPECT_NE(text.find("fisheye"), std::string::npos) << text;
  const std::string bad = bin + " calibrate camera --recording " + (dir / "rec").string() +
                          " --board " + (dir / "boards.json").string() + " --lens wide --out " +
                          (dir / "bad.yaml").string() + " > " + log + " 2>&1";
  EXPECT_NE(std::system(bad.c_str()), 0);
  EXPECT_FALSE(fs::exists(dir / "bad.yaml"));
}

TEST(Intrinsics, RejectsOutlierView) {
  const TrueCamera truth;
  auto views = synthetic_views(truth, 12, 0.2, 7);
  ASSERT_EQ(views.size(), 12u);
  // View 5: half of its corners displaced by 6 px (a mis-detection).
  std::mt19937 rng(5);
  std::normal_distribution<double> bad(0.0, 6.0);
  for (size_t k = 0; k < views[5].image_points.size(); k += 2) {
    views[5].image_points[k] += Eigen::Vector2d(bad(rng), bad(rng));
  }
  const IntrinsicsResult r = calibrate_intrinsics(views, kWidth, kHeight);
  EXPECT_TRUE(r.views[5].rejected);
  EXPECT_EQ(r.views_used, 11);
  EXPECT_NEAR(r.camera.fx, truth.fx, 0.002 * truth.fx);
  EXPECT_NEAR(r.camera.fy, truth.fy, 0.002 * truth.fy);
  EXPECT_LT(r.rms_px, 0.34);
}

TEST(Intrinsics, RefusesTooFewViews) {
  const TrueCamera truth;
  const auto views = synthetic_views(truth, 3, 0.2, 11);
  expect_error_containing([&] { calibrate_intrinsics(views, kWidth, kHeight); },
                          {"only 3 usable view", "Capture"});
}

TEST(Intrinsics, RefusesFrontoParallelViews) {
  const TrueCamera truth;
  ViewSpec spec;
  spec.max_tilt_deg = 1.5;
  const auto views = synthetic_views(truth, 10, 0.2, 13, spec);
  ASSERT_EQ(views.size(), 10u);
  expect_error_containing([&] { calibrate_intrinsics(views, kWidth, kHeight); },
                          {"orientation", "tilted"});
  // Without lens distortion the orientation check before the solve already refuses.
  TrueCamera pinhole;
  pinhole.k1 = pinhole.k2 = pinhole.p1 = pinhole.p2 = pinhole.k3 = 0.0;
  const auto flat = synthetic_views(pinhole, 10, 0.2, 13, spec);
  expect_error_containing([&] { calibrate_intrinsics(flat, kWidth, kHeight); },
                          {"same orientation", "tilted"});
}

TEST(Intrinsics, RefusesCornersOnlyInImageCentre) {
  const TrueCamera truth;
  ViewSpec spec;
  spec.min_depth_mm = 1400;
  spec.max_depth_mm = 1600;
  spec.centre_lo = 0.45;
  spec.centre_hi = 0.55;
  const auto views = synthetic_views(truth, 10, 0.2, 17, spec);
  ASSERT_EQ(views.size(), 10u);
  expect_error_containing([&] { calibrate_intrinsics(views, kWidth, kHeight); },
                          {"cover only", "top-left", "bottom-right"});
}

TEST(Intrinsics, ParsesChessboardSpec) {
  const auto spec = parse_chessboard_spec("chessboard:9x6:25");
  ASSERT_TRUE(spec.has_value());
  EXPECT_EQ(spec->cols, 9);
  EXPECT_EQ(spec->rows, 6);
  EXPECT_DOUBLE_EQ(spec->square_mm, 25.0);
  EXPECT_FALSE(parse_chessboard_spec("boards.json").has_value());
  expect_error_containing([] { parse_chessboard_spec("chessboard:9x6"); }, {"COLSxROWS"});
  expect_error_containing([] { parse_chessboard_spec("chessboard:9by6:25"); }, {"9by6"});
  expect_error_containing([] { parse_chessboard_spec("chessboard:9x6:-2"); }, {"SQUARE_MM"});
}

// Renders a chessboard of (cols+1) x (rows+1) squares seen by a pinhole camera (no distortion)
// with 4 x 4 supersampling; returns the image and the true inner-corner pixels.
cv::Mat render_chessboard(const ChessboardSpec& spec, const cv::Matx33d& K,
                          const Eigen::Isometry3d& T_cam_board) {
  // Homography board (x, y, 1) -> image.
  Eigen::Matrix3d H;
  Eigen::Matrix3d Ke;
  Ke << K(0, 0), 0, K(0, 2), 0, K(1, 1), K(1, 2), 0, 0, 1;
  H.col(0) = T_cam_board.linear().col(0);
  H.col(1) = T_cam_board.linear().col(1);
  H.col(2) = T_cam_board.translation();
  const Eigen::Matrix3d Hinv = (Ke * H).inverse();
  cv::Mat image(kHeight, kWidth, CV_8UC1);
  const double s = spec.square_mm;
  for (int v = 0; v < kHeight; ++v) {
    for (int u = 0; u < kWidth; ++u) {
      double sum = 0;
      for (int a = 0; a < 4; ++a) {
        for (int b = 0; b < 4; ++b) {
          const Eigen::Vector3d q =
              Hinv * Eigen::Vector3d(u - 0.375 + 0.25 * b, v - 0.375 + 0.25 * a, 1);
          const double x = q.x() / q.z(), y = q.y() / q.z();
          // Squares from -s to cols*s (one square beyond the outer inner corners), white margin.
          double value = 230;
          if (x > -s && y > -s && x < spec.cols * s && y < spec.rows * s) {
            const int i = int(std::floor(x / s)) + 1, j = int(std::floor(y / s)) + 1;
            value = ((i + j) % 2 == 0) ? 25 : 230;
          }
          sum += value;
        }
      }
      image.at<uint8_t>(v, u) = cv::saturate_cast<uint8_t>(sum / 16.0);
    }
  }
  return image;
}

TEST(Intrinsics, DetectsRenderedChessboardCornersToSubPixel) {
  const ChessboardSpec spec{9, 6, 25.0};
  const cv::Matx33d K(900, 0, 640, 0, 900, 360, 0, 0, 1);
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = (Eigen::AngleAxisd(0.35, Eigen::Vector3d::UnitX()) *
                Eigen::AngleAxisd(-0.25, Eigen::Vector3d::UnitY()))
                   .toRotationMatrix();
  T.translation() = Eigen::Vector3d(-90, -60, 600);
  const cv::Mat image = render_chessboard(spec, K, T);
  const auto view = detect_chessboard(image, spec, "rendered");
  ASSERT_TRUE(view.has_value());
  ASSERT_EQ(view->image_points.size(), 54u);
  double worst = 0, sum = 0;
  for (size_t k = 0; k < view->object_points.size(); ++k) {
    const Eigen::Vector3d p = T * view->object_points[k];
    const Eigen::Vector2d truth(K(0, 0) * p.x() / p.z() + K(0, 2),
                                K(1, 1) * p.y() / p.z() + K(1, 2));
    worst = std::max(worst, (view->image_points[k] - truth).norm());
    sum += (view->image_points[k] - truth).norm();
  }
  const double mean = sum / double(view->object_points.size());
  // cornerSubPix on an anti-aliased, perspective-distorted board: a few hundredths of a pixel on
  // average, under a quarter pixel at worst.
  EXPECT_LT(mean, 0.1) << "mean corner error in px";
  EXPECT_LT(worst, 0.25) << "largest corner error in px";
  std::printf("chessboard corner error: mean %.3f px, largest %.3f px\n", mean, worst);
  // A blank image holds no board.
  EXPECT_FALSE(detect_chessboard(cv::Mat(kHeight, kWidth, CV_8UC1, cv::Scalar(128)), spec, "blank")
                   .has_value());
}

// `crepuscular calibrate camera --images DIR --board chessboard:9x6:25` on rendered images: the
// written camera.yaml holds the rendering camera (no distortion) and the refusal exits non-zero.
TEST(Intrinsics, CalibrateCameraCommandOnRenderedChessboards) {
  namespace fs = std::filesystem;
  const test::TemporaryFolder dir;
  fs::create_directories(dir / "shots");
  const ChessboardSpec spec{9, 6, 25.0};
  const cv::Matx33d K(900, 0, 640, 0, 905, 360, 0, 0, 1);
  const double tilts[][2] = {{0.45, 0.0},  {-0.45, 0.1},  {0.1, 0.5},  {0.0, -0.5},
                             {0.35, 0.35}, {-0.3, -0.35}, {0.3, -0.3}, {-0.35, 0.3}};
  const double shifts[][2] = {{-250, -150}, {30, -150}, {-250, 20}, {30, 20},
                              {-110, -60},  {-240, 10}, {20, -140}, {-100, -80}};
  for (int v = 0; v < 8; ++v) {
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = (Eigen::AngleAxisd(tilts[v][0], Eigen::Vector3d::UnitX()) *
                  Eigen::AngleAxisd(tilts[v][1], Eigen::Vector3d::UnitY()))
                     .toRotationMatrix();
    T.translation() = Eigen::Vector3d(shifts[v][0], shifts[v][1], 620);
    cv::imwrite((dir / "shots" / ("view" + std::to_string(v) + ".png")).string(),
                render_chessboard(spec, K, T));
  }
  const std::string out = (dir / "camera.yaml").string();
  const std::string cmd = std::string(CREPUSCULAR_BINARY) + " calibrate camera --images '" +
                          (dir / "shots").string() + "/*.png' --board chessboard:9x6:25 --out " +
                          out + " > " + (dir / "log.txt").string() + " 2>&1";
  ASSERT_EQ(std::system(cmd.c_str()), 0) << cmd;
  cv::FileStorage in(out, cv::FileStorage::READ);
  ASSERT_TRUE(in.isOpened());
  cv::Mat Kc;
  in["camera_matrix"] >> Kc;
  EXPECT_NEAR(Kc.at<double>(0, 0), 900.0, 0.005 * 900.0);
  EXPECT_NEAR(Kc.at<double>(1, 1), 905.0, 0.005 * 905.0);
  EXPECT_NEAR(Kc.at<double>(0, 2), 640.0, 0.005 * 640.0);
  EXPECT_NEAR(Kc.at<double>(1, 2), 360.0, 0.005 * 360.0);
  EXPECT_LT(double(in["rms_reprojection_error_px"]), 0.2);
  EXPECT_EQ(int(in["views_used"]), 8);
  // Three views are too few: refused with advice, no file written.
  for (int v = 3; v < 8; ++v) fs::remove(dir / "shots" / ("view" + std::to_string(v) + ".png"));
  const std::string out2 = (dir / "camera2.yaml").string();
  const std::string cmd2 = std::string(CREPUSCULAR_BINARY) + " calibrate camera --images " +
                           (dir / "shots").string() + " --board chessboard:9x6:25 --out " + out2 +
                           " > " + (dir / "log2.txt").string() + " 2>&1";
  EXPECT_NE(std::system(cmd2.c_str()), 0);
  EXPECT_FALSE(fs::exists(out2));
  std::ifstream log(dir / "log2.txt");
  const std::string text((std::istreambuf_iterator<char>(log)), std::istreambuf_iterator<char>());
  EXPECT_NE(text.find("error: camera calibration: only 3 usable view"), std::string::npos) << text;
}

// AprilTag grid board rendered by tracking's synthetic camera (with lens distortion), detected by
// libapriltag, matched to the board's corners and calibrated: the rendering camera comes back.
TEST(Intrinsics, CalibratesFromRenderedAprilTagGrid) {
  const TrueCamera truth;
  tracking::SyntheticScene scene;
  scene.camera.width = kWidth;
  scene.camera.height = kHeight;
  scene.camera.fx = truth.fx;
  scene.camera.fy = truth.fy;
  scene.camera.cx = truth.cx;
  scene.camera.cy = truth.cy;
  scene.camera.distortion = {truth.k1, truth.k2, truth.p1, truth.p2, truth.k3};
  scene.fps = 1.0;
  scene.noise_sigma = 2.0;
  tracking::SceneBoard board;
  board.board = tracking::make_grid_board("calib", 5, 7, 30.0, 8.0, 0);
  std::vector<Eigen::Vector3d> corners;
  for (const auto& t : board.board.tags)
    corners.insert(corners.end(), t.corners.begin(), t.corners.end());
  std::mt19937 rng(31);
  std::uniform_real_distribution<double> uni(0.0, 1.0);
  int attempts = 0;
  while (board.keyframes.size() < 12 && attempts++ < 100000) {
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = (Eigen::AngleAxisd((2 * uni(rng) - 1) * 0.6, Eigen::Vector3d::UnitX()) *
                  Eigen::AngleAxisd((2 * uni(rng) - 1) * 0.6, Eigen::Vector3d::UnitY()) *
                  Eigen::AngleAxisd((2 * uni(rng) - 1) * 0.3, Eigen::Vector3d::UnitZ()))
                     .toRotationMatrix();
    const double depth = 420 + 250 * uni(rng);
    const double u = uni(rng) * kWidth, v = uni(rng) * kHeight;
    T.translation() = Eigen::Vector3d((u - truth.cx) / truth.fx * depth,
                                      (v - truth.cy) / truth.fy * depth, depth);
    bool inside = true;
    for (const auto& p : project(truth, T, corners)) {
      inside = inside && p.x() > 15 && p.y() > 15 && p.x() < kWidth - 15 && p.y() < kHeight - 15;
    }
    if (!inside) continue;
    board.keyframes.push_back({double(board.keyframes.size()), T});
  }
  ASSERT_EQ(board.keyframes.size(), 12u);
  scene.boards.push_back(board);
  scene.frame_count = 12;
  tracking::SyntheticRenderer renderer(scene);
  tracking::DetectorOptions options;
  options.decimate = 1.0;
  tracking::TagDetector detector(options);
  std::vector<CalibrationView> views;
  for (int64_t f = 0; f < 12; ++f) {
    const cv::Mat image = renderer.render(f);
    const auto matched = tracking::match_board_corners(board.board, detector.detect(image));
    CalibrationView view;
    view.name = "frame " + std::to_string(f);
    view.object_points = matched.board_mm;
    view.image_points = matched.pixels;
    EXPECT_EQ(view.object_points.size(), corners.size()) << view.name;
    views.push_back(view);
  }
  const IntrinsicsResult r = calibrate_intrinsics(views, kWidth, kHeight);
  EXPECT_NEAR(r.camera.fx, truth.fx, 0.005 * truth.fx);
  EXPECT_NEAR(r.camera.fy, truth.fy, 0.005 * truth.fy);
  EXPECT_NEAR(r.camera.cx, truth.cx, 0.01 * truth.cx);
  EXPECT_NEAR(r.camera.cy, truth.cy, 0.01 * truth.cy);
  EXPECT_LT(r.rms_px, 0.5);
  std::printf("AprilTag grid: fx %.2f fy %.2f cx %.2f cy %.2f k1 %.4f, RMS %.3f px over %d views\n",
              r.camera.fx, r.camera.fy, r.camera.cx, r.camera.cy, r.camera.distortion[0], r.rms_px,
              r.views_used);
}

TEST(Intrinsics, SelectsViewsForCoverage) {
  const TrueCamera truth;
  auto views = synthetic_views(truth, 30, 0.2, 21);
  const auto picked = select_views_for_coverage(views, kWidth, kHeight, 8);
  ASSERT_EQ(picked.size(), 8u);
  std::vector<CalibrationView> chosen;
  for (size_t i : picked) chosen.push_back(views[i]);
  std::vector<CalibrationView> first(views.begin(), views.begin() + 8);
  EXPECT_GE(corner_coverage(chosen, kWidth, kHeight, 10),
            corner_coverage(first, kWidth, kHeight, 10));
  for (size_t k = 1; k < picked.size(); ++k) EXPECT_LT(picked[k - 1], picked[k]);
}

}  // namespace
}  // namespace crepuscular::calibration
