// The plan folder's format: plan.json's pieces as the plan pipeline writes them, and load_plan.
#include "planning/plan_folder/plan_folder.hpp"

#include "foundation/output_files.hpp"

#include <itksys/MD5.h>

#include <algorithm>
#include <climits>
#include <filesystem>
#include <fstream>
#include <cmath>
#include <cstdint>
#include <limits>
#include <map>
#include <mutex>
#include <string>
#include <tuple>

#include "foundation/error.hpp"
#include "foundation/json_fields.hpp"
#include "foundation/log.hpp"
#include "planning/imaging/scan_coverage.hpp"
#include "planning/imaging/volume_io.hpp"

namespace fs = std::filesystem;

namespace crepuscular::planning {

// --- Writing ------------------------------------------------------------------------------------

nlohmann::json geometry_json(const ImageGeometry& g) {
  nlohmann::json direction = nlohmann::json::array();
  for (int r = 0; r < 3; ++r) {
    direction.push_back({g.direction(r, 0), g.direction(r, 1), g.direction(r, 2)});
  }
  return {{"dims", {g.dims[0], g.dims[1], g.dims[2]}},
          {"origin_lps_mm", {g.origin.x(), g.origin.y(), g.origin.z()}},
          {"spacing_mm", {g.spacing.x(), g.spacing.y(), g.spacing.z()}},
          {"direction", direction}};
}

nlohmann::json input_json(const std::string& path, const std::string& plan_dir) {
  if (path.empty()) return nullptr;
  // Final paths: a plan staged inside another output (the demo's) names where its inputs will be.
  const fs::path absolute = fs::absolute(final_path_of(path));
  return {
      {"path", absolute.string()},
      {"relative_path", absolute.lexically_relative(fs::absolute(final_path_of(plan_dir))).string()},
      {"md5", file_checksum(path)}};
}

namespace {

std::string compute_checksum(const std::string& path);

// Checksums already taken in this process, by file, size and modification time: a plan over
// breathing phases records each phase's inputs as its phase finishes and the first phase's again
// in plan.json, at its end (0.14 s for a CT and label map at 0.7 mm on the H100's host,
// bench/RESULTS.md, 2026-11-28, a texture of halves). A file written since has another time or
// size.
class ChecksumCache {
 public:
  std::string get(const std::string& path) {
    std::error_code ec;
    if (!fs::is_regular_file(path, ec)) return compute_checksum(path);  // folders: every time
    const Key key{fs::absolute(path, ec).string(), fs::file_size(path, ec),
                  int64_t(fs::last_write_time(path, ec).time_since_epoch().count())};
    if (ec) return compute_checksum(path);
    {
      const std::lock_guard<std::mutex> lock(mutex_);
      const auto it = known_.find(key);
      if (it != known_.end()) return it->second;
    }
    const std::string md5 = compute_checksum(path);  // outside the lock: readers side by side
    const std::lock_guard<std::mutex> lock(mutex_);
    known_[key] = md5;
    return md5;
  }

 private:
  using Key = std::tuple<std::string, uintmax_t, int64_t>;
  std::mutex mutex_;
  std::map<Key, std::string> known_;
};

}  // namespace

std::string file_checksum(const std::string& path) {
  static ChecksumCache cache;
  return cache.get(path);
}

namespace {

std::string compute_checksum(const std::string& path) {
  itksysMD5* md5 = itksysMD5_New();
  itksysMD5_Initialize(md5);
  std::vector<fs::path> files;
  std::error_code ec;
  if (fs::is_directory(path, ec)) {
    for (const auto& e : fs::directory_iterator(path)) {
      if (e.is_regular_file()) files.push_back(e.path());
    }
    std::sort(files.begin(), files.end());
  } else {
    files.push_back(path);
  }
  std::vector<char> buf(1 << 20);
  for (const auto& f : files) {
    if (files.size() > 1 || f.string() != path) {
      const std::string name = f.filename().string();
      itksysMD5_Append(md5, reinterpret_cast<const unsigned char*>(name.data()), int(name.size()));
    }
    std::ifstream in(f, std::ios::binary);
    if (!in) {
      itksysMD5_Delete(md5);
      throw Error(f.string() + ": cannot read file");
    }
    while (in) {
      in.read(buf.data(), std::streamsize(buf.size()));
      const auto got = in.gcount();
      if (got > 0) {
        itksysMD5_Append(md5, reinterpret_cast<const unsigned char*>(buf.data()), int(got));
      }
    }
  }
  char hex[33] = {0};
  itksysMD5_FinalizeHex(md5, hex);
  itksysMD5_Delete(md5);
  return std::string(hex, 32);
}

}  // namespace

nlohmann::json classes_json(unsigned value_bit, const Volume<float>& volume) {
  return classes_json(default_classes(value_bit, volume));
}

nlohmann::json classes_json(const SafetyClasses& c) {
  return {
      {"higher_is_safer", c.higher_is_safer},
      {"safe", c.safe},
      {"dangerous", c.dangerous},
      {"rule", c.higher_is_safer
                   ? "safe: value >= safe; dangerous: value < dangerous; medium in between (%)"
                   : "safe: value <= safe (20th percentile of the non-zero values of the region "
                     "of interest); dangerous: value > dangerous (60th percentile of them); "
                     "medium in between"}};
}

// --- Reading ------------------------------------------------------------------------------------

namespace {

Eigen::Vector3d vector_at(const nlohmann::json& object, const std::string& key,
                          const JsonPath& at) {
  const std::vector<double> v =
      as_numbers(required_field(object, key, at), at.key(key), 3, 3, "[x, y, z]");
  return {v[0], v[1], v[2]};
}

ImageGeometry geometry_at(const nlohmann::json& j, const JsonPath& at) {
  ImageGeometry g;
  const JsonPath dims_at = at.key("dims");
  const nlohmann::json& dims = as_array(required_field(j, "dims", at), dims_at);
  if (dims.size() != 3) dims_at.fail("has " + std::to_string(dims.size()) + " sizes, expected 3");
  for (size_t a = 0; a < 3; ++a) g.dims[int(a)] = as_integer(dims[a], dims_at.index(a));
  g.origin = vector_at(j, "origin_lps_mm", at);
  g.spacing = vector_at(j, "spacing_mm", at);
  const JsonPath direction_at = at.key("direction");
  const nlohmann::json& d = as_array(required_field(j, "direction", at), direction_at);
  if (d.size() != 3) direction_at.fail("has " + std::to_string(d.size()) + " rows, expected 3x3");
  for (size_t r = 0; r < 3; ++r) {
    const std::vector<double> row = as_numbers(d[r], direction_at.index(r), 3, 3, "3 numbers");
    for (int c = 0; c < 3; ++c) g.direction(int(r), c) = row[size_t(c)];
  }
  g.validate(at.describe());
  return g;
}

// An input's path as plan.json records it; when that file is gone but the path relative to the
// plan folder leads to one (the plan moved together with its inputs), that one.
std::string input_path(const nlohmann::json& plan, const char* key, const std::string& plan_dir,
                       const JsonPath& root) {
  if (!plan.contains("inputs") || !plan["inputs"].is_object()) return {};
  const auto& in = plan["inputs"];
  if (!in.contains(key) || !in[key].is_object() || !in[key].contains("path")) return {};
  const JsonPath at = root.key("inputs").key(key);
  // Read back during the run that stages it (the demo): where the input is now.
  const std::string path = staged_path_of(required_string(in[key], "path", at));
  const std::string relative = optional_string(in[key], "relative_path", at, "");
  std::error_code ec;
  if (!fs::exists(path, ec) && !relative.empty()) {
    const fs::path moved = fs::path(plan_dir) / relative;
    if (fs::exists(moved, ec)) return moved.lexically_normal().string();
  }
  return path;
}

// A file named by plan.json: a plain name inside the plan folder. A path that leads elsewhere
// (absolute, "..", a folder) is refused: a swapped path must not put another plan's values
// under this plan's name.
std::string in_plan(const std::string& plan_dir, const std::string& name) {
  const fs::path p(name);
  if (name.empty() || p.is_absolute() || p.has_parent_path() || name == "." || name == "..") {
    throw Error(plan_dir + "/plan.json: output '" + name +
                "' is not a file name inside the plan folder; plan folders name their own files "
                "only (was plan.json edited?)");
  }
  return (fs::path(plan_dir) / name).string();
}

nlohmann::json read_plan_json(const std::string& plan_dir, const std::string& json_path) {
  std::error_code ec;
  if (!fs::is_regular_file(json_path, ec)) {
    throw Error(json_path + ": cannot open (is " + plan_dir +
                " a plan folder written by `crepuscular plan`?)");
  }
  return read_json_file(json_path, "the plan");
}

// plan.json's grid, parameters, tumor centroid and computed values.
void read_parameters(PlanData& plan, const std::string& json_path) {
  const nlohmann::json& j = plan.json;
  const JsonPath root(json_path);
  plan.grid = geometry_at(required_field(j, "grid", root), root.key("grid"));
  const JsonPath parameters_at = root.key("parameters");
  const auto& parameters = required_field(j, "parameters", root);
  plan.gamma_mm = required_number(parameters, "gamma_mm", parameters_at);
  plan.radius_mm = required_number(parameters, "radius_mm", parameters_at);
  if (!(plan.gamma_mm > 0)) parameters_at.key("gamma_mm").fail("must be > 0");
  plan.tumor_centre =
      vector_at(required_field(j, "tumor", root), "centroid_lps_mm", root.key("tumor"));
  const JsonPath values_at = parameters_at.key("values");
  const auto& values = as_array(required_field(parameters, "values", parameters_at), values_at);
  for (size_t i = 0; i < values.size(); ++i) {
    plan.values.push_back(as_string(values[i], values_at.index(i)));
  }
}

// NaN marks voxels without a value (outside the region of interest, or unknown: outside the
// scan), but NIfTI readers hand them back as 0: the voxel states of roi.nii.gz (RegionState; older
// plans: 1 inside, 0 outside), or else the ball of radius R around the grid centre, decide. Only
// computed voxels keep their value; an unknown one must never read as a (safe) 0.
void mark_outside_roi(PlanData& plan, const nlohmann::json& outputs) {
  Volume<uint8_t> roi;
  if (outputs.contains("roi") && outputs["roi"].is_string()) {
    const std::string path = in_plan(plan.dir, outputs["roi"].get<std::string>());
    std::error_code ec;
    if (fs::exists(path, ec)) roi = read_volume<uint8_t>(path);
    if (!roi.empty() && !roi.geometry().same_grid(plan.grid, 1e-4)) {
      throw Error(path + ": not on the plan's grid (plan.json \"grid\")");
    }
  }
  const ImageGeometry& g = plan.grid;
  const Eigen::Vector3d centre = g.index_to_physical(Eigen::Vector3d(
      0.5 * double(g.dims[0] - 1), 0.5 * double(g.dims[1] - 1), 0.5 * double(g.dims[2] - 1)));
  for (auto& [name, volume] : plan.path_safety) {
    if (!volume.geometry().same_grid(g, 1e-4)) {
      throw Error(in_plan(plan.dir, outputs[name].get<std::string>()) +
                  ": not on the plan's grid (plan.json \"grid\")");
    }
    const float nan = std::numeric_limits<float>::quiet_NaN();
    for (int64_t o = 0; o < volume.voxel_count(); ++o) {
      bool inside;
      if (!roi.empty()) {
        inside = roi[o] == 1;  // kRegionComputed
      } else {
        const Index3 idx = g.index_of_offset(o);
        inside =
            (g.index_to_physical(idx[0], idx[1], idx[2]) - centre).norm() <= plan.radius_mm + 1e-6;
      }
      if (!inside) volume[o] = nan;
    }
  }
  plan.region = std::move(roi);
}

// Breathing plans: the phases' names and, when written, their path safety volumes (only where the
// combined plan has a computed value).
void read_phase_volumes(PlanData& plan, const PlanLoadOptions& options,
                        const std::string& json_path) {
  if (!plan.json.contains("breathing")) return;
  const JsonPath at = JsonPath(json_path).key("breathing");
  const nlohmann::json& phases =
      as_array(required_field(as_object(plan.json["breathing"], at), "phases", at), at.key("phases"));
  for (size_t k = 0; k < phases.size(); ++k) {
    const JsonPath pk = at.key("phases").index(k);
    plan.phases.push_back(required_string(as_object(phases[k], pk), "name", pk));
  }
  if (!options.path_safety) return;
  for (const auto& [value, combined] : plan.path_safety) {
    std::vector<Volume<float>> volumes;
    for (size_t k = 0; k < phases.size(); ++k) {
      const JsonPath pk = at.key("phases").index(k);
      if (!phases[k].contains("outputs") || !phases[k]["outputs"].contains(value)) break;
      const std::string path =
          in_plan(plan.dir, required_string(phases[k]["outputs"], value, pk.key("outputs")));
      Volume<float> v = read_volume<float>(path, VolumeReadOptions::path_safety_file());
      if (!v.geometry().same_grid(plan.grid, 1e-4)) {
        throw Error(path + ": not on the plan's grid (plan.json \"grid\")");
      }
      for (int64_t o = 0; o < v.voxel_count(); ++o) {
        if (std::isnan(combined[o])) v[o] = std::numeric_limits<float>::quiet_NaN();
      }
      volumes.push_back(std::move(v));
    }
    if (volumes.size() == phases.size()) plan.phase_path_safety[value] = std::move(volumes);
  }
}

// The blocking volume, the classes of every value and the path safety volumes asked for.
void read_volumes(PlanData& plan, const PlanLoadOptions& options, const std::string& json_path) {
  const JsonPath outputs_at = JsonPath(json_path).key("outputs");
  const auto& outputs = required_field(plan.json, "outputs", JsonPath(json_path));
  if (options.blocking) {
    const std::string name = required_string(outputs, "blocking", outputs_at);
    plan.blocking = read_volume<float>(in_plan(plan.dir, name));
  }
  if (!options.only_value.empty() &&
      std::find(plan.values.begin(), plan.values.end(), options.only_value) == plan.values.end()) {
    std::string list;
    for (const auto& v : plan.values) list += (list.empty() ? "" : ", ") + v;
    throw Error(json_path + ": value \"" + options.only_value +
                "\" was not computed in this plan (it has: " + list + ")");
  }
  for (const auto& v : plan.values) {
    plan.classes[v] = classes_from_json(plan.json, v, json_path);
    if (!options.path_safety) continue;
    if (!options.only_value.empty() && v != options.only_value) continue;
    const std::string name = required_string(outputs, v, outputs_at);
    plan.path_safety[v] = read_volume<float>(in_plan(plan.dir, name), VolumeReadOptions::path_safety_file());
  }
  if (!plan.path_safety.empty()) mark_outside_roi(plan, outputs);
  read_phase_volumes(plan, options, json_path);
}

// The label map and the tumor mask of plan.json's inputs (or the label map given instead).
void read_inputs(PlanData& plan, const PlanLoadOptions& options, const std::string& json_path) {
  const nlohmann::json& j = plan.json;
  if (j.contains("preprocessing") && j["preprocessing"].contains("vulnerability") &&
      j["preprocessing"]["vulnerability"].is_object()) {
    plan.table = VulnerabilityTable::from_json(j["preprocessing"]["vulnerability"],
                                               json_path + ": preprocessing.vulnerability");
  }
  std::error_code ec;
  if (options.labels) {
    std::string path = options.labels_override;
    if (path.empty()) {
      path = input_path(j, "labels", plan.dir, JsonPath(json_path));
      if (!path.empty() && !fs::exists(path, ec)) {
        spdlog::warn(
            "{}: the plan's label map {} no longer exists; structures are not shown "
            "(give the label map explicitly)",
            json_path, path);
        path.clear();
      }
    }
    if (!path.empty()) {
      plan.labels = read_label_map(path, {options.series});
      require_overlap_with_plan(plan.labels.geometry(), plan.grid, path, "the label map");
      plan.labels_path = path;
    }
  }
  if (options.tumor) {
    // The planned lesion as the plan wrote it (a label of a label map, one of several lesions),
    // else (older plans) the tumor mask input.
    const nlohmann::json& outputs = j.contains("outputs") ? j["outputs"] : nlohmann::json::object();
    const std::string path = outputs.contains("tumor") && outputs["tumor"].is_string()
                                 ? in_plan(plan.dir, outputs["tumor"].get<std::string>())
                                 : input_path(j, "tumor", plan.dir, JsonPath(json_path));
    if (!path.empty() && fs::exists(path, ec)) {
      plan.tumor = read_mask(path, {options.series});
    } else if (!path.empty()) {
      spdlog::warn("{}: the plan's tumor mask {} no longer exists", json_path, path);
    }
  }
}

// What a changed input means for the user, by its role.
std::string change_consequence(const std::string& role) {
  if (role == "tumor") return "the plan was computed for another tumor: re-plan";
  if (role == "labels" || role.rfind("label_maps", 0) == 0 || role == "vulnerability" ||
      role == "blocking" || role == "ct") {
    return "the plan's safety was computed from the earlier file: re-plan before trusting it";
  }
  return "re-plan before trusting it";
}

// Every input of plan.json that still exists, checked against its recorded checksum; the label
// map given instead of the plan's, against the plan's.
void check_inputs(PlanData& plan, const PlanLoadOptions& options, const std::string& json_path) {
  const nlohmann::json& j = plan.json;
  if (!j.contains("inputs") || !j["inputs"].is_object()) return;
  const JsonPath root(json_path);
  std::vector<std::pair<std::string, const nlohmann::json*>> recorded;
  for (const auto& [key, value] : j["inputs"].items()) {
    if (value.is_object()) {
      recorded.emplace_back(key, &value);
    } else if (value.is_array()) {
      for (size_t i = 0; i < value.size(); ++i) {
        if (value[i].is_object()) recorded.emplace_back(key + "[" + std::to_string(i) + "]", &value[i]);
      }
    }
  }
  std::error_code ec;
  for (const auto& [role, entry] : recorded) {
    if (!entry->contains("md5") || !(*entry)["md5"].is_string() || !entry->contains("path")) continue;
    const JsonPath at = root.key("inputs").key(role);
    std::string path = staged_path_of(required_string(*entry, "path", at));
    const std::string relative = optional_string(*entry, "relative_path", at, "");
    if (!fs::exists(path, ec) && !relative.empty()) path = (fs::path(plan.dir) / relative).string();
    if (!fs::exists(path, ec)) continue;  // moved away: the readers say so where they need it
    const std::string recorded_md5 = (*entry)["md5"].get<std::string>();
    const bool reported = std::any_of(plan.changed_inputs.begin(), plan.changed_inputs.end(),
                                      [&](const ChangedInput& c) { return c.path == path; });
    if (!reported && file_checksum(path) != recorded_md5) {
      plan.changed_inputs.push_back(
          {role, path,
           path + " (" + role + ") changed since planning (checksum differs from " + json_path +
               "): " + change_consequence(role)});
    }
  }
  // A label map given instead of the plan's: it must be one of the maps planned with.
  if (!options.labels_override.empty() && fs::exists(options.labels_override, ec)) {
    const std::string md5 = file_checksum(options.labels_override);
    bool planned = false;
    for (const auto& [role, entry] : recorded) {
      if ((role == "labels" || role.rfind("label_maps", 0) == 0) && entry->contains("md5") &&
          (*entry)["md5"] == md5) {
        planned = true;
      }
    }
    if (!planned) {
      plan.changed_inputs.push_back(
          {"labels", options.labels_override,
           options.labels_override + " (labels) is not the label map the plan was computed from "
                                     "(its checksum matches none in " + json_path +
               "): structures shown may not match the plan's safety"});
    }
  }
  for (const ChangedInput& c : plan.changed_inputs) spdlog::warn("{}", c.message);
}

// area_safety.vtk; its regions from plan.json when the mesh file carries only per-vertex data.
void read_area(PlanData& plan, const std::string& json_path) {
  const std::string path = in_plan(plan.dir, "area_safety.vtk");
  std::error_code ec;
  if (!fs::exists(path, ec)) return;
  plan.area = read_area_safety_vtk(path);
  const nlohmann::json& j = plan.json;
  if (!plan.area->regions.empty() || !j.contains("area_safety") ||
      !j["area_safety"].contains("regions")) {
    return;
  }
  const JsonPath regions_at = JsonPath(json_path).key("area_safety").key("regions");
  const auto& regions = as_array(j["area_safety"]["regions"], regions_at);
  for (size_t i = 0; i < regions.size(); ++i) {
    const nlohmann::json& r = regions[i];
    const JsonPath at = regions_at.index(i);
    AreaRegion region;
    region.id = int(required_integer(r, "id", at, INT_MIN, INT_MAX));
    region.size_mm3 = required_number(r, "size_mm3", at);
    region.centre = vector_at(r, has_field(r, "centre_lps_mm") ? "centre_lps_mm" : "centre", at);
    region.main_axis = vector_at(r, "main_axis", at);
    region.leeway = required_number(r, "leeway", at);
    region.vertex_count = int(optional_integer(r, "vertex_count", at, 0, INT_MIN, INT_MAX));
    plan.area->regions.push_back(region);
  }
}

}  // namespace

ImageGeometry geometry_from_json(const nlohmann::json& j, const std::string& where) {
  return geometry_at(j, JsonPath(where));
}

SafetyClasses classes_from_json(const nlohmann::json& plan, const std::string& value,
                                const std::string& source) {
  const JsonPath at = JsonPath(source).key("classes").key(value);
  if (!plan.contains("classes") || !plan["classes"].contains(value)) at.fail("is missing");
  const nlohmann::json& c = plan["classes"][value];
  SafetyClasses s;
  s.higher_is_safer = required_bool(c, "higher_is_safer", at);
  s.safe = required_number(c, "safe", at);
  s.dangerous = required_number(c, "dangerous", at);
  return s;
}

PlanData load_plan(const std::string& plan_dir, const PlanLoadOptions& options) {
  PlanData plan;
  plan.dir = plan_dir;
  const std::string json_path = in_plan(plan_dir, "plan.json");
  plan.json = read_plan_json(plan_dir, json_path);
  read_parameters(plan, json_path);
  read_volumes(plan, options, json_path);
  read_inputs(plan, options, json_path);
  if (options.check_inputs) check_inputs(plan, options, json_path);
  if (options.area_safety) read_area(plan, json_path);
  return plan;
}

std::string plan_default_value(const std::string& plan_dir) {
  const std::string json_path = (fs::path(plan_dir) / "plan.json").string();
  std::ifstream in(json_path);
  if (!in) throw Error(json_path + ": cannot open (is " + plan_dir + " a plan folder?)");
  nlohmann::json j;
  try {
    in >> j;
  } catch (const nlohmann::json::exception& e) {
    throw Error(json_path + ": not valid JSON (" + e.what() + ")");
  }
  std::vector<std::string> values;
  if (j.contains("parameters") && j["parameters"].is_object() &&
      j["parameters"].contains("values") && j["parameters"]["values"].is_array()) {
    for (const auto& v : j["parameters"]["values"])
      if (v.is_string()) values.push_back(v.get<std::string>());
  }
  if (values.empty()) throw Error(json_path + ": parameters.values is empty");
  return std::find(values.begin(), values.end(), "svv") != values.end() ? "svv" : values[0];
}

std::string plan_input_path(const PlanData& plan, const char* key) {
  return input_path(plan.json, key, plan.dir,
                    JsonPath((fs::path(plan.dir) / "plan.json").string()));
}

std::string plan_phase_input_path(const PlanData& plan, size_t phase, const char* key) {
  const JsonPath root((fs::path(plan.dir) / "plan.json").string());
  const JsonPath at = root.key("breathing").key("phases").index(phase);
  const nlohmann::json& phases = plan.json.at("breathing").at("phases");
  if (phase >= phases.size() || !phases[phase].contains("inputs")) {
    at.fail("records no inputs for this phase");
  }
  const nlohmann::json& in = phases[phase]["inputs"];
  if (std::string(key) != "labels") return input_path(phases[phase], key, plan.dir, at);
  if (!in.contains("label_maps") || !in["label_maps"].is_array() || in["label_maps"].size() != 1) {
    at.key("inputs").key("label_maps").fail("is not one label map: breathing guidance reads one per phase");
  }
  const nlohmann::json one = {{"inputs", {{"labels", in["label_maps"][0]}}}};
  return input_path(one, "labels", plan.dir, at);
}

}  // namespace crepuscular::planning
