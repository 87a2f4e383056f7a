// Tests of the built-in phantom: determinism, grid geometry, anatomy where the demo expects
// it (LPS mm), tumor size and placement, and straight approaches that are safe and unsafe.
#include "planning/simulation/phantom.hpp"

#include <gtest/gtest.h>

#include <Eigen/Core>
#include <array>
#include <cmath>
#include <filesystem>
#include <limits>
#include <set>
#include <string>

#include "foundation/error.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/preprocessing/vulnerability.hpp"
#include "tests/support/temporary_folder.hpp"

namespace crepuscular::planning {
namespace {

constexpr double kPi = 3.14159265358979323846;

// Label values of the phantom (planning/simulation/phantom.cpp, planning/preprocessing/presets/phantom.json).
enum : uint8_t {
  kAir = 0,
  kFat = 1,
  kMuscle = 2,
  kBone = 3,
  kAorta = 4,
  kVenaCava = 5,
  kLiver = 6,
  kLiverVessel = 7,
  kKidney = 8,
  kLung = 9,
  kBowel = 10,
  kSpleen = 11,
  kGallbladder = 12
};

PhantomOptions options(double spacing_mm, uint64_t seed) {
  PhantomOptions o;
  o.spacing_mm = spacing_mm;
  o.seed = seed;
  return o;
}

// Built once per process: most tests read the same 3 mm phantom.
const Phantom& phantom_3mm() {
  static const Phantom p = make_phantom(options(3.0, 1));
  return p;
}
const Phantom& phantom_4mm() {
  static const Phantom p = make_phantom(options(4.0, 1));
  return p;
}

struct Stats {
  int64_t count = 0;
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
  Eigen::Vector3d min = Eigen::Vector3d::Constant(std::numeric_limits<double>::max());
  Eigen::Vector3d max = Eigen::Vector3d::Constant(std::numeric_limits<double>::lowest());
};

// Count, centroid (LPS mm) and bounding box of the voxels where pred(offset, position) holds.
template <typename Pred>
Stats stats_where(const Volume<uint8_t>& v, Pred pred) {
  Stats s;
  const auto& d = v.dims();
  for (int64_t k = 0; k < d[2]; ++k) {
    for (int64_t j = 0; j < d[1]; ++j) {
      for (int64_t i = 0; i < d[0]; ++i) {
        const Eigen::Vector3d p = v.index_to_physical(i, j, k);
        if (!pred(v(i, j, k), p)) continue;
        ++s.count;
        s.centroid += p;
        s.min = s.min.cwiseMin(p);
        s.max = s.max.cwiseMax(p);
      }
    }
  }
  if (s.count > 0) s.centroid /= double(s.count);
  return s;
}

Stats label_stats(const Phantom& ph, uint8_t label) {
  return stats_where(ph.labels, [label](uint8_t l, const Eigen::Vector3d&) { return l == label; });
}

Stats tumor_stats(const Phantom& ph) {
  return stats_where(ph.tumor, [](uint8_t t, const Eigen::Vector3d&) { return t != 0; });
}

double equivalent_diameter_mm(const Phantom& ph) {
  const double volume = double(tumor_stats(ph).count) * ph.tumor.geometry().voxel_volume_mm3();
  return std::cbrt(6.0 * volume / kPi);
}

TEST(Phantom, SameSeedGivesIdenticalVolumes) {
  const Phantom a = make_phantom(options(4.0, 7));
  const Phantom b = make_phantom(options(4.0, 7));
  EXPECT_TRUE(a.labels.geometry().same_grid(b.labels.geometry(), 0.0));
  EXPECT_TRUE(a.labels.values() == b.labels.values());
  EXPECT_TRUE(a.ct.values() == b.ct.values());
  EXPECT_TRUE(a.tumor.values() == b.tumor.values());
  EXPECT_EQ(a.vulnerability, b.vulnerability);
}

TEST(Phantom, DifferentSeedGivesDifferentVesselTree) {
  const Phantom& a = phantom_4mm();  // seed 1
  const Phantom b = make_phantom(options(4.0, 2));
  int64_t differing = 0, vessels = 0;
  for (int64_t n = 0; n < a.labels.voxel_count(); ++n) {
    const bool va = a.labels[n] == kLiverVessel, vb = b.labels[n] == kLiverVessel;
    differing += va != vb;
    vessels += va;
  }
  // Two random trees share little more than the hilum: most vessel voxels differ.
  EXPECT_GT(differing, vessels / 4) << "vessel voxels (seed 1): " << vessels;
  EXPECT_FALSE(a.ct.values() == b.ct.values());  // the noise differs too
}

TEST(Phantom, GridIsCentredWithRequestedSpacing) {
  for (const double s : {3.0, 4.0, 7.5}) {
    const Phantom ph = s == 3.0 ? phantom_3mm() : make_phantom(options(s, 1));
    const ImageGeometry& g = ph.labels.geometry();
    EXPECT_TRUE(g.spacing.isApprox(Eigen::Vector3d::Constant(s))) << "spacing " << s;
    EXPECT_TRUE(g.direction.isIdentity());
    const Eigen::Vector3d extent(360, 260, 240);
    for (int a = 0; a < 3; ++a) {
      EXPECT_NEAR(double(g.dims[size_t(a)]) * s, extent[a], s) << "axis " << a;
    }
    // Centre of the grid at (0, 0, 0).
    const Eigen::Vector3d centre = g.index_to_physical(
        Eigen::Vector3d(double(g.dims[0] - 1), double(g.dims[1] - 1), double(g.dims[2] - 1)) * 0.5);
    EXPECT_LT(centre.norm(), 1e-9) << "spacing " << s;
    EXPECT_TRUE(g.same_grid(ph.ct.geometry()));
    EXPECT_TRUE(g.same_grid(ph.tumor.geometry()));
  }
}

TEST(Phantom, AllTwelveLabelsArePresent) {
  const Phantom& ph = phantom_3mm();
  std::array<int64_t, 256> counts{};
  for (const uint8_t l : ph.labels.values()) ++counts[l];
  for (int l = 0; l <= 12; ++l) EXPECT_GT(counts[size_t(l)], 0) << "label " << l;
  for (int l = 13; l < 256; ++l) EXPECT_EQ(counts[size_t(l)], 0) << "label " << l;
  // Tumor mask is binary.
  for (const uint8_t t : ph.tumor.values()) ASSERT_LE(t, 1);
}

TEST(Phantom, TumorEquivalentDiameterIsBetween20And30Mm) {
  // Designed as 25 mm; voxelisation at 3 mm changes the volume by a few percent.
  const double d = equivalent_diameter_mm(phantom_3mm());
  EXPECT_GE(d, 20.0);
  EXPECT_LE(d, 30.0);
  EXPECT_NEAR(d, 25.0, 2.0);
}

TEST(Phantom, TumorLiesInsideTheLiverAndNoVesselCrossesIt) {
  for (const Phantom* ph : {&phantom_3mm(), &phantom_4mm()}) {
    int64_t tumor = 0;
    for (int64_t n = 0; n < ph->tumor.voxel_count(); ++n) {
      if (!ph->tumor[n]) continue;
      ++tumor;
      ASSERT_EQ(ph->labels[n], kLiver) << "tumor voxel " << n << " is not liver";
    }
    EXPECT_GT(tumor, 0);
    // No vessel voxel in the tumor's 6-neighbourhood either: the tree is routed around it.
    const auto& d = ph->labels.dims();
    for (int64_t k = 1; k + 1 < d[2]; ++k) {
      for (int64_t j = 1; j + 1 < d[1]; ++j) {
        for (int64_t i = 1; i + 1 < d[0]; ++i) {
          if (!ph->tumor(i, j, k)) continue;
          for (const auto& o : {Index3{1, 0, 0}, Index3{-1, 0, 0}, Index3{0, 1, 0},
                                Index3{0, -1, 0}, Index3{0, 0, 1}, Index3{0, 0, -1}}) {
            EXPECT_NE(ph->labels(i + o[0], j + o[1], k + o[2]), kLiverVessel);
          }
        }
      }
    }
  }
}

TEST(Phantom, TumorIsInTheLateralRightLobe) {
  const Phantom& ph = phantom_3mm();
  const Stats t = tumor_stats(ph);
  const Stats liver = label_stats(ph, kLiver);
  EXPECT_LT(t.centroid.x(), liver.centroid.x());  // lateral (patient right) of the liver centre
  EXPECT_NEAR(t.centroid.x(), -92.0, 3.0);
  EXPECT_NEAR(t.centroid.y(), -22.0, 3.0);
  EXPECT_NEAR(t.centroid.z(), 4.0, 3.0);
  // The tumor's CT value differs from the liver's (35 vs 60 HU, noise sigma 10).
  double tumor_hu = 0, liver_hu = 0;
  int64_t nt = 0, nl = 0;
  for (int64_t n = 0; n < ph.ct.voxel_count(); ++n) {
    if (ph.tumor[n]) {
      tumor_hu += ph.ct[n];
      ++nt;
    } else if (ph.labels[n] == kLiver) {
      liver_hu += ph.ct[n];
      ++nl;
    }
  }
  EXPECT_NEAR(tumor_hu / double(nt), 35.0, 3.0);
  EXPECT_NEAR(liver_hu / double(nl), 60.0, 3.0);
}

TEST(Phantom, OrgansLieWhereTheAnatomySaysInLps) {
  const Phantom& ph = phantom_3mm();
  const Stats liver = label_stats(ph, kLiver), spleen = label_stats(ph, kSpleen);
  const Stats aorta = label_stats(ph, kAorta), cava = label_stats(ph, kVenaCava);
  const Stats lungs = label_stats(ph, kLung), kidneys = label_stats(ph, kKidney);
  const Stats bowel = label_stats(ph, kBowel), gallbladder = label_stats(ph, kGallbladder);
  const Stats spine = stats_where(ph.labels, [](uint8_t l, const Eigen::Vector3d& p) {
    return l == kBone && std::abs(p.x()) < 25.0;
  });
  EXPECT_LT(liver.centroid.x(), -20.0);  // patient right is -x in LPS
  EXPECT_GT(spleen.centroid.x(), 40.0);  // patient left
  EXPECT_GT(aorta.centroid.x(), 0.0);    // aorta left of the midline, cava right
  EXPECT_LT(cava.centroid.x(), 0.0);
  EXPECT_GT(spine.centroid.y(), aorta.centroid.y() + 15.0);  // spine posterior (+y) of aorta
  EXPECT_GT(spine.centroid.y(), cava.centroid.y() + 15.0);
  EXPECT_GT(lungs.centroid.z(), kidneys.centroid.z() + 60.0);  // lungs superior (+z)
  EXPECT_GT(lungs.centroid.z(), liver.centroid.z());
  EXPECT_GT(kidneys.centroid.y(), liver.centroid.y());  // kidneys posterior of the liver
  EXPECT_GT(bowel.centroid.x(), 0.0);                   // bowel: lower left, anterior
  EXPECT_LT(bowel.centroid.z(), kidneys.centroid.z());
  EXPECT_LT(bowel.centroid.y(), spine.centroid.y());
  EXPECT_LT(gallbladder.centroid.z(), liver.centroid.z());  // under the liver
  // Two kidneys, one either side of the spine.
  const Stats right_kidney = stats_where(
      ph.labels, [](uint8_t l, const Eigen::Vector3d& p) { return l == kKidney && p.x() < 0; });
  const Stats left_kidney = stats_where(
      ph.labels, [](uint8_t l, const Eigen::Vector3d& p) { return l == kKidney && p.x() > 0; });
  EXPECT_NEAR(right_kidney.count, left_kidney.count, 0.2 * double(left_kidney.count));
  // Every structure inside the body: air only outside.
  EXPECT_GT(label_stats(ph, kFat).count, 0);
  EXPECT_GT(label_stats(ph, kMuscle).count, 0);
}

TEST(Phantom, RibsLieLateralToTheLiver) {
  const Phantom& ph = phantom_3mm();
  const Stats liver = label_stats(ph, kLiver);
  // Bone further right than any liver voxel, at the liver's height: the right ribs.
  const Stats ribs = stats_where(ph.labels, [&](uint8_t l, const Eigen::Vector3d& p) {
    return l == kBone && p.x() < liver.min.x() && p.z() > liver.min.z() && p.z() < liver.max.z();
  });
  EXPECT_GT(ribs.count, 20);
  // And on the left side as well, mirrored.
  const Stats left_ribs = stats_where(ph.labels, [&](uint8_t l, const Eigen::Vector3d& p) {
    return l == kBone && p.x() > -liver.min.x() && p.z() > liver.min.z();
  });
  EXPECT_GT(left_ribs.count, 20);
}

TEST(Phantom, TumorVolumeAgreesAcrossSpacings) {
  // Geometry is defined in mm: only the voxelisation error differs between 3 and 4 mm.
  const double v3 = double(tumor_stats(phantom_3mm()).count) * 27.0;
  const double v4 = double(tumor_stats(phantom_4mm()).count) * 64.0;
  EXPECT_NEAR(v4 / v3, 1.0, 0.15) << "3 mm: " << v3 << " mm3, 4 mm: " << v4 << " mm3";
}

TEST(Phantom, HasSafeAndUnsafeStraightApproaches) {
  // Straight lines from the tumor centroid in 200 directions (Fibonacci sphere) out to 150 mm,
  // sampled every 0.5 mm at the nearest voxel: safe when they meet only air, fat, muscle and liver;
  // unsafe when they meet bone, aorta, vena cava or lung.
  for (const Phantom* ph : {&phantom_3mm(), &phantom_4mm()}) {
    const Eigen::Vector3d c = tumor_stats(*ph).centroid;
    const ImageGeometry& g = ph->labels.geometry();
    constexpr int kDirections = 200;
    int safe = 0, unsafe = 0;
    for (int n = 0; n < kDirections; ++n) {
      const double z = 1.0 - 2.0 * (n + 0.5) / kDirections;
      const double r = std::sqrt(1.0 - z * z);
      const double phi = n * kPi * (3.0 - std::sqrt(5.0));
      const Eigen::Vector3d dir(r * std::cos(phi), r * std::sin(phi), z);
      std::set<int> met;
      for (double t = 0.0; t <= 150.0; t += 0.5) {
        const Index3 idx = g.nearest_index(c + t * dir);
        if (!g.contains(idx[0], idx[1], idx[2])) break;
        met.insert(ph->labels(idx[0], idx[1], idx[2]));
      }
      bool only_safe = true, any_unsafe = false;
      for (const int l : met) {
        only_safe = only_safe && (l == kAir || l == kFat || l == kMuscle || l == kLiver);
        any_unsafe = any_unsafe || l == kBone || l == kAorta || l == kVenaCava || l == kLung;
      }
      safe += only_safe;
      unsafe += any_unsafe;
    }
    EXPECT_GT(safe, kDirections / 10) << "safe " << safe << ", unsafe " << unsafe;
    EXPECT_GT(unsafe, kDirections / 10) << "safe " << safe << ", unsafe " << unsafe;
  }
}

TEST(Phantom, SafeApproachesHoldForOtherSeeds) {
  // The vessel tree is random; the lateral approach must stay free for any seed. Checks the
  // horizontal lateral ray (-x) from the tumor centroid for seeds 1..6 at 4 mm.
  for (uint64_t seed = 1; seed <= 6; ++seed) {
    const Phantom ph = seed == 1 ? phantom_4mm() : make_phantom(options(4.0, seed));
    const Eigen::Vector3d c = tumor_stats(ph).centroid;
    const ImageGeometry& g = ph.labels.geometry();
    for (double t = 0.0; t <= 100.0; t += 0.5) {
      const Index3 idx = g.nearest_index(c + t * Eigen::Vector3d(-1, 0, 0));
      if (!g.contains(idx[0], idx[1], idx[2])) break;
      const int l = ph.labels(idx[0], idx[1], idx[2]);
      ASSERT_TRUE(l == kAir || l == kFat || l == kMuscle || l == kLiver)
          << "seed " << seed << ": label " << l << " at " << t << " mm lateral of the tumor";
    }
  }
}

TEST(Phantom, CtValuesFollowTheLabelsWithMildNoise) {
  const Phantom& ph = phantom_3mm();
  double sum = 0, sum2 = 0;
  int64_t n_air = 0;
  for (int64_t n = 0; n < ph.ct.voxel_count(); ++n) {
    if (ph.labels[n] != kAir) continue;
    const double v = ph.ct[n];
    sum += v;
    sum2 += v * v;
    ++n_air;
  }
  const double mean = sum / double(n_air);
  const double sd = std::sqrt(sum2 / double(n_air) - mean * mean);
  EXPECT_NEAR(mean, -1000.0, 1.0);
  EXPECT_NEAR(sd, 10.0, 1.0);  // noise sigma ~10 HU
  const Stats bone = label_stats(ph, kBone);
  double bone_hu = 0;
  for (int64_t n = 0; n < ph.ct.voxel_count(); ++n) bone_hu += ph.labels[n] == kBone ? ph.ct[n] : 0;
  EXPECT_GT(bone_hu / double(bone.count), 300.0);
}

TEST(Phantom, VulnerabilityTableListsEveryLabel) {
  const nlohmann::json& j = phantom_3mm().vulnerability;
  EXPECT_EQ(j.at("name"), "phantom");
  ASSERT_EQ(j.at("levels").size(), 5u);
  EXPECT_EQ(j.at("levels").back().at("blocking_per_mm").get<double>(), 100.0);
  // Expected levels, by label value 1..12 (the phantom's design).
  const std::array<int, 13> level = {-1, 0, 1, 4, 4, 4, 0, 3, 2, 4, 2, 2, 2};
  std::set<int> seen;
  for (const auto& l : j.at("labels")) {
    const int v = l.at("value").get<int>();
    ASSERT_GE(v, 1);
    ASSERT_LE(v, 12);
    EXPECT_EQ(l.at("level").get<int>(), level[size_t(v)]) << "label " << v;
    seen.insert(v);
  }
  EXPECT_EQ(seen.size(), 12u);
  // The project's parser accepts it, and it is the preset "phantom".
  const VulnerabilityTable table = VulnerabilityTable::from_json(j, "phantom.vulnerability");
  EXPECT_EQ(table.blocking_of_label(7, "phantom"), 1.0);
  EXPECT_EQ(table.to_json(), VulnerabilityTable::preset("phantom").to_json());
}

TEST(Phantom, RejectsUnusableSpacing) {
  for (const double s : {0.0, -1.0, -3.0, 0.1, 20.0, std::numeric_limits<double>::quiet_NaN(),
                         std::numeric_limits<double>::infinity()}) {
    EXPECT_THROW(make_phantom(options(s, 1)), Error) << "spacing " << s;
  }
}

TEST(Phantom, WritesFourFilesThatReadBack) {
  const test::TemporaryFolder folder;
  const std::string dir = folder.file("out");
  const Phantom ph = make_phantom(options(6.0, 3));
  write_phantom(ph, dir);  // creates the missing folders
  for (const char* name : {"ct.nii.gz", "labels.nii.gz", "tumor.nii.gz", "vulnerability.json"}) {
    EXPECT_TRUE(std::filesystem::exists(dir + "/" + name)) << name;
  }
  const Volume<uint8_t> labels = read_volume<uint8_t>(dir + "/labels.nii.gz");
  EXPECT_TRUE(labels.geometry().same_grid(ph.labels.geometry(), 1e-4));
  EXPECT_TRUE(labels.values() == ph.labels.values());
  const Volume<int16_t> ct = read_volume<int16_t>(dir + "/ct.nii.gz");
  EXPECT_TRUE(ct.values() == ph.ct.values());
  const Volume<uint8_t> tumor = read_mask(dir + "/tumor.nii.gz");
  EXPECT_TRUE(tumor.values() == ph.tumor.values());
}

// Breathing (docs/ARCHITECTURE.md §10). Phases of a 10-phase cycle at 12 mm, 3 mm voxels.
Phantom breathing_phase(int phase) {
  PhantomOptions o = options(3.0, 1);
  o.inhale = breathing_inhale(phase, 10);
  o.amplitude_mm = 12.0;
  return make_phantom(o);
}

TEST(PhantomBreathing, DisplacementIsTwelveMmCaudalAtTheDomeAndFadesBelow) {
  // At the right dome's apex (x -65, y -10, z 80) the full displacement: 12 mm caudal, 0.35 x 12
  // anterior (LPS: -z, -y).
  const Eigen::Vector3d u = breathing_displacement(Eigen::Vector3d(-65, -10, 80), 1.0, 12.0);
  EXPECT_NEAR(u.x(), 0.0, 1e-12);
  EXPECT_NEAR(u.y(), -0.35 * 12.0, 1e-9);
  EXPECT_NEAR(u.z(), -12.0, 1e-9);
  // 70 mm below the dome (one sigma): exp(-1/2) of it.
  const Eigen::Vector3d v = breathing_displacement(Eigen::Vector3d(-65, -10, 10), 1.0, 12.0);
  EXPECT_NEAR(v.z(), -12.0 * std::exp(-0.5), 1e-9);
  // The cycle: phase 0 at rest, the middle phase full inhale, symmetric.
  EXPECT_EQ(breathing_inhale(0, 10), 0.0);
  EXPECT_NEAR(breathing_inhale(5, 10), 1.0, 1e-15);
  EXPECT_NEAR(breathing_inhale(2, 10), breathing_inhale(8, 10), 1e-15);
}

TEST(PhantomBreathing, TumorCentroidFollowsTheMotionCurveAndBonesStay) {
  const Phantom rest = breathing_phase(0);
  // Phase 0 is the phantom at rest, voxel for voxel.
  EXPECT_TRUE(rest.labels.values() == phantom_3mm().labels.values());
  const Eigen::Vector3d c0 = tumor_stats(rest).centroid;
  const Stats bone0 = label_stats(rest, kBone);
  double largest = 0.0;
  for (const int phase : {2, 5}) {
    const Phantom ph = breathing_phase(phase);
    const Eigen::Vector3d c = tumor_stats(ph).centroid;
    const Eigen::Vector3d expected = breathing_position(c0, breathing_inhale(phase, 10), 12.0);
    EXPECT_LT((c - expected).norm(), 0.5)
        << "phase " << phase << ": centroid " << c.transpose() << ", curve "
        << expected.transpose();
    // Mostly cranio-caudal (caudal = -z), with a smaller anterior (-y) component.
    const Eigen::Vector3d moved = c - c0;
    EXPECT_LT(moved.z(), -2.0) << "phase " << phase;
    EXPECT_LT(moved.y(), 0.0) << "phase " << phase;
    EXPECT_GT(std::abs(moved.z()), 2.0 * std::abs(moved.y())) << "phase " << phase;
    largest = std::max(largest, moved.norm());
    // Bones stay, voxel for voxel; air turns to body only in front of the mid-coronal plane,
    // where the anterior wall rises, and never the other way.
    int64_t bone_changed = 0, air_behind = 0, air_to_body = 0, body_to_air = 0;
    for (int64_t n = 0; n < ph.labels.voxel_count(); ++n) {
      if ((rest.labels[n] == kBone) != (ph.labels[n] == kBone)) ++bone_changed;
      const bool was_air = rest.labels[n] == kAir, is_air = ph.labels[n] == kAir;
      if (was_air == is_air || rest.labels[n] == kLung || ph.labels[n] == kLung) continue;
      const auto ijk = ph.labels.geometry().index_of_offset(n);
      if (ph.labels.index_to_physical(ijk[0], ijk[1], ijk[2]).y() >= 0) ++air_behind;
      (was_air ? air_to_body : body_to_air)++;
    }
    EXPECT_EQ(bone_changed, 0) << "phase " << phase;
    EXPECT_EQ(air_behind, 0) << "phase " << phase;
    EXPECT_EQ(body_to_air, 0) << "phase " << phase;
    EXPECT_GT(air_to_body, 0) << "phase " << phase;
    EXPECT_EQ(label_stats(ph, kBone).count, bone0.count) << "phase " << phase;
  }
  // The liver 70 mm below the dome moves about 12 x exp(-1/2) ~ 7.3 mm x 1.06 at end-inhale.
  EXPECT_GT(largest, 6.0);
  EXPECT_LT(largest, 9.0);
}

// The anterior skin at the abdomen's middle (x = 0, z = -30 mm) rises by 0.7 x 12 mm x inhale
// (within a voxel of 3 mm); the posterior skin there stays.
TEST(PhantomBreathing, AnteriorWallRisesWithInhalation) {
  const auto skin = [](const Phantom& ph, bool anterior) {
    const auto& g = ph.labels.geometry();
    const Eigen::Vector3d ijk = g.physical_to_index(Eigen::Vector3d(0, 0, -30));
    const int64_t i = std::llround(ijk.x()), k = std::llround(ijk.z());
    const int64_t n = g.dims[1];
    for (int64_t s = 0; s < n; ++s) {
      const int64_t j = anterior ? s : n - 1 - s;
      if (ph.labels(i, j, k) != kAir) return g.index_to_physical(i, j, k).y();
    }
    return 0.0;
  };
  const Phantom rest = breathing_phase(0);
  for (const int phase : {2, 5}) {
    const Phantom ph = breathing_phase(phase);
    const double rise = skin(rest, true) - skin(ph, true);
    EXPECT_NEAR(rise, 0.7 * 12.0 * breathing_inhale(phase, 10), 3.0) << "phase " << phase;
    EXPECT_NEAR(breathing_wall_displacement(Eigen::Vector3d(0, -105, -30), breathing_inhale(phase, 10), 12.0).y(),
                -0.7 * 12.0 * breathing_inhale(phase, 10), 1e-9);
    EXPECT_EQ(skin(ph, false), skin(rest, false)) << "phase " << phase;
  }
}

TEST(PhantomBreathing, DiaphragmDescendsByTheAmplitude) {
  // The highest liver voxel in the column under the right dome drops by ~12 mm (one voxel of 3 mm).
  const auto liver_top = [](const Phantom& ph) {
    const auto& g = ph.labels.geometry();
    const Eigen::Vector3d ijk = g.physical_to_index(Eigen::Vector3d(-65, -10, 0));
    const int64_t i = std::llround(ijk.x()), j = std::llround(ijk.y());
    for (int64_t k = g.dims[2] - 1; k >= 0; --k) {
      if (ph.labels(i, j, k) == kLiver || ph.labels(i, j, k) == kLiverVessel) {
        return g.index_to_physical(i, j, k).z();
      }
    }
    return -1e9;
  };
  const double drop = liver_top(breathing_phase(0)) - liver_top(breathing_phase(5));
  EXPECT_NEAR(drop, 12.0, 3.0);
}

TEST(PhantomBreathing, WritesPhasesJsonThatListsEveryPhase) {
  const test::TemporaryFolder folder;
  const std::string dir = folder.file("cycle");
  PhantomOptions o = options(8.0, 2);
  const nlohmann::json doc = write_breathing_phantom(o, 3, dir);
  ASSERT_EQ(doc.at("phases").size(), 3u);
  for (const auto& p : doc.at("phases")) {
    for (const char* key : {"labels", "tumor", "ct"}) {
      EXPECT_TRUE(std::filesystem::exists(dir + "/" + p.at(key).get<std::string>())) << key;
    }
  }
  EXPECT_TRUE(std::filesystem::exists(dir + "/phases.json"));
  EXPECT_TRUE(std::filesystem::exists(dir + "/vulnerability.json"));
  EXPECT_THROW(write_breathing_phantom(o, 1, folder.file("one")), Error);
  o.amplitude_mm = 100.0;
  EXPECT_THROW(write_breathing_phantom(o, 3, folder.file("far")), Error);
}

}  // namespace
}  // namespace crepuscular::planning
