// The built-in phantom: a procedural abdomen (skin and fat, ribs and spine, aorta and vena cava, a
// liver with a branching vessel tree, kidneys, lungs, bowel) with a 2-3 cm tumor in the liver.
#pragma once

#include <cstdint>
#include <functional>
#include <string>

// The full json.hpp: Phantom holds its vulnerability table as a JSON value.
#include <nlohmann/json.hpp>
#include <Eigen/Core>

#include "planning/imaging/volume.hpp"

namespace crepuscular::planning {

// Breathing (docs/ARCHITECTURE.md §10): the diaphragm, the organs below it (liver, its vessels, the
// tumor, kidneys, spleen, bowel) and the heart and lungs' bases move by the displacement field
// u = inhale * amplitude * w * (0, -0.35, -1) (caudal and anterior), with w = 1 at the
// diaphragm's dome and a Gaussian fade (sigma 70 mm) with the vertical distance from it. The
// anterior abdominal wall (skin, fat, muscle) rises: breathing_wall_displacement. Bones, the
// posterior wall, spine, aorta and vena cava stay.
constexpr double kMaxBreathingAmplitudeMm = 30.0;

struct PhantomOptions {
  double spacing_mm = 3.0;  // isotropic voxel size
  uint64_t seed = 1;        // same seed, same phantom
  double inhale = 0.0;         // 0: end-exhale (the phantom at rest) .. 1: end-inhale
  double amplitude_mm = 12.0;  // cranio-caudal motion of the diaphragm's dome at end-inhale
};

struct Phantom {
  Volume<int16_t> ct;       // Hounsfield units
  Volume<uint8_t> labels;   // label map, values as listed in planning/preprocessing/presets/phantom.json
  Volume<uint8_t> tumor;    // 0/1
  nlohmann::json vulnerability;  // the phantom's vulnerability table (same as preset "phantom")
};

// Builds the phantom. Deterministic for (spacing, seed). Throws Error on a spacing outside
// [0.3, 10] mm.
Phantom make_phantom(const PhantomOptions& options);

// Writes ct.nii.gz, labels.nii.gz, tumor.nii.gz and vulnerability.json as the folder `dir`,
// staged: complete or not at all; an existing `dir` is replaced only when crepuscular wrote it.
void write_phantom(const Phantom& phantom, const std::string& dir);

// The breathing displacement u (LPS mm) at a point p of a phase (inhale 0..1, amplitude in mm):
// the content of the phase at p is the phantom at rest at p - u(p).
Eigen::Vector3d breathing_displacement(const Eigen::Vector3d& p, double inhale,
                                       double amplitude_mm);
// The body wall's displacement at a point of a phase: anterior (-y), inhale * amplitude * 0.7 at
// the anterior skin of the abdomen's middle (z = -30 mm), fading (smoothstep) to none at the
// mid-coronal plane and with the height (Gaussian, sigma 60 mm); in front of the skin as at it.
Eigen::Vector3d breathing_wall_displacement(const Eigen::Vector3d& p, double inhale,
                                            double amplitude_mm);
// Where the material at `p_rest` (end-exhale) lies in a phase: the q with q - u(q) = p_rest.
Eigen::Vector3d breathing_position(const Eigen::Vector3d& p_rest, double inhale,
                                   double amplitude_mm);
// Inhale fraction of phase k of a cycle of n phases: sin^2(pi k / n) (phase 0 end-exhale, phase
// n/2 end-inhale).
double breathing_inhale(int phase, int phases);

// Writes a breathing cycle of `phases` phases (2..50) of the phantom `base` into the folder `dir`,
// staged: phaseKK/{ct,labels,tumor}.nii.gz per phase, vulnerability.json, and phases.json (the
// list the plan reads: per phase its files, inhale fraction and the tumor centroid the motion
// predicts). `progress(k)` is called after phase k is written. Returns phases.json's content.
nlohmann::json write_breathing_phantom(const PhantomOptions& base, int phases,
                                       const std::string& dir,
                                       const std::function<void(int, const Phantom&)>& progress = {});

}  // namespace crepuscular::planning
