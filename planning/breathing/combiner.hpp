// Path safety over the breathing cycle (docs/ARCHITECTURE.md §10): the phases' volumes on one
// output grid combined so that a voxel is safe only if it is safe in every phase.
#pragma once

#include <algorithm>
#include <array>
#include <future>
#include <cstdint>
#include <functional>
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
  // `combined`, where given, is called as soon as the combination is complete and readable
  // (volumes_after), before the other extreme is folded in. A later phase's add is its fold
  // and its fold_extreme.
  void add(const PathSafetyResult& phase, const Volume<uint8_t>& region,
           const std::function<void()>& combined = {});
  void add(PathSafetyResult&& phase, const Volume<uint8_t>& region,
           const std::function<void()>& combined = {});
  // A later phase in two steps: its fold into the combination (the folds one after another),
  // then its fold into the other extreme, which may run beside the next phases' folds (those
  // one after another too; in any order, the extreme is the same). Every phase's extreme must be
  // in before other_extreme or class_change_shares is read.
  void fold(const PathSafetyResult& phase, const Volume<uint8_t>& region,
            const std::function<void()>& combined = {});
  void fold_extreme(const PathSafetyResult& phase);

  int phases() const;
  // Keeps the `count` combinations before the last fold readable while later ones are folded
  // (memory: `count` more sets of volumes): a phase computed beside the phases before it asks for
  // the combination of the phases before those (`volumes_after`). Set before the second phase is
  // added.
  void keep_earlier(int count) { keep_ = std::max(0, count); }
  // The combined volumes' data after the first `folded` phases (NaN-free slots are null for values
  // not computed): the latest combination, or one of the `keep_earlier` before it. Safe to call
  // beside `add`; the data stays put until `keep_earlier` + 1 more folds are made.
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
  // The same for every slot whose classes are given (null: not asked, 0 returned), in one pass.
  std::array<double, kernels::kValueCount> class_change_shares(
      const std::array<const SafetyClasses*, kernels::kValueCount>& classes) const;

 private:
  void fold_check(const PathSafetyResult& phase);
  // The volumes the later folds write (the other extreme, a copy of the first phase, and with
  // keep_earlier the buffers beside the combination) made on a thread of their own after the
  // first fold: a few GB, which would otherwise hold up the second fold and every sampler
  // waiting for it.
  void make_spares();

  int phases_ = 0;
  int keep_ = 0;
  mutable std::mutex swap_;  // phases_ and which buffer holds which combination
  std::mutex extreme_;       // one fold_extreme at a time
  PathSafetyResult combined_;
  // With keep_earlier: the combinations before the latest, the newest first (the last one is
  // the buffer the next fold writes).
  std::vector<std::array<Volume<float>, kernels::kValueCount>> earlier_;
  std::array<Volume<float>, kernels::kValueCount> other_;
  std::future<void> spares_;  // make_spares, after the first fold
  Volume<uint8_t> region_;
  std::shared_ptr<CheckSample> check_;
};

}  // namespace crepuscular::planning
