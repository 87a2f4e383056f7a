// The plan job: a segmented CT (or a CT, or a ready blocking volume) and a tumor mask -> blocking
// volume -> path safety volumes -> area safety -> PLAN_DIR (planning/plan_folder), written as one
// folder that appears complete or not at all.
#pragma once

#include <nlohmann/json_fwd.hpp>
#include <Eigen/Core>
#include <optional>
#include <string>
#include <vector>

#include "pipelines/plan_inputs.hpp"
#include "planning/preprocessing/blocking.hpp"
#include "planning/safety/area_safety.hpp"
#include "planning/safety/path_safety.hpp"

namespace crepuscular::pipelines {

// The inputs (label maps, tumor and lesion, tables, CT, blocking volume, margin: PlanInputOptions)
// and what to compute from them.
struct PlanRequest : PlanInputOptions {
  planning::PathSafetyOptions path_safety;
  planning::AreaSafetyPlanOptions area_safety;  // §3.3: area_safety.vtk for the first value
  // Voxels of the region of interest outside the scan are left out (not computed) instead of
  // being unknown.
  bool crop_to_scan = false;
  std::string out_dir;
  // Breathing (docs/ARCHITECTURE.md §10): phases.json; then the label maps, tumor and CT come from
  // it, one set per phase, and the plan combines the phases (planning/breathing/).
  std::string phases;
  // Also write path_safety_<value>_<phase>.nii.gz per phase; every phase's class boundaries are
  // then refined (none is left to the combination), so that each phase's volumes are right.
  bool per_phase = false;
  // Phases computed at once: 0 chooses (3 on a GPU, 1 on the cores); each holds its volumes in
  // memory (planning/breathing/schedule.hpp).
  int phases_at_once = 0;
};

// Runs preprocessing and path safety and writes PLAN_DIR/blocking.nii.gz, PLAN_DIR/roi.nii.gz
// (planning::RegionState: 0 not computed, 1 computed, 2 unknown: inside the region of interest but
// outside the scan), PLAN_DIR/path_safety_<value>.nii.gz (float32, NaN where not computed or
// unknown) and
// PLAN_DIR/plan.json, and (area_safety.enabled) PLAN_DIR/area_safety.vtk with plan.json's
// "area_safety" section. Returns the content of plan.json. Throws Error on bad input, naming the
// input by its role; then nothing is left at out_dir (an earlier plan there stays untouched).
//
// With `phases`: one output grid for all phases, centred on the mean of the phases' tumor
// centroids (radius: the largest of the phases' defaults); each phase's path safety on it,
// combined voxelwise (SVV the minimum, the others the maximum; unknown in any phase: unknown).
// The combined volumes are the plan's path_safety_<value> files; blocking, tumor and label map are
// the first phase's (the planning scan); plan.json "breathing" lists the phases, their inputs and
// statistics and, per value, the share of the region whose class changes over the cycle.
nlohmann::json run_plan(const PlanRequest& request);

}  // namespace crepuscular::pipelines
