// Tests of tracking/detector: corners against exact projections, against OpenCV's own AprilTag
// dictionary detector, and region-of-interest search against full-frame search.
#include "tracking/detector.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <map>
#include <opencv2/aruco.hpp>
#include <opencv2/imgproc.hpp>

#include "foundation/error.hpp"
#include "tests/tracking/tag_scene.hpp"
#include "tracking/synthetic.hpp"

namespace crepuscular::tracking {
namespace {

using testing::hd_camera;
using testing::look_at_board;
using testing::project_corners;
using testing::SceneRenderer;

double corner_error(const std::array<Eigen::Vector2d, 4>& a, const std::array<Eigen::Vector2d, 4>& b) {
  double e = 0;
  for (int k = 0; k < 4; ++k) e = std::max(e, (a[k] - b[k]).norm());
  return e;
}

// Largest distance between our corners and cv::aruco's (mapped as explained below) over the tags
// both found; ids of both, sorted.
struct ArucoComparison {
  std::vector<int> our_ids, their_ids;
  double worst_px = 0;
};
ArucoComparison compare_with_aruco(const cv::Mat& image, const std::vector<Detection>& ours) {
  cv::Mat grey;
  cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
  std::vector<std::vector<cv::Point2f>> cv_corners;
  std::vector<int> cv_ids;
  cv::Ptr<cv::aruco::DetectorParameters> params = cv::aruco::DetectorParameters::create();
  params->cornerRefinementMethod = cv::aruco::CORNER_REFINE_SUBPIX;
  params->cornerRefinementWinSize = 3;
  cv::aruco::detectMarkers(grey, cv::aruco::getPredefinedDictionary(cv::aruco::DICT_APRILTAG_36h11),
                           cv_corners, cv_ids, params);
  ArucoComparison c;
  for (const Detection& d : ours) c.our_ids.push_back(d.id);
  c.their_ids = cv_ids;
  std::sort(c.our_ids.begin(), c.our_ids.end());
  std::sort(c.their_ids.begin(), c.their_ids.end());
  for (size_t m = 0; m < cv_ids.size(); ++m) {
    auto it = std::find_if(ours.begin(), ours.end(),
                           [&](const Detection& d) { return d.id == cv_ids[m]; });
    if (it == ours.end()) continue;
    for (int i = 0; i < 4; ++i) {
      const Eigen::Vector2d theirs(cv_corners[m][i].x, cv_corners[m][i].y);
      c.worst_px = std::max(c.worst_px, (theirs - it->corners[(5 - i) % 4]).norm());
    }
  }
  return c;
}

struct Scene {
  calibration::CameraModel cam = hd_camera();
  Board board = make_grid_board("patient", 2, 3, 40.0, 10.0, 0);
  Eigen::Isometry3d T = look_at_board(30, -20, 500, 20, -15, 10);
};

TEST(TagDetector, UnknownFamilyAndBadOptionsAreErrors) {
  DetectorOptions o;
  o.family = "tag99h1";
  EXPECT_THROW(TagDetector{o}, Error);
  o = {};
  o.decimate = 0.5;
  EXPECT_THROW(TagDetector{o}, Error);
  o = {};
  o.threads = 0;
  EXPECT_THROW(TagDetector{o}, Error);
  o = {};
  o.family = "tag25h9";
  EXPECT_NO_THROW(TagDetector{o});
}

TEST(TagDetector, EmptyImageHasNoDetections) {
  TagDetector det;
  EXPECT_TRUE(det.detect(cv::Mat()).empty());
  EXPECT_TRUE(det.detect(cv::Mat(), {cv::Rect(0, 0, 10, 10)}).empty());
  EXPECT_TRUE(det.detect(cv::Mat(720, 1280, CV_8UC3, cv::Scalar(128, 128, 128))).empty());
}

// The renderer maps each tag's bitmap onto the board; its corners are exact projections
// (cv::projectPoints, with distortion). Detected corners must land on them, in BoardTag order.
TEST(TagDetector, CornersMatchExactProjections) {
  Scene s;
  SceneRenderer renderer(s.cam);
  const cv::Mat image = renderer.render({{&s.board, s.T}});
  const auto truth = project_corners(s.cam, s.board, s.T);
  TagDetector det;
  const std::vector<Detection> found = det.detect(image);
  ASSERT_EQ(found.size(), 6u);
  std::vector<double> errors;
  for (const Detection& d : found) {
    ASSERT_TRUE(truth.count(d.id)) << "unexpected id " << d.id;
    EXPECT_EQ(d.hamming, 0);
    EXPECT_GT(d.decision_margin, 50.0);
    for (int k = 0; k < 4; ++k) errors.push_back((d.corners[k] - truth.at(d.id)[k]).norm());
  }
  std::sort(errors.begin(), errors.end());
  const double median = errors[errors.size() / 2];
  std::printf("corner error vs projection: median %.3f px, max %.3f px\n", median, errors.back());
  EXPECT_LT(median, 0.15);
  EXPECT_LT(errors.back(), 0.4);
}

TEST(TagDetector, GreyAndColourImagesGiveTheSameCorners) {
  Scene s;
  SceneRenderer renderer(s.cam);
  const cv::Mat image = renderer.render({{&s.board, s.T}});
  cv::Mat grey;
  cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
  TagDetector det;
  auto a = det.detect(image), b = det.detect(grey);
  ASSERT_EQ(a.size(), b.size());
  std::map<int, Detection> by_id;
  for (const Detection& d : b) by_id[d.id] = d;
  for (const Detection& d : a) EXPECT_LT(corner_error(d.corners, by_id.at(d.id).corners), 1e-9);
}

// OpenCV's aruco module carries the same tag36h11 codes (DICT_APRILTAG_36h11), but its marker is
// libapriltag's bitmap turned by 180 degrees, and it reports corners clockwise in the image from
// its marker's top-left. libapriltag's p runs counter-clockwise from the bitmap's bottom-left (p0
// bottom-left, p1 bottom-right, p2 top-right, p3 top-left). So OpenCV's top-left is p1 and
// cv[0] = p1, cv[1] = p0, cv[2] = p3, cv[3] = p2, i.e. cv[i] = p[(5 - i) % 4].
TEST(TagDetector, AgreesWithOpenCvArucoAprilTagDictionary) {
  Scene s;
  SceneRenderer renderer(s.cam);
  testing::RenderOptions ro;
  ro.noise_sigma = 2.0;
  for (int view = 0; view < 3; ++view) {
    const Eigen::Isometry3d T =
        look_at_board(-40.0 + 40 * view, 10.0 * view, 420.0 + 90 * view, 25 - 20 * view,
                      10 + 5 * view, -30 + 35 * view);
    ro.seed = 10 + view;
    const cv::Mat image = renderer.render({{&s.board, T}}, ro);
    TagDetector det;
    const ArucoComparison c = compare_with_aruco(image, det.detect(image));
    EXPECT_EQ(c.our_ids, c.their_ids) << "view " << view;
    EXPECT_EQ(c.our_ids.size(), 6u);
    std::printf("view %d: largest corner difference libapriltag vs cv::aruco %.3f px\n", view,
                c.worst_px);
    EXPECT_LT(c.worst_px, 0.5) << "view " << view;
  }
}

// The same cross-check on frames of the synthetic renderer (built-in scene: patient board of six
// tags and needle board of four, with noise): same ids, corners within 0.5 px.
TEST(TagDetector, AgreesWithOpenCvArucoOnSyntheticFrames) {
  SyntheticScene scene = builtin_scene();
  scene.noise_sigma = 2.0;
  SyntheticRenderer renderer(scene);
  TagDetector det;
  for (int64_t frame : {0, 45, 89}) {
    const cv::Mat image = renderer.render(frame);
    const ArucoComparison c = compare_with_aruco(image, det.detect(image));
    EXPECT_EQ(c.our_ids, c.their_ids) << "frame " << frame;
    EXPECT_EQ(c.our_ids.size(), 10u) << "frame " << frame;
    std::printf("synthetic frame %d: largest corner difference vs cv::aruco %.3f px\n", int(frame),
                c.worst_px);
    EXPECT_LT(c.worst_px, 0.5) << "frame " << frame;
  }
}

TEST(TagDetector, MergeRegionsJoinsOverlapsOnly) {
  auto merged = TagDetector::merge_regions(
      {cv::Rect(0, 0, 10, 10), cv::Rect(5, 5, 10, 10), cv::Rect(100, 100, 5, 5),
       cv::Rect(14, 14, 3, 3), cv::Rect(50, 50, 0, 4)});
  ASSERT_EQ(merged.size(), 2u);
  std::sort(merged.begin(), merged.end(), [](auto& a, auto& b) { return a.x < b.x; });
  EXPECT_EQ(merged[0], cv::Rect(0, 0, 17, 17));
  EXPECT_EQ(merged[1], cv::Rect(100, 100, 5, 5));
}

// Search in crops around the tags finds every tag the full frame finds, at the same corners (up to
// the decimation grid, which starts elsewhere in a crop); a
// crop that holds no tag finds nothing.
TEST(TagDetector, RegionSearchMatchesFullFrameSearch) {
  Scene s;
  SceneRenderer renderer(s.cam);
  testing::RenderOptions ro;
  ro.noise_sigma = 1.5;
  const cv::Mat image = renderer.render({{&s.board, s.T}}, ro);
  const auto truth = project_corners(s.cam, s.board, s.T);
  TagDetector det;
  const auto full = det.detect(image);
  std::vector<cv::Rect> rois;
  for (const auto& kv : truth) {
    std::vector<cv::Point2f> pts;
    for (const auto& c : kv.second) pts.emplace_back(float(c.x()), float(c.y()));
    cv::Rect r = cv::boundingRect(pts);
    rois.push_back(cv::Rect(r.x - 15, r.y - 15, r.width + 30, r.height + 30));
  }
  const auto cropped = det.detect(image, rois);
  ASSERT_EQ(cropped.size(), full.size());
  std::map<int, Detection> by_id;
  for (const Detection& d : full) by_id[d.id] = d;
  for (const Detection& d : cropped) {
    ASSERT_TRUE(by_id.count(d.id));
    EXPECT_LT(corner_error(d.corners, by_id[d.id].corners), 0.25) << "id " << d.id;
    EXPECT_LT(corner_error(d.corners, truth.at(d.id)), 0.4) << "id " << d.id;
  }
  // Only the first tag's crop: only that tag.
  const auto one = det.detect(image, {rois.front()});
  ASSERT_EQ(one.size(), 1u);
  EXPECT_EQ(one[0].id, truth.begin()->first);
  // A crop of background and one reaching outside the image: nothing, no crash.
  EXPECT_TRUE(det.detect(image, {cv::Rect(0, 0, 60, 60), cv::Rect(1250, 690, 100, 100)}).empty());
}

}  // namespace
}  // namespace crepuscular::tracking

namespace crepuscular::tracking {
namespace {

// A Kalibr aprilgrid as Kalibr prints it: 6 x 6 tag36h11 tags with a black border two cells wide
// (the square: 10 cells), tags 0.3 x their size apart, and black corner squares of the gap's size
// at every tag corner. Family "tag36h11b2" finds all 36 tags, each corner where it was drawn.
TEST(TagDetector, KalibrAprilgridWithATwoCellBorderIsDetectedWithAllItsTags) {
  const int cell = 8;                  // pixels per cell
  const int square = 10 * cell;        // the tag's black square
  const int gap = 3 * cell;            // tagSpacing 0.3
  const int margin = 2 * gap;
  const int n = 6;
  const int size = 2 * margin + n * square + (n - 1) * gap;
  cv::Mat image(size, size, CV_8U, cv::Scalar(255));
  std::map<int, cv::Point> origin;  // top-left pixel of each tag's square
  for (int row = 0; row < n; ++row) {
    for (int col = 0; col < n; ++col) {
      const int id = row * n + col;
      const TagPattern p = tag_pattern("tag36h11b2", id);
      ASSERT_EQ(p.width_at_border, 10);
      cv::Mat scaled;
      cv::resize(p.cells, scaled, cv::Size(), cell, cell, cv::INTER_NEAREST);
      const cv::Point at(margin + col * (square + gap), margin + row * (square + gap));
      const int b = p.border_start() * cell;
      scaled(cv::Rect(b, b, square, square)).copyTo(image(cv::Rect(at.x, at.y, square, square)));
      origin[id] = at;
      // Kalibr's corner squares, in the gaps at the four corners of the tag.
      for (int dy : {-gap, square})
        for (int dx : {-gap, square}) {
          image(cv::Rect(at.x + dx, at.y + dy, gap, gap)).setTo(0);
        }
    }
  }
  // As a camera sees the print: slightly blurred (the corner squares then no longer touch the
  // tags' corners in the thresholded image).
  cv::GaussianBlur(image, image, cv::Size(0, 0), 1.0);
  DetectorOptions o;
  o.family = "tag36h11b2";
  o.decimate = 1.0;
  TagDetector detector(o);
  const std::vector<Detection> found = detector.detect(image);
  std::map<int, const Detection*> by_id;
  for (const Detection& d : found) by_id[d.id] = &d;
  EXPECT_EQ(found.size(), 36u);
  for (int id = 0; id < 36; ++id) {
    ASSERT_TRUE(by_id.count(id)) << "tag " << id << " not found";
    // The centre of the square (pixel centres at integers in cv; libapriltag's at +0.5).
    const Eigen::Vector2d expected(origin[id].x + square / 2.0 - 0.5,
                                   origin[id].y + square / 2.0 - 0.5);
    EXPECT_LT((by_id[id]->center - expected).norm(), 0.75) << "tag " << id;
    for (const Eigen::Vector2d& c : by_id[id]->corners) {
      const double dx = std::abs(c.x() - expected.x()), dy = std::abs(c.y() - expected.y());
      EXPECT_NEAR(dx, square / 2.0, 0.75) << "tag " << id;
      EXPECT_NEAR(dy, square / 2.0, 0.75) << "tag " << id;
    }
  }
  // The one-cell-border family reads none of them as the right tag.
  o.family = "tag36h11";
  TagDetector standard(o);
  int right = 0;
  for (const Detection& d : standard.detect(image)) {
    const Eigen::Vector2d expected(origin[d.id % 36].x + square / 2.0 - 0.5,
                                   origin[d.id % 36].y + square / 2.0 - 0.5);
    if (d.id < 36 && (d.center - expected).norm() < 2) ++right;
  }
  EXPECT_EQ(right, 0);
}

}  // namespace
}  // namespace crepuscular::tracking
