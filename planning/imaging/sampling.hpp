// Sampling a Volume at physical points (LPS mm): nearest voxel, trilinear interpolation (zero
// outside, NaN-skipping, clamped to the grid), and the physical -> index affine the kernels take.
// kernels::sample_blocking stays the path-safety definition of trilinear sampling (host and
// device, docs/ARCHITECTURE.md §4); everything else on the host samples through the functions here.
#pragma once

#include <Eigen/Core>
#include <cmath>
#include <cstdint>
#include <optional>

#include "kernels/path_safety_math.hpp"
#include "planning/imaging/volume.hpp"

namespace crepuscular::planning {

// --- The kernels' plain structs, filled from a Volume --------------------------------------------

// physical (LPS mm) -> continuous index (voxel centres at integers) as kernels::Affine.
kernels::Affine<double> physical_to_index_affine(const ImageGeometry& g);

// The blocking volume as the kernels sample it (kernels::sample_blocking), without empty-space
// bricks. Points into `blocking`, which must outlive it.
kernels::BlockingGrid<double> blocking_grid(const Volume<float>& blocking);

// --- Nearest voxel -------------------------------------------------------------------------------

// The value of the voxel nearest to p (LPS mm); nullopt when that voxel is outside the grid.
template <typename T>
std::optional<T> nearest_voxel(const Volume<T>& v, const Eigen::Vector3d& p) {
  if (v.empty()) return std::nullopt;
  const Index3 n = v.geometry().nearest_index(p);
  if (!v.geometry().contains(n[0], n[1], n[2])) return std::nullopt;
  return v(n[0], n[1], n[2]);
}

// The same, `outside` when the nearest voxel is outside the grid.
template <typename T>
T nearest_voxel_or(const Volume<T>& v, const Eigen::Vector3d& p, T outside) {
  return nearest_voxel(v, p).value_or(outside);
}

// --- Trilinear interpolation (q: continuous index, voxel centres at integers) --------------------

// Calls f(offset, weight) for each of the 8 corners of q's trilinear stencil that lies in the grid,
// in the order x fastest; weights are the products of 1 - frac and frac per axis (they sum to 1
// over all 8 corners).
template <typename F>
void for_each_trilinear_corner(const ImageGeometry& g, const Eigen::Vector3d& q, F&& f) {
  const double fx = std::floor(q.x()), fy = std::floor(q.y()), fz = std::floor(q.z());
  const int64_t i = int64_t(fx), j = int64_t(fy), k = int64_t(fz);
  const double w[3] = {q.x() - fx, q.y() - fy, q.z() - fz};
  for (int c = 0; c < 8; ++c) {
    const int64_t ii = i + (c & 1), jj = j + ((c >> 1) & 1), kk = k + ((c >> 2) & 1);
    if (!g.contains(ii, jj, kk)) continue;
    const double weight = ((c & 1) ? w[0] : 1 - w[0]) * (((c >> 1) & 1) ? w[1] : 1 - w[1]) *
                          (((c >> 2) & 1) ? w[2] : 1 - w[2]);
    f(g.offset(ii, jj, kk), weight);
  }
}

// Trilinear interpolation of value(voxel) at q; voxels outside the grid count as 0.
template <typename T, typename Value>
double trilinear(const Volume<T>& v, const Eigen::Vector3d& q, Value&& value) {
  double sum = 0;
  for_each_trilinear_corner(v.geometry(), q,
                            [&](int64_t offset, double w) { sum += w * double(value(v[offset])); });
  return sum;
}

// Trilinear interpolation of the voxel values at q; voxels outside the grid count as 0.
template <typename T>
double trilinear(const Volume<T>& v, const Eigen::Vector3d& q) {
  return trilinear(v, q, [](T x) { return double(x); });
}

// Trilinear interpolation over the corners that lie in the grid and hold a finite value,
// renormalised by their total weight; NaN when that weight is <= min_weight (q outside the grid,
// or only non-finite values around it: path safety marks voxels it did not compute with NaN).
double trilinear_finite(const Volume<float>& v, const Eigen::Vector3d& q,
                        double min_weight = 1e-12);
// The same on raw values laid out on grid g (x fastest), for callers that keep only a pointer.
double trilinear_finite(const ImageGeometry& g, const float* values, const Eigen::Vector3d& q,
                        double min_weight = 1e-12);

// Whether q lies within the grid's extent: at most half a voxel beyond the outer voxel centres.
bool within_extent(const ImageGeometry& g, const Eigen::Vector3d& q);

// Trilinear interpolation at q clamped to the outer voxel centres (the edge voxels extend to the
// grid's extent); nullopt when q is not within_extent.
std::optional<double> trilinear_clamped(const Volume<float>& v, const Eigen::Vector3d& q);

}  // namespace crepuscular::planning
