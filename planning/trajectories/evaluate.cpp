// The retrospective evaluation of straight needle trajectories against a plan.
#include "planning/trajectories/evaluate.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>
#include <sstream>

#include <nlohmann/json.hpp>

#include "foundation/csv.hpp"
#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "kernels/path_safety_math.hpp"
#include "planning/trajectories/markups.hpp"
#include "planning/safety/path_safety_scene.hpp"
#include "planning/imaging/sampling.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/safety/unknown.hpp"

namespace fs = std::filesystem;

namespace crepuscular::planning {

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

const char* class_name(SafetyClass c) {
  return c == SafetyClass::kSafe ? "safe" : c == SafetyClass::kMedium ? "medium" : "dangerous";
}

std::string point_text(const Eigen::Vector3d& p) {
  return fmt::format("({:.1f}, {:.1f}, {:.1f})", p.x(), p.y(), p.z());
}

}  // namespace

double sample_path_safety(const Volume<float>& volume, const Eigen::Vector3d& point_lps) {
  if (volume.empty()) return kNaN;
  return trilinear_finite(volume, volume.physical_to_index(point_lps), 1e-12);
}

Eigen::Vector3d parse_point(const std::string& text, const std::string& what) {
  const auto fields = split_csv_line(text, ',', true);
  Eigen::Vector3d p;
  bool ok = fields.size() == 3;
  for (size_t a = 0; ok && a < 3; ++a) ok = parse_double(fields[a], &p[int(a)]);
  if (!ok) throw Error(what + ": \"" + text + "\" is not a point (expected x,y,z in LPS mm)");
  return p;
}

// --- Evaluation ---------------------------------------------------------------------------------

struct TrajectoryEvaluator::Impl {
  const PlanData& plan;
  Volume<uint8_t> no_tumor;
  TumorSurface no_surface;
  kernels::PathSafetyScene<double> scene{};
  std::map<std::string, std::vector<float>> sorted;  // finite ROI values per value

  explicit Impl(const PlanData& p) : plan(p) {
    if (plan.blocking.empty()) {
      throw Error(plan.dir + ": the plan's blocking volume is needed to evaluate a trajectory");
    }
    // The scene of the path safety kernels: the very same trilinear sampler and ray stepping.
    scene = make_scene(plan.blocking, no_tumor, no_surface, plan.gamma_mm, 0.0);
    for (const auto& [name, volume] : plan.path_safety) {
      auto& v = sorted[name];
      for (float x : volume.values()) {
        if (std::isfinite(x)) v.push_back(x);
      }
      std::sort(v.begin(), v.end());
    }
  }
};

TrajectoryEvaluator::TrajectoryEvaluator(const PlanData& plan)
    : impl_(std::make_unique<Impl>(plan)) {}
TrajectoryEvaluator::~TrajectoryEvaluator() = default;

namespace {

// Line integral exactly as docs/ARCHITECTURE.md §4 defines it for a ray p -> t (kernels): sets the
// integral, its sample count and its step.
void integrate_blocking(const kernels::PathSafetyScene<double>& scene, const Trajectory& t,
                        TrajectoryEvaluation& e,
                        double stop_above = std::numeric_limits<double>::infinity()) {
  kernels::SurfacePoint<double> target{};
  target.position = {t.target.x(), t.target.y(), t.target.z()};
  target.normal = {0, 0, 0};
  target.offset = -1;
  const kernels::Vec3<double> p{t.entry.x(), t.entry.y(), t.entry.z()};
  const auto ray = kernels::make_ray(scene, p, target);
  const kernels::GridSampler<double> sampler{scene.blocking};
  double integral = 0;
  for (int k = 1; k <= ray.n; ++k) {
    integral += sampler(kernels::along(ray.q0, ray.dq, double(k))) * double(ray.step);
    if (integral > stop_above) break;
  }
  e.samples = ray.n;
  e.step_mm = double(ray.step);
  e.line_integral = integral;
}

// The structure search's sample count M over `length_mm`: the step is at most gamma and at most
// half the finest spacing of the label map and the tumor mask.
int structure_sample_count(const PlanData& plan, double length_mm) {
  double step_bound = plan.gamma_mm;
  if (!plan.labels.empty())
    step_bound = std::min(step_bound, 0.5 * plan.labels.geometry().spacing.minCoeff());
  if (!plan.tumor.empty())
    step_bound = std::min(step_bound, 0.5 * plan.tumor.geometry().spacing.minCoeff());
  return std::max(1, int(std::ceil(length_mm / step_bound)));
}

// A structure first met at `depth_mm`, named and rated from the plan's vulnerability table.
StructureHit structure_hit(const PlanData& plan, int32_t label, double depth_mm) {
  StructureHit h;
  h.label = label;
  h.name = "label " + std::to_string(label);
  h.depth_mm = depth_mm;
  if (plan.table) {
    if (const LabelClass* c = plan.table->find_label(label)) {
      h.name = c->name;
      h.level = c->level;
      if (const VulnerabilityLevel* lv = plan.table->find_level(c->level)) {
        h.level_name = lv->name;
        h.blocking_per_mm = lv->blocking_per_mm;
      }
    }
  }
  return h;
}

// Structures and tumor: nearest-voxel lookups at samples k = 0..M (entry to target). A structure
// is entered half a step before its first sample; its length is its sample count times the step.
void find_structures_and_tumor(const PlanData& plan, const Trajectory& t, TrajectoryEvaluation& e) {
  const Eigen::Vector3d d = t.target - t.entry;
  const int m = structure_sample_count(plan, e.length_mm);
  const double l = e.length_mm / m;
  e.structure_step_mm = l;
  e.labels_available = !plan.labels.empty();
  std::map<int, StructureHit> hits;
  int tumor_first = -1;
  for (int k = 0; k <= m; ++k) {
    const Eigen::Vector3d x = t.entry + (double(k) / m) * d;
    const double depth = k == 0 ? 0.0 : (k - 0.5) * l;
    if (e.labels_available) {
      const int32_t label = nearest_voxel_or<int32_t>(plan.labels, x, 0);
      if (label != 0) {
        auto it = hits.find(label);
        if (it == hits.end()) it = hits.emplace(label, structure_hit(plan, label, depth)).first;
        it->second.length_mm += l;
      }
    }
    if (!plan.tumor.empty() && tumor_first < 0 && nearest_voxel_or<uint8_t>(plan.tumor, x, 0)) {
      tumor_first = k;
    }
  }
  for (const auto& [label, h] : hits) e.structures.push_back(h);
  std::stable_sort(
      e.structures.begin(), e.structures.end(),
      [](const StructureHit& a, const StructureHit& b) { return a.depth_mm < b.depth_mm; });
  if (!plan.tumor.empty()) {
    e.target_in_tumor = nearest_voxel_or<uint8_t>(plan.tumor, t.target, 0) != 0;
    e.tumor_depth_mm = tumor_first < 0 ? -1.0 : tumor_first == 0 ? 0.0 : (tumor_first - 0.5) * l;
  }
}

// Whether p lies outside the scan, as far as the plan records it (TrajectoryEvaluation).
bool outside_scan(const PlanData& plan, const Eigen::Vector3d& p) {
  if (plan.region.empty()) return false;
  if (nearest_voxel_or<uint8_t>(plan.region, p, kRegionNotComputed) == kRegionUnknown) return true;
  return !plan.blocking.empty() &&
         !within_extent(plan.blocking.geometry(), plan.blocking.physical_to_index(p));
}

// The entry outside the scan, and the length of entry -> target outside it: the midpoints of the
// structure search's M steps, each step counted whole.
void find_scan_coverage(const PlanData& plan, const Trajectory& t, TrajectoryEvaluation& e) {
  e.entry_outside_scan = outside_scan(plan, t.entry);
  if (plan.region.empty()) return;
  const int m = structure_sample_count(plan, e.length_mm);
  const double l = e.length_mm / m;
  int outside = 0;
  for (int k = 1; k <= m; ++k) {
    outside += outside_scan(plan, t.entry + ((double(k) - 0.5) / m) * (t.target - t.entry));
  }
  e.outside_scan_mm = outside * l;
}

// Path safety of one value at the entry, its class and its rank within the region of interest
// (`sorted`: the finite values of the volume, ascending).
EntryValue entry_value(const std::string& value, const Volume<float>& volume,
                       const SafetyClasses& classes, const std::vector<float>& sorted,
                       const Eigen::Vector3d& entry) {
  EntryValue ev;
  ev.value = value;
  ev.at_entry = sample_path_safety(volume, entry);
  if (std::isfinite(ev.at_entry)) {
    ev.safety_class = class_name(classes.classify(ev.at_entry));
    const auto& s = sorted;
    const auto lo = std::lower_bound(s.begin(), s.end(), float(ev.at_entry));
    const auto hi = std::upper_bound(s.begin(), s.end(), float(ev.at_entry));
    const double below = double(lo - s.begin()), equal = double(hi - lo);
    ev.percentile = s.empty() ? kNaN : 100.0 * (below + 0.5 * equal) / double(s.size());
    ev.safety_percentile = classes.higher_is_safer ? ev.percentile : 100.0 - ev.percentile;
  } else {
    ev.safety_class = "outside";
    ev.percentile = ev.safety_percentile = kNaN;
  }
  return ev;
}

// Area safety: the extrusion column (normal ray of a base vertex) nearest to the entry.
EntryArea entry_area(const AreaSafetyGeometry& a, const Eigen::Vector3d& entry) {
  EntryArea area;
  area.available = true;
  double best = std::numeric_limits<double>::infinity();
  for (size_t i = 0; i < a.base.size(); ++i) {
    const Eigen::Vector3d w = entry - a.base[i];
    const double s = w.dot(a.normals[i]);
    const double dist = s > 0 ? (w - s * a.normals[i]).norm() : w.norm();
    if (dist < best) {
      best = dist;
      area.vertex = int(i);
      area.along_normal_mm = std::max(0.0, s);
    }
  }
  const size_t v = size_t(area.vertex);
  area.ray_distance_mm = best;
  area.extrusion_mm = (v < a.vertices.size()) ? (a.vertices[v] - a.base[v]).norm() : 0.0;
  area.safe = v < a.safe.size() && a.safe[v] != 0;
  area.region = v < a.region.size() ? a.region[v] : -1;
  double largest = 0;
  for (const auto& r : a.regions) largest = std::max(largest, r.size_mm3);
  for (const auto& r : a.regions) {
    if (r.id == area.region) area.region_size_mm3 = r.size_mm3;
  }
  if (area.region >= 0 && largest > 0) {
    area.relative_area_safety = area.region_size_mm3 / largest;
  } else if (area.region >= 0 && v < a.leeway.size()) {
    area.relative_area_safety = a.leeway[v];  // no region sizes: the stored leeway
  }
  return area;
}

}  // namespace

namespace {

// Breathing plans (docs/ARCHITECTURE.md §10): the entry's value in each phase and the least safe
// phase.
void worst_phase(const PlanData& plan, const std::string& value, const Eigen::Vector3d& entry,
                 EntryValue& ev) {
  ev.at_worst_phase = kNaN;
  const auto it = plan.phase_path_safety.find(value);
  if (it == plan.phase_path_safety.end()) return;
  const bool higher_is_safer = plan.classes.at(value).higher_is_safer;
  for (size_t k = 0; k < it->second.size(); ++k) {
    const double x = sample_path_safety(it->second[k], entry);
    ev.per_phase.push_back(x);
    if (!std::isfinite(x)) continue;
    const bool worse = std::isnan(ev.at_worst_phase) ||
                       (higher_is_safer ? x < ev.at_worst_phase : x > ev.at_worst_phase);
    if (worse && k < plan.phases.size()) {
      ev.at_worst_phase = x;
      ev.worst_phase = plan.phases[k];
    }
  }
}

}  // namespace

namespace {

// A trajectory with its length, checked: throws Error naming it when the entry or target is not
// finite, when they coincide, or when it is longer than any needle.
TrajectoryEvaluation checked_trajectory(const Trajectory& t) {
  TrajectoryEvaluation e;
  e.trajectory = t;
  e.length_mm = (t.target - t.entry).norm();
  if (!std::isfinite(e.length_mm) || !t.entry.allFinite() || !t.target.allFinite()) {
    throw Error("trajectory \"" + t.name + "\": entry or target is not a finite point");
  }
  if (!(e.length_mm > 1e-6)) {
    throw Error("trajectory \"" + t.name + "\": entry and target coincide " + point_text(t.entry));
  }
  // Longer than any needle by far: a typing error (metres for millimetres, a stray exponent),
  // refused before millions of samples are taken or a sample count overflows.
  constexpr double kLongestPathMm = 2000.0;
  if (e.length_mm > kLongestPathMm) {
    throw Error("trajectory \"" + t.name + "\": entry " + point_text(t.entry) + " lies " +
                fmt::format("{:.6g}", e.length_mm) + " mm from the target; a needle path is at most " +
                fmt::format("{:.0f}", kLongestPathMm) + " mm (coordinates are LPS millimetres)");
  }
  return e;
}

// Unknown is never safe: no value at an entry outside the scan (the trilinear sample could borrow
// one from computed neighbours), and no "safe" for a path that leaves the scan.
void mark_unknown(const TrajectoryEvaluation& e, EntryValue& ev) {
  if (e.entry_outside_scan) {
    ev.at_entry = ev.percentile = ev.safety_percentile = kNaN;
    ev.safety_class = "unknown";
  } else if (e.leaves_scan() && ev.safety_class == "safe") {
    ev.safety_class = "unknown";
  }
}

}  // namespace

TrajectoryEvaluation TrajectoryEvaluator::evaluate_class(const Trajectory& t,
                                                         double stop_above) const {
  const PlanData& plan = impl_->plan;
  TrajectoryEvaluation e = checked_trajectory(t);
  e.structure_step_mm = e.length_mm / structure_sample_count(plan, e.length_mm);
  e.labels_available = !plan.labels.empty();
  find_scan_coverage(plan, t, e);
  for (const auto& value : plan.values) {
    const auto vol = plan.path_safety.find(value);
    if (vol == plan.path_safety.end()) continue;
    EntryValue ev;
    ev.value = value;
    ev.at_entry = sample_path_safety(vol->second, t.entry);
    ev.safety_class = std::isfinite(ev.at_entry)
                          ? class_name(plan.classes.at(value).classify(ev.at_entry))
                          : "outside";
    ev.percentile = ev.safety_percentile = ev.at_worst_phase = kNaN;
    mark_unknown(e, ev);
    e.values.push_back(std::move(ev));
    break;  // the first value only
  }
  if (e.values.empty() || e.values.front().safety_class != "dangerous") {
    integrate_blocking(impl_->scene, t, e, stop_above);
  }
  return e;
}

TrajectoryEvaluation TrajectoryEvaluator::evaluate(const Trajectory& t) const {
  const PlanData& plan = impl_->plan;
  TrajectoryEvaluation e = checked_trajectory(t);
  integrate_blocking(impl_->scene, t, e);
  find_structures_and_tumor(plan, t, e);
  find_scan_coverage(plan, t, e);
  for (const auto& value : plan.values) {
    const auto vol = plan.path_safety.find(value);
    if (vol == plan.path_safety.end()) continue;
    e.values.push_back(
        entry_value(value, vol->second, plan.classes.at(value), impl_->sorted.at(value), t.entry));
    EntryValue& ev = e.values.back();
    worst_phase(plan, value, t.entry, ev);
    mark_unknown(e, ev);
  }
  if (plan.area && !plan.area->base.empty() &&
      plan.area->normals.size() == plan.area->base.size()) {
    e.area = entry_area(*plan.area, t.entry);
    if (e.leaves_scan()) e.area.safe = false;  // not reported safe: see evaluation_text
  }
  return e;
}

// --- Output -------------------------------------------------------------------------------------

nlohmann::json evaluation_json(const TrajectoryEvaluation& e) {
  const auto num = [](double v) -> nlohmann::json {
    return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(nullptr);
  };
  const auto vec = [](const Eigen::Vector3d& p) { return nlohmann::json{p.x(), p.y(), p.z()}; };
  nlohmann::json j;
  j["name"] = e.trajectory.name;
  j["entry_lps_mm"] = vec(e.trajectory.entry);
  j["target_lps_mm"] = vec(e.trajectory.target);
  j["length_mm"] = e.length_mm;
  j["line_integral"] = e.line_integral;
  j["line_integral_samples"] = e.samples;
  j["line_integral_step_mm"] = e.step_mm;
  nlohmann::json structures = nlohmann::json::array();
  for (const auto& h : e.structures) {
    structures.push_back({{"label", h.label},
                          {"name", h.name},
                          {"level", h.level},
                          {"level_name", h.level_name},
                          {"blocking_per_mm", h.blocking_per_mm},
                          {"depth_mm", h.depth_mm},
                          {"length_mm", h.length_mm}});
  }
  j["structures"] = e.labels_available ? structures : nlohmann::json(nullptr);
  j["structure_step_mm"] = e.structure_step_mm;
  j["target_in_tumor"] = e.target_in_tumor;
  j["tumor_depth_mm"] = e.tumor_depth_mm >= 0 ? nlohmann::json(e.tumor_depth_mm) : nullptr;
  j["scan"] = {{"entry_outside_scan", e.entry_outside_scan},
               {"length_outside_scan_mm", e.outside_scan_mm},
               {"leaves_scan", e.leaves_scan()},
               {"note",
                "outside the scan the anatomy is unknown: never reported safe (class "
                "\"unknown\")"}};
  nlohmann::json values = nlohmann::json::object();
  for (const auto& v : e.values) {
    values[v.value] = {{"at_entry", num(v.at_entry)},
                       {"class", v.safety_class},
                       {"percentile", num(v.percentile)},
                       {"safety_percentile", num(v.safety_percentile)}};
    if (!v.per_phase.empty()) {
      nlohmann::json per_phase = nlohmann::json::array();
      for (double x : v.per_phase) per_phase.push_back(num(x));
      values[v.value]["per_phase"] = per_phase;
      values[v.value]["worst_phase"] =
          v.worst_phase.empty() ? nlohmann::json(nullptr) : nlohmann::json(v.worst_phase);
      values[v.value]["at_worst_phase"] = num(v.at_worst_phase);
    }
  }
  j["path_safety"] = values;
  if (e.area.available) {
    j["area_safety"] = {{"method",
                         "base vertex whose extrusion ray (along its normal) passes "
                         "closest to the entry"},
                        {"vertex", e.area.vertex},
                        {"ray_distance_mm", e.area.ray_distance_mm},
                        {"along_normal_mm", e.area.along_normal_mm},
                        {"extrusion_mm", e.area.extrusion_mm},
                        {"in_safe_region", e.area.safe},
                        {"region", e.area.region},
                        {"region_size_mm3", e.area.region_size_mm3},
                        {"relative_area_safety", e.area.relative_area_safety}};
  } else {
    j["area_safety"] = nullptr;
  }
  return j;
}

std::string evaluation_text(const TrajectoryEvaluation& e) {
  std::ostringstream s;
  const auto& t = e.trajectory;
  s << "Trajectory" << (t.name.empty() ? "" : " \"" + t.name + "\"") << ": entry "
    << point_text(t.entry) << " -> target " << point_text(t.target) << " LPS mm, length "
    << fmt::format("{:.1f}", e.length_mm) << " mm\n";
  s << "Line integral of blocking: " << fmt::format("{:.4g}", e.line_integral) << "  ("
    << e.samples << " samples of " << fmt::format("{:.2f}", e.step_mm) << " mm)\n";
  if (!e.labels_available) {
    s << "Structures: no label map in this plan\n";
  } else if (e.structures.empty()) {
    s << "Structures: none (background only)\n";
  } else {
    s << "Structures along the path (depth from the entry, length inside, +/- "
      << fmt::format("{:.1f}", e.structure_step_mm) << " mm):\n";
    for (const auto& h : e.structures) {
      const std::string level =
          h.level >= 0 ? "level " + std::to_string(h.level) + " " + h.level_name : "no level";
      s << fmt::format("  {:<18} label {:<4} {:<18} depth {:>6.1f} mm  length {:>6.1f} mm\n",
                       h.name, h.label, level, h.depth_mm, h.length_mm);
    }
  }
  if (e.tumor_depth_mm >= 0) {
    s << "Tumor entered at depth " << fmt::format("{:.1f}", e.tumor_depth_mm) << " mm; target "
      << (e.target_in_tumor ? "inside" : "OUTSIDE") << " the tumor\n";
  } else {
    s << "Tumor: " << (e.target_in_tumor ? "target inside" : "not reached (or no tumor mask)")
      << "\n";
  }
  if (e.entry_outside_scan) {
    s << "Scan: the entry lies OUTSIDE the scan: the anatomy there is unknown (no path safety "
         "value; never safe)\n";
  }
  if (e.outside_scan_mm > 0) {
    s << "Scan: " << fmt::format("{:.1f}", e.outside_scan_mm) << " mm of the path (of "
      << fmt::format("{:.1f}", e.length_mm)
      << " mm) lie OUTSIDE the scan: unknown anatomy, the path is never reported safe\n";
  }
  if (!e.values.empty()) s << "Path safety at the entry:\n";
  for (const auto& v : e.values) {
    if (v.safety_class == "unknown" && !std::isfinite(v.at_entry)) {
      s << "  " << v.value << ": unknown (outside the scan)\n";
      continue;
    }
    if (!std::isfinite(v.at_entry)) {
      s << "  " << v.value << ": outside the region of interest\n";
      continue;
    }
    s << fmt::format("  {:<5} {:>12.4g}  {:<9} safer than {:>5.1f} % of the region of interest\n",
                     v.value, v.at_entry, v.safety_class, v.safety_percentile);
    if (!v.worst_phase.empty()) {
      s << fmt::format("        worst over {} breathing phases: {:.4g} in {}\n",
                       v.per_phase.size(), v.at_worst_phase, v.worst_phase);
    }
  }
  if (e.area.available) {
    if (e.leaves_scan()) {
      s << "Area safety: unknown (the path leaves the scan; nearest extrusion column "
        << (e.area.region >= 0 ? "in region " + std::to_string(e.area.region) : "unsafe") << ")";
    } else if (e.area.safe) {
      s << "Area safety: entry in safe region " << e.area.region << " ("
        << fmt::format("{:.0f}", e.area.region_size_mm3) << " mm^3), relative area safety "
        << fmt::format("{:.0f}", 100.0 * e.area.relative_area_safety) << " %";
    } else {
      s << "Area safety: entry NOT in a safe region (extrusion stopped after "
        << fmt::format("{:.1f}", e.area.extrusion_mm) << " mm)";
    }
    s << "  [vertex " << e.area.vertex << ", " << fmt::format("{:.1f}", e.area.ray_distance_mm)
      << " mm from its extrusion ray]\n";
  } else {
    s << "Area safety: not in this plan (no area_safety.vtk)\n";
  }
  return s.str();
}

std::string evaluation_csv_header(const TrajectoryEvaluation& e) {
  std::string h =
      "name,entry_x,entry_y,entry_z,target_x,target_y,target_z,length_mm,line_integral,"
      "max_level,structures,tumor_depth_mm,target_in_tumor";
  for (const auto& v : e.values) {
    h += "," + v.value + "_at_entry," + v.value + "_class," + v.value + "_safety_percentile";
  }
  h += ",in_safe_region,area_region,relative_area_safety,entry_outside_scan,outside_scan_mm";
  return h;
}

std::string evaluation_csv_row(const TrajectoryEvaluation& e) {
  // Empty when not finite.
  const auto num = [](double v, fmt::format_string<double> format) {
    return std::isfinite(v) ? fmt::format(format, v) : std::string();
  };
  const auto& t = e.trajectory;
  std::string r = quote_csv_field(t.name);
  for (const auto* p : {&t.entry, &t.target}) {
    for (int a = 0; a < 3; ++a) r += "," + num((*p)[a], "{:.3f}");
  }
  r += "," + num(e.length_mm, "{:.2f}") + "," + num(e.line_integral, "{:.6g}");
  int max_level = -1;
  std::string list;
  for (const auto& h : e.structures) {
    max_level = std::max(max_level, h.level);
    list += (list.empty() ? "" : ";") +
            fmt::format("{}@{:.1f}+{:.1f}", h.name, h.depth_mm, h.length_mm);
  }
  r += "," + (e.labels_available && max_level >= 0 ? std::to_string(max_level) : std::string());
  r += "," + quote_csv_field(list);
  r += "," + (e.tumor_depth_mm >= 0 ? fmt::format("{:.1f}", e.tumor_depth_mm) : std::string());
  r += std::string(",") + (e.target_in_tumor ? "1" : "0");
  for (const auto& v : e.values) {
    r += "," + num(v.at_entry, "{:.6g}") + "," + v.safety_class + "," +
         num(v.safety_percentile, "{:.2f}");
  }
  if (e.area.available) {
    r += std::string(",") + (e.area.safe ? "1" : "0") + "," + std::to_string(e.area.region) + "," +
         fmt::format("{:.4f}", e.area.relative_area_safety);
  } else {
    r += ",,,";
  }
  r += std::string(",") + (e.entry_outside_scan ? "1" : "0") + "," +
       fmt::format("{:.1f}", e.outside_scan_mm);
  return r;
}

std::vector<Trajectory> read_trajectories_csv(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw Error(path + ": cannot open trajectories CSV");
  const std::vector<std::string> expected = {"name",     "entry_x",  "entry_y", "entry_z",
                                             "target_x", "target_y", "target_z"};
  std::string line;
  int line_no = 0;
  bool header = false;
  std::vector<Trajectory> result;
  while (std::getline(in, line)) {
    ++line_no;
    if (line.find_first_not_of(" \t\r") == std::string::npos) continue;
    auto fields = split_csv_line(line, ',', true);
    if (!header) {
      for (auto& f : fields) {
        std::transform(f.begin(), f.end(), f.begin(),
                       [](unsigned char c) { return std::tolower(c); });
      }
      if (fields != expected) {
        throw Error(path + ": line " + std::to_string(line_no) + ": header \"" + line +
                    "\" (expected name,entry_x,entry_y,entry_z,target_x,target_y,target_z, "
                    "LPS mm)");
      }
      header = true;
      continue;
    }
    if (fields.size() != 7) {
      throw Error(path + ": line " + std::to_string(line_no) + ": " +
                  std::to_string(fields.size()) + " fields (expected 7)");
    }
    Trajectory t;
    t.name = fields[0];
    double v[6];
    const CsvLocation at{path, line_no};
    for (int i = 0; i < 6; ++i) v[i] = csv_double(fields[size_t(i + 1)], expected[size_t(i + 1)], at);
    t.entry = Eigen::Vector3d(v[0], v[1], v[2]);
    t.target = Eigen::Vector3d(v[3], v[4], v[5]);
    result.push_back(t);
  }
  if (!header) throw Error(path + ": empty (expected a header and one row per trajectory)");
  if (result.empty()) throw Error(path + ": no trajectories after the header");
  return result;
}

Trajectory trajectory_from_markup(const std::string& path, const Eigen::Vector3d& tumor_centre) {
  const LineMarkup line = read_line_markup(path);
  Trajectory t;
  t.name = line.name.empty() ? fs::path(path).filename().string() : line.name;
  const bool first_is_target =
      (line.first - tumor_centre).norm() < (line.second - tumor_centre).norm();
  t.entry = first_is_target ? line.second : line.first;
  t.target = first_is_target ? line.first : line.second;
  spdlog::debug("{}: {} coordinates; target = control point {} (nearer the tumor centre)", path,
                line.file_coordinate_system, first_is_target ? 1 : 2);
  return t;
}

}  // namespace crepuscular::planning
