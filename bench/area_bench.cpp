// Area safety (§3.3) at the headline's size, timed alone: a 513^3 path safety volume at 0.7 mm
// (SVV 100 with shadows of lower visibility, a third of the region beyond the scan), the 2 cm
// tumor's ellipsoid, extruded up to R = 179.2 mm as `plan` does. `bench_area [--half 256]`.
#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include <chrono>
#include <cmath>
#include <iostream>
#include <random>

#include "planning/safety/area_safety.hpp"
#include "planning/safety/unknown.hpp"

using namespace crepuscular::planning;

int main(int argc, char** argv) {
  CLI::App app{"area safety at the headline's size, timed"};
  int half = 256, shadows = 60;
  app.add_option("--half", half, "grid half width in voxels (the grid is 2 half + 1 a side)");
  app.add_option("--shadows", shadows, "shadow cones of low SVV");
  CLI11_PARSE(app, argc, argv);
  const int n = 2 * half + 1;
  const double h = 0.7;
  ImageGeometry g;
  g.dims = {n, n, n};
  g.spacing = Eigen::Vector3d::Constant(h);
  g.origin = Eigen::Vector3d::Constant(-half * h);
  Volume<float> svv(g, NAN);
  Volume<uint8_t> states(g, kRegionNotComputed);
  std::mt19937 rng(3);
  std::normal_distribution<double> u(0.0, 1.0);
  std::vector<Eigen::Vector3d> cones;
  for (int s = 0; s < shadows; ++s) cones.push_back(Eigen::Vector3d(u(rng), u(rng), u(rng)).normalized());
  const double r2 = double(half) * half;
#pragma omp parallel for schedule(dynamic, 1)
  for (int64_t k = 0; k < n; ++k)
    for (int64_t j = 0; j < n; ++j)
      for (int64_t i = 0; i < n; ++i) {
        const Eigen::Vector3d d(double(i - half), double(j - half), double(k - half));
        if (d.squaredNorm() > r2) continue;
        if (i > half + half / 3) {  // beyond the scan
          states(i, j, k) = kRegionUnknown;
          continue;
        }
        states(i, j, k) = kRegionComputed;
        float v = 100.0f;
        const Eigen::Vector3d dir = d.norm() > 0 ? d.normalized() : Eigen::Vector3d::UnitX();
        for (const Eigen::Vector3d& c : cones) {
          if (dir.dot(c) > 0.97 && d.norm() > 20.0) v = std::min(v, float(30.0 + 20.0 * dir.dot(c)));
        }
        svv(i, j, k) = v;
      }
  Ellipsoid e;
  e.radii = Eigen::Vector3d::Constant(10.0);
  AreaSafetyOptions o;
  o.spacing_mm = h;
  o.max_distance_mm = half * h;
  const auto t0 = std::chrono::steady_clock::now();
  const AreaSafetyGeometry geometry =
      compute_area_safety(e, path_safety_test(svv, true, 50.0, o.max_distance_mm, &states), o);
  const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  std::cout << nlohmann::json{{"vertices", geometry.base.size()},
                              {"unknown_vertices", geometry.unknown_vertex_count},
                              {"regions", geometry.regions.size()},
                              {"seconds", s}}
                   .dump()
            << "\n";
  return 0;
}
