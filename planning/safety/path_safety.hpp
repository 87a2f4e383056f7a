// Path safety volume (§3.2, DESIGN.md §4): for every point of a ball around the tumor, the four
// values summarising all straight paths from that point to the tumor. CPU backend here; the CUDA
// backend (kernels/) runs the same host/device math.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "kernels/path_safety_math.hpp"
#include "planning/imaging/scan_coverage.hpp"
#include "planning/imaging/volume.hpp"
#include "planning/safety/safety_classes.hpp"

namespace crepuscular::planning {

enum class Device { kAuto, kCpu, kCuda };
// exact: every ray marched (DESIGN.md §4, the reference); fast: the grid sampled coarse to fine,
// exact values where the classes change and interpolated inside regions of one class
// (adaptive_sampling.hpp); tables: rays cast once per surface point and looked up by direction
// and distance (kernels/path_safety_fast.hpp).
enum class Mode { kExact, kFast, kTables };

// Parses "svv,isbv,ivbv,bvv" (any subset, any order, or "all") into PathSafetyValue bits; throws
// Error on an unknown name.
unsigned parse_value_set(const std::string& text);
// "svv", "isbv", "ivbv", "bvv" for one bit.
const char* value_name(unsigned bit);
Device parse_device(const std::string& text);
const char* device_name(Device device);
Mode parse_mode(const std::string& text);
const char* mode_name(Mode mode);

// Breathing: the phases computed before one, combined on its grid, as its sampler reads them.
// Per value slot (null where that value is not combined): the combination of the phases folded
// so far, and where given the volume of one more phase not folded into it yet, read through it
// (SVV the minimum of the two, the other values the maximum; NaN, unknown, where either is NaN),
// which is what its fold will write. So a phase need not wait for the fold of the phase before.
struct CombinedVolumes {
  std::array<const float*, kernels::kValueCount> folded{};
  std::array<const float*, kernels::kValueCount> pending{};
  CombinedVolumes() = default;
  CombinedVolumes(const std::array<const float*, kernels::kValueCount>& combination)  // NOLINT
      : folded(combination) {}
};

struct PathSafetyOptions {
  unsigned values = kernels::kAllValues;
  // Insignificant blocking for SVV: a path whose line integral of b is <= eps counts as clear.
  // 0.5 lets a path cross the abdominal wall (25 mm of muscle at 0.02 per mm) but not 5 mm of an
  // organ at 0.1 per mm nor more than 0.5 mm of a high-risk vessel at 1 per mm.
  double eps = 0.5;
  double spacing_mm = 0.0;  // output spacing h; 0: the smallest spacing of the inputs
  double radius_mm = 0.0;   // region of interest R; 0: distance to the farthest voxel with b > 0
  // Centre of the output grid, LPS mm; unset: the tumor centroid. Several breathing phases share
  // one grid centred on their mean tumor centroid (DESIGN.md §10).
  std::optional<Eigen::Vector3d> centre_lps_mm;
  // Spacing the tumor mask is resampled to before its surface is taken (DESIGN.md §4, tumor
  // sampling). kTumorSpacingAuto: the output spacing h, applied only where the mask is finer than
  // h; 0: the mask's own voxels, never resampled.
  static constexpr double kTumorSpacingAuto = -1.0;
  double tumor_spacing_mm = kTumorSpacingAuto;
  Device device = Device::kAuto;
  Mode mode = Mode::kExact;
  int threads = 0;  // CPU threads; 0: all cores
  int max_gpus = 0;  // CUDA devices to use; 0: all visible
  // CUDA only: sample the blocking volume through a 3D texture with hardware trilinear filtering
  // (9-bit weights) instead of float filtering in global memory (the exact definition). Exact and
  // tables mode; fast mode always samples through the texture, and this applies to its self-check.
  bool cuda_texture = false;
  // CUDA: rays walk over the samples of the tumor's box whose voxels are known to be of one kind
  // (kernels::TumorGrid::leap): the same values, fewer lookups. Off, and always on the CPU (where
  // it was slower): every sample looked up.
  bool tumor_leaps = true;
  // Fast mode: the coarsest lattice (every fast_stride-th voxel, a power of two; 0: automatic,
  // `coarsest_stride`), and how close to a class threshold a corner may lie before its cell is
  // refined (adaptive_sampling.hpp).
  int fast_stride = 0;
  double fast_svv_margin = 3.0;
  double fast_blocking_margin = 0.25;
  // Breathing: the combination's side of what a phase leaves to it, a share of the blocking
  // margin (AdaptiveOptions::combination_margin_share).
  double fast_combination_margin_share = 0.25;
  bool fast_dilate = true;  // refine the neighbours of refined coarsest cells too
  // The finest level's share of the margins (adaptive_sampling.hpp): 0, a point between two
  // computed voxels is computed only where their classes differ (bench/RESULTS.md, eleventh
  // session: 31 % fewer points, every test scene still >= 99.5 % in exact mode's class).
  double fast_finest_margin = 0.0;
  // The level above the finest point by point too (AdaptiveOptions::pointwise_halves).
  bool fast_pointwise_halves = true;
  // Fast mode: one ray per block of fast_surface_block^3 tumor voxels, cast to the block's surface
  // point nearest the mean of its surface points and counted once for each of them (1: every
  // surface point, as exact mode). Rays to the points of a block of 2 stay within about one
  // voxel of each other along their whole length, where the blocking volume is smooth (the
  // safety margin); the self-check compares with exact mode's every ray.
  int fast_surface_block = 1;
  // Fast mode: blocking samples per quadrature point along a ray (PathSafetyScene::
  // blocking_stride). 1: every sample x_k, as exact mode; 2: runs of two samples taken at their
  // midpoint, half the samples (the tumor's occupancy is still looked up at every sample);
  // 0: automatic (automatic_ray_stride). The self-check compares with exact mode's every sample.
  int fast_ray_stride = 0;
  // Tables mode: octahedral direction cells per (distance / spacing), i.e. the angular sampling of
  // the rays cast from each surface point (cost ~ square). 2: neighbouring rays about 1.75
  // voxels apart at the far edge; the rays between cells that disagree are marched exactly, so
  // a finer table buys speed only where few rays graze structures.
  double fast_angular = 2.0;
  // Tables mode: a ray whose four neighbouring direction cells differ in line integral by more
  // than fast_refine + fast_refine_relative x its value (or on whether t is seen, or on the side
  // of eps) is marched exactly (fast_refine < 0: never).
  double fast_refine = 0.01;
  double fast_refine_relative = 0.03;
  // Fast and tables mode: ROI voxels recomputed exactly afterwards to report the difference (0: none).
  int fast_check_voxels = 1000;
  // Fast mode on the GPU: the check's exact values are computed right after the sampling, and
  // their comparison with the fast volumes is left to finish_fast_check (the classes it needs are
  // passes over each volume, which the plan takes anyway while it writes them).
  bool fast_check_later = false;
  // Fast mode on the GPU: the sampler's host steps beside the GPU's work
  // (AdaptiveOptions::overlap_host_steps); off only to measure what it saves.
  bool fast_overlap_host = true;
  // Tables mode on CUDA: direction tables cast per batch (0: as many as fit, at most 16).
  int cuda_fast_slots = 0;
  // Memory the output may take, bytes; 0: 80 % of the memory available now.
  uint64_t memory_limit_bytes = 0;
  // The scanned volume (DESIGN.md §4): output voxels outside it are unknown and not computed
  // (left NaN) in exact and fast mode. Null or empty: every voxel of the ball is computed.
  const ScanCoverage* coverage = nullptr;
  // Fast mode, breathing: the phases computed before this one, combined on this grid
  // (CombinedVolumes), asked for once the coarsest level is computed: refinement is then left
  // out where this phase cannot change the combination's class
  // (AdaptiveOptions::combined_so_far). Null: every class boundary of this phase is refined.
  std::function<CombinedVolumes()> combined_so_far;
  // A later combination, asked for before the decisions of level `newer_from_level`
  // (AdaptiveOptions::combined_newer). Null: combined_so_far throughout.
  std::function<CombinedVolumes()> combined_newer;
  int newer_from_level = 1;
  // Fast mode: called once everything is prepared (the scene on the device, the volumes
  // allocated), before the first point is sampled; a plan computing phases side by side holds a
  // phase prepared ahead there until its turn. An exception it throws ends the run.
  std::function<void()> before_sampling;
  // Called from the computing thread with the fraction done (0..1), about every 2 % of the work.
  std::function<void(double)> progress;
};

// Tumor surface for the rays: surface voxels with centres and outward normals.
struct TumorSurface {
  std::vector<kernels::SurfacePoint<double>> points;
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();  // mean of tumor voxel centres, LPS mm
  int64_t tumor_voxels = 0;
  double s2_mm2 = 0.0;  // (voxel volume)^(2/3)
  int lo[3] = {0, 0, 0}, hi[3] = {0, 0, 0};  // index bounding box of the tumor voxels
};

// Extracts surface voxels (6-neighbourhood) and their normals: the negative gradient of the mask
// smoothed with a Gaussian of sigma = 1 voxel. Throws Error when the mask is empty.
TumorSurface extract_tumor_surface(const Volume<uint8_t>& tumor, const std::string& source);

// Output grid Θ of DESIGN.md §4: isotropic spacing h, axes of the blocking volume, centre voxel on
// the tumor centroid, 2 ceil(R/h) + 1 voxels per axis. Throws Error when the region of interest
// lies inside the tumor (a ball around a centre in the tumor that does not reach its surface).
struct OutputGrid {
  ImageGeometry geometry;
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  double radius_mm = 0.0;
  int64_t half = 0;        // index of the centre voxel along each axis
  int64_t max_sq = 0;      // ROI: (i-half)^2 + (j-half)^2 + (k-half)^2 <= max_sq
  int64_t roi_voxels = 0;  // voxels inside the ball

  // The ROI's voxels in row (j, k) lie at |i - half| <= the returned width; -1: none.
  int64_t roi_half_width(int64_t j, int64_t k) const {
    const int64_t rest = max_sq - (j - half) * (j - half) - (k - half) * (k - half);
    if (rest < 0) return -1;
    int64_t w = int64_t(std::sqrt(double(rest)));
    while (w * w > rest) --w;
    while ((w + 1) * (w + 1) <= rest) ++w;
    return w;
  }
  // The ROI's voxels of row (j, k) within the grid: i from first to last; none: first > last.
  std::pair<int64_t, int64_t> roi_run(int64_t j, int64_t k) const {
    const int64_t w = roi_half_width(j, k);
    if (w < 0) return {geometry.dims[0], -1};
    return {std::max<int64_t>(0, half - w), std::min<int64_t>(geometry.dims[0] - 1, half + w)};
  }
  bool in_roi(int64_t i, int64_t j, int64_t k) const {
    const int64_t di = i - half, dj = j - half, dk = k - half;
    return di * di + dj * dj + dk * dk <= max_sq;
  }
};
OutputGrid make_output_grid(const Volume<float>& blocking, const Volume<uint8_t>& tumor,
                            const TumorSurface& surface, const PathSafetyOptions& options);
// The default region of interest radius: the distance from `centre` (LPS mm) to the farthest voxel
// centre with b > 0; 0 when there is none.
double farthest_blocking_mm(const Volume<float>& blocking, const Eigen::Vector3d& centre);

// The tumor mask on an isotropic grid of `spacing` with the axes of the output grid and a lattice
// through its centre (DESIGN.md §4, tumor sampling): a voxel is tumor when its centre lies in a
// tumor voxel of the mask (nearest voxel). Covers the mask's tumor voxels with one voxel to spare.
// `surface` is the mask's own (its index bounding box is used).
Volume<uint8_t> resample_tumor(const Volume<uint8_t>& tumor, const TumorSurface& surface,
                               const OutputGrid& grid, double spacing);

// Fast mode's self-check: voxels of the region inside the scan (offsets into the output grid),
// drawn at random with a fixed seed, and their exact values (kValueCount per voxel).
struct CheckSample {
  std::vector<int64_t> offsets;
  std::vector<float> exact;
};

struct PathSafetyResult {
  OutputGrid grid;
  unsigned values = 0;
  Mode mode = Mode::kExact;
  int direction_cells = 0;  // tables mode: octahedral map side
  int64_t evaluated_points = 0;     // fast mode: points computed exactly (lattice corners)
  int64_t interpolated_voxels = 0;  // fast mode: ROI voxels interpolated
  // Fast mode: points computed exactly per level of the sampler (stride, count; stride 0: the
  // finest level's points inside refined cells of edge 2).
  std::vector<std::pair<int, int64_t>> sampler_levels;
  int fast_stride = 0;  // fast mode: the coarsest lattice's stride used
  // Fast mode with PathSafetyOptions::combined_so_far: cells not split and finest points
  // interpolated because the phases before decide the combination's class there.
  int64_t cells_left_to_combination = 0;
  int64_t points_left_to_combination = 0;
  int fast_ray_stride = 0;  // fast mode: blocking samples per quadrature point used
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
  // Fast mode: rays cast per voxel (surface points standing for blocks of them), else 0.
  int64_t fast_surface_points = 0;
  double s2_mm2 = 0.0;
  double gamma_mm = 0.0;
  double eps = 0.0;
  std::string device;  // "cpu" or "cuda:<name>"
  int threads = 0;
  double seconds = 0.0;
  // Where the time went (seconds), when the backend says: e.g. fast mode on CUDA.
  std::vector<std::pair<std::string, double>> phases;
  uint64_t rays = 0;  // output voxels in the ROI x surface points
  // Fast mode: its difference from exact mode at `check_voxels` random ROI voxels (classes by
  // default_classes of the fast volume); empty in exact mode.
  int64_t check_voxels = 0;
  std::array<double, kernels::kValueCount> check_relative_l2{};
  std::array<double, kernels::kValueCount> check_class_agreement{};
  // default_classes of each volume where already taken (fast mode's self-check, the plan before
  // writing), so that the writes and area safety do not take them again; reset by whatever
  // changes a volume's values (apply_scan_coverage). classes_of() fills a missing one.
  std::array<std::optional<SafetyClasses>, kernels::kValueCount> classes;
  // The volumes' statistics, kept as the classes are (classes_of takes both in one pass).
  std::array<std::optional<ValueStatistics>, kernels::kValueCount> statistics;
  // PathSafetyOptions::fast_check_later: the check's comparison, for finish_fast_check.
  std::function<void(PathSafetyResult&)> pending_check;
  // The check's voxels and exact values (breathing combines the phases' into the combination's).
  std::shared_ptr<const CheckSample> check_sample;
  // What the computation holds on a device (the CUDA scenes), released with the result or by
  // whoever takes it: freeing device memory waits for every kernel on the device, so that the
  // sampler of a phase computed beside this one is not held up by this phase's end.
  std::shared_ptr<void> device_memory;
};

// Fast mode against a check sample's exact values: check_voxels, check_relative_l2 and
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

// Fast mode's automatic coarsest stride at output spacing h and region radius R: the largest
// power of two whose lattice is at most min(8 mm, R / 4) apart, at least 4 (h = 2 mm: 4; h = 0.7
// or 1 mm with R >= 32 mm: 8). A coarser lattice in voxels costs fewer points on fine grids; in
// millimetres it is never coarser than the 8 mm that the 2 mm plans were measured with, and a
// small region keeps at least four cells across its radius.
int coarsest_stride(double spacing_mm, double radius_mm);

// Fast mode's automatic ray stride at output spacing h over a blocking volume whose smallest
// spacing is s_b: the most blocking samples (at most 4) whose run, taken at its midpoint, spans at
// most kMaxQuadratureStepMm and at most kMaxQuadratureStepVoxels x s_b, so that a ray crossing
// a single blocking voxel (a trilinear footprint 2 s_b wide) is sampled inside it. At h = 0.7 mm
// over 0.7 mm voxels: 3 (runs of 1.05 mm); at 1 mm: 2; from 1.4 mm on: 1, every sample as exact
// mode. Measured (bench/RESULTS.md, twelfth and sixteenth sessions): classes >= 99.96 % of exact
// mode's at the headline with runs of 0.7 and 1.05 mm, 99.98 % on the 1 mm test scene with runs
// of 1 mm; on the 2 mm test scenes, whose impassable tubes are as thin as 1.5 mm, runs of 2 mm
// keep only 99.0 %, which the caps never choose.
constexpr double kMaxQuadratureStepMm = 1.05;
constexpr double kMaxQuadratureStepVoxels = 1.5;
int automatic_ray_stride(double spacing_mm, double blocking_spacing_mm);

// The blocking volume's bricks (kernels::kBrickShift, kernels::brick_code): the value every
// sample whose lower corner lies in the brick takes where that is one value (0 in empty space),
// else -1; an empty brick at Chebyshev distance d >= 2 bricks from the nearest brick that is not
// empty holds -d (capped at kernels::kMaxEmptyRun), so rays leap over the cube of empty bricks.
std::vector<float> blocking_bricks(const Volume<float>& blocking);

// The tumor's leaps (kernels::TumorGrid::leap) over its index box [lo, hi]: one byte per voxel,
// kernels::kTumorLeapInside for tumor plus the Chebyshev distance (capped at
// kernels::kMaxTumorLeap) to the nearest voxel of the other kind, voxels beyond the box counting
// as not tumor. Empty when the box is.
std::vector<uint8_t> tumor_leaps(const Volume<uint8_t>& tumor, const int lo[3], const int hi[3]);

// Builds the scene the kernels read. The returned views point into `blocking`, `tumor`,
// `surface`, `bricks` (may be empty: no uniform-space skipping) and `leaps` (tumor_leaps of the
// surface's box; may be empty: every sample of a ray's tumor walk looked up), which must outlive
// them.
kernels::PathSafetyScene<double> make_scene(const Volume<float>& blocking,
                                            const Volume<uint8_t>& tumor,
                                            const TumorSurface& surface, double gamma_mm,
                                            double eps,
                                            const std::vector<float>& bricks = {},
                                            const std::vector<uint8_t>& leaps = {});

// Starts the GPU's runtime on its own thread (a good part of a second), once per process, so that
// a command can overlap it with reading its inputs; compute_path_safety then finds it started.
// Nothing for Device::kCpu or a build without CUDA.
void start_device_warm_up(Device device);

// The GPUs path safety runs on for `device` (0: it runs on the cores).
int gpus_for(Device device);

// Bytes of memory available to this process now (MemAvailable), 0 when unknown.
uint64_t available_memory_bytes();

}  // namespace crepuscular::planning
