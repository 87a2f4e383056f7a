// The executor of a breathing plan's schedule: signals between the steps' threads.
#include "planning/breathing/executor.hpp"

#include <omp.h>

#include <algorithm>
#include <exception>
#include <future>
#include <mutex>
#include <stdexcept>
#include <utility>
#include <vector>

#include "foundation/trace.hpp"

namespace crepuscular::planning {

namespace {

// Set once, or failed once (every waiter then takes the error).
struct Signal {
  std::promise<void> promise;
  std::shared_future<void> done = promise.get_future().share();
  std::once_flag once;
  void set() {
    std::call_once(once, [this] { promise.set_value(); });
  }
  void fail(std::exception_ptr e) {
    std::call_once(once, [this, e] { promise.set_exception(e); });
  }
};

}  // namespace

struct ScheduleRun::State {
  const PhaseSchedule& schedule;
  PhaseCombiner& combiner;
  StepHooks hooks;
  size_t n;
  // Per step: its combination readable (`folded`); its fold made, and for the first step its
  // report taken too (the next fold waits for it: the folds go in step order); its other extreme
  // folded; its volumes final (`covered`: lent to the steps that read it before its fold); free
  // to sample.
  std::vector<Signal> folded, fold_made, extreme_made, covered, may_sample;
  std::mutex pending_lock;
  // A later step's final result until its fold, and per step the result it reads so.
  std::vector<std::shared_ptr<const PathSafetyResult>> pending, reading;
  std::vector<std::future<PathSafetyResult>> computing;
  std::vector<std::future<void>> finishing;

  State(const PhaseSchedule& s, PhaseCombiner& c, StepHooks h)
      : schedule(s), combiner(c), hooks(std::move(h)), n(s.steps.size()), folded(n),
        fold_made(n), extreme_made(n), covered(n), may_sample(n), pending(n), reading(n),
        computing(n), finishing(n) {}

  void fail_all(std::exception_ptr e) {
    for (auto* signals : {&folded, &fold_made, &extreme_made, &covered, &may_sample}) {
      for (Signal& s : *signals) s.fail(e);
    }
  }

  // The combination of steps 0..source, once that step's fold is made.
  std::function<CombinedVolumes()> combination_of(size_t source) {
    return [this, source]() -> CombinedVolumes {
      trace::event("comb_wait_begin");
      folded[source].done.get();
      trace::event("comb_wait_end");
      return combiner.volumes_after(int(source) + 1);
    };
  }

  // The combination of steps 0..source for step `at`, without waiting for the fold of `source`:
  // its final volumes read through the combination of the steps before it (folded before it, in
  // order), or where its fold is made already the combination itself. The combination before
  // `source` stays put while `at` samples: the combiner keeps it (kept_combinations).
  std::function<CombinedVolumes()> combination_before_fold(size_t source, size_t at) {
    return [this, source, at]() -> CombinedVolumes {
      trace::event("comb_wait_begin");
      covered[source].done.get();
      std::shared_ptr<const PathSafetyResult> lent;
      {
        const std::lock_guard<std::mutex> lock(pending_lock);
        lent = pending[source];
      }
      if (!lent) {
        folded[source].done.get();
        trace::event("comb_wait_end");
        return combiner.volumes_after(int(source) + 1);
      }
      folded[source - 1].done.get();
      CombinedVolumes v = combiner.volumes_after(int(source));
      for (int s = 0; s < kernels::kValueCount; ++s) {
        if (v.folded[size_t(s)]) v.pending[size_t(s)] = lent->volumes[size_t(s)].data();
      }
      reading[at] = std::move(lent);  // released once `at` has computed
      trace::event("comb_wait_end");
      return v;
    };
  }

  void start(size_t at) {
    const PhaseStep& step = schedule.steps[at];
    CombinationSource combination;
    if (step.coarse_to >= 0) {
      combination.so_far = combination_of(size_t(step.coarse_to));
      if (step.fine_to > step.coarse_to) {
        combination.newer = combination_before_fold(size_t(step.fine_to), at);
        combination.newer_from_level = 1;
      }
    }
    std::function<void()> before_sampling;
    if (step.samples_after >= 0) before_sampling = [this, at] { may_sample[at].done.get(); };
    trace::event("start", 0, int(at));
    computing[at] = std::async(std::launch::async, [this, at, combination, before_sampling] {
      trace::current_phase() = int(at);
      trace::event("compute_begin");
      // The turns that wait for this step's computation come when it has computed, or failed;
      // the step it read before that step's fold is released then.
      struct OnExit {
        State& s;
        size_t at;
        ~OnExit() {
          s.reading[at].reset();
          for (size_t later = at + 1; later < s.n; ++later) {
            if (s.schedule.steps[later].samples_after == int(at)) s.may_sample[later].set();
          }
        }
      } on_exit{*this, at};
      PathSafetyResult r = hooks.compute(at, combination, before_sampling);
      trace::event("compute_end");
      return r;
    });
  }

  // Made final, folded after the step before it, then its report; beside the next steps.
  void finish(size_t at, PathSafetyResult result) {
    trace::event("finish_begin", 0, int(at));
    // Its device memory freed at the end of this finish: freeing waits for the device, here
    // beside the samplers rather than in their way.
    const std::shared_ptr<void> device_memory = std::move(result.device_memory);
    const Volume<uint8_t> region = hooks.cover(at, result);
    trace::event("coverage_applied", 0, int(at));
    std::shared_ptr<PathSafetyResult> final_result;
    if (at > 0) {
      final_result = std::make_shared<PathSafetyResult>(std::move(result));
      const std::lock_guard<std::mutex> lock(pending_lock);
      pending[at] = final_result;
    }
    covered[at].set();
    if (at > 0) fold_made[at - 1].done.get();  // the folds in order (its error taken here)
    const auto combined = [this, at] {
      {
        const std::lock_guard<std::mutex> lock(pending_lock);
        pending[at].reset();  // its readers read the combination from now on
      }
      folded[at].set();
      trace::event("folded", 0, int(at));
    };
    PathSafetyResult* reported = final_result.get();
    if (at == 0) {
      // The first step lends its volumes to the combination; its report is taken of them there,
      // before the next fold may change them.
      combiner.add(std::move(result), region, combined);
      reported = &combiner.combined();
      extreme_made[at].set();
    } else {
      combiner.fold(*final_result, region, combined);
      fold_made[at].set();
      // Off the folds' path: fewer cores while samplers run beside it (the last step's take
      // them all, beside the plan's writes). The other extreme beside the next step's fold.
      if (at + 1 < n) omp_set_num_threads(std::max(1, omp_get_num_procs() / 4));
      combiner.fold_extreme(*final_result);
      extreme_made[at].set();
    }
    trace::event("fold_done", 0, int(at));
    hooks.report(at, *reported);
    if (at == 0) fold_made[at].set();
    trace::event("finish_end", 0, int(at));
  }

  void hand_over(size_t at) {
    PathSafetyResult result = computing[at].get();
    if (hooks.computed) hooks.computed(at);
    finishing[at] = std::async(std::launch::async, [this, at, r = std::move(result)]() mutable {
      try {
        finish(at, std::move(r));
      } catch (...) {
        const std::exception_ptr e = std::current_exception();
        folded[at].fail(e);
        fold_made[at].fail(e);
        extreme_made[at].fail(e);
        covered[at].fail(e);
        throw;
      }
    });
  }

  void wait_all() {
    for (auto& c : computing) {
      if (c.valid()) c.wait();
    }
    for (auto& f : finishing) {
      if (f.valid()) f.wait();
    }
  }
};

ScheduleRun::ScheduleRun(const PhaseSchedule& schedule, PhaseCombiner& combiner,
                         StepHooks hooks)
    : state_(std::make_unique<State>(schedule, combiner, std::move(hooks))) {
  combiner.keep_earlier(schedule.kept_combinations);
}

ScheduleRun::~ScheduleRun() {
  state_->fail_all(std::make_exception_ptr(std::runtime_error("breathing plan stopped")));
  state_->wait_all();
}

void ScheduleRun::run() {
  State& s = *state_;
  try {
    for (size_t at = 0; at < s.n; ++at) {
      if (s.schedule.steps[at].samples_after < 0) s.may_sample[at].set();
    }
    // A step is started once the step it is prepared after has computed (and been handed over).
    size_t handed = 0;
    for (size_t at = 0; at < s.n; ++at) {
      const int after = s.schedule.steps[at].prepared_after;
      while (after >= 0 && handed <= size_t(after)) s.hand_over(handed++);
      s.start(at);
    }
    while (handed < s.n) s.hand_over(handed++);
    s.folded.back().done.get();  // the combination is whole
  } catch (...) {
    const std::exception_ptr error = std::current_exception();
    if (s.hooks.failed) s.hooks.failed();
    s.fail_all(error);
    s.wait_all();
    throw;
  }
}

void ScheduleRun::wait_extremes() {
  for (auto& e : state_->extreme_made) e.done.get();
}

void ScheduleRun::wait_reports() {
  for (auto& f : state_->finishing) {
    if (f.valid()) f.get();
  }
}

}  // namespace crepuscular::planning
