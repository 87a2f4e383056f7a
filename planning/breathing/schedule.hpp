// The order in which a plan over breathing phases computes them (docs/ARCHITECTURE.md §10): a
// plain value computed up front from the number of phases and how many are computed at once,
// printed in the log, and run by the plan.
//
// Steps are the phases in the order they are computed (the phases at the ends of the motion
// first). Each step's result is folded into the combination in step order. With `leave` on (fast
// mode, the phases' own volumes not written), a step leaves a class boundary unrefined where the
// combination of earlier steps is already at least as unsafe (combination.hpp); it can only read
// combinations whose steps are computed, so with several steps at once it reads an older one.
#pragma once

#include <cstddef>
#include <string>
#include <vector>

namespace crepuscular::planning {

struct PhaseStep {
  // Its computation starts (preparation: the scene uploaded, the volumes allocated) once the
  // computation of this step has ended; -1: at the plan's start.
  int prepared_after = -1;
  // It samples its first point once the computation of this step has ended; -1: once prepared.
  int samples_after = -1;
  // Its coarsest level's decisions leave to the combination of steps 0..coarse_to (waiting for
  // that step's fold); -1: it refines every class boundary.
  int coarse_to = -1;
  // Its finer levels' decisions leave to the combination of steps 0..fine_to. Where fine_to is
  // past coarse_to the step does not wait for the fold of step fine_to: it reads that step's
  // final volumes through the combination of the steps before it.
  int fine_to = -1;
};

struct PhaseSchedule {
  int at_once = 1;           // steps computed at once
  int kept_combinations = 0;  // combinations before the latest kept readable (PhaseCombiner)
  std::vector<PhaseStep> steps;
  // One line per step, for the log and the tests: "step 3: prepared after -, samples after -,
  // coarsest level leaves to 1, finer to 1-2 (2 before its fold)"; with `names` (one per step),
  // each step's name after its number.
  std::string table(const std::vector<std::string>& names = {}) const;
};

// The schedule of `phases` steps, `at_once` of them computed at once (>= 1; at most `phases`
// used), leaving refinement to the combination where `leave`. One step at once computes each
// after the one before and leaves to all steps before it. With several at once, one more step is
// prepared beside them and samples once the step `at_once` before it has computed; a step leaves
// only to steps that are computed by the time it needs them: its finer levels to the steps up to
// two before it (the step just before is computed beside it), its coarsest level, with three at
// once, to the steps up to three before it; the third step's finer levels to the first two.
PhaseSchedule schedule_phases(int phases, int at_once, bool leave);

}  // namespace crepuscular::planning
