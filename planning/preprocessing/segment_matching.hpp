// Segments of a 3D Slicer segmentation matched to a vulnerability table by name: the tables that
// make each layer of the segmentation a label map the blocking computation can use.
#pragma once

#include <string>
#include <vector>

#include "planning/imaging/segmentation.hpp"
#include "planning/preprocessing/label_maps.hpp"
#include "planning/preprocessing/vulnerability.hpp"

namespace crepuscular::planning {

// The table of a set of segments with unique label values (those of one layer): the levels of
// `table`, and per segment its label value, its name and the level of the table entry whose name
// matches (structure_names_match: case-insensitive, spaces as underscores; several entries of one
// name: the highest level). Segments named (or with an ID) in `excluded`, e.g. the tumor itself,
// get the table's lowest level. Throws Error naming `source` when segments match no entry (listing
// them all and the table's names) or when an excluded name matches no segment.
VulnerabilityTable match_segment_names(const std::vector<Segment>& segments,
                                       const VulnerabilityTable& table, const std::string& source,
                                       const std::vector<std::string>& excluded = {});

// One table per layer of `segmentation` (match_segment_names on each layer's segments; an excluded
// name may be in any layer). All unmatched names of all layers are reported at once.
std::vector<VulnerabilityTable> layer_tables(const Segmentation& segmentation,
                                             const VulnerabilityTable& table,
                                             const std::vector<std::string>& excluded = {});

// The inputs of combine_label_maps() for every layer: layer l with tables[l], named
// "<file> layer l". Points into `segmentation` and `tables`, which must outlive its use.
std::vector<LabelMapInput> segmentation_label_maps(const Segmentation& segmentation,
                                                   const std::vector<VulnerabilityTable>& tables);

}  // namespace crepuscular::planning
