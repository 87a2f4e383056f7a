// Layer 3 "entry": the entry areas on the skin (patches and contours by leeway) and the planned
// trajectory.
#include "overlay/guidance_drawing.hpp"

#include <algorithm>
#include <cmath>
#include <map>

#include "planning/imaging/ray_march.hpp"

namespace crepuscular::overlay {

namespace {

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

}  // namespace

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

std::vector<GuidanceOverlay::Patch> GuidanceOverlay::entry_patches_of(const planning::PlanData& plan) {
  std::vector<Patch> patches;
  if (!plan.area) return patches;
  const planning::AreaSafetyGeometry& g = *plan.area;
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
        if (auto p = skin_exit_in(plan, g.base[size_t(vertex)], g.normals[size_t(vertex)])) {
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
    if (!patch.triangles.empty()) patches.push_back(std::move(patch));
  }
  return patches;
}

cv::Mat GuidanceOverlay::entry_patch_mask(const Eigen::Isometry3d& T_cam_ct,
                                          const calibration::CameraModel& camera,
                                          int region) const {
  cv::Mat mask(camera.height, camera.width, CV_8U, cv::Scalar(0));
  for (const Patch& p : patches_) {
    if (region < 0 || p.region == region) fill_front_triangles(mask, p, T_cam_ct, camera);
  }
  return mask;
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

}  // namespace crepuscular::overlay
