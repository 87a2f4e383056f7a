// The track job: marker-board poses for every frame of a camera, recording or synthetic scene,
// written as a poses CSV, with per-board tracking counts and (synthetic sources) the error
// against the ground truth.
#pragma once

#include <cstdint>
#include <map>
#include <string>

namespace crepuscular::pipelines {

struct TrackRequest {
  std::string source;  // open_frame_source URI
  std::string boards;  // boards.json ("": the recording's own)
  std::string camera;  // camera.yaml ("": the source's own)
  std::string out = "poses.csv";
  double max_age_ms = 100.0;
  double decimate = 2.0;
  int threads = 2;
  int full_search_interval = 15;
  bool smoothing = true;
  std::string family;  // AprilTag family; empty: the first board's
};

struct TrackSummary {
  int64_t frames = 0, dropped = 0, problems = 0;
  double seconds = 0;                                // wall time
  double tracking_ms = 0;                            // mean tracking time per frame
  std::map<std::string, int64_t> tracked, measured;  // frames per board
  // Against the ground truth (synthetic sources): median errors per board.
  std::map<std::string, double> median_error_mm, median_error_deg;
};

// Tracks every frame and writes `out` (complete or not at all); logs progress and the summary.
TrackSummary run_track(const TrackRequest& request);

}  // namespace crepuscular::pipelines
