// Tests of synthetic frames (tracking/synthetic.hpp): rendered tags detected by libapriltag land
// where CameraModel::project puts the true corners (with distortion), pose interpolation, lighting,
// noise and blur levels, dropped and corrupt frames, scene files, and the built-in scene.
#include "tracking/synthetic.hpp"

#include <apriltag.h>
#include <gtest/gtest.h>
#include <tag36h11.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <opencv2/aruco/charuco.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>

#include "calibration/aruco.hpp"
#include "foundation/error.hpp"
#include "tests/support/temporary_folder.hpp"

namespace crepuscular::tracking {
namespace {

namespace fs = std::filesystem;
constexpr double kDeg = 3.14159265358979323846 / 180.0;

Eigen::Isometry3d pose(const Eigen::Vector3d& rotvec_deg, const Eigen::Vector3d& t) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  if (rotvec_deg.norm() > 0) {
    T.linear() = Eigen::AngleAxisd(rotvec_deg.norm() * kDeg, rotvec_deg.normalized()).matrix();
  }
  T.translation() = t;
  return T;
}

struct Detected {
  int id;
  std::array<Eigen::Vector2d, 4> p;
};

// libapriltag places pixel centres at (i + 0.5, j + 0.5), OpenCV and CameraModel at (i, j):
// measured here on rotated tags, libapriltag's corners lie +0.50 px (x and y, within 0.02) from
// the projected truth while OpenCV's cv::aruco DICT_APRILTAG_36h11 corners lie within 0.04 px.
constexpr double kApriltagPixelOffset = 0.5;

// libapriltag at full resolution with edge refinement: the most accurate corners it gives, in
// CameraModel's pixel convention.
std::vector<Detected> detect(const cv::Mat& bgr) {
  cv::Mat grey;
  cv::cvtColor(bgr, grey, cv::COLOR_BGR2GRAY);
  apriltag_family_t* fam = tag36h11_create();
  apriltag_detector_t* td = apriltag_detector_create();
  apriltag_detector_add_family(td, fam);
  td->quad_decimate = 1.0;
  td->nthreads = 2;
  td->refine_edges = 1;
  image_u8_t im{grey.cols, grey.rows, int32_t(grey.step[0]), grey.data};
  zarray_t* dets = apriltag_detector_detect(td, &im);
  std::vector<Detected> out;
  for (int i = 0; i < zarray_size(dets); ++i) {
    apriltag_detection_t* d = nullptr;
    zarray_get(dets, i, &d);
    Detected r;
    r.id = d->id;
    for (int k = 0; k < 4; ++k) {
      r.p[size_t(k)] = {d->p[k][0] - kApriltagPixelOffset, d->p[k][1] - kApriltagPixelOffset};
    }
    out.push_back(r);
  }
  apriltag_detections_destroy(dets);
  apriltag_detector_destroy(td);
  tag36h11_destroy(fam);
  return out;
}

SyntheticScene single_tag_scene(const std::array<double, 5>& distortion, double size_mm,
                                const Eigen::Isometry3d& T) {
  SyntheticScene s;
  s.camera.fx = 1010;
  s.camera.fy = 1005;
  s.camera.cx = 642.3;
  s.camera.cy = 357.1;
  s.camera.distortion = distortion;
  s.background = "plain";
  SceneBoard b;
  b.board.name = "tag";
  BoardTag tag;
  tag.id = 7;
  tag.corners = square_tag_corners({0, 0}, size_mm);
  b.board.tags = {tag};
  b.plate = false;  // the tag's own white ring on a grey background
  b.keyframes = {{0.0, T}};
  s.boards = {b};
  s.frame_count = 1;
  return s;
}

// The accuracy that the pose tests downstream rely on: sub-pixel corners through distortion.
TEST(Synthetic, DetectedCornersMatchProjectedTrueCorners) {
  struct Case {
    std::array<double, 5> distortion;
    double size_mm;
    Eigen::Isometry3d T;
  };
  const std::vector<Case> cases = {
      {{0, 0, 0, 0, 0}, 60, pose({0, 0, 0}, {0, 0, 500})},
      {{0, 0, 0, 0, 0}, 40, pose({-30, 20, 10}, {-60, 40, 450})},
      {{-0.05, 0.02, 0, 0, 0}, 40, pose({-25, 5, 3}, {-120, -60, 520})},
      {{-0.12, 0.05, 0.001, -0.0008, 0}, 50, pose({20, -25, 40}, {150, 80, 550})},
      {{0.08, -0.03, 0, 0, 0.01}, 40, pose({-15, -35, -20}, {-200, 100, 600})},
  };
  double worst = 0;
  for (size_t c = 0; c < cases.size(); ++c) {
    const SyntheticScene scene =
        single_tag_scene(cases[c].distortion, cases[c].size_mm, cases[c].T);
    SyntheticRenderer renderer(scene);
    std::vector<TruePose> truth;
    const cv::Mat img = renderer.render(0, &truth);
    ASSERT_EQ(truth.size(), 1u);
    EXPECT_TRUE(truth[0].T_cam_board.isApprox(cases[c].T));
    const std::vector<Detected> dets = detect(img);
    ASSERT_EQ(dets.size(), 1u) << "case " << c;
    EXPECT_EQ(dets[0].id, 7);
    const BoardTag& tag = scene.boards[0].board.tags[0];
    double case_worst = 0;
    for (size_t k = 0; k < 4; ++k) {
      const Eigen::Vector2d expected = scene.camera.project(cases[c].T * tag.corners[k]);
      const double err = (dets[0].p[k] - expected).norm();
      worst = std::max(worst, err);
      case_worst = std::max(case_worst, err);
      EXPECT_LT(err, 0.3) << "case " << c << " corner " << k << " detected "
                          << dets[0].p[k].transpose() << " expected " << expected.transpose();
    }
    std::printf("case %zu: worst corner error %.3f px\n", c, case_worst);
  }
  std::printf("worst corner error over %zu cases: %.3f px\n", cases.size(), worst);
}

// Through a strong fisheye (TUM VI-like, 512 x 512, f 191 px) every pixel shows what the ray that
// cv::fisheye::undistortPoints gives for it meets: the tag's white outer ring, its black ring, or
// the background (pixels within 0.3 cells of a boundary are not judged), out to 58 degrees off
// axis; the image corners, more than 90 degrees off axis, see the background. libapriltag finds
// the corners too, to within the bias of fitting straight lines to the edges a fisheye bends.
TEST(Synthetic, FisheyeFramesShowWhatOpenCvFisheyeRaysMeet) {
  const std::vector<Eigen::Isometry3d> poses = {pose({0, 0, 0}, {-30, -30, 250}),
                                                pose({15, -20, 10}, {-180, 60, 230}),
                                                pose({-10, 40, -30}, {200, 160, 170})};
  double worst_corner = 0;
  for (size_t c = 0; c < poses.size(); ++c) {
    SyntheticScene scene = single_tag_scene({0, 0, 0, 0, 0}, 60, poses[c]);
    calibration::CameraModel& cam = scene.camera;
    cam.model = calibration::DistortionModel::equidistant;
    cam.width = cam.height = 512;
    cam.fx = 190.98;
    cam.fy = 190.97;
    cam.cx = 254.93;
    cam.cy = 256.90;
    cam.distortion = {0.0034824, 0.00071503, -0.0020532, 0.00020294, 0.0};
    const cv::Mat img = SyntheticRenderer(scene).render(0);
    EXPECT_NEAR(img.at<cv::Vec3b>(0, 0)[0], scene.background_grey, 1.0) << "case " << c;
    EXPECT_NEAR(img.at<cv::Vec3b>(511, 511)[0], scene.background_grey, 1.0) << "case " << c;

    // The tag in its board frame: u, v in cells of the black-bordered square from corner 3 (its
    // top-left), which spans [0, 8]^2; the white ring is [-1, 9]^2 around it.
    const std::array<Eigen::Vector3d, 4>& k = scene.boards[0].board.tags[0].corners;
    const Eigen::Vector3d ex = (k[2] - k[3]) / 8.0, ey = (k[0] - k[3]) / 8.0;
    const Eigen::Vector3d normal = poses[c].linear() * ex.cross(ey).normalized();
    const Eigen::Vector3d origin = poses[c] * k[3];
    std::vector<cv::Point2d> pixels, rays;
    for (int y = 0; y < 512; ++y) {
      for (int x = 0; x < 512; ++x) {
        // Only pixels under 83 degrees off axis: OpenCV's inverse has no answer past 90.
        if (std::hypot((x - cam.cx) / cam.fx, (y - cam.cy) / cam.fy) < 1.45) {
          pixels.emplace_back(x, y);
        }
      }
    }
    cv::fisheye::undistortPoints(pixels, rays, cam.camera_matrix(), cam.distortion_coefficients());
    const auto inside = [](double u, double v, double lo, double hi) {
      return u > lo && u < hi && v > lo && v < hi;
    };
    constexpr double m = 0.3;  // cells (about 1.4 px) left unjudged on each side of a boundary
    int judged[3] = {0, 0, 0}, wrong = 0;
    for (size_t i = 0; i < pixels.size(); ++i) {
      const Eigen::Vector3d d(rays[i].x, rays[i].y, 1.0);
      const double lambda = normal.dot(origin) / normal.dot(d);
      double u = 1e9, v = 1e9;
      if (lambda > 0) {
        const Eigen::Vector3d q = poses[c].inverse() * (lambda * d) - k[3];
        u = q.dot(ex) / ex.squaredNorm();
        v = q.dot(ey) / ey.squaredNorm();
      }
      int want = -1;
      if (!inside(u, v, -1 - m, 9 + m)) want = 0;                             // background
      if (inside(u, v, -1 + m, 9 - m) && !inside(u, v, -m, 8 + m)) want = 1;  // white ring
      if (inside(u, v, m, 8 - m) && !inside(u, v, 1 - m, 7 + m)) want = 2;    // black ring
      if (want < 0) continue;
      const double level[3] = {scene.background_grey, scene.white, scene.black};
      const double got = img.at<cv::Vec3b>(int(pixels[i].y), int(pixels[i].x))[0];
      ++judged[want];
      if (std::abs(got - level[want]) > 1.0) ++wrong;
    }
    EXPECT_EQ(wrong, 0) << "case " << c;
    EXPECT_GT(judged[1], 100) << "case " << c;
    EXPECT_GT(judged[2], 100) << "case " << c;

    const std::vector<Detected> dets = detect(img);
    ASSERT_EQ(dets.size(), 1u) << "case " << c;
    std::vector<cv::Point3d> object;
    for (const Eigen::Vector3d& corner : k) {
      const Eigen::Vector3d q = poses[c] * corner;
      object.emplace_back(q.x(), q.y(), q.z());
    }
    std::vector<cv::Point2d> expected;
    cv::fisheye::projectPoints(object, expected, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0),
                               cam.camera_matrix(), cam.distortion_coefficients());
    double case_worst = 0;
    for (size_t j = 0; j < 4; ++j) {
      case_worst = std::max(case_worst,
                            (dets[0].p[j] - Eigen::Vector2d(expected[j].x, expected[j].y)).norm());
    }
    EXPECT_LT(case_worst, 0.6) << "case " << c;
    worst_corner = std::max(worst_corner, case_worst);
    std::printf(
        "fisheye case %zu (%.0f deg off axis): %d background, %d white, %d black pixels "
        "judged, %d wrong; libapriltag corner error %.3f px\n",
        c, std::atan2(std::hypot(object[0].x, object[0].y), object[0].z) / kDeg, judged[0],
        judged[1], judged[2], wrong, case_worst);
  }
}

TEST(Synthetic, SceneFileTakesAFisheyeCamera) {
  const test::TemporaryFolder dir;
  write_boards((dir / "boards.json").string(), {make_grid_board("patient", 2, 3, 40, 10, 0)});
  const auto scene = [&](const std::string& camera) {
    const std::string path = (dir / "scene.json").string();
    std::ofstream(path) << R"({"camera": )" << camera << R"(, "boards": "boards.json",
      "poses": {"patient": [{"t": 0, "translation_mm": [0, 0, 300]}]}})";
    return path;
  };
  const SyntheticScene s = read_scene(scene(
      R"({"width": 512, "height": 512, "fx": 190, "distortion_model": "equidistant",
          "distortion": [0.003, 0.0007, -0.002, 0.0002]})"));
  EXPECT_EQ(s.camera.model, calibration::DistortionModel::equidistant);
  EXPECT_DOUBLE_EQ(s.camera.distortion[3], 0.0002);
  EXPECT_DOUBLE_EQ(s.camera.distortion[4], 0.0);
  // Five numbers are Brown-Conrady's, not a fisheye's; an unknown model is named.
  EXPECT_THROW(read_scene(scene(R"({"distortion_model": "equidistant",
                                     "distortion": [0, 0, 0, 0, 0]})")),
               Error);
  try {
    read_scene(scene(R"({"distortion_model": "omnidirectional"})"));
    ADD_FAILURE() << "expected Error";
  } catch (const Error& e) {
    for (const char* part : {"scene.json", "omnidirectional", "equidistant", "plumb_bob"}) {
      EXPECT_NE(std::string(e.what()).find(part), std::string::npos) << e.what();
    }
  }
}

// An edge between black and white lands where the camera model puts it: along a row crossing the
// left edge of a fronto-parallel tag, the grey level crosses the mid level at the projected edge.
TEST(Synthetic, EdgeIsAntiAliasedAtTheProjectedPosition) {
  // 80 mm tag at 500 mm, f = 1000: 20 px per cell, edge at a fractional pixel position.
  const Eigen::Isometry3d T = pose({0, 0, 0}, {0.37, 0.0, 500});
  SyntheticScene scene = single_tag_scene({0, 0, 0, 0, 0}, 80, T);
  scene.camera.fx = scene.camera.fy = 1000;
  scene.camera.cx = 639.5;
  scene.camera.cy = 359.5;
  scene.background_grey = 230;  // as white as the paper
  SyntheticRenderer renderer(scene);
  const cv::Mat img = renderer.render(0);
  // The outer edge of the black border: x = -40 mm in the board frame.
  const double edge_x = scene.camera.project(T * Eigen::Vector3d(-40, 0, 0)).x();
  const int row = 365;  // inside the border's left column, away from data cells
  // A box-filtered step: each pixel's grey level is its white fraction, so the white area left of
  // the edge, summed from a fully white pixel on, is the edge position.
  const int start = int(edge_x) - 4;
  double white_px = 0;
  for (int x = start; x < int(edge_x) + 5; ++x) {
    white_px += (img.at<cv::Vec3b>(row, x)[0] - scene.black) / (scene.white - scene.black);
  }
  const double crossing = start - 0.5 + white_px;
  EXPECT_NEAR(crossing, edge_x, 0.03) << "edge at " << edge_x;
}

TEST(Synthetic, PosesInterpolateLinearlyAndBySlerp) {
  SceneBoard b;
  b.keyframes = {{1.0, pose({0, 0, 0}, {0, 0, 400})}, {3.0, pose({0, 60, 0}, {100, -20, 600})}};
  const Eigen::Isometry3d mid = pose_at(b, 2.0);
  EXPECT_TRUE(mid.translation().isApprox(Eigen::Vector3d(50, -10, 500)));
  const Eigen::AngleAxisd aa(mid.linear());
  EXPECT_NEAR(aa.angle(), 30 * kDeg, 1e-12);
  EXPECT_NEAR(std::abs(aa.axis().y()), 1.0, 1e-12);
  EXPECT_TRUE(pose_at(b, 0.0).isApprox(b.keyframes[0].T_cam_board));
  EXPECT_TRUE(pose_at(b, 9.0).isApprox(b.keyframes[1].T_cam_board));
}

TEST(Synthetic, LightingNoiseAndBlurHaveTheirStatedLevels) {
  SyntheticScene s = single_tag_scene({0, 0, 0, 0, 0}, 40, pose({0, 0, 0}, {0, 0, 500}));
  s.background_grey = 100;
  s.gain = 1.2;
  s.offset = 10;
  const cv::Mat lit = SyntheticRenderer(s).render(0);
  EXPECT_EQ(lit.at<cv::Vec3b>(10, 10)[1], 130);                               // 1.2 * 100 + 10
  EXPECT_EQ(lit.at<cv::Vec3b>(360, 640)[2], lit.at<cv::Vec3b>(360, 640)[0]);  // grey in BGR

  s.gain = 1;
  s.offset = 0;
  const cv::Mat clean = SyntheticRenderer(s).render(0);
  s.noise_sigma = 4.0;
  const cv::Mat noisy = SyntheticRenderer(s).render(0);
  cv::Mat diff;
  cv::subtract(noisy, clean, diff, cv::noArray(), CV_32F);
  cv::Scalar mean, stddev;
  cv::meanStdDev(diff.reshape(1), mean, stddev);
  EXPECT_NEAR(stddev[0], 4.0, 0.15);  // rounding adds 1/12 in variance
  EXPECT_NEAR(mean[0], 0.0, 0.05);

  s.noise_sigma = 0;
  s.blur_sigma = 2.0;
  const cv::Mat blurred = SyntheticRenderer(s).render(0);
  cv::Mat expected;
  cv::GaussianBlur(clean, expected, cv::Size(0, 0), 2.0, 2.0, cv::BORDER_REPLICATE);
  // Same blur, applied before rounding in the renderer: within one grey level.
  EXPECT_LE(cv::norm(blurred, expected, cv::NORM_INF), 1.0);
}

TEST(Synthetic, SourceDropsAndCorruptsFramesAndCarriesTruth) {
  SyntheticScene s = single_tag_scene({0, 0, 0, 0, 0}, 40, pose({0, 0, 0}, {0, 0, 500}));
  s.boards[0].keyframes.push_back({1.0, pose({0, 0, 0}, {30, 0, 500})});
  s.frame_count = 6;
  s.fps = 5;
  s.dropped_frames = {2};
  s.corrupt_frames = {4};
  s.occlusions = {{cv::Rect2d(600, 340, 80, 40), 3, 3, 10}};
  auto src = make_synthetic_source(s, "test");
  ASSERT_TRUE(src->camera().has_value());
  EXPECT_EQ(src->camera()->width, 1280);
  std::vector<int64_t> indices;
  while (auto f = src->next()) {
    indices.push_back(f->index);
    EXPECT_EQ(f->timestamp_ns, f->index * 200000000);
    ASSERT_EQ(f->truth.size(), 1u);
    EXPECT_NEAR(f->truth[0].T_cam_board.translation().x(), 30.0 * f->index / 5.0, 1e-9);
    if (f->index == 4) {
      EXPECT_TRUE(f->image.empty());
      EXPECT_NE(f->problem.find("corrupt JPEG"), std::string::npos) << f->problem;
      EXPECT_FALSE(f->encoded.empty());
      EXPECT_EQ(f->encoded_format, "jpg");
    } else {
      EXPECT_FALSE(f->image.empty());
      EXPECT_TRUE(f->problem.empty());
    }
    if (f->index == 3) {
      EXPECT_EQ(f->image.at<cv::Vec3b>(360, 640)[0], 10);  // occluded
    }
    if (f->index == 1) {
      EXPECT_NE(f->image.at<cv::Vec3b>(360, 640)[0], 10);
    }
  }
  EXPECT_EQ(indices, (std::vector<int64_t>{0, 1, 3, 4, 5}));
}

TEST(Synthetic, SceneFileIsReadWithBoardsPosesAndOptions) {
  const test::TemporaryFolder dir;
  write_boards((dir / "boards.json").string(), {make_grid_board("patient", 2, 3, 40, 10, 0),
                                                make_grid_board("needle", 1, 2, 20, 5, 10)});
  std::ofstream(dir / "scene.json") << R"({
    "camera": {"width": 640, "height": 480, "fx": 600, "distortion": [-0.1, 0.01, 0, 0, 0]},
    "background": {"type": "noise", "grey": 120, "contrast": 40},
    "boards": "boards.json",
    "poses": {"patient": [{"t": 0, "translation_mm": [0, 0, 500], "rotvec_deg": [20, 0, 0]}],
              "needle": [{"t": 0, "translation_mm": [50, 0, 300]},
                         {"t": 1, "translation_mm": [50, 0, 400], "quaternion": [1, 0, 0, 0]}]},
    "fps": 10, "frames": 12, "noise_sigma": 1, "dropped_frames": [3], "corrupt_frames": [5],
    "occlusions": [{"rect_px": [0, 0, 10, 10], "frames": [1, 2], "grey": 0}]})";
  const SyntheticScene s = read_scene((dir / "scene.json").string());
  EXPECT_EQ(s.camera.width, 640);
  EXPECT_DOUBLE_EQ(s.camera.fy, 600);
  EXPECT_DOUBLE_EQ(s.camera.cx, 319.5);
  EXPECT_DOUBLE_EQ(s.camera.distortion[0], -0.1);
  EXPECT_EQ(s.background, "noise");
  ASSERT_EQ(s.boards.size(), 2u);
  EXPECT_EQ(s.boards[1].keyframes.size(), 2u);
  EXPECT_NEAR(pose_at(s.boards[1], 0.5).translation().z(), 350, 1e-9);
  EXPECT_NEAR(Eigen::AngleAxisd(s.boards[0].keyframes[0].T_cam_board.linear()).angle(), 20 * kDeg,
              1e-12);
  EXPECT_EQ(s.frame_count, 12);
  EXPECT_EQ(s.dropped_frames, std::vector<int64_t>{3});
  ASSERT_EQ(s.occlusions.size(), 1u);
  EXPECT_EQ(s.occlusions[0].last_frame, 2);

  std::ofstream(dir / "bad.json") << R"({"boards": "boards.json", "poses": {"patient": []}})";
  try {
    read_scene((dir / "bad.json").string());
    ADD_FAILURE() << "expected Error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("needle"), std::string::npos) << e.what();
  }
  std::ofstream(dir / "bad2.json") << R"({"boards": "boards.json", "poses": {"other": []}})";
  EXPECT_THROW(read_scene((dir / "bad2.json").string()), Error);
}

// The built-in scene keeps both boards in view at the stated distances and brings the needle tip
// toward the target; its frames render fast enough for tests that use many of them.
TEST(Synthetic, BuiltinSceneKeepsBoardsInViewAndApproachesTarget) {
  const SyntheticScene s = builtin_scene();
  ASSERT_EQ(s.boards.size(), 2u);
  EXPECT_EQ(s.boards[0].board.tags.size(), 6u);
  EXPECT_EQ(s.boards[0].board.fiducials.size(), 4u);
  EXPECT_EQ(s.boards[1].board.tags.size(), 4u);
  double first_gap = 0, last_gap = 0;
  for (int64_t f = 0; f < s.frame_count; ++f) {
    const double t = double(f) / s.fps;
    const Eigen::Isometry3d T_cam_patient = pose_at(s.boards[0], t);
    const Eigen::Isometry3d T_cam_needle = pose_at(s.boards[1], t);
    const double z = T_cam_patient.translation().z();
    EXPECT_GE(z, 400);
    EXPECT_LE(z, 600);
    for (const SceneBoard& b : s.boards) {
      const Eigen::Isometry3d T = pose_at(b, t);
      for (const BoardTag& tag : b.board.tags) {
        for (const Eigen::Vector3d& c : tag.corners) {
          const Eigen::Vector2d px = s.camera.project(T * c);
          EXPECT_TRUE(px.x() > 20 && px.y() > 20 && px.x() < 1260 && px.y() < 700)
              << b.board.name << " tag " << tag.id << " frame " << f << " at " << px.transpose();
        }
      }
    }
    const Eigen::Vector3d tip = T_cam_patient.inverse() * T_cam_needle * kNeedleTipInNeedle;
    const double gap = (tip - kTumorTargetInPatient).norm();
    if (f == 0) first_gap = gap;
    last_gap = gap;
  }
  EXPECT_NEAR(first_gap, 200.0, 1.0);
  EXPECT_LT(last_gap, 70.0);

  SyntheticRenderer renderer(s);
  std::vector<TruePose> truth;
  const cv::Mat img = renderer.render(45, &truth);
  std::map<int, int> seen;
  for (const Detected& d : detect(img)) ++seen[d.id];
  for (int id : {0, 1, 2, 3, 4, 5, 10, 11, 12, 13}) EXPECT_EQ(seen[id], 1) << "tag " << id;
}

// Boards are drawn as printed. A ChArUco board seen square-on: every chessboard square is dark
// where OpenCV's own drawing of the board (CharucoBoard::draw) is dark, and light where it is
// light. A Kalibr aprilgrid: its corner squares are dark, the paper between them light, from the
// side its tags face (Kalibr's frame has z out of the print).
TEST(Synthetic, ChArUcoAndKalibrBoardsAreDrawnAsPrinted) {
  calibration::CharucoSpec spec;
  spec.squares_x = 5;
  spec.squares_y = 7;
  spec.square_mm = 40;
  spec.marker_mm = 30;
  spec.dictionary = "DICT_6X6_250";
  SyntheticScene scene;
  scene.frame_count = 1;
  scene.background = "plain";
  scene.background_grey = 128;
  SceneBoard charuco;
  charuco.board = make_charuco_board("calib", spec);
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.translation() = Eigen::Vector3d(-100, -140, 600);  // the board's centre on the optical axis
  charuco.keyframes = {{0.0, T}};
  scene.boards = {charuco};
  cv::Mat image;
  cv::cvtColor(SyntheticRenderer(scene).render(0), image, cv::COLOR_BGR2GRAY);
  cv::Mat drawn;  // OpenCV's print at 2 px per mm
  calibration::make_charuco_board(spec)->draw(cv::Size(400, 560), drawn, 0, 1);
  int dark = 0;
  for (int y = 0; y < spec.squares_y; ++y) {
    for (int x = 0; x < spec.squares_x; ++x) {
      // A point inside the square clear of any marker: 4 mm from its top-left corner.
      const Eigen::Vector3d p(x * 40.0 + 4.0, y * 40.0 + 4.0, 0.0);
      const Eigen::Vector2d px = scene.camera.project(T * p);
      const bool ours = image.at<uint8_t>(int(std::lround(px.y())), int(std::lround(px.x()))) < 128;
      const bool opencv = drawn.at<uint8_t>(int(p.y() * 2), int(p.x() * 2)) < 128;
      EXPECT_EQ(ours, opencv) << "square (" << x << ", " << y << ")";
      dark += ours;
    }
  }
  EXPECT_EQ(dark, 18);  // 35 squares, 17 of them holding a marker

  SyntheticScene kalibr_scene = scene;
  SceneBoard grid;
  grid.board = make_kalibr_aprilgrid_board("aprilgrid", 3, 4, 40.0, 0.3);
  Eigen::Isometry3d Tk = Eigen::Isometry3d::Identity();
  Tk.linear() = Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitX()).toRotationMatrix();  // y up
  Tk.translation() = Eigen::Vector3d(-100, 70, 600);
  grid.keyframes = {{0.0, Tk}};
  kalibr_scene.boards = {grid};
  cv::cvtColor(SyntheticRenderer(kalibr_scene).render(0), image, cv::COLOR_BGR2GRAY);
  const auto level = [&](double x, double y) {
    const Eigen::Vector2d px = kalibr_scene.camera.project(Tk * Eigen::Vector3d(x, y, 0));
    return image.at<uint8_t>(int(std::lround(px.y())), int(std::lround(px.x())));
  };
  const double pitch = 52.0, gap = 12.0;
  for (int r = 0; r <= 3; ++r) {
    for (int c = 0; c <= 4; ++c) {
      EXPECT_LT(level(c * pitch - 0.5 * gap, r * pitch - 0.5 * gap), 80) << "corner square";
    }
  }
  // Paper: in a gap between two tags, halfway between corner squares, and beyond the squares.
  EXPECT_GT(level(pitch - 0.5 * gap, 20.0), 180);
  EXPECT_GT(level(20.0, -gap - 5.0), 180);
}

// A breathing patient board: at every frame its pose is the still pose raised along its own -z by
// 8 mm x sin^2(pi t / 4 s) at 15 breaths a minute (none at 0 s, 8 mm at 2 s); the needle board
// does not move with it; an unknown board or rate is refused.
TEST(SyntheticBreathing, PatientBoardRisesOffTheSkinWithEachBreath) {
  const SyntheticScene still = builtin_scene();
  SyntheticScene breathing = still;
  add_breathing(breathing, "patient", 15.0, 8.0);
  for (const double t : {0.0, 0.5, 1.0, 2.0, 2.9}) {
    const Eigen::Isometry3d a = pose_at(still.boards[0], t), b = pose_at(breathing.boards[0], t);
    const double rise = 8.0 * std::pow(std::sin(M_PI * t / 4.0), 2);
    EXPECT_LT((b.translation() - (a.translation() - rise * a.linear().col(2))).norm(), 1e-6) << t;
    EXPECT_LT((b.linear() - a.linear()).norm(), 1e-9) << t;
    EXPECT_NEAR(breathing_rise_mm(t, 15.0, 8.0), rise, 1e-9);
    EXPECT_LT((pose_at(breathing.boards[1], t).translation() -
               pose_at(still.boards[1], t).translation()).norm(), 1e-9);
  }
  EXPECT_NEAR(breathing_cycle_fraction(5.0, 15.0), 0.25, 1e-12);
  EXPECT_THROW(add_breathing(breathing, "chest", 15.0, 8.0), Error);
  EXPECT_THROW(add_breathing(breathing, "patient", 0.0, 8.0), Error);
}

}  // namespace
}  // namespace crepuscular::tracking
