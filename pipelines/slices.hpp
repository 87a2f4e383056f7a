// The slices job: 2D slice images (PNG) of a plan for radiologists (planning/views/slices.hpp
// draws them), with the pixel <-> LPS mm geometry of every image in slices.json.
#pragma once

#include <Eigen/Core>
#include <nlohmann/json_fwd.hpp>
#include <string>
#include <vector>

#include "planning/views/slices.hpp"

namespace crepuscular::pipelines {

struct SlicesRequest {
  std::string plan_dir;
  std::string ct;
  std::string labels;  // overrides the plan's label map
  // SeriesInstanceUIDs chosen for DICOM folders of several series (--series; see
  // planning::VolumeReadOptions::dicom_series).
  std::vector<std::string> series;
  std::string value;   // path safety value; empty: svv when computed, else the first
  bool have_at = false;
  Eigen::Vector3d at = Eigen::Vector3d::Zero();
  int region = -1;  // >= 0: centre on this area safety region (and oblique along its axis)
  std::vector<planning::SlicePlaneKind> planes{planning::SlicePlaneKind::kAxial,
                                               planning::SlicePlaneKind::kCoronal,
                                               planning::SlicePlaneKind::kSagittal};
  planning::SliceOptions options;
  std::string out_dir;
};

// Writes OUT/<plane>.png for every plane and OUT/slices.json (each view's plane, pixel geometry
// and what it shows); the folder appears complete or not at all. Returns slices.json's content.
nlohmann::json run_slices(const SlicesRequest& request);

}  // namespace crepuscular::pipelines
