// A property of fast mode's breathing shortcut (AdaptiveOptions::combination, its so_far and
// newer, planning/safety/adaptive_sampling.hpp), on seeded random scenes sampled as a plan
// samples its phases: one, two or three at once.
//
// The property, per scene and number of phases at once, for SVV and ISBV: at every voxel of the
// region where the combination of the phases each refined fully (no combination given) has the
// class of the combination of the fields evaluated exactly at every voxel, the combination of
// the phases that leave refinement to the combination so far has that class too. The classes of
// all three are default_classes of the exact final combination: the thresholds of the plan's
// final combination, without the sampling noise of either run in them.
//
// Why it must hold: a phase leaves a cell unrefined only where every voxel of it is at least as
// dangerous in the combination it reads as the most dangerous of the cell's corners (the corners
// moved toward danger by the whole margins, the combination toward safety by a share,
// kCombinationMarginShare, of the blocking margin). Its values there are interpolated from those
// corners, so they stay within the corners' classes; fast mode's premise (a phase's class inside a
// cell, edge or face lies within the classes of its corners) keeps its exact values there too. So
// where a phase is left to the combination, the combination's class is the class it gets with the
// phase's exact values, and elsewhere the phase is sampled as fast mode samples a phase. Two things
// make that true here, and the test holds the scenes to both:
// - the premise, by construction: every phase's SVV and ISBV are monotone along each axis (the
//   SVV of each phase a minimum of clamped linear ramps whose normals lie in one octant, its ISBV
//   a floor plus soft ramps whose normals lie in one octant), so on any axis-aligned box of the
//   lattice (cell, face, edge) the values lie between those of the box's corners, on both sides.
//   Both sides matter: a phase given the combination takes its ISBV thresholds from it, not from
//   itself alone, so it computes other points than when refined alone, and a value safer inside
//   a box than at its corners (a ridge between two shadows) would be computed in one run and
//   interpolated in the other;
// - the thresholds: SVV's are fixed; the blocking thresholds a phase takes (of its coarsest
//   samples combined with the phases before) differ from the final ones as later phases fold in.
//   The combination's share of the margin absorbs a rise of up to 0.25 of the blocking margin,
//   and the corners' whole margin a fall of up to a factor 1 / (1 + blocking margin). A scene
//   (at a number of phases at once) whose phases' ISBV thresholds drift beyond that lies outside
//   the guarantee: it is counted, not asserted, and most scenes must lie within it.
// The phases of a scene are one anatomy moved (a breathing displacement and a little jitter),
// tilted and scaled a little against each other, so that the blocking thresholds drift as phases
// fold in.
#include <gtest/gtest.h>
#include <omp.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <limits>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "planning/imaging/volume.hpp"
#include "planning/safety/adaptive_sampling.hpp"
#include "planning/safety/safety_classes.hpp"
#include "tests/support/grids.hpp"

namespace crepuscular::planning {
namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
constexpr unsigned kValues = kernels::kSvv | kernels::kIsbv;
constexpr int kSvvSlot = 0, kIsbvSlot = 1;
constexpr int kHalf = 24;   // a grid of 49^3 voxels, the region a ball of radius 24
constexpr int kStride = 4;  // the coarsest lattice
constexpr int kScenes = 20;
constexpr unsigned kFirstSeed = 1;
// The share of the blocking margin by which the sampler moves the combination toward safety: the
// rise of the thresholds it absorbs.
constexpr double kCombinationShare = kCombinationMarginShare;

using test::ball_grid;

// SVV 95 % on the near side of a plane, falling by `slope` points per voxel of depth behind it,
// down to 20 %: a shadow's edge, sharp (60 points a voxel) or soft (5).
struct Shadow {
  Eigen::Vector3d normal;  // unit, pointing into the shadow
  double offset = 0.0;     // the plane: normal . p = offset
  double slope = 10.0;
};

// Blocking rising across a plane: amplitude * softplus((normal . p - offset) / width).
struct Ramp {
  Eigen::Vector3d normal;
  double offset = 0.0, width = 5.0, amplitude = 1.0;
};

double softplus(double z) { return z > 30.0 ? z : std::log1p(std::exp(z)); }

// One phase's fields, at positions in voxels from the grid's centre.
struct PhaseField {
  Eigen::Vector3d shift = Eigen::Vector3d::Zero();  // where breathing moved this phase
  std::vector<Shadow> shadows;
  std::vector<Ramp> ramps;
  double floor = 1.0, gain = 1.0;

  float svv(const Eigen::Vector3d& at) const {
    const Eigen::Vector3d p = at - shift;
    double v = 95.0;
    for (const Shadow& s : shadows) v = std::min(v, 95.0 - s.slope * (s.normal.dot(p) - s.offset));
    return float(std::clamp(v, 20.0, 95.0));
  }
  float isbv(const Eigen::Vector3d& at) const {
    const Eigen::Vector3d p = at - shift;
    double v = floor;
    for (const Ramp& r : ramps) v += r.amplitude * softplus((r.normal.dot(p) - r.offset) / r.width);
    return float(gain * v);
  }
};

// A random unit vector; with `octant` (components +-1), one in that octant.
Eigen::Vector3d random_direction(std::mt19937& rng, const Eigen::Vector3d* octant = nullptr) {
  std::normal_distribution<double> normal;
  Eigen::Vector3d d;
  do {
    d = Eigen::Vector3d(normal(rng), normal(rng), normal(rng));
    if (octant) d = d.cwiseAbs().cwiseProduct(*octant);
  } while (d.norm() < 1e-3);
  return d.normalized();
}

// A scene: one anatomy (1 to 3 shadows, 2 to 4 blocking ramps, one of them gentle), and 2 to 5
// phases of it, each moved by a breathing displacement along one direction and a little of its
// own, its planes tilted (within their octants) and its shadows moved a little, its blocking
// scaled by up to 2 %.
std::vector<PhaseField> random_scene(unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  const auto between = [&](double a, double b) { return a + (b - a) * u(rng); };
  const auto random_octant = [&] {
    Eigen::Vector3d o;
    for (int a = 0; a < 3; ++a) o[a] = rng() % 2 ? 1.0 : -1.0;
    return o;
  };
  const double h = kHalf;
  PhaseField anatomy;
  const Eigen::Vector3d shadow_octant = random_octant(), ramp_octant = random_octant();
  const int shadows = 1 + int(rng() % 3);
  for (int s = 0; s < shadows; ++s) {
    anatomy.shadows.push_back(
        {random_direction(rng, &shadow_octant), between(0.2, 0.8) * h, between(5.0, 60.0)});
  }
  const int ramps = 1 + int(rng() % 3);
  for (int r = 0; r < ramps; ++r) {
    anatomy.ramps.push_back({random_direction(rng, &ramp_octant), between(-0.5, 0.5) * h,
                             between(0.5, 6.0), between(0.3, 2.0)});
  }
  anatomy.ramps.push_back({random_direction(rng, &ramp_octant), between(-0.3, 0.3) * h,
                           between(15.0, 30.0), between(0.3, 1.0)});
  anatomy.floor = between(0.5, 1.5);

  const auto tilted = [&](const Eigen::Vector3d& d, const Eigen::Vector3d& octant) {
    Eigen::Vector3d t = d + 0.05 * random_direction(rng);
    for (int a = 0; a < 3; ++a) t[a] = octant[a] * std::max(0.0, octant[a] * t[a]);
    return t.norm() > 1e-6 ? Eigen::Vector3d(t.normalized()) : d;
  };
  const int phases = 2 + int(rng() % 4);
  const Eigen::Vector3d breathing = random_direction(rng) * between(0.3, 1.0);
  const double gain_spread = between(0.0, 0.02);
  std::vector<PhaseField> out;
  for (int p = 0; p < phases; ++p) {
    PhaseField f = anatomy;
    f.shift = breathing * std::cos(2.0 * M_PI * p / phases) + 0.15 * random_direction(rng);
    for (Shadow& s : f.shadows) {
      s.normal = tilted(s.normal, shadow_octant);
      s.offset += between(-1.0, 1.0);
    }
    for (Ramp& r : f.ramps) r.normal = tilted(r.normal, ramp_octant);
    f.gain = 1.0 + gain_spread * between(-1.0, 1.0);
    out.push_back(f);
  }
  return out;
}

// SVV and ISBV of every voxel of the grid; NaN outside the region.
struct Volumes {
  std::vector<float> svv, isbv;
};

// The phases combined: SVV the minimum, ISBV the maximum; unknown (NaN) in either stays unknown.
Volumes fold(const Volumes& a, const Volumes& b) {
  Volumes f{a.svv, a.isbv};
  for (size_t v = 0; v < f.svv.size(); ++v) {
    f.svv[v] = std::isnan(a.svv[v]) || std::isnan(b.svv[v]) ? kNaN : std::min(a.svv[v], b.svv[v]);
    f.isbv[v] =
        std::isnan(a.isbv[v]) || std::isnan(b.isbv[v]) ? kNaN : std::max(a.isbv[v], b.isbv[v]);
  }
  return f;
}

Eigen::Vector3d position(const OutputGrid& g, int64_t i, int64_t j, int64_t k) {
  return Eigen::Vector3d(double(i - g.half), double(j - g.half), double(k - g.half));
}

size_t voxel(int64_t n, int64_t i, int64_t j, int64_t k) { return size_t((k * n + j) * n + i); }

// The phase's fields evaluated at every voxel of the region.
Volumes exact_phase(const OutputGrid& g, const PhaseField& f) {
  const int64_t n = g.geometry.dims[0];
  Volumes e{std::vector<float>(size_t(n * n * n), kNaN),
            std::vector<float>(size_t(n * n * n), kNaN)};
  for (int64_t k = 0; k < n; ++k)
    for (int64_t j = 0; j < n; ++j)
      for (int64_t i = 0; i < n; ++i) {
        if (!g.in_roi(i, j, k)) continue;
        e.svv[voxel(n, i, j, k)] = f.svv(position(g, i, j, k));
        e.isbv[voxel(n, i, j, k)] = f.isbv(position(g, i, j, k));
      }
  return e;
}

// What a phase reads of the phases before: those folded so far, and where given one more, done
// but not folded yet (read through the fold: CombinedVolumes::pending).
struct Source {
  const Volumes* folded = nullptr;
  const Volumes* pending = nullptr;
};

CombinedVolumes combined(const Source& s) {
  CombinedVolumes c = std::array<const float*, kernels::kValueCount>{
      s.folded->svv.data(), s.folded->isbv.data(), nullptr, nullptr};
  if (s.pending) {
    c.pending[kSvvSlot] = s.pending->svv.data();
    c.pending[kIsbvSlot] = s.pending->isbv.data();
  }
  return c;
}

struct Sampled {
  Volumes volumes;
  AdaptiveReport report;
};

// One phase sampled by fast mode, after `so_far` and from the second level on `newer` where the
// plan gives them. The evaluator returns the fields' values: the exact volume's inside the
// region, the fields' own at corners outside it.
Sampled sample_phase(const OutputGrid& g, const PhaseField& f, const Volumes& exact,
                     const Source* so_far, const Source* newer) {
  const int64_t n = g.geometry.dims[0];
  Sampled run;
  run.volumes = {std::vector<float>(size_t(n * n * n), kNaN),
                 std::vector<float>(size_t(n * n * n), kNaN)};
  float* out[kernels::kValueCount] = {run.volumes.svv.data(), run.volumes.isbv.data(), nullptr,
                                      nullptr};
  AdaptiveOptions o;
  o.values = kValues;
  o.stride = kStride;
  if (so_far) o.combination.so_far = [so_far] { return combined(*so_far); };
  if (newer) {
    o.combination.newer = [newer] { return combined(*newer); };
    o.combination.newer_from_level = 1;
  }
  const PointEvaluator evaluate = [&](const std::vector<GridPoint>& points,
                                      std::vector<float>& values) {
    for (size_t p = 0; p < points.size(); ++p) {
      const GridPoint& q = points[p];
      float* to = &values[p * kernels::kValueCount];
      if (q.i >= 0 && q.j >= 0 && q.k >= 0 && q.i < n && q.j < n && q.k < n &&
          g.in_roi(q.i, q.j, q.k)) {
        to[kSvvSlot] = exact.svv[voxel(n, q.i, q.j, q.k)];
        to[kIsbvSlot] = exact.isbv[voxel(n, q.i, q.j, q.k)];
      } else {
        to[kSvvSlot] = f.svv(position(g, q.i, q.j, q.k));
        to[kIsbvSlot] = f.isbv(position(g, q.i, q.j, q.k));
      }
    }
  };
  run.report = sample_adaptively(g, o, evaluate, out);
  return run;
}

SafetyClasses classes_of(const OutputGrid& g, unsigned value_bit, const std::vector<float>& v) {
  Volume<float> volume(g.geometry, kNaN);
  std::copy(v.begin(), v.end(), volume.values().begin());
  return default_classes(value_bit, volume);
}

// A plan's phases sampled in order and folded. `at_once` 0: every phase refined fully, alone.
// `at_once` m >= 1: m phases computed at once; phase `at` reads the phases up to at - m folded
// (the m - 1 before it are computed beside it), and with m >= 2 from the second level on the
// next one too, at - m + 1, done by then and read through the fold before it is folded.
struct PlanRun {
  Volumes combination;
  int64_t evaluated = 0, left = 0;
  // The ISBV thresholds of each phase that read a combination.
  std::vector<SafetyClasses> isbv_thresholds;
};

PlanRun plan(const OutputGrid& g, const std::vector<PhaseField>& phases,
             const std::vector<Volumes>& exact, int at_once) {
  PlanRun r;
  std::vector<Volumes> sampled;
  std::vector<Volumes> folds;  // folds[m]: phases 0..m folded
  for (int at = 0; at < int(phases.size()); ++at) {
    const int last = at - at_once;  // the newest phase folded into what phase `at` reads
    const bool reads = at_once > 0 && last >= 0;
    const bool reads_newer = reads && at_once >= 2;
    const Source so_far{reads ? &folds[size_t(last)] : nullptr, nullptr};
    const Source newer{so_far.folded, reads_newer ? &sampled[size_t(last + 1)] : nullptr};
    Sampled s = sample_phase(g, phases[size_t(at)], exact[size_t(at)], reads ? &so_far : nullptr,
                             reads_newer ? &newer : nullptr);
    r.evaluated += s.report.evaluated;
    r.left += s.report.cells_left_to_combination + s.report.points_left_to_combination;
    if (reads) r.isbv_thresholds.push_back(s.report.classes[size_t(kIsbvSlot)]);
    sampled.push_back(std::move(s.volumes));
    folds.push_back(at == 0 ? sampled[0] : fold(folds.back(), sampled.back()));
  }
  r.combination = folds.back();
  return r;
}

// Voxels of the region by how the two runs' classes compare with the exact one.
struct ClassCount {
  int64_t full_wrong = 0, shortcut_wrong = 0;
  int64_t violations = 0;  // of the exact class refined fully, of another with the shortcut
  std::string first;       // the first violation, for the message
};

ClassCount compare(const OutputGrid& g, const SafetyClasses& c, const std::vector<float>& exact,
                   const std::vector<float>& full, const std::vector<float>& shortcut) {
  const int64_t n = g.geometry.dims[0];
  ClassCount count;
  for (int64_t k = 0; k < n; ++k)
    for (int64_t j = 0; j < n; ++j)
      for (int64_t i = 0; i < n; ++i) {
        if (!g.in_roi(i, j, k)) continue;
        const size_t v = voxel(n, i, j, k);
        const SafetyClass e = c.classify(exact[v]), f = c.classify(full[v]),
                          s = c.classify(shortcut[v]);
        count.full_wrong += f != e;
        count.shortcut_wrong += s != e;
        if (f == e && s != e) {
          if (count.violations++ == 0) {
            std::ostringstream m;
            m << "voxel " << i << "," << j << "," << k << ": exact " << exact[v]
              << ", refined fully " << full[v] << ", with the shortcut " << shortcut[v];
            count.first = m.str();
          }
        }
      }
  return count;
}

// The sampler on one thread while it lives: its points and values do not depend on the number of
// threads, and one thread keeps this test quick on a machine whose cores are shared.
struct OneThread {
  int before = omp_get_max_threads();
  OneThread() { omp_set_num_threads(1); }
  ~OneThread() { omp_set_num_threads(before); }
  OneThread(const OneThread&) = delete;
  OneThread& operator=(const OneThread&) = delete;
};

TEST(CombinationShortcut, CombinedClassesAgreeWithEveryPhaseRefinedFully) {
  const OneThread one_thread;
  const auto t0 = std::chrono::steady_clock::now();
  const OutputGrid g = ball_grid(kHalf);
  const double margin = AdaptiveOptions{}.blocking_margin;
  const double rise = kCombinationShare * margin, fall = 1.0 / (1.0 + margin) - 1.0;
  int runs = 0, within = 0, fewer = 0, leaving = 0;
  int64_t full_points = 0, shortcut_points = 0, voxels = 0, full_wrong = 0, shortcut_wrong = 0;
  // How far each run's own final ISBV thresholds lie from the exact combination's (reported).
  double own_thresholds = 0.0;
  for (int scene = 0; scene < kScenes; ++scene) {
    const unsigned seed = kFirstSeed + unsigned(scene);
    const std::vector<PhaseField> phases = random_scene(seed);
    std::vector<Volumes> exact;
    for (const PhaseField& f : phases) exact.push_back(exact_phase(g, f));
    Volumes truth = exact[0];
    for (size_t p = 1; p < exact.size(); ++p) truth = fold(truth, exact[p]);
    const std::array<SafetyClasses, 2> classes = {classes_of(g, kernels::kSvv, truth.svv),
                                                  classes_of(g, kernels::kIsbv, truth.isbv)};
    const PlanRun full = plan(g, phases, exact, 0);
    for (int at_once = 1; at_once <= 3 && at_once < int(phases.size()); ++at_once) {
      SCOPED_TRACE(::testing::Message() << "seed " << seed << ", " << phases.size() << " phases, "
                                        << at_once << " at once");
      const PlanRun shortcut = plan(g, phases, exact, at_once);
      ++runs;
      fewer += shortcut.evaluated < full.evaluated;
      leaving += shortcut.left > 0;
      full_points += full.evaluated;
      shortcut_points += shortcut.evaluated;
      // Within the guarantee: every phase's ISBV thresholds rose to the final ones by no more
      // than the combination's share of the margin absorbs, and fell by no more than the
      // corners' margin does.
      bool in_guarantee = true;
      for (const SafetyClasses& t : shortcut.isbv_thresholds) {
        for (const double drift :
             {classes[1].safe / t.safe - 1.0, classes[1].dangerous / t.dangerous - 1.0}) {
          in_guarantee = in_guarantee && drift <= rise && drift >= fall;
        }
      }
      if (!in_guarantee) continue;
      ++within;
      for (const Volumes* run : {&full.combination, &shortcut.combination}) {
        const SafetyClasses own = classes_of(g, kernels::kIsbv, run->isbv);
        own_thresholds = std::max({own_thresholds, std::abs(own.safe / classes[1].safe - 1.0),
                                   std::abs(own.dangerous / classes[1].dangerous - 1.0)});
      }
      for (const int slot : {kSvvSlot, kIsbvSlot}) {
        const bool svv = slot == kSvvSlot;
        const ClassCount count =
            compare(g, classes[size_t(slot)], svv ? truth.svv : truth.isbv,
                    svv ? full.combination.svv : full.combination.isbv,
                    svv ? shortcut.combination.svv : shortcut.combination.isbv);
        EXPECT_EQ(count.violations, 0)
            << (svv ? "SVV" : "ISBV") << ": voxels of the exact class with every phase refined "
            << "fully, of another with the shortcut (" << count.full_wrong
            << " voxels of another class refined fully, " << count.shortcut_wrong
            << " with the shortcut); first: " << count.first;
        voxels += g.roi_voxels;
        full_wrong += count.full_wrong;
        shortcut_wrong += count.shortcut_wrong;
      }
    }
  }
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  std::printf(
      "%d scenes, %d plans with a combination (%d within the guarantee, %d with fewer "
      "points, %d leaving cells); points %lld with the shortcut, %lld refined fully; "
      "voxels of another class than exact: %lld refined fully, %lld with the shortcut, "
      "of %lld; each run's own final ISBV thresholds within %.2g of the exact ones; "
      "%.2f s\n",
      kScenes, runs, within, fewer, leaving, (long long)shortcut_points, (long long)full_points,
      (long long)full_wrong, (long long)shortcut_wrong, (long long)voxels, own_thresholds, seconds);
  // Not vacuous: most plans lie within the guarantee, leave cells to the combination and so
  // compute fewer points; refined fully, the classes are almost all the exact ones.
  EXPECT_GE(runs, kScenes);
  EXPECT_GE(within * 5, runs * 4);
  EXPECT_GE(leaving * 4, runs * 3);
  EXPECT_GE(fewer * 4, runs * 3);
  EXPECT_LT(shortcut_points, full_points);
  EXPECT_LE(full_wrong * 1000, voxels);
}

}  // namespace
}  // namespace crepuscular::planning
