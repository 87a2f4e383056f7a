// Tests of CameraModel (calibration/camera_model.hpp): projection and unprojection against OpenCV's
// cv::projectPoints and cv::undistortPoints on random points for several distortion sets, and
// against cv::fisheye on a strong equidistant fisheye out to 89 degrees off axis; YAML round trip
// readable by cv::FileStorage (with distortion_model), and errors on bad files.
#include "calibration/camera_model.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <opencv2/calib3d.hpp>
#include <random>
#include <string>
#include <vector>

#include "foundation/error.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/temporary_folder.hpp"

namespace crepuscular::calibration {
namespace {

using test::expect_error_containing;

namespace fs = std::filesystem;

CameraModel make_camera(const std::array<double, 5>& distortion) {
  CameraModel m;
  m.width = 1280;
  m.height = 720;
  m.fx = 1012.5;
  m.fy = 1008.25;
  m.cx = 641.3;
  m.cy = 357.9;
  m.distortion = distortion;
  return m;
}

// Distortion sets of real lenses: none, barrel, pincushion, decentred (tangential), strong k3.
const std::vector<std::array<double, 5>> kDistortions = {
    {0, 0, 0, 0, 0},
    {-0.28, 0.09, 0, 0, -0.012},
    {0.12, -0.05, 0, 0, 0.01},
    {-0.11, 0.04, 0.0012, -0.0009, 0.0},
    {0.05, -0.21, -0.0021, 0.0015, 0.34},
};

TEST(CameraModel, ProjectAgreesWithOpenCvProjectPoints) {
  std::mt19937 rng(20261123);
  for (size_t set = 0; set < kDistortions.size(); ++set) {
    const CameraModel m = make_camera(kDistortions[set]);
    // Points in front of the camera whose images fall inside (and a little beyond) the frame.
    std::uniform_real_distribution<double> nx(-0.7, 0.7), ny(-0.4, 0.4), z(150.0, 900.0);
    std::vector<cv::Point3d> points;
    for (int i = 0; i < 500; ++i) {
      const double zz = z(rng);
      points.emplace_back(nx(rng) * zz, ny(rng) * zz, zz);
    }
    std::vector<cv::Point2d> expected;
    cv::projectPoints(points, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), m.camera_matrix(),
                      m.distortion_coefficients(), expected);
    for (size_t i = 0; i < points.size(); ++i) {
      const Eigen::Vector2d p = m.project({points[i].x, points[i].y, points[i].z});
      ASSERT_NEAR(p.x(), expected[i].x, 1e-6) << "set " << set << " point " << i;
      ASSERT_NEAR(p.y(), expected[i].y, 1e-6) << "set " << set << " point " << i;
    }
  }
}

TEST(CameraModel, UnprojectAgreesWithOpenCvUndistortPoints) {
  std::mt19937 rng(7);
  for (size_t set = 0; set < kDistortions.size(); ++set) {
    const CameraModel m = make_camera(kDistortions[set]);
    std::uniform_real_distribution<double> u(0.0, m.width - 1.0), v(0.0, m.height - 1.0);
    std::vector<cv::Point2d> pixels;
    for (int i = 0; i < 500; ++i) pixels.emplace_back(u(rng), v(rng));
    // OpenCV iterates a fixed point 5 times by default; ask it to converge fully.
    std::vector<cv::Point2d> expected;
    cv::undistortPoints(
        pixels, expected, m.camera_matrix(), m.distortion_coefficients(), cv::noArray(),
        cv::noArray(),
        cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 500, 1e-14));
    for (size_t i = 0; i < pixels.size(); ++i) {
      const Eigen::Vector2d xy = m.unproject({pixels[i].x, pixels[i].y});
      // Normalised units times the focal length = pixels.
      ASSERT_NEAR(xy.x() * m.fx, expected[i].x * m.fx, 1e-6) << "set " << set << " px " << i;
      ASSERT_NEAR(xy.y() * m.fy, expected[i].y * m.fy, 1e-6) << "set " << set << " px " << i;
      // Newton's method from a nearby guess reaches the same point.
      const Eigen::Vector2d from_guess =
          m.unproject({pixels[i].x, pixels[i].y}, xy + Eigen::Vector2d(2e-3, -1.5e-3));
      ASSERT_NEAR((from_guess - xy).norm() * m.fx, 0.0, 1e-9) << "set " << set << " px " << i;
      // And it is the inverse of the projection.
      const Eigen::Vector2d back = m.project({xy.x() * 500.0, xy.y() * 500.0, 500.0});
      ASSERT_NEAR(back.x(), pixels[i].x, 1e-8) << "set " << set << " px " << i;
      ASSERT_NEAR(back.y(), pixels[i].y, 1e-8) << "set " << set << " px " << i;
    }
  }
}

TEST(CameraModel, ProjectOfPrincipalRayIsPrincipalPoint) {
  const CameraModel m = make_camera(kDistortions[1]);
  const Eigen::Vector2d p = m.project({0, 0, 400});
  EXPECT_DOUBLE_EQ(p.x(), m.cx);
  EXPECT_DOUBLE_EQ(p.y(), m.cy);
  // Barrel distortion (k1 < 0) pulls a point towards the centre: x_d = x (1 + k1 r^2 + ...).
  const double x = 0.3;
  const double r2 = x * x;
  const auto& d = m.distortion;
  const double expected = m.cx + m.fx * x * (1 + d[0] * r2 + d[1] * r2 * r2 + d[4] * r2 * r2 * r2);
  EXPECT_NEAR(m.project({x * 100, 0, 100}).x(), expected, 1e-9);
}

TEST(CameraModel, YamlRoundTripIsReadableByOpenCv) {
  const test::TemporaryFolder dir;
  const CameraModel m = make_camera(kDistortions[4]);
  const std::string path = (dir / "camera.yaml").string();
  m.write_yaml(path);
  const CameraModel r = CameraModel::read_yaml(path);
  EXPECT_EQ(r.width, m.width);
  EXPECT_EQ(r.height, m.height);
  EXPECT_DOUBLE_EQ(r.fx, m.fx);
  EXPECT_DOUBLE_EQ(r.fy, m.fy);
  EXPECT_DOUBLE_EQ(r.cx, m.cx);
  EXPECT_DOUBLE_EQ(r.cy, m.cy);
  for (size_t i = 0; i < 5; ++i) EXPECT_DOUBLE_EQ(r.distortion[i], m.distortion[i]) << i;

  // OpenCV reads the same fields the way ROS and OpenCV tools do.
  cv::FileStorage fsr(path, cv::FileStorage::READ);
  ASSERT_TRUE(fsr.isOpened());
  cv::Mat k, d;
  fsr["camera_matrix"] >> k;
  fsr["distortion_coefficients"] >> d;
  EXPECT_EQ(int(fsr["image_width"]), 1280);
  EXPECT_EQ(int(fsr["image_height"]), 720);
  ASSERT_EQ(k.rows, 3);
  ASSERT_EQ(k.cols, 3);
  EXPECT_DOUBLE_EQ(k.at<double>(0, 0), m.fx);
  EXPECT_DOUBLE_EQ(k.at<double>(1, 2), m.cy);
  ASSERT_EQ(d.total(), 5u);
  EXPECT_DOUBLE_EQ(d.at<double>(0, 4), m.distortion[4]);
  // No temporary file is left beside it.
  int files = 0;
  for ([[maybe_unused]] const auto& e : fs::directory_iterator(dir)) ++files;
  EXPECT_EQ(files, 1);
}

TEST(CameraModel, ReadsFileWrittenByOpenCvWithFourCoefficients) {
  const test::TemporaryFolder dir;
  const std::string path = (dir / "cam.yml").string();
  {
    cv::FileStorage out(path, cv::FileStorage::WRITE);
    out << "image_width" << 640 << "image_height" << 480;
    out << "camera_matrix" << (cv::Mat_<double>(3, 3) << 500, 0, 320, 0, 501, 240, 0, 0, 1);
    out << "distortion_coefficients" << (cv::Mat_<double>(4, 1) << -0.1, 0.01, 0.001, 0.002);
  }
  const CameraModel m = CameraModel::read_yaml(path);
  EXPECT_EQ(m.width, 640);
  EXPECT_DOUBLE_EQ(m.fy, 501);
  EXPECT_DOUBLE_EQ(m.distortion[3], 0.002);
  EXPECT_DOUBLE_EQ(m.distortion[4], 0.0);
}

TEST(CameraModel, BadFilesNameTheFileAndTheField) {
  const test::TemporaryFolder dir;
  const auto write = [&](const std::string& name, const std::string& text) {
    const std::string path = (dir / name).string();
    std::ofstream(path) << text;
    return path;
  };
  expect_error_containing([&] { CameraModel::read_yaml((dir / "absent.yaml").string()); },
                          {"absent.yaml", "not found"});
  const std::string garbage = write("garbage.yaml", "%YAML:1.0\ncamera_matrix: [1, 2\n  : :\n");
  expect_error_containing([&] { CameraModel::read_yaml(garbage); }, {"garbage.yaml"});
  const std::string missing =
      write("missing.yaml",
            "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n"
            "   rows: 3\n   cols: 3\n   dt: d\n   data: [ 500., 0., 320., 0., 500., 240., 0., 0., "
            "1. ]\n");
  expect_error_containing([&] { CameraModel::read_yaml(missing); },
                          {"missing.yaml", "distortion_coefficients", "missing"});
  const std::string wrong_shape =
      write("shape.yaml",
            "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n"
            "   rows: 2\n   cols: 3\n   dt: d\n   data: [ 500., 0., 320., 0., 500., 240. ]\n"
            "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
            "   data: [ 0., 0., 0., 0., 0. ]\n");
  expect_error_containing([&] { CameraModel::read_yaml(wrong_shape); },
                          {"shape.yaml", "camera_matrix", "2x3", "3x3"});
  const std::string no_width = write(
      "width.yaml",
      "%YAML:1.0\n---\nimage_width: -4\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n"
      "   rows: 3\n   cols: 3\n   dt: d\n   data: [ 500., 0., 320., 0., 500., 240., 0., 0., 1. ]\n"
      "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
      "   data: [ 0., 0., 0., 0., 0. ]\n");
  expect_error_containing([&] { CameraModel::read_yaml(no_width); },
                          {"width.yaml", "image_width", "-4"});
  const std::string rational = write(
      "rational.yaml",
      "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n"
      "   rows: 3\n   cols: 3\n   dt: d\n   data: [ 500., 0., 320., 0., 500., 240., 0., 0., 1. ]\n"
      "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 8\n   dt: d\n"
      "   data: [ 0., 0., 0., 0., 0., 0.3, 0., 0. ]\n");
  expect_error_containing([&] { CameraModel::read_yaml(rational); },
                          {"rational.yaml", "distortion_coefficients", "entry 5"});
  const std::string zero_focal = write(
      "focal.yaml",
      "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n"
      "   rows: 3\n   cols: 3\n   dt: d\n   data: [ 0., 0., 320., 0., 500., 240., 0., 0., 1. ]\n"
      "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
      "   data: [ 0., 0., 0., 0., 0. ]\n");
  expect_error_containing([&] { CameraModel::read_yaml(zero_focal); }, {"focal.yaml", "fx"});
}

// A TUM VI-like fisheye (512 x 512, about 190 degrees across the diagonal): Kalibr's equidistant
// calibration of its cam0.
CameraModel tum_vi_camera() {
  CameraModel m;
  m.model = DistortionModel::equidistant;
  m.width = 512;
  m.height = 512;
  m.fx = 190.97847715128717;
  m.fy = 190.9733070521226;
  m.cx = 254.93170605935475;
  m.cy = 256.8974428996504;
  m.distortion = {0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202,
                  0.00020293673591811182, 0.0};
  return m;
}

// Random camera-frame points 0 to max_deg degrees off the optical axis, 50 to 2000 mm away.
std::vector<cv::Point3d> points_off_axis(double max_deg, int count, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> angle(0.0, max_deg * M_PI / 180.0), azimuth(-M_PI, M_PI),
      range(50.0, 2000.0);
  std::vector<cv::Point3d> points;
  for (int i = 0; i < count; ++i) {
    const double t = angle(rng), a = azimuth(rng), r = range(rng);
    points.emplace_back(r * std::sin(t) * std::cos(a), r * std::sin(t) * std::sin(a),
                        r * std::cos(t));
  }
  points.emplace_back(0.0, 0.0, 300.0);  // the optical axis itself
  return points;
}

TEST(FisheyeCameraModel, ProjectAgreesWithOpenCvFisheyeProjectPoints) {
  const CameraModel m = tum_vi_camera();
  const std::vector<cv::Point3d> points = points_off_axis(89.0, 2000, 11);
  std::vector<cv::Point2d> expected;
  cv::fisheye::projectPoints(points, expected, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0),
                             m.camera_matrix(), m.distortion_coefficients());
  ASSERT_EQ(m.distortion_coefficients().total(), 4u);
  double worst = 0;
  for (size_t i = 0; i < points.size(); ++i) {
    const Eigen::Vector2d p = m.project({points[i].x, points[i].y, points[i].z});
    worst = std::max(worst, (p - Eigen::Vector2d(expected[i].x, expected[i].y)).norm());
    // The normalised path (distort, normalized_to_pixel) is the same projection.
    const Eigen::Vector2d q =
        m.normalized_to_pixel({points[i].x / points[i].z, points[i].y / points[i].z});
    ASSERT_NEAR((q - p).norm(), 0.0, 1e-9) << i;
  }
  EXPECT_LT(worst, 1e-9);
  std::printf("fisheye project vs cv::fisheye::projectPoints: worst %.2e px over %zu points\n",
              worst, points.size());
  // At 90 degrees an equidistant lens (k = 0) images at f * pi / 2 from the centre.
  CameraModel ideal = m;
  ideal.distortion = {0, 0, 0, 0, 0};
  EXPECT_NEAR(ideal.project({1e9, 0, 1e-3}).x() - m.cx, m.fx * M_PI / 2, 1e-6);
}

TEST(FisheyeCameraModel, UnprojectInvertsProjectionAndAgreesWithOpenCv) {
  const CameraModel m = tum_vi_camera();
  const std::vector<cv::Point3d> points = points_off_axis(89.0, 2000, 12);
  std::vector<cv::Point2d> pixels;
  for (const auto& p : points) {
    const Eigen::Vector2d px = m.project({p.x, p.y, p.z});
    pixels.emplace_back(px.x(), px.y());
  }
  std::vector<cv::Point2d> expected;
  cv::fisheye::undistortPoints(
      pixels, expected, m.camera_matrix(), m.distortion_coefficients(), cv::noArray(),
      cv::noArray(), cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 100, 1e-15));
  double worst_ray = 0, worst_opencv = 0, worst_round_trip = 0;
  for (size_t i = 0; i < points.size(); ++i) {
    const Eigen::Vector2d xy = m.unproject({pixels[i].x, pixels[i].y});
    ASSERT_TRUE(xy.allFinite()) << i;
    // The ray's angle to the true ray, in pixels at the focal length.
    const Eigen::Vector3d ray = Eigen::Vector3d(xy.x(), xy.y(), 1.0).normalized();
    const Eigen::Vector3d truth =
        Eigen::Vector3d(points[i].x, points[i].y, points[i].z).normalized();
    worst_ray = std::max(worst_ray, std::atan2(ray.cross(truth).norm(), ray.dot(truth)) * m.fx);
    const Eigen::Vector3d cv_ray = Eigen::Vector3d(expected[i].x, expected[i].y, 1.0).normalized();
    worst_opencv =
        std::max(worst_opencv, std::atan2(ray.cross(cv_ray).norm(), ray.dot(cv_ray)) * m.fx);
    const Eigen::Vector2d back = m.project({xy.x(), xy.y(), 1.0});
    worst_round_trip =
        std::max(worst_round_trip, (back - Eigen::Vector2d(pixels[i].x, pixels[i].y)).norm());
    // The overload with a guess gives the same point.
    const Eigen::Vector2d guessed = m.unproject({pixels[i].x, pixels[i].y}, xy * 1.01);
    ASSERT_EQ(guessed, xy) << i;
  }
  EXPECT_LT(worst_ray, 1e-9);
  EXPECT_LT(worst_opencv, 1e-9);
  EXPECT_LT(worst_round_trip, 1e-9);
  std::printf(
      "fisheye unproject: ray %.2e px, vs cv::fisheye::undistortPoints %.2e px, round "
      "trip %.2e px\n",
      worst_ray, worst_opencv, worst_round_trip);
}

TEST(FisheyeCameraModel, PixelsWithoutAnInverseUnprojectToNan) {
  const CameraModel m = tum_vi_camera();
  // The image corners of a TUM VI camera look more than 90 degrees off axis: no x/z exists.
  EXPECT_FALSE(m.unproject({0.0, 0.0}).allFinite());
  EXPECT_FALSE(m.unproject({511.0, 511.0}, {1.0, 1.0}).allFinite());
  // Just inside 90 degrees the inverse exists.
  const Eigen::Vector2d edge = m.project({std::tan(89.5 * M_PI / 180.0), 0.0, 1.0});
  EXPECT_TRUE(m.unproject(edge).allFinite());
  // A lens with k1 = -0.3: theta_d = theta (1 - 0.3 theta^2) stops growing where its slope
  // 1 - 0.9 theta^2 vanishes, at theta = 1 / sqrt(0.9) (60.4 degrees); past that fold no inverse.
  CameraModel folded = m;
  folded.distortion = {-0.3, 0, 0, 0, 0};
  const double fold = 1.0 / std::sqrt(0.9);
  const double peak = fold * (1 - 0.3 * fold * fold);  // theta_d at the fold
  EXPECT_TRUE(folded.unproject({folded.cx + folded.fx * peak * 0.999, folded.cy}).allFinite());
  EXPECT_FALSE(folded.unproject({folded.cx + folded.fx * peak * 1.001, folded.cy}).allFinite());
  // Inside the fold the inverse is exact.
  const Eigen::Vector2d in = folded.unproject({folded.cx + folded.fx * peak * 0.9, folded.cy});
  EXPECT_NEAR(folded.project({in.x(), in.y(), 1.0}).x(), folded.cx + folded.fx * peak * 0.9, 1e-9);
  EXPECT_LT(std::atan(in.norm()), fold);
}

TEST(FisheyeCameraModel, YamlRoundTripCarriesTheDistortionModel) {
  const test::TemporaryFolder dir;
  const CameraModel m = tum_vi_camera();
  const std::string path = (dir / "camera.yaml").string();
  m.write_yaml(path);
  const CameraModel r = CameraModel::read_yaml(path);
  EXPECT_EQ(r.model, DistortionModel::equidistant);
  EXPECT_EQ(r.width, 512);
  EXPECT_DOUBLE_EQ(r.fx, m.fx);
  EXPECT_DOUBLE_EQ(r.cy, m.cy);
  for (size_t i = 0; i < 5; ++i) EXPECT_DOUBLE_EQ(r.distortion[i], m.distortion[i]) << i;
  // As ROS camera files say it, with the four coefficients cv::fisheye takes.
  cv::FileStorage fsr(path, cv::FileStorage::READ);
  EXPECT_EQ(std::string(fsr["distortion_model"]), "equidistant");
  cv::Mat d;
  fsr["distortion_coefficients"] >> d;
  ASSERT_EQ(d.total(), 4u);
  EXPECT_DOUBLE_EQ(d.at<double>(3), m.distortion[3]);
  // Brown-Conrady files say plumb_bob.
  make_camera(kDistortions[1]).write_yaml(path);
  EXPECT_EQ(CameraModel::read_yaml(path).model, DistortionModel::brown_conrady);
  cv::FileStorage again(path, cv::FileStorage::READ);
  EXPECT_EQ(std::string(again["distortion_model"]), "plumb_bob");
}

TEST(FisheyeCameraModel, BadDistortionModelsAreRefused) {
  const test::TemporaryFolder dir;
  const auto write = [&](const std::string& name, const std::string& model, int n) {
    const std::string path = (dir / name).string();
    std::string data;
    for (int i = 0; i < n; ++i) data += std::string(i ? ", " : "") + "0.001";
    std::ofstream(path) << "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n"
                        << "distortion_model: " << model << "\n"
                        << "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
                        << "   data: [ 300., 0., 320., 0., 300., 240., 0., 0., 1. ]\n"
                        << "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: " << n
                        << "\n   dt: d\n   data: [ " << data << " ]\n";
    return path;
  };
  expect_error_containing(
      [&] { CameraModel::read_yaml(write("kb.yaml", "kannala_brandt8", 4)); },
      {"kb.yaml", "distortion_model", "kannala_brandt8", "plumb_bob", "equidistant"});
  expect_error_containing([&] { CameraModel::read_yaml(write("num.yaml", "3", 4)); },
                          {"num.yaml", "distortion_model", "string"});
  expect_error_containing([&] { CameraModel::read_yaml(write("five.yaml", "equidistant", 5)); },
                          {"five.yaml", "distortion_coefficients", "5 entries", "expected 4"});
  const CameraModel ok = CameraModel::read_yaml(write("ok.yaml", "equidistant", 4));
  EXPECT_EQ(ok.model, DistortionModel::equidistant);
  EXPECT_DOUBLE_EQ(ok.distortion[3], 0.001);
  CameraModel bad = tum_vi_camera();
  bad.distortion[4] = 0.1;
  expect_error_containing([&] { bad.validate("cam"); },
                          {"cam", "equidistant", "0.1", "expected 0"});
}

}  // namespace
}  // namespace crepuscular::calibration
