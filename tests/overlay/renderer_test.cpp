// Overlay renderer, run for real on an OpenGL 3.3 core context (Mesa llvmpipe under Xvfb).
#include "overlay/renderer.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <memory>
#include <random>


#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>

#include "foundation/error.hpp"
#include "tests/support/renderer.hpp"
#include "tests/support/xvfb_environment.hpp"

namespace crepuscular::overlay {
namespace {

using test::make_renderer;
using test::noise_frame;

calibration::CameraModel test_camera(int width = 640, int height = 480) {
  calibration::CameraModel cam;
  cam.width = width;
  cam.height = height;
  cam.fx = 0.9 * width;
  cam.fy = 0.92 * width;
  cam.cx = width / 2.0 + 7.3;
  cam.cy = height / 2.0 - 4.1;
  cam.distortion = {-0.28, 0.09, 0.0012, -0.0009, -0.01};  // strong barrel distortion
  return cam;
}

cv::Mat differing(const cv::Mat& a, const cv::Mat& b) {
  cv::Mat diff;
  cv::absdiff(a, b, diff);
  cv::Mat gray;
  cv::transform(diff, gray, cv::Matx13f(1, 1, 1));
  return gray > 0;
}

TEST(OverlayRenderer, DotsLandWhereOpenCvProjects) {
  const auto cam = test_camera();
  auto renderer = make_renderer(cam);
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context";
  renderer->set_frame(cv::Mat::zeros(cam.height, cam.width, CV_8UC3));

  // Known 3D points spread over the image, including the strongly distorted corners.
  std::vector<Eigen::Vector3d> points;
  std::vector<cv::Point3d> cv_points;
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-0.55, 0.55), depth(150, 400);
  for (int i = 0; i < 40; ++i) {
    const double z = depth(rng);
    const Eigen::Vector3d p(u(rng) * z, u(rng) * z * 0.75, z);
    points.push_back(p);
    cv_points.emplace_back(p.x(), p.y(), p.z());
  }
  std::vector<cv::Point2d> expected;
  cv::projectPoints(cv_points, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), cam.camera_matrix(),
                    cam.distortion_coefficients(), expected);

  int checked = 0;
  for (size_t i = 0; i < points.size(); ++i) {
    const cv::Point2d e = expected[i];
    if (e.x < 3 || e.y < 3 || e.x > cam.width - 4 || e.y > cam.height - 4) continue;
    renderer->clear_layer("dots");
    renderer->add_points("dots", {points[i]}, cv::Scalar(255, 255, 255));
    const cv::Mat image = renderer->render();
    // Intensity-weighted centroid of the drawn pixels around the expectation.
    double sum = 0, sx = 0, sy = 0;
    int lit = 0;
    for (int y = 0; y < image.rows; ++y)
      for (int x = 0; x < image.cols; ++x) {
        const double v = image.at<cv::Vec3b>(y, x)[1];
        if (v == 0) continue;
        ++lit;
        sum += v;
        sx += v * x;
        sy += v * y;
      }
    ASSERT_GT(sum, 0) << "dot " << i << " not drawn";
    EXPECT_LE(lit, 4) << "a dot covers at most 2x2 pixels";
    const cv::Point2d c(sx / sum, sy / sum);
    EXPECT_LT(cv::norm(c - e), 0.5) << "dot " << i << " at " << c << ", OpenCV says " << e;
    EXPECT_LT(cv::norm(c - e), 0.05) << "dot " << i << " at " << c << ", OpenCV says " << e;
    ++checked;
  }
  EXPECT_GE(checked, 30);
}

TEST(OverlayRenderer, BackgroundUnchangedWhereNothingIsDrawn) {
  const auto cam = test_camera();
  auto renderer = make_renderer(cam);
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context";
  const cv::Mat frame = noise_frame(cam.width, cam.height, 3);
  renderer->set_frame(frame);
  const cv::Mat bare = renderer->render();
  EXPECT_EQ(cv::norm(bare, frame, cv::NORM_INF), 0) << "background alone must be the frame";

  Polyline square;
  square.points_cam = {{-40, -30, 300}, {40, -30, 300}, {40, 30, 300}, {-40, 30, 300}};
  square.closed = true;
  square.width_px = 3;
  square.colour = cv::Scalar(0, 0, 255);
  renderer->add_polyline("outline", square);
  const cv::Mat drawn = renderer->render();
  const cv::Mat changed = differing(drawn, frame);
  const int changed_count = cv::countNonZero(changed);
  EXPECT_GT(changed_count, 4 * 60 * 3) << "the square's outline was drawn";
  // Away from the outline (its projected vertices' bounding box grown by 4 px), nothing changed.
  std::vector<cv::Point2f> corners;
  for (const auto& p : square.points_cam) {
    const auto px = cam.project(p);
    corners.emplace_back(static_cast<float>(px.x()), static_cast<float>(px.y()));
  }
  cv::Rect box = cv::boundingRect(corners);
  box -= cv::Point(5, 5);
  box += cv::Size(10, 10);
  cv::Mat outside = changed.clone();
  outside(box).setTo(0);
  EXPECT_EQ(cv::countNonZero(outside), 0);
  // Drawn pixels are the line colour exactly.
  for (int y = 0; y < drawn.rows; ++y)
    for (int x = 0; x < drawn.cols; ++x)
      if (changed.at<uchar>(y, x)) {
        ASSERT_EQ(drawn.at<cv::Vec3b>(y, x), cv::Vec3b(0, 0, 255)) << x << "," << y;
      }
}

TEST(OverlayRenderer, DistortionBendsLongLines) {
  const auto cam = test_camera();
  auto renderer = make_renderer(cam);
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context";
  renderer->set_frame(cv::Mat::zeros(cam.height, cam.width, CV_8UC3));
  // A long straight edge near the top of the image: barrel distortion bows it.
  Polyline edge;
  edge.points_cam = {{-150, -105, 300}, {150, -105, 300}};
  edge.width_px = 1;
  edge.colour = cv::Scalar(255, 255, 255);
  renderer->add_polyline("edge", edge);
  const cv::Mat image = renderer->render();
  double max_bow = 0;
  for (double t = 0.05; t < 0.96; t += 0.05) {
    const Eigen::Vector3d p = edge.points_cam[0] + t * (edge.points_cam[1] - edge.points_cam[0]);
    const Eigen::Vector2d px = cam.project(p);
    const int x = static_cast<int>(std::lround(px.x())), y = static_cast<int>(std::lround(px.y()));
    ASSERT_TRUE(x >= 0 && y >= 0 && x < cam.width && y < cam.height);
    EXPECT_GT(image.at<cv::Vec3b>(y, x)[0], 0) << "curve point t=" << t << " at " << px.transpose();
    // Distance to the chord between the projected end points.
    const Eigen::Vector2d a = cam.project(edge.points_cam[0]), b = cam.project(edge.points_cam[1]);
    const Eigen::Vector2d d = (b - a).normalized();
    max_bow = std::max(max_bow, std::abs((px - a).x() * d.y() - (px - a).y() * d.x()));
  }
  EXPECT_GT(max_bow, 10.0) << "the test line must be visibly bent for this test to mean anything";

  // A 4-px wide version: per image column, the centroid of the drawn pixels follows the distorted
  // curve (quantisation allows 0.5 px per column; no systematic offset on average).
  renderer->clear_layer("edge");
  edge.width_px = 4;
  renderer->add_polyline("edge", edge);
  const cv::Mat wide = renderer->render();
  const Eigen::Vector2d a = cam.project(edge.points_cam[0]), b = cam.project(edge.points_cam[1]);
  double sum_error = 0, max_error = 0;
  int columns = 0;
  for (int x = static_cast<int>(a.x()) + 8; x < static_cast<int>(b.x()) - 8; x += 3) {
    double lo = 0, hi = 1;  // the curve's parameter where its projection reaches column x
    for (int it = 0; it < 60; ++it) {
      const double mid = (lo + hi) / 2;
      const Eigen::Vector3d p = edge.points_cam[0] + mid * (edge.points_cam[1] - edge.points_cam[0]);
      (cam.project(p).x() < x ? lo : hi) = mid;
    }
    const double expected_y =
        cam.project(edge.points_cam[0] + lo * (edge.points_cam[1] - edge.points_cam[0])).y();
    double sum = 0, sy = 0;
    for (int y = 0; y < wide.rows; ++y) {
      const double v = wide.at<cv::Vec3b>(y, x)[0];
      sum += v;
      sy += v * y;
    }
    ASSERT_GT(sum, 0) << "column " << x;
    const double error = sy / sum - expected_y;
    sum_error += error;
    max_error = std::max(max_error, std::abs(error));
    ++columns;
  }
  ASSERT_GT(columns, 100);
  EXPECT_LE(max_error, 0.55);
  EXPECT_LT(std::abs(sum_error / columns), 0.1);
}

TEST(OverlayRenderer, TogglingALayerChangesExactlyItsPixels) {
  const auto cam = test_camera();
  auto renderer = make_renderer(cam);
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context";
  const cv::Mat frame = noise_frame(cam.width, cam.height, 11);
  renderer->set_frame(frame);

  Polyline a;  // first layer: a diagonal
  a.points_cam = {{-80, -60, 250}, {80, 60, 250}};
  a.width_px = 5;
  a.colour = cv::Scalar(0, 255, 0);
  Polyline b;  // second layer, drawn on top and crossing the first
  b.points_cam = {{-80, 60, 250}, {0, 0, 250}, {80, -60, 250}};
  b.width_px = 7;
  b.colour = cv::Scalar(255, 0, 255);
  renderer->add_polyline("first", a);
  renderer->add_polyline("second", b);

  const cv::Mat both = renderer->render();
  renderer->set_layer_visible("first", false);
  EXPECT_FALSE(renderer->layer_visible("first"));
  const cv::Mat without_first = renderer->render();
  renderer->set_layer_visible("second", false);
  const cv::Mat neither = renderer->render();
  renderer->set_layer_visible("first", true);
  const cv::Mat only_first = renderer->render();
  renderer->set_layer_visible("second", true);
  EXPECT_EQ(cv::norm(renderer->render(), both, cv::NORM_INF), 0) << "back on: same image";

  EXPECT_EQ(cv::norm(neither, frame, cv::NORM_INF), 0);
  const cv::Mat first_pixels = differing(only_first, frame);
  const cv::Mat second_pixels = differing(without_first, frame);
  ASSERT_GT(cv::countNonZero(first_pixels), 500);
  ASSERT_GT(cv::countNonZero(second_pixels), 500);
  // Turning "first" off changes exactly its pixels, except where "second" covers them.
  cv::Mat expected = first_pixels & ~second_pixels;
  const cv::Mat changed = differing(both, without_first);
  EXPECT_EQ(cv::countNonZero(changed ^ expected), 0);
  EXPECT_GT(cv::countNonZero(first_pixels & second_pixels), 0) << "the layers must overlap";
}

// A layer image given again with its revision shows the same pixels (kept in the texture, not
// uploaded again); a new revision shows the new pixels, and revision 0 always the given ones.
TEST(OverlayRenderer, LayerImageOfTheSameRevisionIsKeptAndANewOneReplacesIt) {
  const auto cam = test_camera();
  auto renderer = make_renderer(cam);
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context";
  const cv::Mat frame = noise_frame(cam.width, cam.height, 5);
  renderer->set_frame(frame);
  const cv::Mat red(40, 60, CV_8UC4, cv::Scalar(0, 0, 255, 255));
  const cv::Mat blue(40, 60, CV_8UC4, cv::Scalar(255, 0, 0, 255));
  const cv::Point at(100, 50);
  const cv::Rect box(at, red.size());
  const auto shows = [&](const cv::Scalar& bgr) {
    const cv::Mat image = renderer->render();
    cv::Mat expected(box.size(), CV_8UC3, bgr);
    return cv::norm(image(box), expected, cv::NORM_INF) == 0 &&
           cv::norm(differing(image, frame)(cv::Rect(0, 0, cam.width, at.y)), cv::NORM_INF) == 0;
  };
  const uint64_t r1 = OverlayRenderer::new_image_revision();
  const uint64_t r2 = OverlayRenderer::new_image_revision();
  EXPECT_NE(r1, 0u);
  EXPECT_NE(r1, r2);
  renderer->add_layer_image("pictures", red, at, r1);
  EXPECT_TRUE(shows(cv::Scalar(0, 0, 255)));
  renderer->clear_layer("pictures");
  renderer->add_layer_image("pictures", red, at, r1);  // the same pixels: kept
  EXPECT_TRUE(shows(cv::Scalar(0, 0, 255)));
  renderer->clear_layer("pictures");
  renderer->add_layer_image("pictures", blue, at, r2);  // new pixels: uploaded
  EXPECT_TRUE(shows(cv::Scalar(255, 0, 0)));
  renderer->clear_layer("pictures");
  renderer->add_layer_image("pictures", red, at);  // revision 0: always uploaded
  EXPECT_TRUE(shows(cv::Scalar(0, 0, 255)));
  renderer->clear_layer("pictures");
  EXPECT_EQ(cv::norm(renderer->render(), frame, cv::NORM_INF), 0);
}

// An image placed by an affine map lands where OpenCV's warpAffine puts it: bilinear in
// premultiplied colour (transparent texels darken no edge), blended over the frame.
TEST(OverlayRenderer, WarpedLayerImageMatchesOpenCvsWarpAffine) {
  const auto cam = test_camera();
  auto renderer = make_renderer(cam);
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context";
  const cv::Mat frame = noise_frame(cam.width, cam.height, 9);
  renderer->set_frame(frame);
  // Smooth colours, opaque in the middle, half transparent around it, transparent outside.
  cv::Mat picture(50, 70, CV_8UC4, cv::Scalar(0, 0, 0, 0));
  for (int y = 4; y < 46; ++y) {
    for (int x = 4; x < 66; ++x) {
      const bool core = y >= 12 && y < 38 && x >= 12 && x < 58;
      picture.at<cv::Vec4b>(y, x) = cv::Vec4b(uchar(3 * x), uchar(200 - 3 * y), uchar(60 + x + y),
                                              uchar(core ? 255 : 128));
    }
  }
  const cv::Point at(200, 150);
  // Drawn at `at`, now shown turned by 3 degrees, scaled 1.02 and moved by (15.3, -6.6) px.
  const double a = 3.0 * M_PI / 180.0, k = 1.02;
  const Eigen::Vector2d c(at.x + 35.0, at.y + 25.0);
  Eigen::Matrix<double, 2, 3> warp;
  warp.leftCols<2>() << k * std::cos(a), -k * std::sin(a), k * std::sin(a), k * std::cos(a);
  warp.col(2) = c + Eigen::Vector2d(15.3, -6.6) - warp.leftCols<2>() * c;
  renderer->add_layer_image_warped("pictures", picture, at, warp);
  const cv::Mat image = renderer->render();

  // The reference: premultiplied BGRA warped by OpenCV, then blended over the frame.
  cv::Mat premultiplied(picture.size(), CV_32FC4);
  for (int y = 0; y < picture.rows; ++y) {
    for (int x = 0; x < picture.cols; ++x) {
      const cv::Vec4b p = picture.at<cv::Vec4b>(y, x);
      const float al = p[3] / 255.0f;
      premultiplied.at<cv::Vec4f>(y, x) = cv::Vec4f(p[0] * al, p[1] * al, p[2] * al, al);
    }
  }
  cv::Mat to_frame(2, 3, CV_64F);  // image pixel -> frame pixel
  for (int r = 0; r < 2; ++r) {
    for (int col = 0; col < 2; ++col) to_frame.at<double>(r, col) = warp(r, col);
    to_frame.at<double>(r, 2) = warp(r, 2) + warp(r, 0) * at.x + warp(r, 1) * at.y;
  }
  cv::Mat warped;
  cv::warpAffine(premultiplied, warped, to_frame, frame.size(), cv::INTER_LINEAR,
                 cv::BORDER_CONSTANT, cv::Scalar::all(0));
  int worst = 0, covered = 0;
  for (int y = 0; y < frame.rows; ++y) {
    for (int x = 0; x < frame.cols; ++x) {
      const cv::Vec4f w = warped.at<cv::Vec4f>(y, x);
      const cv::Vec3b f = frame.at<cv::Vec3b>(y, x), g = image.at<cv::Vec3b>(y, x);
      covered += w[3] > 0.01f;
      for (int ch = 0; ch < 3; ++ch) {
        const double expected = w[ch] * 255.0 / 255.0 + f[ch] * (1.0 - w[3]);
        worst = std::max(worst, int(std::lround(std::abs(expected - g[ch]))));
      }
    }
  }
  EXPECT_GT(covered, 2500);  // the picture shows (42 x 62 px of it are not transparent)
  EXPECT_LE(worst, 3);
  // Far from it, the frame is untouched.
  EXPECT_EQ(cv::norm(image(cv::Rect(0, 0, cam.width, 100)), frame(cv::Rect(0, 0, cam.width, 100)),
                     cv::NORM_INF),
            0);
  // A singular map is refused.
  EXPECT_THROW(renderer->add_layer_image_warped("pictures", picture, at,
                                                Eigen::Matrix<double, 2, 3>::Zero()),
               Error);
}

TEST(OverlayRenderer, RejectsFrameOfWrongSize) {
  const auto cam = test_camera();
  auto renderer = make_renderer(cam);
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context";
  EXPECT_THROW(renderer->set_frame(cv::Mat::zeros(100, 100, CV_8UC3)), Error);
  EXPECT_THROW(renderer->set_frame(cv::Mat::zeros(cam.height, cam.width, CV_8UC1)), Error);
}

// The same input for two renderers: noise frame, lines in 3D (opaque and translucent), dots,
// a pixel-space outline and a text image layer.
void draw_scene(OverlayRenderer& r, const cv::Mat& frame) {
  const auto& cam = r.camera();
  r.set_frame(frame);
  Polyline ring;
  for (int k = 0; k < 48; ++k) {
    const double a = 2 * M_PI * k / 48;
    ring.points_cam.emplace_back(60 * std::cos(a), 45 * std::sin(a), 280 + 10 * std::sin(3 * a));
  }
  ring.closed = true;
  ring.width_px = 4;
  ring.colour = cv::Scalar(0, 200, 255);
  r.add_polyline("rays", ring);
  Polyline ray;
  ray.points_cam = {{-150, -100, 300}, {0, 0, 260}, {140, 110, 320}};
  ray.width_px = 6;
  ray.opacity = 0.6;
  ray.colour = cv::Scalar(40, 220, 40);
  r.add_polyline("rays", ray);
  r.add_points("dots", {{10, 20, 250}, {-50, 30, 300}, {70, -40, 200}}, cv::Scalar(255, 255, 255));
  r.add_polyline_px("outline", {{20.5, 20.5}, {200.3, 40.7}, {180, 150}}, cv::Scalar(255, 0, 0), 3,
                    true, 0.8);
  cv::Mat text(cam.height, cam.width, CV_8UC4, cv::Scalar(0, 0, 0, 0));
  cv::putText(text, "tracking OK  12.3 ms", cv::Point(30, cam.height - 40),
              cv::FONT_HERSHEY_SIMPLEX, 1.0, cv::Scalar(255, 255, 255, 255), 2, cv::LINE_AA);
  r.set_layer_image("status", text);
}

std::unique_ptr<OverlayRenderer> make_renderer_with(const calibration::CameraModel& cam,
                                                    bool visible, RendererBackend backend) {
  RendererOptions options;
  options.visible = visible;
  options.backend = backend;
  return test::make_renderer(cam, options);
}

// What the user sees in the live window (read back from the X server) is the headless frame.
TEST(OverlayRenderer, WindowScreenshotMatchesHeadlessFrame) {
  const auto cam = test_camera();
  auto window = make_renderer_with(cam, true, RendererBackend::kAuto);
  if (!window) GTEST_SKIP() << "no X display with GLX";
  auto headless = make_renderer_with(cam, false, RendererBackend::kAuto);
  ASSERT_TRUE(headless);
  EXPECT_EQ(window->backend(), RendererBackend::kGlfw);
  EXPECT_EQ(headless->backend(), RendererBackend::kEgl) << headless->gl_description();
  std::cout << "window: " << window->gl_description()
            << "\nheadless: " << headless->gl_description() << "\n";

  const cv::Mat frame = noise_frame(cam.width, cam.height, 21);
  draw_scene(*window, frame);
  draw_scene(*headless, frame);
  const cv::Mat expected = headless->render();
  window->draw();
  cv::Mat shot;
  for (int i = 0; i < 3; ++i) {  // the first swaps may reach the X server late
    ASSERT_TRUE(window->present());
    shot = window->screenshot_window();
    ASSERT_EQ(shot.size(), expected.size());
    if (cv::norm(shot, expected, cv::NORM_INF) <= 2) break;
  }
  EXPECT_LE(cv::norm(shot, expected, cv::NORM_INF), 2) << "screenshot differs from headless frame";
  // Not trivially equal: both hold the drawings over the frame, in the same pixels.
  const cv::Mat drawn_headless = differing(expected, frame);
  const cv::Mat drawn_window = differing(shot, frame);
  EXPECT_GT(cv::countNonZero(drawn_headless), 3000);
  EXPECT_GT(cv::countNonZero(drawn_window), 3000);
  EXPECT_EQ(cv::countNonZero(drawn_headless ^ drawn_window), 0);
  // And the window shows the (noise) video frame itself, exactly, wherever nothing is drawn: not a
  // black, stale or scaled image.
  EXPECT_GT(cam.width * cam.height - cv::countNonZero(drawn_window), cam.width * cam.height * 3 / 4);

  // Hiding a layer in the window changes the screenshot exactly as it changes the headless image.
  window->set_layer_visible("status", false);
  headless->set_layer_visible("status", false);
  const cv::Mat expected_without = headless->render();
  window->draw();
  cv::Mat shot_without;
  for (int i = 0; i < 3; ++i) {
    ASSERT_TRUE(window->present());
    shot_without = window->screenshot_window();
    if (cv::norm(shot_without, expected_without, cv::NORM_INF) <= 2) break;
  }
  EXPECT_LE(cv::norm(shot_without, expected_without, cv::NORM_INF), 2);
  EXPECT_GT(cv::countNonZero(differing(shot_without, shot)), 200) << "the text layer went away";
}

// Headless through EGL and through a hidden GLFW window: the same pixels.
TEST(OverlayRenderer, EglAndHiddenGlfwWindowGiveIdenticalImages) {
  const auto cam = test_camera();
  auto egl = make_renderer_with(cam, false, RendererBackend::kEgl);
  ASSERT_TRUE(egl) << "EGL (Mesa) must work here";
  auto glfw = make_renderer_with(cam, false, RendererBackend::kGlfw);
  if (!glfw) GTEST_SKIP() << "no X display with GLX";
  EXPECT_EQ(egl->backend(), RendererBackend::kEgl);
  EXPECT_EQ(glfw->backend(), RendererBackend::kGlfw);
  EXPECT_NE(egl->gl_description().find("[EGL"), std::string::npos) << egl->gl_description();
  EXPECT_NE(glfw->gl_description().find("[GLFW/GLX]"), std::string::npos)
      << glfw->gl_description();
  const cv::Mat frame = noise_frame(cam.width, cam.height, 22);
  draw_scene(*egl, frame);
  draw_scene(*glfw, frame);
  // Interleaved use of both contexts on one thread.
  const cv::Mat a = egl->render();
  const cv::Mat b = glfw->render();
  const cv::Mat a2 = egl->render();
  EXPECT_EQ(cv::norm(a, b, cv::NORM_INF), 0);
  EXPECT_EQ(cv::norm(a, a2, cv::NORM_INF), 0);
  EXPECT_GT(cv::countNonZero(differing(a, frame)), 3000) << "the drawings are in the image";
}

TEST(OverlayRenderer, HeadlessEglHasNoWindow) {
  const auto cam = test_camera();
  auto r = make_renderer_with(cam, false, RendererBackend::kEgl);
  ASSERT_TRUE(r);
  EXPECT_TRUE(r->present());
  EXPECT_TRUE(r->poll_keys().empty());
  EXPECT_THROW(r->screenshot_window(), Error);
  RendererOptions options;
  options.visible = true;
  options.backend = RendererBackend::kEgl;
  EXPECT_THROW(OverlayRenderer(cam, options), Error) << "a window needs GLFW";
}

}  // namespace
}  // namespace crepuscular::overlay
