// The demo scene's meshes: the body as a height field over a table, the needle as cylinders.
#include "pipelines/scene_meshes.hpp"

#include <algorithm>
#include <cmath>
#include <optional>
#include <vector>

#include "planning/imaging/ray_march.hpp"

namespace crepuscular::pipelines {

namespace {

constexpr double kMeshPi = 3.14159265358979323846;

// A closed-sided cylinder (no caps) of radius r from z0 to z1 on the z axis, n segments.
void add_cylinder(tracking::SceneMesh& m, double r, double z0, double z1, int n,
                  const Eigen::Vector3f& colour) {
  const int base = int(m.vertices.size());
  for (int k = 0; k < n; ++k) {
    const double a = 2 * kMeshPi * k / n;
    for (double z : {z0, z1}) {
      m.vertices.emplace_back(float(r * std::cos(a)), float(r * std::sin(a)), float(z));
      m.colours.push_back(colour);
    }
  }
  for (int k = 0; k < n; ++k) {
    const int i0 = base + 2 * k, i1 = base + 2 * ((k + 1) % n);
    m.triangles.emplace_back(i0, i1, i0 + 1);
    m.triangles.emplace_back(i1, i1 + 1, i0 + 1);
  }
}

}  // namespace

tracking::SceneMesh body_mesh(const planning::Volume<int32_t>& labels,
                              const Eigen::Isometry3d& T_ct_patient, const BodyMeshOptions& o) {
  const planning::ImageGeometry& g = labels.geometry();
  // Extent of the grid and of the body in LPS.
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e300), hi = -lo;
  double body_x0 = 1e300, body_x1 = -1e300, table_y = -1e300;
  for (int c = 0; c < 8; ++c) {
    const Eigen::Vector3d idx((c & 1) ? g.dims[0] - 1 : 0, (c & 2) ? g.dims[1] - 1 : 0,
                              (c & 4) ? g.dims[2] - 1 : 0);
    const Eigen::Vector3d p = g.index_to_physical(idx);
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  for (int64_t k = 0; k < g.dims[2]; ++k) {
    for (int64_t j = 0; j < g.dims[1]; ++j) {
      for (int64_t i = 0; i < g.dims[0]; ++i) {
        if (labels(i, j, k) <= 0) continue;
        const Eigen::Vector3d p = g.index_to_physical(Eigen::Vector3d(double(i), double(j), double(k)));
        body_x0 = std::min(body_x0, p.x());
        body_x1 = std::max(body_x1, p.x());
        table_y = std::max(table_y, p.y());
      }
    }
  }
  tracking::SceneMesh m;
  m.name = "body";
  m.board = "patient";
  if (body_x0 > body_x1) return m;  // no body
  table_y += 0.5 * g.spacing.maxCoeff();
  const double step = std::max(0.5, o.step_mm);
  const double x0 = body_x0 - o.table_margin_mm, x1 = body_x1 + o.table_margin_mm;
  const double z0 = lo.z() - o.beyond_scan_mm, z1 = hi.z() + o.beyond_scan_mm;
  const int nx = int(std::ceil((x1 - x0) / step)) + 1;
  // Along the body: every step within the scan, every 4 steps beyond it (the profile is constant).
  std::vector<double> zs_list;
  for (double z = lo.z(); z > z0; z -= 4 * step) zs_list.push_back(z);
  std::reverse(zs_list.begin(), zs_list.end());
  zs_list.pop_back();
  for (double z = lo.z(); z < hi.z(); z += step) zs_list.push_back(z);
  for (double z = hi.z(); z < z1 + 4 * step; z += 4 * step) zs_list.push_back(z);
  const int nz = int(zs_list.size());
  const double march = 0.5 * g.spacing.minCoeff();
  const double inset = 0.5 * g.spacing.maxCoeff();  // stay inside the scan's end slices
  const Eigen::Isometry3d T_patient_ct = T_ct_patient.inverse();
  m.vertices.reserve(size_t(nx) * size_t(nz));
  for (int iz = 0; iz < nz; ++iz) {
    const double z = zs_list[size_t(iz)];
    const double zs = std::clamp(z, lo.z() + inset, hi.z() - inset);
    for (int ix = 0; ix < nx; ++ix) {
      const double x = x0 + ix * step;
      const Eigen::Vector3d start(x, lo.y() - 1.0, zs);
      const std::optional<planning::Crossing> c = planning::first_entry(
          start, Eigen::Vector3d::UnitY(), march, table_y - start.y(),
          [&](const Eigen::Vector3d& p) { return planning::body_fraction(labels, p) >= 0.5; }, 0.05);
      const bool body = c.has_value();
      const double y = body ? start.y() + c->inside_s : table_y;
      const Eigen::Vector3d p_ct(x, y, z);
      Eigen::Vector3f colour = kTableBgr;
      if (body) {
        const double ex = (x - o.field_centre_ct.x()) / o.field_half_x_mm;
        const double ez = (z - o.field_centre_ct.z()) / o.field_half_z_mm;
        colour = ex * ex + ez * ez <= 1.0 ? kSkinBgr : kDrapeBgr;
      }
      Eigen::Vector3d p = T_patient_ct * p_ct;
      if (std::abs(p.x()) <= o.board_half_x_mm && std::abs(p.y()) <= o.board_half_y_mm &&
          p.z() < 1.0) {
        p.z() = 1.0;
      }
      m.vertices.push_back(p.cast<float>());
      m.colours.push_back(colour);
    }
  }
  for (int iz = 0; iz + 1 < nz; ++iz) {
    for (int ix = 0; ix + 1 < nx; ++ix) {
      const int a = iz * nx + ix, b = a + 1, c = a + nx, d = c + 1;
      m.triangles.emplace_back(a, b, d);
      m.triangles.emplace_back(a, d, c);
    }
  }
  return m;
}

tracking::SceneMesh needle_mesh(double tip_z_mm, double diameter_mm) {
  tracking::SceneMesh m;
  m.name = "needle";
  m.board = "needle";
  constexpr double kHubStart = 0.5, kHubEnd = 12.0;
  add_cylinder(m, 3.5, kHubStart, kHubEnd, 16, Eigen::Vector3f(190, 150, 100));
  add_cylinder(m, 0.5 * diameter_mm, kHubEnd, tip_z_mm, 8, Eigen::Vector3f(205, 200, 195));
  return m;
}

}  // namespace crepuscular::pipelines
