// `crepuscular calibrate camera --board april_6x6.yaml` (Kalibr's target yaml) on 16-bit PNGs of a
// Kalibr aprilgrid rendered through EuRoC's camera: the written camera is the rendering camera.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>

#include "tests/support/cli.hpp"
#include "tests/support/temporary_folder.hpp"
#include "tests/tracking/kalibr_frames.hpp"

namespace crepuscular::tracking {
namespace {

// Measured: fx, fy, cx, cy within 0.07 % of the truth (asserted 0.2 %), k1 within 0.0004, RMS
// 0.12 px.
TEST(KalibrAprilgridCommand, CalibrateCameraTakesKalibrsTargetYamlAnd16BitImages) {
  namespace fs = std::filesystem;
  const test::TemporaryFolder dir;
  fs::create_directories(dir / "shots");
  std::ofstream(dir.file("april_6x6.yaml")) << "target_type: 'aprilgrid' #gridtype\n"
                                               "tagCols: 6\ntagRows: 6\ntagSize: 0.088\n"
                                               "tagSpacing: 0.3\n";
  const testing::KalibrTestCamera cam = testing::euroc_camera();
  const testing::KalibrGridRenderer r(cam, testing::KalibrGridSpec{});
  // Tilted 35 degrees about 8 directions, the board's centre toward the image corners and sides.
  for (int v = 0; v < 8; ++v) {
    const double a = 45.0 * v;
    const double dx = 180 * std::cos(a * M_PI / 180), dy = 110 * std::sin(a * M_PI / 180);
    testing::KalibrFrameOptions o;
    o.depth = CV_16U;
    o.scale16 = 16;  // 12-bit data in 16-bit words
    o.noise_sigma = 1.0;
    o.blur_sigma = 0.7;
    o.seed = uint64_t(v + 1);
    const cv::Mat image = r.render(r.pose(35, a + 90, 0.35, dx, dy), o);
    ASSERT_TRUE(cv::imwrite((dir / "shots" / ("v" + std::to_string(v) + ".png")).string(), image));
  }
  const std::string out = dir.file("camera.yaml");
  std::string log;
  ASSERT_EQ(test::run_cli("calibrate camera --images " + (dir / "shots").string() + " --board " +
                              dir.file("april_6x6.yaml") + " --out " + out,
                          &log),
            0)
      << log;
  cv::FileStorage in(out, cv::FileStorage::READ);
  ASSERT_TRUE(in.isOpened());
  cv::Mat K, d;
  in["camera_matrix"] >> K;
  in["distortion_coefficients"] >> d;
  std::printf("fx %.3f fy %.3f cx %.3f cy %.3f k1 %.5f k2 %.5f rms %.3f px\n", K.at<double>(0, 0),
              K.at<double>(1, 1), K.at<double>(0, 2), K.at<double>(1, 2), d.at<double>(0),
              d.at<double>(1), double(in["rms_reprojection_error_px"]));
  EXPECT_NEAR(K.at<double>(0, 0), cam.fx, 0.002 * cam.fx);
  EXPECT_NEAR(K.at<double>(1, 1), cam.fy, 0.002 * cam.fy);
  EXPECT_NEAR(K.at<double>(0, 2), cam.cx, 0.002 * cam.cx);
  EXPECT_NEAR(K.at<double>(1, 2), cam.cy, 0.002 * cam.cy);
  EXPECT_NEAR(d.at<double>(0), cam.d[0], 0.005);
  EXPECT_LT(double(in["rms_reprojection_error_px"]), 0.2);
  EXPECT_EQ(int(in["views_used"]), 8);
}

// `crepuscular track --boards april_6x6.yaml` on a synthetic scene whose board is that target (the
// project's renderer draws its tags; Kalibr's frame: z toward the camera): tracked in every frame,
// at the scene's true pose (the log's ground-truth error; measured 0.24 mm at 1.2 m).
TEST(KalibrAprilgridCommand, TrackTakesKalibrsTargetYaml) {
  const test::TemporaryFolder dir;
  std::ofstream(dir.file("april_6x6.yaml")) << "target_type: 'aprilgrid'\ntagCols: 6\ntagRows: 6\n"
                                               "tagSize: 0.088\ntagSpacing: 0.3\n";
  std::ofstream(dir.file("scene.json"))
      << R"({"boards": "april_6x6.yaml", "frames": 3, "background": {"type": "plain"},)"
      << R"( "poses": {"aprilgrid": [{"t": 0, "translation_mm": [-330, 330, 1200],)"
      << R"( "rotvec_deg": [180, 0, 0]}]}})";
  std::string log;
  ASSERT_EQ(test::run_cli("track --source synthetic:" + dir.file("scene.json") + " --boards " +
                              dir.file("april_6x6.yaml") + " --out " + dir.file("poses.csv"),
                          &log),
            0)
      << log;
  EXPECT_NE(log.find("aprilgrid: tracked in 3 of 3 frames"), std::string::npos) << log;
  const size_t at = log.find("against ground truth: median ");
  ASSERT_NE(at, std::string::npos) << log;
  const double mm = std::stod(log.substr(at + 29));
  std::printf("ground truth error %.3f mm\n", mm);
  EXPECT_LT(mm, 1.0);
}

}  // namespace
}  // namespace crepuscular::tracking
