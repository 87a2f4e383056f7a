// Tests of marker boards (tracking/board.hpp): grid geometry, boards.json round trip and errors,
// tag patterns against libapriltag's own apriltag_to_image, and the corner order checked by
// rendering a tag and detecting it with libapriltag.
#include "tracking/board.hpp"

#include <apriltag.h>
#include <tag36h11.h>
#include <gtest/gtest.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>

#include <opencv2/imgproc.hpp>

#include "foundation/error.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/temporary_folder.hpp"

namespace crepuscular::tracking {
namespace {

using test::expect_error_containing;

namespace fs = std::filesystem;

TEST(Board, GridTagsAreCentredRowMajorWithPitchSizePlusGap) {
  const Board b = make_grid_board("patient", 2, 3, 40.0, 10.0, 5);
  ASSERT_EQ(b.tags.size(), 6u);
  // Pitch 50 mm: columns at x = -50, 0, 50; rows at y = -25, 25; ids row by row from 5.
  EXPECT_EQ(b.tags[0].id, 5);
  EXPECT_EQ(b.tags[5].id, 10);
  EXPECT_TRUE(b.tags[0].center().isApprox(Eigen::Vector3d(-50, -25, 0)));
  EXPECT_TRUE(b.tags[5].center().isApprox(Eigen::Vector3d(50, 25, 0)));
  // Corner order: bottom-left, bottom-right, top-right, top-left (y down).
  const auto& c = b.tags[0].corners;
  EXPECT_TRUE(c[0].isApprox(Eigen::Vector3d(-70, -5, 0)));
  EXPECT_TRUE(c[1].isApprox(Eigen::Vector3d(-30, -5, 0)));
  EXPECT_TRUE(c[2].isApprox(Eigen::Vector3d(-30, -45, 0)));
  EXPECT_TRUE(c[3].isApprox(Eigen::Vector3d(-70, -45, 0)));
  EXPECT_DOUBLE_EQ(b.tags[3].side_mm(), 40.0);
  EXPECT_EQ(b.find(7), &b.tags[2]);
  EXPECT_EQ(b.find(99), nullptr);
}

TEST(Board, JsonRoundTripAndGridExpansion) {
  const test::TemporaryFolder dir;
  const std::string grid_path = (dir / "grid.json").string();
  std::ofstream(grid_path) << R"({"boards": [
    {"name": "patient", "grid": {"rows": 2, "cols": 3, "tag_size_mm": 40, "gap_mm": 10},
     "fiducials": [[-80, -50, 0], [80, -50, 0], [80, 50, 0], [-80, 50, 0]]},
    {"name": "needle", "family": "tag36h11",
     "tags": [{"id": 20, "corners": [[-10, 10, 0], [10, 10, 0], [10, -10, 0], [-10, -10, 0]]}],
     "grid": {"rows": 1, "cols": 2, "tag_size_mm": 20, "gap_mm": 5, "first_id": 21,
              "origin_mm": [0, 30, 0]}}]})";
  const std::vector<Board> boards = read_boards(grid_path);
  ASSERT_EQ(boards.size(), 2u);
  const Board expected = make_grid_board("patient", 2, 3, 40, 10, 0);
  ASSERT_EQ(boards[0].tags.size(), 6u);
  for (size_t t = 0; t < 6; ++t) {
    EXPECT_EQ(boards[0].tags[t].id, expected.tags[t].id);
    for (size_t k = 0; k < 4; ++k) {
      EXPECT_TRUE(boards[0].tags[t].corners[k].isApprox(expected.tags[t].corners[k])) << t << k;
    }
  }
  ASSERT_EQ(boards[0].fiducials.size(), 4u);
  EXPECT_TRUE(boards[0].fiducials[2].isApprox(Eigen::Vector3d(80, 50, 0)));
  ASSERT_EQ(boards[1].tags.size(), 3u);
  EXPECT_EQ(boards[1].tags[2].id, 22);
  EXPECT_TRUE(boards[1].tags[2].center().isApprox(Eigen::Vector3d(12.5, 30, 0)));

  const std::string out = (dir / "boards.json").string();
  write_boards(out, boards);
  const std::vector<Board> again = read_boards(out);
  ASSERT_EQ(again.size(), 2u);
  for (size_t b = 0; b < 2; ++b) {
    EXPECT_EQ(again[b].name, boards[b].name);
    EXPECT_EQ(again[b].family, boards[b].family);
    ASSERT_EQ(again[b].tags.size(), boards[b].tags.size());
    for (size_t t = 0; t < again[b].tags.size(); ++t) {
      EXPECT_EQ(again[b].tags[t].id, boards[b].tags[t].id);
      for (size_t k = 0; k < 4; ++k) {
        EXPECT_EQ(again[b].tags[t].corners[k], boards[b].tags[t].corners[k]);
      }
    }
    EXPECT_EQ(again[b].fiducials.size(), boards[b].fiducials.size());
  }
}

TEST(Board, BadFilesNameTheFileAndTheField) {
  const test::TemporaryFolder dir;
  const auto write = [&](const std::string& name, const std::string& text) {
    const std::string path = (dir / name).string();
    std::ofstream(path) << text;
    return path;
  };
  expect_error_containing([&] { read_boards((dir / "absent.json").string()); }, {"absent.json"});
  expect_error_containing([&] { read_boards(write("a.json", "{\"boards\": [")); },
                          {"a.json", "JSON"});
  expect_error_containing([&] { read_boards(write("b.json", "{\"tags\": []}")); },
                          {"b.json", "boards"});
  expect_error_containing(
      [&] {
        read_boards(write("c.json", R"({"boards": [{"name": "x", "tags": [{"id": 1,
          "corners": [[0,0,0],[1,0,0],[1,1,0]]}]}]})"));
      },
      {"c.json", "boards[0].tags[0].corners", "3 points", "expected 4"});
  expect_error_containing(
      [&] {
        read_boards(write("d.json", R"({"boards": [
          {"name": "a", "grid": {"rows": 1, "cols": 2, "tag_size_mm": 20, "gap_mm": 5}},
          {"name": "b", "grid": {"rows": 1, "cols": 2, "tag_size_mm": 20, "gap_mm": 5,
                                 "first_id": 1}}]})"));
      },
      {"d.json", "tag id 1", "'a'", "'b'"});
  expect_error_containing(
      [&] {
        read_boards(write("e.json", R"({"boards": [{"name": "a", "family": "tag99h1",
          "grid": {"rows": 1, "cols": 1, "tag_size_mm": 20, "gap_mm": 5}}]})"));
      },
      {"e.json", "boards[0].family", "tag99h1", "tag36h11"});
  expect_error_containing(
      [&] {
        read_boards(write("f.json", R"({"boards": [{"name": "a",
          "grid": {"rows": 1, "cols": 1, "tag_size_mm": 20, "gap_mm": 5, "first_id": 587}}]})"));
      },
      {"f.json", "587", "0 to 586"});
  expect_error_containing(
      [&] {
        read_boards(
            write("g.json", R"({"boards": [{"name": "a", "grid": {"rows": 2, "cols": 2}}]})"));
      },
      {"g.json", "boards[0].grid.tag_size_mm", "missing"});
  expect_error_containing(
      [&] { read_boards(write("h.json", R"({"boards": [{"name": "a"}]})")); },
      {"h.json", "no tags"});
}

TEST(Board, TagPatternMatchesLibapriltagImage) {
  apriltag_family_t* fam = tag36h11_create();
  for (int id : {0, 1, 17, 300, 586}) {
    const TagPattern p = tag_pattern("tag36h11", id);
    ASSERT_EQ(p.total_width, 10);
    ASSERT_EQ(p.width_at_border, 8);
    image_u8_t* im = apriltag_to_image(fam, id);
    ASSERT_EQ(im->width, p.total_width);
    // Cells inside the white ring: black border and data, as libapriltag draws them.
    for (int y = 1; y < 9; ++y) {
      for (int x = 1; x < 9; ++x) {
        EXPECT_EQ(int(p.cells.at<uint8_t>(y, x)), int(im->buf[y * im->stride + x]))
            << "id " << id << " cell " << x << "," << y;
      }
    }
    // libapriltag 3.3 does not export image_u8_destroy; the image is two calloc'ed blocks.
    free(im->buf);
    free(im);
    // The ring: white outside, black border inside.
    for (int i = 0; i < 10; ++i) {
      EXPECT_EQ(p.cells.at<uint8_t>(0, i), 255);
      EXPECT_EQ(p.cells.at<uint8_t>(9, i), 255);
      EXPECT_EQ(p.cells.at<uint8_t>(i, 0), 255);
      EXPECT_EQ(p.cells.at<uint8_t>(i, 9), 255);
    }
    for (int i = 1; i < 9; ++i) {
      EXPECT_EQ(p.cells.at<uint8_t>(1, i), 0);
      EXPECT_EQ(p.cells.at<uint8_t>(8, i), 0);
    }
  }
  tag36h11_destroy(fam);
  expect_error_containing([] { tag_pattern("tag36h11", 587); }, {"587", "tag36h11"});
  expect_error_containing([] { tag_pattern("nope", 0); }, {"nope"});
}

// Renders tag `id` upright at `cell_px` pixels per cell on white, rotates the image by quarter
// turns, detects it with libapriltag and checks that detection corner k lies where board corner k
// of square_tag_corners() maps: the BoardTag corner order is libapriltag's, following the tag.
TEST(Board, CornerOrderIsLibapriltagDetectionOrder) {
  const int id = 42;
  const int cell_px = 12;
  const int margin = 30;
  const TagPattern p = tag_pattern("tag36h11", id);
  cv::Mat tag;
  cv::resize(p.cells, tag, cv::Size(), cell_px, cell_px, cv::INTER_NEAREST);
  cv::Mat upright(tag.rows + 2 * margin, tag.cols + 2 * margin, CV_8U, cv::Scalar(255));
  tag.copyTo(upright(cv::Rect(margin, margin, tag.cols, tag.rows)));
  const int n = upright.cols;  // square image
  // Board frame (mm) -> upright pixel: tag side 8 cells = 8 * cell_px px, 1 mm = 1 px for side 96.
  const double side = p.width_at_border * cell_px;
  const std::array<Eigen::Vector3d, 4> corners = square_tag_corners({0, 0}, side);
  const double centre = (n - 1) / 2.0;  // pixel centres at integers: the image spans -0.5..n-0.5

  apriltag_family_t* fam = tag36h11_create();
  apriltag_detector_t* td = apriltag_detector_create();
  apriltag_detector_add_family(td, fam);
  td->quad_decimate = 1.0;
  for (int quarter = 0; quarter < 4; ++quarter) {
    cv::Mat img = upright.clone();
    for (int q = 0; q < quarter; ++q) cv::rotate(img, img, cv::ROTATE_90_CLOCKWISE);
    image_u8_t im{img.cols, img.rows, int32_t(img.step[0]), img.data};
    zarray_t* dets = apriltag_detector_detect(td, &im);
    ASSERT_EQ(zarray_size(dets), 1) << "quarter " << quarter;
    apriltag_detection_t* det = nullptr;
    zarray_get(dets, 0, &det);
    EXPECT_EQ(det->id, id);
    for (int k = 0; k < 4; ++k) {
      Eigen::Vector2d px(centre + corners[size_t(k)].x(), centre + corners[size_t(k)].y());
      // A clockwise quarter turn of the image maps pixel (x, y) to (n - 1 - y, x).
      for (int q = 0; q < quarter; ++q) px = Eigen::Vector2d(n - 1 - px.y(), px.x());
      // libapriltag puts pixel centres at (i + 0.5, j + 0.5), see tests/tracking/synthetic_test.cpp.
      EXPECT_NEAR(det->p[k][0] - 0.5, px.x(), 0.25) << "quarter " << quarter << " corner " << k;
      EXPECT_NEAR(det->p[k][1] - 0.5, px.y(), 0.25) << "quarter " << quarter << " corner " << k;
    }
    apriltag_detections_destroy(dets);
  }
  apriltag_detector_destroy(td);
  tag36h11_destroy(fam);
}

}  // namespace
}  // namespace crepuscular::tracking
