// Marker boards: grids, boards.json reading and writing, and the printed pattern of a tag taken
// from libapriltag's family definitions.
#include "tracking/board.hpp"

#include <fmt/format.h>

#include <apriltag.h>

#include <algorithm>
#include <cctype>
#include <climits>
#include <cmath>
#include <cstdlib>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <set>
#include <sstream>

#include "calibration/aruco.hpp"
#include "foundation/error.hpp"
#include "foundation/json_fields.hpp"
#include "foundation/log.hpp"
#include "foundation/output_files.hpp"
#include "foundation/text.hpp"
#include "tracking/tag_family.hpp"

namespace crepuscular::tracking {

namespace {

using nlohmann::json;

Eigen::Vector3d point_at(const json& j, const JsonPath& at) {
  const std::vector<double> v = as_numbers(j, at, 2, 3, "[x, y, z] in mm");
  return Eigen::Vector3d(v[0], v[1], v.size() == 3 ? v[2] : 0.0);
}

json point_json(const Eigen::Vector3d& p) { return json::array({p.x(), p.y(), p.z()}); }

// The explicit "tags" of a board: ids and corners.
void parse_tags(const json& tags, const JsonPath& at, Board& b) {
  as_array(tags, at);
  for (size_t t = 0; t < tags.size(); ++t) {
    const JsonPath tf = at.index(t);
    const json& tj = tags[t];
    if (!tj.is_object() || !tj.contains("id") || !tj.contains("corners")) {
      tf.fail("needs \"id\" and \"corners\" (4 points [x, y, z] in mm)");
    }
    BoardTag tag;
    tag.id = int(as_integer(tj["id"], tf.key("id"), INT32_MIN, INT32_MAX));
    const json& cj = tj["corners"];
    if (!cj.is_array() || cj.size() != 4) {
      tf.key("corners").fail("has " +
                             (cj.is_array() ? std::to_string(cj.size()) : std::string("no")) +
                             " points, expected 4 (apriltag_detection_t::p order)");
    }
    for (size_t c = 0; c < 4; ++c) {
      tag.corners[c] = point_at(cj[c], tf.key("corners").index(c));
    }
    if (tag.side_mm() <= 0.0) tf.key("corners").fail("coincide");
    b.tags.push_back(tag);
  }
}

// A "grid" of tags, expanded into b.tags.
void parse_grid(const json& g, const JsonPath& at, Board& b) {
  as_object(g, at);
  for (const char* key : {"rows", "cols", "tag_size_mm", "gap_mm"}) {
    if (!g.contains(key)) {
      at.key(key).fail("is missing (grid needs rows, cols, tag_size_mm, gap_mm; first_id optional)");
    }
  }
  const int rows = int(required_integer(g, "rows", at, INT32_MIN, INT32_MAX));
  const int cols = int(required_integer(g, "cols", at, INT32_MIN, INT32_MAX));
  const double size = required_number(g, "tag_size_mm", at);
  const double gap = required_number(g, "gap_mm", at);
  const int first = int(optional_integer(g, "first_id", at, 0, INT32_MIN, INT32_MAX));
  if (rows < 1 || cols < 1) {
    at.fail("needs rows and cols >= 1 (found " + std::to_string(rows) + " x " +
            std::to_string(cols) + ")");
  }
  if (!(size > 0) || gap < 0) at.fail("needs tag_size_mm > 0 and gap_mm >= 0");
  Board grid = make_grid_board(b.name, rows, cols, size, gap, first);
  if (g.contains("origin_mm")) {
    const Eigen::Vector3d origin = point_at(g["origin_mm"], at.key("origin_mm"));
    for (BoardTag& t : grid.tags) {
      for (Eigen::Vector3d& c : t.corners) c += origin;
    }
  }
  b.tags.insert(b.tags.end(), grid.tags.begin(), grid.tags.end());
}

// The markers of OpenCV's board in apriltag_detection_t::p order (cv::aruco lists a marker's
// corners from its top-left, clockwise as printed; p runs the other way from the bottom-left).
void add_opencv_markers(const cv::aruco::Board& board, Board& b) {
  for (size_t m = 0; m < board.ids.size(); ++m) {
    BoardTag t;
    t.id = board.ids[m];
    for (int k = 0; k < 4; ++k) {
      const cv::Point3f& p = board.objPoints[m][size_t(3 - k)];
      t.corners[k] = Eigen::Vector3d(p.x, p.y, p.z);
    }
    b.tags.push_back(t);
  }
}

// A "charuco" board's markers, expanded into b.tags; returns its dictionary.
std::string parse_charuco(const json& g, const JsonPath& at, Board& b) {
  as_object(g, at);
  for (const char* key : {"squares_x", "squares_y", "square_mm", "marker_mm", "dictionary"}) {
    if (!g.contains(key)) {
      at.key(key).fail(
          "is missing (charuco needs squares_x, squares_y, square_mm, marker_mm, dictionary; "
          "first_id optional)");
    }
  }
  calibration::CharucoSpec spec;
  spec.squares_x = int(required_integer(g, "squares_x", at, 2, 100));
  spec.squares_y = int(required_integer(g, "squares_y", at, 2, 100));
  spec.square_mm = required_number(g, "square_mm", at);
  spec.marker_mm = required_number(g, "marker_mm", at);
  spec.dictionary = optional_string(g, "dictionary", at, "");
  spec.first_id = int(optional_integer(g, "first_id", at, 0, 0, INT32_MAX));
  try {
    const Board charuco = make_charuco_board(b.name, spec);
    b.tags.insert(b.tags.end(), charuco.tags.begin(), charuco.tags.end());
    b.ink_squares.insert(b.ink_squares.end(), charuco.ink_squares.begin(),
                         charuco.ink_squares.end());
  } catch (const Error& e) {
    at.fail(std::string("is not a ChArUco board OpenCV can make: ") + e.what());
  }
  return spec.dictionary;
}

// An "aruco_grid" board's markers, expanded into b.tags; returns its dictionary.
std::string parse_aruco_grid(const json& g, const JsonPath& at, Board& b) {
  as_object(g, at);
  for (const char* key : {"markers_x", "markers_y", "marker_mm", "separation_mm", "dictionary"}) {
    if (!g.contains(key)) {
      at.key(key).fail(
          "is missing (aruco_grid needs markers_x, markers_y, marker_mm, separation_mm, "
          "dictionary; first_id optional)");
    }
  }
  const int mx = int(required_integer(g, "markers_x", at, 1, 1000));
  const int my = int(required_integer(g, "markers_y", at, 1, 1000));
  const double marker = required_number(g, "marker_mm", at);
  const double separation = required_number(g, "separation_mm", at);
  const std::string dictionary = optional_string(g, "dictionary", at, "");
  const int first = int(optional_integer(g, "first_id", at, 0, 0, INT32_MAX));
  if (!(marker > 0) || !(separation >= 0)) {
    at.fail("needs marker_mm > 0 and separation_mm >= 0 (found " + std::to_string(marker) +
            " and " + std::to_string(separation) + ")");
  }
  try {
    calibration::aruco_dictionary(dictionary);
  } catch (const Error& e) {
    at.key("dictionary").fail(std::string("names no dictionary: ") + e.what());
  }
  const Board grid = make_aruco_grid_board(b.name, mx, my, marker, separation, dictionary, first);
  b.tags.insert(b.tags.end(), grid.tags.begin(), grid.tags.end());
  return dictionary;
}

constexpr const char* kKalibrFamily = "tag36h11b2";

// A Kalibr aprilgrid from the fields of `g` (Kalibr's names; the size's key is size_key, in
// metres), as make_kalibr_aprilgrid_board.
Board parse_kalibr_aprilgrid(const json& g, const JsonPath& at, const std::string& size_key,
                             const std::string& name) {
  const std::string needs = "tagRows, tagCols, " + size_key + " [m] and tagSpacing [ratio]";
  for (const std::string& key :
       {std::string("tagRows"), std::string("tagCols"), size_key, std::string("tagSpacing")}) {
    if (!g.contains(key)) at.key(key).fail("is missing (a Kalibr aprilgrid needs " + needs + ")");
  }
  const int rows = int(required_integer(g, "tagRows", at, 1, 1000));
  const int cols = int(required_integer(g, "tagCols", at, 1, 1000));
  const double size_m = required_number(g, size_key, at);
  const double spacing = required_number(g, "tagSpacing", at);
  if (!(size_m > 0)) {
    at.key(size_key).fail("is " + std::to_string(size_m) +
                          ", expected the tag's side in metres (> 0)");
  }
  if (size_m > 10) {
    at.key(size_key).fail("is " + std::to_string(size_m) +
                          ", expected the tag's side in metres (Kalibr's unit; 0.088 is 88 mm)");
  }
  if (!(spacing > 0)) {
    at.key("tagSpacing")
        .fail("is " + std::to_string(spacing) +
              ", expected the gap between tags as a ratio of tagSize (> 0)");
  }
  const int codes = tag_family_code_count(kKalibrFamily);
  if (rows * cols > codes) {
    at.fail("has " + std::to_string(rows) + " x " + std::to_string(cols) + " tags, more than the " +
            std::to_string(codes) + " codes of tag36h11");
  }
  return make_kalibr_aprilgrid_board(name, rows, cols, 1000.0 * size_m, spacing);
}

// Kalibr's target yaml as flat fields: `key: value` lines, `#` comments, values quoted strings,
// numbers (integers kept as integers) or bare words. Anything else (nesting, lists) is refused.
json parse_flat_yaml(const std::string& text, const std::string& what) {
  json out = json::object();
  std::istringstream in(text);
  std::string line;
  int number = 0;
  while (std::getline(in, line)) {
    ++number;
    const std::string where = what + ": line " + std::to_string(number);
    // Kalibr writes plain ASCII; any other byte (binary data, another encoding) is not its file.
    for (const char ch : line) {
      const auto byte = static_cast<unsigned char>(ch);
      if (byte >= 0x80 || (byte < 0x20 && ch != '\t' && ch != '\r')) {
        throw Error(where + ": holds the byte " + fmt::format("0x{:02X}", unsigned(byte)) +
                    ", which is not plain text; expected a Kalibr target yaml (ASCII `key: value` "
                    "lines)");
      }
    }
    // Strip the comment (a # outside quotes).
    char quote = 0;
    size_t end = line.size();
    for (size_t i = 0; i < line.size(); ++i) {
      const char ch = line[i];
      if (quote) {
        if (ch == quote) quote = 0;
      } else if (ch == '\'' || ch == '"') {
        quote = ch;
      } else if (ch == '#') {
        end = i;
        break;
      }
    }
    std::string s = line.substr(0, end);
    while (!s.empty() && std::isspace(static_cast<unsigned char>(s.back()))) s.pop_back();
    if (s.empty() || s.find_first_not_of(" \t\r") == std::string::npos) continue;
    if (s.rfind("%YAML", 0) == 0 || s == "---") continue;
    if (std::isspace(static_cast<unsigned char>(s[0]))) {
      throw Error(where + ": \"" + s + "\" is indented; expected flat `key: value` lines");
    }
    const size_t colon = s.find(':');
    std::string key = s.substr(0, colon);
    const bool identifier = !key.empty() && std::all_of(key.begin(), key.end(), [](char ch) {
      return std::isalnum(static_cast<unsigned char>(ch)) || ch == '_';
    });
    if (colon == std::string::npos || !identifier) {
      throw Error(where + ": \"" + s + "\" is not a `key: value` line (Kalibr target yaml)");
    }
    std::string value = s.substr(colon + 1);
    value.erase(0, value.find_first_not_of(" \t"));
    if (value.empty()) throw Error(where + ": field " + key + " has no value");
    if (out.contains(key)) throw Error(where + ": field " + key + " appears twice");
    if (value[0] == '\'' || value[0] == '"') {
      if (value.size() < 2 || value.back() != value[0] ||
          value.find(value[0], 1) != value.size() - 1) {
        throw Error(where + ": field " + key + " has the unclosed string " + value);
      }
      out[key] = value.substr(1, value.size() - 2);
      continue;
    }
    const char* begin = value.c_str();
    char* stop = nullptr;
    const long long integer = std::strtoll(begin, &stop, 10);
    if (*stop == '\0') {
      out[key] = int64_t(integer);
      continue;
    }
    const double number_value = std::strtod(begin, &stop);
    if (*stop == '\0' && std::isfinite(number_value)) {
      out[key] = number_value;
    } else {
      out[key] = value;
    }
  }
  return out;
}

// Whether a boards file's text is a Kalibr target yaml rather than boards.json.
bool looks_like_kalibr_target(const std::string& text) {
  const size_t first = text.find_first_not_of(" \t\r\n");
  if (first == std::string::npos || text[first] == '{' || text[first] == '[') return false;
  return text.find("target_type") != std::string::npos;
}

Board parse_board(const json& j, const JsonPath& at) {
  as_object(j, at);
  Board b;
  if (!j.contains("name") || !j["name"].is_string() || j["name"].get<std::string>().empty()) {
    at.key("name").fail("is missing, expected a board name such as \"patient\" or \"needle\"");
  }
  b.name = j["name"].get<std::string>();
  const bool kalibr = j.contains("kalibr_aprilgrid");
  if (kalibr) b.family = kKalibrFamily;
  b.family = optional_string(j, "family", at, b.family);
  for (const char* key : {"charuco", "aruco_grid"}) {
    if (!j.contains(key)) continue;
    if (j.contains("grid") || j.contains("charuco") + j.contains("aruco_grid") > 1) {
      at.key(key).fail("comes with another of grid, charuco, aruco_grid; expected one per board");
    }
    const std::string dictionary = key == std::string("charuco")
                                       ? parse_charuco(j[key], at.key(key), b)
                                       : parse_aruco_grid(j[key], at.key(key), b);
    if (j.contains("family") && b.family != dictionary) {
      at.key("family").fail("is " + b.family + " but " + key + " uses " + dictionary +
                            "; expected the same (or no family)");
    }
    b.family = dictionary;
  }
  if (kalibr && b.family != kKalibrFamily) {
    at.key("family").fail("is " + b.family + ", but a kalibr_aprilgrid is printed as " +
                          kKalibrFamily + "; remove \"family\"");
  }
  const int codes = [&] {
    try {
      return tag_family_code_count(b.family);
    } catch (const Error& e) {
      throw Error(at.key("family").describe() + ": " + e.what());
    }
  }();
  if (j.contains("tags")) parse_tags(j["tags"], at.key("tags"), b);
  if (j.contains("grid")) parse_grid(j["grid"], at.key("grid"), b);
  if (kalibr) {
    const JsonPath kat = at.key("kalibr_aprilgrid");
    const Board grid =
        parse_kalibr_aprilgrid(as_object(j["kalibr_aprilgrid"], kat), kat, "tagSize_m", b.name);
    b.tags.insert(b.tags.end(), grid.tags.begin(), grid.tags.end());
    b.ink_squares.insert(b.ink_squares.end(), grid.ink_squares.begin(), grid.ink_squares.end());
  }
  if (b.tags.empty()) {
    at.fail("(board '" + b.name +
            "') has no tags; expected \"tags\", \"grid\" or "
            "\"kalibr_aprilgrid\"");
  }
  for (const BoardTag& t : b.tags) {
    if (t.id < 0 || t.id >= codes) {
      at.fail("has tag id " + std::to_string(t.id) + " (board '" + b.name +
              "'), outside family " + b.family + " (0 to " + std::to_string(codes - 1) + ")");
    }
  }
  if (j.contains("fiducials")) {
    const json& fj = as_array(j["fiducials"], at.key("fiducials"));
    for (size_t i = 0; i < fj.size(); ++i) {
      b.fiducials.push_back(point_at(fj[i], at.key("fiducials").index(i)));
    }
  }
  return b;
}

}  // namespace

const BoardTag* Board::find(int id) const {
  for (const BoardTag& t : tags) {
    if (t.id == id) return &t;
  }
  return nullptr;
}

std::array<Eigen::Vector3d, 4> square_tag_corners(const Eigen::Vector2d& center, double size_mm) {
  const double h = 0.5 * size_mm;
  return {Eigen::Vector3d(center.x() - h, center.y() + h, 0.0),
          Eigen::Vector3d(center.x() + h, center.y() + h, 0.0),
          Eigen::Vector3d(center.x() + h, center.y() - h, 0.0),
          Eigen::Vector3d(center.x() - h, center.y() - h, 0.0)};
}

Board make_grid_board(const std::string& name, int rows, int cols, double tag_size_mm,
                      double gap_mm, int first_id) {
  Board b;
  b.name = name;
  const double pitch = tag_size_mm + gap_mm;
  for (int r = 0; r < rows; ++r) {
    for (int c = 0; c < cols; ++c) {
      BoardTag t;
      t.id = first_id + r * cols + c;
      const Eigen::Vector2d center((c - 0.5 * (cols - 1)) * pitch, (r - 0.5 * (rows - 1)) * pitch);
      t.corners = square_tag_corners(center, tag_size_mm);
      b.tags.push_back(t);
    }
  }
  return b;
}

Board make_kalibr_aprilgrid_board(const std::string& name, int tag_rows, int tag_cols,
                                  double tag_size_mm, double tag_spacing) {
  Board b;
  b.name = name;
  b.family = kKalibrFamily;
  const double pitch = (1.0 + tag_spacing) * tag_size_mm;
  for (int r = 0; r < tag_rows; ++r) {
    for (int c = 0; c < tag_cols; ++c) {
      BoardTag t;
      t.id = r * tag_cols + c;
      const Eigen::Vector3d bl(c * pitch, r * pitch, 0.0);
      t.corners = {bl, bl + Eigen::Vector3d(tag_size_mm, 0, 0),
                   bl + Eigen::Vector3d(tag_size_mm, tag_size_mm, 0),
                   bl + Eigen::Vector3d(0, tag_size_mm, 0)};
      b.tags.push_back(t);
    }
  }
  // Kalibr's corner squares: side tagSpacing * tagSize, in every gap where tag corners meet and
  // along the outer rows and columns, touching the tags at their corners.
  const double gap = tag_spacing * tag_size_mm;
  for (int r = 0; r <= tag_rows; ++r) {
    for (int c = 0; c <= tag_cols; ++c) {
      b.ink_squares.push_back({Eigen::Vector3d(c * pitch - 0.5 * gap, r * pitch - 0.5 * gap, 0.0), gap});
    }
  }
  return b;
}

Board read_kalibr_target_text(const std::string& yaml_text, const std::string& what,
                              const std::string& name) {
  const json fields = parse_flat_yaml(yaml_text, what);
  const JsonPath at(what);
  if (!fields.contains("target_type")) {
    at.key("target_type").fail("is missing (a Kalibr target yaml, expected 'aprilgrid')");
  }
  const std::string type = as_string(fields["target_type"], at.key("target_type"));
  if (type != "aprilgrid") {
    at.key("target_type")
        .fail("is '" + type +
              "'; Crepuscular reads Kalibr targets of type "
              "'aprilgrid' only (for a checkerboard use --board chessboard:...)");
  }
  for (const std::string& field :
       unknown_fields(fields, {"target_type", "tagRows", "tagCols", "tagSize", "tagSpacing"}, at)) {
    spdlog::warn("{}: field {} is not one of Kalibr's aprilgrid fields; ignored", what, field);
  }
  return parse_kalibr_aprilgrid(fields, at, "tagSize", name);
}

std::vector<Board> read_boards(const std::string& path) {
  const std::string text = read_text_or_empty(path);
  if (looks_like_kalibr_target(text)) return {read_kalibr_target_text(text, path)};
  return read_boards_json(read_json_file(path, "boards file"), path);
}

std::vector<Board> read_boards_text(const std::string& json_text, const std::string& what) {
  return read_boards_json(parse_json_text(json_text, what), what);
}

std::vector<Board> read_boards_json(const json& j, const std::string& what) {
  if (!j.is_object() || !j.contains("boards") || !j["boards"].is_array()) {
    throw Error(what + ": field boards is missing, expected {\"boards\": [ ... ]}");
  }
  std::vector<Board> boards;
  std::map<std::string, std::map<int, std::string>> owner;  // family -> id -> board
  std::set<std::string> names;
  for (size_t i = 0; i < j["boards"].size(); ++i) {
    Board b = parse_board(j["boards"][i], JsonPath(what, "boards").index(i));
    if (!names.insert(b.name).second) {
      throw Error(what + ": board name '" + b.name + "' appears twice, expected unique names");
    }
    for (const BoardTag& t : b.tags) {
      auto& ids = owner[b.family];
      const auto it = ids.find(t.id);
      if (it != ids.end()) {
        throw Error(what + ": tag id " + std::to_string(t.id) + " (" + b.family +
                    ") is used by board '" + it->second + "' and board '" + b.name +
                    "'; expected each id on one tag only");
      }
      ids[t.id] = b.name;
    }
    boards.push_back(std::move(b));
  }
  if (boards.empty()) throw Error(what + ": field boards is empty, expected at least one board");
  return boards;
}

std::string boards_json_text(const std::vector<Board>& boards) {
  json out;
  out["boards"] = json::array();
  for (const Board& b : boards) {
    json bj;
    bj["name"] = b.name;
    bj["family"] = b.family;
    bj["tags"] = json::array();
    for (const BoardTag& t : b.tags) {
      json corners = json::array();
      for (const Eigen::Vector3d& c : t.corners) corners.push_back(point_json(c));
      bj["tags"].push_back({{"id", t.id}, {"corners", corners}});
    }
    if (!b.fiducials.empty()) {
      bj["fiducials"] = json::array();
      for (const Eigen::Vector3d& f : b.fiducials) bj["fiducials"].push_back(point_json(f));
    }
    out["boards"].push_back(bj);
  }
  return out.dump(2) + "\n";
}

void write_boards(const std::string& path, const std::vector<Board>& boards) {
  write_text_file(path, boards_json_text(boards));
}

Board make_charuco_board(const std::string& name, const calibration::CharucoSpec& spec) {
  Board b;
  b.name = name;
  b.family = spec.dictionary;
  const cv::Ptr<cv::aruco::CharucoBoard> board = calibration::make_charuco_board(spec);
  add_opencv_markers(*board, b);
  // The chessboard's black squares: the squares that hold no marker.
  const double side = board->getSquareLength();
  for (int y = 0; y < spec.squares_y; ++y) {
    for (int x = 0; x < spec.squares_x; ++x) {
      const Eigen::Vector3d centre((x + 0.5) * side, (y + 0.5) * side, 0.0);
      const bool marker = std::any_of(b.tags.begin(), b.tags.end(), [&](const BoardTag& t) {
        return (t.center() - centre).norm() < 0.25 * side;
      });
      if (!marker) b.ink_squares.push_back({centre, side});
    }
  }
  return b;
}

Board make_aruco_grid_board(const std::string& name, int markers_x, int markers_y, double marker_mm,
                            double separation_mm, const std::string& dictionary, int first_id) {
  const cv::Ptr<cv::aruco::GridBoard> grid =
      cv::aruco::GridBoard::create(markers_x, markers_y, float(marker_mm), float(separation_mm),
                                   calibration::aruco_dictionary(dictionary), first_id);
  Board b;
  b.name = name;
  b.family = dictionary;
  add_opencv_markers(*grid, b);
  return b;
}

int tag_family_code_count(const std::string& family) {
  if (calibration::is_aruco_dictionary(family)) {
    return calibration::aruco_dictionary(family)->bytesList.rows;
  }
  return int(open_tag_family(family)->ncodes);
}

namespace {

// An OpenCV dictionary's marker (cv::aruco::drawMarker, one black border cell) in a white ring of
// one cell.
TagPattern aruco_pattern(const std::string& dictionary, int id) {
  const cv::Ptr<cv::aruco::Dictionary> dict = calibration::aruco_dictionary(dictionary);
  if (id < 0 || id >= dict->bytesList.rows) {
    throw Error("tag id " + std::to_string(id) + " is outside dictionary " + dictionary +
                " (0 to " + std::to_string(dict->bytesList.rows - 1) + ")");
  }
  TagPattern p;
  p.width_at_border = dict->markerSize + 2;
  p.total_width = dict->markerSize + 4;
  p.cells = cv::Mat(p.total_width, p.total_width, CV_8U, cv::Scalar(255));
  cv::Mat marker;
  cv::aruco::drawMarker(dict, id, p.width_at_border, marker, 1);
  marker.copyTo(p.cells(cv::Rect(1, 1, p.width_at_border, p.width_at_border)));
  return p;
}

}  // namespace

TagPattern tag_pattern(const std::string& family, int id) {
  if (calibration::is_aruco_dictionary(family)) return aruco_pattern(family, id);
  const TagFamilyPtr fam = open_tag_family(family);
  if (id < 0 || uint32_t(id) >= fam->ncodes) {
    throw Error("tag id " + std::to_string(id) + " is outside family " + family + " (0 to " +
                std::to_string(fam->ncodes - 1) + ")");
  }
  TagPattern p;
  p.width_at_border = fam->width_at_border;
  p.total_width = fam->total_width;
  const int n = fam->total_width;
  p.cells = cv::Mat(n, n, CV_8U, cv::Scalar(0));
  // The white ring: just outside the black border, or (reversed border) just inside it.
  const int white_width = fam->width_at_border + (fam->reversed_border ? 0 : 2);
  const int white_start = (n - white_width) / 2;
  for (int i = 0; i < white_width; ++i) {
    p.cells.at<uint8_t>(white_start, white_start + i) = 255;
    p.cells.at<uint8_t>(white_start + white_width - 1, white_start + i) = 255;
    p.cells.at<uint8_t>(white_start + i, white_start) = 255;
    p.cells.at<uint8_t>(white_start + i, white_start + white_width - 1) = 255;
  }
  // Data bits: bit i is code bit (nbits - 1 - i), at cell (bit_x, bit_y) from the border start;
  // positions may lie outside the border (negative as signed numbers) for the newer families.
  const uint64_t code = fam->codes[id];
  const int start = p.border_start();
  for (uint32_t i = 0; i < fam->nbits; ++i) {
    const int x = int32_t(fam->bit_x[i]) + start;
    const int y = int32_t(fam->bit_y[i]) + start;
    const bool white = (code >> (fam->nbits - 1 - i)) & 1u;
    if (x >= 0 && y >= 0 && x < n && y < n) p.cells.at<uint8_t>(y, x) = white ? 255 : 0;
  }
  return p;
}

}  // namespace crepuscular::tracking
