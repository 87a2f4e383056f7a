// Path safety over the breathing cycle: the voxelwise combination of the phases.
#include "planning/breathing/combiner.hpp"

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <unordered_map>
#include <utility>

#include "foundation/error.hpp"
#include "kernels/path_safety_math.hpp"
#include "planning/safety/unknown.hpp"

namespace crepuscular::planning {

namespace {

// SVV is safer when higher: the least safe phase has the smallest value.
bool higher_is_safer(int slot) { return (1u << slot) == kernels::kSvv; }

// A copy of a volume made on every core (a 513^3 volume is 540 MB).
template <typename T>
Volume<T> parallel_copy(const Volume<T>& from) {
  Volume<T> to(from.geometry());
  const int64_t n = from.voxel_count();
  constexpr int64_t kChunk = int64_t(1) << 20;
#pragma omp parallel for schedule(static)
  for (int64_t c = 0; c < n; c += kChunk) {
    std::memcpy(&to[c], &from[c], size_t(std::min(kChunk, n - c)) * sizeof(T));
  }
  return to;
}

// Calls f(first, last) for runs of voxel offsets (first..last inclusive), in parallel: the whole
// grid in chunks, or (`whole` false) only the rows' runs inside the region of interest, a ball.
// Voxels outside it are not computed in any phase (NaN in every volume). Dynamic: the folds run
// beside the samplers of other phases, whose threads share the cores, and a share fixed per
// thread would wait for the thread the system serves last.
template <typename F>
void for_runs(const OutputGrid& grid, bool whole, const F& f) {
  const Index3& d = grid.geometry.dims;
  if (whole) {
    const int64_t n = grid.geometry.voxel_count();
    constexpr int64_t kChunk = int64_t(1) << 16;
#pragma omp parallel for schedule(dynamic, 1)
    for (int64_t c = 0; c < n; c += kChunk) f(c, std::min(n, c + kChunk) - 1);
    return;
  }
  const int64_t rows = d[1] * d[2];
#pragma omp parallel for schedule(dynamic, 128)
  for (int64_t row = 0; row < rows; ++row) {
    const auto [i0, i1] = grid.roi_run(row % d[1], row / d[1]);
    if (i0 <= i1) f(row * d[0] + i0, row * d[0] + i1);
  }
}

}  // namespace

void PhaseCombiner::add(const PathSafetyResult& phase, const Volume<uint8_t>& region,
                        const std::function<void()>& combined) {
  if (phases_ == 0) {
    PathSafetyResult first = phase;
    add(std::move(first), region, combined);
  } else {
    fold(phase, region, combined);
    fold_extreme(phase);
  }
}

void PhaseCombiner::add(PathSafetyResult&& phase, const Volume<uint8_t>& region,
                        const std::function<void()>& combined) {
  if (phases_ > 0) {
    fold(phase, region, combined);
    fold_extreme(phase);
    return;
  }
  if (!region.geometry().same_grid(phase.grid.geometry, 1e-6)) {
    throw Error("breathing phase 1: its voxel states are not on its path safety grid");
  }
  combined_ = std::move(phase);
  if (combined_.check_sample) check_ = std::make_shared<CheckSample>(*combined_.check_sample);
  combined_.check_sample = nullptr;
  region_ = parallel_copy(region);
  // The other extreme of one phase is the phase itself: copied, with the buffers of the folds to
  // come, on a thread of its own (here it would hold up the next phase's sampler).
  spares_ = std::async(std::launch::async, [this] { make_spares(); });
  {
    const std::lock_guard<std::mutex> lock(swap_);
    phases_ = 1;
  }
  if (combined) combined();
}

void PhaseCombiner::make_spares() {
  const ImageGeometry& g = combined_.grid.geometry;
  for (int v = 0; v < kernels::kValueCount; ++v) {
    if (!(combined_.values & (1u << v))) continue;
    other_[size_t(v)] = parallel_copy(combined_.volumes[size_t(v)]);
  }
  earlier_.resize(size_t(keep_));
  for (auto& set : earlier_) {
    for (int v = 0; v < kernels::kValueCount; ++v) {
      if (combined_.values & (1u << v)) set[size_t(v)] = Volume<float>(g);
    }
  }
}

int PhaseCombiner::phases() const {
  const std::lock_guard<std::mutex> lock(swap_);
  return phases_;
}

std::array<const float*, kernels::kValueCount> PhaseCombiner::volumes_after(int folded) const {
  const std::lock_guard<std::mutex> lock(swap_);
  const int back = phases_ - folded;  // folds made since
  if (folded < 1 || back < 0 || back > keep_) {
    throw Error("breathing: the combination after " + std::to_string(folded) +
                " phases is no longer kept (" + std::to_string(phases_) + " folded)");
  }
  std::array<const float*, kernels::kValueCount> out{};
  for (int v = 0; v < kernels::kValueCount; ++v) {
    if (!(combined_.values & (1u << v))) continue;
    out[size_t(v)] = back == 0 ? combined_.volumes[size_t(v)].data()
                               : earlier_[size_t(back - 1)][size_t(v)].data();
  }
  return out;
}

void PhaseCombiner::fold(const PathSafetyResult& phase, const Volume<uint8_t>& region,
                         const std::function<void()>& combined) {
  const ImageGeometry& g = phase.grid.geometry;
  if (!region.geometry().same_grid(g, 1e-6)) {
    throw Error("breathing phase " + std::to_string(phases_ + 1) +
                ": its voxel states are not on its path safety grid");
  }
  if (!g.same_grid(combined_.grid.geometry, 1e-6) || phase.values != combined_.values) {
    throw Error("breathing phase " + std::to_string(phases_ + 1) +
                ": its path safety grid or values differ from the first phase's (the phases "
                "must share one output grid)");
  }
  if (spares_.valid()) spares_.get();
  if (earlier_.size() != size_t(keep_)) {  // keep_earlier set after the first fold
    const std::lock_guard<std::mutex> lock(swap_);
    earlier_.resize(size_t(keep_));
  }
  const int64_t n = g.voxel_count();
  const float nan = std::numeric_limits<float>::quiet_NaN();
  // Voxel states: computed only where computed in every phase; unknown wins over not computed.
  for_runs(phase.grid, /*whole=*/true, [&](int64_t first, int64_t last) {
    for (int64_t i = first; i <= last; ++i) {
      const uint8_t a = region_[i], b = region[i];
      if (a == kRegionComputed && b == kRegionComputed) continue;
      region_[i] =
          (a == kRegionUnknown || b == kRegionUnknown) ? kRegionUnknown : kRegionNotComputed;
    }
  });
  // With keep_earlier the combination is written beside the ones kept (into the buffer of the
  // oldest, which no phase reads any more), then the buffers move down one place.
  for (int v = 0; v < kernels::kValueCount; ++v) {
    if (!(phase.values & (1u << v))) continue;
    const bool svv = higher_is_safer(v);
    const Volume<float>& was = combined_.volumes[size_t(v)];
    if (keep_ > 0 && !earlier_.back()[size_t(v)].geometry().same_grid(g, 0.0)) {
      earlier_.back()[size_t(v)] = Volume<float>(g);
    }
    Volume<float>& worst = keep_ > 0 ? earlier_.back()[size_t(v)] : combined_.volumes[size_t(v)];
    Volume<float>& other = other_[size_t(v)];
    const Volume<float>& x = phase.volumes[size_t(v)];
    if (keep_ == 0) {
      // In place: the other extreme in the same pass.
#pragma omp parallel for schedule(static)
      for (int64_t i = 0; i < n; ++i) {
        const float w = was[i], o = other[i], p = x[i];
        if (std::isnan(w) || std::isnan(p)) {
          worst[i] = nan;
          other[i] = nan;
          continue;
        }
        worst[i] = svv ? std::min(w, p) : std::max(w, p);
        other[i] = svv ? std::max(o, p) : std::min(o, p);
      }
      continue;
    }
    // Outside the region every volume is NaN: only the region's runs, once the buffer written
    // holds NaN outside it (the first `keep_` folds write fresh buffers whole). A voxel not
    // computed in some phase (unknown there, NaN) is NaN without reading the values.
    const auto fold_runs = [&](int64_t first, int64_t last) {
      for (int64_t i = first; i <= last; ++i) {
        if (region_[i] != kRegionComputed) {
          worst[i] = nan;
          continue;
        }
        const float w = was[i], p = x[i];
        worst[i] = std::isnan(w) || std::isnan(p) ? nan : svv ? std::min(w, p) : std::max(w, p);
      }
    };
    for_runs(phase.grid, /*whole=*/phases_ <= keep_, fold_runs);
  }
  {
    const std::lock_guard<std::mutex> lock(swap_);
    if (keep_ > 0) {
      for (int v = 0; v < kernels::kValueCount; ++v) {
        if (!(phase.values & (1u << v))) continue;
        Volume<float> written = std::move(earlier_.back()[size_t(v)]);
        for (size_t e = earlier_.size() - 1; e > 0; --e) {
          earlier_[e][size_t(v)] = std::move(earlier_[e - 1][size_t(v)]);
        }
        earlier_[0][size_t(v)] = std::move(combined_.volumes[size_t(v)]);
        combined_.volumes[size_t(v)] = std::move(written);
      }
    }
    ++phases_;
  }
  fold_check(phase);
  // Fast mode's points, summed over the phases, level by level (by stride).
  FastModeReport& fast = combined_.fast;
  fast.evaluated_points += phase.fast.evaluated_points;
  fast.interpolated_voxels += phase.fast.interpolated_voxels;
  fast.cells_left_to_combination += phase.fast.cells_left_to_combination;
  fast.points_left_to_combination += phase.fast.points_left_to_combination;
  for (const auto& [stride, points] : phase.fast.levels) {
    auto& levels = fast.levels;
    const auto at = std::find_if(levels.begin(), levels.end(),
                                 [stride = stride](const auto& l) { return l.first == stride; });
    if (at != levels.end()) {
      at->second += points;
    } else {
      levels.emplace_back(stride, points);
    }
  }
  combined_.classes = {};  // the first phase's, if taken: the combination's values have changed
  combined_.statistics = {};
  combined_.seconds += phase.seconds;
  combined_.rays += phase.rays;
  // The combination is complete: the samplers waiting for it go on.
  if (combined) combined();
}

void PhaseCombiner::fold_extreme(const PathSafetyResult& phase) {
  if (keep_ == 0) return;  // taken in the fold's own pass
  const std::lock_guard<std::mutex> lock(extreme_);
  const float nan = std::numeric_limits<float>::quiet_NaN();
  for (int v = 0; v < kernels::kValueCount; ++v) {
    if (!(phase.values & (1u << v))) continue;
    const bool svv = higher_is_safer(v);
    float* other = other_[size_t(v)].data();
    const float* x = phase.volumes[size_t(v)].data();
    // NaN where some phase folded in is: where the combination is, once every phase is in.
    for_runs(phase.grid, /*whole=*/false, [&](int64_t first, int64_t last) {
      for (int64_t i = first; i <= last; ++i) {
        const float o = other[i], p = x[i];
        other[i] = std::isnan(o) || std::isnan(p) ? nan : svv ? std::max(o, p) : std::min(o, p);
      }
    });
  }
}

void PhaseCombiner::fold_check(const PathSafetyResult& phase) {
  if (!check_) return;
  if (!phase.check_sample) {
    check_.reset();
    return;
  }
  const CheckSample& other = *phase.check_sample;
  std::unordered_map<int64_t, size_t> at;
  for (size_t s = 0; s < other.offsets.size(); ++s) at.emplace(other.offsets[s], s);
  constexpr size_t kSlots = kernels::kValueCount;
  CheckSample folded;
  for (size_t s = 0; s < check_->offsets.size(); ++s) {
    const auto it = at.find(check_->offsets[s]);
    if (it == at.end()) continue;  // outside that phase's scan: unknown in the combination
    folded.offsets.push_back(check_->offsets[s]);
    for (size_t v = 0; v < kSlots; ++v) {
      const float a = check_->exact[s * kSlots + v], b = other.exact[it->second * kSlots + v];
      folded.exact.push_back(higher_is_safer(int(v)) ? std::min(a, b) : std::max(a, b));
    }
  }
  *check_ = std::move(folded);
}

double PhaseCombiner::class_change_share(int slot, const SafetyClasses& classes) const {
  std::array<const SafetyClasses*, kernels::kValueCount> asked{};
  asked[size_t(slot)] = &classes;
  return class_change_shares(asked)[size_t(slot)];
}

std::array<double, kernels::kValueCount> PhaseCombiner::class_change_shares(
    const std::array<const SafetyClasses*, kernels::kValueCount>& classes) const {
  constexpr int kSlots = kernels::kValueCount;
  const float* worst[kSlots] = {};
  const float* other[kSlots] = {};
  for (int s = 0; s < kSlots; ++s) {
    if (!classes[size_t(s)]) continue;
    worst[s] = combined_.volumes[size_t(s)].data();
    other[s] = other_extreme(s).data();
  }
  int64_t known[kSlots] = {}, changing[kSlots] = {};
#pragma omp parallel for schedule(static) reduction(+ : known[:kSlots], changing[:kSlots])
  for (int64_t i = 0; i < region_.voxel_count(); ++i) {
    if (region_[i] != kRegionComputed) continue;
    for (int s = 0; s < kSlots; ++s) {
      if (!worst[s] || std::isnan(worst[s][i])) continue;
      ++known[s];
      if (classes[size_t(s)]->classify(worst[s][i]) != classes[size_t(s)]->classify(other[s][i])) {
        ++changing[s];
      }
    }
  }
  std::array<double, kSlots> share{};
  for (int s = 0; s < kSlots; ++s) {
    share[size_t(s)] = known[s] ? double(changing[s]) / double(known[s]) : 0.0;
  }
  return share;
}

}  // namespace crepuscular::planning
