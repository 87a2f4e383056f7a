// The area job (§3.3, docs/ARCHITECTURE.md §6): the area safety geometry alone, as a fast preview
// from the blocking volume or from an existing plan's path safety volume, written as
// OUT/area_safety.vtk and OUT/area.json.
#pragma once

#include <limits>
#include <nlohmann/json_fwd.hpp>
#include <string>
#include <vector>

namespace crepuscular::pipelines {

struct AreaRequest {
  std::string tumor;     // tumor mask; path safety mode: default is the plan's tumor
  bool preview = false;  // blocking threshold instead of path safety
  // Preview: the blocking volume, from labels + table, or a ready blocking volume.
  std::string labels, vulnerability, preset, blocking;
  double margin_fwhm_mm = 5.0;
  // Path safety mode: an existing plan folder and the value to use (empty: first in the plan).
  std::string plan_dir, value;
  // Unsafe threshold. Preview: blocking per mm (NaN: the table's second-lowest non-zero
  // coefficient, i.e. anything above the lowest risk level blocks). Path safety: value threshold
  // (NaN: from the plan's classes and unsafe_class).
  double threshold = std::numeric_limits<double>::quiet_NaN();
  std::string unsafe_class = "dangerous";  // path safety: "dangerous" or "medium" (medium+)
  double max_distance_mm = 0;              // 0: the plan's R (path safety) or 120 mm (preview)
  double spacing_mm = 0;  // 0: the plan's h (path safety) or the smallest input spacing
  double angular_step_deg = 1.0;  // planning::AreaSafetyOptions::angular_step_deg
  std::string out_dir;
  // SeriesInstanceUIDs chosen for DICOM folders of several series (--series; see
  // planning::VolumeReadOptions::dicom_series).
  std::vector<std::string> series;
};

// Runs the job and writes OUT/area_safety.vtk and OUT/area.json (staged: complete or nothing;
// never into a plan folder). Returns area.json's content. Throws Error naming the input by its
// role on bad input.
nlohmann::json run_area(const AreaRequest& request);

}  // namespace crepuscular::pipelines
