// The path safety values of docs/ARCHITECTURE.md §4 (paper §3.2, Algorithm 1), written once as
// host/device functions: the CPU backend and the CUDA kernels call exactly these. Plain structs,
// raw buffers, no Eigen or STL containers, so nvcc and the host compiler read the same code.
#pragma once

#include <math.h>
#include <stdint.h>

#include <type_traits>

#include "kernels/hd.hpp"
#include "kernels/value_bits.hpp"

namespace crepuscular::kernels {

template <typename Real>
struct Vec3 {
  Real x, y, z;
};

template <typename Real>
CREPUSCULAR_HD Vec3<Real> operator-(Vec3<Real> a, Vec3<Real> b) {
  return {a.x - b.x, a.y - b.y, a.z - b.z};
}
template <typename Real>
CREPUSCULAR_HD Real dot(Vec3<Real> a, Vec3<Real> b) {
  return a.x * b.x + a.y * b.y + a.z * b.z;
}

// Double arithmetic that rounds identically on host and device: nvcc would otherwise fuse a * b + c
// into one fused multiply-add (one rounding instead of two). The ray geometry (sample positions,
// sample count, tumor occupancy) is computed with these in double on every backend, so that a
// sample lying exactly half-way between two tumor voxels (common where grids are aligned) is
// resolved the same way by the CPU and the GPU.
CREPUSCULAR_HD double mul_rn(double a, double b) {
#ifdef __CUDA_ARCH__
  return __dmul_rn(a, b);
#else
  return a * b;
#endif
}
CREPUSCULAR_HD double add_rn(double a, double b) {
#ifdef __CUDA_ARCH__
  return __dadd_rn(a, b);
#else
  return a + b;
#endif
}
CREPUSCULAR_HD double dot_rn(Vec3<double> a, Vec3<double> b) {
  return add_rn(add_rn(mul_rn(a.x, b.x), mul_rn(a.y, b.y)), mul_rn(a.z, b.z));
}
// origin + k step, one rounding per operation.
CREPUSCULAR_HD Vec3<double> along_rn(Vec3<double> origin, Vec3<double> step, double k) {
  return {add_rn(origin.x, mul_rn(k, step.x)), add_rn(origin.y, mul_rn(k, step.y)),
          add_rn(origin.z, mul_rn(k, step.z))};
}
// Centre of voxel (i, j, k) of a grid: origin + i axes[0] + j axes[1] + k axes[2] (LPS mm). The
// one definition of an output voxel's position for every backend.
CREPUSCULAR_HD Vec3<double> grid_point(const double origin[3], const double axes[3][3],
                                              int i, int j, int k) {
  double r[3];
  for (int a = 0; a < 3; ++a) {
    r[a] = add_rn(add_rn(add_rn(origin[a], mul_rn(double(i), axes[0][a])),
                         mul_rn(double(j), axes[1][a])),
                  mul_rn(double(k), axes[2][a]));
  }
  return {r[0], r[1], r[2]};
}

template <typename To, typename From>
CREPUSCULAR_HD Vec3<To> vec_cast(Vec3<From> v) {
  return {To(v.x), To(v.y), To(v.z)};
}

// Affine map x -> m[r][0..2] . x + m[r][3]; used for physical (LPS mm) -> continuous voxel index.
template <typename Real>
struct Affine {
  Real m[3][4];

  CREPUSCULAR_HD Vec3<Real> apply(Vec3<Real> p) const {
    return {m[0][0] * p.x + m[0][1] * p.y + m[0][2] * p.z + m[0][3],
            m[1][0] * p.x + m[1][1] * p.y + m[1][2] * p.z + m[1][3],
            m[2][0] * p.x + m[2][1] * p.y + m[2][2] * p.z + m[2][3]};
  }
  CREPUSCULAR_HD Vec3<Real> apply_linear(Vec3<Real> d) const {
    return {m[0][0] * d.x + m[0][1] * d.y + m[0][2] * d.z,
            m[1][0] * d.x + m[1][1] * d.y + m[1][2] * d.z,
            m[2][0] * d.x + m[2][1] * d.y + m[2][2] * d.z};
  }
};

// The same maps in double with host/device-identical rounding (see mul_rn).
CREPUSCULAR_HD Vec3<double> apply_linear_rn(const Affine<double>& a, Vec3<double> d) {
  double r[3];
  for (int row = 0; row < 3; ++row) {
    r[row] = add_rn(add_rn(mul_rn(a.m[row][0], d.x), mul_rn(a.m[row][1], d.y)),
                    mul_rn(a.m[row][2], d.z));
  }
  return {r[0], r[1], r[2]};
}
CREPUSCULAR_HD Vec3<double> apply_rn(const Affine<double>& a, Vec3<double> p) {
  const Vec3<double> l = apply_linear_rn(a, p);
  return {add_rn(l.x, a.m[0][3]), add_rn(l.y, a.m[1][3]), add_rn(l.z, a.m[2][3])};
}

// floor(x) of a grid index as an int, the same value on host and device for |x| < 2^22. On the
// GPU one round-down addition instead of a conversion: x + 1.5 * 2^23 (float; 1.5 * 2^52 for
// double) has a unit in the last place of 1, so rounding it down leaves floor(x) in the low bits
// of its mantissa. Conversions issue at an eighth of the rate of additions on the H100, and the
// ray marches take three per sample (bench/RESULTS.md, 2026-11-26, fast mode reads the blocking
// volume in runs).
CREPUSCULAR_HD_INLINE int floor_int(float x) {
#ifdef __CUDA_ARCH__
  return __float_as_int(__fadd_rd(x, 12582912.0f)) - 0x4B400000;
#else
  return int(floorf(x));
#endif
}
CREPUSCULAR_HD_INLINE int floor_int(double x) {
#ifdef __CUDA_ARCH__
  return __double2loint(__dadd_rd(x, 6755399441055744.0));
#else
  return int(floor(x));
#endif
}

// Blocking volume b (risk per mm), x fastest. Sampled with trilinear interpolation between voxel
// centres; voxels outside the grid count as 0 (CUDA's border addressing).
// Uniform-space skipping, exact: bricks of 2^kBrickShift voxels per axis; a brick holds the value
// c >= 0 when every voxel it covers, and the next voxel along each axis (the trilinear support,
// 0 beyond the grid), equals c, so a sample whose lower corner lies in it is c without reading
// the volume (trilinear interpolation of equal values is that value, exactly); -1 otherwise.
// Empty space (c = 0: air, fat) and the inside of an organ away from its margin are uniform.
// Empty-space leaping, exact: an empty brick whose every brick within Chebyshev distance d - 1
// (d >= 2, in bricks) is empty too holds -d instead of 0 (kEmptyRunBelow), so that a ray may leap
// over the samples that stay in that cube of empty bricks: their values are 0 exactly.
template <typename Real>
struct BlockingGrid {
  const float* values;
  int nx, ny, nz;
  Affine<Real> physical_to_index;
  const float* bricks;  // may be null: no skipping
  int bx, by, bz;       // bricks per axis
};
constexpr int kBrickShift = 2;
constexpr float kMixedBrick = -1.0f;     // a brick of more than one value
constexpr float kEmptyRunBelow = -1.5f;  // codes below: empty, with empty neighbours (-d, d >= 2)
constexpr int kMaxEmptyRun = 32;         // the largest d stored

CREPUSCULAR_HD int bricks_along(int n) { return (n + (1 << kBrickShift) - 1) >> kBrickShift; }

// The code of the brick holding a lower corner (i, j, k): c >= 0 uniform, kMixedBrick, or -d
// (empty, and so is every brick within d - 1). Beyond the bricks: kMixedBrick.
template <typename Real>
CREPUSCULAR_HD_INLINE float brick_code(const BlockingGrid<Real>& g, int i, int j, int k) {
  if (!g.bricks) return kMixedBrick;
  // A negative index is a huge unsigned one: one comparison per axis bounds both sides.
  const unsigned bi = unsigned(i) >> kBrickShift, bj = unsigned(j) >> kBrickShift,
                 bk = unsigned(k) >> kBrickShift;
  if (bi >= unsigned(g.bx) || bj >= unsigned(g.by) || bk >= unsigned(g.bz)) return kMixedBrick;
  return g.bricks[(bk * unsigned(g.by) + bj) * unsigned(g.bx) + bi];  // < 2^31 bricks
}

// The value every sample at a lower corner (i, j, k) takes when its brick is uniform, else -1.
template <typename Real>
CREPUSCULAR_HD float uniform_brick(const BlockingGrid<Real>& g, int i, int j, int k) {
  const float code = brick_code(g, i, j, k);
  return code < kEmptyRunBelow ? 0.0f : code;
}

// How many samples after this one a ray may leap when this one's brick code is -d (d >= 2): they
// move the lower corner by at most 2^kBrickShift (d - 1) - 1/100 voxel along every axis, so their
// bricks lie within d - 1 of this one and are empty (the 1/100 voxel covers the rounding of the
// samples' positions). step: the ray's blocking index step per sample; at most n.
template <typename Real>
CREPUSCULAR_HD_INLINE int empty_leap(float code, Vec3<Real> step, int n) {
  const Real step_max = fmax(fabs(step.x), fmax(fabs(step.y), fabs(step.z)));
  const Real reach = Real(-code - 1.0f) * Real(1 << kBrickShift) - Real(0.01);
  return reach < Real(n) * step_max ? int(reach / step_max) : n;
}

// Tumor mask (0/1), x fastest, looked up at the nearest voxel. [lo, hi] is the index bounding box
// of the tumor voxels.
// Leaping, exact: `leap` (may be null: every sample looked up in the mask) holds one byte per
// voxel of the box [lo, hi] (x fastest): kTumorLeapInside when the voxel is tumor, plus its
// Chebyshev distance d (1..kMaxTumorLeap) to the nearest voxel of the other kind (voxels outside
// the box are not tumor). Every voxel within d - 1 of it is of its kind, so a ray walks over the
// samples that stay in that cube without looking at them: outside the tumor they are outside,
// inside they are inside (and counted).
template <typename Real>
struct TumorGrid {
  const uint8_t* mask;
  int nx, ny, nz;
  Affine<Real> physical_to_index;
  int lo[3], hi[3];
  const uint8_t* leap = nullptr;
};
constexpr uint8_t kTumorLeapInside = 0x80u;
constexpr int kMaxTumorLeap = 0x7f;

// One tumor surface voxel (a tumor voxel with a 6-neighbour outside the tumor).
template <typename Real>
struct SurfacePoint {
  Vec3<Real> position;  // voxel centre, LPS mm
  Vec3<Real> normal;    // outward unit normal (docs/ARCHITECTURE.md §4); zero when undefined
  int offset;           // linear offset of its voxel in the tumor mask
  // Surface points this one stands for (fast mode's representatives of a block of the surface;
  // 1 in exact mode): its ray counts `weight` times in every value.
  int weight = 1;
};

// Everything a pass needs, passed by value to kernels. Real is the precision of blocking samples
// and sums; the tumor, its surface points and the ray geometry are always double.
template <typename Real>
struct PathSafetyScene {
  BlockingGrid<Real> blocking;
  TumorGrid<double> tumor;
  const SurfacePoint<double>* surface;
  int surface_count;
  Real gamma;  // sampling step bound, mm (h / 2)
  Real eps;    // insignificant blocking for SVV (integral of b, dimensionless)
  Real s2;     // s_T^2 = (tumor voxel volume)^(2/3), mm^2
  // Blocking samples per quadrature point: 1, every sample x_k (the definition, exact mode);
  // fast mode may take runs of `blocking_stride` samples at their midpoints (combine_ray), the
  // tumor's occupancy still looked up at every sample.
  int blocking_stride = 1;
};

// ---------------------------------------------------------------------------------------------
// Sampling

template <typename Real>
CREPUSCULAR_HD float blocking_at_index(const BlockingGrid<Real>& g, int i, int j, int k) {
  if (i < 0 || j < 0 || k < 0 || i >= g.nx || j >= g.ny || k >= g.nz) return 0.0f;
  return g.values[(int64_t(k) * g.ny + j) * g.nx + i];
}

// Trilinear interpolation at a continuous index (voxel centres at integers), zero outside.
// Without looking at the bricks.
template <typename Real>
CREPUSCULAR_HD_INLINE Real trilinear_blocking(const BlockingGrid<Real>& g, Vec3<Real> q) {
  const Real fx = floor(q.x), fy = floor(q.y), fz = floor(q.z);
  const int i = int(fx), j = int(fy), k = int(fz);
  const Real wx = q.x - fx, wy = q.y - fy, wz = q.z - fz;
  if (i >= 0 && j >= 0 && k >= 0 && i + 1 < g.nx && j + 1 < g.ny && k + 1 < g.nz) {
    const int64_t sx = 1, sy = g.nx, sz = int64_t(g.nx) * g.ny;
    const float* v = g.values + (k * sz + j * sy + i);
    const Real c00 = v[0] + wx * (Real(v[sx]) - v[0]);
    const Real c10 = v[sy] + wx * (Real(v[sy + sx]) - v[sy]);
    const Real c01 = v[sz] + wx * (Real(v[sz + sx]) - v[sz]);
    const Real c11 = v[sz + sy] + wx * (Real(v[sz + sy + sx]) - v[sz + sy]);
    const Real c0 = c00 + wy * (c10 - c00);
    const Real c1 = c01 + wy * (c11 - c01);
    return c0 + wz * (c1 - c0);
  }
  if (i < -1 || j < -1 || k < -1 || i >= g.nx || j >= g.ny || k >= g.nz) return Real(0);
  const Real c00 = blocking_at_index(g, i, j, k) +
                   wx * (Real(blocking_at_index(g, i + 1, j, k)) - blocking_at_index(g, i, j, k));
  const Real c10 =
      blocking_at_index(g, i, j + 1, k) +
      wx * (Real(blocking_at_index(g, i + 1, j + 1, k)) - blocking_at_index(g, i, j + 1, k));
  const Real c01 =
      blocking_at_index(g, i, j, k + 1) +
      wx * (Real(blocking_at_index(g, i + 1, j, k + 1)) - blocking_at_index(g, i, j, k + 1));
  const Real c11 = blocking_at_index(g, i, j + 1, k + 1) +
                   wx * (Real(blocking_at_index(g, i + 1, j + 1, k + 1)) -
                         blocking_at_index(g, i, j + 1, k + 1));
  const Real c0 = c00 + wy * (c10 - c00);
  const Real c1 = c01 + wy * (c11 - c01);
  return c0 + wz * (c1 - c0);
}

template <typename Real>
CREPUSCULAR_HD_INLINE Real sample_blocking(const BlockingGrid<Real>& g, Vec3<Real> q) {
  const float uniform = uniform_brick(g, floor_int(q.x), floor_int(q.y), floor_int(q.z));
  if (uniform >= 0.0f) return Real(uniform);
  return trilinear_blocking(g, q);
}

// Tumor lookups take the voxel nearest to a continuous tumor index r. A point on a face between two
// voxels belongs to the lower one: the tie is broken by 1e-10 voxel, far above rounding noise
// (1e-12 at index 4096), so that it does not depend on where the grid's origin lies. Ties are
// common where the tumor lies on the output lattice (a resampled tumor, docs/ARCHITECTURE.md §4):
// samples every h/2 along an axis land on faces. The voxel is floor(r + kHalfBelowTies) per axis.
constexpr double kHalfBelowTies = 0.5 - 1e-10;

// Offset of the tumor voxel at the shifted point r + kHalfBelowTies, or -1 when that voxel is
// outside the grid or not tumor. A ray shifts its origin once (shift_for_ties), not every sample.
CREPUSCULAR_HD int tumor_offset_at_shifted(const TumorGrid<double>& g, Vec3<double> shifted) {
  const int i = floor_int(shifted.x), j = floor_int(shifted.y), k = floor_int(shifted.z);
  // Below lo wraps to a huge unsigned: one comparison per axis bounds both sides.
  if (unsigned(i - g.lo[0]) > unsigned(g.hi[0] - g.lo[0]) ||
      unsigned(j - g.lo[1]) > unsigned(g.hi[1] - g.lo[1]) ||
      unsigned(k - g.lo[2]) > unsigned(g.hi[2] - g.lo[2]))
    return -1;
  const int offset = (k * g.ny + j) * g.nx + i;
  return g.mask[offset] ? offset : -1;
}

// The same lookup with the leap of its voxel (TumorGrid::leap): how many voxels around it, d - 1
// along every axis, are of its kind. kLeaps false: the mask itself, leap 1 (no leap), for a grid
// without leaps; true: the leaps alone (TumorGrid::leap is set), the mask not read. Leap 1
// outside the box.
template <bool kLeaps>
CREPUSCULAR_HD_INLINE int tumor_offset_and_leap(const TumorGrid<double>& g, Vec3<double> shifted,
                                                int& leap) {
  leap = 1;
  const int i = floor_int(shifted.x), j = floor_int(shifted.y), k = floor_int(shifted.z);
  const unsigned bi = unsigned(i - g.lo[0]), bj = unsigned(j - g.lo[1]),
                 bk = unsigned(k - g.lo[2]);
  const unsigned mx = unsigned(g.hi[0] - g.lo[0]), my = unsigned(g.hi[1] - g.lo[1]),
                 mz = unsigned(g.hi[2] - g.lo[2]);
  if (bi > mx || bj > my || bk > mz) return -1;
  const int offset = (k * g.ny + j) * g.nx + i;
  if constexpr (!kLeaps) {
    return g.mask[offset] ? offset : -1;
  } else {
    const uint8_t code = g.leap[(bk * (my + 1u) + bj) * (mx + 1u) + bi];
    leap = code & uint8_t(kMaxTumorLeap);
    return (code & kTumorLeapInside) ? offset : -1;
  }
}

// Samples a walk may pass over after one whose voxel has leap d (> 1): they move the nearest voxel
// by less than d - 1 along every axis (a hundredth of a voxel covers the rounding of their
// positions, and of this product in float: a relative 1e-7 of at most 127 voxels), so they stay
// in its cube. inv_step: 1 / the walk's largest index step per sample along an axis. Capped at
// 10^9 (tiny steps: a point a millionth of a step from t), which passes every sample of a walk.
CREPUSCULAR_HD_INLINE int tumor_leap_samples(int leap, float inv_step) {
  const float samples = (float(leap) - 1.01f) * inv_step;
  return samples < 1e9f ? int(samples) : 1000000000;
}

CREPUSCULAR_HD Vec3<double> shift_for_ties(Vec3<double> r) {
  return {add_rn(r.x, kHalfBelowTies), add_rn(r.y, kHalfBelowTies), add_rn(r.z, kHalfBelowTies)};
}

// Offset of the tumor voxel nearest to r, or -1 when that voxel is outside the grid or not tumor.
CREPUSCULAR_HD int tumor_offset_at(const TumorGrid<double>& g, Vec3<double> r) {
  return tumor_offset_at_shifted(g, shift_for_ties(r));
}

// ---------------------------------------------------------------------------------------------
// One ray p -> t: N = ceil(|t-p| / gamma), l = |t-p| / N, x_k = p + k (t-p) / N, k = 1..N.

template <typename Real>
struct RayGeometry {
  Vec3<Real> q0, dq;      // blocking index of p, and its step per sample
  Vec3<double> r0, dr;    // tumor index of p, and its step per sample
  int n;                  // N samples; 0 when p coincides with t
  Real step;              // l, mm
  Real cos_alpha;         // |cos| of the angle between the ray and t's normal
};

// The ray from p to t. Its geometry is computed in double with identical rounding on every
// backend (sample count, tumor occupancy); only the blocking index is taken to Real.
template <typename Real>
CREPUSCULAR_HD RayGeometry<Real> make_ray(const PathSafetyScene<Real>& s, Vec3<double> p,
                                          const SurfacePoint<double>& t) {
  RayGeometry<Real> ray;
  const Vec3<double> d = t.position - p;
  const double dist = sqrt(dot_rn(d, d));
  const double gamma = double(s.gamma);
  // Points closer than a millionth of a step coincide (rounding of the grids' transforms).
  ray.n = dist > 1e-6 * gamma ? int(ceil(dist / gamma)) : 0;
  const double step = ray.n > 0 ? dist / double(ray.n) : 0.0;
  const double inv_n = ray.n > 0 ? 1.0 / double(ray.n) : 0.0;
  const Vec3<double> dn = {mul_rn(d.x, inv_n), mul_rn(d.y, inv_n), mul_rn(d.z, inv_n)};
  ray.step = Real(step);
  ray.q0 = s.blocking.physical_to_index.apply(vec_cast<Real>(p));
  ray.dq = s.blocking.physical_to_index.apply_linear(vec_cast<Real>(dn));
  ray.r0 = apply_rn(s.tumor.physical_to_index, p);
  ray.dr = apply_linear_rn(s.tumor.physical_to_index, dn);
  // A zero normal (a blob too small to have a gradient) has no preferred direction: |cos| = 1.
  const bool has_normal = dot(t.normal, t.normal) > 0.0;
  ray.cos_alpha = Real((dist > 0.0 && has_normal) ? fabs(dot(d, t.normal)) / dist : 1.0);
  return ray;
}

template <typename Real>
CREPUSCULAR_HD Vec3<Real> along(Vec3<Real> origin, Vec3<Real> step, Real k) {
  return {origin.x + k * step.x, origin.y + k * step.y, origin.z + k * step.z};
}

// Range of k (real valued) for which origin + k step lies inside the box [lo - 1, hi + 1]; the box
// is one voxel wider than the tumor so that rounding never misses a tumor voxel.
template <typename Real>
CREPUSCULAR_HD void box_range(Vec3<Real> origin, Vec3<Real> step, const int lo[3], const int hi[3],
                              Real& k_in, Real& k_out) {
  const Real o[3] = {origin.x, origin.y, origin.z};
  const Real d[3] = {step.x, step.y, step.z};
  k_in = Real(-1e30);
  k_out = Real(1e30);
  for (int a = 0; a < 3; ++a) {
    const Real a_lo = Real(lo[a]) - Real(1), a_hi = Real(hi[a]) + Real(1);
    if (d[a] == Real(0)) {
      if (o[a] < a_lo || o[a] > a_hi) {
        k_in = Real(1);
        k_out = Real(0);
      }
      continue;
    }
    // One division per axis (a ray's fixed cost counts on the GPU); the box's extra voxel
    // absorbs the rounding of the product.
    const Real inv = Real(1) / d[a];
    Real k0 = (a_lo - o[a]) * inv, k1 = (a_hi - o[a]) * inv;
    if (k0 > k1) {
      const Real tmp = k0;
      k0 = k1;
      k1 = tmp;
    }
    k_in = k0 > k_in ? k0 : k_in;
    k_out = k1 < k_out ? k1 : k_out;
  }
}

// Tumor occupancy along one ray (docs/ARCHITECTURE.md §4): is t front-facing from p, is it
// back-facing, and how many samples k <= N lie in the tumor (the chord is that count times l). The
// chord is needed only where t is back-facing (IVBV): a ray that is neither front- nor back-facing
// (nor asked about back-facing) contributes nothing, and its walk stops where it sees another tumor
// voxel, leaving samples_in_tumor a partial count.
struct TumorCrossing {
  bool front_facing;
  bool back_facing;
  int samples_in_tumor;
};

// The walk of cross_tumor, with the grid's leaps (kLeaps: TumorGrid::leap is set) or without.
template <bool kLeaps, typename Real>
CREPUSCULAR_HD_INLINE TumorCrossing walk_tumor(const TumorGrid<double>& g,
                                               const RayGeometry<Real>& ray, int own_offset,
                                               bool want_back) {
  TumorCrossing c{true, true, 0};
  double k_in, k_out;
  box_range(ray.r0, ray.dr, g.lo, g.hi, k_in, k_out);
  // Samples at shifted0 + k dr: the tie's half voxel added to the origin once, not per sample
  // (rounded differently by far less than the tie's 1e-10 voxel; the same on every backend).
  const Vec3<double> shifted0 = shift_for_ties(ray.r0);
  // Leaps (TumorGrid::leap) over the samples whose voxels are known to be of the kind of the one
  // just looked up: never from t's own voxel, so that leapt samples never decide front-facing.
  // The same occupancy as looking at every sample (test: TumorLeapsGiveTheWalkOfEverySample).
  float inv_step = 0.0f;
  if constexpr (kLeaps) {
    const double step_max = fmax(fabs(ray.dr.x), fmax(fabs(ray.dr.y), fabs(ray.dr.z)));
    inv_step = step_max > 0.0 ? float(1.0 / step_max) : 0.0f;
  }
  if (want_back) {
    // Beyond t with the same step, walked first: where t is not back-facing, the walk toward p
    // below may stop at the first other tumor voxel it meets. Only when p lies within a small
    // fraction of a voxel of t is that step so tiny (< 1/100 voxel) that samples 1/100 voxel
    // apart stand in for it, which see the same voxels at a bounded cost (and are never leapt
    // over: their positions are sums).
    double stride = 1.0;
    const double step_sq = dot_rn(ray.dr, ray.dr);  // the root only where it is needed
    if (step_sq < 1e-4) stride = 0.01 / sqrt(step_sq);
    for (double k = double(ray.n) + stride; k <= k_out; k = add_rn(k, stride)) {
      int leap;
      const int off = tumor_offset_and_leap<kLeaps>(g, along_rn(shifted0, ray.dr, k), leap);
      if (off >= 0 && off != own_offset) {
        c.back_facing = false;
        break;
      }
      if constexpr (kLeaps) {
        if (off < 0 && leap > 1 && stride == 1.0) k += double(tumor_leap_samples(leap, inv_step));
      }
    }
  }
  const bool chord_needed = want_back && c.back_facing;
  int k_first = k_in < 1.0 ? 1 : int(floor(k_in));
  if (k_first < 1) k_first = 1;
  const int k_last = k_out > 2e9 ? 2000000000 : int(ceil(k_out));
  const int k_end = ray.n < k_last ? ray.n : k_last;
  double kd = double(k_first) - 1.0;  // k as a double, counted rather than converted (exact)
  for (int k = k_first; k <= k_end; ++k) {
    kd += 1.0;
    int leap;
    const int off = tumor_offset_and_leap<kLeaps>(g, along_rn(shifted0, ray.dr, kd), leap);
    if (off >= 0) {
      ++c.samples_in_tumor;
      if (off != own_offset && k < ray.n) {
        c.front_facing = false;
        if (!chord_needed) return c;  // nothing more of this walk is used
      }
    }
    if constexpr (kLeaps) {
      if (leap > 1 && off != own_offset) {
        int skip = tumor_leap_samples(leap, inv_step);
        if (skip > k_end - k) skip = k_end - k;
        if (off >= 0) c.samples_in_tumor += skip;
        k += skip;
        kd += double(skip);
      }
    }
  }
  return c;
}

template <typename Real>
CREPUSCULAR_HD TumorCrossing cross_tumor(const TumorGrid<double>& g, const RayGeometry<Real>& ray,
                                         int own_offset, bool want_back) {
  if (ray.n == 0) {  // p is t's centre: nothing in front, no direction to look behind
    return TumorCrossing{true, false, 1};
  }
  return g.leap ? walk_tumor<true>(g, ray, own_offset, want_back)
                : walk_tumor<false>(g, ray, own_offset, want_back);
}

// ---------------------------------------------------------------------------------------------
// The four values as ACCUMULATEVALUE / COMBINEVALUES / FINALIZEVALUE of Algorithm 1.
// accumulate: one blocking sample b_k of a ray; combine: one finished ray into the voxel's state;
// finalize: the voxel's value.

template <typename Real>
struct RaySample {
  Real b;      // b(x_k), risk per mm
  Real step;   // l, mm
  Real k;      // 1..N (exact: N < 2^24)
  Real inv_n;  // 1 / N
};

template <typename Real>
struct RayContext {
  TumorCrossing crossing;
  Real step;       // l, mm
  Real cos_alpha;  // |cos alpha_t|
  Real eps;
  int weight = 1;  // surface points the ray stands for (SurfacePoint::weight)
};

// The ray state of SVV, ISBV and IVBV: the line integral L(p, t) = sum_k b(x_k) l. One
// accumulation serves the three (combine_ray).
template <typename Real>
struct LineIntegral {
  Real line_integral = 0;
};

// SVV = 100 |{t in F(p) : L(p,t) <= eps}| / |F(p)|, 0 when F(p) is empty.
template <typename Real>
struct SurfaceVisibility {
  static constexpr unsigned kBit = kSvv;
  static constexpr bool kFront = true, kBack = false;
  using Ray = LineIntegral<Real>;
  struct Voxel {
    int visible = 0, clear = 0;
  };
  static CREPUSCULAR_HD void accumulate(Ray& r, const RaySample<Real>& s) {
    r.line_integral += s.b * s.step;
  }
  static CREPUSCULAR_HD void combine(Voxel& v, const Ray& r, const RayContext<Real>& c) {
    if (!c.crossing.front_facing) return;
    v.visible += c.weight;
    if (r.line_integral <= c.eps) v.clear += c.weight;
  }
  static CREPUSCULAR_HD Real finalize(const Voxel& v, Real /*s2*/) {
    return v.visible > 0 ? Real(100) * Real(v.clear) / Real(v.visible) : Real(0);
  }
};

// ISBV = sum over t in F(p) of L(p,t) s_T^2.
template <typename Real>
struct IntegralSurfaceBlocking {
  static constexpr unsigned kBit = kIsbv;
  static constexpr bool kFront = true, kBack = false;
  using Ray = LineIntegral<Real>;
  struct Voxel {
    Real sum = 0;
  };
  static CREPUSCULAR_HD void accumulate(Ray& r, const RaySample<Real>& s) {
    r.line_integral += s.b * s.step;
  }
  static CREPUSCULAR_HD void combine(Voxel& v, const Ray& r, const RayContext<Real>& c) {
    if (c.crossing.front_facing) v.sum += Real(c.weight) * r.line_integral;
  }
  static CREPUSCULAR_HD Real finalize(const Voxel& v, Real s2) { return v.sum * s2; }
};

// IVBV = sum over t in B(p) of L(p,t) c(p,t) s_T^2, c = l * (samples k <= N inside T).
template <typename Real>
struct IntegralVolumeBlocking {
  static constexpr unsigned kBit = kIvbv;
  static constexpr bool kFront = false, kBack = true;
  using Ray = LineIntegral<Real>;
  struct Voxel {
    Real sum = 0;
  };
  static CREPUSCULAR_HD void accumulate(Ray& r, const RaySample<Real>& s) {
    r.line_integral += s.b * s.step;
  }
  static CREPUSCULAR_HD void combine(Voxel& v, const Ray& r, const RayContext<Real>& c) {
    if (c.crossing.back_facing)
      v.sum += Real(c.weight) * r.line_integral * (c.step * Real(c.crossing.samples_in_tumor));
  }
  static CREPUSCULAR_HD Real finalize(const Voxel& v, Real s2) { return v.sum * s2; }
};

// BVV = sum over t in B(p) of sum_k b(x_k) s_T^2 |cos alpha_t| (k/N)^2 l   (paper eq. 13-14).
template <typename Real>
struct BlockerVolume {
  static constexpr unsigned kBit = kBvv;
  static constexpr bool kFront = false, kBack = true;
  struct Ray {
    Real weighted = 0;  // sum_k b_k (k/N)^2 l; while marching, sum_k b_k k^2 (close)
  };
  struct Voxel {
    Real sum = 0;
  };
  static CREPUSCULAR_HD void accumulate(Ray& r, const RaySample<Real>& s) {
    r.weighted += s.b * (s.k * s.k);
  }
  // The ray's end: its factor (1/N)^2 l, taken once instead of at every sample.
  static CREPUSCULAR_HD void close(Ray& r, Real inv_n, Real step) {
    r.weighted *= inv_n * inv_n * step;
  }
  static CREPUSCULAR_HD void combine(Voxel& v, const Ray& r, const RayContext<Real>& c) {
    if (c.crossing.back_facing) v.sum += Real(c.weight) * c.cos_alpha * r.weighted;
  }
  static CREPUSCULAR_HD Real finalize(const Voxel& v, Real s2) { return v.sum * s2; }
};

// The per-voxel state of all four values (COMBINEVALUES' accumulator), for passes that visit a
// voxel once per surface point (fast mode) rather than all at once.
template <typename Real>
struct VoxelState {
  typename SurfaceVisibility<Real>::Voxel svv;
  typename IntegralSurfaceBlocking<Real>::Voxel isbv;
  typename IntegralVolumeBlocking<Real>::Voxel ivbv;
  typename BlockerVolume<Real>::Voxel bvv;
};

// FINALIZEVALUE of every requested value into out[value_slot(bit)].
template <typename Real>
CREPUSCULAR_HD void finalize_values(const VoxelState<Real>& v, unsigned values, Real s2,
                                    float* out) {
  if (values & kSvv) out[0] = float(SurfaceVisibility<Real>::finalize(v.svv, s2));
  if (values & kIsbv) out[1] = float(IntegralSurfaceBlocking<Real>::finalize(v.isbv, s2));
  if (values & kIvbv) out[2] = float(IntegralVolumeBlocking<Real>::finalize(v.ivbv, s2));
  if (values & kBvv) out[3] = float(BlockerVolume<Real>::finalize(v.bvv, s2));
}

// ---------------------------------------------------------------------------------------------
// COMPUTEACCESSIBILITY for one output voxel centre p (LPS mm): casts a ray to every surface point,
// combines, finalizes. Writes out[value_slot(bit)] for every bit in Values; other slots untouched.

// The blocking sampler of the exact definition: trilinear in Real precision over the grid.
template <typename Real>
struct GridSampler {
  BlockingGrid<Real> grid;
  CREPUSCULAR_HD_INLINE Real operator()(Vec3<Real> q) const { return sample_blocking(grid, q); }
  // The sample where its brick is mixed (combine_ray has looked at the brick).
  CREPUSCULAR_HD_INLINE Real mixed(Vec3<Real> q) const { return trilinear_blocking(grid, q); }
};

// What a sampler adds to a blocking index (its member kShift; 0 without one): combine_ray adds it
// to a ray's origin once, so the sampler takes shifted coordinates. A sampler with a shift is
// used with kMarchEverySample only (it reads no brick codes at blocking indices).
template <typename Sampler, typename = void>
struct SamplerShift {
  static constexpr float value = 0.0f;
};
template <typename Sampler>
struct SamplerShift<Sampler, std::void_t<decltype(Sampler::kShift)>> {
  static constexpr float value = Sampler::kShift;
};

// How a ray crosses empty space: leaping over the samples in a cube of empty bricks
// (kLeapEmptySpace), or sampling each (kMarchEverySample: the sampler maps every brick code to its
// value). The values are the same bits either way.
enum EmptySpace { kLeapEmptySpace, kMarchEverySample };

// The blocking samples origin + k step, k = 1..n, each handed to visit(b, k) (k as a Real):
// every one sampled (kMarchEverySample), or uniform bricks read from their code and the samples
// in a cube of empty bricks leapt over (kLeapEmptySpace; they are 0 and not visited). The same
// values either way.
template <EmptySpace Empty, typename Real, typename Sampler, typename Visit>
CREPUSCULAR_HD_INLINE void march_samples(const BlockingGrid<Real>& g, const Sampler& blocking_at,
                                         Vec3<Real> origin, Vec3<Real> step, int n,
                                         const Visit& visit) {
  // k as a Real is counted alongside k rather than converted (exact below 2^24 samples; the
  // conversion is the march's slowest instruction on the GPU).
  Real kr = Real(0);
  if constexpr (Empty == kMarchEverySample) {
    for (int k = 1; k <= n; ++k) {
      kr += Real(1);
      visit(Real(blocking_at(along(origin, step, kr))), kr);
    }
  } else {
    for (int k = 1; k <= n; ++k) {
      kr += Real(1);
      const Vec3<Real> q = along(origin, step, kr);
      const float code = brick_code(g, floor_int(q.x), floor_int(q.y), floor_int(q.z));
      Real b;
      if (code >= 0.0f) {
        b = Real(code);
      } else if (code < kEmptyRunBelow) {  // 0 here and at the samples leapt over: nothing to add
        k += empty_leap(code, step, n);
        kr = Real(k);
        continue;
      } else {
        b = Real(blocking_at.mixed(q));
      }
      visit(b, kr);
    }
  }
}

// COMBINEVALUES of the ray from p to one surface point into a voxel's state.
// Sampler: mixed(q), the sample at blocking index q where its brick holds more than one value
// (uniform bricks are read here, empty ones leapt over), and operator()(q), any sample
// (kMarchEverySample); the CUDA backend may pass a texture sampler. Every sample takes the value
// sample_blocking gives it: results do not depend on the bricks.
template <typename Real, unsigned Values, typename Sampler, EmptySpace Empty = kLeapEmptySpace>
CREPUSCULAR_HD void combine_ray(VoxelState<Real>& v, const PathSafetyScene<Real>& s,
                                Vec3<double> p, const SurfacePoint<double>& target,
                                const Sampler& blocking_at) {
  using Svv = SurfaceVisibility<Real>;
  using Isbv = IntegralSurfaceBlocking<Real>;
  using Ivbv = IntegralVolumeBlocking<Real>;
  using Bvv = BlockerVolume<Real>;
  constexpr bool kWantFront = (Values & (kSvv | kIsbv)) != 0;
  constexpr bool kWantBack = (Values & (kIvbv | kBvv)) != 0;
  const RayGeometry<Real> ray = make_ray(s, p, target);
  const TumorCrossing crossing = cross_tumor(s.tumor, ray, target.offset, kWantBack);
  if (!((kWantFront && crossing.front_facing) || (kWantBack && crossing.back_facing))) return;

  // SVV, ISBV and IVBV share their ray state and its accumulation (the line integral): done once.
  static_assert(std::is_same_v<typename Svv::Ray, typename Isbv::Ray> &&
                    std::is_same_v<typename Svv::Ray, typename Ivbv::Ray>,
                "one line integral for SVV, ISBV and IVBV");
  constexpr bool kLine = (Values & (kSvv | kIsbv | kIvbv)) != 0;
  typename Svv::Ray line_ray;
  typename Bvv::Ray bvv_ray;
  const Real inv_n = ray.n > 0 ? Real(1) / Real(ray.n) : Real(0);
  const auto accumulate = [&](Real b, Real k) {
    const RaySample<Real> sample{b, ray.step, k, inv_n};
    if constexpr (kLine) Svv::accumulate(line_ray, sample);  // = Isbv's = Ivbv's
    if constexpr ((Values & kBvv) != 0) Bvv::accumulate(bvv_ray, sample);
  };
  // The sampler's coordinates: the blocking index plus its shift (SamplerShift; a texture's
  // voxel centres lie at +0.5), added to the origin once rather than at every sample.
  Vec3<Real> q0 = ray.q0;
  constexpr float kShift = SamplerShift<Sampler>::value;
  if constexpr (kShift != 0.0f) {
    static_assert(Empty == kMarchEverySample, "a shifted sampler reads no brick codes");
    q0 = Vec3<Real>{q0.x + Real(kShift), q0.y + Real(kShift), q0.z + Real(kShift)};
  }
  const int stride = s.blocking_stride;
  if (stride <= 1) {
    march_samples<Empty>(s.blocking, blocking_at, q0, ray.dq, ray.n, accumulate);
  } else {
    // Fast mode's quadrature (PathSafetyScene::blocking_stride): the samples k = 1..N taken in
    // runs of `stride`, each run by one sample at its midpoint k_c = stride j - (stride - 1) / 2,
    // weighted by the run's length; the samples after the last whole run one by one, as exact
    // mode takes them. Midpoint rule: a run's error is second order in its length.
    const int runs = ray.n / stride;
    const Real sr = Real(stride), half = Real(stride - 1) * Real(0.5);
    const RaySample<Real> run_sample{Real(0), ray.step * sr, Real(0), inv_n};
    typename Bvv::Ray bvv_runs;
    const auto accumulate_run = [&](Real b, Real j) {
      RaySample<Real> sample = run_sample;
      sample.b = b;
      sample.k = sr * j - half;
      if constexpr (kLine) Svv::accumulate(line_ray, sample);
      if constexpr ((Values & kBvv) != 0) Bvv::accumulate(bvv_runs, sample);
    };
    const Vec3<Real> dq_run = {ray.dq.x * sr, ray.dq.y * sr, ray.dq.z * sr};
    march_samples<Empty>(s.blocking, blocking_at, along(q0, ray.dq, -half), dq_run, runs,
                         accumulate_run);
    if constexpr ((Values & kBvv) != 0) bvv_ray.weighted = bvv_runs.weighted * sr;
    Real kr = Real(runs) * sr;
    for (int k = runs * stride + 1; k <= ray.n; ++k) {
      kr += Real(1);
      accumulate(Real(blocking_at(along(q0, ray.dq, kr))), kr);
    }
  }
  if constexpr ((Values & kBvv) != 0) Bvv::close(bvv_ray, inv_n, ray.step);
  const RayContext<Real> context{crossing, ray.step, ray.cos_alpha, s.eps, target.weight};
  if constexpr ((Values & kSvv) != 0) Svv::combine(v.svv, line_ray, context);
  if constexpr ((Values & kIsbv) != 0) Isbv::combine(v.isbv, line_ray, context);
  if constexpr ((Values & kIvbv) != 0) Ivbv::combine(v.ivbv, line_ray, context);
  if constexpr ((Values & kBvv) != 0) Bvv::combine(v.bvv, bvv_ray, context);
}

// The state of two disjoint sets of rays of one voxel, combined into `a`.
template <typename Real>
CREPUSCULAR_HD void add_state(VoxelState<Real>& a, const VoxelState<Real>& b) {
  a.svv.visible += b.svv.visible;
  a.svv.clear += b.svv.clear;
  a.isbv.sum += b.isbv.sum;
  a.ivbv.sum += b.ivbv.sum;
  a.bvv.sum += b.bvv.sum;
}

template <typename Real, unsigned Values, typename Sampler, EmptySpace Empty = kLeapEmptySpace>
CREPUSCULAR_HD void path_safety_at(const PathSafetyScene<Real>& s, Vec3<double> p, float* out,
                                   const Sampler& blocking_at) {
  VoxelState<Real> state;
  for (int t = 0; t < s.surface_count; ++t) {
    combine_ray<Real, Values, Sampler, Empty>(state, s, p, s.surface[t], blocking_at);
  }
  finalize_values(state, Values, s.s2, out);
}

template <typename Real, unsigned Values>
CREPUSCULAR_HD void path_safety_at(const PathSafetyScene<Real>& s, Vec3<double> p, float* out) {
  path_safety_at<Real, Values>(s, p, out, GridSampler<Real>{s.blocking});
}

}  // namespace crepuscular::kernels
