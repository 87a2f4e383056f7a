// OpenCV's ArUco dictionaries by name, and detection of ChArUco calibration targets.
#include "calibration/aruco.hpp"

#include <algorithm>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "foundation/error.hpp"

namespace crepuscular::calibration {

namespace {

struct DictionaryEntry {
  const char* name;
  cv::aruco::PREDEFINED_DICTIONARY_NAME id;
};

#define CREPUSCULAR_DICT(n) \
  { #n, cv::aruco::n }
constexpr DictionaryEntry kDictionaries[] = {
    CREPUSCULAR_DICT(DICT_4X4_50),         CREPUSCULAR_DICT(DICT_4X4_100),
    CREPUSCULAR_DICT(DICT_4X4_250),        CREPUSCULAR_DICT(DICT_4X4_1000),
    CREPUSCULAR_DICT(DICT_5X5_50),         CREPUSCULAR_DICT(DICT_5X5_100),
    CREPUSCULAR_DICT(DICT_5X5_250),        CREPUSCULAR_DICT(DICT_5X5_1000),
    CREPUSCULAR_DICT(DICT_6X6_50),         CREPUSCULAR_DICT(DICT_6X6_100),
    CREPUSCULAR_DICT(DICT_6X6_250),        CREPUSCULAR_DICT(DICT_6X6_1000),
    CREPUSCULAR_DICT(DICT_7X7_50),         CREPUSCULAR_DICT(DICT_7X7_100),
    CREPUSCULAR_DICT(DICT_7X7_250),        CREPUSCULAR_DICT(DICT_7X7_1000),
    CREPUSCULAR_DICT(DICT_ARUCO_ORIGINAL), CREPUSCULAR_DICT(DICT_APRILTAG_16h5),
    CREPUSCULAR_DICT(DICT_APRILTAG_25h9),  CREPUSCULAR_DICT(DICT_APRILTAG_36h10),
    CREPUSCULAR_DICT(DICT_APRILTAG_36h11),
};
#undef CREPUSCULAR_DICT

std::string joined_names() {
  std::string names;
  for (const DictionaryEntry& d : kDictionaries) names += std::string(" ") + d.name;
  return names;
}

cv::Mat grey_of(const cv::Mat& image) {
  cv::Mat grey;
  if (image.channels() == 3) {
    cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
  } else if (image.channels() == 4) {
    cv::cvtColor(image, grey, cv::COLOR_BGRA2GRAY);
  } else {
    grey = image;
  }
  if (grey.depth() != CV_8U) grey.convertTo(grey, CV_8U);
  return grey;
}

}  // namespace

std::vector<std::string> aruco_dictionary_names() {
  std::vector<std::string> names;
  for (const DictionaryEntry& d : kDictionaries) names.emplace_back(d.name);
  return names;
}

bool is_aruco_dictionary(const std::string& name) {
  for (const DictionaryEntry& d : kDictionaries) {
    if (name == d.name) return true;
  }
  return false;
}

cv::Ptr<cv::aruco::Dictionary> aruco_dictionary(const std::string& name) {
  for (const DictionaryEntry& d : kDictionaries) {
    if (name == d.name) return cv::aruco::getPredefinedDictionary(d.id);
  }
  throw Error("ArUco dictionary '" + name + "' is unknown; expected one of" + joined_names());
}

std::optional<CharucoSpec> parse_charuco_spec(const std::string& text) {
  const std::string prefix = "charuco:";
  if (text.rfind(prefix, 0) != 0) return std::nullopt;
  CharucoSpec spec;
  char x = 0, c1 = 0, c2 = 0, c3 = 0;
  std::istringstream in(text.substr(prefix.size()));
  in >> spec.squares_x >> x >> spec.squares_y >> c1 >> spec.square_mm >> c2 >> spec.marker_mm >> c3;
  std::getline(in, spec.dictionary);
  if (in.bad() || (x != 'x' && x != 'X') || c1 != ':' || c2 != ':' || c3 != ':' ||
      spec.dictionary.empty()) {
    throw Error("board \"" + text +
                "\": expected charuco:SQUARES_XxSQUARES_Y:SQUARE_MM:MARKER_MM:DICT, e.g. "
                "charuco:5x7:40:30:DICT_6X6_250 for 5 x 7 squares of 40 mm with markers of 30 mm");
  }
  check_charuco_spec(spec, "board \"" + text + "\"");
  return spec;
}

void check_charuco_spec(const CharucoSpec& spec, const std::string& what) {
  if (spec.squares_x < 2 || spec.squares_y < 2 || spec.squares_x > 100 || spec.squares_y > 100) {
    throw Error(what + ": " + std::to_string(spec.squares_x) + " x " +
                std::to_string(spec.squares_y) + " squares; expected 2 to 100 each way");
  }
  if (!(spec.square_mm > 0) || !(spec.marker_mm > 0) || !(spec.marker_mm < spec.square_mm)) {
    throw Error(what + ": square " + std::to_string(spec.square_mm) + " mm, marker " +
                std::to_string(spec.marker_mm) +
                " mm; expected 0 < marker < square (the marker sits inside a white square)");
  }
  cv::Ptr<cv::aruco::Dictionary> dict;
  try {
    dict = aruco_dictionary(spec.dictionary);
  } catch (const Error& e) {
    throw Error(what + ": " + e.what());
  }
  const int markers = spec.squares_x * spec.squares_y / 2;
  if (spec.first_id < 0 || spec.first_id + markers > dict->bytesList.rows) {
    throw Error(what + ": markers " + std::to_string(spec.first_id) + " to " +
                std::to_string(spec.first_id + markers - 1) + " do not fit " + spec.dictionary +
                " (ids 0 to " + std::to_string(dict->bytesList.rows - 1) +
                "); choose fewer squares or a larger dictionary");
  }
}

cv::Ptr<cv::aruco::CharucoBoard> make_charuco_board(const CharucoSpec& spec) {
  check_charuco_spec(spec, "ChArUco board");
  cv::Ptr<cv::aruco::CharucoBoard> board =
      cv::aruco::CharucoBoard::create(spec.squares_x, spec.squares_y, float(spec.square_mm),
                                      float(spec.marker_mm), aruco_dictionary(spec.dictionary));
  for (int& id : board->ids) id += spec.first_id;
  return board;
}

std::optional<CalibrationView> detect_charuco(const cv::Mat& image, const CharucoSpec& spec,
                                              const std::string& name) {
  if (image.empty()) return std::nullopt;
  const cv::Ptr<cv::aruco::CharucoBoard> board = make_charuco_board(spec);
  const cv::Mat grey = grey_of(image);
  std::vector<std::vector<cv::Point2f>> marker_corners;
  std::vector<int> marker_ids;
  cv::aruco::detectMarkers(grey, board->dictionary, marker_corners, marker_ids);
  if (marker_ids.empty()) return std::nullopt;
  std::vector<cv::Point2f> corners;
  std::vector<int> ids;
  cv::aruco::interpolateCornersCharuco(marker_corners, marker_ids, grey, board, corners, ids);
  if (ids.size() < 6) return std::nullopt;
  // OpenCV 4.6 returns the corners that cornerSubPix found shifted by +0.5 px in x and y
  // (opencv/opencv#25539, fixed upstream by opencv/opencv#28380): measured +0.51, +0.44 px on
  // rendered boards (tests/calibration/charuco_test.cpp). Refined again here, in OpenCV's pixel
  // convention, with a window that stays clear of the nearest marker corner.
  for (cv::Point2f& c : corners) {
    double nearest = 1e9;
    for (const auto& marker : marker_corners) {
      for (const cv::Point2f& m : marker) nearest = std::min(nearest, double(cv::norm(m - c)));
    }
    const int half = std::clamp(int(0.5 * nearest), 2, 5);
    std::vector<cv::Point2f> one = {c};
    cv::cornerSubPix(grey, one, cv::Size(half, half), cv::Size(-1, -1),
                     cv::TermCriteria(cv::TermCriteria::EPS + cv::TermCriteria::COUNT, 40, 0.001));
    c = one[0];
  }
  CalibrationView view;
  view.name = name;
  for (size_t k = 0; k < ids.size(); ++k) {
    const cv::Point3f& p = board->chessboardCorners[size_t(ids[k])];
    view.object_points.emplace_back(p.x, p.y, p.z);
    view.image_points.emplace_back(corners[k].x, corners[k].y);
  }
  return view;
}

}  // namespace crepuscular::calibration
