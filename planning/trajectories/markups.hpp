// 3D Slicer markups files (.mrk.json): reading needle trajectories drawn as line markups, and
// writing them back, with the coordinate system stated in the file (DESIGN.md section 3).
#pragma once

#include <Eigen/Core>
#include <nlohmann/json_fwd.hpp>
#include <string>

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

}  // namespace crepuscular::planning
