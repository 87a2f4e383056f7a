// The output grid Θ of path safety (docs/ARCHITECTURE.md §4): isotropic spacing h, the axes of
// the blocking volume, the centre voxel on the tumor centroid (or a given centre), 2 ceil(R/h) + 1
// voxels per axis; the region of interest is the ball of radius R around the centre voxel.
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <utility>

#include "planning/imaging/volume.hpp"

namespace crepuscular::planning {

struct OutputGrid {
  ImageGeometry geometry;
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  double radius_mm = 0.0;
  int64_t half = 0;        // index of the centre voxel along each axis
  int64_t max_sq = 0;      // ROI: (i-half)^2 + (j-half)^2 + (k-half)^2 <= max_sq
  int64_t roi_voxels = 0;  // voxels inside the ball

  // The ROI's voxels in row (j, k) lie at |i - half| <= the returned width; -1: none.
  int64_t roi_half_width(int64_t j, int64_t k) const {
    const int64_t rest = max_sq - (j - half) * (j - half) - (k - half) * (k - half);
    if (rest < 0) return -1;
    int64_t w = int64_t(std::sqrt(double(rest)));
    while (w * w > rest) --w;
    while ((w + 1) * (w + 1) <= rest) ++w;
    return w;
  }
  // The ROI's voxels of row (j, k) within the grid: i from first to last; none: first > last.
  std::pair<int64_t, int64_t> roi_run(int64_t j, int64_t k) const {
    const int64_t w = roi_half_width(j, k);
    if (w < 0) return {geometry.dims[0], -1};
    return {std::max<int64_t>(0, half - w), std::min<int64_t>(geometry.dims[0] - 1, half + w)};
  }
  bool in_roi(int64_t i, int64_t j, int64_t k) const {
    const int64_t di = i - half, dj = j - half, dk = k - half;
    return di * di + dj * dj + dk * dk <= max_sq;
  }
};

}  // namespace crepuscular::planning
