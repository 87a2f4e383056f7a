// The scanned volume: the intersection of the anatomy inputs' grid extents.
#include "planning/imaging/scan_coverage.hpp"
#include "foundation/error.hpp"

#include <fmt/format.h>

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

template <typename F>
void for_each_voxel_coverage(const std::vector<ScanCoverage::Grid>& grids,
                             const ImageGeometry& grid, F&& f) {
  const std::vector<IndexMap> maps = index_maps(grids, grid);
  const Index3& d = grid.dims;
#pragma omp parallel for schedule(dynamic, 1)
  for (int64_t k = 0; k < d[2]; ++k) {
    for (int64_t j = 0; j < d[1]; ++j) {
      for (int64_t i = 0; i < d[0]; ++i) {
        const Eigen::Vector3d ijk(static_cast<double>(i), static_cast<double>(j),
                                  static_cast<double>(k));
        bool covered = true;
        for (const IndexMap& m : maps) {
          if (!within_extent(*m.geometry, m.a * ijk + m.b)) {
            covered = false;
            break;
          }
        }
        f(grid.offset(i, j, k), covered);
      }
    }
  }
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
  for_each_voxel_coverage(grids_, grid, [&](int64_t v, bool covered) { m[v] = covered ? 1 : 0; });
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
