#include "tests/support/plans.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <nlohmann/json.hpp>

#include "foundation/json_fields.hpp"
#include "planning/imaging/segmentation.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/views/palette.hpp"
#include "tests/support/grids.hpp"

namespace crepuscular::test {

planning::ImageGeometry mini_plan_grid() { return cube_grid(24, 2.0, Eigen::Vector3d(-20, 10, 5)); }

pipelines::PlanRequest MiniPlanInputs::request(const std::string& out_dir) const {
  pipelines::PlanRequest r;
  r.labels = {labels};
  r.tumor = tumor;
  r.vulnerability = vulnerability;
  r.ct = ct;  // recorded in plan.json when written (on the labels' grid: the plan is the same)
  r.path_safety.radius_mm = 16.0;
  r.path_safety.device = planning::Device::kCpu;
  r.out_dir = out_dir;
  return r;
}

void write_fat_and_vessel_table(const std::string& path) {
  std::ofstream(path) << R"({"name": "test", "levels": [
      {"level": 0, "name": "none", "blocking_per_mm": 0.0},
      {"level": 1, "name": "low", "blocking_per_mm": 0.01},
      {"level": 2, "name": "medium", "blocking_per_mm": 0.1},
      {"level": 3, "name": "impassable", "blocking_per_mm": 10.0}],
    "labels": [{"value": 1, "name": "fat", "level": 0},
               {"value": 2, "name": "vessel", "level": 3}]})";
}

MiniPlanInputs write_mini_plan_inputs(const std::filesystem::path& dir,
                                      const MiniPlanOptions& options) {
  MiniPlanInputs in;
  in.grid = options.grid;
  planning::Volume<int32_t> labels(in.grid, 1);
  planning::Volume<uint8_t> tumor(in.grid, 0);
  for (int k = 10; k <= 12; ++k)
    for (int j = 10; j <= 12; ++j)
      for (int i = 10; i <= 12; ++i) tumor(i, j, k) = 1;
  const int first_row = options.vessel_sheet ? 0 : 9;
  const int last_row = options.vessel_sheet ? 23 : 13;
  for (int k = 0; k < 24; ++k)
    for (int j = first_row; j <= last_row; ++j) labels(16, j, k) = 2;
  in.labels = (dir / "labels.nii.gz").string();
  in.tumor = (dir / "tumor.nii.gz").string();
  in.vulnerability = (dir / "table.json").string();
  planning::write_volume(labels, in.labels);
  planning::write_volume(tumor, in.tumor);
  write_fat_and_vessel_table(in.vulnerability);
  if (options.ct) {
    in.ct = (dir / "ct.nii.gz").string();
    planning::write_volume(planning::Volume<float>(in.grid, 40.0f), in.ct);
  }
  return in;
}

pipelines::PlanRequest phantom_plan_request(const std::filesystem::path& phantom_dir,
                                            const std::string& out_dir) {
  pipelines::PlanRequest r;
  r.labels = {(phantom_dir / "labels.nii.gz").string()};
  r.tumor = (phantom_dir / "tumor.nii.gz").string();
  r.vulnerability = (phantom_dir / "vulnerability.json").string();
  r.path_safety.values = planning::parse_value_set("svv");
  r.path_safety.mode = planning::Mode::kFast;
  r.path_safety.device = planning::Device::kCpu;
  r.path_safety.radius_mm = 100.0;
  r.out_dir = out_dir;
  return r;
}

int expected_class_label(double value, uint8_t state, bool higher_is_safer, double safe,
                         double dangerous) {
  if (state == 2) return 4;
  if (state != 1) return 0;
  if (higher_is_safer) return value >= safe ? 1 : (value < dangerous ? 3 : 2);
  return value <= safe ? 1 : (value > dangerous ? 3 : 2);
}

std::array<int64_t, 4> expect_classes_segmentation_matches_plan(
    const std::filesystem::path& plan_dir, const std::string& value) {
  std::array<int64_t, 4> counts{};
  const nlohmann::json plan = read_json_file((plan_dir / "plan.json").string(), "the plan");
  const std::string file = "path_safety_" + value + "_classes.seg.nrrd";
  EXPECT_EQ(plan["outputs"].value(value + "_classes", ""), file) << value;
  const planning::Volume<float> values =
      planning::read_volume<float>((plan_dir / plan["outputs"][value].get<std::string>()).string(),
                                   planning::VolumeReadOptions::path_safety_file());
  const planning::Volume<uint8_t> roi = planning::read_volume<uint8_t>(
      (plan_dir / plan["outputs"]["roi"].get<std::string>()).string());
  const planning::Segmentation seg = planning::read_segmentation((plan_dir / file).string());
  EXPECT_TRUE(seg.geometry().same_grid(values.geometry(), 1e-6)) << file;
  if (!seg.geometry().same_grid(values.geometry(), 1e-6)) return counts;
  const std::array<planning::Rgb, 3> palette = planning::class_colours(planning::Palette::kDefault);
  const char* const names[] = {"safe", "medium", "dangerous", "unknown"};
  EXPECT_EQ(seg.segments.size(), 4u) << file;
  if (seg.segments.size() != 4u) return counts;
  const nlohmann::json& t = plan["classes"][value];
  const bool higher = t["higher_is_safer"].get<bool>();
  const double safe = t["safe"].get<double>(), dangerous = t["dangerous"].get<double>();
  for (int c = 0; c < 4; ++c) {
    const planning::Segment& s = seg.segments[size_t(c)];
    EXPECT_EQ(s.id, names[c]) << file;
    EXPECT_EQ(s.name, names[c]) << file;
    EXPECT_EQ(s.label_value, c + 1) << file << " " << names[c];
    EXPECT_EQ(s.layer, 0) << file << " " << names[c];
    EXPECT_TRUE(s.colour.has_value()) << file << " " << names[c];
    for (size_t k = 0; k < 3 && s.colour; ++k) {
      const double want = c < 3 ? palette[size_t(c)][k] / 255.0 : 0.5;
      EXPECT_NEAR((*s.colour)[k], want, 1e-12) << file << " " << names[c] << " channel " << k;
    }
    const planning::Volume<uint8_t> mask = seg.segment_mask(s);
    int64_t differing = 0;
    for (int64_t v = 0; v < values.voxel_count(); ++v) {
      const bool expected =
          expected_class_label(values[v], roi[v], higher, safe, dangerous) == c + 1;
      differing += (mask[v] != 0) != expected ? 1 : 0;
      counts[size_t(c)] += mask[v] != 0 ? 1 : 0;
    }
    EXPECT_EQ(differing, 0) << file << ": voxels of segment " << names[c];
  }
  return counts;
}

}  // namespace crepuscular::test
