// Reading and writing volumes through ITK: NIfTI (.nii, .nii.gz), NRRD (.nrrd, .nhdr), MetaImage
// (.mha, .mhd) and DICOM series folders (read only). Physical space is LPS mm, as in ITK.
#pragma once

#include <cstdint>
#include <mutex>
#include <string>
#include <vector>

#include "planning/imaging/volume.hpp"

namespace crepuscular::planning {

// Held while ITK reads an image file (header or voxels, every format). ITK's readers are not known
// to be safe on several threads at once: concurrent reads of a breathing plan's phases corrupt the
// heap inside NiftiImageIO::ReadImageInformation (bench/RESULTS.md, 2026-11-27, runs of 1.05 mm
// along the rays), as concurrent NIfTI reads are reported to elsewhere. Reads take turns; what is
// done with the voxels afterwards (conversion, checks, preprocessing) runs side by side.
// Recursive: one read may open its header under it and then read its voxels.
std::recursive_mutex& image_read_mutex();

// How a volume is read where its source leaves a choice; files ignore it.
struct VolumeReadOptions {
  // SeriesInstanceUIDs (0020,000E) a user chose (`--series`): a DICOM folder holding several
  // series is read as the one of them listed here (one list serves every folder of a job: UIDs
  // are unique). A folder of one series is read as that series; one of several, none listed, is
  // refused with the list of its series.
  std::vector<std::string> dicom_series;
  // NaN marks voxels without a value, as the plan writes its path safety volumes (outside the
  // region of interest, unknown): allowed, and read as niftilib reads it (0, to be masked by the
  // plan's voxel states). Infinite voxels are refused all the same. False for every input of a
  // plan: a NaN there is a file that says nothing, never a value.
  bool nan_means_no_value = false;

  // The options of a plan's own path safety volumes (NaN: no value).
  static VolumeReadOptions path_safety_file() {
    VolumeReadOptions o;
    o.nan_means_no_value = true;
    return o;
  }
};

// Reads a scalar volume and converts its values to T. `path` is a file, or a folder holding one
// DICOM series (or several, one of them chosen in `options`), its slices checked first
// (dicom_series.hpp). Throws Error naming the file when it is missing, unreadable, not 3D, not
// scalar, has an unusable geometry (zero or negative spacing, non-orthonormal direction), or
// (NIfTI float32/float64) a NaN or infinite voxel, which niftilib would read as 0.
// Supported T: uint8_t, int16_t, int32_t, float, double.
template <typename T>
Volume<T> read_volume(const std::string& path, const VolumeReadOptions& options = {});

// Reads a label map: every value must be an integer in [0, 65535]; throws Error otherwise.
Volume<int32_t> read_label_map(const std::string& path, const VolumeReadOptions& options = {});

// Reads a binary mask: voxels > 0.5 are 1, all others 0.
Volume<uint8_t> read_mask(const std::string& path, const VolumeReadOptions& options = {});

// The grid of a volume from its header alone (a DICOM folder: from its series, checked and read),
// checked as read_volume checks it; a file's voxels are not read. Throws Error naming the file.
ImageGeometry read_volume_geometry(const std::string& path, const VolumeReadOptions& options = {});

// Frames along the 4th axis of a file: breathing phases of a 4D NIfTI (or NRRD, MetaImage); 1 for
// a 3D volume or a folder. Throws Error naming the file when it cannot be read.
int volume_frames(const std::string& path);

// Writes frame t of a 4D file as the 3D volume frame_paths[t] (values as float: exact for labels
// and CT numbers) with the geometry of the first three axes. Throws Error naming the file when it
// is not 4D with that many frames, is unreadable, or has an unusable geometry or a NaN or
// infinite value (naming the phase and the voxel).
void split_volume_frames(const std::string& path, const std::vector<std::string>& frame_paths);

// Writes volumes of one grid as the frames of a 4D file (.nii.gz or .nii), e.g. the phases of a
// breathing cycle as a 4D CT holds them. Atomic like write_volume. Throws Error on failure.
void write_volume_frames(const std::vector<Volume<float>>& frames, const std::string& path);

// Writes a volume with its full geometry. The format follows the extension (.nii.gz preferred;
// .nii, .nrrd, .mha also work). The file is written under a temporary name in the same folder and
// renamed when complete, so a failure never leaves a partial file. Throws Error on failure.
// Supported T: uint8_t, int16_t, int32_t, float.
template <typename T>
void write_volume(const Volume<T>& volume, const std::string& path);

}  // namespace crepuscular::planning
