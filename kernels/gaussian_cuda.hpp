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

}  // namespace crepuscular::kernels
