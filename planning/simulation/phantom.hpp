// The built-in phantom: a procedural abdomen (skin and fat, ribs and spine, aorta and vena cava, a
// liver with a branching vessel tree, kidneys, lungs, bowel) with a 2-3 cm tumor in the liver.
#pragma once

#include <cstdint>
#include <string>

// The full json.hpp: Phantom holds its vulnerability table as a JSON value.
#include <nlohmann/json.hpp>

#include "planning/imaging/volume.hpp"

namespace crepuscular::planning {

struct PhantomOptions {
  double spacing_mm = 3.0;  // isotropic voxel size
  uint64_t seed = 1;        // same seed, same phantom
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

}  // namespace crepuscular::planning
