// The guidance overlay on an analytic plan: a ball-shaped body (radius 40 mm) around a ball tumor
// (5 mm) with an impassable vessel column parallel to z at x = 16 mm (radius 4 mm). Ray bundles end
// on the skin and never pass through the vessel; entry contours lie on the skin; every layer on
// and off changes only its own pixels; the needle's colour switches from safe to dangerous as it
// swings onto the vessel; no overlay is drawn from a pose older than the tracker's limit.
#include "overlay/guidance.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <memory>
#include <set>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "foundation/error.hpp"
#include "overlay/renderer.hpp"
#include "overlay/targeting_view.hpp"
#include "pipelines/plan.hpp"
#include "planning/imaging/ray_march.hpp"
#include "planning/imaging/sampling.hpp"
#include "planning/safety/unknown.hpp"
#include "planning/imaging/volume_io.hpp"
#include "tests/support/plans.hpp"
#include "tests/support/renderer.hpp"
#include "tests/support/temporary_folder.hpp"
#include "tracking/synthetic.hpp"
#include "tracking/tracker.hpp"

namespace crepuscular::overlay {
namespace {

using test::make_renderer;

constexpr double kBody = 40.0, kTumor = 5.0, kVesselX = 16.0, kVesselR = 4.0;

// Azimuth (deg, from +x toward +y) and elevation (deg, from the xy plane) of a direction.
double azimuth_deg(const Eigen::Vector3d& d) { return std::atan2(d.y(), d.x()) * 180 / M_PI; }
double elevation_deg(const Eigen::Vector3d& d) {
  return std::asin(std::clamp(d.z() / d.norm(), -1.0, 1.0)) * 180 / M_PI;
}

// Camera 300 mm anterior of the tumor (-y, LPS), looking posterior; image x = patient left.
Eigen::Isometry3d T_ct_cam() {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear().col(0) = Eigen::Vector3d(1, 0, 0);
  T.linear().col(1) = Eigen::Vector3d(0, 0, -1);
  T.linear().col(2) = Eigen::Vector3d(0, 1, 0);
  T.translation() = Eigen::Vector3d(0, -300, 0);
  return T;
}

calibration::CameraModel test_camera() {
  calibration::CameraModel c;
  c.width = 640;
  c.height = 480;
  c.fx = c.fy = 700;
  c.cx = 321.5;
  c.cy = 238.0;
  c.distortion = {-0.1, 0.02, 0, 0, 0};
  return c;
}

// The registration of the test: a board frame turned and shifted against CT.
Eigen::Isometry3d T_ct_patient() {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = Eigen::AngleAxisd(0.4, Eigen::Vector3d(0.3, 1, -0.2).normalized()).toRotationMatrix();
  T.translation() = Eigen::Vector3d(-30, -45, 12);
  return T;
}

tracking::BoardStatus board(const std::string& name, const Eigen::Isometry3d& T_cam_board,
                            bool tracked = true) {
  tracking::BoardStatus s;
  s.board = name;
  s.tracked = tracked;
  s.measured = tracked;
  s.T_cam_board = T_cam_board;
  s.age_ms = tracked ? 0 : 1e9;
  return s;
}

// A needle board whose needle (tip at +150 mm along z) ends at `tip` pointing along `axis` (CT).
Eigen::Isometry3d T_ct_needle_for(const Eigen::Vector3d& tip, const Eigen::Vector3d& axis) {
  const Eigen::Vector3d z = axis.normalized();
  const Eigen::Vector3d x = z.unitOrthogonal();
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear().col(0) = x;
  T.linear().col(1) = z.cross(x);
  T.linear().col(2) = z;
  T.translation() = tip - z * 150.0;
  return T;
}

class GuidanceTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new test::TemporaryFolder;
    planning::ImageGeometry g;
    g.dims = {44, 44, 44};
    g.spacing = Eigen::Vector3d::Constant(2.0);
    g.origin = Eigen::Vector3d::Constant(-43.0);  // voxel centres at -43 .. 43 mm
    planning::Volume<int32_t> labels(g, 0);
    planning::Volume<uint8_t> tumor(g, 0);
    for (int64_t k = 0; k < 44; ++k)
      for (int64_t j = 0; j < 44; ++j)
        for (int64_t i = 0; i < 44; ++i) {
          const Eigen::Vector3d p = g.index_to_physical(i, j, k);
          if (p.norm() < kBody) labels(i, j, k) = 1;
          if (p.norm() < kBody && std::hypot(p.x() - kVesselX, p.y()) < kVesselR) labels(i, j, k) = 2;
          if (p.norm() < kTumor) tumor(i, j, k) = 1;
        }
    planning::write_volume(labels, (*dir_ / "labels.nii.gz").string());
    planning::write_volume(tumor, (*dir_ / "tumor.nii.gz").string());
    test::write_fat_and_vessel_table((*dir_ / "table.json").string());
    pipelines::PlanRequest r;
    r.labels = {(*dir_ / "labels.nii.gz").string()};
    r.tumor = (*dir_ / "tumor.nii.gz").string();
    r.vulnerability = (*dir_ / "table.json").string();
    r.margin.fwhm_mm = 0.0;
    r.path_safety.radius_mm = 43.0;
    r.path_safety.device = planning::Device::kCpu;
    r.path_safety.mode = planning::Mode::kFast;
    r.out_dir = (*dir_ / "plan").string();
    pipelines::run_plan(r);
    plan_ = new planning::PlanData(planning::load_plan((*dir_ / "plan").string()));
    GuidanceSetup setup;
    setup.camera = test_camera();
    setup.T_ct_patient = T_ct_patient();
    GuidanceOptions options;
    options.ray_directions = 1500;
    overlay_ = new GuidanceOverlay(*plan_, setup, options);
  }
  static void TearDownTestSuite() {
    delete overlay_;
    delete plan_;
    delete dir_;
  }

  // A frame and tracking result with the patient board seen and, optionally, the needle.
  static tracking::TrackResult track(const std::optional<Eigen::Isometry3d>& T_ct_needle) {
    tracking::TrackResult t;
    const Eigen::Isometry3d T_cam_ct = T_ct_cam().inverse();
    t.boards.push_back(board("patient", T_cam_ct * T_ct_patient()));
    if (T_ct_needle) {
      t.boards.push_back(board("needle", T_cam_ct * *T_ct_needle));
    } else {
      t.boards.push_back(board("needle", Eigen::Isometry3d::Identity(), false));
    }
    return t;
  }
  static tracking::Frame grey_frame(int64_t index = 0) {
    tracking::Frame f;
    f.index = index;
    f.image = cv::Mat(480, 640, CV_8UC3, cv::Scalar(90, 100, 110));
    return f;
  }

  static test::TemporaryFolder* dir_;
  static planning::PlanData* plan_;
  static GuidanceOverlay* overlay_;
};
test::TemporaryFolder* GuidanceTest::dir_ = nullptr;
planning::PlanData* GuidanceTest::plan_ = nullptr;
GuidanceOverlay* GuidanceTest::overlay_ = nullptr;

TEST_F(GuidanceTest, RayBundlesEndOnTheSkinAndAvoidTheVessel) {
  const auto& rays = overlay_->rays();
  ASSERT_GT(rays.size(), 500u);
  int through_vessel_core = 0, far_from_vessel = 0;
  for (const auto& ray : rays) {
    const Eigen::Vector3d d = (ray.end - ray.start).normalized();
    EXPECT_NEAR(ray.start.norm(), kTumor, 2.5);
    EXPECT_NEAR(ray.end.norm(), kBody, 3.0);
    // Blocked: the ray's xy path meets the column (|azimuth| < asin(4/16) = 14.5 deg) before it
    // leaves the body (|elevation| < acos(16/40) = 66 deg); 6 deg of margin for the tumor's size.
    if (std::abs(azimuth_deg(d)) < 8.5 && std::abs(elevation_deg(d)) < 60) ++through_vessel_core;
    if (std::abs(azimuth_deg(d)) > 40) ++far_from_vessel;
  }
  EXPECT_EQ(through_vessel_core, 0);
  // Every direction well away from the vessel is drawn, as safe: the whole tumor is in view.
  int expected = 0;
  for (const Eigen::Vector3d& d : planning::fibonacci_sphere(1500)) {
    if (std::abs(azimuth_deg(d)) > 40) ++expected;
  }
  EXPECT_EQ(far_from_vessel, expected);
  for (const auto& ray : rays) {
    const Eigen::Vector3d d = (ray.end - ray.start).normalized();
    if (std::abs(azimuth_deg(d)) > 40) {
      EXPECT_EQ(ray.safety_class, planning::SafetyClass::kSafe);
    }
  }
}

// The same patient scanned only from x = -6 mm on (the CT's grid ends there; the label map covers
// everything): no ray drawn reaches the unknown side, whatever its value borrows from known voxels,
// and every direction that stays on the scanned side is still drawn.
TEST_F(GuidanceTest, NoRayIsDrawnIntoTheUnknownOutsideTheScan) {
  test::TemporaryFolder dir;
  const planning::Volume<int32_t> labels =
      planning::read_label_map((*dir_ / "labels.nii.gz").string());
  planning::ImageGeometry ct_grid = labels.geometry();
  const int64_t first = 16;  // voxel 16 of 44 at 2 mm: x = -6 mm
  ct_grid.origin = ct_grid.index_to_physical(first, 0, 0);
  ct_grid.dims[0] -= first;
  const double cut_x = ct_grid.origin.x() - 1.0;  // the scan's edge: half a voxel before
  planning::write_volume(planning::Volume<float>(ct_grid, 40.0f), dir.file("ct.nii.gz"));
  pipelines::PlanRequest r;
  r.labels = {(*dir_ / "labels.nii.gz").string()};
  r.tumor = (*dir_ / "tumor.nii.gz").string();
  r.vulnerability = (*dir_ / "table.json").string();
  r.ct = dir.file("ct.nii.gz");
  r.margin.fwhm_mm = 0.0;
  r.path_safety.radius_mm = 43.0;
  r.path_safety.device = planning::Device::kCpu;
  r.path_safety.mode = planning::Mode::kFast;
  r.out_dir = dir.file("plan");
  const nlohmann::json plan = pipelines::run_plan(r);
  ASSERT_GT(plan["scan_coverage"]["unknown_voxels"].get<int64_t>(), 1000);
  const planning::PlanData cut = planning::load_plan(dir.file("plan"));
  GuidanceSetup setup;
  setup.camera = test_camera();
  setup.T_ct_patient = T_ct_patient();
  GuidanceOptions options;
  options.ray_directions = 1500;
  const GuidanceOverlay overlay(cut, setup, options);
  EXPECT_GT(overlay.unknown_rays(), 100);
  int kept_far_side = 0;
  for (const auto& ray : overlay.rays()) {
    // Every drawn ray ends in the scan: its end's voxel is computed, and x is at most the
    // nearest-voxel rounding of the region's 2 mm voxels (1 mm) before the scan's edge.
    EXPECT_EQ(planning::nearest_voxel_or<uint8_t>(cut.region, ray.end, 0),
              planning::kRegionComputed)
        << ray.end.transpose();
    EXPECT_GE(ray.end.x(), cut_x - 1.0 - 1e-6) << ray.end.transpose();
    if (ray.end.x() > 10.0) ++kept_far_side;
  }
  // Directions that stay well inside the scan (x > 10 mm at the skin) and away from the vessel
  // (which lies at +x) are drawn as in the full scan.
  int full_far_side = 0;
  for (const auto& ray : overlay_->rays()) {
    if (ray.end.x() > 10.0) ++full_far_side;
  }
  EXPECT_GE(kept_far_side, 0.9 * full_far_side);
  EXPECT_GT(full_far_side, 100);
}

TEST_F(GuidanceTest, EntryContoursLieOnTheSkin) {
  const auto& contours = overlay_->entry_contours();
  ASSERT_FALSE(contours.empty());
  size_t points = 0;
  bool closed = false;
  for (const auto& c : contours) {
    closed |= c.closed;
    EXPECT_GE(c.leeway, 0.0);
    EXPECT_LE(c.leeway, 1.0);
    for (const auto& p : c.points) {
      EXPECT_NEAR(p.norm(), kBody, 3.5);
      ++points;
    }
  }
  EXPECT_TRUE(closed);
  EXPECT_GT(points, 20u);
}

// The entry patches lie on the skin: their points on the 40 mm ball, and every pixel they fill in
// the camera image looks at the body (the pixel's ray enters the label map's body), where the
// body's first point along that ray lies on a patch (within 3 mm of a patch point): only the
// sides facing the camera are drawn, never a patch on the far side seen through the body.
TEST_F(GuidanceTest, EntryPatchesLieOnSkinPixels) {
  const auto& patches = overlay_->entry_patches();
  ASSERT_FALSE(patches.empty());
  std::vector<Eigen::Vector3d> points;
  for (const auto& p : patches) {
    EXPECT_FALSE(p.triangles.empty());
    EXPECT_FALSE(p.border.empty());
    for (const auto& q : p.points) {
      EXPECT_NEAR(q.norm(), kBody, 3.0);
      points.push_back(q);
    }
  }
  const calibration::CameraModel cam = test_camera();
  const Eigen::Isometry3d T = T_ct_cam();
  // Without the outermost pixel: a rasterised triangle covers every pixel its edge touches.
  cv::Mat mask;
  cv::erode(overlay_->entry_patch_mask(T.inverse(), cam), mask, cv::Mat());
  const int filled = cv::countNonZero(mask);
  EXPECT_GT(filled, 5000);
  int checked = 0, off_body = 0, off_patch = 0;
  for (int y = 0; y < mask.rows; y += 2) {
    for (int x = 0; x < mask.cols; x += 2) {
      if (!mask.at<uint8_t>(y, x)) continue;
      ++checked;
      const Eigen::Vector2d n = cam.unproject(Eigen::Vector2d(x, y));
      const Eigen::Vector3d dir = (T.linear() * Eigen::Vector3d(n.x(), n.y(), 1.0)).normalized();
      const auto hit = planning::first_entry(
          T.translation(), dir, 0.25, 600.0,
          [&](const Eigen::Vector3d& p) { return planning::in_body(plan_->labels, p); });
      if (!hit) {
        ++off_body;
        continue;
      }
      const Eigen::Vector3d skin = T.translation() + hit->inside_s * dir;
      double nearest = 1e9;
      for (const auto& q : points) nearest = std::min(nearest, (q - skin).norm());
      if (nearest > 3.0) ++off_patch;
    }
  }
  EXPECT_GT(checked, 1000);
  EXPECT_EQ(off_body, 0);
  EXPECT_EQ(off_patch, 0);
  // The planned trajectory: from the skin of the largest region to the tumor centre.
  ASSERT_TRUE(overlay_->planned_trajectory().has_value());
  const auto& plan = *overlay_->planned_trajectory();
  EXPECT_EQ(plan.region, 0);
  EXPECT_NEAR(plan.entry.norm(), kBody, 2.0);
  EXPECT_NEAR((plan.target - plan_->tumor_centre).norm(), 0.0, 1e-9);
}

TEST_F(GuidanceTest, EachLayerOnAndOffChangesOnlyItsPixels) {
  auto renderer = make_renderer(test_camera());
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context on this machine";
  GuidanceOverlay& o = *overlay_;
  // A needle 70 mm out along a safe direction (-x, +y side), pointing at the tumor.
  const Eigen::Vector3d dir = Eigen::Vector3d(-1, -1, 0.3).normalized();
  const auto needle = T_ct_needle_for(70.0 * dir, -dir);
  const tracking::TrackResult t = track(needle);
  GuidanceTiming timing;
  timing.fps = 30;
  timing.latency_ms = 20;
  auto render_with = [&](const std::vector<GuidanceLayer>& on) {
    for (int l = 0; l < kGuidanceLayerCount; ++l) o.set_visible(GuidanceLayer(l), false);
    for (auto l : on) o.set_visible(l, true);
    o.update(*renderer, grey_frame(), t, timing);
    return renderer->render();
  };
  // Pixels that differ by more than `levels` (in grey).
  auto changed = [](const cv::Mat& a, const cv::Mat& b, int levels = 0) {
    cv::Mat diff, mask;
    cv::absdiff(a, b, diff);
    cv::cvtColor(diff, mask, cv::COLOR_BGR2GRAY);
    return cv::Mat(mask > levels);
  };
  const std::vector<GuidanceLayer> all = {GuidanceLayer::kRays, GuidanceLayer::kVolume, GuidanceLayer::kEntry,
                                          GuidanceLayer::kTumor, GuidanceLayer::kNeedle,
                                          GuidanceLayer::kStatus, GuidanceLayer::kTarget};
  const cv::Mat none = render_with({});
  const cv::Mat everything = render_with(all);
  for (GuidanceLayer layer : all) {
    std::vector<GuidanceLayer> others;
    for (auto l : all)
      if (l != layer) others.push_back(l);
    const cv::Mat without = render_with(others);
    const cv::Mat alone = render_with({layer});
    // What switching it off changes; beyond 2 grey levels: a faint translucent layer that leaves
    // the grey frame unchanged in 8 bits can change a coloured translucent layer below by one.
    const cv::Mat toggled = changed(everything, without, 2);
    const cv::Mat own = changed(alone, none);              // where it draws at all
    const int toggled_count = cv::countNonZero(toggled);
    EXPECT_GT(toggled_count, 50) << guidance_layer_name(layer);
    cv::Mat outside;
    cv::bitwise_and(toggled, ~own, outside);
    EXPECT_EQ(cv::countNonZero(outside), 0) << guidance_layer_name(layer);
  }
}

TEST_F(GuidanceTest, NeedleColourSwitchesFromSafeToDangerousOnTheVessel) {
  auto renderer = make_renderer(test_camera());
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context on this machine";
  GuidanceOverlay& o = *overlay_;
  for (int l = 0; l < kGuidanceLayerCount; ++l) o.set_visible(GuidanceLayer(l), false);
  o.set_visible(GuidanceLayer::kNeedle, true);
  const auto colours = planning::class_colours(o.palette());
  const cv::Vec3b safe(colours[0][2], colours[0][1], colours[0][0]);
  const cv::Vec3b dangerous(colours[2][2], colours[2][1], colours[2][0]);
  const Eigen::Isometry3d T_cam_ct = T_ct_cam().inverse();
  // The needle swings in the plane z = 0 from 60 deg azimuth onto the vessel (0 deg), its tip
  // 60 mm from the tumor, always aimed at the centre.
  std::vector<planning::NeedleSafety> seen;
  for (double az : {60.0, 45.0, 30.0, 15.0, 5.0, 0.0}) {
    const double a = az * M_PI / 180;
    const Eigen::Vector3d out(std::cos(a), std::sin(a), 0.0);
    const Eigen::Vector3d tip = 60.0 * out;
    const GuidanceFrameInfo info =
        o.update(*renderer, grey_frame(), track(T_ct_needle_for(tip, -out)), {});
    ASSERT_TRUE(info.needle.has_value());
    const auto& s = info.needle->state;
    seen.push_back(s.safety);
    const cv::Mat image = renderer->render();
    // The extension's pixel halfway between the tip and the target (drawn 3 px wide, opaque).
    const Eigen::Vector2d uv = test_camera().project(T_cam_ct * (0.5 * (tip + s.target)));
    const cv::Vec3b px = image.at<cv::Vec3b>(int(std::lround(uv.y())), int(std::lround(uv.x())));
    if (s.safety == planning::NeedleSafety::kSafe) {
      EXPECT_EQ(px, safe) << "azimuth " << az;
    }
    if (s.safety == planning::NeedleSafety::kDangerous) {
      EXPECT_EQ(px, dangerous) << "azimuth " << az;
      EXPECT_FALSE(s.clear);
      bool vessel = false;
      for (const auto& h : s.evaluation.structures) vessel |= h.name == "vessel";
      EXPECT_TRUE(vessel);
    }
  }
  EXPECT_EQ(seen.front(), planning::NeedleSafety::kSafe);
  EXPECT_EQ(seen.back(), planning::NeedleSafety::kDangerous);
  for (int l = 0; l < kGuidanceLayerCount; ++l) o.set_visible(GuidanceLayer(l), true);
}

// A needle aimed at the tumor just clear of the vessel (3 deg beyond the last azimuth whose line
// is dangerous): safe, and safe in the overlay without uncertainty; with a registration known to
// 2 mm per axis, a line of its 95 % region crosses the vessel: UNCERTAIN, dangerous, in the frame's
// reading. A lost needle marker still shows as lost, with no reading to be uncertain about.
TEST_F(GuidanceTest, NeedleBesideTheVesselIsUncertainWithTheRegistrationsError) {
  auto renderer = make_renderer(test_camera());
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context on this machine";
  const planning::NeedleGuide& guide = overlay_->needle_guide();
  const auto tip_at = [](double az) {
    const double a = az * M_PI / 180;
    return Eigen::Vector3d(60.0 * std::cos(a), 60.0 * std::sin(a), 0.0);
  };
  double last_dangerous = -1;
  for (double az = 0; az <= 40; az += 0.25) {
    if (guide.line_safety(tip_at(az), -tip_at(az)) == planning::NeedleSafety::kDangerous) {
      last_dangerous = az;
    }
  }
  ASSERT_GT(last_dangerous, 5.0);
  ASSERT_LT(last_dangerous, 30.0);
  const Eigen::Vector3d tip = tip_at(last_dangerous + 3.0);
  const Eigen::Isometry3d T_ct_needle = T_ct_needle_for(tip, -tip.normalized());
  const GuidanceFrameInfo exact = overlay_->update(*renderer, grey_frame(), track(T_ct_needle), {});
  ASSERT_TRUE(exact.needle.has_value());
  EXPECT_EQ(exact.needle->state.safety, planning::NeedleSafety::kSafe);
  EXPECT_FALSE(exact.needle->region.uncertain());
  EXPECT_NEAR(exact.needle->uncertainty.major95_mm, 0.0, 1e-6);

  GuidanceSetup setup = overlay_->setup();
  setup.uncertainty.registration_tre_mm = 2.0 * std::sqrt(3.0);
  GuidanceOverlay noisy(*plan_, setup);
  const GuidanceFrameInfo info = noisy.update(*renderer, grey_frame(), track(T_ct_needle), {});
  ASSERT_TRUE(info.needle.has_value());
  EXPECT_EQ(info.needle->state.safety, planning::NeedleSafety::kSafe);
  EXPECT_TRUE(info.needle->region.uncertain());
  EXPECT_EQ(info.needle->region.worst, planning::NeedleSafety::kDangerous);
  EXPECT_NEAR(info.needle->uncertainty.major95_mm, 2.0 * std::sqrt(planning::kChi2_95_2dof), 1e-3);
  EXPECT_FALSE(info.needle->pose_covariance_known);

  const GuidanceFrameInfo lost = noisy.update(*renderer, grey_frame(), track(std::nullopt), {});
  EXPECT_FALSE(lost.needle.has_value());
  bool warned = false;
  for (const auto& w : lost.warnings) warned |= w == "NEEDLE MARKER LOST";
  EXPECT_TRUE(warned);
}

// Breathing: four phases whose plans differ only in a blob of bone (impassable) on a needle's safe
// line in phases 1-3; the skin under the board rises 0, 4, 8, 4 mm over them. The board rises and
// falls with a 4 s breath; the needle is held still in the room. Once the phase is known it is
// within one phase of the truth in at least 95 % of the frames; the needle is safe in the frames
// estimated as phase 0 (the gating bar: safe in phase 0 only) and dangerous in the others.
TEST_F(GuidanceTest, PathSafeOnlyAtExhaleIsSafeThereAndDangerousElsewhere) {
  auto renderer = make_renderer(test_camera());
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context on this machine";
  const double a = 60.0 * M_PI / 180;
  const Eigen::Vector3d out(std::cos(a), std::sin(a), 0.0);
  const Eigen::Vector3d tip = 60.0 * out;
  ASSERT_EQ(overlay_->needle_guide().line_safety(tip, -out), planning::NeedleSafety::kSafe);
  auto phases = std::make_unique<BreathingPhases>();
  const Eigen::Vector3d up(0.0, -1.0, 0.0);  // the skin rises anteriorly
  phases->skin.direction = up;
  phases->skin.displacement_mm = {0.0, 4.0, 8.0, 4.0};
  phases->skin.inhale_phase = 2;
  for (int k = 0; k < 4; ++k) {
    auto p = std::make_unique<planning::PlanData>(*plan_);
    if (k > 0) {
      const Eigen::Vector3d blob = 25.0 * out;
      const auto& g = p->blocking.geometry();
      for (int64_t n = 0; n < p->blocking.voxel_count(); ++n) {
        const auto ijk = g.index_of_offset(n);
        if ((p->blocking.index_to_physical(ijk[0], ijk[1], ijk[2]) - blob).norm() < 5.0) {
          p->blocking[n] = 100.0f;
        }
      }
    }
    phases->names.push_back("phase0" + std::to_string(k));
    phases->plans.push_back(std::move(p));
  }
  GuidanceOverlay o(*plan_, overlay_->setup());
  o.set_breathing(std::move(phases));
  const Eigen::Isometry3d T_cam_ct = T_ct_cam().inverse();
  const Eigen::Isometry3d T_ct_needle = T_ct_needle_for(tip, -out);
  int known = 0, within_one = 0, safe_at_exhale = 0, exhale = 0, other = 0, dangerous_other = 0;
  for (int i = 0; i < 30 * 12; ++i) {
    const double t = i / 30.0, cycle = t / 4.0 - std::floor(t / 4.0);
    const double rise = 8.0 * std::pow(std::sin(M_PI * cycle), 2);
    tracking::TrackResult track;
    track.boards.push_back(board("patient", T_cam_ct * Eigen::Translation3d(rise * up) * T_ct_patient()));
    track.boards.push_back(board("needle", T_cam_ct * T_ct_needle));
    tracking::Frame f = grey_frame(i);
    f.timestamp_ns = int64_t(std::llround(t * 1e9));
    const GuidanceFrameInfo info = o.update(*renderer, f, track, {});
    ASSERT_TRUE(info.breathing.has_value());
    ASSERT_TRUE(info.needle.has_value());
    ASSERT_EQ(info.breathing->phase_safety.size(), 4u);
    EXPECT_EQ(info.breathing->phase_safety[0], planning::NeedleSafety::kSafe) << "frame " << i;
    for (int k = 1; k < 4; ++k) {
      EXPECT_EQ(info.breathing->phase_safety[size_t(k)], planning::NeedleSafety::kDangerous) << i;
    }
    const planning::PhaseEstimate& e = info.breathing->estimate;
    if (!e.known) continue;
    ++known;
    within_one += planning::phase_distance(e.phase, int(std::lround(cycle * 4)) % 4, 4) <= 1;
    // The needle stays where it is in the CT: the registration moves with the skin.
    EXPECT_LT((info.needle->state.tip - tip).norm(), 0.5) << "frame " << i;
    if (e.phase == 0) {
      ++exhale;
      safe_at_exhale += info.needle->state.safety == planning::NeedleSafety::kSafe;
    } else {
      ++other;
      dangerous_other += info.needle->state.safety == planning::NeedleSafety::kDangerous;
    }
  }
  EXPECT_GT(known, 30 * 8);
  EXPECT_GE(double(within_one) / known, 0.95);
  EXPECT_GT(exhale, 0);
  EXPECT_GT(other, 0);
  EXPECT_EQ(safe_at_exhale, exhale);
  EXPECT_EQ(dangerous_other, other);
}

// A needle whose tip has passed the vessel: the line is evaluated from where it entered the body,
// so the vessel it pierced still makes it dangerous.
TEST_F(GuidanceTest, NeedlePastTheVesselStaysDangerous) {
  const planning::NeedleGuide& guide = overlay_->needle_guide();
  const Eigen::Vector3d out = Eigen::Vector3d::UnitX();
  for (double tip_distance : {60.0, 30.0, 10.0}) {  // outside, in front of and past the vessel
    const Eigen::Isometry3d T = T_ct_needle_for(tip_distance * out, -out);
    const planning::NeedleState s =
        guide.evaluate(T, Eigen::Vector3d(0, 0, 150), Eigen::Vector3d::UnitZ());
    EXPECT_EQ(s.safety, planning::NeedleSafety::kDangerous) << tip_distance;
    EXPECT_FALSE(s.clear) << tip_distance;
    EXPECT_EQ(s.tip_in_body, tip_distance < kBody) << tip_distance;
    if (s.tip_in_body) {
      EXPECT_NEAR(s.line_start.norm(), kBody, 2.5) << tip_distance;
    }
    bool vessel = false;
    for (const auto& h : s.evaluation.structures) {
      if (h.name != "vessel") continue;
      vessel = true;
      // Depth from where the line starts: the vessel's outer wall at x = 20 mm.
      EXPECT_NEAR(h.depth_mm, (s.line_start.x() - (kVesselX + kVesselR)), 2.5) << tip_distance;
    }
    EXPECT_TRUE(vessel) << tip_distance;
  }
}

// Through the real tracker: a frame showing both boards, then frames without them. While the last
// pose is younger than the limit (100 ms) the overlay stays; after that, nothing but the frame,
// the status and the warning.
TEST_F(GuidanceTest, NoOverlayFromAPoseOlderThanTheLimit) {
  tracking::SyntheticScene scene = tracking::builtin_scene();
  auto renderer = make_renderer(scene.camera);
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context on this machine";
  std::vector<tracking::Board> boards;
  for (const auto& b : scene.boards) boards.push_back(b.board);
  tracking::TrackerOptions to;
  to.max_age_ms = 100;
  tracking::Tracker tracker(scene.camera, boards, to);
  // Registration: the tumor centre (CT origin here) at the scene's target, axes as if the board
  // lay on the anterior skin.
  GuidanceSetup setup;
  setup.camera = scene.camera;
  Eigen::Isometry3d T_ct_patient = Eigen::Isometry3d::Identity();
  T_ct_patient.linear().col(0) = Eigen::Vector3d(1, 0, 0);
  T_ct_patient.linear().col(1) = Eigen::Vector3d(0, 0, -1);
  T_ct_patient.linear().col(2) = Eigen::Vector3d(0, 1, 0);
  T_ct_patient.translation() = -(T_ct_patient.linear() * tracking::kTumorTargetInPatient);
  setup.T_ct_patient = T_ct_patient;
  GuidanceOverlay o(*plan_, setup);

  tracking::SyntheticRenderer frames(scene);
  const cv::Mat seen = frames.render(0);
  const cv::Mat empty(seen.size(), CV_8UC3, cv::Scalar(128, 128, 128));
  struct Step {
    int64_t ms;
    bool boards_visible;
    bool expect_overlay;
  };
  int64_t index = 0;
  for (const Step& step : {Step{0, true, true}, Step{60, false, true}, Step{160, false, false}}) {
    tracking::Frame f;
    f.index = index++;
    f.timestamp_ns = step.ms * 1000000;
    f.image = step.boards_visible ? seen : empty;
    const tracking::TrackResult t = tracker.process(f);
    const GuidanceFrameInfo info = o.update(*renderer, f, t, {});
    EXPECT_EQ(info.patient_tracked, step.expect_overlay) << step.ms << " ms";
    EXPECT_EQ(info.anatomy_drawn, step.expect_overlay) << step.ms << " ms";
    EXPECT_EQ(info.needle.has_value(), step.expect_overlay) << step.ms << " ms";
    // Hide the status panel: what remains besides the frame is overlay (and warnings).
    o.set_visible(GuidanceLayer::kStatus, false);
    o.update(*renderer, f, t, {});
    const cv::Mat image = renderer->render();
    o.set_visible(GuidanceLayer::kStatus, true);
    cv::Mat diff, grey;
    cv::absdiff(image, f.image, diff);
    cv::cvtColor(diff, grey, cv::COLOR_BGR2GRAY);
    const int changed = cv::countNonZero(grey > 0);
    if (step.expect_overlay) {
      EXPECT_GT(changed, 500) << step.ms << " ms";
    } else {
      bool warned = false;
      for (const auto& w : info.warnings) warned |= w.find("PATIENT MARKER LOST") != std::string::npos;
      EXPECT_TRUE(warned);
      // Only the warning banner at the top: nothing below the banners.
      EXPECT_EQ(cv::countNonZero(grey(cv::Rect(0, 120, grey.cols, grey.rows - 120)) > 0), 0);
    }
  }
}

// The targeting view of a needle aimed 3 mm beside the tumor centre from an oblique direction: the
// white cross of the picture lies where the needle's line meets the plane through the centroid
// perpendicular to it (the analytic intersection, mapped with the view's own right/down axes,
// built here from the hint), within 1 px; the tumor (a 5 mm ball) is drawn as a circle of 5 mm.
TEST_F(GuidanceTest, TargetingCrossMarksTheNeedleCrossingWithinOnePixel) {
  const planning::NeedleGuide& guide = overlay_->needle_guide();
  const Eigen::Vector3d c = plan_->tumor_centre;
  const Eigen::Vector3d tip(-55, -30, 12), aim = c + Eigen::Vector3d(3, -2, 1);
  const Eigen::Vector3d a = (aim - tip).normalized();
  const planning::NeedleState s =
      guide.evaluate(T_ct_needle_for(tip, a), Eigen::Vector3d(0, 0, 150), Eigen::Vector3d::UnitZ());
  planning::TargetingOptions to;
  to.size_px = 300;
  to.half_extent_mm = 20.0;  // 300 px over 40 mm: 0.1333 mm per pixel
  to.right_hint = Eigen::Vector3d(0, 0, 1);
  const planning::TargetingGeometry g =
      planning::targeting_geometry(guide, s, overlay_->tumor_surface(), 2.0, to);
  ASSERT_TRUE(g.valid);
  // The analytic crossing: tip + s a with (p - c) . a = 0.
  const Eigen::Vector3d q = tip + (c - tip).dot(a) * a;
  EXPECT_NEAR((g.crossing - q).norm(), 0.0, 1e-9);
  const Eigen::Vector3d u = (to.right_hint - to.right_hint.dot(a) * a).normalized();
  const Eigen::Vector3d v = a.cross(u);
  const double mm_per_px = 40.0 / 300.0;
  const Eigen::Vector2d expected =
      Eigen::Vector2d(149.5, 149.5) + Eigen::Vector2d((q - c).dot(u), (q - c).dot(v)) / mm_per_px;
  // The needle misses the centre by sqrt(14) mm less its part along the axis: well off the centre.
  ASSERT_GT((expected - Eigen::Vector2d(149.5, 149.5)).norm(), 15.0);
  auto cross_centroid = [](const cv::Mat& bgra) {
    cv::Mat bgr, mask;
    cv::cvtColor(bgra, bgr, cv::COLOR_BGRA2BGR);
    cv::inRange(bgr, kTargetingCrossColour, kTargetingCrossColour, mask);
    const cv::Moments m = cv::moments(mask, true);
    return std::make_pair(Eigen::Vector2d(m.m10 / m.m00, m.m01 / m.m00), int(m.m00));
  };
  const cv::Mat view = render_targeting_view(g, planning::Palette::kDefault);
  ASSERT_EQ(view.rows, 300);
  const auto [found, count] = cross_centroid(view);
  EXPECT_GT(count, 40);
  EXPECT_LE((found - expected).norm(), 1.0) << found.transpose() << " vs " << expected.transpose();
  // The tumor's outline: a ball of 5 mm radius (voxel centres within 5 mm, 2 mm voxels drawn as
  // discs of 0.6 voxel): its outline lies 4 to 6.5 mm from the centre.
  for (const auto& outline : point_cloud_outlines(g.tumor_px, g.tumor_point_radius_px)) {
    for (const auto& p : outline) {
      const double r_mm = (Eigen::Vector2d(p.x, p.y) - g.centre_px).norm() * mm_per_px;
      EXPECT_GT(r_mm, 4.0);
      EXPECT_LT(r_mm, 6.5);
    }
  }

  // The same through the overlay and the renderer: the picture-in-picture in the frame.
  auto renderer = make_renderer(test_camera());
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context on this machine";
  GuidanceOverlay& o = *overlay_;
  for (int l = 0; l < kGuidanceLayerCount; ++l) o.set_visible(GuidanceLayer(l), false);
  o.set_visible(GuidanceLayer::kTarget, true);
  o.update(*renderer, grey_frame(), track(T_ct_needle_for(tip, a)), {});
  const cv::Mat image = renderer->render();
  for (int l = 0; l < kGuidanceLayerCount; ++l) o.set_visible(GuidanceLayer(l), l != 1);
  const planning::TargetingGeometry& shown = o.last_targeting();
  ASSERT_TRUE(shown.valid);
  const cv::Rect box(o.last_targeting_origin(), cv::Size(shown.size_px, shown.size_px));
  ASSERT_EQ(box & cv::Rect(0, 0, image.cols, image.rows), box);
  cv::Mat pip;
  cv::cvtColor(image(box), pip, cv::COLOR_BGR2BGRA);
  // Its own scale and axes (the camera's right): the analytic crossing in those.
  const Eigen::Vector2d shown_expected =
      shown.centre_px +
      Eigen::Vector2d((q - c).dot(shown.u), (q - c).dot(shown.v)) / shown.mm_per_px;
  EXPECT_NEAR(shown.u.dot(a), 0.0, 1e-12);
  // Right in the view: the camera's right, projected onto the plane.
  const Eigen::Vector3d cam_x = T_ct_cam().linear().col(0);
  EXPECT_NEAR((shown.u - (cam_x - cam_x.dot(a) * a).normalized()).norm(), 0.0, 1e-9);
  const auto [found_in_frame, n_in_frame] = cross_centroid(pip);
  EXPECT_GT(n_in_frame, 40);
  EXPECT_LE((found_in_frame - shown_expected).norm(), 1.0);
}

// The polar map's classes, cell by cell along 8 directions (every other sector of 16) on two
// rings, equal those of `evaluate` for the same straight lines: from the pivot just outside the
// skin along the tilted direction to its point nearest the tumor centre. The needle comes in at
// 30 deg azimuth, past the vessel (x = 16 mm, |y| < 4 mm): tilts of 17.5 deg toward -y cross it.
TEST_F(GuidanceTest, PolarSafetyMapAgreesWithEvaluateAlongEightDirections) {
  const planning::NeedleGuide& guide = overlay_->needle_guide();
  const Eigen::Vector3d c = plan_->tumor_centre;
  const double az = 30.0 * M_PI / 180.0;
  const Eigen::Vector3d out(std::cos(az), std::sin(az), 0.0);
  const planning::NeedleState s = guide.evaluate(T_ct_needle_for(c + 60.0 * out, -out),
                                                 Eigen::Vector3d(0, 0, 150),
                                                 Eigen::Vector3d::UnitZ());
  planning::TargetingOptions to;
  to.right_hint = Eigen::Vector3d(0, 1, 0);
  to.max_tilt_deg = 25.0;  // rings of 5 deg
  const planning::TargetingGeometry g =
      planning::targeting_geometry(guide, s, overlay_->tumor_surface(), 2.0, to);
  ASSERT_TRUE(g.valid);
  ASSERT_EQ(int(g.cells.size()), to.rings * to.sectors);
  // The pivot: on the needle's line, just outside the 40 mm ball.
  EXPECT_NEAR(g.pivot.norm(), kBody, 2.0);
  EXPECT_FALSE(planning::in_body(plan_->labels, g.pivot));
  EXPECT_NEAR(((g.pivot - s.tip).cross(s.axis)).norm(), 0.0, 1e-6);
  EXPECT_NEAR(g.u.dot(g.v), 0.0, 1e-12);
  EXPECT_NEAR(g.u.dot(g.axis), 0.0, 1e-12);
  const planning::TrajectoryEvaluator evaluator(*plan_);
  std::set<planning::NeedleSafety> seen;
  for (int ring : {1, 3}) {
    for (int k = 0; k < 8; ++k) {
      const int sector = 2 * k;
      const planning::PolarCell& cell = g.cells[size_t(ring * to.sectors + sector)];
      ASSERT_EQ(cell.ring, ring);
      ASSERT_EQ(cell.sector, sector);
      const double tilt = (ring + 0.5) * to.max_tilt_deg / to.rings * M_PI / 180.0;
      const double phi = k * 45.0 * M_PI / 180.0;
      const Eigen::Vector3d d = std::cos(tilt) * g.axis +
                                std::sin(tilt) * (std::cos(phi) * g.u + std::sin(phi) * g.v);
      EXPECT_NEAR((cell.direction - d).norm(), 0.0, 1e-9);
      planning::Trajectory t;
      t.entry = g.pivot;
      t.target = g.pivot + (c - g.pivot).dot(d) * d;
      const planning::TrajectoryEvaluation e = evaluator.evaluate(t);
      ASSERT_FALSE(e.values.empty());
      const std::string& at_entry = e.values.front().safety_class;
      const planning::NeedleSafety expected =
          e.line_integral > s.eps || at_entry == "dangerous" ? planning::NeedleSafety::kDangerous
          : e.leaves_scan()                                   ? planning::NeedleSafety::kUnknown
          : at_entry == "medium"                              ? planning::NeedleSafety::kMedium
                                                              : planning::NeedleSafety::kSafe;
      EXPECT_EQ(cell.safety, expected)
          << "ring " << ring << " sector " << sector << ": line integral " << e.line_integral
          << ", at entry " << at_entry;
      seen.insert(cell.safety);
    }
  }
  // Both sides of the vessel are among them: the map can tell which way to tilt.
  EXPECT_TRUE(seen.count(planning::NeedleSafety::kSafe));
  EXPECT_TRUE(seen.count(planning::NeedleSafety::kDangerous));
}

// The anatomy layers' pictures (cones, entry patches, tumor) are drawn once for a still patient
// board and shown again: the same pixels as an overlay that draws them anew every frame. A board
// moved by 1 mm (about 2 px at 300 mm) draws them anew where they now lie, the same as drawn anew;
// a move of 1 um (far below the quarter pixel allowed) keeps them; another palette redraws them.
TEST_F(GuidanceTest, AnatomyPicturesAreKeptForAStillBoardAndRedrawnWhenItMoves) {
  auto renderer = make_renderer(test_camera());
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context on this machine";
  GuidanceSetup setup;
  setup.camera = test_camera();
  setup.T_ct_patient = T_ct_patient();
  GuidanceOptions options;
  options.ray_directions = 1500;
  GuidanceOverlay kept(*plan_, setup, options);
  options.anatomy_reuse_px = 0;
  GuidanceOverlay fresh(*plan_, setup, options);
  ASSERT_FALSE(kept.entry_patches().empty());
  const auto image = [&](GuidanceOverlay& o, const tracking::TrackResult& t) {
    o.update(*renderer, grey_frame(), t, {});
    return renderer->render();
  };
  const tracking::TrackResult still = track(std::nullopt);
  const cv::Mat first = image(kept, still);
  EXPECT_EQ(kept.anatomy_pictures_drawn(), 1);
  EXPECT_EQ(cv::norm(image(kept, still), first, cv::NORM_INF), 0);
  EXPECT_EQ(kept.anatomy_pictures_drawn(), 1) << "a still board: the pictures are kept";
  EXPECT_EQ(cv::norm(image(fresh, still), first, cv::NORM_INF), 0);
  EXPECT_EQ(cv::norm(image(fresh, still), first, cv::NORM_INF), 0);
  EXPECT_EQ(fresh.anatomy_pictures_drawn(), 2) << "no reuse: drawn every frame";

  tracking::TrackResult moved = still;
  moved.boards[0].T_cam_board.translation() += Eigen::Vector3d(1.0, 0.0, 0.0);
  const cv::Mat after = image(kept, moved);
  EXPECT_EQ(kept.anatomy_pictures_drawn(), 2) << "a moved board: drawn anew";
  EXPECT_GT(cv::norm(after, first, cv::NORM_INF), 0);
  EXPECT_EQ(cv::norm(image(fresh, moved), after, cv::NORM_INF), 0);

  tracking::TrackResult nudged = moved;
  nudged.boards[0].T_cam_board.translation() += Eigen::Vector3d(0.001, 0.0, 0.0);
  EXPECT_EQ(cv::norm(image(kept, nudged), after, cv::NORM_INF), 0);
  EXPECT_EQ(kept.anatomy_pictures_drawn(), 2) << "1 um: within the tolerance";

  kept.set_palette(planning::Palette::kColorblind);
  fresh.set_palette(planning::Palette::kColorblind);
  const cv::Mat colourblind = image(kept, nudged);
  EXPECT_EQ(kept.anatomy_pictures_drawn(), 3) << "another palette: drawn anew";
  EXPECT_EQ(cv::norm(image(fresh, nudged), colourblind, cv::NORM_INF), 0);
}

// A board that moves a little (more than the still-board tolerance, too little for parallax to
// matter) gets the kept pictures placed by an affine map at once, close to pictures drawn for its
// pose; the pictures for that pose, drawn meanwhile, are shown from the next frame on, pixel for
// pixel as an overlay that never keeps anything draws them.
TEST_F(GuidanceTest, SlightlyMovedBoardShowsPlacedPicturesThenThoseDrawnAhead) {
  auto renderer = make_renderer(test_camera());
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context on this machine";
  GuidanceSetup setup;
  setup.camera = test_camera();
  setup.T_ct_patient = T_ct_patient();
  GuidanceOptions options;
  options.ray_directions = 1500;
  GuidanceOverlay kept(*plan_, setup, options);
  options.anatomy_reuse_px = 0;
  GuidanceOverlay fresh(*plan_, setup, options);
  const auto image = [&](GuidanceOverlay& o, const tracking::TrackResult& t) {
    o.update(*renderer, grey_frame(), t, {});
    return renderer->render();
  };
  const tracking::TrackResult still = track(std::nullopt);
  const cv::Mat first = image(kept, still);
  EXPECT_EQ(kept.anatomy_pictures_waited(), 1);

  tracking::TrackResult moved = still;
  moved.boards[0].T_cam_board.translation() += Eigen::Vector3d(0.3, -0.2, 0.0);
  const cv::Mat placed = image(kept, moved);
  EXPECT_EQ(kept.anatomy_pictures_warped(), 1) << "placed, not drawn";
  EXPECT_EQ(kept.anatomy_pictures_waited(), 1) << "the frame did not wait for a drawing";
  const cv::Mat truth = image(fresh, moved);
  // Where the anatomy lies: the centroid of each picture's difference from the grey frame, below
  // the status panels. The placed pictures sit where the truth is; the old ones do not.
  const cv::Mat grey = grey_frame().image;
  const auto centroid = [&](const cv::Mat& img) {
    const cv::Rect below(0, 110, img.cols, img.rows - 110);
    cv::Mat d;
    cv::absdiff(img(below), grey(below), d);
    cv::Mat w;
    cv::transform(d, w, cv::Matx13f(1, 1, 1));
    const cv::Moments m = cv::moments(w);
    return Eigen::Vector2d(m.m10 / m.m00, m.m01 / m.m00 + below.y);
  };
  const double placed_off = (centroid(placed) - centroid(truth)).norm();
  const double stale_off = (centroid(first) - centroid(truth)).norm();
  EXPECT_GT(stale_off, 0.2);
  EXPECT_LT(placed_off, 0.25 * stale_off) << placed_off << " px vs " << stale_off << " px";
  // The warp is taken only when its largest error at the anatomy's points is within a quarter
  // pixel (docs/ARCHITECTURE.md §7): the placed pictures' centroid lies within that of the truth.
  EXPECT_LT(placed_off, 0.25);
  std::printf("anatomy centroid off by %.3f px placed, %.3f px stale\n", placed_off, stale_off);

  // The next frame shows the pictures drawn for this pose meanwhile: exactly the fresh ones.
  EXPECT_EQ(cv::norm(image(kept, moved), truth, cv::NORM_INF), 0);
  EXPECT_EQ(kept.anatomy_pictures_warped(), 1);
  EXPECT_EQ(kept.anatomy_pictures_waited(), 1);

  // A jump no map can follow (parallax over the anatomy's depth) is drawn then and there.
  tracking::TrackResult jumped = moved;
  jumped.boards[0].T_cam_board.translation() += Eigen::Vector3d(40.0, 0.0, 0.0);
  EXPECT_EQ(cv::norm(image(kept, jumped), image(fresh, jumped), cv::NORM_INF), 0);
  EXPECT_EQ(kept.anatomy_pictures_waited(), 2);
}

// The targeting view's polar map is computed once for a still needle and kept; a needle moved to
// another approach gets the map of its new line at once (the same cells as targeting_geometry
// gives for it, different from the old ones): the old map is never shown for the moved needle.
TEST_F(GuidanceTest, MovedNeedleUpdatesThePolarMapAndAStillOneKeepsIt) {
  auto renderer = make_renderer(test_camera());
  if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context on this machine";
  GuidanceSetup setup;
  setup.camera = test_camera();
  setup.T_ct_patient = T_ct_patient();
  GuidanceOptions options;
  options.ray_directions = 1500;
  GuidanceOverlay o(*plan_, setup, options);
  const Eigen::Vector3d c = plan_->tumor_centre;
  // From the -x side (clear) and from the +x side, through the vessel at x = 16 mm.
  const auto needle_from = [&](double azimuth_deg) {
    const double az = azimuth_deg * M_PI / 180.0;
    const Eigen::Vector3d out(std::cos(az), std::sin(az), 0.0);
    return T_ct_needle_for(c + 60.0 * out, -out);
  };
  const auto expected_cells = [&](const Eigen::Isometry3d& T_ct_needle) {
    const planning::NeedleState s =
        o.needle_guide().evaluate(T_ct_needle, setup.tip_in_needle, setup.axis_in_needle);
    planning::TargetingOptions to = options.targeting;
    to.size_px = 240;  // half the 480 px image's height
    to.right_hint = T_ct_cam().linear().col(0);
    return planning::targeting_geometry(o.needle_guide(), s, o.tumor_surface(), 2.0, to).cells;
  };
  const auto same_cells = [](const std::vector<planning::PolarCell>& a,
                             const std::vector<planning::PolarCell>& b) {
    if (a.size() != b.size()) return false;
    for (size_t i = 0; i < a.size(); ++i) {
      if (a[i].safety != b[i].safety || (a[i].direction - b[i].direction).norm() > 1e-12) {
        return false;
      }
    }
    return true;
  };
  o.update(*renderer, grey_frame(), track(needle_from(180.0)), {});
  EXPECT_EQ(o.targeting_maps_computed(), 1);
  const std::vector<planning::PolarCell> clear = o.last_targeting().cells;
  EXPECT_TRUE(same_cells(clear, expected_cells(needle_from(180.0))));
  o.update(*renderer, grey_frame(), track(needle_from(180.0)), {});
  EXPECT_EQ(o.targeting_maps_computed(), 1) << "a still needle: the map is kept";

  o.update(*renderer, grey_frame(), track(needle_from(0.0)), {});
  EXPECT_EQ(o.targeting_maps_computed(), 2) << "a moved needle: the map is computed anew";
  const std::vector<planning::PolarCell>& through = o.last_targeting().cells;
  EXPECT_TRUE(same_cells(through, expected_cells(needle_from(0.0))));
  int changed = 0;
  for (size_t i = 0; i < clear.size() && i < through.size(); ++i) {
    changed += clear[i].safety != through[i].safety;
  }
  EXPECT_GT(changed, 0) << "the two approaches must differ for this test to mean anything";
}

TEST(GuidanceLayers, NamesParseBothWays) {
  for (int i = 0; i < kGuidanceLayerCount; ++i) {
    const auto layer = static_cast<GuidanceLayer>(i);
    EXPECT_EQ(parse_guidance_layer(guidance_layer_name(layer)), layer);
    EXPECT_EQ(parse_guidance_layer(std::to_string(i + 1)), layer);
  }
  EXPECT_THROW(parse_guidance_layer("bones"), Error);
}

}  // namespace
}  // namespace crepuscular::overlay
