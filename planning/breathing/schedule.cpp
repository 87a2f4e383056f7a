// The phase schedule of a breathing plan: which step waits for which, and leaves to which
// combination.
#include "planning/breathing/schedule.hpp"

#include <fmt/format.h>

#include <algorithm>

#include "foundation/error.hpp"

namespace crepuscular::planning {

PhaseSchedule schedule_phases(int phases, int at_once, bool leave) {
  if (phases < 1 || at_once < 1) {
    throw Error(fmt::format("breathing schedule: {} phases, {} at once (expected 1 or more each)",
                            phases, at_once));
  }
  PhaseSchedule s;
  s.at_once = std::min(at_once, phases);
  const int n = phases, k = s.at_once;
  // One more step prepared beside the ones computing, where several compute at once.
  const int started = std::min(n, k > 1 ? k + 1 : k);
  // How far back a step's finer and coarsest levels leave: the step just before is computed
  // beside it (with several at once), so the finer levels leave to the steps up to two back;
  // with three at once the coarsest level, sampled while the step two back is still computed,
  // leaves to the steps up to three back.
  const int fine_lag = std::min(k, 2);
  const int coarse_lag = k >= 3 ? 3 : fine_lag;
  s.kept_combinations = leave && k > 1 ? coarse_lag - 1 : 0;
  s.steps.resize(size_t(n));
  for (int at = 0; at < n; ++at) {
    PhaseStep& step = s.steps[size_t(at)];
    step.prepared_after = at >= started ? at - started : -1;
    step.samples_after = at >= k ? at - k : -1;
    if (!leave || at == 0) continue;
    // The third step, computed beside the fourth after the second, leaves its finer levels to
    // the first two.
    step.fine_to = at > fine_lag ? at - fine_lag : (at == 2 && coarse_lag == 3) ? 1 : 0;
    step.coarse_to = at > coarse_lag ? at - coarse_lag : 0;
  }
  return s;
}

std::string PhaseSchedule::table(const std::vector<std::string>& names) const {
  const auto step_name = [](int step) {
    return step < 0 ? std::string("-") : std::to_string(step + 1);
  };
  std::string out;
  for (size_t at = 0; at < steps.size(); ++at) {
    const PhaseStep& p = steps[at];
    std::string leaves = "refines every boundary";
    if (p.coarse_to >= 0) {
      const auto steps_to = [&](int last) { return last == 0 ? "1" : "1-" + step_name(last); };
      leaves = "coarsest level leaves to " + steps_to(p.coarse_to);
      leaves += ", finer to " + steps_to(p.fine_to);
      if (p.fine_to > p.coarse_to) leaves += " (" + step_name(p.fine_to) + " before its fold)";
    }
    const std::string name = at < names.size() ? " " + names[at] : std::string();
    out += fmt::format("{}step {}{}: prepared after {}, samples after {}, {}", at ? "\n" : "",
                       at + 1, name, step_name(p.prepared_after), step_name(p.samples_after),
                       leaves);
  }
  return out;
}

}  // namespace crepuscular::planning
