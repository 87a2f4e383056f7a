// Layer 7 "target": the targeting view, looking down the needle at the plane through the tumor.
#include "overlay/guidance_drawing.hpp"

#include <chrono>
#include <cmath>

#include "overlay/targeting_view.hpp"

namespace crepuscular::overlay {

void GuidanceOverlay::draw_targeting(LayerCalls& renderer, const Eigen::Isometry3d& T_cam_ct,
                                     const NeedleReading& reading) {
  const planning::NeedleState& s = reading.state;
  const auto palette = options_.palette;
  const cv::Size frame(renderer.camera().width, renderer.camera().height);
  const auto targeting_start = std::chrono::steady_clock::now();
  targeting_ms_ = 0;

  if (visible(GuidanceLayer::kTarget)) {
    // The targeting view, top right; right in it is the camera's right.
    planning::TargetingOptions to = options_.targeting;
    to.size_px = std::min(to.size_px, std::min(frame.width, frame.height) / 2);
    to.right_hint = T_cam_ct.inverse().linear().col(0);
    if (to.size_px >= 32) {
      // The polar map costs a few dozen line evaluations: kept while the needle and the view
      // stay within 0.1 mm and 0.05 deg of the last frame's (a needle held still, a still camera).
      const double kSame = std::cos(0.05 * M_PI / 180.0);
      const bool same = targeting_.valid && !s.points_away && targeting_guide_ == current_guide_ &&
                        (s.tip - targeting_tip_).norm() < 0.1 && s.axis.dot(targeting_.axis) > kSame &&
                        to.right_hint.dot(targeting_right_) > kSame &&
                        to.size_px == targeting_.size_px;
      if (!same) {
        ++targeting_maps_computed_;
        // The current breathing phase's guide and tumor (the plan's own otherwise).
        std::vector<Eigen::Vector3d> tumor = tumor_surface_;
        for (auto& p : tumor) p += phase_shown_.tumor_shift;
        targeting_ = planning::targeting_geometry(*current_guide_, s, tumor, tumor_voxel_mm_, to);
        targeting_tip_ = s.tip;
        targeting_guide_ = current_guide_;
        targeting_right_ = to.right_hint;
      }
      targeting_origin_ = cv::Point(frame.width - to.size_px - 10, 10);
      // The 95 % ellipse of the line's crossing: drawn anew when it moves by half a pixel.
      const std::vector<Eigen::Vector3d> ellipse = reading.uncertainty.ellipse_at_tumor(48);
      bool ellipse_moved = ellipse.size() != targeting_ellipse_.size();
      for (size_t i = 0; i < ellipse.size() && !ellipse_moved; ++i) {
        ellipse_moved = (ellipse[i] - targeting_ellipse_[i]).norm() > 0.5 * targeting_.mm_per_px;
      }
      if (!same || ellipse_moved || !targeting_picture_.drawn || targeting_palette_ != palette) {
        targeting_ellipse_ = ellipse;
        targeting_picture_.bgra = render_targeting_view(targeting_, palette, ellipse);
        targeting_picture_.revision = OverlayRenderer::new_image_revision();
        targeting_picture_.drawn = true;
        targeting_palette_ = palette;
      }
      renderer.add_layer_image("target", targeting_picture_.bgra, targeting_origin_,
                               targeting_picture_.revision);
    }
    targeting_ms_ = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() -
                                                              targeting_start).count();
  }
}

}  // namespace crepuscular::overlay
