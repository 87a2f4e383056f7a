// 3D Slicer markups files (.mrk.json): reading needle trajectories drawn as line markups, and
// writing them back, with the coordinate system stated in the file (docs/ARCHITECTURE.md §3).
#pragma once

#include <Eigen/Core>
#include <nlohmann/json_fwd.hpp>
#include <string>
#include <vector>

#include "planning/imaging/volume.hpp"
#include "planning/safety/area_safety.hpp"

namespace crepuscular::planning {

// A straight line between two control points, LPS mm, in the order they appear in the file.
struct LineMarkup {
  std::string name;  // the markup's "name" (may be empty)
  Eigen::Vector3d first = Eigen::Vector3d::Zero();
  Eigen::Vector3d second = Eigen::Vector3d::Zero();
  std::string first_label, second_label;  // control point labels (may be empty)
  std::string file_coordinate_system;     // "LPS" or "RAS": as found in (or implied for) the file
};

// Reads the first markup of type "Line" in a Slicer markups JSON document (`source` names the
// file in errors). Slicer writes "coordinateSystem": "LPS" (since Slicer 4.11) or "RAS"; a file
// without the field is LPS, as Slicer itself reads it (vtkMRMLMarkupsJsonStorageNode defaults to
// "LPS"). RAS positions are converted to LPS by negating x and y. "coordinateUnits", when given,
// must be "mm". Throws Error naming `source` and the field when there is no line markup, when it
// does not have exactly two control points with three finite coordinates, or when the coordinate
// system is neither LPS nor RAS.
LineMarkup parse_line_markup(const nlohmann::json& document, const std::string& source);
LineMarkup read_line_markup(const std::string& path);

// A Slicer markups JSON document holding one line markup, written in `coordinate_system`
// ("LPS" or "RAS"; points are given in LPS and converted). Opens in 3D Slicer 4.11 and later.
nlohmann::json line_markup_json(const LineMarkup& line, const std::string& coordinate_system);
void write_line_markup(const std::string& path, const LineMarkup& line,
                       const std::string& coordinate_system = "LPS");

// --- The plan's markups: one planned trajectory per safe region

// The planned trajectory of one safe region of the area safety geometry: from the region's most
// central direction (its extruded vertex nearest to the region's centre, so the one farthest
// from its unsafe border) to the tumor centre. The entry lies on the skin where the label map
// shows it (the outermost exit of that line from the body), else at the extruded vertex.
struct RegionTrajectory {
  int region = 0;         // region id (0 = largest)
  double leeway = 0;      // the region's size relative to the largest, 0..1
  double size_mm3 = 0;
  Eigen::Vector3d entry = Eigen::Vector3d::Zero(), target = Eigen::Vector3d::Zero();
  bool on_skin = false;   // entry found on the skin of the label map
  double value = 0;       // path safety at the entry (NaN where none was computed)
};

// One trajectory per safe region, largest region first. A region gets none when its line meets
// the skin only at the label map's edge (skin outside the scan: unknown) or beyond
// `max_distance_mm` (the region of interest: the path there was not computed, so not known to
// be safe). `labels` may be empty.
std::vector<RegionTrajectory> region_trajectories(const AreaSafetyGeometry& geometry,
                                                  const Eigen::Vector3d& target,
                                                  const Volume<int32_t>& labels,
                                                  const Volume<float>& path_safety,
                                                  double max_distance_mm);

// trajectories.mrk.json: one Line markup per trajectory (entry, then target), named with its
// region, leeway and `value_name`'s path safety at the entry. entries.mrk.json: the entries as
// one point list. Both Slicer markups schema v1.0.3, in `coordinate_system` (LPS or RAS).
nlohmann::json trajectories_markups_json(const std::vector<RegionTrajectory>& trajectories,
                                         const std::string& value_name,
                                         const std::string& coordinate_system = "LPS");
nlohmann::json entries_markups_json(const std::vector<RegionTrajectory>& trajectories,
                                    const std::string& value_name,
                                    const std::string& coordinate_system = "LPS");

}  // namespace crepuscular::planning
