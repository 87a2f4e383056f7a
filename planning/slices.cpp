// 2D slice views of a plan: CT, path safety classes, structure outlines, area safety contour.
#include "planning/slices.hpp"

#include <spdlog/spdlog.h>

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
#include <set>
#include <sstream>

#include "kernels/error.hpp"
#include "planning/evaluate.hpp"
#include "planning/output_files.hpp"
#include "planning/volume_io.hpp"

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

std::string trim(const std::string& s) {
  const auto b = s.find_first_not_of(" \t");
  const auto e = s.find_last_not_of(" \t");
  return b == std::string::npos ? std::string() : s.substr(b, e - b + 1);
}

std::vector<std::string> split_list(const std::string& text) {
  std::vector<std::string> out;
  std::stringstream ss(text);
  std::string item;
  while (std::getline(ss, item, ',')) {
    item = trim(item);
    if (!item.empty()) out.push_back(item);
  }
  return out;
}

// Trilinear CT value at a point; false outside the CT's extent (beyond half a voxel).
bool sample_ct(const Volume<float>& ct, const Eigen::Vector3d& p, double& hu) {
  const ImageGeometry& g = ct.geometry();
  const Eigen::Vector3d q = g.physical_to_index(p);
  for (int a = 0; a < 3; ++a) {
    if (q[a] < -0.5 || q[a] > double(g.dims[a]) - 0.5) return false;
  }
  int64_t i0[3], i1[3];
  double w[3];
  for (int a = 0; a < 3; ++a) {
    const double c = std::clamp(q[a], 0.0, double(g.dims[a] - 1));
    const double f = std::floor(c);
    i0[a] = int64_t(f);
    i1[a] = std::min<int64_t>(i0[a] + 1, g.dims[a] - 1);
    w[a] = c - f;
  }
  double v = 0;
  for (int c = 0; c < 8; ++c) {
    const int64_t i = (c & 1) ? i1[0] : i0[0];
    const int64_t j = (c & 2) ? i1[1] : i0[1];
    const int64_t k = (c & 4) ? i1[2] : i0[2];
    const double weight =
        ((c & 1) ? w[0] : 1 - w[0]) * ((c & 2) ? w[1] : 1 - w[1]) * ((c & 4) ? w[2] : 1 - w[2]);
    v += weight * double(ct(i, j, k));
  }
  hu = v;
  return true;
}

template <typename T>
bool nearest(const Volume<T>& v, const Eigen::Vector3d& p, T& out) {
  const Index3 n = v.geometry().nearest_index(p);
  if (!v.geometry().contains(n[0], n[1], n[2])) return false;
  out = v(n[0], n[1], n[2]);
  return true;
}

std::string fmt(const char* f, double v) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), f, v);
  return buf;
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
  const std::string s = fmt("%.4g", c.safe) + unit, d = fmt("%.4g", c.dangerous) + unit;
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
      throw Error("--planes: unknown plane \"" + name +
                  "\" (expected axial, coronal, sagittal, oblique)");
    if (std::find(planes.begin(), planes.end(), k) == planes.end()) planes.push_back(k);
  }
  if (planes.empty()) throw Error("--planes: no plane given (e.g. axial,coronal,sagittal)");
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
      throw Error("--hide: unknown class \"" + name + "\" (expected safe, medium, dangerous)");
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
    throw Error("oblique plane: no main axis (give --region K of a plan with area safety)");
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

SliceView render_slice(const SliceScene& scene, const SlicePlane& plane,
                       const SliceOptions& options) {
  if (!scene.ct || scene.ct->empty()) throw Error("slices: a CT volume is required");
  const Volume<float>& ct = *scene.ct;
  const ImageGeometry& cg = ct.geometry();
  SliceView view;
  view.plane = plane;

  // Extent: the CT's corners (voxel edges) projected onto the plane's axes.
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
                " pixels is too large (choose a larger --pixel)");
  }
  view.view_width = w;
  view.view_height = h;
  view.origin =
      plane.centre + (umin + 0.5 * pixel) * plane.right + (vmin + 0.5 * pixel) * plane.down;

  const auto colours = class_colours(options.palette);
  cv::Mat img(h, w, CV_8UC3, cv::Scalar(0, 0, 0));
  cv::Mat labels(h, w, CV_32S, cv::Scalar(0));
  cv::Mat tumor(h, w, CV_8U, cv::Scalar(0));
  const double alpha = std::clamp(options.overlay_opacity, 0.0, 1.0);

#pragma omp parallel for schedule(static)
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const Eigen::Vector3d p = view.point_of(x, y);
      double hu = 0;
      if (!sample_ct(ct, p, hu)) continue;
      const uint8_t g = window_grey(hu, options.window_width, options.window_level);
      double rgb[3] = {double(g), double(g), double(g)};
      float value = 0;
      if (scene.path_safety && nearest(*scene.path_safety, p, value) && std::isfinite(value)) {
        const int k = int(scene.classes.classify(value));
        if (!options.hidden[size_t(k)]) {
          for (int c = 0; c < 3; ++c)
            rgb[c] = (1 - alpha) * rgb[c] + alpha * colours[size_t(k)][size_t(c)];
        }
      }
      cv::Vec3b& px = img.at<cv::Vec3b>(y, x);
      for (int c = 0; c < 3; ++c) px[2 - c] = uint8_t(std::lround(rgb[c]));
      int32_t label = 0;
      if (scene.labels && nearest(*scene.labels, p, label)) labels.at<int32_t>(y, x) = label;
      uint8_t t = 0;
      if (scene.tumor && nearest(*scene.tumor, p, t)) tumor.at<uint8_t>(y, x) = t ? 255 : 0;
    }
  }

  // Structure outlines: pixels of a structure with a 4-neighbour of another label.
  std::set<int> seen;
  if (scene.labels) {
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
  }
  for (int l : seen) {
    const LabelClass* c = scene.table ? scene.table->find_label(l) : nullptr;
    view.structures.push_back(c ? c->name : "label " + std::to_string(l));
  }
  bool tumor_shown = false;
  if (scene.tumor) {
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(tumor, contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_NONE);
    cv::drawContours(img, contours, -1, bgr(kTumorColour), 2, cv::LINE_8);
    tumor_shown = !contours.empty();
  }

  // Area safety contour (§3.4): the mesh cut by the plane; each segment drawn as a band on its
  // outer side, as wide as leeway * max width (paper: at most 1 cm in the patient), coloured by
  // the leeway. Unsafe parts (extrusion stopped) as thin lines in the dangerous colour.
  if (scene.area && !scene.area->vertices.empty()) {
    const AreaSafetyGeometry& a = *scene.area;
    const Eigen::Vector3d n = plane.normal();
    const bool have_normals = a.normals.size() == a.vertices.size();
    const Eigen::Vector2d centre_px = view.pixel_of(a.ellipsoid.centre);
    const double max_px = options.max_line_width_mm / pixel;
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
        ++view.contour_segments;
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
      ++view.contour_segments;
    }
  }

  // Main axis of the selected region (paper Fig. 9), dashed, from the tumor centre outward.
  bool axis_shown = false;
  if (scene.region && scene.area && scene.region->main_axis.norm() > 0) {
    const Eigen::Vector3d m = scene.region->main_axis.normalized();
    if (std::abs(m.dot(plane.normal())) < std::sin(15.0 * M_PI / 180.0)) {
      const Eigen::Vector3d o = scene.area->ellipsoid.centre;
      const double reach =
          std::max((scene.region->centre - o).norm() * 1.5,
                   scene.area->max_distance_mm > 0 ? scene.area->max_distance_mm : 100.0);
      for (double t = 0; t < reach; t += 8.0) {
        const Eigen::Vector2d a0 = view.pixel_of(o + t * m), a1 = view.pixel_of(o + (t + 4.0) * m);
        cv::line(img, cv::Point2d(a0.x(), a0.y()), cv::Point2d(a1.x(), a1.y()),
                 cv::Scalar(255, 255, 255), 2, cv::LINE_AA);
      }
      axis_shown = true;
    }
  }

  // Orientation letters at the middle of each edge.
  {
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
  {
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
    outlined_text(img, fmt("%.0f mm", bar_mm), cv::Point(x0, y0 - 6), 0.5,
                  cv::Scalar(255, 255, 255), 1);
  }

  // Legend panel right of the view.
  const int lw = std::max(0, options.legend_width);
  std::vector<std::pair<std::string, Rgb>> structure_rows;
  for (int l : seen) {
    const LabelClass* c = scene.table ? scene.table->find_label(l) : nullptr;
    std::string text = c ? c->name : "label " + std::to_string(l);
    if (c) text += " (level " + std::to_string(c->level) + ")";
    structure_rows.push_back({text, label_colour(l)});
  }
  const int legend_height = 330 + 18 * int(structure_rows.size());
  const int H = lw > 0 ? std::max(h, legend_height) : h;
  cv::Mat out(H, w + lw, CV_8UC3, cv::Scalar(0, 0, 0));
  img.copyTo(out(cv::Rect(0, 0, w, h)));
  if (lw > 0) {
    cv::Mat panel = out(cv::Rect(w, 0, lw, H));
    panel.setTo(cv::Scalar(40, 40, 40));
    const cv::Scalar text_colour(235, 235, 235);
    const double fs = 0.45;
    int y = 22;
    const auto line = [&](const std::string& text, int indent = 10) {
      cv::putText(panel, text, cv::Point(indent, y), cv::FONT_HERSHEY_SIMPLEX, fs, text_colour, 1,
                  cv::LINE_AA);
      y += 18;
    };
    std::string title = plane_name(plane.kind);
    title[0] = char(std::toupper(title[0]));
    cv::putText(panel, title, cv::Point(10, y), cv::FONT_HERSHEY_SIMPLEX, 0.7, text_colour, 2,
                cv::LINE_AA);
    y += 24;
    char buf[160];
    std::snprintf(buf, sizeof(buf), "at (%.1f, %.1f, %.1f) LPS mm", plane.centre.x(),
                  plane.centre.y(), plane.centre.z());
    line(buf);
    std::snprintf(buf, sizeof(buf), "CT W%.0f / L%.0f HU, pixel %.2f mm", options.window_width,
                  options.window_level, pixel);
    line(buf);
    if (plane.right.x() > 0.7) line("patient's left on image right");
    y += 6;
    if (scene.path_safety) {
      std::string v = scene.value_name;
      std::transform(v.begin(), v.end(), v.begin(),
                     [](unsigned char c) { return std::toupper(c); });
      line("Path safety (" + v + ")");
      const std::string unit = scene.classes.higher_is_safer ? " %" : "";
      const char* names[3] = {"safe", "medium", "dangerous"};
      for (int k = 0; k < 3; ++k) {
        cv::rectangle(panel, cv::Rect(12, y - 11, 22, 13), bgr(colours[size_t(k)]), cv::FILLED);
        std::string text =
            std::string(names[k]) + "  " + class_rule(scene.classes, SafetyClass(k), unit);
        if (options.hidden[size_t(k)]) text += "  (hidden)";
        line(text, 42);
      }
    } else {
      line("Path safety: not shown");
    }
    y += 6;
    if (scene.area) {
      line("Area safety: leeway of the region");
      line("(line width, at most " + fmt("%.0f", options.max_line_width_mm) + " mm)");
      for (double l : {1.0, 0.5, 0.1}) {
        const int width = std::max(1, int(std::lround(l * options.max_line_width_mm / pixel)));
        const int bar = std::min(width, 30);
        cv::rectangle(panel, cv::Rect(12, y - 6 - bar / 2, 40, bar),
                      bgr(leeway_colour(options.palette, l)), cv::FILLED);
        line(fmt("%.0f %% of the largest region", 100 * l), 60);
        y += std::max(0, bar - 12);
      }
      cv::line(panel, cv::Point(12, y - 6), cv::Point(52, y - 6), bgr(colours[2]), 1, cv::LINE_AA);
      line("unsafe (extrusion stopped)", 60);
    } else {
      line("Area safety: not in this plan");
    }
    if (axis_shown) {
      for (int x = 12; x < 52; x += 10) {
        cv::line(panel, cv::Point(x, y - 6), cv::Point(x + 5, y - 6), cv::Scalar(255, 255, 255), 2);
      }
      line("main axis of region " + std::to_string(scene.region->id), 60);
    }
    y += 6;
    if (tumor_shown || scene.tumor) {
      cv::rectangle(panel, cv::Rect(12, y - 11, 22, 13), bgr(kTumorColour), 2);
      line("tumor", 42);
    }
    if (!structure_rows.empty()) line("Structures (outlines):");
    for (const auto& [text, c] : structure_rows) {
      if (y > H - 6) break;
      cv::rectangle(panel, cv::Rect(12, y - 11, 22, 13), bgr(c), 2);
      line(text, 42);
    }
  }

  view.image.width = out.cols;
  view.image.height = out.rows;
  view.image.rgb.resize(size_t(out.cols) * size_t(out.rows) * 3);
  for (int y = 0; y < out.rows; ++y) {
    for (int x = 0; x < out.cols; ++x) {
      const cv::Vec3b& px = out.at<cv::Vec3b>(y, x);
      const size_t o = (size_t(y) * size_t(out.cols) + size_t(x)) * 3;
      view.image.rgb[o] = px[2];
      view.image.rgb[o + 1] = px[1];
      view.image.rgb[o + 2] = px[0];
    }
  }
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
  const std::string tmp = temporary_sibling(path);
  bool ok = false;
  try {
    ok = cv::imwrite(tmp, m);
  } catch (const cv::Exception& e) {
    ok = false;
  }
  if (!ok) {
    std::error_code ec;
    fs::remove(tmp, ec);
    throw Error(path + ": cannot write PNG image");
  }
  commit_file(tmp, path);
}

// --- The job ------------------------------------------------------------------------------------

nlohmann::json run_slices(const SlicesRequest& req) {
  const auto t0 = std::chrono::steady_clock::now();
  if (req.plan_dir.empty()) throw Error("--plan: a plan folder is required");
  if (req.ct.empty()) throw Error("--ct: the CT is required");
  if (req.out_dir.empty()) throw Error("--out: an output folder is required");
  if (req.planes.empty()) throw Error("--planes: no plane given");

  // Which value: asked for, else svv when computed, else the plan's first.
  std::string value = req.value;
  {
    const std::string json_path = (fs::path(req.plan_dir) / "plan.json").string();
    std::ifstream in(json_path);
    if (!in) throw Error(json_path + ": cannot open (is --plan a plan folder?)");
    nlohmann::json j;
    try {
      in >> j;
    } catch (const nlohmann::json::exception& e) {
      throw Error(json_path + ": not valid JSON (" + e.what() + ")");
    }
    std::vector<std::string> values;
    if (j.contains("parameters") && j["parameters"].contains("values")) {
      for (const auto& v : j["parameters"]["values"]) values.push_back(v.get<std::string>());
    }
    if (value.empty()) {
      if (values.empty()) throw Error(json_path + ": parameters.values is empty");
      value = std::find(values.begin(), values.end(), "svv") != values.end() ? "svv" : values[0];
    }
  }
  PlanLoadOptions load;
  load.blocking = false;
  load.only_value = value;
  load.labels_override = req.labels;
  spdlog::info("reading plan {}", req.plan_dir);
  const PlanData plan = load_plan(req.plan_dir, load);
  spdlog::info("reading CT {}", req.ct);
  const Volume<float> ct = read_volume<float>(req.ct);

  Eigen::Vector3d centre = req.have_at ? req.at : plan.tumor_centre;
  Eigen::Vector3d axis = Eigen::Vector3d::Zero();
  const AreaRegion* region = nullptr;
  if (req.region >= 0) {
    if (!plan.area) {
      throw Error("--region " + std::to_string(req.region) + ": " + req.plan_dir +
                  " has no area safety geometry (area_safety.vtk)");
    }
    for (const auto& r : plan.area->regions) {
      if (r.id == req.region) region = &r;
    }
    if (!region) {
      throw Error("--region " + std::to_string(req.region) + ": no such region (the plan has " +
                  std::to_string(plan.area->regions.size()) + ", numbered from 0)");
    }
    if (!req.have_at) centre = region->centre;
    axis = region->main_axis;
  }
  const bool want_oblique =
      std::find(req.planes.begin(), req.planes.end(), SlicePlaneKind::kOblique) != req.planes.end();
  if (want_oblique && !region) {
    if (!plan.area || plan.area->regions.empty()) {
      throw Error("--planes oblique: the plane follows a safe region's main axis, but " +
                  req.plan_dir + " has no area safety regions (area_safety.vtk)");
    }
    region = &plan.area->regions[0];
    axis = region->main_axis;
    spdlog::info("oblique plane along the main axis of region {} (the largest)", region->id);
  }

  SliceScene scene;
  scene.ct = &ct;
  scene.path_safety = &plan.path_safety.at(value);
  scene.value_name = value;
  scene.classes = plan.classes.at(value);
  scene.labels = plan.labels.empty() ? nullptr : &plan.labels;
  scene.table = plan.table ? &*plan.table : nullptr;
  scene.tumor = plan.tumor.empty() ? nullptr : &plan.tumor;
  scene.area = plan.area ? &*plan.area : nullptr;
  scene.region = region;
  if (!scene.area)
    spdlog::info("{}: no area_safety.vtk; slices show no leeway contour", req.plan_dir);

  // One pixel size for every view of the run, so that the images compare at a glance: the finest
  // spacing of the CT and the plan, divided so that the CT's largest extent spans at least
  // min_view_pixels.
  SliceOptions options = req.options;
  if (!(options.pixel_mm > 0)) {
    const ImageGeometry& g = ct.geometry();
    Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e300), hi = -lo;
    for (int c = 0; c < 8; ++c) {
      const Eigen::Vector3d p = g.index_to_physical(
          Eigen::Vector3d((c & 1) ? g.dims[0] - 0.5 : -0.5, (c & 2) ? g.dims[1] - 0.5 : -0.5,
                          (c & 4) ? g.dims[2] - 0.5 : -0.5));
      lo = lo.cwiseMin(p);
      hi = hi.cwiseMax(p);
    }
    const double finest = std::min(g.spacing.minCoeff(), plan.grid.spacing.minCoeff());
    const double extent = (hi - lo).maxCoeff();
    const int factor = std::max(1, int(std::ceil(options.min_view_pixels / (extent / finest))));
    options.pixel_mm = finest / factor;
  }

  StagedDirectory out(req.out_dir);
  nlohmann::json views = nlohmann::json::array();
  const auto vec = [](const Eigen::Vector3d& p) { return nlohmann::json{p.x(), p.y(), p.z()}; };
  for (const auto kind : req.planes) {
    const SlicePlane plane = make_slice_plane(kind, centre, axis);
    const SliceView view = render_slice(scene, plane, options);
    const std::string file = std::string(plane_name(kind)) + ".png";
    write_png(view.image, out.file(file));
    spdlog::info("{}: {} x {} pixels of {:.2f} mm, {} structures, {} contour segments", file,
                 view.view_width, view.view_height, view.pixel_mm, view.structures.size(),
                 view.contour_segments);
    views.push_back({{"file", file},
                     {"plane", plane_name(kind)},
                     {"centre_lps_mm", vec(plane.centre)},
                     {"right_lps", vec(plane.right)},
                     {"down_lps", vec(plane.down)},
                     {"pixel_0_0_lps_mm", vec(view.origin)},
                     {"pixel_mm", view.pixel_mm},
                     {"view_width", view.view_width},
                     {"view_height", view.view_height},
                     {"image_width", view.image.width},
                     {"image_height", view.image.height},
                     {"structures", view.structures},
                     {"contour_segments", view.contour_segments}});
  }
  nlohmann::json j = {
      {"plan", fs::absolute(req.plan_dir).string()},
      {"ct", fs::absolute(req.ct).string()},
      {"value", value},
      {"palette", req.options.palette == Palette::kColorblind ? "colorblind" : "default"},
      {"window_hu", {{"width", req.options.window_width}, {"level", req.options.window_level}}},
      {"region", region ? nlohmann::json(region->id) : nlohmann::json(nullptr)},
      {"pixel_convention",
       "pixel (x, y) shows pixel_0_0 + x pixel_mm right + y pixel_mm down; the "
       "view occupies columns [0, view_width), the legend the rest"},
      {"views", views}};
  write_text_file(out.file("slices.json"), j.dump(2) + "\n");
  out.commit();
  spdlog::info("slices written to {} ({:.2f} s)", req.out_dir,
               std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  return j;
}

}  // namespace crepuscular::planning
