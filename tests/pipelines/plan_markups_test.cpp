// The plan's markups for 3D Slicer on a 4 mm phantom plan: trajectories.mrk.json (one line per
// safe region, entry on the skin, to the tumor centre) and entries.mrk.json are valid against
// Slicer's markups schema v1.0.3 (python3-jsonschema, tests/data/slicer-markups-schema), read back
// by our own reader, and every planned entry is outside the body next to the skin, not
// dangerous, in the region it names, on a line to the tumor centre that crosses no high-level
// structure.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "pipelines/plan.hpp"
#include "planning/imaging/fiducials.hpp"
#include "planning/imaging/sampling.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/plan_folder/plan_folder.hpp"
#include "planning/simulation/phantom.hpp"
#include "planning/trajectories/evaluate.hpp"
#include "planning/trajectories/markups.hpp"
#include "tests/support/plans.hpp"
#include "tests/support/temporary_folder.hpp"

namespace fs = std::filesystem;

namespace crepuscular::planning {
namespace {

// Validates `file` against the schema with python3-jsonschema; "" when valid, else its message.
std::string schema_problem(const fs::path& file) {
  const fs::path schema =
      fs::path(CREPUSCULAR_TEST_DATA) / "slicer-markups-schema" / "markups-schema-v1.0.3.json";
  const fs::path out = file.string() + ".validation";
  const std::string command =
      "/usr/bin/python3 -c 'import json, sys, jsonschema; "
      "jsonschema.validate(json.load(open(sys.argv[1])), json.load(open(sys.argv[2])))' '" +
      file.string() + "' '" + schema.string() + "' > '" + out.string() + "' 2>&1";
  const int rc = std::system(command.c_str());
  std::ifstream in(out);
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  return rc == 0 ? std::string() : "rc " + std::to_string(rc) + ": " + text;
}

TEST(PlanMarkups, OneLinePerSafeRegionFromTheSkinToTheTumorCentreValidInSlicersSchema) {
  const test::TemporaryFolder dir;
  PhantomOptions po;
  po.spacing_mm = 4.0;
  write_phantom(make_phantom(po), (dir / "phantom").string());
  const pipelines::PlanRequest r = test::phantom_plan_request(dir / "phantom", (dir / "plan").string());
  const nlohmann::json plan_json = pipelines::run_plan(r);
  ASSERT_TRUE(plan_json["outputs"].contains("trajectories")) << plan_json["outputs"].dump();

  for (const char* name : {"trajectories.mrk.json", "entries.mrk.json"}) {
    EXPECT_EQ(schema_problem(dir / "plan" / name), "") << name;
  }
  // A file the schema refuses is refused here too (the check can fail).
  std::ofstream(dir / "bad.mrk.json") << R"({"markups": [{"type": "Spline"}]})";
  EXPECT_NE(schema_problem(dir / "bad.mrk.json"), "");

  std::ifstream in(dir / "plan" / "trajectories.mrk.json");
  const nlohmann::json lines = nlohmann::json::parse(in);
  const PlanData plan = load_plan((dir / "plan").string());
  const Volume<int32_t> labels = read_label_map(r.labels.front());
  const size_t regions = plan.area->regions.size();
  ASSERT_GE(lines["markups"].size(), 1u);
  EXPECT_LE(lines["markups"].size(), regions);
  // Our own reader reads the first line back: the largest region's entry, then the centre.
  const LineMarkup first = read_line_markup((dir / "plan" / "trajectories.mrk.json").string());
  EXPECT_LT((first.second - plan.tumor_centre).norm(), 1e-6);
  EXPECT_EQ(lines["markups"][0]["coordinateSystem"], "LPS");

  const TrajectoryEvaluator evaluator(plan);
  for (const auto& markup : lines["markups"]) {
    const auto& p = markup["controlPoints"][0]["position"];
    const Eigen::Vector3d entry(p[0].get<double>(), p[1].get<double>(), p[2].get<double>());
    SCOPED_TRACE(markup["name"].get<std::string>() + " at " +
                 std::to_string((entry - plan.tumor_centre).norm()) + " mm");
    // On the skin: just outside the body, within one voxel of it.
    EXPECT_EQ(nearest_voxel_or(labels, entry, -1), 0);
    const Eigen::Vector3d inward = (plan.tumor_centre - entry).normalized();
    EXPECT_GT(nearest_voxel_or(labels, Eigen::Vector3d(entry + 4.0 * inward), 0), 0);
    // Not dangerous at the entry (the criterion area safety used), and the line crosses no
    // structure of a high or impassable level; the entry lies in the region it is named after.
    const SafetyClasses& classes = plan.classes.at("svv");
    const Volume<float>& svv = plan.path_safety.at("svv");
    EXPECT_GT(trilinear_finite(svv, svv.physical_to_index(entry)), classes.dangerous);
    Trajectory t;
    t.name = "planned";
    t.entry = entry;
    t.target = plan.tumor_centre;
    const TrajectoryEvaluation e = evaluator.evaluate(t);
    for (const StructureHit& hit : e.structures) EXPECT_LT(hit.level, 3) << hit.name;
    EXPECT_TRUE(e.target_in_tumor);
    ASSERT_TRUE(e.area.available);
    EXPECT_EQ("Region " + std::to_string(e.area.region + 1),
              markup["name"].get<std::string>().substr(0, 8));
  }
  std::ifstream pin(dir / "plan" / "entries.mrk.json");
  const nlohmann::json entries = nlohmann::json::parse(pin);
  EXPECT_EQ(entries["markups"][0]["controlPoints"].size(), lines["markups"].size());
  EXPECT_EQ(read_fiducial_markups((dir / "plan" / "entries.mrk.json").string()).size(),
            lines["markups"].size());
}

}  // namespace
}  // namespace crepuscular::planning
