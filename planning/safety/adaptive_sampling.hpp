// Fast mode of the path safety values: the output grid sampled coarse to fine. The values are
// computed exactly (every ray marched, docs/ARCHITECTURE.md §4) on a lattice of every `stride`-th
// voxel; a cell of that lattice whose eight corners fall in the same safety class, none of them
// near a class threshold, is filled by trilinear interpolation of its corners, and every other cell
// is split in eight and sampled again at half the stride, down to single voxels. Where the classes
// change (the edges of shadows, of the region's safe bundles) every voxel is exact; inside a region
// of one class the values are interpolated. The cost follows the area of the class boundaries
// rather than the volume of the region.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "kernels/value_bits.hpp"
#include "planning/safety/combination.hpp"
#include "planning/safety/fast_mode.hpp"
#include "planning/safety/output_grid.hpp"
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

// The sampler's design, fixed: cells beside a refined cell of the coarsest lattice are refined as
// well (a shadow thinner than a cell, seen by the corners of only one of the cells it crosses, is
// found); the finest level is sampled point by point: inside a refined cell of edge 2 only the
// points between computed voxels of different classes are computed (a point between two voxels of
// one class is interpolated: the finest level has no margins); the level above it point by point
// too: inside a refined cell of edge 4 only the points of the lattice of stride 2 whose corners
// around them differ in class (or lie near a threshold) are computed, and its children of edge 2
// go to the finest level where their corners differ. A cell refined only as a dilated neighbour
// is split whole.
struct AdaptiveOptions {
  unsigned values = kernels::kAllValues;
  int stride = 4;  // coarsest lattice, a power of two >= 2
  // A corner this close to a class threshold makes its cell refined: SVV within `svv_margin`
  // percentage points; a blocking value within a factor (1 + blocking_margin) of a threshold.
  double svv_margin = kSvvMargin;
  double blocking_margin = kBlockingMargin;
  // For an evaluator on another device (the GPU), whose calls leave the cores free: the host's
  // steps beside its work. The finest level is gathered in pieces, each computed (and stored)
  // while the next is gathered; a level's uniform cells are filled while the next level is
  // computed (not the level of edge 2, whose fill the finest level reads). The points and values
  // are the same either way.
  bool overlap_host_steps = false;
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
  // Breathing (combination.hpp): the phases computed before this one, combined on this grid. With
  // it:
  // - the thresholds are the default classes of the coarsest samples combined with it, the
  //   classes the combination will have;
  // - refinement is left out where this phase cannot change the combination's class: a cell
  //   whose corners differ in a value's class (or lie near a threshold) is not split, but filled
  //   from its corners, when every voxel of it is at least as dangerous in the combination as
  //   the most dangerous of those corners, for each such value; a point of the finest level
  //   likewise, by its own voxel. The phase's corners carry the whole margins (they stand for
  //   the values inside the cell); the combination's values are its own, moved toward safety by
  //   kCombinationMarginShare of blocking_margin (none for SVV, whose thresholds are fixed): the
  //   blocking thresholds are percentiles of the final combination, which rise a little as later
  //   phases fold in after this phase took its thresholds (breathing phantom, 2 mm: at most 3 %).
  //   Interpolation keeps the phase's values within the classes of its corners, so the
  //   combination's class is the one it had, which is what refining would have found where the
  //   phase's class inside a cell lies within the classes of its corners (fast mode's premise).
  CombinationSource combination;
  std::function<void(double)> progress;
};

// The combination's side of the comparison above, a share of blocking_margin: 6 % at the default
// margin, about twice the thresholds' drift over a cycle.
constexpr double kCombinationMarginShare = 0.25;

struct AdaptiveReport {
  int64_t evaluated = 0;     // voxels (and lattice corners) whose values were computed
  int64_t interpolated = 0;  // ROI voxels filled by interpolation
  // Points evaluated per lattice level, coarsest first; stride 0: the finest level point by point.
  std::vector<std::pair<int, int64_t>> levels;
  std::array<SafetyClasses, kernels::kValueCount> classes{};  // the thresholds refinement used
  // AdaptiveOptions::combination: cells not split and finest points interpolated because
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
