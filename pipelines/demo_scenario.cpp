// The demo's guidance scenario: approach directions searched from the tumor centroid and judged
// with the plan (NeedleGuide), the patient board fitted to the skin of the label map, the camera
// placed so both boards stay in view, and the needle scripted frame by frame.
#include "pipelines/demo_scenario.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>
#include <nlohmann/json.hpp>
#include <optional>

#include <opencv2/imgproc.hpp>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "foundation/output_files.hpp"
#include "planning/imaging/ray_march.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/simulation/phantom.hpp"
#include "pipelines/scene_meshes.hpp"

namespace crepuscular::pipelines {


namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kDeg = kPi / 180.0;

double angle_deg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::acos(std::clamp(a.normalized().dot(b.normalized()), -1.0, 1.0)) / kDeg;
}

// First crossing of the smooth skin (planning::body_fraction 0.5) on start + s dir,
// 0 <= s <= max_mm, bisected to 0.001 mm: the first s on or inside the skin; 0 when start is.
std::optional<double> first_skin(const planning::Volume<int32_t>& labels,
                                 const Eigen::Vector3d& start, const Eigen::Vector3d& dir,
                                 double max_mm, double step_mm) {
  const std::optional<planning::Crossing> c =
      planning::first_entry(start, dir, step_mm, max_mm + 1e-9, [&](const Eigen::Vector3d& p) {
        return planning::body_fraction(labels, p) >= 0.5;
      });
  if (!c) return std::nullopt;
  return c->inside_s;
}

bool contains_ci(const std::string& text, const std::string& word) {
  std::string t = text;
  std::transform(t.begin(), t.end(), t.begin(), [](unsigned char c) { return std::tolower(c); });
  return t.find(word) != std::string::npos;
}

// A frame whose z axis is d and whose x axis is `x_hint` made orthogonal to d.
Eigen::Matrix3d frame_along(const Eigen::Vector3d& d, const Eigen::Vector3d& x_hint) {
  Eigen::Vector3d x = x_hint - x_hint.dot(d) * d;
  if (x.norm() < 1e-6) x = d.unitOrthogonal();
  x.normalize();
  Eigen::Matrix3d R;
  R.col(0) = x;
  R.col(1) = d.cross(x);
  R.col(2) = d;
  return R;
}

// T_ct_needle of a needle whose tip (kNeedleTipInNeedle) lies at tip_ct and whose +z is d.
Eigen::Isometry3d needle_pose(const Eigen::Vector3d& tip_ct, const Eigen::Matrix3d& R) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = R;
  T.translation() = tip_ct - R * tracking::kNeedleTipInNeedle;
  return T;
}

// A candidate approach: outward unit direction u from the centroid (direction_ct = -u).
struct Candidate {
  Eigen::Vector3d u = Eigen::Vector3d::Zero();
  Eigen::Vector3d entry = Eigen::Vector3d::Zero();
  planning::NeedleState state;
  std::vector<std::string> vessels;
  double vessel_length_mm = 0;
  bool other_high_risk = false;  // crosses bone, lung or another non-vessel structure >= 1 per mm
  bool valid = false;
};

class Searcher {
 public:
  Searcher(const planning::PlanData& plan, const Eigen::Vector3d& centroid)
      : plan_(plan), guide_(plan), centroid_(centroid) {}

  Candidate evaluate(const Eigen::Vector3d& u_in) const {
    Candidate c;
    c.u = u_in.normalized();
    const std::optional<Eigen::Vector3d> e =
        planning::outermost_body_exit(plan_.labels, centroid_, c.u);
    if (!e || (*e - centroid_).norm() < 1.0) return c;
    c.entry = *e;
    const Eigen::Vector3d d = -c.u;
    c.state = guide_.evaluate(needle_pose(c.entry, frame_along(d, Eigen::Vector3d::UnitX())),
                              tracking::kNeedleTipInNeedle, Eigen::Vector3d::UnitZ());
    for (const planning::StructureHit& h : c.state.evaluation.structures) {
      if (is_vessel_name(h.name)) {
        c.vessels.push_back(h.name);
        c.vessel_length_mm += h.length_mm;
      } else if (h.blocking_per_mm >= 1.0) {
        c.other_high_risk = true;
      }
    }
    c.valid = true;
    return c;
  }

  bool is_safe(const Candidate& c) const {
    return c.valid && c.state.clear && c.state.tip_class == "safe" && c.vessels.empty() &&
           c.state.safety == planning::NeedleSafety::kSafe;
  }
  bool is_dangerous(const Candidate& c) const {
    return c.valid && !c.vessels.empty() && c.state.safety == planning::NeedleSafety::kDangerous;
  }

  // The 8 directions at angle_deg around u.
  static std::vector<Eigen::Vector3d> ring(const Eigen::Vector3d& u, double angle_deg) {
    const Eigen::Vector3d a = u.unitOrthogonal(), b = u.cross(a);
    std::vector<Eigen::Vector3d> out;
    for (int k = 0; k < 8; ++k) {
      const double phi = 2 * kPi * k / 8;
      const Eigen::Vector3d w = std::cos(phi) * a + std::sin(phi) * b;
      out.push_back((std::cos(angle_deg * kDeg) * u + std::sin(angle_deg * kDeg) * w).normalized());
    }
    return out;
  }

 private:
  const planning::PlanData& plan_;
  planning::NeedleGuide guide_;
  Eigen::Vector3d centroid_;
};

// Fibonacci sphere points within max_deg of axis.
std::vector<Eigen::Vector3d> fibonacci_cap(int n, const Eigen::Vector3d& axis, double max_deg) {
  std::vector<Eigen::Vector3d> out;
  for (const Eigen::Vector3d& p : planning::fibonacci_sphere(n)) {
    if (angle_deg(p, axis) <= max_deg) out.push_back(p);
  }
  return out;
}

// ---------------------------------------------------------------------------------------------
// Patient board on the skin

struct BoardPlacement {
  Eigen::Isometry3d T_ct_patient = Eigen::Isometry3d::Identity();
  double max_fiducial_offset_mm = 0;  // largest distance of a fiducial from the skin along z
};

// CT-visible fiducial layout on the patient board (board frame, mm; the plate spans +-85 x +-60 mm):
// all ten mutual distances differ by 4.5 mm or more (the registration pairs beads by them) and
// none is below 40 mm; within +-30 mm across the board, where the skin curves.
const std::vector<Eigen::Vector3d> kPatientFiducials = {
    {30, 10, 0}, {-56, -30, 0}, {60, -30, 0}, {-78, 28, 0}, {-6, 28, 0}};

// The board lies flat on the skin around `centre_xz` (its x axis along CT -z, z into the body):
// the plane of least squares through the skin under its footprint.
std::optional<BoardPlacement> place_board(const planning::Volume<int32_t>& labels,
                                          const Eigen::Vector3d& anterior_point) {
  // Skin point straight below anterior_point (which lies outside the body, anterior).
  const auto skin_below = [&](const Eigen::Vector3d& p) -> std::optional<Eigen::Vector3d> {
    const std::optional<double> s =
        first_skin(labels, p, Eigen::Vector3d::UnitY(), 400.0, 0.25 * labels.geometry().spacing.minCoeff());
    if (!s) return std::nullopt;
    return Eigen::Vector3d(p + *s * Eigen::Vector3d::UnitY());
  };
  const std::optional<Eigen::Vector3d> c0 = skin_below(anterior_point);
  const std::optional<Eigen::Vector3d> cm = skin_below(anterior_point - Eigen::Vector3d(15, 0, 0));
  const std::optional<Eigen::Vector3d> cp = skin_below(anterior_point + Eigen::Vector3d(15, 0, 0));
  if (!c0 || !cm || !cp) return std::nullopt;
  // Initial frame: x along CT -z, y across the body along the skin, z into the body.
  Eigen::Vector3d x = -Eigen::Vector3d::UnitZ();
  Eigen::Vector3d across = (*cp - *cm).normalized();
  Eigen::Vector3d z = x.cross(across).normalized();
  if (z.y() < 0) z = -z;
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  const auto set_frame = [&](const Eigen::Vector3d& zz, const Eigen::Vector3d& origin) {
    const Eigen::Vector3d xx = (x - x.dot(zz) * zz).normalized();
    T.linear().col(0) = xx;
    T.linear().col(1) = zz.cross(xx);
    T.linear().col(2) = zz;
    T.translation() = origin;
  };
  set_frame(z, *c0);
  // Two rounds of plane fitting: depth h of the skin below the plane at footprint points.
  for (int round = 0; round < 2; ++round) {
    Eigen::MatrixXd A(0, 3);
    Eigen::VectorXd h(0);
    std::vector<std::array<double, 3>> rows;
    // Around each fiducial (the board rests on the skin where its beads are).
    for (const Eigen::Vector3d& f : kPatientFiducials) {
      for (double dx = -4; dx <= 4.001; dx += 2) {
        for (double dy = -4; dy <= 4.001; dy += 2) {
          const double bx = f.x() + dx, by = f.y() + dy;
          const Eigen::Vector3d start = T * Eigen::Vector3d(bx, by, -40.0);
          const std::optional<double> s = first_skin(labels, start, T.linear().col(2), 120.0,
                                                       0.1);
          if (!s) continue;
          rows.push_back({bx, by, *s - 40.0});
        }
      }
    }
    if (rows.size() < 3 * kPatientFiducials.size()) return std::nullopt;
    A.resize(Eigen::Index(rows.size()), 3);
    h.resize(Eigen::Index(rows.size()));
    for (size_t i = 0; i < rows.size(); ++i) {
      A.row(Eigen::Index(i)) << 1.0, rows[i][0], rows[i][1];
      h(Eigen::Index(i)) = rows[i][2];
    }
    const Eigen::Vector3d p = A.colPivHouseholderQr().solve(h);
    // Plane: board z = p0 + p1 x + p2 y. New origin and normal.
    const Eigen::Vector3d origin = T * Eigen::Vector3d(0, 0, p(0));
    const Eigen::Vector3d nz =
        (T.linear() * Eigen::Vector3d(-p(1), -p(2), 1.0)).normalized();
    set_frame(nz, origin);
  }
  BoardPlacement out;
  out.T_ct_patient = T;
  for (const Eigen::Vector3d& f : kPatientFiducials) {
    const std::optional<double> s = first_skin(labels, T * Eigen::Vector3d(f.x(), f.y(), -30.0),
                                                 T.linear().col(2), 60.0, 0.1);
    out.max_fiducial_offset_mm =
        std::max(out.max_fiducial_offset_mm, s ? std::abs(*s - 30.0) : 1e9);
  }
  return out;
}

// ---------------------------------------------------------------------------------------------
// Scene

struct Script {
  Eigen::Vector3d centroid;
  Eigen::Vector3d entry_s, entry_d, d_s, d_d;
  Eigen::Matrix3d R_s, R_d;
  double hold = 0, approach = 0, sw = 0, outside = 0, short_of = 0;

  Eigen::Isometry3d T_ct_needle(double t) const {
    const double s0 = hold, s1 = hold + approach, s2 = s1 + sw;
    const Eigen::Vector3d a_s = entry_s - outside * d_s, b_s = centroid - short_of * d_s;
    const Eigen::Vector3d a_d = entry_d - outside * d_d, b_d = centroid - short_of * d_d;
    const auto lerp = [](const Eigen::Vector3d& a, const Eigen::Vector3d& b, double f) {
      f = std::clamp(f, 0.0, 1.0);
      return Eigen::Vector3d((1.0 - f) * a + f * b);
    };
    if (t <= s1) return needle_pose(lerp(a_s, b_s, (t - s0) / approach), R_s);
    if (t < s1 + 0.5 * sw) return needle_pose(lerp(b_s, a_s, (t - s1) / (0.5 * sw)), R_s);
    if (t < s2) {
      const double f = (t - s1 - 0.5 * sw) / (0.5 * sw);
      const Eigen::Quaterniond q =
          Eigen::Quaterniond(R_s).slerp(std::clamp(f, 0.0, 1.0), Eigen::Quaterniond(R_d));
      return needle_pose(lerp(a_s, a_d, f), q.toRotationMatrix());
    }
    return needle_pose(lerp(a_d, b_d, (t - s2) / approach), R_d);
  }
};

Eigen::Isometry3d small_motion(const Eigen::Vector3d& rot_deg, const Eigen::Vector3d& t_mm) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  if (rot_deg.norm() > 0) {
    T.linear() = Eigen::AngleAxisd(rot_deg.norm() * kDeg, rot_deg.normalized()).toRotationMatrix();
  }
  T.translation() = t_mm;
  return T;
}

// All tag corners inside the image with the margin, boards facing the camera (within 60 degrees)
// and their images apart with a gap, in every frame. Returns an empty string when so, else what failed.
std::string check_view(const tracking::SyntheticScene& scene, double margin_px) {
  const calibration::CameraModel& cam = scene.camera;
  for (int64_t f = 0; f < scene.frame_count; ++f) {
    const double t = double(f) / scene.fps;
    std::vector<std::vector<cv::Point2f>> hulls;
    for (const tracking::SceneBoard& b : scene.boards) {
      const Eigen::Isometry3d T = tracking::pose_at(b, t);
      if (T.linear()(2, 2) < 0.5) {
        return "board '" + b.board.name + "' turns away from the camera at frame " +
               std::to_string(f);
      }
      std::vector<cv::Point2f> pts;
      for (const tracking::BoardTag& tag : b.board.tags) {
        for (const Eigen::Vector3d& c : tag.corners) {
          const Eigen::Vector3d p = T * c;
          if (p.z() < 50) return "board '" + b.board.name + "' behind the camera";
          const Eigen::Vector2d px = cam.project(p);
          if (px.x() < margin_px || px.y() < margin_px || px.x() > cam.width - 1 - margin_px ||
              px.y() > cam.height - 1 - margin_px) {
            return "board '" + b.board.name + "' leaves the image at frame " + std::to_string(f);
          }
          pts.emplace_back(float(px.x()), float(px.y()));
        }
      }
      std::vector<cv::Point2f> hull;
      cv::convexHull(pts, hull);
      // Grown by 30 % about its centre: the plates and a gap stay apart too.
      cv::Point2f centre(0, 0);
      for (const cv::Point2f& p : hull) centre += p * (1.0f / float(hull.size()));
      for (cv::Point2f& p : hull) p = centre + 1.3f * (p - centre);
      hulls.push_back(hull);
    }
    for (size_t i = 0; i < hulls.size(); ++i) {
      for (size_t j = i + 1; j < hulls.size(); ++j) {
        std::vector<cv::Point2f> inter;
        if (cv::intersectConvexConvex(hulls[i], hulls[j], inter, true) > 0.0f) {
          return "the boards overlap in the image at frame " + std::to_string(f);
        }
      }
    }
  }
  return "";
}

// Where the patient board goes: beside the entries, toward the midline (anterior skin, flattest
// there), 95 mm inside the label map's z range, 5 mm anterior of the map (outside the body).
Eigen::Vector3d board_anchor(const planning::ImageGeometry& g, const Candidate& safe,
                             const Candidate& danger) {
  const Eigen::Vector3d mid = 0.5 * (safe.entry + danger.entry);
  const double side = mid.x() > 0 ? -1.0 : 1.0;
  const double spread = std::abs(safe.entry.x() - danger.entry.x());
  const double board_x = mid.x() + side * (60.0 + 70.0 + 0.5 * spread);
  const Eigen::Vector3d lo = g.index_to_physical(Eigen::Vector3d::Zero());
  const Eigen::Vector3d hi =
      g.index_to_physical(Eigen::Vector3d(g.dims[0] - 1, g.dims[1] - 1, g.dims[2] - 1));
  const double zmin = std::min(lo.z(), hi.z()) + 95, zmax = std::max(lo.z(), hi.z()) - 95;
  const double board_z = zmin <= zmax ? std::clamp(mid.z(), zmin, zmax) : 0.5 * (lo.z() + hi.z());
  const double ymin = std::min(lo.y(), hi.y());
  return Eigen::Vector3d(board_x, ymin - 5.0, board_z);
}

// Lays the patient board on the skin (sc.T_ct_patient). Returns an empty string on success.
std::string place_patient_board(GuidanceScenario& sc, const planning::Volume<int32_t>& labels,
                                const Candidate& safe, const Candidate& danger) {
  const Eigen::Vector3d anchor = board_anchor(labels.geometry(), safe, danger);
  const std::optional<BoardPlacement> placement = place_board(labels, anchor);
  if (!placement) {
    return "no anterior skin for the patient board at x = " + std::to_string(anchor.x());
  }
  if (placement->max_fiducial_offset_mm > 2.0) {
    return "the skin under the patient board is too curved (a fiducial lies " +
           std::to_string(placement->max_fiducial_offset_mm) + " mm from it)";
  }
  sc.T_ct_patient = placement->T_ct_patient;
  return "";
}

// The needle's script: the safe approach, then the dangerous one, the needle's x axis along the
// camera image's x.
Script make_script(const Eigen::Vector3d& centroid, const Candidate& safe, const Candidate& danger,
                   const Eigen::Matrix3d& R_ct_cam, const GuidanceScenarioOptions& o) {
  Script script;
  script.centroid = centroid;
  script.entry_s = safe.entry;
  script.entry_d = danger.entry;
  script.d_s = -safe.u;
  script.d_d = -danger.u;
  script.R_s = frame_along(script.d_s, R_ct_cam.col(0));
  script.R_d = frame_along(script.d_d, R_ct_cam.col(0));
  script.hold = o.hold_s;
  script.approach = o.approach_s;
  script.sw = o.switch_s;
  script.outside = o.start_outside_mm;
  script.short_of = o.stop_short_mm;
  return script;
}

// Tag corners in CT: the patient board's, and the needle board's every third frame.
std::vector<Eigen::Vector3d> tag_corners_ct(const GuidanceScenario& sc,
                                            const tracking::SceneBoard& patient,
                                            const tracking::SceneBoard& needle,
                                            const Script& script) {
  const tracking::SyntheticScene& s = sc.scene;
  std::vector<Eigen::Vector3d> points;
  for (const tracking::BoardTag& t : patient.board.tags) {
    for (const Eigen::Vector3d& p : t.corners) points.push_back(sc.T_ct_patient * p);
  }
  for (int64_t f = 0; f < s.frame_count; f += 3) {
    const Eigen::Isometry3d T = script.T_ct_needle(double(f) / s.fps);
    for (const tracking::BoardTag& t : needle.board.tags) {
      for (const Eigen::Vector3d& p : t.corners) points.push_back(T * p);
    }
  }
  return points;
}

// Camera position (cam_ct) on the optical axis v: the image of `points` centred, the board centre
// at camera_distance_mm. Returns an empty string on success.
std::string place_camera(const std::vector<Eigen::Vector3d>& points,
                         const Eigen::Vector3d& board_ct, Eigen::Vector3d look,
                         const Eigen::Matrix3d& R_ct_cam, const Eigen::Vector3d& v,
                         const calibration::CameraModel& camera, double camera_distance_mm,
                         Eigen::Vector3d& cam_ct) {
  cam_ct = look - camera_distance_mm * v;
  for (int it = 0; it < 12; ++it) {
    const Eigen::Vector3d w = board_ct - look;
    const double wv = w.dot(v);
    const double disc = wv * wv - w.squaredNorm() + camera_distance_mm * camera_distance_mm;
    if (disc < 0) return "cannot place the camera";
    cam_ct = look - (-wv + std::sqrt(disc)) * v;
    double u0 = 1e300, u1 = -1e300, v0 = 1e300, v1 = -1e300, depth = 0;
    for (const Eigen::Vector3d& p : points) {
      const Eigen::Vector3d q = R_ct_cam.transpose() * (p - cam_ct);
      if (q.z() < 50) return "a board lies behind the camera";
      const Eigen::Vector2d px = camera.project(q);
      u0 = std::min(u0, px.x());
      u1 = std::max(u1, px.x());
      v0 = std::min(v0, px.y());
      v1 = std::max(v1, px.y());
      depth += q.z();
    }
    depth /= double(points.size());
    const double du = 0.5 * (u0 + u1) - camera.cx, dv = 0.5 * (v0 + v1) - camera.cy;
    look += R_ct_cam * Eigen::Vector3d(du * depth / camera.fx, dv * depth / camera.fy, 0.0);
  }
  return "";
}

// Keyframes: the patient board's under the camera drift (breathing, a camera arm settling: three
// keyframes of T_cam_ct), and the needle board's every frame, following the script.
void add_keyframes(const GuidanceScenario& sc, const Script& script,
                   const GuidanceScenarioOptions& o, tracking::SceneBoard& patient,
                   tracking::SceneBoard& needle) {
  if (sc.breathing_period_s > 0) {
    // Breathing: the camera and the needle stay in the room; the board rises with the skin.
    for (int64_t f = 0; f < sc.scene.frame_count; ++f) {
      const double t = double(f) / sc.scene.fps;
      patient.keyframes.push_back(
          {t, sc.T_cam_ct_nominal * Eigen::Translation3d(sc.skin_displacement_at(t)) * sc.T_ct_patient});
      needle.keyframes.push_back({t, sc.T_cam_ct_nominal * script.T_ct_needle(t)});
    }
    return;
  }
  const double dr = o.camera_drift_mm;
  const std::vector<std::pair<double, Eigen::Isometry3d>> drift = {
      {0.0, small_motion({0.0, 0.0, 0.0}, {0.0, 0.0, -0.5 * dr})},
      {0.5 * sc.duration_s, small_motion({0.8, -1.0, 0.5}, {0.3 * dr, -0.2 * dr, 0.0})},
      {sc.duration_s, small_motion({-0.6, 1.2, -0.4}, {-0.2 * dr, 0.25 * dr, 0.5 * dr})}};
  for (const auto& [t, D] : drift) {
    patient.keyframes.push_back({t, D * sc.T_cam_ct_nominal * sc.T_ct_patient});
  }
  const Eigen::Isometry3d T_patient_ct = sc.T_ct_patient.inverse();
  for (int64_t f = 0; f < sc.scene.frame_count; ++f) {
    const double t = double(f) / sc.scene.fps;
    needle.keyframes.push_back(
        {t, tracking::pose_at(patient, t) * T_patient_ct * script.T_ct_needle(t)});
  }
}

// Builds the scene for one pair of approaches. Returns an empty string on success.
std::string build_scene(GuidanceScenario& sc, const planning::PlanData& plan, const Candidate& safe,
                        const Candidate& danger, const GuidanceScenarioOptions& o,
                        const Eigen::Vector3d& view_axis) {
  const Eigen::Vector3d v = view_axis.normalized();
  // Camera orientation: optical axis v; image x along CT x (the boards lie side by side across the
  // body), image y down.
  const Eigen::Matrix3d R_ct_cam = frame_along(v, Eigen::Vector3d::UnitX());
  const std::string board_problem = place_patient_board(sc, plan.labels, safe, danger);
  if (!board_problem.empty()) return board_problem;
  const Script script = make_script(sc.target_ct, safe, danger, R_ct_cam, o);
  sc.duration_s = 2 * o.hold_s + 2 * o.approach_s + o.switch_s;
  if (o.breaths_per_minute > 0 && o.breathing_phases > 0) {
    sc.breathing_period_s = 60.0 / o.breaths_per_minute;
    sc.breathing_amplitude_mm = o.breathing_amplitude_mm;
    sc.breathing_phases = o.breathing_phases;
  }

  const tracking::SyntheticScene builtin = tracking::builtin_scene();
  tracking::SyntheticScene& s = sc.scene;
  s = builtin;
  s.fps = o.fps;
  s.frame_count = int64_t(std::floor(sc.duration_s * o.fps + 1e-9)) + 1;
  s.seed = o.seed;
  tracking::SceneBoard patient = builtin.boards.at(0);
  tracking::SceneBoard needle = builtin.boards.at(1);
  patient.board.fiducials = kPatientFiducials;
  patient.keyframes.clear();
  needle.keyframes.clear();

  // Camera: looking at the middle between the board and the entries to begin with.
  const Eigen::Vector3d mid = 0.5 * (safe.entry + danger.entry);
  const Eigen::Vector3d board_ct = sc.T_ct_patient.translation();
  Eigen::Vector3d cam_ct;
  const std::string camera_problem =
      place_camera(tag_corners_ct(sc, patient, needle, script), board_ct, 0.5 * (board_ct + mid),
                   R_ct_cam, v, s.camera, o.camera_distance_mm, cam_ct);
  if (!camera_problem.empty()) return camera_problem;
  Eigen::Isometry3d T_ct_cam = Eigen::Isometry3d::Identity();
  T_ct_cam.linear() = R_ct_cam;
  T_ct_cam.translation() = cam_ct;
  sc.T_cam_ct_nominal = T_ct_cam.inverse();

  add_keyframes(sc, script, o, patient, needle);
  s.boards = {patient, needle};
  s.validate("guidance scene");
  return check_view(s, o.image_margin_px);
}

// Smallest angle (degrees) over the frames of the scene between the needle's axis and the ray
// from the camera to the approach's skin entry, within [start_s, end_s].
double min_view_obliquity_deg(const GuidanceScenario& sc, const Eigen::Vector3d& entry_ct,
                              double start_s, double end_s) {
  const tracking::SyntheticScene& s = sc.scene;
  const tracking::SceneBoard& patient = s.boards.at(0);
  const tracking::SceneBoard& needle = s.boards.at(1);
  double best = 180;
  for (int64_t f = 0; f < s.frame_count; ++f) {
    const double t = double(f) / s.fps;
    if (t < start_s - 1e-9 || t > end_s + 1e-9) continue;
    const Eigen::Isometry3d T_cam_patient = tracking::pose_at(patient, t);
    const Eigen::Vector3d entry = T_cam_patient * (sc.T_ct_patient.inverse() * entry_ct);
    const Eigen::Vector3d axis = tracking::pose_at(needle, t).linear().col(2);
    best = std::min(best, angle_deg(axis, entry));
  }
  return best;
}

// Camera axes that see both approaches obliquely, as an OR camera above the table and to one
// side would: within 60 degrees of looking straight down (+y), 25 degrees or more off vertical
// and 20 or more across the body (x), 36 to 54 degrees from both needle directions; the most even (nearest 44 degrees to both) first.
std::vector<Eigen::Vector3d> oblique_axes(const Candidate& safe, const Candidate& danger) {
  const Eigen::Vector3d ds = -safe.u, dd = -danger.u;
  std::vector<std::pair<double, Eigen::Vector3d>> ranked;
  for (const Eigen::Vector3d& v : fibonacci_cap(3000, Eigen::Vector3d::UnitY(), 60.0)) {
    // To the patient's left or right: 20 degrees or more of the tilt across the body.
    if (angle_deg(v, Eigen::Vector3d::UnitY()) < 25.0 || std::abs(v.x()) < 0.34) continue;
    const double as = angle_deg(v, ds), ad = angle_deg(v, dd);
    if (as < 33 || as > 48 || ad < 33 || ad > 48) continue;
    ranked.emplace_back(std::abs(as - 38) + std::abs(ad - 38), v);
  }
  std::sort(ranked.begin(), ranked.end(),
            [](const auto& a, const auto& b) { return a.first < b.first; });
  std::vector<Eigen::Vector3d> out;
  for (const auto& [score, v] : ranked) {
    // Spread the tries: skip axes within 4 degrees of one already listed.
    const bool near = std::any_of(out.begin(), out.end(),
                                  [&](const Eigen::Vector3d& w) { return angle_deg(v, w) < 4.0; });
    if (!near) out.push_back(v);
    if (out.size() >= 24) break;
  }
  return out;
}

// The scene with the first oblique camera axis (oblique_axes) that keeps both boards in view and
// apart and sees each needle at kMinObliquityDeg or more from its viewing ray.
constexpr double kMinObliquityDeg = 30.0;

std::string build_scene_any_view(GuidanceScenario& sc, const planning::PlanData& plan,
                                 const Candidate& safe, const Candidate& danger,
                                 const GuidanceScenarioOptions& o) {
  const std::vector<Eigen::Vector3d> axes = oblique_axes(safe, danger);
  if (axes.empty()) return "no camera axis sees both approaches obliquely";
  std::string first_problem;
  const double t_safe0 = o.hold_s, t_safe1 = o.hold_s + o.approach_s;
  const double t_danger0 = t_safe1 + o.switch_s, t_danger1 = t_danger0 + o.approach_s;
  for (const Eigen::Vector3d& v : axes) {
    GuidanceScenario trial = sc;
    std::string problem = build_scene(trial, plan, safe, danger, o, v);
    if (problem.empty()) {
      const double os = min_view_obliquity_deg(trial, safe.entry, t_safe0, t_safe1);
      const double od = min_view_obliquity_deg(trial, danger.entry, t_danger0, t_danger1);
      if (os < kMinObliquityDeg || od < kMinObliquityDeg) {
        problem = "a needle is seen within " + std::to_string(int(kMinObliquityDeg)) +
                  " deg of its viewing ray";
      }
    }
    if (problem.empty()) {
      sc = std::move(trial);
      return "";
    }
    if (first_problem.empty()) first_problem = problem;
  }
  return first_problem;
}

GuidanceApproach make_approach(const std::string& name, const Candidate& c,
                               const GuidanceScenarioOptions& o, const Eigen::Vector3d& view_axis,
                               double start_s) {
  GuidanceApproach a;
  a.name = name;
  a.direction_ct = -c.u;
  a.entry_ct = c.entry;
  a.state = c.state;
  a.angle_from_anterior_deg = angle_deg(c.u, -Eigen::Vector3d::UnitY());
  a.angle_to_view_axis_deg = angle_deg(-c.u, view_axis);
  a.vessels = c.vessels;
  a.start_s = start_s;
  a.end_s = start_s + o.approach_s;
  return a;
}

std::string describe(const GuidanceApproach& a) {
  std::string structures;
  for (const planning::StructureHit& h : a.state.evaluation.structures) {
    if (!structures.empty()) structures += ", ";
    char b[160];
    std::snprintf(b, sizeof(b), "%s at %.1f mm (%.1f mm)", h.name.c_str(), h.depth_mm,
                  h.length_mm);
    structures += b;
  }
  char b[400];
  std::snprintf(b, sizeof(b),
                "%s approach: direction (%.3f, %.3f, %.3f), %.1f deg from anterior, entry (%.1f, "
                "%.1f, %.1f) mm, line integral %.3f, tip class %s, %s; crosses ",
                a.name.c_str(), a.direction_ct.x(), a.direction_ct.y(), a.direction_ct.z(),
                a.angle_from_anterior_deg, a.entry_ct.x(), a.entry_ct.y(), a.entry_ct.z(),
                a.state.evaluation.line_integral, a.state.tip_class.c_str(),
                planning::needle_safety_name(a.state.safety));
  return b + (structures.empty() ? std::string("nothing") : structures);
}

void check_scenario_inputs(const planning::PlanData& plan, const GuidanceScenarioOptions& o,
                           const std::string& what) {
  if (plan.labels.empty()) {
    throw Error(what + ": the plan has no label map (plan.json inputs.labels)");
  }
  if (plan.values.empty() || plan.path_safety.empty()) {
    throw Error(what + ": the plan has no path safety volume");
  }
  if (!(o.fps > 0) || !(o.approach_s > 0) || !(o.switch_s > 0) || o.hold_s < 0) {
    throw Error(what + ": fps, approach_s and switch_s must be > 0 and hold_s >= 0");
  }
  if (!(o.view_axis_ct.norm() > 0)) throw Error(what + ": view_axis_ct must not be zero");
}

// The candidate approaches: directions within max_angle_from_anterior_deg of anterior on a
// Fibonacci sphere, those whose line enters the body.
std::vector<Candidate> candidate_approaches(const Searcher& searcher,
                                            const GuidanceScenarioOptions& o) {
  const std::vector<Eigen::Vector3d> dirs =
      fibonacci_cap(o.sphere_points, -Eigen::Vector3d::UnitY(), o.max_angle_from_anterior_deg);
  std::vector<Candidate> all;
  all.reserve(dirs.size());
  for (const Eigen::Vector3d& u : dirs) {
    Candidate c = searcher.evaluate(u);
    if (c.valid) all.push_back(std::move(c));
  }
  return all;
}

// The safe candidates, nearest to the view axis v first, and how many are dangerous.
struct Census {
  std::vector<const Candidate*> safe;
  size_t n_dangerous = 0;
};

Census census_of(const Searcher& searcher, const std::vector<Candidate>& all,
                 const Eigen::Vector3d& v) {
  Census census;
  for (const Candidate& c : all) {
    if (searcher.is_safe(c)) census.safe.push_back(&c);
    if (searcher.is_dangerous(c)) ++census.n_dangerous;
  }
  std::sort(census.safe.begin(), census.safe.end(), [&](const Candidate* a, const Candidate* b) {
    return angle_deg(-a->u, v) < angle_deg(-b->u, v);
  });
  return census;
}

// Safe also when turned by robust_deg in any of 8 directions.
bool is_robustly_safe(const Searcher& searcher, const Candidate& s, double robust_deg) {
  for (const Eigen::Vector3d& w : Searcher::ring(s.u, robust_deg)) {
    if (!searcher.is_safe(searcher.evaluate(w))) return false;
  }
  return true;
}

// A dangerous candidate with its steadiness: still dangerous when turned by 1 degree in any of 8
// directions (no flicker under tracking noise).
struct Danger {
  const Candidate* c;
  bool steady;
};

// The dangerous partners of the safe candidate s, min..max_separation_deg from it, best first:
// vessel-only crossings first, then steady ones, then a clear crossing (>= 3 mm in the vessel),
// then a short swing (within 28 degrees), then the direction nearest the camera's axis v.
std::vector<Danger> dangerous_partners(const Searcher& searcher, const std::vector<Candidate>& all,
                                       const Candidate& s, const GuidanceScenarioOptions& o,
                                       const Eigen::Vector3d& v) {
  std::vector<Danger> danger;
  for (const Candidate& c : all) {
    const double sep = angle_deg(c.u, s.u);
    if (sep < o.min_separation_deg || sep > o.max_separation_deg || !searcher.is_dangerous(c)) {
      continue;
    }
    bool steady = true;
    for (const Eigen::Vector3d& w : Searcher::ring(c.u, 1.0)) {
      if (!searcher.is_dangerous(searcher.evaluate(w))) {
        steady = false;
        break;
      }
    }
    danger.push_back({&c, steady});
  }
  const double short_swing_deg = std::min(28.0, o.max_separation_deg);
  std::sort(danger.begin(), danger.end(), [&](const Danger& a, const Danger& b) {
    const auto key = [&](const Danger& d) {
      return std::make_tuple(d.c->other_high_risk, !d.steady, d.c->vessel_length_mm < 3.0,
                             angle_deg(d.c->u, s.u) > short_swing_deg, angle_deg(-d.c->u, v));
    };
    return key(a) < key(b);
  });
  return danger;
}

// The body on its table (skin in a field around the entries and the board, drape elsewhere) and
// the needle's shaft and hub.
void add_scene_meshes(GuidanceScenario& sc, const planning::PlanData& plan, const Candidate& s,
                      const Candidate& d) {
  BodyMeshOptions bo;
  const Eigen::Vector3d mid = 0.5 * (s.entry + d.entry);
  const Eigen::Vector3d board = sc.T_ct_patient.translation();
  bo.field_centre_ct = 0.5 * (mid + board);
  bo.field_half_x_mm = 0.5 * std::abs(board.x() - mid.x()) + 110.0;
  bo.field_half_z_mm = 0.5 * std::abs(board.z() - mid.z()) + 110.0;
  bo.step_mm = std::max(3.0, plan.labels.geometry().spacing.minCoeff());
  sc.scene.meshes = {body_mesh(plan.labels, sc.T_ct_patient, bo),
                     needle_mesh(tracking::kNeedleTipInNeedle.z())};
  sc.scene.validate("guidance scene");
}

// A built scene's approaches and needle calibration, logged.
void complete_scenario(GuidanceScenario& sc, const Candidate& s, const Candidate& d,
                       const GuidanceScenarioOptions& o) {
  const Eigen::Vector3d view = sc.T_cam_ct_nominal.linear().row(2).transpose();
  sc.safe = make_approach("safe", s, o, view, o.hold_s);
  sc.dangerous = make_approach("dangerous", d, o, view, o.hold_s + o.approach_s + o.switch_s);
  for (GuidanceApproach* a : {&sc.safe, &sc.dangerous}) {
    a->view_obliquity_deg = min_view_obliquity_deg(sc, a->entry_ct, a->start_s, a->end_s);
  }
  sc.needle.date = calibration::utc_timestamp();
  sc.needle.inputs = {"synthetic guidance scene (ground truth)"};
  sc.needle.board = "needle";
  sc.needle.tip_needle = tracking::kNeedleTipInNeedle;
  sc.needle.axis_needle = Eigen::Vector3d::UnitZ();
  spdlog::info("guidance scenario: {}", describe(sc.safe));
  spdlog::info("guidance scenario: {}", describe(sc.dangerous));
  const Eigen::Vector3d cam_ct = sc.T_cam_ct_nominal.inverse().translation();
  spdlog::info("guidance scenario: {:.1f} deg between the approaches; {} frames at {} fps; the "
               "camera {:.0f} deg off vertical, {:.0f} mm from the board, sees the needles at "
               "{:.0f} and {:.0f} deg from their viewing rays",
               angle_deg(sc.safe.direction_ct, sc.dangerous.direction_ct), sc.scene.frame_count,
               sc.scene.fps, angle_deg(view, Eigen::Vector3d::UnitY()),
               (cam_ct - sc.T_ct_patient.translation()).norm(), sc.safe.view_obliquity_deg,
               sc.dangerous.view_obliquity_deg);
}

}  // namespace

bool is_vessel_name(const std::string& name) {
  for (const char* w : {"vessel", "vein", "artery", "aorta", "cava", "portal"}) {
    if (contains_ci(name, w)) return true;
  }
  return false;
}

Eigen::Isometry3d GuidanceScenario::T_ct_needle_at(double time_s) const {
  const tracking::SceneBoard* patient = nullptr;
  const tracking::SceneBoard* needle_board = nullptr;
  for (const tracking::SceneBoard& b : scene.boards) {
    if (b.board.name == "patient") patient = &b;
    if (b.board.name == "needle") needle_board = &b;
  }
  if (!patient || !needle_board) throw Error("guidance scene: boards 'patient' and 'needle' needed");
  return Eigen::Translation3d(skin_displacement_at(time_s)) * T_ct_patient *
         tracking::pose_at(*patient, time_s).inverse() * tracking::pose_at(*needle_board, time_s);
}

Eigen::Vector3d GuidanceScenario::skin_displacement_at(double time_s) const {
  if (!(breathing_period_s > 0)) return Eigen::Vector3d::Zero();
  const double s = std::sin(M_PI * time_s / breathing_period_s);
  return planning::breathing_wall_displacement(T_ct_patient.translation(), s * s,
                                               breathing_amplitude_mm);
}

int GuidanceScenario::breathing_phase_at(double time_s) const {
  if (!(breathing_period_s > 0) || breathing_phases < 1) return -1;
  const double cycle = time_s / breathing_period_s - std::floor(time_s / breathing_period_s);
  return int(std::lround(cycle * breathing_phases)) % breathing_phases;
}

GuidanceScenario make_guidance_scenario(const planning::PlanData& plan,
                                        const GuidanceScenarioOptions& o) {
  const std::string what = "guidance scenario (plan " + plan.dir + ")";
  check_scenario_inputs(plan, o, what);
  GuidanceScenario sc;
  sc.target_ct = plan.tumor_centre;
  const Searcher searcher(plan, sc.target_ct);
  const std::vector<Candidate> all = candidate_approaches(searcher, o);
  const Eigen::Vector3d v = o.view_axis_ct.normalized();
  const Census census = census_of(searcher, all, v);
  spdlog::info("guidance scenario: {} directions within {} deg of anterior, {} safe, {} crossing "
               "a vessel dangerously",
               all.size(), o.max_angle_from_anterior_deg, census.safe.size(), census.n_dangerous);

  // The first pair (robustly safe, dangerous partner) whose scene can be built, at most 200 tried.
  std::string last_problem = "no direction is safe";
  int robust_found = 0, pairs_tried = 0;
  for (const Candidate* s : census.safe) {
    if (!is_robustly_safe(searcher, *s, o.robust_deg)) continue;
    ++robust_found;
    last_problem = "no dangerous direction crossing a vessel " +
                   std::to_string(int(o.min_separation_deg)) + " to " +
                   std::to_string(int(o.max_separation_deg)) + " deg from the safe one";
    const std::vector<Danger> danger = dangerous_partners(searcher, all, *s, o, v);
    for (const Danger& dg : danger) {
      if (++pairs_tried > 200) break;
      GuidanceScenario trial = sc;
      const std::string problem = build_scene_any_view(trial, plan, *s, *dg.c, o);
      if (!problem.empty()) {
        last_problem = problem;
        continue;
      }
      add_scene_meshes(trial, plan, *s, *dg.c);
      complete_scenario(trial, *s, *dg.c, o);
      return trial;
    }
    spdlog::debug("guidance scenario: safe direction {:.1f} deg from the view axis: {} dangerous "
                  "directions in range; {}",
                  angle_deg(-s->u, v), danger.size(), last_problem);
    if (pairs_tried > 200) break;
  }
  throw Error(what + ": cannot script the guidance scene: " + last_problem + " (" +
              std::to_string(census.safe.size()) + " safe directions, " +
              std::to_string(robust_found) + " of them safe within " +
              std::to_string(o.robust_deg) + " deg, " + std::to_string(census.n_dangerous) +
              " crossing a vessel dangerously)");
}

// ---------------------------------------------------------------------------------------------
// Files

std::string meshes_json_text(const tracking::SyntheticScene& s) {
  using nlohmann::json;
  json list = json::array();
  for (const tracking::SceneMesh& m : s.meshes) {
    std::vector<float> v, c;
    std::vector<int> t;
    for (const Eigen::Vector3f& p : m.vertices) v.insert(v.end(), {p.x(), p.y(), p.z()});
    for (const Eigen::Vector3f& p : m.colours) c.insert(c.end(), {p.x(), p.y(), p.z()});
    for (const Eigen::Vector3i& p : m.triangles) t.insert(t.end(), {p.x(), p.y(), p.z()});
    list.push_back({{"name", m.name}, {"board", m.board}, {"vertices_mm", v}, {"colours", c},
                    {"triangles", t}});
  }
  return list.dump();
}

std::string scene_json_text(const tracking::SyntheticScene& s, const std::string& camera_file,
                            const std::string& boards_file, const std::string& meshes_file) {
  using nlohmann::json;
  json j;
  if (!s.meshes.empty()) {
    j["meshes"] = meshes_file.empty() ? json::parse(meshes_json_text(s)) : json(meshes_file);
  }
  j["camera"] = camera_file;
  j["boards"] = boards_file;
  j["background"] = {{"type", s.background},
                     {"grey", s.background_grey},
                     {"contrast", s.background_contrast}};
  json poses = json::object();
  bool plate = true;
  for (const tracking::SceneBoard& b : s.boards) {
    plate = plate && b.plate;
    json keys = json::array();
    for (const tracking::PoseKeyframe& k : b.keyframes) {
      const Eigen::Quaterniond q(k.T_cam_board.linear());
      const Eigen::Vector3d t = k.T_cam_board.translation();
      keys.push_back({{"t", k.time_s},
                      {"translation_mm", {t.x(), t.y(), t.z()}},
                      {"quaternion", {q.w(), q.x(), q.y(), q.z()}}});
    }
    poses[b.board.name] = keys;
  }
  j["poses"] = poses;
  j["plate"] = plate;
  j["fps"] = s.fps;
  j["frames"] = s.frame_count;
  j["noise_sigma"] = s.noise_sigma;
  j["blur_sigma"] = s.blur_sigma;
  j["gain"] = s.gain;
  j["offset"] = s.offset;
  j["black"] = s.black;
  j["white"] = s.white;
  j["seed"] = s.seed;
  j["supersampling"] = s.supersampling;
  j["dropped_frames"] = s.dropped_frames;
  j["corrupt_frames"] = s.corrupt_frames;
  return j.dump(1);
}

void write_guidance_setup(const GuidanceScenario& sc, const std::string& dir) {
  namespace fs = std::filesystem;
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec) throw Error(dir + ": cannot create the folder (" + ec.message() + ")");
  const fs::path base(dir);
  sc.scene.camera.write_yaml((base / "camera.yaml").string());
  calibration::write_needle_calibration((base / "needle.yaml").string(), sc.needle);

  calibration::RegistrationRecord r;
  r.date = calibration::utc_timestamp();
  r.inputs = {"synthetic guidance scene (ground truth)"};
  r.board = "patient";
  r.T_ct_patient = sc.T_ct_patient;
  for (const tracking::SceneBoard& b : sc.scene.boards) {
    if (b.board.name != "patient") continue;
    r.board_fiducials = b.board.fiducials;
  }
  for (const Eigen::Vector3d& f : r.board_fiducials) {
    r.ct_fiducials.push_back(sc.T_ct_patient * f);
    r.fre_mm.push_back(0.0);
  }
  r.fiducials_in_board = r.fiducials_in_ct = int(r.board_fiducials.size());
  r.target_ct = sc.target_ct;
  calibration::write_registration((base / "registration.yaml").string(), r);

  std::vector<tracking::Board> boards;
  for (const tracking::SceneBoard& b : sc.scene.boards) boards.push_back(b.board);
  tracking::write_boards((base / "boards.json").string(), boards);

  if (!sc.scene.meshes.empty()) {
    write_text_file((base / "meshes.json").string(), meshes_json_text(sc.scene) + "\n");
  }
  write_text_file((base / "scene.json").string(),
                  scene_json_text(sc.scene, "camera.yaml", "boards.json",
                                  sc.scene.meshes.empty() ? "" : "meshes.json") +
                      "\n");
}

// The patient board's CT-visible fiducials, as a CT shows metal beads of 3 mm radius: painted
// into the phantom's CT where the scenario puts the board (partial volume from 4^3 subsamples
// per voxel), so that `register` has something to find.
int paint_board_beads(const GuidanceScenario& scenario, const std::string& ct_path) {
  planning::Volume<int16_t> ct = planning::read_volume<int16_t>(ct_path);
  const planning::ImageGeometry& g = ct.geometry();
  constexpr double kRadius = 3.0, kBeadHu = 6000.0;
  int painted = 0;
  for (const tracking::SceneBoard& b : scenario.scene.boards) {
    if (b.board.name != "patient") continue;
    for (const Eigen::Vector3d& f : b.board.fiducials) {
      const Eigen::Vector3d p = scenario.T_ct_patient * f;
      const Eigen::Vector3d c = g.physical_to_index(p);
      const Eigen::Vector3d reach = (kRadius / g.spacing.array() + 1.0).matrix();
      bool inside = false;
      for (int64_t k = int64_t(std::floor(c.z() - reach.z())); k <= int64_t(std::ceil(c.z() + reach.z())); ++k)
        for (int64_t j = int64_t(std::floor(c.y() - reach.y())); j <= int64_t(std::ceil(c.y() + reach.y())); ++j)
          for (int64_t i = int64_t(std::floor(c.x() - reach.x())); i <= int64_t(std::ceil(c.x() + reach.x())); ++i) {
            if (!g.contains(i, j, k)) continue;
            int in = 0;
            for (int s = 0; s < 64; ++s) {
              const Eigen::Vector3d q(double(i) + ((s & 3) + 0.5) / 4 - 0.5,
                                      double(j) + (((s >> 2) & 3) + 0.5) / 4 - 0.5,
                                      double(k) + (((s >> 4) & 3) + 0.5) / 4 - 0.5);
              if ((g.index_to_physical(q) - p).norm() <= kRadius) ++in;
            }
            if (in == 0) continue;
            inside = true;
            const double frac = in / 64.0;
            int16_t& v = ct(i, j, k);
            v = int16_t(std::lround(frac * kBeadHu + (1 - frac) * double(v)));
          }
      painted += inside ? 1 : 0;
    }
  }
  planning::write_volume(ct, ct_path);
  return painted;
}

}  // namespace crepuscular::pipelines
