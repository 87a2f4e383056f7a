// The demo's guidance scenario on a coarse phantom plan, checked against independent truth: the
// registration puts the board's fiducials on the skin of the label map; the safe line is clear by
// a separate TrajectoryEvaluator and crosses no vessel voxel, the dangerous line crosses vessel
// voxels (brute-force sampling of the label map); the needle tip of every keyframe, composed from
// the scene's poses, lies on the scripted lines; every tag corner projects (cv::projectPoints)
// inside the image with the boards apart; the written calibration files read back equal.
#include "pipelines/demo_scenario.hpp"
#include "pipelines/registration.hpp"

#include <gtest/gtest.h>

#include <array>
#include <chrono>
#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <iostream>

#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "calibration/camera_model.hpp"
#include "calibration/registration.hpp"
#include "foundation/error.hpp"
#include "planning/trajectories/needle_guidance.hpp"
#include "planning/simulation/phantom.hpp"
#include "pipelines/plan.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/plans.hpp"
#include "tests/support/temporary_folder.hpp"
#include "tracking/board.hpp"
#include "tracking/tracker.hpp"

#include <spdlog/spdlog.h>

namespace fs = std::filesystem;

namespace crepuscular::pipelines {
namespace {

class GuidanceSceneTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new test::TemporaryFolder;
    planning::PhantomOptions po;
    po.spacing_mm = 4.0;
    const planning::Phantom ph = planning::make_phantom(po);
    planning::write_phantom(ph, (*dir_ / "phantom").string());
    // Vessel label values of the phantom's own table (by name, independent of the code under test).
    vessel_labels_ = new std::vector<int>();
    for (const auto& l : ph.vulnerability["labels"]) {
      const std::string name = l["name"].get<std::string>();
      for (const char* w : {"vessel", "vein", "artery", "aorta", "cava", "portal"}) {
        if (name.find(w) != std::string::npos) {
          vessel_labels_->push_back(l["value"].get<int>());
          break;
        }
      }
    }
    const PlanRequest r =
        test::phantom_plan_request(*dir_ / "phantom", (*dir_ / "plan").string());
    run_plan(r);
    if (std::getenv("GS_DEBUG")) spdlog::set_level(spdlog::level::debug);
    plan_ = new planning::PlanData(planning::load_plan(r.out_dir));
    scenario_ = new GuidanceScenario(make_guidance_scenario(*plan_));
  }
  static void TearDownTestSuite() {
    delete scenario_;
    delete plan_;
    delete vessel_labels_;
    delete dir_;
  }

  static int label_at(const Eigen::Vector3d& p) {
    const planning::Volume<int32_t>& L = plan_->labels;
    const Eigen::Vector3d idx = L.physical_to_index(p);
    const int64_t i = std::llround(idx.x()), j = std::llround(idx.y()), k = std::llround(idx.z());
    if (!L.geometry().contains(i, j, k)) return 0;
    return L(i, j, k);
  }
  static bool is_vessel_label(int v) {
    return std::find(vessel_labels_->begin(), vessel_labels_->end(), v) != vessel_labels_->end();
  }
  // Length (mm) of the segment a -> b inside vessel voxels, sampled every 0.1 mm.
  static double vessel_length(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
    const double len = (b - a).norm();
    const int n = int(std::ceil(len / 0.1));
    int hits = 0;
    for (int s = 0; s <= n; ++s) {
      if (is_vessel_label(label_at(a + (b - a) * (double(s) / n)))) ++hits;
    }
    return hits * len / n;
  }
  static const tracking::SceneBoard& board(const std::string& name) {
    for (const tracking::SceneBoard& b : scenario_->scene.boards) {
      if (b.board.name == name) return b;
    }
    throw std::runtime_error("no board " + name);
  }

  static test::TemporaryFolder* dir_;
  static planning::PlanData* plan_;
  static GuidanceScenario* scenario_;
  static std::vector<int>* vessel_labels_;
};
test::TemporaryFolder* GuidanceSceneTest::dir_ = nullptr;
planning::PlanData* GuidanceSceneTest::plan_ = nullptr;
GuidanceScenario* GuidanceSceneTest::scenario_ = nullptr;
std::vector<int>* GuidanceSceneTest::vessel_labels_ = nullptr;

TEST_F(GuidanceSceneTest, RegistrationPutsTheBoardFlatOnTheSkinBesideTheEntries) {
  const GuidanceScenario& sc = *scenario_;
  const Eigen::Isometry3d& T = sc.T_ct_patient;
  EXPECT_NEAR(T.linear().determinant(), 1.0, 1e-9);
  EXPECT_LT((T.linear().transpose() * T.linear() - Eigen::Matrix3d::Identity()).norm(), 1e-9);
  // The board's z axis points into the body (posterior, +y LPS).
  EXPECT_GT(T.linear().col(2).y(), 0.7);
  const tracking::Board& b = board("patient").board;
  ASSERT_GE(b.fiducials.size(), 4u);
  // Every fiducial on the skin: within 3 mm both outside (label 0) and body (label > 0) voxels.
  for (const Eigen::Vector3d& f : b.fiducials) {
    const Eigen::Vector3d p = T * f;
    bool outside = false, inside = false;
    for (double dx = -3; dx <= 3; dx += 0.5) {
      for (double dy = -3; dy <= 3; dy += 0.5) {
        for (double dz = -3; dz <= 3; dz += 0.5) {
          if (dx * dx + dy * dy + dz * dz > 9.0) continue;
          (label_at(p + Eigen::Vector3d(dx, dy, dz)) > 0 ? inside : outside) = true;
        }
      }
    }
    EXPECT_TRUE(outside && inside) << "fiducial " << f.transpose() << " at CT " << p.transpose();
  }
  // No two pairwise fiducial distances alike (a layout the registration can tell apart).
  std::vector<double> d;
  for (size_t i = 0; i < b.fiducials.size(); ++i) {
    for (size_t j = i + 1; j < b.fiducials.size(); ++j) {
      d.push_back((b.fiducials[i] - b.fiducials[j]).norm());
    }
  }
  std::sort(d.begin(), d.end());
  for (size_t i = 1; i < d.size(); ++i) EXPECT_GT(d[i] - d[i - 1], 2.0);
  // The registration of the calibration module finds the board from the CT beads (given in
  // reverse order, pairs unknown) and agrees with the scenario's T_ct_patient.
  std::vector<Eigen::Vector3d> ct;
  for (auto it = b.fiducials.rbegin(); it != b.fiducials.rend(); ++it) ct.push_back(T * *it);
  const calibration::RegistrationResult reg = calibration::register_fiducials(b.fiducials, ct);
  EXPECT_EQ(reg.matched, int(b.fiducials.size()));
  EXPECT_LT((reg.T_ct_patient.matrix() - T.matrix()).norm(), 1e-6);
  // Not under the needle: both entries lie beyond the plate (+-85 x +-60 mm) by 20 mm.
  for (const GuidanceApproach* a : {&sc.safe, &sc.dangerous}) {
    const Eigen::Vector3d q = T.inverse() * a->entry_ct;
    EXPECT_TRUE(std::abs(q.x()) > 105 || std::abs(q.y()) > 80) << a->name << " " << q.transpose();
  }
}

TEST_F(GuidanceSceneTest, SafeLineIsClearAndDangerousLineCrossesAVessel) {
  const GuidanceScenario& sc = *scenario_;
  ASSERT_FALSE(vessel_labels_->empty());
  EXPECT_LT((sc.target_ct - plan_->tumor_centre).norm(), 1e-9);
  planning::TrajectoryEvaluator evaluator(*plan_);
  for (const GuidanceApproach* a : {&sc.safe, &sc.dangerous}) {
    // The direction points from the entry at the centroid; the entry is where the body starts.
    EXPECT_NEAR(a->direction_ct.norm(), 1.0, 1e-12);
    EXPECT_LT(((sc.target_ct - a->entry_ct).normalized() - a->direction_ct).norm(), 1e-9);
    EXPECT_EQ(label_at(a->entry_ct), 0) << a->name;
    EXPECT_GT(label_at(a->entry_ct + 0.01 * a->direction_ct), 0) << a->name;
    for (double s = 1.0; s < 400; s += 0.5) {  // nothing but air further out
      ASSERT_EQ(label_at(a->entry_ct - s * a->direction_ct), 0) << a->name << " at " << s;
    }
    // Outward within 50 degrees of anterior.
    EXPECT_LT(std::acos(-a->direction_ct.dot(-Eigen::Vector3d::UnitY())) * 180 / M_PI, 50.0 + 1e-9);
  }
  planning::Trajectory t;
  t.entry = sc.safe.entry_ct;
  t.target = sc.target_ct;
  const planning::TrajectoryEvaluation safe = evaluator.evaluate(t);
  EXPECT_LE(safe.line_integral, 0.5);
  EXPECT_NEAR(safe.line_integral, sc.safe.state.evaluation.line_integral, 1e-9);
  EXPECT_TRUE(sc.safe.state.clear);
  EXPECT_EQ(sc.safe.state.tip_class, "safe");
  EXPECT_EQ(sc.safe.state.safety, planning::NeedleSafety::kSafe);
  EXPECT_EQ(vessel_length(sc.safe.entry_ct, sc.target_ct), 0.0);

  t.entry = sc.dangerous.entry_ct;
  const planning::TrajectoryEvaluation danger = evaluator.evaluate(t);
  EXPECT_GT(danger.line_integral, 0.5);
  EXPECT_EQ(sc.dangerous.state.safety, planning::NeedleSafety::kDangerous);
  const double len = vessel_length(sc.dangerous.entry_ct, sc.target_ct);
  EXPECT_GT(len, 1.0) << "the dangerous line must pass through vessel voxels";
  bool named = false;
  for (const planning::StructureHit& h : danger.structures) {
    if (is_vessel_label(h.label)) named = true;
  }
  EXPECT_TRUE(named);
  EXPECT_FALSE(sc.dangerous.vessels.empty());

  const double sep = std::acos(sc.safe.direction_ct.dot(sc.dangerous.direction_ct)) * 180 / M_PI;
  EXPECT_GE(sep, 15.0);
  EXPECT_LE(sep, 35.0);
  std::printf("safe: line integral %.3f, dangerous: %.3f, %.1f mm in vessels, %.1f deg apart\n",
              safe.line_integral, danger.line_integral, len, sep);
}

TEST_F(GuidanceSceneTest, NeedleTipOfEveryKeyframeLiesOnTheScriptedLine) {
  const GuidanceScenario& sc = *scenario_;
  const tracking::SceneBoard& patient = board("patient");
  const tracking::SceneBoard& needle = board("needle");
  ASSERT_EQ(int64_t(needle.keyframes.size()), sc.scene.frame_count);
  EXPECT_LT(sc.safe.end_s, sc.dangerous.start_s);
  int on_safe = 0, on_danger = 0;
  double deepest_safe = 1e9, deepest_danger = 1e9;
  for (const tracking::PoseKeyframe& k : needle.keyframes) {
    const double t = k.time_s;
    const Eigen::Isometry3d T_ct_needle =
        sc.T_ct_patient * tracking::pose_at(patient, t).inverse() * k.T_cam_board;
    const Eigen::Vector3d tip = T_ct_needle * tracking::kNeedleTipInNeedle;
    const Eigen::Vector3d axis = T_ct_needle.linear().col(2);
    EXPECT_LT((sc.T_ct_needle_at(t).matrix() - T_ct_needle.matrix()).norm(), 1e-9);
    for (const GuidanceApproach* a : {&sc.safe, &sc.dangerous}) {
      if (t < a->start_s - 1e-9 || t > a->end_s + 1e-9) continue;
      const Eigen::Vector3d w = tip - a->entry_ct;
      EXPECT_LT((w - w.dot(a->direction_ct) * a->direction_ct).norm(), 1e-6) << a->name << " " << t;
      EXPECT_GT(axis.dot(a->direction_ct), 1.0 - 1e-9);
      // From 60 mm outside the entry to 10 mm short of the centroid.
      const double to_target = (sc.target_ct - tip).norm();
      EXPECT_GE(w.dot(a->direction_ct), -60.0 - 1e-6);
      EXPECT_GE(to_target, 10.0 - 1e-6);
      (a == &sc.safe ? on_safe : on_danger)++;
      (a == &sc.safe ? deepest_safe : deepest_danger) =
          std::min(a == &sc.safe ? deepest_safe : deepest_danger, to_target);
    }
  }
  EXPECT_GE(on_safe, int(sc.scene.fps * 2.0));
  EXPECT_GE(on_danger, int(sc.scene.fps * 2.0));
  EXPECT_NEAR(deepest_safe, 10.0, 1e-6);
  EXPECT_NEAR(deepest_danger, 10.0, 1e-6);
  // The start of each approach: 60 mm outside the entry.
  for (const GuidanceApproach* a : {&sc.safe, &sc.dangerous}) {
    const Eigen::Vector3d tip = sc.T_ct_needle_at(a->start_s) * tracking::kNeedleTipInNeedle;
    EXPECT_LT((tip - (a->entry_ct - 60.0 * a->direction_ct)).norm(), 1e-6) << a->name;
  }
}

// What guide will show: the needle of the scene, evaluated with the plan while its tip is still
// outside the body, is safe all along the safe approach and dangerous all along the dangerous one.
TEST_F(GuidanceSceneTest, NeedleIsSafeOnTheSafeApproachAndDangerousOnTheOther) {
  const GuidanceScenario& sc = *scenario_;
  const planning::NeedleGuide guide(*plan_);
  int safe_frames = 0, danger_frames = 0;
  for (int64_t f = 0; f < sc.scene.frame_count; ++f) {
    const double t = double(f) / sc.scene.fps;
    const Eigen::Isometry3d T = sc.T_ct_needle_at(t);
    if (label_at(T * tracking::kNeedleTipInNeedle) > 0) continue;  // tip in the body
    const planning::NeedleState s =
        guide.evaluate(T, tracking::kNeedleTipInNeedle, Eigen::Vector3d::UnitZ());
    if (t >= sc.safe.start_s && t <= sc.safe.end_s) {
      EXPECT_EQ(s.safety, planning::NeedleSafety::kSafe) << "t " << t;
      EXPECT_NEAR(s.miss_distance_mm, 0.0, 1e-6);
      ++safe_frames;
    }
    if (t >= sc.dangerous.start_s && t <= sc.dangerous.end_s) {
      EXPECT_EQ(s.safety, planning::NeedleSafety::kDangerous) << "t " << t;
      EXPECT_FALSE(s.clear);
      ++danger_frames;
    }
  }
  EXPECT_GE(safe_frames, 10);
  EXPECT_GE(danger_frames, 10);
}

TEST_F(GuidanceSceneTest, AllTagsStayInsideTheImageAndTheBoardsApart) {
  const GuidanceScenario& sc = *scenario_;
  const calibration::CameraModel& cam = sc.scene.camera;
  const calibration::CameraModel builtin = tracking::builtin_scene().camera;
  EXPECT_EQ(cam.fx, builtin.fx);
  EXPECT_EQ(cam.cx, builtin.cx);
  EXPECT_EQ(cam.distortion, builtin.distortion);
  const cv::Mat K = cam.camera_matrix(), dist = cam.distortion_coefficients();
  double near_mm = 1e9, far_mm = 0;
  for (int64_t f = 0; f < sc.scene.frame_count; ++f) {
    const double t = double(f) / sc.scene.fps;
    std::vector<std::vector<cv::Point2f>> hulls;
    for (const tracking::SceneBoard& b : sc.scene.boards) {
      const Eigen::Isometry3d T = tracking::pose_at(b, t);
      if (b.board.name == "patient") {
        near_mm = std::min(near_mm, T.translation().norm());
        far_mm = std::max(far_mm, T.translation().norm());
      }
      // Tags face the camera.
      EXPECT_GT(T.linear()(2, 2), 0.3) << b.board.name << " frame " << f;
      std::vector<cv::Point3d> corners;
      for (const tracking::BoardTag& tag : b.board.tags) {
        for (const Eigen::Vector3d& c : tag.corners) {
          const Eigen::Vector3d p = T * c;
          corners.emplace_back(p.x(), p.y(), p.z());
        }
      }
      std::vector<cv::Point2d> px;
      cv::projectPoints(corners, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), K, dist, px);
      std::vector<cv::Point2f> pf;
      for (const cv::Point2d& p : px) {
        EXPECT_TRUE(p.x >= 0 && p.y >= 0 && p.x <= cam.width - 1 && p.y <= cam.height - 1)
            << b.board.name << " frame " << f << " corner " << p;
        pf.emplace_back(float(p.x), float(p.y));
      }
      std::vector<cv::Point2f> hull;
      cv::convexHull(pf, hull);
      hulls.push_back(hull);
    }
    ASSERT_EQ(hulls.size(), 2u);
    std::vector<cv::Point2f> inter;
    EXPECT_EQ(cv::intersectConvexConvex(hulls[0], hulls[1], inter, true), 0.0f) << "frame " << f;
  }
  EXPECT_GE(near_mm, 490.0);
  EXPECT_LE(far_mm, 590.0);
  std::printf("patient board %.0f to %.0f mm from the camera\n", near_mm, far_mm);
}

// Rendered frames of the scene are trackable: the project's tracker (AprilTag detection and board
// pose, no smoothing) sees both boards in frames of each approach and of the swing between them,
// and the needle tip it implies in CT lies within 3 mm of the scripted tip (the tip is 150 mm from
// a 46 mm board: 0.5 degree of board rotation error moves it 1.3 mm; measured 0.2 to 1.9 mm).
TEST_F(GuidanceSceneTest, RenderedFramesTrackBothBoardsAndPlaceTheTip) {
  const GuidanceScenario& sc = *scenario_;
  tracking::SyntheticRenderer renderer(sc.scene);
  std::vector<tracking::Board> boards;
  for (const tracking::SceneBoard& b : sc.scene.boards) boards.push_back(b.board);
  tracking::TrackerOptions options;
  options.smoothing = false;
  const double fps = sc.scene.fps;
  const std::vector<int64_t> frames = {
      int64_t(std::lround(sc.safe.start_s * fps)), int64_t(std::lround(sc.safe.end_s * fps)),
      int64_t(std::lround(0.5 * (sc.safe.end_s + sc.dangerous.start_s) * fps)),
      int64_t(std::lround(sc.dangerous.start_s * fps)),
      int64_t(std::lround(sc.dangerous.end_s * fps))};
  for (int64_t f : frames) {
    tracking::Tracker tracker(sc.scene.camera, boards, options);  // fresh: a full-frame search
    tracking::Frame frame;
    frame.index = f;
    frame.timestamp_ns = renderer.timestamp_ns_of(f);
    frame.image = renderer.render(f);
    if (const char* png_dir = std::getenv("GS_PNG_DIR")) {
      cv::imwrite(std::string(png_dir) + "/frame_" + std::to_string(f) + ".png", frame.image);
    }
    const tracking::TrackResult r = tracker.process(frame);
    ASSERT_EQ(r.boards.size(), 2u);
    for (const tracking::BoardStatus& b : r.boards) {
      EXPECT_TRUE(b.measured) << b.board << " frame " << f << ": " << b.problem;
    }
    if (!r.boards[0].measured || !r.boards[1].measured) continue;
    EXPECT_EQ(r.boards[0].tags, 6) << "frame " << f;
    EXPECT_EQ(r.boards[1].tags, 4) << "frame " << f;
    const Eigen::Vector3d tracked = sc.T_ct_patient * r.boards[0].T_measured.inverse() *
                                    r.boards[1].T_measured * tracking::kNeedleTipInNeedle;
    const Eigen::Vector3d truth = sc.T_ct_needle_at(double(f) / fps) * tracking::kNeedleTipInNeedle;
    EXPECT_LT((tracked - truth).norm(), 3.0) << "frame " << f;
    std::printf("frame %lld: tracked tip %.2f mm from the truth\n", static_cast<long long>(f),
                (tracked - truth).norm());
  }
}

// The camera is where an OR camera would be: above the patient (anterior) and to one side, 40 to
// 70 cm from the patient board and the entries in every frame, and it sees each needle from the
// side: in every frame of an approach the needle's axis (the needle board's z) makes 30 degrees
// or more with the ray from the camera to the skin entry, so the needle is a line, not a dot.
TEST_F(GuidanceSceneTest, CameraAboveAndBesideSeesBothNeedlesObliquely) {
  const GuidanceScenario& sc = *scenario_;
  const Eigen::Vector3d cam_ct = sc.T_cam_ct_nominal.inverse().translation();
  const Eigen::Vector3d mid = 0.5 * (sc.safe.entry_ct + sc.dangerous.entry_ct);
  EXPECT_LT(cam_ct.y(), mid.y() - 250.0) << "camera above (anterior of) the entries";
  const double side_mm = std::abs(cam_ct.x() - mid.x());
  EXPECT_GT(side_mm, 150.0) << "camera to one side of the entries";
  const double fps = sc.scene.fps;
  double near_mm = 1e9, far_mm = 0;
  for (const GuidanceApproach* a : {&sc.safe, &sc.dangerous}) {
    double min_deg = 180;
    for (int64_t f = 0; f < sc.scene.frame_count; ++f) {
      const double t = double(f) / fps;
      const Eigen::Isometry3d T_cam_patient = tracking::pose_at(board("patient"), t);
      const Eigen::Vector3d entry = T_cam_patient * (sc.T_ct_patient.inverse() * a->entry_ct);
      near_mm = std::min({near_mm, entry.norm(), T_cam_patient.translation().norm()});
      far_mm = std::max({far_mm, entry.norm(), T_cam_patient.translation().norm()});
      if (t < a->start_s || t > a->end_s) continue;
      const Eigen::Vector3d axis = tracking::pose_at(board("needle"), t).linear().col(2);
      const double deg =
          std::acos(std::clamp(axis.dot(entry.normalized()), -1.0, 1.0)) * 180.0 / M_PI;
      min_deg = std::min(min_deg, deg);
    }
    EXPECT_GE(min_deg, 30.0) << a->name;
    EXPECT_NEAR(a->view_obliquity_deg, min_deg, 1e-6) << a->name;
    std::printf("%s needle: at least %.1f deg from its viewing ray\n", a->name.c_str(), min_deg);
  }
  EXPECT_GE(near_mm, 400.0);
  EXPECT_LE(far_mm, 700.0);
  std::printf("camera %.0f mm to the side, %.0f to %.0f mm from the board and the entries\n",
              side_mm, near_mm, far_mm);
}

// The body in the frames: rendered alone (boards without tags or plates, a black background), it
// covers exactly the pixels onto which its mesh projects, computed independently (vertices through
// cv::projectPoints, each triangle filled with cv::fillConvexPoly): every projected pixel 2 px
// inside the outline is covered and none 2 px outside it. Both entries lie on visible skin: the
// pixel they project to shows skin colour and the rendered depth there is the entry's own.
TEST_F(GuidanceSceneTest, RenderedBodyCoversItsProjectedMeshAndShowsTheEntriesOnSkin) {
  const GuidanceScenario& sc = *scenario_;
  tracking::SyntheticScene alone = sc.scene;
  for (tracking::SceneBoard& b : alone.boards) {
    b.board.tags.clear();
    b.plate = false;
  }
  alone.meshes.erase(std::remove_if(alone.meshes.begin(), alone.meshes.end(),
                                    [](const tracking::SceneMesh& m) { return m.name != "body"; }),
                     alone.meshes.end());
  alone.background = "plain";
  alone.background_grey = 0;
  alone.noise_sigma = 0;
  const tracking::SceneMesh* body = nullptr;
  for (const tracking::SceneMesh& m : alone.meshes) {
    if (m.name == "body") body = &m;
  }
  ASSERT_NE(body, nullptr);
  EXPECT_EQ(body->board, "patient");
  const tracking::SyntheticRenderer renderer(alone);
  const calibration::CameraModel& cam = alone.camera;
  const cv::Mat K = cam.camera_matrix(), dist = cam.distortion_coefficients();
  const double fps = alone.fps;
  for (const GuidanceApproach* a : {&sc.safe, &sc.dangerous}) {
    const int64_t f = int64_t(std::lround(a->end_s * fps));
    const double t = double(f) / fps;
    const auto t0 = std::chrono::steady_clock::now();
    const cv::Mat image = renderer.render(f);
    const double ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    cv::Mat depth;
    renderer.render_meshes(f, nullptr, &depth);
    std::vector<cv::Mat> ch;
    cv::split(image, ch);
    const cv::Mat covered = cv::max(cv::max(ch[0], ch[1]), ch[2]) > 15;

    // Independent truth: the projected triangles of the body mesh.
    const Eigen::Isometry3d T_cam_patient = tracking::pose_at(board("patient"), t);
    std::vector<cv::Point3d> cam_points;
    for (const Eigen::Vector3f& v : body->vertices) {
      const Eigen::Vector3d p = T_cam_patient * v.cast<double>();
      ASSERT_GT(p.z(), 10.0);
      cam_points.emplace_back(p.x(), p.y(), p.z());
    }
    std::vector<cv::Point2d> px;
    cv::projectPoints(cam_points, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), K, dist, px);
    cv::Mat truth(cam.height, cam.width, CV_8U, cv::Scalar(0));
    constexpr int kShift = 8;  // sub-pixel vertices for fillConvexPoly
    for (const Eigen::Vector3i& tri : body->triangles) {
      std::array<cv::Point, 3> pts;
      bool far_out = false;
      for (int i = 0; i < 3; ++i) {
        const cv::Point2d& q = px[size_t(tri[i])];
        far_out = far_out || std::abs(q.x) > 1e5 || std::abs(q.y) > 1e5;
        pts[size_t(i)] = cv::Point(int(std::lround(q.x * (1 << kShift))),
                                   int(std::lround(q.y * (1 << kShift))));
      }
      if (!far_out) cv::fillConvexPoly(truth, pts.data(), 3, cv::Scalar(255), cv::LINE_8, kShift);
    }
    const cv::Mat k5 = cv::getStructuringElement(cv::MORPH_RECT, cv::Size(5, 5));
    cv::Mat inner, outer;
    cv::erode(truth, inner, k5, cv::Point(-1, -1), 1, cv::BORDER_REPLICATE);
    cv::dilate(truth, outer, k5, cv::Point(-1, -1), 1, cv::BORDER_REPLICATE);
    const int n_truth = cv::countNonZero(truth);
    const int missed = cv::countNonZero(inner & ~covered);
    const int spilled = cv::countNonZero(covered & ~outer);
    EXPECT_GT(n_truth, cam.width * cam.height / 4) << "the body fills a good part of the frame";
    EXPECT_EQ(missed, 0) << a->name << " frame " << f;
    EXPECT_EQ(spilled, 0) << a->name << " frame " << f;
    std::printf("%s frame %lld: body mesh projects onto %d px, %d missed, %d outside; rendered "
                "in %.0f ms\n",
                a->name.c_str(), static_cast<long long>(f), n_truth, missed, spilled, ms);

    // Both entries on visible skin.
    for (const GuidanceApproach* e : {&sc.safe, &sc.dangerous}) {
      const Eigen::Vector3d p = T_cam_patient * sc.T_ct_patient.inverse() * e->entry_ct;
      const Eigen::Vector2d uv = cam.project(p);
      const int x = int(std::lround(uv.x())), y = int(std::lround(uv.y()));
      ASSERT_TRUE(x >= 2 && y >= 2 && x < cam.width - 2 && y < cam.height - 2)
          << e->name << " entry outside the image at " << uv.transpose();
      const cv::Vec3b c = image.at<cv::Vec3b>(y, x);
      // Skin (BGR 140, 165, 215 shaded): red above green above blue.
      EXPECT_GT(int(c[2]), int(c[1]) + 10) << e->name << " entry pixel " << cv::Mat(c);
      EXPECT_GT(int(c[1]), int(c[0]) + 5) << e->name << " entry pixel " << cv::Mat(c);
      EXPECT_NEAR(depth.at<float>(y, x), p.z(), 6.0) << e->name << " entry hidden or off the skin";
    }
  }
}

TEST_F(GuidanceSceneTest, UnusablePlanOrOptionsAreRefusedWithTheReason) {
  planning::PlanData no_labels = *plan_;
  no_labels.labels = planning::Volume<int32_t>();
  test::expect_error_containing([&] { make_guidance_scenario(no_labels); },
                                {"label map", plan_->dir});
  // No dangerous direction can be that close to the safe one: the message says what is missing.
  GuidanceScenarioOptions o;
  o.min_separation_deg = 0.1;
  o.max_separation_deg = 0.5;
  test::expect_error_containing([&] { make_guidance_scenario(*plan_, o); },
                                "no dangerous direction");
  o = GuidanceScenarioOptions();
  o.fps = 0;
  EXPECT_THROW(make_guidance_scenario(*plan_, o), Error);
}

// The demo performs the registration: beads painted where the board lies are found by
// `register` (pipelines/registration) and paired with the board's layout; the result is within
// 1 mm of the scenario's truth at the tumor.
TEST_F(GuidanceSceneTest, RegistrationFromBeadsInTheCtIsWithinAMillimetreAtTheTumor) {
  const fs::path ct = *dir_ / "phantom" / "ct_with_beads.nii.gz";
  fs::copy_file(*dir_ / "phantom" / "ct.nii.gz", ct, fs::copy_options::overwrite_existing);
  EXPECT_EQ(paint_board_beads(*scenario_, ct.string()), 5);
  write_guidance_setup(*scenario_, (*dir_ / "registration_setup").string());
  RegistrationRequest rr;
  rr.ct = ct.string();
  rr.boards = (*dir_ / "registration_setup" / "boards.json").string();
  rr.board_name = "patient";
  rr.target = scenario_->target_ct;
  rr.out = (*dir_ / "registration_setup" / "registration.yaml").string();
  const calibration::RegistrationRecord r = run_registration(rr);
  EXPECT_EQ(r.board_fiducials.size(), 5u);
  const Eigen::Vector3d c = scenario_->target_ct;
  const double error = (r.T_ct_patient * (scenario_->T_ct_patient.inverse() * c) - c).norm();
  EXPECT_LT(error, 1.0);
  EXPECT_LT(r.fre_rms_mm, 1.0);
  // The file guidance reads holds this registration, not the truth.
  const calibration::RegistrationRecord back = calibration::read_registration(rr.out);
  EXPECT_LT((back.T_ct_patient.matrix() - r.T_ct_patient.matrix()).cwiseAbs().maxCoeff(), 1e-9);
}

TEST_F(GuidanceSceneTest, WrittenSetupReadsBackEqual) {
  const GuidanceScenario& sc = *scenario_;
  const fs::path out = *dir_ / "setup";
  write_guidance_setup(sc, out.string());

  const calibration::CameraModel cam = calibration::CameraModel::read_yaml((out / "camera.yaml").string());
  EXPECT_EQ(cam.width, sc.scene.camera.width);
  EXPECT_EQ(cam.height, sc.scene.camera.height);
  EXPECT_NEAR(cam.fx, sc.scene.camera.fx, 1e-9);
  EXPECT_NEAR(cam.cy, sc.scene.camera.cy, 1e-9);
  for (int i = 0; i < 5; ++i) EXPECT_NEAR(cam.distortion[i], sc.scene.camera.distortion[i], 1e-12);

  const calibration::NeedleCalibration n =
      calibration::read_needle_calibration((out / "needle.yaml").string());
  EXPECT_EQ(n.board, "needle");
  EXPECT_LT((n.tip_needle - tracking::kNeedleTipInNeedle).norm(), 1e-9);
  ASSERT_TRUE(n.axis_needle.has_value());
  EXPECT_LT((*n.axis_needle - Eigen::Vector3d::UnitZ()).norm(), 1e-9);

  const calibration::RegistrationRecord r =
      calibration::read_registration((out / "registration.yaml").string());
  EXPECT_EQ(r.board, "patient");
  EXPECT_LT((r.T_ct_patient.matrix() - sc.T_ct_patient.matrix()).norm(), 1e-9);
  const tracking::Board& patient = board("patient").board;
  ASSERT_EQ(r.board_fiducials.size(), patient.fiducials.size());
  for (size_t i = 0; i < patient.fiducials.size(); ++i) {
    EXPECT_LT((r.board_fiducials[i] - patient.fiducials[i]).norm(), 1e-9);
    EXPECT_LT((r.ct_fiducials[i] - sc.T_ct_patient * patient.fiducials[i]).norm(), 1e-9);
  }

  const std::vector<tracking::Board> boards = tracking::read_boards((out / "boards.json").string());
  ASSERT_EQ(boards.size(), 2u);
  for (size_t b = 0; b < 2; ++b) {
    const tracking::Board& want = sc.scene.boards[b].board;
    EXPECT_EQ(boards[b].name, want.name);
    ASSERT_EQ(boards[b].tags.size(), want.tags.size());
    for (size_t i = 0; i < want.tags.size(); ++i) {
      EXPECT_EQ(boards[b].tags[i].id, want.tags[i].id);
      for (int c = 0; c < 4; ++c) {
        EXPECT_LT((boards[b].tags[i].corners[c] - want.tags[i].corners[c]).norm(), 1e-9);
      }
    }
    EXPECT_EQ(boards[b].fiducials.size(), want.fiducials.size());
  }
  EXPECT_EQ(boards[1].tags.front().id, 10);
  EXPECT_NEAR(boards[0].tags.front().side_mm(), 40.0, 1e-9);
  EXPECT_NEAR(boards[1].tags.front().side_mm(), 20.0, 1e-9);

  // The scene file reproduces every pose.
  const tracking::SyntheticScene s = tracking::read_scene((out / "scene.json").string());
  EXPECT_EQ(s.frame_count, sc.scene.frame_count);
  EXPECT_EQ(s.fps, sc.scene.fps);
  ASSERT_EQ(s.boards.size(), 2u);
  for (size_t b = 0; b < 2; ++b) {
    for (int64_t f = 0; f < s.frame_count; f += 7) {
      const double t = double(f) / s.fps;
      EXPECT_LT((tracking::pose_at(s.boards[b], t).matrix() -
                 tracking::pose_at(sc.scene.boards[b], t).matrix())
                    .norm(),
                1e-9);
    }
  }
  // The meshes (meshes.json beside it) read back.
  ASSERT_EQ(s.meshes.size(), sc.scene.meshes.size());
  for (size_t m = 0; m < s.meshes.size(); ++m) {
    EXPECT_EQ(s.meshes[m].name, sc.scene.meshes[m].name);
    EXPECT_EQ(s.meshes[m].board, sc.scene.meshes[m].board);
    ASSERT_EQ(s.meshes[m].vertices.size(), sc.scene.meshes[m].vertices.size());
    ASSERT_EQ(s.meshes[m].triangles.size(), sc.scene.meshes[m].triangles.size());
    for (size_t i = 0; i < s.meshes[m].vertices.size(); i += 97) {
      EXPECT_LT((s.meshes[m].vertices[i] - sc.scene.meshes[m].vertices[i]).norm(), 1e-3);
    }
    EXPECT_EQ(s.meshes[m].triangles.back(), sc.scene.meshes[m].triangles.back());
  }
  // Only the files, no temporaries.
  int files = 0;
  for (const auto& e : fs::directory_iterator(out)) {
    ++files;
    EXPECT_NE(e.path().filename().string().front(), '.') << e.path();
  }
  EXPECT_EQ(files, 6);
}

}  // namespace
}  // namespace crepuscular::pipelines
