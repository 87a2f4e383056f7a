#include "overlay/guidance_drawing.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

namespace crepuscular::overlay {

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

cv::Point fixed_px(const Eigen::Vector2d& p, const cv::Point& origin) {
  return cv::Point(int(std::lround(p.x() * 16)) - 16 * origin.x,
                   int(std::lround(p.y() * 16)) - 16 * origin.y);
}

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

void add_text_box(std::vector<Eigen::Vector2d>& px, const std::string& text, const cv::Point& at,
                  double scale, int thickness) {
  int base = 0;
  const cv::Size size = cv::getTextSize(text, cv::FONT_HERSHEY_SIMPLEX, scale, thickness, &base);
  px.emplace_back(at.x - thickness, at.y - size.height - thickness);
  px.emplace_back(at.x + size.width + thickness, at.y + base + thickness);
}

std::optional<Eigen::Vector2d> pixel_of(const Eigen::Vector3d& p, const Eigen::Isometry3d& T_cam_ct,
                                        const calibration::CameraModel& camera) {
  const Eigen::Vector3d q = T_cam_ct * p;
  if (q.z() <= 1.0) return std::nullopt;
  const Eigen::Vector2d x = camera.project(q);
  if (!fits(x)) return std::nullopt;
  return x;
}

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

void paint(cv::Mat& bgra, const cv::Mat& mask, const cv::Scalar& colour, double alpha) {
  bgra.setTo(cv::Scalar(colour[0], colour[1], colour[2], alpha), mask);
}

cv::Scalar leeway_bgr(planning::Palette palette, double leeway) {
  // Every entry area is safe: its leeway runs from the medium colour (a small region) to the safe
  // colour (the largest).
  return bgr(planning::leeway_colour(palette, 0.5 + 0.5 * std::clamp(leeway, 0.0, 1.0)));
}

std::vector<std::vector<cv::Point>> mask_outlines(const cv::Mat& mask) {
  std::vector<std::vector<cv::Point>> outlines;
  cv::findContours(mask.clone(), outlines, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_SIMPLE);
  for (auto& o : outlines)
    for (auto& q : o) q = cv::Point(q.x * 16 + 8, q.y * 16 + 8);  // centres of the pixels
  return outlines;
}

}  // namespace crepuscular::overlay
