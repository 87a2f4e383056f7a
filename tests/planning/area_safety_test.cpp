// Area safety geometry (§3.3): PCA ellipsoid against analytic ellipsoids, the tessellation's edge
// bound and topology, extrusion against analytic ray-cylinder intersections, region counts of
// scenes whose regions are known, divergence-theorem sizes against 4/3 pi r^3, the VTK file, and
// the area safety section of a small plan.
#include "planning/safety/area_safety.hpp"

#include <gtest/gtest.h>
#include <sys/wait.h>

#include <Eigen/Geometry>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <set>
#include <sstream>

#include "foundation/error.hpp"
#include "pipelines/plan.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/safety/unknown.hpp"
#include "tests/support/cli.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/grids.hpp"
#include "tests/support/plans.hpp"
#include "tests/support/temporary_folder.hpp"

namespace fs = std::filesystem;

namespace crepuscular::planning {
namespace {

using pipelines::PlanRequest;
using pipelines::run_plan;
using test::centred_cube_grid;
using test::expect_error_containing;
using test::run_cli;

double angle_deg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::acos(std::min(1.0, std::abs(a.normalized().dot(b.normalized())))) * 180.0 / M_PI;
}

Ellipsoid sphere(double r) {
  Ellipsoid e;
  e.radii = Eigen::Vector3d::Constant(r);
  return e;
}

// --- PCA ---------------------------------------------------------------------------------------

struct PcaCase {
  Eigen::Vector3d radii;
  Eigen::Vector3d spacing;
  Eigen::Matrix3d rotation;   // ellipsoid axes (columns) in LPS
  Eigen::Matrix3d direction;  // grid direction
  Eigen::Vector3d centre;
};

void check_pca(const PcaCase& c) {
  // Rasterise: voxels whose centre lies inside the ellipsoid.
  ImageGeometry g;
  const double reach = c.radii.maxCoeff() + 3.0;
  for (int a = 0; a < 3; ++a) g.dims[size_t(a)] = int64_t(std::ceil(2 * reach / c.spacing[a])) + 1;
  g.spacing = c.spacing;
  g.direction = c.direction;
  // Put the grid centre near c.centre, off by a fraction of a voxel.
  const Eigen::Vector3d half(double(g.dims[0] - 1) / 2, double(g.dims[1] - 1) / 2,
                             double(g.dims[2] - 1) / 2);
  g.origin =
      c.centre - g.direction * c.spacing.asDiagonal() * half + Eigen::Vector3d(0.31, -0.17, 0.23);
  Volume<uint8_t> mask(g, 0);
  int64_t n = 0;
  for (int64_t k = 0; k < g.dims[2]; ++k)
    for (int64_t j = 0; j < g.dims[1]; ++j)
      for (int64_t i = 0; i < g.dims[0]; ++i) {
        const Eigen::Vector3d local =
            c.rotation.transpose() * (g.index_to_physical(i, j, k) - c.centre);
        if (local.cwiseQuotient(c.radii).squaredNorm() <= 1.0) {
          mask(i, j, k) = 1;
          ++n;
        }
      }
  ASSERT_GT(n, 100);
  const Ellipsoid e = fit_tumor_ellipsoid(mask);
  const double voxel = c.spacing.maxCoeff();
  EXPECT_LT((e.centre - c.centre).norm(), 0.5 * voxel);
  for (int a = 0; a < 3; ++a) {
    EXPECT_NEAR(e.radii[a], c.radii[a], voxel) << "axis " << a;
    EXPECT_NEAR(e.radii[a], c.radii[a], 0.35 * voxel) << "axis " << a << " (tighter)";
    EXPECT_LT(angle_deg(e.axes.col(a), c.rotation.col(a)), 3.0) << "axis " << a;
    EXPECT_NEAR(e.axes.col(a).norm(), 1.0, 1e-9);
  }
  EXPECT_NEAR(e.axes.determinant(), 1.0, 1e-9);
}

TEST(AreaSafetyEllipsoid, PcaOfRotatedAnalyticEllipsoidGivesItsAxesAndRadii) {
  PcaCase c;
  c.radii = Eigen::Vector3d(14, 9, 5);
  c.spacing = Eigen::Vector3d(1, 1, 1);
  c.rotation = (Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized()) *
                Eigen::AngleAxisd(-0.4, Eigen::Vector3d::UnitX()))
                   .toRotationMatrix();
  c.direction = Eigen::Matrix3d::Identity();
  c.centre = Eigen::Vector3d(-12.0, 40.0, 7.5);
  check_pca(c);
}

TEST(AreaSafetyEllipsoid, PcaOnARotatedGridWithThickSlices) {
  PcaCase c;
  c.radii = Eigen::Vector3d(18, 11, 7);
  c.spacing = Eigen::Vector3d(1.0, 1.0, 2.0);
  c.rotation = Eigen::AngleAxisd(1.1, Eigen::Vector3d(-1, 0.5, 2).normalized()).toRotationMatrix();
  c.direction = Eigen::AngleAxisd(0.3, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  c.centre = Eigen::Vector3d(5.0, -3.0, 100.0);
  check_pca(c);
}

TEST(AreaSafetyEllipsoid, EmptyMaskIsRefusedNamingTheSource) {
  Volume<uint8_t> mask(centred_cube_grid(5, 1.0), 0);
  expect_error_containing([&] { fit_tumor_ellipsoid(mask, "tumor.nii.gz"); }, "tumor.nii.gz");
}

// --- Tessellation ------------------------------------------------------------------------------

Ellipsoid tilted_ellipsoid() {
  Ellipsoid e;
  e.centre = Eigen::Vector3d(3, -2, 1);
  e.axes = Eigen::AngleAxisd(0.5, Eigen::Vector3d(1, 1, 0).normalized()).toRotationMatrix();
  e.radii = Eigen::Vector3d(12, 9, 7);
  return e;
}

TEST(AreaSafetyTessellation, ClosedConsistentlyOutwardWithEllipsoidNormals) {
  const Ellipsoid e = tilted_ellipsoid();
  const AreaSafetyGeometry g = tessellate_ellipsoid(e, 24);
  const int64_t v = int64_t(g.base.size()), f = int64_t(g.triangles.size());
  EXPECT_EQ(v, 2 + 23 * 48);
  // Every directed edge once, and its reverse once: closed and consistently oriented.
  std::map<std::pair<int, int>, int> directed;
  for (const auto& t : g.triangles)
    for (int k = 0; k < 3; ++k) ++directed[{t[size_t(k)], t[size_t((k + 1) % 3)]}];
  for (const auto& [edge, count] : directed) {
    ASSERT_EQ(count, 1) << edge.first << "-" << edge.second;
    ASSERT_EQ(directed.count({edge.second, edge.first}), 1u) << edge.first << "-" << edge.second;
  }
  const int64_t edges = int64_t(directed.size()) / 2;
  EXPECT_EQ(v - edges + f, 2);  // Euler characteristic of a sphere
  // Outward: each triangle's normal agrees with the ellipsoid normals at its corners.
  for (const auto& t : g.triangles) {
    const Eigen::Vector3d n = (g.base[size_t(t[1])] - g.base[size_t(t[0])])
                                  .cross(g.base[size_t(t[2])] - g.base[size_t(t[0])]);
    ASSERT_GT(n.dot(g.normals[size_t(t[0])] + g.normals[size_t(t[1])] + g.normals[size_t(t[2])]),
              0.0);
  }
  // Base points on the ellipsoid; normals = normalised gradient of the implicit function.
  for (size_t i = 0; i < g.base.size(); ++i) {
    const Eigen::Vector3d local = e.axes.transpose() * (g.base[i] - e.centre);
    ASSERT_NEAR(local.cwiseQuotient(e.radii).squaredNorm(), 1.0, 1e-12);
    const Eigen::Vector3d grad = e.axes * local.cwiseQuotient(e.radii.cwiseProduct(e.radii));
    ASSERT_LT((grad.normalized() - g.normals[i]).norm(), 1e-12);
  }
  // Volume of the inscribed polyhedron: a little under the ellipsoid's.
  const double exact = 4.0 / 3.0 * M_PI * e.radii.prod();
  EXPECT_LT(enclosed_volume(g), exact);
  EXPECT_GT(enclosed_volume(g), 0.97 * exact);
}

TEST(AreaSafetyTessellation, NoEdgeLongerThanSpacingAfterExtrusion) {
  const Ellipsoid e = tilted_ellipsoid();
  for (const auto& [h, d] :
       std::vector<std::pair<double, double>>{{3.0, 120.0}, {1.0, 30.0}, {2.0, 0.0}}) {
    const int rings = rings_for_edge_bound(e, d, h, 4000000);
    const AreaSafetyGeometry g = tessellate_ellipsoid(e, rings);
    EXPECT_LE(max_edge_length(g, d), h) << "h " << h << " distance " << d;
    // Every partial extrusion as well (edges grow with the distance on a convex surface).
    for (double f : {0.0, 0.25, 0.5, 0.75}) EXPECT_LE(max_edge_length(g, f * d), h);
    // And not needlessly fine: one ring fewer breaks the bound.
    EXPECT_GT(max_edge_length(tessellate_ellipsoid(e, rings - 1), d), h) << "rings " << rings;
  }
  // The full computation with nothing unsafe: every vertex at the maximum distance.
  AreaSafetyOptions o;
  o.spacing_mm = 2.0;
  o.max_distance_mm = 40.0;
  const AreaSafetyGeometry g = compute_area_safety(
      e, [](const Eigen::Vector3d&) { return PointSafety::kSafe; }, o);
  EXPECT_LE(max_edge_length(g), 2.0);
  EXPECT_NEAR(g.step_mm, 1.0, 1e-12);
  for (float x : g.extrusion) ASSERT_FLOAT_EQ(x, 40.0f);
}

// Far from the tumor the mesh resolves directions, not voxels: with R = 179 mm at h = 0.7 mm the
// edge bound is R x 1 degree = 3.12 mm, not h (the paper's rule would need 2.9 M vertices).
TEST(AreaSafetyTessellation, FarExtrusionsAreBoundedByTheAngularStep) {
  AreaSafetyOptions o;
  o.spacing_mm = 0.7;
  o.max_distance_mm = 179.0;
  const AreaSafetyGeometry g = compute_area_safety(
      sphere(10), [](const Eigen::Vector3d&) { return PointSafety::kSafe; }, o);
  const double bound = 179.0 * M_PI / 180.0;
  EXPECT_NEAR(g.edge_bound_mm, bound, 1e-9);
  EXPECT_LE(max_edge_length(g), bound);
  // The longest edges are the diagonals of the grid's cells at the equator, 189 mm from the
  // centre: sqrt(2) pi 189 / rings <= 3.124 mm gives 269 rings, 2 x 269^2 = 144 700 vertices.
  EXPECT_GT(max_edge_length(g), 0.98 * bound);
  EXPECT_EQ(g.rings, 269);
  EXPECT_NEAR(double(g.vertices.size()), 2.0 * 269 * 269, 1000.0);
  EXPECT_EQ(area_safety_json(g)["edge_bound_mm"].get<double>(), g.edge_bound_mm);
  // Near the tumor h is the bound: 1 degree at 30 mm is 0.52 mm < h = 2 mm.
  o.spacing_mm = 2.0;
  o.max_distance_mm = 30.0;
  EXPECT_EQ(compute_area_safety(sphere(10), [](const Eigen::Vector3d&) { return PointSafety::kSafe; }, o)
                .edge_bound_mm,
            2.0);
  o.angular_step_deg = -1.0;
  EXPECT_THROW(compute_area_safety(sphere(10), [](const Eigen::Vector3d&) { return PointSafety::kSafe; }, o),
               Error);
}

TEST(AreaSafetyTessellation, MeshBeyondTheVertexLimitIsRefused) {
  EXPECT_THROW(rings_for_edge_bound(sphere(20), 200.0, 0.5, 10000), Error);
}

// --- Mass by the divergence theorem ----------------------------------------------------------

TEST(AreaSafetyMass, ClosedTessellatedSphereHasTheBallsVolume) {
  for (double r : {5.0, 20.0}) {
    AreaSafetyGeometry g =
        tessellate_ellipsoid(sphere(r), rings_for_edge_bound(sphere(r), 0.0, 1.0, 4000000));
    measure_regions(g);
    const double exact = 4.0 / 3.0 * M_PI * r * r * r;
    ASSERT_EQ(g.regions.size(), 1u);
    EXPECT_NEAR(g.regions[0].size_mm3, exact, 0.01 * exact) << "r " << r;
    EXPECT_NEAR(g.regions[0].size_mm3, enclosed_volume(g), 1e-9 * exact);
    EXPECT_DOUBLE_EQ(g.regions[0].leeway, 1.0);
    EXPECT_EQ(g.regions[0].vertex_count, int(g.vertices.size()));
  }
  // Extruded by 30 mm everywhere: the ball of radius r + 30.
  AreaSafetyOptions o;
  o.spacing_mm = 1.5;
  o.max_distance_mm = 30.0;
  const AreaSafetyGeometry g = compute_area_safety(
      sphere(10), [](const Eigen::Vector3d&) { return PointSafety::kSafe; }, o);
  const double exact = 4.0 / 3.0 * M_PI * 40 * 40 * 40;
  ASSERT_EQ(g.regions.size(), 1u);
  EXPECT_NEAR(g.regions[0].size_mm3, exact, 0.01 * exact);
}

// --- Extrusion against analytic blockers -------------------------------------------------------

// Closest approach of the segment b + t n, t in [0, d], to the axis line (p0, a) of a cylinder.
double segment_axis_distance(const Eigen::Vector3d& b, const Eigen::Vector3d& n, double d,
                             const Eigen::Vector3d& p0, const Eigen::Vector3d& a) {
  const auto perp = [&](const Eigen::Vector3d& x) { return Eigen::Vector3d(x - x.dot(a) * a); };
  const Eigen::Vector3d w0 = perp(b - p0), wn = perp(n);
  double t = wn.squaredNorm() > 0 ? -w0.dot(wn) / wn.squaredNorm() : 0.0;
  t = std::clamp(t, 0.0, d);
  return (w0 + t * wn).norm();
}

TEST(AreaSafetyExtrusion, ExactlyTheRaysMeetingACylinderAreUnsafe) {
  // 1 mm blocking grid with a solid, slanted cylinder (radius 6 mm) beside a tilted ellipsoid.
  Volume<float> blocking(centred_cube_grid(101, 1.0), 0.0f);
  const Eigen::Vector3d p0(24, 5, 0), a = Eigen::Vector3d(0.2, 0.1, 1.0).normalized();
  const double rc = 6.0;
  for (int64_t k = 0; k < 101; ++k)
    for (int64_t j = 0; j < 101; ++j)
      for (int64_t i = 0; i < 101; ++i) {
        // Partial-volume edge: 1 inside, 0 outside, a 1-voxel linear ramp across the surface,
        // so that the trilinear 0.5 level lies on the analytic surface.
        const Eigen::Vector3d x = blocking.index_to_physical(i, j, k) - p0;
        const double dist = (x - x.dot(a) * a).norm();
        blocking(i, j, k) = float(std::clamp(0.5 + (rc - dist), 0.0, 1.0));
      }
  Ellipsoid e = tilted_ellipsoid();
  e.centre = Eigen::Vector3d(-3, 2, 1);
  AreaSafetyOptions o;
  o.spacing_mm = 1.0;
  o.max_distance_mm = 30.0;
  const AreaSafetyGeometry g = compute_area_safety(e, blocking_safety_test(blocking, 0.5), o);
  const double step = g.step_mm;
  EXPECT_LE(step, 0.5);
  // Ambiguity band: one sampling step (a ray may cross the cylinder's edge between samples).
  const double band = step;
  int64_t unsafe = 0, must_unsafe = 0, must_safe = 0, grazing = 0, grazing_disagree = 0;
  for (size_t v = 0; v < g.base.size(); ++v) {
    const Eigen::Vector3d& b = g.base[v];
    const Eigen::Vector3d& n = g.normals[v];
    const bool is_unsafe = !g.safe[v];
    unsafe += is_unsafe;
    const bool hits_inner =
        segment_axis_distance(b, n, o.max_distance_mm - band, p0, a) <= rc - band;
    const bool misses_outer =
        segment_axis_distance(b, n, o.max_distance_mm + band, p0, a) > rc + band;
    if (hits_inner) {
      ++must_unsafe;
      EXPECT_TRUE(is_unsafe) << "vertex " << v << " meets the cylinder but is safe";
      // Stopped at the first sample inside the cylinder: that sample lies on or inside its
      // surface, the sample before outside (0.1 mm: the interpolated edge's curvature error).
      const double e = g.extrusion[v];
      EXPECT_LE(segment_axis_distance(b + e * n, n, 0.0, p0, a), rc + 0.1) << "vertex " << v;
      if (e > 0) {
        EXPECT_GE(segment_axis_distance(b + (e - step) * n, n, 0.0, p0, a), rc - 0.1)
            << "vertex " << v;
      }
    } else if (misses_outer) {
      ++must_safe;
      EXPECT_FALSE(is_unsafe) << "vertex " << v << " misses the cylinder but is unsafe";
      EXPECT_FLOAT_EQ(g.extrusion[v], 30.0f);
    } else {
      ++grazing;
      // Grazing rays: judged against the exact cylinder, they may go either way.
      const bool meets = segment_axis_distance(b, n, o.max_distance_mm, p0, a) <= rc;
      grazing_disagree += meets != is_unsafe;
    }
  }
  std::printf(
      "cylinder: %zu vertices, %lld unsafe; analytic: %lld must be unsafe, %lld must be "
      "safe, %lld grazing (%lld of them disagree with the exact cylinder)\n",
      g.base.size(), (long long)unsafe, (long long)must_unsafe, (long long)must_safe,
      (long long)grazing, (long long)grazing_disagree);
  EXPECT_GT(must_unsafe, 5000);
  EXPECT_GT(must_safe, 50000);
  // Grazing rays are a thin rim around the cylinder's shadow.
  EXPECT_LT(double(grazing), 0.03 * double(g.base.size()));
  EXPECT_LT(double(grazing_disagree), 0.005 * double(g.base.size()));
  // One hole in the sphere of directions: the safe vertices form one region.
  EXPECT_EQ(g.regions.size(), 1u);
}

// Blocking 1 inside rings |z - zc| <= hz, 15 mm <= hypot(x, y) <= 35 mm, around a sphere of
// radius 10 mm at the origin, extruded 30 mm.
AreaSafetyGeometry sphere_in_rings(const std::vector<std::pair<double, double>>& rings) {
  Volume<float> blocking(centred_cube_grid(91, 1.0), 0.0f);
  for (int64_t k = 0; k < 91; ++k)
    for (int64_t j = 0; j < 91; ++j)
      for (int64_t i = 0; i < 91; ++i) {
        const Eigen::Vector3d x = blocking.index_to_physical(i, j, k);
        const double rho = std::hypot(x.x(), x.y());
        for (const auto& [zc, hz] : rings) {
          if (rho >= 15.0 && rho <= 35.0 && std::abs(x.z() - zc) <= hz) blocking(i, j, k) = 1.0f;
        }
      }
  AreaSafetyOptions o;
  o.spacing_mm = 1.5;
  o.max_distance_mm = 30.0;
  return compute_area_safety(sphere(10), blocking_safety_test(blocking, 0.5), o);
}

TEST(AreaSafetyRegions, EquatorialRingLeavesTwoEqualCaps) {
  const AreaSafetyGeometry g = sphere_in_rings({{0.0, 3.0}});
  ASSERT_EQ(g.regions.size(), 2u);
  // North and south caps: mirror images, so equal sizes (leeway 1 and ~1) and opposite axes.
  EXPECT_DOUBLE_EQ(g.regions[0].leeway, 1.0);
  EXPECT_NEAR(g.regions[1].leeway, 1.0, 0.02);
  EXPECT_LT(angle_deg(g.regions[0].main_axis, Eigen::Vector3d::UnitZ()), 2.0);
  EXPECT_LT(g.regions[0].main_axis.dot(g.regions[1].main_axis), -0.999);
  EXPECT_NEAR(g.regions[0].centre.z(), -g.regions[1].centre.z(), 0.5);
  EXPECT_GT(std::abs(g.regions[0].centre.z()), 15.0);
  // Safe vertices above and below the ring, unsafe vertices on the equator.
  for (size_t v = 0; v < g.base.size(); ++v) {
    const double elevation_deg = std::asin(g.normals[v].z()) * 180 / M_PI;
    if (std::abs(elevation_deg) < 9.0) {
      ASSERT_FALSE(g.safe[v]) << elevation_deg;
    }
    if (std::abs(elevation_deg) > 13.0) {
      ASSERT_TRUE(g.safe[v]) << elevation_deg;
    }
    if (g.safe[v]) {
      ASSERT_EQ(g.region[v], g.normals[v].z() * g.regions[0].main_axis.z() > 0 ? 0 : 1);
      ASSERT_FLOAT_EQ(g.leeway[v], float(g.regions[size_t(g.region[v])].leeway));
    } else {
      ASSERT_EQ(g.region[v], -1);
      ASSERT_EQ(g.leeway[v], 0.0f);
    }
  }
  // The sizes and the unsafe share add up to the enclosed volume (the triangle-thirds rule).
  double unsafe_share = 0.0;
  const Eigen::Vector3d c = g.ellipsoid.centre;
  for (const auto& t : g.triangles) {
    const double vol =
        (g.vertices[size_t(t[0])] - c)
            .dot((g.vertices[size_t(t[1])] - c).cross(g.vertices[size_t(t[2])] - c)) /
        6.0;
    for (int v : t) unsafe_share += g.safe[size_t(v)] ? 0.0 : vol / 3.0;
  }
  EXPECT_NEAR(g.regions[0].size_mm3 + g.regions[1].size_mm3 + unsafe_share, enclosed_volume(g),
              1e-6 * enclosed_volume(g));
}

TEST(AreaSafetyRegions, TwoSeparatedRingsLeaveThreeRegions) {
  // Rings at z = +-7 mm block the elevations of about 8 to 30 degrees: north cap, equatorial
  // belt and south cap stay safe.
  const AreaSafetyGeometry g = sphere_in_rings({{7.0, 2.0}, {-7.0, 2.0}});
  ASSERT_EQ(g.regions.size(), 3u);
  // Vertex 0 is the grid's pole, on the sphere's first axis (+x): on the equator, in the belt.
  const int belt = g.region[0];
  ASSERT_GE(belt, 0);
  EXPECT_LT(std::abs(g.normals[0].z()), 1e-12);
  for (const auto& r : g.regions) {
    if (r.id != belt) {
      EXPECT_GT(std::abs(r.main_axis.z()), 0.999) << r.id;
    }
  }
  for (size_t v = 0; v < g.base.size(); ++v) {
    const double elevation_deg = std::asin(g.normals[v].z()) * 180 / M_PI;
    if (std::abs(elevation_deg) < 4.0) {
      ASSERT_EQ(g.region[v], belt) << elevation_deg;
    }
    if (std::abs(elevation_deg) > 12.0 && std::abs(elevation_deg) < 25.0) {
      ASSERT_FALSE(g.safe[v]) << elevation_deg;
    }
  }
  // Caps: mirror images of each other.
  std::vector<double> caps;
  for (const auto& r : g.regions)
    if (r.id != belt) caps.push_back(r.size_mm3);
  EXPECT_NEAR(caps[0], caps[1], 0.02 * caps[0]);
}

TEST(AreaSafetyExtrusion, PathSafetyTestSkipsUncomputedVoxels) {
  // A path safety volume computed in a ball of radius 10 mm (NaN outside), value = x (mm).
  Volume<float> ps(centred_cube_grid(31, 1.0), std::nanf(""));
  for (int64_t k = 0; k < 31; ++k)
    for (int64_t j = 0; j < 31; ++j)
      for (int64_t i = 0; i < 31; ++i) {
        const Eigen::Vector3d x = ps.index_to_physical(i, j, k);
        if (x.norm() <= 10.0) ps(i, j, k) = float(x.x());
      }
  const SafetyTest lower = path_safety_test(ps, false, 3.0, 10.0);  // unsafe where x > 3
  EXPECT_EQ(lower(Eigen::Vector3d(2.5, 0.3, 0.2)), PointSafety::kSafe);
  EXPECT_EQ(lower(Eigen::Vector3d(3.5, 0.3, 0.2)), PointSafety::kUnsafe);
  EXPECT_EQ(lower(Eigen::Vector3d(0.0, 10.1, 0.0)), PointSafety::kBeyond);
  EXPECT_EQ(lower(Eigen::Vector3d(0.0, 13.0, 0.0)), PointSafety::kBeyond);
  EXPECT_EQ(lower(Eigen::Vector3d(0.0, 40.0, 0.0)), PointSafety::kBeyond);
  // Without the region's radius a point with no value is not computed, not beyond.
  EXPECT_EQ(path_safety_test(ps, false, 3.0, 0.0)(Eigen::Vector3d(0.0, 13.0, 0.0)),
            PointSafety::kOutside);
  const SafetyTest higher = path_safety_test(ps, true, -3.0, 10.0);  // unsafe where x < -3
  EXPECT_EQ(higher(Eigen::Vector3d(-3.5, 0.3, 0.2)), PointSafety::kUnsafe);
  // Near the edge of the ball the NaN corners are left out: still the computed value.
  EXPECT_EQ(higher(Eigen::Vector3d(-9.7, 0.5, 0.5)), PointSafety::kUnsafe);
  EXPECT_EQ(lower(Eigen::Vector3d(9.7, 0.5, 0.5)), PointSafety::kUnsafe);
  // Extrusion from a sphere of radius 4: rays toward +x turn unsafe at x > 3; all other rays leave
  // the ball (10 mm) before 30 mm and stop there, safe.
  AreaSafetyOptions o;
  o.spacing_mm = 1.0;
  o.max_distance_mm = 30.0;
  const AreaSafetyGeometry g = compute_area_safety(sphere(4), lower, o);
  for (size_t v = 0; v < g.base.size(); ++v) {
    const double reach = (g.vertices[v] - g.ellipsoid.centre).norm();
    if (g.safe[v]) {
      ASSERT_LE(reach, 10.0 + std::sqrt(3.0));  // cells with any computed corner
      ASSERT_GE(reach, 9.5);
      ASSERT_LE(g.vertices[v].x(), 3.6);
    }
    // A ray from the origin-centred sphere reaches x = 10 n_x at the ball's edge: unsafe when
    // n_x > 0.3 (margins for the interpolation at the edge).
    if (g.normals[v].x() > 0.36) {
      ASSERT_FALSE(g.safe[v]) << g.normals[v].transpose();
    }
    if (g.normals[v].x() < 0.25) {
      ASSERT_TRUE(g.safe[v]) << g.normals[v].transpose();
    }
  }
}

TEST(AreaSafetyExtrusion, ExtrusionsReachingTheUnknownStopThereNotSafe) {
  // Path safety computed in a ball of radius 10 mm, safe everywhere (0, unsafe above 3); the
  // scan ends at z = 5.5 mm: voxels above are unknown (NaN, region state 2).
  const ImageGeometry grid = centred_cube_grid(31, 1.0);
  Volume<float> ps(grid, std::nanf(""));
  Volume<uint8_t> state(grid, kRegionNotComputed);
  for (int64_t k = 0; k < 31; ++k)
    for (int64_t j = 0; j < 31; ++j)
      for (int64_t i = 0; i < 31; ++i) {
        const Eigen::Vector3d x = ps.index_to_physical(i, j, k);
        if (x.norm() > 10.0) continue;
        state(i, j, k) = x.z() > 5.5 ? kRegionUnknown : kRegionComputed;
        if (state(i, j, k) == kRegionComputed) ps(i, j, k) = 0.0f;
      }
  const SafetyTest test = path_safety_test(ps, false, 3.0, 10.0, &state);
  EXPECT_EQ(test(Eigen::Vector3d(0.3, 0.2, 3.0)), PointSafety::kSafe);
  // Beside computed voxels (the interpolation alone would borrow their value): unknown.
  EXPECT_EQ(test(Eigen::Vector3d(0.3, 0.2, 6.2)), PointSafety::kUnknown);
  EXPECT_EQ(test(Eigen::Vector3d(0.0, 13.0, 0.0)), PointSafety::kBeyond);
  AreaSafetyOptions o;
  o.spacing_mm = 1.0;
  o.max_distance_mm = 30.0;
  const AreaSafetyGeometry g = compute_area_safety(sphere(4), test, o);
  // A ray from the centre meets the scan's edge (z = 5.5) inside the ball (10 mm) when
  // n_z > 0.55: those stop there, not safe (margins for the voxels at the edges).
  int64_t toward = 0;
  for (size_t v = 0; v < g.base.size(); ++v) {
    const Eigen::Vector3d& n = g.normals[v];
    if (n.z() > 0.7) {
      ++toward;
      ASSERT_FALSE(g.safe[v]) << n.transpose();
      ASSERT_EQ(g.region[v], -1);
      ASSERT_LE(g.vertices[v].z(), 6.0 + 1e-9) << "extruded past the scan's edge";
    }
    if (n.z() < 0.45) {
      ASSERT_TRUE(g.safe[v]) << n.transpose();
    }
  }
  EXPECT_GT(toward, 0);
  EXPECT_GE(g.unknown_vertex_count, toward);
  EXPECT_EQ(area_safety_json(g)["unknown_vertex_count"].get<int64_t>(), g.unknown_vertex_count);
  // Without the states the unknown voxels are voxels with no value inside the region: the
  // extrusions that meet them are not safe either, counted as not computed.
  const AreaSafetyGeometry blind =
      compute_area_safety(sphere(4), path_safety_test(ps, false, 3.0, 10.0), o);
  EXPECT_EQ(blind.unknown_vertex_count, 0);
  EXPECT_GE(blind.uncomputed_vertex_count, toward);
  for (size_t v = 0; v < blind.base.size(); ++v) {
    if (blind.normals[v].z() > 0.7) ASSERT_FALSE(blind.safe[v]) << blind.normals[v].transpose();
    if (blind.normals[v].z() < 0.45) ASSERT_TRUE(blind.safe[v]) << blind.normals[v].transpose();
  }
}

TEST(AreaSafetyExtrusion, RegionOfInterestInsideTheTumorLeavesNoVertexSafe) {
  // The region of interest (5 mm) lies inside the tumor (radius 10 mm): no extrusion starts on a
  // computed voxel, so none reached its distance through known values. Every computed voxel is
  // safe (0, unsafe above 3): only the rule, not the values, may refuse the vertices.
  const ImageGeometry grid = centred_cube_grid(11, 1.0);
  Volume<float> ps(grid, std::nanf(""));
  for (int64_t k = 0; k < 11; ++k)
    for (int64_t j = 0; j < 11; ++j)
      for (int64_t i = 0; i < 11; ++i) {
        if (ps.index_to_physical(i, j, k).norm() <= 5.0) ps(i, j, k) = 0.0f;
      }
  AreaSafetyOptions o;
  o.spacing_mm = 1.0;
  o.max_distance_mm = 5.0;
  const AreaSafetyGeometry g = compute_area_safety(sphere(10), path_safety_test(ps, false, 3.0, 5.0), o);
  ASSERT_GT(g.base.size(), 100u);
  for (size_t v = 0; v < g.base.size(); ++v) {
    ASSERT_FALSE(g.safe[v]) << v;
    ASSERT_EQ(g.extrusion[v], 0.0f) << v;
  }
  EXPECT_TRUE(g.regions.empty());
  EXPECT_EQ(g.uncomputed_vertex_count, int64_t(g.base.size()));
  EXPECT_EQ(area_safety_json(g)["uncomputed_vertex_count"].get<int64_t>(), int64_t(g.base.size()));
}

TEST(AreaSafetyExtrusion, PreviewBeyondTheScanIsUnknown) {
  // Blocking 0 everywhere on a grid reaching x, y, z in [-10.5, 10.5] mm (its extent).
  Volume<float> blocking(centred_cube_grid(21, 1.0), 0.0f);
  const SafetyTest test = blocking_safety_test(blocking, 0.5);
  EXPECT_EQ(test(Eigen::Vector3d(10.4, 0.0, 0.0)), PointSafety::kSafe);
  EXPECT_EQ(test(Eigen::Vector3d(10.6, 0.0, 0.0)), PointSafety::kUnknown);
  AreaSafetyOptions o;
  o.spacing_mm = 1.0;
  o.max_distance_mm = 20.0;
  // A tumor at the centre: every extrusion (4 + 20 mm) leaves the scan before its distance.
  const AreaSafetyGeometry inside = compute_area_safety(sphere(4), test, o);
  EXPECT_EQ(inside.unknown_vertex_count, int64_t(inside.base.size()));
  EXPECT_TRUE(inside.regions.empty());
  // A tumor 16 mm outside the scan: nothing known at all, nothing safe.
  Ellipsoid away = sphere(4);
  away.centre = Eigen::Vector3d(26.5, 0.0, 0.0);
  const AreaSafetyGeometry outside = compute_area_safety(away, test, o);
  for (size_t v = 0; v < outside.base.size(); ++v) ASSERT_FALSE(outside.safe[v]) << v;
  EXPECT_TRUE(outside.regions.empty());
  // With a distance that stays inside the scan the same tumor at the centre is safe all round.
  o.max_distance_mm = 5.0;
  const AreaSafetyGeometry short_reach = compute_area_safety(sphere(4), test, o);
  EXPECT_EQ(short_reach.unknown_vertex_count, 0);
  ASSERT_EQ(short_reach.regions.size(), 1u);
  EXPECT_EQ(short_reach.regions[0].vertex_count, int(short_reach.base.size()));
}

// --- VTK file ----------------------------------------------------------------------------------

class AreaSafetyFiles : public ::testing::Test {
 protected:
  test::TemporaryFolder dir_;
};

TEST_F(AreaSafetyFiles, VtkRoundTripAndHeader) {
  const AreaSafetyGeometry g = sphere_in_rings({{0.0, 3.0}});
  const std::string path = (dir_ / "area_safety.vtk").string();
  write_area_safety_vtk(path, g);
  std::ifstream in(path);
  std::string l1, l2, l3, l4;
  std::getline(in, l1);
  std::getline(in, l2);
  std::getline(in, l3);
  std::getline(in, l4);
  EXPECT_EQ(l1, "# vtk DataFile Version 3.0");
  EXPECT_NE(l2.find("SPACE=LPS"), std::string::npos) << l2;
  EXPECT_LT(l2.size(), 256u);
  EXPECT_EQ(l3, "BINARY");
  EXPECT_EQ(l4, "DATASET POLYDATA");
  std::stringstream all;
  all << std::ifstream(path).rdbuf();
  const std::string text = all.str();
  const std::string nv = std::to_string(g.vertices.size()), nt = std::to_string(g.triangles.size());
  for (const std::string& key :
       {"\nPOINTS " + nv + " double\n",
        "\nPOLYGONS " + nt + " " + std::to_string(4 * g.triangles.size()) + "\n",
        "\nPOINT_DATA " + nv + "\n", std::string("\nNORMALS normals double\n"),
        std::string("\nSCALARS safe unsigned_char 1\nLOOKUP_TABLE default\n"),
        std::string("\nSCALARS region int 1\nLOOKUP_TABLE default\n"),
        std::string("\nSCALARS leeway float 1\nLOOKUP_TABLE default\n"),
        std::string("\nSCALARS extrusion_mm float 1\nLOOKUP_TABLE default\n"),
        std::string("\nFIELD FieldData 7\n")}) {
    EXPECT_NE(text.find(key), std::string::npos) << key;
  }
  EXPECT_TRUE(std::none_of(fs::directory_iterator(dir_), fs::directory_iterator(),
                           [](const fs::directory_entry& e) {
                             return e.path().filename().string().rfind(".tmp", 0) == 0;
                           }));

  // VTK's own legacy reader (where python3-vtk9 is installed): same counts, the point arrays,
  // a closed surface, and vtkMassProperties' volume equal to our divergence-theorem sum.
  const std::string script = dir_.string() + "/check.py";
  std::ofstream(script) << R"(import sys
try:
    from vtkmodules.vtkIOLegacy import vtkPolyDataReader
    from vtkmodules.vtkFiltersCore import vtkMassProperties, vtkFeatureEdges
except ImportError:
    sys.exit(1)
r = vtkPolyDataReader()
r.SetFileName(sys.argv[1])
r.ReadAllScalarsOn()
r.ReadAllNormalsOn()
r.ReadAllFieldsOn()
r.Update()
pd = r.GetOutput()
ok = "SPACE=LPS" in r.GetHeader()
ok = ok and pd.GetNumberOfPoints() == int(sys.argv[2]) and pd.GetNumberOfPolys() == int(sys.argv[3])
for name in ("safe", "region", "leeway", "extrusion_mm"):
    ok = ok and pd.GetPointData().GetArray(name) is not None
ok = ok and pd.GetPointData().GetNormals() is not None
active = vtkPolyDataReader()
active.SetFileName(sys.argv[1])
active.Update()
ok = ok and active.GetOutput().GetPointData().GetScalars().GetName() == "leeway"
ok = ok and pd.GetFieldData().GetArray("region_size_mm3").GetNumberOfTuples() == int(sys.argv[5])
m = vtkMassProperties()
m.SetInputData(pd)
m.Update()
ok = ok and abs(m.GetVolume() - float(sys.argv[4])) <= 1e-6 * float(sys.argv[4])
e = vtkFeatureEdges()
e.SetInputData(pd)
e.BoundaryEdgesOn()
e.NonManifoldEdgesOn()
e.FeatureEdgesOff()
e.ManifoldEdgesOff()
e.Update()
ok = ok and e.GetOutput().GetNumberOfLines() == 0
sys.exit(0 if ok else 3)
)";
  char volume[64];
  std::snprintf(volume, sizeof(volume), "%.12g", enclosed_volume(g));
  const int rc =
      std::system(("/usr/bin/python3 " + script + " " + path + " " + nv + " " + nt + " " + volume +
                   " " + std::to_string(g.regions.size()) + " 2>/dev/null")
                      .c_str());
  if (WEXITSTATUS(rc) == 1) {
    std::printf("VTK's python module is missing: reading through VTK not checked\n");
  } else {
    EXPECT_EQ(WEXITSTATUS(rc), 0) << "VTK's reader disagrees";
  }

  const AreaSafetyGeometry r = read_area_safety_vtk(path);
  ASSERT_EQ(r.vertices.size(), g.vertices.size());
  ASSERT_EQ(r.triangles, g.triangles);
  EXPECT_EQ(r.safe, g.safe);
  EXPECT_EQ(r.region, g.region);
  ASSERT_EQ(r.leeway.size(), g.leeway.size());
  for (size_t v = 0; v < g.vertices.size(); ++v) {
    ASSERT_LT((r.vertices[v] - g.vertices[v]).norm(), 1e-6);
    ASSERT_LT((r.normals[v] - g.normals[v]).norm(), 1e-8);
    ASSERT_LT((r.base[v] - g.base[v]).norm(), 1e-4);
    ASSERT_NEAR(r.leeway[v], g.leeway[v], 1e-6);
    ASSERT_NEAR(r.extrusion[v], g.extrusion[v], 1e-5);
  }
  ASSERT_EQ(r.regions.size(), g.regions.size());
  for (size_t k = 0; k < g.regions.size(); ++k) {
    EXPECT_NEAR(r.regions[k].size_mm3, g.regions[k].size_mm3, 1e-6 * g.regions[k].size_mm3);
    EXPECT_NEAR(r.regions[k].leeway, g.regions[k].leeway, 1e-8);
    EXPECT_EQ(r.regions[k].vertex_count, g.regions[k].vertex_count);
    EXPECT_LT((r.regions[k].centre - g.regions[k].centre).norm(), 1e-6);
    EXPECT_LT((r.regions[k].main_axis - g.regions[k].main_axis).norm(), 1e-8);
  }
  EXPECT_LT((r.ellipsoid.centre - g.ellipsoid.centre).norm(), 1e-9);
  EXPECT_LT((r.ellipsoid.axes - g.ellipsoid.axes).norm(), 1e-8);
  EXPECT_LT((r.ellipsoid.radii - g.ellipsoid.radii).norm(), 1e-8);
  EXPECT_DOUBLE_EQ(r.max_distance_mm, 30.0);
  EXPECT_EQ(r.rings, g.rings);
  // Measuring the read mesh again gives the same regions (sizes need only the file).
  AreaSafetyGeometry again = r;
  measure_regions(again);
  ASSERT_EQ(again.regions.size(), g.regions.size());
  EXPECT_NEAR(again.regions[1].size_mm3, g.regions[1].size_mm3, 1e-5 * g.regions[1].size_mm3);
}

// VTK's legacy reader makes the first SCALARS of POINT_DATA the active scalars (3D Slicer and
// ParaView colour by them): the file's point data are the normals, then the leeway. Files in the
// order written before (safe, region, leeway) read back the same.
TEST_F(AreaSafetyFiles, LeewayIsTheFirstPointScalarsAndEarlierOrderStillReads) {
  // Three regions of different sizes: leeways 1 and between 0 and 1.
  const AreaSafetyGeometry g = sphere_in_rings({{7.0, 2.0}, {-7.0, 2.0}});
  const std::string path = (dir_ / "area_safety.vtk").string();
  write_area_safety_vtk(path, g);
  std::stringstream all;
  all << std::ifstream(path, std::ios::binary).rdbuf();
  const std::string text = all.str();
  const size_t nv = g.vertices.size();
  const std::string point_data = "\nPOINT_DATA " + std::to_string(nv) + "\n";
  size_t at = text.find(point_data);
  ASSERT_NE(at, std::string::npos);
  at += point_data.size();
  const std::string normals = "NORMALS normals double\n";
  ASSERT_EQ(text.compare(at, normals.size(), normals), 0);
  at += normals.size() + 3 * nv * sizeof(double) + 1;  // big-endian doubles, then '\n'
  // The blocks of the scalars in the order written: header lines, nv values, '\n'.
  const std::string leeway_header = "SCALARS leeway float 1\nLOOKUP_TABLE default\n";
  const std::string safe_header = "SCALARS safe unsigned_char 1\nLOOKUP_TABLE default\n";
  const std::string region_header = "SCALARS region int 1\nLOOKUP_TABLE default\n";
  const size_t leeway_at = at;
  ASSERT_EQ(text.substr(leeway_at, leeway_header.size()), leeway_header);
  const size_t safe_at = leeway_at + leeway_header.size() + 4 * nv + 1;
  ASSERT_EQ(text.substr(safe_at, safe_header.size()), safe_header);
  const size_t region_at = safe_at + safe_header.size() + nv + 1;
  ASSERT_EQ(text.substr(region_at, region_header.size()), region_header);
  const size_t rest_at = region_at + region_header.size() + 4 * nv + 1;
  ASSERT_EQ(text.compare(rest_at, 16, "SCALARS extrusio"), 0);
  // The first leeway value, big-endian float: the mesh's first vertex's.
  uint32_t bits = 0;
  for (size_t b = 0; b < 4; ++b) {
    bits = bits << 8 | uint8_t(text[leeway_at + leeway_header.size() + b]);
  }
  float first = 0.0f;
  std::memcpy(&first, &bits, 4);
  EXPECT_EQ(first, g.leeway[0]);
  int64_t leeway_between = 0;  // a leeway strictly between 0 and 1 somewhere: the values matter
  for (const float x : g.leeway) leeway_between += x > 0.0f && x < 1.0f ? 1 : 0;
  EXPECT_GT(leeway_between, 0);

  const std::string earlier = text.substr(0, leeway_at) + text.substr(safe_at, rest_at - safe_at) +
                              text.substr(leeway_at, safe_at - leeway_at) + text.substr(rest_at);
  ASSERT_EQ(earlier.size(), text.size());
  const std::string earlier_path = (dir_ / "earlier.vtk").string();
  std::ofstream(earlier_path, std::ios::binary) << earlier;
  for (const std::string& p : {path, earlier_path}) {
    SCOPED_TRACE(p);
    const AreaSafetyGeometry r = read_area_safety_vtk(p);
    EXPECT_EQ(r.safe, g.safe);
    EXPECT_EQ(r.region, g.region);
    EXPECT_EQ(r.leeway, g.leeway);
    ASSERT_EQ(r.extrusion.size(), nv);
    for (size_t v = 0; v < nv; ++v) ASSERT_EQ(r.extrusion[v], g.extrusion[v]) << v;
  }
}

TEST_F(AreaSafetyFiles, ReadingSomethingElseNamesTheFile) {
  const std::string path = (dir_ / "bad.vtk").string();
  std::ofstream(path) << "# vtk DataFile Version 3.0\nx\nASCII\nDATASET POLYDATA\nPOINTS 3 "
                         "float\n0 0 0 1 0\n";
  expect_error_containing([&] { read_area_safety_vtk(path); }, "bad.vtk");
  EXPECT_THROW(read_area_safety_vtk((dir_ / "missing.vtk").string()), Error);
}

// --- Plan and command --------------------------------------------------------------------------

TEST_F(AreaSafetyFiles, PlanWhoseScanEndsOnOneSideStopsExtrusionsTowardItNotSafe) {
  // The mini plan (tumor on voxels 10..12, vessel column at i = 16) with a CT that starts at
  // i = 7: the scan ends 9 mm from the tumor's centre on the -x side, inside R = 16 mm.
  const test::MiniPlanInputs inputs = test::write_mini_plan_inputs(dir_);
  ImageGeometry ct_grid = inputs.grid;
  ct_grid.origin = inputs.grid.index_to_physical(7, 0, 0);
  ct_grid.dims[0] -= 7;
  write_volume(Volume<float>(ct_grid, 40.0f), (dir_ / "ct.nii.gz").string());
  PlanRequest req = inputs.request((dir_ / "plan").string());
  req.ct = (dir_ / "ct.nii.gz").string();
  req.path_safety.values = kernels::kSvv;
  const nlohmann::json plan = run_plan(req);
  EXPECT_GT(plan["scan_coverage"]["roi_beyond_scan_mm"]["right"].get<double>(), 0.0)
      << plan["scan_coverage"].dump();
  const nlohmann::json& a = plan["area_safety"];
  EXPECT_GT(a["unknown_vertex_count"].get<int64_t>(), 0) << a.dump();
  const AreaSafetyGeometry g = read_area_safety_vtk((dir_ / "plan" / "area_safety.vtk").string());
  const double edge_x = inputs.grid.index_to_physical(Eigen::Vector3d(6.5, 0, 0)).x();
  int toward = 0, along = 0;
  for (size_t v = 0; v < g.vertices.size(); ++v) {
    const Eigen::Vector3d& n = g.normals[v];
    if (n.x() < -0.9) {  // toward the scan's edge (-x, patient right)
      ++toward;
      EXPECT_FALSE(g.safe[v]) << n.transpose();
      EXPECT_GE(g.vertices[v].x(), edge_x - 1.0) << "extruded past the scan's edge";
    }
    if (std::abs(n.z()) > 0.9) along += g.safe[v];  // along the scan (+-z): free fat
  }
  EXPECT_GT(toward, 0);
  EXPECT_GT(along, 0);
  // The classes for 3D Slicer: the region beyond the scan is the unknown segment, never safe.
  const std::array<int64_t, 4> classes =
      test::expect_classes_segmentation_matches_plan(dir_ / "plan", "svv");
  EXPECT_EQ(classes[3], plan["scan_coverage"]["unknown_voxels"].get<int64_t>());
  EXPECT_GT(classes[3], 0);
  EXPECT_GT(classes[0], 0);
}

TEST_F(AreaSafetyFiles, PlanWritesAreaSafetyAndTheAreaCommandRuns) {
  // The mini plan with a rotated direction and an impassable "vessel" sheet at i = 16 on one side.
  test::MiniPlanOptions o;
  o.grid.direction = Eigen::AngleAxisd(0.3, Eigen::Vector3d(0, 0, 1)).toRotationMatrix();
  o.vessel_sheet = true;
  const test::MiniPlanInputs inputs = test::write_mini_plan_inputs(dir_, o);
  const ImageGeometry& grid = inputs.grid;
  const std::string& labels_path = inputs.labels;
  const std::string& tumor_path = inputs.tumor;
  const std::string& table = inputs.vulnerability;
  PlanRequest req = inputs.request((dir_ / "plan").string());
  req.margin.fwhm_mm = 2.0;
  req.path_safety.values = kernels::kSvv;
  const nlohmann::json plan = run_plan(req);
  ASSERT_TRUE(plan.contains("area_safety")) << plan.dump(2);
  const nlohmann::json& a = plan["area_safety"];
  EXPECT_EQ(a["value"], "svv");
  EXPECT_EQ(a["unsafe_class"], "dangerous");
  EXPECT_DOUBLE_EQ(a["threshold"].get<double>(), plan["classes"]["svv"]["dangerous"].get<double>());
  EXPECT_DOUBLE_EQ(a["max_distance_mm"].get<double>(), 16.0);
  EXPECT_LE(a["max_edge_full_extrusion_mm"].get<double>(), 2.0);
  EXPECT_EQ(plan["outputs"]["area_safety"], "area_safety.vtk");
  ASSERT_TRUE(fs::exists(dir_ / "plan" / "area_safety.vtk"));
  const AreaSafetyGeometry g = read_area_safety_vtk((dir_ / "plan" / "area_safety.vtk").string());
  EXPECT_EQ(a["vertex_count"].get<size_t>(), g.vertices.size());
  EXPECT_EQ(a["triangle_count"].get<size_t>(), g.triangles.size());
  ASSERT_GE(a["regions"].size(), 1u);
  EXPECT_DOUBLE_EQ(a["regions"][0]["leeway"].get<double>(), 1.0);
  EXPECT_GT(a["regions"][0]["size_mm3"].get<double>(), 0.0);
  EXPECT_EQ(a["regions"][0]["centre_lps_mm"].size(), 3u);
  // The vessel sheet lies 4 voxels (8 mm) from the tumor centre along +i: rays that way are
  // unsafe, rays the other way safe; the largest region looks away from the vessel.
  const Eigen::Vector3d toward_vessel = grid.direction.col(0);
  int64_t toward_unsafe = 0, toward = 0, away_safe = 0, away = 0;
  for (size_t v = 0; v < g.vertices.size(); ++v) {
    const double c = g.normals[v].dot(toward_vessel);
    if (c > 0.9) {
      ++toward;
      toward_unsafe += !g.safe[v];
    } else if (c < -0.5) {
      ++away;
      away_safe += g.safe[v];
    }
  }
  EXPECT_EQ(toward_unsafe, toward);
  EXPECT_EQ(away_safe, away);
  Eigen::Vector3d axis0;
  for (int c = 0; c < 3; ++c) axis0[c] = a["regions"][0]["main_axis"][size_t(c)].get<double>();
  EXPECT_LT(axis0.dot(toward_vessel), -0.5);

  // The command: preview from the labels, then path safety from the plan.
  std::string err;
  const std::string preview = (dir_ / "preview").string();
  ASSERT_EQ(run_cli("area --labels " + labels_path + " --vulnerability " + table + " --tumor " +
                        tumor_path + " --preview --margin 2 --max-distance 16 --out " + preview,
                    &err, test::Capture::kStderr),
            0)
      << err;
  std::ifstream area_json(preview + "/area.json");
  const nlohmann::json pj = nlohmann::json::parse(area_json);
  EXPECT_EQ(pj["inputs"]["mode"], "preview");
  // Default preview threshold: the second-lowest non-zero coefficient of the table (0.1).
  EXPECT_DOUBLE_EQ(pj["area_safety"]["threshold"].get<double>(), 0.1);
  const AreaSafetyGeometry p = read_area_safety_vtk(preview + "/area_safety.vtk");
  EXPECT_EQ(pj["area_safety"]["vertex_count"].get<size_t>(), p.vertices.size());
  const std::string from_plan = (dir_ / "from_plan").string();
  ASSERT_EQ(
      run_cli("area --plan " + req.out_dir + " --out " + from_plan, &err, test::Capture::kStderr),
      0)
      << err;
  const AreaSafetyGeometry q = read_area_safety_vtk(from_plan + "/area_safety.vtk");
  // The same criterion as inside the plan (the volume went through NIfTI: positions may move by
  // float rounding, so a sample on a class border may flip).
  ASSERT_EQ(q.safe.size(), g.safe.size());
  int64_t differ = 0;
  for (size_t v = 0; v < g.safe.size(); ++v) differ += q.safe[v] != g.safe[v];
  EXPECT_LE(differ, int64_t(g.safe.size() / 100));
  // Bad input: an error naming the problem, nothing written; the plan folder is never replaced.
  EXPECT_EQ(
      run_cli("area --plan " + req.out_dir + " --out " + req.out_dir, &err, test::Capture::kStderr),
      1);
  EXPECT_NE(err.find("is the input --plan"), std::string::npos) << err;
  EXPECT_TRUE(fs::exists(dir_ / "plan" / "path_safety_svv.nii.gz"));
  EXPECT_NE(
      run_cli("area --plan " + (dir_ / "nowhere").string() + " --out " + (dir_ / "x").string(),
              &err, test::Capture::kStderr),
      0);
  EXPECT_NE(err.find("nowhere"), std::string::npos) << err;
  EXPECT_FALSE(fs::exists(dir_ / "x"));
}

}  // namespace
}  // namespace crepuscular::planning
