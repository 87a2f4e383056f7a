// Marker boards: rigid sets of AprilTags (or OpenCV ArUco markers) with known corner positions
// (board frame, mm).
//
// A tag's corners are the corners of the square that libapriltag detects: the outer edge of the
// black border for tag36h11 (8 of its 10 cells; the white ring of one cell lies outside). Its
// "size" is the side of that square. Board frame of a printed board seen upright: x to the right,
// y down, z into the board (away from a camera that looks at the printed face), as libapriltag's
// own tag pose. Corner order = apriltag_detection_t::p: bottom-left, bottom-right, top-right,
// top-left of the tag as printed, i.e. (-s/2, +s/2), (+s/2, +s/2), (+s/2, -s/2), (-s/2, -s/2) around
// the tag centre (checked by rendering and detecting in tests/tracking/board_test.cpp).
// Note: libapriltag's detection coordinates put pixel centres at (i + 0.5, j + 0.5); OpenCV and
// calibration::CameraModel put them at (i, j). Measured on rendered tags: libapriltag's corners lie
// +0.50 px in x and y from the projected truth (tests/tracking/synthetic_test.cpp).
#pragma once

#include <Eigen/Core>
#include <array>
#include <string>
#include <vector>

#include <nlohmann/json_fwd.hpp>
#include <opencv2/core.hpp>

#include "calibration/aruco.hpp"

namespace crepuscular::tracking {

struct BoardTag {
  int id = 0;
  // Corners in the board frame (mm), in libapriltag's order of apriltag_detection_t::p.
  std::array<Eigen::Vector3d, 4> corners;

  Eigen::Vector3d center() const {
    return 0.25 * (corners[0] + corners[1] + corners[2] + corners[3]);
  }
  double side_mm() const { return (corners[1] - corners[0]).norm(); }
};

struct Board {
  std::string name;                       // e.g. "patient", "needle"
  std::string family = "tag36h11";
  std::vector<BoardTag> tags;
  std::vector<Eigen::Vector3d> fiducials;  // CT-visible fiducials (patient board), board frame mm
  // Solid black squares printed beside the tags, as the synthetic renderer draws them: Kalibr's
  // corner squares, a ChArUco board's chessboard squares. Centres in the board frame (mm), sides
  // parallel to the tags' edges. Made with the board from its description; boards.json as
  // write_boards writes it carries the tags only.
  struct InkSquare {
    Eigen::Vector3d centre = Eigen::Vector3d::Zero();
    double side_mm = 0;
  };
  std::vector<InkSquare> ink_squares;

  // The tag with this id, or nullptr.
  const BoardTag* find(int id) const;
};

// A planar grid of rows x cols tags of side tag_size_mm with gap_mm between them, ids from first_id,
// in the z = 0 plane of the board frame.
// Origin at the centre of the grid; ids run row by row from the top-left tag (smallest x, y).
Board make_grid_board(const std::string& name, int rows, int cols, double tag_size_mm,
                      double gap_mm, int first_id);

// The markers of OpenCV's boards (cv::aruco::CharucoBoard::create, cv::aruco::GridBoard::create
// of OpenCV 4.6), in OpenCV's own board frame: origin at the board's top-left corner as printed,
// x right, y down, z into the board (the convention above), so that poses equal those of
// cv::aruco::estimatePoseCharucoBoard and cv::aruco::estimatePoseBoard. family = the dictionary.
// Throw Error for sizes out of range, an unknown dictionary or ids outside it.
Board make_charuco_board(const std::string& name, const calibration::CharucoSpec& spec);
Board make_aruco_grid_board(const std::string& name, int markers_x, int markers_y, double marker_mm,
                            double separation_mm, const std::string& dictionary, int first_id);

// A Kalibr aprilgrid (Kalibr's target yaml: tagRows, tagCols, tagSize [m], tagSpacing [ratio of
// tagSize]), family tag36h11b2, corners in Kalibr's target frame (mm): origin at the bottom-left
// corner of tag 0's black square, x to the right and y up on the print as seen upright, z = x cross
// y (out of the print, toward a camera that looks at it). Ids as Kalibr numbers them: 0 at the
// bottom-left, along a row to the right, rows upward. Tag in row r (from the bottom) and column c:
// bottom-left corner at ((1 + tagSpacing) * tagSize * (c, r)), corners in libapriltag's order
// (bottom-left, bottom-right, top-right, top-left as printed), which is Kalibr's.
Board make_kalibr_aprilgrid_board(const std::string& name, int tag_rows, int tag_cols,
                                  double tag_size_mm, double tag_spacing);

// The four corners of an upright square tag of side size_mm centred at `center` (z = 0 plane).
std::array<Eigen::Vector3d, 4> square_tag_corners(const Eigen::Vector2d& center, double size_mm);

// boards.json: {"boards": [ {...}, ... ]}. Errors name the file and the field.
// A board: {"name": "patient", "family": "tag36h11" (default),
//           "tags": [{"id": 0, "corners": [[x,y,z] x 4]}, ...],
//           "grid": {"rows": 2, "cols": 3, "tag_size_mm": 40, "gap_mm": 10, "first_id": 0,
//                    "origin_mm": [0, 0, 0] (optional offset of the grid centre)},
//           "charuco": {"squares_x": 5, "squares_y": 7, "square_mm": 40, "marker_mm": 30,
//                       "dictionary": "DICT_6X6_250", "first_id": 0 (optional)},
//           "aruco_grid": {"markers_x": 4, "markers_y": 3, "marker_mm": 40, "separation_mm": 10,
//                          "dictionary": "DICT_6X6_250", "first_id": 0 (optional)},
//           "fiducials": [[x,y,z], ...]}
// "charuco" and "aruco_grid" (one of grid, charuco, aruco_grid per board) give the markers of
// make_charuco_board / make_aruco_grid_board and set family to their dictionary.
// "grid" is expanded into tags on reading (after any explicit "tags"); at least one tag; ids
// unique within a family across all boards and within the family's code count.
// A Kalibr aprilgrid board: {"name": "aprilgrid", "kalibr_aprilgrid": {"tagRows": 6, "tagCols": 6,
// "tagSize_m": 0.088, "tagSpacing": 0.3}} (family tag36h11b2, make_kalibr_aprilgrid_board).
// read_boards also reads Kalibr's own target yaml (told by its content, `target_type:`) as one
// board named "aprilgrid".
std::vector<Board> read_boards(const std::string& path);
// A Kalibr target yaml's text (flat `key: value  # comment` lines, as Kalibr writes it) as the
// aprilgrid board `name`; `what` names its origin in errors. Throws Error for other target types.
Board read_kalibr_target_text(const std::string& yaml_text, const std::string& what,
                              const std::string& name = "aprilgrid");
// The same from JSON text or a parsed document; `what` names its origin in errors.
std::vector<Board> read_boards_text(const std::string& json_text, const std::string& what);
std::vector<Board> read_boards_json(const nlohmann::json& document, const std::string& what);
// boards.json text of these boards (as write_boards writes it).
std::string boards_json_text(const std::vector<Board>& boards);
// Writes every tag explicitly (grids expanded); through a temporary file and a rename.
void write_boards(const std::string& path, const std::vector<Board>& boards);

// A tag's printed pattern from libapriltag's family definition (codes, bit_x/bit_y,
// width_at_border, total_width, reversed_border): total_width x total_width cells, CV_8U, 0 black,
// 255 white, row 0 at the top. The detected square spans cells [border_start, border_start +
// width_at_border) in both directions. An OpenCV dictionary's marker comes from
// cv::aruco::drawMarker (one black border cell) in a white ring of one cell.
struct TagPattern {
  cv::Mat cells;
  int width_at_border = 0;
  int total_width = 0;
  int border_start() const { return (total_width - width_at_border) / 2; }
};
// Throws Error for an unknown family or an id outside the family.
TagPattern tag_pattern(const std::string& family, int id);
// Number of codes in a family (e.g. 587 for tag36h11); throws Error for an unknown family.
int tag_family_code_count(const std::string& family);

}  // namespace crepuscular::tracking
