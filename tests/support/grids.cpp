#include "tests/support/grids.hpp"

#include <Eigen/Geometry>

namespace crepuscular::test {

planning::ImageGeometry cube_grid(int n, double spacing, const Eigen::Vector3d& origin) {
  planning::ImageGeometry g;
  g.dims = {n, n, n};
  g.spacing = Eigen::Vector3d::Constant(spacing);
  g.origin = origin;
  return g;
}

planning::ImageGeometry centred_cube_grid(int n, double spacing, const Eigen::Vector3d& centre) {
  return cube_grid(n, spacing, centre - Eigen::Vector3d::Constant(0.5 * (n - 1) * spacing));
}

planning::ImageGeometry oblique_geometry() {
  constexpr double kPi = 3.14159265358979323846;
  planning::ImageGeometry g;
  g.dims = {7, 5, 4};
  g.origin = Eigen::Vector3d(-12.5, 40.25, 7.75);
  g.spacing = Eigen::Vector3d(0.8, 1.3, 2.1);
  g.direction = Eigen::AngleAxisd(30.0 * kPi / 180.0, Eigen::Vector3d(1, 2, 3).normalized())
                    .toRotationMatrix();
  return g;
}

planning::OutputGrid ball_grid(int half) {
  planning::OutputGrid g;
  const int n = 2 * half + 1;
  g.geometry.dims = {n, n, n};
  g.geometry.spacing = Eigen::Vector3d::Ones();
  g.geometry.origin = Eigen::Vector3d::Constant(-half);
  g.half = half;
  g.max_sq = int64_t(half) * half;
  for (int k = 0; k < n; ++k)
    for (int j = 0; j < n; ++j)
      for (int i = 0; i < n; ++i) g.roi_voxels += g.in_roi(i, j, k);
  g.radius_mm = half;
  return g;
}

}  // namespace crepuscular::test
