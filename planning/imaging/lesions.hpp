// The tumor as one label of a label map, and one lesion among several: connected components of the
// label's voxels, ranked by size, chosen by rank or by a point.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "planning/imaging/volume.hpp"

namespace crepuscular::planning {

// One connected component of a mask (26-connected: voxels touching at a face, an edge or a corner
// are one lesion).
struct Lesion {
  int rank = 0;  // 1 = largest; equal sizes are ranked by their first voxel in file order
  int64_t voxels = 0;
  double volume_ml = 0;                                // voxels x voxel volume / 1000
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();  // mean of the voxel centres, LPS mm
};

// Which lesion a plan is for: the only one, the K-th largest, or the one at a point.
struct LesionSelection {
  enum class Kind { kOnly, kRank, kPoint };
  Kind kind = Kind::kOnly;
  int rank = 1;                                     // kRank: 1 = largest
  Eigen::Vector3d point = Eigen::Vector3d::Zero();  // kPoint: LPS mm

  static LesionSelection only() { return {}; }
  static LesionSelection by_rank(int k) { return {Kind::kRank, k, Eigen::Vector3d::Zero()}; }
  static LesionSelection at(const Eigen::Vector3d& p_lps) { return {Kind::kPoint, 1, p_lps}; }
};

struct SelectedLesion {
  Volume<uint8_t> mask;  // the chosen lesion's voxels (1), on the input mask's grid
  Lesion lesion;
  int lesion_count = 0;  // lesions in the input mask
  double distance_mm =
      0.0;  // kPoint: from the point to the lesion's nearest voxel centre (0 inside)
};

// 1 where `labels` holds `value`. Throws Error naming `source` and listing the values present when
// no voxel holds it.
Volume<uint8_t> label_mask(const Volume<int32_t>& labels, int value, const std::string& source);

// The connected components of `mask` (voxels > 0), largest first. When `component_of` is given it
// receives, per voxel, the rank of its lesion (0 outside the mask).
std::vector<Lesion> find_lesions(const Volume<uint8_t>& mask,
                                 Volume<int32_t>* component_of = nullptr);

// The lesion chosen by `selection`:
//  - kOnly: the mask's single lesion; several -> Error listing them (describe_lesions);
//  - kRank: the K-th largest; K outside 1..count -> Error listing them;
//  - kPoint: the lesion holding the voxel nearest to the point, else the lesion whose nearest
//    voxel centre is closest (ties: the larger lesion).
// `what` names the mask in messages (e.g. "tumor.nii.gz label 2"). Empty mask -> Error.
SelectedLesion select_lesion(const Volume<uint8_t>& mask, const LesionSelection& selection,
                             const std::string& what);

// "#1: 1234 voxels, 2.70 mL, centroid (x, y, z) mm LPS" per lesion, one per line.
std::string describe_lesions(const std::vector<Lesion>& lesions);

}  // namespace crepuscular::planning
