// Area safety geometry (§3.3, docs/ARCHITECTURE.md §6): PCA ellipsoid of the tumor, spherical
// tessellation, extrusion along the normals, connected safe regions and their sizes, the VTK mesh
// file, and the plan's area safety step (the `area` job itself is pipelines/area.cpp).
#include "planning/safety/area_safety.hpp"

#include <fmt/format.h>
#include <omp.h>
#include "foundation/log.hpp"

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <algorithm>
#include <atomic>
#include <cctype>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <mutex>
#include <numeric>
#include <sstream>

#include <nlohmann/json.hpp>

#include "foundation/error.hpp"
#include "kernels/path_safety_math.hpp"
#include "planning/preprocessing/blocking.hpp"
#include "foundation/output_files.hpp"
#include "planning/safety/safety_classes.hpp"
#include "planning/safety/unknown.hpp"
#include "planning/imaging/sampling.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/preprocessing/vulnerability.hpp"

namespace fs = std::filesystem;

namespace crepuscular::planning {

namespace {

using Clock = std::chrono::steady_clock;

double seconds_since(Clock::time_point t) {
  return std::chrono::duration<double>(Clock::now() - t).count();
}

std::string number(double x) { return fmt::format("{:g}", x); }

int64_t grid_vertex_count(int64_t rings) { return 2 + (rings - 1) * 2 * rings; }

nlohmann::json vec_json(const Eigen::Vector3d& v) { return {v.x(), v.y(), v.z()}; }

}  // namespace

// ---------------------------------------------------------------------------------------------
// Ellipsoid

Ellipsoid fit_tumor_ellipsoid(const Volume<uint8_t>& tumor, const std::string& source) {
  const ImageGeometry& g = tumor.geometry();
  const auto& d = g.dims;
  // Two passes in index space (mean, then scatter) keep the sums well conditioned.
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  int64_t n = 0;
  for (int64_t k = 0; k < d[2]; ++k)
    for (int64_t j = 0; j < d[1]; ++j)
      for (int64_t i = 0; i < d[0]; ++i) {
        if (!tumor(i, j, k)) continue;
        sum += Eigen::Vector3d(double(i), double(j), double(k));
        ++n;
      }
  if (n == 0) throw Error(source + ": tumor mask is empty (0 voxels > 0)");
  const Eigen::Vector3d mean = sum / double(n);
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  for (int64_t k = 0; k < d[2]; ++k)
    for (int64_t j = 0; j < d[1]; ++j)
      for (int64_t i = 0; i < d[0]; ++i) {
        if (!tumor(i, j, k)) continue;
        const Eigen::Vector3d q = Eigen::Vector3d(double(i), double(j), double(k)) - mean;
        scatter += q * q.transpose();
      }
  const Eigen::Matrix3d m = g.index_to_physical_matrix();
  const Eigen::Matrix3d cov = m * (scatter / double(n)) * m.transpose();
  // Covariance of one voxel's cube (uniform over [-1/2, 1/2]^3 in index space): the part of the
  // solid's variance that the voxel centres do not carry.
  const Eigen::Matrix3d cube = m * m.transpose() / 12.0;

  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(cov);  // ascending eigenvalues
  Ellipsoid e;
  e.centre = g.index_to_physical(mean);
  for (int c = 0; c < 3; ++c) {
    Eigen::Vector3d u = es.eigenvectors().col(2 - c);
    // Deterministic sign: the largest component positive.
    Eigen::Index big = 0;
    u.cwiseAbs().maxCoeff(&big);
    if (u[big] < 0) u = -u;
    e.axes.col(c) = u;
    const double var = std::max(0.0, es.eigenvalues()[2 - c]) + u.dot(cube * u);
    e.radii[c] = std::sqrt(5.0 * var);
  }
  e.axes.col(2) = e.axes.col(0).cross(e.axes.col(1)).normalized();  // right-handed
  return e;
}

// ---------------------------------------------------------------------------------------------
// Tessellation

AreaSafetyGeometry tessellate_ellipsoid(const Ellipsoid& e, int rings) {
  if (rings < 2) throw Error("area safety: the spherical grid needs at least 2 rings");
  if (!(e.radii.minCoeff() > 0.0) || !e.radii.allFinite()) {
    throw Error("area safety: ellipsoid radii must be finite and > 0");
  }
  const int n = rings, m = 2 * rings;
  AreaSafetyGeometry g;
  g.ellipsoid = e;
  g.rings = n;
  g.segments = m;
  const size_t vcount = size_t(grid_vertex_count(n));
  g.base.reserve(vcount);
  g.normals.reserve(vcount);
  const auto add = [&](double theta, double phi) {
    // Pole on the first (largest) axis.
    const Eigen::Vector3d u(std::cos(theta), std::sin(theta) * std::cos(phi),
                            std::sin(theta) * std::sin(phi));
    g.base.push_back(e.centre + e.axes * e.radii.cwiseProduct(u));
    g.normals.push_back((e.axes * u.cwiseQuotient(e.radii)).normalized());
  };
  const double step = M_PI / double(n);
  add(0.0, 0.0);
  for (int i = 1; i < n; ++i)
    for (int j = 0; j < m; ++j) add(step * i, step * j);
  add(M_PI, 0.0);
  const int north = 0, south = int(vcount) - 1;
  const auto at = [m](int i, int j) { return 1 + (i - 1) * m + (j % m); };
  // Outward: with theta growing southward and phi eastward, (d theta) x (d phi) points outward,
  // so a quad a=(i,j) b=(i,j+1) c=(i+1,j) d=(i+1,j+1) gives (a, c, b) and (b, c, d).
  g.triangles.reserve(size_t(4 * n * (n - 1)));
  for (int j = 0; j < m; ++j) g.triangles.push_back({north, at(1, j), at(1, j + 1)});
  for (int i = 1; i + 1 < n; ++i)
    for (int j = 0; j < m; ++j) {
      const int a = at(i, j), b = at(i, j + 1), c = at(i + 1, j), d = at(i + 1, j + 1);
      g.triangles.push_back({a, c, b});
      g.triangles.push_back({b, c, d});
    }
  for (int j = 0; j < m; ++j) g.triangles.push_back({at(n - 1, j), south, at(n - 1, j + 1)});
  g.vertices = g.base;
  g.extrusion.assign(vcount, 0.0f);
  g.safe.assign(vcount, 1);
  g.region.assign(vcount, -1);
  g.leeway.assign(vcount, 0.0f);
  return g;
}

namespace {
double max_edge(const std::vector<Eigen::Vector3d>& p, const std::vector<std::array<int, 3>>& t) {
  double best = 0.0;
  for (const auto& tri : t)
    for (int e = 0; e < 3; ++e) {
      best = std::max(
          best, (p[size_t(tri[size_t(e)])] - p[size_t(tri[size_t((e + 1) % 3)])]).squaredNorm());
    }
  return std::sqrt(best);
}
}  // namespace

double max_edge_length(const AreaSafetyGeometry& g, double distance_mm) {
  std::vector<Eigen::Vector3d> p(g.base.size());
  for (size_t i = 0; i < p.size(); ++i) p[i] = g.base[i] + distance_mm * g.normals[i];
  return max_edge(p, g.triangles);
}

double max_edge_length(const AreaSafetyGeometry& g) { return max_edge(g.vertices, g.triangles); }

int rings_for_edge_bound(const Ellipsoid& e, double max_distance_mm, double spacing_mm,
                         int64_t max_vertices) {
  if (!(spacing_mm > 0.0) || !std::isfinite(spacing_mm)) {
    throw Error("area safety: spacing h must be > 0 mm (got " + number(spacing_mm) + ")");
  }
  const auto fits = [&](int rings) {
    return max_edge_length(tessellate_ellipsoid(e, rings), max_distance_mm) <= spacing_mm;
  };
  int rings_max = 2;
  while (grid_vertex_count(rings_max + 1) <= max_vertices) ++rings_max;
  const auto too_fine = [&] {
    return Error("area safety: a mesh whose edges stay within h = " + number(spacing_mm) +
                 " mm at the maximum distance " + number(max_distance_mm) + " mm needs more than " +
                 std::to_string(max_vertices) +
                 " vertices; give a larger spacing or a smaller maximum distance");
  };
  // Doubling, then bisection: hi always fits, lo never does (1 stands for "none").
  int lo = 1, hi = 2;
  while (!fits(hi)) {
    if (hi >= rings_max) throw too_fine();
    lo = hi;
    hi = std::min(2 * hi, rings_max);
  }
  while (hi - lo > 1) {
    const int mid = (lo + hi) / 2;
    (fits(mid) ? hi : lo) = mid;
  }
  return hi;
}

// ---------------------------------------------------------------------------------------------
// Unsafe criteria

SafetyTest blocking_safety_test(const Volume<float>& blocking, double threshold) {
  const kernels::BlockingGrid<double> grid = blocking_grid(blocking);
  const ImageGeometry geometry = blocking.geometry();
  // The same trilinear sampling as the path safety rays (kernels::sample_blocking), whose 0
  // beyond the grid would read as "nothing vulnerable" where nothing was scanned.
  return [grid, geometry, threshold](const Eigen::Vector3d& p) {
    const kernels::Vec3<double> q = grid.physical_to_index.apply({p.x(), p.y(), p.z()});
    if (!within_extent(geometry, Eigen::Vector3d(q.x, q.y, q.z))) return PointSafety::kUnknown;
    return kernels::sample_blocking(grid, q) >= threshold ? PointSafety::kUnsafe
                                                          : PointSafety::kSafe;
  };
}

SafetyTest path_safety_test(const Volume<float>& volume, bool higher_is_safer, double threshold,
                            double roi_radius_mm, const Volume<uint8_t>* region_state) {
  const float* values = volume.data();
  const ImageGeometry geometry = volume.geometry();
  const kernels::Affine<double> to_index = physical_to_index_affine(geometry);
  const Volume<uint8_t>* states = region_state && !region_state->empty() ? region_state : nullptr;
  // The states' nearest voxel through an affine map taken once (not a matrix inverse per point,
  // which was most of area safety's time); on the volume's own grid (as plan passes them), the
  // volume's continuous index itself.
  const bool same_grid = states && states->geometry().same_grid(geometry, 0.0);
  const kernels::Affine<double> to_state =
      physical_to_index_affine(states ? states->geometry() : geometry);
  const int64_t nx = geometry.dims[0], ny = geometry.dims[1], nz = geometry.dims[2];
  // The region of interest in index units: the ball around the centre voxel (the output grid is
  // isotropic). Every point within it has a cell corner within it (the corner on the centre's
  // side along each axis), so the interpolation finds a value wherever the ball was computed.
  const Eigen::Vector3d centre_index(double(nx - 1) / 2.0, double(ny - 1) / 2.0,
                                    double(nz - 1) / 2.0);
  const double ball_sq = roi_radius_mm > 0.0
                             ? std::pow(roi_radius_mm / geometry.spacing.minCoeff(), 2) + 1e-9
                             : std::numeric_limits<double>::infinity();
  // Trilinear over the computed (finite) voxels around p; none (weight <= 1e-9): outside.
  return [=](const Eigen::Vector3d& p) {
    const kernels::Vec3<double> q = to_index.apply({p.x(), p.y(), p.z()});
    if ((Eigen::Vector3d(q.x, q.y, q.z) - centre_index).squaredNorm() > ball_sq) {
      return PointSafety::kBeyond;
    }
    if (states) {
      const kernels::Vec3<double> s = same_grid ? q : to_state.apply({p.x(), p.y(), p.z()});
      const int64_t i = std::llround(s.x), j = std::llround(s.y), k = std::llround(s.z);
      if (states->geometry().contains(i, j, k) && (*states)(i, j, k) == kRegionUnknown) {
        return PointSafety::kUnknown;
      }
    }
    double value;
    const double fx = std::floor(q.x), fy = std::floor(q.y), fz = std::floor(q.z);
    const int64_t i = int64_t(fx), j = int64_t(fy), k = int64_t(fz);
    if (i >= 0 && j >= 0 && k >= 0 && i + 1 < nx && j + 1 < ny && k + 1 < nz) {
      // All eight corners in the grid: trilinear_finite's sum, corner by corner in its order.
      const double w[3] = {q.x - fx, q.y - fy, q.z - fz};
      const float* base = values + (k * ny + j) * nx + i;
      const int64_t step[8] = {0, 1, nx, nx + 1, nx * ny, nx * ny + 1, nx * ny + nx,
                               nx * ny + nx + 1};
      double sum = 0, weight = 0;
      for (int c = 0; c < 8; ++c) {
        const double wc = ((c & 1) ? w[0] : 1 - w[0]) * (((c >> 1) & 1) ? w[1] : 1 - w[1]) *
                          (((c >> 2) & 1) ? w[2] : 1 - w[2]);
        const float x = base[step[c]];
        if (std::isfinite(x) && wc > 0) {
          sum += wc * double(x);
          weight += wc;
        }
      }
      value = weight > 1e-9 ? sum / weight : std::numeric_limits<double>::quiet_NaN();
    } else {
      value = trilinear_finite(geometry, values, Eigen::Vector3d(q.x, q.y, q.z), 1e-9);
    }
    if (std::isnan(value)) return PointSafety::kOutside;
    const bool unsafe = higher_is_safer ? value < threshold : value > threshold;
    return unsafe ? PointSafety::kUnsafe : PointSafety::kSafe;
  };
}

// ---------------------------------------------------------------------------------------------
// Extrusion and regions

AreaSafetyGeometry compute_area_safety(const Ellipsoid& e, const SafetyTest& test,
                                       const AreaSafetyOptions& o) {
  const auto t0 = Clock::now();
  const double h = o.spacing_mm, dmax = o.max_distance_mm;
  if (!(h > 0.0) || !std::isfinite(h)) {
    throw Error("area safety: spacing must be > 0 mm (got " + number(h) + ")");
  }
  if (!(dmax > 0.0) || !std::isfinite(dmax)) {
    throw Error("area safety: maximum distance must be > 0 mm (got " + number(dmax) + ")");
  }
  if (!test) throw Error("area safety: no unsafe criterion given");
  double step = o.step_mm;
  if (!(step > 0.0) || step > h / 2.0) step = h / 2.0;

  if (!(o.angular_step_deg >= 0.0) || !(o.angular_step_deg <= 30.0)) {
    throw Error("area safety: angular step must be within 0 and 30 degrees (got " +
                number(o.angular_step_deg) + ")");
  }
  const double edge_bound = std::max(h, dmax * o.angular_step_deg * M_PI / 180.0);
  const int rings = rings_for_edge_bound(e, dmax, edge_bound, o.max_vertices);
  AreaSafetyGeometry g = tessellate_ellipsoid(e, rings);
  g.max_distance_mm = dmax;
  g.spacing_mm = h;
  g.edge_bound_mm = edge_bound;
  g.angular_step_deg = o.angular_step_deg;
  const int64_t samples = int64_t(std::ceil(dmax / step - 1e-9));
  g.step_mm = dmax / double(samples);
  const int64_t nv = int64_t(g.base.size());
  spdlog::info(
      "area safety: {} vertices ({} rings of latitude), extruded up to {} mm in steps "
      "of {:.3g} mm",
      nv, rings - 1, dmax, g.step_mm);

  const int threads = o.threads > 0 ? o.threads : omp_get_max_threads();
  std::exception_ptr failure;
  std::mutex failure_mutex;
  std::atomic<int64_t> done{0};
  std::atomic<int64_t> unknown_count{0};
  std::atomic<int64_t> uncomputed_count{0};
  int last_decile = 0;
#pragma omp parallel for schedule(dynamic, 64) num_threads(threads)
  for (int64_t v = 0; v < nv; ++v) {
    try {
      const Eigen::Vector3d& b = g.base[size_t(v)];
      const Eigen::Vector3d& n = g.normals[size_t(v)];
      double length = dmax;
      uint8_t safe = 1;
      for (int64_t k = 0; k <= samples; ++k) {
        const double d = k == samples ? dmax : double(k) * g.step_mm;
        const PointSafety s = test(b + d * n);
        if (s == PointSafety::kSafe) continue;
        if (s == PointSafety::kUnsafe) {
          length = d;
          safe = 0;
          break;
        }
        length = k == 0 ? 0.0 : double(k - 1) * g.step_mm;
        // Safe only when it left the region of interest through computed, safe values; unknown
        // and uncomputed points are never safe.
        safe = s == PointSafety::kBeyond && k > 0;
        if (s == PointSafety::kUnknown) {
          ++unknown_count;
        } else if (!safe) {
          ++uncomputed_count;
        }
        break;
      }
      g.extrusion[size_t(v)] = float(length);
      g.safe[size_t(v)] = safe;
      g.vertices[size_t(v)] = b + length * n;
    } catch (...) {
      std::lock_guard<std::mutex> lock(failure_mutex);
      if (!failure) failure = std::current_exception();
    }
    const int64_t count = ++done;
    if (omp_get_thread_num() == 0 && nv > 200000) {
      const int decile = int(10 * count / nv);
      if (decile > last_decile) {
        last_decile = decile;
        spdlog::info("area safety: {:3d} %", decile * 10);
      }
    }
  }
  if (failure) std::rethrow_exception(failure);
  g.unknown_vertex_count = unknown_count;
  if (g.unknown_vertex_count > 0) {
    spdlog::warn("area safety: {} of {} extrusions reach the unknown (outside the scan): not safe",
                 g.unknown_vertex_count, nv);
  }
  g.uncomputed_vertex_count = uncomputed_count;
  if (g.uncomputed_vertex_count > 0) {
    spdlog::warn(
        "area safety: {} of {} extrusions meet points with no path safety value before the edge "
        "of the region of interest (not computed there): not safe",
        g.uncomputed_vertex_count, nv);
  }
  measure_regions(g);
  int64_t safe_count = 0;
  for (uint8_t s : g.safe) safe_count += s;
  spdlog::info("area safety: {} of {} vertices safe, {} region(s), {:.2f} s", safe_count, nv,
               g.regions.size(), seconds_since(t0));
  return g;
}

namespace {

int find_root(std::vector<int>& parent, int x) {
  while (parent[size_t(x)] != x) {
    parent[size_t(x)] = parent[size_t(parent[size_t(x)])];
    x = parent[size_t(x)];
  }
  return x;
}

// Throws Error when the safe flags or a triangle's vertex indices do not fit the vertices.
void check_region_inputs(const AreaSafetyGeometry& g) {
  const size_t nv = g.vertices.size();
  if (g.safe.size() != nv) {
    throw Error("area safety: " + std::to_string(g.safe.size()) + " safe flags for " +
                std::to_string(nv) + " vertices");
  }
  for (const auto& t : g.triangles)
    for (int v : t)
      if (v < 0 || size_t(v) >= nv) {
        throw Error("area safety: triangle vertex " + std::to_string(v) + " out of range (" +
                    std::to_string(nv) + " vertices)");
      }
}

// Connected safe regions over the mesh edges, numbered in the order of their first vertex.
struct SafeComponents {
  std::vector<int> of_vertex;     // component of each vertex, -1 for an unsafe one
  std::vector<int> first_vertex;  // lowest vertex index of each component
  int count() const { return int(first_vertex.size()); }
};

SafeComponents safe_components(const AreaSafetyGeometry& g) {
  const size_t nv = g.vertices.size();
  // Union-find over the edges whose two ends are safe.
  std::vector<int> parent(nv);
  std::iota(parent.begin(), parent.end(), 0);
  for (const auto& t : g.triangles)
    for (int e = 0; e < 3; ++e) {
      const int a = t[size_t(e)], b = t[size_t((e + 1) % 3)];
      if (!g.safe[size_t(a)] || !g.safe[size_t(b)]) continue;
      const int ra = find_root(parent, a), rb = find_root(parent, b);
      if (ra != rb) parent[size_t(std::max(ra, rb))] = std::min(ra, rb);
    }
  SafeComponents c;
  c.of_vertex.assign(nv, -1);
  for (size_t v = 0; v < nv; ++v) {
    if (!g.safe[v]) continue;
    const int r = find_root(parent, int(v));
    if (c.of_vertex[size_t(r)] < 0) {
      c.of_vertex[size_t(r)] = c.count();
      c.first_vertex.push_back(int(v));
    }
    c.of_vertex[v] = c.of_vertex[size_t(r)];
  }
  return c;
}

// Per-vertex shares: a third of each adjacent signed tetrahedron from the ellipsoid centre (mass,
// mm^3), a third of each adjacent base triangle's area (weight of centre and axis, mm^2).
struct VertexShares {
  std::vector<double> mass, weight;
};

VertexShares vertex_shares(const AreaSafetyGeometry& g) {
  const size_t nv = g.vertices.size();
  const Eigen::Vector3d c = g.ellipsoid.centre;
  const bool have_base = g.base.size() == nv;
  VertexShares s{std::vector<double>(nv, 0.0), std::vector<double>(nv, 0.0)};
  for (const auto& t : g.triangles) {
    const Eigen::Vector3d a = g.vertices[size_t(t[0])] - c, b = g.vertices[size_t(t[1])] - c,
                          d = g.vertices[size_t(t[2])] - c;
    const double vol = a.dot(b.cross(d)) / 6.0;
    const auto& p = have_base ? g.base : g.vertices;
    const double area =
        0.5 * (p[size_t(t[1])] - p[size_t(t[0])]).cross(p[size_t(t[2])] - p[size_t(t[0])]).norm();
    for (int v : t) {
      s.mass[size_t(v)] += vol / 3.0;
      s.weight[size_t(v)] += area / 3.0;
    }
  }
  return s;
}

// Sums over the vertices of one component, in vertex order.
struct ComponentSums {
  double size = 0, wsum = 0;
  Eigen::Vector3d centre = Eigen::Vector3d::Zero(), axis = Eigen::Vector3d::Zero();
  int vertices = 0, first = 0;
};

std::vector<ComponentSums> component_sums(const AreaSafetyGeometry& g, const SafeComponents& comp,
                                          const VertexShares& shares) {
  const size_t nv = g.vertices.size();
  const Eigen::Vector3d c = g.ellipsoid.centre;
  const bool have_normals = g.normals.size() == nv;
  std::vector<ComponentSums> acc(static_cast<size_t>(comp.count()));
  for (int r = 0; r < comp.count(); ++r) acc[size_t(r)].first = comp.first_vertex[size_t(r)];
  for (size_t v = 0; v < nv; ++v) {
    if (comp.of_vertex[v] < 0) continue;
    ComponentSums& a = acc[size_t(comp.of_vertex[v])];
    a.size += shares.mass[v];
    a.wsum += shares.weight[v];
    a.centre += shares.weight[v] * g.vertices[v];
    const Eigen::Vector3d dir = have_normals ? g.normals[v] : (g.vertices[v] - c).normalized();
    a.axis += shares.weight[v] * dir;
    ++a.vertices;
  }
  return acc;
}

// The region of one component: weighted centre, main axis, leeway against the largest size.
AreaRegion make_region(const AreaSafetyGeometry& g, const ComponentSums& a, int id,
                       double largest) {
  AreaRegion r;
  r.id = id;
  r.size_mm3 = a.size;
  r.centre = a.wsum > 0 ? Eigen::Vector3d(a.centre / a.wsum)
                        : Eigen::Vector3d(g.vertices[size_t(a.first)]);
  // A region around the whole tumor has no preferred direction: its mean normal vanishes; then
  // the ellipsoid's shortest axis (the shortest way out of the tumor) stands for it.
  r.main_axis = a.axis.norm() > 1e-3 * std::max(a.wsum, 1e-12)
                    ? Eigen::Vector3d(a.axis.normalized())
                    : Eigen::Vector3d(g.ellipsoid.axes.col(2));
  r.leeway = largest > 0 ? std::max(0.0, a.size / largest) : 0.0;
  r.vertex_count = a.vertices;
  return r;
}

// Writes g.regions largest first (ties: the lower first vertex) and each vertex's region and
// leeway.
void rank_regions(AreaSafetyGeometry& g, const SafeComponents& comp,
                  const std::vector<ComponentSums>& acc) {
  const int count = comp.count();
  std::vector<int> order(static_cast<size_t>(count));
  std::iota(order.begin(), order.end(), 0);
  std::sort(order.begin(), order.end(), [&](int x, int y) {
    const ComponentSums &a = acc[size_t(x)], &b = acc[size_t(y)];
    if (a.size != b.size) return a.size > b.size;
    return a.first < b.first;
  });
  std::vector<int> id_of(static_cast<size_t>(count));
  g.regions.clear();
  const double largest = count > 0 ? acc[size_t(order[0])].size : 0.0;
  for (int k = 0; k < count; ++k) {
    id_of[size_t(order[size_t(k)])] = k;
    g.regions.push_back(make_region(g, acc[size_t(order[size_t(k)])], k, largest));
  }
  const size_t nv = g.vertices.size();
  g.region.assign(nv, -1);
  g.leeway.assign(nv, 0.0f);
  for (size_t v = 0; v < nv; ++v) {
    if (comp.of_vertex[v] < 0) continue;
    const int id = id_of[size_t(comp.of_vertex[v])];
    g.region[v] = id;
    g.leeway[v] = float(g.regions[size_t(id)].leeway);
  }
}

}  // namespace

double enclosed_volume(const AreaSafetyGeometry& g) {
  const Eigen::Vector3d c = g.ellipsoid.centre;
  double sum = 0.0;
  for (const auto& t : g.triangles) {
    const Eigen::Vector3d a = g.vertices[size_t(t[0])] - c, b = g.vertices[size_t(t[1])] - c,
                          d = g.vertices[size_t(t[2])] - c;
    sum += a.dot(b.cross(d));
  }
  return sum / 6.0;
}

void measure_regions(AreaSafetyGeometry& g) {
  check_region_inputs(g);
  const SafeComponents components = safe_components(g);
  rank_regions(g, components, component_sums(g, components, vertex_shares(g)));
}

// ---------------------------------------------------------------------------------------------
// VTK legacy PolyData

namespace {

// Legacy VTK BINARY: every value big-endian, each block followed by a newline.
template <typename T>
void append_be(std::string& s, T value) {
  char bytes[sizeof(T)];
  std::memcpy(bytes, &value, sizeof(T));
  for (size_t i = sizeof(T); i-- > 0;) s.push_back(bytes[i]);
}

void append3(std::string& s, const Eigen::Vector3d& v) {
  for (int c = 0; c < 3; ++c) append_be(s, v[c]);
}

}  // namespace

void write_area_safety_vtk(const std::string& path, const AreaSafetyGeometry& g) {
  const size_t nv = g.vertices.size();
  if (g.safe.size() != nv || g.region.size() != nv || g.leeway.size() != nv) {
    throw Error(path + ": area safety geometry has per-vertex arrays of the wrong length");
  }
  std::string s;
  s.reserve(nv * 70 + g.triangles.size() * 16 + 4096);
  s += "# vtk DataFile Version 3.0\n";
  // The title line is the header that 3D Slicer searches for "SPACE=": without it Slicer takes
  // legacy VTK models as RAS and would mirror this LPS mesh (x and y negated).
  s += "Crepuscular area safety geometry SPACE=LPS (mm)\n";
  s += "BINARY\nDATASET POLYDATA\n";
  // Dataset field data: the ellipsoid, the settings and the regions (one tuple per region).
  const size_t nr = g.regions.size();
  s += "FIELD FieldData " + std::to_string(nr > 0 ? 7 : 2) + "\n";
  s += "ellipsoid 15 1 double\n";
  append3(s, g.ellipsoid.centre);
  for (int c = 0; c < 3; ++c) append3(s, g.ellipsoid.axes.col(c));
  append3(s, g.ellipsoid.radii);
  s += "\narea_settings 5 1 double\n";
  for (double x : {g.max_distance_mm, g.step_mm, g.spacing_mm, g.threshold, double(g.rings)}) {
    append_be(s, x);
  }
  s += "\n";
  if (nr > 0) {
    s += "region_size_mm3 1 " + std::to_string(nr) + " double\n";
    for (const auto& r : g.regions) append_be(s, r.size_mm3);
    s += "\nregion_leeway 1 " + std::to_string(nr) + " double\n";
    for (const auto& r : g.regions) append_be(s, r.leeway);
    s += "\nregion_vertex_count 1 " + std::to_string(nr) + " int\n";
    for (const auto& r : g.regions) append_be(s, int32_t(r.vertex_count));
    s += "\nregion_centre 3 " + std::to_string(nr) + " double\n";
    for (const auto& r : g.regions) append3(s, r.centre);
    s += "\nregion_main_axis 3 " + std::to_string(nr) + " double\n";
    for (const auto& r : g.regions) append3(s, r.main_axis);
    s += "\n";
  }
  s += "POINTS " + std::to_string(nv) + " double\n";
  for (const auto& v : g.vertices) append3(s, v);
  s += "\nPOLYGONS " + std::to_string(g.triangles.size()) + " " +
       std::to_string(4 * g.triangles.size()) + "\n";
  for (const auto& t : g.triangles) {
    append_be(s, int32_t(3));
    for (int c = 0; c < 3; ++c) append_be(s, int32_t(t[size_t(c)]));
  }
  s += "\nPOINT_DATA " + std::to_string(nv) + "\n";
  if (g.normals.size() == nv) {
    s += "NORMALS normals double\n";
    for (const auto& n : g.normals) append3(s, n);
    s += "\n";
  }
  // Leeway first: VTK's legacy reader (vtkDataReader::ReadScalarData) makes the first SCALARS of
  // POINT_DATA the active scalars, which 3D Slicer and ParaView colour the mesh by.
  s += "SCALARS leeway float 1\nLOOKUP_TABLE default\n";
  for (float x : g.leeway) append_be(s, x);
  s += "\nSCALARS safe unsigned_char 1\nLOOKUP_TABLE default\n";
  for (uint8_t x : g.safe) s.push_back(char(x ? 1 : 0));
  s += "\nSCALARS region int 1\nLOOKUP_TABLE default\n";
  for (int x : g.region) append_be(s, int32_t(x));
  s += "\n";
  if (g.extrusion.size() == nv) {
    s += "SCALARS extrusion_mm float 1\nLOOKUP_TABLE default\n";
    for (float x : g.extrusion) append_be(s, x);
    s += "\n";
  }
  write_text_file(path, s);
}

namespace {

// Whitespace tokens of a text buffer, with the line number for messages.
class Tokens {
 public:
  Tokens(const std::string& path, std::string text) : path_(path), text_(std::move(text)) {}

  std::string line() {  // the rest of the current line
    const size_t end = text_.find('\n', pos_);
    std::string l = text_.substr(pos_, end == std::string::npos ? std::string::npos : end - pos_);
    pos_ = end == std::string::npos ? text_.size() : end + 1;
    ++line_;
    if (!l.empty() && l.back() == '\r') l.pop_back();
    return l;
  }
  bool next(std::string& word) {
    skip();
    if (pos_ >= text_.size()) return false;
    const size_t start = pos_;
    while (pos_ < text_.size() && !std::isspace(static_cast<unsigned char>(text_[pos_]))) ++pos_;
    word.assign(text_, start, pos_ - start);
    return true;
  }
  std::string word(const char* what) {
    std::string w;
    if (!next(w)) fail(std::string("file ends where ") + what + " was expected");
    return w;
  }
  double number(const char* what) {
    skip();
    if (pos_ >= text_.size()) fail(std::string("file ends where ") + what + " was expected");
    const char* begin = text_.c_str() + pos_;
    char* end = nullptr;
    const double x = std::strtod(begin, &end);
    if (end == begin) {
      fail(std::string("expected a number for ") + what + ", found '" +
           std::string(begin, std::min<size_t>(20, std::strcspn(begin, " \t\r\n"))) + "'");
    }
    pos_ += size_t(end - begin);
    return x;
  }
  int64_t integer(const char* what) {
    const double x = number(what);
    if (x != std::floor(x)) fail(std::string("expected an integer for ") + what);
    if (!(std::abs(x) <= 9e15)) fail(std::string("impossible integer for ") + what);
    return int64_t(x);
  }
  [[noreturn]] void fail(const std::string& message) const {
    throw Error(path_ + ": line " + std::to_string(line_) + ": " + message);
  }

  void set_binary(bool binary) { binary_ = binary; }
  // `count` values of a VTK data type ("double", "float", "int", "unsigned_char", ...): text in an
  // ASCII file; in a BINARY one a big-endian block that starts after the header line's newline.
  std::vector<double> values(size_t count, const std::string& type, const char* what) {
    // A count the file cannot hold is refused before anything is allocated for it.
    const size_t remaining = text_.size() - std::min(pos_, text_.size());
    if (!binary_) {
      if (count > remaining / 2 + 1) {
        fail("the file is too short for " + std::to_string(count) + " values of " + what);
      }
      std::vector<double> out(count);
      for (double& x : out) x = number(what);
      return out;
    }
    const size_t size = type == "double"                       ? 8
                        : type == "float" || type == "int" ||
                                  type == "unsigned_int"       ? 4
                        : type == "short" || type == "unsigned_short" ? 2
                        : type == "unsigned_char" || type == "char" || type == "bit" ? 1
                                                                                     : 0;
    if (size == 0 || type == "bit") fail(std::string("unsupported binary type '") + type + "' for " + what);
    while (pos_ < text_.size() && text_[pos_] != '\n') ++pos_;  // the header line's end
    ++pos_;
    ++line_;
    if (count > (text_.size() - std::min(pos_, text_.size())) / size) {
      fail(std::string("file ends inside the binary data of ") + what);
    }
    std::vector<double> out(count);
    for (double& x : out) {
      unsigned char b[8];
      for (size_t i = 0; i < size; ++i) b[size - 1 - i] = static_cast<unsigned char>(text_[pos_ + i]);
      pos_ += size;
      if (type == "double") {
        double v;
        std::memcpy(&v, b, 8);
        x = v;
      } else if (type == "float") {
        float v;
        std::memcpy(&v, b, 4);
        x = v;
      } else if (type == "int") {
        int32_t v;
        std::memcpy(&v, b, 4);
        x = v;
      } else if (type == "unsigned_int") {
        uint32_t v;
        std::memcpy(&v, b, 4);
        x = v;
      } else if (type == "short") {
        int16_t v;
        std::memcpy(&v, b, 2);
        x = v;
      } else if (type == "unsigned_short") {
        uint16_t v;
        std::memcpy(&v, b, 2);
        x = v;
      } else if (type == "char") {
        x = double(static_cast<signed char>(b[0]));
      } else {
        x = double(b[0]);
      }
    }
    return out;
  }

 private:
  void skip() {
    while (pos_ < text_.size() && std::isspace(static_cast<unsigned char>(text_[pos_]))) {
      if (text_[pos_] == '\n') ++line_;
      ++pos_;
    }
  }
  std::string path_, text_;
  size_t pos_ = 0;
  int line_ = 1;
  bool binary_ = false;
};

// Reads the file and checks the legacy VTK header, up to 'DATASET POLYDATA'.
Tokens open_polydata(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(path + ": cannot read file");
  std::stringstream buf;
  buf << in.rdbuf();
  Tokens tok(path, buf.str());
  if (tok.line().rfind("# vtk DataFile", 0) != 0) {
    tok.fail("not a VTK legacy file (expected '# vtk DataFile Version ...' on line 1)");
  }
  tok.line();  // title
  const std::string format = tok.line();
  if (format.rfind("BINARY", 0) == 0) {
    tok.set_binary(true);
  } else if (format.rfind("ASCII", 0) != 0) {
    tok.fail("expected ASCII or BINARY on line 3");
  }
  if (tok.word("DATASET") != "DATASET" || tok.word("POLYDATA") != "POLYDATA") {
    tok.fail("expected 'DATASET POLYDATA'");
  }
  return tok;
}

// The dataset field arrays that write_area_safety_vtk writes, as read (others are skipped).
struct VtkFieldArrays {
  std::vector<double> ellipsoid, settings, sizes, leeways, counts, centres, axes;
};

void read_field_data(Tokens& tok, VtkFieldArrays& f) {
  tok.word("field name");
  const int64_t arrays = tok.integer("array count");
  for (int64_t a = 0; a < arrays; ++a) {
    const std::string name = tok.word("array name");
    const int64_t comps = tok.integer("components"), tuples = tok.integer("tuples");
    if (comps < 0 || tuples < 0 || comps > 1000000 || tuples > 100000000) {
      tok.fail("field array '" + name + "' has an impossible size");
    }
    const std::string type = tok.word("data type");
    const std::vector<double> values = tok.values(size_t(comps * tuples), type, name.c_str());
    if (name == "ellipsoid")
      f.ellipsoid = values;
    else if (name == "area_settings")
      f.settings = values;
    else if (name == "region_size_mm3")
      f.sizes = values;
    else if (name == "region_leeway")
      f.leeways = values;
    else if (name == "region_vertex_count")
      f.counts = values;
    else if (name == "region_centre")
      f.centres = values;
    else if (name == "region_main_axis")
      f.axes = values;
  }
}

// Returns the point count.
int64_t read_points(Tokens& tok, AreaSafetyGeometry& g) {
  const int64_t nv = tok.integer("point count");
  if (nv < 0 || nv > 100000000) tok.fail("POINTS: impossible point count");
  const std::string type = tok.word("point type");
  const std::vector<double> x = tok.values(size_t(3 * nv), type, "point coordinate");
  g.vertices.resize(size_t(nv));
  for (size_t v = 0; v < size_t(nv); ++v) g.vertices[v] = Eigen::Vector3d(x[3 * v], x[3 * v + 1], x[3 * v + 2]);
  return nv;
}

void read_polygons(Tokens& tok, int64_t nv, AreaSafetyGeometry& g) {
  const int64_t n = tok.integer("polygon count");
  const int64_t size = tok.integer("polygon list size");
  if (n < 0 || size != 4 * n || n > 200000000) {
    tok.fail("POLYGONS: only triangles are read (list size 4 x count)");
  }
  const std::vector<double> list = tok.values(size_t(size), "int", "polygon list");
  g.triangles.resize(size_t(n));
  for (size_t k = 0; k < size_t(n); ++k) {
    if (list[4 * k] != 3) tok.fail("POLYGONS: only triangles are read");
    for (size_t c = 0; c < 3; ++c) {
      const double v = list[4 * k + 1 + c];
      if (!(v >= 0 && v < double(nv))) tok.fail("POLYGONS: vertex index out of range");
      g.triangles[k][c] = int(v);
    }
  }
}

void read_normals(Tokens& tok, int64_t nv, AreaSafetyGeometry& g) {
  tok.word("normals name");
  const std::string type = tok.word("normals type");
  if (nv < 0) tok.fail("NORMALS before POINTS");
  const std::vector<double> x = tok.values(size_t(3 * nv), type, "normal component");
  g.normals.resize(size_t(nv));
  for (size_t v = 0; v < size_t(nv); ++v) g.normals[v] = Eigen::Vector3d(x[3 * v], x[3 * v + 1], x[3 * v + 2]);
}

// One SCALARS array of the point data: safe, region, leeway, extrusion_mm (others are skipped).
void read_scalars(Tokens& tok, int64_t nv, AreaSafetyGeometry& g) {
  const std::string name = tok.word("scalars name");
  const std::string type = tok.word("scalars type");
  std::string lut = tok.word("LOOKUP_TABLE");
  if (lut != "LOOKUP_TABLE") {  // optional component count
    lut = tok.word("LOOKUP_TABLE");
  }
  tok.word("lookup table name");
  if (nv < 0) tok.fail("SCALARS before POINTS");
  const std::vector<double> values = tok.values(size_t(nv), type, name.c_str());
  const auto all = [&](auto valid, const char* expected) {
    if (!std::all_of(values.begin(), values.end(), valid)) {
      tok.fail("SCALARS " + name + ": a value that is not " + expected);
    }
  };
  if (name == "safe") {
    all([](double x) { return x == 0 || x == 1; }, "0 or 1");
    g.safe.assign(values.begin(), values.end());
  } else if (name == "region") {
    all([](double x) { return x >= -1 && x <= 1e9 && x == std::floor(x); }, "a region number");
    g.region.assign(values.begin(), values.end());
  } else if (name == "leeway") {
    g.leeway.assign(values.begin(), values.end());
  } else if (name == "extrusion_mm") {
    g.extrusion.assign(values.begin(), values.end());
  }
}

// The sections every area safety file has: points, triangles and the per-vertex scalars.
void check_sections(const Tokens& tok, int64_t nv, const AreaSafetyGeometry& g) {
  if (nv < 0) tok.fail("no POINTS section");
  if (g.triangles.empty()) tok.fail("no POLYGONS section");
  if (g.safe.size() != size_t(nv) || g.region.size() != size_t(nv) ||
      g.leeway.size() != size_t(nv)) {
    tok.fail("POINT_DATA must hold the scalars safe, region and leeway");
  }
}

// The ellipsoid, the settings and the regions, where the field arrays hold them whole.
void apply_field_arrays(const VtkFieldArrays& f, AreaSafetyGeometry& g) {
  if (f.ellipsoid.size() == 15) {
    const auto& e = f.ellipsoid;
    g.ellipsoid.centre = Eigen::Vector3d(e[0], e[1], e[2]);
    for (int c = 0; c < 3; ++c)
      g.ellipsoid.axes.col(c) =
          Eigen::Vector3d(e[size_t(3 + 3 * c)], e[size_t(4 + 3 * c)], e[size_t(5 + 3 * c)]);
    g.ellipsoid.radii = Eigen::Vector3d(e[12], e[13], e[14]);
  }
  if (f.settings.size() == 5) {
    g.max_distance_mm = f.settings[0];
    g.step_mm = f.settings[1];
    g.spacing_mm = f.settings[2];
    g.threshold = f.settings[3];
    g.rings = f.settings[4] >= 0 && f.settings[4] <= 1e6 ? int(f.settings[4]) : 0;
    g.segments = 2 * g.rings;
  }
  const size_t nr = f.sizes.size();
  if (f.leeways.size() == nr && f.counts.size() == nr && f.centres.size() == 3 * nr &&
      f.axes.size() == 3 * nr) {
    for (size_t r = 0; r < nr; ++r) {
      AreaRegion region;
      region.id = int(r);
      region.size_mm3 = f.sizes[r];
      region.leeway = f.leeways[r];
      region.vertex_count = f.counts[r] >= 0 && f.counts[r] <= 2e9 ? int(f.counts[r]) : 0;
      region.centre = Eigen::Vector3d(f.centres[3 * r], f.centres[3 * r + 1], f.centres[3 * r + 2]);
      region.main_axis = Eigen::Vector3d(f.axes[3 * r], f.axes[3 * r + 1], f.axes[3 * r + 2]);
      g.regions.push_back(region);
    }
  }
}

// The unextruded base surface, where the extrusion and the normals are both present.
void restore_base(AreaSafetyGeometry& g) {
  const size_t nv = g.vertices.size();
  if (g.extrusion.size() != nv || g.normals.size() != nv) return;
  g.base.resize(nv);
  for (size_t v = 0; v < nv; ++v) {
    g.base[v] = g.vertices[v] - double(g.extrusion[v]) * g.normals[v];
  }
}

}  // namespace

AreaSafetyGeometry read_area_safety_vtk(const std::string& path) {
  Tokens tok = open_polydata(path);
  AreaSafetyGeometry g;
  VtkFieldArrays fields;
  int64_t nv = -1;
  std::string w;
  while (tok.next(w)) {
    if (w == "FIELD") {
      read_field_data(tok, fields);
    } else if (w == "POINTS") {
      nv = read_points(tok, g);
    } else if (w == "POLYGONS") {
      read_polygons(tok, nv, g);
    } else if (w == "POINT_DATA") {
      if (tok.integer("point data count") != nv) tok.fail("POINT_DATA count differs from POINTS");
    } else if (w == "NORMALS") {
      read_normals(tok, nv, g);
    } else if (w == "SCALARS") {
      read_scalars(tok, nv, g);
    } else {
      tok.fail("unexpected keyword '" + w + "'");
    }
  }
  check_sections(tok, nv, g);
  apply_field_arrays(fields, g);
  restore_base(g);
  return g;
}

nlohmann::json area_safety_json(const AreaSafetyGeometry& g) {
  int64_t safe = 0;
  for (uint8_t s : g.safe) safe += s;
  nlohmann::json regions = nlohmann::json::array();
  for (const auto& r : g.regions) {
    regions.push_back({{"id", r.id},
                       {"size_mm3", r.size_mm3},
                       {"centre_lps_mm", vec_json(r.centre)},
                       {"main_axis", vec_json(r.main_axis)},
                       {"leeway", r.leeway},
                       {"vertex_count", r.vertex_count}});
  }
  nlohmann::json axes = nlohmann::json::array();
  for (int c = 0; c < 3; ++c) axes.push_back(vec_json(g.ellipsoid.axes.col(c)));
  return {{"criterion", g.criterion},
          {"threshold", g.threshold},
          {"max_distance_mm", g.max_distance_mm},
          {"step_mm", g.step_mm},
          {"spacing_mm", g.spacing_mm},
          {"angular_step_deg", g.angular_step_deg},
          {"edge_bound_mm", g.edge_bound_mm},
          {"rings", g.rings},
          {"segments", g.segments},
          {"vertex_count", g.vertices.size()},
          {"triangle_count", g.triangles.size()},
          {"safe_vertex_count", safe},
          {"unknown_vertex_count", g.unknown_vertex_count},
          {"uncomputed_vertex_count", g.uncomputed_vertex_count},
          {"max_edge_full_extrusion_mm",
           g.base.empty() ? nlohmann::json(nullptr)
                          : nlohmann::json(max_edge_length(g, g.max_distance_mm))},
          {"enclosed_volume_mm3", enclosed_volume(g)},
          {"size_rule",
           "divergence theorem on the closed extruded surface, tetrahedra from the ellipsoid "
           "centre; a triangle counts one third for each of its vertices in the region"},
          {"ellipsoid",
           {{"centre_lps_mm", vec_json(g.ellipsoid.centre)},
            {"axes", axes},
            {"radii_mm", vec_json(g.ellipsoid.radii)}}},
          {"regions", regions}};
}

// ---------------------------------------------------------------------------------------------
// The plan's area safety step

nlohmann::json plan_area_safety(const Volume<uint8_t>& tumor, const PathSafetyResult& result,
                                const AreaSafetyPlanOptions& options, const std::string& vtk_path,
                                const Volume<uint8_t>* region_state,
                                AreaSafetyGeometry* geometry) {
  const auto t0 = Clock::now();
  int slot = -1;
  for (int v = 0; v < kernels::kValueCount; ++v) {
    if (result.values & (1u << v)) {
      slot = v;
      break;
    }
  }
  if (slot < 0) throw Error("area safety: the plan computed no path safety value");
  const unsigned bit = 1u << slot;
  const Volume<float>& volume = result.volumes[size_t(slot)];
  const SafetyClasses classes = result.classes[size_t(slot)] ? *result.classes[size_t(slot)]
                                                             : default_classes(bit, volume);
  if (options.unsafe_class != "dangerous" && options.unsafe_class != "medium") {
    throw Error("area safety: unsafe class: expected 'dangerous' or 'medium', got '" +
                options.unsafe_class + "'");
  }
  double threshold = options.threshold;
  if (std::isnan(threshold)) {
    threshold = options.unsafe_class == "dangerous" ? classes.dangerous : classes.safe;
  }
  AreaSafetyOptions o;
  o.spacing_mm = result.grid.geometry.spacing[0];
  o.max_distance_mm = options.max_distance_mm > 0 ? options.max_distance_mm : result.grid.radius_mm;
  o.angular_step_deg = options.angular_step_deg;
  const Ellipsoid e = fit_tumor_ellipsoid(tumor);
  AreaSafetyGeometry g =
      compute_area_safety(e, path_safety_test(volume, classes.higher_is_safer, threshold,
                                              result.grid.radius_mm, region_state), o);
  g.criterion = std::string("path safety ") + value_name(bit) +
                (classes.higher_is_safer ? " < " : " > ") + number(threshold) + " (" +
                options.unsafe_class + (options.unsafe_class == "medium" ? " or dangerous" : "") +
                " is unsafe)";
  g.threshold = threshold;
  write_area_safety_vtk(vtk_path, g);
  nlohmann::json j = area_safety_json(g);
  j["value"] = value_name(bit);
  j["unsafe_class"] = options.unsafe_class;
  j["file"] = fs::path(vtk_path).filename().string();
  j["seconds"] = seconds_since(t0);
  if (geometry) *geometry = std::move(g);
  return j;
}

}  // namespace crepuscular::planning
