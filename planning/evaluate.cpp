// Plan folder reading and the retrospective evaluation of straight needle trajectories.
#include "planning/evaluate.hpp"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>
#include <sstream>

#include "kernels/error.hpp"
#include "kernels/path_safety_math.hpp"
#include "planning/markups.hpp"
#include "planning/path_safety.hpp"
#include "planning/volume_io.hpp"

namespace fs = std::filesystem;

namespace crepuscular::planning {

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

const nlohmann::json& require(const nlohmann::json& j, const char* key, const std::string& where) {
  if (!j.is_object() || !j.contains(key) || j[key].is_null()) {
    throw Error(where + ": field \"" + key + "\" is missing");
  }
  return j[key];
}

Eigen::Vector3d vector_field(const nlohmann::json& j, const char* key, const std::string& where) {
  const auto& v = require(j, key, where);
  if (!v.is_array() || v.size() != 3) {
    throw Error(where + ": field \"" + key + "\": expected [x, y, z]");
  }
  Eigen::Vector3d r;
  for (int a = 0; a < 3; ++a) {
    if (!v[size_t(a)].is_number()) {
      throw Error(where + ": field \"" + key + "\": expected three numbers");
    }
    r[a] = v[size_t(a)].get<double>();
  }
  return r;
}

ImageGeometry geometry_from_json(const nlohmann::json& j, const std::string& where) {
  ImageGeometry g;
  const auto& dims = require(j, "dims", where);
  if (!dims.is_array() || dims.size() != 3) throw Error(where + ": \"dims\": expected 3 sizes");
  for (int a = 0; a < 3; ++a) g.dims[a] = dims[size_t(a)].get<int64_t>();
  g.origin = vector_field(j, "origin_lps_mm", where);
  g.spacing = vector_field(j, "spacing_mm", where);
  const auto& d = require(j, "direction", where);
  if (!d.is_array() || d.size() != 3) throw Error(where + ": \"direction\": expected 3x3");
  for (int r = 0; r < 3; ++r) {
    if (!d[size_t(r)].is_array() || d[size_t(r)].size() != 3) {
      throw Error(where + ": \"direction\": expected 3x3");
    }
    for (int c = 0; c < 3; ++c) g.direction(r, c) = d[size_t(r)][size_t(c)].get<double>();
  }
  g.validate(where);
  return g;
}

// An input's path as plan.json records it; when that file is gone but the path relative to the
// plan folder leads to one (the plan moved together with its inputs), that one.
std::string input_path(const nlohmann::json& plan, const char* key, const std::string& plan_dir) {
  if (!plan.contains("inputs") || !plan["inputs"].is_object()) return {};
  const auto& in = plan["inputs"];
  if (!in.contains(key) || !in[key].is_object() || !in[key].contains("path")) return {};
  const std::string path = in[key]["path"].get<std::string>();
  std::error_code ec;
  if (!fs::exists(path, ec) && in[key].contains("relative_path") &&
      in[key]["relative_path"].is_string()) {
    const fs::path moved = fs::path(plan_dir) / in[key]["relative_path"].get<std::string>();
    if (fs::exists(moved, ec)) return moved.lexically_normal().string();
  }
  return path;
}

// Trilinear weights of a continuous index; calls f(offset, weight) for the corners in the grid.
template <typename F>
void for_each_corner(const ImageGeometry& g, const Eigen::Vector3d& q, F&& f) {
  const double fx = std::floor(q.x()), fy = std::floor(q.y()), fz = std::floor(q.z());
  const int64_t i = int64_t(fx), j = int64_t(fy), k = int64_t(fz);
  const double w[3] = {q.x() - fx, q.y() - fy, q.z() - fz};
  for (int c = 0; c < 8; ++c) {
    const int64_t ii = i + (c & 1), jj = j + ((c >> 1) & 1), kk = k + ((c >> 2) & 1);
    if (!g.contains(ii, jj, kk)) continue;
    const double weight = ((c & 1) ? w[0] : 1 - w[0]) * (((c >> 1) & 1) ? w[1] : 1 - w[1]) *
                          (((c >> 2) & 1) ? w[2] : 1 - w[2]);
    f(g.offset(ii, jj, kk), weight);
  }
}

template <typename T>
T nearest_value(const Volume<T>& v, const Eigen::Vector3d& p, T outside) {
  if (v.empty()) return outside;
  const Index3 n = v.geometry().nearest_index(p);
  if (!v.geometry().contains(n[0], n[1], n[2])) return outside;
  return v(n[0], n[1], n[2]);
}

const char* class_name(SafetyClass c) {
  return c == SafetyClass::kSafe ? "safe" : c == SafetyClass::kMedium ? "medium" : "dangerous";
}

std::string format(const char* fmt, double v) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), fmt, v);
  return buf;
}

std::string point_text(const Eigen::Vector3d& p) {
  char buf[96];
  std::snprintf(buf, sizeof(buf), "(%.1f, %.1f, %.1f)", p.x(), p.y(), p.z());
  return buf;
}

std::string csv_quote(const std::string& s) {
  if (s.find_first_of(",\"\n") == std::string::npos) return s;
  std::string q = "\"";
  for (char c : s) {
    if (c == '"') q += '"';
    q += c;
  }
  return q + "\"";
}

std::vector<std::string> csv_split(const std::string& line) {
  std::vector<std::string> fields(1);
  bool quoted = false;
  for (size_t i = 0; i < line.size(); ++i) {
    const char c = line[i];
    if (quoted) {
      if (c == '"' && i + 1 < line.size() && line[i + 1] == '"') {
        fields.back() += '"';
        ++i;
      } else if (c == '"') {
        quoted = false;
      } else {
        fields.back() += c;
      }
    } else if (c == '"') {
      quoted = true;
    } else if (c == ',') {
      fields.emplace_back();
    } else if (c != '\r') {
      fields.back() += c;
    }
  }
  for (auto& f : fields) {
    const auto b = f.find_first_not_of(" \t");
    const auto e = f.find_last_not_of(" \t");
    f = b == std::string::npos ? std::string() : f.substr(b, e - b + 1);
  }
  return fields;
}

}  // namespace

// --- Plan folder --------------------------------------------------------------------------------

SafetyClasses classes_from_json(const nlohmann::json& plan, const std::string& value,
                                const std::string& source) {
  if (!plan.contains("classes") || !plan["classes"].contains(value)) {
    throw Error(source + ": classes." + value + " is missing");
  }
  const auto& c = plan["classes"][value];
  SafetyClasses s;
  try {
    s.higher_is_safer = c.at("higher_is_safer").get<bool>();
    s.safe = c.at("safe").get<double>();
    s.dangerous = c.at("dangerous").get<double>();
  } catch (const nlohmann::json::exception&) {
    throw Error(source + ": classes." + value +
                ": expected higher_is_safer (bool), safe and dangerous (numbers)");
  }
  return s;
}

PlanData load_plan(const std::string& plan_dir, const PlanLoadOptions& options) {
  PlanData plan;
  plan.dir = plan_dir;
  const std::string json_path = (fs::path(plan_dir) / "plan.json").string();
  {
    std::ifstream in(json_path);
    if (!in) {
      throw Error(json_path + ": cannot open (is " + plan_dir +
                  " a plan folder written by `crepuscular plan`?)");
    }
    try {
      in >> plan.json;
    } catch (const nlohmann::json::exception& e) {
      throw Error(json_path + ": not valid JSON (" + e.what() + ")");
    }
  }
  const nlohmann::json& j = plan.json;
  plan.grid = geometry_from_json(require(j, "grid", json_path), json_path + ": grid");
  const auto& parameters = require(j, "parameters", json_path);
  plan.gamma_mm = require(parameters, "gamma_mm", json_path + ": parameters").get<double>();
  plan.radius_mm = require(parameters, "radius_mm", json_path + ": parameters").get<double>();
  if (!(plan.gamma_mm > 0)) throw Error(json_path + ": parameters.gamma_mm must be > 0");
  plan.tumor_centre =
      vector_field(require(j, "tumor", json_path), "centroid_lps_mm", json_path + ": tumor");
  for (const auto& v : require(parameters, "values", json_path + ": parameters")) {
    plan.values.push_back(v.get<std::string>());
  }
  const auto& outputs = require(j, "outputs", json_path);

  if (options.blocking) {
    const std::string name = require(outputs, "blocking", json_path + ": outputs");
    plan.blocking = read_volume<float>((fs::path(plan_dir) / name).string());
  }
  if (!options.only_value.empty() &&
      std::find(plan.values.begin(), plan.values.end(), options.only_value) == plan.values.end()) {
    std::string list;
    for (const auto& v : plan.values) list += (list.empty() ? "" : ", ") + v;
    throw Error(json_path + ": value \"" + options.only_value +
                "\" was not computed in this plan (it has: " + list + ")");
  }
  for (const auto& v : plan.values) {
    plan.classes[v] = classes_from_json(j, v, json_path);
    if (!options.path_safety) continue;
    if (!options.only_value.empty() && v != options.only_value) continue;
    const std::string name = require(outputs, v.c_str(), json_path + ": outputs");
    plan.path_safety[v] = read_volume<float>((fs::path(plan_dir) / name).string());
  }
  // NaN marks voxels outside the region of interest, but NIfTI readers may hand them back as 0:
  // the ROI mask beside the volumes (or the ball of radius R around the grid centre) decides.
  if (!plan.path_safety.empty()) {
    Volume<uint8_t> roi;
    if (outputs.contains("roi") && outputs["roi"].is_string()) {
      const std::string path = (fs::path(plan_dir) / outputs["roi"].get<std::string>()).string();
      std::error_code ec;
      if (fs::exists(path, ec)) roi = read_mask(path);
    }
    if (!roi.empty() && !roi.geometry().same_grid(plan.grid, 1e-4)) {
      throw Error((fs::path(plan_dir) / outputs["roi"].get<std::string>()).string() +
                  ": not on the plan's grid (plan.json \"grid\")");
    }
    const Eigen::Vector3d centre = plan.grid.index_to_physical(
        Eigen::Vector3d(0.5 * double(plan.grid.dims[0] - 1), 0.5 * double(plan.grid.dims[1] - 1),
                        0.5 * double(plan.grid.dims[2] - 1)));
    for (auto& [name, volume] : plan.path_safety) {
      if (!volume.geometry().same_grid(plan.grid, 1e-4)) {
        throw Error((fs::path(plan_dir) / outputs[name].get<std::string>()).string() +
                    ": not on the plan's grid (plan.json \"grid\")");
      }
      const float nan = std::numeric_limits<float>::quiet_NaN();
      for (int64_t o = 0; o < volume.voxel_count(); ++o) {
        bool inside;
        if (!roi.empty()) {
          inside = roi[o] != 0;
        } else {
          const Index3 idx = plan.grid.index_of_offset(o);
          inside = (plan.grid.index_to_physical(idx[0], idx[1], idx[2]) - centre).norm() <=
                   plan.radius_mm + 1e-6;
        }
        if (!inside) volume[o] = nan;
      }
    }
  }

  if (j.contains("preprocessing") && j["preprocessing"].contains("vulnerability") &&
      j["preprocessing"]["vulnerability"].is_object()) {
    plan.table = VulnerabilityTable::from_json(j["preprocessing"]["vulnerability"],
                                               json_path + ": preprocessing.vulnerability");
  }
  if (options.labels) {
    std::string path = options.labels_override;
    if (path.empty()) {
      path = input_path(j, "labels", plan_dir);
      std::error_code ec;
      if (!path.empty() && !fs::exists(path, ec)) {
        spdlog::warn(
            "{}: the plan's label map {} no longer exists; structures are not shown "
            "(give --labels)",
            json_path, path);
        path.clear();
      }
    }
    if (!path.empty()) {
      plan.labels = read_label_map(path);
      plan.labels_path = path;
    }
  }
  if (options.tumor) {
    const std::string path = input_path(j, "tumor", plan_dir);
    std::error_code ec;
    if (!path.empty() && fs::exists(path, ec)) {
      plan.tumor = read_mask(path);
    } else if (!path.empty()) {
      spdlog::warn("{}: the plan's tumor mask {} no longer exists", json_path, path);
    }
  }
  if (options.area_safety) {
    const std::string path = (fs::path(plan_dir) / "area_safety.vtk").string();
    std::error_code ec;
    if (fs::exists(path, ec)) {
      plan.area = read_area_safety_vtk(path);
      if (plan.area->regions.empty() && j.contains("area_safety") &&
          j["area_safety"].contains("regions")) {
        // Regions as plan.json lists them, when the mesh file carries only per-vertex data.
        for (const auto& r : j["area_safety"]["regions"]) {
          AreaRegion region;
          region.id = r.at("id").get<int>();
          region.size_mm3 = r.at("size_mm3").get<double>();
          region.centre = vector_field(r, r.contains("centre_lps_mm") ? "centre_lps_mm" : "centre",
                                       json_path + ": area_safety.regions");
          region.main_axis = vector_field(r, "main_axis", json_path + ": area_safety.regions");
          region.leeway = r.at("leeway").get<double>();
          region.vertex_count = r.value("vertex_count", 0);
          plan.area->regions.push_back(region);
        }
      }
    }
  }
  return plan;
}

double sample_path_safety(const Volume<float>& volume, const Eigen::Vector3d& point_lps) {
  if (volume.empty()) return kNaN;
  const ImageGeometry& g = volume.geometry();
  double sum = 0, weight = 0;
  for_each_corner(g, g.physical_to_index(point_lps), [&](int64_t offset, double w) {
    const float v = volume[offset];
    if (std::isfinite(v) && w > 0) {
      sum += w * double(v);
      weight += w;
    }
  });
  return weight > 1e-12 ? sum / weight : kNaN;
}

Eigen::Vector3d parse_point(const std::string& text, const std::string& what) {
  const auto fields = csv_split(text);
  Eigen::Vector3d p;
  bool ok = fields.size() == 3;
  for (size_t a = 0; ok && a < 3; ++a) {
    char* end = nullptr;
    p[int(a)] = std::strtod(fields[a].c_str(), &end);
    ok = !fields[a].empty() && end && *end == '\0' && std::isfinite(p[int(a)]);
  }
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

TrajectoryEvaluation TrajectoryEvaluator::evaluate(const Trajectory& t) const {
  const PlanData& plan = impl_->plan;
  TrajectoryEvaluation e;
  e.trajectory = t;
  const Eigen::Vector3d d = t.target - t.entry;
  e.length_mm = d.norm();
  if (!(e.length_mm > 1e-6)) {
    throw Error("trajectory \"" + t.name + "\": entry and target coincide " + point_text(t.entry));
  }

  // Line integral exactly as DESIGN.md section 4 defines it for a ray p -> t (kernels).
  kernels::SurfacePoint<double> target{};
  target.position = {t.target.x(), t.target.y(), t.target.z()};
  target.normal = {0, 0, 0};
  target.offset = -1;
  const kernels::Vec3<double> p{t.entry.x(), t.entry.y(), t.entry.z()};
  const auto ray = kernels::make_ray(impl_->scene, p, target);
  const kernels::GridSampler<double> sampler{impl_->scene.blocking};
  double integral = 0;
  for (int k = 1; k <= ray.n; ++k) {
    integral += sampler(kernels::along(ray.q0, ray.dq, double(k))) * double(ray.step);
  }
  e.samples = ray.n;
  e.step_mm = double(ray.step);
  e.line_integral = integral;

  // Structures and tumor: nearest-voxel lookups at samples k = 0..M (entry to target), M so that
  // the step is at most gamma and at most half the finest label spacing. A structure is entered
  // half a step before its first sample; its length is its sample count times the step.
  double step_bound = plan.gamma_mm;
  if (!plan.labels.empty())
    step_bound = std::min(step_bound, 0.5 * plan.labels.geometry().spacing.minCoeff());
  if (!plan.tumor.empty())
    step_bound = std::min(step_bound, 0.5 * plan.tumor.geometry().spacing.minCoeff());
  const int m = std::max(1, int(std::ceil(e.length_mm / step_bound)));
  const double l = e.length_mm / m;
  e.structure_step_mm = l;
  e.labels_available = !plan.labels.empty();
  std::map<int, StructureHit> hits;
  int tumor_first = -1;
  for (int k = 0; k <= m; ++k) {
    const Eigen::Vector3d x = t.entry + (double(k) / m) * d;
    const double depth = k == 0 ? 0.0 : (k - 0.5) * l;
    if (e.labels_available) {
      const int32_t label = nearest_value<int32_t>(plan.labels, x, 0);
      if (label != 0) {
        auto it = hits.find(label);
        if (it == hits.end()) {
          StructureHit h;
          h.label = label;
          h.name = "label " + std::to_string(label);
          h.depth_mm = depth;
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
          it = hits.emplace(label, h).first;
        }
        it->second.length_mm += l;
      }
    }
    if (!plan.tumor.empty() && tumor_first < 0 && nearest_value<uint8_t>(plan.tumor, x, 0)) {
      tumor_first = k;
    }
  }
  for (const auto& [label, h] : hits) e.structures.push_back(h);
  std::stable_sort(
      e.structures.begin(), e.structures.end(),
      [](const StructureHit& a, const StructureHit& b) { return a.depth_mm < b.depth_mm; });
  if (!plan.tumor.empty()) {
    e.target_in_tumor = nearest_value<uint8_t>(plan.tumor, t.target, 0) != 0;
    e.tumor_depth_mm = tumor_first < 0 ? -1.0 : tumor_first == 0 ? 0.0 : (tumor_first - 0.5) * l;
  }

  // Path safety at the entry and its rank within the region of interest.
  for (const auto& value : plan.values) {
    const auto vol = plan.path_safety.find(value);
    if (vol == plan.path_safety.end()) continue;
    EntryValue ev;
    ev.value = value;
    ev.at_entry = sample_path_safety(vol->second, t.entry);
    const SafetyClasses& classes = plan.classes.at(value);
    if (std::isfinite(ev.at_entry)) {
      ev.safety_class = class_name(classes.classify(ev.at_entry));
      const auto& s = impl_->sorted.at(value);
      const auto lo = std::lower_bound(s.begin(), s.end(), float(ev.at_entry));
      const auto hi = std::upper_bound(s.begin(), s.end(), float(ev.at_entry));
      const double below = double(lo - s.begin()), equal = double(hi - lo);
      ev.percentile = s.empty() ? kNaN : 100.0 * (below + 0.5 * equal) / double(s.size());
      ev.safety_percentile = classes.higher_is_safer ? ev.percentile : 100.0 - ev.percentile;
    } else {
      ev.safety_class = "outside";
      ev.percentile = ev.safety_percentile = kNaN;
    }
    e.values.push_back(ev);
  }

  // Area safety: the extrusion column (normal ray of a base vertex) nearest to the entry.
  if (plan.area && !plan.area->base.empty() &&
      plan.area->normals.size() == plan.area->base.size()) {
    const AreaSafetyGeometry& a = *plan.area;
    EntryArea& area = e.area;
    area.available = true;
    double best = std::numeric_limits<double>::infinity();
    for (size_t i = 0; i < a.base.size(); ++i) {
      const Eigen::Vector3d w = t.entry - a.base[i];
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
  nlohmann::json values = nlohmann::json::object();
  for (const auto& v : e.values) {
    values[v.value] = {{"at_entry", num(v.at_entry)},
                       {"class", v.safety_class},
                       {"percentile", num(v.percentile)},
                       {"safety_percentile", num(v.safety_percentile)}};
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
    << format("%.1f", e.length_mm) << " mm\n";
  s << "Line integral of blocking: " << format("%.4g", e.line_integral) << "  (" << e.samples
    << " samples of " << format("%.2f", e.step_mm) << " mm)\n";
  if (!e.labels_available) {
    s << "Structures: no label map in this plan\n";
  } else if (e.structures.empty()) {
    s << "Structures: none (background only)\n";
  } else {
    s << "Structures along the path (depth from the entry, length inside, +/- "
      << format("%.1f", e.structure_step_mm) << " mm):\n";
    for (const auto& h : e.structures) {
      char buf[256];
      const std::string level =
          h.level >= 0 ? "level " + std::to_string(h.level) + " " + h.level_name : "no level";
      std::snprintf(buf, sizeof(buf), "  %-18s label %-4d %-18s depth %6.1f mm  length %6.1f mm\n",
                    h.name.c_str(), h.label, level.c_str(), h.depth_mm, h.length_mm);
      s << buf;
    }
  }
  if (e.tumor_depth_mm >= 0) {
    s << "Tumor entered at depth " << format("%.1f", e.tumor_depth_mm) << " mm; target "
      << (e.target_in_tumor ? "inside" : "OUTSIDE") << " the tumor\n";
  } else {
    s << "Tumor: " << (e.target_in_tumor ? "target inside" : "not reached (or no tumor mask)")
      << "\n";
  }
  if (!e.values.empty()) s << "Path safety at the entry:\n";
  for (const auto& v : e.values) {
    if (!std::isfinite(v.at_entry)) {
      s << "  " << v.value << ": outside the region of interest\n";
      continue;
    }
    char buf[256];
    std::snprintf(buf, sizeof(buf),
                  "  %-5s %12.4g  %-9s safer than %5.1f %% of the region of "
                  "interest\n",
                  v.value.c_str(), v.at_entry, v.safety_class.c_str(), v.safety_percentile);
    s << buf;
  }
  if (e.area.available) {
    if (e.area.safe) {
      s << "Area safety: entry in safe region " << e.area.region << " ("
        << format("%.0f", e.area.region_size_mm3) << " mm^3), relative area safety "
        << format("%.0f", 100.0 * e.area.relative_area_safety) << " %";
    } else {
      s << "Area safety: entry NOT in a safe region (extrusion stopped after "
        << format("%.1f", e.area.extrusion_mm) << " mm)";
    }
    s << "  [vertex " << e.area.vertex << ", " << format("%.1f", e.area.ray_distance_mm)
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
  h += ",in_safe_region,area_region,relative_area_safety";
  return h;
}

std::string evaluation_csv_row(const TrajectoryEvaluation& e) {
  const auto num = [](double v, const char* fmt) {
    return std::isfinite(v) ? format(fmt, v) : std::string();
  };
  const auto& t = e.trajectory;
  std::string r = csv_quote(t.name);
  for (const auto* p : {&t.entry, &t.target}) {
    for (int a = 0; a < 3; ++a) r += "," + num((*p)[a], "%.3f");
  }
  r += "," + num(e.length_mm, "%.2f") + "," + num(e.line_integral, "%.6g");
  int max_level = -1;
  std::string list;
  for (const auto& h : e.structures) {
    max_level = std::max(max_level, h.level);
    char buf[160];
    std::snprintf(buf, sizeof(buf), "%s@%.1f+%.1f", h.name.c_str(), h.depth_mm, h.length_mm);
    list += (list.empty() ? "" : ";") + std::string(buf);
  }
  r += "," + (e.labels_available && max_level >= 0 ? std::to_string(max_level) : std::string());
  r += "," + csv_quote(list);
  r += "," + (e.tumor_depth_mm >= 0 ? format("%.1f", e.tumor_depth_mm) : std::string());
  r += std::string(",") + (e.target_in_tumor ? "1" : "0");
  for (const auto& v : e.values) {
    r += "," + num(v.at_entry, "%.6g") + "," + v.safety_class + "," +
         num(v.safety_percentile, "%.2f");
  }
  if (e.area.available) {
    r += std::string(",") + (e.area.safe ? "1" : "0") + "," + std::to_string(e.area.region) + "," +
         format("%.4f", e.area.relative_area_safety);
  } else {
    r += ",,,";
  }
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
    auto fields = csv_split(line);
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
    for (int i = 0; i < 6; ++i) {
      char* end = nullptr;
      v[i] = std::strtod(fields[size_t(i + 1)].c_str(), &end);
      if (fields[size_t(i + 1)].empty() || !end || *end != '\0' || !std::isfinite(v[i])) {
        throw Error(path + ": line " + std::to_string(line_no) + ": " + expected[size_t(i + 1)] +
                    " = \"" + fields[size_t(i + 1)] + "\" is not a number");
      }
    }
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
