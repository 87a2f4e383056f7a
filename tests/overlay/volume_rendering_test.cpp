// Volume rendering of the path safety volume (overlay layer 2), run for real on an OpenGL 3.3 core
// context (Mesa llvmpipe under Xvfb): the GPU image against the CPU reference of the same integral,
// an analytic slab, hidden classes, the colour-blind palette and NaN voxels.
#include "overlay/volume_rendering.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <memory>


#include <opencv2/imgproc.hpp>

#include "foundation/error.hpp"
#include "tests/support/renderer.hpp"
#include "tests/support/xvfb_environment.hpp"

namespace crepuscular::overlay {
namespace {

using planning::ImageGeometry;
using planning::Volume;
using test::make_renderer;
using test::noise_frame;

calibration::CameraModel camera_320(double k1 = 0.0) {
  calibration::CameraModel cam;
  cam.width = 320;
  cam.height = 240;
  cam.fx = 300;
  cam.fy = 305;
  cam.cx = 160;
  cam.cy = 120;
  cam.distortion = {k1, 0, 0, 0, 0};
  return cam;
}

// Classes: value <= 1 safe, > 2 dangerous, medium between.
planning::SafetyClasses test_classes() {
  planning::SafetyClasses c;
  c.safe = 1.0;
  c.dangerous = 2.0;
  return c;
}
constexpr float kSafe = 0.5f, kMedium = 1.5f, kDangerous = 2.5f;
const float kNaN = std::numeric_limits<float>::quiet_NaN();

ImageGeometry cube_grid(int n = 64) {
  ImageGeometry g;
  g.dims = {n, n, n};
  return g;  // 1 mm voxels, identity direction, origin 0
}

// T_cam_ct of a camera at `eye` (LPS mm) looking at `target`, with `up_hint` roughly image-up.
Eigen::Isometry3d look_at(const Eigen::Vector3d& eye, const Eigen::Vector3d& target,
                          const Eigen::Vector3d& up_hint) {
  const Eigen::Vector3d z = (target - eye).normalized();
  const Eigen::Vector3d x = (-up_hint).cross(z).normalized();  // image y points down
  const Eigen::Vector3d y = z.cross(x);
  Eigen::Isometry3d T_ct_cam = Eigen::Isometry3d::Identity();
  T_ct_cam.linear().col(0) = x;
  T_ct_cam.linear().col(1) = y;
  T_ct_cam.linear().col(2) = z;
  T_ct_cam.translation() = eye;
  return T_ct_cam.inverse();
}

// The layer alone over `frame`.
cv::Mat render(OverlayRenderer& renderer, SafetyVolumeRendering& volume, const cv::Mat& frame) {
  renderer.set_frame(frame);
  renderer.set_layer_draw("volume", [&volume](const DrawContext& c) { volume.draw(c); });
  return renderer.render();
}

// Reference image over `frame` (premultiplied compositing), as doubles 0..255, BGR.
cv::Mat reference_image(const SafetyVolumeRendering& volume, const calibration::CameraModel& cam,
                        const cv::Mat& frame) {
  cv::Mat out(cam.height, cam.width, CV_64FC3);
  for (int y = 0; y < cam.height; ++y)
    for (int x = 0; x < cam.width; ++x) {
      const Eigen::Vector4d p = volume.reference_pixel(cam, x, y);
      const cv::Vec3b bg = frame.at<cv::Vec3b>(y, x);
      out.at<cv::Vec3d>(y, x) = cv::Vec3d(255 * p[2] + (1 - p[3]) * bg[0],
                                          255 * p[1] + (1 - p[3]) * bg[1],
                                          255 * p[0] + (1 - p[3]) * bg[2]);
    }
  return out;
}

double max_difference(const cv::Mat& image, const cv::Mat& reference, cv::Point* where = nullptr) {
  cv::Mat image64;
  image.convertTo(image64, CV_64FC3);
  cv::Mat diff = cv::abs(image64 - reference);
  double worst = 0;
  cv::Point at;
  cv::minMaxLoc(diff.reshape(1), nullptr, &worst, nullptr, &at);
  if (where) *where = cv::Point(at.x / 3, at.y);
  return worst;
}

// A rotated, anisotropic grid whose values change class every few voxels (many class borders),
// NaN outside a ball (the region of interest).
Volume<float> striped_volume() {
  ImageGeometry g;
  g.dims = {48, 56, 40};
  g.spacing = Eigen::Vector3d(1.2, 1.0, 1.5);
  g.origin = Eigen::Vector3d(-20, 35, -12);
  g.direction = Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  Volume<float> v(g);
  for (int k = 0; k < 40; ++k)
    for (int j = 0; j < 56; ++j)
      for (int i = 0; i < 48; ++i) {
        const double r = std::hypot(i - 23.5, j - 27.5, (k - 19.5) * 1.25);
        v(i, j, k) = r > 24 ? kNaN
                            : float(1.5 + 1.2 * std::sin(0.35 * i) * std::cos(0.27 * j) +
                                    0.4 * std::sin(0.5 * k));
      }
  return v;
}

Eigen::Vector3d grid_centre(const ImageGeometry& g) {
  return g.index_to_physical(Eigen::Vector3d((g.dims[0] - 1) / 2.0, (g.dims[1] - 1) / 2.0,
                                             (g.dims[2] - 1) / 2.0));
}

TEST(SafetyVolumeRendering, GpuImageMatchesCpuReferenceWithAndWithoutDistortion) {
  const Volume<float> volume = striped_volume();
  VolumeRenderingOptions options;
  options.opacity_per_mm[0] = 0.02;
  options.opacity_per_mm[1] = 0.04;
  options.opacity_per_mm[2] = 0.08;  // strong enough that some rays stop early at alpha 0.99
  SafetyVolumeRendering rendering(volume, test_classes(), options);
  const Eigen::Vector3d centre = grid_centre(volume.geometry());
  for (const double k1 : {0.0, -0.2}) {
    const auto cam = camera_320(k1);
    auto renderer = make_renderer(cam);
    if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context";
    for (const auto& eye : {Eigen::Vector3d(40, -90, 60), Eigen::Vector3d(-70, 20, -60)}) {
      rendering.set_pose(look_at(centre + eye, centre, Eigen::Vector3d(0, 0, 1)));
      const cv::Mat black = cv::Mat::zeros(cam.height, cam.width, CV_8UC3);
      const cv::Mat image = render(*renderer, rendering, black);
      // Per pixel: the CPU reference, and whether a sample of it sits on a class border so close
      // (1e-4 voxel) that single precision may put it in the neighbouring voxel.
      int ambiguous_pixels = 0, over = 0;
      double worst = 0, worst_ambiguous = 0;
      for (int y = 0; y < cam.height; ++y)
        for (int x = 0; x < cam.width; ++x) {
          bool ambiguous = false;
          const Eigen::Vector4d p = rendering.reference_pixel(cam, x, y, &ambiguous);
          const cv::Vec3b got = image.at<cv::Vec3b>(y, x);
          double d = 0;
          for (int ch = 0; ch < 3; ++ch) d = std::max(d, std::abs(got[2 - ch] - 255 * p[ch]));
          ambiguous_pixels += ambiguous;
          (ambiguous ? worst_ambiguous : worst) = std::max(ambiguous ? worst_ambiguous : worst, d);
          if (!ambiguous && d > 3.0 && over++ < 5) {
            ADD_FAILURE() << "k1 " << k1 << " pixel " << x << "," << y << ": GPU " << got
                          << " CPU " << (255 * p).transpose();
          }
        }
      std::cout << "k1 " << k1 << " eye " << eye.transpose() << ": max difference " << worst
                << " (" << ambiguous_pixels << " pixels on a class border: " << worst_ambiguous
                << ")\n";
      EXPECT_LE(worst, 3.0);
      // On a class border, one sample of at most 1 - exp(-0.08 * 0.5) = 3.9 % may differ.
      EXPECT_LE(worst_ambiguous, 3.0 + 255 * (1 - std::exp(-0.08 * 0.5)));
      EXPECT_LT(ambiguous_pixels, cam.width * cam.height / 100);
      // Not trivially black: the ball covers a good part of the image, with all three colours.
      cv::Mat grey;
      cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
      EXPECT_GT(cv::countNonZero(grey), cam.width * cam.height / 8);
      double opaque_pixels = 0;
      for (int y = 0; y < cam.height; y += 4)
        for (int x = 0; x < cam.width; x += 4)
          opaque_pixels += rendering.reference_pixel(cam, x, y)[3] > 0.9;
      EXPECT_GT(opaque_pixels, 50);
    }
  }
}

// A uniform dangerous slab 20 voxels (20 mm) thick, k = 0.05 / mm, seen head-on from 100 mm in
// front of the grid; two safe voxels in far corners (hidden) stretch the marched box to the grid.
TEST(SafetyVolumeRendering, HeadOnSlabHasAnalyticOpacity) {
  Volume<float> volume(cube_grid(), kNaN);
  for (int k = 20; k < 40; ++k)
    for (int j = 0; j < 64; ++j)
      for (int i = 0; i < 64; ++i) volume(i, j, k) = kDangerous;
  volume(0, 0, 0) = kSafe;
  volume(63, 63, 63) = kSafe;
  VolumeRenderingOptions options;
  options.show_safe = false;
  options.opacity_per_mm[2] = 0.05;
  options.step_mm = 0.1;
  SafetyVolumeRendering rendering(volume, test_classes(), options);
  // Camera axes along the CT axes, optical centre over (31.7, 30.2), 100 mm before the grid.
  Eigen::Isometry3d T_cam_ct = Eigen::Isometry3d::Identity();
  T_cam_ct.translation() = -Eigen::Vector3d(31.7, 30.2, -100.5);
  rendering.set_pose(T_cam_ct);
  const auto cam = camera_320();
  auto renderer = make_renderer(cam);
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context";
  const cv::Mat image = render(*renderer, rendering, cv::Mat::zeros(cam.height, cam.width, CV_8UC3));
  const double k = 0.05, thickness = 20.0;
  const auto red = planning::class_colours(planning::Palette::kDefault)[2];
  int checked = 0;
  for (int y = 80; y <= 160; y += 5)
    for (int x = 120; x <= 200; x += 5) {
      // Path length through the slab grows as 1 / cos of the ray's angle to the optical axis.
      const Eigen::Vector3d d = Eigen::Vector3d((x - cam.cx) / cam.fx, (y - cam.cy) / cam.fy, 1);
      const double expected = 1 - std::exp(-k * thickness * d.norm());
      const cv::Vec3b px = image.at<cv::Vec3b>(y, x);
      const double alpha = px[2] / double(red[0]);
      EXPECT_NEAR(alpha, expected, 0.01 * expected) << x << "," << y;
      EXPECT_EQ(px[1], 0) << x << "," << y;
      EXPECT_EQ(px[0], 0) << x << "," << y;
      EXPECT_NEAR(rendering.reference_pixel(cam, x, y)[3], expected, 0.005 * expected)
          << x << "," << y;
      ++checked;
    }
  EXPECT_EQ(checked, 17 * 17);
  // The optical axis itself: 1 - e^-1.
  EXPECT_NEAR(rendering.reference_pixel(cam, cam.cx, cam.cy)[3], 1 - std::exp(-1.0), 1e-3);
}

// Three separate balls, one per class, NaN around them.
Volume<float> three_balls() {
  Volume<float> volume(cube_grid(), kNaN);
  const Eigen::Vector3d centres[3] = {{16, 20, 30}, {46, 18, 34}, {32, 46, 28}};
  const float values[3] = {kSafe, kMedium, kDangerous};
  for (int k = 0; k < 64; ++k)
    for (int j = 0; j < 64; ++j)
      for (int i = 0; i < 64; ++i)
        for (int c = 0; c < 3; ++c)
          if ((Eigen::Vector3d(i, j, k) - centres[c]).norm() < 11) volume(i, j, k) = values[c];
  return volume;
}

Eigen::Isometry3d front_view() {
  return look_at(Eigen::Vector3d(31.5, 31.5, -90), Eigen::Vector3d(31.5, 31.5, 31.5),
                 Eigen::Vector3d(0, -1, 0));
}

TEST(SafetyVolumeRendering, HiddenClassIsExactlyTransparent) {
  const Volume<float> volume = three_balls();
  VolumeRenderingOptions all;
  all.opacity_per_mm[0] = all.opacity_per_mm[1] = all.opacity_per_mm[2] = 0.05;
  SafetyVolumeRendering rendering(volume, test_classes(), all);
  rendering.set_pose(front_view());
  const auto cam = camera_320(-0.2);
  auto renderer = make_renderer(cam);
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context";
  const cv::Mat frame = noise_frame(cam.width, cam.height, 11);
  const cv::Mat with_all = render(*renderer, rendering, frame);

  for (int hidden = 0; hidden < 3; ++hidden) {
    VolumeRenderingOptions options = all;
    bool* show[3] = {&options.show_safe, &options.show_medium, &options.show_dangerous};
    *show[hidden] = false;
    rendering.set_options(options);
    const cv::Mat image = render(*renderer, rendering, frame);
    // Which pixels see the hidden class at all (CPU reference with only that class shown).
    VolumeRenderingOptions only = all;
    bool* only_show[3] = {&only.show_safe, &only.show_medium, &only.show_dangerous};
    for (int c = 0; c < 3; ++c) *only_show[c] = c == hidden;
    rendering.set_options(only);
    int sees_hidden = 0, mismatched = 0, unchanged_wrong = 0;
    for (int y = 0; y < cam.height; ++y)
      for (int x = 0; x < cam.width; ++x) {
        if (rendering.reference_pixel(cam, x, y)[3] > 0) {
          // The balls do not overlap in this view: the pixel shows the background exactly.
          ++sees_hidden;
          mismatched += image.at<cv::Vec3b>(y, x) != frame.at<cv::Vec3b>(y, x);
        } else {
          unchanged_wrong += image.at<cv::Vec3b>(y, x) != with_all.at<cv::Vec3b>(y, x);
        }
      }
    EXPECT_GT(sees_hidden, 500) << "class " << hidden;
    EXPECT_EQ(mismatched, 0) << "class " << hidden << " hidden but drawn";
    EXPECT_EQ(unchanged_wrong, 0) << "hiding class " << hidden << " changed other pixels";
    // Where it was drawn before, it was visible (not transparent already).
    rendering.set_options(all);
  }
}

TEST(SafetyVolumeRendering, ColourBlindPaletteUsesItsColours) {
  const Volume<float> volume = three_balls();
  VolumeRenderingOptions options;
  options.opacity_per_mm[0] = options.opacity_per_mm[1] = options.opacity_per_mm[2] = 0.05;
  SafetyVolumeRendering rendering(volume, test_classes(), options);
  rendering.set_pose(front_view());
  const auto cam = camera_320();
  auto renderer = make_renderer(cam);
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context";
  const cv::Mat black = cv::Mat::zeros(cam.height, cam.width, CV_8UC3);
  const cv::Mat normal = render(*renderer, rendering, black);
  options.palette = planning::Palette::kColorblind;
  rendering.set_options(options);
  const cv::Mat colourblind = render(*renderer, rendering, black);
  const auto palette = planning::class_colours(planning::Palette::kColorblind);
  const auto defaults = planning::class_colours(planning::Palette::kDefault);
  // Each ball's centre: colour = alpha * the palette's class colour.
  const Eigen::Vector3d centres[3] = {{16, 20, 30}, {46, 18, 34}, {32, 46, 28}};
  for (int c = 0; c < 3; ++c) {
    const Eigen::Vector2d px = cam.project(front_view() * centres[c]);
    const int x = int(std::lround(px.x())), y = int(std::lround(px.y()));
    const double alpha = rendering.reference_pixel(cam, x, y)[3];
    ASSERT_GT(alpha, 0.5) << "class " << c;
    const cv::Vec3b got = colourblind.at<cv::Vec3b>(y, x), before = normal.at<cv::Vec3b>(y, x);
    for (int ch = 0; ch < 3; ++ch) {
      EXPECT_NEAR(got[2 - ch], alpha * palette[size_t(c)][size_t(ch)], 2.0) << "class " << c;
      EXPECT_NEAR(before[2 - ch], alpha * defaults[size_t(c)][size_t(ch)], 2.0) << "class " << c;
    }
    EXPECT_NE(got, before) << "class " << c;
  }
  cv::Mat reference = reference_image(rendering, cam, black);
  EXPECT_LE(max_difference(colourblind, reference), 3.0);
}

// A dangerous cube pierced along the viewing direction by a NaN hole: rays through the hole
// only meet NaN voxels and leave the background untouched.
TEST(SafetyVolumeRendering, NanVoxelsAreTransparent) {
  Volume<float> volume(cube_grid(), kDangerous);
  for (int k = 0; k < 64; ++k)
    for (int j = 20; j < 44; ++j)
      for (int i = 20; i < 44; ++i) volume(i, j, k) = kNaN;
  VolumeRenderingOptions options;
  options.opacity_per_mm[2] = 0.05;
  SafetyVolumeRendering rendering(volume, test_classes(), options);
  Eigen::Isometry3d T_cam_ct = Eigen::Isometry3d::Identity();
  T_cam_ct.translation() = -Eigen::Vector3d(31.5, 31.5, -150);
  rendering.set_pose(T_cam_ct);
  const auto cam = camera_320();
  auto renderer = make_renderer(cam);
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context";
  const cv::Mat frame = noise_frame(cam.width, cam.height, 5);
  const cv::Mat image = render(*renderer, rendering, frame);
  // The hole is 24 mm wide; from 150 mm to 214 mm depth it spans at least 24 / 214 * f pixels.
  int inside = 0, covered = 0;
  for (int y = 0; y < cam.height; ++y)
    for (int x = 0; x < cam.width; ++x) {
      const double nx = (x - cam.cx) / cam.fx, ny = (y - cam.cy) / cam.fy;
      const bool in_hole = std::abs(nx) * 214.5 < 11.5 && std::abs(ny) * 214.5 < 11.5;
      const bool in_cube = std::abs(nx) * 150.5 < 31.5 && std::abs(ny) * 150.5 < 31.5;
      if (in_hole) {
        ++inside;
        EXPECT_EQ(image.at<cv::Vec3b>(y, x), frame.at<cv::Vec3b>(y, x)) << x << "," << y;
      } else if (in_cube) {
        covered += image.at<cv::Vec3b>(y, x) != frame.at<cv::Vec3b>(y, x);
      }
    }
  EXPECT_GT(inside, 20 * 20);
  EXPECT_GT(covered, 5000);
}

// Rays cast at half resolution, upsampled bilinearly: close to the full-resolution image, and the
// background untouched away from the volume.
TEST(SafetyVolumeRendering, ReducedResolutionIsCloseToFull) {
  const Volume<float> volume = three_balls();
  VolumeRenderingOptions options;
  options.opacity_per_mm[0] = options.opacity_per_mm[1] = options.opacity_per_mm[2] = 0.05;
  SafetyVolumeRendering rendering(volume, test_classes(), options);
  rendering.set_pose(front_view());
  const auto cam = camera_320(-0.2);
  auto renderer = make_renderer(cam);
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context";
  const cv::Mat frame = noise_frame(cam.width, cam.height, 9);
  const cv::Mat full = render(*renderer, rendering, frame);
  options.resolution_scale = 0.5;
  rendering.set_options(options);
  const cv::Mat half = render(*renderer, rendering, frame);
  cv::Mat diff;
  cv::absdiff(full, half, diff);
  // Inside the balls' images the shading varies slowly; only their rims (a pixel or two) differ
  // much.
  EXPECT_LT(cv::mean(diff)[0] + cv::mean(diff)[1] + cv::mean(diff)[2], 3.0);
  cv::Mat changed;
  cv::transform(diff, changed, cv::Matx13f(1, 1, 1));
  EXPECT_LT(cv::countNonZero(changed > 30), cam.width * cam.height / 50);
  // Far from every ball (image corners), both are exactly the frame.
  EXPECT_EQ(cv::norm(half(cv::Rect(0, 0, 20, 20)), frame(cv::Rect(0, 0, 20, 20)), cv::NORM_INF), 0);
}

TEST(SafetyVolumeRendering, RejectsBadInput) {
  const Volume<float> volume = three_balls();
  VolumeRenderingOptions options;
  options.opacity_per_mm[1] = -1;
  EXPECT_THROW(SafetyVolumeRendering(volume, test_classes(), options), Error);
  options.opacity_per_mm[1] = 0.01;
  options.resolution_scale = 0;
  EXPECT_THROW(SafetyVolumeRendering(volume, test_classes(), options), Error);
  EXPECT_THROW(SafetyVolumeRendering(Volume<float>(), test_classes()), Error);
  SafetyVolumeRendering rendering(volume, test_classes());
  options.resolution_scale = 1;
  options.step_mm = -1;
  EXPECT_THROW(rendering.set_options(options), Error);
  // Voxel classes as documented.
  EXPECT_EQ(rendering.voxel_classes()[size_t(volume.geometry().offset(16, 20, 30))], 1);
  EXPECT_EQ(rendering.voxel_classes()[size_t(volume.geometry().offset(46, 18, 34))], 2);
  EXPECT_EQ(rendering.voxel_classes()[size_t(volume.geometry().offset(32, 46, 28))], 3);
  EXPECT_EQ(rendering.voxel_classes()[0], 0);
}

}  // namespace
}  // namespace crepuscular::overlay
