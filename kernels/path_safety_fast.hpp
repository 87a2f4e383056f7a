// Fast mode of the path safety values: rays are cast outward from each tumor surface point once,
// on an octahedral grid of directions fine enough that neighbouring rays are at most about one
// output voxel apart at the edge of the region of interest. Each ray stores its running integrals
// of b (and the moments BVV needs) at every output spacing, and whether the tumor hides t in that
// direction. Every output voxel then looks its rays up by direction and distance instead of
// marching them. The values are combined and finalized by the same functions as exact mode
// (kernels/path_safety_math.hpp). Host/device, plain structs.
#pragma once

#include "kernels/path_safety_math.hpp"

namespace crepuscular::kernels {

// Octahedral map: unit direction <-> (u, v) in [-1, 1]^2.
template <typename Real>
CREPUSCULAR_HD void octahedral_encode(Vec3<Real> d, Real& u, Real& v) {
  const Real n = fabs(d.x) + fabs(d.y) + fabs(d.z);
  Real x = d.x / n, y = d.y / n;
  if (d.z < Real(0)) {
    const Real ox = x, oy = y;
    x = (Real(1) - fabs(oy)) * (ox >= Real(0) ? Real(1) : Real(-1));
    y = (Real(1) - fabs(ox)) * (oy >= Real(0) ? Real(1) : Real(-1));
  }
  u = x;
  v = y;
}

template <typename Real>
CREPUSCULAR_HD Vec3<Real> octahedral_decode(Real u, Real v) {
  Vec3<Real> d = {u, v, Real(1) - fabs(u) - fabs(v)};
  if (d.z < Real(0)) {
    const Real ox = d.x, oy = d.y;
    d.x = (Real(1) - fabs(oy)) * (ox >= Real(0) ? Real(1) : Real(-1));
    d.y = (Real(1) - fabs(ox)) * (oy >= Real(0) ? Real(1) : Real(-1));
  }
  const Real len = sqrt(dot(d, d));
  return {d.x / len, d.y / len, d.z / len};
}

// Flags of one direction cell.
constexpr uint8_t kFrontFacing = 1u;  // nothing of the tumor between t and a point in this direction
constexpr uint8_t kBackFacing = 2u;   // nothing of the tumor behind t, seen from this direction

// How the ray of one direction cell crosses the tumor (8 bytes: one memory sector per lookup).
struct DirectionCrossing {
  uint16_t first_hit;  // index k of the first sample k gamma toward the point that lies in
                       // another tumor voxel (65535: none)
  uint16_t chord;      // samples in the tumor toward the point, t's own included
  uint16_t last_in;    // index of the last of them
  uint8_t flags;       // kBackFacing
  uint8_t unused;
};

// The rays of one surface point t. Cell (a, b) holds the direction at the centre of octahedral
// cell (a, b) of an m x m map; radial sample j lies at distance j * dr from t. The running
// integrals are stored radius-major ([j * cells + cell]) so that neighbouring voxels, which look
// up neighbouring cells at about the same distance, read neighbouring memory.
template <typename Real>
struct DirectionTable {
  int m;
  int radial;
  int64_t cells;  // m * m
  Real dr;        // mm between stored radial samples (gamma: every sample stored)
  Real gamma;     // mm between blocking samples along a ray (half the output spacing)
  Real refine;    // corner spread of the line integral above which a ray is marched exactly,
                  // plus refine_relative times the value (refine < 0: never); corners that
                  // disagree on facing, or on the side of eps, always are
  Real refine_relative;
  float* c0;      // integral of b from t to distance j dr
  float* c1;      // integral of b s, s = distance from t (BVV only; may be null)
  float* c2;      // integral of b s^2 (BVV only; may be null)
  DirectionCrossing* crossing;  // [cell]
};

// Casts the ray of cell (a, b) from surface point t: samples of b every gamma, stored every dr; tumor occupancy in both directions with the nearest-voxel lookup of exact mode.
template <typename Real, typename Sampler>
CREPUSCULAR_HD void cast_direction(const PathSafetyScene<Real>& s, const SurfacePoint<double>& t,
                                   const DirectionTable<Real>& table, int a, int b,
                                   const Sampler& blocking_at) {
  const Real inv_m = Real(2) / Real(table.m);
  const Vec3<Real> u =
      octahedral_decode((Real(a) + Real(0.5)) * inv_m - Real(1), (Real(b) + Real(0.5)) * inv_m - Real(1));
  const int64_t cell = int64_t(b) * table.m + a;

  // Tumor occupancy: forward (toward the point) for front-facing and chord, backward for
  // back-facing, one sample every gamma until the ray leaves the tumor's box.
  const Vec3<Real> du = {u.x * table.gamma, u.y * table.gamma, u.z * table.gamma};
  const Vec3<double> r0 = apply_rn(s.tumor.physical_to_index, t.position);
  const Vec3<double> dr = apply_linear_rn(s.tumor.physical_to_index, vec_cast<double>(du));
  uint8_t flags = kBackFacing;
  int chord = 1, first_hit = 65535, last_in = 0;
  for (int dir = 1; dir >= -1; dir -= 2) {
    const Vec3<double> step = {dr.x * dir, dr.y * dir, dr.z * dir};
    double k_in, k_out;
    box_range(r0, step, s.tumor.lo, s.tumor.hi, k_in, k_out);
    const int k_last = k_out > 60000.0 ? 60000 : int(ceil(k_out));
    for (int k = 1; k <= k_last; ++k) {
      const int off = tumor_offset_at(s.tumor, along_rn(r0, step, double(k)));
      if (off < 0) continue;
      if (dir > 0) {
        ++chord;
        last_in = k;
        if (off != t.offset && first_hit == 65535) first_hit = k;
      } else if (off != t.offset) {
        flags = 0;
        break;
      }
    }
  }
  table.crossing[cell] = {uint16_t(first_hit), uint16_t(chord), uint16_t(last_in), flags, 0};

  // Running integrals along the ray with the samples of exact mode seen from t: b at t, then
  // every gamma outward (exact mode sums x_1..x_N, which from t's side are s = 0, l, .., D - l).
  const Vec3<Real> q0 = s.blocking.physical_to_index.apply(vec_cast<Real>(t.position));
  const Vec3<Real> dq = s.blocking.physical_to_index.apply_linear(du);
  const int per_store = int(table.dr / table.gamma + Real(0.5));
  Real c0 = 0, c1 = 0, c2 = 0;
  const int64_t stride = table.cells;
  float* out0 = table.c0 + cell;
  float* out1 = table.c1 ? table.c1 + cell : nullptr;
  float* out2 = table.c2 ? table.c2 + cell : nullptr;
  out0[0] = 0.0f;
  if (out1) out1[0] = out2[0] = 0.0f;
  int k = 0;
  for (int j = 1; j < table.radial; ++j) {
    for (int sub = 0; sub < per_store; ++sub, ++k) {
      const Real dist = Real(k) * table.gamma;
      const Real bval = Real(blocking_at(along(q0, dq, Real(k)))) * table.gamma;
      c0 += bval;
      c1 += bval * dist;
      c2 += bval * dist * dist;
    }
    out0[j * stride] = float(c0);
    if (out1) {
      out1[j * stride] = float(c1);
      out2[j * stride] = float(c2);
    }
  }
}

// Continuous cell coordinates of a direction, and the wrap of the octahedral map's outer edges
// (the fold: (-1, v) meets (-1, -v)) so that bilinear lookups are continuous across them.
template <typename Real>
CREPUSCULAR_HD void wrap_cell(int m, int& a, int& b) {
  if (a < 0) {
    a = 0;
    b = m - 1 - b;
  } else if (a >= m) {
    a = m - 1;
    b = m - 1 - b;
  }
  if (b < 0) {
    b = 0;
    a = m - 1 - a;
  } else if (b >= m) {
    b = m - 1;
    a = m - 1 - a;
  }
}

// One ray value looked up at (cell corners a0..a0+1, b0..b0+1, radial position x).
// `lowest` and `highest`, when given, receive the extremes of the four cells' values.
template <typename Real>
CREPUSCULAR_HD Real lookup_radial(const float* c, const DirectionTable<Real>& t, const int cells[4],
                                  const Real w[4], int j, Real fj, Real* lowest = nullptr,
                                  Real* highest = nullptr) {
  Real v = 0, lo_v = Real(3e38), hi_v = Real(-3e38);
  const float* lo = c + int64_t(j) * t.cells;
  const float* hi = lo + t.cells;
  for (int n = 0; n < 4; ++n) {
    const Real a = lo[cells[n]];
    const Real corner = a + fj * (Real(hi[cells[n]]) - a);
    v += w[n] * corner;
    lo_v = corner < lo_v ? corner : lo_v;
    hi_v = corner > hi_v ? corner : hi_v;
  }
  if (lowest) *lowest = lo_v;
  if (highest) *highest = hi_v;
  return v;
}

// COMBINEVALUES of the ray from p to t marched as exact mode marches it (DESIGN.md §4).
template <typename Real, unsigned Values>
CREPUSCULAR_HD void combine_exact_ray(VoxelState<Real>& state, const PathSafetyScene<Real>& s,
                                      const SurfacePoint<double>& t, Vec3<Real> p) {
  constexpr bool kWantBack = (Values & (kIvbv | kBvv)) != 0;
  const RayGeometry<Real> ray = make_ray(s, vec_cast<double>(p), t);
  const TumorCrossing crossing = cross_tumor(s.tumor, ray, t.offset, kWantBack);
  const bool front = (Values & (kSvv | kIsbv)) != 0 && crossing.front_facing;
  const bool back = kWantBack && crossing.back_facing;
  if (!front && !back) return;
  const GridSampler<Real> blocking_at{s.blocking};
  Real line = 0, weighted = 0;
  for (int k = 1; k <= ray.n; ++k) {
    const Real b = Real(blocking_at(along(ray.q0, ray.dq, Real(k)))) * ray.step;
    const Real f = Real(k) / Real(ray.n);
    line += b;
    weighted += b * f * f;
  }
  const RayContext<Real> context{crossing, ray.step, ray.cos_alpha, s.eps};
  if constexpr ((Values & kSvv) != 0) SurfaceVisibility<Real>::combine(state.svv, {line}, context);
  if constexpr ((Values & kIsbv) != 0) {
    IntegralSurfaceBlocking<Real>::combine(state.isbv, {line}, context);
  }
  if constexpr ((Values & kIvbv) != 0) {
    IntegralVolumeBlocking<Real>::combine(state.ivbv, {line}, context);
  }
  if constexpr ((Values & kBvv) != 0) BlockerVolume<Real>::combine(state.bvv, {weighted}, context);
}

// COMBINEVALUES of the ray from output voxel p to surface point t, looked up in t's table. Where
// the four direction cells around the ray disagree (on facing, or on the line integral by more
// than table.refine: the ray grazes the edge of a structure or of the tumor) the lookup would be
// a blend of different paths, and the ray is marched exactly instead.
template <typename Real, unsigned Values>
CREPUSCULAR_HD void combine_from_table(VoxelState<Real>& state, const PathSafetyScene<Real>& s,
                                       const SurfacePoint<double>& t,
                                       const DirectionTable<Real>& table, Vec3<Real> p) {
  const Vec3<Real> d = p - vec_cast<Real>(t.position);
  const Real dist = sqrt(dot(d, d));
  TumorCrossing crossing{true, false, 1};
  Real line = 0, weighted = 0, cos_alpha = 1;
  if (dist > Real(0)) {
    const Vec3<Real> u = {d.x / dist, d.y / dist, d.z / dist};
    Real eu, ev;
    octahedral_encode(u, eu, ev);
    const Real x = (eu + Real(1)) * Real(0.5) * Real(table.m) - Real(0.5);
    const Real y = (ev + Real(1)) * Real(0.5) * Real(table.m) - Real(0.5);
    const Real fx = floor(x), fy = floor(y);
    const Real wx = x - fx, wy = y - fy;
    int cells[4];
    Real w[4] = {(1 - wx) * (1 - wy), wx * (1 - wy), (1 - wx) * wy, wx * wy};
    for (int n = 0; n < 4; ++n) {
      int a = int(fx) + (n & 1), b = int(fy) + (n >> 1);
      wrap_cell<Real>(table.m, a, b);
      cells[n] = b * table.m + a;
    }
    // Tumor crossing of the nearest cell, cut at the point: exact mode looks at samples strictly
    // between p and t (s in [l, D - l] from t) for front-facing, and s in [0, D - l] for the chord.
    const int nearest = cells[(wx >= Real(0.5) ? 1 : 0) + (wy >= Real(0.5) ? 2 : 0)];
    const Real reach = (dist - Real(0.5) * table.gamma) / table.gamma;  // last index before p
    if (table.refine >= Real(0)) {
      bool facing_differs = false;
      const DirectionCrossing c0 = table.crossing[cells[0]];
      const bool f0 = Real(c0.first_hit) > reach;
      for (int n = 1; n < 4; ++n) {
        const DirectionCrossing cn = table.crossing[cells[n]];
        facing_differs |= (Real(cn.first_hit) > reach) != f0 ||
                          ((cn.flags ^ c0.flags) & kBackFacing) != 0;
      }
      if (facing_differs) {
        combine_exact_ray<Real, Values>(state, s, t, p);
        return;
      }
    }
    const DirectionCrossing cell = table.crossing[nearest];
    crossing.front_facing = Real(cell.first_hit) > reach;
    crossing.back_facing = (cell.flags & kBackFacing) != 0;
    const int chord = cell.chord;
    crossing.samples_in_tumor =
        Real(cell.last_in) <= reach ? chord : (reach < Real(0) ? 1 : int(reach) + 1);
    if (crossing.samples_in_tumor > chord) crossing.samples_in_tumor = chord;
    const bool front = (Values & (kSvv | kIsbv)) != 0 && crossing.front_facing;
    const bool back = (Values & (kIvbv | kBvv)) != 0 && crossing.back_facing;
    if (!front && !back) return;
    Real rj = dist / table.dr;
    if (rj > Real(table.radial - 1)) rj = Real(table.radial - 1);
    int j = int(floor(rj));
    if (j > table.radial - 2) j = table.radial - 2;
    const Real fj = rj - Real(j);
    Real lowest = 0, highest = 0;
    line = lookup_radial(table.c0, table, cells, w, j, fj, &lowest, &highest);
    // The cells disagree where it matters: on which side of eps the path lies (SVV), or by more
    // than table.refine plus table.refine_relative of the value (a structure's edge, not the
    // texture of the tissue around it).
    const bool straddles_eps = (Values & kSvv) != 0 && lowest <= s.eps && highest > s.eps;
    if (table.refine >= Real(0) &&
        (straddles_eps || highest - lowest > table.refine + table.refine_relative * line)) {
      combine_exact_ray<Real, Values>(state, s, t, p);
      return;
    }
    if ((Values & kBvv) != 0 && back && table.c1) {
      // sum b (1 - s/D)^2 ds = C0 - 2 C1 / D + C2 / D^2, s measured from t.
      const Real c1 = lookup_radial(table.c1, table, cells, w, j, fj);
      const Real c2 = lookup_radial(table.c2, table, cells, w, j, fj);
      weighted = line - Real(2) * c1 / dist + c2 / (dist * dist);
      if (weighted < Real(0)) weighted = Real(0);
    }
    const Vec3<Real> normal = vec_cast<Real>(t.normal);
    const bool has_normal = dot(normal, normal) > Real(0);
    cos_alpha = has_normal ? fabs(dot(u, normal)) : Real(1);
  }
  const RayContext<Real> context{crossing, table.gamma, cos_alpha, s.eps};
  if constexpr ((Values & kSvv) != 0) {
    SurfaceVisibility<Real>::combine(state.svv, {line}, context);
  }
  if constexpr ((Values & kIsbv) != 0) {
    IntegralSurfaceBlocking<Real>::combine(state.isbv, {line}, context);
  }
  if constexpr ((Values & kIvbv) != 0) {
    IntegralVolumeBlocking<Real>::combine(state.ivbv, {line}, context);
  }
  if constexpr ((Values & kBvv) != 0) {
    BlockerVolume<Real>::combine(state.bvv, {weighted}, context);
  }
}

// Table size for a region of interest reaching `max_distance_mm` from any surface point at
// output spacing h: m = angular * max_distance / h cells per side of the octahedral map (about
// 3.5 / m rad between rays on average, so angular = 3.5 puts neighbouring rays one voxel apart
// at the far edge), and one radial sample per blocking sample (gamma = h / 2). Storing every
// sample lets a lookup at distance D sum exactly the samples before the point, as exact mode
// does; one per h mixed in half of a sample beyond it, which biased voxels beside a structure.
CREPUSCULAR_HD void direction_table_size(double max_distance_mm, double h, int& m,
                                               int& radial, double angular) {
  m = int(ceil(angular * max_distance_mm / h));
  if (m < 8) m = 8;
  radial = int(ceil(max_distance_mm / (0.5 * h))) + 2;
}

}  // namespace crepuscular::kernels
