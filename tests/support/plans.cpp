#include "tests/support/plans.hpp"

#include <fstream>

#include "planning/imaging/volume_io.hpp"
#include "tests/support/grids.hpp"

namespace crepuscular::test {

planning::ImageGeometry mini_plan_grid() { return cube_grid(24, 2.0, Eigen::Vector3d(-20, 10, 5)); }

pipelines::PlanRequest MiniPlanInputs::request(const std::string& out_dir) const {
  pipelines::PlanRequest r;
  r.labels = {labels};
  r.tumor = tumor;
  r.vulnerability = vulnerability;
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

}  // namespace crepuscular::test
