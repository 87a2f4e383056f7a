// The built-in phantom (planning/phantom.hpp): a procedural abdomen made of analytic shapes in LPS
// mm, voxelised by sampling them at voxel centres, so it looks the same at any spacing.
#include "planning/simulation/phantom.hpp"

#include <fmt/format.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <cmath>
#include <filesystem>
#include <map>
#include <random>
#include <sstream>
#include <system_error>
#include <vector>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "foundation/output_files.hpp"
#include "planning/imaging/volume_io.hpp"

namespace crepuscular::planning {

// Generated at configure time from planning/preprocessing/presets/*.json (planning/CMakeLists.txt).
const std::map<std::string, std::string>& preset_sources();

namespace {

using Vec3 = Eigen::Vector3d;

// Label values of labels.nii.gz; presets/phantom.json names them and gives their levels.
enum Label : uint8_t {
  kAir = 0,
  kFat = 1,     // skin, subcutaneous and visceral fat
  kMuscle = 2,  // abdominal wall, diaphragm, back muscles, psoas, heart, discs, spinal cord
  kBone = 3,
  kAorta = 4,
  kVenaCava = 5,
  kLiver = 6,
  kLiverVessel = 7,
  kKidney = 8,
  kLung = 9,
  kBowel = 10,
  kSpleen = 11,
  kGallbladder = 12,
};
constexpr int kLabelCount = 13;

// CT value of each label in HU (before the structure-specific details and the noise).
constexpr std::array<int16_t, kLabelCount> kLabelHu = {-1000, -100, 50,   700, 200, 200, 60,
                                                       180,   150,  -850, 20,  50,  10};
constexpr int16_t kTumorHu = 35;
constexpr int16_t kBowelGasHu = -700;
constexpr int16_t kCancellousBoneHu = 300;
constexpr int16_t kDiscHu = 90;
constexpr int16_t kSpinalCordHu = 30;
constexpr int kNoiseSigmaHu = 10;

constexpr double kPi = 3.14159265358979323846;
constexpr double kDeg = kPi / 180.0;

// ---------------------------------------------------------------------------------------------
// Anatomy, in LPS mm (x: patient right -> left, y: anterior -> posterior, z: inferior -> superior).
// The grid is centred on (0, 0, 0).
constexpr double kExtentMm[3] = {360.0, 260.0, 240.0};

// Body cross-section: a superellipse |x/a|^p + |y/b|^p <= 1, constant along z. Inward from the
// skin: subcutaneous fat, the muscle wall, then the abdominal / thoracic cavity.
constexpr double kBodyA = 150.0, kBodyB = 105.0, kBodyP = 2.2;
constexpr double kFatMm = 15.0;     // skin to muscle wall
constexpr double kMuscleMm = 12.0;  // muscle wall thickness
constexpr double kCavityA = kBodyA - kFatMm - kMuscleMm, kCavityB = kBodyB - kFatMm - kMuscleMm;
constexpr double kRibOffsetMm = 21.0;  // rib centre line below the skin (inside the muscle wall)

// Diaphragm: two domes (right higher), z = apex - h * ((x-cx)^2/ax^2 + (y-cy)^2/ay^2), the upper
// surface of the diaphragm muscle; below it the muscle layer, then the abdomen.
constexpr double kDomeRightX = -65.0, kDomeRightApex = 80.0;
constexpr double kDomeLeftX = 65.0, kDomeLeftApex = 72.0;
constexpr double kDomeY = -10.0, kDomeH = 40.0, kDomeAx = 75.0, kDomeAy = 85.0;
constexpr double kDiaphragmMm = 5.0;
constexpr double kMediastinumHalfWidth = 26.0;  // lungs lie at |x| beyond this

// Organs: ellipsoids (centre, semi-axes).
const Vec3 kLiverRightC(-68, -5, 20), kLiverRightR(72, 68, 60);  // right lobe
const Vec3 kLiverLeftC(8, -38, 42), kLiverLeftR(58, 30, 26);     // left lobe, over the midline
constexpr double kLiverBlendMm = 20.0;                           // smooth union of the lobes
constexpr double kLiverWobbleMm = 2.5;                           // low-frequency surface relief
const Vec3 kSpleenC(88, 32, 32), kSpleenR(24, 40, 44);
const Vec3 kGallbladderC(-46, -42, -20), kGallbladderR(13, 14, 26);
const Vec3 kHeartC(10, -25, 125), kHeartR(60, 48, 45);
// Kidneys: right lower than left; long axis tilted so the upper pole is medial; a hilum notch.
const Vec3 kKidneyRightC(-72, 42, -32), kKidneyLeftC(72, 42, -20), kKidneyR(25, 18, 50);
constexpr double kKidneyTiltDeg = 12.0, kKidneyHilumR = 11.0, kKidneyHilumOffset = 22.0;
constexpr double kOrganGapMm = 3.0;  // fat between liver / spleen and the kidneys

// Great vessels: tubes along z; below the bifurcation, two iliac branches diverge.
constexpr double kAortaX = 16, kAortaY = 14, kAortaR = 11, kAortaSplitZ = -85, kIliacArteryR = 8;
constexpr double kCavaX = -22, kCavaY = 18, kCavaRx = 12, kCavaRy = 10, kCavaSplitZ = -95;
constexpr double kIliacVeinR = 8;

// Spine: vertebral bodies (period along z: body then disc) and posterior elements.
constexpr double kSpineY = 45, kVertebraRx = 22, kVertebraRy = 18;
constexpr double kVertebraPeriod = 32, kVertebraHeight = 25, kVertebraZ0 = -117;
constexpr double kCanalY = 73, kCanalR = 9, kArchR = 17;
constexpr double kCorticalMm = 3.0;
// Back muscles (erector spinae) either side of the spinous processes.
constexpr double kBackMuscleX = 36, kBackMuscleY = 80, kBackMuscleRx = 25, kBackMuscleRy = 17;

// Tumor: union of three ellipsoids, equivalent diameter 25 mm, centroid near kTumorC, in the
// lateral right lobe: lateral and anterolateral paths cross fat, muscle and liver only.
const Vec3 kTumorC(-92, -22, 4);
struct Lobe {
  Vec3 offset, radii;
};
const std::array<Lobe, 3> kTumorLobes = {{{Vec3(0, 0, 0), Vec3(12.5, 11.0, 11.5)},
                                          {Vec3(6.3, -5.2, 5.2), Vec3(8.4, 7.3, 7.8)},
                                          {Vec3(-5.2, 4.2, -6.3), Vec3(7.8, 7.3, 7.3)}}};
constexpr double kTumorBoundingR = 18.0;  // all lobes lie within this distance of kTumorC
constexpr double kVesselClearance = 5.0;  // least gap (mm) between tumor lobes and vessel tree

// ---------------------------------------------------------------------------------------------
// Random numbers: std::mt19937_64's sequence is fixed by the standard; the distributions below are
// our own, so the phantom is the same with every standard library.
class Rng {
 public:
  explicit Rng(uint64_t seed) : engine_(seed) {}
  double uniform() { return double(engine_() >> 11) * 0x1.0p-53; }  // [0, 1)
  double uniform(double lo, double hi) { return lo + (hi - lo) * uniform(); }
  // Standard normal (Box-Muller).
  double normal() {
    const double u1 = 1.0 - uniform();
    const double u2 = uniform();
    return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * kPi * u2);
  }
  // Uniform on the unit sphere (rejection from the cube).
  Vec3 unit_vector() {
    for (;;) {
      const Vec3 v(uniform(-1, 1), uniform(-1, 1), uniform(-1, 1));
      const double n2 = v.squaredNorm();
      if (n2 > 1e-4 && n2 <= 1.0) return v / std::sqrt(n2);
    }
  }

 private:
  std::mt19937_64 engine_;
};

uint64_t splitmix64(uint64_t x) {
  x += 0x9E3779B97F4A7C15ull;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
  return x ^ (x >> 31);
}

// Approximately Gaussian CT noise in HU with sigma kNoiseSigmaHu (Irwin-Hall: sum of 12 uniforms),
// a pure function of (key, voxel) in integer arithmetic: identical on every platform and for any
// number of threads.
int noise_hu(uint64_t key, int64_t voxel) {
  int64_t sum = 0;
  for (uint64_t w = 0; w < 3; ++w) {
    uint64_t h = splitmix64(key + uint64_t(voxel) * 3 + w);
    for (int q = 0; q < 4; ++q, h >>= 16) sum += int64_t(h & 0xFFFF);
  }
  // 12 uniforms on [0, 65535]: mean 6 * 65535, standard deviation ~65536.
  const int64_t scaled = (sum - 6 * 65535) * kNoiseSigmaHu;
  return int((scaled + (scaled >= 0 ? 32768 : -32768)) / 65536);
}

// ---------------------------------------------------------------------------------------------
// Shapes. "sdf" functions return an approximate signed distance in mm (negative inside).

// Ellipsoid with semi-axes r centred at the origin (Quilez's approximation; exact on the axes).
double ellipsoid_sdf(const Vec3& q, const Vec3& r) {
  const double k0 = q.cwiseQuotient(r).norm();
  const double k1 = q.cwiseQuotient(r.cwiseProduct(r)).norm();
  if (k1 <= 0.0) return -r.minCoeff();
  return k0 * (k0 - 1.0) / k1;
}

bool in_ellipsoid(const Vec3& q, const Vec3& r) { return q.cwiseQuotient(r).squaredNorm() <= 1.0; }

double smooth_min(double a, double b, double k) {
  const double h = std::max(k - std::abs(a - b), 0.0) / k;
  return std::min(a, b) - h * h * k * 0.25;
}

// Superellipse "radius": < 1 inside |x/a|^p + |y/b|^p <= 1.
double superellipse_q(double x, double y, double a, double b) {
  return std::pow(std::pow(std::abs(x) / a, kBodyP) + std::pow(std::abs(y) / b, kBodyP),
                  1.0 / kBodyP);
}
// Approximate signed distance to the body cavity's boundary (negative inside the cavity).
double cavity_sdf(double x, double y) {
  return (superellipse_q(x, y, kCavityA, kCavityB) - 1.0) * kCavityB;
}

double dome_z(double x, double y) {
  const auto dome = [&](double cx, double apex) {
    const double dx = (x - cx) / kDomeAx, dy = (y - kDomeY) / kDomeAy;
    return apex - kDomeH * (dx * dx + dy * dy);
  };
  return std::max(dome(kDomeRightX, kDomeRightApex), dome(kDomeLeftX, kDomeLeftApex));
}

// Breathing (docs/ARCHITECTURE.md §10): the moving anatomy's displacement field, smooth, largest at
// the diaphragm and fading with the vertical distance from it; bones, skin, the body wall, the
// spine and the great vessels stay.
constexpr double kBreathingAnteriorRatio = 0.35;  // anterior motion per mm of caudal motion
constexpr double kBreathingFadeSigmaMm = 70.0;    // Gaussian fade with distance from the dome

Vec3 breathing_direction() { return Vec3(0.0, -kBreathingAnteriorRatio, -1.0); }

// The anterior abdominal wall rises with inhalation: skin, fat and muscle in front of the
// mid-coronal plane move anteriorly by up to kWallRiseRatio times the diaphragm's motion at the
// anterior skin (8.4 mm for the default 12 mm), fading toward the mid-coronal plane (smoothstep)
// and with the height from the abdomen's middle (Gaussian); the air in front moves with the skin.
constexpr double kWallRiseRatio = 0.7;
constexpr double kWallCentreZ = -30.0, kWallSigmaZ = 60.0;

Vec3 wall_displacement(const Vec3& p, double inhale, double amplitude_mm) {
  const double a = std::clamp(-p.y() / kBodyB, 0.0, 1.0);
  const double dz = p.z() - kWallCentreZ;
  const double fade = a * a * (3.0 - 2.0 * a) * std::exp(-0.5 * dz * dz / (kWallSigmaZ * kWallSigmaZ));
  return Vec3(0.0, -inhale * amplitude_mm * kWallRiseRatio * fade, 0.0);
}

// Where a voxel's content comes from: in a phase, the moving anatomy at p is the anatomy at rest
// (end-exhale) at p - u(p). Identity when the phase does not move.
struct Warp {
  double inhale = 0.0, amplitude_mm = 0.0;
  bool moves() const { return inhale * amplitude_mm != 0.0; }
  // Largest |u| anywhere (mm): a margin for bounding boxes.
  double max_mm() const { return std::abs(inhale * amplitude_mm) * breathing_direction().norm(); }
  Vec3 source(const Vec3& p) const {
    return moves() ? Vec3(p - breathing_displacement(p, inhale, amplitude_mm)) : p;
  }
  // Where the body wall's content at p comes from: the q with q + wall_displacement(q) = p.
  Vec3 wall_source(const Vec3& p) const {
    Vec3 q = p;
    for (int it = 0; it < 4 && moves(); ++it) q = p - wall_displacement(q, inhale, amplitude_mm);
    return q;
  }
};

// Kidney: tilted ellipsoid minus a hilum notch on its medial side. side = -1 right, +1 left.
double kidney_sdf(const Vec3& p, int side) {
  const Vec3& c = side < 0 ? kKidneyRightC : kKidneyLeftC;
  const Vec3 d = p - c;
  // Upper pole tilted towards the midline (towards -side in x).
  const double t = kKidneyTiltDeg * kDeg;
  const Vec3 axis(-side * std::sin(t), 0.0, std::cos(t));
  const Vec3 across(std::cos(t), 0.0, side * std::sin(t));
  const Vec3 local(d.dot(across), d.y(), d.dot(axis));
  const double body = ellipsoid_sdf(local, kKidneyR);
  const Vec3 hilum(-side * kKidneyHilumOffset, -6.0, 0.0);
  const double notch = (local - hilum).norm() - kKidneyHilumR;
  return std::max(body, -notch);
}

double liver_wobble(const Vec3& p) {
  return kLiverWobbleMm * std::sin(0.071 * p.x() + 0.4) * std::sin(0.053 * p.y() + 1.1) *
         std::sin(0.067 * p.z() + 2.3);
}

// Liver: smooth union of two lobes, inside the cavity, below the diaphragm, away from the right
// kidney. cavity_d and dome are cavity_sdf and dome_z at (p.x, p.y).
double liver_sdf(const Vec3& p, double cavity_d, double dome) {
  double d = smooth_min(ellipsoid_sdf(p - kLiverRightC, kLiverRightR),
                        ellipsoid_sdf(p - kLiverLeftC, kLiverLeftR), kLiverBlendMm);
  if (std::abs(d) < kLiverWobbleMm + 1.0) d += liver_wobble(p);
  d = std::max(d, p.z() - (dome - kDiaphragmMm - 1.0));
  d = std::max(d, cavity_d + 2.0);
  if (d < 0.0 && p.z() < kKidneyRightC.z() + kKidneyR.z() + kOrganGapMm + 10.0) {
    d = std::max(d, kOrganGapMm - kidney_sdf(p, -1));
  }
  return d;
}
double liver_sdf(const Vec3& p) {
  return liver_sdf(p, cavity_sdf(p.x(), p.y()), dome_z(p.x(), p.y()));
}

bool in_tumor(const Vec3& p) {
  for (const Lobe& lobe : kTumorLobes) {
    if (in_ellipsoid(p - kTumorC - lobe.offset, lobe.radii)) return true;
  }
  return false;
}

// Tube piece: all points within r of the segment ab.
struct Capsule {
  Vec3 a, b;
  double r;
};

double segment_distance(const Vec3& p, const Vec3& a, const Vec3& b) {
  const Vec3 ab = b - a;
  const double len2 = ab.squaredNorm();
  const double t = len2 > 0.0 ? std::clamp((p - a).dot(ab) / len2, 0.0, 1.0) : 0.0;
  return (p - (a + t * ab)).norm();
}

// A sphere of gas in the bowel.
struct Sphere {
  Vec3 c;
  double r;
};

// ---------------------------------------------------------------------------------------------
// Structures built from tubes: ribs, liver vessel tree, bowel.

Vec3 rib_point(double theta_deg, int side, double z) {
  const double a = kBodyA - kRibOffsetMm, b = kBodyB - kRibOffsetMm;
  const double s = std::sin(theta_deg * kDeg), c = std::cos(theta_deg * kDeg);
  const double e = 2.0 / kBodyP;
  return Vec3(side * a * std::pow(std::abs(s), e), b * (c >= 0 ? 1 : -1) * std::pow(std::abs(c), e),
              z);
}

// Ribs: arcs in the muscle wall from the transverse processes around the side towards the front,
// sloping down anteriorly; two short floating ribs below them.
std::vector<Capsule> make_ribs() {
  struct RibSpec {
    double z_posterior, theta_end_deg;
  };
  const RibSpec ribs[] = {{26, 70}, {44, 100}, {62, 150}, {86, 150}, {110, 150}, {134, 150}};
  constexpr double kRibR = 5.0, kSlopeMmPerDeg = 0.3, kThetaStart = 25.0, kThetaStep = 5.0;
  std::vector<Capsule> out;
  for (const RibSpec& rib : ribs) {
    for (int side : {-1, 1}) {
      const auto z_of = [&](double theta) {
        return rib.z_posterior - kSlopeMmPerDeg * (theta - kThetaStart);
      };
      Vec3 prev(side * 36.0, 69.0, rib.z_posterior + 4.0);  // transverse process tip
      for (double theta = kThetaStart; theta <= rib.theta_end_deg + 1e-9; theta += kThetaStep) {
        const Vec3 p = rib_point(theta, side, z_of(theta));
        out.push_back({prev, p, kRibR});
        prev = p;
      }
    }
  }
  return out;
}

Vec3 any_perpendicular(const Vec3& d, Rng& rng) {
  for (;;) {
    const Vec3 v = rng.unit_vector();
    const Vec3 w = v - v.dot(d) * d;
    if (w.norm() > 0.1) return w.normalized();
  }
}

// d rotated by a random angle (normal, sd sigma_deg) about a random perpendicular axis.
Vec3 perturb(const Vec3& d, double sigma_deg, Rng& rng) {
  const double angle = rng.normal() * sigma_deg * kDeg;
  const Vec3 axis = any_perpendicular(d, rng);
  return (Eigen::AngleAxisd(angle, axis) * d).normalized();
}

// Grows a vessel tree inside the liver: each branch is a slightly curved tube of three pieces that
// stays inside the liver and clear of the tumor; at its end it forks in two thinner, shorter
// branches. A branch that finds no admissible course in a few tries is left out.
class VesselTreeBuilder {
 public:
  VesselTreeBuilder(Rng& rng, std::vector<Capsule>& out) : rng_(rng), out_(out) {}

  void grow(const Vec3& start, const Vec3& direction, double length, double radius,
            int generations_left) {
    constexpr int kTries = 12;
    for (int attempt = 0; attempt < kTries; ++attempt) {
      const double spread = attempt == 0 ? 8.0 : 8.0 + 6.0 * attempt;
      const Vec3 dir = perturb(direction, spread, rng_);
      std::array<Vec3, 4> pts;
      pts[0] = start;
      Vec3 d = dir;
      for (int k = 1; k < 4; ++k) {
        d = perturb(d, 10.0, rng_);
        pts[size_t(k)] = pts[size_t(k - 1)] + d * (length / 3.0);
      }
      if (!admissible(pts, radius)) continue;
      for (size_t k = 1; k < 4; ++k) out_.push_back({pts[k - 1], pts[k], radius});
      if (generations_left > 0) {
        const Vec3 end_dir = (pts[3] - pts[2]).normalized();
        const Vec3 axis = any_perpendicular(end_dir, rng_);
        for (int sign : {1, -1}) {
          const double angle = sign * rng_.uniform(20.0, 45.0) * kDeg;
          const Vec3 child = (Eigen::AngleAxisd(angle, axis) * end_dir).normalized();
          grow(pts[3], child, length * rng_.uniform(0.7, 0.85), radius * 0.78,
               generations_left - 1);
        }
      }
      return;
    }
  }

 private:
  bool admissible(const std::array<Vec3, 4>& pts, double radius) const {
    for (size_t k = 1; k < 4; ++k) {
      if (segment_distance(kTumorC, pts[k - 1], pts[k]) <
          kTumorBoundingR + radius + kVesselClearance) {
        return false;
      }
      const int samples = 4;
      for (int s = 1; s <= samples; ++s) {
        const Vec3 p = pts[k - 1] + (pts[k] - pts[k - 1]) * (double(s) / samples);
        if (liver_sdf(p) > -(radius + 1.0)) return false;
      }
    }
    return true;
  }

  Rng& rng_;
  std::vector<Capsule>& out_;
};

// Portal tree from the hilum and hepatic veins draining into the vena cava, random for each seed.
std::vector<Capsule> make_liver_vessels(uint64_t seed) {
  Rng rng(splitmix64(seed ^ 0x76657373656C73ull));
  std::vector<Capsule> out;
  VesselTreeBuilder tree(rng, out);
  // Portal vein: trunk from below the hilum (outside the liver parts are not drawn), then lobar
  // branches.
  const Vec3 hilum(-40, -8, 0);
  out.push_back({Vec3(-28, 0, -30), hilum, 6.5});
  const Vec3 portal_dirs[] = {Vec3(-1.0, 0.5, 0.3), Vec3(-1.0, -0.6, 0.5), Vec3(1.0, -0.5, 0.5),
                              Vec3(-0.3, 0.2, 1.0)};
  const double portal_len[] = {40, 40, 45, 35};
  for (size_t b = 0; b < 4; ++b) {
    tree.grow(hilum, portal_dirs[b].normalized(), portal_len[b], b == 3 ? 4.5 : 5.0, 3);
  }
  // Hepatic veins: from the vena cava below the diaphragm into the liver.
  const Vec3 confluence(kCavaX, kCavaY - kCavaRy, 58);
  const Vec3 hepatic_dirs[] = {Vec3(-1.0, -0.1, -0.15), Vec3(-0.5, -1.0, -0.1),
                               Vec3(0.6, -1.0, 0.0)};
  const double hepatic_len[] = {45, 40, 40};
  for (size_t b = 0; b < 3; ++b) {
    tree.grow(confluence, hepatic_dirs[b].normalized(), hepatic_len[b], b == 0 ? 5.0 : 4.5, 2);
  }
  return out;
}

// Small bowel loops (serpentine tubes, lower left anterior abdomen) and the descending colon;
// gas pockets at random places along them.
void make_bowel(uint64_t seed, std::vector<Capsule>& tubes, std::vector<Sphere>& gas) {
  Rng rng(splitmix64(seed ^ 0x626F77656Cull));
  std::vector<std::vector<Vec3>> lines;
  for (int loop = 0; loop < 4; ++loop) {
    const double z0 = -50.0 - 20.0 * loop;
    const double phase = rng.uniform(0.0, 2.0 * kPi);
    const double phase_z = rng.uniform(0.0, 2.0 * kPi);
    std::vector<Vec3> line;
    for (double x = -5.0; x <= 100.0 + 1e-9; x += 7.5) {
      line.emplace_back(x, -42.0 + 18.0 * std::sin(0.105 * x + phase) + rng.uniform(-2, 2),
                        z0 + 5.0 * std::sin(0.07 * x + phase_z));
    }
    lines.push_back(line);
  }
  std::vector<Vec3> colon;
  for (double z = 5.0; z >= -120.0; z -= 12.5) {
    colon.emplace_back(100.0 - 0.03 * (5.0 - z) + rng.uniform(-2, 2), -8.0 + rng.uniform(-2, 2), z);
  }
  const size_t colon_index = lines.size();
  lines.push_back(colon);
  for (size_t l = 0; l < lines.size(); ++l) {
    const double r = l == colon_index ? 14.0 : 10.0;
    for (size_t k = 1; k < lines[l].size(); ++k) tubes.push_back({lines[l][k - 1], lines[l][k], r});
  }
  const int pockets = 14;
  for (int g = 0; g < pockets; ++g) {
    const size_t l = g < 5 ? colon_index : size_t(rng.uniform() * double(colon_index));
    const auto& line = lines[std::min(l, lines.size() - 1)];
    const double t = rng.uniform() * double(line.size() - 1);
    const size_t k = std::min(size_t(t), line.size() - 2);
    const Vec3 c = line[k] + (line[k + 1] - line[k]) * (t - double(k));
    gas.push_back({c + rng.unit_vector() * rng.uniform(0.0, 3.0), rng.uniform(4.0, 8.0)});
  }
}

// ---------------------------------------------------------------------------------------------
// Voxelisation.

// What a voxel column (fixed x, y) holds independently of z.
enum Column : uint8_t { kColAir, kColFat, kColMuscle, kColCavity };

struct ColumnMaps {
  std::vector<uint8_t> kind;     // Column, per (i, j)
  std::vector<double> cavity_d;  // cavity_sdf
  std::vector<double> dome;      // dome_z
};

// What the body holds at (x, y) at rest (the same at every height).
Column column_kind(double x, double y) {
  const double body = superellipse_q(x, y, kBodyA, kBodyB);
  const double wall = superellipse_q(x, y, kBodyA - kFatMm, kBodyB - kFatMm);
  const double bx = (std::abs(x) - kBackMuscleX) / kBackMuscleRx;
  const double by = (y - kBackMuscleY) / kBackMuscleRy;
  if (body > 1.0) return kColAir;
  if (bx * bx + by * by <= 1.0) return kColMuscle;
  if (wall > 1.0) return kColFat;
  if (cavity_sdf(x, y) > 0.0) return kColMuscle;
  return kColCavity;
}

ColumnMaps make_column_maps(const ImageGeometry& g) {
  ColumnMaps m;
  const size_t n = size_t(g.dims[0] * g.dims[1]);
  m.kind.assign(n, kColAir);
  m.cavity_d.assign(n, 0.0);
  m.dome.assign(n, 0.0);
  for (int64_t j = 0; j < g.dims[1]; ++j) {
    for (int64_t i = 0; i < g.dims[0]; ++i) {
      const Vec3 p = g.index_to_physical(i, j, 0);
      const size_t c = size_t(i + g.dims[0] * j);
      m.cavity_d[c] = cavity_sdf(p.x(), p.y());
      m.dome[c] = dome_z(p.x(), p.y());
      m.kind[c] = column_kind(p.x(), p.y());
    }
  }
  return m;
}

struct Scene {
  std::vector<Capsule> ribs, liver_vessels, bowel;
  std::vector<Sphere> gas;
};

// Index range [lo, hi] of voxels along axis `a` whose centres lie within [min_mm, max_mm].
std::pair<int64_t, int64_t> index_range(const ImageGeometry& g, int a, double min_mm,
                                        double max_mm) {
  const double s = g.spacing[a], o = g.origin[a];
  const int64_t lo = std::max<int64_t>(0, int64_t(std::ceil((min_mm - o) / s)));
  const int64_t hi = std::min<int64_t>(g.dims[a] - 1, int64_t(std::floor((max_mm - o) / s)));
  return {lo, hi};
}

// Paints the capsules that cross slice k into labels / hu where `allowed(label, column)` holds.
template <typename Allowed>
void paint_capsules(const std::vector<Capsule>& capsules, const ImageGeometry& g, int64_t k,
                    const ColumnMaps& cols, uint8_t* labels, int16_t* hu, uint8_t label,
                    const Warp& warp, Allowed allowed) {
  const double z = g.origin.z() + g.spacing.z() * double(k);
  const double m = warp.max_mm();
  for (const Capsule& c : capsules) {
    const double r = c.r + m;
    if (z < std::min(c.a.z(), c.b.z()) - r || z > std::max(c.a.z(), c.b.z()) + r) continue;
    const auto [i0, i1] =
        index_range(g, 0, std::min(c.a.x(), c.b.x()) - r, std::max(c.a.x(), c.b.x()) + r);
    const auto [j0, j1] =
        index_range(g, 1, std::min(c.a.y(), c.b.y()) - r, std::max(c.a.y(), c.b.y()) + r);
    for (int64_t j = j0; j <= j1; ++j) {
      for (int64_t i = i0; i <= i1; ++i) {
        const size_t col = size_t(i + g.dims[0] * j);
        if (!allowed(labels[col], cols.kind[col])) continue;
        const Vec3 p(g.origin.x() + g.spacing.x() * double(i),
                     g.origin.y() + g.spacing.y() * double(j), z);
        if (segment_distance(warp.source(p), c.a, c.b) <= c.r) {
          labels[col] = label;
          hu[col] = kLabelHu[label];
        }
      }
    }
  }
}

// Label and base HU of a voxel inside the body cavity from the smooth organs.
void cavity_voxel(const Vec3& p, double cavity_d, double dome, uint8_t& label, int16_t& hu) {
  const double z = p.z();
  auto set = [&](uint8_t l) {
    label = l;
    hu = kLabelHu[l];
  };
  set(kFat);
  if (z > dome) {  // thorax
    if (in_ellipsoid(p - kHeartC, kHeartR)) {
      set(kMuscle);
    } else if (std::abs(p.x()) > kMediastinumHalfWidth) {
      set(kLung);
    }
    return;
  }
  if (z > dome - kDiaphragmMm) {
    set(kMuscle);
    return;
  }
  // Psoas muscles: grow thicker and move laterally towards the pelvis.
  if (z < 10.0) {
    const double t = 10.0 - z;
    const double r = 7.0 + 0.11 * t, cx = 36.0 + 0.09 * t, dx = std::abs(p.x()) - cx;
    const double dy = p.y() - 38.0;
    if (dx * dx + dy * dy <= r * r) set(kMuscle);
  }
  if (liver_sdf(p, cavity_d, dome) <= 0.0) set(kLiver);
  if (z < kSpleenC.z() + kSpleenR.z() && z > kSpleenC.z() - kSpleenR.z() &&
      in_ellipsoid(p - kSpleenC, kSpleenR) && z < dome - kDiaphragmMm - 1.0 &&
      kidney_sdf(p, 1) > kOrganGapMm) {
    set(kSpleen);
  }
  if (in_ellipsoid(p - kGallbladderC, kGallbladderR)) set(kGallbladder);
  const double kidney_top = std::max(kKidneyRightC.z(), kKidneyLeftC.z()) + kKidneyR.z() + 5.0;
  const double kidney_bottom = std::min(kKidneyRightC.z(), kKidneyLeftC.z()) - kKidneyR.z() - 5.0;
  if (z < kidney_top && z > kidney_bottom && kidney_sdf(p, p.x() < 0 ? -1 : 1) <= 0.0) {
    set(kKidney);
  }
}

// Aorta, vena cava and the spine, which override everything below them.
void vessel_and_spine_voxel(const Vec3& p, uint8_t& label, int16_t& hu) {
  const double x = p.x(), y = p.y(), z = p.z();
  // Aorta and common iliac arteries.
  {
    bool in = false;
    if (z >= kAortaSplitZ) {
      in = (x - kAortaX) * (x - kAortaX) + (y - kAortaY) * (y - kAortaY) <= kAortaR * kAortaR;
    } else {
      const double t = kAortaSplitZ - z;
      for (double cx : {kAortaX - 0.55 * t, kAortaX + 0.45 * t}) {
        in = in ||
             (x - cx) * (x - cx) + (y - kAortaY) * (y - kAortaY) <= kIliacArteryR * kIliacArteryR;
      }
    }
    if (in) {
      label = kAorta;
      hu = kLabelHu[kAorta];
    }
  }
  // Vena cava and common iliac veins.
  {
    bool in = false;
    if (z >= kCavaSplitZ) {
      const double dx = (x - kCavaX) / kCavaRx, dy = (y - kCavaY) / kCavaRy;
      in = dx * dx + dy * dy <= 1.0;
    } else {
      const double t = kCavaSplitZ - z;
      for (double cx : {kCavaX - 0.5 * t, kCavaX + 0.5 * t}) {
        in = in || (x - cx) * (x - cx) + (y - kCavaY - 4.0) * (y - kCavaY - 4.0) <=
                       kIliacVeinR * kIliacVeinR;
      }
    }
    if (in) {
      label = kVenaCava;
      hu = kLabelHu[kVenaCava];
    }
  }
  // Spine. Position within the vertebra's period: [0, height) bone, then the disc.
  if (std::abs(x) > 40.0 || y < kSpineY - kVertebraRy - 1.0) return;
  double w = std::fmod(z - kVertebraZ0, kVertebraPeriod);
  if (w < 0) w += kVertebraPeriod;
  const bool in_body_level = w < kVertebraHeight;
  const double mid = std::abs(w - 0.5 * kVertebraHeight);  // distance from the vertebra's middle
  const double bx = x / kVertebraRx, by = (y - kSpineY) / kVertebraRy;
  const double body_q = bx * bx + by * by;
  if (body_q <= 1.0) {
    if (!in_body_level) {
      label = kMuscle;
      hu = kDiscHu;
    } else {
      const double ix = x / (kVertebraRx - kCorticalMm),
                   iy = (y - kSpineY) / (kVertebraRy - kCorticalMm);
      const bool cancellous = ix * ix + iy * iy <= 1.0 && mid < 0.5 * kVertebraHeight - kCorticalMm;
      label = kBone;
      hu = cancellous ? kCancellousBoneHu : kLabelHu[kBone];
    }
    return;
  }
  const double canal_d = std::hypot(x, y - kCanalY);
  if (canal_d <= kCanalR) {
    label = kMuscle;  // spinal cord
    hu = kSpinalCordHu;
    return;
  }
  if (!in_body_level || mid > 9.0) return;
  const bool arch = canal_d <= kArchR && y > kSpineY;
  const bool spinous = std::abs(x) <= 4.5 && y >= kCanalY && y <= 95.0 && mid <= 7.0;
  const bool transverse = std::abs(x) <= 38.0 && y >= 64.0 && y <= 74.0 && mid <= 5.0;
  if (arch || spinous || transverse) {
    label = kBone;
    hu = kLabelHu[kBone];
  }
}

void check_options(const PhantomOptions& options) {
  if (!(options.spacing_mm >= 0.3 && options.spacing_mm <= 10.0)) {
    std::ostringstream m;
    m << "phantom: spacing " << options.spacing_mm << " mm is not usable (expected 0.3 to 10 mm)";
    throw Error(m.str());
  }
  if (!(options.inhale >= 0.0 && options.inhale <= 1.0)) {
    throw Error("phantom: inhale fraction " + std::to_string(options.inhale) +
                " is not usable (expected 0 to 1)");
  }
  if (!(options.amplitude_mm >= 0.0 && options.amplitude_mm <= kMaxBreathingAmplitudeMm)) {
    throw Error("phantom: breathing amplitude " + std::to_string(options.amplitude_mm) +
                " mm is not usable (expected 0 to " + std::to_string(int(kMaxBreathingAmplitudeMm)) +
                " mm)");
  }
}

// The phantom's grid: isotropic `s` mm voxels over kExtentMm, centred on (0, 0, 0), LPS axes.
ImageGeometry phantom_geometry(double s) {
  ImageGeometry g;
  for (int a = 0; a < 3; ++a) {
    g.dims[size_t(a)] = std::max<int64_t>(1, int64_t(std::llround(kExtentMm[a] / s)));
    g.spacing[a] = s;
    g.origin[a] = -0.5 * double(g.dims[size_t(a)] - 1) * s;  // grid centred on (0, 0, 0)
  }
  g.direction.setIdentity();
  return g;
}

// Ribs, liver vessels, bowel and its gas pockets (the seed varies the vessels and the bowel).
Scene make_scene_parts(uint64_t seed) {
  Scene scene;
  scene.ribs = make_ribs();
  scene.liver_vessels = make_liver_vessels(seed);
  make_bowel(seed, scene.bowel, scene.gas);
  return scene;
}

// One axial slice k of the phantom's three volumes (each a row-major x-y plane) at height z.
struct Slice {
  int64_t k = 0;
  double z = 0;
  uint8_t* labels = nullptr;
  int16_t* hu = nullptr;
  uint8_t* tumor = nullptr;
};

// Centre of voxel (i, j) of the slice.
Vec3 voxel_centre(const ImageGeometry& g, int64_t i, int64_t j, double z) {
  const double s = g.spacing.x();
  return Vec3(g.origin.x() + s * double(i), g.origin.y() + s * double(j), z);
}

// Body wall and smooth organs, from the column maps.
void paint_body_and_organs(const ImageGeometry& g, const ColumnMaps& cols, const Warp& warp,
                           const Slice& sl) {
  const int64_t nx = g.dims[0], ny = g.dims[1];
  for (int64_t j = 0; j < ny; ++j) {
    for (int64_t i = 0; i < nx; ++i) {
      const size_t c = size_t(i + nx * j);
      const Vec3 p = voxel_centre(g, i, j, sl.z);
      // The wall of a breathing phase: its rest shape at the wall's source.
      Column kind = Column(cols.kind[c]);
      if (warp.moves()) {
        const Vec3 w = warp.wall_source(p);
        kind = column_kind(w.x(), w.y());
      }
      switch (kind) {
        case kColAir:
          sl.labels[c] = kAir;
          break;
        case kColFat:
          sl.labels[c] = kFat;
          break;
        case kColMuscle:
          sl.labels[c] = kMuscle;
          break;
        default:
          if (warp.moves()) {  // the cavity's content moves with the organs' field
            const Vec3 q = warp.source(p);
            cavity_voxel(q, cavity_sdf(q.x(), q.y()), dome_z(q.x(), q.y()), sl.labels[c],
                         sl.hu[c]);
          } else {
            cavity_voxel(p, cols.cavity_d[c], cols.dome[c], sl.labels[c], sl.hu[c]);
          }
          continue;
      }
      sl.hu[c] = kLabelHu[sl.labels[c]];
    }
  }
}

// Great vessels and spine, inside the body.
void paint_vessels_and_spine(const ImageGeometry& g, const ColumnMaps& cols, const Slice& sl) {
  const int64_t nx = g.dims[0], ny = g.dims[1];
  for (int64_t j = 0; j < ny; ++j) {
    for (int64_t i = 0; i < nx; ++i) {
      const size_t c = size_t(i + nx * j);
      if (cols.kind[c] == kColAir) continue;
      vessel_and_spine_voxel(voxel_centre(g, i, j, sl.z), sl.labels[c], sl.hu[c]);
    }
  }
}

// Gas pockets in the bowel.
void paint_gas(const std::vector<Sphere>& gas, const ImageGeometry& g, const Warp& warp,
               const Slice& sl) {
  const int64_t nx = g.dims[0];
  for (const Sphere& sphere : gas) {
    const double r = sphere.r + warp.max_mm();
    if (std::abs(sl.z - sphere.c.z()) > r) continue;
    const auto [i0, i1] = index_range(g, 0, sphere.c.x() - r, sphere.c.x() + r);
    const auto [j0, j1] = index_range(g, 1, sphere.c.y() - r, sphere.c.y() + r);
    for (int64_t j = j0; j <= j1; ++j) {
      for (int64_t i = i0; i <= i1; ++i) {
        const size_t c = size_t(i + nx * j);
        const Vec3 p = voxel_centre(g, i, j, sl.z);
        if (sl.labels[c] == kBowel && (warp.source(p) - sphere.c).norm() <= sphere.r) {
          sl.hu[c] = kBowelGasHu;
        }
      }
    }
  }
}

// Index ranges of the tumor's bounding box.
struct IndexBox {
  std::pair<int64_t, int64_t> x, y, z;
};

IndexBox tumor_box(const ImageGeometry& g, const Warp& warp) {
  IndexBox b;
  const double r = kTumorBoundingR + warp.max_mm();
  b.z = index_range(g, 2, kTumorC.z() - r, kTumorC.z() + r);
  b.x = index_range(g, 0, kTumorC.x() - r, kTumorC.x() + r);
  b.y = index_range(g, 1, kTumorC.y() - r, kTumorC.y() + r);
  return b;
}

// The tumor: liver tissue (vessels carved out) inside the lobes.
void paint_tumor(const ImageGeometry& g, const IndexBox& box, const Warp& warp, const Slice& sl) {
  if (sl.k < box.z.first || sl.k > box.z.second) return;
  const int64_t nx = g.dims[0];
  for (int64_t j = box.y.first; j <= box.y.second; ++j) {
    for (int64_t i = box.x.first; i <= box.x.second; ++i) {
      const size_t c = size_t(i + nx * j);
      if (sl.labels[c] != kLiver && sl.labels[c] != kLiverVessel) continue;
      if (!in_tumor(warp.source(voxel_centre(g, i, j, sl.z)))) continue;
      sl.labels[c] = kLiver;
      sl.hu[c] = kTumorHu;
      sl.tumor[c] = 1;
    }
  }
}

// Noise, clamped to the HU range -1024..3071.
void add_noise(uint64_t noise_key, int64_t slice_size, const Slice& sl) {
  for (int64_t c = 0; c < slice_size; ++c) {
    const int v = int(sl.hu[c]) + noise_hu(noise_key, sl.k * slice_size + c);
    sl.hu[c] = int16_t(std::clamp(v, -1024, 3071));
  }
}

// Paints one slice; each step overrides what the steps before it painted.
void paint_slice(const ImageGeometry& g, const Scene& scene, const ColumnMaps& cols,
                 const IndexBox& tumor, const Warp& warp, uint64_t noise_key, const Slice& sl) {
  paint_body_and_organs(g, cols, warp, sl);
  // Bowel in the fat of the abdominal cavity; liver vessels inside the liver.
  paint_capsules(scene.bowel, g, sl.k, cols, sl.labels, sl.hu, kBowel, warp,
                 [](uint8_t l, uint8_t col) { return l == kFat && col == kColCavity; });
  paint_capsules(scene.liver_vessels, g, sl.k, cols, sl.labels, sl.hu, kLiverVessel, warp,
                 [](uint8_t l, uint8_t) { return l == kLiver; });
  paint_vessels_and_spine(g, cols, sl);
  // Ribs after the spine (inside the body).
  paint_capsules(scene.ribs, g, sl.k, cols, sl.labels, sl.hu, kBone, Warp{},
                 [](uint8_t, uint8_t col) { return col != kColAir; });
  paint_gas(scene.gas, g, warp, sl);
  paint_tumor(g, tumor, warp, sl);
  add_noise(noise_key, g.dims[0] * g.dims[1], sl);
}

}  // namespace

Phantom make_phantom(const PhantomOptions& options) {
  check_options(options);
  const ImageGeometry g = phantom_geometry(options.spacing_mm);
  Phantom ph;
  ph.ct = Volume<int16_t>(g, kLabelHu[kAir]);
  ph.labels = Volume<uint8_t>(g, kAir);
  ph.tumor = Volume<uint8_t>(g, 0);

  const Scene scene = make_scene_parts(options.seed);
  const ColumnMaps cols = make_column_maps(g);
  const Warp warp{options.inhale, options.amplitude_mm};
  const IndexBox tumor = tumor_box(g, warp);
  const uint64_t noise_key = splitmix64(options.seed ^ 0x6E6F697365ull);
  const int64_t nx = g.dims[0], ny = g.dims[1], nz = g.dims[2];
  const int64_t slice_size = nx * ny;
#pragma omp parallel for schedule(dynamic, 1)
  for (int64_t k = 0; k < nz; ++k) {
    const Slice slice{k, g.origin.z() + g.spacing.z() * double(k),
                      ph.labels.data() + k * slice_size, ph.ct.data() + k * slice_size,
                      ph.tumor.data() + k * slice_size};
    paint_slice(g, scene, cols, tumor, warp, noise_key, slice);
  }

  ph.vulnerability = nlohmann::json::parse(preset_sources().at("phantom"));
  spdlog::debug("phantom: {}x{}x{} voxels of {} mm, {} vessel tube pieces, seed {}", nx, ny, nz,
                options.spacing_mm, scene.liver_vessels.size(), options.seed);
  return ph;
}

void write_phantom(const Phantom& phantom, const std::string& dir) {
  // Staged: a failed write (a full disk) leaves no folder, never one mixing two seeds; an
  // existing folder is replaced only when this tool wrote it (foundation/output_files.hpp).
  StagedDirectory out(dir);
  write_volume(phantom.ct, out.file("ct.nii.gz"));
  write_volume(phantom.labels, out.file("labels.nii.gz"));
  write_volume(phantom.tumor, out.file("tumor.nii.gz"));
  write_text_file(out.file("vulnerability.json"), phantom.vulnerability.dump(2) + "\n");
  out.commit();
}

Eigen::Vector3d breathing_displacement(const Eigen::Vector3d& p, double inhale,
                                       double amplitude_mm) {
  const double d = p.z() - dome_z(p.x(), p.y());  // vertical distance from the diaphragm
  const double w = std::exp(-0.5 * d * d / (kBreathingFadeSigmaMm * kBreathingFadeSigmaMm));
  return inhale * amplitude_mm * w * breathing_direction();
}

Eigen::Vector3d breathing_wall_displacement(const Eigen::Vector3d& p, double inhale,
                                            double amplitude_mm) {
  return wall_displacement(p, inhale, amplitude_mm);
}

Eigen::Vector3d breathing_position(const Eigen::Vector3d& p_rest, double inhale,
                                   double amplitude_mm) {
  // q = p_rest + u(q): a contraction (|grad u| < 0.5 for amplitudes up to the maximum).
  Vec3 q = p_rest;
  for (int it = 0; it < 100; ++it) {
    const Vec3 next = p_rest + breathing_displacement(q, inhale, amplitude_mm);
    const bool done = (next - q).norm() < 1e-9;
    q = next;
    if (done) break;
  }
  return q;
}

double breathing_inhale(int phase, int phases) {
  const double s = std::sin(kPi * double(phase) / double(phases));
  return s * s;
}

nlohmann::json write_breathing_phantom(const PhantomOptions& base, int phases,
                                       const std::string& dir,
                                       const std::function<void(int, const Phantom&)>& progress) {
  if (phases < 2 || phases > 50) {
    throw Error("phantom: " + std::to_string(phases) + " breathing phases are not usable (expected "
                "2 to 50)");
  }
  check_options(base);
  StagedDirectory out(dir);
  nlohmann::json list = nlohmann::json::array();
  Vec3 rest_centroid = Vec3::Zero();
  nlohmann::json vulnerability;
  for (int k = 0; k < phases; ++k) {
    PhantomOptions o = base;
    o.inhale = breathing_inhale(k, phases);
    const Phantom ph = make_phantom(o);
    // The tumor's centroid at rest, from the mask: the motion curve starts there.
    if (k == 0) {
      const ImageGeometry& g = ph.tumor.geometry();
      Vec3 sum = Vec3::Zero();
      int64_t n = 0;
      for (int64_t kk = 0; kk < g.dims[2]; ++kk) {
        for (int64_t j = 0; j < g.dims[1]; ++j) {
          for (int64_t i = 0; i < g.dims[0]; ++i) {
            if (ph.tumor(i, j, kk)) {
              sum += g.index_to_physical(i, j, kk);
              ++n;
            }
          }
        }
      }
      rest_centroid = sum / double(std::max<int64_t>(n, 1));
      vulnerability = ph.vulnerability;
    }
    const std::string name = fmt::format("phase{:02d}", k);
    std::filesystem::create_directories(std::filesystem::path(out.path()) / name);
    write_volume(ph.ct, out.file(name + "/ct.nii.gz"));
    write_volume(ph.labels, out.file(name + "/labels.nii.gz"));
    write_volume(ph.tumor, out.file(name + "/tumor.nii.gz"));
    const Vec3 c = breathing_position(rest_centroid, o.inhale, o.amplitude_mm);
    list.push_back({{"name", name},
                    {"cycle_fraction", double(k) / double(phases)},
                    {"inhale", o.inhale},
                    {"labels", name + "/labels.nii.gz"},
                    {"tumor", name + "/tumor.nii.gz"},
                    {"ct", name + "/ct.nii.gz"},
                    {"tumor_centroid_lps_mm", {c.x(), c.y(), c.z()}}});
    if (progress) progress(k, ph);
  }
  write_text_file(out.file("vulnerability.json"), vulnerability.dump(2) + "\n");
  const Vec3 dir_lps = breathing_direction().normalized();
  nlohmann::json doc = {
      {"format", "crepuscular-phases"},
      {"version", 1},
      {"description",
       "breathing cycle of the built-in phantom: phase 0 end-exhale, the middle phase "
       "end-inhale; paths are relative to this file"},
      {"vulnerability", "vulnerability.json"},
      {"motion",
       {{"amplitude_mm", base.amplitude_mm},
        {"direction_lps", {dir_lps.x(), dir_lps.y(), dir_lps.z()}},
        {"fade_sigma_mm", kBreathingFadeSigmaMm},
        {"inhale", "sin^2(pi k / phases)"},
        {"moves", "diaphragm, liver and its vessels, tumor, kidneys, spleen, bowel, heart, lungs"},
        {"wall", "the anterior abdominal wall rises (-y), by up to 0.7 amplitude at the skin"},
        {"stays", "posterior wall, ribs, spine, aorta, vena cava"}}},
      {"seed", base.seed},
      {"spacing_mm", base.spacing_mm},
      {"phases", list}};
  write_text_file(out.file("phases.json"), doc.dump(2) + "\n");
  out.commit();
  return doc;
}

}  // namespace crepuscular::planning
