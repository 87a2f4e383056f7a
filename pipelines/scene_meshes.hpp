// What the demo's synthetic camera sees besides the marker boards: the patient's body lying on a
// table (skin in the operative field, a drape around it) and the needle's shaft and hub.
#pragma once

#include <Eigen/Geometry>
#include <cstdint>

#include "planning/imaging/volume.hpp"
#include "tracking/synthetic.hpp"

namespace crepuscular::pipelines {

struct BodyMeshOptions {
  double step_mm = 4;            // grid step of the height field (x and z, CT)
  double table_margin_mm = 250;  // table beyond the body on each side (x)
  double beyond_scan_mm = 700;   // the body continues this far beyond the scan's ends (z)
  // Operative field: skin inside an ellipse (half-axes in x and z, mm) around `field_centre_ct`
  // (its y ignored); drape elsewhere on the body.
  Eigen::Vector3d field_centre_ct = Eigen::Vector3d::Zero();
  double field_half_x_mm = 150, field_half_z_mm = 110;
  // The patient board presses the skin flat under its plate: vertices within this rectangle of the
  // board (|x|, |y| in the board frame, mm) that rise above its plane are put 1 mm below it.
  double board_half_x_mm = 100, board_half_y_mm = 70;
};

// Skin colour, drape and table (BGR, before shading).
inline const Eigen::Vector3f kSkinBgr(140, 165, 215), kDrapeBgr(150, 125, 55),
    kTableBgr(95, 95, 100);

// The body surface seen from the anterior (-y, LPS) as a height field: on each grid column (x, z)
// the first skin crossing (planning::body_fraction 0.5) marching posteriorly, or the table (the
// body's most posterior extent) where the column misses the body; the profile of the scan's first
// and last slice continues beyond it. Vertices in the patient board's frame (T_ct_patient), the
// mesh attached to board "patient".
tracking::SceneMesh body_mesh(const planning::Volume<int32_t>& labels,
                              const Eigen::Isometry3d& T_ct_patient,
                              const BodyMeshOptions& options);

// A needle in the needle board's frame (board "needle"): a steel shaft of diameter_mm from the
// hub to the tip at tip_z_mm along +z, and a plastic hub (7 mm across, 12 mm long) behind the
// board's plane (z > 0), so that neither hides the board's tags.
tracking::SceneMesh needle_mesh(double tip_z_mm, double diameter_mm = 1.2);

}  // namespace crepuscular::pipelines
