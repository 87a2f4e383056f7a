// 3D Slicer segmentations (.seg.nrrd): the segments named in the NRRD header and one label map per
// layer, read through ITK (LPS mm, whatever the file's 'space').
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "planning/imaging/volume.hpp"

namespace crepuscular::planning {

// One segment, from the header keys Segment<N>_* (N = `index`). Slicer's defaults apply where a key
// is missing: name = ID, label value 1, layer N.
struct Segment {
  int index = 0;        // N in Segment<N>_*
  std::string id;       // Segment<N>_ID (e.g. "Segment_1")
  std::string name;     // Segment<N>_Name (e.g. "Liver")
  int label_value = 1;  // Segment<N>_LabelValue: the value of the segment's voxels in its layer
  int layer = 0;        // Segment<N>_Layer: index into Segmentation::layers
};

// Design: segments may overlap only across layers, so the segmentation stays one label map per
// layer (a voxel of layer L holds the label value of the one segment of L it belongs to, 0 for
// none). Each layer, with a table for its segments, is an input of combine_label_maps()
// (preprocessing/label_maps.hpp), which resolves overlaps by level. Memory: 4 bytes per voxel per
// layer.
struct Segmentation {
  std::string source;                   // the file, as given
  std::vector<Segment> segments;        // in file order (N = 0, 1, ...)
  std::vector<Volume<int32_t>> layers;  // one label map per layer, all on one grid

  const ImageGeometry& geometry() const { return layers.front().geometry(); }
  // The segments of one layer, in file order.
  std::vector<Segment> segments_in_layer(int layer) const;
  // The segment named `name_or_id`: its ID exactly, or its name as structure_names_match() compares
  // them. Throws Error naming the file and listing the segments when none or several match.
  const Segment& find_segment(const std::string& name_or_id) const;
  // The segment's voxels: 1 where its layer holds its label value, 0 elsewhere.
  Volume<uint8_t> segment_mask(const Segment& segment) const;
};

// Reads a 3D Slicer segmentation (.seg.nrrd / .seg.nhdr). Layouts read:
//  - 3D image: one layer;
//  - 3D image with a 'list' axis (NRRD kinds "list domain domain domain", what Slicer writes for
//    several layers): ITK reads that axis as the voxel's components, one component per layer;
//  - the obsolete 4D layout (4th axis = segment, binary values): one layer per segment.
// Voxels outside a segment's Segment<N>_Extent (file index coordinates) are not that segment's, as
// in Slicer; voxel values that no segment of their layer declares are dropped (warning).
// Throws Error naming the file, and the key where a header value is wrong (e.g.
// "liver.seg.nrrd: Segment2_LabelValue is 'x' (expected an integer 1 to 65535)"), when the file is
// missing or not NRRD, declares no segment, has an unusable geometry, or two segments of one layer
// share a label value.
Segmentation read_segmentation(const std::string& path);

// Whether `path` names a 3D Slicer segmentation by its extension (.seg.nrrd, .seg.nhdr; any case).
bool is_segmentation_file(const std::string& path);

// Structure names compared as people write them: case-insensitive, spaces and underscores the same,
// leading and trailing blanks ignored ("Portal Vein" matches "portal_vein").
std::string normalized_structure_name(const std::string& name);
bool structure_names_match(const std::string& a, const std::string& b);

}  // namespace crepuscular::planning
