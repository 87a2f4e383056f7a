// Planning over the breathing cycle (docs/ARCHITECTURE.md §10): the combination of the phases on one grid,
// checked against the single-phase plan, the per-phase volumes, a vessel that moves across a path
// and a rigid shift of the whole scene.
#include <gtest/gtest.h>
#include <omp.h>

#include <array>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "foundation/error.hpp"
#include "pipelines/plan.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/plan_folder/plan_folder.hpp"
#include "planning/safety/unknown.hpp"
#include "planning/simulation/phantom.hpp"
#include "planning/trajectories/evaluate.hpp"
#include "tests/support/plans.hpp"
#include "tests/support/temporary_folder.hpp"

namespace fs = std::filesystem;

namespace crepuscular::planning {
namespace {

using pipelines::PlanRequest;
using pipelines::run_plan;

const char* const kValues[] = {"svv", "isbv", "ivbv", "bvv"};

// phases.json listing (labels, tumor) per phase, paths relative to `dir`.
std::string write_phase_list(const fs::path& dir,
                             const std::vector<std::pair<std::string, std::string>>& phases) {
  nlohmann::json list = nlohmann::json::array();
  for (const auto& [labels, tumor] : phases) {
    list.push_back({{"labels", fs::relative(labels, dir).string()},
                    {"tumor", fs::relative(tumor, dir).string()}});
  }
  const std::string path = (dir / "phases.json").string();
  std::ofstream(path) << nlohmann::json{{"vulnerability", "table.json"}, {"phases", list}}.dump(2);
  return path;
}

PlanRequest phases_request(const std::string& phases, const std::string& out) {
  PlanRequest r;
  r.phases = phases;
  r.path_safety.radius_mm = 16.0;
  r.path_safety.device = Device::kCpu;
  r.per_phase = true;
  r.out_dir = out;
  return r;
}

// Same values bit for bit, NaN at the same voxels.
void expect_identical(const Volume<float>& a, const Volume<float>& b, const std::string& what) {
  ASSERT_TRUE(a.geometry().same_grid(b.geometry(), 0.0)) << what;
  int64_t differing = 0;
  for (int64_t n = 0; n < a.voxel_count(); ++n) {
    const bool same = std::isnan(a[n]) ? std::isnan(b[n]) : a[n] == b[n];
    differing += same ? 0 : 1;
  }
  EXPECT_EQ(differing, 0) << what;
}

// The mini plan's labels (fat, tumor block at voxels 10..12) with the vessel column on
// i = vessel_i, j = 9..13, every k.
std::string write_labels_with_vessel_at(const fs::path& dir, const std::string& name,
                                        int vessel_i) {
  Volume<int32_t> labels(test::mini_plan_grid(), 1);
  for (int k = 0; k < 24; ++k) {
    for (int j = 9; j <= 13; ++j) labels(vessel_i, j, k) = 2;
  }
  const std::string path = (dir / name).string();
  write_volume(labels, path);
  return path;
}

// The mini plan's inputs, its labels with the vessel column at i = 16 (a) and at i = 4 (b), and
// phases.json listing a, b and the mini plan's own labels, each with the mini tumor.
struct ThreePhases {
  test::MiniPlanInputs in;
  std::string a, b, list;
};
ThreePhases write_three_phases(const fs::path& dir) {
  ThreePhases t;
  t.in = test::write_mini_plan_inputs(dir);
  t.a = write_labels_with_vessel_at(dir, "labels_a.nii.gz", 16);
  t.b = write_labels_with_vessel_at(dir, "labels_b.nii.gz", 4);
  t.list = write_phase_list(dir, {{t.a, t.in.tumor}, {t.b, t.in.tumor}, {t.in.labels, t.in.tumor}});
  return t;
}

TEST(PlanBreathing, IdenticalPhasesGiveExactlyTheSinglePhasePlan) {
  const test::TemporaryFolder dir;
  const test::MiniPlanInputs in = test::write_mini_plan_inputs(dir.path());
  const nlohmann::json single = run_plan(in.request(dir.file("single")));
  const std::string list =
      write_phase_list(dir.path(), {{in.labels, in.tumor}, {in.labels, in.tumor},
                                    {in.labels, in.tumor}});
  const nlohmann::json cycle = run_plan(phases_request(list, dir.file("cycle")));
  EXPECT_EQ(cycle["grid"], single["grid"]);
  for (const char* v : kValues) {
    expect_identical(read_volume<float>(dir.file("single/path_safety_") + v + ".nii.gz", VolumeReadOptions::path_safety_file()),
                     read_volume<float>(dir.file("cycle/path_safety_") + v + ".nii.gz", VolumeReadOptions::path_safety_file()), v);
    EXPECT_EQ(cycle["classes"][v], single["classes"][v]) << v;
    EXPECT_EQ(cycle["breathing"]["class_change_share"][v].get<double>(), 0.0) << v;
  }
  const Volume<uint8_t> roi_single = read_volume<uint8_t>(dir.file("single/roi.nii.gz"));
  const Volume<uint8_t> roi_cycle = read_volume<uint8_t>(dir.file("cycle/roi.nii.gz"));
  EXPECT_TRUE(roi_single.values() == roi_cycle.values());
  EXPECT_EQ(cycle["breathing"]["phases"].size(), 3u);
}

// Two phases: the vessel column at i = 16 (between the tumor and the voxels at i >= 17, inside the 16 mm region) and at
// i = 4 (on the other side).
class MovingVessel : public ::testing::Test {
 protected:
  void SetUp() override {
    in_ = test::write_mini_plan_inputs(dir_.path());
    const std::string a = write_labels_with_vessel_at(dir_.path(), "labels_a.nii.gz", 16);
    const std::string b = write_labels_with_vessel_at(dir_.path(), "labels_b.nii.gz", 4);
    plan_ = run_plan(phases_request(
        write_phase_list(dir_.path(), {{a, in_.tumor}, {b, in_.tumor}}), dir_.file("plan")));
  }
  Volume<float> volume(const std::string& name) const {
    return read_volume<float>(dir_.file("plan/" + name + ".nii.gz"), VolumeReadOptions::path_safety_file());
  }
  test::TemporaryFolder dir_;
  test::MiniPlanInputs in_;
  nlohmann::json plan_;
};

TEST_F(MovingVessel, CombinationIsTheVoxelwiseMinimumOfSvvAndMaximumOfTheOthers) {
  // Voxels computed in every phase (roi.nii.gz state 1): ITK's NIfTI reader turns NaN into 0, so
  // the voxel states say where there is a value.
  const Volume<uint8_t> roi = read_volume<uint8_t>(dir_.file("plan/roi.nii.gz"));
  for (const char* v : kValues) {
    const std::string value = v;
    const Volume<float> combined = volume("path_safety_" + value);
    const Volume<float> a = volume("path_safety_" + value + "_phase00");
    const Volume<float> b = volume("path_safety_" + value + "_phase01");
    int64_t checked = 0, differing_phases = 0;
    for (int64_t n = 0; n < combined.voxel_count(); ++n) {
      if (roi[n] != kRegionComputed) continue;
      const float expected = value == "svv" ? std::min(a[n], b[n]) : std::max(a[n], b[n]);
      ASSERT_EQ(combined[n], expected) << value << " voxel " << n;
      ++checked;
      differing_phases += a[n] != b[n] ? 1 : 0;
    }
    EXPECT_GT(checked, 1000) << value;
    EXPECT_GT(differing_phases, 100) << value << ": the phases should differ";
    // The combination's classes for 3D Slicer: the combined volume's, by the plan's thresholds.
    const std::array<int64_t, 4> classes =
        test::expect_classes_segmentation_matches_plan(dir_.path() / "plan", value);
    EXPECT_EQ(classes[0] + classes[1] + classes[2], checked) << value;
    EXPECT_EQ(classes[3], 0) << value;
  }
}

// Each phase is finished (check, coverage, statistics, combination) while the next one is
// computed, in order: four phases, the vessel moving back and forth, in fast mode (on the GPU
// where one is found). Each phase's volumes are those of the same phase planned again, and the
// combination is their voxelwise minimum (SVV) and maximum (the others).
TEST(PlanBreathing, PhasesFinishedBesideTheNextAreEachPhasesOwnAndCombineInOrder) {
  const bool gpu = gpus_for(Device::kCuda) > 0;
  const test::TemporaryFolder dir;
  const test::MiniPlanInputs in = test::write_mini_plan_inputs(dir.path());
  const std::string a = write_labels_with_vessel_at(dir.path(), "labels_a.nii.gz", 16);
  const std::string b = write_labels_with_vessel_at(dir.path(), "labels_b.nii.gz", 4);
  const auto on_gpu = [gpu](PlanRequest r) {
    r.path_safety.device = gpu ? Device::kCuda : Device::kCpu;
    r.path_safety.mode = Mode::kFast;
    r.phases_at_once = 2;  // each phase beside another
    return r;
  };
  const nlohmann::json cycle = run_plan(on_gpu(phases_request(
      write_phase_list(dir.path(), {{a, in.tumor}, {b, in.tumor}, {a, in.tumor}, {b, in.tumor}}),
      dir.file("cycle"))));
  ASSERT_EQ(cycle["breathing"]["phases"].size(), 4u);
  // The same phase twice, planned again.
  run_plan(on_gpu(phases_request(write_phase_list(dir.path(), {{b, in.tumor}, {b, in.tumor}}),
                                 dir.file("alone"))));
  const Volume<uint8_t> roi = read_volume<uint8_t>(dir.file("cycle/roi.nii.gz"));
  for (const char* v : kValues) {
    const std::string value = v;
    const auto phase = [&](const std::string& plan, int k) {
      return read_volume<float>(dir.file(plan + "/path_safety_" + value + "_phase0" +
                                         std::to_string(k) + ".nii.gz"), VolumeReadOptions::path_safety_file());
    };
    const Volume<float> combined =
        read_volume<float>(dir.file("cycle/path_safety_" + value + ".nii.gz"), VolumeReadOptions::path_safety_file());
    const Volume<float> p0 = phase("cycle", 0), p1 = phase("cycle", 1);
    expect_identical(phase("cycle", 2), p0, value + ": phase 2 against phase 0");
    expect_identical(phase("cycle", 3), p1, value + ": phase 3 against phase 1");
    expect_identical(phase("alone", 0), p1, value + ": phase 1 against the same phase alone");
    expect_identical(phase("alone", 1), p1, value + ": phase 1 against the same phase alone");
    int64_t checked = 0, differing = 0;
    for (int64_t n = 0; n < combined.voxel_count(); ++n) {
      if (roi[n] != kRegionComputed) continue;
      ASSERT_EQ(combined[n], value == "svv" ? std::min(p0[n], p1[n]) : std::max(p0[n], p1[n]))
          << value << " voxel " << n;
      ++checked;
      differing += p0[n] != p1[n] ? 1 : 0;
    }
    EXPECT_GT(checked, 1000) << value;
    EXPECT_GT(differing, 100) << value << ": the phases should differ";
  }
}

TEST_F(MovingVessel, ClassChangeShareCountsTheVoxelsWhosePhasesDifferInClass) {
  // Brute force over the written volumes: a computed voxel changes class over the cycle where
  // its two phases fall in different classes under the plan's thresholds.
  const Volume<uint8_t> roi = read_volume<uint8_t>(dir_.file("plan/roi.nii.gz"));
  for (const char* v : kValues) {
    const std::string value = v;
    const Volume<float> a = volume("path_safety_" + value + "_phase00");
    const Volume<float> b = volume("path_safety_" + value + "_phase01");
    const SafetyClasses classes = classes_from_json(plan_, value, "plan.json");
    int64_t known = 0, changing = 0;
    for (int64_t n = 0; n < a.voxel_count(); ++n) {
      if (roi[n] != kRegionComputed) continue;
      ++known;
      changing += classes.classify(a[n]) != classes.classify(b[n]) ? 1 : 0;
    }
    ASSERT_GT(known, 1000) << value;
    EXPECT_GT(changing, 0) << value << ": the vessel's move changes no class";
    EXPECT_DOUBLE_EQ(plan_["breathing"]["class_change_share"][value].get<double>(),
                     double(changing) / double(known))
        << value;
  }
}

TEST_F(MovingVessel, PathSafeInOnePhaseIsUnsafeInTheCombination) {
  // Voxel (18, 11, 11) of the mini grid, on the +x side of the tumor: behind the vessel at
  // i = 16 in phase 0, in the open in phase 1 (the vessel then lies at i = 4, on the far side).
  const Eigen::Vector3d p = test::mini_plan_grid().index_to_physical(18, 11, 11);
  const Volume<float> combined = volume("path_safety_svv");
  const Volume<float> a = volume("path_safety_svv_phase00");
  const Volume<float> b = volume("path_safety_svv_phase01");
  const Eigen::Vector3d ijk = combined.physical_to_index(p);
  const int64_t i = std::llround(ijk.x()), j = std::llround(ijk.y()), k = std::llround(ijk.z());
  ASSERT_NEAR((combined.index_to_physical(i, j, k) - p).norm(), 0.0, 1e-6);
  EXPECT_GE(b(i, j, k), 90.0f) << "safe in phase 1: every visible tumor point in the open";
  EXPECT_LT(a(i, j, k), 50.0f) << "dangerous in phase 0: the vessel lies across the paths";
  EXPECT_EQ(combined(i, j, k), a(i, j, k));
  const SafetyClasses classes = classes_from_json(plan_, "svv", "plan.json");
  EXPECT_EQ(classes.classify(combined(i, j, k)), SafetyClass::kDangerous);
  // Some of the region changes class over the cycle, not all of it.
  const double share = plan_["breathing"]["class_change_share"]["svv"].get<double>();
  EXPECT_GT(share, 0.01);
  EXPECT_LT(share, 0.9);
}

TEST_F(MovingVessel, EvaluateNamesTheWorstPhaseAndItsValue) {
  const PlanData plan = load_plan(dir_.file("plan"));
  ASSERT_EQ(plan.phases, (std::vector<std::string>{"phase00", "phase01"}));
  const TrajectoryEvaluator evaluator(plan);
  const Eigen::Vector3d entry = test::mini_plan_grid().index_to_physical(18, 11, 11);
  const TrajectoryEvaluation e = evaluator.evaluate({"lateral", entry, plan.tumor_centre});
  const Volume<float> a = volume("path_safety_svv_phase00");
  const Eigen::Vector3d ijk = a.physical_to_index(entry);
  const float a_entry = a(std::llround(ijk.x()), std::llround(ijk.y()), std::llround(ijk.z()));
  bool found = false;
  for (const EntryValue& v : e.values) {
    if (v.value != "svv") continue;
    found = true;
    ASSERT_EQ(v.per_phase.size(), 2u);
    EXPECT_EQ(v.worst_phase, "phase00");  // the vessel lies across the path in phase 0
    EXPECT_NEAR(v.at_worst_phase, a_entry, 1e-4);
    EXPECT_GE(v.per_phase[1], 90.0);
    EXPECT_NE(evaluation_text(e).find("in phase00"), std::string::npos) << evaluation_text(e);
  }
  EXPECT_TRUE(found);
}

TEST(PlanBreathing, RigidShiftOfTheSceneShiftsEachPhasesVolumeByTheSameVector) {
  // Phase 1 is phase 0 moved by s = (0, 0, 4) mm (two voxels of the 2 mm output grid): its path
  // safety at x is phase 0's at x - s. The shared grid sits on the mean centroid, so both x and
  // x - s are voxels of it.
  const test::TemporaryFolder dir;
  fs::create_directories(dir.path() / "a");
  fs::create_directories(dir.path() / "b");
  const test::MiniPlanInputs a = test::write_mini_plan_inputs(dir.path() / "a");
  test::MiniPlanOptions shifted;
  shifted.grid.origin += Eigen::Vector3d(0, 0, 4);
  const test::MiniPlanInputs b = test::write_mini_plan_inputs(dir.path() / "b", shifted);
  test::write_fat_and_vessel_table(dir.file("table.json"));
  const nlohmann::json plan = run_plan(phases_request(
      write_phase_list(dir.path(), {{a.labels, a.tumor}, {b.labels, b.tumor}}), dir.file("plan")));
  // The grid's centre: the mean of the two centroids, 2 mm above phase 0's.
  const Eigen::Vector3d c0 = test::mini_plan_grid().index_to_physical(11, 11, 11);
  const auto centre = plan["grid"]["centre_lps_mm"].get<std::vector<double>>();
  EXPECT_NEAR(centre[0], c0.x(), 1e-9);
  EXPECT_NEAR(centre[1], c0.y(), 1e-9);
  EXPECT_NEAR(centre[2], c0.z() + 2.0, 1e-9);
  const Volume<uint8_t> roi = read_volume<uint8_t>(dir.file("plan/roi.nii.gz"));
  for (const char* v : kValues) {
    const std::string value = v;
    const Volume<float> pa = read_volume<float>(dir.file("plan/path_safety_" + value + "_phase00.nii.gz"), VolumeReadOptions::path_safety_file());
    const Volume<float> pb = read_volume<float>(dir.file("plan/path_safety_" + value + "_phase01.nii.gz"), VolumeReadOptions::path_safety_file());
    const auto& d = pa.dims();
    int64_t compared = 0;
    double worst = 0.0, largest = 0.0;
    for (int64_t k = 2; k < d[2]; ++k) {
      for (int64_t j = 0; j < d[1]; ++j) {
        for (int64_t i = 0; i < d[0]; ++i) {
          // Both voxels computed (ITK's NIfTI reader turns the NaN of the others into 0).
          if (roi(i, j, k) != kRegionComputed || roi(i, j, k - 2) != kRegionComputed) continue;
          const float x = pb(i, j, k), y = pa(i, j, k - 2);
          worst = std::max(worst, double(std::abs(x - y)));
          largest = std::max(largest, double(std::abs(y)));
          ++compared;
        }
      }
    }
    EXPECT_GT(compared, 1000) << value;
    EXPECT_GT(largest, 0.0) << value;
    EXPECT_LE(worst, 1e-4 * largest) << value << " (largest value " << largest << ")";
  }
}

// Fast mode over the breathing phantom's phases: a phase's class boundaries are left to the
// phases computed before it where they already decide the combination's class. The ends of the
// motion come first (end-exhale, then end-inhale); the later phases compute fewer points; the
// combination has the classes of the plan that refines every phase (--per-phase), and both agree
// with the exact plan's combination, one, two or three phases at once (the schedule's table is
// phase_schedule_test's). plan.json's check is the combination's against every phase's exact
// values combined.
TEST(PlanBreathing, FastPhasesLeaveToTheCombinationOnlyWhatTheyCannotChange) {
  const test::TemporaryFolder dir;
  PhantomOptions po;
  po.spacing_mm = 3.0;
  write_breathing_phantom(po, 4, dir.file("cycle"));
  const auto request = [&](const std::string& out, Mode mode, bool every_phase,
                           int at_once = 1) {
    PlanRequest r;
    r.phases_at_once = at_once;
    r.phases = dir.file("cycle/phases.json");
    r.path_safety.device = Device::kCpu;
    r.path_safety.mode = mode;
    r.path_safety.spacing_mm = 3.0;
    r.path_safety.radius_mm = 60.0;
    r.area_safety.enabled = false;
    r.per_phase = every_phase;
    r.out_dir = dir.file(out);
    return r;
  };
  const nlohmann::json left = run_plan(request("left", Mode::kFast, false));
  const nlohmann::json every = run_plan(request("every", Mode::kFast, true));
  const nlohmann::json exact = run_plan(request("exact", Mode::kExact, false));
  // Two phases at once: the later of two leaves refinement to the phases before the other.
  const nlohmann::json two = run_plan(request("two", Mode::kFast, false, 2));
  // Three at once (the default on a GPU): the fourth phase's coarsest decisions leave to the
  // first phase alone (three back), its finer ones to the first two (two back), as two at once;
  // the third's finer ones to the first two as well (one back, as one at a time), its coarsest
  // to the first alone.
  const nlohmann::json three = run_plan(request("three", Mode::kFast, false, 3));
  const auto& phases = left["breathing"]["phases"];
  ASSERT_EQ(phases.size(), 4u);
  EXPECT_EQ(phases[0]["computed_as"], 1);
  EXPECT_EQ(phases[2]["computed_as"], 2);  // end-inhale: the other end of the motion
  int64_t points_left = 0, points_every = 0, left_out = 0;
  for (size_t k = 0; k < 4; ++k) {
    points_left += phases[k]["points_computed_exactly"].get<int64_t>();
    int64_t by_level = 0;  // each phase's points, level by level
    for (const auto& level : phases[k]["points_per_level"]) by_level += level["points"].get<int64_t>();
    EXPECT_EQ(by_level, phases[k]["points_computed_exactly"].get<int64_t>()) << k;
    EXPECT_GE(phases[k]["points_per_level"].size(), 2u) << k;
    points_every += every["breathing"]["phases"][k]["points_computed_exactly"].get<int64_t>();
    EXPECT_FALSE(every["breathing"]["phases"][k].contains("left_to_earlier_phases"));
    if (k == 0) {
      EXPECT_FALSE(phases[k].contains("left_to_earlier_phases"));  // nothing before it
      continue;
    }
    left_out += phases[k]["left_to_earlier_phases"]["finest_points"].get<int64_t>() +
                phases[k]["left_to_earlier_phases"]["cells"].get<int64_t>();
  }
  EXPECT_GT(left_out, 0);
  EXPECT_LT(points_left, points_every * 9 / 10) << points_left << " vs " << points_every;
  // Two at once: end-inhale (computed second) leaves to end-exhale, as one at a time, so it
  // computes the same points; the third and fourth leave to the phases before the one beside
  // them.
  const auto& two_phases = two["breathing"]["phases"];
  int64_t points_two = 0;
  for (size_t k = 0; k < 4; ++k) {
    points_two += two_phases[k]["points_computed_exactly"].get<int64_t>();
    EXPECT_EQ(two_phases[k]["computed_as"], phases[k]["computed_as"]);
  }
  EXPECT_EQ(two_phases[2]["points_computed_exactly"], phases[2]["points_computed_exactly"]);
  bool fourth_differs = false;
  int64_t third_points = 0, third_points_two = 0;
  for (size_t k = 0; k < 4; ++k) {
    const auto& p = three["breathing"]["phases"][k];
    const int as = p["computed_as"].get<int>();
    if (as < 3) {  // nothing three back, the second leaves to the first: as two at once
      EXPECT_EQ(p["points_computed_exactly"], two_phases[k]["points_computed_exactly"]) << k;
    } else if (as == 3) {
      // Its finer decisions have the second's boundaries to leave to as well.
      third_points = p["points_computed_exactly"].get<int64_t>();
      third_points_two = two_phases[k]["points_computed_exactly"].get<int64_t>();
    } else {
      fourth_differs = p["points_computed_exactly"] != two_phases[k]["points_computed_exactly"];
      EXPECT_GT(p["left_to_earlier_phases"]["cells"].get<int64_t>(), 0);
    }
  }
  // The fourth's coarsest decisions had less to leave to (the first phase only).
  EXPECT_TRUE(fourth_differs);
  EXPECT_LT(third_points, third_points_two);
  EXPECT_LT(points_two, points_every * 9 / 10) << points_two << " vs " << points_every;
  EXPECT_EQ(left["fast_mode_vs_exact"]["points_computed_exactly"].get<int64_t>(), points_left);
  const Volume<uint8_t> roi = read_volume<uint8_t>(dir.file("exact/roi.nii.gz"));
  for (const char* v : kValues) {
    const std::string value = v;
    SCOPED_TRACE(value);
    const auto volume = [&](const std::string& plan) {
      return read_volume<float>(dir.file(plan + "/path_safety_" + value + ".nii.gz"), VolumeReadOptions::path_safety_file());
    };
    const Volume<float> l = volume("left"), e = volume("every"), x = volume("exact"),
                        t = volume("two"), three_default = volume("three");
    SafetyClasses classes;
    const nlohmann::json& c = exact["classes"][value];
    classes.higher_is_safer = value == "svv";
    classes.safe = c["safe"].get<double>();
    classes.dangerous = c["dangerous"].get<double>();
    int64_t computed = 0, left_vs_every = 0, left_vs_exact = 0, every_vs_exact = 0;
    int64_t two_vs_exact = 0, three_vs_exact = 0;
    for (int64_t n = 0; n < roi.voxel_count(); ++n) {
      if (roi[n] != kRegionComputed) continue;
      ++computed;
      two_vs_exact += classes.classify(t[n]) != classes.classify(x[n]);
      three_vs_exact += classes.classify(three_default[n]) != classes.classify(x[n]);
      left_vs_every += classes.classify(l[n]) != classes.classify(e[n]);
      left_vs_exact += classes.classify(l[n]) != classes.classify(x[n]);
      every_vs_exact += classes.classify(e[n]) != classes.classify(x[n]);
    }
    ASSERT_GT(computed, 10000);
    EXPECT_LE(left_vs_every, computed / 200) << left_vs_every << " of " << computed;
    EXPECT_LE(left_vs_exact, every_vs_exact + computed / 500)
        << left_vs_exact << " vs " << every_vs_exact << " of " << computed;
    EXPECT_LE(left_vs_exact, computed / 100) << left_vs_exact << " of " << computed;
    EXPECT_LE(two_vs_exact, every_vs_exact + computed / 500)
        << two_vs_exact << " vs " << every_vs_exact << " of " << computed;
    EXPECT_LE(three_vs_exact, every_vs_exact + computed / 500)
        << three_vs_exact << " vs " << every_vs_exact << " of " << computed;
    const nlohmann::json& check = left["fast_mode_vs_exact"];
    EXPECT_GE(check["voxels"].get<int64_t>(), 900);
    EXPECT_GE(check[value]["class_agreement"].get<double>(), 0.98);
  }
}

TEST(PlanBreathing, BadPhaseListsAreRefusedNamingTheFile) {
  const test::TemporaryFolder dir;
  const test::MiniPlanInputs in = test::write_mini_plan_inputs(dir.path());
  const std::string one = write_phase_list(dir.path(), {{in.labels, in.tumor}});
  try {
    run_plan(phases_request(one, dir.file("plan")));
    ADD_FAILURE() << "one phase accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("phases.json"), std::string::npos) << e.what();
  }
  std::ofstream(dir.file("phases.json"))
      << R"({"phases": [{"labels": "labels.nii.gz", "tumor": "tumor.nii.gz"},
                        {"labels": "missing.nii.gz", "tumor": "tumor.nii.gz"}]})";
  try {
    run_plan(phases_request(dir.file("phases.json"), dir.file("plan")));
    ADD_FAILURE() << "missing label map accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("missing.nii.gz"), std::string::npos) << e.what();
  }
  EXPECT_FALSE(fs::exists(dir.file("plan")));
}

// Phases are read side by side, one reader per four threads: with 8 threads two readers take the
// phases, and the plan is the one read a phase at a time (1 thread), volume for volume; an error
// is the first failing phase's in the list's order, whichever reader met it first.
TEST(PlanBreathing, PhasesReadSideBySidePlanAsReadOneByOne) {
  const test::TemporaryFolder dir;
  const ThreePhases three = write_three_phases(dir.path());
  const std::string& list = three.list;
  const int threads = omp_get_max_threads();
  omp_set_num_threads(1);
  run_plan(phases_request(list, dir.file("one_by_one")));
  omp_set_num_threads(8);
  run_plan(phases_request(list, dir.file("side_by_side")));
  EXPECT_EQ(omp_get_max_threads(), 8);  // the plan's own steps had every thread again
  for (const char* v : kValues) {
    expect_identical(read_volume<float>(dir.file("one_by_one/path_safety_") + v + ".nii.gz", VolumeReadOptions::path_safety_file()),
                     read_volume<float>(dir.file("side_by_side/path_safety_") + v + ".nii.gz", VolumeReadOptions::path_safety_file()),
                     v);
    for (int k = 0; k < 3; ++k) {
      const std::string phase = "_phase0" + std::to_string(k) + ".nii.gz";
      expect_identical(
          read_volume<float>(dir.file("one_by_one/path_safety_") + v + phase, VolumeReadOptions::path_safety_file()),
          read_volume<float>(dir.file("side_by_side/path_safety_") + v + phase, VolumeReadOptions::path_safety_file()), v + phase);
    }
  }
  // Files that exist but are no label maps: met while reading, not before.
  std::ofstream(dir.file("corrupt_first.nii.gz")) << "not a label map";
  std::ofstream(dir.file("corrupt_second.nii.gz")) << "not one either";
  std::ofstream(dir.file("phases.json"))
      << R"({"vulnerability": "table.json", "phases": [
           {"labels": "labels_a.nii.gz", "tumor": "tumor.nii.gz"},
           {"labels": "corrupt_first.nii.gz", "tumor": "tumor.nii.gz"},
           {"labels": "corrupt_second.nii.gz", "tumor": "tumor.nii.gz"}]})";
  try {
    run_plan(phases_request(dir.file("phases.json"), dir.file("plan")));
    ADD_FAILURE() << "corrupt label maps accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("corrupt_first.nii.gz"), std::string::npos) << e.what();
  }
  omp_set_num_threads(threads);
  EXPECT_FALSE(fs::exists(dir.file("plan")));
}

// With the spacing and radius given, the tumors are read first and each blocking volume beside
// the computation, in the order the phases are computed: the same plan, volume for volume, as
// with every input read first (the radius not given), also with two phases at once. A corrupted label map met while
// phases are computed fails the plan naming it, leaves nothing, and nothing waits for it.
TEST(PlanBreathing, BlockingVolumesReadBesideTheComputationPlanAsReadFirst) {
  const test::TemporaryFolder dir;
  const ThreePhases three = write_three_phases(dir.path());
  const test::MiniPlanInputs& in = three.in;
  const std::string &a = three.a, &b = three.b, &list = three.list;
  const auto request = [&](const std::string& phases, const std::string& out, double radius,
                           int at_once) {
    PlanRequest r = phases_request(phases, dir.file(out));
    r.path_safety.spacing_mm = 2.0;
    r.path_safety.radius_mm = radius;  // 0: the default, which needs every input first
    r.phases_at_once = at_once;
    return r;
  };
  const nlohmann::json first = run_plan(request(list, "first", 0.0, 1));
  const double radius = first["parameters"]["radius_mm"].get<double>();
  const nlohmann::json beside = run_plan(request(list, "beside", radius, 2));
  EXPECT_EQ(first["grid"], beside["grid"]);
  for (const char* v : kValues) {
    expect_identical(read_volume<float>(dir.file("first/path_safety_") + v + ".nii.gz", VolumeReadOptions::path_safety_file()),
                     read_volume<float>(dir.file("beside/path_safety_") + v + ".nii.gz", VolumeReadOptions::path_safety_file()), v);
    for (int k = 0; k < 3; ++k) {
      const std::string phase = "_phase0" + std::to_string(k) + ".nii.gz";
      expect_identical(read_volume<float>(dir.file("first/path_safety_") + v + phase, VolumeReadOptions::path_safety_file()),
                       read_volume<float>(dir.file("beside/path_safety_") + v + phase, VolumeReadOptions::path_safety_file()),
                       v + phase);
    }
  }
  EXPECT_TRUE(beside["breathing"]["phases"][1]["read_s"].contains("blocking"));
  // The first phase's label map is read beside the tumors, the others beside the computation.
  std::ofstream(dir.file("corrupt.nii.gz")) << "not a label map";
  const std::string corrupt = dir.file("corrupt.nii.gz");
  for (int at : {0, 2}) {
    std::vector<std::pair<std::string, std::string>> phases = {
        {a, in.tumor}, {b, in.tumor}, {in.labels, in.tumor}};
    phases[size_t(at)].first = corrupt;
    const std::string bad = write_phase_list(dir.path(), phases);
    for (int at_once : {1, 2}) {
      try {
        run_plan(request(bad, "plan", radius, at_once));
        ADD_FAILURE() << "corrupt label map of phase " << at << " accepted";
      } catch (const Error& e) {
        EXPECT_NE(std::string(e.what()).find("corrupt.nii.gz"), std::string::npos) << e.what();
      }
      EXPECT_FALSE(fs::exists(dir.file("plan")));
    }
  }
}

// A 4D label map (phases along the 4th axis, as a 4D CT's segmentation comes) plans exactly like
// the phase list of its frames; the 3D tumor serves every phase; nothing of the split frames stays.
TEST(PlanBreathing, FourDInputsPlanExactlyLikeThePhaseListOfTheirFrames) {
  const test::TemporaryFolder dir;
  const test::MiniPlanInputs in = test::write_mini_plan_inputs(dir.path());
  const std::string a = write_labels_with_vessel_at(dir.path(), "labels_a.nii.gz", 16);
  const std::string b = write_labels_with_vessel_at(dir.path(), "labels_b.nii.gz", 4);
  run_plan(phases_request(write_phase_list(dir.path(), {{a, in.tumor}, {b, in.tumor}}),
                          dir.file("listed")));
  const std::string four_d = dir.file("labels_4d.nii.gz");
  write_volume_frames({read_volume<float>(a, VolumeReadOptions::path_safety_file()), read_volume<float>(b, VolumeReadOptions::path_safety_file())}, four_d);
  ASSERT_EQ(volume_frames(four_d), 2);
  ASSERT_EQ(volume_frames(a), 1);

  PlanRequest r = phases_request("", dir.file("four_d"));
  r.labels = {four_d};
  r.tumor = in.tumor;
  r.vulnerability = in.vulnerability;
  const nlohmann::json plan = run_plan(r);
  for (const char* v : kValues) {
    const std::string value = v;
    for (const std::string suffix : {"", "_phase00", "_phase01"}) {
      expect_identical(read_volume<float>(dir.file("listed/path_safety_" + value + suffix + ".nii.gz"), VolumeReadOptions::path_safety_file()),
                       read_volume<float>(dir.file("four_d/path_safety_" + value + suffix + ".nii.gz"), VolumeReadOptions::path_safety_file()),
                       value + suffix);
    }
  }
  const nlohmann::json& phases = plan["breathing"]["phases"];
  ASSERT_EQ(phases.size(), 2u);
  EXPECT_EQ(phases[1]["inputs"]["frame"], 1);
  EXPECT_NE(phases[1]["inputs"]["label_maps"][0].dump().find("labels_4d.nii.gz"), std::string::npos)
      << phases[1]["inputs"].dump();
  EXPECT_TRUE(plan["breathing"]["phase_list"].is_null());
  for (const auto& entry : fs::directory_iterator(dir.path())) {
    EXPECT_EQ(entry.path().filename().string().find("4d-frames"), std::string::npos)
        << entry.path() << " left behind";
  }
}

TEST(PlanBreathing, FourDInputsOfDifferentPhaseCountsAreRefusedNamingBoth) {
  const test::TemporaryFolder dir;
  const test::MiniPlanInputs in = test::write_mini_plan_inputs(dir.path());
  const Volume<float> labels = read_volume<float>(in.labels, VolumeReadOptions::path_safety_file());
  const Volume<float> tumor = read_volume<float>(in.tumor, VolumeReadOptions::path_safety_file());
  write_volume_frames({labels, labels}, dir.file("labels_4d.nii.gz"));
  write_volume_frames({tumor, tumor, tumor}, dir.file("tumor_4d.nii.gz"));
  PlanRequest r = phases_request("", dir.file("plan"));
  r.labels = {dir.file("labels_4d.nii.gz")};
  r.tumor = dir.file("tumor_4d.nii.gz");
  r.vulnerability = in.vulnerability;
  try {
    run_plan(r);
    ADD_FAILURE() << "2 and 3 phases accepted";
  } catch (const Error& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("labels_4d.nii.gz"), std::string::npos) << what;
    EXPECT_NE(what.find("tumor_4d.nii.gz"), std::string::npos) << what;
    EXPECT_NE(what.find("3 phases"), std::string::npos) << what;
  }
  EXPECT_FALSE(fs::exists(dir.file("plan")));
}

}  // namespace
}  // namespace crepuscular::planning
