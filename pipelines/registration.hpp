// The registration job: the patient marker board's frame in the CT (T_ct_patient) from the
// board's CT-visible fiducials. Board side: the board definition's fiducials, a points file, or
// fiducials digitised with the calibrated needle tip in a recording. CT side: beads found in the
// CT, or Slicer markups. Writes registration.yaml with the FRE and the expected TRE.
#pragma once

#include <Eigen/Core>
#include <optional>
#include <string>
#include <vector>

#include "calibration/calibration_files.hpp"
#include "tracking/board.hpp"

namespace crepuscular::pipelines {

struct RegistrationRequest {
  std::string ct;            // the CT (LPS mm); beads are found in it unless ct_fiducials
  // SeriesInstanceUIDs chosen for DICOM folders of several series (--series; see
  // planning::VolumeReadOptions::dicom_series).
  std::vector<std::string> series;
  std::string boards;        // boards.json ("": the recording's own)
  std::string board_name;    // the patient board ("": "patient", else the first with fiducials)
  std::string ct_fiducials;  // Slicer .mrk.json of the CT fiducials
  std::string points;        // board-frame fiducial positions, CSV (x,y,z or label,x,y,z)
  std::string recording;     // or digitised with the needle tip in this recording ...
  std::string needle;        // ... with this needle calibration (needle.yaml)
  std::string camera;        // camera.yaml for the recording ("": the recording's own)
  std::string tumor;         // tumor mask: the expected TRE at its centroid
  std::optional<Eigen::Vector3d> target;  // or at this point (LPS mm)
  std::string save_ct_fiducials;          // also write the CT fiducials as .mrk.json
  std::string out = "registration.yaml";
  double threshold_hu = 2500.0;  // automatic bead detection
  double tolerance_mm = 2.0;     // pairing tolerance
  double fle_mm = 0.0;           // fiducial localisation error (0: estimated from the FRE)
  double still_mm = 1.0;         // digitising: the tip rests while within this distance ...
  int still_frames = 10;         // ... for this many frames
  bool in_order = false;         // pair by order instead of by the board's layout
};

// Pairs, fits, writes `out` and returns what it wrote. Throws Error naming the input when the
// fiducials cannot be found, paired or fitted (mirrored, collinear, symmetric layouts).
calibration::RegistrationRecord run_registration(const RegistrationRequest& request);

// Points of a CSV file: rows "x,y,z" or "label,x,y,z" (mm); a header row and lines starting with
// '#' are skipped. Throws Error naming the file and line; at least 3 points are required.
std::vector<Eigen::Vector3d> read_points_csv(const std::string& path);

// Fiducial positions in the patient board frame, digitised with the calibrated needle tip: every
// stretch of at least `still_frames` frames in which the tip (seen in the patient board's frame)
// stays within `still_mm` of where it began gives one point (repeats within 3 still_mm merged).
std::vector<Eigen::Vector3d> digitise_fiducials(const RegistrationRequest& request,
                                                const std::vector<tracking::Board>& boards,
                                                const tracking::Board& patient);

}  // namespace crepuscular::pipelines
