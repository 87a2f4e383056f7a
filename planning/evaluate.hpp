// Reading a plan folder back, and the retrospective check of one straight needle trajectory
// against it (paper section 5, "gold standard comparison"): line integral of blocking, structures
// hit, path safety at the entry and its rank, and the area safety region the entry lies in.
#pragma once

#include <Eigen/Core>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "planning/area_safety.hpp"
#include "planning/safety_classes.hpp"
#include "planning/volume.hpp"
#include "planning/vulnerability.hpp"

namespace crepuscular::planning {

// --- Plan folder
// ----------------------------------------------------------------------------------

struct PlanLoadOptions {
  bool blocking = true;     // PLAN_DIR/blocking.nii.gz (required when true)
  bool path_safety = true;  // every path_safety_<value>.nii.gz listed in plan.json
  std::string only_value;   // when set: load only this path safety value ("svv", ...)
  bool labels = true;       // the label map: labels_override, else plan.json inputs.labels
  std::string labels_override;
  bool tumor = true;        // the tumor mask of plan.json inputs.tumor (skipped if missing)
  bool area_safety = true;  // PLAN_DIR/area_safety.vtk when present
};

// A plan folder as `crepuscular plan` wrote it. Optional parts are empty when absent.
struct PlanData {
  std::string dir;
  nlohmann::json json;  // plan.json
  ImageGeometry grid;   // path safety grid (plan.json "grid")
  double gamma_mm = 0;  // sampling step bound of the plan (h / 2)
  Eigen::Vector3d tumor_centre = Eigen::Vector3d::Zero();  // plan.json tumor centroid, LPS mm
  double radius_mm = 0;                                    // region of interest radius R
  Volume<float> blocking;
  std::vector<std::string> values;  // computed values, plan.json order ("svv", "isbv", ...)
  std::map<std::string, Volume<float>> path_safety;  // NaN outside the region of interest
  std::map<std::string, SafetyClasses> classes;      // plan.json "classes"
  Volume<int32_t> labels;                            // empty when the plan has no label map
  std::string labels_path;
  std::optional<VulnerabilityTable> table;  // plan.json preprocessing.vulnerability
  Volume<uint8_t> tumor;                    // empty when the mask is not found
  std::optional<AreaSafetyGeometry> area;   // area_safety.vtk, when the plan has one
};

// Reads plan.json and the files asked for. Throws Error naming the file and the field when
// plan.json is missing or malformed or a required volume cannot be read. A label map or tumor
// mask that moved since planning is skipped with a warning (give labels_override instead).
PlanData load_plan(const std::string& plan_dir, const PlanLoadOptions& options = {});

// Classes of a value as plan.json states them ("classes"); throws Error when absent.
SafetyClasses classes_from_json(const nlohmann::json& plan, const std::string& value,
                                const std::string& source);

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
  double at_entry = 0;           // NaN when the entry lies outside the region of interest
  std::string safety_class;      // "safe", "medium", "dangerous" or "outside"
  double percentile = 0;         // % of ROI voxels with a lower value (ties count half)
  double safety_percentile = 0;  // % of ROI voxels less safe than the entry (100: safest)
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
  double line_integral = 0;      // sum_k b(x_k) l, DESIGN.md section 4 (k = 1..N, x_N = target)
  double structure_step_mm = 0;  // sampling step of the structure search
  std::vector<StructureHit> structures;  // by depth
  bool labels_available = false;
  bool target_in_tumor = false;
  double tumor_depth_mm = -1;  // where the path first enters the tumor; -1: never / no mask
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
