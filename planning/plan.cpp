// The plan job: inputs -> blocking volume -> path safety -> PLAN_DIR, written atomically.
#include "planning/plan.hpp"

#include <itksys/MD5.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <vector>

#include "planning/output_files.hpp"
#include "planning/safety_classes.hpp"
#include "planning/volume_io.hpp"
#include "planning/vulnerability.hpp"

namespace fs = std::filesystem;

namespace crepuscular::planning {

namespace {

using Clock = std::chrono::steady_clock;

double seconds_since(Clock::time_point t) {
  return std::chrono::duration<double>(Clock::now() - t).count();
}

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

// An input file: its absolute path, its path relative to the plan folder (so a plan moved together
// with its inputs, e.g. a whole demo folder, still finds them) and its checksum.
nlohmann::json input_json(const std::string& path, const std::string& plan_dir) {
  if (path.empty()) return nullptr;
  const fs::path absolute = fs::absolute(path);
  return {{"path", absolute.string()},
          {"relative_path", fs::absolute(absolute).lexically_relative(fs::absolute(plan_dir)).string()},
          {"md5", file_checksum(path)}};
}

std::string now_iso8601() {
  const std::time_t t = std::time(nullptr);
  char buf[32];
  std::strftime(buf, sizeof(buf), "%Y-%m-%dT%H:%M:%SZ", std::gmtime(&t));
  return buf;
}

void require_file(const std::string& path, const char* option) {
  std::error_code ec;
  if (!fs::exists(path, ec)) {
    throw Error(path + ": file does not exist (given as " + option + ")");
  }
}

}  // namespace

std::string file_checksum(const std::string& path) {
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

nlohmann::json classes_json(unsigned value_bit, const Volume<float>& volume) {
  const SafetyClasses c = default_classes(value_bit, volume);
  return {{"higher_is_safer", c.higher_is_safer},
          {"safe", c.safe},
          {"dangerous", c.dangerous},
          {"rule", c.higher_is_safer
                       ? "safe: value >= safe; dangerous: value < dangerous; medium in between (%)"
                       : "safe: value <= safe (20th percentile of the non-zero values of the region "
                         "of interest); dangerous: value > dangerous (60th percentile of them); "
                         "medium in between"}};
}

nlohmann::json run_plan(const PlanRequest& req) {
  const auto t_start = Clock::now();
  if (req.tumor.empty()) throw Error("--tumor: a tumor mask is required");
  if (req.out_dir.empty()) throw Error("--out: an output folder is required");
  const int sources = int(!req.labels.empty()) + int(!req.blocking.empty());
  if (sources > 1) throw Error("give either --labels or --blocking, not both");
  if (sources == 0 && req.ct.empty()) {
    throw Error("no blocking information: give --labels (with --vulnerability or --preset), "
                "--blocking, or --ct for thresholding");
  }
  require_file(req.tumor, "--tumor");
  if (!req.labels.empty()) require_file(req.labels, "--labels");
  if (!req.blocking.empty()) require_file(req.blocking, "--blocking");
  if (!req.ct.empty()) require_file(req.ct, "--ct");
  if (!req.vulnerability.empty()) require_file(req.vulnerability, "--vulnerability");

  // Staged first: a failure below removes it and leaves no plan behind.
  StagedDirectory out(req.out_dir);

  nlohmann::json plan;
  plan["crepuscular_version"] = CREPUSCULAR_VERSION;
  plan["created_utc"] = now_iso8601();
  nlohmann::json timings;

  // --- Blocking volume -------------------------------------------------------------------------
  auto t = Clock::now();
  Volume<float> blocking;
  nlohmann::json preprocessing;
  std::string blocking_source;
  if (!req.blocking.empty()) {
    spdlog::info("reading blocking volume {}", req.blocking);
    blocking = read_volume<float>(req.blocking);
    blocking_source = req.blocking;
    preprocessing = {{"mode", "ready blocking volume"}};
  } else if (!req.labels.empty()) {
    VulnerabilityTable table;
    std::string table_source;
    if (!req.vulnerability.empty()) {
      table = VulnerabilityTable::load(req.vulnerability);
      table_source = req.vulnerability;
    } else if (!req.preset.empty()) {
      table = VulnerabilityTable::preset(req.preset);
      table_source = "preset " + req.preset;
    } else {
      const fs::path beside = fs::path(req.labels).parent_path() / "vulnerability.json";
      if (!fs::exists(beside)) {
        throw Error(req.labels + ": no vulnerability table: give --vulnerability FILE or --preset "
                    "NAME (" + [] {
                      std::string s;
                      for (const auto& n : VulnerabilityTable::preset_names()) {
                        s += (s.empty() ? "" : ", ") + n;
                      }
                      return s;
                    }() + "), or put vulnerability.json beside the label map");
      }
      table = VulnerabilityTable::load(beside.string());
      table_source = beside.string();
      spdlog::info("using vulnerability table {}", table_source);
    }
    spdlog::info("reading label map {}", req.labels);
    const Volume<int32_t> labels = read_label_map(req.labels);
    blocking = blocking_from_labels(labels, table, req.margin, req.labels);
    blocking_source = req.labels;
    preprocessing = {{"mode", "labels"},
                     {"vulnerability_source", table_source},
                     {"vulnerability", table.to_json()},
                     {"margin_fwhm_mm", req.margin.fwhm_mm}};
  } else {
    spdlog::info("reading CT {} for thresholding", req.ct);
    const Volume<float> ct = read_volume<float>(req.ct);
    blocking = blocking_from_ct(ct, req.ct_thresholds, req.margin);
    blocking_source = req.ct;
    preprocessing = {{"mode", "ct thresholds"},
                     {"bone_hu", req.ct_thresholds.bone_hu},
                     {"air_hu", req.ct_thresholds.air_hu},
                     {"impassable_per_mm", req.ct_thresholds.impassable_per_mm},
                     {"margin_fwhm_mm", req.margin.fwhm_mm}};
  }
  validate_blocking(blocking, blocking_source);
  timings["preprocessing_s"] = seconds_since(t);

  t = Clock::now();
  spdlog::info("reading tumor mask {}", req.tumor);
  const Volume<uint8_t> tumor = read_mask(req.tumor);
  timings["read_tumor_s"] = seconds_since(t);

  // --- Path safety -----------------------------------------------------------------------------
  t = Clock::now();
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
  const PathSafetyResult result = compute_path_safety(blocking, tumor, ps, blocking_source,
                                                      req.tumor);
  timings["path_safety_s"] = seconds_since(t);
  spdlog::info("path safety done in {:.1f} s on {}", result.seconds, result.device);

  // --- Outputs ---------------------------------------------------------------------------------
  t = Clock::now();
  write_volume(blocking, out.file("blocking.nii.gz"));
  // The region of interest as a mask: ITK-based readers (3D Slicer among them) turn NaN into 0
  // when they load NIfTI, so "not computed" must also be visible without NaN.
  Volume<uint8_t> roi(result.grid.geometry, 0);
  for (int64_t k = 0; k < roi.dims()[2]; ++k)
    for (int64_t j = 0; j < roi.dims()[1]; ++j)
      for (int64_t i = 0; i < roi.dims()[0]; ++i) roi(i, j, k) = result.grid.in_roi(i, j, k);
  write_volume(roi, out.file("roi.nii.gz"));
  nlohmann::json outputs = {{"blocking", "blocking.nii.gz"}, {"roi", "roi.nii.gz"}};
  nlohmann::json classes, statistics;
  for (int v = 0; v < kernels::kValueCount; ++v) {
    const unsigned bit = 1u << v;
    if (!(result.values & bit)) continue;
    const std::string name = value_name(bit);
    const std::string file = "path_safety_" + name + ".nii.gz";
    const Volume<float>& vol = result.volumes[size_t(v)];
    write_volume(vol, out.file(file));
    outputs[name] = file;
    classes[name] = classes_json(bit, vol);
    double lo = INFINITY, hi = -INFINITY, sum = 0.0;
    int64_t n = 0;
    for (float x : vol.values()) {
      if (!std::isfinite(x)) continue;
      lo = std::min(lo, double(x));
      hi = std::max(hi, double(x));
      sum += x;
      ++n;
    }
    statistics[name] = {{"min", lo}, {"max", hi}, {"mean", n ? sum / double(n) : 0.0},
                        {"voxels", n}};
  }
  timings["write_s"] = seconds_since(t);

  // --- Area safety (§3.3): the first computed value ---------------------------------------------
  nlohmann::json area_safety;
  if (req.area_safety.enabled) {
    const auto t_area = Clock::now();
    area_safety = plan_area_safety(tumor, result, req.area_safety, out.file("area_safety.vtk"));
    outputs["area_safety"] = "area_safety.vtk";
    timings["area_safety_s"] = seconds_since(t_area);
  }
  timings["total_s"] = seconds_since(t_start);

  plan["inputs"] = {{"labels", input_json(req.labels, req.out_dir)},
                    {"tumor", input_json(req.tumor, req.out_dir)},
                    {"vulnerability", input_json(req.vulnerability, req.out_dir)},
                    {"preset", req.preset.empty() ? nlohmann::json(nullptr) : nlohmann::json(req.preset)},
                    {"ct", input_json(req.ct, req.out_dir)},
                    {"blocking", input_json(req.blocking, req.out_dir)}};
  plan["preprocessing"] = preprocessing;
  nlohmann::json values = nlohmann::json::array();
  for (int v = 0; v < kernels::kValueCount; ++v) {
    if (result.values & (1u << v)) values.push_back(value_name(1u << v));
  }
  plan["parameters"] = {{"values", values},
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
  if (result.mode == Mode::kFast) {
    nlohmann::json check = {{"voxels", result.check_voxels},
                            {"direction_cells", result.direction_cells},
                            {"angular_oversampling", req.path_safety.fast_angular}};
    for (int v = 0; v < kernels::kValueCount; ++v) {
      if (!(result.values & (1u << v))) continue;
      check[value_name(1u << v)] = {
          {"relative_l2", result.check_relative_l2[size_t(v)]},
          {"class_agreement", result.check_class_agreement[size_t(v)]}};
    }
    plan["fast_mode_vs_exact"] = check;
  }
  plan["grid"] = geometry_json(result.grid.geometry);
  plan["grid"]["centre_lps_mm"] = {result.grid.centre.x(), result.grid.centre.y(),
                                   result.grid.centre.z()};
  plan["grid"]["roi_voxels"] = result.grid.roi_voxels;
  plan["grid"]["outside_roi"] = "NaN (not computed)";
  plan["tumor"] = {{"voxels", result.tumor_voxels},
                   {"surface_points", result.surface_points},
                   {"s2_mm2", result.s2_mm2},
                   {"centroid_lps_mm", {result.grid.centre.x(), result.grid.centre.y(),
                                        result.grid.centre.z()}}};
  plan["blocking_grid"] = geometry_json(blocking.geometry());
  plan["rays"] = result.rays;
  plan["classes"] = classes;
  plan["statistics"] = statistics;
  if (!area_safety.is_null()) plan["area_safety"] = area_safety;
  plan["outputs"] = outputs;
  plan["timings"] = timings;
  write_text_file(out.file("plan.json"), plan.dump(2) + "\n");
  out.commit();
  spdlog::info("plan written to {} ({:.1f} s)", req.out_dir, seconds_since(t_start));
  return plan;
}

}  // namespace crepuscular::planning
