// Preprocessing (§3.1, docs/ARCHITECTURE.md §5): the blocking volume b (risk per mm) from a
// label map and a vulnerability table, or from CT thresholds when no labels exist, with a
// Gaussian safety margin.
#pragma once

#include <cstdint>
#include <string>

#include "planning/imaging/volume.hpp"
#include "planning/preprocessing/vulnerability.hpp"

namespace crepuscular::planning {

struct MarginOptions {
  // Full width at half maximum of the Gaussian safety margin, mm (the paper's 5 mm kernel).
  // 0 disables the margin.
  double fwhm_mm = 5.0;
  // Smooth on a CUDA device where one is found (the same values; plan asks for it unless told
  // --device cpu).
  bool on_gpu = false;
};

// b(x) = max over levels L of coeff(L) * max(mask_L(x), (G * mask_L)(x)): each level's mask is
// smoothed with a Gaussian of the given FWHM, never lowered inside the structure, and the levels
// are combined by maximum. Throws Error for a label missing from the table.
Volume<float> blocking_from_labels(const Volume<int32_t>& labels, const VulnerabilityTable& table,
                                   const MarginOptions& margin, const std::string& labels_source);

// Thresholding when no labels exist: bone (HU >= bone_hu) and air inside the body are
// impassable; returns the blocking volume with margin. Air is outside the body when it touches one
// of the four side faces of the volume; the two faces across the table axis (the index axis
// closest to S) usually cut through the patient, so lungs, trachea and bowel gas that reach them
// still count as inside.
struct CtThresholds {
  double bone_hu = 250.0;
  double air_hu = -400.0;
  double impassable_per_mm = 100.0;
};
Volume<float> blocking_from_ct(const Volume<float>& ct_hu, const CtThresholds& thresholds,
                               const MarginOptions& margin);

// Checks a ready blocking volume: every value finite and >= 0; throws Error naming `source`, the
// first bad voxel and its value otherwise.
void validate_blocking(const Volume<float>& blocking, const std::string& source);

}  // namespace crepuscular::planning
