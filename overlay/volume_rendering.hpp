// Volume rendering of a path safety volume from a camera's viewpoint (§3.4): the operating-room
// camera's (overlay layer 2) or a planning camera's (the 3D planning view, overlay/plan_view.hpp).
// The class transfer function (safe, medium, dangerous, each with its colour and absorption, and
// unknown in grey where the plan's region states say so), no shading on the classes, classes
// hideable, colour-blind palette; optionally the anatomy as context in the same rays: translucent,
// lit surfaces where a ray enters the body, a bone, the tumor or a structure. Rays come through the
// calibrated camera model, distortion included; a CPU reference computes the same integral for any
// pixel.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "calibration/camera_model.hpp"
#include "overlay/renderer.hpp"
#include "planning/safety/safety_classes.hpp"
#include "planning/views/palette.hpp"
#include "planning/imaging/volume.hpp"

namespace crepuscular::overlay {

struct VolumeRenderingOptions {
  // Colours of the classes: planning::class_colours(palette) (green/yellow/red, or blue to yellow
  // for colour-blind users).
  planning::Palette palette = planning::Palette::kDefault;
  // Hidden classes are fully transparent (§3.4: "remove certain safety classes").
  bool show_safe = true, show_medium = true, show_dangerous = true;
  // Unknown voxels (region state unknown: outside the scan), drawn in kUnknownGrey, never in a
  // class colour. Only with region states given to the constructor.
  bool show_unknown = true;
  double unknown_opacity_per_mm = 0.006;
  // Absorption coefficient per mm of each class (safe, medium, dangerous): a ray crossing L mm of
  // one class gets opacity 1 - exp(-k L). Defaults keep the video visible: 100 mm of safe region
  // give 33 %, of medium 45 %, of dangerous 63 %. Each must be >= 0.
  double opacity_per_mm[3] = {0.004, 0.006, 0.010};
  // Distance between samples along a ray, mm; 0: half the smallest voxel spacing.
  double step_mm = 0;
  // Fraction of the image resolution the rays are cast at (0 < s <= 1); below 1 the result is
  // upsampled bilinearly when composited (for software OpenGL; 1 on a GPU).
  double resolution_scale = 1.0;
  // Anatomy kinds (AnatomyContext) whose surfaces are hidden: bit k hides kind k.
  uint32_t hidden_surfaces = 0;
};

// Colour of unknown voxels in the 3D view (RGB).
inline constexpr planning::Rgb kUnknownGrey = {150, 150, 150};

// The anatomy around the tumor, drawn as context in the same rays: one kind per voxel of the path
// safety grid (0: nothing, e.g. air), each kind a translucent surface where a ray enters it, lit
// from the camera (shade = kSurfaceAmbient + (1 - kSurfaceAmbient) |cos| between the ray and the
// kind's gradient). At most kMaxAnatomyKinds kinds. With a context, the voxels of kind 0 (outside
// the body) show no class (a needle path starts on the skin), unknown ones excepted; the first
// sample of a ray shows no surface (the grid's faces cut the anatomy, they are not its surfaces).
inline constexpr int kMaxAnatomyKinds = 16;
inline constexpr double kSurfaceAmbient = 0.35;
struct AnatomySurface {
  std::string name;                  // "skin", "bone", "tumor", "portal vein", ...
  planning::Rgb colour = {255, 255, 255};
  double opacity = 0.3;              // alpha of one crossing, 0..1 (0: not drawn)
};
struct AnatomyContext {
  planning::Volume<uint8_t> kinds;   // on the path safety grid; values < surfaces.size()
  std::vector<AnatomySurface> surfaces;  // by kind; surfaces[0] (nothing) is never drawn
};

// Front-to-back emission-absorption compositing ends once the opacity reaches this.
inline constexpr double kVolumeRenderingOpaque = 0.99;
// Distance to a voxel face (index units) within which a sample's voxel is not certain in single
// precision (float rounding of positions ~100 voxels from the origin is ~1e-5).
inline constexpr double kVolumeRenderingAmbiguity = 1e-4;

class SafetyVolumeRendering {
 public:
  // Classifies every voxel once (NaN: none; NaN where `region_state` is kRegionUnknown: unknown).
  // `region_state` and `context`, when given, lie on the path safety grid. Throws Error when the
  // volume is empty, its geometry is unusable, a grid differs, or an option is out of range.
  SafetyVolumeRendering(const planning::Volume<float>& path_safety,
                        const planning::SafetyClasses& classes, VolumeRenderingOptions options = {},
                        const planning::Volume<uint8_t>* region_state = nullptr,
                        const AnatomyContext* context = nullptr);
  ~SafetyVolumeRendering();
  SafetyVolumeRendering(const SafetyVolumeRendering&) = delete;
  SafetyVolumeRendering& operator=(const SafetyVolumeRendering&) = delete;

  void set_options(const VolumeRenderingOptions& options);
  const VolumeRenderingOptions& options() const { return options_; }
  // Pose of the CT in the camera: CT LPS mm -> camera mm.
  void set_pose(const Eigen::Isometry3d& T_cam_ct);
  const Eigen::Isometry3d& pose() const { return T_cam_ct_; }

  // The layer's drawing step (OverlayRenderer::set_layer_draw): draws over what the bound
  // framebuffer holds, within its current viewport, which holds the camera's image (context.width x
  // context.height pixels). Creates its OpenGL objects on the first call, in the current context (one
  // rendering serves one renderer), and re-makes the per-pixel rays when the camera or the image
  // size changes. Throws Error on an OpenGL failure.
  void draw(const DrawContext& context);
  // Frees the OpenGL objects; call with the context they were made in current. (Without it they
  // go when that context is destroyed.)
  void release_gl();

  // CPU reference of the same emission-absorption integral for the ray of pixel (u, v) (OpenCV
  // convention, (0,0) = centre of the top-left pixel): premultiplied RGB and alpha, 0..1. At pixel
  // centres it takes the same samples as draw() at resolution_scale 1. `ambiguous` (optional) is
  // set when a sample lies within kVolumeRenderingAmbiguity (index units) of a face between voxels
  // of different classes: there single-precision arithmetic on the GPU may pick the neighbour, and
  // the pixel may differ by up to one sample's contribution.
  Eigen::Vector4d reference_pixel(const calibration::CameraModel& camera, double u, double v,
                                  bool* ambiguous = nullptr) const;

  // Class index per voxel (0 none/NaN, 1 safe, 2 medium, 3 dangerous, 4 unknown), i fastest.
  const std::vector<uint8_t>& voxel_classes() const { return voxel_classes_; }
  const planning::ImageGeometry& geometry() const { return geometry_; }
  // The anatomy kind per voxel (empty without context) and the kinds' surfaces.
  const std::vector<uint8_t>& voxel_kinds() const { return voxel_kinds_; }
  const std::vector<AnatomySurface>& surfaces() const { return surfaces_; }

 private:
  struct Gl;
  // The ray's transform into index space, as the shader gets it (single precision).
  struct RaySetup {
    Eigen::Matrix3f M;   // camera direction -> index-space direction (per mm along the ray)
    Eigen::Vector3f m0;  // camera centre in index space
  };
  RaySetup ray_setup() const;
  double step() const;

  planning::ImageGeometry geometry_;
  std::vector<uint8_t> voxel_classes_;
  std::vector<uint8_t> voxel_kinds_;       // empty without context
  std::vector<AnatomySurface> surfaces_;
  // Index-space box of the voxels with a class or an anatomy kind (empty: lo > hi).
  Eigen::Vector3f box_lo_, box_hi_;
  VolumeRenderingOptions options_;
  Eigen::Isometry3d T_cam_ct_ = Eigen::Isometry3d::Identity();
  std::unique_ptr<Gl> gl_;
};

// Unit viewing ray of pixel (u, v) in the camera frame through the exact undistortion, rounded to
// single precision as the renderer stores it; zero where the pixel cannot be undistorted.
Eigen::Vector3f pixel_ray(const calibration::CameraModel& camera, double u, double v);

}  // namespace crepuscular::overlay
