// The scanned volume: the intersection of the anatomy inputs' grid extents.
#include "planning/imaging/scan_coverage.hpp"
#include "foundation/error.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>

#include <limits>
#include <string>

#include "planning/imaging/sampling.hpp"

namespace crepuscular::planning {

namespace {

// Continuous index of the voxel centres of `grid` in each covering grid, as an affine map:
// index_c = A * ijk + b.
struct IndexMap {
  Eigen::Matrix3d a;
  Eigen::Vector3d b;
  const ImageGeometry* geometry;
};

std::vector<IndexMap> index_maps(const std::vector<ScanCoverage::Grid>& grids,
                                 const ImageGeometry& grid) {
  std::vector<IndexMap> maps;
  for (const auto& c : grids) {
    const Eigen::Matrix3d to_index = c.geometry.index_to_physical_matrix().inverse();
    maps.push_back({to_index * grid.index_to_physical_matrix(),
                    to_index * (grid.origin - c.geometry.origin), &c.geometry});
  }
  return maps;
}

// Whether voxel (i, j, k) of the grid is covered: its centre within the extent of every grid.
bool covered_at(const std::vector<IndexMap>& maps, int64_t i, int64_t j, int64_t k) {
  const Eigen::Vector3d ijk(static_cast<double>(i), static_cast<double>(j), static_cast<double>(k));
  for (const IndexMap& m : maps) {
    if (!within_extent(*m.geometry, m.a * ijk + m.b)) return false;
  }
  return true;
}

// The covered voxels of row (j, k) of a grid of `n` voxels along i: the covered region is
// convex (an intersection of boxes), so a row meets it in one run [first, last] (first > last:
// none). The run's ends are found from the linear constraints and settled by covered_at itself
// within two voxels of them, so the result is the voxel-by-voxel test's; a row nearly parallel
// to a grid's face (where rounding could flicker along the whole row) is tested voxel by voxel.
void covered_run(const std::vector<IndexMap>& maps, int64_t n, int64_t j, int64_t k,
                 uint8_t* row) {
  double lo = 0.0, hi = double(n - 1);
  bool voxelwise = false;
  for (const IndexMap& m : maps) {
    const Eigen::Vector3d r0 = m.a * Eigen::Vector3d(0.0, double(j), double(k)) + m.b;
    for (int a = 0; a < 3 && !voxelwise; ++a) {
      const double c = m.a(a, 0), top = double(m.geometry->dims[a]) - 0.5;
      if (std::abs(c) < 1e-6) {
        // Constant along the row: inside or outside everywhere, unless on the face itself.
        if (std::abs(r0[a] + 0.5) < 1e-3 || std::abs(r0[a] - top) < 1e-3) {
          voxelwise = true;
        } else if (r0[a] < -0.5 || r0[a] > top) {
          hi = -1e9;  // no voxel of the row
        }
        continue;
      }
      const double t0 = (-0.5 - r0[a]) / c, t1 = (top - r0[a]) / c;
      lo = std::max(lo, std::min(t0, t1));
      hi = std::min(hi, std::max(t0, t1));
    }
  }
  if (voxelwise) {
    for (int64_t i = 0; i < n; ++i) row[i] = covered_at(maps, i, j, k) ? 1 : 0;
    return;
  }
  std::fill(row, row + n, uint8_t(0));
  if (hi < lo - 4.0) return;  // no voxel near the run
  const int64_t a = std::max<int64_t>(0, int64_t(std::floor(lo)) - 2);
  const int64_t b = std::min<int64_t>(n - 1, int64_t(std::ceil(hi)) + 2);
  if (b - a <= 8) {
    for (int64_t i = a; i <= b; ++i) row[i] = covered_at(maps, i, j, k) ? 1 : 0;
    return;
  }
  // The ends tested; voxels more than two inside both bounds are covered.
  int64_t first = a, last = b;
  while (first <= a + 4 && !covered_at(maps, first, j, k)) ++first;
  while (last >= b - 4 && !covered_at(maps, last, j, k)) --last;
  std::fill(row + first, row + last + 1, uint8_t(1));
}

}  // namespace

void ScanCoverage::add(const ImageGeometry& geometry, const std::string& source) {
  geometry.validate(source);
  // Inputs that describe the anatomy must share some space: a CT or label map elsewhere (another
  // patient, another frame) would leave the whole plan unknown, or worse, silently unrelated.
  if (!grids_.empty()) {
    const Eigen::AlignedBox3d before = bounding_box(), added = extent_box(geometry);
    if (before.isEmpty() || !before.intersects(added)) {
      const Eigen::Vector3d gap =
          ((before.center() - added.center()).cwiseAbs() - 0.5 * (before.sizes() + added.sizes()))
              .cwiseMax(0.0);
      std::string others;
      for (const Grid& g : grids_) others += (others.empty() ? "" : ", ") + g.source;
      throw Error(source + ": does not overlap " + others + " (" +
                  std::to_string(int64_t(std::llround(gap.norm()))) +
                  " mm apart in LPS): the inputs must show the same patient in the same frame");
    }
  }
  grids_.push_back({geometry, source});
}

bool ScanCoverage::contains(const Eigen::Vector3d& p) const {
  for (const Grid& g : grids_) {
    if (!within_extent(g.geometry, g.geometry.physical_to_index(p))) return false;
  }
  return true;
}

Volume<uint8_t> ScanCoverage::mask(const ImageGeometry& grid) const {
  Volume<uint8_t> out(grid, 1);
  if (grids_.empty()) return out;
  uint8_t* m = out.data();
  const std::vector<IndexMap> maps = index_maps(grids_, grid);
  const Index3& d = grid.dims;
#pragma omp parallel for collapse(2) schedule(static)
  for (int64_t k = 0; k < d[2]; ++k) {
    for (int64_t j = 0; j < d[1]; ++j) covered_run(maps, d[0], j, k, m + grid.offset(0, j, k));
  }
  return out;
}

Eigen::AlignedBox3d extent_box(const ImageGeometry& g) {
  Eigen::AlignedBox3d box;
  for (int c = 0; c < 8; ++c) {
    const Eigen::Vector3d corner((c & 1) ? double(g.dims[0]) - 0.5 : -0.5,
                                 (c & 2) ? double(g.dims[1]) - 0.5 : -0.5,
                                 (c & 4) ? double(g.dims[2]) - 0.5 : -0.5);
    box.extend(g.index_to_physical(corner));
  }
  return box;
}

void require_overlap_with_plan(const ImageGeometry& input, const ImageGeometry& plan_grid,
                               const std::string& path, const std::string& what) {
  const Eigen::AlignedBox3d a = extent_box(input), b = extent_box(plan_grid);
  if (a.intersects(b)) return;
  const Eigen::Vector3d gap = (a.center() - b.center()).cwiseAbs() - 0.5 * (a.sizes() + b.sizes());
  throw Error(fmt::format("{}: {} does not overlap the plan's region of interest (they are "
                          "{:.0f} mm apart; its centre ({:.1f}, {:.1f}, {:.1f}), the plan's "
                          "({:.1f}, {:.1f}, {:.1f}) LPS mm): is it this patient's, in the same "
                          "frame?",
                          path, what, gap.cwiseMax(0.0).norm(), a.center().x(), a.center().y(),
                          a.center().z(), b.center().x(), b.center().y(), b.center().z()));
}

Eigen::AlignedBox3d ScanCoverage::bounding_box() const {
  constexpr double kInf = std::numeric_limits<double>::infinity();
  Eigen::AlignedBox3d box(Eigen::Vector3d::Constant(-kInf), Eigen::Vector3d::Constant(kInf));
  for (const Grid& g : grids_) box = box.intersection(extent_box(g.geometry));
  return box;
}

}  // namespace crepuscular::planning
