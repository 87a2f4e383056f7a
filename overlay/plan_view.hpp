// The 3D planning view (paper §3.4, Fig. 8): the path safety volume rendered directly from a
// planning camera that orbits the tumor, with the anatomy as context in the same rays (skin, bone
// from the CT, the tumor and the vulnerable structures as translucent lit surfaces) and, on
// request, the area safety mesh's vertices coloured by leeway. It is the overlay's volume rendering
// (SafetyVolumeRendering) seen from a virtual pinhole camera: `view` shows it in a window,
// `render` writes it as a picture.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "calibration/camera_model.hpp"
#include "overlay/volume_rendering.hpp"
#include "planning/plan_folder/plan_folder.hpp"

namespace crepuscular::overlay {

// Where the planning camera looks from, about the point it looks at: azimuth about the patient's
// superior axis, 0 from anterior, 90 from the patient's left, 180 from posterior, -90 (270) from
// the patient's right; elevation toward superior (90: from above the head, -90: from the feet).
struct ViewAngles {
  double azimuth_deg = 0;
  double elevation_deg = 0;
};
// "anterior", "posterior", "left", "right", "superior", "inferior" or "AZ,EL" (degrees). Throws
// Error naming the text otherwise.
ViewAngles parse_view_angles(const std::string& text);

// A pinhole camera (no distortion) orbiting `centre`: it sits distance_mm away in the direction of
// `angles` and looks at the centre, the patient's superior side up (from above or below: anterior
// up). Image y grows downward, as for the operating-room camera.
struct OrbitCamera {
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();  // LPS mm
  ViewAngles angles;
  double distance_mm = 500;
  double fov_deg = 30;  // vertical field of view

  // T_cam_ct: CT LPS mm -> camera mm (x right, y down, z forward).
  Eigen::Isometry3d pose() const;
  // The camera model of a width x height image; the principal point at the image centre.
  calibration::CameraModel camera(int width, int height) const;
  // Distance at which a sphere of radius_mm around the centre fills the image's smaller field of
  // view (with a 5 % margin).
  static double fitting_distance(double radius_mm, double fov_deg, double aspect);
};

// Kinds of the anatomy context (AnatomyContext::kinds); structures follow from kStructureKind.
enum AnatomyKind : uint8_t {
  kOutside = 0,
  kSkin = 1,   // the body (label > 0): its surface is the skin
  kBone = 2,   // CT >= kBoneHu inside the body, or labels named as bones
  kTumor = 3,  // the plan's tumor mask
  kStructureKind = 4,  // the first vulnerable structure; one kind each, up to kMaxAnatomyKinds
};
inline constexpr double kBoneHu = 250;

// The anatomy context of a plan on its path safety grid: body from the label map, bone from the
// CT (when given, else labels whose names say bone), tumor from its mask, and one kind per
// vulnerable structure (labels of the table's third level and above; beyond the kinds available,
// structures share them). Each path safety voxel takes the nearest voxel of each input. Without a
// label map or a CT the whole grid counts as body (no skin is drawn, no class removed).
AnatomyContext make_anatomy_context(const planning::PlanData& plan,
                                    const planning::Volume<float>* ct);

struct PlanViewOptions {
  std::string value;  // the path safety value shown ("": svv when computed, else the first)
  planning::Palette palette = planning::Palette::kDefault;
  // Hidden classes: safe, medium, dangerous, unknown.
  std::array<bool, 4> hidden{false, false, false, false};
  // Multiplies every class's absorption (VolumeRenderingOptions defaults are for the video).
  double opacity_scale = 4.0;
  bool context = true;      // the anatomy surfaces
  uint32_t hidden_surfaces = 0;  // by AnatomyKind bit
  bool area_mesh = false;   // the area safety mesh's vertices, coloured by leeway
  // Resolution of the rays relative to the image (0 < s <= 1; 0: automatic: 1 on a GPU; on a
  // software renderer 0.5, and 0.25 while the camera moves).
  double resolution_scale = 0;
};

// The 3D view of one plan. The volume renderings (one per value, made when first shown) keep their
// OpenGL objects in the context of the first renderer they draw with.
class PlanView3D {
 public:
  // `plan` and `ct` must outlive the view. Throws Error when the plan has no path safety volume or
  // the value asked for is not in it.
  PlanView3D(const planning::PlanData& plan, const planning::Volume<float>* ct,
             PlanViewOptions options = {});
  ~PlanView3D();

  const PlanViewOptions& options() const { return options_; }
  void set_options(const PlanViewOptions& options);
  const std::string& value() const { return value_; }
  // The value after the present one in plan.json's order among those at hand (wraps around).
  void next_value();
  // Values of another load of the same plan (on the same grid; e.g. every value, read after the
  // first picture) join those at hand. `plan` must outlive the view.
  void add_values(const planning::PlanData& plan);
  // The CT arrived (or changed): the anatomy context is made again (bone from it) and the
  // renderings with it, at the next draw. `ct` must outlive the view.
  void set_ct(const planning::Volume<float>* ct);
  // The present value's volume and classes.
  const planning::Volume<float>& volume() const { return *values_.at(value_).first; }
  const planning::SafetyClasses& classes() const { return values_.at(value_).second; }

  // The camera that shows the whole region of interest from `angles`.
  OrbitCamera default_camera(ViewAngles angles = {}, double aspect = 16.0 / 9.0) const;

  // Draws the view into `panel` (pixels of the renderer's image, `frame`) as `camera` (an image of
  // the panel's size) sees it from T_cam_ct: what OverlayRenderer::set_layer_draw runs.
  // `software`: the renderer is Mesa's; `moving`: the camera moves (both for the automatic
  // resolution).
  void draw(const DrawContext& frame, const cv::Rect& panel, const calibration::CameraModel& camera,
            const Eigen::Isometry3d& T_cam_ct, bool software, bool moving = false);
  // The area safety mesh's vertices (when options.area_mesh) in the camera frame with their
  // leeway colours (BGR), for OverlayRenderer::add_points.
  std::vector<std::pair<Eigen::Vector3d, cv::Scalar>> mesh_points(
      const Eigen::Isometry3d& T_cam_ct) const;

  // The rendering of the present value (made on first use).
  SafetyVolumeRendering& rendering();
  const AnatomyContext& context() const { return context_; }
  // Where the camera ray of pixel (u, v) first enters the body (anatomy kind != outside) within
  // the plan's grid: the LPS point, or nullopt when it misses the body.
  std::optional<Eigen::Vector3d> pick_skin(const calibration::CameraModel& camera,
                                           const Eigen::Isometry3d& T_cam_ct, double u,
                                           double v) const;
  // Frees the renderings' OpenGL objects (their context current).
  void release_gl();

 private:
  VolumeRenderingOptions rendering_options(bool software, bool moving) const;
  const planning::PlanData& plan_;
  const planning::Volume<float>* ct_;
  PlanViewOptions options_;
  std::string value_;
  AnatomyContext context_;
  std::map<std::string, std::pair<const planning::Volume<float>*, planning::SafetyClasses>>
      values_;
  std::map<std::string, std::unique_ptr<SafetyVolumeRendering>> renderings_;
  // Renderings of an earlier context, their OpenGL objects freed at the next draw.
  std::vector<std::unique_ptr<SafetyVolumeRendering>> retired_;
};

}  // namespace crepuscular::overlay
