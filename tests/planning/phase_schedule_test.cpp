// The schedule of a breathing plan (planning/breathing/schedule.hpp) as a table: for one, two and
// three phases at once, what each step waits for and which combination it leaves to; and the
// rules every schedule keeps (a step waits only for earlier steps, so no step waits for itself).
#include "planning/breathing/schedule.hpp"

#include <gtest/gtest.h>

#include <tuple>
#include <vector>

#include "foundation/error.hpp"

namespace crepuscular::planning {
namespace {

// (prepared_after, samples_after, coarse_to, fine_to) per step, 0-based, -1: none.
using Row = std::tuple<int, int, int, int>;

std::vector<Row> rows(const PhaseSchedule& s) {
  std::vector<Row> out;
  for (const PhaseStep& p : s.steps) {
    out.emplace_back(p.prepared_after, p.samples_after, p.coarse_to, p.fine_to);
  }
  return out;
}

TEST(PhaseSchedule, OneAtATimeEachStepAfterTheOneBeforeLeavingToAllBefore) {
  const PhaseSchedule s = schedule_phases(5, 1, true);
  EXPECT_EQ(s.at_once, 1);
  EXPECT_EQ(s.kept_combinations, 0);
  EXPECT_EQ(rows(s), (std::vector<Row>{{-1, -1, -1, -1},
                                       {0, 0, 0, 0},
                                       {1, 1, 1, 1},
                                       {2, 2, 2, 2},
                                       {3, 3, 3, 3}}));
}

TEST(PhaseSchedule, TwoAtOnceLeaveToTheStepsBeforeTheOneBeside) {
  const PhaseSchedule s = schedule_phases(6, 2, true);
  EXPECT_EQ(s.at_once, 2);
  EXPECT_EQ(s.kept_combinations, 1);
  EXPECT_EQ(rows(s), (std::vector<Row>{{-1, -1, -1, -1},
                                       {-1, -1, 0, 0},
                                       {-1, 0, 0, 0},
                                       {0, 1, 1, 1},
                                       {1, 2, 2, 2},
                                       {2, 3, 3, 3}}));
}

TEST(PhaseSchedule, ThreeAtOnceCoarsestThreeBackFinerTwoBack) {
  const PhaseSchedule s = schedule_phases(6, 3, true);
  EXPECT_EQ(s.at_once, 3);
  EXPECT_EQ(s.kept_combinations, 2);
  EXPECT_EQ(rows(s), (std::vector<Row>{{-1, -1, -1, -1},
                                       {-1, -1, 0, 0},
                                       {-1, -1, 0, 1},
                                       {-1, 0, 0, 1},
                                       {0, 1, 1, 2},
                                       {1, 2, 2, 3}}));
  EXPECT_EQ(s.table(),
            "step 1: prepared after -, samples after -, refines every boundary\n"
            "step 2: prepared after -, samples after -, coarsest level leaves to 1, finer to 1\n"
            "step 3: prepared after -, samples after -, coarsest level leaves to 1, finer to 1-2 "
            "(2 before its fold)\n"
            "step 4: prepared after -, samples after 1, coarsest level leaves to 1, finer to 1-2 "
            "(2 before its fold)\n"
            "step 5: prepared after 1, samples after 2, coarsest level leaves to 1-2, finer to 1-3 "
            "(3 before its fold)\n"
            "step 6: prepared after 2, samples after 3, coarsest level leaves to 1-3, finer to 1-4 "
            "(4 before its fold)");
  EXPECT_EQ(schedule_phases(2, 2, true).table({"end-exhale", "end-inhale"}),
            "step 1 end-exhale: prepared after -, samples after -, refines every boundary\n"
            "step 2 end-inhale: prepared after -, samples after -, coarsest level leaves to 1, "
            "finer to 1");
}

TEST(PhaseSchedule, WithoutLeavingEveryStepRefinesEverything) {
  const PhaseSchedule s = schedule_phases(4, 3, false);
  EXPECT_EQ(s.kept_combinations, 0);
  for (const PhaseStep& p : s.steps) {
    EXPECT_EQ(p.coarse_to, -1);
    EXPECT_EQ(p.fine_to, -1);
  }
  EXPECT_EQ(s.steps[3].samples_after, 0);
}

TEST(PhaseSchedule, MoreAtOnceThanPhasesComputesThemAllAtOnce) {
  const PhaseSchedule s = schedule_phases(2, 3, true);
  EXPECT_EQ(s.at_once, 2);
  EXPECT_EQ(rows(s), (std::vector<Row>{{-1, -1, -1, -1}, {-1, -1, 0, 0}}));
  EXPECT_THROW(schedule_phases(0, 1, true), Error);
  EXPECT_THROW(schedule_phases(3, 0, true), Error);
}

// Every schedule: a step waits for earlier steps only, leaves to earlier steps only, its finer
// levels to at least the combination its coarsest leave to, and reads one step before its fold at
// most as far back as the combinations kept (the combination it reads through stays put).
TEST(PhaseSchedule, EveryStepWaitsOnlyForEarlierSteps) {
  for (int n = 1; n <= 12; ++n) {
    for (int at_once = 1; at_once <= 4; ++at_once) {
      for (const bool leave : {false, true}) {
        SCOPED_TRACE(::testing::Message() << n << " phases, " << at_once << " at once");
        const PhaseSchedule s = schedule_phases(n, at_once, leave);
        ASSERT_EQ(s.steps.size(), size_t(n));
        int sampling_at_first = 0;
        for (int at = 0; at < n; ++at) {
          const PhaseStep& p = s.steps[size_t(at)];
          EXPECT_LT(p.prepared_after, at);
          EXPECT_LT(p.samples_after, at);
          EXPECT_LT(p.coarse_to, at);
          EXPECT_LT(p.fine_to, at);
          EXPECT_LE(p.coarse_to, p.fine_to);
          EXPECT_EQ(p.coarse_to >= 0, leave && at > 0);
          if (p.fine_to > p.coarse_to) {
            EXPECT_LE(p.fine_to - p.coarse_to, s.kept_combinations);
          }
          sampling_at_first += p.samples_after < 0;
        }
        EXPECT_EQ(sampling_at_first, s.at_once);
      }
    }
  }
}

}  // namespace
}  // namespace crepuscular::planning
