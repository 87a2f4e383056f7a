// Layer 1 "rays": the safe directions, one translucent cone per safe area-safety region (or the
// safe ray bundles of plans without area safety).
#include "overlay/guidance_drawing.hpp"

#include <cmath>

#include "planning/imaging/ray_march.hpp"
#include "planning/imaging/sampling.hpp"
#include "planning/safety/unknown.hpp"

namespace crepuscular::overlay {

bool GuidanceOverlay::crosses_unknown(const Eigen::Vector3d& from, const Eigen::Vector3d& to,
                                      double step) const {
  if (plan_.region.empty()) return false;
  const double length = (to - from).norm();
  const int n = std::max(1, int(std::ceil(length / step)));
  for (int k = 0; k <= n; ++k) {
    const Eigen::Vector3d p = from + (to - from) * (double(k) / n);
    if (planning::nearest_voxel_or<uint8_t>(plan_.region, p, planning::kRegionNotComputed) ==
        planning::kRegionUnknown) {
      return true;
    }
  }
  return false;
}

void GuidanceOverlay::build_rays() {
  const auto& volume = plan_.path_safety.at(value_);
  const planning::SafetyClasses& classes = plan_.classes.at(value_);
  const Eigen::Vector3d& centre = plan_.tumor_centre;
  const double step = 0.5 * plan_.grid.spacing.minCoeff();
  for (const Eigen::Vector3d& dir : planning::fibonacci_sphere(options_.ray_directions)) {
    // Leave the tumor (mask, else the centre itself).
    Eigen::Vector3d start = centre;
    if (!plan_.tumor.empty()) {
      for (double t = 0; t < 100.0; t += step) {
        if (planning::nearest_voxel_or<uint8_t>(plan_.tumor, centre + t * dir, 0) == 0) {
          start = centre + t * dir;
          break;
        }
      }
    }
    const auto end = skin_exit(start, dir);
    if (!end) continue;
    // Unknown is never safe: a ray that meets the outside of the scan (region state unknown) on
    // its way to the skin is not drawn, even where the value at its end borrows known neighbours.
    if (crosses_unknown(start, *end, step)) {
      ++unknown_rays_;
      continue;
    }
    const double value = planning::sample_path_safety(volume, *end);
    if (!std::isfinite(value)) continue;
    const planning::SafetyClass c = classes.classify(value);
    if (c == planning::SafetyClass::kDangerous) continue;
    rays_.push_back({start, *end, c});
  }
}

void add_rays(OverlayRenderer& renderer, const std::vector<GuidanceOverlay::Ray>& rays,
              const Eigen::Isometry3d& T_cam_ct, planning::Palette palette) {
  for (const GuidanceOverlay::Ray& ray : rays) {
    Polyline line;
    line.points_cam = {T_cam_ct * ray.start, T_cam_ct * ray.end};
    line.colour = class_bgr(palette, ray.safety_class);
    line.width_px = 1.5;
    line.opacity = 0.45;
    renderer.add_polyline("rays", line);
  }
}

// One translucent cone per patch: from the patch (its whole surface) to `apex`, i.e. the patch and
// the triangles from the apex to its border, which together cover the cone's projection; a faint
// outline around it. The picture spans the part of the frame the cones cover.
Picture cone_image(const std::vector<GuidanceOverlay::Patch>& patches, const Eigen::Vector3d& apex,
                   const Eigen::Isometry3d& T_cam_ct, const calibration::CameraModel& camera,
                   planning::Palette palette) {
  const Eigen::Vector3d apex_cam = T_cam_ct * apex;
  if (apex_cam.z() <= 1.0) return {};
  const Eigen::Vector2d apex_px = camera.project(apex_cam);
  std::vector<std::vector<Eigen::Vector2d>> projected;
  std::vector<Eigen::Vector2d> all = {apex_px};
  for (const auto& patch : patches) {
    projected.push_back(project_all(patch.points, T_cam_ct, camera));
    all.insert(all.end(), projected.back().begin(), projected.back().end());
  }
  const cv::Rect roi = region_around(all, 4, cv::Size(camera.width, camera.height));
  if (roi.empty()) return {};
  const cv::Point o = roi.tl();
  Picture picture{cv::Mat(roi.size(), CV_8UC4, cv::Scalar(0, 0, 0, 0)), o};
  cv::Mat& image = picture.bgra;
  for (size_t i = 0; i < patches.size(); ++i) {
    const auto& patch = patches[i];
    const auto& px = projected[i];
    // The apex after the patch's points; the fan from it to the border, large triangles, shared
    // among threads in smaller lots.
    FixedPixels f = fixed_pixels(px, o);
    const int apex_index = int(px.size());
    f.fits.push_back(fits(apex_px));
    f.px.push_back(fits(apex_px) ? fixed_px(apex_px, o) : cv::Point());
    std::vector<std::array<int, 3>> fan;
    fan.reserve(patch.border.size());
    for (const auto& e : patch.border) fan.push_back({apex_index, e[0], e[1]});
    cv::Mat mask(image.size(), CV_8U, cv::Scalar(0));
    const auto all = [](size_t) { return true; };
    fill_triangles(mask, patch.triangles, f, all);
    fill_triangles(mask, fan, f, all, 100);
    const cv::Scalar colour = leeway_bgr(palette, patch.leeway);
    paint(image, mask, colour, 75);
    cv::polylines(image, mask_outlines(mask), true,
                  cv::Scalar(colour[0], colour[1], colour[2], 200), 1, cv::LINE_AA, 4);
  }
  return picture;
}

}  // namespace crepuscular::overlay
