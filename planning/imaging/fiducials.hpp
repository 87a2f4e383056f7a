// CT-visible fiducials of the patient marker board: automatic detection of small, very bright beads
// in a CT (threshold, connected components, sub-voxel intensity-weighted centroid), and reading and
// writing 3D Slicer point markups (.mrk.json). Positions are LPS mm.
#pragma once

#include <Eigen/Core>
#include <string>
#include <vector>

#include "planning/imaging/volume.hpp"

namespace crepuscular::planning {

struct Fiducial {
  std::string label;
  Eigen::Vector3d position = Eigen::Vector3d::Zero();  // LPS mm
  double volume_mm3 = 0;  // above-threshold volume (detected beads)
  double peak = 0;        // brightest voxel (detected beads)
};

struct FiducialDetectionOptions {
  double threshold = 2500.0;       // beads are brighter than this (HU); cortical bone stays below
  double min_volume_mm3 = 1.0;     // smaller components are noise
  double max_volume_mm3 = 600.0;   // larger ones are implants or contrast, not beads (10 mm bead: 524)
  double max_elongation = 3.0;     // longest / shortest principal extent: rejects wires and edges
  int margin_voxels = 2;           // the centroid window reaches this far beyond the component
};

// Beads in `ct`, ordered by decreasing peak intensity, labelled "B-1", "B-2", ... The centroid is
// weighted by intensity above the local background (median of the window's border), so partial
// volume at the bead's edge moves it by a fraction of a voxel as it should.
// Supported T: int16_t, float.
template <typename T>
std::vector<Fiducial> detect_fiducials(const Volume<T>& ct,
                                       const FiducialDetectionOptions& options = {});

// Control points of every point-list ("Fiducial") markup of a Slicer .mrk.json file, converted to
// LPS ("coordinateSystem" RAS negates x and y; a file without the field is LPS, as Slicer reads it).
// Throws Error naming the file and the field when there is none or a position is malformed.
std::vector<Fiducial> read_fiducial_markups(const std::string& path);

// Writes a point-list markup that opens in 3D Slicer 4.11 and later (through a temporary file).
void write_fiducial_markups(const std::string& path, const std::vector<Fiducial>& fiducials,
                            const std::string& coordinate_system = "LPS");

}  // namespace crepuscular::planning
