// Overlay renderer without any display: headless output goes through EGL (a GPU's EGL device or
// Mesa), never through X. The suite removes DISPLAY and WAYLAND_DISPLAY before any renderer exists
// (ctest also runs it under `env -u DISPLAY`).
#include "overlay/renderer.hpp"

#include <gtest/gtest.h>

#include <cstdlib>
#include <iostream>
#include <random>
#include <string>

#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>

#include "foundation/error.hpp"

namespace crepuscular::overlay {
namespace {

class NoDisplayEnvironment : public ::testing::Environment {
 public:
  void SetUp() override {
    unsetenv("DISPLAY");
    unsetenv("WAYLAND_DISPLAY");
  }
};
const auto* const no_display_environment =
    ::testing::AddGlobalTestEnvironment(new NoDisplayEnvironment);

calibration::CameraModel test_camera() {
  calibration::CameraModel cam;
  cam.width = 640;
  cam.height = 480;
  cam.fx = 580;
  cam.fy = 585;
  cam.cx = 327.5;
  cam.cy = 236.2;
  cam.distortion = {-0.25, 0.08, 0.001, -0.0008, -0.01};
  return cam;
}

TEST(OverlayRendererHeadless, DrawsWithoutAnyDisplay) {
  ASSERT_EQ(std::getenv("DISPLAY"), nullptr);
  const auto cam = test_camera();
  OverlayRenderer renderer(cam);  // default: headless, EGL first
  EXPECT_EQ(renderer.backend(), RendererBackend::kEgl);
  const std::string description = renderer.gl_description();
  std::cout << description << "\n";
  EXPECT_NE(description.find("[EGL"), std::string::npos) << description;

  cv::Mat frame(cam.height, cam.width, CV_8UC3);
  cv::RNG(5).fill(frame, cv::RNG::UNIFORM, 0, 256);
  renderer.set_frame(frame);
  EXPECT_EQ(cv::norm(renderer.render(), frame, cv::NORM_INF), 0) << "background alone is the frame";

  // Dots land where OpenCV projects them (intensity-weighted centroid within 0.05 px).
  renderer.set_frame(cv::Mat::zeros(cam.height, cam.width, CV_8UC3));
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-0.45, 0.45), depth(150, 400);
  int checked = 0;
  for (int i = 0; i < 12; ++i) {
    const double z = depth(rng);
    const Eigen::Vector3d p(u(rng) * z, u(rng) * z * 0.75, z);
    std::vector<cv::Point2d> expected;
    cv::projectPoints(std::vector<cv::Point3d>{{p.x(), p.y(), p.z()}}, cv::Vec3d(0, 0, 0),
                      cv::Vec3d(0, 0, 0), cam.camera_matrix(), cam.distortion_coefficients(),
                      expected);
    const cv::Point2d e = expected[0];
    if (e.x < 3 || e.y < 3 || e.x > cam.width - 4 || e.y > cam.height - 4) continue;
    renderer.clear_layer("dots");
    renderer.add_points("dots", {p}, cv::Scalar(255, 255, 255));
    const cv::Mat image = renderer.render();
    double sum = 0, sx = 0, sy = 0;
    for (int y = 0; y < image.rows; ++y)
      for (int x = 0; x < image.cols; ++x) {
        const double v = image.at<cv::Vec3b>(y, x)[1];
        sum += v;
        sx += v * x;
        sy += v * y;
      }
    ASSERT_GT(sum, 0) << "dot " << i << " not drawn";
    EXPECT_LT(cv::norm(cv::Point2d(sx / sum, sy / sum) - e), 0.05) << "dot " << i;
    ++checked;
  }
  EXPECT_GE(checked, 8);
  EXPECT_TRUE(renderer.present()) << "headless present() is a no-op";
  EXPECT_TRUE(renderer.poll_keys().empty());
}

TEST(OverlayRendererHeadless, TwoRenderersShareTheEglDisplay) {
  const auto cam = test_camera();
  auto a = std::make_unique<OverlayRenderer>(cam);
  auto b = std::make_unique<OverlayRenderer>(cam);
  Polyline line;
  line.points_cam = {{-50, 0, 300}, {50, 0, 300}};
  line.width_px = 3;
  a->add_polyline("line", line);
  b->add_polyline("line", line);
  const cv::Mat ia = a->render();
  a.reset();  // ending one renderer leaves the other's context intact
  const cv::Mat ib = b->render();
  EXPECT_EQ(cv::norm(ia, ib, cv::NORM_INF), 0);
  EXPECT_GT(cv::countNonZero(ib.reshape(1)), 3 * 90);
}

TEST(OverlayRendererHeadless, WindowWithoutDisplayNamesTheWayOut) {
  const auto cam = test_camera();
  RendererOptions options;
  options.backend = RendererBackend::kGlfw;
  try {
    OverlayRenderer renderer(cam, options);
    FAIL() << "a GLFW window cannot exist without a display";
  } catch (const Error& e) {
    const std::string message = e.what();
    EXPECT_NE(message.find("xvfb-run -a"), std::string::npos) << message;
  }
  options.visible = true;
  options.backend = RendererBackend::kAuto;
  EXPECT_THROW(OverlayRenderer(cam, options), Error);
}

}  // namespace
}  // namespace crepuscular::overlay
