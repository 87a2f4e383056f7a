// OpenCV's ArUco dictionaries by name and ChArUco calibration targets (cv::aruco, OpenCV 4.6):
// the one place that maps names such as DICT_6X6_250 to cv::aruco's predefined dictionaries.
#pragma once

#include <opencv2/aruco/charuco.hpp>
#include <optional>
#include <string>
#include <vector>

#include "calibration/intrinsics.hpp"

namespace crepuscular::calibration {

// Names of OpenCV's predefined dictionaries: DICT_4X4_50 ... DICT_7X7_1000, DICT_ARUCO_ORIGINAL,
// DICT_APRILTAG_16h5 ... DICT_APRILTAG_36h11 (OpenCV's bitmaps, turned by 180 degrees against
// libapriltag's families of the same codes).
std::vector<std::string> aruco_dictionary_names();
bool is_aruco_dictionary(const std::string& name);
// Throws Error naming the accepted names when `name` is not one of them.
cv::Ptr<cv::aruco::Dictionary> aruco_dictionary(const std::string& name);

// "charuco:SQUARES_XxSQUARES_Y:SQUARE_MM:MARKER_MM:DICT", squares counted as
// cv::aruco::CharucoBoard::create counts them (5x7 has 4 x 6 inner corners); marker ids from 0.
struct CharucoSpec {
  int squares_x = 0;
  int squares_y = 0;
  double square_mm = 0;
  double marker_mm = 0;
  std::string dictionary;
  int first_id = 0;  // id of the first marker; the others follow in OpenCV's order
};
// Parses the spec; throws Error naming the text when it is malformed. Returns nullopt when the
// text does not start with "charuco:".
std::optional<CharucoSpec> parse_charuco_spec(const std::string& text);
// Throws Error (prefixed by `what`) for sizes out of range, a marker not smaller than its square,
// an unknown dictionary, or more markers than the dictionary holds.
void check_charuco_spec(const CharucoSpec& spec, const std::string& what);
// OpenCV's board: markers and chessboard corners in OpenCV's board frame (mm; origin at the
// board's top-left corner as printed, x right, y down, z into the board).
cv::Ptr<cv::aruco::CharucoBoard> make_charuco_board(const CharucoSpec& spec);

// The chessboard corners of a ChArUco board (cv::aruco::detectMarkers, then
// cv::aruco::interpolateCornersCharuco, refined again with cornerSubPix to undo OpenCV 4.6's
// half-pixel shift of its refined corners): object points in
// OpenCV's board frame, pixels in OpenCV's convention. Returns nullopt when fewer than 6 corners
// are found.
std::optional<CalibrationView> detect_charuco(const cv::Mat& image, const CharucoSpec& spec,
                                              const std::string& name);

}  // namespace crepuscular::calibration
