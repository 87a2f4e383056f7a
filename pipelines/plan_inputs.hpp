// The plan job's inputs as radiologists have them: several label maps (NIfTI/NRRD label maps with
// a table each, 3D Slicer segmentations matched by name), the tumor as a mask or as one label of
// a label map with lesion selection, and the scanned volume they describe.
#pragma once

#include <Eigen/Core>
#include <nlohmann/json.hpp>
#include <optional>
#include <map>
#include <string>
#include <vector>

#include "planning/imaging/scan_coverage.hpp"
#include "planning/imaging/volume.hpp"
#include "planning/preprocessing/blocking.hpp"

namespace crepuscular::pipelines {

struct PlanInputOptions {
  // Label maps, "FILE[:TABLE]" each: TABLE is a preset name or a vulnerability table JSON; without
  // it `vulnerability`, else `preset`, else vulnerability.json beside the map. A 3D Slicer
  // segmentation (.seg.nrrd) has its segments matched to the table by name. Where maps overlap,
  // the higher level wins.
  std::vector<std::string> labels;
  std::string vulnerability;
  std::string preset;
  std::string ct;        // CT in HU: thresholded when no labels are given; part of the scan
  std::string blocking;  // ready blocking volume (risk per mm)
  planning::MarginOptions margin;
  planning::CtThresholds ct_thresholds;
  // "FILE" (a mask: voxels > 0.5) or "FILE:LABEL" (a label value, or a segment name of a .seg.nrrd).
  std::string tumor;
  int lesion = 0;                                // K-th largest lesion (1 = largest); 0: the only one
  std::optional<Eigen::Vector3d> lesion_at;      // the lesion at (or nearest to) this point, LPS mm
  // SeriesInstanceUIDs chosen for DICOM folders of several series (--series; see
  // planning::VolumeReadOptions::dicom_series).
  std::vector<std::string> series;
};

struct PlanInputs {
  planning::Volume<float> blocking;
  std::string blocking_source;        // names the blocking's origin in messages
  nlohmann::json preprocessing;       // plan.json "preprocessing"
  planning::Volume<uint8_t> tumor;    // the chosen lesion
  nlohmann::json tumor_source;        // plan.json "tumor_source": file, label, lesion
  planning::ScanCoverage coverage;    // the scanned volume: the anatomy inputs' grids
  planning::Volume<int32_t> labels;   // the (combined) label map, for the skin; empty without one
  nlohmann::json seconds;             // the steps' wall times (blocking, tumor: concurrent)
};

// A breathing cycle (docs/ARCHITECTURE.md §10) as phases.json lists it: per phase its label maps,
// tumor and optional CT (paths relative to phases.json), in the order of the cycle.
struct PlanPhase {
  std::string name;                 // "phase00", or "phase<K>" when phases.json names none
  std::vector<std::string> labels;  // label specs FILE[:TABLE]
  std::string tumor;                // tumor spec FILE[:LABEL]
  std::string ct;
  // 4D inputs: each file above that is a frame of one, mapped to that 4D file; and the frame.
  std::map<std::string, std::string> frame_of;
  int frame = -1;
};
struct PhaseList {
  std::string file;           // phases.json; "" for 4D inputs
  std::string vulnerability;  // the table phases.json names, "" when none
  std::string preset;
  std::vector<PlanPhase> phases;
};
// Reads phases.json: {"phases": [{"name", "labels" (a spec or a list), "tumor", "ct"}, ...],
// "vulnerability" or "preset" (optional)}. Throws Error naming the file and the field; at least 2
// phases, every named file must exist.
PhaseList read_phase_list(const std::string& path);

// Reads and combines the inputs. Throws Error naming the file and the problem.
PlanInputs read_plan_inputs(const PlanInputOptions& options);
// The same in two parts (together read_plan_inputs): the tumor (its mask, lesion chosen) and the
// blocking volume with the scan's coverage, each into `in`.
void read_plan_tumor(const PlanInputOptions& options, PlanInputs& in);
void read_plan_blocking(const PlanInputOptions& options, PlanInputs& in);

// The files named by the label specs (without their table), for checks and checksums.
std::vector<std::string> label_files(const std::vector<std::string>& label_specs);
// The file named by a tumor spec.
std::string tumor_file(const std::string& tumor_spec);

}  // namespace crepuscular::pipelines
