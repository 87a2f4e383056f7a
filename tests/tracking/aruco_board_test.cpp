// Tests of OpenCV ArUco dictionaries as tag families and of ChArUco / ArUco grid boards: patterns
// against cv::aruco::drawMarker, boards.json expansion against OpenCV's board objPoints, detected
// corners against exact projections (in apriltag_detection_t::p order), poses against the truth
// and against cv::aruco::estimatePoseBoard / estimatePoseCharucoBoard on the same image.
#include <gtest/gtest.h>

#include <algorithm>
#include <cstdio>
#include <fstream>
#include <opencv2/aruco/charuco.hpp>
#include <opencv2/imgproc.hpp>

#include "foundation/error.hpp"
#include "tests/support/charuco_scene.hpp"
#include "tests/support/cli.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/temporary_folder.hpp"
#include "tracking/board.hpp"
#include "tracking/detector.hpp"
#include "tracking/pose.hpp"
#include "tracking/poses_csv.hpp"
#include "tracking/synthetic.hpp"
#include "tracking/tracker.hpp"

namespace crepuscular::tracking {
namespace {

using test::expect_error_containing;

constexpr double kRadToDeg = 57.29577951308232;

calibration::CameraModel small_camera() {
  calibration::CameraModel cam;
  cam.width = 640;
  cam.height = 480;
  cam.fx = 610.0;
  cam.fy = 606.0;
  cam.cx = 322.5;
  cam.cy = 237.0;
  cam.distortion = {-0.11, 0.04, 0.0006, -0.0004, 0.0};
  return cam;
}

Eigen::Isometry3d pose(double ax_deg, double ay_deg, double az_deg, const Eigen::Vector3d& t) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = (Eigen::AngleAxisd(az_deg / kRadToDeg, Eigen::Vector3d::UnitZ()) *
                Eigen::AngleAxisd(ay_deg / kRadToDeg, Eigen::Vector3d::UnitY()) *
                Eigen::AngleAxisd(ax_deg / kRadToDeg, Eigen::Vector3d::UnitX()))
                   .toRotationMatrix();
  T.translation() = t;
  return T;
}

Eigen::Isometry3d from_rvec_tvec(const cv::Vec3d& rvec, const cv::Vec3d& tvec) {
  cv::Matx33d R;
  cv::Rodrigues(rvec, R);
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) T.linear()(r, c) = R(r, c);
  T.translation() = Eigen::Vector3d(tvec[0], tvec[1], tvec[2]);
  return T;
}

double angle_deg(const Eigen::Isometry3d& a, const Eigen::Isometry3d& b) {
  return Eigen::AngleAxisd(a.linear().transpose() * b.linear()).angle() * kRadToDeg;
}

// Largest distance of each detection's corner k from the projection of board corner k, over all
// detections of the board; also checks that every detected id is on the board.
double worst_corner_error(const calibration::CameraModel& cam, const Board& board,
                          const Eigen::Isometry3d& T, const std::vector<Detection>& found) {
  double worst = 0;
  for (const Detection& d : found) {
    const BoardTag* tag = board.find(d.id);
    EXPECT_NE(tag, nullptr) << "id " << d.id;
    if (!tag) continue;
    std::vector<cv::Point3f> pts;
    for (const Eigen::Vector3d& c : tag->corners) pts.emplace_back(c.x(), c.y(), c.z());
    const auto truth = test::project_points(cam, T, pts);
    for (int k = 0; k < 4; ++k) worst = std::max(worst, (d.corners[k] - truth[k]).norm());
  }
  return worst;
}

TEST(ArucoFamily, DictionariesAreFamiliesWithOpenCvPatterns) {
  const auto names = tag_family_names();
  for (const char* n : {"tag36h11", "DICT_4X4_50", "DICT_6X6_250", "DICT_7X7_1000",
                        "DICT_ARUCO_ORIGINAL", "DICT_APRILTAG_36h11"}) {
    EXPECT_NE(std::find(names.begin(), names.end(), n), names.end()) << n;
  }
  EXPECT_EQ(tag_family_code_count("DICT_4X4_50"), 50);
  EXPECT_EQ(tag_family_code_count("DICT_6X6_250"), 250);
  EXPECT_EQ(tag_family_code_count("DICT_ARUCO_ORIGINAL"), 1024);
  EXPECT_EQ(tag_family_code_count("DICT_APRILTAG_36h11"), 587);
  const auto dict = cv::aruco::getPredefinedDictionary(cv::aruco::DICT_6X6_250);
  for (int id : {0, 23, 249}) {
    const TagPattern p = tag_pattern("DICT_6X6_250", id);
    ASSERT_EQ(p.width_at_border, 8);
    ASSERT_EQ(p.total_width, 10);
    ASSERT_EQ(p.border_start(), 1);
    cv::Mat marker;
    cv::aruco::drawMarker(dict, id, 8, marker, 1);
    EXPECT_EQ(cv::norm(p.cells(cv::Rect(1, 1, 8, 8)), marker, cv::NORM_INF), 0.0) << "id " << id;
    for (int i = 0; i < 10; ++i) {
      EXPECT_EQ(p.cells.at<uint8_t>(0, i), 255);
      EXPECT_EQ(p.cells.at<uint8_t>(9, i), 255);
      EXPECT_EQ(p.cells.at<uint8_t>(i, 0), 255);
      EXPECT_EQ(p.cells.at<uint8_t>(i, 9), 255);
    }
  }
  expect_error_containing([] { tag_pattern("DICT_6X6_250", 250); }, {"250", "DICT_6X6_250"});
  // Unknown names are refused with the list of accepted ones.
  DetectorOptions o;
  o.family = "DICT_6X6_999";
  expect_error_containing([&] { TagDetector{o}; },
                          {"DICT_6X6_999", "unknown", "tag36h11", "DICT_4X4_50", "DICT_7X7_1000"});
  expect_error_containing([] { tag_family_code_count("DICT_6x6_250"); },
                          {"DICT_6x6_250", "DICT_6X6_250"});
}

TEST(ArucoFamily, BoardsJsonExpandsOpenCvBoards) {
  const std::vector<Board> boards = read_boards_text(R"({"boards": [
      {"name": "calib", "charuco": {"squares_x": 5, "squares_y": 7, "square_mm": 40,
                                    "marker_mm": 30, "dictionary": "DICT_6X6_250"}},
      {"name": "needle", "family": "DICT_4X4_50",
       "aruco_grid": {"markers_x": 3, "markers_y": 2, "marker_mm": 30, "separation_mm": 10,
                      "dictionary": "DICT_4X4_50", "first_id": 7}}]})",
                                                     "boards.json");
  ASSERT_EQ(boards.size(), 2u);
  const auto check = [](const Board& b, const cv::aruco::Board& cv_board) {
    ASSERT_EQ(b.tags.size(), cv_board.ids.size());
    for (size_t m = 0; m < b.tags.size(); ++m) {
      EXPECT_EQ(b.tags[m].id, cv_board.ids[m]);
      // p order: OpenCV's corners 3, 2, 1, 0 (bottom-left, bottom-right, top-right, top-left).
      for (int k = 0; k < 4; ++k) {
        const cv::Point3f& p = cv_board.objPoints[m][size_t(3 - k)];
        EXPECT_LT((b.tags[m].corners[k] - Eigen::Vector3d(p.x, p.y, p.z)).norm(), 1e-5);
      }
      // Bottom-left as printed: y grows downwards in the board frame.
      EXPECT_GT(b.tags[m].corners[0].y(), b.tags[m].corners[3].y());
      EXPECT_LT(b.tags[m].corners[0].x(), b.tags[m].corners[1].x());
    }
  };
  EXPECT_EQ(boards[0].family, "DICT_6X6_250");
  EXPECT_EQ(boards[0].tags.size(), 17u);
  check(boards[0],
        *cv::aruco::CharucoBoard::create(
            5, 7, 40.f, 30.f, cv::aruco::getPredefinedDictionary(cv::aruco::DICT_6X6_250)));
  EXPECT_EQ(boards[1].family, "DICT_4X4_50");
  EXPECT_EQ(boards[1].tags.front().id, 7);
  check(boards[1],
        *cv::aruco::GridBoard::create(
            3, 2, 30.f, 10.f, cv::aruco::getPredefinedDictionary(cv::aruco::DICT_4X4_50), 7));
  // Written back and read again: same family and corners.
  const auto again = read_boards_text(boards_json_text(boards), "again");
  EXPECT_EQ(again[1].family, "DICT_4X4_50");
  EXPECT_LT((again[0].tags[5].corners[2] - boards[0].tags[5].corners[2]).norm(), 1e-9);
}

TEST(ArucoFamily, BoardsJsonErrorsNameTheField) {
  const auto read = [](const std::string& board) {
    read_boards_text(R"({"boards": [)" + board + "]}", "b.json");
  };
  expect_error_containing(
      [&] {
        read(R"({"name": "a", "charuco": {"squares_x": 5, "square_mm": 40, "marker_mm": 30,
                 "dictionary": "DICT_6X6_250"}})");
      },
      {"b.json", "boards[0].charuco.squares_y", "missing"});
  expect_error_containing(
      [&] {
        read(R"({"name": "a", "charuco": {"squares_x": 5, "squares_y": 7, "square_mm": 40,
                 "marker_mm": 40, "dictionary": "DICT_6X6_250"}})");
      },
      {"b.json", "boards[0].charuco", "marker", "square"});
  expect_error_containing(
      [&] {
        read(R"({"name": "a", "charuco": {"squares_x": 5, "squares_y": 7, "square_mm": 40,
                 "marker_mm": 30, "dictionary": "DICT_6X6_2500"}})");
      },
      {"b.json", "boards[0].charuco", "DICT_6X6_2500", "DICT_6X6_250"});
  expect_error_containing(
      [&] {
        read(R"({"name": "a", "charuco": {"squares_x": 11, "squares_y": 11, "square_mm": 40,
                 "marker_mm": 30, "dictionary": "DICT_4X4_50"}})");
      },
      {"b.json", "boards[0].charuco", "0 to 59", "DICT_4X4_50", "0 to 49"});
  expect_error_containing(
      [&] {
        read(R"({"name": "a", "family": "tag36h11", "aruco_grid": {"markers_x": 2,
                 "markers_y": 2, "marker_mm": 30, "separation_mm": 5,
                 "dictionary": "DICT_4X4_50"}})");
      },
      {"b.json", "boards[0].family", "tag36h11", "DICT_4X4_50"});
  expect_error_containing(
      [&] {
        read(R"({"name": "a", "aruco_grid": {"markers_x": 2, "markers_y": 2, "marker_mm": 30,
                 "separation_mm": 5, "dictionary": "tag36h11"}})");
      },
      {"b.json", "boards[0].aruco_grid.dictionary", "tag36h11", "DICT_4X4_50"});
  expect_error_containing(
      [&] {
        read(R"({"name": "a", "aruco_grid": {"markers_x": 2, "markers_y": 2, "marker_mm": -3,
                 "separation_mm": 5, "dictionary": "DICT_4X4_50"}})");
      },
      {"b.json", "boards[0].aruco_grid", "marker_mm > 0"});
  expect_error_containing(
      [&] {
        read(R"({"name": "a", "aruco_grid": {"markers_x": 8, "markers_y": 8, "marker_mm": 30,
                 "separation_mm": 5, "dictionary": "DICT_4X4_50"}})");
      },
      {"b.json", "tag id 50", "DICT_4X4_50"});
  expect_error_containing(
      [&] {
        read(R"({"name": "a", "grid": {"rows": 1, "cols": 1, "tag_size_mm": 9, "gap_mm": 1},
                 "aruco_grid": {"markers_x": 2, "markers_y": 2, "marker_mm": 30,
                 "separation_mm": 5, "dictionary": "DICT_4X4_50"}})");
      },
      {"b.json", "boards[0].aruco_grid", "one per board"});
}

// An ArUco grid board rendered by the synthetic camera (distortion, noise): corners in p order on
// the exact projections, the pose near the truth and near cv::aruco::estimatePoseBoard's.
TEST(ArucoBoards, GridBoardPoseMatchesTruthAndOpenCv) {
  SyntheticScene scene;
  scene.camera = small_camera();
  scene.noise_sigma = 2.0;
  scene.frame_count = 1;
  SceneBoard sb;
  sb.board = make_aruco_grid_board("grid", 4, 3, 35.0, 8.0, "DICT_6X6_250", 3);
  const Eigen::Isometry3d T = pose(25, -20, 12, Eigen::Vector3d(-70, -45, 420));
  sb.keyframes.push_back({0.0, T});
  scene.boards.push_back(sb);
  const cv::Mat image = SyntheticRenderer(scene).render(0);

  DetectorOptions o;
  o.family = "DICT_6X6_250";
  TagDetector detector(o);
  const std::vector<Detection> found = detector.detect(image);
  EXPECT_EQ(found.size(), 12u);
  const double worst = worst_corner_error(scene.camera, sb.board, T, found);
  EXPECT_LT(worst, 0.4) << "largest corner error vs projection (px)";

  const BoardPose ours =
      estimate_board_pose(scene.camera, match_board_corners(sb.board, found), nullptr);
  ASSERT_TRUE(ours.valid) << ours.problem;

  // OpenCV on the same image, through its own board object.
  const auto dict = cv::aruco::getPredefinedDictionary(cv::aruco::DICT_6X6_250);
  const auto grid = cv::aruco::GridBoard::create(4, 3, 35.f, 8.f, dict, 3);
  cv::Mat grey;
  cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
  std::vector<std::vector<cv::Point2f>> corners;
  std::vector<int> ids;
  auto params = cv::aruco::DetectorParameters::create();
  params->cornerRefinementMethod = cv::aruco::CORNER_REFINE_SUBPIX;
  params->cornerRefinementWinSize = 3;  // OpenCV's default 5 reaches the next chessboard square
  cv::aruco::detectMarkers(grey, dict, corners, ids, params);
  cv::Vec3d rvec, tvec;
  ASSERT_EQ(cv::aruco::estimatePoseBoard(corners, ids, grid, test::camera_matrix_of(scene.camera),
                                         test::distortion_of(scene.camera), rvec, tvec),
            12);
  const Eigen::Isometry3d theirs = from_rvec_tvec(rvec, tvec);
  std::printf(
      "ArUco grid: corners within %.3f px; ours vs truth %.3f deg %.3f mm, vs OpenCV "
      "%.3f deg %.3f mm; OpenCV vs truth %.3f deg %.3f mm\n",
      worst, angle_deg(ours.T_cam_board, T),
      (ours.T_cam_board.translation() - T.translation()).norm(),
      angle_deg(ours.T_cam_board, theirs),
      (ours.T_cam_board.translation() - theirs.translation()).norm(), angle_deg(theirs, T),
      (theirs.translation() - T.translation()).norm());
  EXPECT_LT(angle_deg(ours.T_cam_board, T), 0.3);
  EXPECT_LT((ours.T_cam_board.translation() - T.translation()).norm(), 1.0);
  EXPECT_LT(angle_deg(ours.T_cam_board, theirs), 0.3);
  EXPECT_LT((ours.T_cam_board.translation() - theirs.translation()).norm(), 1.0);
}

// A frontal, upright marker: detection corner 0 is its bottom-left in the image, and the corners
// run counter-clockwise as seen (libapriltag's p order), so a turned order fails here.
TEST(ArucoBoards, CornerOrderIsBottomLeftCounterClockwise) {
  const TagPattern p = tag_pattern("DICT_5X5_100", 42);
  cv::Mat tag;
  cv::resize(p.cells, tag, cv::Size(), 12, 12, cv::INTER_NEAREST);
  cv::Mat image(tag.rows + 60, tag.cols + 60, CV_8U, cv::Scalar(255));
  tag.copyTo(image(cv::Rect(30, 30, tag.cols, tag.rows)));
  DetectorOptions o;
  o.family = "DICT_5X5_100";
  TagDetector detector(o);
  for (int quarter = 0; quarter < 4; ++quarter) {
    const auto found = detector.detect(image);
    ASSERT_EQ(found.size(), 1u);
    EXPECT_EQ(found[0].id, 42);
    // Black border from pixel 42 to 42 + 84 - 1 in both directions: edges at 41.5 and 125.5.
    const double lo = 30 + 12 - 0.5, hi = 30 + 12 + 7 * 12 - 0.5;
    const Eigen::Vector2d upright[4] = {{lo, hi}, {hi, hi}, {hi, lo}, {lo, lo}};
    // Turning the image clockwise by quarter turns moves the upright corners with it.
    const double n = image.cols - 1;
    for (int k = 0; k < 4; ++k) {
      Eigen::Vector2d c = upright[k];
      for (int q = 0; q < quarter; ++q) c = Eigen::Vector2d(n - c.y(), c.x());
      EXPECT_LT((found[0].corners[k] - c).norm(), 0.6)
          << "quarter " << quarter << " corner " << k << " at " << found[0].corners[k].transpose();
    }
    EXPECT_LT((found[0].center - Eigen::Vector2d(n / 2, n / 2)).norm(), 0.3);
    cv::rotate(image, image, cv::ROTATE_90_CLOCKWISE);
  }
}

// A ChArUco board (CharucoBoard::draw seen through a distorted camera, blur and noise) tracked by
// its markers: pose near the truth, near cv::aruco::estimatePoseBoard (markers) and
// cv::aruco::estimatePoseCharucoBoard (on the chessboard corners of calibration::detect_charuco)
// on the same image; the Tracker measures it too.
TEST(ArucoBoards, CharucoBoardPoseMatchesTruthAndOpenCv) {
  const calibration::CameraModel cam = small_camera();
  calibration::CharucoSpec spec{5, 7, 40.0, 30.0, "DICT_6X6_250", 0};
  const auto cv_board = calibration::make_charuco_board(spec);
  const test::CharucoRenderer renderer(cam, cv_board);
  const Board board = make_charuco_board("calib", spec);
  const Eigen::Isometry3d T = pose(-20, 25, -8, Eigen::Vector3d(-95, -140, 560));
  const cv::Mat grey = renderer.render(T, 0.6, 1.5, 3);

  DetectorOptions o;
  o.family = "DICT_6X6_250";
  TagDetector detector(o);
  const std::vector<Detection> found = detector.detect(grey);
  EXPECT_EQ(found.size(), 17u);
  const double worst = worst_corner_error(cam, board, T, found);
  EXPECT_LT(worst, 0.5) << "largest corner error vs projection (px)";
  const BoardPose ours = estimate_board_pose(cam, match_board_corners(board, found), nullptr);
  ASSERT_TRUE(ours.valid) << ours.problem;

  std::vector<std::vector<cv::Point2f>> corners;
  std::vector<int> ids;
  auto params = cv::aruco::DetectorParameters::create();
  params->cornerRefinementMethod = cv::aruco::CORNER_REFINE_SUBPIX;
  params->cornerRefinementWinSize = 3;  // OpenCV's default 5 reaches the next chessboard square
  cv::aruco::detectMarkers(grey, cv_board->dictionary, corners, ids, params);
  const cv::Mat K = test::camera_matrix_of(cam), dist = test::distortion_of(cam);
  cv::Vec3d rvec, tvec;
  ASSERT_EQ(cv::aruco::estimatePoseBoard(corners, ids, cv_board, K, dist, rvec, tvec), 17);
  const Eigen::Isometry3d markers = from_rvec_tvec(rvec, tvec);
  // Chessboard corners of calibration::detect_charuco (OpenCV's, free of its half-pixel shift).
  const auto view = calibration::detect_charuco(grey, spec, "view");
  ASSERT_TRUE(view.has_value());
  EXPECT_EQ(view->object_points.size(), 24u);
  std::vector<cv::Point2f> chess;
  std::vector<int> chess_ids;
  for (size_t k = 0; k < view->object_points.size(); ++k) {
    chess.emplace_back(float(view->image_points[k].x()), float(view->image_points[k].y()));
    chess_ids.push_back(int(std::lround(view->object_points[k].y() / 40.0 - 1)) * 4 +
                        int(std::lround(view->object_points[k].x() / 40.0 - 1)));
  }
  ASSERT_TRUE(cv::aruco::estimatePoseCharucoBoard(chess, chess_ids, cv_board, K, dist, rvec, tvec));
  const Eigen::Isometry3d charuco = from_rvec_tvec(rvec, tvec);
  std::printf(
      "ChArUco markers: corners within %.3f px; ours vs truth %.3f deg %.3f mm, vs "
      "estimatePoseBoard %.3f deg %.3f mm, vs estimatePoseCharucoBoard %.3f deg %.3f mm "
      "(which is %.3f deg %.3f mm from the truth)\n",
      worst, angle_deg(ours.T_cam_board, T),
      (ours.T_cam_board.translation() - T.translation()).norm(),
      angle_deg(ours.T_cam_board, markers),
      (ours.T_cam_board.translation() - markers.translation()).norm(),
      angle_deg(ours.T_cam_board, charuco),
      (ours.T_cam_board.translation() - charuco.translation()).norm(), angle_deg(charuco, T),
      (charuco.translation() - T.translation()).norm());
  EXPECT_LT(angle_deg(ours.T_cam_board, T), 0.3);
  EXPECT_LT((ours.T_cam_board.translation() - T.translation()).norm(), 1.0);
  EXPECT_LT(angle_deg(ours.T_cam_board, markers), 0.3);
  EXPECT_LT((ours.T_cam_board.translation() - markers.translation()).norm(), 1.0);
  EXPECT_LT(angle_deg(ours.T_cam_board, charuco), 0.3);
  EXPECT_LT((ours.T_cam_board.translation() - charuco.translation()).norm(), 1.0);

  // The Tracker of `crepuscular track` measures the board from the same frame.
  TrackerOptions to;
  to.detector.family = "DICT_6X6_250";
  to.smoothing = false;
  Tracker tracker(cam, {board}, to);
  Frame frame;
  cv::cvtColor(grey, frame.image, cv::COLOR_GRAY2BGR);
  const TrackResult r = tracker.process(frame);
  ASSERT_EQ(r.boards.size(), 1u);
  ASSERT_TRUE(r.boards[0].measured) << r.boards[0].problem;
  EXPECT_EQ(r.boards[0].tags, 17);
  EXPECT_LT(angle_deg(r.boards[0].T_measured, T), 0.3);
  EXPECT_LT((r.boards[0].T_measured.translation() - T.translation()).norm(), 1.0);
}

// `crepuscular track` on a synthetic scene of an ArUco grid board and a ChArUco board's markers
// (boards.json "aruco_grid" and "charuco", one dictionary): both tracked in every frame at the
// scene's poses.
TEST(ArucoBoards, TrackCommandTracksArucoBoards) {
  const test::TemporaryFolder dir;
  {
    std::ofstream b(dir / "boards.json");
    b << R"({"boards": [
      {"name": "grid", "aruco_grid": {"markers_x": 4, "markers_y": 3, "marker_mm": 35,
       "separation_mm": 8, "dictionary": "DICT_6X6_250", "first_id": 3}},
      {"name": "calib", "charuco": {"squares_x": 5, "squares_y": 7, "square_mm": 40,
       "marker_mm": 30, "dictionary": "DICT_6X6_250", "first_id": 20}}]})";
    std::ofstream s(dir / "scene.json");
    s << R"({"boards": "boards.json", "frames": 4, "noise_sigma": 2,
      "poses": {"grid": [{"t": 0, "translation_mm": [-250, -100, 600], "rotvec_deg": [15, -10, 5]}],
                "calib": [{"t": 0, "translation_mm": [20, -150, 650], "rotvec_deg": [-10, 20, -4]}]}})";
  }
  const std::string out = (dir / "poses.csv").string();
  std::string log;
  ASSERT_EQ(
      test::run_cli("track --source synthetic:" + (dir / "scene.json").string() + " --boards " +
                        (dir / "boards.json").string() + " --out " + out,
                    &log),
      0)
      << log;
  const auto rotvec = [](double x, double y, double z, const Eigen::Vector3d& t) {
    const Eigen::Vector3d w = Eigen::Vector3d(x, y, z) / kRadToDeg;
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = Eigen::AngleAxisd(w.norm(), w.normalized()).toRotationMatrix();
    T.translation() = t;
    return T;
  };
  const Eigen::Isometry3d truth_grid = rotvec(15, -10, 5, Eigen::Vector3d(-250, -100, 600));
  const Eigen::Isometry3d truth_calib = rotvec(-10, 20, -4, Eigen::Vector3d(20, -150, 650));
  const std::vector<PoseRecord> rows = read_poses_csv(out);
  ASSERT_EQ(rows.size(), 8u);
  for (const PoseRecord& r : rows) {
    ASSERT_TRUE(r.tracked) << r.board << " frame " << r.frame;
    const Eigen::Isometry3d& truth = r.board == "grid" ? truth_grid : truth_calib;
    EXPECT_LT(angle_deg(r.T_cam_board, truth), 0.3) << r.board << " frame " << r.frame;
    EXPECT_LT((r.T_cam_board.translation() - truth.translation()).norm(), 1.5)
        << r.board << " frame " << r.frame;
  }
}

}  // namespace
}  // namespace crepuscular::tracking
