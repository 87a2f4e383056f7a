// PLUS sequence files: the recording format of the PLUS toolkit and of 3D Slicer's Sequences
// module. A MetaImage (`.igs.mha`, `.seq.mha`) or NRRD (`.igs.nrrd`) whose last axis is time
// (frames of 2D images; none where a size is 0), with per-frame fields in its header:
// `Seq_FrameNNNN_<From>To<To>Transform` (16 numbers, a row-major 4x4, mm), its `...TransformStatus`
// (OK, INVALID: a lost tool), `Seq_FrameNNNN_Timestamp` (s) and `..._ImageStatus`; any other
// field is kept as text. Read whole; written as an uncompressed MetaImage that PLUS and Slicer
// read, and that this reader reads back field for field and pixel for pixel.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <map>
#include <string>
#include <utility>
#include <vector>

namespace crepuscular::recordings {

struct PlusTransform {
  Eigen::Matrix4d matrix = Eigen::Matrix4d::Identity();  // maps From to To, mm
  bool valid = true;  // status OK (a missing status counts as OK, as PLUS reads it)
};

struct PlusFrame {
  double timestamp_s = 0;  // Seq_FrameNNNN_Timestamp; NaN when the frame has none
  // Transforms by name without the "Transform" suffix: "StylusToTracker".
  std::map<std::string, PlusTransform> transforms;
  // Every per-frame field in the file's order (name without "Seq_FrameNNNN_"), as text.
  std::vector<std::pair<std::string, std::string>> fields;
  // The field's text, "" when absent.
  std::string field(const std::string& name) const;
};

struct PlusSequence {
  // Header fields other than per-frame ones, in order, except those the image data defines
  // (sizes, element type, compression, data file), which are below.
  std::vector<std::pair<std::string, std::string>> header;
  std::vector<PlusFrame> frames;
  // The image of each frame: width, height (0 0: no images), channels and the pixel type as
  // MetaImage names it (MET_UCHAR, MET_SHORT, ...); pixels of all frames, frame after frame.
  int width = 0, height = 0, channels = 1;
  std::string element_type = "MET_UCHAR";
  std::vector<uint8_t> pixels;

  // Names of the transforms any frame holds, sorted.
  std::vector<std::string> transform_names() const;
  int bytes_per_pixel() const;  // of one channel
};

// Reads a sequence file (by its content: "NRRD" magic or a MetaImage header). Throws Error naming
// the file and what is wrong: not a sequence file, a field that is not 16 numbers, a status that
// is neither OK nor INVALID, frame numbers out of order or beyond the time axis, a data size that
// does not match, data that does not decompress, an external data file.
PlusSequence read_plus_sequence(const std::string& path);

// Writes `sequence` as an uncompressed MetaImage sequence file (.igs.mha / .seq.mha), complete
// or not at all. Throws Error naming the file when the pixels do not match the sizes.
void write_plus_sequence(const std::string& path, const PlusSequence& sequence);

// The MetaImage header write_plus_sequence writes (up to and with "ElementDataFile = LOCAL"), for
// a writer that streams the pixels itself: `sequence`'s pixels are not looked at.
std::string plus_sequence_header(const PlusSequence& sequence);

// A transform's 16 numbers as a sequence file holds them (row-major, 10 significant digits).
std::string plus_matrix_text(const Eigen::Matrix4d& m);
// A board's name as the first part of a PLUS transform name: "patient" -> "Patient".
std::string plus_tool_name(const std::string& name);

// "StylusToTracker" from "StylusToTrackerTransform"; "" when `field` names no transform.
std::string plus_transform_name(const std::string& field);

}  // namespace crepuscular::recordings
