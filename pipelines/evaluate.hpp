// The evaluate job: straight needle trajectories checked against a plan (the paper's
// retrospective gold-standard comparison), as text, JSON or CSV rows.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "planning/trajectories/evaluate.hpp"

namespace crepuscular::pipelines {

struct EvaluateRequest {
  std::string plan_dir;
  std::string labels;  // label map for the structures ("": the plan's)
  // SeriesInstanceUIDs chosen for DICOM folders of several series (--series; see
  // planning::VolumeReadOptions::dicom_series).
  std::vector<std::string> series;
  // The trajectories: one given by its points, a Slicer line markup, or a batch CSV.
  std::optional<planning::Trajectory> trajectory;
  std::string markup;
  std::string batch;
  bool json = false;  // JSON instead of text (a batch: an array; else CSV rows)
  std::string out;    // write the result here (whole or not at all); "": only return it
};

// Evaluates the trajectories and returns the result text (written to `out` when given). Throws
// Error when no trajectory is given or an input is unusable.
std::string run_evaluate(const EvaluateRequest& request);

}  // namespace crepuscular::pipelines
