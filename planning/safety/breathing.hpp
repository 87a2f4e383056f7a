// Path safety over the breathing cycle (DESIGN.md §10): the phases' volumes on one output grid
// combined so that a voxel is safe only if it is safe in every phase.
#pragma once

#include <array>
#include <future>
#include <cstdint>
#include <memory>
#include <mutex>
#include <vector>

#include "planning/safety/path_safety.hpp"
#include "planning/safety/safety_classes.hpp"

namespace crepuscular::planning {

// Folds the phases in one at a time (memory: two sets of volumes, whatever the number of phases).
// Combination per voxel: SVV the minimum over the phases, ISBV, IVBV and BVV the maximum (the
// least safe phase); a voxel unknown (NaN, state kRegionUnknown) in any phase is unknown in the
// combination; one not computed in some phase (outside its region) is not computed.
class PhaseCombiner {
 public:
  // The first phase fixes the grid and the values; later ones must match (Error otherwise).
  // Every voxel on every core; a first phase given as an rvalue lends its volumes.
  void add(const PathSafetyResult& phase, const Volume<uint8_t>& region);
  void add(PathSafetyResult&& phase, const Volume<uint8_t>& region);

  int phases() const;
  // Keeps the combination before the last fold readable while the next is folded (memory: a third
  // set of volumes): a phase computed beside the one before it asks for the combination of the
  // phases before that one (`volumes_after`). Set before the second phase is added.
  void keep_previous(bool keep) { keep_previous_ = keep; }
  // The combined volumes' data after the first `folded` phases (NaN-free slots are null for values
  // not computed): the latest combination, or with keep_previous the one before it. Safe to call
  // beside `add`; the data stays put until the fold after next.
  std::array<const float*, kernels::kValueCount> volumes_after(int folded) const;
  // The combination: the first phase's grid and parameters, the combined volumes, the summed
  // time and rays.
  const PathSafetyResult& combined() const { return combined_; }
  PathSafetyResult& combined() { return combined_; }
  // Fast mode's check of the combination: the voxels of every phase's check sample (the same
  // voxels where the phases share their scan) with the combination of the phases' exact values
  // there; null when a phase had no check.
  const CheckSample* check_sample() const { return check_.get(); }
  const Volume<uint8_t>& region() const { return region_; }
  // Per value slot, the other end of the range over the phases (SVV: the maximum; the others: the
  // minimum); NaN where the combination is.
  const Volume<float>& other_extreme(int slot) const {
    return phases() < 2 ? combined_.volumes[size_t(slot)] : other_[size_t(slot)];
  }

  // Share (0..1) of the computed voxels of the combination whose class under `classes` is not the
  // same in every phase: classes are monotone in the value, so the class changes over the cycle
  // exactly where the minimum and the maximum over the phases fall in different classes.
  double class_change_share(int slot, const SafetyClasses& classes) const;

 private:
  void add_phase(const PathSafetyResult& phase, const Volume<uint8_t>& region);
  void fold_check(const PathSafetyResult& phase);
  // The volumes the second fold writes (the other extreme, and with keep_previous the buffer
  // beside the combination) made on a thread of their own after the first fold: cleared pages of
  // a few GB, which would otherwise hold up the second fold and every sampler waiting for it.
  void make_spares();

  int phases_ = 0;
  bool keep_previous_ = false;
  mutable std::mutex swap_;  // phases_ and which buffer holds which combination
  PathSafetyResult combined_;
  std::array<Volume<float>, kernels::kValueCount> previous_;  // with keep_previous
  std::array<Volume<float>, kernels::kValueCount> other_;
  std::future<void> spares_;  // make_spares, after the first fold
  Volume<uint8_t> region_;
  std::shared_ptr<CheckSample> check_;
};

}  // namespace crepuscular::planning
