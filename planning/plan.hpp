// A plan: the blocking volume, the path safety volumes and plan.json, computed from a segmented CT
// and a tumor mask and written as one folder that appears complete or not at all.
#pragma once

#include <string>

#include <nlohmann/json.hpp>

#include "planning/area_safety.hpp"
#include "planning/blocking.hpp"
#include "planning/path_safety.hpp"

namespace crepuscular::planning {

struct PlanRequest {
  std::string labels;         // label map (with vulnerability table or preset)
  std::string tumor;          // tumor mask (required)
  std::string vulnerability;  // vulnerability table JSON
  std::string preset;         // built-in vulnerability table
  std::string ct;             // CT in HU: thresholded when no labels are given
  std::string blocking;       // ready blocking volume (risk per mm): used as is
  PathSafetyOptions path_safety;
  MarginOptions margin;
  CtThresholds ct_thresholds;
  AreaSafetyPlanOptions area_safety;  // §3.3: area_safety.vtk for the first computed value
  std::string out_dir;
};

// Runs preprocessing and path safety and writes PLAN_DIR/blocking.nii.gz,
// PLAN_DIR/path_safety_<value>.nii.gz (float32, NaN outside the region of interest) and
// PLAN_DIR/plan.json, and (area_safety.enabled) PLAN_DIR/area_safety.vtk with plan.json's
// "area_safety" section. Returns the content of plan.json. Throws Error on bad input; then nothing is
// left at out_dir (an earlier plan there stays untouched).
nlohmann::json run_plan(const PlanRequest& request);

// Hex MD5 of a file's bytes (a folder: of its files' names and bytes, in name order).
std::string file_checksum(const std::string& path);

// The class thresholds of one value as written in plan.json.
nlohmann::json classes_json(unsigned value_bit, const Volume<float>& volume);

}  // namespace crepuscular::planning
