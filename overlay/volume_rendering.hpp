// Volume rendering of a path safety volume from the camera's viewpoint (overlay layer 2, §3.4):
// the class transfer function (safe, medium, dangerous, each with its colour and absorption), no
// shading, classes hideable, colour-blind palette. Rays come through the calibrated camera model,
// distortion included; a CPU reference computes the same integral for any pixel.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <cstdint>
#include <memory>
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
  // Absorption coefficient per mm of each class (safe, medium, dangerous): a ray crossing L mm of
  // one class gets opacity 1 - exp(-k L). Defaults keep the video visible: 100 mm of safe region
  // give 33 %, of medium 45 %, of dangerous 63 %. Each must be >= 0.
  double opacity_per_mm[3] = {0.004, 0.006, 0.010};
  // Distance between samples along a ray, mm; 0: half the smallest voxel spacing.
  double step_mm = 0;
  // Fraction of the image resolution the rays are cast at (0 < s <= 1); below 1 the result is
  // upsampled bilinearly when composited (for software OpenGL; 1 on a GPU).
  double resolution_scale = 1.0;
};

// Front-to-back emission-absorption compositing ends once the opacity reaches this.
inline constexpr double kVolumeRenderingOpaque = 0.99;
// Distance to a voxel face (index units) within which a sample's voxel is not certain in single
// precision (float rounding of positions ~100 voxels from the origin is ~1e-5).
inline constexpr double kVolumeRenderingAmbiguity = 1e-4;

class SafetyVolumeRendering {
 public:
  // Classifies every voxel once (NaN: none). Throws Error when the volume is empty, its geometry
  // is unusable, or an option is out of range.
  SafetyVolumeRendering(const planning::Volume<float>& path_safety,
                        const planning::SafetyClasses& classes, VolumeRenderingOptions options = {});
  ~SafetyVolumeRendering();
  SafetyVolumeRendering(const SafetyVolumeRendering&) = delete;
  SafetyVolumeRendering& operator=(const SafetyVolumeRendering&) = delete;

  void set_options(const VolumeRenderingOptions& options);
  const VolumeRenderingOptions& options() const { return options_; }
  // Pose of the CT in the camera: CT LPS mm -> camera mm.
  void set_pose(const Eigen::Isometry3d& T_cam_ct);
  const Eigen::Isometry3d& pose() const { return T_cam_ct_; }

  // The layer's drawing step (OverlayRenderer::set_layer_draw): draws over what the bound
  // framebuffer holds. Creates its OpenGL objects on the first call, in the current context (one
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

  // Class index per voxel (0 none/NaN, 1 safe, 2 medium, 3 dangerous), i fastest.
  const std::vector<uint8_t>& voxel_classes() const { return voxel_classes_; }

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
  Eigen::Vector3f box_lo_, box_hi_;  // index-space box of the classified voxels (empty: lo > hi)
  VolumeRenderingOptions options_;
  Eigen::Isometry3d T_cam_ct_ = Eigen::Isometry3d::Identity();
  std::unique_ptr<Gl> gl_;
};

// Unit viewing ray of pixel (u, v) in the camera frame through the exact undistortion, rounded to
// single precision as the renderer stores it; zero where the pixel cannot be undistorted.
Eigen::Vector3f pixel_ray(const calibration::CameraModel& camera, double u, double v);

}  // namespace crepuscular::overlay
