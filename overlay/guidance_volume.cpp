// Layer 2 "volume": the path safety volume rendered directly (SafetyVolumeRendering).
#include "overlay/guidance_drawing.hpp"

#include <cmath>
#include <limits>

#include "overlay/volume_rendering.hpp"
#include "planning/imaging/ray_march.hpp"

namespace crepuscular::overlay {

namespace {

// The volume rendering's options from the guidance options. Without a resolution scale: a quarter
// on software OpenGL (llvmpipe), full resolution on a GPU.
VolumeRenderingOptions volume_rendering_options(const GuidanceOptions& options,
                                                const OverlayRenderer& renderer) {
  VolumeRenderingOptions vo;
  vo.palette = options.palette;
  vo.resolution_scale = options.volume_resolution_scale;
  if (!(vo.resolution_scale > 0)) {
    vo.resolution_scale =
        renderer.gl_description().find("llvmpipe") != std::string::npos ? 0.25 : 1.0;
  }
  vo.show_safe = options.volume_classes[0];
  vo.show_medium = options.volume_classes[1];
  vo.show_dangerous = options.volume_classes[2];
  return vo;
}

// Sets every computed voxel whose centre is outside the body (inside_body(p) false) to NaN.
template <typename InsideBody>
void clear_outside_body(planning::Volume<float>& volume, const InsideBody& inside_body) {
  const auto d = volume.dims();
  for (int64_t k = 0; k < d[2]; ++k)
    for (int64_t j = 0; j < d[1]; ++j)
      for (int64_t i = 0; i < d[0]; ++i) {
        float& v = volume(i, j, k);
        if (std::isfinite(v) && !inside_body(volume.index_to_physical(i, j, k))) {
          v = std::numeric_limits<float>::quiet_NaN();
        }
      }
}

}  // namespace

void GuidanceOverlay::draw_volume(OverlayRenderer& renderer, const Eigen::Isometry3d& T_cam_ct) {
  if (!volume_) {
    const VolumeRenderingOptions vo = volume_rendering_options(options_, renderer);
    // Only inside the body: air in front of the patient has path safety values too.
    planning::Volume<float> inside = plan_.path_safety.at(value_);
    if (!plan_.labels.empty()) {
      clear_outside_body(inside, [this](const Eigen::Vector3d& p) { return inside_body(p); });
    }
    volume_ = std::make_unique<SafetyVolumeRendering>(inside, plan_.classes.at(value_), vo);
  }
  volume_->set_pose(T_cam_ct);
  SafetyVolumeRendering* volume = volume_.get();
  renderer.set_layer_draw("volume", [volume](const DrawContext& c) { volume->draw(c); });
}

}  // namespace crepuscular::overlay
