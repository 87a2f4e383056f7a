// Area safety geometry (paper section 3.3, DESIGN.md section 6): a tessellated PCA ellipsoid of
// the tumor, every vertex extruded along its normal until the maximum distance or an unsafe point;
// connected safe regions; each region's size by the divergence theorem; every vertex weighted by
// its region's size (its leeway).
#pragma once

#include <Eigen/Core>
#include <array>
#include <string>
#include <vector>

#include "planning/volume.hpp"

namespace crepuscular::planning {

// Ellipsoid from the PCA of the tumor's voxel centres (LPS mm).
struct Ellipsoid {
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  Eigen::Matrix3d axes = Eigen::Matrix3d::Identity();  // columns: unit main axes, largest first
  Eigen::Vector3d radii = Eigen::Vector3d::Ones();      // mm, largest first
};

// One connected safe region of the extruded surface.
struct AreaRegion {
  int id = 0;                                        // 0, 1, ... by decreasing size
  double size_mm3 = 0;                               // mass by the divergence theorem
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();  // LPS mm, centre of its extruded vertices
  Eigen::Vector3d main_axis = Eigen::Vector3d::Zero();  // unit, from the tumor centre outward
  double leeway = 0;                                 // size relative to the largest region, 0..1
  int vertex_count = 0;
};

struct AreaSafetyGeometry {
  Ellipsoid ellipsoid;
  std::vector<Eigen::Vector3d> base;       // vertex on the ellipsoid (LPS mm)
  std::vector<Eigen::Vector3d> normals;    // unit outward normal at the base vertex
  std::vector<Eigen::Vector3d> vertices;   // extruded vertex (LPS mm)
  std::vector<std::array<int, 3>> triangles;  // outward-facing, closed surface
  std::vector<uint8_t> safe;               // 1 where the extrusion reached the maximum distance
  std::vector<int> region;                 // region id per vertex, -1 where unsafe
  std::vector<float> leeway;               // per vertex: its region's leeway, 0 where unsafe
  std::vector<AreaRegion> regions;         // by decreasing size
};

}  // namespace crepuscular::planning
