// Reading and writing volumes through ITK: NIfTI (.nii, .nii.gz), NRRD (.nrrd, .nhdr), MetaImage
// (.mha, .mhd) and DICOM series folders (read only). Physical space is LPS mm, as in ITK.
#pragma once

#include <cstdint>
#include <string>

#include "planning/imaging/volume.hpp"

namespace crepuscular::planning {

// Reads a scalar volume and converts its values to T. `path` is a file, or a folder holding one
// DICOM series (the series with the most slices is taken when there are several).
// Throws Error naming the file when it is missing, unreadable, not 3D, not scalar, or has an
// unusable geometry (zero or negative spacing, non-orthonormal direction).
// Supported T: uint8_t, int16_t, int32_t, float, double.
template <typename T>
Volume<T> read_volume(const std::string& path);

// Reads a label map: every value must be an integer in [0, 65535]; throws Error otherwise.
Volume<int32_t> read_label_map(const std::string& path);

// Reads a binary mask: voxels > 0.5 are 1, all others 0.
Volume<uint8_t> read_mask(const std::string& path);

// Writes a volume with its full geometry. The format follows the extension (.nii.gz preferred;
// .nii, .nrrd, .mha also work). The file is written under a temporary name in the same folder and
// renamed when complete, so a failure never leaves a partial file. Throws Error on failure.
// Supported T: uint8_t, int16_t, int32_t, float.
template <typename T>
void write_volume(const Volume<T>& volume, const std::string& path);

}  // namespace crepuscular::planning
