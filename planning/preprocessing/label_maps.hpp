// Several label maps at once (TotalSegmentator tasks, layers of a 3D Slicer segmentation, ...),
// each with its vulnerability table and grid, combined into the one (label map, table) pair that
// blocking_from_labels() takes. Where maps overlap, the higher level wins.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "planning/imaging/scan_coverage.hpp"
#include "planning/imaging/volume.hpp"
#include "planning/preprocessing/vulnerability.hpp"

namespace crepuscular::planning {

// One label map and the table of its values; both must outlive the call that takes them.
struct LabelMapInput {
  const Volume<int32_t>* labels = nullptr;
  const VulnerabilityTable* table = nullptr;
  std::string source;  // names the map in messages (a file, "liver.seg.nrrd layer 1", ...)
};

// The combination on one grid:
//  - labels(x) = k + 1 where table.levels[k] is the highest level any map gives x, 0 where no map
//    labels a structure at x (background, or outside every map);
//  - table: the inputs' levels (one scale, see combine_label_maps) and one label per level,
//    value k + 1, named after the level;
//  - coverage: the scanned volume, the intersection of the input maps' grids (docs/ARCHITECTURE.md
//    §4); add the CT's grid to it where a CT is given.
// blocking_from_labels(labels, table, ...) then gives per level the union of the maps' masks of
// that level, with the margin as for one map; for a single map on its own grid it is exactly
// blocking_from_labels() of that map.
struct CombinedLabels {
  Volume<int32_t> labels;
  VulnerabilityTable table;
  ScanCoverage coverage;
  std::vector<int64_t> voxels_per_level;  // voxels of `labels` per table.levels entry
};

// Combines `inputs` (at least one) on `grid`, by default the grid of the first map. Every other
// map is sampled at the voxel centres of the grid (nearest voxel); a voxel outside a map gets
// nothing from it. Levels compare by number, so the tables must share one scale: a level number
// defined by several tables must have the same blocking_per_mm in each (the presets
// 'totalsegmentator', 'totalsegmentator_liver_vessels' and 'phantom' do). Throws Error naming the
// map for a value missing from its table (as blocking_from_labels), and naming both tables for a
// level they define differently.
CombinedLabels combine_label_maps(const std::vector<LabelMapInput>& inputs,
                                  const std::optional<ImageGeometry>& grid = std::nullopt);

}  // namespace crepuscular::planning
