// The demo job: the whole product on the built-in data, written under one folder: phantom ->
// plan (path safety, area safety) -> slice views -> a synthetic recording of a needle approaching
// the tumor along a safe path and then along one that crosses a vessel -> guidance, headless ->
// the overlay video, snapshots of both moments and a short report (report.md).
#pragma once

#include <string>

#include "planning/safety/path_safety.hpp"

namespace crepuscular::pipelines {

struct DemoRequest {
  std::string out_dir = "demo";
  double spacing_mm = 3.0;  // phantom voxel size
  planning::Device device = planning::Device::kAuto;
  planning::Mode mode = planning::Mode::kExact;
  // Region of interest around the tumor, mm: the reach of a long needle (the plan's own default,
  // the farthest voxel with any blocking, spans the whole phantom because muscle carries risk).
  double radius_mm = 120.0;
  bool guidance = true;  // false: stop after the plan and the slice views
  // Breathing (docs/ARCHITECTURE.md §10): the phantom as a cycle of this many phases (0: at rest),
  // planned over all of them with per-phase volumes (SVV only); slices, scenario and guidance use
  // the combined plan, report.md tabulates both approaches' safety per phase.
  int breathing_phases = 0;
  double breathing_amplitude_mm = 12.0;
};

// Writes OUT/phantom/ (with breathing: phases.json, phaseKK/), plan/, slices/, and with guidance setup/, recording/, overlay.mp4,
// overlay.csv, snapshots/; then report.md and times.json. OUT appears complete or not at all.
void run_demo(const DemoRequest& request);

}  // namespace crepuscular::pipelines
