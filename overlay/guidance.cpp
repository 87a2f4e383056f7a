#include "overlay/guidance.hpp"

#include <algorithm>
#include <functional>
#include <future>
#include <chrono>
#include <filesystem>
#include <limits>
#include <cmath>
#include <map>
#include <set>

#include <fmt/format.h>
#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "overlay/renderer.hpp"
#include "overlay/targeting_view.hpp"
#include "overlay/volume_rendering.hpp"
#include "planning/imaging/ray_march.hpp"
#include "planning/safety/unknown.hpp"
#include "planning/imaging/sampling.hpp"

namespace crepuscular::overlay {

namespace {

constexpr std::array<const char*, kGuidanceLayerCount> kLayerNames = {
    "rays", "volume", "entry", "tumor", "needle", "status", "target"};

cv::Scalar bgr(const std::array<uint8_t, 3>& rgb) { return cv::Scalar(rgb[2], rgb[1], rgb[0]); }

cv::Scalar class_bgr(planning::Palette palette, planning::SafetyClass c) {
  return bgr(planning::class_colours(palette)[static_cast<size_t>(c)]);
}

cv::Scalar safety_bgr(planning::Palette palette, planning::NeedleSafety s) {
  switch (s) {
    case planning::NeedleSafety::kSafe: return class_bgr(palette, planning::SafetyClass::kSafe);
    case planning::NeedleSafety::kMedium: return class_bgr(palette, planning::SafetyClass::kMedium);
    case planning::NeedleSafety::kDangerous: break;
    case planning::NeedleSafety::kUnknown: return cv::Scalar(170, 170, 170);  // grey: not known
  }
  return class_bgr(palette, planning::SafetyClass::kDangerous);
}

// Text panel helpers: lines of text on a translucent dark box, drawn into a BGRA image.
struct TextLine {
  std::string text;
  cv::Scalar colour{255, 255, 255};
  double scale = 0.55;
};

// A panel of text lines on a translucent dark box, as a BGRA image of its own size; its top-left
// corner in the frame goes to *origin (anchored at `at`, from below when anchor_bottom).
cv::Mat text_panel(const std::vector<TextLine>& lines, cv::Point at, bool anchor_bottom,
                   const cv::Size& frame, cv::Point* origin) {
  const int font = cv::FONT_HERSHEY_SIMPLEX;
  int width = 0, height = 8;
  std::vector<int> heights;
  for (const auto& l : lines) {
    int base = 0;
    const cv::Size s = cv::getTextSize(l.text, font, l.scale, 1, &base);
    width = std::max(width, s.width);
    heights.push_back(s.height + base + 6);
    height += heights.back();
  }
  cv::Rect box(at.x, anchor_bottom ? at.y - height : at.y, width + 16, height);
  box &= cv::Rect(0, 0, frame.width, frame.height);
  if (lines.empty() || box.empty()) return {};
  cv::Mat panel(box.size(), CV_8UC4, cv::Scalar(20, 20, 20, 170));
  int y = 4;
  for (size_t i = 0; i < lines.size(); ++i) {
    y += heights[i];
    // Coloured text lightened 40 % toward white: a class's red or blue keeps its hue but stands
    // out from the dark box as white text does.
    const cv::Scalar c = lines[i].colour;
    const auto light = [](double v) { return v + 0.4 * (255.0 - v); };
    cv::putText(panel, lines[i].text, cv::Point(8, y - 6), font, lines[i].scale,
                cv::Scalar(light(c[0]), light(c[1]), light(c[2]), 255), 1, cv::LINE_AA);
  }
  *origin = box.tl();
  return panel;
}

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

}  // namespace

const char* guidance_layer_name(GuidanceLayer layer) { return kLayerNames[size_t(layer)]; }

GuidanceLayer parse_guidance_layer(const std::string& text) {
  for (int i = 0; i < kGuidanceLayerCount; ++i) {
    if (text == kLayerNames[size_t(i)] || text == std::to_string(i + 1)) {
      return static_cast<GuidanceLayer>(i);
    }
  }
  throw Error("unknown overlay layer '" + text +
              "', expected rays, volume, entry, tumor, needle, status or target (or 1-7)");
}

std::vector<std::string> needle_text(const planning::NeedleState& s) {
  std::vector<std::string> out;
  for (const auto& hit : s.evaluation.structures) {
    if (hit.blocking_per_mm <= 0) continue;
    out.push_back(fmt::format("{} ({}) at {:.0f} mm, {:.1f} mm long", hit.name,
                              hit.level_name.empty() ? "?" : hit.level_name, hit.depth_mm,
                              hit.length_mm));
  }
  return out;
}

GuidanceOverlay::GuidanceOverlay(const planning::PlanData& plan, GuidanceSetup setup,
                                 GuidanceOptions options)
    : plan_(plan), setup_(std::move(setup)), options_(std::move(options)) {
  if (plan_.values.empty() || plan_.path_safety.empty()) {
    throw Error(plan_.dir + "/plan.json: the plan has no path safety volume to guide with");
  }
  value_ = options_.value.empty() ? plan_.values.front() : options_.value;
  if (!plan_.path_safety.count(value_) || !plan_.classes.count(value_)) {
    throw Error(plan_.dir + "/plan.json: no path safety volume '" + value_ + "' in the plan");
  }
  if (!(setup_.axis_in_needle.norm() > 0)) throw Error("guidance: the needle axis is zero");
  setup_.axis_in_needle.normalize();
  if (options_.ray_directions < 1 || options_.ray_directions > 200000) {
    throw Error("guidance: ray directions must be 1 to 200000");
  }
  guide_ = std::make_unique<planning::NeedleGuide>(plan_);
  build_tumor_surface();
  build_rays();
  build_entry_contours();
  build_entry_patches();
  if (plan_.area) {
    const auto planned = planning::region_trajectories(*plan_.area, plan_.tumor_centre,
                                                       plan_.labels, plan_.path_safety.at(value_),
                                                       plan_.radius_mm);
    if (!planned.empty()) planned_ = planned.front();
  }
  // The box around everything the anatomy pictures show (the ring of the planned entry: 5 mm).
  Eigen::AlignedBox3d box(plan_.tumor_centre);
  for (const auto& p : tumor_surface_) box.extend(p);
  for (const Patch& patch : patches_)
    for (const auto& p : patch.points) box.extend(p);
  if (planned_) {
    box.extend(planned_->entry);
    box.extend(planned_->target);
  }
  box.min() -= Eigen::Vector3d::Constant(std::max(5.0, tumor_voxel_mm_));
  box.max() += Eigen::Vector3d::Constant(std::max(5.0, tumor_voxel_mm_));
  for (int i = 0; i < 8; ++i) {
    anatomy_box_[size_t(i)] = box.corner(static_cast<Eigen::AlignedBox3d::CornerType>(i));
  }
  // Points of everything the pictures show, for the placed pictures' error: patch points, cone
  // lines half-way to the tumor, tumor surface points, the planned trajectory (about 150 in all).
  const auto every = [](size_t n, size_t want) { return std::max<size_t>(1, n / want); };
  size_t patch_points = 0;
  for (const Patch& patch : patches_) patch_points += patch.points.size();
  anatomy_anchors_.push_back(plan_.tumor_centre);
  for (const Patch& patch : patches_) {
    const size_t step = every(patch_points, 60);
    for (size_t i = 0; i < patch.points.size(); i += step) {
      anatomy_anchors_.push_back(patch.points[i]);
      anatomy_anchors_.push_back(0.5 * (patch.points[i] + plan_.tumor_centre));
    }
  }
  for (size_t i = 0; i < tumor_surface_.size(); i += every(tumor_surface_.size(), 30)) {
    anatomy_anchors_.push_back(tumor_surface_[i]);
  }
  if (planned_) {
    anatomy_anchors_.push_back(planned_->entry);
    anatomy_anchors_.push_back(planned_->target);
  }
  // A plan without these still gets a placement only where its box moves as one.
  if (anatomy_anchors_.size() < 8) {
    anatomy_anchors_.insert(anatomy_anchors_.end(), anatomy_box_.begin(), anatomy_box_.end());
  }
  spdlog::info("guidance: {} safe or medium rays of {} ({} not drawn: they reach the unknown "
               "outside the scan), {} entry contours, {} tumor surface points",
               rays_.size(), options_.ray_directions, unknown_rays_, contours_.size(),
               tumor_surface_.size());
}

GuidanceOverlay::~GuidanceOverlay() = default;

void GuidanceOverlay::set_visible(GuidanceLayer layer, bool visible) {
  options_.visible[size_t(layer)] = visible;
}
bool GuidanceOverlay::visible(GuidanceLayer layer) const {
  return options_.visible[size_t(layer)];
}
void GuidanceOverlay::set_palette(planning::Palette palette) {
  options_.palette = palette;
  if (volume_) {
    VolumeRenderingOptions vo = volume_->options();
    vo.palette = palette;
    volume_->set_options(vo);
  }
}

bool GuidanceOverlay::inside_body(const Eigen::Vector3d& p) const {
  return planning::in_body(plan_.labels, p);
}

std::optional<Eigen::Vector3d> GuidanceOverlay::skin_exit(const Eigen::Vector3d& from,
                                                          const Eigen::Vector3d& dir) const {
  const double step = 0.5 * plan_.grid.spacing.minCoeff();
  const double reach = plan_.radius_mm > 0 ? plan_.radius_mm : 200.0;
  if (plan_.labels.empty()) return from + dir * reach;  // no body outline: the region's edge
  const Eigen::Vector3d& centre = plan_.tumor_centre;
  // None when still inside the body at the region's edge.
  const auto exit = planning::first_body_exit(
      plan_.labels, from, dir, step, 2 * reach,
      [&](const Eigen::Vector3d& p) { return (p - centre).norm() <= reach; });
  if (!exit) return std::nullopt;
  return exit->last_inside;
}

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

void GuidanceOverlay::build_entry_contours() {
  if (!plan_.area) return;
  const planning::AreaSafetyGeometry& g = *plan_.area;
  const double fallback = g.max_distance_mm > 0 ? g.max_distance_mm : 50.0;
  // Marching triangles on the region id: a contour point at the middle of every edge between a
  // vertex of region r and one outside it; each triangle with such edges gives a segment.
  for (const auto& region : g.regions) {
    const int r = region.id;
    using Key = std::pair<int, int>;
    std::vector<std::array<Key, 2>> segments;
    for (const auto& tri : g.triangles) {
      std::vector<Key> crossing;
      for (int e = 0; e < 3; ++e) {
        const int a = tri[size_t(e)], b = tri[size_t((e + 1) % 3)];
        if ((g.region[size_t(a)] == r) != (g.region[size_t(b)] == r)) {
          crossing.emplace_back(std::min(a, b), std::max(a, b));
        }
      }
      if (crossing.size() == 2) segments.push_back({crossing[0], crossing[1]});
    }
    if (segments.empty()) continue;
    // Chain segments that share an edge point into polylines.
    std::map<Key, std::vector<size_t>> by_point;
    for (size_t s = 0; s < segments.size(); ++s)
      for (const Key& k : segments[s]) by_point[k].push_back(s);
    std::vector<bool> used(segments.size(), false);
    std::map<Key, Eigen::Vector3d> skin;
    auto skin_point = [&](const Key& k) {
      auto it = skin.find(k);
      if (it != skin.end()) return it->second;
      const Eigen::Vector3d base = 0.5 * (g.base[size_t(k.first)] + g.base[size_t(k.second)]);
      const Eigen::Vector3d n =
          (g.normals[size_t(k.first)] + g.normals[size_t(k.second)]).normalized();
      const Eigen::Vector3d p = skin_exit(base, n).value_or(base + fallback * n);
      skin.emplace(k, p);
      return p;
    };
    for (size_t s0 = 0; s0 < segments.size(); ++s0) {
      if (used[s0]) continue;
      used[s0] = true;
      std::vector<Key> chain = {segments[s0][0], segments[s0][1]};
      // Extend forward from the back, then backward from the front.
      for (int direction = 0; direction < 2; ++direction) {
        while (true) {
          const Key end = direction == 0 ? chain.back() : chain.front();
          size_t next = segments.size();
          for (size_t s : by_point[end])
            if (!used[s]) next = s;
          if (next == segments.size()) break;
          used[next] = true;
          const Key other = segments[next][0] == end ? segments[next][1] : segments[next][0];
          if (direction == 0) {
            chain.push_back(other);
          } else {
            chain.insert(chain.begin(), other);
          }
        }
      }
      Contour c;
      c.region = r;
      c.leeway = region.leeway;
      c.closed = chain.size() > 2 && chain.front() == chain.back();
      if (c.closed) chain.pop_back();
      for (const Key& k : chain) c.points.push_back(skin_point(k));
      if (c.points.size() >= 2) contours_.push_back(std::move(c));
    }
  }
}

void GuidanceOverlay::build_entry_patches() {
  if (!plan_.area) return;
  const planning::AreaSafetyGeometry& g = *plan_.area;
  for (const auto& region : g.regions) {
    Patch patch;
    patch.region = region.id;
    patch.leeway = std::clamp(region.leeway, 0.0, 1.0);
    std::map<int, int> index;  // mesh vertex -> patch point (-1: no skin in the scan)
    auto point = [&](int vertex) {
      auto it = index.find(vertex);
      if (it != index.end()) return it->second;
      int i = -1;
      if (g.region[size_t(vertex)] == region.id) {
        if (auto p = skin_exit(g.base[size_t(vertex)], g.normals[size_t(vertex)])) {
          i = int(patch.points.size());
          patch.points.push_back(*p);
        }
      }
      index.emplace(vertex, i);
      return i;
    };
    std::map<std::pair<int, int>, int> edges;  // how many triangles share an edge
    for (const auto& tri : g.triangles) {
      const std::array<int, 3> t = {point(tri[0]), point(tri[1]), point(tri[2])};
      if (t[0] < 0 || t[1] < 0 || t[2] < 0) continue;
      patch.triangles.push_back(t);
      for (int e = 0; e < 3; ++e) {
        const int a = t[size_t(e)], b = t[size_t((e + 1) % 3)];
        ++edges[{std::min(a, b), std::max(a, b)}];
      }
    }
    for (const auto& [edge, count] : edges) {
      if (count == 1) patch.border.push_back({edge.first, edge.second});
    }
    if (!patch.triangles.empty()) patches_.push_back(std::move(patch));
  }
}

std::optional<Eigen::Vector3d> GuidanceOverlay::needle_skin_entry(
    const planning::NeedleState& s) const {
  if (s.points_away) return std::nullopt;
  if (s.tip_in_body) return s.line_start;
  return planning::body_entry_along(plan_.labels, s.tip, s.axis, s.along_axis_mm);
}

namespace {

// Projected points of `points` (CT) with T_cam_ct; NaN for points behind the near plane.
std::vector<Eigen::Vector2d> project_all(const std::vector<Eigen::Vector3d>& points,
                                         const Eigen::Isometry3d& T_cam_ct,
                                         const calibration::CameraModel& camera) {
  std::vector<Eigen::Vector2d> px;
  px.reserve(points.size());
  for (const auto& p : points) {
    const Eigen::Vector3d q = T_cam_ct * p;
    px.push_back(q.z() > 1.0 ? camera.project(q)
                             : Eigen::Vector2d::Constant(std::numeric_limits<double>::quiet_NaN()));
  }
  return px;
}

bool fits(const Eigen::Vector2d& p) { return p.allFinite() && p.cwiseAbs().maxCoeff() < 1e5; }

// A pixel in fixed point (4 bits) for OpenCV's drawing, in an image whose top-left pixel lies at
// `origin` in the frame.
cv::Point fixed_px(const Eigen::Vector2d& p, const cv::Point& origin = cv::Point(0, 0)) {
  return cv::Point(int(std::lround(p.x() * 16)) - 16 * origin.x,
                   int(std::lround(p.y() * 16)) - 16 * origin.y);
}

// A picture of a part of the frame: its pixels (BGRA) and where its top-left pixel lies in the
// frame. Empty: nothing to show.
struct Picture {
  cv::Mat bgra;
  cv::Point origin;
};

// The tumor's outline and centre (BGR magenta: no safety class uses it).
const cv::Scalar kTumorColour(255, 0, 255);

// The frame's pixels within `pad` of the bounding box of the points that fits() (pixels); empty
// when there are none or the box misses the frame.
cv::Rect region_around(const std::vector<Eigen::Vector2d>& px, int pad, const cv::Size& frame) {
  double x0 = std::numeric_limits<double>::infinity(), y0 = x0, x1 = -x0, y1 = -x0;
  for (const auto& p : px) {
    if (!fits(p)) continue;
    x0 = std::min(x0, p.x()), y0 = std::min(y0, p.y());
    x1 = std::max(x1, p.x()), y1 = std::max(y1, p.y());
  }
  if (!(x0 <= x1)) return {};
  const cv::Rect box(cv::Point(int(std::floor(x0)) - pad, int(std::floor(y0)) - pad),
                     cv::Point(int(std::ceil(x1)) + pad + 1, int(std::ceil(y1)) + pad + 1));
  return box & cv::Rect(cv::Point(0, 0), frame);
}

// The corners of the box a text drawn at `at` (cv::putText's origin, frame pixels) covers, with
// its stroke.
void add_text_box(std::vector<Eigen::Vector2d>& px, const std::string& text, const cv::Point& at,
                  double scale, int thickness) {
  int base = 0;
  const cv::Size size = cv::getTextSize(text, cv::FONT_HERSHEY_SIMPLEX, scale, thickness, &base);
  px.emplace_back(at.x - thickness, at.y - size.height - thickness);
  px.emplace_back(at.x + size.width + thickness, at.y + base + thickness);
}

// Fills a triangle (fixed point, 4 bits) into an 8-bit mask with 255, as cv::fillConvexPoly does,
// except when every pixel it can touch is 255 already and the fill would change nothing: the case
// of most of the small triangles of a dense mesh. cv::fillConvexPoly draws the edges between the
// vertices rounded to pixels and fills the rows between them, x rounded: it touches only the
// pixels between the rounded extremes of the vertices, (v + 8) >> 4.
void fill_triangle(cv::Mat& mask, const cv::Point tri[3]) {
  const int x0 = std::max(0, (std::min({tri[0].x, tri[1].x, tri[2].x}) + 8) >> 4);
  const int x1 = std::min(mask.cols - 1, (std::max({tri[0].x, tri[1].x, tri[2].x}) + 8) >> 4);
  const int y0 = std::max(0, (std::min({tri[0].y, tri[1].y, tri[2].y}) + 8) >> 4);
  const int y1 = std::min(mask.rows - 1, (std::max({tri[0].y, tri[1].y, tri[2].y}) + 8) >> 4);
  if (x0 > x1 || y0 > y1) return;  // wholly outside the mask
  if ((x1 - x0 + 1) * (y1 - y0 + 1) <= 64) {
    bool full = true;
    for (int y = y0; y <= y1 && full; ++y) {
      const uint8_t* row = mask.ptr<uint8_t>(y);
      for (int x = x0; x <= x1; ++x) {
        if (row[x] != 255) {
          full = false;
          break;
        }
      }
    }
    if (full) return;
  }
  cv::fillConvexPoly(mask, tri, 3, cv::Scalar(255), cv::LINE_8, 4);
}

// Points projected for drawing: pixels in fixed point (fixed_px, for an image whose top-left
// pixel lies at `origin`), and whether each fits().
struct FixedPixels {
  std::vector<cv::Point> px;
  std::vector<uint8_t> fits;
};
FixedPixels fixed_pixels(const std::vector<Eigen::Vector2d>& px, const cv::Point& origin) {
  FixedPixels f;
  f.px.reserve(px.size());
  f.fits.reserve(px.size());
  for (const auto& p : px) {
    const bool ok = fits(p);
    f.fits.push_back(ok);
    f.px.push_back(ok ? fixed_px(p, origin) : cv::Point());
  }
  return f;
}

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

// Fills the patch's triangles that face the camera (their outward side: the mesh's triangles are
// outward, seen counter-clockwise from outside) into mask, whose top-left pixel lies at `origin`
// in the frame.
void fill_front_triangles(cv::Mat& mask, const GuidanceOverlay::Patch& patch,
                          const Eigen::Isometry3d& T_cam_ct, const calibration::CameraModel& camera,
                          const cv::Point& origin = cv::Point(0, 0)) {
  std::vector<Eigen::Vector3d> cam;
  cam.reserve(patch.points.size());
  for (const auto& p : patch.points) cam.push_back(T_cam_ct * p);
  const FixedPixels f = fixed_pixels(project_all(patch.points, T_cam_ct, camera), origin);
  fill_triangles(mask, patch.triangles, f, [&](size_t i) {
    const auto& t = patch.triangles[i];
    const Eigen::Vector3d& a = cam[size_t(t[0])];
    const Eigen::Vector3d& b = cam[size_t(t[1])];
    const Eigen::Vector3d& c = cam[size_t(t[2])];
    return (b - a).cross(c - a).dot(a) < 0;  // faces the camera
  });
}

// Paints `colour` at `alpha` (0..255) into the BGRA image where mask is set (over what is there).
void paint(cv::Mat& bgra, const cv::Mat& mask, const cv::Scalar& colour, double alpha) {
  bgra.setTo(cv::Scalar(colour[0], colour[1], colour[2], alpha), mask);
}

}  // namespace

cv::Mat GuidanceOverlay::entry_patch_mask(const Eigen::Isometry3d& T_cam_ct,
                                          const calibration::CameraModel& camera,
                                          int region) const {
  cv::Mat mask(camera.height, camera.width, CV_8U, cv::Scalar(0));
  for (const Patch& p : patches_) {
    if (region < 0 || p.region == region) fill_front_triangles(mask, p, T_cam_ct, camera);
  }
  return mask;
}

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

cv::Scalar leeway_bgr(planning::Palette palette, double leeway) {
  // Every entry area is safe: its leeway runs from the medium colour (a small region) to the safe
  // colour (the largest).
  return bgr(planning::leeway_colour(palette, 0.5 + 0.5 * std::clamp(leeway, 0.0, 1.0)));
}

// Outlines of the mask's regions, in fixed point (4 bits) for cv::polylines.
std::vector<std::vector<cv::Point>> mask_outlines(const cv::Mat& mask) {
  std::vector<std::vector<cv::Point>> outlines;
  cv::findContours(mask.clone(), outlines, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_SIMPLE);
  for (auto& o : outlines)
    for (auto& q : o) q = cv::Point(q.x * 16 + 8, q.y * 16 + 8);  // centres of the pixels
  return outlines;
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

// The planned trajectory's drawing: dashes of 5 mm from the entry to the target, a ring of 5 mm
// radius at the entry (CT points: segments and the ring's points) and its label's position.
struct PlannedMarks {
  std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3d>> dashes;
  std::vector<Eigen::Vector3d> ring;
};
PlannedMarks planned_marks(const planning::RegionTrajectory& plan) {
  PlannedMarks m;
  const Eigen::Vector3d d = plan.target - plan.entry;
  const double length = d.norm();
  if (!(length > 1e-6)) return m;
  const Eigen::Vector3d u = d / length;
  for (double s = 0; s < length; s += 10.0) {
    m.dashes.emplace_back(plan.entry + s * u, plan.entry + std::min(s + 5.0, length) * u);
  }
  const Eigen::Vector3d e1 = u.unitOrthogonal(), e2 = u.cross(e1);
  for (int k = 0; k < 48; ++k) {
    const double t = 2 * M_PI * k / 48;
    m.ring.push_back(plan.entry + 5.0 * (std::cos(t) * e1 + std::sin(t) * e2));
  }
  return m;
}

// The pixel of a CT point, nullopt behind the near plane or far outside the image.
std::optional<Eigen::Vector2d> pixel_of(const Eigen::Vector3d& p, const Eigen::Isometry3d& T_cam_ct,
                                        const calibration::CameraModel& camera) {
  const Eigen::Vector3d q = T_cam_ct * p;
  if (q.z() <= 1.0) return std::nullopt;
  const Eigen::Vector2d x = camera.project(q);
  if (!fits(x)) return std::nullopt;
  return x;
}

// Where the planned entry's label goes (cv::putText's origin, frame pixels).
cv::Point planned_label_at(const Eigen::Vector2d& entry_px) {
  const cv::Point q = fixed_px(entry_px);
  return cv::Point(q.x / 16 + 12, q.y / 16 - 10);
}

// The planned trajectory into a BGRA image whose top-left pixel lies at `origin` in the frame:
// dashes of 5 mm from the entry to the target (white with a dark edge, so it reads on any skin), a
// ring of 5 mm radius at the entry and its label.
void draw_planned(cv::Mat& image, const cv::Point& origin, const planning::RegionTrajectory& plan,
                  const Eigen::Isometry3d& T_cam_ct, const calibration::CameraModel& camera) {
  const PlannedMarks marks = planned_marks(plan);
  auto px = [&](const Eigen::Vector3d& p) -> std::optional<cv::Point> {
    if (auto x = pixel_of(p, T_cam_ct, camera)) return fixed_px(*x, origin);
    return std::nullopt;
  };
  const cv::Scalar white(255, 255, 255, 255), dark(40, 40, 40, 220);
  for (const auto& [from, to] : marks.dashes) {
    const auto a = px(from), b = px(to);
    if (!a || !b) continue;
    cv::line(image, *a, *b, dark, 5, cv::LINE_AA, 4);
    cv::line(image, *a, *b, white, 2, cv::LINE_AA, 4);
  }
  std::vector<cv::Point> ring;
  for (const auto& p : marks.ring) {
    if (auto q = px(p)) ring.push_back(*q);
  }
  if (!marks.ring.empty() && ring.size() == marks.ring.size()) {
    cv::polylines(image, std::vector<std::vector<cv::Point>>{ring}, true, dark, 5, cv::LINE_AA, 4);
    cv::polylines(image, std::vector<std::vector<cv::Point>>{ring}, true, white, 2, cv::LINE_AA, 4);
  }
  if (marks.dashes.empty()) return;
  if (auto q = pixel_of(plan.entry, T_cam_ct, camera)) {
    const cv::Point at = planned_label_at(*q) - origin;
    cv::putText(image, "PLANNED ENTRY", at, cv::FONT_HERSHEY_SIMPLEX, 0.5, dark, 4, cv::LINE_AA);
    cv::putText(image, "PLANNED ENTRY", at, cv::FONT_HERSHEY_SIMPLEX, 0.5, white, 1, cv::LINE_AA);
  }
}

// The entry patches facing the camera, translucent, each outlined with a width (2-8 px) and colour
// that show its leeway, and the planned trajectory over them (when there is one). The picture
// spans the part of the frame they cover.
Picture patch_image(const std::vector<GuidanceOverlay::Patch>& patches,
                    const std::optional<planning::RegionTrajectory>& planned,
                    const Eigen::Isometry3d& T_cam_ct, const calibration::CameraModel& camera,
                    planning::Palette palette) {
  std::vector<Eigen::Vector2d> all;
  for (const auto& patch : patches) {
    const auto px = project_all(patch.points, T_cam_ct, camera);
    all.insert(all.end(), px.begin(), px.end());
  }
  if (planned) {
    const PlannedMarks marks = planned_marks(*planned);
    for (const auto& [from, to] : marks.dashes) {
      for (const auto& p : {from, to}) {
        if (auto x = pixel_of(p, T_cam_ct, camera)) all.push_back(*x);
      }
    }
    for (const auto& p : marks.ring) {
      if (auto x = pixel_of(p, T_cam_ct, camera)) all.push_back(*x);
    }
    if (auto q = pixel_of(planned->entry, T_cam_ct, camera)) {
      add_text_box(all, "PLANNED ENTRY", planned_label_at(*q), 0.5, 4);
    }
  }
  // Outlines up to 8 px wide, dashes 5 px, smoothed: 10 px around the shapes hold them.
  const cv::Rect roi = region_around(all, 10, cv::Size(camera.width, camera.height));
  if (roi.empty()) return {};
  const cv::Point o = roi.tl();
  Picture picture{cv::Mat(roi.size(), CV_8UC4, cv::Scalar(0, 0, 0, 0)), o};
  cv::Mat& image = picture.bgra;
  for (const auto& patch : patches) {
    cv::Mat mask(image.size(), CV_8U, cv::Scalar(0));
    for (const auto& p : patches) {
      if (p.region == patch.region) fill_front_triangles(mask, p, T_cam_ct, camera, o);
    }
    const cv::Scalar colour = leeway_bgr(palette, patch.leeway);
    paint(image, mask, colour, 110);
    const int width = int(std::lround(2.0 + 6.0 * patch.leeway));
    cv::polylines(image, mask_outlines(mask), true,
                  cv::Scalar(colour[0], colour[1], colour[2], 235), width, cv::LINE_AA, 4);
  }
  if (planned) draw_planned(image, o, *planned, T_cam_ct, camera);
  return picture;
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

GuidanceOverlay::AnatomyPictures GuidanceOverlay::draw_pictures(
    const Eigen::Isometry3d& T_cam_ct, const calibration::CameraModel& cam,
    planning::Palette palette, std::array<bool, 3> layers) const {
  AnatomyPictures pictures;
  pictures.valid = true;
  pictures.T_cam_ct = T_cam_ct;
  pictures.palette = palette;
  pictures.camera = cam;
  pictures.anchors_px = project_anchors(anatomy_anchors_, T_cam_ct, cam);
  if (layers[0] && !patches_.empty()) {
    draw_picture(AnatomyPicture::kCones, pictures.cones, T_cam_ct, cam, palette);
  }
  if (layers[1]) draw_picture(AnatomyPicture::kEntry, pictures.entry, T_cam_ct, cam, palette);
  if (layers[2]) draw_picture(AnatomyPicture::kTumor, pictures.tumor, T_cam_ct, cam, palette);
  return pictures;
}

void GuidanceOverlay::draw_picture(AnatomyPicture which, LayerPicture& picture,
                                   const Eigen::Isometry3d& T_cam_ct,
                                   const calibration::CameraModel& cam,
                                   planning::Palette palette) const {
  Picture p;
  switch (which) {
    case AnatomyPicture::kCones:
      p = cone_image(patches_, plan_.tumor_centre, T_cam_ct, cam, palette);
      break;
    case AnatomyPicture::kEntry:
      p = patch_image(patches_, planned_, T_cam_ct, cam, palette);
      break;
    case AnatomyPicture::kTumor:
      p = tumor_image(tumor_surface_, tumor_voxel_mm_, T_cam_ct, cam, kTumorColour);
      break;
  }
  picture.bgra = p.bgra;
  picture.origin = p.origin;
  picture.revision = OverlayRenderer::new_image_revision();
  picture.drawn = true;
}

void GuidanceOverlay::draw_anatomy(OverlayRenderer& renderer, const Eigen::Isometry3d& T_cam_ct) {
  const auto palette = options_.palette;
  if (visible(GuidanceLayer::kVolume)) {
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
  const calibration::CameraModel& cam = renderer.camera();
  const std::array<bool, 3> layers = {visible(GuidanceLayer::kRays), visible(GuidanceLayer::kEntry),
                                      visible(GuidanceLayer::kTumor)};
  const auto usable = [&](const AnatomyPictures& p) {
    return p.valid && p.palette == palette && same_camera(p.camera, cam);
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
    anatomy_ = draw_pictures(T_cam_ct, cam, palette, {false, false, false});
  }
  bool drew = false;
  const Eigen::Isometry3d T_drawn = anatomy_.T_cam_ct;
  const auto show = [&](const char* layer, LayerPicture& picture, AnatomyPicture which) {
    if (!picture.drawn) {  // drawn for the pictures' own pose, also when placed
      draw_picture(which, picture, T_drawn, cam, palette);
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
    if (patches_.empty()) {
      add_rays(renderer, rays_, T_cam_ct, palette);
    } else {
      show("rays", anatomy_.cones, AnatomyPicture::kCones);
    }
  }
  if (layers[1]) show("entry", anatomy_.entry, AnatomyPicture::kEntry);
  if (layers[2]) {
    show("tumor", anatomy_.tumor, AnatomyPicture::kTumor);
    add_tumor_centre(renderer, plan_.tumor_centre, T_cam_ct, kTumorColour);
  }
  if (drew) {
    ++anatomy_pictures_drawn_;
    if (!keep && !placed) ++anatomy_pictures_waited_;
  }
  if (placed) ++anatomy_pictures_warped_;
  // The pictures shown were drawn for another pose: those for this one are drawn beside the next
  // frame's tracking, from the plan's geometry alone (the values captured here).
  if (placed && options_.anatomy_ahead) {
    anatomy_ahead_ = std::async(std::launch::async, [this, T_cam_ct, cam, palette, layers] {
      return draw_pictures(T_cam_ct, cam, palette, layers);
    });
  }
}

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

template <typename Renderer>
void GuidanceOverlay::draw_needle(Renderer& renderer, const Eigen::Isometry3d& T_cam_ct,
                                  const Eigen::Isometry3d& T_cam_needle,
                                  const NeedleReading& reading) {
  const auto& s = reading.state;
  const auto palette = options_.palette;
  const cv::Scalar colour = safety_bgr(palette, s.safety);
  const Eigen::Vector3d tip = T_cam_needle * setup_.tip_in_needle;
  // The shaft: from the hub (the board origin's foot on the axis) to the tip.
  const double length = setup_.tip_in_needle.dot(setup_.axis_in_needle);
  const Eigen::Vector3d hub = T_cam_needle * (setup_.tip_in_needle - length * setup_.axis_in_needle);
  // Drawn first, under the needle and its extension.
  const std::optional<Eigen::Vector3d> entry = needle_skin_entry(s);
  if (entry) {
    // Where the needle's line enters the skin: a ring of 4 mm radius across the needle.
    const Eigen::Vector3d e1 = s.axis.unitOrthogonal(), e2 = s.axis.cross(e1);
    Polyline ring;
    for (int k = 0; k < 32; ++k) {
      const double t = 2 * M_PI * k / 32;
      ring.points_cam.push_back(T_cam_ct * (*entry + 4.0 * (std::cos(t) * e1 + std::sin(t) * e2)));
    }
    ring.closed = true;
    ring.colour = cv::Scalar(30, 30, 30);  // a dark rim, so that the ring reads on the patches
    ring.width_px = 5;
    renderer.add_polyline("needle", ring);
    ring.colour = colour;
    ring.width_px = 2.5;
    renderer.add_polyline("needle", ring);
  }
  Polyline shaft;
  shaft.points_cam = {hub, tip};
  shaft.colour = cv::Scalar(255, 255, 255);
  shaft.width_px = 3;
  renderer.add_polyline("needle", shaft);
  if (!s.points_away) {
    Polyline ext;
    ext.points_cam = {tip, T_cam_ct * s.target};
    ext.colour = colour;
    ext.width_px = 3;
    renderer.add_polyline("needle", ext);
  }
  if (s.nearest_safe_vertex >= 0 && s.safety != planning::NeedleSafety::kSafe) {
    // The nearest safe direction, from the tumor out: where to turn the needle.
    Polyline dir;
    const Eigen::Vector3d c = plan_.tumor_centre;
    for (int k = 0; k < 12; k += 2) {
      Polyline dash;
      dash.points_cam = {T_cam_ct * (c + (10.0 + 8.0 * k) * s.nearest_safe_direction),
                         T_cam_ct * (c + (10.0 + 8.0 * (k + 1)) * s.nearest_safe_direction)};
      dash.colour = class_bgr(palette, planning::SafetyClass::kSafe);
      dash.width_px = 2;
      renderer.add_polyline("needle", dash);
    }
  }

  // Text panel, bottom left.
  std::vector<TextLine> lines;
  std::string headline = std::string("NEEDLE PATH: ") + planning::needle_safety_name(s.safety);
  std::transform(headline.begin(), headline.end(), headline.begin(), ::toupper);
  lines.push_back({headline, colour, 0.8});
  if (s.points_away) {
    lines.push_back({"needle points away from the tumor"});
  } else {
    lines.push_back({fmt::format("line integral {:.2f} (insignificant <= {:.2f})",
                                 s.evaluation.line_integral, s.eps)});
    for (const auto& t : needle_text(s)) lines.push_back({"crosses " + t, colour, 0.5});
    lines.push_back({fmt::format("tip to target {:.1f} mm, passes {:.1f} mm from the centre",
                                 s.tip_to_centroid_mm, s.miss_distance_mm)});
  }
  // Deviations: between the skin entries (mm) and the directions (degrees).
  if (std::isfinite(s.angle_to_safe_deg)) {
    const Eigen::Vector3d dir = s.nearest_safe_direction;
    const auto safe_entry = skin_exit(plan_.tumor_centre, dir);
    if (entry && safe_entry) {
      const planning::Deviation d = planning::line_deviation(*entry, s.axis, *safe_entry, -dir);
      lines.push_back({fmt::format("to nearest safe direction: {:.0f} mm at the skin, {:.1f} deg",
                                   d.entry_mm, s.angle_to_safe_deg)});
    } else {
      lines.push_back({fmt::format("to nearest safe direction: {:.1f} deg", s.angle_to_safe_deg)});
    }
  }
  if (planned_ && entry && !s.points_away) {
    const planning::Deviation d = planning::line_deviation(
        *entry, s.axis, planned_->entry, (planned_->target - planned_->entry).normalized());
    lines.push_back({fmt::format("to planned trajectory: {:.0f} mm at the skin, {:.1f} deg",
                                 d.entry_mm, d.angle_deg)});
  }

  // The panel's text is drawn beside the targeting view (layers keep their own order).
  const cv::Size frame(renderer.camera().width, renderer.camera().height);
  std::future<Picture> panel =
      std::async(std::launch::async, [this, lines = std::move(lines), frame] {
        const auto t0 = std::chrono::steady_clock::now();
        Picture p;
        p.bgra = text_panel(lines, cv::Point(10, frame.height - 10), true, frame, &p.origin);
        needle_panel_ms_ = std::chrono::duration<double, std::milli>(
                               std::chrono::steady_clock::now() - t0).count();
        return p;
      });
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
      const bool same = targeting_.valid && !s.points_away &&
                        (s.tip - targeting_tip_).norm() < 0.1 && s.axis.dot(targeting_.axis) > kSame &&
                        to.right_hint.dot(targeting_right_) > kSame &&
                        to.size_px == targeting_.size_px;
      if (!same) {
        ++targeting_maps_computed_;
        targeting_ = planning::targeting_geometry(*guide_, s, tumor_surface_, tumor_voxel_mm_, to);
        targeting_tip_ = s.tip;
        targeting_right_ = to.right_hint;
      }
      targeting_origin_ = cv::Point(frame.width - to.size_px - 10, 10);
      if (!same || !targeting_picture_.drawn || targeting_palette_ != palette) {
        targeting_picture_.bgra = render_targeting_view(targeting_, palette);
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
  const Picture p = panel.get();
  renderer.add_layer_image("needle", p.bgra, p.origin);
}

void GuidanceOverlay::draw_status(OverlayRenderer& renderer, const GuidanceFrameInfo& info,
                                  const GuidanceTiming& timing) {
  const auto& cam = renderer.camera();
  const cv::Size frame(cam.width, cam.height);
  const cv::Scalar ok(120, 230, 120), bad(60, 60, 255);
  std::vector<TextLine> lines;
  auto board_line = [&](const char* name, bool tracked, double age) {
    lines.push_back({tracked ? fmt::format("{} marker: tracked ({:.0f} ms)", name, age)
                             : fmt::format("{} marker: LOST", name),
                     tracked ? ok : bad});
  };
  board_line("patient", info.patient_tracked, info.patient_age_ms);
  board_line("needle", info.needle_tracked, info.needle_age_ms);
  lines.push_back({fmt::format("{:.1f} fps, frame {}", timing.fps, (long long)info.frame)});
  if (timing.latency_ms >= 0) {
    lines.push_back({fmt::format("latency {:.0f} ms ({})", timing.latency_ms,
                                 timing.latency_from_capture ? "from capture"
                                                             : "from frame arrival")});
  }
  if (visible(GuidanceLayer::kStatus)) {
    cv::Point origin;
    const cv::Mat panel = text_panel(lines, cv::Point(10, 10), false, frame, &origin);
    renderer.add_layer_image("status", panel, origin);
  }
  // Warnings: large, red, at the top centre.
  int y = 20;
  for (const auto& w : info.warnings) {
    int base = 0;
    const cv::Size s = cv::getTextSize(w, cv::FONT_HERSHEY_SIMPLEX, 1.0, 2, &base);
    const cv::Rect box =
        cv::Rect(std::max(0, (cam.width - s.width) / 2 - 12), y, s.width + 24, s.height + base + 16) &
        cv::Rect(0, 0, cam.width, cam.height);
    if (box.empty()) break;
    cv::Mat banner(box.size(), CV_8UC4, cv::Scalar(0, 0, 160, 200));
    cv::putText(banner, w, cv::Point(12, s.height + 8), cv::FONT_HERSHEY_SIMPLEX, 1.0,
                cv::Scalar(255, 255, 255, 255), 2, cv::LINE_AA);
    renderer.add_layer_image("status", banner, box.tl());
    y += box.height + 8;
  }
}

GuidanceFrameInfo GuidanceOverlay::update(OverlayRenderer& renderer, const tracking::Frame& frame,
                                          const tracking::TrackResult& track,
                                          const GuidanceTiming& timing, bool frame_uploaded) {
  const calibration::CameraModel& cam = renderer.camera();
  GuidanceFrameInfo info;
  info.frame = frame.index;
  info.timestamp_ns = frame.timestamp_ns;
  info.problem = frame.problem.empty() ? track.problem : frame.problem;
  // A frame of another size (or kind) than the camera's cannot be shown under this overlay.
  const bool fits = frame.image.cols == cam.width && frame.image.rows == cam.height &&
                    frame.image.type() == CV_8UC3;
  info.image = !frame.image.empty() && fits;
  if (!frame.image.empty() && !fits && info.problem.empty()) {
    info.problem = "frame " + std::to_string(frame.index) + " is " +
                   std::to_string(frame.image.cols) + "x" + std::to_string(frame.image.rows) +
                   ", not the camera's " + std::to_string(cam.width) + "x" +
                   std::to_string(cam.height) + ": skipped";
  }

  for (int i = 0; i < kGuidanceLayerCount; ++i) {
    const char* name = kLayerNames[size_t(i)];
    renderer.clear_layer(name);
    renderer.set_layer_visible(name, options_.visible[size_t(i)]);
  }

  const tracking::BoardStatus* patient = nullptr;
  const tracking::BoardStatus* needle = nullptr;
  for (const auto& b : track.boards) {
    if (b.board == setup_.patient_board) patient = &b;
    if (b.board == setup_.needle_board) needle = &b;
  }
  info.patient_tracked = patient && patient->tracked;
  info.needle_tracked = needle && needle->tracked;
  if (info.patient_tracked) info.patient_age_ms = patient->age_ms;
  if (info.needle_tracked) info.needle_age_ms = needle->age_ms;

  using Clock = std::chrono::steady_clock;
  const auto ms_since = [](Clock::time_point t) {
    return std::chrono::duration<double, std::milli>(Clock::now() - t).count();
  };
  auto t = Clock::now();
  if (info.image) {
    if (!frame_uploaded) renderer.set_frame(frame.image);
  } else {
    // No picture: a dark frame, no overlay, and the reason.
    renderer.set_frame(cv::Mat(cam.height, cam.width, CV_8UC3, cv::Scalar(40, 40, 40)));
    info.warnings.push_back("NO CAMERA IMAGE" +
                            (info.problem.empty() ? std::string() : ": " + info.problem));
  }
  if (track.dropped > 0) {
    info.warnings.push_back(std::to_string(track.dropped) + " FRAME(S) DROPPED");
  }
  // A plan whose inputs changed since planning is shown as such on every frame.
  for (const planning::ChangedInput& c : plan_.changed_inputs) {
    info.warnings.push_back("PLAN INPUT CHANGED: " +
                            std::filesystem::path(c.path).filename().string() + " (" + c.role +
                            "), RE-PLAN");
  }

  info.upload_ms = ms_since(t);
  if (info.image && info.patient_tracked) {
    const Eigen::Isometry3d T_cam_ct = patient->T_cam_board * setup_.T_ct_patient.inverse();
    info.anatomy_drawn = true;
    // The needle's reading and drawing run beside the anatomy's: they share only what neither
    // changes (plan, setup, options; each keeps its own pictures). Their renderer calls are
    // recorded and made here afterwards, so the layers are the same as drawn one after the other.
    struct NeedlePart {
      NeedleReading reading;
      LayerCalls calls;
      double ms = 0.0, evaluate_ms = 0.0;
    };
    std::future<NeedlePart> needle_part;
    if (info.needle_tracked) {
      const Eigen::Isometry3d T_cam_needle = needle->T_cam_board;
      const Eigen::Isometry3d T_ct_needle =
          setup_.T_ct_patient * patient->T_cam_board.inverse() * T_cam_needle;
      needle_part = std::async(std::launch::async, [this, &renderer, T_cam_ct, T_cam_needle,
                                                    T_ct_needle] {
        const auto t0 = Clock::now();
        NeedlePart part{NeedleReading{}, LayerCalls(renderer.camera())};
        part.reading.T_ct_needle = T_ct_needle;
        part.reading.state =
            guide_->evaluate(T_ct_needle, setup_.tip_in_needle, setup_.axis_in_needle);
        part.evaluate_ms =
            std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
        if (visible(GuidanceLayer::kNeedle) || visible(GuidanceLayer::kTarget)) {
          draw_needle(part.calls, T_cam_ct, T_cam_needle, part.reading);
        }
        part.ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
        return part;
      });
    }
    t = Clock::now();
    draw_anatomy(renderer, T_cam_ct);
    info.anatomy_ms = ms_since(t);
    if (needle_part.valid()) {
      NeedlePart part = needle_part.get();  // rethrows what the needle's part threw
      part.calls.replay(renderer);
      info.needle = std::move(part.reading);
      info.needle_ms = part.ms;
      info.needle_evaluate_ms = part.evaluate_ms;
      info.targeting_ms = targeting_ms_;
      info.needle_panel_ms = needle_panel_ms_;
    }
  }
  if (info.image && !info.patient_tracked) {
    info.warnings.push_back("PATIENT MARKER LOST: NO GUIDANCE SHOWN");
  } else if (info.image && !info.needle_tracked) {
    info.warnings.push_back("NEEDLE MARKER LOST");
  }
  // Warnings always show: hiding the status layer hides only its panel.
  t = Clock::now();
  draw_status(renderer, info, timing);
  info.status_ms = ms_since(t);
  renderer.set_layer_visible("status", true);
  return info;
}

}  // namespace crepuscular::overlay
