// Fast mode (docs/ARCHITECTURE.md §11): the output grid sampled coarse to fine, every voxel where
// the safety classes change computed exactly, the inside of a region of one class interpolated.
// What a user chooses, and the design's fixed quantities.
#pragma once

namespace crepuscular::planning {

struct FastModeOptions {
  // One ray per block of surface_block^3 tumor voxels, cast to the block's surface point nearest
  // the mean of its surface points and counted once for each of them (1: every surface point, as
  // exact mode; 2: about a third of the rays, a first look). Command line --fast-surface-block.
  int surface_block = 1;
  // Blocking samples per quadrature point along a ray (1: every sample, as exact mode; 0:
  // automatic_ray_stride). Command line --fast-ray-stride.
  int ray_stride = 0;
  // Voxels of the region recomputed exactly afterwards, their difference reported (0: none).
  // Command line --fast-check-voxels.
  int check_voxels = 1000;
  // Throws Error naming the option (as on the command line) that is out of range.
  void check() const;
};

// How close to a class threshold a lattice corner may lie before its cell is refined: SVV within
// kSvvMargin percentage points; a blocking value within a factor (1 + kBlockingMargin).
constexpr double kSvvMargin = 3.0;
constexpr double kBlockingMargin = 0.25;

// The coarsest lattice's stride at output spacing h and region radius R: the largest power of two
// whose lattice is at most min(8 mm, R / 4) apart, at least 4 (h = 2 mm: 4; h = 0.7 or 1 mm with
// R >= 32 mm: 8). Never coarser in millimetres than the 8 mm the 2 mm plans hold at, and a small
// region keeps at least four cells across its radius.
int coarsest_stride(double spacing_mm, double radius_mm);

// The automatic ray stride at output spacing h over a blocking volume whose smallest spacing is
// s_b: the most blocking samples (at most 4) whose run, taken at its midpoint, spans at most
// kMaxQuadratureStepMm and at most kMaxQuadratureStepVoxels x s_b, so that a ray crossing a single
// blocking voxel (a trilinear footprint 2 s_b wide) is sampled inside it. At h = 0.7 mm over
// 0.7 mm voxels: 3 (runs of 1.05 mm); at 1 mm: 2; from 1.4 mm on: 1, every sample as exact mode.
// Runs of 2 mm on the 2 mm test scenes, whose impassable tubes are 1.5 mm thin, lose classes; the
// caps never choose them (bench/RESULTS.md, 2026-11-26 and 2026-11-27).
constexpr double kMaxQuadratureStepMm = 1.05;
constexpr double kMaxQuadratureStepVoxels = 1.5;
int automatic_ray_stride(double spacing_mm, double blocking_spacing_mm);

}  // namespace crepuscular::planning
