// 3D Slicer markups files (.mrk.json): line markups in LPS or RAS.
#include "planning/trajectories/markups.hpp"

#include <fmt/format.h>
#include <nlohmann/json.hpp>

#include <algorithm>
#include <cmath>
#include <limits>

#include "foundation/error.hpp"
#include "foundation/json_fields.hpp"
#include "foundation/output_files.hpp"
#include "planning/imaging/ray_march.hpp"
#include "planning/imaging/sampling.hpp"

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

// ---------------------------------------------------------------------------------------------

std::vector<RegionTrajectory> region_trajectories(const AreaSafetyGeometry& g,
                                                  const Eigen::Vector3d& target,
                                                  const Volume<int32_t>& labels,
                                                  const Volume<float>& path_safety,
                                                  double max_distance_mm) {
  std::vector<RegionTrajectory> out;
  for (const AreaRegion& r : g.regions) {
    // The region's extruded vertex nearest to its centre.
    int best = -1;
    double best_d = std::numeric_limits<double>::infinity();
    for (size_t v = 0; v < g.vertices.size() && v < g.region.size(); ++v) {
      if (g.region[v] != r.id || (v < g.safe.size() && !g.safe[v])) continue;
      const double d = (g.vertices[v] - r.centre).squaredNorm();
      if (d < best_d) {
        best_d = d;
        best = int(v);
      }
    }
    if (best < 0) continue;
    const Eigen::Vector3d far = g.vertices[size_t(best)];
    const Eigen::Vector3d u = (far - target).normalized();
    if (!u.allFinite()) continue;
    RegionTrajectory t;
    t.region = r.id;
    t.leeway = r.leeway;
    t.size_mm3 = r.size_mm3;
    t.target = target;
    t.entry = far;
    if (labels.voxel_count() > 0) {
      const std::optional<Eigen::Vector3d> skin = outermost_body_exit(labels, target, u);
      if (!skin) continue;  // the skin on this line is not in the scan: no entry to offer
      if ((*skin - target).norm() > max_distance_mm) continue;  // beyond what was computed
      t.entry = *skin;
      t.on_skin = true;
    }
    t.value = path_safety.voxel_count() > 0
                  ? trilinear_finite(path_safety, path_safety.physical_to_index(t.entry))
                                            : std::numeric_limits<double>::quiet_NaN();
    out.push_back(t);
  }
  return out;
}

namespace {

std::string value_text(const std::string& value_name, double value) {
  if (!std::isfinite(value)) return value_name + " not computed at the entry";
  return value_name == "svv" ? fmt::format("svv {:.0f} %", value)
                             : fmt::format("{} {:.3g}", value_name, value);
}

nlohmann::json position(const Eigen::Vector3d& p, bool ras) {
  const Eigen::Vector3d q = ras ? flip_xy(p) : p;
  return {q.x(), q.y(), q.z()};
}

void check_system(const std::string& coordinate_system) {
  if (coordinate_system != "LPS" && coordinate_system != "RAS") {
    throw Error("markups: coordinate system \"" + coordinate_system +
                "\" is not supported (expected \"LPS\" or \"RAS\")");
  }
}

}  // namespace

nlohmann::json trajectories_markups_json(const std::vector<RegionTrajectory>& trajectories,
                                         const std::string& value_name,
                                         const std::string& coordinate_system) {
  check_system(coordinate_system);
  const bool ras = coordinate_system == "RAS";
  nlohmann::json markups = nlohmann::json::array();
  for (const RegionTrajectory& t : trajectories) {
    const std::string name = fmt::format("Region {}: leeway {:.2f}, {}", t.region + 1, t.leeway,
                                         value_text(value_name, t.value));
    markups.push_back(
        {{"type", "Line"},
         {"name", name},
         {"coordinateSystem", coordinate_system},
         {"coordinateUnits", "mm"},
         {"controlPoints",
          {{{"id", "1"},
            {"label", fmt::format("R{} entry", t.region + 1)},
            {"description", t.on_skin ? "on the skin" : "extruded safe direction (no skin found)"},
            {"position", position(t.entry, ras)},
            {"positionStatus", "defined"}},
           {{"id", "2"},
            {"label", "tumor centre"},
            {"position", position(t.target, ras)},
            {"positionStatus", "defined"}}}},
         {"measurements", {{{"name", "length"}, {"enabled", true}}}}});
  }
  return {{"@schema", kSchema}, {"markups", markups}};
}

nlohmann::json entries_markups_json(const std::vector<RegionTrajectory>& trajectories,
                                    const std::string& value_name,
                                    const std::string& coordinate_system) {
  check_system(coordinate_system);
  const bool ras = coordinate_system == "RAS";
  nlohmann::json points = nlohmann::json::array();
  for (size_t i = 0; i < trajectories.size(); ++i) {
    const RegionTrajectory& t = trajectories[i];
    points.push_back({{"id", std::to_string(i + 1)},
                      {"label", fmt::format("R{} entry", t.region + 1)},
                      {"description", fmt::format("leeway {:.2f}, {}", t.leeway,
                                                  value_text(value_name, t.value))},
                      {"position", position(t.entry, ras)},
                      {"positionStatus", "defined"}});
  }
  nlohmann::json markup = {{"type", "Fiducial"},
                           {"name", "Safe entries"},
                           {"coordinateSystem", coordinate_system},
                           {"coordinateUnits", "mm"},
                           {"controlPoints", points}};
  return {{"@schema", kSchema}, {"markups", nlohmann::json::array({markup})}};
}

}  // namespace crepuscular::planning
