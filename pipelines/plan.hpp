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
  // Breathing (DESIGN.md §10): phases.json; then the label maps, tumor and CT come from it, one
  // set per phase, and the plan combines the phases (planning/safety/breathing.hpp).
  std::string phases;
  bool per_phase = false;  // also write path_safety_<value>_<phase>.nii.gz per phase
  // Fast mode over phases: refine every phase's class boundaries, also where the phases computed
  // before decide the combination's class (PathSafetyOptions::combined_so_far). Slower; implied
  // by per_phase, whose volumes must each be right.
  bool refine_every_phase = false;
  // Phases computed at once: 0 chooses (3 on a GPU, 1 on the cores).
  int phases_at_once = 0;
  // Three or more at once, fast mode: a phase's decisions from this level of its lattice on
  // (1: the second) leave to the combination of the phases up to two before it, the coarser
  // ones to that of the phases up to three before it, folded earlier
  // (PathSafetyOptions::combined_newer). 0: every level to the phases up to two before it.
  int newer_combination_from_level = 1;
  // With the above (> 0): the third phase computed leaves its finer decisions to the combination
  // of the first two (waiting for the second's computing, beside which the fourth samples its
  // coarsest level), not to the first alone beside the second (false).
  bool third_after_second = true;
  // Phases side by side: one more phase prepared beside them, sampling at its turn (false: a
  // phase is prepared when its turn comes).
  bool prepare_phase_ahead = true;
  // With spacing and radius given: the tumors read first, the blocking volumes beside the
  // computation (false: every input read before the first phase is computed).
  bool stream_phase_reads = true;
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
