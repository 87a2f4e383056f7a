// 3D Slicer markups files (.mrk.json): line markups in LPS or RAS.
#include "planning/trajectories/markups.hpp"

#include <nlohmann/json.hpp>

#include "foundation/error.hpp"
#include "foundation/json_fields.hpp"
#include "foundation/output_files.hpp"

namespace crepuscular::planning {

namespace {

const char* kSchema =
    "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/"
    "Schema/markups-schema-v1.0.3.json#";

// RAS <-> LPS: negate x and y (the same map both ways).
Eigen::Vector3d flip_xy(const Eigen::Vector3d& p) { return {-p.x(), -p.y(), p.z()}; }

}  // namespace

LineMarkup parse_line_markup(const nlohmann::json& document, const std::string& source) {
  if (!document.is_object() || !document.contains("markups") || !document["markups"].is_array()) {
    throw Error(source +
                ": not a 3D Slicer markups file (expected an object with a \"markups\" "
                "array, as Slicer's .mrk.json)");
  }
  const nlohmann::json* line = nullptr;
  JsonPath at(source);
  std::string types;
  const nlohmann::json& markups = document["markups"];
  for (size_t i = 0; i < markups.size(); ++i) {
    const nlohmann::json& m = markups[i];
    const JsonPath mi = JsonPath(source, "markups").index(i);
    const std::string type = m.is_object() ? optional_string(m, "type", mi, "") : std::string();
    if (type == "Line") {
      line = &m;
      at = mi;
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
  result.name = optional_string(*line, "name", at, "");

  // Slicer reads a file without "coordinateSystem" as LPS (vtkMRMLMarkupsJsonStorageNode).
  const std::string system = optional_string(*line, "coordinateSystem", at, "LPS");
  if (system != "LPS" && system != "RAS") {
    at.key("coordinateSystem")
        .fail("is \"" + system + "\", which is not supported (expected \"LPS\" or \"RAS\")");
  }
  result.file_coordinate_system = system;
  if (line->contains("coordinateUnits")) {
    const auto& units = (*line)["coordinateUnits"];
    if (!units.is_string() || units.get<std::string>() != "mm") {
      at.key("coordinateUnits").fail("is " + units.dump() + " (expected \"mm\")");
    }
  }

  const JsonPath points_at = at.key("controlPoints");
  if (!line->contains("controlPoints") || !(*line)["controlPoints"].is_array()) {
    points_at.fail("is missing (expected two control points)");
  }
  const auto& points = (*line)["controlPoints"];
  if (points.size() != 2) {
    points_at.fail("has " + std::to_string(points.size()) +
                   " points (expected 2: the entry and the target)");
  }
  Eigen::Vector3d p[2];
  std::string labels[2];
  for (int i = 0; i < 2; ++i) {
    const auto& cp = points[size_t(i)];
    const JsonPath where = points_at.index(size_t(i));
    as_object(cp, where);
    const std::string status = optional_string(cp, "positionStatus", where, "");
    if (!status.empty() && status != "defined") {
      where.key("positionStatus")
          .fail("is \"" + status +
                "\" (expected \"defined\": place the point in Slicer before saving)");
    }
    const std::vector<double> v =
        as_numbers(required_field(cp, "position", where), where.key("position"), 3, 3,
                   "[x, y, z] in mm");
    p[i] = Eigen::Vector3d(v[0], v[1], v[2]);
    if (system == "RAS") p[i] = flip_xy(p[i]);
    labels[i] = optional_string(cp, "label", where, "");
  }
  result.first = p[0];
  result.second = p[1];
  result.first_label = labels[0];
  result.second_label = labels[1];
  return result;
}

LineMarkup read_line_markup(const std::string& path) {
  return parse_line_markup(read_json_file(path, "markups file"), path);
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
