// The 3D planning view (overlay/plan_view.hpp) on OpenGL 3.3 core (Mesa llvmpipe under Xvfb): the
// orbiting camera's conventions, and analytic scenes (a safe cone around the tumor, the shadow of a
// ball obstacle, an unknown band beyond the scan, a body with a skin) drawn from planning cameras
// against a CPU ray cast of the same volume: each class's pixels where the CPU puts them within
// 1 px at the edges, the anatomy's surfaces to within rounding, unknown never in a class colour.
#include "overlay/plan_view.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "foundation/error.hpp"
#include "overlay/renderer.hpp"
#include "planning/safety/unknown.hpp"
#include "tests/support/renderer.hpp"
#include "tests/support/xvfb_environment.hpp"

namespace crepuscular::overlay {
namespace {

using planning::ImageGeometry;
using planning::Volume;

constexpr float kSafe = 0.5f, kMedium = 1.5f, kDangerous = 2.5f;
const float kNaN = std::numeric_limits<float>::quiet_NaN();
constexpr double kRadius = 28;  // region of interest, mm

TEST(OrbitCamera, LooksAtTheCentreWithThePatientsSidesWhereRadiologistsExpectThem) {
  OrbitCamera o;
  o.centre = Eigen::Vector3d(10, -20, 30);
  o.distance_mm = 400;
  const calibration::CameraModel cam = o.camera(640, 480);
  const auto pixel = [&](const Eigen::Vector3d& offset) {
    return cam.project(o.pose() * (o.centre + offset));
  };
  const Eigen::Vector2d centre = pixel(Eigen::Vector3d::Zero());
  EXPECT_NEAR(centre.x(), 319.5, 1e-9);
  EXPECT_NEAR(centre.y(), 239.5, 1e-9);
  const Eigen::Vector3d left(10, 0, 0), anterior(0, -10, 0), superior(0, 0, 10);
  // From anterior the patient faces the viewer: the patient's left on the image right.
  o.angles = parse_view_angles("anterior");
  EXPECT_GT(pixel(left).x(), centre.x() + 10);
  EXPECT_LT(pixel(superior).y(), centre.y() - 10);
  EXPECT_LT((o.pose().inverse().translation() - (o.centre + Eigen::Vector3d(0, -400, 0))).norm(),
            1e-9);
  o.angles = parse_view_angles("posterior");
  EXPECT_LT(pixel(left).x(), centre.x() - 10);
  o.angles = parse_view_angles("left");  // from the patient's left: anterior on the image left
  EXPECT_LT(pixel(anterior).x(), centre.x() - 10);
  EXPECT_LT(pixel(superior).y(), centre.y() - 10);
  o.angles = parse_view_angles("superior");  // from above the head: anterior up
  EXPECT_LT(pixel(anterior).y(), centre.y() - 10);
  o.angles = parse_view_angles("inferior");  // from the feet: anterior up
  EXPECT_LT(pixel(anterior).y(), centre.y() - 10);
  o.angles = parse_view_angles("30,20");
  EXPECT_DOUBLE_EQ(o.angles.azimuth_deg, 30);
  EXPECT_DOUBLE_EQ(o.angles.elevation_deg, 20);
  EXPECT_THROW(parse_view_angles("sideways"), Error);
  EXPECT_THROW(parse_view_angles("30,95"), Error);
  EXPECT_THROW(parse_view_angles("30,"), Error);
  // A sphere at the fitting distance fills the smaller field of view: its angular radius is that
  // half angle (within the 5 % margin).
  const double d = OrbitCamera::fitting_distance(50, 30, 16.0 / 9.0);
  EXPECT_NEAR(std::asin(50 / d), 0.5 * 30 * M_PI / 180 / 1.05, 0.01);
}

// The analytic plan: 64^3 voxels of 1 mm around the tumor centre. Inside the region of interest a
// safe cone (30 degrees about anterior), the shadow of a ball obstacle (dangerous: points whose
// straight path to the centre crosses it), medium elsewhere; NaN outside; superior of z = c + 18
// the scan ends (unknown).
struct AnalyticPlan {
  planning::PlanData plan;
  Eigen::Vector3d obstacle = Eigen::Vector3d::Zero();
};

AnalyticPlan analytic_plan(bool body) {
  AnalyticPlan a;
  planning::PlanData& p = a.plan;
  ImageGeometry g;
  g.dims = {64, 64, 64};
  g.origin = Eigen::Vector3d(-31.5, -31.5, -31.5);
  p.dir = "analytic";
  p.grid = g;
  p.tumor_centre = Eigen::Vector3d::Zero();
  p.radius_mm = kRadius;
  a.obstacle = Eigen::Vector3d(14, 0, 0);
  const double obstacle_r = 5;
  Volume<float> v(g, kNaN);
  Volume<uint8_t> region(g, planning::kRegionNotComputed);
  const Eigen::Vector3d axis(0, -1, 0);
  for (int64_t k = 0; k < 64; ++k)
    for (int64_t j = 0; j < 64; ++j)
      for (int64_t i = 0; i < 64; ++i) {
        const Eigen::Vector3d x = g.index_to_physical(i, j, k);
        const double r = x.norm();
        if (r > kRadius) continue;
        if (x.z() > 18) {
          region(i, j, k) = planning::kRegionUnknown;
          continue;
        }
        region(i, j, k) = planning::kRegionComputed;
        float value = kMedium;
        if (r > 1e-9 && x.normalized().dot(axis) > std::cos(30 * M_PI / 180)) value = kSafe;
        // The segment x -> centre passes within obstacle_r of the obstacle's centre.
        const double t = std::clamp(a.obstacle.dot(x) / std::max(1e-9, x.squaredNorm()), 0.0, 1.0);
        if ((t * x - a.obstacle).norm() < obstacle_r) value = kDangerous;
        v(i, j, k) = value;
      }
  p.values = {"svv"};
  p.path_safety["svv"] = std::move(v);
  planning::SafetyClasses c;
  c.safe = 1.0;
  c.dangerous = 2.0;
  p.classes["svv"] = c;
  p.region = std::move(region);
  if (body) {
    // A body: a ball of 26 mm (label 1); the tumor a ball of 4 mm.
    p.labels = Volume<int32_t>(g, 0);
    p.tumor = Volume<uint8_t>(g, 0);
    for (int64_t k = 0; k < 64; ++k)
      for (int64_t j = 0; j < 64; ++j)
        for (int64_t i = 0; i < 64; ++i) {
          const double r = g.index_to_physical(i, j, k).norm();
          p.labels(i, j, k) = r <= 26 ? 1 : 0;
          p.tumor(i, j, k) = r <= 4 ? 1 : 0;
        }
  }
  return a;
}

// The view drawn by the renderer, and the CPU ray cast of the same volume (BGR 0..255, over black).
struct Pictures {
  cv::Mat gpu;        // CV_8UC3
  cv::Mat cpu;        // CV_64FC3
  cv::Mat ambiguous;  // CV_8U: pixels whose ray grazes a face between voxels of two classes
};

Pictures draw_both(PlanView3D& view, const ViewAngles& angles, int width = 240, int height = 180) {
  const OrbitCamera orbit = view.default_camera(angles, double(width) / height);
  const calibration::CameraModel cam = orbit.camera(width, height);
  auto renderer = test::make_renderer(cam);
  renderer->set_frame(cv::Mat(height, width, CV_8UC3, cv::Scalar(0, 0, 0)));
  const Eigen::Isometry3d pose = orbit.pose();
  renderer->set_layer_draw("3d", [&](const DrawContext& c) {
    view.draw(c, cv::Rect(0, 0, width, height), cam, pose, false);
  });
  Pictures p;
  p.gpu = renderer->render();
  view.release_gl();
  p.cpu = cv::Mat(height, width, CV_64FC3);
  p.ambiguous = cv::Mat(height, width, CV_8U, cv::Scalar(0));
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x) {
      bool ambiguous = false;
      const Eigen::Vector4d c = view.rendering().reference_pixel(cam, x, y, &ambiguous);
      p.cpu.at<cv::Vec3d>(y, x) = cv::Vec3d(255 * c[2], 255 * c[1], 255 * c[0]);
      p.ambiguous.at<uint8_t>(y, x) = ambiguous ? 255 : 0;
    }
  return p;
}

// Pixels covered by one class shown alone: brighter than half its colour.
cv::Mat covered(const cv::Mat& image, const planning::Rgb& colour) {
  cv::Mat image64;
  image.convertTo(image64, CV_64FC3);
  const double full = double(colour[0]) + colour[1] + colour[2];
  cv::Mat mask(image.rows, image.cols, CV_8U);
  for (int y = 0; y < image.rows; ++y)
    for (int x = 0; x < image.cols; ++x) {
      const cv::Vec3d p = image64.at<cv::Vec3d>(y, x);
      mask.at<uint8_t>(y, x) = (p[0] + p[1] + p[2]) > 0.5 * full ? 255 : 0;
    }
  return mask;
}

// Pixels where the masks differ with no pixel of the CPU's mask within 1 px holding the GPU's
// value: disagreements beyond the edges.
int beyond_one_pixel(const cv::Mat& gpu, const cv::Mat& cpu) {
  int n = 0;
  for (int y = 0; y < gpu.rows; ++y)
    for (int x = 0; x < gpu.cols; ++x) {
      const uint8_t g = gpu.at<uint8_t>(y, x);
      if (g == cpu.at<uint8_t>(y, x)) continue;
      bool near = false;
      for (int dy = -1; dy <= 1 && !near; ++dy)
        for (int dx = -1; dx <= 1 && !near; ++dx) {
          const int yy = y + dy, xx = x + dx;
          near = yy >= 0 && xx >= 0 && yy < gpu.rows && xx < gpu.cols && cpu.at<uint8_t>(yy, xx) == g;
        }
      n += near ? 0 : 1;
    }
  return n;
}

TEST(PlanView3D, EachClassShowsWhereTheCpuRayCastPutsItWithinOnePixel) {
  const AnalyticPlan a = analytic_plan(false);
  const char* names[4] = {"safe", "medium", "dangerous", "unknown"};
  const auto colours = planning::class_colours(planning::Palette::kDefault);
  for (const char* view_name : {"anterior", "30,20", "right"}) {
    for (size_t shown = 0; shown < 4; ++shown) {
      PlanViewOptions o;
      for (size_t c = 0; c < 4; ++c) o.hidden[c] = c != shown;
      o.opacity_scale = 100;  // 0.4 to 1 per mm: a few mm of a class cover a pixel
      o.resolution_scale = 1;
      PlanView3D view(a.plan, nullptr, o);
      const Pictures p = draw_both(view, parse_view_angles(view_name));
      const planning::Rgb colour = shown < 3 ? colours[shown] : kUnknownGrey;
      const cv::Mat gpu = covered(p.gpu, colour);
      cv::Mat cpu8;
      p.cpu.convertTo(cpu8, CV_8UC3);
      const cv::Mat cpu = covered(cpu8, colour);
      const std::string what = std::string(view_name) + ", " + names[shown];
      // The dangerous shadow lies behind the obstacle (+x): from the patient's right it hides
      // behind nothing but is thin; every class covers a good part of the picture.
      EXPECT_GT(cv::countNonZero(cpu), shown == 2 ? 100 : 1000) << what;
      EXPECT_EQ(beyond_one_pixel(gpu, cpu), 0) << what;
      cv::Mat diff;
      cv::bitwise_xor(gpu, cpu, diff);
      EXPECT_LT(cv::countNonZero(diff), 0.02 * cv::countNonZero(cpu) + 20) << what;
    }
  }
}

TEST(PlanView3D, UnknownIsGreyNeverAClassColour) {
  const AnalyticPlan a = analytic_plan(false);
  PlanViewOptions o;
  o.opacity_scale = 20;
  o.resolution_scale = 1;
  o.hidden = {false, true, true, false};  // safe and unknown
  PlanView3D view(a.plan, nullptr, o);
  // Every unknown voxel is of the unknown class, none of a safety class.
  const auto& classes = view.rendering().voxel_classes();
  int64_t unknown = 0;
  for (int64_t v = 0; v < a.plan.region.voxel_count(); ++v) {
    if (a.plan.region[v] != planning::kRegionUnknown) continue;
    ++unknown;
    ASSERT_EQ(classes[size_t(v)], 4) << "voxel " << v;
  }
  EXPECT_GT(unknown, 1000);
  // From above the head the rays meet the unknown cap first, then the safe cone below it: where
  // the CPU ray cast is grey (the cap covers the cone), the picture is grey.
  const Pictures p = draw_both(view, parse_view_angles("superior"));
  int grey = 0;
  for (int y = 0; y < p.gpu.rows; ++y)
    for (int x = 0; x < p.gpu.cols; ++x) {
      const cv::Vec3d c = p.cpu.at<cv::Vec3d>(y, x);
      if (c[0] + c[1] + c[2] < 200 || std::abs(c[1] - c[0]) > 2 || std::abs(c[1] - c[2]) > 2)
        continue;
      const cv::Vec3b g = p.gpu.at<cv::Vec3b>(y, x);
      EXPECT_LE(std::abs(int(g[1]) - int(g[2])), 3) << "pixel " << x << "," << y;
      EXPECT_LE(std::abs(int(g[1]) - int(g[0])), 3) << "pixel " << x << "," << y;
      ++grey;
    }
  EXPECT_GT(grey, 500);
}

TEST(PlanView3D, AnatomySurfacesMatchTheCpuRayCast) {
  const AnalyticPlan a = analytic_plan(true);
  PlanViewOptions o;
  o.resolution_scale = 1;
  PlanView3D view(a.plan, nullptr, o);
  const AnatomyContext& context = view.context();
  // Body inside 26 mm, tumor inside 4 mm, air outside.
  const auto& g = a.plan.grid;
  const auto kind_at = [&](const Eigen::Vector3d& p) {
    const auto n = g.nearest_index(p);
    return context.kinds(n[0], n[1], n[2]);
  };
  EXPECT_EQ(kind_at({0, 0, 0}), kTumor);
  EXPECT_EQ(kind_at({0, -15, 0}), kSkin);
  EXPECT_EQ(kind_at({0, -29, 0}), kOutside);
  for (const char* view_name : {"anterior", "30,20"}) {
    const Pictures p = draw_both(view, parse_view_angles(view_name));
    cv::Mat gpu64, diff;
    p.gpu.convertTo(gpu64, CV_64FC3);
    cv::absdiff(gpu64, p.cpu, diff);
    int off = 0, counted = 0;
    for (int y = 0; y < diff.rows; ++y)
      for (int x = 0; x < diff.cols; ++x) {
        if (p.ambiguous.at<uint8_t>(y, x)) continue;
        ++counted;
        const cv::Vec3d d = diff.at<cv::Vec3d>(y, x);
        if (std::max({d[0], d[1], d[2]}) > 2.5) ++off;
      }
    EXPECT_LT(off, counted / 200) << view_name << ": " << off << " of " << counted;
    // The classes show only inside the body: the corner pixels (air around the ball) are empty.
    EXPECT_EQ(p.gpu.at<cv::Vec3b>(0, 0), cv::Vec3b(0, 0, 0)) << view_name;
    // The skin's surface shows where the body is seen edge-on: a ring of pixels lit by it.
    const cv::Vec3b mid = p.gpu.at<cv::Vec3b>(p.gpu.rows / 2, p.gpu.cols / 2);
    EXPECT_GT(int(mid[0]) + mid[1] + mid[2], 30) << view_name;
  }
}

}  // namespace
}  // namespace crepuscular::overlay
