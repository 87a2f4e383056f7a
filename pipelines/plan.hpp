// The plan job: a segmented CT (or a CT, or a ready blocking volume) and a tumor mask -> blocking
// volume -> path safety volumes -> area safety -> PLAN_DIR (planning/plan_folder), written as one
// folder that appears complete or not at all.
#pragma once

#include <nlohmann/json_fwd.hpp>
#include <string>

#include "planning/preprocessing/blocking.hpp"
#include "planning/safety/area_safety.hpp"
#include "planning/safety/path_safety.hpp"

namespace crepuscular::pipelines {

struct PlanRequest {
  std::string labels;         // label map (with vulnerability table or preset)
  std::string tumor;          // tumor mask (required)
  std::string vulnerability;  // vulnerability table JSON
  std::string preset;         // built-in vulnerability table
  std::string ct;             // CT in HU: thresholded when no labels are given
  std::string blocking;       // ready blocking volume (risk per mm): used as is
  planning::PathSafetyOptions path_safety;
  planning::MarginOptions margin;
  planning::CtThresholds ct_thresholds;
  planning::AreaSafetyPlanOptions area_safety;  // §3.3: area_safety.vtk for the first value
  std::string out_dir;
};

// Runs preprocessing and path safety and writes PLAN_DIR/blocking.nii.gz, PLAN_DIR/roi.nii.gz,
// PLAN_DIR/path_safety_<value>.nii.gz (float32, NaN outside the region of interest) and
// PLAN_DIR/plan.json, and (area_safety.enabled) PLAN_DIR/area_safety.vtk with plan.json's
// "area_safety" section. Returns the content of plan.json. Throws Error on bad input, naming the
// input by its role; then nothing is left at out_dir (an earlier plan there stays untouched).
nlohmann::json run_plan(const PlanRequest& request);

}  // namespace crepuscular::pipelines
