// Sampling a Volume: the kernels' affine and blocking grid, NaN-skipping and clamped trilinear.
#include "planning/imaging/sampling.hpp"

#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <limits>

namespace crepuscular::planning {

kernels::Affine<double> physical_to_index_affine(const ImageGeometry& g) {
  const Eigen::Matrix3d inv = g.index_to_physical_matrix().inverse();
  const Eigen::Vector3d t = -inv * g.origin;
  kernels::Affine<double> a{};
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) a.m[r][c] = inv(r, c);
    a.m[r][3] = t[r];
  }
  return a;
}

kernels::BlockingGrid<double> blocking_grid(const Volume<float>& blocking) {
  kernels::BlockingGrid<double> grid{};
  grid.values = blocking.data();
  grid.nx = int(blocking.dims()[0]);
  grid.ny = int(blocking.dims()[1]);
  grid.nz = int(blocking.dims()[2]);
  grid.physical_to_index = physical_to_index_affine(blocking.geometry());
  grid.bricks = nullptr;
  return grid;
}

double trilinear_finite(const ImageGeometry& g, const float* values, const Eigen::Vector3d& q,
                        double min_weight) {
  double sum = 0, weight = 0;
  for_each_trilinear_corner(g, q, [&](int64_t offset, double w) {
    const float x = values[offset];
    if (std::isfinite(x) && w > 0) {
      sum += w * double(x);
      weight += w;
    }
  });
  return weight > min_weight ? sum / weight : std::numeric_limits<double>::quiet_NaN();
}

double trilinear_finite(const Volume<float>& v, const Eigen::Vector3d& q, double min_weight) {
  return trilinear_finite(v.geometry(), v.data(), q, min_weight);
}

bool within_extent(const ImageGeometry& g, const Eigen::Vector3d& q) {
  for (int a = 0; a < 3; ++a) {
    if (q[a] < -0.5 || q[a] > double(g.dims[a]) - 0.5) return false;
  }
  return true;
}

std::optional<double> trilinear_clamped(const Volume<float>& v, const Eigen::Vector3d& q) {
  const ImageGeometry& g = v.geometry();
  if (!within_extent(g, q)) return std::nullopt;
  Eigen::Vector3d c;
  for (int a = 0; a < 3; ++a) c[a] = std::clamp(q[a], 0.0, double(g.dims[a] - 1));
  // On the clamped index every corner outside the grid has weight 0.
  return trilinear(v, c);
}

}  // namespace crepuscular::planning
