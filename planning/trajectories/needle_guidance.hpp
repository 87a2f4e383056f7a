// Live safety of a tracked needle against a plan (issue 7, overlay layer 5): the needle's tip and
// axis in CT, its line extended to the tumor and evaluated as a straight trajectory (evaluate.hpp:
// line integral of docs/ARCHITECTURE.md §4, structures crossed with depth), the distance to the
// target, whether the line meets the tumor, its safety class, and the angle to the nearest safe
// direction of the area safety geometry. No rendering.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <memory>
#include <string>
#include <vector>

#include "planning/trajectories/evaluate.hpp"

namespace crepuscular::planning {

// kUnknown: the needle's line leaves the scanned volume (docs/ARCHITECTURE.md §4) between the
// body and the target: what it crosses there is not known, so it is never called safe (a crossing
// seen in the scan still makes it dangerous). A tip held in the air beyond the scan's edge is not
// unknown.
enum class NeedleSafety { kSafe, kMedium, kDangerous, kUnknown };
const char* needle_safety_name(NeedleSafety s);  // "safe", "medium", "dangerous", "unknown"

struct NeedleState {
  Eigen::Vector3d tip = Eigen::Vector3d::Zero();   // needle tip in CT, LPS mm
  Eigen::Vector3d axis = Eigen::Vector3d::UnitZ();  // unit, from the tip forward (into the body)
  // The extension: the forward ray tip + s axis (s >= 0) ends at its point of closest approach to
  // the tumor centroid (plan.json tumor.centroid_lps_mm), the target of the line.
  Eigen::Vector3d target = Eigen::Vector3d::Zero();
  double along_axis_mm = 0;        // s of the target (0 when the needle points away)
  double tip_to_centroid_mm = 0;   // straight distance from the tip to the tumor centroid
  double miss_distance_mm = 0;     // distance from the centroid to the forward ray (0: dead on)
  bool points_away = false;        // the centroid lies behind the tip (no extension to evaluate)
  // The forward line meets the tumor: a tumor mask voxel between tip and target (mask loaded);
  // without a mask, the target inside the area safety ellipsoid; without either, miss <= 0.5 mm.
  bool hits_tumor = false;
  double tumor_depth_mm = -1;  // distance from the tip to where the line enters the tumor mask

  // Where the evaluated line starts: the tip, or, when the tip is already inside the body (label
  // map > 0), the point where the needle's line entered it (the first voxel outside the body
  // behind the tip), so that structures the needle has already pierced still count.
  Eigen::Vector3d line_start = Eigen::Vector3d::Zero();
  bool tip_in_body = false;
  // The trajectory line_start -> target, evaluated exactly as `crepuscular evaluate` does (entry =
  // line_start): line integral, structures with depth from line_start, path safety values there.
  // Empty (samples 0, line integral 0) when the needle points away.
  TrajectoryEvaluation evaluation;
  double eps = 0.5;   // insignificant blocking (plan.json parameters.eps)
  bool clear = true;  // line_integral <= eps (docs/ARCHITECTURE.md §4)
  // Path safety class at line_start for the plan's first value ("safe", "medium", "dangerous",
  // "outside" beyond the region of interest, "" when the plan has no path safety volume).
  std::string tip_class;
  // Overall, by one rule set: dangerous when not clear or the tip's class is dangerous; else
  // unknown when the needle points away from the tumor (its centre behind the tip: pointing away
  // or the tip beyond it), when its line leaves the scan inside the body, or when there is no
  // extension and no path safety value at the tip; else medium when the tip's class is medium;
  // safe otherwise (clear, and the tip safe or outside the computed region). Never safe without
  // a line to the tumor inside the scan.
  NeedleSafety safety = NeedleSafety::kSafe;

  // Nearest safe direction: the smallest angle between the needle's outward direction (-axis,
  // from the tumor back along the needle) and the unit directions from the tumor centroid to the
  // extruded safe vertices of the area safety geometry. NaN (vertex -1) without safe vertices.
  double angle_to_safe_deg = 0;
  int nearest_safe_vertex = -1;
  Eigen::Vector3d nearest_safe_direction = Eigen::Vector3d::Zero();  // unit, outward from tumor
};

// Built once per plan; evaluate() per tracked frame (a few hundred lookups, well under 1 ms).
class NeedleGuide {
 public:
  // Loads the plan folder (load_plan: blocking, path safety, labels, tumor, area safety).
  explicit NeedleGuide(const std::string& plan_dir);
  // Uses a plan already in memory; `plan` must outlive the guide.
  explicit NeedleGuide(const PlanData& plan);
  ~NeedleGuide();
  NeedleGuide(const NeedleGuide&) = delete;
  NeedleGuide& operator=(const NeedleGuide&) = delete;

  // T_ct_needle maps needle coordinates to CT (LPS mm); tip and axis are in needle coordinates
  // (the axis need not be unit). Throws Error when the axis is zero or not finite.
  NeedleState evaluate(const Eigen::Isometry3d& T_ct_needle, const Eigen::Vector3d& tip_in_needle,
                       const Eigen::Vector3d& axis_in_needle) const;

  // The safety evaluate() gives a needle whose tip is at `tip` (CT) pointing along `axis` (CT,
  // need not be unit), by the same rule set; only what the
  // class depends on is computed (no structures, ranks or area safety; the line integral up to
  // where it exceeds eps), so it costs a fraction of evaluate(). For many lines at once, e.g. the
  // targeting view's polar map. Throws Error as evaluate() does.
  NeedleSafety line_safety(const Eigen::Vector3d& tip, const Eigen::Vector3d& axis) const;

  const PlanData& plan() const { return *plan_; }
  // Unit directions from the tumor centroid to each safe extruded vertex, and those vertices.
  const std::vector<Eigen::Vector3d>& safe_directions() const { return safe_dirs_; }

 private:
  void init();
  std::unique_ptr<PlanData> owned_;
  const PlanData* plan_ = nullptr;
  std::unique_ptr<TrajectoryEvaluator> evaluator_;
  std::vector<Eigen::Vector3d> safe_dirs_;
  std::vector<int> safe_vertex_;
  double eps_ = 0.5;
};

// One-off form (builds a NeedleGuide on `plan`; for many frames keep a NeedleGuide).
NeedleState needle_guidance(const PlanData& plan, const Eigen::Isometry3d& T_ct_needle,
                            const Eigen::Vector3d& tip_in_needle,
                            const Eigen::Vector3d& axis_in_needle);

}  // namespace crepuscular::planning
