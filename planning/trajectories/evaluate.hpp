// The retrospective check of one straight needle trajectory against a plan folder (paper
// section 5, "gold standard comparison"): line integral of blocking, structures
// hit, path safety at the entry and its rank, and the area safety region the entry lies in.
#pragma once

#include <Eigen/Core>
#include <limits>
#include <map>
#include <memory>
#include <nlohmann/json_fwd.hpp>
#include <optional>
#include <string>
#include <vector>

#include "planning/imaging/volume.hpp"
#include "planning/plan_folder/plan_folder.hpp"

namespace crepuscular::planning {

// Path safety value at a point: trilinear over the computed voxels (NaN voxels are left out and
// the weights of the others renormalised); NaN where no corner of the cell was computed.
double sample_path_safety(const Volume<float>& volume, const Eigen::Vector3d& point_lps);

// Parses "x,y,z" (mm); throws Error naming `what`.
Eigen::Vector3d parse_point(const std::string& text, const std::string& what);

// --- Trajectory evaluation
// ------------------------------------------------------------------------

struct Trajectory {
  std::string name;
  Eigen::Vector3d entry = Eigen::Vector3d::Zero();   // skin entry point, LPS mm
  Eigen::Vector3d target = Eigen::Vector3d::Zero();  // needle tip in the tumor, LPS mm
};

// One labelled structure the straight path passes through.
struct StructureHit {
  int label = 0;
  std::string name;  // from the vulnerability table ("label <v>" when not listed)
  int level = -1;    // vulnerability level, -1 when not listed
  std::string level_name;
  double blocking_per_mm = 0;
  double depth_mm = 0;   // distance from the entry to where the path first enters it
  double length_mm = 0;  // total path length inside it
};

struct EntryValue {
  std::string value;             // "svv", "isbv", ...
  double at_entry = 0;           // NaN outside the region of interest or outside the scan
  // "safe", "medium", "dangerous", "outside" (the region of interest) or "unknown": the entry
  // lies outside the scan, or the path leaves the scan where the value alone would say safe
  // (the anatomy there is unknown; a medium or dangerous value stays: unknown parts only add).
  std::string safety_class;
  double percentile = 0;         // % of ROI voxels with a lower value (ties count half)
  double safety_percentile = 0;  // % of ROI voxels less safe than the entry (100: safest)
  // Breathing plans with per-phase volumes: the value at the entry in each phase, and the least
  // safe phase (svv: the lowest value; the others: the highest); empty / NaN otherwise.
  std::vector<double> per_phase;
  std::string worst_phase;
  double at_worst_phase = 0;
};

// The area safety region of the entry: the base vertex of the area safety geometry whose normal
// ray (base + t normal, t >= 0; the direction each vertex was extruded in) passes closest to the
// entry. That column of the extrusion is where the needle leaves the tumor's surroundings.
struct EntryArea {
  bool available = false;  // the plan has an area safety geometry
  int vertex = -1;
  double ray_distance_mm = 0;  // distance from the entry to that vertex's normal ray
  double along_normal_mm = 0;  // the entry's distance along the ray from the base vertex
  double extrusion_mm = 0;     // how far that vertex was extruded
  bool safe = false;           // the vertex belongs to a safe region
  int region = -1;
  double region_size_mm3 = 0;
  double relative_area_safety = 0;  // region size / largest region size, 0..1 (paper section 5)
};

struct TrajectoryEvaluation {
  Trajectory trajectory;
  double length_mm = 0;
  double step_mm = 0;            // the line integral's sampling step l (<= gamma)
  int samples = 0;               // N
  double line_integral = 0;      // sum_k b(x_k) l, docs/ARCHITECTURE.md §4 (k = 1..N, x_N = target)
  double structure_step_mm = 0;  // sampling step of the structure search
  std::vector<StructureHit> structures;  // by depth
  bool labels_available = false;
  bool target_in_tumor = false;
  double tumor_depth_mm = -1;  // where the path first enters the tumor; -1: never / no mask
  // Scan coverage (planning/safety/unknown.hpp): a point is outside the scan where its nearest
  // voxel of the plan's region states is unknown, or (plans with region states) where it lies
  // beyond the blocking grid. Plans without roi.nii.gz: always inside.
  bool entry_outside_scan = false;
  double outside_scan_mm = 0;  // length of entry -> target outside the scan (+/- structure step)
  bool leaves_scan() const { return entry_outside_scan || outside_scan_mm > 0; }
  std::vector<EntryValue> values;
  EntryArea area;
};

// Evaluates straight trajectories against one plan. Building it sorts each path safety volume's
// region of interest once, so batches are cheap.
class TrajectoryEvaluator {
 public:
  explicit TrajectoryEvaluator(const PlanData& plan);
  ~TrajectoryEvaluator();
  // Throws Error (naming the trajectory) when entry and target coincide.
  TrajectoryEvaluation evaluate(const Trajectory& trajectory) const;
  // What a path's safety class depends on, the same as evaluate() gives: the scan coverage
  // (entry_outside_scan, outside_scan_mm, structure_step_mm), the first value at the entry with
  // its class (values holds that one only, without ranks or breathing phases) and the line
  // integral, whose sum stops once it exceeds `stop_above` (the samples after that are left out:
  // the blocking is never negative, so the integral only grows) or when the entry's class is
  // "dangerous" (line_integral 0 then). No structures, tumor or area safety. For many lines at
  // once, e.g. the targeting view's polar map.
  TrajectoryEvaluation evaluate_class(
      const Trajectory& trajectory,
      double stop_above = std::numeric_limits<double>::infinity()) const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

nlohmann::json evaluation_json(const TrajectoryEvaluation& e);
std::string evaluation_text(const TrajectoryEvaluation& e);

// Batch CSV. Input header: name,entry_x,entry_y,entry_z,target_x,target_y,target_z (LPS mm).
std::vector<Trajectory> read_trajectories_csv(const std::string& path);
// Output: one row per trajectory; columns depend on the plan's values (the same for every row).
std::string evaluation_csv_header(const TrajectoryEvaluation& e);
std::string evaluation_csv_row(const TrajectoryEvaluation& e);

// The entry/target of a line markup: the control point nearer the tumor centre is the target.
Trajectory trajectory_from_markup(const std::string& path, const Eigen::Vector3d& tumor_centre);

}  // namespace crepuscular::planning
