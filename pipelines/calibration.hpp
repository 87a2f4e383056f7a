// Calibration jobs from captured data: the camera's intrinsics from images or a recording of a
// flat target (the frames picked for coverage of the image), and the needle's tip (pivoting) and
// axis (spinning) from poses CSV files or recordings. Each writes the file `guide` reads.
#pragma once

#include <string>

#include "calibration/calibration_files.hpp"
#include "calibration/intrinsics.hpp"
#include "tracking/detector.hpp"

namespace crepuscular::pipelines {

struct CameraCalibrationRequest {
  std::string images;     // a folder of images, or a glob such as "shots/*.png"
  std::string recording;  // or a recording folder (exactly one of the two)
  // The target: boards.json of an AprilTag grid board, or "chessboard:COLSxROWS:SQUARE_MM".
  std::string board;
  std::string board_name;  // which board of boards.json ("": the one with the most tags)
  std::string out = "camera.yaml";
  int max_views = 40;  // views kept from a recording (picked for coverage)
  int min_views = 4;   // fewer usable views are refused
  bool fix_k3 = false;
  bool fisheye = false;  // calibrate the equidistant fisheye model instead of Brown-Conrady
  tracking::DetectorOptions detector;  // tag detection settings (the family is the board's)
};

// Finds the target in every image (a recording: in up to 6 frames per wanted view, spread over
// it, then max_views of them picked for coverage), calibrates, writes `out`, logs the parameters
// and per-view errors. Throws Error naming the input and what to capture next.
calibration::IntrinsicsResult run_camera_calibration(const CameraCalibrationRequest& request);

struct PivotCalibrationRequest {
  // Poses of the pivoting: a poses CSV (from `crepuscular track`), or a PLUS sequence file
  // (.igs.mha, .seq.mha, .igs.nrrd) whose transform `tool` (e.g. StylusToTracker) is the needle's
  // pose in the tracker's frame.
  std::string poses;
  std::string recording;  // or a recording of it (exactly one of the two)
  std::string boards;     // boards.json ("": the recording's own)
  std::string camera;     // camera.yaml ("": the recording's own)
  std::string board_name = "needle";
  std::string tool;  // the PLUS sequence's transform ("": its only one)
  std::string spin_poses;      // optional spin capture: poses CSV ...
  std::string spin_recording;  // ... or recording (at most one of the two)
  std::string out = "needle.yaml";
  double min_rotation_deg = 15.0;
  double max_tip_stddev_mm = 0.5;  // refuse a tip whose 3D standard deviation is larger
  double warn_rms_mm = 2.0;        // warn when the inlier residual RMS is larger
};

// Tip from the pivoting (and axis from the spin capture), written to `out` with its standard
// deviation, the residuals, the motion and the outlier frames. Throws Error naming the input when
// a capture has no poses of the needle board, too little rotation, or a tip too uncertain.
calibration::NeedleCalibration run_pivot_calibration(const PivotCalibrationRequest& request);

}  // namespace crepuscular::pipelines
