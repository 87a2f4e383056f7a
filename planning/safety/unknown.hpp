// Unknown is never safe (docs/ARCHITECTURE.md §4 "Scan coverage"): the voxels of the region of
// interest that lie outside the scanned volume get no path safety value and a state of their own,
// distinct from every safety class, in the volumes (NaN), in roi.nii.gz (kRegionUnknown) and in
// plan.json.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "planning/imaging/scan_coverage.hpp"
#include "planning/safety/path_safety.hpp"

namespace crepuscular::planning {

// The state of an output voxel, as roi.nii.gz stores it.
enum RegionState : uint8_t {
  kRegionNotComputed = 0,  // outside the region of interest (or cropped to the scan)
  kRegionComputed = 1,     // inside the region of interest and the scan: a path safety value
  kRegionUnknown = 2,      // inside the region of interest, outside the scan: unknown
};

struct CoverageOptions {
  // Voxels outside the scan leave the region of interest (not computed) instead of being unknown.
  bool crop_to_scan = false;
};

// How far the region of interest reaches beyond the scan, per patient side.
struct ScanReach {
  // mm beyond the scan's bounding box on each side: right (-L), left (+L), anterior (-P),
  // posterior (+P), inferior (-S), superior (+S); 0 where the region stays inside.
  std::array<double, 6> beyond_mm{};
  static const std::array<const char*, 6>& side_names();
  // "superior 52 mm, inferior 12 mm"; empty when the region stays inside on every side.
  std::string describe() const;
};

struct CoverageReport {
  int64_t roi_voxels = 0;      // inside the region of interest before cropping
  int64_t unknown_voxels = 0;  // inside the region of interest, outside the scan (0 when cropped)
  int64_t cropped_voxels = 0;  // removed from the region of interest by crop_to_scan
  double unknown_share = 0.0;  // unknown / roi voxels
  ScanReach reach;
  int64_t tumor_edge_voxels = 0;  // tumor voxels with a 6-neighbour outside the scan
  std::vector<std::string> grids;  // the inputs whose grids make the scan
};

// Marks the result's voxels outside `coverage` (NaN in every volume) and returns the voxel states
// (RegionState) on the result's grid with the report. `tumor` is the tumor mask (for the edge
// check). An empty coverage covers everything. `coverage` must be the one path safety was given
// (PathSafetyOptions::coverage): its mask, kept in result.scan_mask, is taken over.
Volume<uint8_t> apply_scan_coverage(PathSafetyResult& result, const ScanCoverage& coverage,
                                    const Volume<uint8_t>& tumor, const CoverageOptions& options,
                                    CoverageReport* report);

// Tumor voxels with a 6-neighbour centre outside the scan: the tumor touches the scan's edge.
int64_t tumor_voxels_at_scan_edge(const Volume<uint8_t>& tumor, const ScanCoverage& coverage);

}  // namespace crepuscular::planning
