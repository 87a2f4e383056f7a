// The safety margin's separable Gaussian passes (planning/preprocessing/smoothing.hpp) on the GPU:
// the same taps summed in the same order in double, each product and sum rounded once as on the
// host (no fused multiply-add), float between passes, so the same bits as the host's passes.
#pragma once

#include <cstdint>
#include <vector>

namespace crepuscular::kernels {

// Smooths the box of an image: `in` holds the box's values (x fastest, dims[3] voxels from the
// image voxel lo[3]); image[3] are the image's dims (a tap beyond its edge reads the edge voxel:
// zero flux; a tap outside the box reads 0). taps[a]: the odd-sized kernel along axis a. Passes
// along z, y, then x into `out` (dims voxels). Returns false, touching nothing, when no CUDA
// device is found; throws Error on a CUDA failure.
bool gaussian_box_cuda(const float* in, const int64_t lo[3], const int64_t dims[3],
                       const int64_t image[3], const std::vector<double> taps[3], float* out);

// One vulnerability level of a blocking volume made on the GPU (blocking_levels_cuda).
struct MarginLevel {
  uint8_t code = 0;            // the level's voxels hold this code (> 0) in the level map
  float coeff = 0.0f;          // its risk per mm
  int64_t lo[3] = {0, 0, 0};   // the box its margin reaches (image voxels): its voxels grown by
  int64_t dims[3] = {0, 0, 0};  // the kernel's radius, clamped to the image
  std::vector<double> taps[3];  // the Gaussian's taps per axis; empty: no margin
};

// The whole blocking volume of a label map on the GPU: b = max over `levels` of
// coeff * max(mask, G * mask), mask(v) = (codes[v] == code), G the separable passes above (z, y,
// then x over the level's box), so the same bits as the host's add_level. codes: one byte per
// image voxel (x fastest, dims image[3]); b: the image's values, written whole (0 where no level
// reaches). Returns false, touching nothing, when no CUDA device is found or its memory does not
// hold the volumes (the caller computes on the cores); throws Error on another CUDA failure.
bool blocking_levels_cuda(const uint8_t* codes, const int64_t image[3],
                          const std::vector<MarginLevel>& levels, float* b);

}  // namespace crepuscular::kernels
