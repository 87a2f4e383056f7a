// The plan job: inputs -> blocking volume -> path safety -> area safety -> PLAN_DIR, written
// atomically. The folder's format (plan.json's pieces) is planning/plan_folder's.
#include "pipelines/plan.hpp"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cmath>
#include <ctime>
#include <nlohmann/json.hpp>

#include "foundation/error.hpp"
#include "foundation/output_files.hpp"
#include "pipelines/job_inputs.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/plan_folder/plan_folder.hpp"

namespace crepuscular::pipelines {

using namespace planning;  // NOLINT: the job drives the planning modules throughout

namespace {

std::string now_iso8601() {
  const std::time_t t = std::time(nullptr);
  char buf[32];
  std::strftime(buf, sizeof(buf), "%Y-%m-%dT%H:%M:%SZ", std::gmtime(&t));
  return buf;
}

void check_request(const PlanRequest& req) {
  if (req.tumor.empty()) throw Error("plan: a tumor mask is required");
  if (req.out_dir.empty()) throw Error("plan: an output folder is required");
  const int sources = int(!req.labels.empty()) + int(!req.blocking.empty());
  if (sources > 1) throw Error("plan: give either a label map or a blocking volume, not both");
  if (sources == 0 && req.ct.empty()) {
    throw Error(
        "plan: no blocking information: give a label map (with a vulnerability table or "
        "preset), a ready blocking volume, or a CT for thresholding");
  }
  require_input(req.tumor, "the tumor mask");
  if (!req.labels.empty()) require_input(req.labels, "the label map");
  if (!req.blocking.empty()) require_input(req.blocking, "the blocking volume");
  if (!req.ct.empty()) require_input(req.ct, "the CT");
  if (!req.vulnerability.empty()) require_input(req.vulnerability, "the vulnerability table");
}

struct Blocking {
  Volume<float> volume;
  std::string source;          // the file it came from
  nlohmann::json description;  // plan.json "preprocessing"
};

// Step 1: the blocking volume, from a ready volume, a label map and its table, or CT thresholds.
Blocking make_blocking(const PlanRequest& req) {
  Blocking b;
  if (!req.blocking.empty()) {
    spdlog::info("reading blocking volume {}", req.blocking);
    b.volume = read_volume<float>(req.blocking);
    b.source = req.blocking;
    b.description = {{"mode", "ready blocking volume"}};
  } else if (!req.labels.empty()) {
    const ChosenTable table = choose_vulnerability_table(req.labels, req.vulnerability, req.preset);
    spdlog::info("reading label map {}", req.labels);
    const Volume<int32_t> labels = read_label_map(req.labels);
    b.volume = blocking_from_labels(labels, table.table, req.margin, req.labels);
    b.source = req.labels;
    b.description = {{"mode", "labels"},
                     {"vulnerability_source", table.source},
                     {"vulnerability", table.table.to_json()},
                     {"margin_fwhm_mm", req.margin.fwhm_mm}};
  } else {
    spdlog::info("reading CT {} for thresholding", req.ct);
    const Volume<float> ct = read_volume<float>(req.ct);
    b.volume = blocking_from_ct(ct, req.ct_thresholds, req.margin);
    b.source = req.ct;
    b.description = {{"mode", "ct thresholds"},
                     {"bone_hu", req.ct_thresholds.bone_hu},
                     {"air_hu", req.ct_thresholds.air_hu},
                     {"impassable_per_mm", req.ct_thresholds.impassable_per_mm},
                     {"margin_fwhm_mm", req.margin.fwhm_mm}};
  }
  validate_blocking(b.volume, b.source);
  return b;
}

// Step 2: path safety, with progress in steps of 10 % unless the caller reports it.
PathSafetyResult compute(const PlanRequest& req, const Blocking& blocking,
                         const Volume<uint8_t>& tumor) {
  PathSafetyOptions ps = req.path_safety;
  if (!ps.progress) {
    ps.progress = [last = -1](double f) mutable {
      const int pct = int(f * 100.0);
      if (pct / 10 != last / 10 || pct == 100) {
        spdlog::info("path safety: {:3d} %", pct);
        last = pct;
      }
    };
  }
  const PathSafetyResult result =
      compute_path_safety(blocking.volume, tumor, ps, blocking.source, req.tumor);
  spdlog::info("path safety done in {:.1f} s on {}", result.seconds, result.device);
  return result;
}

// The volumes' files, classes and statistics as plan.json lists them.
struct Written {
  nlohmann::json outputs, classes, statistics;
};

nlohmann::json statistics_json(const Volume<float>& vol) {
  double lo = INFINITY, hi = -INFINITY, sum = 0.0;
  int64_t n = 0;
  for (float x : vol.values()) {
    if (!std::isfinite(x)) continue;
    lo = std::min(lo, double(x));
    hi = std::max(hi, double(x));
    sum += x;
    ++n;
  }
  return {{"min", lo}, {"max", hi}, {"mean", n ? sum / double(n) : 0.0}, {"voxels", n}};
}

// Step 3: blocking, region of interest and path safety volumes into the staged folder.
Written write_volumes(const StagedDirectory& out, const Volume<float>& blocking,
                      const PathSafetyResult& result) {
  write_volume(blocking, out.file("blocking.nii.gz"));
  // The region of interest as a mask: ITK-based readers (3D Slicer among them) turn NaN into 0
  // when they load NIfTI, so "not computed" must also be visible without NaN.
  Volume<uint8_t> roi(result.grid.geometry, 0);
  for (int64_t k = 0; k < roi.dims()[2]; ++k)
    for (int64_t j = 0; j < roi.dims()[1]; ++j)
      for (int64_t i = 0; i < roi.dims()[0]; ++i) roi(i, j, k) = result.grid.in_roi(i, j, k);
  write_volume(roi, out.file("roi.nii.gz"));
  Written w;
  w.outputs = {{"blocking", "blocking.nii.gz"}, {"roi", "roi.nii.gz"}};
  for (int v = 0; v < kernels::kValueCount; ++v) {
    const unsigned bit = 1u << v;
    if (!(result.values & bit)) continue;
    const std::string name = value_name(bit);
    const std::string file = "path_safety_" + name + ".nii.gz";
    const Volume<float>& vol = result.volumes[size_t(v)];
    write_volume(vol, out.file(file));
    w.outputs[name] = file;
    w.classes[name] = classes_json(bit, vol);
    w.statistics[name] = statistics_json(vol);
  }
  return w;
}

nlohmann::json parameters_json(const PlanRequest& req, const PathSafetyResult& result) {
  nlohmann::json values = nlohmann::json::array();
  for (int v = 0; v < kernels::kValueCount; ++v) {
    if (result.values & (1u << v)) values.push_back(value_name(1u << v));
  }
  return {{"values", values},
          {"mode", mode_name(result.mode)},
          {"eps", result.eps},
          {"spacing_mm", result.grid.geometry.spacing[0]},
          {"spacing_requested_mm", req.path_safety.spacing_mm},
          {"radius_mm", result.grid.radius_mm},
          {"radius_requested_mm", req.path_safety.radius_mm},
          {"gamma_mm", result.gamma_mm},
          {"device_requested", device_name(req.path_safety.device)},
          {"device", result.device},
          {"threads", result.threads}};
}

// Fast mode's check against the exact method on random voxels.
nlohmann::json fast_check_json(const PlanRequest& req, const PathSafetyResult& result) {
  nlohmann::json check = {{"voxels", result.check_voxels},
                          {"direction_cells", result.direction_cells},
                          {"angular_oversampling", req.path_safety.fast_angular}};
  for (int v = 0; v < kernels::kValueCount; ++v) {
    if (!(result.values & (1u << v))) continue;
    check[value_name(1u << v)] = {{"relative_l2", result.check_relative_l2[size_t(v)]},
                                  {"class_agreement", result.check_class_agreement[size_t(v)]}};
  }
  return check;
}

// Step 5: plan.json from the request, the blocking, the result and what was written.
nlohmann::json plan_json(const PlanRequest& req, const Blocking& blocking,
                         const PathSafetyResult& result, const Written& written) {
  nlohmann::json plan;
  plan["crepuscular_version"] = CREPUSCULAR_VERSION;
  plan["created_utc"] = now_iso8601();
  plan["inputs"] = {
      {"labels", input_json(req.labels, req.out_dir)},
      {"tumor", input_json(req.tumor, req.out_dir)},
      {"vulnerability", input_json(req.vulnerability, req.out_dir)},
      {"preset", req.preset.empty() ? nlohmann::json(nullptr) : nlohmann::json(req.preset)},
      {"ct", input_json(req.ct, req.out_dir)},
      {"blocking", input_json(req.blocking, req.out_dir)}};
  plan["preprocessing"] = blocking.description;
  plan["parameters"] = parameters_json(req, result);
  if (result.mode == Mode::kFast) plan["fast_mode_vs_exact"] = fast_check_json(req, result);
  const Eigen::Vector3d& c = result.grid.centre;
  plan["grid"] = geometry_json(result.grid.geometry);
  plan["grid"]["centre_lps_mm"] = {c.x(), c.y(), c.z()};
  plan["grid"]["roi_voxels"] = result.grid.roi_voxels;
  plan["grid"]["outside_roi"] = "NaN (not computed)";
  plan["tumor"] = {{"voxels", result.tumor_voxels},
                   {"surface_points", result.surface_points},
                   {"s2_mm2", result.s2_mm2},
                   {"centroid_lps_mm", {c.x(), c.y(), c.z()}}};
  plan["blocking_grid"] = geometry_json(blocking.volume.geometry());
  plan["rays"] = result.rays;
  plan["classes"] = written.classes;
  plan["statistics"] = written.statistics;
  return plan;
}

}  // namespace

nlohmann::json run_plan(const PlanRequest& req) {
  const auto t_start = Clock::now();
  check_request(req);
  // Staged first: a failure below removes it and leaves no plan behind.
  StagedDirectory out(req.out_dir);
  nlohmann::json timings;

  auto t = Clock::now();
  const Blocking blocking = make_blocking(req);
  timings["preprocessing_s"] = seconds_since(t);

  t = Clock::now();
  spdlog::info("reading tumor mask {}", req.tumor);
  const Volume<uint8_t> tumor = read_mask(req.tumor);
  timings["read_tumor_s"] = seconds_since(t);

  t = Clock::now();
  const PathSafetyResult result = compute(req, blocking, tumor);
  timings["path_safety_s"] = seconds_since(t);

  t = Clock::now();
  Written written = write_volumes(out, blocking.volume, result);
  timings["write_s"] = seconds_since(t);

  // Step 4, area safety (§3.3): the first computed value.
  nlohmann::json area_safety;
  if (req.area_safety.enabled) {
    t = Clock::now();
    area_safety = plan_area_safety(tumor, result, req.area_safety, out.file("area_safety.vtk"));
    written.outputs["area_safety"] = "area_safety.vtk";
    timings["area_safety_s"] = seconds_since(t);
  }
  timings["total_s"] = seconds_since(t_start);

  nlohmann::json plan = plan_json(req, blocking, result, written);
  if (!area_safety.is_null()) plan["area_safety"] = area_safety;
  plan["outputs"] = written.outputs;
  plan["timings"] = timings;
  write_text_file(out.file("plan.json"), plan.dump(2) + "\n");
  out.commit();
  spdlog::info("plan written to {} ({:.1f} s)", req.out_dir, seconds_since(t_start));
  return plan;
}

}  // namespace crepuscular::pipelines
