// 2D slice views of a plan: CT, path safety classes, structure outlines, area safety contour.
#include "planning/views/slices.hpp"

#include <fmt/format.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <set>
#include <sstream>

#include "foundation/csv.hpp"
#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "foundation/output_files.hpp"
#include "planning/imaging/sampling.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/safety/unknown.hpp"

namespace fs = std::filesystem;

namespace crepuscular::planning {

namespace {


// Outline colours of labelled structures (by label value, cycling); none is a class colour.
const Rgb kLabelColours[] = {{230, 159, 0},   {86, 180, 233},  {204, 121, 167}, {166, 86, 40},
                             {0, 200, 200},   {148, 103, 189}, {200, 200, 200}, {188, 189, 34},
                             {255, 152, 150}, {31, 119, 180},  {196, 156, 148}, {197, 176, 213}};
const Rgb kTumorColour = {255, 0, 255};

Rgb label_colour(int label) {
  const int n = int(sizeof(kLabelColours) / sizeof(kLabelColours[0]));
  return kLabelColours[((label - 1) % n + n) % n];
}

cv::Scalar bgr(const Rgb& c) { return cv::Scalar(c[2], c[1], c[0]); }

// The non-empty items of a comma-separated list, trimmed.
std::vector<std::string> split_list(const std::string& text) {
  std::vector<std::string> out;
  for (std::string& item : split_csv_line(text, ',', true)) {
    if (!item.empty()) out.push_back(std::move(item));
  }
  return out;
}

// Text with a dark outline so it reads on any background.
void outlined_text(cv::Mat& img, const std::string& text, cv::Point org, double scale,
                   const cv::Scalar& colour, int thickness = 1) {
  cv::putText(img, text, org, cv::FONT_HERSHEY_SIMPLEX, scale, cv::Scalar(0, 0, 0), thickness + 2,
              cv::LINE_AA);
  cv::putText(img, text, org, cv::FONT_HERSHEY_SIMPLEX, scale, colour, thickness, cv::LINE_AA);
}

cv::Size text_size(const std::string& text, double scale, int thickness) {
  int baseline = 0;
  return cv::getTextSize(text, cv::FONT_HERSHEY_SIMPLEX, scale, thickness, &baseline);
}


std::string class_rule(const SafetyClasses& c, SafetyClass k, const std::string& unit) {
  const std::string s = fmt::format("{:.4g}", c.safe) + unit,
                    d = fmt::format("{:.4g}", c.dangerous) + unit;
  if (c.higher_is_safer) {
    return k == SafetyClass::kSafe        ? ">= " + s
           : k == SafetyClass::kDangerous ? "< " + d
                                          : d + " .. " + s;
  }
  return k == SafetyClass::kSafe        ? "<= " + s
         : k == SafetyClass::kDangerous ? "> " + d
                                        : s + " .. " + d;
}

}  // namespace

// --- Names and parsing --------------------------------------------------------------------------

const char* plane_name(SlicePlaneKind kind) {
  switch (kind) {
    case SlicePlaneKind::kAxial:
      return "axial";
    case SlicePlaneKind::kCoronal:
      return "coronal";
    case SlicePlaneKind::kSagittal:
      return "sagittal";
    case SlicePlaneKind::kOblique:
      return "oblique";
  }
  return "?";
}

std::vector<SlicePlaneKind> parse_planes(const std::string& text) {
  std::vector<SlicePlaneKind> planes;
  for (const auto& name : split_list(text)) {
    SlicePlaneKind k;
    if (name == "axial")
      k = SlicePlaneKind::kAxial;
    else if (name == "coronal")
      k = SlicePlaneKind::kCoronal;
    else if (name == "sagittal")
      k = SlicePlaneKind::kSagittal;
    else if (name == "oblique")
      k = SlicePlaneKind::kOblique;
    else
      throw Error("unknown slice plane \"" + name +
                  "\" (expected axial, coronal, sagittal, oblique)");
    if (std::find(planes.begin(), planes.end(), k) == planes.end()) planes.push_back(k);
  }
  if (planes.empty()) throw Error("no slice plane given (e.g. axial,coronal,sagittal)");
  return planes;
}


std::array<bool, 3> parse_hidden_classes(const std::string& text) {
  std::array<bool, 3> hidden{false, false, false};
  for (const auto& name : split_list(text)) {
    if (name == "safe")
      hidden[0] = true;
    else if (name == "medium")
      hidden[1] = true;
    else if (name == "dangerous")
      hidden[2] = true;
    else
      throw Error("unknown safety class \"" + name + "\" (expected safe, medium, dangerous)");
  }
  return hidden;
}

// --- Geometry -----------------------------------------------------------------------------------

SlicePlane make_slice_plane(SlicePlaneKind kind, const Eigen::Vector3d& centre,
                            const Eigen::Vector3d& main_axis) {
  SlicePlane p;
  p.kind = kind;
  p.centre = centre;
  const Eigen::Vector3d L = Eigen::Vector3d::UnitX(), P = Eigen::Vector3d::UnitY(),
                        S = Eigen::Vector3d::UnitZ();
  // Standard planes: image right and image down (radiological convention).
  const Eigen::Vector3d right_std[3] = {L, L, P};  // axial, coronal, sagittal
  const Eigen::Vector3d down_std[3] = {P, -S, -S};
  const Eigen::Vector3d normal_std[3] = {S, P, L};
  switch (kind) {
    case SlicePlaneKind::kAxial:
    case SlicePlaneKind::kCoronal:
    case SlicePlaneKind::kSagittal: {
      const int i = int(kind);
      p.right = right_std[i];
      p.down = down_std[i];
      return p;
    }
    case SlicePlaneKind::kOblique:
      break;
  }
  const double norm = main_axis.norm();
  if (!(norm > 1e-9)) {
    throw Error("oblique plane: no main axis (give a safe region of a plan with area safety)");
  }
  const Eigen::Vector3d m = main_axis / norm;
  int best = 0;
  for (int i = 1; i < 3; ++i) {
    if (std::abs(normal_std[i].dot(m)) < std::abs(normal_std[best].dot(m))) best = i;
  }
  const Eigen::Vector3d n = (normal_std[best] - normal_std[best].dot(m) * m).normalized();
  Eigen::Vector3d right = right_std[best] - right_std[best].dot(n) * n;
  Eigen::Vector3d down = down_std[best] - down_std[best].dot(n) * n;
  if (right.norm() >= down.norm()) {
    right.normalize();
    down = (down - down.dot(right) * right).normalized();
  } else {
    down.normalize();
    right = (right - right.dot(down) * down).normalized();
  }
  p.right = right;
  p.down = down;
  return p;
}

std::string orientation_letters(const Eigen::Vector3d& direction) {
  const Eigen::Vector3d d = direction.normalized();
  std::vector<std::pair<double, char>> parts;
  const char pos[3] = {'L', 'P', 'S'}, neg[3] = {'R', 'A', 'I'};
  for (int a = 0; a < 3; ++a) {
    if (std::abs(d[a]) > 0.3) parts.push_back({std::abs(d[a]), d[a] > 0 ? pos[a] : neg[a]});
  }
  std::sort(parts.begin(), parts.end(),
            [](const auto& x, const auto& y) { return x.first > y.first; });
  std::string s;
  for (const auto& [w, c] : parts) s += c;
  return s;
}

Eigen::Vector2d SliceView::pixel_of(const Eigen::Vector3d& p) const {
  const Eigen::Vector3d d = p - origin;
  return {d.dot(plane.right) / pixel_mm, d.dot(plane.down) / pixel_mm};
}

Eigen::Vector3d SliceView::point_of(double x, double y) const {
  return origin + (x * pixel_mm) * plane.right + (y * pixel_mm) * plane.down;
}

// --- Colours ------------------------------------------------------------------------------------


uint8_t window_grey(double hu, double width, double level) {
  const double g = (hu - (level - 0.5 * width)) / width * 255.0;
  return uint8_t(std::lround(std::clamp(g, 0.0, 255.0)));
}

// --- Rendering ----------------------------------------------------------------------------------

namespace {

// The frame of a view: the CT's extent (its corner voxel edges) projected onto the plane's axes,
// the pixel size (options.pixel_mm, else the finest spacing of the CT and the path safety grid
// divided so that the view is at least options.min_view_pixels wide), the size in pixels and the
// centre of pixel (0, 0).
SliceView frame_view(const SliceScene& scene, const SlicePlane& plane,
                     const SliceOptions& options) {
  const ImageGeometry& cg = scene.ct->geometry();
  SliceView view;
  view.plane = plane;
  double umin = 1e300, umax = -1e300, vmin = 1e300, vmax = -1e300;
  for (int c = 0; c < 8; ++c) {
    const Eigen::Vector3d idx((c & 1) ? cg.dims[0] - 0.5 : -0.5, (c & 2) ? cg.dims[1] - 0.5 : -0.5,
                              (c & 4) ? cg.dims[2] - 0.5 : -0.5);
    const Eigen::Vector3d d = cg.index_to_physical(idx) - plane.centre;
    umin = std::min(umin, d.dot(plane.right));
    umax = std::max(umax, d.dot(plane.right));
    vmin = std::min(vmin, d.dot(plane.down));
    vmax = std::max(vmax, d.dot(plane.down));
  }
  // Unknown voxels beyond the CT (a thin scan, a large region of interest) are shown too.
  if (scene.region_state) {
    const Volume<uint8_t>& r = *scene.region_state;
    Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e300), hi = -lo;
    for (int64_t k = 0; k < r.dims()[2]; ++k)
      for (int64_t j = 0; j < r.dims()[1]; ++j)
        for (int64_t i = 0; i < r.dims()[0]; ++i) {
          if (r(i, j, k) != kRegionUnknown) continue;
          lo = lo.cwiseMin(Eigen::Vector3d(double(i), double(j), double(k)));
          hi = hi.cwiseMax(Eigen::Vector3d(double(i), double(j), double(k)));
        }
    if (lo.x() <= hi.x()) {
      for (int c = 0; c < 8; ++c) {
        const Eigen::Vector3d idx((c & 1) ? hi.x() + 0.5 : lo.x() - 0.5,
                                  (c & 2) ? hi.y() + 0.5 : lo.y() - 0.5,
                                  (c & 4) ? hi.z() + 0.5 : lo.z() - 0.5);
        const Eigen::Vector3d d = r.geometry().index_to_physical(idx) - plane.centre;
        umin = std::min(umin, d.dot(plane.right));
        umax = std::max(umax, d.dot(plane.right));
        vmin = std::min(vmin, d.dot(plane.down));
        vmax = std::max(vmax, d.dot(plane.down));
      }
    }
  }
  double pixel = options.pixel_mm;
  if (!(pixel > 0)) {
    double finest = cg.spacing.minCoeff();
    if (scene.path_safety)
      finest = std::min(finest, scene.path_safety->geometry().spacing.minCoeff());
    const double extent = std::max(umax - umin, vmax - vmin);
    const int factor = std::max(1, int(std::ceil(options.min_view_pixels / (extent / finest))));
    pixel = finest / factor;
  }
  view.pixel_mm = pixel;
  const int w = std::max(1, int(std::ceil((umax - umin) / pixel)));
  const int h = std::max(1, int(std::ceil((vmax - vmin) / pixel)));
  if (int64_t(w) * h > 64LL * 1024 * 1024) {
    throw Error("slices: a view of " + std::to_string(w) + " x " + std::to_string(h) +
                " pixels is too large (choose a larger pixel size)");
  }
  view.view_width = w;
  view.view_height = h;
  view.origin =
      plane.centre + (umin + 0.5 * pixel) * plane.right + (vmin + 0.5 * pixel) * plane.down;
  return view;
}

// The layers of a view sampled at its pixel centres: the CT in its window with the path safety
// classes blended over it (BGR, black outside the CT) and unknown voxels hatched, and the label
// and tumor values (nearest voxel) that the outlines are traced on.
struct SliceLayers {
  cv::Mat image;   // CV_8UC3
  cv::Mat labels;  // CV_32S, 0 where none
  cv::Mat tumor;   // CV_8U, 255 in the tumor
  int64_t unknown_pixels = 0;
};

SliceLayers sample_layers(const SliceScene& scene, const SliceView& view,
                          const SliceOptions& options) {
  const Volume<float>& ct = *scene.ct;
  const int w = view.view_width, h = view.view_height;
  const auto colours = class_colours(options.palette);
  SliceLayers layers{cv::Mat(h, w, CV_8UC3, cv::Scalar(0, 0, 0)),
                     cv::Mat(h, w, CV_32S, cv::Scalar(0)), cv::Mat(h, w, CV_8U, cv::Scalar(0))};
  const double alpha = std::clamp(options.overlay_opacity, 0.0, 1.0);
  int64_t unknown_pixels = 0;
#pragma omp parallel for schedule(static) reduction(+ : unknown_pixels)
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const Eigen::Vector3d p = view.point_of(x, y);
      const bool unknown = scene.region_state &&
                           nearest_voxel_or<uint8_t>(*scene.region_state, p, kRegionNotComputed) ==
                               kRegionUnknown;
      const std::optional<double> hu = trilinear_clamped(ct, ct.physical_to_index(p));
      if (!hu && !unknown) continue;
      const uint8_t g = hu ? window_grey(*hu, options.window_width, options.window_level) : 0;
      double rgb[3] = {double(g), double(g), double(g)};
      const std::optional<float> value =
          scene.path_safety && !unknown ? nearest_voxel(*scene.path_safety, p) : std::nullopt;
      if (unknown) {
        // Unknown (outside the scan): hatched, never a class colour, never hidden.
        ++unknown_pixels;
        if (unknown_hatch_pixel(x, y)) rgb[0] = rgb[1] = rgb[2] = kUnknownHatchGrey;
      } else if (value && std::isfinite(*value)) {
        const int k = int(scene.classes.classify(*value));
        if (!options.hidden[size_t(k)]) {
          for (int c = 0; c < 3; ++c)
            rgb[c] = (1 - alpha) * rgb[c] + alpha * colours[size_t(k)][size_t(c)];
        }
      }
      cv::Vec3b& px = layers.image.at<cv::Vec3b>(y, x);
      for (int c = 0; c < 3; ++c) px[2 - c] = uint8_t(std::lround(rgb[c]));
      if (scene.labels) {
        const std::optional<int32_t> label = nearest_voxel(*scene.labels, p);
        if (label) layers.labels.at<int32_t>(y, x) = *label;
      }
      if (scene.tumor) {
        const std::optional<uint8_t> t = nearest_voxel(*scene.tumor, p);
        if (t) layers.tumor.at<uint8_t>(y, x) = *t ? 255 : 0;
      }
    }
  }
  layers.unknown_pixels = unknown_pixels;
  return layers;
}

// Structure outlines: pixels of a structure with a 4-neighbour of another label, in the label's
// colour. Returns the labels outlined.
std::set<int> draw_structure_outlines(const cv::Mat& labels, cv::Mat& img) {
  std::set<int> seen;
  const int w = labels.cols, h = labels.rows;
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const int32_t l = labels.at<int32_t>(y, x);
      if (l == 0) continue;
      const bool edge = (x > 0 && labels.at<int32_t>(y, x - 1) != l) ||
                        (x + 1 < w && labels.at<int32_t>(y, x + 1) != l) ||
                        (y > 0 && labels.at<int32_t>(y - 1, x) != l) ||
                        (y + 1 < h && labels.at<int32_t>(y + 1, x) != l);
      if (!edge) continue;
      const Rgb c = label_colour(l);
      img.at<cv::Vec3b>(y, x) = cv::Vec3b(c[2], c[1], c[0]);
      seen.insert(l);
    }
  }
  return seen;
}

// Area safety contour (§3.4): the mesh cut by the plane; each segment drawn as a band on its
// outer side, as wide as leeway * max width (paper: at most 1 cm in the patient), coloured by
// the leeway. Unsafe parts (extrusion stopped) as thin lines in the dangerous colour. Returns the
// number of segments drawn.
int draw_area_contour(const AreaSafetyGeometry& a, const SliceView& view,
                      const SliceOptions& options, cv::Mat& img) {
  const SlicePlane& plane = view.plane;
  const auto colours = class_colours(options.palette);
  int segments = 0;
  const Eigen::Vector3d n = plane.normal();
  const bool have_normals = a.normals.size() == a.vertices.size();
  const Eigen::Vector2d centre_px = view.pixel_of(a.ellipsoid.centre);
  const double max_px = options.max_line_width_mm / view.pixel_mm;
  std::vector<double> s(a.vertices.size());
  for (size_t i = 0; i < a.vertices.size(); ++i) s[i] = (a.vertices[i] - plane.centre).dot(n);
  const auto leeway_of = [&](int i) {
    return size_t(i) < a.leeway.size() ? double(a.leeway[size_t(i)]) : 0.0;
  };
  for (const auto& tri : a.triangles) {
    Eigen::Vector2d pts[2];
    double lw[2] = {0, 0};
    Eigen::Vector3d nrm[2] = {Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero()};
    int count = 0;
    for (int e = 0; e < 3 && count < 2; ++e) {
      const int i = tri[size_t(e)], j = tri[size_t((e + 1) % 3)];
      const double si = s[size_t(i)], sj = s[size_t(j)];
      if ((si >= 0) == (sj >= 0)) continue;
      const double t = si / (si - sj);
      pts[count] = view.pixel_of(a.vertices[size_t(i)] +
                                 t * (a.vertices[size_t(j)] - a.vertices[size_t(i)]));
      lw[count] = leeway_of(i) + t * (leeway_of(j) - leeway_of(i));
      if (have_normals)
        nrm[count] = a.normals[size_t(i)] + t * (a.normals[size_t(j)] - a.normals[size_t(i)]);
      ++count;
    }
    if (count < 2) continue;
    const double leeway = 0.5 * (lw[0] + lw[1]);
    const cv::Point2d p0(pts[0].x(), pts[0].y()), p1(pts[1].x(), pts[1].y());
    if (leeway <= 1e-6) {
      if (options.hidden[2]) continue;
      cv::line(img, p0, p1, bgr(colours[2]), 1, cv::LINE_AA);
      ++segments;
      continue;
    }
    const Rgb colour = leeway_colour(options.palette, leeway);
    const double width = std::max(1.0, leeway * max_px);
    Eigen::Vector2d seg = pts[1] - pts[0];
    if (seg.norm() < 1e-9) continue;
    Eigen::Vector2d perp(-seg.y(), seg.x());
    perp.normalize();
    // Outward: along the surface normal projected onto the view, else away from the tumor.
    const Eigen::Vector3d avg = nrm[0] + nrm[1];
    const Eigen::Vector2d proj(avg.dot(plane.right), avg.dot(plane.down));
    const Eigen::Vector2d away = 0.5 * (pts[0] + pts[1]) - centre_px;
    const double side =
        proj.norm() > 0.1 * avg.norm() && avg.norm() > 0 ? proj.dot(perp) : away.dot(perp);
    if (side < 0) perp = -perp;
    const Eigen::Vector2d q0 = pts[0] + width * perp, q1 = pts[1] + width * perp;
    const cv::Point quad[4] = {
        cv::Point(int(std::lround(pts[0].x())), int(std::lround(pts[0].y()))),
        cv::Point(int(std::lround(pts[1].x())), int(std::lround(pts[1].y()))),
        cv::Point(int(std::lround(q1.x())), int(std::lround(q1.y()))),
        cv::Point(int(std::lround(q0.x())), int(std::lround(q0.y())))};
    cv::fillConvexPoly(img, quad, 4, bgr(colour), cv::LINE_AA);
    cv::line(img, p0, p1, bgr(colour), 1, cv::LINE_AA);
    ++segments;
  }
  return segments;
}

// Main axis of the selected region (paper Fig. 9), dashed, from the tumor centre outward, where it
// runs within 15 degrees of the plane. Returns whether it was drawn.
bool draw_main_axis(const SliceScene& scene, const SliceView& view, cv::Mat& img) {
  if (!scene.region || !scene.area || !(scene.region->main_axis.norm() > 0)) return false;
  const Eigen::Vector3d m = scene.region->main_axis.normalized();
  if (!(std::abs(m.dot(view.plane.normal())) < std::sin(15.0 * M_PI / 180.0))) return false;
  const Eigen::Vector3d o = scene.area->ellipsoid.centre;
  const double reach =
      std::max((scene.region->centre - o).norm() * 1.5,
               scene.area->max_distance_mm > 0 ? scene.area->max_distance_mm : 100.0);
  for (double t = 0; t < reach; t += 8.0) {
    const Eigen::Vector2d a0 = view.pixel_of(o + t * m), a1 = view.pixel_of(o + (t + 4.0) * m);
    cv::line(img, cv::Point2d(a0.x(), a0.y()), cv::Point2d(a1.x(), a1.y()),
             cv::Scalar(255, 255, 255), 2, cv::LINE_AA);
  }
  return true;
}

// Orientation letters at the middle of each edge of the view.
void draw_orientation_letters(const SlicePlane& plane, cv::Mat& img) {
  const int w = img.cols, h = img.rows;
  const double scale = 0.8;
  const int th = 2;
  const std::string left = orientation_letters(-plane.right),
                    right = orientation_letters(plane.right),
                    top = orientation_letters(-plane.down),
                    bottom = orientation_letters(plane.down);
  const cv::Scalar white(255, 255, 255);
  cv::Size sz = text_size(left, scale, th);
  outlined_text(img, left, cv::Point(6, h / 2 + sz.height / 2), scale, white, th);
  sz = text_size(right, scale, th);
  outlined_text(img, right, cv::Point(w - sz.width - 6, h / 2 + sz.height / 2), scale, white, th);
  sz = text_size(top, scale, th);
  outlined_text(img, top, cv::Point(w / 2 - sz.width / 2, sz.height + 6), scale, white, th);
  sz = text_size(bottom, scale, th);
  outlined_text(img, bottom, cv::Point(w / 2 - sz.width / 2, h - 8), scale, white, th);
}

// Scale bar, bottom left: the largest of 1-2-5 x 10^k mm within a quarter of the view width.
void draw_scale_bar(double pixel, cv::Mat& img) {
  const int w = img.cols, h = img.rows;
  double bar_mm = 1;
  for (double decade = 1; decade <= 1e4; decade *= 10) {
    for (double m : {1.0, 2.0, 5.0}) {
      if (m * decade / pixel <= 0.25 * w) bar_mm = m * decade;
    }
  }
  const int len = int(std::lround(bar_mm / pixel));
  const int x0 = 16, y0 = h - 34;
  cv::rectangle(img, cv::Point(x0 - 1, y0 - 1), cv::Point(x0 + len + 1, y0 + 5),
                cv::Scalar(0, 0, 0), cv::FILLED);
  cv::rectangle(img, cv::Point(x0, y0), cv::Point(x0 + len, y0 + 4), cv::Scalar(255, 255, 255),
                cv::FILLED);
  outlined_text(img, fmt::format("{:.0f} mm", bar_mm), cv::Point(x0, y0 - 6), 0.5,
                cv::Scalar(255, 255, 255), 1);
}

// The legend panel right of the view, written top to bottom one text line at a time.
class LegendWriter {
 public:
  explicit LegendWriter(cv::Mat panel) : panel_(std::move(panel)) {}
  cv::Mat& panel() { return panel_; }
  int& y() { return y_; }  // baseline of the next line, pixels
  void title(const std::string& text) {
    cv::putText(panel_, text, cv::Point(10, y_), cv::FONT_HERSHEY_SIMPLEX, 0.7, text_colour_, 2,
                cv::LINE_AA);
    y_ += 24;
  }
  void line(const std::string& text, int indent = 10) {
    cv::putText(panel_, text, cv::Point(indent, y_), cv::FONT_HERSHEY_SIMPLEX, 0.45,
                text_colour_, 1, cv::LINE_AA);
    y_ += 18;
  }
  void gap() { y_ += 6; }

 private:
  cv::Mat panel_;
  const cv::Scalar text_colour_{235, 235, 235};
  int y_ = 22;
};

// Legend rows of the path safety classes: colour swatch, name and rule.
void legend_path_safety(const SliceScene& scene, const SliceOptions& options, LegendWriter& out) {
  if (!scene.path_safety) {
    out.line("Path safety: not shown");
    return;
  }
  const auto colours = class_colours(options.palette);
  std::string v = scene.value_name;
  std::transform(v.begin(), v.end(), v.begin(), [](unsigned char c) { return std::toupper(c); });
  out.line("Path safety (" + v + ")");
  const std::string unit = scene.classes.higher_is_safer ? " %" : "";
  const char* names[3] = {"safe", "medium", "dangerous"};
  for (int k = 0; k < 3; ++k) {
    cv::rectangle(out.panel(), cv::Rect(12, out.y() - 11, 22, 13), bgr(colours[size_t(k)]),
                  cv::FILLED);
    std::string text =
        std::string(names[k]) + "  " + class_rule(scene.classes, SafetyClass(k), unit);
    if (options.hidden[size_t(k)]) text += "  (hidden)";
    out.line(text, 42);
  }
}

// Legend row of the unknown state: a hatched swatch.
void legend_unknown(LegendWriter& out) {
  const cv::Rect swatch(12, out.y() - 11, 22, 13);
  cv::rectangle(out.panel(), swatch, cv::Scalar(0, 0, 0), cv::FILLED);
  for (int y = 0; y < swatch.height; ++y)
    for (int x = 0; x < swatch.width; ++x)
      if (unknown_hatch_pixel(x, y))
        out.panel().at<cv::Vec3b>(swatch.y + y, swatch.x + x) =
            cv::Vec3b(kUnknownHatchGrey, kUnknownHatchGrey, kUnknownHatchGrey);
  out.line("unknown (outside the scan)", 42);
}

// Legend rows of the area safety contour: its line width at three leeways, the unsafe line.
void legend_area_safety(const SliceScene& scene, const SliceOptions& options, double pixel,
                        LegendWriter& out) {
  if (!scene.area) {
    out.line("Area safety: not in this plan");
    return;
  }
  const auto colours = class_colours(options.palette);
  out.line("Area safety: leeway of the region");
  out.line("(line width, at most " + fmt::format("{:.0f}", options.max_line_width_mm) + " mm)");
  for (double l : {1.0, 0.5, 0.1}) {
    const int width = std::max(1, int(std::lround(l * options.max_line_width_mm / pixel)));
    const int bar = std::min(width, 30);
    cv::rectangle(out.panel(), cv::Rect(12, out.y() - 6 - bar / 2, 40, bar),
                  bgr(leeway_colour(options.palette, l)), cv::FILLED);
    out.line(fmt::format("{:.0f} % of the largest region", 100 * l), 60);
    out.y() += std::max(0, bar - 12);
  }
  cv::line(out.panel(), cv::Point(12, out.y() - 6), cv::Point(52, out.y() - 6), bgr(colours[2]),
           1, cv::LINE_AA);
  out.line("unsafe (extrusion stopped)", 60);
}

// What the legend lists besides the scene's layers.
struct LegendContent {
  bool axis_shown = false, tumor_shown = false, unknown_shown = false;
  std::vector<std::pair<std::string, Rgb>> structures;  // outlined structures and their colours
};

void draw_legend(const SliceScene& scene, const SliceView& view, const SliceOptions& options,
                 const LegendContent& content, cv::Mat panel) {
  panel.setTo(cv::Scalar(40, 40, 40));
  LegendWriter out(panel);
  const SlicePlane& plane = view.plane;
  std::string title = plane_name(plane.kind);
  title[0] = char(std::toupper(title[0]));
  out.title(title);
  out.line(fmt::format("at ({:.1f}, {:.1f}, {:.1f}) LPS mm", plane.centre.x(), plane.centre.y(),
                       plane.centre.z()));
  out.line(fmt::format("CT W{:.0f} / L{:.0f} HU, pixel {:.2f} mm", options.window_width,
                       options.window_level, view.pixel_mm));
  if (plane.right.x() > 0.7) out.line("patient's left on image right");
  out.gap();
  legend_path_safety(scene, options, out);
  if (content.unknown_shown) legend_unknown(out);
  out.gap();
  legend_area_safety(scene, options, view.pixel_mm, out);
  if (content.axis_shown) {
    for (int x = 12; x < 52; x += 10) {
      cv::line(panel, cv::Point(x, out.y() - 6), cv::Point(x + 5, out.y() - 6),
               cv::Scalar(255, 255, 255), 2);
    }
    out.line("main axis of region " + std::to_string(scene.region->id), 60);
  }
  out.gap();
  if (content.tumor_shown || scene.tumor) {
    cv::rectangle(panel, cv::Rect(12, out.y() - 11, 22, 13), bgr(kTumorColour), 2);
    out.line("tumor", 42);
  }
  if (!content.structures.empty()) out.line("Structures (outlines):");
  for (const auto& [text, c] : content.structures) {
    if (out.y() > panel.rows - 6) break;
    cv::rectangle(panel, cv::Rect(12, out.y() - 11, 22, 13), bgr(c), 2);
    out.line(text, 42);
  }
}

RgbImage rgb_image(const cv::Mat& bgr_image) {
  RgbImage image;
  image.width = bgr_image.cols;
  image.height = bgr_image.rows;
  image.rgb.resize(size_t(image.width) * size_t(image.height) * 3);
  for (int y = 0; y < image.height; ++y) {
    for (int x = 0; x < image.width; ++x) {
      const cv::Vec3b& px = bgr_image.at<cv::Vec3b>(y, x);
      const size_t o = (size_t(y) * size_t(image.width) + size_t(x)) * 3;
      image.rgb[o] = px[2];
      image.rgb[o + 1] = px[1];
      image.rgb[o + 2] = px[0];
    }
  }
  return image;
}

}  // namespace

SliceView render_slice(const SliceScene& scene, const SlicePlane& plane,
                       const SliceOptions& options) {
  if (!scene.ct || scene.ct->empty()) throw Error("slices: a CT volume is required");
  SliceView view = frame_view(scene, plane, options);
  SliceLayers layers = sample_layers(scene, view, options);
  cv::Mat& img = layers.image;
  view.unknown_pixels = layers.unknown_pixels;

  LegendContent legend;
  legend.unknown_shown = layers.unknown_pixels > 0;
  std::set<int> seen;
  if (scene.labels) seen = draw_structure_outlines(layers.labels, img);
  for (int l : seen) {
    const LabelClass* c = scene.table ? scene.table->find_label(l) : nullptr;
    const std::string name = c ? c->name : "label " + std::to_string(l);
    view.structures.push_back(name);
    legend.structures.push_back(
        {c ? name + " (level " + std::to_string(c->level) + ")" : name, label_colour(l)});
  }
  if (scene.tumor) {
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(layers.tumor, contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_NONE);
    cv::drawContours(img, contours, -1, bgr(kTumorColour), 2, cv::LINE_8);
    legend.tumor_shown = !contours.empty();
  }
  if (scene.area && !scene.area->vertices.empty()) {
    view.contour_segments += draw_area_contour(*scene.area, view, options, img);
  }
  legend.axis_shown = draw_main_axis(scene, view, img);
  draw_orientation_letters(plane, img);
  draw_scale_bar(view.pixel_mm, img);

  // The view, and the legend panel right of it.
  const int w = view.view_width, h = view.view_height;
  const int lw = std::max(0, options.legend_width);
  const int legend_height =
      330 + 18 * int(legend.structures.size()) + (legend.unknown_shown ? 18 : 0);
  const int H = lw > 0 ? std::max(h, legend_height) : h;
  cv::Mat out(H, w + lw, CV_8UC3, cv::Scalar(0, 0, 0));
  img.copyTo(out(cv::Rect(0, 0, w, h)));
  if (lw > 0) draw_legend(scene, view, options, legend, out(cv::Rect(w, 0, lw, H)));
  view.image = rgb_image(out);
  return view;
}

void write_png(const RgbImage& image, const std::string& path) {
  cv::Mat m(image.height, image.width, CV_8UC3);
  for (int y = 0; y < image.height; ++y) {
    for (int x = 0; x < image.width; ++x) {
      const auto c = image.at(x, y);
      m.at<cv::Vec3b>(y, x) = cv::Vec3b(c[2], c[1], c[0]);
    }
  }
  write_file_atomically(path, [&](const std::string& temporary) {
    bool ok = false;
    try {
      ok = cv::imwrite(temporary, m);
    } catch (const cv::Exception&) {
      ok = false;
    }
    if (!ok) throw Error(path + ": cannot write PNG image");
  });
}

}  // namespace crepuscular::planning
