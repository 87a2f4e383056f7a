// Small plans several tests share: the mini plan's input files and request, the phantom plan's
// request.
#pragma once

#include <array>
#include <cstdint>
#include <filesystem>
#include <string>

#include "pipelines/plan.hpp"
#include "planning/imaging/volume.hpp"

namespace crepuscular::test {

// 24^3 voxels of 2 mm, voxel (0, 0, 0) at (-20, 10, 5), identity direction.
planning::ImageGeometry mini_plan_grid();

struct MiniPlanOptions {
  planning::ImageGeometry grid = mini_plan_grid();  // 24^3 voxels; spacing, origin, axes free
  bool vessel_sheet = false;  // the vessel on every j (a sheet) instead of j = 9..13 (a column)
  bool ct = false;            // also write a CT of 40 HU everywhere
};

// The input files of the mini plan, in the folder given to write_mini_plan_inputs.
struct MiniPlanInputs {
  planning::ImageGeometry grid;
  std::string labels, tumor, vulnerability;  // labels.nii.gz, tumor.nii.gz, table.json
  std::string ct;                            // ct.nii.gz, or empty

  // These inputs planned into `out_dir`: R = 16 mm on the CPU, the CT (when written) recorded,
  // every other option its default.
  pipelines::PlanRequest request(const std::string& out_dir) const;
};

// Writes the mini plan's inputs into `dir`: a tumor block on voxels 10..12 of every axis; a
// "vessel" (label 2, impassable: 10 per mm) on voxels i = 16, j = 9..13 (or every j), every k;
// "fat" (label 1, free) elsewhere; the vulnerability table of those two labels.
MiniPlanInputs write_mini_plan_inputs(const std::filesystem::path& dir,
                                      const MiniPlanOptions& options = {});

// Writes the mini plan's vulnerability table to `path`: label 1 "fat" (level 0, no blocking),
// label 2 "vessel" (level 3, impassable: 10 per mm); levels 1 and 2 at 0.01 and 0.1 per mm.
void write_fat_and_vessel_table(const std::string& path);

// The plan of a phantom written by planning::write_phantom into `phantom_dir`, made quickly: SVV
// only, fast mode, R = 100 mm, on the CPU, into `out_dir`.
pipelines::PlanRequest phantom_plan_request(const std::filesystem::path& phantom_dir,
                                            const std::string& out_dir);

// The class of a plan's voxel by the definition (docs/ARCHITECTURE.md §4): 4 unknown where
// `state` (roi.nii.gz) is 2, else 0 (no class) where it is not 1, else 1 safe, 2 medium or 3
// dangerous by `thresholds` (plan.json "classes" of the value: higher_is_safer, safe, dangerous).
int expected_class_label(double value, uint8_t state, bool higher_is_safer, double safe,
                         double dangerous);

// Checks PLAN_DIR/path_safety_<value>_classes.seg.nrrd against the plan's path safety volume,
// roi.nii.gz and the thresholds plan.json states for `value` (GoogleTest failures): named in
// plan.json "outputs" as "<value>_classes", on the volume's grid, segments safe, medium,
// dangerous, unknown with label values 1 to 4 in layer 0 and the default palette's colours
// (unknown grey), each segment exactly the voxels expected_class_label gives it. Returns the
// voxels of each segment (safe, medium, dangerous, unknown).
std::array<int64_t, 4> expect_classes_segmentation_matches_plan(
    const std::filesystem::path& plan_dir, const std::string& value);

}  // namespace crepuscular::test
