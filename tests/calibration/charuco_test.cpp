// Tests of calibration/aruco: ChArUco specs, corner detection on rendered boards against the exact
// projections, calibrate_intrinsics on ChArUco views against cv::aruco::calibrateCameraCharuco on
// the same detections and against the rendering camera, and `crepuscular calibrate camera` with a
// charuco: target.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cstdio>
#include <filesystem>
#include <opencv2/core/persistence.hpp>
#include <opencv2/imgcodecs.hpp>
#include <random>
#include <string>
#include <vector>

#include "calibration/aruco.hpp"
#include "tests/support/charuco_scene.hpp"
#include "tests/support/cli.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/temporary_folder.hpp"

namespace crepuscular::calibration {
namespace {

using test::expect_error_containing;

const CharucoSpec kSpec{5, 7, 40.0, 30.0, "DICT_6X6_250", 0};

// The rendering camera: 640 x 480 with barrel distortion.
CameraModel true_camera() {
  CameraModel cam;
  cam.width = 640;
  cam.height = 480;
  cam.fx = 612.0;
  cam.fy = 608.0;
  cam.cx = 323.5;
  cam.cy = 236.0;
  cam.distortion = {-0.12, 0.05, 0.0008, -0.0005, 0.0};
  return cam;
}

// `count` poses of the board, tilted up to 35 degrees about x and y, turned up to 15 degrees,
// whose inner corners all lie at least 20 px inside the image (seeded, reproducible).
std::vector<Eigen::Isometry3d> board_poses(const CameraModel& cam, int count, unsigned seed) {
  const auto board = make_charuco_board(kSpec);
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> uni(0.0, 1.0);
  std::vector<Eigen::Isometry3d> poses;
  const Eigen::Vector3d centre(100.0, 140.0, 0.0);
  const std::vector<cv::Point3f> outline = {{0, 0, 0}, {200, 0, 0}, {200, 280, 0}, {0, 280, 0}};
  for (int attempt = 0; int(poses.size()) < count && attempt < 100000; ++attempt) {
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = (Eigen::AngleAxisd((2 * uni(rng) - 1) * 0.26, Eigen::Vector3d::UnitZ()) *
                  Eigen::AngleAxisd((2 * uni(rng) - 1) * 0.61, Eigen::Vector3d::UnitY()) *
                  Eigen::AngleAxisd((2 * uni(rng) - 1) * 0.61, Eigen::Vector3d::UnitX()))
                     .toRotationMatrix();
    const double depth = 400 + 250 * uni(rng);
    const double u = 0.2 * cam.width + 0.6 * uni(rng) * cam.width;
    const double v = 0.2 * cam.height + 0.6 * uni(rng) * cam.height;
    T.translation() =
        Eigen::Vector3d((u - cam.cx) / cam.fx * depth, (v - cam.cy) / cam.fy * depth, depth) -
        T.linear() * centre;
    bool inside = true;
    for (const auto& p : test::project_points(cam, T, board->chessboardCorners)) {
      inside =
          inside && p.x() > 20 && p.y() > 20 && p.x() < cam.width - 20 && p.y() < cam.height - 20;
    }
    for (const auto& p : test::project_points(cam, T, outline)) {
      inside =
          inside && p.x() > -40 && p.y() > -40 && p.x() < cam.width + 40 && p.y() < cam.height + 40;
    }
    if (inside) poses.push_back(T);
  }
  return poses;
}

TEST(Charuco, ParsesSpec) {
  const auto spec = parse_charuco_spec("charuco:5x7:40:30:DICT_6X6_250");
  ASSERT_TRUE(spec.has_value());
  EXPECT_EQ(spec->squares_x, 5);
  EXPECT_EQ(spec->squares_y, 7);
  EXPECT_DOUBLE_EQ(spec->square_mm, 40.0);
  EXPECT_DOUBLE_EQ(spec->marker_mm, 30.0);
  EXPECT_EQ(spec->dictionary, "DICT_6X6_250");
  EXPECT_FALSE(parse_charuco_spec("chessboard:9x6:25").has_value());
  expect_error_containing([] { parse_charuco_spec("charuco:5x7:40:30"); },
                          {"charuco:5x7:40:30", "SQUARES_XxSQUARES_Y:SQUARE_MM:MARKER_MM:DICT"});
  expect_error_containing([] { parse_charuco_spec("charuco:5x7:40:45:DICT_6X6_250"); },
                          {"marker", "square"});
  expect_error_containing([] { parse_charuco_spec("charuco:5x7:40:30:DICT_6X6_25"); },
                          {"DICT_6X6_25'", "unknown", "DICT_6X6_250", "DICT_ARUCO_ORIGINAL"});
  expect_error_containing([] { parse_charuco_spec("charuco:12x10:40:30:DICT_4X4_50"); },
                          {"0 to 59", "DICT_4X4_50", "0 to 49"});
  expect_error_containing([] { parse_charuco_spec("charuco:1x7:40:30:DICT_6X6_250"); },
                          {"1 x 7", "2 to 100"});
}

// Interpolated chessboard corners of a rendered board land on their exact projections; object
// points are OpenCV's chessboard corners (id 0 at one square from the top-left, row by row).
TEST(Charuco, DetectsRenderedCornersToSubPixel) {
  const CameraModel cam = true_camera();
  const test::CharucoRenderer renderer(cam, make_charuco_board(kSpec));
  const auto T = board_poses(cam, 1, 5).at(0);
  const auto view = detect_charuco(renderer.render(T, 0.6, 1.5), kSpec, "rendered");
  ASSERT_TRUE(view.has_value());
  ASSERT_EQ(view->object_points.size(), 24u);
  std::vector<cv::Point3f> obj;
  for (const auto& p : view->object_points) obj.emplace_back(float(p.x()), float(p.y()), 0.f);
  const auto truth = test::project_points(cam, T, obj);
  double worst = 0, sum = 0;
  for (size_t k = 0; k < truth.size(); ++k) {
    const double e = (view->image_points[k] - truth[k]).norm();
    worst = std::max(worst, e);
    sum += e;
  }
  std::printf("ChArUco corners vs projection: mean %.3f px, largest %.3f px\n",
              sum / double(truth.size()), worst);
  EXPECT_LT(sum / double(truth.size()), 0.15);
  EXPECT_LT(worst, 0.4);
  EXPECT_EQ(view->object_points[0], Eigen::Vector3d(40, 40, 0));
  // OpenCV 4.6's own interpolated corners, for the record: shifted by about half a pixel.
  const cv::Mat image = renderer.render(T, 0.6, 1.5);
  const auto board = make_charuco_board(kSpec);
  std::vector<std::vector<cv::Point2f>> marker_corners;
  std::vector<int> marker_ids, ids;
  std::vector<cv::Point2f> corners;
  cv::aruco::detectMarkers(image, board->dictionary, marker_corners, marker_ids);
  cv::aruco::interpolateCornersCharuco(marker_corners, marker_ids, image, board, corners, ids);
  const auto cv_truth = test::project_points(cam, T, board->chessboardCorners);
  Eigen::Vector2d shift(0, 0);
  for (size_t k = 0; k < ids.size(); ++k) {
    shift += Eigen::Vector2d(corners[k].x, corners[k].y) - cv_truth[size_t(ids[k])];
  }
  shift /= double(std::max<size_t>(1, ids.size()));
  std::printf("cv::aruco::interpolateCornersCharuco alone: mean shift (%.3f, %.3f) px\n", shift.x(),
              shift.y());
  EXPECT_FALSE(detect_charuco(cv::Mat(480, 640, CV_8UC1, cv::Scalar(128)), kSpec, "blank"));
}

// 12 rendered views: our calibration and cv::aruco::calibrateCameraCharuco on the same corners
// agree to 0.1 % on fx fy cx cy, and both land near the rendering camera.
TEST(Charuco, CalibrationAgreesWithCalibrateCameraCharuco) {
  const CameraModel cam = true_camera();
  const auto board = make_charuco_board(kSpec);
  const test::CharucoRenderer renderer(cam, board);
  std::vector<CalibrationView> views;
  std::vector<std::vector<cv::Point2f>> all_corners;
  std::vector<std::vector<int>> all_ids;
  const auto poses = board_poses(cam, 12, 11);
  ASSERT_EQ(poses.size(), 12u);
  for (size_t v = 0; v < poses.size(); ++v) {
    const cv::Mat image = renderer.render(poses[v], 0.6, 1.5, unsigned(v + 1));
    const auto view = detect_charuco(image, kSpec, "view" + std::to_string(v));
    ASSERT_TRUE(view.has_value()) << v;
    EXPECT_GE(view->object_points.size(), 18u) << v;
    views.push_back(*view);
    // The same corners for OpenCV, with their chessboard corner ids.
    std::vector<cv::Point2f> corners;
    std::vector<int> ids;
    for (size_t k = 0; k < view->image_points.size(); ++k) {
      const Eigen::Vector3d& p = view->object_points[k];
      ids.push_back(int(std::lround(p.y() / kSpec.square_mm - 1)) * (kSpec.squares_x - 1) +
                    int(std::lround(p.x() / kSpec.square_mm - 1)));
      ASSERT_LT((Eigen::Vector3d(board->chessboardCorners[size_t(ids.back())].x,
                                 board->chessboardCorners[size_t(ids.back())].y, 0) -
                 p)
                    .norm(),
                1e-4);
      corners.emplace_back(float(view->image_points[k].x()), float(view->image_points[k].y()));
    }
    all_corners.push_back(corners);
    all_ids.push_back(ids);
  }
  // k3 stays 0 in both (a narrow lens: 55 degrees across).
  IntrinsicsOptions options;
  options.fix_k3 = true;
  const IntrinsicsResult ours = calibrate_intrinsics(views, cam.width, cam.height, options);
  cv::Mat K, dist;
  const double cv_rms = cv::aruco::calibrateCameraCharuco(
      all_corners, all_ids, board, cv::Size(cam.width, cam.height), K, dist, cv::noArray(),
      cv::noArray(), cv::CALIB_FIX_K3);
  const double theirs[4] = {K.at<double>(0, 0), K.at<double>(1, 1), K.at<double>(0, 2),
                            K.at<double>(1, 2)};
  const double mine[4] = {ours.camera.fx, ours.camera.fy, ours.camera.cx, ours.camera.cy};
  const double truth[4] = {cam.fx, cam.fy, cam.cx, cam.cy};
  const char* names[4] = {"fx", "fy", "cx", "cy"};
  for (int p = 0; p < 4; ++p) {
    std::printf(
        "%s: ours %.3f +- %.3f, calibrateCameraCharuco %.3f (%.4f %%), truth %.3f (ours "
        "%.3f %%)\n",
        names[p], mine[p], ours.stddev[size_t(p)], theirs[p],
        100 * std::abs(mine[p] - theirs[p]) / theirs[p], truth[p],
        100 * std::abs(mine[p] - truth[p]) / truth[p]);
    EXPECT_NEAR(mine[p], theirs[p], 0.001 * theirs[p]) << names[p];
    EXPECT_NEAR(mine[p], truth[p], 0.005 * truth[p]) << names[p];
  }
  std::printf("RMS ours %.3f px, OpenCV %.3f px; k1 ours %.4f OpenCV %.4f truth %.4f\n",
              ours.rms_px, cv_rms, ours.camera.distortion[0], dist.at<double>(0),
              cam.distortion[0]);
  EXPECT_NEAR(ours.camera.distortion[0], cam.distortion[0], 0.02);
  EXPECT_LT(ours.rms_px, 0.3);
}

// `crepuscular calibrate camera --images DIR --board charuco:...` writes the rendering camera.
TEST(Charuco, CalibrateCameraCommandOnRenderedCharucoBoards) {
  namespace fs = std::filesystem;
  const CameraModel cam = true_camera();
  const test::TemporaryFolder dir;
  fs::create_directories(dir / "shots");
  const test::CharucoRenderer renderer(cam, make_charuco_board(kSpec));
  const auto poses = board_poses(cam, 12, 23);
  ASSERT_EQ(poses.size(), 12u);
  for (size_t v = 0; v < poses.size(); ++v) {
    cv::imwrite((dir / "shots" / ("view" + std::to_string(v) + ".png")).string(),
                renderer.render(poses[v], 0.6, 1.5, unsigned(v + 1)));
  }
  const std::string out = (dir / "camera.yaml").string();
  std::string log;
  ASSERT_EQ(test::run_cli("calibrate camera --images " + (dir / "shots").string() +
                              " --board charuco:5x7:40:30:DICT_6X6_250 --fix-k3 --out " + out,
                          &log),
            0)
      << log;
  cv::FileStorage in(out, cv::FileStorage::READ);
  ASSERT_TRUE(in.isOpened());
  cv::Mat K;
  in["camera_matrix"] >> K;
  std::printf("camera.yaml: fx %.2f fy %.2f cx %.2f cy %.2f\n", K.at<double>(0, 0),
              K.at<double>(1, 1), K.at<double>(0, 2), K.at<double>(1, 2));
  EXPECT_NEAR(K.at<double>(0, 0), cam.fx, 0.005 * cam.fx);
  EXPECT_NEAR(K.at<double>(1, 1), cam.fy, 0.005 * cam.fy);
  EXPECT_NEAR(K.at<double>(0, 2), cam.cx, 0.005 * cam.cx);
  EXPECT_NEAR(K.at<double>(1, 2), cam.cy, 0.005 * cam.cy);
  EXPECT_EQ(int(in["views_used"]), 12);
  EXPECT_LT(double(in["rms_reprojection_error_px"]), 0.3);
  // A malformed target is refused before any image is read.
  EXPECT_NE(test::run_cli("calibrate camera --images " + (dir / "shots").string() +
                              " --board charuco:5x7:40:30:DICT_6X6_999 --out " + out + "2",
                          &log),
            0);
  EXPECT_NE(log.find("DICT_6X6_999"), std::string::npos) << log;
  EXPECT_FALSE(fs::exists(out + "2"));
}

}  // namespace
}  // namespace crepuscular::calibration
