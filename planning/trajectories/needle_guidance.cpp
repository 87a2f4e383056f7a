// Live needle safety: the tracked needle's line extended to the tumor, evaluated against a plan.
#include "planning/trajectories/needle_guidance.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <optional>

#include "foundation/error.hpp"
#include "planning/imaging/ray_march.hpp"
#include "planning/imaging/sampling.hpp"

namespace crepuscular::planning {

namespace {
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// The needle's tip and unit axis in CT and its forward line's closest approach to the tumor centre
// (the target); throws Error on a zero or non-finite axis or a non-finite tip.
NeedleState needle_line(const Eigen::Isometry3d& T_ct_needle, const Eigen::Vector3d& tip_in_needle,
                        const Eigen::Vector3d& axis_in_needle,
                        const Eigen::Vector3d& tumor_centre) {
  NeedleState s;
  const Eigen::Vector3d axis = T_ct_needle.linear() * axis_in_needle;
  if (!axis.allFinite() || !(axis.norm() > 1e-12) || !tip_in_needle.allFinite()) {
    throw Error("needle guidance: the needle axis must be a finite non-zero vector and the tip "
                "finite (needle calibration)");
  }
  s.tip = T_ct_needle * tip_in_needle;
  s.axis = axis.normalized();
  const Eigen::Vector3d c = tumor_centre;
  const Eigen::Vector3d w = c - s.tip;
  s.tip_to_centroid_mm = w.norm();
  const double along = w.dot(s.axis);
  s.points_away = along <= 0 && s.tip_to_centroid_mm > 1e-6;
  s.along_axis_mm = std::max(0.0, along);
  s.target = s.tip + s.along_axis_mm * s.axis;
  s.miss_distance_mm = (c - s.target).norm();
  return s;
}

// A tip already inside the body: the line is evaluated from where it entered the body (the
// nearest voxel outside the body behind the tip), so structures already pierced still count.
void start_line_at_body_entry(const PlanData& plan, NeedleState& s) {
  s.line_start = s.tip;
  if (!plan.labels.empty() && s.along_axis_mm > 1e-6 && in_body(plan.labels, s.tip)) {
    const double step = 0.5 * plan.labels.geometry().spacing.minCoeff();
    const std::optional<BodyExit> exit =
        first_body_exit(plan.labels, s.tip, -s.axis, step, 1000.0);
    // No exit (the body runs out of the scan behind the tip): keep the tip.
    if (exit) {
      s.line_start = exit->first_outside;
      s.tip_in_body = true;
    }
  }
}

// Path safety class at `tip` for the plan's first value ("" without a path safety volume).
std::string tip_class_at(const PlanData& plan, const Eigen::Vector3d& tip) {
  if (plan.values.empty()) return "";
  const auto vol = plan.path_safety.find(plan.values.front());
  if (vol == plan.path_safety.end()) return "";
  const double v = sample_path_safety(vol->second, tip);
  if (!std::isfinite(v)) return "outside";
  const SafetyClass k = plan.classes.at(plan.values.front()).classify(v);
  return k == SafetyClass::kSafe ? "safe" : k == SafetyClass::kMedium ? "medium" : "dangerous";
}

// The trajectory line_start -> target evaluated (clear, class at the start); without an
// extension, the class at the tip alone. class_only: only what the safety class depends on
// (TrajectoryEvaluator::evaluate_class; the line integral up to where it exceeds eps).
void evaluate_extension(const PlanData& plan, const TrajectoryEvaluator& evaluator, double eps,
                        NeedleState& s, bool class_only = false) {
  if (s.along_axis_mm > 1e-6) {
    Trajectory t;
    t.name = "needle";
    t.entry = s.line_start;
    t.target = s.target;
    s.evaluation = class_only ? evaluator.evaluate_class(t, eps) : evaluator.evaluate(t);
    s.clear = s.evaluation.line_integral <= eps;
    if (!s.evaluation.values.empty()) s.tip_class = s.evaluation.values.front().safety_class;
  } else {
    s.evaluation.trajectory.entry = s.evaluation.trajectory.target = s.tip;
    s.evaluation.labels_available = !plan.labels.empty();
    // Path safety at the tip even without an extension.
    s.tip_class = tip_class_at(plan, s.tip);
  }
}

// Whether the line meets the tumor: the mask when the plan has one, else the area safety
// ellipsoid, else the miss distance.
void find_tumor_hit(const PlanData& plan, NeedleState& s) {
  if (!plan.tumor.empty()) {
    s.tumor_depth_mm = s.evaluation.tumor_depth_mm;
    if (s.tumor_depth_mm >= 0 && s.tip_in_body) {
      s.tumor_depth_mm = std::max(0.0, s.tumor_depth_mm - (s.tip - s.line_start).norm());
    }
    if (s.along_axis_mm <= 1e-6 && !s.points_away) {
      const bool in = nearest_voxel_or<uint8_t>(plan.tumor, s.tip, 0) != 0;
      s.tumor_depth_mm = in ? 0.0 : -1.0;
    }
    s.hits_tumor = s.tumor_depth_mm >= 0;
  } else if (plan.area) {
    const Ellipsoid& e = plan.area->ellipsoid;
    const Eigen::Vector3d q =
        (e.axes.transpose() * (s.target - e.centre)).cwiseQuotient(e.radii);
    s.hits_tumor = !s.points_away && q.squaredNorm() <= 1.0;
  } else {
    s.hits_tumor = !s.points_away && s.miss_distance_mm <= 0.5;
  }
}

// Whether the evaluated line leaves the scanned volume where it matters: between the body and the
// target. The scan is convex (an intersection of grid boxes) and holds the target, so the part of
// the line outside it is one piece at the line's start; when that piece is no longer than the
// air between the start and the body (a tip held in front of the skin, the scan's edge in the
// air), the body part is all inside the scan.
bool leaves_scan_in_body(const PlanData& plan, const NeedleState& s) {
  const TrajectoryEvaluation& e = s.evaluation;
  if (e.outside_scan_mm <= 0.0 && !e.entry_outside_scan) return false;
  double air_mm = 0.0;
  if (!plan.labels.empty() && !s.tip_in_body) {
    const double step = 0.5 * plan.labels.geometry().spacing.minCoeff();
    const double length = (s.target - s.line_start).norm();
    while (air_mm < length && !in_body(plan.labels, s.line_start + air_mm * s.axis)) air_mm += step;
  }
  return e.outside_scan_mm > air_mm + e.structure_step_mm;
}

// The one rule set of the needle's class (NeedleState::safety), which the panel, overlay.csv,
// OpenIGTLink and the targeting view all show.
NeedleSafety overall_safety(const PlanData& plan, const NeedleState& s) {
  if (!s.clear || s.tip_class == "dangerous") return NeedleSafety::kDangerous;
  // No line to the tumor (pointing away, or the tip beyond the tumor's centre); a line that
  // leaves the scan inside the body; a tip with no extension where nothing was computed.
  const bool evaluated = s.along_axis_mm > 1e-6 || s.tip_class == "safe" || s.tip_class == "medium";
  if (s.points_away || !evaluated || leaves_scan_in_body(plan, s)) return NeedleSafety::kUnknown;
  return s.tip_class == "medium" ? NeedleSafety::kMedium : NeedleSafety::kSafe;
}

// Nearest safe direction: max dot product of the outward needle direction over the precomputed
// unit directions (angle NaN when there are none).
void find_nearest_safe_direction(const std::vector<Eigen::Vector3d>& safe_dirs,
                                 const std::vector<int>& safe_vertex, NeedleState& s) {
  s.angle_to_safe_deg = kNaN;
  if (safe_dirs.empty()) return;
  const Eigen::Vector3d out = -s.axis;
  double best = -2;
  size_t best_i = 0;
  for (size_t i = 0; i < safe_dirs.size(); ++i) {
    const double d = out.dot(safe_dirs[i]);
    if (d > best) {
      best = d;
      best_i = i;
    }
  }
  s.angle_to_safe_deg = std::acos(std::clamp(best, -1.0, 1.0)) * 180.0 / M_PI;
  s.nearest_safe_vertex = safe_vertex[best_i];
  s.nearest_safe_direction = safe_dirs[best_i];
}

}  // namespace

const char* needle_safety_name(NeedleSafety s) {
  switch (s) {
    case NeedleSafety::kSafe: return "safe";
    case NeedleSafety::kMedium: return "medium";
    case NeedleSafety::kDangerous: return "dangerous";
    case NeedleSafety::kUnknown: break;
  }
  return "unknown";
}

NeedleGuide::NeedleGuide(const std::string& plan_dir)
    : owned_(std::make_unique<PlanData>(load_plan(plan_dir))), plan_(owned_.get()) {
  init();
}

NeedleGuide::NeedleGuide(const PlanData& plan) : plan_(&plan) { init(); }

NeedleGuide::~NeedleGuide() = default;

void NeedleGuide::init() {
  evaluator_ = std::make_unique<TrajectoryEvaluator>(*plan_);
  const nlohmann::json& j = plan_->json;
  if (j.is_object() && j.contains("parameters") && j["parameters"].is_object() &&
      j["parameters"].contains("eps") && j["parameters"]["eps"].is_number()) {
    eps_ = j["parameters"]["eps"].get<double>();
  }
  if (plan_->area) {
    const AreaSafetyGeometry& a = *plan_->area;
    for (size_t i = 0; i < a.vertices.size() && i < a.safe.size(); ++i) {
      if (!a.safe[i]) continue;
      const Eigen::Vector3d d = a.vertices[i] - plan_->tumor_centre;
      if (!(d.norm() > 1e-9)) continue;
      safe_dirs_.push_back(d.normalized());
      safe_vertex_.push_back(int(i));
    }
  }
}

NeedleState NeedleGuide::evaluate(const Eigen::Isometry3d& T_ct_needle,
                                  const Eigen::Vector3d& tip_in_needle,
                                  const Eigen::Vector3d& axis_in_needle) const {
  const PlanData& plan = *plan_;
  NeedleState s = needle_line(T_ct_needle, tip_in_needle, axis_in_needle, plan.tumor_centre);
  s.eps = eps_;
  start_line_at_body_entry(plan, s);
  evaluate_extension(plan, *evaluator_, eps_, s);
  find_tumor_hit(plan, s);
  s.safety = overall_safety(plan, s);
  find_nearest_safe_direction(safe_dirs_, safe_vertex_, s);
  return s;
}

NeedleSafety NeedleGuide::line_safety(const Eigen::Vector3d& tip,
                                      const Eigen::Vector3d& axis) const {
  const PlanData& plan = *plan_;
  NeedleState s = needle_line(Eigen::Isometry3d::Identity(), tip, axis, plan.tumor_centre);
  s.eps = eps_;
  start_line_at_body_entry(plan, s);
  evaluate_extension(plan, *evaluator_, eps_, s, true);
  return overall_safety(plan, s);
}

NeedleState needle_guidance(const PlanData& plan, const Eigen::Isometry3d& T_ct_needle,
                            const Eigen::Vector3d& tip_in_needle,
                            const Eigen::Vector3d& axis_in_needle) {
  return NeedleGuide(plan).evaluate(T_ct_needle, tip_in_needle, axis_in_needle);
}

}  // namespace crepuscular::planning
