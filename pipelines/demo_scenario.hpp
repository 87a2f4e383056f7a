// The guidance scenario of `crepuscular demo` on the built-in phantom: a safe and a dangerous
// (vessel-crossing) needle path to the tumor chosen from a plan, the patient board laid on the
// anterior skin beside their entry points (the registration), and a synthetic camera scene in
// which the needle approaches along the safe path, is withdrawn, and approaches along the
// dangerous one; plus the calibration files `crepuscular guide` reads for that scene.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <string>
#include <vector>

#include "calibration/calibration_files.hpp"
#include "planning/plan_folder/plan_folder.hpp"
#include "planning/trajectories/needle_guidance.hpp"
#include "tracking/synthetic.hpp"

namespace crepuscular::pipelines {

// One straight approach to the tumor centroid.
struct GuidanceApproach {
  std::string name;  // "safe" or "dangerous"
  // Unit, from the skin entry toward the tumor centroid (into the body), CT LPS.
  Eigen::Vector3d direction_ct = Eigen::Vector3d::UnitY();
  // Where the line enters the body: the outermost crossing from label 0 to label > 0 of the plan's
  // label map (nearest voxel), on its outside (label 0, within 0.001 mm of the body), CT LPS mm.
  Eigen::Vector3d entry_ct = Eigen::Vector3d::Zero();
  // NeedleGuide evaluation of a needle with its tip at the entry, pointing along direction_ct.
  planning::NeedleState state;
  // Angle between this approach's outward direction (-direction_ct) and the anterior direction
  // (-y), and between direction_ct and the camera's nominal optical axis (degrees).
  double angle_from_anterior_deg = 0;
  double angle_to_view_axis_deg = 0;
  // Smallest angle over the approach's frames between the needle's axis and the ray from the
  // camera to the entry (degrees): 30 or more, the needle is seen from the side, not end-on.
  double view_obliquity_deg = 0;
  // Names of the vessels (structures named vessel / vein / artery / aorta / cava / portal) the
  // line from the entry to the centroid crosses.
  std::vector<std::string> vessels;
  // Time span of the approach in the recording (s): the tip moves from start_outside_mm outside the
  // entry to stop_short_mm short of the centroid, both along the line.
  double start_s = 0, end_s = 0;
};

struct GuidanceScenarioOptions {
  double fps = 30;
  double approach_s = 2.5;  // duration of each approach
  double switch_s = 0.8;    // withdrawal from the safe line and swing onto the dangerous one
  double hold_s = 0.3;      // still frames at the start and the end of the recording
  double start_outside_mm = 60;  // tip distance outside the skin entry when an approach starts
  double stop_short_mm = 10;     // tip distance short of the tumor centroid when it ends
  // Candidate approach directions: outward from the tumor centroid, within this angle of the
  // anterior direction (-y LPS), on a Fibonacci sphere of this many points.
  double max_angle_from_anterior_deg = 50;
  int sphere_points = 4000;
  // The safe approach must stay safe when turned by this angle in any of 8 directions (tracking
  // noise, a hand that wavers).
  double robust_deg = 6;
  // The dangerous approach lies this far from the safe one.
  double min_separation_deg = 15, max_separation_deg = 35;
  // A breathing recording (breaths_per_minute > 0, phases > 0): the anterior abdominal wall under
  // the patient board rises as the built-in phantom's does (planning::breathing_wall_displacement
  // of this amplitude, inhale sin^2 over each breath, end-exhale at 0 s), the board with it; the
  // camera stays where it is (no drift) and so does the needle, held in the room.
  double breaths_per_minute = 0;
  double breathing_amplitude_mm = 12.0;
  int breathing_phases = 0;
  // Preferred needle direction in CT: the safe approach nearest to it is tried first (default:
  // from anterior and the patient's right, 25 degrees off vertical; the tumor lies in the right
  // lobe). The camera then sits where an OR camera would: above the table and to one side, its
  // axis 25 to 60 degrees off vertical and 36 to 54 degrees from both needle directions, so that
  // each needle is seen at 30 degrees or more from its viewing ray (T_cam_ct_nominal tells).
  Eigen::Vector3d view_axis_ct = Eigen::Vector3d(0.42, 0.906, 0.0);
  double camera_distance_mm = 540;  // mean distance camera -> patient board centre (500..580)
  double camera_drift_mm = 25;      // the camera drifts this much over the recording
  double image_margin_px = 12;      // every tag corner at least this far inside the image
  uint64_t seed = 1;                // image noise of the scene
};

struct GuidanceScenario {
  // The registration: patient board frame -> CT (LPS mm), the ground truth of this setup.
  Eigen::Isometry3d T_ct_patient = Eigen::Isometry3d::Identity();
  Eigen::Vector3d target_ct = Eigen::Vector3d::Zero();  // tumor centroid (plan.json), LPS mm
  GuidanceApproach safe, dangerous;
  // Boards "patient" (2 x 3 tags of 40 mm, ids 0-5, 5 CT fiducials) and "needle" (2 x 2 tags of
  // 20 mm, ids 10-13); the camera of tracking::builtin_scene(); a needle keyframe every frame;
  // meshes "body" (on the patient board: skin, drape, table) and "needle" (shaft and hub).
  tracking::SyntheticScene scene;
  // Tip kNeedleTipInNeedle, axis +z, board "needle".
  calibration::NeedleCalibration needle;
  // Camera pose without its drift (T_cam_ct); its third row is the optical axis in CT. The
  // patient board's keyframes are drift * T_cam_ct_nominal * T_ct_patient at 0, the middle and the
  // end; the camera stays 50-58 cm from the board.
  Eigen::Isometry3d T_cam_ct_nominal = Eigen::Isometry3d::Identity();
  double duration_s = 0;
  // Breathing recordings: the breath's period (0: no breathing), the phantom's amplitude and the
  // plan's number of phases.
  double breathing_period_s = 0, breathing_amplitude_mm = 0;
  int breathing_phases = 0;
  // Where the skin under the patient board lies at time t against end-exhale (CT, mm; zero
  // without breathing), and the true phase then (phase k nearest the breath's fraction k / n; -1
  // without breathing).
  Eigen::Vector3d skin_displacement_at(double time_s) const;
  int breathing_phase_at(double time_s) const;

  // Scripted needle tip and unit axis in CT at time t (s): what the scene's needle keyframes show.
  Eigen::Vector3d tip_ct_at(double time_s) const;
  // T_ct_needle of the scene at time t: T_ct_patient(t) * T_cam_patient(t)^-1 * T_cam_needle(t),
  // T_ct_patient(t) the registration moved with the skin under the board.
  Eigen::Isometry3d T_ct_needle_at(double time_s) const;
};

// Chooses the two approaches, places the patient board and scripts the scene. The plan needs its
// label map, a path safety volume and plan.json's tumor centroid (load_plan defaults). Throws Error
// naming the plan folder when no robustly safe or no vessel-crossing dangerous approach exists, or
// when the boards cannot be kept inside the image.
// Safe: clear (line integral <= eps), tip class "safe", no vessel crossed, and so for the 8
// directions robust_deg around it. Dangerous: NeedleSafety::kDangerous and a vessel crossed,
// min..max_separation_deg from the safe one; preferred: no bone or lung crossed, dangerous also
// 1 degree around it, >= 3 mm in the vessel, within 28 degrees of the safe one, nearest the view
// axis. Patient board: on the anterior skin 130 mm (plus half the entries' spread) medial of the
// entries, its plane fitted to the skin (the 0.5 level of the trilinearly interpolated body mask)
// around its 5 fiducials, which then lie within 2 mm of the skin. Needle: approach, withdrawal
// along the safe line (first half of switch_s), swing to 60 mm outside the dangerous entry (second
// half), approach.
GuidanceScenario make_guidance_scenario(const planning::PlanData& plan,
                                        const GuidanceScenarioOptions& options = {});

// Writes camera.yaml, needle.yaml, registration.yaml, boards.json, meshes.json (the body and the
// needle) and scene.json (the scene for `--source synthetic:DIR/scene.json`; it names the other
// files) into dir (created if missing), each through a temporary file and a rename.
void write_guidance_setup(const GuidanceScenario& scenario, const std::string& dir);

// The scene JSON text of tracking::read_scene for a scene whose camera and boards are written
// beside it as camera_file and boards_file (poses as translation_mm + quaternion keyframes); its
// meshes inline, or named as meshes_file (written with meshes_json_text).
std::string scene_json_text(const tracking::SyntheticScene& scene, const std::string& camera_file,
                            const std::string& boards_file, const std::string& meshes_file = "");
// The scene's meshes as the JSON array of read_scene's "meshes".
std::string meshes_json_text(const tracking::SyntheticScene& scene);

// True for the vulnerability table names of blood vessels ("liver_vessels", "vena_cava", ...).
bool is_vessel_name(const std::string& structure_name);

// Paints the patient board's fiducials into the CT at `ct_path` (rewritten) as metal beads of
// 3 mm radius (6000 HU, partial volume from 4^3 subsamples per voxel) where the scenario puts
// the board, so that `register` finds them. Returns how many lie in the CT's grid.
int paint_board_beads(const GuidanceScenario& scenario, const std::string& ct_path);

}  // namespace crepuscular::pipelines
