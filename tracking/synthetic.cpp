// Synthetic frames: ray tracing of planar tag and plate surfaces through the exact inverse of the
// camera's distortion, adaptive supersampling at edges, then lighting, occlusion, blur and noise;
// scene files; the built-in guidance scene.
#include "tracking/synthetic.hpp"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <functional>
#include <limits>
#include <map>
#include <nlohmann/json.hpp>
#include <optional>
#include <random>

#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>

#include "foundation/error.hpp"
#include "foundation/json_fields.hpp"
#include "foundation/log.hpp"
#include "recordings/recording.hpp"

namespace crepuscular::tracking {

namespace {

using nlohmann::json;
constexpr double kPi = 3.14159265358979323846;
constexpr double kDeg = kPi / 180.0;

// A planar parallelogram in the camera frame: points O + u U + v V, (u, v) in [0, 1)^2, seen from
// the side its normal N = U x V points away from (the printed face).
struct Surface {
  Eigen::Vector3d O, N, a, b;  // a, b: dual basis, u = a . (P - O), v = b . (P - O)
  double n_dot_o = 0;
  double depth_bias = 0;        // tags win over the plate they lie on
  const TagPattern* pattern = nullptr;  // nullptr: plain plate
  int x0 = 0, y0 = 0, x1 = -1, y1 = -1;  // pixel bounding box, inclusive
};

Eigen::Isometry3d make_pose(const Eigen::Quaterniond& q, const Eigen::Vector3d& t) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = q.normalized().toRotationMatrix();
  T.translation() = t;
  return T;
}

Eigen::Quaterniond rotvec_deg(const Eigen::Vector3d& r) {
  const double angle = r.norm() * kDeg;
  if (angle < 1e-15) return Eigen::Quaterniond::Identity();
  return Eigen::Quaterniond(Eigen::AngleAxisd(angle, r.normalized()));
}

}  // namespace

SyntheticScene::SyntheticScene() {
  camera.width = 1280;
  camera.height = 720;
  camera.fx = camera.fy = 1000.0;
  camera.cx = 639.5;
  camera.cy = 359.5;
}

void SyntheticScene::validate(const std::string& what) const {
  camera.validate(what + ": camera");
  if (background != "plain" && background != "gradient" && background != "noise") {
    throw Error(what + ": background '" + background + "', expected plain, gradient or noise");
  }
  if (!(fps > 0) || fps > 10000) throw Error(what + ": fps must be > 0");
  if (frame_count < 1) throw Error(what + ": frames must be >= 1");
  // Blur beyond 50 px (a picture with no tag left) would only exhaust memory in its kernel.
  if (!(noise_sigma >= 0 && noise_sigma <= 255) || !(blur_sigma >= 0 && blur_sigma <= 50)) {
    throw Error(what + ": noise_sigma must be 0 to 255 and blur_sigma 0 to 50 (pixels)");
  }
  if (supersampling < 1 || supersampling > 32) {
    throw Error(what + ": supersampling " + std::to_string(supersampling) + ", expected 1 to 32");
  }
  if (boards.empty()) throw Error(what + ": no boards");
  for (const SceneBoard& b : boards) {
    if (b.keyframes.empty()) {
      throw Error(what + ": board '" + b.board.name + "' has no poses (keyframes)");
    }
    for (size_t k = 1; k < b.keyframes.size(); ++k) {
      if (!(b.keyframes[k].time_s > b.keyframes[k - 1].time_s)) {
        throw Error(what + ": poses of board '" + b.board.name +
                    "' must have increasing times \"t\"");
      }
    }
    for (const BoardTag& t : b.board.tags) tag_pattern(b.board.family, t.id);
  }
  for (const SceneMesh& mesh : meshes) {
    const std::string name = what + ": mesh '" + mesh.name + "'";
    const bool known = std::any_of(boards.begin(), boards.end(),
                                   [&](const SceneBoard& b) { return b.board.name == mesh.board; });
    if (!known) throw Error(name + " is attached to '" + mesh.board + "', which is no board");
    if (mesh.colours.size() != mesh.vertices.size()) {
      throw Error(name + ": " + std::to_string(mesh.colours.size()) + " colours for " +
                  std::to_string(mesh.vertices.size()) + " vertices, expected one per vertex");
    }
    for (const Eigen::Vector3f& v : mesh.vertices) {
      if (!v.allFinite()) throw Error(name + ": a vertex is not finite");
    }
    for (const Eigen::Vector3i& t : mesh.triangles) {
      for (int i = 0; i < 3; ++i) {
        if (t[i] < 0 || size_t(t[i]) >= mesh.vertices.size()) {
          throw Error(name + ": triangle vertex index " + std::to_string(t[i]) + ", expected 0 to " +
                      std::to_string(int64_t(mesh.vertices.size()) - 1));
        }
      }
    }
  }
}

Eigen::Isometry3d pose_at(const SceneBoard& board, double time_s) {
  const auto& k = board.keyframes;
  if (k.empty()) return Eigen::Isometry3d::Identity();
  if (time_s <= k.front().time_s) return k.front().T_cam_board;
  if (time_s >= k.back().time_s) return k.back().T_cam_board;
  size_t i = 1;
  while (k[i].time_s < time_s) ++i;
  const double s = (time_s - k[i - 1].time_s) / (k[i].time_s - k[i - 1].time_s);
  const Eigen::Quaterniond q0(k[i - 1].T_cam_board.linear());
  const Eigen::Quaterniond q1(k[i].T_cam_board.linear());
  const Eigen::Vector3d t =
      (1.0 - s) * k[i - 1].T_cam_board.translation() + s * k[i].T_cam_board.translation();
  return make_pose(q0.slerp(s, q1), t);
}

// ---------------------------------------------------------------------------------------------
// Renderer

namespace {

// What every frame of a renderer shares: the camera's pixel rays, the background, the patterns.
struct RenderTables {
  int w = 0, h = 0;
  // Undistorted normalised image coordinates of the pixel corners: node (i, j) is pixel
  // coordinate (i - 0.5, j - 0.5); (w + 1) x (h + 1) nodes.
  std::vector<Eigen::Vector2d> nodes;
  cv::Mat background;  // CV_32F, grey levels
  std::map<std::pair<std::string, int>, TagPattern> patterns;
  TagPattern ink{cv::Mat(1, 1, CV_8U, cv::Scalar(0)), 1, 1};  // a solid black square

  const Eigen::Vector2d& node(int i, int j) const { return nodes[size_t(j) * size_t(w + 1) + i]; }
};

// The parallelogram O + u U + v V (board frame vectors o_b, u_b, v_b mapped by T into the camera
// frame) with its pixel bounding box; nothing when it is degenerate or covers no pixel.
std::optional<Surface> make_surface(const calibration::CameraModel& cam, const RenderTables& m,
                                    const Eigen::Isometry3d& T, const Eigen::Vector3d& o_b,
                                    const Eigen::Vector3d& u_b, const Eigen::Vector3d& v_b,
                                    const TagPattern* pattern, double bias) {
  Surface s;
  s.O = T * o_b;
  const Eigen::Vector3d U = T.linear() * u_b, V = T.linear() * v_b;
  s.N = U.cross(V);
  if (s.N.norm() < 1e-12) return std::nullopt;
  const Eigen::Vector3d vn = V.cross(s.N), nu = s.N.cross(U);
  s.a = vn / U.dot(vn);
  s.b = nu / V.dot(nu);
  s.n_dot_o = s.N.dot(s.O);
  s.pattern = pattern;
  s.depth_bias = bias;
  // Bounding box from points along the boundary (edges curve under distortion).
  double x0 = 1e300, y0 = 1e300, x1 = -1e300, y1 = -1e300;
  bool behind = false;
  constexpr int kSteps = 24;
  for (int e = 0; e < 4 && !behind; ++e) {
    for (int k = 0; k < kSteps; ++k) {
      const double f = double(k) / kSteps;
      const double uu = e == 0 ? f : e == 1 ? 1.0 : e == 2 ? 1.0 - f : 0.0;
      const double vv = e == 0 ? 0.0 : e == 1 ? f : e == 2 ? 1.0 : 1.0 - f;
      const Eigen::Vector3d p = s.O + uu * U + vv * V;
      if (p.z() < 1.0) {
        behind = true;
        break;
      }
      const Eigen::Vector2d px = cam.project(p);
      x0 = std::min(x0, px.x());
      y0 = std::min(y0, px.y());
      x1 = std::max(x1, px.x());
      y1 = std::max(y1, px.y());
    }
  }
  if (behind) {
    s.x0 = 0;
    s.y0 = 0;
    s.x1 = m.w - 1;
    s.y1 = m.h - 1;
  } else {
    s.x0 = std::max(0, int(std::floor(x0)) - 2);
    s.y0 = std::max(0, int(std::floor(y0)) - 2);
    s.x1 = std::min(m.w - 1, int(std::ceil(x1)) + 2);
    s.y1 = std::min(m.h - 1, int(std::ceil(y1)) + 2);
  }
  if (s.x0 > s.x1 || s.y0 > s.y1) return std::nullopt;
  return s;
}

// The surfaces of one board at pose T (camera frame): its plate, when it has one, and its tags.
void add_board_surfaces(const SceneBoard& sb, const Eigen::Isometry3d& T,
                        const calibration::CameraModel& cam, const RenderTables& m,
                        std::vector<Surface>& surfaces) {
  const auto add = [&](const Eigen::Vector3d& o_b, const Eigen::Vector3d& u_b,
                       const Eigen::Vector3d& v_b, const TagPattern* pattern, double bias) {
    if (auto s = make_surface(cam, m, T, o_b, u_b, v_b, pattern, bias)) surfaces.push_back(*s);
  };
  // The plate: the rectangle around the tags' outer (white ring) corners plus the margin.
  bool planar = true;
  double bx0 = 1e300, by0 = 1e300, bx1 = -1e300, by1 = -1e300;
  for (const BoardTag& tag : sb.board.tags) {
    const TagPattern& p = m.patterns.at({sb.board.family, tag.id});
    const double grow = double(p.border_start()) / p.width_at_border;
    for (const Eigen::Vector3d& c : tag.corners) {
      planar = planar && std::abs(c.z()) < 1e-9;
      const Eigen::Vector3d outer = c + grow * (c - tag.center());
      bx0 = std::min(bx0, outer.x());
      by0 = std::min(by0, outer.y());
      bx1 = std::max(bx1, outer.x());
      by1 = std::max(by1, outer.y());
    }
  }
  // Printed squares beside the tags (Kalibr's corner squares, a ChArUco chessboard), with the
  // edge directions of the first tag.
  Eigen::Vector3d ex = Eigen::Vector3d::UnitX(), ey = Eigen::Vector3d::UnitY();
  if (!sb.board.tags.empty()) {
    const BoardTag& t = sb.board.tags.front();
    ex = (t.corners[2] - t.corners[3]).normalized();
    ey = (t.corners[0] - t.corners[3]).normalized();
  }
  for (const Board::InkSquare& q : sb.board.ink_squares) {
    const Eigen::Vector3d half = 0.5 * q.side_mm * (ex + ey);
    for (const Eigen::Vector3d& c : {Eigen::Vector3d(q.centre - half), Eigen::Vector3d(q.centre + half)}) {
      planar = planar && std::abs(c.z()) < 1e-9;
      bx0 = std::min(bx0, c.x());
      by0 = std::min(by0, c.y());
      bx1 = std::max(bx1, c.x());
      by1 = std::max(by1, c.y());
    }
  }
  if (sb.plate && planar) {
    // Printed on the side the tags face (boards whose frame has z out of the print, as Kalibr's,
    // face +z).
    const double g = sb.plate_margin_mm, w = bx1 - bx0 + 2 * g, h = by1 - by0 + 2 * g;
    if (ex.cross(ey).z() >= 0) {
      add({bx0 - g, by0 - g, 0}, {w, 0, 0}, {0, h, 0}, nullptr, 0.0);
    } else {
      add({bx0 - g, by1 + g, 0}, {w, 0, 0}, {0, -h, 0}, nullptr, 0.0);
    }
  }
  for (const Board::InkSquare& q : sb.board.ink_squares) {
    add(q.centre - 0.5 * q.side_mm * (ex + ey), q.side_mm * ex, q.side_mm * ey, &m.ink, 1e-3);
  }
  for (const BoardTag& tag : sb.board.tags) {
    const TagPattern& p = m.patterns.at({sb.board.family, tag.id});
    // Cell vectors: along the tag's top edge (top-left -> top-right) and down its left edge.
    const Eigen::Vector3d ex = (tag.corners[2] - tag.corners[3]) / p.width_at_border;
    const Eigen::Vector3d ey = (tag.corners[0] - tag.corners[3]) / p.width_at_border;
    const Eigen::Vector3d origin = tag.corners[3] - p.border_start() * (ex + ey);
    add(origin, ex * p.total_width, ey * p.total_width, &p, 1e-3);
  }
}

// Sample positions (a, b) in [0, 1]^2 inside an edge pixel: a Fibonacci lattice (rank-1 lattice
// of N points with generator the preceding Fibonacci number), N distinct positions along each
// axis, well spread in 2D; one central sample without supersampling.
std::vector<std::pair<double, double>> edge_lattice(int supersampling) {
  int fib_a = 1, fib_b = 1;
  while (fib_b < supersampling * supersampling) {
    const int next = fib_a + fib_b;
    fib_a = fib_b;
    fib_b = next;
  }
  const int n_samples = supersampling <= 1 ? 1 : fib_b;
  std::vector<std::pair<double, double>> lattice;
  for (int k = 0; k < n_samples; ++k) {
    const double a = (k + 0.5) / n_samples;
    const double b = std::fmod((double(k) * fib_a + 0.5) / n_samples, 1.0);
    lattice.emplace_back(a, n_samples == 1 ? 0.5 : b);
  }
  return lattice;
}

// The value seen along the camera ray d (camera frame) among the candidate surfaces: the nearest
// one's ink or paper level; NaN = background.
double shade_ray(const std::vector<const Surface*>& cands, const Eigen::Vector3d& d, double black,
                 double white, double mesh_depth) {
  double best = mesh_depth;  // a mesh nearer than a surface hides it
  double value = std::numeric_limits<double>::quiet_NaN();
  for (const Surface* s : cands) {
    const double nd = s->N.dot(d);
    if (!(nd > 0)) continue;  // seen from behind, or edge-on
    const double lambda = s->n_dot_o / nd;
    if (!(lambda > 0)) continue;
    const double z = lambda - s->depth_bias;
    if (z >= best) continue;
    const Eigen::Vector3d q = lambda * d - s->O;
    const double u = s->a.dot(q), v = s->b.dot(q);
    if (u < 0 || u >= 1 || v < 0 || v >= 1) continue;
    best = z;
    if (s->pattern) {
      const int n = s->pattern->total_width;
      const int col = std::min(n - 1, int(u * n));
      const int row = std::min(n - 1, int(v * n));
      value = s->pattern->cells.at<uint8_t>(row, col) ? white : black;
    } else {
      value = white;
    }
  }
  return value;
}

// Traces every pixel that a surface may cover into img (CV_32FC3, holding the background and the
// meshes, whose camera depth is in mesh_depth, CV_32F): a 3 x 3 probe, and the whole lattice
// where the probe sees more than one value.
void trace_surfaces(const RenderTables& m, const std::vector<Surface>& surfaces,
                    const std::vector<std::pair<double, double>>& lattice, double black,
                    double white, const cv::Mat& mesh_depth, cv::Mat& img) {
  cv::parallel_for_(cv::Range(0, m.h), [&](const cv::Range& rows) {
    std::vector<const Surface*> cands, in_row;
    for (int y = rows.start; y < rows.end; ++y) {
      cv::Vec3f* out = img.ptr<cv::Vec3f>(y);
      const float* zrow = mesh_depth.ptr<float>(y);
      // Rows and columns that any surface may cover: the only pixels that need tracing.
      in_row.clear();
      int row_x0 = m.w, row_x1 = -1;
      for (const Surface& s : surfaces) {
        if (y < s.y0 || y > s.y1) continue;
        in_row.push_back(&s);
        row_x0 = std::min(row_x0, s.x0);
        row_x1 = std::max(row_x1, s.x1);
      }
      for (int x = row_x0; x <= row_x1; ++x) {
        cands.clear();
        for (const Surface* s : in_row) {
          if (x >= s->x0 && x <= s->x1) cands.push_back(s);
        }
        if (cands.empty()) continue;
        const double zmesh = double(zrow[x]);
        const Eigen::Vector2d& g00 = m.node(x, y);
        const Eigen::Vector2d& g10 = m.node(x + 1, y);
        const Eigen::Vector2d& g01 = m.node(x, y + 1);
        const Eigen::Vector2d& g11 = m.node(x + 1, y + 1);
        // Value seen along the ray through (a, b) of this pixel (a, b in [0, 1] from its top-left
        // corner); NaN = background.
        const auto shade = [&](double a, double b) {
          const Eigen::Vector2d xy =
              (1 - a) * (1 - b) * g00 + a * (1 - b) * g10 + (1 - a) * b * g01 + a * b * g11;
          return shade_ray(cands, Eigen::Vector3d(xy.x(), xy.y(), 1.0), black, white, zmesh);
        };
        // Probe a 3 x 3 pattern; a pixel that sees one value everywhere needs no more samples.
        constexpr double kProbe[3] = {1.0 / 64, 0.5, 63.0 / 64};
        double first = shade(kProbe[0], kProbe[0]);
        bool uniform = true;
        for (int pj = 0; pj < 3 && uniform; ++pj) {
          for (int pi = 0; pi < 3 && uniform; ++pi) {
            const double v = shade(kProbe[pi], kProbe[pj]);
            uniform = (std::isnan(v) && std::isnan(first)) || v == first;
          }
        }
        const cv::Vec3d bg = out[x];
        if (uniform) {
          if (!std::isnan(first)) out[x] = cv::Vec3f(float(first), float(first), float(first));
          continue;
        }
        cv::Vec3d sum(0, 0, 0);
        int n_bg = 0;
        double grey = 0;
        for (const auto& [a, b] : lattice) {
          const double v = shade(a, b);
          if (std::isnan(v)) {
            ++n_bg;
          } else {
            grey += v;
          }
        }
        sum = bg * double(n_bg) + cv::Vec3d(grey, grey, grey);
        const double n = double(lattice.size());
        out[x] = cv::Vec3f(float(sum[0] / n), float(sum[1] / n), float(sum[2] / n));
      }
    }
  });
}

// The meshes at time t drawn into img (CV_32FC3) and depth (CV_32F, camera z, +inf where none):
// vertices projected through the camera model (distortion included), triangles filled where
// their projection covers a pixel centre, depth interpolated as 1/z, colours (lit per vertex)
// interpolated linearly; a triangle with a vertex less than 10 mm in front of the camera is left out.
void draw_meshes(const SyntheticScene& scene, const std::vector<std::vector<Eigen::Vector3f>>& normals,
                 double t, cv::Mat* img, cv::Mat& depth) {
  const calibration::CameraModel& cam = scene.camera;
  const int w = cam.width, h = cam.height;
  depth = cv::Mat(h, w, CV_32F, cv::Scalar(std::numeric_limits<float>::infinity()));
  // A light above the camera and behind it: surfaces facing the camera are lit.
  const Eigen::Vector3d light = Eigen::Vector3d(0.25, -0.6, -1.0).normalized();
  struct Projected {
    std::vector<Eigen::Vector3f> px;  // x, y pixel; z camera depth (<= 0: unusable)
    std::vector<cv::Vec3f> colour;
  };
  std::vector<Projected> projected(scene.meshes.size());
  for (size_t k = 0; k < scene.meshes.size(); ++k) {
    const SceneMesh& mesh = scene.meshes[k];
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    for (const SceneBoard& b : scene.boards) {
      if (b.board.name == mesh.board) T = pose_at(b, t);
    }
    Projected& p = projected[k];
    p.px.resize(mesh.vertices.size());
    p.colour.resize(mesh.vertices.size());
    cv::parallel_for_(cv::Range(0, int(mesh.vertices.size())), [&](const cv::Range& r) {
      for (int i = r.start; i < r.end; ++i) {
        const Eigen::Vector3d q = T * mesh.vertices[size_t(i)].cast<double>();
        if (q.z() < 10.0) {
          p.px[size_t(i)] = Eigen::Vector3f(0, 0, -1);
          continue;
        }
        const Eigen::Vector2d uv = cam.project(q);
        p.px[size_t(i)] = Eigen::Vector3f(float(uv.x()), float(uv.y()), float(q.z()));
        const Eigen::Vector3d n = T.linear() * normals[k][size_t(i)].cast<double>();
        const double lit = 0.35 + 0.65 * std::abs(n.dot(light));
        const Eigen::Vector3f& c = mesh.colours[size_t(i)];
        p.colour[size_t(i)] = cv::Vec3f(float(c.x() * lit), float(c.y() * lit), float(c.z() * lit));
      }
    });
  }
  // Bands of rows in parallel; every band walks all triangles.
  constexpr int kBand = 32;
  const int n_bands = (h + kBand - 1) / kBand;
  cv::parallel_for_(cv::Range(0, n_bands), [&](const cv::Range& bands) {
    for (int band = bands.start; band < bands.end; ++band) {
      const int by0 = band * kBand, by1 = std::min(h - 1, by0 + kBand - 1);
      for (size_t k = 0; k < scene.meshes.size(); ++k) {
        const Projected& p = projected[k];
        for (const Eigen::Vector3i& tri : scene.meshes[k].triangles) {
          const Eigen::Vector3f& a = p.px[size_t(tri[0])];
          const Eigen::Vector3f& b = p.px[size_t(tri[1])];
          const Eigen::Vector3f& c = p.px[size_t(tri[2])];
          if (!(a.z() > 0 && b.z() > 0 && c.z() > 0)) continue;
          const int y0 = std::max(by0, int(std::ceil(std::min({a.y(), b.y(), c.y()}))));
          const int y1 = std::min(by1, int(std::floor(std::max({a.y(), b.y(), c.y()}))));
          if (y0 > y1) continue;
          const int x0 = std::max(0, int(std::ceil(std::min({a.x(), b.x(), c.x()}))));
          const int x1 = std::min(w - 1, int(std::floor(std::max({a.x(), b.x(), c.x()}))));
          if (x0 > x1) continue;
          const double area = double(b.x() - a.x()) * double(c.y() - a.y()) -
                              double(b.y() - a.y()) * double(c.x() - a.x());
          if (std::abs(area) < 1e-12) continue;
          const double inv_area = 1.0 / area;
          const double iza = 1.0 / a.z(), izb = 1.0 / b.z(), izc = 1.0 / c.z();
          const cv::Vec3f& ca = p.colour[size_t(tri[0])];
          const cv::Vec3f& cb = p.colour[size_t(tri[1])];
          const cv::Vec3f& cc = p.colour[size_t(tri[2])];
          for (int y = y0; y <= y1; ++y) {
            float* zrow = depth.ptr<float>(y);
            cv::Vec3f* row = img ? img->ptr<cv::Vec3f>(y) : nullptr;
            for (int x = x0; x <= x1; ++x) {
              // Barycentric weights of the pixel centre (x, y).
              const double wa = (double(b.x() - x) * double(c.y() - y) -
                                 double(b.y() - y) * double(c.x() - x)) * inv_area;
              const double wb = (double(c.x() - x) * double(a.y() - y) -
                                 double(c.y() - y) * double(a.x() - x)) * inv_area;
              const double wc = 1.0 - wa - wb;
              // Pixel centres on an edge shared by two triangles belong to both.
              constexpr double kEdge = -1e-9;
              if (wa < kEdge || wb < kEdge || wc < kEdge) continue;
              const float z = float(1.0 / (wa * iza + wb * izb + wc * izc));
              if (!(z < zrow[x])) continue;
              zrow[x] = z;
              if (row) {
                row[x] = cv::Vec3f(float(wa * ca[0] + wb * cb[0] + wc * cc[0]),
                                   float(wa * ca[1] + wb * cb[1] + wc * cc[1]),
                                   float(wa * ca[2] + wb * cb[2] + wc * cc[2]));
              }
            }
          }
        }
      }
    }
  });
}

// Area-weighted vertex normals of a mesh (board frame).
std::vector<Eigen::Vector3f> vertex_normals(const SceneMesh& mesh) {
  std::vector<Eigen::Vector3f> n(mesh.vertices.size(), Eigen::Vector3f::Zero());
  for (const Eigen::Vector3i& t : mesh.triangles) {
    const Eigen::Vector3f a = mesh.vertices[size_t(t[0])], b = mesh.vertices[size_t(t[1])],
                          c = mesh.vertices[size_t(t[2])];
    const Eigen::Vector3f f = (b - a).cross(c - a);
    for (int i = 0; i < 3; ++i) n[size_t(t[i])] += f;
  }
  for (Eigen::Vector3f& v : n) {
    const float len = v.norm();
    v = len > 0 ? Eigen::Vector3f(v / len) : Eigen::Vector3f(0, 0, -1);
  }
  return n;
}

// What the camera adds to the traced grey levels of a frame: occlusions, lighting, blur and
// noise; then 8-bit BGR.
cv::Mat apply_camera_effects(const SyntheticScene& scene, int64_t frame, cv::Mat img) {
  for (const OcclusionBox& o : scene.occlusions) {
    if (frame < o.first_frame || frame > o.last_frame) continue;
    const cv::Rect r = cv::Rect(cv::Point(int(std::floor(o.rect_px.x)), int(std::floor(o.rect_px.y))),
                                cv::Point(int(std::ceil(o.rect_px.x + o.rect_px.width)),
                                          int(std::ceil(o.rect_px.y + o.rect_px.height)))) &
                       cv::Rect(0, 0, img.cols, img.rows);
    if (r.area() > 0) img(r).setTo(cv::Scalar(o.grey, o.grey, o.grey));
  }
  if (scene.gain != 1.0 || scene.offset != 0.0) {
    img.convertTo(img, CV_32FC3, scene.gain, scene.offset);
  }
  if (scene.blur_sigma > 0) {
    cv::GaussianBlur(img, img, cv::Size(0, 0), scene.blur_sigma, scene.blur_sigma,
                     cv::BORDER_REPLICATE);
  }
  if (scene.noise_sigma > 0) {
    // One noise value per pixel for its three channels (a grey scene stays grey).
    cv::Mat noise(img.size(), CV_32F), noise3;
    cv::RNG rng(scene.seed * 1000003ULL + uint64_t(frame) * 7919ULL + 1ULL);
    rng.fill(noise, cv::RNG::NORMAL, 0.0, scene.noise_sigma);
    cv::cvtColor(noise, noise3, cv::COLOR_GRAY2BGR);
    img += noise3;
  }
  cv::Mat bgr;
  img.convertTo(bgr, CV_8UC3);  // rounds and saturates
  return bgr;
}

}  // namespace

struct SyntheticRenderer::Impl : RenderTables {
  std::vector<std::vector<Eigen::Vector3f>> normals;  // per mesh, per vertex (board frame)
};

SyntheticRenderer::SyntheticRenderer(SyntheticScene scene)
    : scene_(std::move(scene)), impl_(std::make_unique<Impl>()) {
  scene_.validate("synthetic scene");
  Impl& m = *impl_;
  const calibration::CameraModel& cam = scene_.camera;
  m.w = cam.width;
  m.h = cam.height;
  m.nodes.resize(size_t(m.w + 1) * size_t(m.h + 1));
  // Exact unprojection on a coarse lattice, then every node by Newton's method from the bilinear
  // interpolation of its lattice cell (converges in one or two steps to the exact inverse).
  constexpr int kStep = 8;
  const int cw = m.w / kStep + 2, ch = m.h / kStep + 2;
  std::vector<Eigen::Vector2d> coarse(size_t(cw) * size_t(ch));
  cv::parallel_for_(cv::Range(0, ch), [&](const cv::Range& rows) {
    for (int j = rows.start; j < rows.end; ++j) {
      for (int i = 0; i < cw; ++i) {
        coarse[size_t(j) * cw + i] = cam.unproject({i * kStep - 0.5, j * kStep - 0.5});
      }
    }
  });
  cv::parallel_for_(cv::Range(0, m.h + 1), [&](const cv::Range& rows) {
    for (int j = rows.start; j < rows.end; ++j) {
      const int cj = j / kStep;
      const double b = double(j - cj * kStep) / kStep;
      for (int i = 0; i <= m.w; ++i) {
        const int ci = i / kStep;
        const double a = double(i - ci * kStep) / kStep;
        const Eigen::Vector2d guess = (1 - a) * (1 - b) * coarse[size_t(cj) * cw + ci] +
                                      a * (1 - b) * coarse[size_t(cj) * cw + ci + 1] +
                                      (1 - a) * b * coarse[size_t(cj + 1) * cw + ci] +
                                      a * b * coarse[size_t(cj + 1) * cw + ci + 1];
        m.nodes[size_t(j) * size_t(m.w + 1) + i] = cam.unproject({i - 0.5, j - 0.5}, guess);
      }
    }
  });
  // Background.
  m.background = cv::Mat(m.h, m.w, CV_32F, cv::Scalar(scene_.background_grey));
  if (scene_.background == "gradient") {
    for (int y = 0; y < m.h; ++y) {
      float* row = m.background.ptr<float>(y);
      for (int x = 0; x < m.w; ++x) {
        const double s = 0.5 * (double(x) / std::max(1, m.w - 1) + double(y) / std::max(1, m.h - 1));
        row[x] = float(scene_.background_grey + scene_.background_contrast * (s - 0.5));
      }
    }
  } else if (scene_.background == "noise") {
    cv::RNG rng(scene_.seed * 7919 + 17);
    cv::Mat texture(m.h, m.w, CV_32F, cv::Scalar(0));
    for (int scale : {64, 16, 4}) {
      cv::Mat small(std::max(2, m.h / scale), std::max(2, m.w / scale), CV_32F);
      rng.fill(small, cv::RNG::UNIFORM, -1.0, 1.0);
      cv::Mat up;
      cv::resize(small, up, cv::Size(m.w, m.h), 0, 0, cv::INTER_CUBIC);
      texture += up * (scale / 64.0 + 0.15);
    }
    double lo = 0, hi = 0;
    cv::minMaxLoc(texture, &lo, &hi);
    const double span = std::max(hi - lo, 1e-9);
    m.background = (texture - lo) * (scene_.background_contrast / span) +
                   (scene_.background_grey - 0.5 * scene_.background_contrast);
  }
  for (const SceneMesh& mesh : scene_.meshes) m.normals.push_back(vertex_normals(mesh));
  for (const SceneBoard& b : scene_.boards) {
    for (const BoardTag& t : b.board.tags) {
      m.patterns.emplace(std::make_pair(b.board.family, t.id), tag_pattern(b.board.family, t.id));
    }
  }
}

SyntheticRenderer::~SyntheticRenderer() = default;

int64_t SyntheticRenderer::timestamp_ns_of(int64_t frame) const {
  return int64_t(std::llround(double(frame) * 1e9 / scene_.fps));
}

cv::Mat SyntheticRenderer::render(int64_t frame, std::vector<TruePose>* truth) const {
  const Impl& m = *impl_;
  const double t = time_of(frame);
  // Surfaces in the camera frame, with their pixel bounding boxes.
  std::vector<Surface> surfaces;
  if (truth) truth->clear();
  for (const SceneBoard& sb : scene_.boards) {
    const Eigen::Isometry3d T = pose_at(sb, t);
    if (truth) truth->push_back({sb.board.name, T});
    add_board_surfaces(sb, T, scene_.camera, m, surfaces);
  }
  cv::Mat img;
  cv::cvtColor(m.background, img, cv::COLOR_GRAY2BGR);
  cv::Mat depth;
  draw_meshes(scene_, m.normals, t, &img, depth);
  trace_surfaces(m, surfaces, edge_lattice(scene_.supersampling), scene_.black, scene_.white, depth,
                 img);
  return apply_camera_effects(scene_, frame, std::move(img));
}

void SyntheticRenderer::render_meshes(int64_t frame, cv::Mat* mask, cv::Mat* depth) const {
  cv::Mat z;
  draw_meshes(scene_, impl_->normals, time_of(frame), nullptr, z);
  if (mask) *mask = z < std::numeric_limits<float>::infinity();
  if (depth) *depth = z;
}

// ---------------------------------------------------------------------------------------------
// Scene files

namespace {

// Frame numbers listed under `key` (none when absent).
std::vector<int64_t> frame_list(const json& j, const std::string& key, const JsonPath& at) {
  std::vector<int64_t> out;
  if (!has_field(j, key)) return out;
  const json& list = as_array(j[key], at.key(key));
  for (size_t i = 0; i < list.size(); ++i) out.push_back(as_integer(list[i], at.key(key).index(i)));
  return out;
}

Eigen::Vector3d vec3(const json& j, const JsonPath& at) {
  const std::vector<double> v = as_numbers(j, at, 3, 3, "[x, y, z]");
  return {v[0], v[1], v[2]};
}

// "camera": the path of a camera.yaml, or the model's numbers (defaults: s.camera's size,
// f = 1000 px, centred principal point).
void read_scene_camera(const json& c, const JsonPath& at,
                       const std::function<std::string(const std::string&)>& relative,
                       SyntheticScene& s) {
  if (c.is_string()) {
    s.camera = calibration::CameraModel::read_yaml(relative(c.get<std::string>()));
    return;
  }
  if (!c.is_object()) at.fail("must be an object or the path of a camera.yaml");
  s.camera.width = int(optional_integer(c, "width", at, s.camera.width, 1, 100000));
  s.camera.height = int(optional_integer(c, "height", at, s.camera.height, 1, 100000));
  s.camera.fx = optional_number(c, "fx", at, 1000.0);
  s.camera.fy = optional_number(c, "fy", at, s.camera.fx);
  s.camera.cx = optional_number(c, "cx", at, (s.camera.width - 1) / 2.0);
  s.camera.cy = optional_number(c, "cy", at, (s.camera.height - 1) / 2.0);
  s.camera.model = calibration::parse_distortion_model(
      optional_string(c, "distortion_model", at, "plumb_bob"), at.describe());
  const bool fisheye = s.camera.model == calibration::DistortionModel::equidistant;
  if (c.contains("distortion")) {
    const std::vector<double> d =
        fisheye ? as_numbers(c["distortion"], at.key("distortion"), 4, 4, "[k1, k2, k3, k4]")
                : as_numbers(c["distortion"], at.key("distortion"), 4, 5, "[k1, k2, p1, p2, k3]");
    for (size_t i = 0; i < d.size(); ++i) s.camera.distortion[i] = d[i];
  }
}

// "background": a type name, or {"type", "grey", "contrast"}.
void read_scene_background(const json& b, const JsonPath& at, SyntheticScene& s) {
  if (b.is_string()) {
    s.background = b.get<std::string>();
    return;
  }
  if (!b.is_object()) at.fail("must be an object or a type name");
  s.background = optional_string(b, "type", at, s.background);
  s.background_grey = optional_number(b, "grey", at, s.background_grey);
  s.background_contrast = optional_number(b, "contrast", at, s.background_contrast);
}

// One board's pose keyframes: {"t", "translation_mm", "quaternion" or "rotvec_deg"}.
std::vector<PoseKeyframe> read_keyframes(const json& keys, const JsonPath& at) {
  std::vector<PoseKeyframe> out;
  for (size_t k = 0; k < keys.size(); ++k) {
    const json& kj = keys[k];
    const JsonPath kf = at.index(k);
    if (!kj.is_object() || !kj.contains("translation_mm")) {
      kf.key("translation_mm").fail("is missing");
    }
    PoseKeyframe key;
    key.time_s = optional_number(kj, "t", kf, 0.0);
    const Eigen::Vector3d tr = vec3(kj["translation_mm"], kf.key("translation_mm"));
    Eigen::Quaterniond q = Eigen::Quaterniond::Identity();
    if (kj.contains("quaternion")) {
      const std::vector<double> v =
          as_numbers(kj["quaternion"], kf.key("quaternion"), 4, 4, "[w, x, y, z]");
      q = Eigen::Quaterniond(v[0], v[1], v[2], v[3]);
      if (q.norm() < 1e-9) kf.key("quaternion").fail("is zero");
    } else if (kj.contains("rotvec_deg")) {
      q = rotvec_deg(vec3(kj["rotvec_deg"], kf.key("rotvec_deg")));
    }
    key.T_cam_board = make_pose(q, tr);
    out.push_back(key);
  }
  return out;
}

// "boards" and "poses": every board of the scene with its keyframes; every pose names a board.
std::vector<SceneBoard> read_scene_boards(
    const json& j, const JsonPath& root,
    const std::function<std::string(const std::string&)>& relative) {
  std::vector<Board> boards;
  const json& bj = required_field(j, "boards", root);
  if (bj.is_string()) {
    boards = read_boards(relative(bj.get<std::string>()));
  } else if (bj.is_array()) {
    boards = read_boards_json(json{{"boards", bj}}, root.source());
  } else {
    root.key("boards").fail("must be a boards.json path or an array of boards");
  }
  const JsonPath poses_at = root.key("poses");
  if (!j.contains("poses") || !j["poses"].is_object()) {
    poses_at.fail("is missing, expected {\"BOARD\": [keyframes], ...}");
  }
  const json& poses = j["poses"];
  for (auto it = poses.begin(); it != poses.end(); ++it) {
    const bool known = std::any_of(boards.begin(), boards.end(),
                                   [&](const Board& b) { return b.name == it.key(); });
    if (!known) poses_at.key(it.key()).fail("names no board of the scene");
  }
  const bool plate = optional_bool(j, "plate", root, true);
  std::vector<SceneBoard> out;
  for (const Board& b : boards) {
    SceneBoard sb;
    sb.board = b;
    sb.plate = plate;
    if (!poses.contains(b.name) || !poses[b.name].is_array()) {
      poses_at.key(b.name).fail("is missing, expected keyframes of board '" + b.name + "'");
    }
    sb.keyframes = read_keyframes(poses[b.name], poses_at.key(b.name));
    out.push_back(sb);
  }
  return out;
}

// "occlusions": [{"rect_px": [x, y, w, h], "frames": [first, last], "grey": 60}].
std::vector<OcclusionBox> read_occlusions(const json& list, const JsonPath& at) {
  as_array(list, at);
  std::vector<OcclusionBox> out;
  for (size_t k = 0; k < list.size(); ++k) {
    const json& o = list[k];
    const JsonPath of = at.index(k);
    if (!o.is_object() || !o.contains("rect_px")) {
      of.key("rect_px").fail("is missing, expected [x, y, w, h]");
    }
    OcclusionBox box;
    const std::vector<double> r = as_numbers(o["rect_px"], of.key("rect_px"), 4, 4, "[x, y, w, h]");
    box.rect_px = cv::Rect2d(r[0], r[1], r[2], r[3]);
    box.first_frame = 0;
    box.last_frame = std::numeric_limits<int64_t>::max();
    if (o.contains("frames")) {
      const std::vector<int64_t> f = frame_list(o, "frames", of);
      if (f.size() != 2) of.key("frames").fail("must be [first, last]");
      box.first_frame = f[0];
      box.last_frame = f[1];
    }
    box.grey = optional_number(o, "grey", of, box.grey);
    out.push_back(box);
  }
  return out;
}

// "meshes": [{"name", "board", "vertices_mm": [x, y, z, ...], "triangles": [i, j, k, ...],
// "colours": [b, g, r, ...]}]. At most 4 million vertices and triangles per mesh.
std::vector<SceneMesh> read_meshes(const json& list, const JsonPath& at) {
  as_array(list, at);
  constexpr size_t kMax = 3 * 4'000'000;
  std::vector<SceneMesh> out;
  for (size_t k = 0; k < list.size(); ++k) {
    const json& mj = list[k];
    const JsonPath mf = at.index(k);
    if (!mj.is_object()) mf.fail("must be an object");
    SceneMesh mesh;
    mesh.name = optional_string(mj, "name", mf, "mesh " + std::to_string(k));
    mesh.board = optional_string(mj, "board", mf, "");
    const auto numbers = [&](const char* key, size_t min_size) {
      if (!mj.contains(key)) mf.key(key).fail("is missing");
      const std::vector<double> v = as_numbers(mj[key], mf.key(key), min_size, kMax, "numbers");
      if (v.size() % 3 != 0) mf.key(key).fail("must hold a multiple of 3 numbers");
      return v;
    };
    const std::vector<double> v = numbers("vertices_mm", 3);
    const std::vector<double> c = numbers("colours", 3);
    const std::vector<double> t = numbers("triangles", 0);
    for (size_t i = 0; i < v.size(); i += 3) mesh.vertices.emplace_back(float(v[i]), float(v[i + 1]), float(v[i + 2]));
    for (size_t i = 0; i < c.size(); i += 3) {
      for (size_t j = 0; j < 3; ++j) {
        if (!(c[i + j] >= 0 && c[i + j] <= 255)) mf.key("colours").fail("must lie in 0 to 255");
      }
      mesh.colours.emplace_back(float(c[i]), float(c[i + 1]), float(c[i + 2]));
    }
    for (size_t i = 0; i < t.size(); i += 3) {
      Eigen::Vector3i tri;
      for (size_t j = 0; j < 3; ++j) {
        if (!(t[i + j] >= 0 && t[i + j] < double(v.size() / 3) && t[i + j] == std::floor(t[i + j]))) {
          mf.key("triangles").fail("must hold vertex indices 0 to " + std::to_string(v.size() / 3 - 1));
        }
        tri[int(j)] = int(t[i + j]);
      }
      mesh.triangles.push_back(tri);
    }
    out.push_back(std::move(mesh));
  }
  return out;
}

}  // namespace

SyntheticScene read_scene(const std::string& path) {
  namespace fs = std::filesystem;
  const json j = read_json_file(path, "scene file");
  if (!j.is_object()) throw Error(path + ": expected a JSON object");
  const JsonPath root(path);
  const fs::path base = fs::path(path).parent_path();
  const auto relative = [&](const std::string& p) {
    return fs::path(p).is_absolute() ? p : (base / p).string();
  };
  SyntheticScene s;
  if (j.contains("camera")) read_scene_camera(j["camera"], root.key("camera"), relative, s);
  if (j.contains("background")) {
    read_scene_background(j["background"], root.key("background"), s);
  }
  s.boards = read_scene_boards(j, root, relative);
  s.fps = optional_number(j, "fps", root, s.fps);
  s.frame_count = optional_integer(j, "frames", root, s.frame_count, 1, 10000000);
  s.noise_sigma = optional_number(j, "noise_sigma", root, s.noise_sigma);
  s.blur_sigma = optional_number(j, "blur_sigma", root, s.blur_sigma);
  s.gain = optional_number(j, "gain", root, s.gain);
  s.offset = optional_number(j, "offset", root, s.offset);
  s.black = optional_number(j, "black", root, s.black);
  s.white = optional_number(j, "white", root, s.white);
  s.seed = uint64_t(optional_integer(j, "seed", root, int64_t(s.seed), 0, int64_t(1) << 53));
  s.supersampling = int(optional_integer(j, "supersampling", root, s.supersampling, 1, 32));
  s.dropped_frames = frame_list(j, "dropped_frames", root);
  s.corrupt_frames = frame_list(j, "corrupt_frames", root);
  if (j.contains("occlusions")) s.occlusions = read_occlusions(j["occlusions"], root.key("occlusions"));
  if (j.contains("meshes")) {
    if (j["meshes"].is_string()) {
      const std::string file = relative(j["meshes"].get<std::string>());
      s.meshes = read_meshes(read_json_file(file, "meshes file"), JsonPath(file));
    } else {
      s.meshes = read_meshes(j["meshes"], root.key("meshes"));
    }
  }
  s.validate(path);
  return s;
}

SyntheticScene builtin_scene() {
  SyntheticScene s;
  s.camera.cx = 641.2;
  s.camera.cy = 358.7;
  s.camera.fx = 1000.0;
  s.camera.fy = 1000.0;
  s.camera.distortion = {-0.05, 0.02, 0.0, 0.0, 0.0};
  s.background = "noise";
  s.fps = 30;
  s.frame_count = 90;  // 3 s
  s.noise_sigma = 1.5;

  SceneBoard patient;
  patient.board = make_grid_board("patient", 2, 3, 40.0, 10.0, 0);
  // CT-visible fiducials near the plate corners (the plate spans +-90 x +-60 mm).
  patient.board.fiducials = {{-82, -52, 0}, {82, -52, 0}, {82, 52, 0}, {-82, 52, 0}};
  patient.plate_margin_mm = 15;
  // The camera looks down at the patient from 50 to 58 cm; the board drifts a little (breathing,
  // a camera arm settling).
  const std::vector<std::pair<double, Eigen::Isometry3d>> patient_keys = {
      {0.0, make_pose(rotvec_deg({-25, 5, 3}), {-100, 25, 500})},
      {1.5, make_pose(rotvec_deg({-27, 8, 2}), {-95, 30, 540})},
      {3.0, make_pose(rotvec_deg({-24, 10, 4}), {-90, 35, 580})}};
  for (const auto& [time, T] : patient_keys) patient.keyframes.push_back({time, T});

  SceneBoard needle;
  needle.board = make_grid_board("needle", 2, 2, 20.0, 6.0, 10);
  needle.plate_margin_mm = 4;
  // The needle points from its entry toward the target; the board is square to it at the hub.
  const Eigen::Vector3d d = Eigen::Vector3d(-0.25, -0.12, 1.0).normalized();  // patient frame
  Eigen::Matrix3d R_patient_needle;
  const Eigen::Vector3d x_axis = (Eigen::Vector3d::UnitX() - d.x() * d).normalized();
  R_patient_needle.col(0) = x_axis;
  R_patient_needle.col(1) = d.cross(x_axis);
  R_patient_needle.col(2) = d;
  for (int64_t f = 0; f <= s.frame_count; ++f) {
    const double time = double(f) / s.fps;
    // Tip from 200 mm to 60 mm short of the target, at a steady speed.
    const double remaining = 200.0 - 140.0 * std::min(1.0, time / 3.0);
    const Eigen::Vector3d tip = kTumorTargetInPatient - remaining * d;
    Eigen::Isometry3d T_patient_needle = Eigen::Isometry3d::Identity();
    T_patient_needle.linear() = R_patient_needle;
    T_patient_needle.translation() = tip - R_patient_needle * kNeedleTipInNeedle;
    needle.keyframes.push_back({time, pose_at(patient, time) * T_patient_needle});
  }
  s.boards = {patient, needle};
  return s;
}

double breathing_cycle_fraction(double time_s, double breaths_per_minute) {
  const double cycles = time_s * breaths_per_minute / 60.0;
  return cycles - std::floor(cycles);
}

double breathing_rise_mm(double time_s, double breaths_per_minute, double rise_mm) {
  const double s = std::sin(M_PI * breathing_cycle_fraction(time_s, breaths_per_minute));
  return rise_mm * s * s;
}

void add_breathing(SyntheticScene& scene, const std::string& board, double breaths_per_minute,
                   double rise_mm) {
  if (!(breaths_per_minute >= 1.0 && breaths_per_minute <= 60.0)) {
    throw Error("synth: " + std::to_string(breaths_per_minute) +
                " breaths a minute is not a breathing rate (1 to 60)");
  }
  for (SceneBoard& b : scene.boards) {
    if (b.board.name != board) continue;
    const SceneBoard still = b;
    b.keyframes.clear();
    for (int64_t f = 0; f < scene.frame_count; ++f) {
      const double t = double(f) / scene.fps;
      b.keyframes.push_back({t, pose_at(still, t) *
                                    Eigen::Translation3d(0.0, 0.0,
                                                         -breathing_rise_mm(t, breaths_per_minute, rise_mm))});
    }
    return;
  }
  throw Error("synth: the scene has no board '" + board + "' to breathe with");
}

}  // namespace crepuscular::tracking
