// The area job: the unsafe criterion from the blocking volume (preview) or from a plan's path
// safety volume, then the area safety geometry of the tumor, written as one folder.
#include "pipelines/area.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <vector>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "foundation/output_files.hpp"
#include "pipelines/job_inputs.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/preprocessing/blocking.hpp"
#include "planning/safety/area_safety.hpp"
#include "planning/safety/unknown.hpp"

namespace fs = std::filesystem;

namespace crepuscular::pipelines {

using namespace planning;  // NOLINT: the job drives the planning modules throughout

namespace {

std::string number(double x) { return fmt::format("{:g}", x); }

nlohmann::json read_json_file(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw Error(path + ": cannot read file");
  try {
    return nlohmann::json::parse(in);
  } catch (const nlohmann::json::exception& e) {
    throw Error(path + ": not valid JSON (" + e.what() + ")");
  }
}

// What decides "unsafe", and what the test reads: the test refers to `blocking` or `path_safety`,
// so a Setup stays where it was filled in.
struct Setup {
  Volume<float> blocking, path_safety;
  Volume<uint8_t> region;  // the plan's voxel states (roi): unknown stops an extrusion unsafe
  SafetyTest test;
  std::string criterion;
  double threshold = 0;
  std::string tumor_path;
  AreaSafetyOptions options;
  nlohmann::json info;  // area.json "inputs"
};

// Threshold of a path safety value from plan.json's "classes" entry: unsafe_class "dangerous"
// gives its dangerous threshold, "medium" its safe threshold (anything not safe is unsafe).
double path_safety_threshold(const nlohmann::json& classes, const std::string& unsafe_class,
                             bool* higher_is_safer) {
  if (unsafe_class != "dangerous" && unsafe_class != "medium") {
    throw Error("unsafe class: expected 'dangerous' or 'medium', got '" + unsafe_class + "'");
  }
  if (!classes.is_object() || !classes.contains("safe") || !classes.contains("dangerous") ||
      !classes.contains("higher_is_safer")) {
    throw Error("plan.json: classes entry needs 'safe', 'dangerous' and 'higher_is_safer'");
  }
  if (higher_is_safer) *higher_is_safer = classes.at("higher_is_safer").get<bool>();
  return classes.at(unsafe_class == "dangerous" ? "dangerous" : "safe").get<double>();
}

// Anything above the lowest risk level blocks: the second-lowest non-zero coefficient.
double default_blocking_threshold(const ChosenTable& table) {
  std::vector<double> coeffs;
  for (const auto& l : table.table.levels) {
    if (l.blocking_per_mm > 0) coeffs.push_back(l.blocking_per_mm);
  }
  std::sort(coeffs.begin(), coeffs.end());
  coeffs.erase(std::unique(coeffs.begin(), coeffs.end()), coeffs.end());
  if (coeffs.empty()) throw Error(table.source + ": no level blocks; nothing can be unsafe");
  return coeffs.size() > 1 ? coeffs[1] : coeffs[0];
}

// Preview: unsafe where the blocking volume reaches the threshold.
void setup_preview(const AreaRequest& r, Setup& s) {
  if (!r.plan_dir.empty()) throw Error("area: preview mode uses the blocking volume and no plan");
  if (s.tumor_path.empty()) throw Error("area: preview mode needs a tumor mask");
  if (int(!r.labels.empty()) + int(!r.blocking.empty()) != 1) {
    throw Error(
        "area: preview mode needs the blocking: a label map (with a vulnerability table "
        "or preset) or a ready blocking volume, one of them");
  }
  require_input(s.tumor_path, "the tumor mask");
  if (!r.labels.empty()) {
    require_input(r.labels, "the label map");
    if (!r.vulnerability.empty()) require_input(r.vulnerability, "the vulnerability table");
    const ChosenTable table = choose_vulnerability_table(r.labels, r.vulnerability, r.preset);
    spdlog::info("reading label map {}", r.labels);
    MarginOptions margin;
    margin.fwhm_mm = r.margin_fwhm_mm;
    s.blocking = blocking_from_labels(read_label_map(r.labels, {r.series}), table.table, margin, r.labels);
    if (std::isnan(s.threshold)) s.threshold = default_blocking_threshold(table);
    s.info["labels"] = fs::absolute(final_path_of(r.labels)).string();
    s.info["vulnerability"] = table.source;
    s.info["margin_fwhm_mm"] = r.margin_fwhm_mm;
  } else {
    require_input(r.blocking, "the blocking volume");
    s.blocking = read_volume<float>(r.blocking, {r.series});
    validate_blocking(s.blocking, r.blocking);
    if (std::isnan(s.threshold)) {
      throw Error(
          "area: a ready blocking volume has no vulnerability table to take the default "
          "threshold from; give the blocking threshold (risk per mm)");
    }
    s.info["blocking"] = fs::absolute(final_path_of(r.blocking)).string();
  }
  if (!(s.threshold > 0) || !std::isfinite(s.threshold)) {
    throw Error("area: the blocking threshold must be > 0 per mm (got " + number(s.threshold) +
                ")");
  }
  s.test = blocking_safety_test(s.blocking, s.threshold);
  s.criterion = "preview: blocking >= " + number(s.threshold) + " per mm is unsafe";
  s.options.max_distance_mm = r.max_distance_mm > 0 ? r.max_distance_mm : 120.0;
  s.info["mode"] = "preview";
}

// NIfTI readers may turn the NaN of "not computed" into 0: the plan's voxel states (roi,
// planning/safety/unknown.hpp RegionState) say which voxels were computed. Returns the states.
Volume<uint8_t> mark_outside_roi(Volume<float>& path_safety, const std::string& roi_file,
                                 const std::string& file) {
  Volume<uint8_t> roi = read_volume<uint8_t>(roi_file);
  if (!roi.geometry().same_grid(path_safety.geometry(), 1e-3)) {
    throw Error(roi_file + ": not on the grid of " + file);
  }
  for (int64_t i = 0; i < roi.voxel_count(); ++i) {
    if (roi[i] != kRegionComputed) path_safety[i] = std::numeric_limits<float>::quiet_NaN();
  }
  return roi;
}

// Path safety: unsafe where the plan's value is past its class threshold (or the one given).
void setup_from_plan(const AreaRequest& r, Setup& s) {
  if (r.plan_dir.empty()) {
    throw Error(
        "area: give a plan folder (path safety mode), or ask for the preview with a "
        "label map");
  }
  const std::string plan_json = (fs::path(r.plan_dir) / "plan.json").string();
  require_input(plan_json, "the plan's plan.json");
  const nlohmann::json plan = read_json_file(plan_json);
  try {
    std::string value = r.value;
    if (value.empty()) value = plan.at("parameters").at("values").at(0).get<std::string>();
    const nlohmann::json& outputs = plan.at("outputs");
    if (!outputs.contains(value)) {
      throw Error(plan_json + ": outputs: no path safety volume for value '" + value + "'");
    }
    const std::string file = (fs::path(r.plan_dir) / outputs.at(value).get<std::string>()).string();
    bool higher = false;
    const double from_classes =
        path_safety_threshold(plan.at("classes").at(value), r.unsafe_class, &higher);
    if (std::isnan(s.threshold)) s.threshold = from_classes;
    if (s.tumor_path.empty())
      s.tumor_path = plan.at("inputs").at("tumor").at("path").get<std::string>();
    spdlog::info("reading path safety volume {}", file);
    s.path_safety = read_volume<float>(file, VolumeReadOptions::path_safety_file());
    if (outputs.contains("roi")) {
      s.region = mark_outside_roi(s.path_safety,
                       (fs::path(r.plan_dir) / outputs.at("roi").get<std::string>()).string(),
                       file);
    }
    const double roi_radius_mm = plan.at("parameters").at("radius_mm").get<double>();
    s.test = path_safety_test(s.path_safety, higher, s.threshold, roi_radius_mm,
                              s.region.empty() ? nullptr : &s.region);
    s.criterion = "path safety " + value + (higher ? " < " : " > ") + number(s.threshold) + " (" +
                  r.unsafe_class + (r.unsafe_class == "medium" ? " or dangerous" : "") +
                  " is unsafe)";
    s.options.max_distance_mm = r.max_distance_mm > 0 ? r.max_distance_mm : roi_radius_mm;
    if (r.spacing_mm <= 0)
      s.options.spacing_mm = plan.at("parameters").at("spacing_mm").get<double>();
    s.info["mode"] = "path safety";
    s.info["plan"] = fs::absolute(final_path_of(r.plan_dir)).string();
    s.info["value"] = value;
    s.info["unsafe_class"] = r.unsafe_class;
  } catch (const nlohmann::json::exception& e) {
    throw Error(plan_json + ": missing or malformed field (" + e.what() + ")");
  }
  require_input(s.tumor_path, "the tumor mask, by default the plan's inputs.tumor.path");
}

}  // namespace

nlohmann::json run_area(const AreaRequest& r) {
  const auto t0 = Clock::now();
  if (r.out_dir.empty()) throw Error("area: an output folder is required");
  std::error_code ec;
  if (fs::exists(fs::path(r.out_dir) / "plan.json", ec)) {
    throw Error(r.out_dir +
                ": is a plan folder; the area safety output would replace it, choose "
                "another output folder");
  }
  Setup s;
  s.threshold = r.threshold;
  s.tumor_path = r.tumor;
  if (r.preview) {
    setup_preview(r, s);
  } else {
    setup_from_plan(r, s);
  }
  spdlog::info("reading tumor mask {}", s.tumor_path);
  const Volume<uint8_t> tumor = read_mask(s.tumor_path, {r.series});
  if (r.spacing_mm > 0) {
    s.options.spacing_mm = r.spacing_mm;
  } else if (s.options.spacing_mm <= 0) {
    s.options.spacing_mm =
        std::min(s.blocking.geometry().spacing.minCoeff(), tumor.geometry().spacing.minCoeff());
  }
  s.info["tumor"] = fs::absolute(final_path_of(s.tumor_path)).string();
  s.options.angular_step_deg = r.angular_step_deg;

  const Ellipsoid e = fit_tumor_ellipsoid(tumor, s.tumor_path);
  AreaSafetyGeometry g = compute_area_safety(e, s.test, s.options);
  g.criterion = s.criterion;
  g.threshold = s.threshold;

  StagedDirectory out(r.out_dir);
  write_area_safety_vtk(out.file("area_safety.vtk"), g);
  nlohmann::json j;
  j["crepuscular_version"] = CREPUSCULAR_VERSION;
  j["inputs"] = s.info;
  j["area_safety"] = area_safety_json(g);
  j["area_safety"]["file"] = "area_safety.vtk";
  j["seconds"] = seconds_since(t0);
  write_text_file(out.file("area.json"), j.dump(2) + "\n");
  out.commit();
  spdlog::info("area safety written to {} ({:.1f} s)", r.out_dir, seconds_since(t0));
  return j;
}

}  // namespace crepuscular::pipelines
