// CUDA backend of the path safety values: the same host/device math as the CPU backend
// (kernels/path_safety_math.hpp), run on every visible GPU, the output grid split into slabs.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <utility>
#include <vector>

#include "kernels/path_safety_math.hpp"

namespace crepuscular::kernels {

// Number of usable CUDA devices; 0 when there is no driver or no device.
int cuda_device_count();

// The output grid: voxel (i, j, k) lies at origin + i axes[0] + j axes[1] + k axes[2] (LPS mm);
// n = 2 half + 1 voxels per axis; a voxel is in the region of interest when
// (i-half)^2 + (j-half)^2 + (k-half)^2 <= max_sq (the same integer test as the CPU backend).
struct OutputGridDesc {
  double origin[3];
  double axes[3][3];
  int n;
  int half;
  int64_t max_sq;
  // Optional, host memory, n^3 bytes: 0 where a voxel lies outside the scan (unknown) and is
  // not computed (left NaN); null: every voxel of the ball is computed. Exact mode only.
  const uint8_t* known = nullptr;
};

// Where the blocking volume lives on the device: global memory with trilinear filtering in float
// (the exact definition), or a 3D texture with hardware filtering (9-bit interpolation weights) of
// floats or of halves (11-bit significands: half the bytes read per sample; fast mode's storage).
enum class BlockingStorage { kGlobal, kTexture, kTextureHalf };

inline bool is_texture(BlockingStorage s) { return s != BlockingStorage::kGlobal; }

struct CudaRunOptions {
  BlockingStorage storage = BlockingStorage::kGlobal;
  int max_devices = 0;  // 0: all visible devices
  std::function<void(double)> progress;
  // Called once, before the first result is written to out[]: the caller may still be
  // allocating the host arrays that out[] points to (it fills out[] here) while the kernels run.
  std::function<void()> wait_for_outputs;
};

struct CudaRunReport {
  std::string devices;          // e.g. "cuda:NVIDIA H100 80GB HBM3 x1"
  int device_count = 0;
  double kernel_seconds = 0.0;  // wall time of the kernels, all devices together
  // Where the time went on device 0, seconds, where the backend says.
  std::vector<std::pair<std::string, double>> phases;
};

// Computes the requested values (bits of PathSafetyValue) for every voxel of the ball, exactly
// (the output grid split into slabs of whole z-slices, one per device). `scene`
// holds host pointers (blocking, tumor mask, surface points); out[slot] are host arrays of n^3
// floats for the requested values (set to NaN outside the ball). Throws crepuscular::Error on a CUDA
// failure.
// Number of CUDA devices, after creating the context of each (the first CUDA call of a process
// costs a good part of a second; callers overlap it with other work).
int cuda_warm_up();
// Whether every device's waiting host threads sleep rather than spin (cuda_warm_up sets it).
bool cuda_waits_sleep();

// Exact values at listed points of an output grid (fast mode's coarse-to-fine sampling): the
// scene is uploaded once to every device (up to max_devices; 0: all visible) and kept for every
// call; each call splits its points between the devices.
class CudaPointEvaluator {
 public:
  CudaPointEvaluator(const PathSafetyScene<double>& scene, const OutputGridDesc& grid,
                     unsigned values, BlockingStorage storage, int max_devices);
  ~CudaPointEvaluator();
  CudaPointEvaluator(const CudaPointEvaluator&) = delete;
  CudaPointEvaluator& operator=(const CudaPointEvaluator&) = delete;
  // ijk: 3 * count output grid indices (may lie outside the grid); out: kValueCount floats per
  // point, slot order (requested values only).
  void evaluate(const int32_t* ijk, int64_t count, float* out);
  std::string devices() const;
  int device_count() const;
  double setup_seconds() const;   // uploads
  double kernel_seconds() const;  // all evaluate calls, wall time

 private:
  struct Impl;
  Impl* impl_;
};

CudaRunReport run_path_safety_cuda(const PathSafetyScene<double>& scene,
                                   const OutputGridDesc& grid, unsigned values,
                                   float* const out[kValueCount], const CudaRunOptions& options);

}  // namespace crepuscular::kernels
