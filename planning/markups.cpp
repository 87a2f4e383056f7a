// 3D Slicer markups files (.mrk.json): line markups in LPS or RAS.
#include "planning/markups.hpp"

#include <cmath>
#include <fstream>
#include <sstream>

#include "kernels/error.hpp"
#include "planning/output_files.hpp"

namespace crepuscular::planning {

namespace {

const char* kSchema =
    "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/"
    "Schema/markups-schema-v1.0.3.json#";

// RAS <-> LPS: negate x and y (the same map both ways).
Eigen::Vector3d flip_xy(const Eigen::Vector3d& p) { return {-p.x(), -p.y(), p.z()}; }

std::string string_field(const nlohmann::json& object, const char* key) {
  const auto it = object.find(key);
  if (it == object.end() || !it->is_string()) return {};
  return it->get<std::string>();
}

}  // namespace

LineMarkup parse_line_markup(const nlohmann::json& document, const std::string& source) {
  if (!document.is_object() || !document.contains("markups") || !document["markups"].is_array()) {
    throw Error(source +
                ": not a 3D Slicer markups file (expected an object with a \"markups\" "
                "array, as Slicer's .mrk.json)");
  }
  const nlohmann::json* line = nullptr;
  std::string types;
  for (const auto& m : document["markups"]) {
    const std::string type = m.is_object() ? string_field(m, "type") : std::string();
    if (type == "Line") {
      line = &m;
      break;
    }
    types += (types.empty() ? "" : ", ") + (type.empty() ? std::string("(no type)") : type);
  }
  if (!line) {
    throw Error(source + ": markups: no markup of type \"Line\" (found: " +
                (types.empty() ? std::string("none") : types) +
                "); draw the needle trajectory with Slicer's line tool");
  }
  LineMarkup result;
  result.name = string_field(*line, "name");

  // Slicer reads a file without "coordinateSystem" as LPS (vtkMRMLMarkupsJsonStorageNode).
  std::string system = "LPS";
  if (line->contains("coordinateSystem")) {
    if (!(*line)["coordinateSystem"].is_string()) {
      throw Error(source + ": markups[Line].coordinateSystem: expected \"LPS\" or \"RAS\"");
    }
    system = (*line)["coordinateSystem"].get<std::string>();
  }
  if (system != "LPS" && system != "RAS") {
    throw Error(source + ": markups[Line].coordinateSystem: \"" + system +
                "\" is not supported (expected \"LPS\" or \"RAS\")");
  }
  result.file_coordinate_system = system;
  if (line->contains("coordinateUnits")) {
    const auto& units = (*line)["coordinateUnits"];
    if (!units.is_string() || units.get<std::string>() != "mm") {
      throw Error(source + ": markups[Line].coordinateUnits: " + units.dump() +
                  " (expected \"mm\")");
    }
  }

  if (!line->contains("controlPoints") || !(*line)["controlPoints"].is_array()) {
    throw Error(source + ": markups[Line].controlPoints: missing (expected two control points)");
  }
  const auto& points = (*line)["controlPoints"];
  if (points.size() != 2) {
    throw Error(source + ": markups[Line].controlPoints: " + std::to_string(points.size()) +
                " points (expected 2: the entry and the target)");
  }
  Eigen::Vector3d p[2];
  std::string labels[2];
  for (int i = 0; i < 2; ++i) {
    const auto& cp = points[size_t(i)];
    const std::string where = source + ": markups[Line].controlPoints[" + std::to_string(i) + "]";
    if (!cp.is_object()) throw Error(where + ": expected an object");
    const std::string status = string_field(cp, "positionStatus");
    if (!status.empty() && status != "defined") {
      throw Error(where + ".positionStatus: \"" + status +
                  "\" (expected \"defined\": place the "
                  "point in Slicer before saving)");
    }
    if (!cp.contains("position") || !cp["position"].is_array() || cp["position"].size() != 3) {
      throw Error(where + ".position: expected [x, y, z] in mm");
    }
    for (int a = 0; a < 3; ++a) {
      const auto& v = cp["position"][size_t(a)];
      if (!v.is_number() || !std::isfinite(v.get<double>())) {
        throw Error(where + ".position: expected three finite numbers, found " +
                    cp["position"].dump());
      }
      p[i][a] = v.get<double>();
    }
    if (system == "RAS") p[i] = flip_xy(p[i]);
    labels[i] = string_field(cp, "label");
  }
  result.first = p[0];
  result.second = p[1];
  result.first_label = labels[0];
  result.second_label = labels[1];
  return result;
}

LineMarkup read_line_markup(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw Error(path + ": cannot open markups file");
  nlohmann::json document;
  try {
    in >> document;
  } catch (const nlohmann::json::exception& e) {
    throw Error(path + ": not valid JSON (" + e.what() + ")");
  }
  return parse_line_markup(document, path);
}

nlohmann::json line_markup_json(const LineMarkup& line, const std::string& coordinate_system) {
  if (coordinate_system != "LPS" && coordinate_system != "RAS") {
    throw Error("markups: coordinate system \"" + coordinate_system +
                "\" is not supported (expected \"LPS\" or \"RAS\")");
  }
  const bool ras = coordinate_system == "RAS";
  nlohmann::json points = nlohmann::json::array();
  const Eigen::Vector3d p[2] = {line.first, line.second};
  const std::string labels[2] = {line.first_label.empty() ? "entry" : line.first_label,
                                 line.second_label.empty() ? "target" : line.second_label};
  for (int i = 0; i < 2; ++i) {
    const Eigen::Vector3d q = ras ? flip_xy(p[i]) : p[i];
    points.push_back({{"id", std::to_string(i + 1)},
                      {"label", labels[i]},
                      {"position", {q.x(), q.y(), q.z()}},
                      {"positionStatus", "defined"}});
  }
  nlohmann::json markup = {{"type", "Line"},
                           {"coordinateSystem", coordinate_system},
                           {"coordinateUnits", "mm"},
                           {"controlPoints", points}};
  if (!line.name.empty()) markup["name"] = line.name;
  return {{"@schema", kSchema}, {"markups", nlohmann::json::array({markup})}};
}

void write_line_markup(const std::string& path, const LineMarkup& line,
                       const std::string& coordinate_system) {
  write_text_file(path, line_markup_json(line, coordinate_system).dump(2) + "\n");
}

}  // namespace crepuscular::planning
