// A breathing plan's phases for guidance: a plan over four phases whose anterior skin rises by 0,
// 2, 4 and 2 mm (whole voxels of 2 mm) gives each phase's plan and the skin's motion at a board
// lying on it; a board off the skin is refused with its reason; plans without per-phase volumes
// are guided by their combination.
#include "pipelines/guide_breathing.hpp"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "foundation/error.hpp"
#include "pipelines/plan.hpp"
#include "planning/imaging/volume_io.hpp"
#include "tests/support/plans.hpp"
#include "tests/support/temporary_folder.hpp"

namespace fs = std::filesystem;

namespace crepuscular::pipelines {
namespace {

// The mini plan's grid, fat (label 1) from row j = 8 - rise on (posterior), air in front: the
// anterior skin; the tumor of the mini plan.
std::string write_phase_labels(const fs::path& dir, int k, int rise_voxels) {
  planning::Volume<int32_t> labels(test::mini_plan_grid(), 0);
  for (int64_t k3 = 0; k3 < 24; ++k3)
    for (int64_t j = 8 - rise_voxels; j < 24; ++j)
      for (int64_t i = 0; i < 24; ++i) labels(i, j, k3) = 1;
  const std::string path = (dir / ("labels_" + std::to_string(k) + ".nii.gz")).string();
  planning::write_volume(labels, path);
  return path;
}

class GuideBreathingTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new test::TemporaryFolder;
    const test::MiniPlanInputs in = test::write_mini_plan_inputs(dir_->path());
    nlohmann::json list = nlohmann::json::array();
    const int rise[4] = {0, 1, 2, 1};
    for (int k = 0; k < 4; ++k) {
      list.push_back({{"labels", fs::path(write_phase_labels(dir_->path(), k, rise[k])).filename()},
                      {"tumor", fs::path(in.tumor).filename()}});
    }
    std::ofstream(dir_->file("phases.json"))
        << nlohmann::json{{"vulnerability", "table.json"}, {"phases", list}}.dump(2);
    for (const bool per_phase : {true, false}) {
      PlanRequest r;
      r.phases = dir_->file("phases.json");
      r.path_safety.radius_mm = 16.0;
      r.path_safety.device = planning::Device::kCpu;
      r.per_phase = per_phase;
      r.out_dir = dir_->file(per_phase ? "cycle" : "combined");
      run_plan(r);
    }
  }
  static void TearDownTestSuite() { delete dir_; }

  // A board lying on phase 0's skin (between rows 7 and 8) above the tumor, its z axis into the
  // body (+y), `off_mm` in front of the skin.
  static Eigen::Isometry3d board_on_skin(double off_mm = 0) {
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear().col(0) = Eigen::Vector3d(1, 0, 0);
    T.linear().col(1) = Eigen::Vector3d(0, 0, -1);
    T.linear().col(2) = Eigen::Vector3d(0, 1, 0);
    T.translation() = test::mini_plan_grid().index_to_physical(Eigen::Vector3d(11, 7.5, 11)) -
                      Eigen::Vector3d(0, off_mm, 0);
    return T;
  }
  static test::TemporaryFolder* dir_;
};
test::TemporaryFolder* GuideBreathingTest::dir_ = nullptr;

TEST_F(GuideBreathingTest, PhasesOfAPerPhasePlanWithTheSkinsMotionAtTheBoard) {
  const planning::PlanData plan = planning::load_plan(dir_->file("cycle"));
  ASSERT_EQ(plan.phases.size(), 4u);
  const auto phases = load_breathing_phases(plan, board_on_skin());
  ASSERT_TRUE(phases);
  ASSERT_EQ(phases->plans.size(), 4u);
  EXPECT_EQ(phases->names, plan.phases);
  EXPECT_LT((phases->skin.direction - Eigen::Vector3d(0, -1, 0)).norm(), 1e-9);
  const double expected[4] = {0, 2, 4, 2};
  for (int k = 0; k < 4; ++k) {
    EXPECT_NEAR(phases->skin.displacement_mm[size_t(k)], expected[k], 0.05) << "phase " << k;
    const planning::PlanData& p = *phases->plans[size_t(k)];
    // Its own labels, the plan's per-phase path safety, a blocking volume of its labels.
    EXPECT_EQ(p.labels(11, 7, 11), k == 0 ? 0 : 1) << "phase " << k;
    const auto& mine = p.path_safety.at("svv");
    const auto& planned = plan.phase_path_safety.at("svv")[size_t(k)];
    ASSERT_EQ(mine.voxel_count(), planned.voxel_count());
    for (int64_t n = 0; n < mine.voxel_count(); n += 97) {
      EXPECT_TRUE(mine[n] == planned[n] || (std::isnan(mine[n]) && std::isnan(planned[n]))) << n;
    }
    EXPECT_EQ(p.blocking.geometry().dims, p.labels.geometry().dims);
  }
  EXPECT_EQ(phases->skin.inhale_phase, 2);
}

TEST_F(GuideBreathingTest, BoardOffTheSkinIsRefusedAndPlansWithoutPhasesUseTheCombination) {
  const planning::PlanData plan = planning::load_plan(dir_->file("cycle"));
  try {
    load_breathing_phases(plan, board_on_skin(-40.0));  // 40 mm inside the body
    FAIL() << "a board inside the body was accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("does not lie on the skin"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("labels_0.nii.gz"), std::string::npos) << e.what();
  }
  EXPECT_FALSE(load_breathing_phases(planning::load_plan(dir_->file("combined")), board_on_skin()));
}

}  // namespace
}  // namespace crepuscular::pipelines
