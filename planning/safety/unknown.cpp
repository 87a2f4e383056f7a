// Region-of-interest voxels outside the scanned volume: unknown, never safe.
#include "planning/safety/unknown.hpp"

#include <cmath>
#include <limits>

#include <fmt/format.h>

namespace crepuscular::planning {

const std::array<const char*, 6>& ScanReach::side_names() {
  static const std::array<const char*, 6> names = {"right",    "left",     "anterior",
                                                   "posterior", "inferior", "superior"};
  return names;
}

std::string ScanReach::describe() const {
  std::string text;
  for (size_t s = 0; s < beyond_mm.size(); ++s) {
    if (beyond_mm[s] <= 0.0) continue;
    if (!text.empty()) text += ", ";
    text += fmt::format("{} {:.0f} mm", side_names()[s], beyond_mm[s]);
  }
  return text;
}

namespace {

// The region of interest's bounding box (the ball around the centre) against the scan's box.
ScanReach reach_beyond(const OutputGrid& grid, const ScanCoverage& coverage) {
  ScanReach r;
  if (coverage.empty()) return r;
  const Eigen::AlignedBox3d scan = coverage.bounding_box();
  const Eigen::Vector3d lo = grid.centre - Eigen::Vector3d::Constant(grid.radius_mm);
  const Eigen::Vector3d hi = grid.centre + Eigen::Vector3d::Constant(grid.radius_mm);
  if (scan.isEmpty()) {
    for (double& b : r.beyond_mm) b = 2.0 * grid.radius_mm;
    return r;
  }
  for (int a = 0; a < 3; ++a) {
    r.beyond_mm[size_t(2 * a)] = std::max(0.0, scan.min()[a] - lo[a]);
    r.beyond_mm[size_t(2 * a + 1)] = std::max(0.0, hi[a] - scan.max()[a]);
  }
  return r;
}

}  // namespace

int64_t tumor_voxels_at_scan_edge(const Volume<uint8_t>& tumor, const ScanCoverage& coverage) {
  if (coverage.empty()) return 0;
  const ImageGeometry& g = tumor.geometry();
  const Index3& d = g.dims;
  int64_t count = 0;
#pragma omp parallel for reduction(+ : count) schedule(dynamic, 1)
  for (int64_t k = 0; k < d[2]; ++k) {
    for (int64_t j = 0; j < d[1]; ++j) {
      for (int64_t i = 0; i < d[0]; ++i) {
        if (!tumor(i, j, k)) continue;
        const int64_t n[6][3] = {{i - 1, j, k}, {i + 1, j, k}, {i, j - 1, k},
                                 {i, j + 1, k}, {i, j, k - 1}, {i, j, k + 1}};
        for (const auto& q : n) {
          if (!coverage.contains(g.index_to_physical(q[0], q[1], q[2]))) {
            ++count;
            break;
          }
        }
      }
    }
  }
  return count;
}

Volume<uint8_t> apply_scan_coverage(PathSafetyResult& result, const ScanCoverage& coverage,
                                    const Volume<uint8_t>& tumor, const CoverageOptions& options,
                                    CoverageReport* report) {
  const OutputGrid& grid = result.grid;
  // 1 covered, 0 not: path safety's own mask where it made one for this grid. Path safety
  // computes no voxel outside it (they are NaN already): only the states are set then.
  const bool own_mask = result.scan_mask.geometry().same_grid(grid.geometry, 0.0) &&
                        result.scan_mask.voxel_count() > 0;
  Volume<uint8_t> state = own_mask ? std::move(result.scan_mask) : coverage.mask(grid.geometry);
  result.scan_mask = Volume<uint8_t>();
  const Index3& d = grid.geometry.dims;
  const uint8_t outside_scan = options.crop_to_scan ? kRegionNotComputed : kRegionUnknown;
  const float nan = std::numeric_limits<float>::quiet_NaN();
  int64_t roi = 0, uncovered = 0, changed = 0;
  // Row by row: the region's run of the row (a ball), the rest not computed.
#pragma omp parallel for reduction(+ : roi, uncovered, changed) schedule(static)
  for (int64_t row = 0; row < d[1] * d[2]; ++row) {
    uint8_t* s = state.data() + row * d[0];
    const auto [first, last] = grid.roi_run(row % d[1], row / d[1]);
    for (int64_t i = 0; i < d[0]; ++i) {
      if (i < first || i > last) {
        s[i] = kRegionNotComputed;
        continue;
      }
      ++roi;
      if (s[i]) {
        s[i] = kRegionComputed;
        continue;
      }
      ++uncovered;
      s[i] = outside_scan;
      if (own_mask) continue;
      const int64_t offset = row * d[0] + i;
      for (int v = 0; v < kernels::kValueCount; ++v) {
        if (!(result.values & (1u << v))) continue;
        float& x = result.volumes[size_t(v)].data()[offset];
        changed += std::isnan(x) ? 0 : 1;
        x = nan;
      }
    }
  }
  if (changed > 0) {  // taken before these voxels became unknown
    result.classes = {};
    result.statistics = {};
  }
  if (report) {
    report->roi_voxels = roi;
    report->unknown_voxels = options.crop_to_scan ? 0 : uncovered;
    report->cropped_voxels = options.crop_to_scan ? uncovered : 0;
    report->unknown_share = roi ? double(report->unknown_voxels) / double(roi) : 0.0;
    report->reach = reach_beyond(grid, coverage);
    report->tumor_edge_voxels = tumor_voxels_at_scan_edge(tumor, coverage);
    report->grids.clear();
    for (const auto& g : coverage.grids()) report->grids.push_back(g.source);
  }
  return state;
}

}  // namespace crepuscular::planning
