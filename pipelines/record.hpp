// Recording jobs: any frame source (camera, recording, synthetic scene) into a recording folder
// (docs/ARCHITECTURE.md §8), and a synthetic scene rendered into one with its ground truth.
#pragma once

#include <atomic>
#include <cstdint>
#include <string>

#include "tracking/frame_source.hpp"

namespace crepuscular::pipelines {

struct RecordRequest {
  std::string source;          // open_frame_source URI
  std::string out;             // the recording folder; must not exist
  int64_t frames = -1;         // stop after this many frames (-1: no limit)
  double seconds = -1;         // stop after this much capture time (-1: no limit)
  std::string format = "jpg";  // jpg (camera MJPEG stored as received) or png
  int quality = 95;            // JPEG quality of frames encoded here
  std::string boards;          // boards.json stored with the recording ("": none)
  std::string camera;          // camera.yaml stored with it ("": the source's own, if any)
  std::string plan;            // plan folder of the session ("": none)
  const std::atomic<bool>* stop = nullptr;  // set (e.g. by Ctrl-C) to end the recording
};

// Records until the limits, the end of the source or *stop; logs the summary.
tracking::RecordSummary run_record(const RecordRequest& request);

struct SynthRequest {
  std::string scene;  // scene JSON (tracking/synthetic.hpp read_scene); "": the built-in scene
  std::string out;    // the recording folder; must not exist
  std::string format = "jpg";
  int quality = 95;
  int64_t frames = -1;  // at most this many frames (-1: all frames of the scene)
  // A breathing patient: the patient board rises and falls this many times a minute by rise_mm
  // (tracking::add_breathing); breathing.csv holds the truth per frame. 0: no breathing.
  double breaths_per_minute = 0;
  double rise_mm = 8.0;
  std::string breathing_board = "patient";
};

// Renders the scene into a recording with boards.json and ground_truth.csv; logs the summary.
tracking::RecordSummary run_synth(const SynthRequest& request);

}  // namespace crepuscular::pipelines
