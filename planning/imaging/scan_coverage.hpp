// The scanned volume (docs/ARCHITECTURE.md §4 "Scan coverage"): the intersection of the grids of
// the inputs that describe the anatomy (label maps, CT, a blocking volume given). Outside it the
// anatomy is unknown.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <string>
#include <vector>

#include "planning/imaging/volume.hpp"

namespace crepuscular::planning {

class ScanCoverage {
 public:
  struct Grid {
    ImageGeometry geometry;
    std::string source;  // the input it belongs to, for messages
  };

  // Adds an input's grid: the covered region shrinks to its intersection with the grid's extent.
  void add(const ImageGeometry& geometry, const std::string& source);
  const std::vector<Grid>& grids() const { return grids_; }
  // No grid added: nothing restricts coverage, every point is covered.
  bool empty() const { return grids_.empty(); }

  // Whether p (LPS mm) lies in the extent of every grid: within half a voxel of its outer voxel
  // centres (the voxels' footprints; within_extent() of sampling.hpp).
  bool contains(const Eigen::Vector3d& p) const;

  // 1 where the centre of a voxel of `grid` is covered, 0 where it is not.
  Volume<uint8_t> mask(const ImageGeometry& grid) const;

  // Axis-aligned LPS box holding the covered region: the intersection of the grids' bounding
  // boxes; exact when every grid's axes are parallel to L, P, S, larger otherwise. Empty
  // (isEmpty()) when the grids do not overlap; an unbounded box when no grid was added.
  Eigen::AlignedBox3d bounding_box() const;

 private:
  std::vector<Grid> grids_;
};

// The LPS bounding box of a grid's extent (the footprints of all its voxels).
Eigen::AlignedBox3d extent_box(const ImageGeometry& g);

// Throws Error naming `path` (what it is: "the CT", "the label map") when its grid does not meet
// the plan's grid anywhere: black images or "no structures" would follow, not an answer.
void require_overlap_with_plan(const ImageGeometry& input, const ImageGeometry& plan_grid,
                               const std::string& path, const std::string& what);

}  // namespace crepuscular::planning
