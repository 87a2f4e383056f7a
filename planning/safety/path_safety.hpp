// Path safety (docs/ARCHITECTURE.md §4): for every point of a ball around the tumor, the four
// values that summarise all straight paths from that point to the tumor. The request, the result
// and the errors; how they are computed is internal (path_safety_scene.hpp, adaptive_sampling.hpp,
// kernels/).
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "kernels/value_bits.hpp"
#include "planning/imaging/scan_coverage.hpp"
#include "planning/imaging/volume.hpp"
#include "planning/safety/combination.hpp"
#include "planning/safety/fast_mode.hpp"
#include "planning/safety/output_grid.hpp"
#include "planning/safety/safety_classes.hpp"

namespace crepuscular::planning {

enum class Device { kAuto, kCpu, kCuda };
// exact: every ray marched (docs/ARCHITECTURE.md §4, the reference); fast: the grid sampled
// coarse to fine, exact values where the classes change and interpolated inside regions of one
// class (fast_mode.hpp).
enum class Mode { kExact, kFast };

// Parses "svv,isbv,ivbv,bvv" (any subset, any order, or "all") into PathSafetyValue bits; throws
// Error on an unknown name.
unsigned parse_value_set(const std::string& text);
// "svv", "isbv", "ivbv", "bvv" for one bit.
const char* value_name(unsigned bit);
Device parse_device(const std::string& text);
const char* device_name(Device device);
Mode parse_mode(const std::string& text);
const char* mode_name(Mode mode);

struct PathSafetyOptions {
  unsigned values = kernels::kAllValues;
  // Insignificant blocking for SVV: a path whose line integral of b is <= eps counts as clear.
  // 0.5 lets a path cross the abdominal wall (25 mm of muscle at 0.02 per mm) but not 5 mm of an
  // organ at 0.1 per mm nor more than 0.5 mm of a high-risk vessel at 1 per mm.
  double eps = 0.5;
  double spacing_mm = 0.0;  // output spacing h; 0: the smallest spacing of the inputs
  double radius_mm = 0.0;   // region of interest R; 0: distance to the farthest voxel with b > 0
  // Centre of the output grid, LPS mm; unset: the tumor centroid. Several breathing phases share
  // one grid centred on their mean tumor centroid (docs/ARCHITECTURE.md §10).
  std::optional<Eigen::Vector3d> centre_lps_mm;
  // Spacing the tumor mask is resampled to before its surface is taken (docs/ARCHITECTURE.md §4,
  // tumor sampling). kTumorSpacingAuto: the output spacing h, applied only where the mask is
  // finer than h; 0: the mask's own voxels, never resampled.
  static constexpr double kTumorSpacingAuto = -1.0;
  double tumor_spacing_mm = kTumorSpacingAuto;
  Device device = Device::kAuto;
  Mode mode = Mode::kExact;
  FastModeOptions fast;
  int threads = 0;   // CPU threads; 0: all cores
  int max_gpus = 0;  // CUDA devices to use; 0: all visible
  // Memory the output may take, bytes; 0: 80 % of the memory available now.
  uint64_t memory_limit_bytes = 0;
  // The scanned volume (docs/ARCHITECTURE.md §4): output voxels outside it are unknown and not
  // computed (left NaN). Null or empty: every voxel of the ball is computed.
  const ScanCoverage* coverage = nullptr;
  // Fast mode, breathing: the phases computed before this one, combined on this grid; refinement
  // is left out where this phase cannot change the combination's class (combination.hpp). This
  // phase's own volumes are then approximate there. Empty: every class boundary is refined.
  CombinationSource combination;
  // Fast mode's self-check, where its exact values were computed on the GPU: the comparison is
  // left to finish_fast_check (a plan takes the classes it needs while it writes the volumes).
  bool compare_check_later = false;
  // Fast mode: called once everything is prepared (the scene on the device, the volumes
  // allocated), before the first point is sampled; a plan computing phases side by side holds a
  // phase prepared ahead there until its turn. An exception it throws ends the run.
  std::function<void()> before_sampling;
  // Called from the computing thread with the fraction done (0..1), about every 2 % of the work.
  std::function<void(double)> progress;
};

// The tumor mask's centroid (mean of its voxel centres), LPS mm; Error naming `source` when the
// mask is empty.
Eigen::Vector3d tumor_centroid(const Volume<uint8_t>& tumor, const std::string& source);

// The default region of interest radius: the distance from `centre` (LPS mm) to the farthest voxel
// centre with b > 0; 0 when there is none.
double farthest_blocking_mm(const Volume<float>& blocking, const Eigen::Vector3d& centre);

// Fast mode's self-check: voxels of the region inside the scan (offsets into the output grid),
// drawn at random with a fixed seed, and their exact values (kValueCount per voxel).
struct CheckSample {
  std::vector<int64_t> offsets;
  std::vector<float> exact;
};

// What fast mode did, and how it differs from exact mode at the self-check's voxels.
struct FastModeReport {
  int coarsest_stride = 0;  // the coarsest lattice's stride (coarsest_stride)
  int ray_stride = 0;       // blocking samples per quadrature point
  // Rays cast per voxel where surface points stand for blocks of them, else 0.
  int64_t surface_points = 0;
  int64_t evaluated_points = 0;     // points computed exactly (lattice corners)
  int64_t interpolated_voxels = 0;  // ROI voxels interpolated
  // Points computed exactly per level of the sampler (stride, count; stride 0: the finest
  // level's points inside refined cells of edge 2).
  std::vector<std::pair<int, int64_t>> levels;
  // With PathSafetyOptions::combination: cells not split and finest points interpolated because
  // the phases before decide the combination's class there.
  int64_t cells_left_to_combination = 0;
  int64_t points_left_to_combination = 0;
  // The self-check: relative L2 difference and share of voxels in exact mode's class (classes by
  // default_classes of the fast volume) at `check_voxels` random voxels of the region.
  int64_t check_voxels = 0;
  std::array<double, kernels::kValueCount> check_relative_l2{};
  std::array<double, kernels::kValueCount> check_class_agreement{};
};

struct PathSafetyResult {
  OutputGrid grid;
  unsigned values = 0;
  Mode mode = Mode::kExact;
  FastModeReport fast;  // fast mode only
  // One volume per value slot (svv, isbv, ivbv, bvv); only requested ones are filled. Voxels
  // outside the region of interest are NaN (not computed).
  std::array<Volume<float>, kernels::kValueCount> volumes;
  // The scan's mask on the output grid (1 in the scan) where the inputs do not cover the whole
  // grid and path safety used it; empty otherwise (apply_scan_coverage takes it over). Path
  // safety computes no voxel outside it: those are NaN in every volume.
  Volume<uint8_t> scan_mask;
  int64_t tumor_voxels = 0;
  int64_t surface_points = 0;
  double tumor_spacing_mm = 0.0;   // spacing of the tumor grid the rays end on
  bool tumor_resampled = false;    // the mask was resampled to tumor_spacing_mm
  int64_t mask_surface_points = 0;  // surface points of the mask as given
  double s2_mm2 = 0.0;
  double gamma_mm = 0.0;
  double eps = 0.0;
  std::string device;  // "cpu" or "cuda:<name>"
  int threads = 0;
  double seconds = 0.0;
  // Where the time went (seconds), when the backend says: e.g. fast mode on CUDA.
  std::vector<std::pair<std::string, double>> phases;
  uint64_t rays = 0;  // output voxels in the ROI x surface points
  // default_classes of each volume where already taken (fast mode's self-check, the plan before
  // writing), so that the writes and area safety do not take them again; reset by whatever
  // changes a volume's values (apply_scan_coverage). classes_of() fills a missing one.
  std::array<std::optional<SafetyClasses>, kernels::kValueCount> classes;
  // The volumes' statistics, kept as the classes are (classes_of takes both in one pass).
  std::array<std::optional<ValueStatistics>, kernels::kValueCount> statistics;
  // PathSafetyOptions::compare_check_later: the check's comparison, for finish_fast_check.
  std::function<void(PathSafetyResult&)> pending_check;
  // The check's voxels and exact values (breathing combines the phases' into the combination's).
  std::shared_ptr<const CheckSample> check_sample;
  // What the computation holds on a device (the CUDA scenes), released with the result or by
  // whoever takes it: freeing device memory waits for every kernel on the device, so that the
  // sampler of a phase computed beside this one is not held up by this phase's end.
  std::shared_ptr<void> device_memory;
};

// Fast mode against a check sample's exact values: fast.check_voxels, check_relative_l2 and
// check_class_agreement (classes of the result's own volumes, classes_of), logged.
void compare_with_check_sample(const CheckSample& sample, unsigned values,
                               PathSafetyResult& result);

// Compares fast mode with the exact values of its check where that was left for later
// (check_voxels, check_relative_l2, check_class_agreement filled); nothing otherwise.
void finish_fast_check(PathSafetyResult& result);

// The region of interest's runs of `grid` (default_classes, value_statistics) for one of its
// volumes, whose voxels outside the region are NaN; null (every voxel) for a volume of another
// grid or a grid without a region.
RowRun roi_runs(const OutputGrid& grid, const Volume<float>& volume);

// default_classes of the volume of `value_bit`, taken once and kept in result.classes (over the
// region of interest's runs).
const SafetyClasses& classes_of(PathSafetyResult& result, unsigned value_bit);
// value_statistics of the volume of `value_bit`, taken once and kept in result.statistics
// (classes_of takes them in its pass).
const ValueStatistics& statistics_of(PathSafetyResult& result, unsigned value_bit);

// Computes the requested values. Checks every input first (geometry, negative or NaN blocking,
// empty tumor, tumor outside the blocking volume, memory) and throws Error before allocating.
PathSafetyResult compute_path_safety(const Volume<float>& blocking, const Volume<uint8_t>& tumor,
                                     const PathSafetyOptions& options,
                                     const std::string& blocking_source = "blocking volume",
                                     const std::string& tumor_source = "tumor mask");

// Starts the GPU's runtime on its own thread (a good part of a second), once per process, so that
// a command can overlap it with reading its inputs; compute_path_safety then finds it started.
// Nothing for Device::kCpu or a build without CUDA.
void start_device_warm_up(Device device);

// The GPUs path safety runs on for `device` (0: it runs on the cores).
int gpus_for(Device device);

// Bytes of memory available to this process now (MemAvailable), 0 when unknown.
uint64_t available_memory_bytes();

}  // namespace crepuscular::planning
