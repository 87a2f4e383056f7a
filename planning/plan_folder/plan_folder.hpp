// The plan folder (PLAN_DIR), written by the plan pipeline and read by every later step: its
// format in one place. Files: blocking.nii.gz, roi.nii.gz, path_safety_<value>.nii.gz (NaN
// outside the region of interest), path_safety_<value>_classes.seg.nrrd (the value's classes for
// 3D Slicer, docs/ARCHITECTURE.md §4; written by the plan pipeline, not read back here),
// area_safety.vtk (optional) and plan.json, whose pieces are made here (geometry, inputs, classes)
// and read back by load_plan.
#pragma once

#include <Eigen/Core>
#include <map>
// The full json.hpp: PlanData holds plan.json as a JSON value.
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "planning/imaging/volume.hpp"
#include "planning/preprocessing/vulnerability.hpp"
#include "planning/safety/area_safety.hpp"
#include "planning/safety/safety_classes.hpp"

namespace crepuscular::planning {

// --- Writing plan.json
// ----------------------------------------------------------------------------

// Hex MD5 of a file's bytes (a folder: of its files' names and bytes, in name order).
std::string file_checksum(const std::string& path);

// The class thresholds of one value as written in plan.json.
nlohmann::json classes_json(unsigned value_bit, const Volume<float>& volume);
// The same for classes already taken (PathSafetyResult::classes).
nlohmann::json classes_json(const SafetyClasses& classes);

// A grid as plan.json writes it: dims, origin_lps_mm, spacing_mm, direction (rows).
nlohmann::json geometry_json(const ImageGeometry& geometry);

// An input file of the plan: its absolute path, its path relative to the plan folder (so a plan
// moved together with its inputs, e.g. a whole demo folder, still finds them) and its checksum.
// null when `path` is empty.
nlohmann::json input_json(const std::string& path, const std::string& plan_dir);

// --- Reading a plan folder
// ------------------------------------------------------------------------

struct PlanLoadOptions {
  bool blocking = true;     // PLAN_DIR/blocking.nii.gz (required when true)
  bool path_safety = true;  // every path_safety_<value>.nii.gz listed in plan.json
  std::string only_value;   // when set: load only this path safety value ("svv", ...)
  bool labels = true;       // the label map: labels_override, else plan.json inputs.labels
  std::string labels_override;
  std::vector<std::string> series;  // DICOM series chosen (VolumeReadOptions::dicom_series)
  bool tumor = true;        // the tumor mask of plan.json inputs.tumor (skipped if missing)
  bool area_safety = true;  // PLAN_DIR/area_safety.vtk when present
  bool check_inputs = true; // compare every input still present with its checksum in plan.json
};

// An input of the plan (plan.json "inputs") whose file is no longer the one planned with.
struct ChangedInput {
  std::string role;  // "tumor", "labels", "label_maps[1]", "ct", "vulnerability", ...
  std::string path;
  std::string message;  // one line for the user: what changed and what it means
};

// A plan folder as the plan pipeline wrote it. Optional parts are empty when absent.
struct PlanData {
  std::string dir;
  nlohmann::json json;  // plan.json
  ImageGeometry grid;   // path safety grid (plan.json "grid")
  double gamma_mm = 0;  // sampling step bound of the plan (h / 2)
  Eigen::Vector3d tumor_centre = Eigen::Vector3d::Zero();  // plan.json tumor centroid, LPS mm
  double radius_mm = 0;                                    // region of interest radius R
  Volume<float> blocking;
  std::vector<std::string> values;  // computed values, plan.json order ("svv", "isbv", ...)
  std::map<std::string, Volume<float>> path_safety;  // NaN outside the region of interest
  // Voxel states of roi.nii.gz (planning/safety/unknown.hpp RegionState: 0 not computed, 1
  // computed, 2 unknown: outside the scan); empty for plans without it.
  Volume<uint8_t> region;
  // Breathing plans (plan.json "breathing", docs/ARCHITECTURE.md §10): the phases' names in cycle
  // order and, when the plan was made with per-phase volumes, each value's volume per phase (same
  // order; NaN wherever the combined plan has no computed value). Empty otherwise.
  std::vector<std::string> phases;
  std::map<std::string, std::vector<Volume<float>>> phase_path_safety;
  std::map<std::string, SafetyClasses> classes;      // plan.json "classes"
  Volume<int32_t> labels;                            // empty when the plan has no label map
  std::string labels_path;
  std::optional<VulnerabilityTable> table;  // plan.json preprocessing.vulnerability
  Volume<uint8_t> tumor;                    // empty when the mask is not found
  std::optional<AreaSafetyGeometry> area;   // area_safety.vtk, when the plan has one
  // Inputs whose checksum differs from plan.json's (each also logged as a warning); a label map
  // given instead of the plan's counts when it differs from the one planned with.
  std::vector<ChangedInput> changed_inputs;
};

// Reads plan.json and the files asked for. Throws Error naming the file and the field when
// plan.json is missing or malformed or a required volume cannot be read. A label map or tumor
// mask that moved since planning is skipped with a warning (give labels_override instead). An
// input that changed since planning is reported in changed_inputs, never silently used.
PlanData load_plan(const std::string& plan_dir, const PlanLoadOptions& options = {});

// A grid as geometry_json wrote it; throws Error naming `where` and the field.
ImageGeometry geometry_from_json(const nlohmann::json& j, const std::string& where);

// The value a view shows when none is asked for: svv when the plan computed it, else its first.
// Reads only plan.json; throws Error naming it when it is missing or lists no value.
std::string plan_default_value(const std::string& plan_dir);

// The path of an input recorded in plan.json "inputs" (`key`: "ct", "labels", "tumor", ...), or,
// when that file is gone and the plan moved with its inputs, the one at its relative path; "" when
// plan.json records none.
std::string plan_input_path(const PlanData& plan, const char* key);

// The same for phase `phase` of a breathing plan (plan.json "breathing" "phases"): "labels" (its one
// label map), "tumor" or "ct". Throws Error naming plan.json's field when the phase records none
// or several label maps.
std::string plan_phase_input_path(const PlanData& plan, size_t phase, const char* key);

// Classes of a value as plan.json states them ("classes"); throws Error when absent.
SafetyClasses classes_from_json(const nlohmann::json& plan, const std::string& value,
                                const std::string& source);

}  // namespace crepuscular::planning
