// The AR guidance overlay: what the radiologist sees on the live video. Geometry that depends only
// on the plan (safe ray bundles, entry-area contours on the skin, the tumor's surface) is built
// once in CT coordinates; every frame it is moved into the camera with the tracked patient board
// and handed to the OverlayRenderer, together with the tracked needle, its live safety and the
// tracking status. The pictures drawn on the CPU cover only the part of the frame their shapes
// cover; those of the anatomy are kept while the patient board moves them by less than a quarter
// pixel, and the targeting view's while the needle stays where it was.
//
// Layers (names, keys in the window), each drawn by a file of its own (overlay/guidance_rays.cpp,
// _volume, _entry, _tumor, _needle, _status, _target); guidance_pictures.cpp keeps the anatomy
// layers' CPU pictures, guidance_drawing.hpp holds what the layers share:
//   1 "rays"    safe directions: one translucent cone per safe area-safety region, from its entry
//               patch on the skin to the tumor centre (plans without area safety: the safe ray
//               bundles, rays from the tumor out to the skin whose entry point is safe or medium in
//               the plan's path safety volume, coloured by class)
//   2 "volume"  volume rendering of the path safety volume (SafetyVolumeRendering), off by default
//   3 "entry"   entry areas: where each safe area-safety region's directions meet the skin, as
//               translucent patches on the skin (the sides facing the camera) whose outline width
//               and colour show the region's leeway; the planned trajectory (the best entry of the
//               largest safe region to the tumor centre) dashed, with a ring at its entry
//   4 "tumor"   the tumor seen through the skin: its silhouette filled translucently, outlined,
//               labelled, and its centre
//   5 "needle"  the tracked needle, its line extended to the tumor coloured by its live safety,
//               a ring where that line enters the skin, the nearest safe direction, and a text
//               panel (line integral, structures crossed with depth, tip-to-target distance, the
//               deviation from the nearest safe direction and from the planned trajectory: mm
//               between the skin entries, degrees between the directions)
//   6 "status"  tracking state of both boards, frame rate, end-to-end latency, and warnings
//   7 "target"  targeting view (picture-in-picture, top right): looking down the needle at the
//               plane through the tumor centroid; tumor outline, the needle's crossing, and the
//               polar map of path safety for tilts of the needle about its skin entry
//
// Tracking loss is shown, never hidden: the anatomy layers (1-4) are drawn only while the patient
// board is tracked (the tracker reports a pose older than its limit as lost), the needle and
// target layers only while both boards are, and a frame without an image shows no overlay at all.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <future>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "calibration/camera_model.hpp"
#include "planning/plan_folder/plan_folder.hpp"
#include "planning/trajectories/markups.hpp"
#include "planning/breathing/respiratory_phase.hpp"
#include "planning/trajectories/needle_guidance.hpp"
#include "planning/trajectories/needle_uncertainty.hpp"
#include "planning/trajectories/targeting.hpp"
#include "planning/views/palette.hpp"
#include "tracking/tracker.hpp"

namespace crepuscular::overlay {

class OverlayRenderer;
class LayerCalls;
class SafetyVolumeRendering;

enum class GuidanceLayer { kRays = 0, kVolume, kEntry, kTumor, kNeedle, kStatus, kTarget };
constexpr int kGuidanceLayerCount = 7;
const char* guidance_layer_name(GuidanceLayer layer);  // "rays", "volume", ...
// "rays" -> kRays, ... ; also "1".."7". Throws Error naming the text otherwise.
GuidanceLayer parse_guidance_layer(const std::string& text);

// How the tracked boards relate to the plan.
struct GuidanceSetup {
  calibration::CameraModel camera;
  Eigen::Isometry3d T_ct_patient = Eigen::Isometry3d::Identity();  // registration
  std::string patient_board = "patient";
  std::string needle_board = "needle";
  Eigen::Vector3d tip_in_needle = Eigen::Vector3d(0, 0, 150);  // needle frame, mm
  // Unit direction of the needle from the hub toward the tip, needle frame. When the needle
  // calibration has no spin axis, the direction from the board origin to the tip.
  Eigen::Vector3d axis_in_needle = Eigen::Vector3d::UnitZ();
  // What the calibrations say of their own errors: the tip's covariance, the axis's (or that it
  // follows the tip) and the registration's expected error at the tumor. The boards' pose
  // covariances come with each frame's tracking.
  planning::NeedleUncertaintySources uncertainty;
};

struct GuidanceOptions {
  std::string value;  // path safety value for the ray bundles ("" = the plan's first)
  planning::Palette palette = planning::Palette::kDefault;
  int ray_directions = 3000;  // directions sampled evenly on the sphere around the tumor
  std::array<bool, kGuidanceLayerCount> visible = {true, false, true, true, true, true, true};
  // The targeting view (layer 7); its size is reduced to fit half the image's smaller side.
  planning::TargetingOptions targeting;
  // Volume rendering resolution relative to the image (0 < s <= 1); 0: automatic, 1 on a GPU and
  // 0.25 on a software renderer (Mesa llvmpipe), where a full-size rendering takes ~0.5 s.
  double volume_resolution_scale = 0;
  // Classes the volume rendering shows (safe, medium, dangerous): by default the safe and medium
  // paths only, as the paper shows them, so the safe funnels stand out. Voxels outside the body
  // (label 0) are never drawn.
  std::array<bool, 3> volume_classes = {true, true, false};
  // The pictures of the anatomy layers drawn on the CPU (cones, entry patches with the planned
  // trajectory, the tumor) are kept and shown again while the patient board's pose moves no point
  // of the plan's geometry by more than this in the image (pixels; a still board under a still
  // camera); 0: drawn anew every frame.
  double anatomy_reuse_px = 0.25;
  // When the board has moved them by more than that, the kept pictures are still shown, placed by
  // the affine map that best carries them to the present pose, where that map's largest error
  // over points of everything they show (patches, cones, tumor, planned trajectory) is within
  // anatomy_reuse_px; meanwhile the pictures for the present pose are drawn on another thread and
  // taken up at the next frame. The frame waits only when the pose jumped too far for any map (or
  // the layers changed).
  // false: only the still-board rule above.
  bool anatomy_ahead = true;
};

// The needle part of one frame (present when both boards were tracked).
struct NeedleReading {
  Eigen::Isometry3d T_ct_needle = Eigen::Isometry3d::Identity();
  planning::NeedleState state;
  // How well the line is known (planning/trajectories/needle_uncertainty.hpp), and the worst class
  // of the lines of its 95 % region (none evaluated when the needle points away).
  planning::LineUncertainty uncertainty;
  planning::RegionSafety region;
  // Both boards' pose covariances came with the tracking (poses received over OpenIGTLink carry
  // none: the uncertainty then holds the calibrations' and the registration's errors only).
  bool pose_covariance_known = false;
};

// A breathing plan's phases for guidance (pipelines/guide_breathing.hpp reads them): each phase's
// plan on the plan's grid (its labels, tumor, blocking, path safety and tumor centre) and the
// skin's motion at the patient board over the phases. The registration is taken as made at
// phase 0 (end-exhale), as the plan's phase 0 is.
struct BreathingPhases {
  std::vector<std::string> names;
  std::vector<std::unique_ptr<planning::PlanData>> plans;
  planning::SkinMotion skin;
};

// The breathing part of one frame (breathing plans only).
struct BreathingReading {
  planning::PhaseEstimate estimate;
  // The needle's line's class in each phase (empty without a needle reading); when the phase is
  // known, the needle reading itself is the current phase's.
  std::vector<planning::NeedleSafety> phase_safety;
};

// What one frame showed, for logs and reports.
struct GuidanceFrameInfo {
  int64_t frame = 0;
  int64_t timestamp_ns = 0;
  bool image = true;           // the frame had an image
  std::string problem;         // the frame's own problem (corrupt, missing), or ""
  bool patient_tracked = false;
  bool needle_tracked = false;
  double patient_age_ms = 0, needle_age_ms = 0;  // age of the pose in use (when tracked)
  bool anatomy_drawn = false;  // layers 1-4 were drawn from a current patient pose
  std::optional<NeedleReading> needle;
  std::optional<BreathingReading> breathing;
  std::vector<std::string> warnings;  // shown on screen
  // Where update() spent its time (ms): the video frame's upload, layers 1-4, the needle's
  // evaluation and layer (computed beside layers 1-4, on another thread), the status layer.
  double upload_ms = 0, anatomy_ms = 0, needle_ms = 0, status_ms = 0;
  // The needle part's pieces (ms): its evaluation, the targeting view (polar map and picture),
  // the text panel (drawn beside the targeting view).
  double needle_evaluate_ms = 0, targeting_ms = 0, needle_panel_ms = 0;
  double uncertainty_ms = 0;  // the line's uncertainty and the safety of its 95 % region
};

// Frame rate and latency shown in the status layer.
struct GuidanceTiming {
  double fps = 0;              // frames shown per second, recent average
  double latency_ms = -1;      // of the previous frame (this one is not shown yet); -1: unknown
  bool latency_from_capture = false;  // true: from the capture timestamp; false: from arrival
  double track_ms = 0;
};

class GuidanceOverlay {
 public:
  // Builds the plan's geometry (ray bundles, entry contours, tumor surface). The plan must hold a
  // path safety volume; labels, tumor mask and area safety are used when present. `plan` must
  // outlive the overlay.
  GuidanceOverlay(const planning::PlanData& plan, GuidanceSetup setup, GuidanceOptions options = {});
  ~GuidanceOverlay();
  GuidanceOverlay(const GuidanceOverlay&) = delete;
  GuidanceOverlay& operator=(const GuidanceOverlay&) = delete;

  // Fills the renderer's layers for one frame: background, anatomy, needle, status. Returns what
  // was shown. The renderer's camera must be setup.camera's image size.
  // frame_uploaded: the caller already gave the frame's image to renderer.set_frame() (e.g. while
  // tracking ran on another thread).
  GuidanceFrameInfo update(OverlayRenderer& renderer, const tracking::Frame& frame,
                           const tracking::TrackResult& track, const GuidanceTiming& timing,
                           bool frame_uploaded = false);

  // Guidance over the breathing cycle: each frame estimates the phase from the patient board's
  // motion, moves the registration with the skin under the board, evaluates the needle against
  // the current phase and every phase (the gating bar) and draws the current phase's tumor.
  void set_breathing(std::unique_ptr<BreathingPhases> phases);
  const BreathingPhases* breathing() const { return breathing_.get(); }

  void set_visible(GuidanceLayer layer, bool visible);
  bool visible(GuidanceLayer layer) const;
  void toggle(GuidanceLayer layer) { set_visible(layer, !visible(layer)); }
  void set_palette(planning::Palette palette);
  planning::Palette palette() const { return options_.palette; }

  // The plan geometry in CT (LPS mm), for tests and logs.
  struct Ray {
    Eigen::Vector3d start, end;  // tumor surface -> skin
    planning::SafetyClass safety_class;
  };
  const std::vector<Ray>& rays() const { return rays_; }
  int unknown_rays() const { return unknown_rays_; }
  struct Contour {
    int region = 0;
    double leeway = 0;  // 0..1
    std::vector<Eigen::Vector3d> points;
    bool closed = false;
  };
  const std::vector<Contour>& entry_contours() const { return contours_; }
  // Entry patch of one safe region: the skin points where its vertices' extrusion directions leave
  // the body (vertices whose line meets no skin in the scan are left out), triangulated as the
  // area safety mesh is, and the edges of its border (edges of one triangle only).
  struct Patch {
    int region = 0;
    double leeway = 0;  // 0..1
    std::vector<Eigen::Vector3d> points;
    std::vector<std::array<int, 3>> triangles;
    std::vector<std::array<int, 2>> border;
  };
  const std::vector<Patch>& entry_patches() const { return patches_; }
  // The pixels (CV_8U, 255) of the camera image that the patches' triangles facing the camera
  // cover; region -1: all regions.
  cv::Mat entry_patch_mask(const Eigen::Isometry3d& T_cam_ct,
                           const calibration::CameraModel& camera, int region = -1) const;
  // The planned trajectory: the best entry of the largest safe region reaching the skin, to the
  // tumor centre (planning::region_trajectories); none without area safety.
  const std::optional<planning::RegionTrajectory>& planned_trajectory() const { return planned_; }
  // Where the needle's line enters the skin (the point just outside), as the panel's deviations
  // use it; nullopt when it points away or never meets the body before the target.
  std::optional<Eigen::Vector3d> needle_skin_entry(const planning::NeedleState& s) const;
  const std::vector<Eigen::Vector3d>& tumor_surface() const { return tumor_surface_; }
  const planning::NeedleGuide& needle_guide() const { return *guide_; }
  const GuidanceSetup& setup() const { return setup_; }
  // The targeting view of the last frame that drew it (valid false before), and where its
  // top-left pixel lay in the frame.
  const planning::TargetingGeometry& last_targeting() const { return targeting_; }
  cv::Point last_targeting_origin() const { return targeting_origin_; }
  // How many frames drew the anatomy layers' pictures anew (the others showed the kept ones), and
  // how many computed the targeting view's polar map anew; for tests and logs.
  int64_t anatomy_pictures_drawn() const { return anatomy_pictures_drawn_; }
  // How many frames showed pictures drawn for an earlier pose, placed by an affine map, and how
  // many waited for pictures drawn then and there (the others took them from the thread drawing
  // ahead, or kept them for a still board).
  int64_t anatomy_pictures_warped() const { return anatomy_pictures_warped_; }
  int64_t anatomy_pictures_waited() const { return anatomy_pictures_waited_; }
  int64_t targeting_maps_computed() const { return targeting_maps_computed_; }

 private:
  void build_rays();
  // Whether the segment meets a voxel of the plan's region whose state is unknown.
  bool crosses_unknown(const Eigen::Vector3d& from, const Eigen::Vector3d& to, double step) const;
  void build_entry_contours();
  void build_tumor_surface();
  // The entry patches of a plan's area safety on its own skin (its labels).
  static std::vector<Patch> entry_patches_of(const planning::PlanData& plan);
  void draw_anatomy(OverlayRenderer& renderer, const Eigen::Isometry3d& T_cam_ct);
  void draw_volume(OverlayRenderer& renderer, const Eigen::Isometry3d& T_cam_ct);
  // The reading's uncertainty and region safety from both boards' tracking and the setup.
  void read_uncertainty(NeedleReading& reading, const planning::NeedleGuide& guide,
                        const Eigen::Isometry3d& T_ct_patient, const tracking::BoardStatus& patient,
                        const tracking::BoardStatus& needle) const;
  // The breathing phase of a frame whose patient board is tracked; moves T_ct_patient with the
  // skin and returns the guide of the current phase (the plan's own when the phase is unknown).
  const planning::NeedleGuide* read_breathing(const tracking::Frame& frame,
                                              const tracking::BoardStatus& patient,
                                              Eigen::Isometry3d& T_ct_patient,
                                              BreathingReading& reading);
  void draw_gating_bar(LayerCalls& renderer, const BreathingReading& reading) const;
  // Into a LayerCalls (guidance_drawing.hpp) that records what is added, so that the needle's
  // part can be drawn beside the anatomy's and added afterwards.
  void draw_needle(LayerCalls& renderer, const Eigen::Isometry3d& T_cam_ct,
                   const Eigen::Isometry3d& T_cam_needle, const NeedleReading& reading,
                   const BreathingReading* breathing);
  void draw_targeting(LayerCalls& renderer, const Eigen::Isometry3d& T_cam_ct,
                      const NeedleReading& reading);
  void draw_status(OverlayRenderer& renderer, const GuidanceFrameInfo& info,
                   const GuidanceTiming& timing);
  // Last point inside the body going out from `from` along `dir` (labels > 0), within the plan's
  // region of interest; nullopt when the walk never leaves the body there.
  std::optional<Eigen::Vector3d> skin_exit(const Eigen::Vector3d& from,
                                           const Eigen::Vector3d& dir) const;
  static std::optional<Eigen::Vector3d> skin_exit_in(const planning::PlanData& plan,
                                                     const Eigen::Vector3d& from,
                                                     const Eigen::Vector3d& dir);
  bool inside_body(const Eigen::Vector3d& p) const;

  // What the anatomy pictures show of a breathing phase (phase -1: the plan's own).
  struct PhaseShown {
    int phase = -1;
    Eigen::Vector3d tumor_shift = Eigen::Vector3d::Zero();
    bool operator==(const PhaseShown& o) const { return phase == o.phase && tumor_shift == o.tumor_shift; }
  };
  const planning::PlanData& plan_;
  GuidanceSetup setup_;
  std::unique_ptr<BreathingPhases> breathing_;
  std::vector<std::unique_ptr<planning::NeedleGuide>> phase_guides_;
  std::unique_ptr<planning::RespiratoryPhaseEstimator> phase_estimator_;
  // The current phase's tumor: its centre, and how far its surface lies from the plan's mask.
  Eigen::Vector3d tumor_centre_shown_ = Eigen::Vector3d::Zero();
  PhaseShown phase_shown_;
  // The guide of this frame (the current phase's, else guide_), and the one the targeting view
  // was computed with.
  const planning::NeedleGuide* current_guide_ = nullptr;
  const planning::NeedleGuide* targeting_guide_ = nullptr;
  std::vector<std::vector<Patch>> phase_patches_;  // per phase, from its own area safety
  GuidanceOptions options_;
  std::string value_;
  std::unique_ptr<planning::NeedleGuide> guide_;
  std::unique_ptr<SafetyVolumeRendering> volume_;
  std::vector<Ray> rays_;
  int unknown_rays_ = 0;  // directions not drawn because they reach the unknown
  std::vector<Contour> contours_;
  std::vector<Patch> patches_;
  std::optional<planning::RegionTrajectory> planned_;
  std::vector<Eigen::Vector3d> tumor_surface_;
  double tumor_voxel_mm_ = 1;
  // The anatomy layers' pictures and what they were drawn for (draw_anatomy).
  struct LayerPicture {
    bool drawn = false;
    cv::Mat bgra;  // empty: nothing to show
    cv::Point origin;
    uint64_t revision = 0;  // OverlayRenderer::new_image_revision() of these pixels
  };
  struct AnatomyPictures {
    bool valid = false;
    Eigen::Isometry3d T_cam_ct = Eigen::Isometry3d::Identity();
    planning::Palette palette = planning::Palette::kDefault;
    calibration::CameraModel camera;
    // Breathing: the phase whose cones and entry patches these are (-1: the plan's own) and how
    // far its tumor lies from the plan's mask.
    int phase = -1;
    Eigen::Vector3d tumor_shift = Eigen::Vector3d::Zero();
    LayerPicture cones, entry, tumor;
    std::vector<Eigen::Vector2d> anchors_px;  // anatomy_anchors_ in the image (empty: unusable)
  };
  // The three anatomy pictures, in the order of AnatomyPictures and of draw_pictures' layers.
  enum class AnatomyPicture { kCones, kEntry, kTumor };
  // One picture for one pose, drawn from the plan's geometry only (safe to run on another
  // thread), into `picture`, which it marks drawn.
  void draw_picture(AnatomyPicture which, LayerPicture& picture, const Eigen::Isometry3d& T_cam_ct,
                    const calibration::CameraModel& camera, planning::Palette palette,
                    const PhaseShown& shown) const;
  // The pictures of the visible layers for one pose.
  AnatomyPictures draw_pictures(const Eigen::Isometry3d& T_cam_ct,
                                const calibration::CameraModel& camera, planning::Palette palette,
                                std::array<bool, 3> layers, const PhaseShown& shown) const;
  // The entry patches of what is shown, and the cones' apex.
  const std::vector<Patch>& patches_shown(const PhaseShown& shown) const;
  Eigen::Vector3d cone_apex(const PhaseShown& shown) const;
  AnatomyPictures anatomy_;
  std::future<AnatomyPictures> anatomy_ahead_;  // drawn for the last frame's pose
  // The corners of a box (CT) around everything the pictures show, for the reuse test, and
  // points of it, for the placed pictures' error.
  std::array<Eigen::Vector3d, 8> anatomy_box_{};
  std::vector<Eigen::Vector3d> anatomy_anchors_;  // points of what the pictures show
  int64_t anatomy_pictures_drawn_ = 0, targeting_maps_computed_ = 0;
  int64_t anatomy_pictures_warped_ = 0, anatomy_pictures_waited_ = 0;
  planning::TargetingGeometry targeting_;
  LayerPicture targeting_picture_;  // the view of targeting_
  std::vector<Eigen::Vector3d> targeting_ellipse_;  // the uncertainty drawn into it
  planning::Palette targeting_palette_ = planning::Palette::kDefault;
  Eigen::Vector3d targeting_tip_ = Eigen::Vector3d::Zero(), targeting_right_ = Eigen::Vector3d::Zero();
  cv::Point targeting_origin_;
  // Timings of the last draw_needle (ms), read once its thread is joined.
  double targeting_ms_ = 0, needle_panel_ms_ = 0;
};

// One line per structure the needle's line crosses: "portal vein (high) at 43 mm, 6.2 mm long".
std::vector<std::string> needle_text(const planning::NeedleState& state);

}  // namespace crepuscular::overlay
