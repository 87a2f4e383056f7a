// ImageGeometry: validation and nearest-voxel lookup.
#include "planning/imaging/volume.hpp"

#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <cstring>
#include <sstream>

namespace crepuscular::planning {

Index3 ImageGeometry::nearest_index(const Eigen::Vector3d& p) const {
  const Eigen::Vector3d idx = physical_to_index(p);
  return {int64_t(std::llround(idx.x())), int64_t(std::llround(idx.y())),
          int64_t(std::llround(idx.z()))};
}

void ImageGeometry::validate(const std::string& what) const {
  for (int a = 0; a < 3; ++a) {
    if (dims[a] <= 0) {
      std::ostringstream m;
      m << what << ": dimension " << a << " is " << dims[a] << " (expected > 0)";
      throw Error(m.str());
    }
    if (!std::isfinite(spacing[a]) || spacing[a] <= 0.0) {
      std::ostringstream m;
      m << what << ": spacing along axis " << a << " is " << spacing[a] << " mm (expected > 0)";
      throw Error(m.str());
    }
    if (!std::isfinite(origin[a])) {
      throw Error(what + ": origin is not finite");
    }
  }
  const double det = direction.determinant();
  if (!std::isfinite(det) || std::abs(std::abs(det) - 1.0) > 1e-3) {
    std::ostringstream m;
    m << what << ": direction matrix has determinant " << det << " (expected +-1, orthonormal)";
    throw Error(m.str());
  }
}

bool ImageGeometry::same_grid(const ImageGeometry& other, double tol) const {
  return dims == other.dims && (origin - other.origin).cwiseAbs().maxCoeff() <= tol &&
         (spacing - other.spacing).cwiseAbs().maxCoeff() <= tol &&
         (direction - other.direction).cwiseAbs().maxCoeff() <= tol;
}

namespace {

// The first and last byte of a row that is not 0 (first = n: none).
void row_extent(const uint8_t* row, int64_t n, int64_t& first, int64_t& last) {
  int64_t i = 0;
  for (; i + 8 <= n; i += 8) {
    uint64_t w;
    std::memcpy(&w, row + i, 8);
    if (w) break;
  }
  while (i < n && !row[i]) ++i;
  first = i;
  if (i == n) return;
  int64_t e = n - 1;
  while (e >= 8 && e - 7 > i) {
    uint64_t w;
    std::memcpy(&w, row + e - 7, 8);
    if (w) break;
    e -= 8;
  }
  while (!row[e]) --e;
  last = e;
}

}  // namespace

VoxelBox nonzero_box(const Volume<uint8_t>& mask) {
  const Index3& d = mask.dims();
  const uint8_t* data = mask.data();
  VoxelBox box;
  box.lo = d;
#pragma omp parallel
  {
    VoxelBox mine;
    mine.lo = d;
#pragma omp for schedule(static) nowait
    for (int64_t k = 0; k < d[2]; ++k) {
      for (int64_t j = 0; j < d[1]; ++j) {
        int64_t first = 0, last = -1;
        row_extent(data + (k * d[1] + j) * d[0], d[0], first, last);
        if (first == d[0]) continue;
        mine.lo = {std::min(mine.lo[0], first), std::min(mine.lo[1], j), std::min(mine.lo[2], k)};
        mine.hi = {std::max(mine.hi[0], last), std::max(mine.hi[1], j), std::max(mine.hi[2], k)};
      }
    }
#pragma omp critical
    for (int a = 0; a < 3; ++a) {
      box.lo[size_t(a)] = std::min(box.lo[size_t(a)], mine.lo[size_t(a)]);
      box.hi[size_t(a)] = std::max(box.hi[size_t(a)], mine.hi[size_t(a)]);
    }
  }
  if (box.hi[0] < 0) return VoxelBox{};
  return box;
}

}  // namespace crepuscular::planning
