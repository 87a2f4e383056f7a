// Drawing helpers shared by the guidance overlay's layers (guidance_*.cpp): colours, text panels,
// projected points in OpenCV's fixed point, triangle fills, and the record of renderer calls that
// lets a layer be drawn off the render thread. Internal to the overlay library.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>

#include "overlay/guidance.hpp"
#include "overlay/renderer.hpp"

namespace crepuscular::overlay {

cv::Scalar bgr(const std::array<uint8_t, 3>& rgb);

cv::Scalar class_bgr(planning::Palette palette, planning::SafetyClass c);

cv::Scalar safety_bgr(planning::Palette palette, planning::NeedleSafety s);

// Text panel helpers: lines of text on a translucent dark box, drawn into a BGRA image.
struct TextLine {
  std::string text;
  cv::Scalar colour{255, 255, 255};
  double scale = 0.55;
};

// A panel of text lines on a translucent dark box, as a BGRA image of its own size; its top-left
// corner in the frame goes to *origin (anchored at `at`, from below when anchor_bottom).
cv::Mat text_panel(const std::vector<TextLine>& lines, cv::Point at, bool anchor_bottom,
                   const cv::Size& frame, cv::Point* origin);

// A picture of a part of the frame: its pixels (BGRA) and where its top-left pixel lies in the
// frame. Empty: nothing to show.
struct Picture {
  cv::Mat bgra;
  cv::Point origin;
};

// Projected points of `points` (CT) with T_cam_ct; NaN for points behind the near plane.
std::vector<Eigen::Vector2d> project_all(const std::vector<Eigen::Vector3d>& points,
                                         const Eigen::Isometry3d& T_cam_ct,
                                         const calibration::CameraModel& camera);

bool fits(const Eigen::Vector2d& p);

// A pixel in fixed point (4 bits) for OpenCV's drawing, in an image whose top-left pixel lies at
// `origin` in the frame.
cv::Point fixed_px(const Eigen::Vector2d& p, const cv::Point& origin = cv::Point(0, 0));

// The frame's pixels within `pad` of the bounding box of the points that fits() (pixels); empty
// when there are none or the box misses the frame.
cv::Rect region_around(const std::vector<Eigen::Vector2d>& px, int pad, const cv::Size& frame);

// The corners of the box a text drawn at `at` (cv::putText's origin, frame pixels) covers, with
// its stroke.
void add_text_box(std::vector<Eigen::Vector2d>& px, const std::string& text, const cv::Point& at,
                  double scale, int thickness);

// The pixel of a CT point, nullopt behind the near plane or far outside the image.
std::optional<Eigen::Vector2d> pixel_of(const Eigen::Vector3d& p, const Eigen::Isometry3d& T_cam_ct,
                                        const calibration::CameraModel& camera);

// Fills a triangle (fixed point, 4 bits) into an 8-bit mask with 255, as cv::fillConvexPoly does,
// except when every pixel it can touch is 255 already and the fill would change nothing: the case
// of most of the small triangles of a dense mesh. cv::fillConvexPoly draws the edges between the
// vertices rounded to pixels and fills the rows between them, x rounded: it touches only the
// pixels between the rounded extremes of the vertices, (v + 8) >> 4.
void fill_triangle(cv::Mat& mask, const cv::Point tri[3]);

// Points projected for drawing: pixels in fixed point (fixed_px, for an image whose top-left
// pixel lies at `origin`), and whether each fits().
struct FixedPixels {
  std::vector<cv::Point> px;
  std::vector<uint8_t> fits;
};
FixedPixels fixed_pixels(const std::vector<Eigen::Vector2d>& px, const cv::Point& origin);

// Fills the triangles (vertex indices into f) for which keep(index) holds into the 8-bit mask with
// 255, from several threads when there are more than per_thread of them: each fills a share of
// them into a mask of its own and the masks are combined, which gives the same pixels (a fill only
// sets them to 255).
template <typename Keep>
void fill_triangles(cv::Mat& mask, const std::vector<std::array<int, 3>>& triangles,
                    const FixedPixels& f, const Keep& keep, size_t per_thread = 2000) {
  const auto fill_range = [&](cv::Mat& into, size_t from, size_t to) {
    for (size_t i = from; i < to; ++i) {
      const auto& t = triangles[i];
      if (!f.fits[size_t(t[0])] || !f.fits[size_t(t[1])] || !f.fits[size_t(t[2])] || !keep(i)) {
        continue;
      }
      const cv::Point tri[3] = {f.px[size_t(t[0])], f.px[size_t(t[1])], f.px[size_t(t[2])]};
      fill_triangle(into, tri);
    }
  };
  const size_t n = triangles.size();
  const int parts =
      int(std::min<size_t>(size_t(std::max(1, cv::getNumThreads())), n / per_thread + 1));
  if (parts <= 1) {
    fill_range(mask, 0, n);
    return;
  }
  std::vector<cv::Mat> masks(static_cast<size_t>(parts));
  cv::parallel_for_(cv::Range(0, parts), [&](const cv::Range& r) {
    for (int k = r.start; k < r.end; ++k) {
      cv::Mat& m = masks[size_t(k)];
      m = cv::Mat(mask.size(), CV_8U, cv::Scalar(0));
      fill_range(m, n * size_t(k) / size_t(parts), n * size_t(k + 1) / size_t(parts));
    }
  });
  for (const cv::Mat& m : masks) cv::bitwise_or(mask, m, mask);
}

// Paints `colour` at `alpha` (0..255) into the BGRA image where mask is set (over what is there).
void paint(cv::Mat& bgra, const cv::Mat& mask, const cv::Scalar& colour, double alpha);

cv::Scalar leeway_bgr(planning::Palette palette, double leeway);

// Outlines of the mask's regions, in fixed point (4 bits) for cv::polylines.
std::vector<std::vector<cv::Point>> mask_outlines(const cv::Mat& mask);

// The tumor's outline and centre (BGR magenta: no safety class uses it).
inline const cv::Scalar kTumorColour(255, 0, 255);

// One translucent cone per patch: from the patch (its whole surface) to `apex`, i.e. the patch and
// the triangles from the apex to its border, which together cover the cone's projection; a faint
// outline around it. The picture spans the part of the frame the cones cover.
Picture cone_image(const std::vector<GuidanceOverlay::Patch>& patches, const Eigen::Vector3d& apex,
                   const Eigen::Isometry3d& T_cam_ct, const calibration::CameraModel& camera,
                   planning::Palette palette);

// The entry patches facing the camera, translucent, each outlined with a width (2-8 px) and colour
// that show its leeway, and the planned trajectory over them (when there is one). The picture
// spans the part of the frame they cover.
Picture patch_image(const std::vector<GuidanceOverlay::Patch>& patches,
                    const std::optional<planning::RegionTrajectory>& planned,
                    const Eigen::Isometry3d& T_cam_ct, const calibration::CameraModel& camera,
                    planning::Palette palette);

// The tumor seen through the skin: its surface voxels (CT LPS mm, `voxel_mm` wide) projected as
// discs of their apparent size; their union filled translucently, outlined and labelled. The
// picture spans the part of the frame it covers.
Picture tumor_image(const std::vector<Eigen::Vector3d>& surface, double voxel_mm,
                    const Eigen::Isometry3d& T_cam_ct, const calibration::CameraModel& cam,
                    const cv::Scalar& colour);

// The safe ray bundles (plans without area safety), layer "rays".
void add_rays(OverlayRenderer& renderer, const std::vector<GuidanceOverlay::Ray>& rays,
              const Eigen::Isometry3d& T_cam_ct, planning::Palette palette);

// The tumor centre: a small cross in 3D, 8 mm across.
void add_tumor_centre(OverlayRenderer& renderer, const Eigen::Vector3d& centre,
                      const Eigen::Isometry3d& T_cam_ct, const cv::Scalar& colour);

// What a drawing adds to the renderer, recorded (in order) off the render thread and added on
// it: the renderer's GL state belongs to one thread.
class LayerCalls {
 public:
  explicit LayerCalls(const calibration::CameraModel& camera) : camera_(&camera) {}
  void add_polyline(const std::string& layer, const Polyline& polyline) {
    calls_.push_back([layer, polyline](OverlayRenderer& r) { r.add_polyline(layer, polyline); });
  }
  void add_layer_image(const std::string& layer, const cv::Mat& bgra, const cv::Point& origin,
                       uint64_t revision = 0) {
    calls_.push_back([layer, bgra, origin, revision](OverlayRenderer& r) {
      r.add_layer_image(layer, bgra, origin, revision);
    });
  }
  const calibration::CameraModel& camera() const { return *camera_; }
  void replay(OverlayRenderer& renderer) const {
    for (const auto& call : calls_) call(renderer);
  }

 private:
  const calibration::CameraModel* camera_;
  std::vector<std::function<void(OverlayRenderer&)>> calls_;
};

}  // namespace crepuscular::overlay
