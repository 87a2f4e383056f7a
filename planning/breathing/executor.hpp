// Runs a breathing plan's PhaseSchedule: each step's path safety on a thread of its own, its
// result finished on another beside the next steps (made final, folded into the combination in
// step order, then its own report), a step's combination handed to it when it asks.
#pragma once

#include <cstddef>
#include <functional>
#include <memory>

#include "planning/breathing/combiner.hpp"
#include "planning/breathing/schedule.hpp"
#include "planning/imaging/volume.hpp"
#include "planning/safety/path_safety.hpp"

namespace crepuscular::planning {

struct StepHooks {
  // Computes step `at`'s path safety, leaving refinement to `combination` and calling
  // `before_sampling` before its first point (both given to PathSafetyOptions). On the step's
  // own thread.
  std::function<PathSafetyResult(size_t at, const CombinationSource& combination,
                                 const std::function<void()>& before_sampling)>
      compute;
  // Step `at` has computed (its result taken, on the scheduling thread).
  std::function<void(size_t at)> computed;
  // Makes step `at`'s volumes final (e.g. the scan's coverage) and returns its region
  // (PhaseCombiner::add). On the step's finishing thread, before its fold.
  std::function<Volume<uint8_t>(size_t at, PathSafetyResult& result)> cover;
  // After step `at`'s fold: its own report. `result` is its result, or for the first step the
  // combination that holds its volumes (the next fold waits for this call). On its finishing
  // thread, beside the later steps.
  std::function<void(size_t at, PathSafetyResult& result)> report;
  // A step failed: stop what feeds the steps (e.g. input reads). May be empty.
  std::function<void()> failed;
};

class ScheduleRun {
 public:
  ScheduleRun(const PhaseSchedule& schedule, PhaseCombiner& combiner, StepHooks hooks);
  ~ScheduleRun();  // waits for every thread it started
  ScheduleRun(const ScheduleRun&) = delete;
  ScheduleRun& operator=(const ScheduleRun&) = delete;

  // Runs every step and returns once the combination is whole. Throws the first error of a
  // step (in step order); every thread has stopped by then.
  void run();
  // Waits for every step's other extreme (PhaseCombiner::fold_extreme).
  void wait_extremes();
  // Waits for every step's report.
  void wait_reports();

 private:
  struct State;
  std::unique_ptr<State> state_;
};

}  // namespace crepuscular::planning
