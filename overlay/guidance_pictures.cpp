// The anatomy layers' pictures (cones, entry, tumor), drawn on the CPU and kept, placed or drawn
// ahead while the patient board moves.
#include "overlay/guidance_drawing.hpp"

#include <cmath>
#include <future>
#include <limits>

#include "foundation/log.hpp"

namespace crepuscular::overlay {

namespace {

bool same_camera(const calibration::CameraModel& a, const calibration::CameraModel& b) {
  return a.width == b.width && a.height == b.height && a.fx == b.fx && a.fy == b.fy &&
         a.cx == b.cx && a.cy == b.cy && a.model == b.model && a.distortion == b.distortion;
}

// Whether going from pose `from` to pose `to` (T_cam_ct) moves no point of the box with these
// corners (CT) by more than tol_px in the image. The move of a point in the camera frame is
// largest at a corner (its length is convex over the box), the depth smallest and the off-axis
// slope |(x, y)| / z largest there too, and a move of d mm at depth z shifts the point's pixel by
// about f d (1 + slope) / z at most. False when the box reaches the camera plane.
bool moves_less_than(const Eigen::Isometry3d& from, const Eigen::Isometry3d& to,
                     const std::array<Eigen::Vector3d, 8>& corners,
                     const calibration::CameraModel& camera, double tol_px) {
  double move = 0, z_min = std::numeric_limits<double>::infinity(), slope = 0;
  for (const Eigen::Vector3d& p : corners) {
    const Eigen::Vector3d a = from * p, b = to * p;
    move = std::max(move, (a - b).norm());
    z_min = std::min({z_min, a.z(), b.z()});
    if (a.z() > 0) slope = std::max(slope, a.head<2>().norm() / a.z());
  }
  if (!(z_min > 1.0) || !std::isfinite(move)) return false;
  return std::max(camera.fx, camera.fy) * move * (1.0 + slope) / z_min <= tol_px;
}

// The anchors' projections (pixels); empty when one lies behind or within 1 mm of the camera
// plane, where no picture is placed.
std::vector<Eigen::Vector2d> project_anchors(const std::vector<Eigen::Vector3d>& anchors,
                                             const Eigen::Isometry3d& T_cam_ct,
                                             const calibration::CameraModel& camera) {
  std::vector<Eigen::Vector2d> px;
  px.reserve(anchors.size());
  for (const Eigen::Vector3d& a : anchors) {
    const Eigen::Vector3d p = T_cam_ct * a;
    if (!(p.z() > 1.0)) return {};
    px.push_back(camera.project(p));
    if (!px.back().allFinite()) return {};
  }
  return px;
}

// The affine map that carries `from` onto `to` best (least squares) and its largest error there,
// pixels; nullopt when the points do not determine one.
struct PlacedPictures {
  Eigen::Matrix<double, 2, 3> warp;
  double error_px = 0;
};

std::optional<PlacedPictures> fit_placement(const std::vector<Eigen::Vector2d>& from,
                                            const std::vector<Eigen::Vector2d>& to) {
  if (from.size() < 3 || from.size() != to.size()) return std::nullopt;
  Eigen::MatrixXd a(from.size(), 3);
  Eigen::MatrixXd b(from.size(), 2);
  for (size_t i = 0; i < from.size(); ++i) {
    a.row(Eigen::Index(i)) << from[i].x(), from[i].y(), 1.0;
    b.row(Eigen::Index(i)) = to[i].transpose();
  }
  const auto qr = a.colPivHouseholderQr();
  if (qr.rank() < 3) return std::nullopt;
  PlacedPictures placed;
  placed.warp = qr.solve(b).transpose();
  if (!placed.warp.allFinite() || std::abs(placed.warp.leftCols<2>().determinant()) < 1e-3) {
    return std::nullopt;
  }
  for (size_t i = 0; i < from.size(); ++i) {
    placed.error_px = std::max(
        placed.error_px, (placed.warp * from[i].homogeneous() - to[i]).norm());
  }
  return placed;
}

}  // namespace

const std::vector<GuidanceOverlay::Patch>& GuidanceOverlay::patches_shown(
    const PhaseShown& shown) const {
  return shown.phase >= 0 && size_t(shown.phase) < phase_patches_.size()
             ? phase_patches_[size_t(shown.phase)]
             : patches_;
}

Eigen::Vector3d GuidanceOverlay::cone_apex(const PhaseShown& shown) const {
  return shown.phase >= 0 && breathing_ ? breathing_->plans[size_t(shown.phase)]->tumor_centre
                                        : plan_.tumor_centre;
}

GuidanceOverlay::AnatomyPictures GuidanceOverlay::draw_pictures(
    const Eigen::Isometry3d& T_cam_ct, const calibration::CameraModel& cam,
    planning::Palette palette, std::array<bool, 3> layers, const PhaseShown& shown) const {
  AnatomyPictures pictures;
  pictures.valid = true;
  pictures.phase = shown.phase;
  pictures.tumor_shift = shown.tumor_shift;
  pictures.T_cam_ct = T_cam_ct;
  pictures.palette = palette;
  pictures.camera = cam;
  pictures.anchors_px = project_anchors(anatomy_anchors_, T_cam_ct, cam);
  if (layers[0] && !patches_shown(shown).empty()) {
    draw_picture(AnatomyPicture::kCones, pictures.cones, T_cam_ct, cam, palette, shown);
  }
  if (layers[1]) draw_picture(AnatomyPicture::kEntry, pictures.entry, T_cam_ct, cam, palette, shown);
  if (layers[2]) draw_picture(AnatomyPicture::kTumor, pictures.tumor, T_cam_ct, cam, palette, shown);
  return pictures;
}

void GuidanceOverlay::draw_picture(AnatomyPicture which, LayerPicture& picture,
                                   const Eigen::Isometry3d& T_cam_ct,
                                   const calibration::CameraModel& cam,
                                   planning::Palette palette,
                                   const PhaseShown& shown) const {
  Picture p;
  switch (which) {
    case AnatomyPicture::kCones:
      p = cone_image(patches_shown(shown), cone_apex(shown), T_cam_ct, cam, palette);
      break;
    case AnatomyPicture::kEntry:
      p = patch_image(patches_shown(shown), planned_, T_cam_ct, cam, palette);
      break;
    case AnatomyPicture::kTumor:
      p = tumor_image(tumor_surface_, tumor_voxel_mm_,
                      T_cam_ct * Eigen::Translation3d(shown.tumor_shift), cam, kTumorColour);
      break;
  }
  picture.bgra = p.bgra;
  picture.origin = p.origin;
  picture.revision = OverlayRenderer::new_image_revision();
  picture.drawn = true;
}

void GuidanceOverlay::draw_anatomy(OverlayRenderer& renderer, const Eigen::Isometry3d& T_cam_ct) {
  const auto palette = options_.palette;
  if (visible(GuidanceLayer::kVolume)) draw_volume(renderer, T_cam_ct);
  const calibration::CameraModel& cam = renderer.camera();
  const std::array<bool, 3> layers = {visible(GuidanceLayer::kRays), visible(GuidanceLayer::kEntry),
                                      visible(GuidanceLayer::kTumor)};
  const auto usable = [&](const AnatomyPictures& p) {
    return p.valid && p.palette == palette && same_camera(p.camera, cam) &&
           PhaseShown{p.phase, p.tumor_shift} == phase_shown_;
  };
  // Pictures drawn ahead for the last frame's pose replace the kept ones.
  if (anatomy_ahead_.valid()) {
    AnatomyPictures ahead = anatomy_ahead_.get();  // rethrows what the drawing threw
    if (usable(ahead)) {
      anatomy_ = std::move(ahead);
      ++anatomy_pictures_drawn_;
    }
  }
  // The kept pictures show the pose they were drawn for: as they are while the pose moves them by
  // less than the tolerance (and the palette and the camera stay), else placed by an affine map
  // whose error over the anatomy's box is within the tolerance, else drawn anew now.
  const double tol = options_.anatomy_reuse_px;
  const bool usable_now = tol > 0 && usable(anatomy_);
  const bool keep =
      usable_now && moves_less_than(anatomy_.T_cam_ct, T_cam_ct, anatomy_box_, cam, tol);
  std::optional<PlacedPictures> placed;
  if (usable_now && !keep && options_.anatomy_ahead && !anatomy_.anchors_px.empty()) {
    const std::vector<Eigen::Vector2d> now = project_anchors(anatomy_anchors_, T_cam_ct, cam);
    placed = fit_placement(anatomy_.anchors_px, now);
    if (placed && !(placed->error_px <= tol)) {
      spdlog::debug("guidance: anatomy pictures drawn anew: the best affine placement is off by "
                    "{:.2f} px", placed->error_px);
      placed.reset();
    }
  }
  if (!keep && !placed) {
    anatomy_ = draw_pictures(T_cam_ct, cam, palette, {false, false, false}, phase_shown_);
  }
  bool drew = false;
  const Eigen::Isometry3d T_drawn = anatomy_.T_cam_ct;
  const auto show = [&](const char* layer, LayerPicture& picture, AnatomyPicture which) {
    if (!picture.drawn) {  // drawn for the pictures' own pose, also when placed
      draw_picture(which, picture, T_drawn, cam, palette, PhaseShown{anatomy_.phase, anatomy_.tumor_shift});
      drew = true;
    }
    if (picture.bgra.empty()) return;
    if (placed) {
      renderer.add_layer_image_warped(layer, picture.bgra, picture.origin, placed->warp,
                                      picture.revision);
    } else {
      renderer.add_layer_image(layer, picture.bgra, picture.origin, picture.revision);
    }
  };
  if (layers[0]) {
    // One cone per safe region; the ray bundles where the plan has no area safety.
    if (patches_.empty()) {  // a plan without area safety (its phases have none either)
      add_rays(renderer, rays_, T_cam_ct, palette);
    } else {
      show("rays", anatomy_.cones, AnatomyPicture::kCones);
    }
  }
  if (layers[1]) show("entry", anatomy_.entry, AnatomyPicture::kEntry);
  if (layers[2]) {
    show("tumor", anatomy_.tumor, AnatomyPicture::kTumor);
    add_tumor_centre(renderer, tumor_centre_shown_, T_cam_ct, kTumorColour);
  }
  if (drew) {
    ++anatomy_pictures_drawn_;
    if (!keep && !placed) ++anatomy_pictures_waited_;
  }
  if (placed) ++anatomy_pictures_warped_;
  // The pictures shown were drawn for another pose: those for this one are drawn beside the next
  // frame's tracking, from the plan's geometry alone (the values captured here).
  if (placed && options_.anatomy_ahead) {
    anatomy_ahead_ = std::async(std::launch::async, [this, T_cam_ct, cam, palette, layers,
                                                     shown = phase_shown_] {
      return draw_pictures(T_cam_ct, cam, palette, layers, shown);
    });
  }
}

}  // namespace crepuscular::overlay
