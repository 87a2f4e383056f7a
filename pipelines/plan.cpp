// The plan job: inputs -> blocking volume -> path safety -> area safety -> PLAN_DIR, written
// atomically. The folder's format (plan.json's pieces) is planning/plan_folder's.
#include "pipelines/plan.hpp"

#include <omp.h>
#include "foundation/log.hpp"

#include <algorithm>
#include <array>
#include <filesystem>
#include <atomic>
#include <exception>
#include <functional>
#include <future>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>
#include <cmath>
#include <nlohmann/json.hpp>

#include "foundation/error.hpp"
#include "foundation/json_fields.hpp"
#include "foundation/output_files.hpp"
#include "foundation/text.hpp"
#include "foundation/trace.hpp"
#include "pipelines/job_inputs.hpp"
#include "pipelines/plan_inputs.hpp"
#include "planning/imaging/segmentation.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/plan_folder/plan_folder.hpp"
#include "planning/breathing/combiner.hpp"
#include "planning/breathing/executor.hpp"
#include "planning/breathing/schedule.hpp"
#include "planning/safety/unknown.hpp"
#include "planning/trajectories/markups.hpp"
#include "planning/views/palette.hpp"

namespace crepuscular::pipelines {

using namespace planning;  // NOLINT: the job drives the planning modules throughout

namespace {

void check_request(const PlanRequest& req) {
  if (!req.phases.empty()) {
    if (!req.tumor.empty() || !req.labels.empty() || !req.ct.empty() || !req.blocking.empty()) {
      throw Error("plan: with a phase list the label maps, tumors and CTs come from it; give no "
                  "other label map, tumor, CT or blocking volume");
    }
    if (req.out_dir.empty()) throw Error("plan: an output folder is required");
    require_input(req.phases, "the phase list");
    return;
  }
  if (req.per_phase) throw Error("plan: per-phase volumes need a phase list");
  if (req.tumor.empty()) throw Error("plan: a tumor mask is required");
  if (req.out_dir.empty()) throw Error("plan: an output folder is required");
  const int sources = int(!req.labels.empty()) + int(!req.blocking.empty());
  if (sources > 1) throw Error("plan: give either label maps or a blocking volume, not both");
  if (sources == 0 && req.ct.empty()) {
    throw Error(
        "plan: no blocking information: give a label map (with a vulnerability table or "
        "preset), a ready blocking volume, or a CT for thresholding");
  }
  if (!req.preset.empty() && !req.vulnerability.empty()) {
    throw Error("plan: give either a vulnerability table or a preset, not both (plan.json would "
                "record only one of them)");
  }
  if (req.lesion < 0) throw Error("plan: the lesion number counts from 1 (the largest)");
  if (req.lesion > 0 && req.lesion_at) {
    throw Error("plan: choose the lesion either by number or by a point, not both");
  }
  require_input(tumor_file(req.tumor), "the tumor");
  for (const auto& f : label_files(req.labels)) require_input(f, "a label map");
  if (!req.blocking.empty()) require_input(req.blocking, "the blocking volume");
  if (!req.ct.empty()) require_input(req.ct, "the CT");
  if (!req.vulnerability.empty()) require_input(req.vulnerability, "the vulnerability table");
}


// Progress logged in steps of 10 %, after `what`.
std::function<void(double)> progress_in_steps(std::string what) {
  return [what = std::move(what), last = -1](double f) mutable {
    const int pct = int(f * 100.0);
    if (pct / 10 != last / 10 || pct == 100) {
      spdlog::info("{}: {:3d} %", what, pct);
      last = pct;
    }
  };
}

// Step 2: path safety, with progress in steps of 10 % unless the caller reports it.
PathSafetyResult compute(const PlanRequest& req, const PlanInputs& in) {
  PathSafetyOptions ps = req.path_safety;
  ps.coverage = &in.coverage;  // voxels outside the scan are unknown: not computed
  if (!ps.progress) ps.progress = progress_in_steps("path safety");
  PathSafetyResult result =
      compute_path_safety(in.blocking, in.tumor, ps, in.blocking_source, tumor_file(req.tumor));
  spdlog::info("path safety done in {:.1f} s on {}", result.seconds, result.device);
  return result;
}

// The volumes' files, classes and statistics as plan.json lists them.
struct Written {
  nlohmann::json outputs, classes, statistics;
};

nlohmann::json statistics_json(const ValueStatistics& s) {
  return {{"min", s.min},
          {"max", s.max},
          {"mean", s.voxels ? s.sum / double(s.voxels) : 0.0},
          {"voxels", s.voxels}};
}

// Step 3: blocking, region of interest and path safety volumes into the staged folder.
// Grids above this many voxels are written as uncompressed NIfTI (.nii): gzip, even at level 1,
// runs at ~100 MB/s a core while the disk takes GB/s (bench/RESULTS.md, plan end to end).
constexpr int64_t kUncompressedAboveVoxels = 32 * 1024 * 1024;

// The NIfTI extension of a volume of `voxels` voxels.
std::string volume_extension(int64_t voxels) {
  return voxels > kUncompressedAboveVoxels ? ".nii" : ".nii.gz";
}

// Step 3a, while path safety runs (they depend on the inputs alone): the blocking volume and the
// planned lesion itself (a label of a label map, or one of several lesions: what slices,
// evaluate and guidance outline) into the staged folder. `outputs` gets their names.
std::vector<std::future<void>> write_inputs(const StagedDirectory& out, const PlanInputs& in,
                                            nlohmann::json& outputs) {
  const std::string blocking = "blocking" + volume_extension(in.blocking.voxel_count());
  outputs["blocking"] = blocking;
  outputs["tumor"] = "tumor.nii.gz";
  std::vector<std::future<void>> writes;
  writes.push_back(std::async(std::launch::async,
                              [&out, &in, blocking] { write_volume(in.blocking, out.file(blocking)); }));
  writes.push_back(std::async(std::launch::async,
                              [&out, &in] { write_volume(in.tumor, out.file("tumor.nii.gz")); }));
  return writes;
}

// Area safety (§3.3) of the first computed value on a thread of its own while the volumes are
// written (the writes wait on the disk); its classes are taken here, before the writes take the
// others' beside it. Fills `json` and `geometry`; an invalid future when it is off.
std::future<double> area_safety_beside_writes(const PlanRequest& req,
                                              const Volume<uint8_t>& tumor,
                                              PathSafetyResult& result,
                                              const StagedDirectory& out,
                                              const Volume<uint8_t>& region, nlohmann::json& json,
                                              AreaSafetyGeometry& geometry) {
  if (!req.area_safety.enabled) return {};
  classes_of(result, result.values & (~result.values + 1));  // the lowest value computed
  return std::async(std::launch::async, [&req, &tumor, &result, &out, &region, &json, &geometry] {
    const auto ta = Clock::now();
    json = plan_area_safety(tumor, result, req.area_safety, out.file("area_safety.vtk"), &region,
                            &geometry);
    return seconds_since(ta);
  });
}

// The segments of path_safety_<value>_classes.seg.nrrd: the classes with their label values
// (class_label), the default palette's colours and unknown grey.
std::vector<SegmentSpec> class_segments() {
  const std::array<Rgb, 3> colours = class_colours(Palette::kDefault);
  const auto unit = [](const Rgb& c) {
    return std::array<double, 3>{c[0] / 255.0, c[1] / 255.0, c[2] / 255.0};
  };
  return {{"safe", "safe", class_label(SafetyClass::kSafe), unit(colours[0])},
          {"medium", "medium", class_label(SafetyClass::kMedium), unit(colours[1])},
          {"dangerous", "dangerous", class_label(SafetyClass::kDangerous), unit(colours[2])},
          {"unknown", "unknown", class_label(SafetyClass::kUnknown), {0.5, 0.5, 0.5}}};
}

// Step 3b: voxel states, path safety volumes and their classes
// (path_safety_<value>_classes.seg.nrrd) into the staged folder, concurrently, and the writes of
// step 3a finished. `beside`, when given, runs once every volume's classes are taken, while the
// writes go on.
Written write_volumes(const StagedDirectory& out, PathSafetyResult& result,
                      const Volume<uint8_t>& region, std::vector<std::future<void>> writes,
                      const nlohmann::json& outputs,
                      const std::function<void()>& beside = nullptr) {
  const std::string ext = volume_extension(result.grid.geometry.voxel_count());
  Written w;
  w.outputs = outputs;
  w.outputs["roi"] = "roi" + ext;
  // The voxel states (RegionState): ITK-based readers (3D Slicer among them) turn NaN into 0 when
  // they load NIfTI, so "not computed" and "unknown" must also be visible without NaN.
  writes.push_back(std::async(std::launch::async,
                              [&] { write_volume(region, out.file("roi" + ext)); }));
  for (int v = 0; v < kernels::kValueCount; ++v) {
    const unsigned bit = 1u << v;
    if (!(result.values & bit)) continue;
    const std::string name = value_name(bit);
    const std::string file = "path_safety_" + name + ext;
    const Volume<float>& vol = result.volumes[size_t(v)];
    writes.push_back(
        std::async(std::launch::async, [&out, &vol, file] { write_volume(vol, out.file(file)); }));
    w.outputs[name] = file;
    // Taken once, in one pass (or where fast mode's check took the classes, one for these).
    const SafetyClasses classes = classes_of(result, bit);
    w.classes[name] = classes_json(classes);
    // The classes for 3D Slicer, by the thresholds plan.json states, unknown where roi says so.
    const std::string classes_file = "path_safety_" + name + "_classes.seg.nrrd";
    writes.push_back(std::async(std::launch::async, [&out, &vol, &region, classes, classes_file] {
      write_segmentation(out.file(classes_file), class_labels(vol, classes, region),
                         class_segments());
    }));
    w.outputs[name + "_classes"] = classes_file;
    w.statistics[name] = statistics_json(statistics_of(result, bit));
  }
  trace::event("classes_taken", 0, -1);
  if (beside) {
    try {
      beside();
    } catch (...) {
      for (auto& f : writes) f.wait();  // before the staged folder goes
      throw;
    }
  }
  for (auto& f : writes) f.get();  // rethrows the first failure; the staged folder goes with it
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
          {"tumor_spacing_mm", result.tumor_spacing_mm},
          {"tumor_spacing_requested_mm", req.path_safety.tumor_spacing_mm},
          {"device_requested", device_name(req.path_safety.device)},
          {"device", result.device},
          {"threads", result.threads}};
}

// Fast mode's points, level by level (the coarsest first).
nlohmann::json points_per_level_json(const PathSafetyResult& result) {
  nlohmann::json levels = nlohmann::json::array();
  for (const auto& [stride, count] : result.fast.levels) {
    levels.push_back({{"stride", stride}, {"points", count}});
  }
  return levels;
}

// Fast mode's check against the exact method on random voxels.
nlohmann::json fast_check_json(const PlanRequest& req, const PathSafetyResult& result) {
  const FastModeReport& fast = result.fast;
  nlohmann::json check = {{"voxels", fast.check_voxels}, {"mode", mode_name(result.mode)}};
  check["coarsest_stride"] = fast.coarsest_stride;
  check["surface_block"] = req.path_safety.fast.surface_block;
  check["ray_stride"] = fast.ray_stride;
  check["rays_per_voxel"] = fast.surface_points > 0 ? fast.surface_points : result.surface_points;
  check["points_computed_exactly"] = fast.evaluated_points;
  check["voxels_interpolated"] = fast.interpolated_voxels;
  check["points_per_level"] = points_per_level_json(result);
  for (int v = 0; v < kernels::kValueCount; ++v) {
    if (!(result.values & (1u << v))) continue;
    check[value_name(1u << v)] = {{"relative_l2", fast.check_relative_l2[size_t(v)]},
                                  {"class_agreement", fast.check_class_agreement[size_t(v)]}};
  }
  return check;
}

// Step 5: plan.json from the request, the blocking, the result and what was written.
nlohmann::json coverage_json(const CoverageReport& c) {
  nlohmann::json beyond;
  for (size_t side = 0; side < c.reach.beyond_mm.size(); ++side) {
    beyond[ScanReach::side_names()[side]] = c.reach.beyond_mm[side];
  }
  return {{"scan_grids", c.grids},
          {"roi_voxels", c.roi_voxels},
          {"unknown_voxels", c.unknown_voxels},
          {"unknown_share", c.unknown_share},
          {"cropped_voxels", c.cropped_voxels},
          {"roi_beyond_scan_mm", beyond},
          {"tumor_voxels_at_scan_edge", c.tumor_edge_voxels},
          {"unknown",
           "inside the region of interest but outside the scanned volume (the intersection of "
           "the anatomy inputs' grids): no path safety value (NaN), 2 in roi.nii.gz; never safe"}};
}

// Says when the scan does not show all of the region or touches the tumor.
void warn_about_coverage(const CoverageReport& c, bool cropped) {
  const std::string sides = c.reach.describe();
  if (!sides.empty()) {
    if (cropped) {
      spdlog::warn("the region of interest reaches beyond the scan ({}): {} voxels left out "
                   "(--crop-to-scan)", sides, c.cropped_voxels);
    } else {
      spdlog::warn("the region of interest reaches beyond the scan ({}): {:.1f} % of it is "
                   "UNKNOWN (no path safety; never shown as safe)", sides, 100.0 * c.unknown_share);
    }
  }
  if (c.tumor_edge_voxels > 0) {
    spdlog::warn("the tumor touches the edge of the scan ({} voxels): paths beyond that edge are "
                 "unknown", c.tumor_edge_voxels);
  }
}

nlohmann::json plan_json(const PlanRequest& req, const PlanInputs& in,
                         const PathSafetyResult& result, const Written& written) {
  nlohmann::json plan;
  plan["crepuscular_version"] = CREPUSCULAR_VERSION;
  plan["created_utc"] = utc_now_iso8601();
  const std::vector<std::string> labels = label_files(req.labels);
  nlohmann::json all_labels = nlohmann::json::array();
  for (const auto& f : labels) all_labels.push_back(input_json(f, req.out_dir));
  plan["inputs"] = {
      // The first label map: the body outline and structure names of slices, evaluate, guide.
      {"labels", labels.empty() ? nlohmann::json(nullptr) : input_json(labels.front(), req.out_dir)},
      {"label_maps", all_labels},
      {"tumor", input_json(tumor_file(req.tumor), req.out_dir)},
      {"vulnerability", input_json(req.vulnerability, req.out_dir)},
      {"preset", req.preset.empty() ? nlohmann::json(nullptr) : nlohmann::json(req.preset)},
      {"ct", input_json(req.ct, req.out_dir)},
      {"blocking", input_json(req.blocking, req.out_dir)}};
  plan["preprocessing"] = in.preprocessing;
  plan["tumor_source"] = in.tumor_source;
  plan["parameters"] = parameters_json(req, result);
  if (result.mode == Mode::kFast) plan["fast_mode_vs_exact"] = fast_check_json(req, result);
  const Eigen::Vector3d& c = result.grid.centre;
  plan["grid"] = geometry_json(result.grid.geometry);
  plan["grid"]["centre_lps_mm"] = {c.x(), c.y(), c.z()};
  plan["grid"]["roi_voxels"] = result.grid.roi_voxels;
  plan["grid"]["outside_roi"] = "NaN (not computed), 0 in roi.nii.gz";
  plan["tumor"] = {{"voxels", result.tumor_voxels},
                   {"surface_points", result.surface_points},
                   {"resampled_to_mm",
                    result.tumor_resampled ? nlohmann::json(result.tumor_spacing_mm) : nlohmann::json()},
                   {"mask_surface_points", result.mask_surface_points},
                   {"s2_mm2", result.s2_mm2},
                   {"centroid_lps_mm", {c.x(), c.y(), c.z()}}};
  plan["blocking_grid"] = geometry_json(in.blocking.geometry());
  plan["rays"] = result.rays;
  plan["classes"] = written.classes;
  plan["statistics"] = written.statistics;
  return plan;
}

// --- Breathing (docs/ARCHITECTURE.md §10) -----------------------------------------------------

// The phases' inputs and the request of each (the plan's own request with its files).
struct PhaseInputs {
  PlanPhase phase;
  PlanRequest request;
  PlanInputs inputs;
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
};

// Each phase's request: the plan's own with the phase's files.
std::vector<PhaseInputs> phase_requests(const PlanRequest& req, const PhaseList& list) {
  std::vector<PhaseInputs> out(list.phases.size());
  for (size_t k = 0; k < out.size(); ++k) {
    const PlanPhase& phase = list.phases[k];
    PhaseInputs& p = out[k];
    p.phase = phase;
    p.request = req;
    p.request.phases.clear();
    p.request.per_phase = false;
    p.request.labels = phase.labels;
    p.request.tumor = phase.tumor;
    p.request.ct = phase.ct;
    if (req.vulnerability.empty() && req.preset.empty()) {
      p.request.vulnerability = list.vulnerability;
      p.request.preset = list.vulnerability.empty() ? list.preset : "";
    }
    check_request(p.request);
  }
  return out;
}

// Reader threads for the phases' files: a phase's files decompress on one core each, its
// preprocessing takes the cores it is given, so a few phases at a time (one per four cores, each
// with its share of the cores) keep a large machine busy; two cores read one phase at a time.
// `read(k)` reads phase k; phases are taken in `order`. Every phase is answered in `ready`, an
// error as itself; after an error the phases not yet taken are answered as skipped, unread.
class PhaseReaders {
 public:
  PhaseReaders(std::vector<size_t> order, std::function<void(size_t)> read)
      : order_(std::move(order)), read_(std::move(read)),
        errors_(order_.empty() ? 0 : *std::max_element(order_.begin(), order_.end()) + 1),
        promises_(errors_.size()) {
    for (auto& p : promises_) ready_.push_back(p.get_future().share());
    cores_ = std::max(1, omp_get_max_threads());
    const size_t readers = std::min(order_.size(), size_t(std::max(1, cores_ / 4)));
    for (size_t r = 0; r < readers; ++r) {
      threads_.emplace_back([this, readers] {
        omp_set_num_threads(std::max(1, cores_ / int(readers)));
        run();
      });
    }
  }
  PhaseReaders(const PhaseReaders&) = delete;
  PhaseReaders& operator=(const PhaseReaders&) = delete;
  ~PhaseReaders() { join(); }

  size_t readers() const { return threads_.size(); }
  // Returns when phase k is read; throws the first failing phase's error (in the list's order,
  // once every reader has stopped) if any phase failed.
  void wait(size_t k) {
    ready_[k].wait();
    if (failed_) rethrow_first();
  }
  // Returns when phase k is read (true) or has failed (false); unlike `wait`, it neither joins
  // the readers nor throws, so another thread may call it beside `wait`.
  bool read(size_t k) const {
    try {
      ready_[k].get();
      return true;
    } catch (...) {
      return false;
    }
  }
  // The phases not yet taken are not read (after an error elsewhere).
  void stop() { stopped_ = true; }
  // Every phase read (or an error, as in `wait`).
  void wait_all() {
    join();
    if (failed_) rethrow_first();
  }

 private:
  void run() {
    for (size_t at = next_++; at < order_.size(); at = next_++) {
      const size_t k = order_[at];
      if (failed_ || stopped_) {
        promises_[k].set_exception(std::make_exception_ptr(Error("not read: the plan failed")));
        continue;
      }
      try {
        read_(k);
        promises_[k].set_value();
      } catch (...) {
        errors_[k] = std::current_exception();
        failed_ = true;
        promises_[k].set_exception(errors_[k]);
      }
    }
  }
  // Any thread may join the readers, several at once (a failing phase's waiter beside the plan's
  // own unwinding): one joins, the others wait for it.
  void join() {
    const std::lock_guard<std::mutex> lock(join_lock_);
    for (auto& t : threads_) {
      if (t.joinable()) t.join();
    }
  }
  void rethrow_first() {
    join();
    for (const auto& e : errors_) {
      if (e) std::rethrow_exception(e);
    }
  }

  std::vector<size_t> order_;
  std::function<void(size_t)> read_;
  std::vector<std::exception_ptr> errors_;
  std::vector<std::promise<void>> promises_;
  std::vector<std::shared_future<void>> ready_;
  std::atomic<size_t> next_{0};
  std::atomic<bool> failed_{false}, stopped_{false};
  int cores_ = 1;
  std::mutex join_lock_;
  std::vector<std::thread> threads_;
};

std::vector<size_t> listed_order(size_t n) {
  std::vector<size_t> order(n);
  for (size_t k = 0; k < n; ++k) order[k] = k;
  return order;
}

// A phase's tumor, its lesion chosen, and its centroid.
void read_phase_tumor(PhaseInputs& p) {
  read_plan_tumor(p.request, p.inputs);
  p.centroid = tumor_centroid(p.inputs.tumor, tumor_file(p.phase.tumor));
}

// A phase's input file as plan.json records it: a frame of a 4D input as that file.
std::string recorded_file(const PlanPhase& phase, const std::string& f) {
  const auto four_d = phase.frame_of.find(f);
  return four_d == phase.frame_of.end() ? f : four_d->second;
}

// A phase's blocking volume. Only the first phase's label map is used again (the plan's own
// files, area safety's skin); the others would hold 4 bytes of every voxel to the end.
void read_phase_blocking(PhaseInputs& p, size_t k) {
  read_plan_blocking(p.request, p.inputs);
  if (k > 0) p.inputs.labels = {};
}

// A phase's input files checksummed ahead of its entry in plan.json (file_checksum keeps them):
// the last phase's finish is on the plan's way to its end. A file that cannot be read is
// reported where the entry is written.
void checksum_phase_inputs(const PlanPhase& phase) {
  std::vector<std::string> files = label_files(phase.labels);
  files.push_back(tumor_file(phase.tumor));
  files.push_back(phase.ct);
  for (const std::string& f : files) {
    if (f.empty()) continue;
    try {
      file_checksum(recorded_file(phase, f));
    } catch (const Error&) {
    }
  }
}

// Every phase's inputs, side by side. An error is the first failing phase's, in the list's order.
std::vector<PhaseInputs> read_phases(const PlanRequest& req, const PhaseList& list) {
  std::vector<PhaseInputs> out = phase_requests(req, list);
  std::atomic<size_t> done{0};
  {
    PhaseReaders readers(listed_order(out.size()), [&](size_t k) {
      PhaseInputs& p = out[k];
      const auto t_read = Clock::now();
      p.inputs = read_plan_inputs(p.request);
      p.inputs.seconds["inputs"] = seconds_since(t_read);
      if (k > 0) p.inputs.labels = {};
      p.centroid = tumor_centroid(p.inputs.tumor, tumor_file(p.phase.tumor));
      spdlog::info("breathing: read {} ({} of {} phases)", p.phase.name, ++done, out.size());
    });
    spdlog::info("breathing: reading {} phases, {} at a time", out.size(), readers.readers());
    readers.wait_all();  // the readers set their own threads' cores, not this thread's
  }
  return out;
}

// One grid for all phases: centred on the mean tumor centroid (the first phase's plus the mean
// difference, so identical phases give the single-phase centre exactly), spacing and radius the
// single-phase defaults taken over all phases.
PathSafetyOptions shared_grid(const PlanRequest& req, const std::vector<PhaseInputs>& phases) {
  PathSafetyOptions ps = req.path_safety;
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  for (const PhaseInputs& p : phases) sum += p.centroid - phases.front().centroid;
  const Eigen::Vector3d centre = phases.front().centroid + sum / double(phases.size());
  ps.centre_lps_mm = centre;
  if (ps.spacing_mm == 0.0) {
    double h = INFINITY;
    for (const PhaseInputs& p : phases) {
      h = std::min({h, p.inputs.blocking.geometry().spacing.minCoeff(),
                    p.inputs.tumor.geometry().spacing.minCoeff()});
    }
    ps.spacing_mm = h;
  }
  if (ps.radius_mm == 0.0) {
    double r = 0.0;
    for (const PhaseInputs& p : phases) {
      r = std::max(r, farthest_blocking_mm(p.inputs.blocking, centre));
    }
    if (r == 0.0) {
      throw Error("breathing: no phase has a voxel with blocking > 0, so the region of interest "
                  "is empty; give a region of interest radius");
    }
    ps.radius_mm = r;
  }
  return ps;
}

// The order in which the phases are computed: the first listed (the reference), then each time
// the phase whose tumor centroid lies farthest from those of the phases chosen so far, so that
// the ends of the motion come first and the phases between them find most of their class
// boundaries decided by the combination already (PathSafetyOptions::combined_so_far). Ties go
// to the phase listed first.
std::vector<size_t> phase_order(const std::vector<PhaseInputs>& phases) {
  std::vector<size_t> order{0};
  std::vector<double> nearest(phases.size(), INFINITY);
  std::vector<bool> chosen(phases.size(), false);
  chosen[0] = phases.size() > 0;
  while (order.size() < phases.size()) {
    size_t best = 0;
    double farthest = -1.0;
    for (size_t k = 0; k < phases.size(); ++k) {
      if (chosen[k]) continue;
      nearest[k] = std::min(nearest[k], (phases[k].centroid - phases[order.back()].centroid).norm());
      if (nearest[k] > farthest) {
        farthest = nearest[k];
        best = k;
      }
    }
    chosen[best] = true;
    order.push_back(best);
  }
  return order;
}

nlohmann::json point_json(const Eigen::Vector3d& p) { return {p.x(), p.y(), p.z()}; }

// `req`'s phases come from `list` (phases.json, or the frames of 4D inputs).
nlohmann::json run_plan_phases(const PlanRequest& req, const PhaseList& list,
                               Clock::time_point t_start) {
  trace::event("plan_begin", 0, -1);
  StagedDirectory out(req.out_dir);
  nlohmann::json timings;
  auto t = Clock::now();
  // With the region's spacing and radius given, the grid needs only the tumors' centroids: every
  // tumor is read first, then the blocking volumes beside the computation, in the order the
  // phases are computed (a phase starts once its own are read). Otherwise every input first.
  const bool stream = req.path_safety.spacing_mm > 0.0 && req.path_safety.radius_mm > 0.0;
  std::vector<PhaseInputs> phases;
  std::future<void> first_blocking;  // the first phase's (always computed first), beside the tumors
  if (stream) {
    phases = phase_requests(req, list);
    first_blocking =
        std::async(std::launch::async, [&phases] { read_phase_blocking(phases[0], 0); });
    spdlog::info("breathing: reading {} tumors", phases.size());
    try {
      PhaseReaders tumors(listed_order(phases.size()),
                          [&](size_t k) { read_phase_tumor(phases[k]); });
      tumors.wait_all();
      trace::event("tumors_read", 0, -1);
    } catch (...) {
      first_blocking.get();  // its error first: the first phase's, and a blocking's before a tumor's
      throw;
    }
  } else {
    phases = read_phases(req, list);
  }
  timings["read_and_preprocess_s"] = seconds_since(t);

  PlanRequest shared = req;
  shared.path_safety = shared_grid(req, phases);
  const Eigen::Vector3d centre = *shared.path_safety.centre_lps_mm;
  spdlog::info("breathing: {} phases on one grid centred on the mean tumor centroid ({:.1f}, "
               "{:.1f}, {:.1f}) LPS mm, radius {:.1f} mm, spacing {} mm",
               phases.size(), centre.x(), centre.y(), centre.z(), shared.path_safety.radius_mm,
               shared.path_safety.spacing_mm);
  PhaseCombiner combiner;
  std::vector<nlohmann::json> phase_entries(phases.size());
  CoverageReport first_coverage;
  const std::vector<size_t> order = phase_order(phases);
  std::unique_ptr<PhaseReaders> blocking_reads;  // declared after `phases`: joined before they go
  if (stream) {
    // The first phase's blocking volume (read beside the tumors) on the cores alone, then the
    // others': read beside it, they shared the cores with it and held up the first rays, while
    // none of them is needed before the first phase has sampled its coarsest level.
    first_blocking.get();
    std::shared_ptr<std::atomic<size_t>> done = std::make_shared<std::atomic<size_t>>(0);
    blocking_reads = std::make_unique<PhaseReaders>(
        std::vector<size_t>(order.begin() + 1, order.end()), [&phases, done](size_t k) {
          read_phase_blocking(phases[k], k);
          spdlog::info("breathing: read {} ({} of {} later phases)", phases[k].phase.name,
                       ++*done, phases.size() - 1);
        });
  }
  // The later phases' inputs checksummed as they are read, on one thread beside the computation
  // (not in the readers, where they would hold back each phase's start). Declared after
  // `blocking_reads`: joined before it goes.
  std::future<void> checksums;
  if (blocking_reads) {
    checksums = std::async(std::launch::async, [&phases, &order, &blocking_reads] {
      for (size_t at = 1; at < order.size(); ++at) {
        if (!blocking_reads->read(order[at])) return;  // the plan fails with the reader's error
        checksum_phase_inputs(phases[order[at]].phase);
      }
    });
  }
  // Fast mode leaves refinement out where a phase cannot change the combination's class
  // (combination.hpp), unless every phase's own volumes are written.
  const bool leave_to_combination = req.path_safety.mode == Mode::kFast && !req.per_phase;
  // Phases computed at once: on a GPU three, so that the phases' host steps (preparation, the
  // sampler's steps between launches) run beside the others' rays; one on the cores, where they
  // would share them.
  const int at_once = req.phases_at_once > 0
                          ? req.phases_at_once
                          : (gpus_for(shared.path_safety.device) > 0 ? 3 : 1);
  const PhaseSchedule schedule = schedule_phases(int(phases.size()), at_once, leave_to_combination);
  std::vector<std::string> step_names;
  for (const size_t k : order) step_names.push_back(phases[k].phase.name);
  spdlog::info("breathing: {} at once; the schedule (steps in the order computed):\n{}",
               schedule.at_once, schedule.table(step_names));
  std::vector<Clock::time_point> t_phase(phases.size());
  nlohmann::json outputs;
  std::vector<std::future<void>> input_writes;
  StepHooks hooks;
  hooks.compute = [&](size_t at, const CombinationSource& combination,
                      const std::function<void()>& before_sampling) {
    const size_t k = order[at];
    const PhaseInputs& p = phases[k];
    spdlog::info("breathing: path safety of {} ({} of {})", p.phase.name, at + 1,
                 phases.size());
    t_phase[at] = Clock::now();
    // Its blocking volume: the first phase's is read before the later ones' reads start, those
    // beside the computation.
    if (k > 0 && blocking_reads) blocking_reads->wait(k);
    PlanRequest phase_request = p.request;
    phase_request.path_safety = shared.path_safety;
    if (!phase_request.path_safety.progress) {  // named: two phases may run at once
      phase_request.path_safety.progress =
          progress_in_steps("breathing: path safety of " + p.phase.name);
    }
    phase_request.path_safety.combination = combination;
    phase_request.path_safety.before_sampling = before_sampling;
    return compute(phase_request, p.inputs);
  };
  // The plan's own inputs (the first phase's blocking volume and tumor) written once the first
  // phase has computed, beside the later phases; a later phase's blocking volume is done with
  // then (its finish needs its tumor and scan).
  hooks.computed = [&](size_t at) {
    if (at == 0) input_writes = write_inputs(out, phases.front().inputs, outputs);
    if (order[at] > 0) phases[order[at]].inputs.blocking = {};
  };
  hooks.cover = [&](size_t at, PathSafetyResult& result) {
    const size_t k = order[at];
    CoverageReport coverage;
    Volume<uint8_t> region = apply_scan_coverage(result, phases[k].inputs.coverage,
                                                 phases[k].inputs.tumor, {req.crop_to_scan},
                                                 &coverage);
    if (k == 0) first_coverage = coverage;
    warn_about_coverage(coverage, req.crop_to_scan);
    phase_entries[k]["unknown_voxels"] = coverage.unknown_voxels;
    return region;
  };
  hooks.report = [&](size_t at, PathSafetyResult& result) {
    const size_t k = order[at];
    const PhaseInputs& p = phases[k];
    // The first phase's result check (its statistics come from the check's pass). A later phase
    // that left refinement to the phases before it has approximate values there, so its result
    // check would tell little (the combination's is the plan's): its statistics alone.
    if (at == 0 || !leave_to_combination) finish_fast_check(result);
    trace::event("checked", 0, int(at));
    nlohmann::json& entry = phase_entries[k];
    entry["name"] = p.phase.name;
    // A frame of a 4D input is recorded as that file (the frame is the phase's).
    const auto recorded = [&](const std::string& f) {
      return input_json(recorded_file(p.phase, f), req.out_dir);
    };
    nlohmann::json labels = nlohmann::json::array();
    for (const auto& f : label_files(p.phase.labels)) labels.push_back(recorded(f));
    entry["inputs"] = {{"label_maps", labels},
                       {"tumor", recorded(tumor_file(p.phase.tumor))},
                       {"ct", recorded(p.phase.ct)}};
    if (p.phase.frame >= 0) entry["inputs"]["frame"] = p.phase.frame;
    entry["tumor_centroid_lps_mm"] = point_json(p.centroid);
    entry["tumor_voxels"] = result.tumor_voxels;
    entry["device"] = result.device;
    entry["computed_as"] = at + 1;
    if (result.mode == Mode::kFast) {
      entry["points_computed_exactly"] = result.fast.evaluated_points;
      entry["points_per_level"] = points_per_level_json(result);
      if (leave_to_combination && at > 0) {
        entry["left_to_earlier_phases"] = {{"cells", result.fast.cells_left_to_combination},
                                           {"finest_points", result.fast.points_left_to_combination}};
      }
    }
    entry["read_s"] = p.inputs.seconds;
    entry["path_safety_s"] = result.seconds;
    for (const auto& [step, seconds] : result.phases) entry["path_safety_phases"][step] = seconds;
    for (int v = 0; v < kernels::kValueCount; ++v) {
      const unsigned bit = 1u << v;
      if (!(result.values & bit)) continue;
      // Taken with the classes by the check's comparison, where it ran.
      entry["statistics"][value_name(bit)] = statistics_json(statistics_of(result, bit));
      if (req.per_phase) {
        const std::string file = std::string("path_safety_") + value_name(bit) + "_" +
                                 p.phase.name + ".nii.gz";
        write_volume(result.volumes[size_t(v)], out.file(file));
        entry["outputs"][value_name(bit)] = file;
      }
    }
    entry["seconds"] = seconds_since(t_phase[at]);
  };
  hooks.failed = [&] {
    if (blocking_reads) blocking_reads->stop();
  };
  t = Clock::now();
  // Declared after `out`: its threads are joined before a failed plan's folder goes.
  ScheduleRun run(schedule, combiner, hooks);
  try {
    run.run();
  } catch (...) {
    for (auto& f : input_writes) {
      if (f.valid()) f.wait();  // before the staged folder goes
    }
    throw;
  }
  timings["path_safety_s"] = seconds_since(t);
  trace::event("path_safety_end", 0, -1);
  PathSafetyResult& combined = combiner.combined();
  const Volume<uint8_t>& region = combiner.region();
  combined.pending_check = nullptr;
  combined.fast.check_voxels = 0;

  // The plan's own files: the combination, with the first phase's blocking, tumor and labels.
  const PhaseInputs& first = phases.front();
  t = Clock::now();
  // Area safety beside the writes, as a single phase's.
  nlohmann::json area_safety;
  AreaSafetyGeometry geometry;
  std::future<double> area = area_safety_beside_writes(req, first.inputs.tumor, combined, out,
                                                       region, area_safety, geometry);
  // Fast mode's check of the combination (every phase's exact values at the check's voxels,
  // combined, against the combined volumes) beside area safety: taken before it, its classes'
  // passes would hold area safety back at the plan's end.
  if (const CheckSample* check = combiner.check_sample()) {
    spdlog::info("breathing: the combination against the phases' exact values combined");
    compare_with_check_sample(*check, combined.values, combined);
  }
  // The share of the region whose class changes over the cycle, on every core while the
  // volumes are written (it needs their classes, which the writes take).
  std::array<double, kernels::kValueCount> class_change{};
  const auto class_change_beside = [&] {
    // Every phase's other extreme, taken after its fold (a failed finish fails its turn too).
    run.wait_extremes();
    trace::event("last_extreme", 0, -1);
    std::array<const SafetyClasses*, kernels::kValueCount> classes{};
    for (int v = 0; v < kernels::kValueCount; ++v) {
      if (combined.values & (1u << v)) classes[size_t(v)] = &classes_of(combined, 1u << v);
    }
    class_change = combiner.class_change_shares(classes);
    trace::event("class_change", 0, -1);
  };
  Written written;
  try {
    written = write_volumes(out, combined, region, std::move(input_writes), outputs,
                            class_change_beside);
  } catch (...) {
    if (area.valid()) area.wait();  // before the staged folder goes
    throw;
  }
  timings["write_s"] = seconds_since(t);
  trace::event("written", 0, -1);
  nlohmann::json breathing;
  if (!list.file.empty()) {
    breathing["phase_list"] = input_json(list.file, req.out_dir);
  } else {
    breathing["phase_list"] = nullptr;
    breathing["phases_from"] = "4D inputs: phase K is frame K of each 4D file (the 4th axis)";
  }
  breathing["combination"] =
      "one output grid for all phases, centred on the mean tumor centroid; per voxel svv the "
      "minimum over the phases, isbv, ivbv, bvv the maximum: safe only if safe in every phase; "
      "unknown in any phase: unknown";
  breathing["reference_phase"] = first.phase.name;
  breathing["reference"] =
      "blocking, tumor and label map of the plan are the reference phase's (the first listed)";
  run.wait_reports();  // the phases' own statistics, taken beside the writes
  nlohmann::json phase_list = nlohmann::json::array();
  for (nlohmann::json& e : phase_entries) phase_list.push_back(std::move(e));
  breathing["phases"] = phase_list;
  for (int v = 0; v < kernels::kValueCount; ++v) {
    const unsigned bit = 1u << v;
    if (!(combined.values & bit)) continue;
    const double share = class_change[size_t(v)];
    breathing["class_change_share"][value_name(bit)] = share;
    spdlog::info("breathing: {} class changes over the cycle in {:.1f} % of the known region",
                 value_name(bit), 100.0 * share);
  }
  breathing["class_change_rule"] =
      "share of the computed voxels whose class (the combined plan's thresholds) is not the same "
      "in every phase";
  trace::event("finishes_and_area", 0, -1);
  if (area.valid()) {
    timings["area_safety_s"] = area.get();  // rethrows its failure
    trace::event("area_done", 0, -1);
    written.outputs["area_safety"] = "area_safety.vtk";
    const std::string value = area_safety["value"].get<std::string>();
    const std::vector<RegionTrajectory> planned = region_trajectories(
        geometry, combined.grid.centre, first.inputs.labels,
        combined.volumes[size_t(kernels::value_slot(parse_value_set(value)))],
        combined.grid.radius_mm);
    write_text_file(out.file("trajectories.mrk.json"),
                    trajectories_markups_json(planned, value).dump(2) + "\n");
    write_text_file(out.file("entries.mrk.json"),
                    entries_markups_json(planned, value).dump(2) + "\n");
    written.outputs["trajectories"] = "trajectories.mrk.json";
    written.outputs["entries"] = "entries.mrk.json";
  }
  trace::event("trajectories", 0, -1);
  timings["total_s"] = seconds_since(t_start);

  // Unknown in the combination: in any phase.
  CoverageReport coverage = first_coverage;
  int64_t unknown = 0;
#pragma omp parallel for schedule(static) reduction(+ : unknown)
  for (int64_t i = 0; i < region.voxel_count(); ++i) unknown += region[i] == kRegionUnknown ? 1 : 0;
  coverage.unknown_voxels = unknown;
  coverage.unknown_share =
      coverage.roi_voxels ? double(coverage.unknown_voxels) / double(coverage.roi_voxels) : 0.0;
  nlohmann::json plan = plan_json(first.request, first.inputs, combined, written);
  plan["scan_coverage"] = coverage_json(coverage);
  if (!area_safety.is_null()) plan["area_safety"] = area_safety;
  plan["breathing"] = breathing;
  plan["outputs"] = written.outputs;
  plan["timings"] = timings;
  record_final_paths(plan);
  write_text_file(out.file("plan.json"), plan.dump(2) + "\n");
  trace::event("plan_json", 0, -1);
  out.commit();
  spdlog::info("plan over {} breathing phases written to {} ({:.1f} s)", phases.size(),
               req.out_dir, seconds_since(t_start));
  trace::event("plan_end", 0, -1);
  return plan;
}

// The phase count of 4D inputs (label maps, tumor, CT with phases along the 4th axis): 1 when
// none is 4D. Throws Error when 4D inputs disagree on it, or a blocking volume is 4D.
int four_d_phases(const PlanRequest& req, std::vector<std::pair<std::string, int>>& frames) {
  std::vector<std::string> files = label_files(req.labels);
  if (!req.tumor.empty()) files.push_back(tumor_file(req.tumor));
  if (!req.ct.empty()) files.push_back(req.ct);
  int phases = 1;
  std::string first;
  for (const std::string& f : files) {
    if (!std::filesystem::exists(f)) continue;  // check_request names it
    const int n = volume_frames(f);
    frames.emplace_back(f, n);
    if (n <= 1) continue;
    if (phases > 1 && n != phases) {
      throw Error("plan: " + f + " holds " + std::to_string(n) + " phases (4th axis), " + first +
                  " holds " + std::to_string(phases) + "; 4D inputs must have the same phases");
    }
    phases = n;
    first = f;
  }
  if (phases > 1 && !req.blocking.empty()) {
    throw Error("plan: 4D inputs with a ready blocking volume are not supported; give the label "
                "maps of every phase instead");
  }
  return phases;
}

// The frames of 4D inputs as phases: each 4D file is split into 3D files in `folder` (a staged
// folder this run makes and removes), 3D inputs serve every phase.
PhaseList four_d_phase_list(const PlanRequest& req, int phases,
                            const std::vector<std::pair<std::string, int>>& frames,
                            const StagedDirectory& folder) {
  PhaseList list;
  list.vulnerability = req.vulnerability;
  list.preset = req.preset;
  for (int k = 0; k < phases; ++k) {
    PlanPhase phase;
    phase.name = k < 10 ? "phase0" + std::to_string(k) : "phase" + std::to_string(k);
    phase.frame = k;
    list.phases.push_back(phase);
  }
  std::map<std::string, std::vector<std::string>> split;  // 4D file -> its frames' files
  for (size_t i = 0; i < frames.size(); ++i) {
    const auto& [file, n] = frames[i];
    if (n <= 1 || split.count(file)) continue;
    std::vector<std::string> paths;
    for (int k = 0; k < phases; ++k) {
      paths.push_back(folder.file("input" + std::to_string(i) + "_" + list.phases[size_t(k)].name +
                                  ".nii"));
    }
    spdlog::info("{}: {} phases along the 4th axis", file, phases);
    split_volume_frames(file, paths);
    split[file] = paths;
  }
  // A spec FILE[:QUALIFIER] of phase k: the frame's file with the same qualifier.
  const auto of_phase = [&](const std::string& spec, const std::string& file, int k,
                            PlanPhase& phase) {
    const auto four_d = split.find(file);
    if (four_d == split.end()) return spec;
    const std::string frame = four_d->second[size_t(k)];
    phase.frame_of[frame] = file;
    return frame + spec.substr(file.size());
  };
  const std::vector<std::string> label_paths = label_files(req.labels);
  for (int k = 0; k < phases; ++k) {
    PlanPhase& phase = list.phases[size_t(k)];
    for (size_t i = 0; i < req.labels.size(); ++i) {
      phase.labels.push_back(of_phase(req.labels[i], label_paths[i], k, phase));
    }
    phase.tumor = of_phase(req.tumor, tumor_file(req.tumor), k, phase);
    phase.ct = req.ct.empty() ? std::string() : of_phase(req.ct, req.ct, k, phase);
  }
  return list;
}

}  // namespace

nlohmann::json run_plan(const PlanRequest& request) {
  PlanRequest req = request;
  req.path_safety.compare_check_later = true;  // compared while the volumes are written
  // The GPU starts while the inputs are read, and smooths the safety margin unless the CPU was
  // asked for.
  start_device_warm_up(req.path_safety.device);
  req.margin.on_gpu = req.path_safety.device != Device::kCpu;
  if (!req.phases.empty()) {
    const auto t_start = Clock::now();
    check_request(req);
    return run_plan_phases(req, read_phase_list(req.phases), t_start);
  }
  std::vector<std::pair<std::string, int>> frames;
  if (const int phases = four_d_phases(req, frames); phases > 1) {
    const auto t_start = Clock::now();
    if (req.out_dir.empty()) throw Error("plan: an output folder is required");
    StagedDirectory folder(req.out_dir + ".4d-frames");  // never committed: removed at the end
    const PhaseList list = four_d_phase_list(req, phases, frames, folder);
    PlanRequest phased = req;
    phased.labels.clear();
    phased.tumor.clear();
    phased.ct.clear();
    return run_plan_phases(phased, list, t_start);
  }
  const auto t_start = Clock::now();
  check_request(req);
  // Staged first: a failure below removes it and leaves no plan behind.
  StagedDirectory out(req.out_dir);
  nlohmann::json timings;

  auto t = Clock::now();
  const PlanInputs in = read_plan_inputs(req);
  timings["read_and_preprocess_s"] = seconds_since(t);
  timings["read_and_preprocess_phases"] = in.seconds;
  // The inputs' volumes are written while path safety runs.
  nlohmann::json input_outputs;
  std::vector<std::future<void>> input_writes = write_inputs(out, in, input_outputs);

  t = Clock::now();
  PathSafetyResult result = compute(req, in);
  timings["path_safety_s"] = seconds_since(t);
  for (const auto& [phase, seconds] : result.phases) timings["path_safety_phases"][phase] = seconds;

  // Unknown is never safe: the region outside the scan gets no value.
  t = Clock::now();
  CoverageReport coverage;
  const Volume<uint8_t> region = apply_scan_coverage(result, in.coverage, in.tumor,
                                                     {req.crop_to_scan}, &coverage);
  warn_about_coverage(coverage, req.crop_to_scan);
  timings["scan_coverage_s"] = seconds_since(t);

  // Step 4, area safety (§3.3) of the first computed value, on the cores while the volumes
  // are written.
  nlohmann::json area_safety;
  AreaSafetyGeometry geometry;
  std::future<double> area =
      area_safety_beside_writes(req, in.tumor, result, out, region, area_safety, geometry);
  t = Clock::now();
  Written written;
  try {
    written = write_volumes(out, result, region, std::move(input_writes), input_outputs);
  } catch (...) {
    if (area.valid()) area.wait();  // before the staged folder goes
    throw;
  }
  timings["write_s"] = seconds_since(t);
  // Fast mode's check against its exact values (computed after the sampling), now that the
  // volumes' classes are taken.
  finish_fast_check(result);

  if (area.valid()) {
    timings["area_safety_s"] = area.get();  // rethrows its failure
    timings["write_and_area_safety_s"] = seconds_since(t);
    written.outputs["area_safety"] = "area_safety.vtk";
    // The planned trajectories for 3D Slicer: one line per safe region, and their entries.
    const std::string value = area_safety["value"].get<std::string>();
    const std::vector<RegionTrajectory> planned = region_trajectories(
        geometry, result.grid.centre, in.labels,
        result.volumes[size_t(kernels::value_slot(parse_value_set(value)))], result.grid.radius_mm);
    write_text_file(out.file("trajectories.mrk.json"),
                    trajectories_markups_json(planned, value).dump(2) + "\n");
    write_text_file(out.file("entries.mrk.json"), entries_markups_json(planned, value).dump(2) + "\n");
    written.outputs["trajectories"] = "trajectories.mrk.json";
    written.outputs["entries"] = "entries.mrk.json";
    spdlog::info("{} planned trajectories (one per safe region whose line reaches the skin "
                 "within the region of interest): "
                 "trajectories.mrk.json, entries.mrk.json",
                 planned.size());
  }
  timings["total_s"] = seconds_since(t_start);

  nlohmann::json plan = plan_json(req, in, result, written);
  plan["scan_coverage"] = coverage_json(coverage);
  if (!area_safety.is_null()) plan["area_safety"] = area_safety;
  plan["outputs"] = written.outputs;
  plan["timings"] = timings;
  record_final_paths(plan);
  write_text_file(out.file("plan.json"), plan.dump(2) + "\n");
  out.commit();
  spdlog::info("plan written to {} ({:.1f} s)", req.out_dir, seconds_since(t_start));
  return plan;
}

}  // namespace crepuscular::pipelines
