// Kalibr aprilgrids: the target yaml reader against Kalibr's corner formula, and detection of
// aprilgrids rendered as Kalibr prints them (corner squares) in sharp, blurred, distorted, fisheye,
// 8- and 16-bit frames against the projected truth, with the board pose in Kalibr's frame.
#include <gtest/gtest.h>

#include <chrono>
#include <cstdio>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <set>

#include "foundation/error.hpp"
#include "recordings/recording.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/temporary_folder.hpp"
#include "tests/tracking/kalibr_frames.hpp"
#include "tracking/board.hpp"
#include "tracking/detector.hpp"
#include "tracking/pose.hpp"

namespace crepuscular::tracking {
namespace {

using testing::KalibrFrameOptions;
using testing::KalibrGridRenderer;
using testing::KalibrGridSpec;

// TUM VI's april_6x6.yaml as Kalibr's documentation writes it (no %YAML header, comments).
constexpr const char* kTumviTarget =
    "target_type: 'aprilgrid' #gridtype\n"
    "tagCols: 6               #number of apriltags\n"
    "tagRows: 6               #number of apriltags\n"
    "tagSize: 0.088           #size of apriltag, edge to edge [m]\n"
    "tagSpacing: 0.3          #ratio of space between tags to tagSize\n"
    "                         #example: tagSize=2m, spacing=0.5m --> tagSpacing=0.25[-]\n";

// Kalibr's grid points (GridCalibrationTargetAprilgrid::createGridPoints, in m) of tag `id`'s
// corner j, with Kalibr's index of that corner (baseId, baseId + 1, baseId + cols + 1,
// baseId + cols for a grid of cols = 2 tagCols points per row).
Eigen::Vector3d kalibr_grid_point(int id, int j, int tag_cols, double size, double spacing) {
  const int cols = 2 * tag_cols;
  const int base = (id / tag_cols) * cols * 2 + (id % tag_cols) * 2;
  const int index[4] = {base, base + 1, base + cols + 1, base + cols};
  const int r = index[j] / cols, c = index[j] % cols;
  return {(c / 2) * (1 + spacing) * size + (c % 2) * size,
          (r / 2) * (1 + spacing) * size + (r % 2) * size, 0.0};
}

TEST(KalibrTarget, YamlGivesKalibrsCornerPositionsInMillimetres) {
  const Board b = read_kalibr_target_text(kTumviTarget, "april_6x6.yaml");
  EXPECT_EQ(b.name, "aprilgrid");
  EXPECT_EQ(b.family, "tag36h11b2");
  ASSERT_EQ(b.tags.size(), 36u);
  // Hand-computed: pitch (1 + 0.3) * 88 = 114.4 mm; tag 0 at the bottom-left, 5 at the
  // bottom-right, 6 above tag 0, 35 at the top-right.
  const auto corner = [&](int id, int k) { return b.find(id)->corners[size_t(k)]; };
  EXPECT_LT((corner(0, 0) - Eigen::Vector3d(0, 0, 0)).norm(), 1e-9);
  EXPECT_LT((corner(0, 2) - Eigen::Vector3d(88, 88, 0)).norm(), 1e-9);
  EXPECT_LT((corner(5, 1) - Eigen::Vector3d(660, 0, 0)).norm(), 1e-9);
  EXPECT_LT((corner(6, 3) - Eigen::Vector3d(0, 202.4, 0)).norm(), 1e-9);
  EXPECT_LT((corner(35, 0) - Eigen::Vector3d(572, 572, 0)).norm(), 1e-9);
  EXPECT_LT((corner(35, 2) - Eigen::Vector3d(660, 660, 0)).norm(), 1e-9);
  // Every corner where Kalibr's formula puts it (a 4 x 3 grid too, rows != cols).
  const Board wide = read_kalibr_target_text(
      "target_type: \"aprilgrid\"\ntagCols: 4\ntagRows: 3\ntagSize: 0.05\ntagSpacing: 0.25\n", "w");
  ASSERT_EQ(wide.tags.size(), 12u);
  for (const Board* board : {&b, &wide}) {
    const int tag_cols = board == &b ? 6 : 4;
    const double size = board == &b ? 0.088 : 0.05, spacing = board == &b ? 0.3 : 0.25;
    for (const BoardTag& t : board->tags) {
      for (int j = 0; j < 4; ++j) {
        const Eigen::Vector3d k = 1000 * kalibr_grid_point(t.id, j, tag_cols, size, spacing);
        EXPECT_LT((t.corners[size_t(j)] - k).norm(), 1e-9) << "tag " << t.id << " corner " << j;
      }
    }
  }
}

TEST(KalibrTarget, ReadBoardsTakesKalibrsYamlAndTheBoardsJsonEntry) {
  test::TemporaryFolder dir;
  {
    std::ofstream(dir.file("april_6x6.yaml")) << kTumviTarget;
    std::ofstream(dir.file("boards.json"))
        << R"({"boards": [{"name": "grid", "kalibr_aprilgrid": {"tagRows": 6, "tagCols": 6,)"
        << R"( "tagSize_m": 0.088, "tagSpacing": 0.3}}]})";
  }
  const std::vector<Board> from_yaml = read_boards(dir.file("april_6x6.yaml"));
  const std::vector<Board> from_json = read_boards(dir.file("boards.json"));
  ASSERT_EQ(from_yaml.size(), 1u);
  ASSERT_EQ(from_json.size(), 1u);
  EXPECT_EQ(from_json[0].family, "tag36h11b2");
  ASSERT_EQ(from_json[0].tags.size(), 36u);
  for (size_t i = 0; i < 36; ++i) {
    EXPECT_EQ(from_json[0].tags[i].id, from_yaml[0].tags[i].id);
    for (size_t k = 0; k < 4; ++k) {
      EXPECT_EQ(from_json[0].tags[i].corners[k], from_yaml[0].tags[i].corners[k]);
    }
  }
}

TEST(KalibrTarget, BadTargetsAreRefusedNamingTheFileAndTheField) {
  const auto refused = [](const std::string& text, std::initializer_list<std::string> parts) {
    test::expect_error_containing([&] { read_kalibr_target_text(text, "t.yaml"); }, parts);
  };
  const std::string ok = "tagCols: 6\ntagRows: 6\ntagSize: 0.088\ntagSpacing: 0.3\n";
  refused("target_type: 'checkerboard'\n" + ok, {"t.yaml", "checkerboard", "'aprilgrid' only"});
  refused(ok, {"t.yaml: field 'target_type' is missing"});
  refused("target_type: aprilgrid\ntagCols: 6\ntagRows: 6\ntagSpacing: 0.3\n",
          {"t.yaml: field 'tagSize' is missing"});
  refused("target_type: aprilgrid\ntagCols: 6\ntagRows: 6\ntagSize: -0.088\ntagSpacing: 0.3\n",
          {"field 'tagSize' is -0.088", "> 0"});
  refused("target_type: aprilgrid\ntagCols: 6\ntagRows: 6\ntagSize: 88\ntagSpacing: 0.3\n",
          {"field 'tagSize' is 88", "in metres"});
  refused("target_type: aprilgrid\ntagCols: 6\ntagRows: 6\ntagSize: 0.088\ntagSpacing: 0\n",
          {"field 'tagSpacing' is 0"});
  refused("target_type: aprilgrid\ntagCols: 6.5\ntagRows: 6\ntagSize: 0.088\ntagSpacing: 0.3\n",
          {"field 'tagCols'"});
  refused("target_type: aprilgrid\ntagCols: 0\ntagRows: 6\ntagSize: 0.088\ntagSpacing: 0.3\n",
          {"field 'tagCols'"});
  refused("target_type: 'aprilgrid\n" + ok, {"t.yaml: line 1", "unclosed"});
  refused("target_type: aprilgrid\n  tagCols: 6\n", {"t.yaml: line 2", "indented"});
  refused("target_type: aprilgrid\ntagCols: 6\ntagCols: 7\n", {"line 3", "appears twice"});
  refused("target_type: aprilgrid\n- 6\n", {"line 2", "not a `key: value` line"});
  refused("target_type: aprilgrid\ntagCols: 30\ntagRows: 30\ntagSize: 0.088\ntagSpacing: 0.3\n",
          {"30 x 30", "587"});
  // boards.json: a family other than the one Kalibr prints, Kalibr's yaml key for the size.
  test::expect_error_containing(
      [] {
        read_boards_text(R"({"boards": [{"name": "g", "family": "tag36h11", "kalibr_aprilgrid":
            {"tagRows": 2, "tagCols": 2, "tagSize_m": 0.05, "tagSpacing": 0.3}}]})",
                         "b.json");
      },
      {"b.json: field 'boards[0].family'", "tag36h11b2"});
  test::expect_error_containing(
      [] {
        read_boards_text(R"({"boards": [{"name": "g", "kalibr_aprilgrid":
            {"tagRows": 2, "tagCols": 2, "tagSize": 0.05, "tagSpacing": 0.3}}]})",
                         "b.json");
      },
      {"b.json: field 'boards[0].kalibr_aprilgrid.tagSize_m' is missing"});
}

// One rendered frame: camera, pose and image effects.
struct FrameCase {
  const char* name;
  bool fisheye;
  double tilt_deg, axis_deg, fill, dx, dy;
  double blur;
  int depth;
  double scale16;
};

std::vector<FrameCase> frame_cases() {
  std::vector<FrameCase> out;
  struct Pose {
    double tilt, axis, fill, dx, dy;
  };
  // The fisheye shows a board that fills much of its 190-degree view so close and so bent that
  // its edges are no longer straight lines over a tag: there it fills 30 to 60 %.
  const std::vector<Pose> pinhole_poses = {{0, 0, 0.6, 0, 0},     {35, 0, 0.45, 20, -10},
                                           {50, 60, 0.8, 0, 0},   {0, 0, 0.3, -60, 40},
                                           {40, 120, 0.3, 50, 0}, {30, 200, 0.9, 0, 0}};
  const std::vector<Pose> fisheye_poses = {{0, 0, 0.6, 0, 0},     {35, 0, 0.45, 20, -10},
                                           {50, 60, 0.45, 0, 0},  {0, 0, 0.3, -60, 40},
                                           {40, 120, 0.3, 50, 0}, {30, 200, 0.55, 0, 0}};
  for (bool fisheye : {false, true}) {
    for (const Pose& p : fisheye ? fisheye_poses : pinhole_poses) {
      for (double blur : {0.0, 0.8}) {
        out.push_back({fisheye ? "tumvi" : "euroc", fisheye, p.tilt, p.axis, p.fill, p.dx, p.dy,
                       blur, fisheye ? CV_16U : CV_8U, 257});
      }
    }
  }
  // A 12-bit range inside 16-bit words.
  out.push_back({"tumvi12", true, 35, 0, 0.6, 0, 0, 0.0, CV_16U, 16});
  out.push_back({"tumvi12", true, 35, 0, 0.6, 0, 0, 0.8, CV_16U, 16});
  return out;
}

// Narrowest width of a quad (px): the least distance from an edge to the far corners.
double narrowest_width(const std::array<Eigen::Vector2d, 4>& q) {
  double w = 1e30;
  for (size_t i = 0; i < 4; ++i) {
    const Eigen::Vector2d a = q[i], e = (q[(i + 1) % 4] - a).normalized();
    const Eigen::Vector2d n(-e.y(), e.x());
    w = std::min(
        w, std::max(std::abs(n.dot(q[(i + 2) % 4] - a)), std::abs(n.dot(q[(i + 3) % 4] - a))));
  }
  return w;
}

// Tags with cells at least this wide (px) across their narrowest width count as resolvable:
// libapriltag samples each of the 10 cells of the square once.
constexpr double kResolvableCellPx = 2.5;

struct Stats {
  int visible = 0, found = 0, resolvable = 0, found_resolvable = 0, wrong = 0;
  double sum = 0, max = 0;
  int corners = 0;
  double mean() const { return corners ? sum / corners : 0; }
  void add(const Stats& s) {
    visible += s.visible;
    found += s.found;
    resolvable += s.resolvable;
    found_resolvable += s.found_resolvable;
    wrong += s.wrong;
    sum += s.sum;
    corners += s.corners;
    max = std::max(max, s.max);
  }
};

// Tags of the board found in a frame, compared with the projected truth.
Stats score(const KalibrGridRenderer& r, const Board& board, const Eigen::Isometry3d& T,
            const std::vector<Detection>& found) {
  Stats s;
  const auto truth = r.truth(board, T);
  std::set<int> visible, resolvable;
  for (const BoardTag& t : board.tags) {
    if (!r.visible(t, T)) continue;
    visible.insert(t.id);
    if (narrowest_width(truth.at(t.id)) >= 10 * kResolvableCellPx) resolvable.insert(t.id);
  }
  for (const Detection& d : found) {
    if (!visible.count(d.id)) {
      if (!board.find(d.id)) ++s.wrong;  // a board tag partly in the image is not wrong
      continue;
    }
    double worst = 0;
    for (size_t k = 0; k < 4; ++k) {
      worst = std::max(worst, (d.corners[k] - truth.at(d.id)[k]).norm());
    }
    if (worst > 5) {
      ++s.wrong;
      continue;
    }
    ++s.found;
    if (resolvable.count(d.id)) ++s.found_resolvable;
    for (size_t k = 0; k < 4; ++k) {
      const double e = (d.corners[k] - truth.at(d.id)[k]).norm();
      s.sum += e;
      s.max = std::max(s.max, e);
      ++s.corners;
    }
  }
  s.visible = int(visible.size());
  s.resolvable = int(resolvable.size());
  return s;
}

struct Frame {
  FrameCase spec;
  Eigen::Isometry3d T_cam_board;
  cv::Mat image;
};

// One renderer per camera (tracing every pixel's ray takes a while).
const KalibrGridRenderer& renderer(bool fisheye) {
  static const KalibrGridRenderer euroc(testing::euroc_camera(), KalibrGridSpec{});
  static const KalibrGridRenderer tumvi(testing::tumvi_camera(), KalibrGridSpec{});
  return fisheye ? tumvi : euroc;
}

// The frames of frame_cases(), rendered once.
const std::vector<Frame>& frames() {
  static const std::vector<Frame> all = [] {
    std::vector<Frame> out;
    uint64_t seed = 1;
    for (const FrameCase& c : frame_cases()) {
      const KalibrGridRenderer& r = renderer(c.fisheye);
      Frame f{c, r.pose(c.tilt_deg, c.axis_deg, c.fill, c.dx, c.dy), {}};
      KalibrFrameOptions fo;
      fo.blur_sigma = c.blur;
      fo.noise_sigma = 1.5;
      fo.depth = c.depth;
      fo.scale16 = c.scale16;
      fo.seed = seed++;
      f.image = r.render(f.T_cam_board, fo);
      out.push_back(f);
    }
    return out;
  }();
  return all;
}

Stats run_frames(const DetectorOptions& o) {
  const Board board = read_kalibr_target_text(kTumviTarget, "april_6x6.yaml");
  TagDetector detector(o);
  Stats all;
  double total_ms = 0;
  for (const Frame& f : frames()) {
    const auto t0 = std::chrono::steady_clock::now();
    const std::vector<Detection> found = detector.detect(f.image);
    const double ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    total_ms += ms;
    const Stats s = score(renderer(f.spec.fisheye), board, f.T_cam_board, found);
    std::printf(
        "  %-7s tilt %2.0f fill %.2f blur %.1f: %2d/%2d tags (resolvable %2d/%2d), "
        "corners mean %.3f max %.3f px, %.1f ms\n",
        f.spec.name, f.spec.tilt_deg, f.spec.fill, f.spec.blur, s.found, s.visible,
        s.found_resolvable, s.resolvable, s.mean(), s.max, ms);
    all.add(s);
  }
  std::printf(
      "decimate %.0f: %d/%d tags (%.1f %%), resolvable %d/%d (%.1f %%), %d wrong, "
      "corners mean %.3f max %.3f px, %.1f ms per frame\n",
      o.decimate, all.found, all.visible, 100.0 * all.found / all.visible, all.found_resolvable,
      all.resolvable, 100.0 * all.found_resolvable / all.resolvable, all.wrong, all.mean(), all.max,
      total_ms / double(frames().size()));
  return all;
}

// 26 frames: EuRoC's pinhole (8 bits) and TUM VI's fisheye (16 bits, full and 12-bit range),
// frontal and tilted 30 to 50 degrees, sharp and blurred (sigma 0.8 px), noise 1.5 grey levels.
// Measured (decimate 1 / 2): 92.2 / 91.8 % of the 892 tags wholly in the frames, 96.7 / 97.5 % of
// the 718 with cells at least 2.5 px wide (the rest: far fisheye periphery), none wrong; corners
// mean 0.12 / 0.13 px, max 2.9 / 3.4 px (a few fisheye corners where the refinement gives up keep
// libapriltag's position). libapriltag alone found 34.4 / 50.8 % (23 wrong ids or corners at
// decimate 2), corners mean 0.30 / 0.35 px, max 4.6 / 4.9 px.
TEST(KalibrAprilgrid, TagsWithCornerSquaresAreFoundInSharpBlurredFisheyeAnd16BitFrames) {
  DetectorOptions o;
  o.family = "tag36h11b2";
  for (double decimate : {1.0, 2.0}) {
    o.decimate = decimate;
    const Stats s = run_frames(o);
    EXPECT_GE(s.found_resolvable, 0.95 * s.resolvable) << "decimate " << decimate;
    EXPECT_GE(s.found, 0.9 * s.visible) << "decimate " << decimate;
    EXPECT_EQ(s.wrong, 0);
    EXPECT_LT(s.mean(), 0.15) << "decimate " << decimate;
    EXPECT_LT(s.max, 4.0) << "decimate " << decimate;
  }
}

}  // namespace
}  // namespace crepuscular::tracking

namespace crepuscular::tracking {
namespace {

// The pose of the board read from Kalibr's yaml, from the tags found in EuRoC-like frames, is the
// rendering's T_cam_board in Kalibr's target frame (origin at tag 0's bottom-left corner, z out of
// the print). Measured: within 0.024 degrees and 0.26 mm at 0.5 to 1.1 m.
TEST(KalibrAprilgrid, BoardPoseIsTheTruthInKalibrsTargetFrame) {
  const Board board = read_kalibr_target_text(kTumviTarget, "april_6x6.yaml");
  const KalibrGridRenderer& r = renderer(false);
  DetectorOptions o;
  o.family = "tag36h11b2";
  TagDetector detector(o);
  int checked = 0;
  for (const Frame& f : frames()) {
    if (f.spec.fisheye) continue;
    const BoardCorners corners = match_board_corners(board, detector.detect(f.image));
    ASSERT_GE(corners.tag_ids.size(), 10u) << f.spec.name;
    const BoardPose pose = estimate_board_pose(r.camera().pinhole(), corners, nullptr);
    ASSERT_TRUE(pose.valid) << pose.problem;
    const Eigen::Isometry3d d = f.T_cam_board.inverse() * pose.T_cam_board;
    const double deg = Eigen::AngleAxisd(d.linear()).angle() * 180 / M_PI;
    const double mm = (pose.T_cam_board.translation() - f.T_cam_board.translation()).norm();
    std::printf("  tilt %2.0f blur %.1f at %.0f mm: %zu tags, rms %.3f px, %.4f deg, %.3f mm\n",
                f.spec.tilt_deg, f.spec.blur, f.T_cam_board.translation().norm(),
                corners.tag_ids.size(), pose.rms_px, deg, mm);
    EXPECT_LT(deg, 0.1);
    EXPECT_LT(mm, 1.0);
    ++checked;
  }
  EXPECT_EQ(checked, 12);
}

}  // namespace
}  // namespace crepuscular::tracking

namespace crepuscular::tracking {
namespace {

// Detection time (median of 7, decimate 2, 2 threads) of a EuRoC-size and a TUM VI-size frame, with
// the corner-square parting and refinement (tag36h11b2) and for libapriltag alone on the same
// image (family tag36h11: the same quad search, no parting). Printed only: times on a shared
// machine vary.
TEST(KalibrAprilgrid, DetectionTimePerFrame) {
  for (const size_t index : {size_t(0), size_t(12)}) {
    const Frame& f = frames()[index];
    for (const char* family : {"tag36h11b2", "tag36h11"}) {
      DetectorOptions o;
      o.family = family;
      TagDetector detector(o);
      std::vector<double> ms;
      size_t n = 0;
      for (int i = 0; i < 7; ++i) {
        const auto t0 = std::chrono::steady_clock::now();
        n = detector.detect(f.image).size();
        ms.push_back(
            std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0)
                .count());
      }
      std::nth_element(ms.begin(), ms.begin() + 3, ms.end());
      std::printf("  %dx%d %s: %.1f ms (%zu tags)\n", f.image.cols, f.image.rows, family, ms[3], n);
    }
  }
}

// A 16-bit PNG holding 12-bit data (TUM VI style) read as recordings read frames: mapped by its own
// range to 0..255, then the same tags as on the 16-bit image itself. OpenCV's own 8-bit reading
// (>> 8) leaves 16 grey levels and loses tags (measured: 24 tags found by range, 11 by >> 8).
TEST(KalibrAprilgrid, SixteenBitPngsAreReadByTheirOwnRange) {
  const Frame* twelve = nullptr;
  for (const Frame& f : frames()) {
    if (f.spec.scale16 == 16 && f.spec.blur > 0) twelve = &f;
  }
  ASSERT_NE(twelve, nullptr);
  std::vector<uint8_t> png;
  ASSERT_TRUE(cv::imencode(".png", twelve->image, png));
  std::string problem;
  const cv::Mat decoded = recordings::decode_image(png, &problem);
  ASSERT_EQ(decoded.type(), CV_8UC3) << problem;
  double lo = 0, hi = 0;
  cv::minMaxLoc(decoded.reshape(1), &lo, &hi);
  EXPECT_EQ(lo, 0);
  EXPECT_EQ(hi, 255);
  DetectorOptions o;
  o.family = "tag36h11b2";
  TagDetector detector(o);
  const std::vector<Detection> direct = detector.detect(twelve->image);
  const std::vector<Detection> read = detector.detect(decoded);
  ASSERT_EQ(direct.size(), read.size());
  for (size_t i = 0; i < direct.size(); ++i) {
    EXPECT_EQ(direct[i].id, read[i].id);
    EXPECT_LT((direct[i].corners[0] - read[i].corners[0]).norm(), 1e-9);
  }
  const std::vector<Detection> shifted =
      detector.detect(cv::imdecode(png, cv::IMREAD_GRAYSCALE));  // OpenCV's >> 8
  std::printf("16-bit with 12-bit data: %zu tags by own range, %zu by >> 8\n", read.size(),
              shifted.size());
  EXPECT_GT(read.size(), shifted.size());
  EXPECT_GE(read.size(), 20u);
  // A hot pixel does not squeeze the range.
  cv::Mat hot = twelve->image.clone();
  hot.at<uint16_t>(5, 5) = 65535;
  EXPECT_EQ(detector.detect(hot).size(), direct.size());
  // Regions of interest of a 16-bit image work too.
  const Eigen::Vector2d c = direct.front().center;
  const std::vector<Detection> in_roi =
      detector.detect(twelve->image, {cv::Rect(int(c.x()) - 30, int(c.y()) - 30, 60, 60)});
  ASSERT_FALSE(in_roi.empty());
  EXPECT_EQ(in_roi.front().id, direct.front().id);
}

}  // namespace
}  // namespace crepuscular::tracking
