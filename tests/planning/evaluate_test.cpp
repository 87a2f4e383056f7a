// Trajectory evaluation on analytic scenes: line integrals of uniform and slab blocking, the
// structures a path crosses (depth and length within one sampling step), the rank of the entry's
// path safety, the area safety region of the entry, the batch CSV, and the command end to end.
#include "planning/trajectories/evaluate.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>

#include "foundation/error.hpp"
#include "planning/trajectories/markups.hpp"
#include "pipelines/plan.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/safety/unknown.hpp"
#include "tests/support/cli.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/grids.hpp"
#include "tests/support/plans.hpp"
#include "tests/support/temporary_folder.hpp"

namespace fs = std::filesystem;

namespace crepuscular::planning {
namespace {

using pipelines::PlanRequest;
using pipelines::run_plan;
using test::cube_grid;
using test::run_cli;

// A plan with only a blocking volume (and h = its spacing, gamma = h / 2).
PlanData blocking_plan(const Volume<float>& blocking) {
  PlanData p;
  p.dir = "(test plan)";
  p.blocking = blocking;
  p.gamma_mm = 0.5 * blocking.geometry().spacing.minCoeff();
  return p;
}

VulnerabilityTable test_table() {
  return VulnerabilityTable::from_json(nlohmann::json::parse(R"({"name": "test", "levels": [
        {"level": 0, "name": "none", "blocking_per_mm": 0.0},
        {"level": 1, "name": "low", "blocking_per_mm": 0.01},
        {"level": 2, "name": "medium", "blocking_per_mm": 0.1},
        {"level": 3, "name": "impassable", "blocking_per_mm": 10.0}],
      "labels": [{"value": 2, "name": "kidney", "level": 2},
                 {"value": 3, "name": "vessel", "level": 3}]})"),
                                       "test table");
}

TEST(EvaluateTest, UniformBlockingIntegralIsCoefficientTimesLength) {
  // b = 0.3 per mm everywhere; trilinear interpolation of a constant is the constant, so every
  // sample is 0.3 and the sum is 0.3 * length exactly (up to rounding).
  const Volume<float> b(cube_grid(40, 2.0), 0.3f);
  const PlanData plan = blocking_plan(b);
  const TrajectoryEvaluator ev(plan);
  Trajectory t;
  t.entry = Eigen::Vector3d(5, 7, 9);
  t.target = Eigen::Vector3d(61, 44, 70);
  const auto e = ev.evaluate(t);
  const double length = (t.target - t.entry).norm();
  EXPECT_NEAR(e.length_mm, length, 1e-9);
  EXPECT_NEAR(e.line_integral, 0.3 * length, 1e-5 * length);
  // N = ceil(length / gamma), l = length / N <= gamma (docs/ARCHITECTURE.md §4).
  EXPECT_EQ(e.samples, int(std::ceil(length / 1.0)));
  EXPECT_LE(e.step_mm, 1.0 + 1e-12);
}

// An entry 5e9 mm away would overflow the sample count and one at 1e9 mm would take seconds to
// march: both are refused at once, as is a point that is not finite.
TEST(EvaluateTest, AbsurdOrNonFinitePointsAreRefusedAtOnce) {
  const Volume<float> b(cube_grid(40, 2.0), 0.3f);
  const PlanData plan = blocking_plan(b);
  const TrajectoryEvaluator ev(plan);
  Trajectory t;
  t.name = "typo";
  t.target = Eigen::Vector3d(61, 44, 70);
  for (const double x : {5e9, 1e9, -3000.0}) {
    t.entry = Eigen::Vector3d(x, 7, 9);
    test::expect_error_containing([&] { ev.evaluate(t); }, {"typo", "mm from the target", "at most 2000"});
  }
  t.entry = Eigen::Vector3d(std::numeric_limits<double>::quiet_NaN(), 7, 9);
  test::expect_error_containing([&] { ev.evaluate(t); }, {"typo", "not a finite point"});
  t.entry = Eigen::Vector3d(5, 7, 1500);  // 1.43 m: long, but a path
  EXPECT_NO_THROW(ev.evaluate(t));
}

TEST(EvaluateTest, SlabBlockingIntegralIsSlabCrossingLength) {
  // b = 1 per mm on voxel columns i = 15..24 (2 mm voxels), 0 elsewhere. Along x the trilinear
  // interpolant is 1 on [15, 24] and ramps to 0 over one voxel each side: its integral is 10
  // voxels = 20 mm for a path along x, and 20 / cos(theta) for a path at angle theta to x.
  Volume<float> b(cube_grid(40, 2.0), 0.0f);
  for (int k = 0; k < 40; ++k)
    for (int j = 0; j < 40; ++j)
      for (int i = 15; i <= 24; ++i) b(i, j, k) = 1.0f;
  const PlanData plan = blocking_plan(b);
  const TrajectoryEvaluator ev(plan);
  for (double theta_deg : {0.0, 25.0, 50.0}) {
    const double th = theta_deg * M_PI / 180.0;
    const Eigen::Vector3d dir(std::cos(th), std::sin(th) * 0.6, std::sin(th) * 0.8);
    Trajectory t;
    t.entry = Eigen::Vector3d(10.3, 20, 20) - 5.0 * dir;
    t.target = t.entry + (60.0 / std::cos(th)) * dir;  // x from 5.3 to 65.3: through the slab
    const auto e = ev.evaluate(t);
    const double expected = 20.0 / std::cos(th);
    // The sum of samples differs from the integral by at most one step times the jump of b.
    EXPECT_NEAR(e.line_integral, expected, e.step_mm) << "theta " << theta_deg;
  }
}

TEST(EvaluateTest, PathThroughLabelledBoxesReportsStructuresDepthsAndLengths) {
  // 1 mm label grid. Along x at y = z = 20: kidney (2) on voxels 20..29 and 70..74, vessel (3)
  // on 50..64. Voxel i covers x in [i - 0.5, i + 0.5].
  Volume<int32_t> labels(cube_grid(100, 1.0), 0);
  for (int k = 0; k < 100; ++k)
    for (int j = 0; j < 100; ++j) {
      for (int i = 20; i <= 29; ++i) labels(i, j, k) = 2;
      for (int i = 50; i <= 64; ++i) labels(i, j, k) = 3;
      for (int i = 70; i <= 74; ++i) labels(i, j, k) = 2;
    }
  PlanData plan = blocking_plan(Volume<float>(cube_grid(50, 2.0), 0.0f));
  plan.labels = labels;
  plan.table = test_table();
  const TrajectoryEvaluator ev(plan);

  Trajectory t;
  t.entry = Eigen::Vector3d(5, 20, 20);
  t.target = Eigen::Vector3d(95, 20, 20);
  auto e = ev.evaluate(t);
  ASSERT_TRUE(e.labels_available);
  ASSERT_EQ(e.structures.size(), 2u);
  const double tol = e.structure_step_mm + 1e-9;
  EXPECT_LE(e.structure_step_mm, 0.5);
  EXPECT_EQ(e.structures[0].label, 2);
  EXPECT_EQ(e.structures[0].name, "kidney");
  EXPECT_EQ(e.structures[0].level, 2);
  EXPECT_EQ(e.structures[0].level_name, "medium");
  EXPECT_NEAR(e.structures[0].depth_mm, 19.5 - 5.0, tol);
  EXPECT_NEAR(e.structures[0].length_mm, 10.0 + 5.0, 2 * tol);  // two crossings
  EXPECT_EQ(e.structures[1].name, "vessel");
  EXPECT_EQ(e.structures[1].level, 3);
  EXPECT_NEAR(e.structures[1].depth_mm, 49.5 - 5.0, tol);
  EXPECT_NEAR(e.structures[1].length_mm, 15.0, tol);

  // Oblique in the xy plane, direction (1, 1, 0) / sqrt(2) from (5, 5, 20): the first kidney box
  // (x in [19.5, 29.5]) is entered after (19.5 - 5) sqrt(2) mm and crossed over 10 sqrt(2) mm.
  t.entry = Eigen::Vector3d(5, 5, 20);
  t.target = Eigen::Vector3d(45, 45, 20);
  e = ev.evaluate(t);
  ASSERT_EQ(e.structures.size(), 1u);
  EXPECT_NEAR(e.structures[0].depth_mm, 14.5 * std::sqrt(2.0), e.structure_step_mm + 1e-9);
  EXPECT_NEAR(e.structures[0].length_mm, 10.0 * std::sqrt(2.0), e.structure_step_mm + 1e-9);
}

TEST(EvaluateTest, EntryValueClassAndPercentileWithinTheRegionOfInterest) {
  // 10^3 grid, value = linear offset (0..999, all distinct); the 8 corner voxels are outside the
  // region of interest (NaN). A voxel of value v ranks above (v - outside below it) others.
  const ImageGeometry g = cube_grid(10, 3.0, Eigen::Vector3d(-13.5, -13.5, -13.5));
  Volume<float> isbv(g, 0.0f);
  for (int64_t o = 0; o < isbv.voxel_count(); ++o) isbv[o] = float(o);
  const float nan = std::numeric_limits<float>::quiet_NaN();
  for (int c = 0; c < 8; ++c) isbv((c & 1) * 9, ((c >> 1) & 1) * 9, ((c >> 2) & 1) * 9) = nan;
  PlanData plan = blocking_plan(Volume<float>(g, 0.0f));
  plan.values = {"isbv"};
  plan.path_safety["isbv"] = isbv;
  SafetyClasses c;
  c.higher_is_safer = false;
  c.safe = 200;
  c.dangerous = 600;
  plan.classes["isbv"] = c;
  const TrajectoryEvaluator ev(plan);

  Trajectory t;
  t.entry = g.index_to_physical(3, 4, 5);  // value 543, medium
  t.target = g.index_to_physical(5, 5, 5);
  auto e = ev.evaluate(t);
  ASSERT_EQ(e.values.size(), 1u);
  EXPECT_NEAR(e.values[0].at_entry, 543.0, 1e-9);
  EXPECT_EQ(e.values[0].safety_class, "medium");
  // Below 543 in the ROI: 543 values minus the corners 0, 9, 90, 99, 900.. that are below: 4.
  const double n = 1000 - 8, below = 543 - 4;
  EXPECT_NEAR(e.values[0].percentile, 100.0 * (below + 0.5) / n, 1e-9);
  EXPECT_NEAR(e.values[0].safety_percentile, 100.0 - 100.0 * (below + 0.5) / n, 1e-9);

  // Half-way between voxels (3,4,5) and (4,4,5): the mean, 543.5.
  t.entry = g.index_to_physical(Eigen::Vector3d(3.5, 4, 5));
  EXPECT_NEAR(ev.evaluate(t).values[0].at_entry, 543.5, 1e-9);
  // A corner voxel is outside the region of interest.
  t.entry = g.index_to_physical(0, 0, 0);
  e = ev.evaluate(t);
  EXPECT_EQ(e.values[0].safety_class, "outside");
  EXPECT_TRUE(std::isnan(e.values[0].at_entry));
}

TEST(EvaluateTest, OutsideTheScanIsUnknownNeverSafeInJsonTextAndCsv) {
  // 10^3 voxels of 3 mm, centres -13.5 .. 13.5: svv 95 (safe) where z < 0 (k < 5), unknown
  // above (outside the scan: NaN and region state 2, as load_plan gives them); one dangerous
  // column at i = j = 2.
  const ImageGeometry g = cube_grid(10, 3.0, Eigen::Vector3d(-13.5, -13.5, -13.5));
  Volume<float> svv(g, 95.0f);
  Volume<uint8_t> region(g, kRegionComputed);
  for (int k = 5; k < 10; ++k)
    for (int j = 0; j < 10; ++j)
      for (int i = 0; i < 10; ++i) {
        svv(i, j, k) = std::numeric_limits<float>::quiet_NaN();
        region(i, j, k) = kRegionUnknown;
      }
  for (int k = 0; k < 5; ++k) svv(2, 2, k) = 10.0f;
  PlanData plan = blocking_plan(Volume<float>(g, 0.0f));
  plan.values = {"svv"};
  plan.path_safety["svv"] = svv;
  SafetyClasses c;
  c.higher_is_safer = true;
  c.safe = 90;
  c.dangerous = 50;
  plan.classes["svv"] = c;
  plan.region = region;
  const TrajectoryEvaluator ev(plan);
  const auto csv_tail = [](const TrajectoryEvaluation& e) {
    const std::string row = evaluation_csv_row(e);
    const size_t a = row.rfind(','), b = row.rfind(',', a - 1);
    return row.substr(b + 1);
  };

  // Inside the scan all the way: safe, nothing outside.
  Trajectory t;
  t.entry = Eigen::Vector3d(1.5, 1.5, -10.5);
  t.target = Eigen::Vector3d(1.5, 1.5, -4.5);
  TrajectoryEvaluation e = ev.evaluate(t);
  EXPECT_EQ(e.values[0].safety_class, "safe");
  EXPECT_FALSE(e.entry_outside_scan);
  EXPECT_EQ(e.outside_scan_mm, 0.0);
  EXPECT_EQ(csv_tail(e), "0,0.0");

  // The entry in an unknown voxel beside computed ones (the trilinear sample alone would borrow
  // 95 from below): unknown, no value; a tenth of the path lies above z = 0.
  t.entry = Eigen::Vector3d(9, 0, 1.0);
  t.target = Eigen::Vector3d(0, 0, -9);
  e = ev.evaluate(t);
  EXPECT_TRUE(e.entry_outside_scan);
  EXPECT_EQ(e.values[0].safety_class, "unknown");
  EXPECT_TRUE(std::isnan(e.values[0].at_entry));
  EXPECT_NEAR(e.outside_scan_mm, 0.1 * e.length_mm, e.structure_step_mm);
  nlohmann::json j = evaluation_json(e);
  EXPECT_EQ(j["path_safety"]["svv"]["class"], "unknown");
  EXPECT_EQ(j["scan"]["entry_outside_scan"], true);
  EXPECT_GT(j["scan"]["length_outside_scan_mm"].get<double>(), 0.0);
  std::string text = evaluation_text(e);
  EXPECT_NE(text.find("entry lies OUTSIDE the scan"), std::string::npos) << text;
  EXPECT_NE(text.find("svv: unknown (outside the scan)"), std::string::npos) << text;
  EXPECT_EQ(csv_tail(e).substr(0, 2), "1,");
  EXPECT_NE(evaluation_csv_row(e).find(",unknown,"), std::string::npos);

  // A safe entry whose path runs on into the unknown part (7.5 of 18 mm): the value stays, the
  // class is unknown, the length is reported.
  t.entry = Eigen::Vector3d(1.5, 1.5, -10.5);
  t.target = Eigen::Vector3d(1.5, 1.5, 7.5);
  e = ev.evaluate(t);
  EXPECT_FALSE(e.entry_outside_scan);
  EXPECT_NEAR(e.values[0].at_entry, 95.0, 1e-9);
  EXPECT_EQ(e.values[0].safety_class, "unknown");
  EXPECT_NEAR(e.outside_scan_mm, 7.5, e.structure_step_mm);
  text = evaluation_text(e);
  EXPECT_NE(text.find("lie OUTSIDE the scan"), std::string::npos) << text;
  EXPECT_EQ(evaluation_json(e)["scan"]["leaves_scan"], true);
  // A dangerous entry stays dangerous (unknown parts can only add blocking).
  t.entry = Eigen::Vector3d(-7.5, -7.5, -10.5);
  t.target = Eigen::Vector3d(-7.5, -7.5, 7.5);
  EXPECT_EQ(ev.evaluate(t).values[0].safety_class, "dangerous");
  // An entry beyond the plan's grids (the blocking grid) is outside the scan too.
  t.entry = Eigen::Vector3d(1.5, 1.5, -30);
  t.target = Eigen::Vector3d(1.5, 1.5, -4.5);
  e = ev.evaluate(t);
  EXPECT_TRUE(e.entry_outside_scan);
  EXPECT_EQ(e.values[0].safety_class, "unknown");
  EXPECT_NEAR(e.outside_scan_mm, 15.0, e.structure_step_mm);

  // A plan without region states (older plans) knows nothing of the scan.
  plan.region = Volume<uint8_t>();
  const TrajectoryEvaluator old(plan);
  t.entry = Eigen::Vector3d(1.5, 1.5, -10.5);
  t.target = Eigen::Vector3d(1.5, 1.5, 7.5);
  EXPECT_EQ(old.evaluate(t).values[0].safety_class, "safe");
}

// Six base vertices on the axes around c (an octahedron), extruded along their normals; +x and
// +y form safe region 0 (300 mm^3), -x alone safe region 1 (100 mm^3); the rest unsafe.
AreaSafetyGeometry octahedron_area(const Eigen::Vector3d& c) {
  AreaSafetyGeometry a;
  a.ellipsoid.centre = c;
  const Eigen::Vector3d axes[6] = {Eigen::Vector3d::UnitX(), -Eigen::Vector3d::UnitX(),
                                   Eigen::Vector3d::UnitY(), -Eigen::Vector3d::UnitY(),
                                   Eigen::Vector3d::UnitZ(), -Eigen::Vector3d::UnitZ()};
  const int region[6] = {0, 1, 0, -1, -1, -1};
  for (int i = 0; i < 6; ++i) {
    a.base.push_back(c + 10 * axes[i]);
    a.normals.push_back(axes[i]);
    const double ext = region[i] >= 0 ? 50 : 12;
    a.vertices.push_back(c + (10 + ext) * axes[i]);
    a.safe.push_back(region[i] >= 0);
    a.region.push_back(region[i]);
    a.leeway.push_back(region[i] == 0 ? 1.0f : region[i] == 1 ? 1.0f / 3.0f : 0.0f);
  }
  AreaRegion r0, r1;
  r0.id = 0;
  r0.size_mm3 = 300;
  r0.leeway = 1;
  r1.id = 1;
  r1.size_mm3 = 100;
  r1.leeway = 1.0 / 3.0;
  a.regions = {r0, r1};
  return a;
}

TEST(EvaluateTest, EntryRegionIsThatOfTheNearestExtrusionRay) {
  const Eigen::Vector3d c(40, 40, 40);
  PlanData plan = blocking_plan(Volume<float>(cube_grid(40, 2.0), 0.0f));
  plan.area = octahedron_area(c);
  const TrajectoryEvaluator ev(plan);
  Trajectory t;
  t.target = c;
  t.entry = c + Eigen::Vector3d(50, 3, 0);  // beside the +x ray, 3 mm off
  auto e = ev.evaluate(t);
  ASSERT_TRUE(e.area.available);
  EXPECT_EQ(e.area.vertex, 0);
  EXPECT_NEAR(e.area.ray_distance_mm, 3.0, 1e-9);
  EXPECT_NEAR(e.area.along_normal_mm, 40.0, 1e-9);
  EXPECT_TRUE(e.area.safe);
  EXPECT_EQ(e.area.region, 0);
  EXPECT_NEAR(e.area.relative_area_safety, 1.0, 1e-12);

  t.entry = c + Eigen::Vector3d(-40, 2, -1);
  e = ev.evaluate(t);
  EXPECT_EQ(e.area.vertex, 1);
  EXPECT_EQ(e.area.region, 1);
  EXPECT_NEAR(e.area.relative_area_safety, 100.0 / 300.0, 1e-12);

  t.entry = c + Eigen::Vector3d(1, -2, 60);  // the +z ray: unsafe, stopped after 12 mm
  e = ev.evaluate(t);
  EXPECT_EQ(e.area.vertex, 4);
  EXPECT_FALSE(e.area.safe);
  EXPECT_EQ(e.area.region, -1);
  EXPECT_NEAR(e.area.extrusion_mm, 12.0, 1e-9);
  EXPECT_EQ(e.area.relative_area_safety, 0.0);
}

TEST(EvaluateTest, BatchCsvIsReadAndEveryRowHasTheHeadersColumns) {
  const test::TemporaryFolder dir;
  const std::string csv = (dir / "paths.csv").string();
  std::ofstream(csv) << "name,entry_x,entry_y,entry_z,target_x,target_y,target_z\n"
                        "\"a, first\",5,7,9,61,44,70\n\n"
                        "b,10,10,10,30,30,30\n";
  const auto ts = read_trajectories_csv(csv);
  ASSERT_EQ(ts.size(), 2u);
  EXPECT_EQ(ts[0].name, "a, first");
  EXPECT_EQ(ts[1].target, Eigen::Vector3d(30, 30, 30));
  PlanData plan = blocking_plan(Volume<float>(cube_grid(40, 2.0), 0.25f));
  plan.area = octahedron_area(Eigen::Vector3d(40, 40, 40));
  const TrajectoryEvaluator ev(plan);
  const auto e = ev.evaluate(ts[0]);
  const auto count = [](const std::string& s) {
    int n = 1;
    bool quoted = false;
    for (char c : s) {
      if (c == '"') quoted = !quoted;
      if (c == ',' && !quoted) ++n;
    }
    return n;
  };
  EXPECT_EQ(count(evaluation_csv_header(e)), count(evaluation_csv_row(e)));
  EXPECT_EQ(evaluation_csv_row(e).rfind("\"a, first\",", 0), 0u);
  EXPECT_DOUBLE_EQ(evaluation_json(e)["line_integral"].get<double>(), e.line_integral);

  std::ofstream(csv) << "name,x,y\n";
  EXPECT_THROW(read_trajectories_csv(csv), Error);
  std::ofstream(csv)
      << "name,entry_x,entry_y,entry_z,target_x,target_y,target_z\nx,1,2,3,4,5,abc\n";
  test::expect_error_containing([&] { read_trajectories_csv(csv); }, {"line 2", "target_z"});
  Trajectory same;
  EXPECT_THROW(ev.evaluate(same), Error);  // entry == target
}

TEST(EvaluateTest, CommandEvaluatesPointsMarkupsAndBatchesOfARealPlan) {
  // The mini plan: a 3-voxel tumor block at voxels 10..12, a vessel column (label 2) at i = 16.
  const test::TemporaryFolder dir;
  const test::MiniPlanInputs inputs = test::write_mini_plan_inputs(dir);
  const ImageGeometry g = inputs.grid;
  PlanRequest r = inputs.request((dir / "plan").string());
  r.margin.fwhm_mm = 0.0;
  run_plan(r);

  // Through the vessel column (+i): from voxel (18, 11, 11), inside the 16 mm region of interest,
  // to the tumor centre (11, 11, 11).
  const Eigen::Vector3d entry = g.index_to_physical(18, 11, 11),
                        target = g.index_to_physical(11, 11, 11);
  const auto pt = [](const Eigen::Vector3d& p) {
    char b[96];
    std::snprintf(b, sizeof(b), "%.4f,%.4f,%.4f", p.x(), p.y(), p.z());
    return std::string(b);
  };
  std::string out;
  ASSERT_EQ(run_cli("evaluate --plan " + (dir / "plan").string() + " --entry " + pt(entry) +
                        " --target " + pt(target) + " --json",
                    &out),
            0)
      << out;
  const auto j = nlohmann::json::parse(out.substr(out.find('{')));
  // Vessel voxels i = 16 cover 2 mm of the path at 10 per mm: the trilinear interpolant's
  // integral over the column is one voxel (2 mm) times 10 = 20 (within one step of 1 mm * 10).
  EXPECT_NEAR(j["line_integral"].get<double>(), 20.0, 10.0 * 1.0 + 1e-6);
  ASSERT_TRUE(j["structures"].is_array());
  bool vessel = false;
  for (const auto& s : j["structures"]) {
    if (s["name"] == "vessel") {
      vessel = true;
      EXPECT_EQ(s["level"].get<int>(), 3);
      // Voxel 16 covers [15.5, 16.5] in index units: 1.5 voxels = 3 mm from voxel 18's centre.
      EXPECT_NEAR(s["depth_mm"].get<double>(), 3.0, j["structure_step_mm"].get<double>() + 1e-9);
      EXPECT_NEAR(s["length_mm"].get<double>(), 2.0, j["structure_step_mm"].get<double>() + 1e-9);
    }
  }
  EXPECT_TRUE(vessel);
  EXPECT_TRUE(j["target_in_tumor"].get<bool>());
  // Tumor voxel 12 ends at index 12.5: 5.5 voxels = 11 mm from the entry.
  EXPECT_NEAR(j["tumor_depth_mm"].get<double>(), 11.0, j["structure_step_mm"].get<double>() + 1e-9);
  EXPECT_TRUE(j["path_safety"].contains("svv"));
  // The entry lies across the vessel from the tumor: SVV well below the free side's 100 %.
  EXPECT_LT(j["path_safety"]["svv"]["at_entry"].get<double>(), 100.0);

  // The plan's area safety geometry, when it has one, places the entry in some column.
  if (fs::exists(dir / "plan" / "area_safety.vtk")) {
    ASSERT_TRUE(j["area_safety"].is_object());
    EXPECT_GE(j["area_safety"]["vertex"].get<int>(), 0);
  }

  // The same line as a RAS markup with the target first gives the same integral.
  LineMarkup line;
  line.first = target;
  line.second = entry;
  write_line_markup((dir / "line.mrk.json").string(), line, "RAS");
  ASSERT_EQ(run_cli("evaluate --plan " + (dir / "plan").string() + " --trajectory " +
                        (dir / "line.mrk.json").string() + " --json",
                    &out),
            0)
      << out;
  const auto jm = nlohmann::json::parse(out.substr(out.find('{')));
  EXPECT_NEAR(jm["line_integral"].get<double>(), j["line_integral"].get<double>(), 1e-9);
  EXPECT_NEAR(
      (Eigen::Vector3d(jm["entry_lps_mm"][0], jm["entry_lps_mm"][1], jm["entry_lps_mm"][2]) - entry)
          .norm(),
      0.0, 1e-9);

  std::ofstream(dir / "paths.csv")
      << "name,entry_x,entry_y,entry_z,target_x,target_y,target_z\n"
      << "through_vessel," << pt(entry) << "," << pt(target) << "\n"
      << "free_side," << pt(g.index_to_physical(4, 11, 11)) << "," << pt(target) << "\n";
  ASSERT_EQ(run_cli("evaluate --plan " + (dir / "plan").string() + " --batch " +
                        (dir / "paths.csv").string(),
                    &out),
            0)
      << out;
  EXPECT_NE(out.find("name,entry_x"), std::string::npos) << out;
  EXPECT_NE(out.find("\nthrough_vessel,"), std::string::npos) << out;
  EXPECT_NE(out.find("\nfree_side,"), std::string::npos) << out;
  std::string quiet;
  ASSERT_EQ(run_cli("evaluate --plan " + (dir / "plan").string() + " --batch " +
                        (dir / "paths.csv").string() + " --out " + (dir / "results.csv").string(),
                    &quiet),
            0)
      << quiet;
  std::ifstream results(dir / "results.csv");
  EXPECT_EQ(std::string(std::istreambuf_iterator<char>(results), {}), out);

  // Bad input: a clear error, non-zero exit.
  EXPECT_NE(
      run_cli("evaluate --plan " + (dir / "plan").string() + " --entry 1,2 --target 3,4,5", &out),
      0);
  EXPECT_NE(out.find("--entry"), std::string::npos) << out;
}

}  // namespace
}  // namespace crepuscular::planning

namespace crepuscular::planning {
namespace {

TEST(EvaluateTest, InputsChangedSincePlanningAreReportedInEveryAnswer) {
  const test::TemporaryFolder dir;
  const test::MiniPlanInputs inputs = test::write_mini_plan_inputs(dir);
  run_plan(inputs.request((dir / "plan").string()));
  const std::string plan_dir = (dir / "plan").string();
  EXPECT_TRUE(load_plan(plan_dir).changed_inputs.empty());

  // The tumor file replaced by another lesion (one voxel further along i): the plan is stale.
  Volume<uint8_t> tumor = read_mask(inputs.tumor);
  Volume<uint8_t> moved(tumor.geometry(), 0);
  for (int k = 0; k < 24; ++k)
    for (int j = 0; j < 24; ++j)
      for (int i = 1; i < 24; ++i) moved(i, j, k) = tumor(i - 1, j, k);
  write_volume(moved, inputs.tumor);
  const PlanData stale = load_plan(plan_dir);
  ASSERT_EQ(stale.changed_inputs.size(), 1u);
  EXPECT_EQ(stale.changed_inputs[0].role, "tumor");
  EXPECT_NE(stale.changed_inputs[0].message.find("another tumor"), std::string::npos);

  const ImageGeometry g = inputs.grid;
  const auto pt = [](const Eigen::Vector3d& p) {
    return std::to_string(p.x()) + "," + std::to_string(p.y()) + "," + std::to_string(p.z());
  };
  const std::string points = " --entry " + pt(g.index_to_physical(4, 11, 11)) + " --target " +
                             pt(g.index_to_physical(11, 11, 11));
  std::string out;
  ASSERT_EQ(run_cli("evaluate --plan " + plan_dir + points + " --json", &out), 0) << out;
  const auto j = nlohmann::json::parse(out.substr(out.find('{')));
  ASSERT_EQ(j["changed_inputs"].size(), 1u) << out;
  EXPECT_NE(j["changed_inputs"][0].get<std::string>().find(inputs.tumor), std::string::npos);
  ASSERT_EQ(run_cli("evaluate --plan " + plan_dir + points, &out), 0) << out;
  EXPECT_NE(out.find("WARNING: " + inputs.tumor + " (tumor) changed since planning"),
            std::string::npos)
      << out;

  // A label map given instead of the plan's that is not one it was planned from.
  Volume<int32_t> labels = read_label_map(inputs.labels);
  labels(0, 0, 0) = 2;
  const std::string other = (dir / "other_labels.nii.gz").string();
  write_volume(labels, other);
  PlanLoadOptions with_other;
  with_other.labels_override = other;
  const PlanData overridden = load_plan(plan_dir, with_other);
  ASSERT_EQ(overridden.changed_inputs.size(), 2u);
  EXPECT_EQ(overridden.changed_inputs[1].path, other);
  // The plan's own label map given explicitly is no change.
  with_other.labels_override = inputs.labels;
  EXPECT_EQ(load_plan(plan_dir, with_other).changed_inputs.size(), 1u);

  // A label map 2 m away would show "no structures": refused, naming it.
  ImageGeometry far_grid = labels.geometry();
  far_grid.origin += Eigen::Vector3d(2000, 0, 0);
  const std::string far = (dir / "far_labels.nii.gz").string();
  write_volume(Volume<int32_t>(far_grid, 2), far);
  std::string err;
  EXPECT_NE(run_cli("evaluate --plan " + plan_dir + points + " --labels " + far, &err), 0);
  EXPECT_NE(err.find("far_labels.nii.gz: the label map does not overlap"), std::string::npos)
      << err;
}

}  // namespace
}  // namespace crepuscular::planning
