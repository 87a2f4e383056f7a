// Layer 4 "tumor": the tumor seen through the skin, its outline, label and centre.
#include "overlay/guidance_drawing.hpp"

#include <cmath>

#include "overlay/targeting_view.hpp"

namespace crepuscular::overlay {

void GuidanceOverlay::build_tumor_surface() {
  const auto& tumor = plan_.tumor;
  if (tumor.empty()) return;
  const auto d = tumor.dims();
  tumor_voxel_mm_ = tumor.geometry().spacing.maxCoeff();
  auto in = [&](int64_t i, int64_t j, int64_t k) {
    return tumor.geometry().contains(i, j, k) && tumor(i, j, k) > 0;
  };
  for (int64_t k = 0; k < d[2]; ++k)
    for (int64_t j = 0; j < d[1]; ++j)
      for (int64_t i = 0; i < d[0]; ++i) {
        if (!in(i, j, k)) continue;
        if (in(i - 1, j, k) && in(i + 1, j, k) && in(i, j - 1, k) && in(i, j + 1, k) &&
            in(i, j, k - 1) && in(i, j, k + 1)) {
          continue;
        }
        tumor_surface_.push_back(tumor.index_to_physical(i, j, k));
      }
  // Thin out very large tumors: the outline needs a few thousand points at most.
  if (tumor_surface_.size() > 6000) {
    const size_t stride = tumor_surface_.size() / 6000 + 1;
    std::vector<Eigen::Vector3d> kept;
    for (size_t i = 0; i < tumor_surface_.size(); i += stride) kept.push_back(tumor_surface_[i]);
    tumor_voxel_mm_ *= std::cbrt(double(stride));
    tumor_surface_.swap(kept);
  }
}

// The tumor seen through the skin: its surface voxels (CT LPS mm, `voxel_mm` wide) projected as
// discs of their apparent size; their union filled translucently, outlined and labelled. The
// picture spans the part of the frame it covers.
Picture tumor_image(const std::vector<Eigen::Vector3d>& surface, double voxel_mm,
                    const Eigen::Isometry3d& T_cam_ct, const calibration::CameraModel& cam,
                    const cv::Scalar& colour) {
  std::vector<Eigen::Vector2d> pts;
  double radius_px = 1;
  for (const auto& p_ct : surface) {
    const Eigen::Vector3d p = T_cam_ct * p_ct;
    if (p.z() < 1.0) continue;
    const Eigen::Vector2d uv = cam.project(p);
    if (!fits(uv)) continue;
    pts.push_back(uv);
    radius_px = std::max(radius_px, 0.6 * cam.fx * voxel_mm / p.z());
  }
  const auto outlines = point_cloud_outlines(pts, radius_px);
  if (outlines.empty()) return {};
  std::vector<Eigen::Vector2d> all;
  int right = -1, top = 1 << 20;
  for (const auto& o : outlines) {
    for (const auto& q : o) {
      all.emplace_back(q.x, q.y);
      right = std::max(right, int(q.x));
      top = std::min(top, int(q.y));
    }
  }
  const cv::Point at(right + 8, std::max(16, top + 12));
  add_text_box(all, "TUMOR", at, 0.6, 4);
  // The outline is 2 px wide, smoothed.
  const cv::Rect roi = region_around(all, 4, cv::Size(cam.width, cam.height));
  if (roi.empty()) return {};
  const cv::Point o = roi.tl();
  Picture picture{cv::Mat(roi.size(), CV_8UC4, cv::Scalar(0, 0, 0, 0)), o};
  cv::Mat& image = picture.bgra;
  std::vector<std::vector<cv::Point>> polys;
  for (const auto& outline : outlines) {
    std::vector<cv::Point> p;
    for (const auto& q : outline) p.push_back(fixed_px(Eigen::Vector2d(q.x, q.y), o));
    polys.push_back(std::move(p));
  }
  cv::fillPoly(image, polys, cv::Scalar(colour[0], colour[1], colour[2], 110), cv::LINE_8, 4);
  cv::polylines(image, polys, true, cv::Scalar(colour[0], colour[1], colour[2], 255), 2,
                cv::LINE_AA, 4);
  const cv::Scalar dark(40, 40, 40, 220), label(colour[0], colour[1], colour[2], 255);
  cv::putText(image, "TUMOR", at - o, cv::FONT_HERSHEY_SIMPLEX, 0.6, dark, 4, cv::LINE_AA);
  cv::putText(image, "TUMOR", at - o, cv::FONT_HERSHEY_SIMPLEX, 0.6, label, 2, cv::LINE_AA);
  return picture;
}

// The tumor centre: a small cross in 3D, 8 mm across.
void add_tumor_centre(OverlayRenderer& renderer, const Eigen::Vector3d& centre,
                      const Eigen::Isometry3d& T_cam_ct, const cv::Scalar& colour) {
  for (int axis = 0; axis < 3; ++axis) {
    Polyline line;
    Eigen::Vector3d d = Eigen::Vector3d::Zero();
    d[axis] = 4.0;
    line.points_cam = {T_cam_ct * (centre - d), T_cam_ct * (centre + d)};
    line.colour = colour;
    line.width_px = 2;
    renderer.add_polyline("tumor", line);
  }
}

}  // namespace crepuscular::overlay
