// The targeting view's picture, drawn with OpenCV from its geometry.
#include "overlay/targeting_view.hpp"

#include <algorithm>
#include <cmath>
#include <map>

#include <fmt/format.h>
#include <opencv2/imgproc.hpp>

namespace crepuscular::overlay {

namespace {

constexpr int kShift = 4;  // sub-pixel bits of OpenCV drawing
cv::Point fixed(const Eigen::Vector2d& p) {
  return cv::Point(int(std::lround(p.x() * (1 << kShift))), int(std::lround(p.y() * (1 << kShift))));
}

cv::Scalar class_colour(planning::Palette palette, planning::NeedleSafety s) {
  const auto c = planning::class_colours(palette);
  switch (s) {
    case planning::NeedleSafety::kSafe: return cv::Scalar(c[0][2], c[0][1], c[0][0]);
    case planning::NeedleSafety::kMedium: return cv::Scalar(c[1][2], c[1][1], c[1][0]);
    case planning::NeedleSafety::kDangerous: return cv::Scalar(c[2][2], c[2][1], c[2][0]);
    case planning::NeedleSafety::kUnknown: break;
  }
  return cv::Scalar(140, 140, 140);  // grey: not known
}

// Blends `colours` (an image like `image`, BGR) into `image` where mask is set, with weight alpha.
void blend(cv::Mat& image, const cv::Mat& mask, const cv::Mat& colours, double alpha) {
  cv::Mat mixed;
  cv::addWeighted(image, 1.0 - alpha, colours, alpha, 0.0, mixed);
  mixed.copyTo(image, mask);
}
void blend(cv::Mat& image, const cv::Mat& mask, const cv::Scalar& colour, double alpha) {
  blend(image, mask, cv::Mat(image.size(), image.type(), colour), alpha);
}

void text(cv::Mat& image, const std::string& s, cv::Point at, double scale = 0.42,
          cv::Scalar colour = cv::Scalar(215, 215, 215)) {
  cv::putText(image, s, at, cv::FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv::LINE_AA);
}

}  // namespace

std::vector<std::vector<cv::Point2f>> point_cloud_outlines(
    const std::vector<Eigen::Vector2d>& points_px, double radius_px) {
  std::vector<std::vector<cv::Point2f>> out;
  if (points_px.empty()) return out;
  double x0 = 1e30, y0 = 1e30, x1 = -1e30, y1 = -1e30;
  for (const auto& p : points_px) {
    if (!p.allFinite()) continue;
    x0 = std::min(x0, p.x()), y0 = std::min(y0, p.y());
    x1 = std::max(x1, p.x()), y1 = std::max(y1, p.y());
  }
  if (x0 > x1 || x1 - x0 > 8000 || y1 - y0 > 8000) return out;
  const int pad = int(std::ceil(radius_px)) + 2;
  const int bx = int(std::floor(x0)) - pad, by = int(std::floor(y0)) - pad;
  cv::Mat mask(int(std::ceil(y1)) + pad - by + 1, int(std::ceil(x1)) + pad - bx + 1, CV_8U,
               cv::Scalar(0));
  // A disc whose pixels (a pixel more on every side) are all set already would change nothing: the
  // discs inside the outline, most of them, are not drawn again.
  const auto covered = [&](const Eigen::Vector2d& c) {
    const int x0 = std::max(0, int(std::floor(c.x() - radius_px)) - 1);
    const int x1 = std::min(mask.cols - 1, int(std::ceil(c.x() + radius_px)) + 1);
    const int y0 = std::max(0, int(std::floor(c.y() - radius_px)) - 1);
    const int y1 = std::min(mask.rows - 1, int(std::ceil(c.y() + radius_px)) + 1);
    for (int y = y0; y <= y1; ++y) {
      const uint8_t* row = mask.ptr<uint8_t>(y);
      for (int x = x0; x <= x1; ++x) {
        if (row[x] != 255) return false;
      }
    }
    return true;
  };
  for (const auto& p : points_px) {
    if (!p.allFinite()) continue;
    const Eigen::Vector2d c = p - Eigen::Vector2d(bx, by);
    if (covered(c)) continue;
    cv::circle(mask, fixed(c), int(std::lround(radius_px * 16)), cv::Scalar(255), cv::FILLED,
               cv::LINE_8, kShift);
  }
  std::vector<std::vector<cv::Point>> contours;
  cv::findContours(mask, contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_SIMPLE);
  for (const auto& c : contours) {
    std::vector<cv::Point2f> o;
    for (const auto& q : c) o.emplace_back(float(q.x + bx), float(q.y + by));
    out.push_back(std::move(o));
  }
  return out;
}

cv::Mat render_targeting_view(const planning::TargetingGeometry& g, planning::Palette palette,
                              const std::vector<Eigen::Vector3d>& uncertainty) {
  const int n = g.size_px;
  cv::Mat image(n, n, CV_8UC3, cv::Scalar(28, 28, 28));
  if (!g.valid) {
    text(image, "TARGET VIEW", cv::Point(8, 18), 0.5);
    text(image, "needle points away", cv::Point(8, n / 2), 0.5, cv::Scalar(170, 170, 170));
    text(image, "from the tumor", cv::Point(8, n / 2 + 20), 0.5, cv::Scalar(170, 170, 170));
  } else {
    // Polar map: each cell an annular sector where those tilts meet the plane.
    const double ring_deg = g.max_tilt_deg / g.rings;
    const double sector_deg = 360.0 / g.sectors;
    cv::Mat cells(n, n, CV_8UC3, cv::Scalar(0, 0, 0)), cells_mask(n, n, CV_8U, cv::Scalar(0));
    // One fill per class (cells of a class never overlap), and one for the mask.
    std::map<int, std::vector<std::vector<cv::Point>>> by_class;
    std::vector<std::vector<cv::Point>> all;
    for (const planning::PolarCell& c : g.cells) {
      std::vector<cv::Point> poly;
      const int arc = 6;
      for (int k = 0; k <= arc; ++k) {
        const double az = c.azimuth_deg + sector_deg * (double(k) / arc - 0.5);
        poly.push_back(fixed(g.tilt_px((c.ring + 1) * ring_deg, az)));
      }
      for (int k = arc; k >= 0; --k) {
        const double az = c.azimuth_deg + sector_deg * (double(k) / arc - 0.5);
        poly.push_back(fixed(g.tilt_px(c.ring * ring_deg, az)));
      }
      by_class[int(c.safety)].push_back(poly);
      all.push_back(std::move(poly));
    }
    for (const auto& [safety, polys] : by_class) {
      cv::fillPoly(cells, polys, class_colour(palette, static_cast<planning::NeedleSafety>(safety)),
                   cv::LINE_8, kShift);
    }
    if (!all.empty()) cv::fillPoly(cells_mask, all, cv::Scalar(255), cv::LINE_8, kShift);
    blend(image, cells_mask, cells, 0.75);
    // Tilt rings: every ring's outer edge, the outer ones labelled.
    const double ring_px = std::abs(g.pivot_to_plane_mm) / g.mm_per_px;
    for (int r = 1; r <= g.rings; ++r) {
      const double tilt = r * ring_deg;
      const double radius = ring_px * std::tan(tilt * M_PI / 180.0);
      cv::circle(image, fixed(g.crossing_px), int(std::lround(radius * 16)),
                 cv::Scalar(90, 90, 90), 1, cv::LINE_AA, kShift);
      if (r == g.rings || r == (g.rings + 1) / 2) {
        const Eigen::Vector2d at = g.crossing_px + Eigen::Vector2d(radius * 0.71, -radius * 0.71);
        text(image, fmt::format("{:.0f}deg", tilt), cv::Point(int(at.x()) + 2, int(at.y()) - 2),
             0.35, cv::Scalar(200, 200, 200));
      }
    }
    // The tumor: filled translucently, outlined, its centre marked.
    const cv::Scalar magenta(255, 0, 255);
    const auto outlines = point_cloud_outlines(g.tumor_px, g.tumor_point_radius_px);
    std::vector<std::vector<cv::Point>> polys;
    for (const auto& o : outlines) {
      // The outline steps from pixel to pixel: within half a pixel, far fewer segments to draw.
      std::vector<cv::Point2f> simple;
      cv::approxPolyDP(o, simple, 0.5, true);
      std::vector<cv::Point> p;
      for (const auto& q : simple) p.push_back(fixed(Eigen::Vector2d(q.x, q.y)));
      polys.push_back(std::move(p));
    }
    cv::Mat tumor_mask(n, n, CV_8U, cv::Scalar(0));
    cv::fillPoly(tumor_mask, polys, cv::Scalar(255), cv::LINE_8, kShift);
    blend(image, tumor_mask, magenta, 0.15);
    cv::polylines(image, polys, true, magenta, 2, cv::LINE_AA, kShift);
    cv::circle(image, fixed(g.centre_px), 4 * 16, magenta, 1, cv::LINE_AA, kShift);
    // The needle's crossing: a white cross (arms 11 px), or an arrow at the edge toward it.
    const Eigen::Vector2d q = g.crossing_px;
    if (q.x() >= 6 && q.y() >= 6 && q.x() <= n - 7 && q.y() <= n - 7) {
      for (const Eigen::Vector2d& d : {Eigen::Vector2d(11, 0), Eigen::Vector2d(0, 11)}) {
        cv::line(image, fixed(q - d), fixed(q + d), kTargetingCrossColour, 2, cv::LINE_8, kShift);
      }
    } else {
      const Eigen::Vector2d dir = (q - g.centre_px).normalized();
      const Eigen::Vector2d tip = g.centre_px + dir * (0.5 * n - 12);
      cv::arrowedLine(image, fixed(tip - 30 * dir), fixed(tip), kTargetingCrossColour, 2,
                      cv::LINE_8, kShift, 0.35);
    }
    // Where the needle's line may cross the plane (95 %): a thin white ellipse around the cross.
    if (uncertainty.size() >= 3) {
      std::vector<cv::Point> ellipse;
      for (const auto& p : uncertainty) ellipse.push_back(fixed(g.to_px(p)));
      cv::polylines(image, std::vector<std::vector<cv::Point>>{ellipse}, true,
                    kTargetingCrossColour, 1, cv::LINE_AA, kShift);
    }
    // Beyond the map: an arrow toward the nearest safe direction, with its tilt.
    if (std::isfinite(g.nearest_safe_deg) && g.nearest_safe_deg > g.max_tilt_deg) {
      const double a = g.nearest_safe_azimuth_deg * M_PI / 180.0;
      const Eigen::Vector2d dir(std::cos(a), std::sin(a));
      const double r0 = ring_px * std::tan(g.max_tilt_deg * M_PI / 180.0) + 4;
      const Eigen::Vector2d from = g.crossing_px + r0 * dir, to = from + 28 * dir;
      const cv::Scalar green = class_colour(palette, planning::NeedleSafety::kSafe);
      cv::arrowedLine(image, fixed(from), fixed(to), green, 2, cv::LINE_AA, kShift, 0.35);
      // The label stays inside the view, whichever way the arrow points.
      const std::string label = fmt::format("safe {:.0f}deg", g.nearest_safe_deg);
      int baseline = 0;
      const cv::Size size = cv::getTextSize(label, cv::FONT_HERSHEY_SIMPLEX, 0.4, 1, &baseline);
      const int x = std::clamp(int(to.x()) + (dir.x() < 0 ? -size.width - 4 : 4), 2,
                               n - size.width - 2);
      const int y = std::clamp(int(to.y()) + (dir.y() < 0 ? -4 : 12), size.height + 2, n - 40);
      text(image, label, cv::Point(x, y), 0.4, green);
    }
    const double miss = (g.crossing - g.centre).norm();
    text(image, fmt::format("needle misses centre by {:.1f} mm", miss), cv::Point(8, n - 10));
    // Scale bar: 10 mm.
    const int bar = int(std::lround(10.0 / g.mm_per_px));
    cv::line(image, cv::Point(n - 12 - bar, n - 24), cv::Point(n - 12, n - 24),
             cv::Scalar(200, 200, 200), 1);
    text(image, "10 mm", cv::Point(n - 12 - bar, n - 30), 0.35);
    text(image, "TARGET VIEW: down the needle", cv::Point(8, 16));
    text(image, "+ needle  o tumor centre", cv::Point(8, 32), 0.35);
    text(image, "tilt toward green", cv::Point(8, 46), 0.35);
  }
  cv::rectangle(image, cv::Rect(0, 0, n, n), cv::Scalar(170, 170, 170), 1);
  cv::Mat bgra;
  cv::cvtColor(image, bgra, cv::COLOR_BGR2BGRA);
  return bgra;
}

}  // namespace crepuscular::overlay
