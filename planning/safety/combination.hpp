// Breathing's view into fast mode (docs/ARCHITECTURE.md §10): the phases computed before a phase,
// combined on its grid, and when the phase asks for them. With them, the phase leaves a class
// boundary unrefined where it cannot change the combination's class (adaptive_sampling.hpp).
#pragma once

#include <array>
#include <functional>

#include "kernels/value_bits.hpp"

namespace crepuscular::planning {

// Per value slot (null where that value is not combined): the combination of the phases folded
// so far, and where given the volume of one more phase not folded into it yet, read through it
// (SVV the minimum of the two, the other values the maximum; NaN, unknown, where either is NaN),
// which is what its fold will write. So a phase need not wait for the fold of the phase before.
struct CombinedVolumes {
  std::array<const float*, kernels::kValueCount> folded{};
  std::array<const float*, kernels::kValueCount> pending{};
  CombinedVolumes() = default;
  CombinedVolumes(const std::array<const float*, kernels::kValueCount>& combination)  // NOLINT
      : folded(combination) {}
};

// The combinations a phase leaves refinement to. `so_far` is asked for once the coarsest level
// is sampled (it may wait for an earlier phase's fold): its classes are the thresholds, and the
// decisions of the levels before `newer_from_level` leave to it. `newer`, where given, is asked
// for before the decisions of level `newer_from_level` (1: the cells of the second lattice), and
// those and every finer level's leave to it instead. Empty: every class boundary is refined.
struct CombinationSource {
  std::function<CombinedVolumes()> so_far;
  std::function<CombinedVolumes()> newer;
  int newer_from_level = 1;
  explicit operator bool() const { return bool(so_far); }
};

}  // namespace crepuscular::planning
