// Coarse-to-fine sampling of the output grid (fast mode): see adaptive_sampling.hpp.
#include "planning/safety/adaptive_sampling.hpp"

#include <omp.h>

#include <algorithm>
#include <chrono>
#include <future>
#include <cmath>
#include <limits>
#include <memory>
#include <optional>
#include <stdexcept>
#include <unordered_map>
#include <utility>

#include "foundation/error.hpp"
#include "foundation/large_buffers.hpp"
#include "foundation/trace.hpp"

namespace crepuscular::planning {

namespace {

// The finest level's margins, a share of the others: none. A point between two computed voxels
// of one class is interpolated (measured on every test scene: the same classes as with the whole
// margins at 31 % fewer points; bench/RESULTS.md, 2026-11-25).
constexpr double kFinestMargin = 0.0;
// Beside an evaluator on another device, the finest level in this many pieces.
constexpr int64_t kFinestPieces = 4;

constexpr uint8_t kPending = 0, kEvaluated = 1, kInterpolated = 2, kQueued = 3, kUnknown = 4;
// Interpolated by a level point by point (sample_between), which decides a point alike from every
// cell that shares it: the others of its pass pass over it. kDecided + the pass's number (from
// 0), so that a later pass decides it again as any interpolated voxel (its corners may have been
// computed since). Otherwise as kInterpolated.
constexpr uint8_t kDecided = 5;
constexpr int kSlots = kernels::kValueCount;

// The values of every point evaluated so far: voxels of the grid in the output arrays (all four
// slots kept here), lattice corners beyond the grid's edge in a map.
class SampleStore {
 public:
  SampleStore(const OutputGrid& grid, const AdaptiveOptions& options, float* const out[kSlots])
      : n_(grid.geometry.dims[0]),
        state_(new uint8_t[size_t(n_ * n_ * n_)]),  // not zeroed here: filled on every core
        known_(options.known),
        known_mask_(options.known_mask) {
    for (int s = 0; s < kSlots; ++s) out_[s] = out[s];
    const int64_t count = n_ * n_ * n_;
    advise_huge_pages(state_.get(), size_t(count));
#pragma omp parallel for schedule(static)
    for (int64_t v = 0; v < count; ++v) state_[size_t(v)] = kPending;
  }

  // Whether a point lies in the scan (AdaptiveOptions::known, known_mask).
  bool known(int64_t i, int64_t j, int64_t k) const {
    if (known_mask_ && inside(i, j, k)) return known_mask_[offset(i, j, k)] != 0;
    return !known_ || known_(i, j, k);
  }
  bool everything_known() const { return !known_mask_ && !known_; }

  bool inside(int64_t i, int64_t j, int64_t k) const {
    return i >= 0 && j >= 0 && k >= 0 && i < n_ && j < n_ && k < n_;
  }
  int64_t offset(int64_t i, int64_t j, int64_t k) const { return (k * n_ + j) * n_ + i; }
  uint8_t& state(int64_t i, int64_t j, int64_t k) { return state_[size_t(offset(i, j, k))]; }
  // The state as it is now, while other threads may change it.
  uint8_t state_now(int64_t i, int64_t j, int64_t k) const {
    return __atomic_load_n(&state_[size_t(offset(i, j, k))], __ATOMIC_RELAXED);
  }

  // Queues a lattice corner beyond the grid's edge for evaluation unless it has values already:
  // an interpolation support (below), computed in or outside the scan.
  void request_beyond(int64_t i, int64_t j, int64_t k, std::vector<GridPoint>& queue) {
    auto [it, added] = outside_.try_emplace(key(i, j, k));
    if (!added) return;
    it->second.fill(std::numeric_limits<float>::quiet_NaN());
    queue.push_back({int32_t(i), int32_t(j), int32_t(k)});
  }

  // A voxel of the grid to compute, safe to call from several threads at once: true when it is
  // newly queued (the caller queues it); false when it has values, is queued, or lies outside
  // the scan (it becomes unknown: NaN). An interpolated voxel (filled from a coarser cell) is
  // reclaimed: now computed.
  bool claim(int64_t i, int64_t j, int64_t k) { return take(i, j, k, kQueued, true); }
  // The same for a lattice corner of a cell that reaches into the scan: an interpolation
  // support, computed even where it lies outside the scan (the values are defined there, rays
  // and all; the voxel itself is reported unknown, NaN, when the sampling finishes). So a cell
  // crossing the scan's edge is refined where classes change, as any other, not split to voxels.
  bool claim_support(int64_t i, int64_t j, int64_t k) { return take(i, j, k, kQueued, false); }
  // Marks a pending voxel of the grid interpolated, from several threads at once: true when the
  // caller is to write its values (false: it has values, is queued, or lies outside the scan).
  bool claim_interpolated(int64_t i, int64_t j, int64_t k) {
    return take(i, j, k, kInterpolated, true);
  }
  // The same for a point that the present level point by point interpolates (decided()); one
  // interpolated already (from a coarser cell or an earlier pass) keeps its values and is marked
  // decided too.
  bool claim_decided(int64_t i, int64_t j, int64_t k) {
    uint8_t* s = &state_[size_t(offset(i, j, k))];
    uint8_t cur = __atomic_load_n(s, __ATOMIC_RELAXED);
    while (interpolated(cur) && cur != decided_) {
      if (__atomic_compare_exchange_n(s, &cur, decided_, false, __ATOMIC_RELAXED,
                                      __ATOMIC_RELAXED)) {
        return false;
      }
    }
    return take(i, j, k, decided_, true);
  }
  // A new level point by point: its own decided state.
  void begin_decisions() {
    if (passes_ == 255 - kDecided) {
      throw std::logic_error("sampler: too many levels point by point");
    }
    decided_ = uint8_t(kDecided + passes_++);
  }
  uint8_t decided() const { return decided_; }
  static bool interpolated(uint8_t state) { return state == kInterpolated || state >= kDecided; }

  void store(const GridPoint& p, const float* values) {
    if (inside(p.i, p.j, p.k)) {
      const int64_t off = offset(p.i, p.j, p.k);
      // Atomic: the finest level's next piece is gathered while this one is stored.
      __atomic_store_n(&state_[size_t(off)], kEvaluated, __ATOMIC_RELAXED);
      for (int s = 0; s < kSlots; ++s) {
        if (out_[s]) out_[s][off] = values[s];
      }
    } else {
      std::copy(values, values + kSlots, outside_[key(p.i, p.j, p.k)].begin());
    }
  }

  float value(int64_t i, int64_t j, int64_t k, int slot) const {
    if (inside(i, j, k)) return out_[slot][offset(i, j, k)];
    return outside_.at(key(i, j, k))[size_t(slot)];
  }

  // The value of a point that may have none (never computed nor interpolated: outside the
  // region, or a point beyond the grid's edge never requested): NaN there.
  float value_if_any(int64_t i, int64_t j, int64_t k, int slot) const {
    if (inside(i, j, k)) {
      const uint8_t st = state_now(i, j, k);
      return st == kEvaluated || interpolated(st) ? out_[slot][offset(i, j, k)]
                                                  : std::numeric_limits<float>::quiet_NaN();
    }
    const auto it = outside_.find(key(i, j, k));
    return it == outside_.end() ? std::numeric_limits<float>::quiet_NaN() : it->second[size_t(slot)];
  }

  void set(int64_t off, int slot, float v) { out_[slot][off] = v; }
  float* out(int slot) const { return out_[slot]; }
  int64_t reclaimed() const { return reclaimed_; }

 private:
  static uint64_t key(int64_t i, int64_t j, int64_t k) {
    constexpr int64_t kBias = 1 << 20;  // corners lie at most one cell beyond the grid
    return (uint64_t(i + kBias) << 42) | (uint64_t(j + kBias) << 21) | uint64_t(k + kBias);
  }

  // Moves a voxel from pending (or, for kQueued, interpolated) to `to`, or, when `in_scan_only`,
  // to unknown where it lies outside the scan; atomic on the voxel's state.
  bool take(int64_t i, int64_t j, int64_t k, uint8_t to, bool in_scan_only) {
    const int64_t off = offset(i, j, k);
    uint8_t* s = &state_[size_t(off)];
    uint8_t cur = __atomic_load_n(s, __ATOMIC_RELAXED);
    for (;;) {
      const bool was_interpolated = interpolated(cur);
      if (!(cur == kPending || (to == kQueued && was_interpolated))) return false;
      const uint8_t next = !in_scan_only || known(i, j, k) ? to : kUnknown;
      if (__atomic_compare_exchange_n(s, &cur, next, false, __ATOMIC_RELAXED, __ATOMIC_RELAXED)) {
        if (next == kUnknown) {
          for (int v = 0; v < kSlots; ++v) {
            if (out_[v]) out_[v][off] = std::numeric_limits<float>::quiet_NaN();
          }
          return false;
        }
        if (was_interpolated) __atomic_fetch_add(&reclaimed_, 1, __ATOMIC_RELAXED);
        return true;
      }
    }
  }

  int64_t n_;
  std::unique_ptr<uint8_t[]> state_;
  std::function<bool(int64_t, int64_t, int64_t)> known_;
  const uint8_t* known_mask_ = nullptr;
  float* out_[kSlots] = {};
  std::unordered_map<uint64_t, std::array<float, kSlots>> outside_;
  int64_t reclaimed_ = 0;
  int passes_ = 0;
  uint8_t decided_ = kDecided;
};

// A lattice cell: lower corner and edge, in output voxels.
struct Cell {
  int32_t i, j, k, size;
  // Corner q (0..7; bit 0: +i, bit 1: +j, bit 2: +k).
  int64_t ci(int q) const { return i + (q & 1) * size; }
  int64_t cj(int q) const { return j + ((q >> 1) & 1) * size; }
  int64_t ck(int q) const { return k + ((q >> 2) & 1) * size; }
};

// The uniform cells of one edge that one fill interpolates, marked by their lattice position, so
// that a voxel shared by several of them (on a face, an edge or a corner) is written by one alone
// (fill_owned). The cells of a fill are then filled side by side, in lattice order, each voxel
// once, and consecutive cells of a fill lie together in memory.
class FilledCells {
 public:
  // The lattice of edge `size` through the centre voxel `half`, over a grid of n voxels per axis,
  // with room for every cell meeting the grid and its neighbours.
  void reset(int64_t n, int64_t half, int size) {
    size_ = size;
    half_ = half;
    lo_ = -((half + size - 1) / size) - 2;
    na_ = (n - 1 - half) / size + 2 - lo_ + 1;
    marks_.assign(size_t(na_ * na_ * na_), 0);
  }
  // Safe from several threads for distinct cells.
  void mark(const Cell& c) {
    const int64_t a = coord(c.i) - lo_, b = coord(c.j) - lo_, d = coord(c.k) - lo_;
    // Every cell of a fill meets the grid; one that did not would be written by each neighbour.
    if (a < 0 || b < 0 || d < 0 || a >= na_ || b >= na_ || d >= na_) return;
    marks_[size_t((d * na_ + b) * na_ + a)] = 1;
  }
  // A cell's lattice coordinate along one axis (its lower corner lies on the lattice).
  int64_t coord(int64_t lower) const { return (lower - half_) / size_; }
  bool filled(int64_t a, int64_t b, int64_t d) const {
    a -= lo_;
    b -= lo_;
    d -= lo_;
    if (a < 0 || b < 0 || d < 0 || a >= na_ || b >= na_ || d >= na_) return false;
    return marks_[size_t((d * na_ + b) * na_ + a)] != 0;
  }

 private:
  int size_ = 1;
  int64_t half_ = 0, lo_ = 0, na_ = 0;
  std::vector<uint8_t> marks_;
};

// Fills the voxels of a uniform cell (or of `part` of it, a child) that it owns by trilinear
// interpolation of the cell's corners, never a voxel evaluated, queued or outside the scan;
// returns how many voxels became interpolated. Every cell (or part) of the fill is marked in
// `filled`. A voxel lies on 0 to 3 lattice planes; the cells of the fill whose boxes hold
// it are the cell c* whose half-open box [lower, lower + size) holds it and those below c* across
// its planes (c* - r, r a set of those axes). Its owner is the marked one of smallest r (bit 0:
// i, bit 1: j, bit 2: k), so every voxel is written once, by the same cell whatever the order.
// Its value is the owner's trilinear interpolation, in j, then k, then i (along a row, a line
// between the cell's two faces across i, in the region's run of the row), taken so that on a
// shared face it is the same bits from either cell (the face's corners alone weigh there).
int64_t fill_owned(const Cell& cell, const FilledCells& filled, const OutputGrid& grid,
                   const std::vector<int>& slots, SampleStore& store, const Cell* part = nullptr) {
  const Cell& box = part ? *part : cell;  // the cells marked in `filled` are of the box's edge
  const int64_t a = filled.coord(box.i), b = filled.coord(box.j), d = filled.coord(box.k);
  bool neighbour[27];
  for (int m = 0; m < 27; ++m) {
    neighbour[m] = filled.filled(a + m % 3 - 1, b + m / 3 % 3 - 1, d + m / 9 - 1);
  }
  // Per voxel class (per axis 0: on the box's lower plane, 1: inside, 2: on its upper plane; i
  // fastest), whether this box writes it: box = c* - own, own the axes of its upper planes.
  bool writes[27];
  for (int m = 0; m < 27; ++m) {
    const int p[3] = {m % 3, m / 3 % 3, m / 9};
    int own = 0, planes = 0;
    for (int axis = 0; axis < 3; ++axis) {
      if (p[axis] == 2) own |= 1 << axis;
      if (p[axis] != 1) planes |= 1 << axis;
    }
    bool w = true;
    for (int r = 0; r < own && w; ++r) {
      if ((r & ~planes) != 0) continue;  // not a box holding the voxel
      int at = 0;  // c* - r relative to the box: own - r per axis
      for (int axis = 2; axis >= 0; --axis) {
        at = at * 3 + ((own >> axis) & 1) - ((r >> axis) & 1) + 1;
      }
      w = !neighbour[at];
    }
    writes[m] = w;
  }
  const int64_t n = grid.geometry.dims[0];
  int64_t interpolated = 0;
  float corner[8][kSlots];
  for (int q = 0; q < 8; ++q) {
    for (const int s : slots) corner[q][s] = store.value(cell.ci(q), cell.cj(q), cell.ck(q), s);
  }
  const auto plane = [](int64_t v, int64_t lower, int size) {
    return v == lower ? 0 : v == lower + size ? 2 : 1;
  };
  // On the cell's upper plane the upper value itself (a + 1 (b - a) can round away from b): a
  // voxel of a face, edge or corner shared with a neighbouring cell then takes the same bits from
  // either, those of the face's corners alone (inside a cell, its parts share its weights).
  const auto lerp = [](float a, float b, float w, bool upper) {
    return upper ? b : a + w * (b - a);
  };
  const int size = cell.size;
  const float inv = 1.0f / float(size);
  const int64_t i0 = std::max<int64_t>(box.i, 0), i1 = std::min<int64_t>(box.i + box.size, n - 1);
  for (int64_t k = std::max<int64_t>(box.k, 0); k <= std::min<int64_t>(box.k + box.size, n - 1);
       ++k) {
    const float wz = float(k - cell.k) * inv;
    const bool uk = k == cell.k + size;
    const int pk = plane(k, box.k, box.size);
    for (int64_t j = std::max<int64_t>(box.j, 0);
         j <= std::min<int64_t>(box.j + box.size, n - 1); ++j) {
      // The row's voxels in the region: all of them where both ends are (a ball is convex).
      int64_t first = i0, last = i1;
      if (!grid.in_roi(first, j, k) || !grid.in_roi(last, j, k)) {
        const auto [a, b] = grid.roi_run(j, k);
        first = std::max(first, a);
        last = std::min(last, b);
      }
      if (first > last) continue;
      const float wy = float(j - cell.j) * inv;
      const bool uj = j == cell.j + size;
      const int row = 9 * pk + 3 * plane(j, box.j, box.size);
      // The row's values on the cell's two faces across i (the lerps in j, then k): the voxels
      // between lie on a line from one to the other.
      float low[kSlots] = {}, high[kSlots] = {};
      for (const int s : slots) {
        low[s] = lerp(lerp(corner[0][s], corner[2][s], wy, uj),
                      lerp(corner[4][s], corner[6][s], wy, uj), wz, uk);
        high[s] = lerp(lerp(corner[1][s], corner[3][s], wy, uj),
                       lerp(corner[5][s], corner[7][s], wy, uj), wz, uk);
      }
      int64_t off = store.offset(first, j, k);
      for (int64_t i = first; i <= last; ++i, ++off) {
        if (!writes[row + plane(i, box.i, box.size)]) continue;
        uint8_t& st = store.state(i, j, k);
        // Queued: claimed by the next level (a fill beside its evaluation), computed there.
        if (st == kEvaluated || st == kUnknown || st == kQueued) continue;
        // A voxel outside the scan is never interpolated. It stays pending (unknown when the
        // sampling finishes), so that a finer cell may still compute it as a support.
        if (!store.known(i, j, k)) continue;
        if (!SampleStore::interpolated(st)) ++interpolated;
        st = kInterpolated;
        const float wx = float(i - cell.i) * inv;
        const bool ui = i == cell.i + size;
        for (const int s : slots) store.set(off, s, lerp(low[s], high[s], wx, ui));
      }
    }
  }
  return interpolated;
}

// Fills the children of edge `h` of `cells` whose bits are set in `bits` (bit `child` of each
// cell's byte), each voxel by the one child that owns it (fill_owned), from the child's own
// corners or, `from_parent`, from its cell's. Returns how many voxels became interpolated.
int64_t fill_children(const std::vector<Cell>& cells, const std::vector<uint8_t>& bits, int h,
                      bool from_parent, FilledCells& filled, const OutputGrid& grid,
                      const std::vector<int>& slots, SampleStore& store) {
  const auto part_of = [h](const Cell& cell, int child) {
    return Cell{cell.i + (child & 1) * h, cell.j + ((child >> 1) & 1) * h,
                cell.k + ((child >> 2) & 1) * h, h};
  };
  const int64_t count = int64_t(cells.size());
  filled.reset(grid.geometry.dims[0], grid.half, h);
#pragma omp parallel for schedule(static)
  for (int64_t c = 0; c < count; ++c) {
    for (int child = 0; bits[size_t(c)] && child < 8; ++child) {
      if (bits[size_t(c)] & (1u << child)) filled.mark(part_of(cells[size_t(c)], child));
    }
  }
  int64_t interpolated = 0;
#pragma omp parallel for schedule(dynamic, 64) reduction(+ : interpolated)
  for (int64_t c = 0; c < count; ++c) {
    for (int child = 0; bits[size_t(c)] && child < 8; ++child) {
      if (!(bits[size_t(c)] & (1u << child))) continue;
      const Cell part = part_of(cells[size_t(c)], child);
      interpolated += from_parent ? fill_owned(cells[size_t(c)], filled, grid, slots, store, &part)
                                  : fill_owned(part, filled, grid, slots, store);
    }
  }
  return interpolated;
}

// `scale` shrinks the margins (the finest level's points lie one voxel from computed ones).
bool near_threshold(const SafetyClasses& c, double v, const AdaptiveOptions& o,
                    double scale = 1.0) {
  if (c.higher_is_safer) {
    const double m = scale * o.svv_margin;
    return std::abs(v - c.safe) < m || std::abs(v - c.dangerous) < m;
  }
  const double f = 1.0 + scale * o.blocking_margin;
  for (const double t : {c.safe, c.dangerous}) {
    if (t > 0.0 && v > t / f && v < t * f) return true;
  }
  return false;
}

// The class of `v` (0 safe, 1 medium, 2 dangerous; -1 unknown) with `v` moved by the margins
// (scaled as in near_threshold) toward danger or toward safety: a value that near_threshold
// calls close to a threshold counts as the class on that side.
int danger_rank(const SafetyClasses& c, double v, const AdaptiveOptions& o, double scale,
                bool toward_danger) {
  if (std::isnan(v)) return -1;
  if (c.higher_is_safer) {
    const double m = scale * o.svv_margin;
    v = toward_danger ? v - m : v + m;
  } else {
    const double f = 1.0 + scale * o.blocking_margin;
    v = toward_danger ? v * f : v / f;
  }
  return int(c.classify(v));
}

// The combination of the phases computed before (AdaptiveOptions::combination): whether this
// phase can change its class. `most_dangerous[s]` is, per value slot whose class changes among
// the supports (or lies near a threshold), the most dangerous class of the supports toward danger
// (-1: the value needs nothing from the combination; -2: a support is unknown, never left).
struct Combination {
  std::array<const float*, kernels::kValueCount> worst{};
  // A phase not folded into `worst` yet, read through it (CombinedVolumes::pending).
  std::array<const float*, kernels::kValueCount> pending{};
  Combination& operator=(const CombinedVolumes& v) {
    worst = v.folded;
    pending = v.pending;
    return *this;
  }
  bool any() const {
    for (const float* w : worst) {
      if (w) return true;
    }
    return false;
  }
  // Slot s's combined value at `offset` (its volume must be given).
  float at(int s, int64_t offset) const {
    const float w = worst[size_t(s)][offset];
    const float* p = pending[size_t(s)];
    if (!p) return w;
    const float q = p[offset];
    if (std::isnan(w) || std::isnan(q)) return std::numeric_limits<float>::quiet_NaN();
    return (1u << s) == kernels::kSvv ? std::min(w, q) : std::max(w, q);
  }
  // The voxel at `offset` is at least as dangerous in the combination (toward safety by
  // AdaptiveOptions::combination_margin_share of the margins) as
  // `most_dangerous` for every value that needs it; a voxel unknown in the combination is
  // unknown whatever this phase says.
  bool covers(int64_t offset, const std::array<int, kernels::kValueCount>& most_dangerous,
              const std::array<SafetyClasses, kernels::kValueCount>& classes,
              const AdaptiveOptions& o, double scale) const {
    for (int s = 0; s < kernels::kValueCount; ++s) {
      if (most_dangerous[size_t(s)] == -1) continue;
      if (most_dangerous[size_t(s)] < -1 || !worst[size_t(s)]) return false;
      const float w = at(s, offset);
      if (std::isnan(w)) continue;
      // The combination's side: its margins a share of the blocking ones, none for SVV
      // (AdaptiveOptions::combination_margin_share).
      const SafetyClasses& c = classes[size_t(s)];
      const double side = c.higher_is_safer ? 0.0 : scale * kCombinationMarginShare;
      if (danger_rank(c, w, o, side, false) < most_dangerous[size_t(s)]) {
        return false;
      }
    }
    return true;
  }
};

// Whether this phase cannot change the combination's class anywhere in `box`: every voxel of it
// in the region and the scan covers `most` (Combination::covers, margins times `scale`).
bool combination_covers_box(const Combination& combination, const SampleStore& store,
                            const OutputGrid& grid, const Cell& box,
                            const std::array<int, kernels::kValueCount>& most,
                            const std::array<SafetyClasses, kernels::kValueCount>& classes,
                            const AdaptiveOptions& options, double scale) {
  const int64_t n = grid.geometry.dims[0];
  for (int64_t k = std::max<int64_t>(box.k, 0); k <= std::min<int64_t>(box.k + box.size, n - 1);
       ++k)
    for (int64_t j = std::max<int64_t>(box.j, 0);
         j <= std::min<int64_t>(box.j + box.size, n - 1); ++j)
      for (int64_t i = std::max<int64_t>(box.i, 0);
           i <= std::min<int64_t>(box.i + box.size, n - 1); ++i) {
        if (!grid.in_roi(i, j, k) || !store.known(i, j, k)) continue;
        if (!combination.covers(store.offset(i, j, k), most, classes, options, scale)) {
          return false;
        }
      }
  return true;
}

// Eight corners' classes per value slot, moved by the margins toward danger (`up`) and toward
// safety (`down`): danger_rank, taken once per cell.
struct CornerRanks {
  int up[8][kernels::kValueCount] = {};
  int down[8][kernels::kValueCount] = {};
};

CornerRanks rank_corners(const float (*value)[kernels::kValueCount],
                         const std::vector<int>& slots,
                         const std::array<SafetyClasses, kernels::kValueCount>& classes,
                         const AdaptiveOptions& o, double scale) {
  CornerRanks r;
  for (int q = 0; q < 8; ++q) {
    for (const int s : slots) {
      r.up[q][s] = danger_rank(classes[size_t(s)], value[q][s], o, scale, true);
      r.down[q][s] = danger_rank(classes[size_t(s)], value[q][s], o, scale, false);
    }
  }
  return r;
}

// Per value slot of `slots`, what the combination must cover for the supports `ends[0..count)`
// among the ranked corners (Combination::covers): -1 where they agree in class and none lies
// near a threshold.
std::array<int, kernels::kValueCount> most_dangerous_of(const CornerRanks& r, const int* ends,
                                                        int count, const std::vector<int>& slots) {
  std::array<int, kernels::kValueCount> most;
  most.fill(-1);
  for (const int s : slots) {
    int lo = 3, hi = -1;
    for (int q = 0; q < count; ++q) {
      const int e = ends[q];
      if (r.up[e][s] < 0) {  // unknown
        hi = -2;
        break;
      }
      lo = std::min(lo, r.down[e][s]);
      hi = std::max(hi, r.up[e][s]);
    }
    most[size_t(s)] = hi == -2 ? -2 : lo != hi ? hi : -1;
  }
  return most;
}

// Wall time of the sampler's steps, summed over its levels.
class StepClock {
 public:
  enum Step {
    kCells, kRequests, kFinestRequests, kStore, kRefine, kFill, kFinish, kEvaluate,
    kCombinationWait, kSteps
  };
  // Also a trace event (foundation/trace.hpp) at the step's end, its count the microseconds.
  void add(Step step, std::chrono::steady_clock::time_point since) {
    const double s =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - since).count();
    seconds_[step] += s;
    trace::event(kNames[step], static_cast<long long>(s * 1e6));
  }
  std::vector<std::pair<std::string, double>> named() const {
    std::vector<std::pair<std::string, double>> out;
    for (int s = 0; s < kSteps; ++s) out.emplace_back(kNames[s], seconds_[s]);
    return out;
  }

 private:
  static constexpr const char* kNames[kSteps] = {
      "sampler_cells",  "sampler_requests", "sampler_finest_requests", "sampler_store",
      "sampler_refine", "sampler_fill",     "sampler_finish",          "sampler_evaluate",
      "sampler_combination_wait"};
  double seconds_[kSteps] = {};
};

// Per-thread lists of gather_requests, kept from call to call: lists that grow afresh in each
// call spend much of the sampler's time in the kernel clearing their new pages.
struct RequestLists {
  std::vector<std::vector<GridPoint>> mine, beyond;
};

// Queues the points that `points_of(c, offer)` offers for items c = 0..count-1, in parallel: grid
// voxels are claimed atomically, the few corners beyond the grid's edge are requested afterwards
// on one thread. The queue keeps the items' order (threads take contiguous ranges).
template <typename PointsOf>
void gather_requests(int64_t count, const PointsOf& points_of, SampleStore& store,
                     RequestLists& lists, std::vector<GridPoint>& queue, bool supports = false) {
  queue.clear();
  const int threads = omp_get_max_threads();
  lists.mine.resize(size_t(threads));
  lists.beyond.resize(size_t(threads));
  for (int t = 0; t < threads; ++t) {
    lists.mine[size_t(t)].clear();
    lists.beyond[size_t(t)].clear();
  }
#pragma omp parallel num_threads(threads)
  {
    const size_t t = size_t(omp_get_thread_num());
    std::vector<GridPoint>& mine = lists.mine[t];
    std::vector<GridPoint>& beyond = lists.beyond[t];
#pragma omp for schedule(static)
    for (int64_t c = 0; c < count; ++c) {
      points_of(c, [&](int64_t i, int64_t j, int64_t k) {
        if (!store.inside(i, j, k)) {
          beyond.push_back({int32_t(i), int32_t(j), int32_t(k)});
        } else if (supports ? store.claim_support(i, j, k) : store.claim(i, j, k)) {
          mine.push_back({int32_t(i), int32_t(j), int32_t(k)});
        }
      });
    }
  }
  // The lists joined in thread order, each copied at its offset on its own core.
  std::vector<size_t> at(size_t(threads) + 1, 0);
  for (int t = 0; t < threads; ++t) at[size_t(t) + 1] = at[size_t(t)] + lists.mine[size_t(t)].size();
  queue.resize(at.back());
#pragma omp parallel for schedule(static, 1) num_threads(threads)
  for (int t = 0; t < threads; ++t) {
    std::copy(lists.mine[size_t(t)].begin(), lists.mine[size_t(t)].end(),
              queue.begin() + std::ptrdiff_t(at[size_t(t)]));
  }
  for (const auto& b : lists.beyond) {
    for (const GridPoint& g : b) store.request_beyond(g.i, g.j, g.k, queue);
  }
}

// Stores the computed values of the queued points (grid voxels in parallel, the few corners
// beyond the grid's edge after them).
void store_values(const std::vector<GridPoint>& queue, const std::vector<float>& values,
                  SampleStore& store) {
#pragma omp parallel for schedule(static)
  for (int64_t p = 0; p < int64_t(queue.size()); ++p) {
    const GridPoint& g = queue[size_t(p)];
    if (store.inside(g.i, g.j, g.k)) store.store(g, &values[size_t(p) * kSlots]);
  }
  for (size_t p = 0; p < queue.size(); ++p) {
    if (!store.inside(queue[p].i, queue[p].j, queue[p].k)) store.store(queue[p], &values[p * kSlots]);
  }
}

// Computes the queued points and stores their values (grid voxels in parallel). `beside`, when
// given, runs on a thread of its own while the evaluator computes (the wait for it after the
// evaluator is done counts as the fill's).
void evaluate_queue(const std::vector<GridPoint>& queue, const PointEvaluator& evaluate,
                    SampleStore& store, std::vector<float>& values, StepClock& clock,
                    const std::function<void()>& beside = {}) {
  auto t = std::chrono::steady_clock::now();
  // Grown, never cleared: the evaluator writes every requested slot of every point, and only
  // those are read back.
  if (values.size() < queue.size() * kSlots) values.resize(queue.size() * kSlots);
  clock.add(StepClock::kStore, t);
  std::future<void> side;
  if (beside) side = std::async(std::launch::async, beside);
  if (!queue.empty()) {
    t = std::chrono::steady_clock::now();
    evaluate(queue, values);
    clock.add(StepClock::kEvaluate, t);
  }
  if (side.valid()) {
    t = std::chrono::steady_clock::now();
    side.get();
    clock.add(StepClock::kFill, t);
  }
  if (queue.empty()) return;
  t = std::chrono::steady_clock::now();
  store_values(queue, values, store);
  clock.add(StepClock::kStore, t);
}

// A corner's classes as one key, so that points compare by one comparison: two bits per
// requested value's class, or kMixedKey where a value is unknown or lies near a threshold (such
// a corner agrees with nothing, not even itself).
constexpr uint16_t kMixedKey = 0x100;

uint16_t class_key(const float* values, const std::vector<int>& slots,
                   const AdaptiveReport& report, const AdaptiveOptions& options, double scale) {
  uint16_t key = 0;
  for (const int s : slots) {
    const SafetyClasses& classes = report.classes[size_t(s)];
    const double v = values[s];
    const SafetyClass c = classes.classify(v);
    if (c == SafetyClass::kUnknown || near_threshold(classes, v, options, scale)) {
      return kMixedKey;
    }
    key = uint16_t(key | (uint16_t(c) & 3u) << (2 * s));
  }
  return key;
}

// The points of a cell of edge 2 other than its corners (edge midpoints, face centres, the
// centre: 19 of the 27), each with the corners of the smallest box of corners around it, in the
// order in which their values are summed (bit b of the box's corner number on the b-th axis
// along which the point lies half-way, axes in the order i, j, k).
struct FinestPoint {
  int di, dj, dk;
  int ends;          // 2, 4 or 8
  int corner[8];     // corner numbers of the cell (bit 0: +i, bit 1: +j, bit 2: +k)
};

std::vector<FinestPoint> finest_points() {
  std::vector<FinestPoint> points;
  for (int m = 0; m < 27; ++m) {
    const int d[3] = {m % 3, (m / 3) % 3, m / 9};
    const int halves = (d[0] == 1) + (d[1] == 1) + (d[2] == 1);
    if (halves == 0) continue;
    FinestPoint p{d[0], d[1], d[2], 1 << halves, {}};
    for (int q = 0; q < p.ends; ++q) {
      int bit = 0, corner = 0;
      for (int a = 0; a < 3; ++a) {
        const int high = d[a] == 1 ? (q >> bit++) & 1 : d[a] / 2;
        corner |= high << a;
      }
      p.corner[q] = corner;
    }
    points.push_back(p);
  }
  return points;
}

// A level point by point: inside the refined cells of edge 2 (the finest level) or 4 (the level
// above it, the level above the finest point by point), an edge's midpoint, a face's centre and the
// cell's centre are computed where the corners around them (the edge's ends, the face's
// corners, the cell's corners) differ in a class or lie near a threshold (the margins times
// `scale`), and interpolated from them where they agree. A class boundary crossing a cell is
// computed on the edges and faces it crosses; the cell's uniform edges and faces are
// interpolated, as a uniform cell is. Each point's decision depends only on its own corners, so
// a point shared by neighbouring cells is decided alike from each; the first to claim it acts,
// and all are gathered in one pass. `beside`, when given, runs while the (last) points are
// computed. Returns the points computed.
int64_t sample_between(const std::vector<Cell>& refined, double scale, const OutputGrid& grid,
                       const AdaptiveOptions& options, const std::vector<int>& slots,
                       const PointEvaluator& evaluate, AdaptiveReport& report, SampleStore& store,
                       RequestLists& lists, std::vector<GridPoint>& queue,
                       std::vector<float>& values, StepClock& clock,
                       const Combination& combination, int leave_box,
                       const std::function<void()>& beside,
                       const std::function<void(double)>& done) {
  static const std::vector<FinestPoint> kPoints = finest_points();
  store.begin_decisions();
  const uint8_t decided = store.decided();
  int64_t interpolated = 0, left = 0;
  const bool combined = combination.any();
  const auto gather = [&](int64_t first, int64_t count, std::vector<GridPoint>& into) {
    gather_requests(
        count,
        [&](int64_t c, const auto& offer) {
          const Cell& cell = refined[size_t(first + c)];
          uint16_t key[8];
          float value[8][kSlots] = {};
          for (int q = 0; q < 8; ++q) {
            const int64_t i = cell.ci(q), j = cell.cj(q), k = cell.ck(q);
            for (const int s : slots) value[q][s] = store.value_if_any(i, j, k, s);
            key[q] = class_key(value[q], slots, report, options, scale);
          }
          // The corners' classes toward danger and toward safety (the finest margins), once per
          // cell, for the points left to the combination.
          const CornerRanks ranks =
              combined ? rank_corners(value, slots, report.classes, options, scale) : CornerRanks{};
          const int h = cell.size / 2;
          int64_t cell_interpolated = 0, cell_left = 0;  // counted once per cell
          for (const FinestPoint& p : kPoints) {
            const int64_t i = cell.i + p.di * h, j = cell.j + p.dj * h, k = cell.k + p.dk * h;
            if (!store.inside(i, j, k) || !grid.in_roi(i, j, k)) continue;
            const uint8_t st = store.state_now(i, j, k);
            // Decided already in this pass, from a cell that shares the point (alike).
            if (st == kEvaluated || st == kQueued || st == kUnknown || st == decided) continue;
            bool uniform = key[p.corner[0]] != kMixedKey;
            for (int q = 1; q < p.ends && uniform; ++q) {
              uniform = key[p.corner[q]] == key[p.corner[0]];
            }
            // Left to the phases before where this one cannot change the combination's class:
            // at the point, and at every voxel within `leave_box` of it (the voxels of the
            // finer cells whose corner it becomes).
            bool left_to_combination = !uniform && combined;
            if (left_to_combination) {
              const auto most = most_dangerous_of(ranks, p.corner, p.ends, slots);
              const int32_t b = leave_box;
              // The combination's side keeps its whole share of the margin (the thresholds'
              // drift as later phases fold in), whatever the finest level's own margins.
              left_to_combination =
                  b == 0 ? combination.covers(store.offset(i, j, k), most, report.classes,
                                              options, 1.0)
                         : combination_covers_box(
                               combination, store, grid,
                               Cell{int32_t(i) - b, int32_t(j) - b, int32_t(k) - b, 2 * b}, most,
                               report.classes, options, 1.0);
            }
            cell_left += left_to_combination ? 1 : 0;
            if (!uniform && !left_to_combination) {
              offer(i, j, k);  // computed (an interpolation from a coarser cell is reclaimed)
            } else if (store.claim_decided(i, j, k)) {
              const int64_t off = store.offset(i, j, k);
              for (const int s : slots) {
                float sum = 0.0f;
                for (int q = 0; q < p.ends; ++q) sum += value[p.corner[q]][s];
                store.set(off, s, sum / float(p.ends));
              }
              ++cell_interpolated;
            }
          }
          if (cell_left) __atomic_fetch_add(&left, cell_left, __ATOMIC_RELAXED);
          if (cell_interpolated) {
            __atomic_fetch_add(&interpolated, cell_interpolated, __ATOMIC_RELAXED);
          }
        },
        store, lists, into);
  };
  const int64_t cells = int64_t(refined.size());
  int64_t computed = 0;
  if (options.overlap_host_steps && cells >= 2) {
    // In pieces: each piece's points computed and stored (on the evaluator's device, the store
    // on the cores) while the next piece's are gathered. The decisions depend on the corners
    // alone, which are never finest points, so the points are those of one pass; a point
    // offered by two pieces is claimed by the first.
    const int64_t pieces = std::min<int64_t>(kFinestPieces, cells);
    std::vector<GridPoint> piece[2];
    std::vector<float> piece_values[2];
    std::future<void> running;
    for (int64_t p = 0; p < pieces; ++p) {
      std::vector<GridPoint>& q = piece[p & 1];
      std::vector<float>& v = piece_values[p & 1];
      const int64_t first = cells * p / pieces, last = cells * (p + 1) / pieces;
      auto t = std::chrono::steady_clock::now();
      gather(first, last - first, q);  // the lists are copied into q: free for the next piece
      clock.add(StepClock::kFinestRequests, t);
      t = std::chrono::steady_clock::now();
      if (running.valid()) running.get();  // the piece before, computed and stored
      clock.add(StepClock::kEvaluate, t);
      computed += int64_t(q.size());
      if (q.empty()) continue;
      if (v.size() < q.size() * kSlots) v.resize(q.size() * kSlots);
      running = std::async(std::launch::async, [&q, &v, &evaluate, &store] {
        evaluate(q, v);
        store_values(q, v, store);
      });
    }
    // `beside` once every point is claimed (it may interpolate voxels a gather would claim),
    // while the last piece is computed.
    auto t = std::chrono::steady_clock::now();
    if (beside) {
      beside();
      clock.add(StepClock::kFill, t);
      t = std::chrono::steady_clock::now();
    }
    if (running.valid()) running.get();
    clock.add(StepClock::kEvaluate, t);
    report.interpolated += interpolated;
  } else {
    const auto t = std::chrono::steady_clock::now();
    gather(0, cells, queue);
    clock.add(StepClock::kFinestRequests, t);
    report.interpolated += interpolated;
    evaluate_queue(queue, evaluate, store, values, clock, beside);
    computed = int64_t(queue.size());
  }
  report.points_left_to_combination += left;
  done(1.0);
  return computed;
}

// Progress through the levels: each level computes about four times the points of the one
// before (a class boundary's area at half the stride), so level k of L weighs 4^k.
class LevelProgress {
 public:
  LevelProgress(int levels, std::function<void(double)> report)
      : levels_(levels), report_(std::move(report)) {}
  // Level `level` (0: the coarsest) done to `fraction`.
  void at(int level, double fraction) {
    if (!report_) return;
    double done = 0.0, total = 0.0;
    for (int k = 0; k < levels_; ++k) {
      const double w = std::pow(4.0, k);
      total += w;
      if (k < level) done += w;
      if (k == level) done += w * fraction;
    }
    const double f = std::min(1.0, done / total);
    if (f > last_) report_(last_ = f);
  }

 private:
  int levels_;
  std::function<void(double)> report_;
  double last_ = 0.0;
};

}  // namespace

AdaptiveReport sample_adaptively(const OutputGrid& grid, const AdaptiveOptions& options,
                                 const PointEvaluator& evaluate,
                                 float* const out[kernels::kValueCount]) {
  const int s0 = options.stride;
  if (s0 < 2 || (s0 & (s0 - 1)) != 0 || s0 > 64) {
    throw Error("fast mode: the coarsest sampling stride must be a power of two from 2 to 64 "
                "(got " + std::to_string(s0) + ")");
  }
  const int64_t n = grid.geometry.dims[0];
  const int64_t half = grid.half;
  const double radius_sq = double(grid.max_sq);
  AdaptiveReport report;
  StepClock clock;
  auto t = std::chrono::steady_clock::now();
  SampleStore store(grid, options, out);
  std::vector<int> slots;
  for (int s = 0; s < kSlots; ++s) {
    if (options.values & (1u << s)) slots.push_back(s);
  }

  // Does the box [lo, lo + size]^3 meet the grid and the ball of the region of interest?
  const auto meets_roi = [&](int64_t i, int64_t j, int64_t k, int64_t size) {
    double d2 = 0.0;
    for (const int64_t lo : {i, j, k}) {
      if (lo > n - 1 || lo + size < 0) return false;
      const double c = double(half);
      const double nearest = std::clamp(c, double(lo), double(lo + size));
      d2 += (nearest - c) * (nearest - c);
    }
    return d2 <= radius_sq;
  };

  // Does the box [lo, lo + size]^3 hold a voxel of the region inside the scan? Cells that do not
  // are never sampled: their voxels are unknown.
  const auto reaches_scan = [&](int64_t i, int64_t j, int64_t k, int64_t size) {
    if (store.everything_known()) return true;
    for (int q = 0; q < 8; ++q) {
      const int64_t ci = i + (q & 1) * size, cj = j + ((q >> 1) & 1) * size,
                    ck = k + ((q >> 2) & 1) * size;
      if (store.inside(ci, cj, ck) && grid.in_roi(ci, cj, ck) && store.known(ci, cj, ck)) {
        return true;
      }
    }
    for (int64_t kk = std::max<int64_t>(k, 0); kk <= std::min<int64_t>(k + size, n - 1); ++kk)
      for (int64_t jj = std::max<int64_t>(j, 0); jj <= std::min<int64_t>(j + size, n - 1); ++jj)
        for (int64_t ii = std::max<int64_t>(i, 0); ii <= std::min<int64_t>(i + size, n - 1); ++ii) {
          if (grid.in_roi(ii, jj, kk) && store.known(ii, jj, kk)) return true;
        }
    return false;
  };

  // The coarsest cells, lattice through the centre voxel, as a dense array for dilation.
  const int64_t a_lo = -((half + s0 - 1) / s0), a_hi = (n - 1 - half + s0 - 1) / s0 - 1;
  const int64_t na = a_hi - a_lo + 1;
  // Which lattice cells to sample, decided on every core, then numbered in lattice order.
  std::vector<Cell> cells;
  std::vector<int32_t> cell_at(size_t(na * na * na), -1);
#pragma omp parallel for schedule(dynamic, 1) collapse(2)
  for (int64_t c = a_lo; c <= a_hi; ++c) {
    for (int64_t b = a_lo; b <= a_hi; ++b) {
      for (int64_t a = a_lo; a <= a_hi; ++a) {
        const int64_t i = half + a * s0, j = half + b * s0, k = half + c * s0;
        if (meets_roi(i, j, k, s0) && reaches_scan(i, j, k, s0)) {
          cell_at[size_t(((c - a_lo) * na + (b - a_lo)) * na + (a - a_lo))] = 0;
        }
      }
    }
  }
  for (int64_t c = a_lo; c <= a_hi; ++c) {
    for (int64_t b = a_lo; b <= a_hi; ++b) {
      for (int64_t a = a_lo; a <= a_hi; ++a) {
        int32_t& at = cell_at[size_t(((c - a_lo) * na + (b - a_lo)) * na + (a - a_lo))];
        if (at < 0) continue;
        at = int32_t(cells.size());
        cells.push_back({int32_t(half + a * s0), int32_t(half + b * s0), int32_t(half + c * s0), s0});
      }
    }
  }

  int levels = 1;
  for (int s = s0; s > 1; s /= 2) ++levels;
  LevelProgress progress(levels, options.progress);
  int level = 0;
  // Points computed at a stride (0: the finest level point by point), one entry per stride.
  const auto add_level = [&](int stride, int64_t points) {
    for (auto& [s, count] : report.levels) {
      if (s == stride) {
        count += points;
        return;
      }
    }
    report.levels.emplace_back(stride, points);
  };
  // Kept from level to level (their capacity: fresh pages cost the kernel's clearing).
  std::vector<GridPoint> queue;
  std::vector<float> values;
  RequestLists lists;
  std::vector<uint8_t> refine, children, left_children;
  std::vector<int64_t> next_at, finest_at;
  std::vector<Cell> next, finest;
  // A level's uniform cells left to fill beside the next level's evaluation (overlap_host_steps).
  std::vector<Cell> filling;
  std::vector<uint8_t> filling_refine;
  int filling_size = 0;
  // The cells of the fills (FilledCells): fill_uniform's, fill_finest_beside's, and those of the
  // children left to the combination.
  FilledCells uniform_cells, finest_cells, left_cells;
  // Fills the cells of edge `size` not marked in `refined` by trilinear interpolation, in
  // parallel, each voxel by the one cell that owns it (fill_owned; size 1: every voxel is a
  // corner, evaluated). Returns the voxels filled.
  const auto fill_uniform = [&](const std::vector<Cell>& level, const std::vector<uint8_t>& refined,
                                int size) {
    int64_t interpolated = 0;
    if (size <= 1) return interpolated;
    uniform_cells.reset(n, half, size);
#pragma omp parallel for schedule(static)
    for (int64_t c = 0; c < int64_t(level.size()); ++c) {
      if (!refined[size_t(c)]) uniform_cells.mark(level[size_t(c)]);
    }
#pragma omp parallel for schedule(dynamic, 64) reduction(+ : interpolated)
    for (int64_t c = 0; c < int64_t(level.size()); ++c) {
      if (refined[size_t(c)]) continue;
      interpolated += fill_owned(level[size_t(c)], uniform_cells, grid, slots, store);
    }
    return interpolated;
  };
  bool classes_known = false;
  // The phases before, combined (AdaptiveOptions::combination), asked for after the coarsest
  // level.
  Combination combination;
  // What the combination must cover for a cell (Combination::covers): its corners' most
  // dangerous class for every value whose class changes at them or lies near a threshold; for a
  // cell refined only as a dilated neighbour (`dilated_only`), dangerous for every value.
  const auto cell_most = [&](const Cell& cell, bool dilated_only) {
    static constexpr int kAllCorners[8] = {0, 1, 2, 3, 4, 5, 6, 7};
    std::array<int, kSlots> most;
    if (dilated_only) {
      most.fill(-1);
      for (const int s : slots) most[size_t(s)] = int(SafetyClass::kDangerous);
      return most;
    }
    float corner[8][kSlots] = {};
    for (int q = 0; q < 8; ++q) {
      for (const int s : slots) corner[q][s] = store.value(cell.ci(q), cell.cj(q), cell.ck(q), s);
    }
    return most_dangerous_of(rank_corners(corner, slots, report.classes, options, 1.0),
                             kAllCorners, 8, slots);
  };
  // Whether this phase cannot change the combination's class anywhere in `box` (a cell or a
  // child of one): every voxel of it in the region and the scan covers `most`.
  const auto combination_covers = [&](const Cell& box, const std::array<int, kSlots>& most) {
    return combination_covers_box(combination, store, grid, box, most, report.classes, options,
                                  1.0);
  };
  clock.add(StepClock::kCells, t);
  while (!cells.empty()) {
    const int size = cells.front().size;
    // Evaluate every corner not known yet.
    t = std::chrono::steady_clock::now();
    gather_requests(
        int64_t(cells.size()),
        [&](int64_t c, const auto& offer) {
          const Cell& cell = cells[size_t(c)];
          for (int corner = 0; corner < 8; ++corner) {
            offer(cell.ci(corner), cell.cj(corner), cell.ck(corner));
          }
        },
        store, lists, queue, /*supports=*/size > 1);
    clock.add(StepClock::kRequests, t);
    int64_t filled = 0;
    std::function<void()> fill_beside;
    if (!filling.empty()) {
      fill_beside = [&] { filled = fill_uniform(filling, filling_refine, filling_size); };
    }
    evaluate_queue(queue, evaluate, store, values, clock, fill_beside);
    report.interpolated += filled;
    filling.clear();
    t = std::chrono::steady_clock::now();
    report.evaluated += int64_t(queue.size());
    add_level(size, int64_t(queue.size()));
    progress.at(level, 1.0);

    // Thresholds from the coarsest lattice's samples inside the region (a uniform sample of it),
    // combined with the phases before where there are any: the combination's classes.
    if (!classes_known) {
      if (options.combination.so_far) {
        const auto tw = std::chrono::steady_clock::now();
        combination = options.combination.so_far();
        clock.add(StepClock::kCombinationWait, tw);
        t += std::chrono::steady_clock::now() - tw;  // the refinement's own time excludes it
      }
      for (const int s : slots) {
        std::vector<float> sample;
        const bool combined = combination.worst[size_t(s)] != nullptr;
        const bool svv = (1u << s) == kernels::kSvv;
        for (size_t p = 0; p < queue.size(); ++p) {
          const GridPoint& g = queue[p];
          const double di = g.i - half, dj = g.j - half, dk = g.k - half;
          if (di * di + dj * dj + dk * dk <= radius_sq && store.known(g.i, g.j, g.k)) {
            float v = values[p * kSlots + s];
            if (combined) {
              const float w = combination.at(s, store.offset(g.i, g.j, g.k));
              if (std::isnan(w)) continue;  // unknown in the combination
              v = svv ? std::min(v, w) : std::max(v, w);
            }
            sample.push_back(v);
          }
        }
        report.classes[size_t(s)] = default_classes_of(1u << s, std::move(sample));
      }
      classes_known = true;
    }

    // A later combination for this level's decisions and the finer ones'.
    if (options.combination.newer && combination.any() &&
        level == options.combination.newer_from_level &&
        level > 0) {
      const auto tw = std::chrono::steady_clock::now();
      combination = options.combination.newer();
      clock.add(StepClock::kCombinationWait, tw);
      t += std::chrono::steady_clock::now() - tw;
    }

    // One class at all corners, none near a threshold: uniform. refine: 1 where the classes
    // disagree or lie near a threshold, 2 where only a corner without a value (NaN) keeps the cell
    // from being filled (its voxels are reached by splitting; no class boundary was seen there).
    // Corners outside the scan have values (supports), so this is a safeguard.
    refine.assign(cells.size(), 0);
#pragma omp parallel for schedule(dynamic, 256) if (size > 1)
    for (int64_t c = 0; c < int64_t(cells.size()); ++c) {
      const Cell& cell = cells[size_t(c)];
      if (size == 1) continue;
      bool split = false, unknown = false;
      for (const int s : slots) {
        const SafetyClasses& classes = report.classes[size_t(s)];
        bool seen = false;
        SafetyClass first = SafetyClass::kUnknown;
        for (int corner = 0; corner < 8 && !split; ++corner) {
          const double v = store.value(cell.ci(corner), cell.cj(corner), cell.ck(corner), s);
          const SafetyClass k = classes.classify(v);
          if (k == SafetyClass::kUnknown) {
            unknown = true;
            continue;
          }
          if (!seen) first = k;
          seen = true;
          split = k != first || near_threshold(classes, v, options);
        }
        if (split) break;
      }
      refine[size_t(c)] = split ? 1 : unknown ? 2 : 0;
    }
    std::vector<uint8_t> own;  // the cells' own decisions, where dilation adds to them
    if (level == 0 && size > 1) {
      std::vector<uint8_t> grown = refine;
      for (size_t c = 0; c < cells.size(); ++c) {
        if (refine[c] != 1) continue;
        const int64_t a = (cells[c].i - half) / s0 - a_lo, b = (cells[c].j - half) / s0 - a_lo,
                      cc = (cells[c].k - half) / s0 - a_lo;
        for (int64_t dc = -1; dc <= 1; ++dc)
          for (int64_t db = -1; db <= 1; ++db)
            for (int64_t da = -1; da <= 1; ++da) {
              const int64_t x = a + da, y = b + db, z = cc + dc;
              if (x < 0 || y < 0 || z < 0 || x >= na || y >= na || z >= na) continue;
              const int32_t other = cell_at[size_t((z * na + y) * na + x)];
              if (other >= 0) grown[size_t(other)] = std::max<uint8_t>(grown[size_t(other)], 1);
            }
      }
      refine.swap(grown);
      own.swap(grown);
    }
    // Cells left to the phases before (AdaptiveOptions::combination): filled from their
    // corners. A cell refined only for its neighbour's sake (dilation: a shadow thinner than a
    // cell may cross it unseen by its corners) is left only where the combination is dangerous
    // throughout it.
    const auto dilated_only = [&](int64_t c) { return !own.empty() && own[size_t(c)] != 1; };
    if (combination.any() && size > 1) {
      int64_t left = 0;
#pragma omp parallel for schedule(dynamic, 64) reduction(+ : left)
      for (int64_t c = 0; c < int64_t(cells.size()); ++c) {
        if (refine[size_t(c)] != 1) continue;
        const Cell& cell = cells[size_t(c)];
        if (combination_covers(cell, cell_most(cell, dilated_only(c)))) {
          refine[size_t(c)] = 0;
          ++left;
        }
      }
      report.cells_left_to_combination += left;
    }

    // Split the cells to refine (cells of edge 2 that only agree, refined for a corner without a
    // value, are split too: their known voxels are all computed), in parallel: each cell's
    // children counted, then written at their offsets, in the order of a split cell by cell.
    const int64_t count = int64_t(cells.size());
    children.assign(cells.size(), 0);  // bit `child`: that child meets the region
    const auto to_finest = [&](int64_t c) {
      return size == 2 && refine[size_t(c)] == 1;
    };
    // Cells of edge 4 sampled point by point (the level above the finest point by point); a cell
    // refined only as a dilated neighbour is split whole, so that a shadow its corners miss is
    // seen.
    const auto to_halves = [&](int64_t c) {
      return size == 4 && refine[size_t(c)] == 1 && !dilated_only(c);
    };
    const int h = size / 2;
    // Children left to the phases before (AdaptiveOptions::combination): a split cell's
    // children in which the combination covers the cell's corners are not split but filled from
    // the cell's corners, as a cell left whole is (children of edge 2 and more: the finest level
    // decides point by point).
    const bool children_left = combination.any() && h >= 2;
    left_children.assign(children_left ? cells.size() : 0, 0);
    int64_t children_left_count = 0;
#pragma omp parallel for schedule(static) reduction(+ : children_left_count)
    for (int64_t c = 0; c < count; ++c) {
      if (!refine[size_t(c)] || to_finest(c) || to_halves(c)) continue;
      const Cell& cell = cells[size_t(c)];
      uint8_t bits = 0, left_bits = 0;
      std::optional<std::array<int, kSlots>> most;  // the cell's, once a child asks for it
      for (int child = 0; child < 8; ++child) {
        const int64_t i = cell.i + (child & 1) * h, j = cell.j + ((child >> 1) & 1) * h,
                      k = cell.k + ((child >> 2) & 1) * h;
        if (!meets_roi(i, j, k, h) || !reaches_scan(i, j, k, h)) continue;
        if (children_left && refine[size_t(c)] == 1) {
          if (!most) most = cell_most(cell, dilated_only(c));
        }
        if (most && combination_covers(Cell{int32_t(i), int32_t(j), int32_t(k), h}, *most)) {
          left_bits = uint8_t(left_bits | 1u << child);
          ++children_left_count;
        } else {
          bits = uint8_t(bits | 1u << child);
        }
      }
      children[size_t(c)] = bits;
      if (children_left) left_children[size_t(c)] = left_bits;
    }
    report.cells_left_to_combination += children_left_count;
    next_at.assign(cells.size() + 1, 0);
    finest_at.assign(cells.size() + 1, 0);
    for (int64_t c = 0; c < count; ++c) {
      next_at[size_t(c) + 1] = next_at[size_t(c)] + __builtin_popcount(children[size_t(c)]);
      finest_at[size_t(c) + 1] =
          finest_at[size_t(c)] + (to_finest(c) || to_halves(c) ? 1 : 0);
    }
    next.resize(size_t(next_at.back()));
    finest.resize(size_t(finest_at.back()));
#pragma omp parallel for schedule(static)
    for (int64_t c = 0; c < count; ++c) {
      const Cell& cell = cells[size_t(c)];
      if (to_finest(c) || to_halves(c)) finest[size_t(finest_at[size_t(c)])] = cell;
      int64_t at = next_at[size_t(c)];
      for (int child = 0; child < 8; ++child) {
        if (!(children[size_t(c)] & (1u << child))) continue;
        next[size_t(at++)] = {cell.i + (child & 1) * h, cell.j + ((child >> 1) & 1) * h,
                              cell.k + ((child >> 2) & 1) * h, h};
      }
    }
    clock.add(StepClock::kRefine, t);
    if (children_left_count > 0) {
      // The children left to the combination, filled now (before the next level's requests
      // claim the corners they share with the children that are split), each voxel by the one
      // child that owns it (fill_owned), from its parent's corners.
      t = std::chrono::steady_clock::now();
      report.interpolated += fill_children(cells, left_children, h, /*from_parent=*/true,
                                           left_cells, grid, slots, store);
      clock.add(StepClock::kFill, t);
    }
    // Fill the uniform cells: now, or (overlap_host_steps) while the next level is computed,
    // whose requests have claimed their voxels by then (the fill passes over claimed voxels,
    // which get their computed values either way). The level of edge 2 is filled now: the
    // finest level reads its voxels' states.
    if (options.overlap_host_steps && size > 2) {
      filling.swap(cells);
      filling_refine.swap(refine);
      filling_size = size;
    } else {
      t = std::chrono::steady_clock::now();
      report.interpolated += fill_uniform(cells, refine, size);
      clock.add(StepClock::kFill, t);
    }
    int finest_level = level + 1;
    std::function<void()> fill_finest_beside;
    if (!finest.empty() && size == 4) {
      // The lattice of stride 2 point by point inside the cells of edge 4,
      // the uniform cells of edge 4 filled beside its computation.
      int64_t filled = 0;
      std::function<void()> fill_beside;
      if (!filling.empty()) {
        fill_beside = [&] { filled = fill_uniform(filling, filling_refine, filling_size); };
      }
      // A point is left to the combination only where it covers every voxel of the children
      // of edge 2 the point is a corner of: within 2 of it.
      const int64_t computed =
          sample_between(finest, 1.0, grid, options, slots, evaluate, report, store, lists, queue,
                         values, clock, combination, 2, fill_beside,
                         [&](double f) { progress.at(level + 1, f); });
      filling.clear();
      report.interpolated += filled;
      report.evaluated += computed;
      add_level(2, computed);
      // Their children of edge 2: to the finest level where their corners (computed or
      // interpolated) differ in a class or lie near a threshold with the finest level's margins
      // (elsewhere it would compute none of their points), filled from them where they agree, as
      // a uniform cell of edge 2 is, or where this phase cannot change the combination's class
      // anywhere in the child (as a cell of edge 2 is left).
      t = std::chrono::steady_clock::now();
      children.assign(finest.size(), 0);
      left_children.assign(finest.size(), 0);
      int64_t left = 0;
#pragma omp parallel for schedule(dynamic, 256) reduction(+ : left)
      for (int64_t c = 0; c < int64_t(finest.size()); ++c) {
        static constexpr int kAllCorners[8] = {0, 1, 2, 3, 4, 5, 6, 7};
        const Cell& cell = finest[size_t(c)];
        float v[27][kSlots] = {};  // the 3 x 3 x 3 points of the cell, i fastest
        uint16_t key[27];
        for (int m = 0; m < 27; ++m) {
          for (const int s : slots) {
            v[m][s] = store.value_if_any(cell.i + (m % 3) * 2, cell.j + (m / 3 % 3) * 2,
                                         cell.k + (m / 9) * 2, s);
          }
          key[m] = class_key(v[m], slots, report, options, kFinestMargin);
        }
        uint8_t split = 0, filled_bits = 0;
        for (int child = 0; child < 8; ++child) {
          const int a = child & 1, b = (child >> 1) & 1, d = (child >> 2) & 1;
          const Cell part{cell.i + 2 * a, cell.j + 2 * b, cell.k + 2 * d, 2};
          if (!meets_roi(part.i, part.j, part.k, 2) || !reaches_scan(part.i, part.j, part.k, 2)) {
            continue;
          }
          int at[8];
          for (int q = 0; q < 8; ++q) {
            at[q] = (a + (q & 1)) + 3 * (b + ((q >> 1) & 1)) + 9 * (d + (q >> 2));
          }
          bool uniform = key[at[0]] != kMixedKey;
          for (int q = 1; q < 8 && uniform; ++q) uniform = key[at[q]] == key[at[0]];
          if (!uniform && combination.any()) {
            float corner[8][kSlots] = {};
            for (int q = 0; q < 8; ++q) std::copy(v[at[q]], v[at[q]] + kSlots, corner[q]);
            if (combination_covers(
                    part, most_dangerous_of(rank_corners(corner, slots, report.classes, options, 1.0),
                                            kAllCorners, 8, slots))) {
              uniform = true;
              ++left;
            }
          }
          (uniform ? filled_bits : split) |= uint8_t(1u << child);
        }
        children[size_t(c)] = split;
        left_children[size_t(c)] = filled_bits;
      }
      report.cells_left_to_combination += left;
      std::vector<Cell> halves;
      halves.swap(finest);
      for (size_t c = 0; c < halves.size(); ++c) {
        for (int child = 0; child < 8; ++child) {
          if (!(children[c] & (1u << child))) continue;
          const Cell& cell = halves[c];
          finest.push_back({cell.i + (child & 1) * 2, cell.j + ((child >> 1) & 1) * 2,
                            cell.k + ((child >> 2) & 1) * 2, 2});
        }
      }
      clock.add(StepClock::kRefine, t);
      // The children filled from their corners: beside the finest level's computation, once its
      // points are claimed (a point it interpolates on a face they share gets the same value).
      fill_finest_beside = [&, halves = std::move(halves)] {
        report.interpolated += fill_children(halves, left_children, 2, /*from_parent=*/false,
                                             finest_cells, grid, slots, store);
      };
      finest_level = level + 2;
    }
    if (!finest.empty()) {
      const int64_t computed =
          sample_between(finest, kFinestMargin, grid, options, slots, evaluate, report,
                         store, lists, queue, values, clock, combination, 0, fill_finest_beside,
                         [&](double f) { progress.at(finest_level, f); });
      report.evaluated += computed;
      add_level(0, computed);
    } else if (fill_finest_beside) {
      t = std::chrono::steady_clock::now();
      fill_finest_beside();
      clock.add(StepClock::kFill, t);
    }
    cells.swap(next);
    ++level;
  }
  if (!filling.empty()) {  // the last level refined nothing: no evaluation to fill beside
    t = std::chrono::steady_clock::now();
    report.interpolated += fill_uniform(filling, filling_refine, filling_size);
    clock.add(StepClock::kFill, t);
  }

  t = std::chrono::steady_clock::now();
  report.interpolated -= store.reclaimed();
  // Corners evaluated outside the region are not part of the result, nor are those outside the
  // scan.
  const float nan = std::numeric_limits<float>::quiet_NaN();
#pragma omp parallel for schedule(static)
  for (int64_t row = 0; row < n * n; ++row) {
    const int64_t j = row % n, k = row / n;
    // The row's run in the region (a ball).
    const auto [first, last] = grid.roi_run(j, k);
    for (int64_t i = 0; i < n; ++i) {
      uint8_t& st = store.state(i, j, k);
      if (i < first || i > last) {
        if (st == kEvaluated) {
          for (const int s : slots) store.set(store.offset(i, j, k), s, nan);
        }
        continue;
      }
      // Interpolation supports outside the scan, and the voxels of cells that never reached
      // into it: unknown.
      if (st == kUnknown || st == kPending || (st == kEvaluated && !store.known(i, j, k))) {
        st = kUnknown;
        for (const int s : slots) store.set(store.offset(i, j, k), s, nan);
      }
    }
  }
  clock.add(StepClock::kFinish, t);
  report.seconds = clock.named();
  progress.at(levels - 1, 1.0);
  return report;
}

}  // namespace crepuscular::planning
