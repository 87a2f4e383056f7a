// The phases of a breathing cycle combined voxel by voxel (planning/breathing/combiner.hpp): the
// least safe phase wins, unknown in any phase stays unknown, and the class change share.
#include "planning/breathing/combiner.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <memory>
#include <vector>

#include "foundation/error.hpp"
#include "planning/safety/unknown.hpp"
#include "tests/support/grids.hpp"

namespace crepuscular::planning {
namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();

// A 4-voxel "result" with SVV and ISBV values and the voxel states given.
PathSafetyResult result(std::array<float, 4> svv, std::array<float, 4> isbv) {
  PathSafetyResult r;
  r.grid.geometry = test::cube_grid(1, 1.0);
  r.grid.geometry.dims = {4, 1, 1};
  r.grid.max_sq = 9;  // the region of interest: every voxel (within 3 of voxel 0)
  r.values = kernels::kSvv | kernels::kIsbv;
  r.volumes[0] = Volume<float>(r.grid.geometry, 0.0f);
  r.volumes[1] = Volume<float>(r.grid.geometry, 0.0f);
  for (int64_t i = 0; i < 4; ++i) {
    r.volumes[0][i] = svv[size_t(i)];
    r.volumes[1][i] = isbv[size_t(i)];
  }
  r.seconds = 1.0;
  r.rays = 10;
  return r;
}

Volume<uint8_t> states(std::array<uint8_t, 4> s, const ImageGeometry& g) {
  Volume<uint8_t> v(g, 0);
  for (int64_t i = 0; i < 4; ++i) v[i] = s[size_t(i)];
  return v;
}

TEST(PhaseCombiner, LeastSafePhaseWinsAndUnknownInAnyPhaseIsUnknown) {
  // Voxel 0: computed everywhere; voxel 1: unknown (outside the scan) in phase 1 only; voxel 2:
  // not computed anywhere; voxel 3: computed everywhere.
  const PathSafetyResult a = result({95, 80, kNaN, 40}, {0.0f, 2.0f, kNaN, 7.0f});
  const PathSafetyResult b = result({60, kNaN, kNaN, 45}, {3.0f, kNaN, kNaN, 1.0f});
  const PathSafetyResult c = result({99, 90, kNaN, 30}, {1.0f, 0.5f, kNaN, 2.0f});
  const ImageGeometry& g = a.grid.geometry;
  PhaseCombiner combiner;
  combiner.add(a, states({1, 1, 0, 1}, g));
  combiner.add(b, states({1, 2, 0, 1}, g));
  combiner.add(c, states({1, 1, 0, 1}, g));
  const PathSafetyResult& m = combiner.combined();
  EXPECT_EQ(combiner.phases(), 3);
  EXPECT_EQ(m.volumes[0][0], 60.0f);  // svv: the minimum
  EXPECT_EQ(m.volumes[1][0], 3.0f);   // isbv: the maximum
  EXPECT_EQ(m.volumes[0][3], 30.0f);
  EXPECT_EQ(m.volumes[1][3], 7.0f);
  EXPECT_TRUE(std::isnan(m.volumes[0][1]));  // unknown in phase 1: unknown
  EXPECT_TRUE(std::isnan(m.volumes[1][1]));
  EXPECT_EQ(combiner.region()[1], kRegionUnknown);
  EXPECT_EQ(combiner.region()[2], kRegionNotComputed);
  EXPECT_EQ(combiner.region()[0], kRegionComputed);
  EXPECT_EQ(combiner.other_extreme(0)[0], 99.0f);  // svv's best phase
  EXPECT_EQ(combiner.other_extreme(1)[3], 1.0f);   // isbv's best phase
  EXPECT_DOUBLE_EQ(m.seconds, 3.0);
  EXPECT_EQ(m.rays, 30u);
  // SVV classes safe >= 90, dangerous < 50: voxel 0 ranges 60..99 (medium to safe: changes),
  // voxel 3 ranges 30..45 (dangerous throughout): 1 of the 2 computed voxels changes.
  SafetyClasses svv;
  svv.higher_is_safer = true;
  svv.safe = 90;
  svv.dangerous = 50;
  EXPECT_DOUBLE_EQ(combiner.class_change_share(0, svv), 0.5);
}

// One phase is its own other extreme (the volumes a second fold would write are made beside the
// first): no class changes over a cycle of one phase.
TEST(PhaseCombiner, OnePhaseIsItsOwnOtherExtreme) {
  for (const bool keep : {false, true}) {
    const PathSafetyResult a = result({95, 80, kNaN, 40}, {0.0f, 2.0f, kNaN, 7.0f});
    PhaseCombiner combiner;
    combiner.keep_earlier(keep ? 1 : 0);
    combiner.add(a, states({1, 1, 0, 1}, a.grid.geometry));
    for (int v = 0; v < 2; ++v) {
      for (int64_t i = 0; i < 4; ++i) {
        const float x = a.volumes[size_t(v)][i], y = combiner.other_extreme(v)[i];
        EXPECT_TRUE(std::isnan(x) ? std::isnan(y) : x == y) << keep << " " << v << " " << i;
      }
    }
    SafetyClasses svv;
    svv.higher_is_safer = true;
    svv.safe = 90;
    svv.dangerous = 50;
    EXPECT_DOUBLE_EQ(combiner.class_change_share(0, svv), 0.0);
    // A second phase folds into the volumes made beside the first: the other extreme of two.
    combiner.add(result({60, 85, kNaN, 45}, {3.0f, 1.0f, kNaN, 1.0f}),
                 states({1, 1, 0, 1}, a.grid.geometry));
    EXPECT_EQ(combiner.other_extreme(0)[0], 95.0f);
    EXPECT_EQ(combiner.other_extreme(0)[1], 85.0f);
    EXPECT_EQ(combiner.other_extreme(1)[0], 0.0f);
    EXPECT_EQ(combiner.other_extreme(1)[3], 1.0f);
    EXPECT_DOUBLE_EQ(combiner.class_change_share(0, svv), 1.0 / 3.0);  // voxel 0: 60..95
  }
}

// With keep_previous (two phases computed at once) the combination before the last fold stays
// readable where it was, the same values as without it, and an older one is refused.
TEST(PhaseCombiner, TheCombinationBeforeTheLastFoldStaysWhereItWas) {
  const PathSafetyResult a = result({95, 80, kNaN, 40}, {0.0f, 2.0f, kNaN, 7.0f});
  const PathSafetyResult b = result({60, 85, kNaN, 45}, {3.0f, 1.0f, kNaN, 1.0f});
  const PathSafetyResult c = result({99, 70, kNaN, 30}, {1.0f, 0.5f, kNaN, 9.0f});
  const ImageGeometry& g = a.grid.geometry;
  PhaseCombiner kept, plain;
  kept.keep_earlier(1);
  for (PhaseCombiner* m : {&kept, &plain}) m->add(a, states({1, 1, 0, 1}, g));
  const auto after_one = kept.volumes_after(1);
  EXPECT_EQ(after_one[2], nullptr);  // IVBV was not computed
  EXPECT_EQ(after_one[0][0], 95.0f);
  for (PhaseCombiner* m : {&kept, &plain}) m->add(b, states({1, 1, 0, 1}, g));
  const auto still_one = kept.volumes_after(1), after_two = kept.volumes_after(2);
  EXPECT_EQ(still_one[0], after_one[0]);  // where it was, unchanged
  EXPECT_EQ(still_one[0][0], 95.0f);
  EXPECT_EQ(still_one[1][0], 0.0f);
  EXPECT_EQ(after_two[0][0], 60.0f);
  EXPECT_EQ(after_two[1][0], 3.0f);
  for (PhaseCombiner* m : {&kept, &plain}) m->add(c, states({1, 1, 0, 1}, g));
  EXPECT_EQ(kept.volumes_after(2)[0], after_two[0]);
  EXPECT_EQ(kept.volumes_after(2)[1][1], 2.0f);
  EXPECT_THROW(kept.volumes_after(1), Error);   // overwritten by the third fold
  EXPECT_THROW(plain.volumes_after(2), Error);  // not kept
  EXPECT_EQ(plain.volumes_after(3)[0], plain.combined().volumes[0].data());
  for (int v = 0; v < 2; ++v) {
    for (int64_t i = 0; i < 4; ++i) {
      const float x = kept.combined().volumes[size_t(v)][i];
      const float y = plain.combined().volumes[size_t(v)][i];
      EXPECT_TRUE(std::isnan(x) ? std::isnan(y) : x == y) << v << " " << i;
      EXPECT_EQ(kept.volumes_after(3)[size_t(v)][i] == x || std::isnan(x), true);
    }
  }
  EXPECT_EQ(kept.combined().volumes[0][3], 30.0f);
  EXPECT_EQ(kept.combined().volumes[1][3], 9.0f);
  EXPECT_EQ(kept.other_extreme(1)[3], 1.0f);
}

// With two kept (three phases computed at once) the two combinations before the last fold stay
// where they were while two more are folded; the values and the other extreme are those of a
// combiner that keeps none, and a fold tells when its combination is readable, once.
TEST(PhaseCombiner, TwoEarlierCombinationsStayWhereTheyWere) {
  const std::vector<PathSafetyResult> phases = {
      result({95, 80, kNaN, 40}, {0.0f, 2.0f, kNaN, 7.0f}),
      result({60, 85, kNaN, 45}, {3.0f, 1.0f, kNaN, 1.0f}),
      result({99, 70, kNaN, 30}, {1.0f, 0.5f, kNaN, 9.0f}),
      result({97, 90, kNaN, 35}, {0.5f, 4.0f, kNaN, 2.0f})};
  const ImageGeometry& g = phases[0].grid.geometry;
  PhaseCombiner kept, plain;
  kept.keep_earlier(2);
  std::vector<std::array<const float*, kernels::kValueCount>> after;
  for (size_t p = 0; p < phases.size(); ++p) {
    int told = 0;
    kept.add(phases[p], states({1, 1, 0, 1}, g), [&] {
      ++told;
      EXPECT_EQ(kept.phases(), int(p) + 1);
      EXPECT_EQ(kept.volumes_after(int(p) + 1)[0], kept.combined().volumes[0].data());
    });
    EXPECT_EQ(told, 1) << p;
    plain.add(phases[p], states({1, 1, 0, 1}, g));
    after.push_back(kept.volumes_after(int(p) + 1));
    if (p >= 2) {  // the two before stay where they were, unchanged
      EXPECT_EQ(kept.volumes_after(int(p) - 1)[0], after[p - 2][0]) << p;
      EXPECT_EQ(kept.volumes_after(int(p))[1], after[p - 1][1]) << p;
    }
  }
  EXPECT_EQ(kept.volumes_after(2)[0][0], 60.0f);  // min(95, 60)
  EXPECT_EQ(kept.volumes_after(2)[1][1], 2.0f);   // max(2, 1)
  EXPECT_EQ(kept.volumes_after(3)[0][1], 70.0f);
  EXPECT_THROW(kept.volumes_after(1), Error);  // overwritten by the fourth fold
  for (int v = 0; v < 2; ++v) {
    for (int64_t i = 0; i < 4; ++i) {
      for (const auto& [x, y] : {std::pair{kept.combined().volumes[size_t(v)][i],
                                           plain.combined().volumes[size_t(v)][i]},
                                 std::pair{kept.other_extreme(v)[i], plain.other_extreme(v)[i]}}) {
        EXPECT_TRUE(std::isnan(x) ? std::isnan(y) : x == y) << v << " " << i;
      }
    }
  }
  EXPECT_EQ(kept.other_extreme(0)[0], 99.0f);
  EXPECT_EQ(kept.other_extreme(1)[3], 1.0f);
  EXPECT_EQ(kept.combined().volumes[1][3], 9.0f);
}

TEST(PhaseCombiner, ClassesTakenOfTheFirstPhaseAreNotTheCombinations) {
  // ISBV's default classes are relative to the volume: the first phase's thresholds, taken (as
  // fast mode's check takes them) before the phases are combined, must not describe the
  // combination, whose values are the maxima over the phases.
  PathSafetyResult a = result({95, 95, 95, 95}, {1.0f, 2.0f, 3.0f, 4.0f});
  const PathSafetyResult b = result({95, 95, 95, 95}, {40.0f, 30.0f, 20.0f, 10.0f});
  const SafetyClasses first = classes_of(a, kernels::kIsbv);
  ASSERT_TRUE(a.classes[1].has_value());
  const ImageGeometry g = a.grid.geometry;
  PhaseCombiner combiner;
  combiner.add(std::move(a), states({1, 1, 1, 1}, g));  // lends its volumes and its classes
  EXPECT_EQ(combiner.combined().volumes[1][0], 1.0f);
  combiner.add(b, states({1, 1, 1, 1}, g));
  PathSafetyResult combined = combiner.combined();
  EXPECT_EQ(combined.volumes[1][0], 40.0f);
  EXPECT_EQ(combined.volumes[1][3], 10.0f);
  EXPECT_EQ(combiner.other_extreme(1)[0], 1.0f);  // the copy kept the first phase's values
  const SafetyClasses expected = default_classes(kernels::kIsbv, combined.volumes[1]);
  const SafetyClasses& taken = classes_of(combined, kernels::kIsbv);
  EXPECT_DOUBLE_EQ(taken.safe, expected.safe);
  EXPECT_DOUBLE_EQ(taken.dangerous, expected.dangerous);
  EXPECT_NE(taken.dangerous, first.dangerous);
}

// Fast mode's check of the combination: each phase's exact values at its check voxels,
// combined like the volumes (SVV the minimum, the others the maximum) at the voxels every phase
// checked; a voxel outside one phase's scan (not in its sample) is unknown in the combination
// and drops out. Compared with the combined volumes, a combination computed right agrees in
// every class where a phase's own check would not.
TEST(PhaseCombiner, TheCheckIsOfTheCombinationAgainstThePhasesExactValuesCombined) {
  PathSafetyResult a = result({95, 80, 60, 40}, {0.0f, 2.0f, 1.0f, 7.0f});
  PathSafetyResult b = result({60, 85, 99, 45}, {3.0f, 1.0f, 1.0f, 1.0f});
  const auto sample = [](std::vector<int64_t> offsets, std::vector<float> svv_isbv) {
    auto s = std::make_shared<CheckSample>();
    s->offsets = std::move(offsets);
    for (size_t v = 0; v < s->offsets.size(); ++v) {
      s->exact.insert(s->exact.end(), {svv_isbv[2 * v], svv_isbv[2 * v + 1], 0.0f, 0.0f});
    }
    return s;
  };
  a.check_sample = sample({0, 1, 3}, {95, 0, 80, 2, 40, 7});
  b.check_sample = sample({3, 0, 2}, {45, 1, 60, 3, 99, 1});  // voxel 1 outside b's scan
  const ImageGeometry g = a.grid.geometry;
  PhaseCombiner combiner;
  combiner.add(std::move(a), states({1, 1, 1, 1}, g));
  combiner.add(b, states({1, 1, 1, 1}, g));
  const CheckSample* check = combiner.check_sample();
  ASSERT_NE(check, nullptr);
  EXPECT_EQ(check->offsets, (std::vector<int64_t>{0, 3}));
  EXPECT_EQ(check->exact, (std::vector<float>{60, 3, 0, 0, 40, 7, 0, 0}));
  PathSafetyResult& combined = combiner.combined();
  compare_with_check_sample(*check, combined.values, combined);
  EXPECT_EQ(combined.fast.check_voxels, 2);
  EXPECT_DOUBLE_EQ(combined.fast.check_class_agreement[0], 1.0);
  EXPECT_DOUBLE_EQ(combined.fast.check_relative_l2[0], 0.0);
  EXPECT_DOUBLE_EQ(combined.fast.check_relative_l2[1], 0.0);
  // A phase without a check leaves the combination without one.
  PathSafetyResult c = result({60, 85, 99, 45}, {3.0f, 1.0f, 1.0f, 1.0f});
  combiner.add(c, states({1, 1, 1, 1}, g));
  EXPECT_EQ(combiner.check_sample(), nullptr);
}

TEST(PhaseCombiner, PhasesOnDifferentGridsAreRefused) {
  PhaseCombiner combiner;
  const PathSafetyResult a = result({1, 2, 3, 4}, {1, 2, 3, 4});
  combiner.add(a, states({1, 1, 1, 1}, a.grid.geometry));
  PathSafetyResult b = result({1, 2, 3, 4}, {1, 2, 3, 4});
  b.grid.geometry.origin.x() += 1.0;
  for (auto& v : b.volumes) {
    if (!v.empty()) v = Volume<float>(b.grid.geometry, 0.0f);
  }
  EXPECT_THROW(combiner.add(b, states({1, 1, 1, 1}, b.grid.geometry)), Error);
}

}  // namespace
}  // namespace crepuscular::planning
