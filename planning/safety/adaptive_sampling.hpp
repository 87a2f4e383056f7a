// Fast mode of the path safety values: the output grid sampled coarse to fine. The values are
// computed exactly (every ray marched, DESIGN.md §4) on a lattice of every `stride`-th voxel;
// a cell of that lattice whose eight corners fall in the same safety class, none of them near a
// class threshold, is filled by trilinear interpolation of its corners, and every other cell is
// split in eight and sampled again at half the stride, down to single voxels. Where the classes
// change (the edges of shadows, of the region's safe bundles) every voxel is exact; inside a
// region of one class the values are interpolated. The cost follows the area of the class
// boundaries rather than the volume of the region.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "kernels/path_safety_math.hpp"
#include "planning/safety/path_safety.hpp"
#include "planning/safety/safety_classes.hpp"

namespace crepuscular::planning {

// Output grid indices of one point to evaluate; may lie outside the grid (a lattice corner
// beyond its edge), where the values are still defined.
struct GridPoint {
  int32_t i, j, k;
};

// Computes the values of `points` into values[4 * n + slot] (slot order svv, isbv, ivbv, bvv;
// only the requested slots are read back).
using PointEvaluator =
    std::function<void(const std::vector<GridPoint>& points, std::vector<float>& values)>;

struct AdaptiveOptions {
  unsigned values = kernels::kAllValues;
  int stride = 4;  // coarsest lattice, a power of two >= 2
  // A corner this close to a class threshold makes its cell refined: SVV within `svv_margin`
  // percentage points; a blocking value within a factor (1 + blocking_margin) of a threshold.
  double svv_margin = 3.0;
  double blocking_margin = 0.25;
  // Cells beside a refined cell of the coarsest lattice are refined as well, so that a shadow
  // thinner than a cell, seen by the corners of only one of the cells it crosses, is found.
  bool dilate = true;
  // The finest level point by point (sample_between): inside a refined cell of edge 2, only the
  // points whose surrounding corners differ in class (or lie near a threshold) are computed.
  bool pointwise_finest = true;
  // The level above it point by point as well: inside a refined cell of edge 4, of the points of
  // the lattice of stride 2 only those are computed whose corners around them differ in class
  // (or lie near a threshold), the others interpolated; the cell's children of edge 2 then go to
  // the finest level where their corners differ and are filled where they agree. A cell refined
  // only as a dilated neighbour is split whole. Only with pointwise_finest. (H100, 513^3 grid:
  // one phase 5.07 -> 4.65 M points, ten phases 26.9 -> 23.8 M, the classes unchanged;
  // bench/RESULTS.md, twenty-second session.) The children of edge 2 go to the finest level only
  // where their corners differ with the finest level's margins (finest_margin): elsewhere it
  // would compute none of their points and interpolate them all.
  bool pointwise_halves = true;
  // For an evaluator on another device (the GPU), whose calls leave the cores free: the host's
  // steps beside its work. The finest level is gathered in `finest_pieces` pieces, each computed
  // (and stored) while the next is gathered, from `overlap_finest_from` refined cells of edge 2
  // on; a level's uniform cells are filled while the next level is computed (not the level of
  // edge 2, whose fill the finest level reads). The points and values are the same either way
  // (H100 headline, fifteenth session: path safety 4.14-4.26 -> 3.76-3.88 s, bench/RESULTS.md).
  bool overlap_host_steps = false;
  int64_t overlap_finest_from = 4096;
  int finest_pieces = 4;
  // The finest level's margins, as a fraction of svv_margin and blocking_margin: a point between
  // two computed voxels is interpolated unless their values lie this close to a threshold.
  double finest_margin = 1.0;
  // Whether a point (output grid indices, possibly beyond the grid) lies in the scan; points
  // that do not are unknown (NaN) in the result. Cells with no voxel in the scan are never
  // sampled. The corners of a cell that reaches into the scan are computed wherever they lie
  // (the values are defined outside the scan too, rays and all): they are supports from which
  // the cell's voxels in the scan are interpolated or refined, as in any cell, and are reported
  // unknown themselves. Null: every point is known.
  std::function<bool(int64_t i, int64_t j, int64_t k)> known;
  // The same for the grid's own voxels, one byte each (x fastest, 1: in the scan), where given:
  // `known` is then asked only about lattice corners beyond the grid's edge.
  const uint8_t* known_mask = nullptr;
  // Breathing (planning/safety/breathing.hpp): the phases computed before this one, combined on
  // this grid (CombinedVolumes: per value slot SVV the minimum over them, the others the
  // maximum; NaN where one of them is unknown; null: that value is not combined yet), asked for
  // once, after the coarsest level (it may wait for the phase before to be computed). With it:
  // - the thresholds are the default classes of the coarsest samples combined with it, the
  //   classes the combination will have;
  // - refinement is left out where this phase cannot change the combination's class: a cell
  //   whose corners differ in a value's class (or lie near a threshold) is not split, but filled
  //   from its corners, when every voxel of it is at least as dangerous in the combination as
  //   the most dangerous of those corners, for each such value (both taken with the margins, each
  //   toward the other); a point of the finest level likewise, by its own voxel. Interpolation
  //   keeps the phase's values within the classes of its corners, so the combination's class is
  //   the one it had, which is what refining would have found where the phase's class inside a
  //   cell lies within the classes of its corners (fast mode's premise). This phase's own
  //   volumes are then approximate there: a plan that writes them (--per-phase) does not use it.
  std::function<CombinedVolumes()> combined_so_far;
  // The combination's side of that comparison. The phase's corners carry the whole margins: they
  // stand for the values inside the cell. The combination's values are its own, so with fixed
  // thresholds it needs none: interpolated or refined, this phase cannot make a voxel more
  // dangerous than the combination's class there. SVV's thresholds are fixed (none). The blocking
  // values' thresholds are percentiles of the final combination, which rise a little as later
  // phases are folded in after this one's thresholds were taken (breathing phantom, 2 mm: at most
  // 3 % between a later phase's thresholds and the plan's): the combination is moved toward
  // safety by this share of blocking_margin (0.25 of 25 %: about twice that drift). (1, the whole
  // margins, until the twenty-ninth session: H200, 10 phases, 6 % more points, 22.51 against
  // 21.27 M, for the same classes at 20 000 voxels; bench/RESULTS.md.)
  double combination_margin_share = 0.25;
  // With combined_so_far: a later combination (more phases folded in), asked for once before the
  // decisions of level `newer_from_level` (1: the cells of the second lattice; 0 never): those
  // and every finer level's leave to it instead. The thresholds stay those of combined_so_far.
  // A phase computed beside the phase before its newest source thus samples its coarser levels
  // while that source is still computed, and waits for it only at the finer ones.
  std::function<CombinedVolumes()> combined_newer;
  int newer_from_level = 1;
  std::function<void(double)> progress;
};

// Fast mode's sampler options from the plan's (`fast_stride` or `coarsest_stride`, the margins,
// dilation, the finest level's margin, values, progress); the scan and the overlap with a device
// are the caller's.
AdaptiveOptions adaptive_options(const PathSafetyOptions& options, const OutputGrid& grid);

struct AdaptiveReport {
  int64_t evaluated = 0;     // voxels (and lattice corners) whose values were computed
  int64_t interpolated = 0;  // ROI voxels filled by interpolation
  // Points evaluated per lattice level, coarsest first; stride 0: the finest level point by point.
  std::vector<std::pair<int, int64_t>> levels;
  std::array<SafetyClasses, kernels::kValueCount> classes{};  // the thresholds refinement used
  // AdaptiveOptions::combined_so_far: cells not split and finest points interpolated because
  // this phase could not change the combination's class there (a point shared by several cells
  // counted once: the first cell to decide it marks it decided, kDecided).
  int64_t cells_left_to_combination = 0;
  int64_t points_left_to_combination = 0;
  // Wall seconds of the sampler's own work, by step ("sampler_cells" (the coarsest lattice's
  // cells chosen), "sampler_requests", "sampler_finest_requests", "sampler_store",
  // "sampler_refine", "sampler_fill", "sampler_finish"), of the evaluator's calls
  // ("sampler_evaluate") and of the wait for the combination so far ("sampler_combination_wait").
  std::vector<std::pair<std::string, double>> seconds;
};

// Fills out[slot] (n^3 floats of the output grid; requested values only) for every voxel of the
// region of interest; voxels outside it are left as they are.
AdaptiveReport sample_adaptively(const OutputGrid& grid, const AdaptiveOptions& options,
                                 const PointEvaluator& evaluate,
                                 float* const out[kernels::kValueCount]);

}  // namespace crepuscular::planning
