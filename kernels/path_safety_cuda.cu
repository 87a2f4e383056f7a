// CUDA launchers of the path safety values: one thread per output voxel, 8x8x4 voxel blocks,
// every visible GPU taking a slab of z-slices. The math is kernels/path_safety_math.hpp.
#include <cuda_fp16.h>
#include <cuda_runtime.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstddef>
#include <exception>
#include <functional>
#include <limits>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "foundation/error.hpp"
#include "foundation/trace.hpp"
#include "kernels/cuda_memory.cuh"
#include "kernels/launch_order.hpp"
#include "kernels/path_safety_cuda.hpp"
#include "kernels/value_set.hpp"

namespace crepuscular::kernels {

namespace {

using cuda::check;
using cuda::DeviceBuffer;

Affine<float> to_float(const Affine<double>& a) {
  Affine<float> f{};
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) f.m[r][c] = float(a.m[r][c]);
  return f;
}

// Hardware-filtered blocking lookups: unnormalised coordinates, voxel centres at +0.5, border 0.
struct TextureSampler {
  cudaTextureObject_t texture;
  BlockingGrid<float> grid;  // for its bricks: uniform-space skipping as in sample_blocking
  __device__ float operator()(Vec3<float> q) const {
    const float uniform = uniform_brick(grid, floor_int(q.x), floor_int(q.y), floor_int(q.z));
    if (uniform >= 0.0f) return uniform;
    return mixed(q);
  }
  __device__ float mixed(Vec3<float> q) const {
    return tex3D<float>(texture, q.x + 0.5f, q.y + 0.5f, q.z + 0.5f);
  }
};

// Fast mode's point kernel (kMarchEverySample): the texture read at texture coordinates (the
// blocking index + 0.5, added to a ray's origin once: kShift), after a brick code of its own
// (MarchBricks): a brick b holds c >= 0 when the voxels 4b - 1 .. 4b + 4 along every axis all
// hold c, which covers the trilinear support of every sample whose texture coordinate floors into
// b; -1 otherwise. Empty bricks hold 0 (no leaping), and the bricks cover every sample of every
// ray of the evaluator's points, so a sample needs neither a bounds check nor a code mapped to
// its value (H100 profile: the brick lookup's bounds, the +0.5 per axis and the leap codes took 8
// of the 38 instructions of a sample; bench/RESULTS.md, 2026-11-28).
struct MarchTextureSampler {
  static constexpr float kShift = 0.5f;
  cudaTextureObject_t texture;
  const float* bricks;  // brick (0, 0, 0), inside an allocation padded on every side
  int row, slice;       // bricks per row and per slice of the padded allocation
  __device__ float operator()(Vec3<float> t) const {
    const int bi = floor_int(t.x) >> kBrickShift, bj = floor_int(t.y) >> kBrickShift,
              bk = floor_int(t.z) >> kBrickShift;
    const float code = bricks[bk * slice + bj * row + bi];
    if (code >= 0.0f) return code;
    return tex3D<float>(texture, t.x, t.y, t.z);
  }
};

// MarchTextureSampler's brick codes on one device: bricks lo .. lo + dims - 1 per axis (lo <= 0),
// derived from the scene's (BlockingGrid::bricks, voxels 4b .. 4b + 4 per axis): a brick holds c
// where the eight scene bricks b - 1 .. b per axis, which cover 4b - 4 .. 4b + 4, all hold c.
struct MarchBricks {
  DeviceBuffer<float> codes;
  int lo[3] = {0, 0, 0}, dims[3] = {1, 1, 1};
  MarchTextureSampler sampler(cudaTextureObject_t texture) const {
    const int row = dims[0], slice = dims[0] * dims[1];
    return {texture, codes.ptr + (-lo[2] * ptrdiff_t(slice) - lo[1] * ptrdiff_t(row) - lo[0]),
            row, slice};
  }
};

// A scene brick's code for MarchBricks, beyond the scene's bricks too: 0 where every voxel of it
// and its support lies outside the volume (border 0), -1 where its support reaches voxel 0 from
// below; an empty brick's leap code (-d) is 0.
__device__ float scene_brick(const BlockingGrid<float>& g, int i, int j, int k) {
  if (i <= -2 || j <= -2 || k <= -2 || i >= g.bx || j >= g.by || k >= g.bz) return 0.0f;
  if (i < 0 || j < 0 || k < 0) return kMixedBrick;
  const float code = g.bricks[(size_t(k) * g.by + j) * g.bx + i];
  return code < kEmptyRunBelow ? 0.0f : code;
}

__global__ void march_bricks_kernel(BlockingGrid<float> g, int lo0, int lo1, int lo2, int d0,
                                    int d1, int d2, float* __restrict__ out) {
  const int64_t n = int64_t(d0) * d1 * d2;
  for (int64_t b = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; b < n;
       b += int64_t(gridDim.x) * blockDim.x) {
    const int i = int(b % d0) + lo0, j = int(b / d0 % d1) + lo1, k = int(b / (int64_t(d0) * d1)) + lo2;
    float c = kMixedBrick;
    if (g.bricks) {
      c = scene_brick(g, i, j, k);
      for (int q = 1; q < 8 && c >= 0.0f; ++q) {
        if (scene_brick(g, i - (q & 1), j - ((q >> 1) & 1), k - (q >> 2)) != c) c = kMixedBrick;
      }
    }
    out[b] = c;
  }
}

__global__ void to_half_kernel(const float* __restrict__ in, int64_t n, __half* __restrict__ out) {
  for (int64_t i = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; i < n;
       i += int64_t(gridDim.x) * blockDim.x)
    out[i] = __float2half_rn(in[i]);
}

// Uniform brick codes (c > 0) rounded to the nearest half, in place; leap and mixed codes stay.
__global__ void round_to_half_kernel(float* codes, int64_t n) {
  for (int64_t i = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; i < n;
       i += int64_t(gridDim.x) * blockDim.x)
    if (codes[i] > 0.0f) codes[i] = __half2float(__float2half_rn(codes[i]));
}

struct SlabGrid {
  double origin[3];
  double axes[3][3];
  int n;
  int z_begin, z_end;  // slices of this launch, global indices
  int z_slab;          // first slice of this device's slab
  int half;
  long long max_sq;
  const uint8_t* known;  // device, this slab's voxels (offset as the outputs); null: all
};

template <unsigned Values, typename Sampler>
__global__ void path_safety_kernel(PathSafetyScene<float> scene, SlabGrid grid, Sampler sampler,
                                   float* __restrict__ out0, float* __restrict__ out1,
                                   float* __restrict__ out2, float* __restrict__ out3) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  const int j = blockIdx.y * blockDim.y + threadIdx.y;
  const int k = grid.z_begin + blockIdx.z * blockDim.z + threadIdx.z;
  if (i >= grid.n || j >= grid.n || k >= grid.z_end) return;
  const Vec3<double> p = grid_point(grid.origin, grid.axes, i, j, k);
  const long long di = i - grid.half, dj = j - grid.half, dk = k - grid.half;
  if (di * di + dj * dj + dk * dk > grid.max_sq) return;
  const size_t off = (size_t(k - grid.z_slab) * grid.n + j) * grid.n + i;
  if (grid.known && !grid.known[off]) return;  // outside the scan: unknown, stays NaN
  float res[kValueCount] = {0.0f, 0.0f, 0.0f, 0.0f};
  path_safety_at<float, Values>(scene, p, res, sampler);
  if constexpr ((Values & kSvv) != 0) out0[off] = res[0];
  if constexpr ((Values & kIsbv) != 0) out1[off] = res[1];
  if constexpr ((Values & kIvbv) != 0) out2[off] = res[2];
  if constexpr ((Values & kBvv) != 0) out3[off] = res[3];
}

// Everything one device needs, uploaded once.
struct DeviceScene {
  DeviceBuffer<float> blocking;
  DeviceBuffer<float> bricks;
  DeviceBuffer<uint8_t> tumor;
  DeviceBuffer<uint8_t> tumor_leap;
  DeviceBuffer<SurfacePoint<double>> surface;
  cudaArray_t array = nullptr;
  cudaTextureObject_t texture = 0;
  PathSafetyScene<float> scene{};

  DeviceScene(const PathSafetyScene<double>& host, BlockingStorage storage)
      : tumor(size_t(host.tumor.nx) * host.tumor.ny * host.tumor.nz),
        tumor_leap(host.tumor.leap ? tumor_box_voxels(host.tumor) : 1),
        surface(size_t(std::max(host.surface_count, 1))) {
    upload_blocking(host.blocking, storage);
    upload_tumor(host.tumor);
    if (host.surface_count > 0) {
      check(cudaMemcpy(surface.ptr, host.surface,
                       size_t(host.surface_count) * sizeof(SurfacePoint<double>),
                       cudaMemcpyHostToDevice),
            "upload surface points");
    }
    scene.surface = surface.ptr;
    scene.surface_count = host.surface_count;
    scene.gamma = float(host.gamma);
    scene.eps = float(host.eps);
    scene.s2 = float(host.s2);
    scene.blocking_stride = host.blocking_stride;
  }
  ~DeviceScene() {
    if (texture) cudaDestroyTextureObject(texture);
    if (array) cudaFreeArray(array);
  }

 private:
  // The blocking volume (global memory, or a texture: `storage`) and its uniform bricks.
  void upload_blocking(const BlockingGrid<double>& host, BlockingStorage storage) {
    const size_t nb = size_t(host.nx) * host.ny * host.nz;
    scene.blocking.nx = host.nx;
    scene.blocking.ny = host.ny;
    scene.blocking.nz = host.nz;
    scene.blocking.physical_to_index = to_float(host.physical_to_index);
    scene.blocking.bricks = nullptr;
    if (host.bricks) {
      const size_t count = size_t(host.bx) * host.by * host.bz;
      bricks.allocate(count);
      check(cudaMemcpy(bricks.ptr, host.bricks, count * sizeof(float), cudaMemcpyHostToDevice),
            "upload bricks");
      if (storage == BlockingStorage::kTextureHalf) {  // uniform values as the texture holds them
        round_to_half_kernel<<<unsigned(std::min<size_t>((count + 255) / 256, 4096)), 256>>>(
            bricks.ptr, int64_t(count));
        check(cudaGetLastError(), "brick rounding launch");
      }
      scene.blocking.bricks = bricks.ptr;
      scene.blocking.bx = host.bx;
      scene.blocking.by = host.by;
      scene.blocking.bz = host.bz;
    }
    if (storage == BlockingStorage::kGlobal) {
      blocking.allocate(nb);
      check(cudaMemcpy(blocking.ptr, host.values, nb * sizeof(float), cudaMemcpyHostToDevice),
            "upload blocking volume");
      scene.blocking.values = blocking.ptr;
    } else {
      upload_texture(host, storage == BlockingStorage::kTextureHalf);
      scene.blocking.values = nullptr;
    }
  }

  // The blocking volume as a 3D texture with hardware trilinear filtering, border 0; halves are
  // rounded on the device (the volume's floats uploaded once).
  void upload_texture(const BlockingGrid<double>& host, bool half) {
    const cudaChannelFormatDesc desc =
        half ? cudaCreateChannelDescHalf() : cudaCreateChannelDesc<float>();
    const cudaExtent extent = make_cudaExtent(size_t(host.nx), size_t(host.ny), size_t(host.nz));
    check(cudaMalloc3DArray(&array, &desc, extent), "cudaMalloc3DArray");
    cudaMemcpy3DParms copy = {};
    const size_t n = size_t(host.nx) * host.ny * host.nz;
    DeviceBuffer<float> staged;
    DeviceBuffer<__half> halves;
    if (half) {
      staged.allocate(n);
      check(cudaMemcpy(staged.ptr, host.values, n * sizeof(float), cudaMemcpyHostToDevice),
            "upload blocking volume");
      halves.allocate(n);
      to_half_kernel<<<unsigned(std::min<size_t>((n + 255) / 256, 65536)), 256>>>(
          staged.ptr, int64_t(n), halves.ptr);
      check(cudaGetLastError(), "half conversion launch");
      copy.srcPtr = make_cudaPitchedPtr(halves.ptr, size_t(host.nx) * sizeof(__half),
                                        size_t(host.nx), size_t(host.ny));
      copy.kind = cudaMemcpyDeviceToDevice;
    } else {
      copy.srcPtr =
          make_cudaPitchedPtr(const_cast<float*>(host.values), size_t(host.nx) * sizeof(float),
                              size_t(host.nx), size_t(host.ny));
      copy.kind = cudaMemcpyHostToDevice;
    }
    copy.dstArray = array;
    copy.extent = extent;
    check(cudaMemcpy3D(&copy), "upload blocking texture");
    cudaResourceDesc res = {};
    res.resType = cudaResourceTypeArray;
    res.res.array.array = array;
    cudaTextureDesc tex = {};
    tex.addressMode[0] = tex.addressMode[1] = tex.addressMode[2] = cudaAddressModeBorder;
    tex.filterMode = cudaFilterModeLinear;
    tex.readMode = cudaReadModeElementType;
    tex.normalizedCoords = 0;
    check(cudaCreateTextureObject(&texture, &res, &tex, nullptr), "cudaCreateTextureObject");
  }

  void upload_tumor(const TumorGrid<double>& host) {
    const size_t nt = size_t(host.nx) * host.ny * host.nz;
    check(cudaMemcpy(tumor.ptr, host.mask, nt, cudaMemcpyHostToDevice), "upload tumor");
    scene.tumor.mask = tumor.ptr;
    scene.tumor.nx = host.nx;
    scene.tumor.ny = host.ny;
    scene.tumor.nz = host.nz;
    scene.tumor.physical_to_index = host.physical_to_index;
    for (int a = 0; a < 3; ++a) {
      scene.tumor.lo[a] = host.lo[a];
      scene.tumor.hi[a] = host.hi[a];
    }
    scene.tumor.leap = nullptr;
    if (host.leap) {
      check(cudaMemcpy(tumor_leap.ptr, host.leap, tumor_box_voxels(host), cudaMemcpyHostToDevice),
            "upload tumor leaps");
      scene.tumor.leap = tumor_leap.ptr;
    }
  }

  static size_t tumor_box_voxels(const TumorGrid<double>& g) {
    return size_t(g.hi[0] - g.lo[0] + 1) * size_t(g.hi[1] - g.lo[1] + 1) *
           size_t(g.hi[2] - g.lo[2] + 1);
  }
};


}  // namespace

int cuda_device_count() {
  int count = 0;
  if (cudaGetDeviceCount(&count) != cudaSuccess) {
    cudaGetLastError();  // clear the sticky "no driver" error
    return 0;
  }
  return count;
}

int cuda_warm_up() {
  const int count = cuda_device_count();
  for (int d = 0; d < count; ++d) {
    if (cudaSetDevice(d) != cudaSuccess) continue;
    // A thread waiting for the device sleeps until the device is done instead of spinning (the
    // default with fewer contexts than cores): a breathing plan has up to five launches in
    // flight, each waited for by a thread of its own, while the phases' host steps, folds and
    // checks need every core. A wait ends a few microseconds later; a launch takes milliseconds
    // at least. (H200, 10 phases: no change measurable within the instances' spread, which the
    // host steps set; bench/RESULTS.md, 2026-11-28.) Flags set on a device already
    // started replace its earlier ones.
    cudaSetDeviceFlags(cudaDeviceScheduleBlockingSync);
    cudaFree(nullptr);
  }
  cudaGetLastError();
  return count;
}

bool cuda_waits_sleep() {
  const int count = cuda_device_count();
  bool all = count > 0;
  for (int d = 0; d < count; ++d) {
    unsigned flags = 0;
    all = all && cudaSetDevice(d) == cudaSuccess && cudaGetDeviceFlags(&flags) == cudaSuccess &&
          (flags & cudaDeviceScheduleMask) == cudaDeviceScheduleBlockingSync;
  }
  cudaGetLastError();
  return all;
}

namespace {

std::string device_name(int d) {
  cudaDeviceProp prop{};
  return cudaGetDeviceProperties(&prop, d) == cudaSuccess ? prop.name : "unknown";
}

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// Milliseconds between two recorded events.
float event_ms(cudaEvent_t a, cudaEvent_t b) {
  float ms = 0.0f;
  check(cudaEventElapsedTime(&ms, a, b), "cudaEventElapsedTime");
  return ms;
}

struct EventPair {
  cudaEvent_t begin = nullptr, end = nullptr;
  EventPair() {
    check(cudaEventCreate(&begin), "cudaEventCreate");
    check(cudaEventCreate(&end), "cudaEventCreate");
  }
  ~EventPair() {
    cudaEventDestroy(begin);
    cudaEventDestroy(end);
  }
};

// Runs work(d) for every device d, each on a host thread of its own; then rethrows the error of
// the first device (in device order) that failed.
template <typename Work>
void on_every_device(int devices, const Work& work) {
  std::vector<std::exception_ptr> errors(static_cast<size_t>(devices));
  std::vector<std::thread> threads;
  for (int d = 0; d < devices; ++d) {
    threads.emplace_back([&work, &errors, d] {
      try {
        work(d);
      } catch (...) {
        errors[size_t(d)] = std::current_exception();
      }
    });
  }
  for (auto& t : threads) t.join();
  for (auto& e : errors) {
    if (e) std::rethrow_exception(e);
  }
}

// Work done over all devices, reported as a fraction of `total` through the caller's callback,
// one call at a time.
class Progress {
 public:
  Progress(const std::function<void(double)>& callback, double total)
      : callback_(callback), total_(total) {}
  void add(int64_t count) {
    const int64_t done = done_ += count;
    if (callback_) {
      std::lock_guard<std::mutex> lock(mutex_);
      callback_(double(done) / total_);
    }
  }

 private:
  const std::function<void(double)>& callback_;
  double total_;
  std::atomic<int64_t> done_{0};
  std::mutex mutex_;
};

// The kernels' view of the output grid (z_begin, z_end and z_slab left 0 for the caller).
SlabGrid slab_grid(const OutputGridDesc& grid) {
  SlabGrid g{};
  for (int a = 0; a < 3; ++a) {
    g.origin[a] = grid.origin[a];
    for (int b = 0; b < 3; ++b) g.axes[a][b] = grid.axes[a][b];
  }
  g.n = grid.n;
  g.half = grid.half;
  g.max_sq = grid.max_sq;
  return g;
}

// Device arrays of the requested values (bits of `values`), `count` floats each, all bits set:
// NaN, so that voxels outside the ball stay "not computed".
struct DeviceOutputs {
  DeviceBuffer<float> buffers[kValueCount];
  float* ptr[kValueCount] = {nullptr, nullptr, nullptr, nullptr};

  DeviceOutputs(unsigned values, size_t count) {
    for (int v = 0; v < kValueCount; ++v) {
      if (!(values & (1u << v))) continue;
      buffers[v].allocate(count);
      ptr[v] = buffers[v].ptr;
      check(cudaMemset(ptr[v], 0xFF, count * sizeof(float)), "cudaMemset");
    }
  }
  // Copies `count` floats of each array to host_out[value] + offset.
  void download(float* const host_out[kValueCount], size_t offset, size_t count) const {
    for (int v = 0; v < kValueCount; ++v) {
      if (!ptr[v]) continue;
      check(cudaMemcpy(host_out[v] + offset, ptr[v], count * sizeof(float), cudaMemcpyDeviceToHost),
            "download results");
    }
  }
};

// ---------------------------------------------------------------------------------------------
// Exact mode: the output grid split into slabs of whole z-slices, one per device.

// Slab boundaries (devices + 1 slice indices), balanced by the number of ball voxels rather than
// by slice count.
std::vector<int> slab_bounds(const OutputGridDesc& grid, int devices) {
  const int n = grid.n;
  std::vector<double> weight(static_cast<size_t>(n));
  double total = 0.0;
  for (int k = 0; k < n; ++k) {
    const double dk = double(k - grid.half);
    weight[size_t(k)] = std::max(0.0, double(grid.max_sq) - dk * dk);
    total += weight[size_t(k)];
  }
  std::vector<int> bounds(size_t(devices) + 1, n);
  bounds[0] = 0;
  double acc = 0.0;
  int dev = 1;
  for (int k = 0; k < n && dev < devices; ++k) {
    acc += weight[size_t(k)];
    if (acc >= total * dev / devices) bounds[size_t(dev++)] = k + 1;
  }
  return bounds;
}

// The name of the last device whose properties can be read ("" when none).
std::string last_device_name(int devices) {
  std::string name;
  for (int d = 0; d < devices; ++d) {
    cudaDeviceProp prop{};
    if (cudaGetDeviceProperties(&prop, d) == cudaSuccess) name = prop.name;
  }
  return name;
}

// The slices [z0, z1) of slab `g` (g.z_slab == z0), kSlicesPerLaunch per launch, into `outputs`
// (slab-sized arrays).
template <unsigned Values>
void launch_slab(const DeviceScene& ds, SlabGrid g, int z0, int z1, const DeviceOutputs& outputs,
                 BlockingStorage storage, Progress& progress) {
  const int n = g.n;
  const dim3 block(8, 8, 4);
  constexpr int kSlicesPerLaunch = 8;
  float* const* dev_out = outputs.ptr;
  for (int z = z0; z < z1; z += kSlicesPerLaunch) {
    g.z_begin = z;
    g.z_end = std::min(z + kSlicesPerLaunch, z1);
    const dim3 blocks((n + 7) / 8, (n + 7) / 8, (g.z_end - g.z_begin + 3) / 4);
    if (is_texture(storage)) {
      path_safety_kernel<Values><<<blocks, block>>>(ds.scene, g,
                                                    TextureSampler{ds.texture, ds.scene.blocking},
                                                    dev_out[0], dev_out[1], dev_out[2], dev_out[3]);
    } else {
      path_safety_kernel<Values><<<blocks, block>>>(ds.scene, g,
                                                    GridSampler<float>{ds.scene.blocking},
                                                    dev_out[0], dev_out[1], dev_out[2], dev_out[3]);
    }
    check(cudaGetLastError(), "kernel launch");
    check(cudaDeviceSynchronize(), "path safety kernel");
    progress.add(g.z_end - g.z_begin);
  }
}

// Device d's slab [z0, z1): upload, launches, download into out[] at the slab's offset.
void exact_on_device(int d, int z0, int z1, const PathSafetyScene<double>& host_scene,
                     const OutputGridDesc& grid, unsigned values, float* const out[kValueCount],
                     const CudaRunOptions& options, Progress& progress,
                     std::once_flag& outputs_ready) {
  check(cudaSetDevice(d), "cudaSetDevice");
  if (z1 <= z0) return;
  const int n = grid.n;
  DeviceScene ds(host_scene, options.storage);
  const size_t slab = size_t(z1 - z0) * size_t(n) * size_t(n);
  const DeviceOutputs outputs(values, slab);
  SlabGrid g = slab_grid(grid);
  g.z_slab = z0;
  DeviceBuffer<uint8_t> known;
  if (grid.known) {
    known.allocate(slab);
    check(cudaMemcpy(known.ptr, grid.known + size_t(z0) * size_t(n) * size_t(n), slab,
                     cudaMemcpyHostToDevice),
          "upload scan coverage");
    g.known = known.ptr;
  }
  with_value_set(values, [&](auto tag) {
    constexpr unsigned kValues = decltype(tag)::value;
    launch_slab<kValues>(ds, g, z0, z1, outputs, options.storage, progress);
  });
  if (options.wait_for_outputs) std::call_once(outputs_ready, options.wait_for_outputs);
  outputs.download(out, size_t(z0) * size_t(n) * size_t(n), slab);
}

// ---------------------------------------------------------------------------------------------
// Listed points (fast mode): one thread per point.

struct PointFrame {
  double origin[3];
  double axes[3][3];
};

// At most 64 registers, so that 8 blocks of 128 threads share a multiprocessor: more warps to
// hide the texture's latency (H100, fast mode's kernels: 10.5 s -> 9.8 s; a few bytes spill).
// Without empty-space leaping: a warp's points are not always neighbours, and lanes that leap by
// different counts lose the coherence of their texture reads (H100, fast mode's kernels: 10.1 s
// plain, 13.3 s leaping, 17.9 s leaping with 80 registers).
template <unsigned Values, typename Sampler>
__global__ void __launch_bounds__(128, 8)
    path_safety_points_kernel(PathSafetyScene<float> scene, PointFrame frame,
                                          const int32_t* __restrict__ ijk, int count,
                                          const int32_t* __restrict__ block_order,
                                          Sampler sampler, float* __restrict__ out) {
  // The block of points this one computes (launch_order.hpp: the longest started first).
  const int p = block_order[blockIdx.x] * blockDim.x + threadIdx.x;
  if (p >= count) return;
  const Vec3<double> x =
      grid_point(frame.origin, frame.axes, ijk[3 * p], ijk[3 * p + 1], ijk[3 * p + 2]);
  float res[kValueCount] = {0.0f, 0.0f, 0.0f, 0.0f};
  path_safety_at<float, Values, Sampler, kMarchEverySample>(scene, x, res, sampler);
  for (int v = 0; v < kValueCount; ++v) out[size_t(p) * kValueCount + v] = res[v];
}

// Few points (fast mode's self-check: 1000): one block per point, its threads splitting the
// surface points, so that every multiprocessor has work. Thread states are summed in a tree.
constexpr int kSplitThreads = 128;

template <unsigned Values, typename Sampler>
__global__ void __launch_bounds__(kSplitThreads)
    path_safety_points_split_kernel(PathSafetyScene<float> scene, PointFrame frame,
                                    const int32_t* __restrict__ ijk, Sampler sampler,
                                    float* __restrict__ out) {
  // Raw storage: a __shared__ array may not have VoxelState's member initializers run.
  __shared__ alignas(VoxelState<float>) unsigned char raw[kSplitThreads * sizeof(VoxelState<float>)];
  VoxelState<float>* part = reinterpret_cast<VoxelState<float>*>(raw);
  const int p = blockIdx.x;
  const Vec3<double> x =
      grid_point(frame.origin, frame.axes, ijk[3 * p], ijk[3 * p + 1], ijk[3 * p + 2]);
  VoxelState<float> state;
  for (int t = threadIdx.x; t < scene.surface_count; t += kSplitThreads) {
    combine_ray<float, Values>(state, scene, x, scene.surface[t], sampler);
  }
  part[threadIdx.x] = state;
  __syncthreads();
  for (int half = kSplitThreads / 2; half > 0; half /= 2) {
    if (threadIdx.x < half) add_state(part[threadIdx.x], part[threadIdx.x + half]);
    __syncthreads();
  }
  if (threadIdx.x == 0) {
    float res[kValueCount] = {0.0f, 0.0f, 0.0f, 0.0f};
    finalize_values(part[0], Values, scene.s2, res);
    for (int v = 0; v < kValueCount; ++v) out[size_t(p) * kValueCount + v] = res[v];
  }
}

// Below this many points a call splits each point's rays over a block.
constexpr int kSplitBelow = 8192;

}  // namespace

struct CudaPointEvaluator::Impl {
  PointFrame frame{};
  unsigned values = 0;
  BlockingStorage storage = BlockingStorage::kGlobal;
  int devices = 0;
  std::string names;
  std::vector<std::unique_ptr<DeviceScene>> scenes;
  // Per device, the points and values of a launch, kept from call to call: freeing device memory
  // waits for the whole device, so a phase computed beside another would wait for its rays.
  struct Launch {
    DeviceBuffer<int32_t> points;
    DeviceBuffer<int32_t> block_order;  // launch_order.hpp
    DeviceBuffer<float> values;
    int64_t capacity = 0;
  };
  // The tumor's centroid and the surface's mean distance from it: a point's work estimate.
  double centre[3] = {0.0, 0.0, 0.0};
  double reach = 0.0;
  std::vector<std::unique_ptr<Launch>> launches;
  // Texture storage: per device, the brick codes of MarchTextureSampler, which cover every ray of
  // a point whose indices lie within kReach of the grid (a sampler's lattice corners lie within
  // its coarsest stride, at most 64); a call with a point beyond reads bricks as the split
  // kernel does (TextureSampler).
  static constexpr int kReach = 64;
  std::vector<std::unique_ptr<MarchBricks>> march;
  int grid_n = 0;
  double setup_s = 0.0, kernel_s = 0.0;

  // The bricks around every sample of a ray from a point within kReach of the grid to a surface
  // point, in texture coordinates (the blocking index + 0.5), with two voxels to spare.
  static void march_extent(const PathSafetyScene<double>& scene, const OutputGridDesc& grid,
                           int lo[3], int dims[3]) {
    double a[3] = {1e300, 1e300, 1e300}, b[3] = {-1e300, -1e300, -1e300};
    const auto add = [&](Vec3<double> x) {
      const Vec3<double> q = scene.blocking.physical_to_index.apply(x);
      const double c[3] = {q.x, q.y, q.z};
      for (int e = 0; e < 3; ++e) {
        a[e] = std::min(a[e], c[e]);
        b[e] = std::max(b[e], c[e]);
      }
    };
    for (int corner = 0; corner < 8; ++corner) {
      const int ijk[3] = {(corner & 1) ? grid.n - 1 + kReach : -kReach,
                          (corner & 2) ? grid.n - 1 + kReach : -kReach,
                          (corner & 4) ? grid.n - 1 + kReach : -kReach};
      Vec3<double> x{grid.origin[0], grid.origin[1], grid.origin[2]};
      for (int e = 0; e < 3; ++e) {
        x.x += ijk[e] * grid.axes[e][0];
        x.y += ijk[e] * grid.axes[e][1];
        x.z += ijk[e] * grid.axes[e][2];
      }
      add(x);
    }
    for (int t = 0; t < scene.surface_count; ++t) add(scene.surface[t].position);
    const int nb[3] = {bricks_along(scene.blocking.nx), bricks_along(scene.blocking.ny),
                       bricks_along(scene.blocking.nz)};
    for (int e = 0; e < 3; ++e) {
      const int first = int(std::floor((a[e] + 0.5 - 2.0) / double(1 << kBrickShift)));
      const int last = int(std::floor((b[e] + 0.5 + 2.0) / double(1 << kBrickShift)));
      lo[e] = std::min(first, 0);
      dims[e] = std::max(last, nb[e] - 1) - lo[e] + 1;
    }
  }
};

CudaPointEvaluator::CudaPointEvaluator(const PathSafetyScene<double>& scene,
                                       const OutputGridDesc& grid, unsigned values,
                                       BlockingStorage storage, int max_devices)
    : impl_(new Impl) {
  const auto t0 = std::chrono::steady_clock::now();
  try {
    int devices = cuda_device_count();
    if (devices == 0) throw Error("CUDA: no device found");
    if (max_devices > 0) devices = std::min(devices, max_devices);
    impl_->devices = devices;
    impl_->values = values;
    impl_->storage = storage;
    impl_->names = last_device_name(devices);
    for (int a = 0; a < 3; ++a) {
      impl_->frame.origin[a] = grid.origin[a];
      for (int b = 0; b < 3; ++b) impl_->frame.axes[a][b] = grid.axes[a][b];
    }
    impl_->scenes.resize(size_t(devices));
    impl_->launches.resize(size_t(devices));
    impl_->march.resize(size_t(devices));
    impl_->grid_n = grid.n;
    if (scene.surface_count > 0) {
      for (int t = 0; t < scene.surface_count; ++t) {
        impl_->centre[0] += scene.surface[t].position.x;
        impl_->centre[1] += scene.surface[t].position.y;
        impl_->centre[2] += scene.surface[t].position.z;
      }
      for (double& c : impl_->centre) c /= scene.surface_count;
      for (int t = 0; t < scene.surface_count; ++t) {
        const Vec3<double>& x = scene.surface[t].position;
        impl_->reach += std::sqrt((x.x - impl_->centre[0]) * (x.x - impl_->centre[0]) +
                                  (x.y - impl_->centre[1]) * (x.y - impl_->centre[1]) +
                                  (x.z - impl_->centre[2]) * (x.z - impl_->centre[2]));
      }
      impl_->reach /= scene.surface_count;
    }
    on_every_device(devices, [&](int d) {
      check(cudaSetDevice(d), "cudaSetDevice");
      impl_->scenes[size_t(d)] = std::make_unique<DeviceScene>(scene, storage);
      if (is_texture(storage)) {
        auto bricks = std::make_unique<MarchBricks>();
        Impl::march_extent(scene, grid, bricks->lo, bricks->dims);
        const int64_t count = int64_t(bricks->dims[0]) * bricks->dims[1] * bricks->dims[2];
        bricks->codes.allocate(size_t(count));
        march_bricks_kernel<<<unsigned(std::min<int64_t>((count + 255) / 256, 4096)), 256>>>(
            impl_->scenes[size_t(d)]->scene.blocking, bricks->lo[0], bricks->lo[1],
            bricks->lo[2], bricks->dims[0], bricks->dims[1], bricks->dims[2], bricks->codes.ptr);
        check(cudaGetLastError(), "march bricks kernel launch");
        impl_->march[size_t(d)] = std::move(bricks);
      }
      check(cudaDeviceSynchronize(), "upload scene");
    });
  } catch (...) {
    delete impl_;
    throw;
  }
  impl_->setup_s = seconds_since(t0);
}

CudaPointEvaluator::~CudaPointEvaluator() {
  for (int d = 0; d < impl_->devices; ++d) {
    if (cudaSetDevice(d) == cudaSuccess) {
      impl_->scenes[size_t(d)].reset();
      impl_->launches[size_t(d)].reset();
    }
  }
  delete impl_;
}

void CudaPointEvaluator::evaluate(const int32_t* ijk, int64_t count, float* out) {
  const auto t0 = std::chrono::steady_clock::now();
  trace::event("eval_begin", count);
  const int devices = impl_->devices;
  // Whether every point lies within kReach of the grid, where the march bricks cover its rays.
  bool within = is_texture(impl_->storage);
  if (within) {
    int32_t lo = 0, hi = 0;
    for (int64_t c = 0; c < 3 * count; ++c) {
      lo = std::min(lo, ijk[c]);
      hi = std::max(hi, ijk[c]);
    }
    within = lo >= -Impl::kReach && hi <= impl_->grid_n - 1 + Impl::kReach;
  }
  // Launches of at most kChunk points: each level of fast mode's sampler in one launch at the
  // headline (each launch ends with its longest threads alone on the card: 2.95 -> 2.85 s of
  // kernels against launches of 2^20 points, bench/RESULTS.md, 2026-11-26).
  constexpr int64_t kChunk = int64_t(1) << 22;
  on_every_device(devices, [&](int d) {
    const int64_t p0 = count * d / devices, p1 = count * (d + 1) / devices;
    if (p1 <= p0) return;
    check(cudaSetDevice(d), "cudaSetDevice");
    const DeviceScene& ds = *impl_->scenes[size_t(d)];
    const int64_t most = std::min<int64_t>(kChunk, p1 - p0);
    std::unique_ptr<Impl::Launch>& buffers = impl_->launches[size_t(d)];
    if (!buffers || buffers->capacity < most) {
      // A sampler's levels grow: room for the largest launch at once (112 MB), unless small.
      const int64_t room = most < kSplitBelow ? most : kChunk;
      buffers.reset();
      buffers = std::make_unique<Impl::Launch>();
      buffers->points.allocate(size_t(3 * room));
      buffers->block_order.allocate(size_t((room + 127) / 128));
      buffers->values.allocate(size_t(kValueCount * room));
      buffers->capacity = room;
    }
    DeviceBuffer<int32_t>& points = buffers->points;
    DeviceBuffer<float>& values = buffers->values;
    for (int64_t c0 = p0; c0 < p1; c0 += kChunk) {
      const int m = int(std::min(kChunk, p1 - c0));
      check(cudaMemcpy(points.ptr, ijk + 3 * c0, size_t(3 * m) * sizeof(int32_t),
                       cudaMemcpyHostToDevice),
            "upload points");
      const unsigned blocks = unsigned((m + 127) / 128);
      if (m >= kSplitBelow) {
        const std::vector<int32_t> order = blocks_longest_first(
            ijk + 3 * c0, m, 128, impl_->frame.origin, impl_->frame.axes, impl_->centre,
            impl_->reach);
        check(cudaMemcpy(buffers->block_order.ptr, order.data(), order.size() * sizeof(int32_t),
                         cudaMemcpyHostToDevice),
              "upload block order");
      }
      // Few points: a block per point, which leaps over empty space (kLeapEmptySpace) with the
      // scene's bricks; many: a thread per point, which marches every sample.
      const auto launch = [&](auto sampler, auto march_sampler) {
        with_value_set(impl_->values, [&](auto tag) {
          constexpr unsigned kValues = decltype(tag)::value;
          if (m < kSplitBelow) {
            path_safety_points_split_kernel<kValues><<<unsigned(m), kSplitThreads>>>(
                ds.scene, impl_->frame, points.ptr, sampler, values.ptr);
          } else {
            path_safety_points_kernel<kValues><<<blocks, 128>>>(
                ds.scene, impl_->frame, points.ptr, m, buffers->block_order.ptr, march_sampler,
                values.ptr);
          }
        });
      };
      if (is_texture(impl_->storage)) {
        const TextureSampler texture{ds.texture, ds.scene.blocking};
        if (within) {
          launch(texture, impl_->march[size_t(d)]->sampler(ds.texture));
        } else {
          launch(texture, texture);
        }
      } else {
        launch(GridSampler<float>{ds.scene.blocking}, GridSampler<float>{ds.scene.blocking});
      }
      check(cudaGetLastError(), "points kernel launch");
      check(cudaMemcpy(out + kValueCount * c0, values.ptr,
                       size_t(kValueCount * m) * sizeof(float), cudaMemcpyDeviceToHost),
            "download values");
    }
  });
  impl_->kernel_s += seconds_since(t0);
  trace::event("eval_end", count);
}

std::string CudaPointEvaluator::devices() const {
  return "cuda:" + impl_->names + " x" + std::to_string(impl_->devices);
}
int CudaPointEvaluator::device_count() const { return impl_->devices; }
double CudaPointEvaluator::setup_seconds() const { return impl_->setup_s; }
double CudaPointEvaluator::kernel_seconds() const { return impl_->kernel_s; }

CudaRunReport run_path_safety_cuda(const PathSafetyScene<double>& host_scene,
                                   const OutputGridDesc& grid, unsigned values,
                                   float* const out[kValueCount], const CudaRunOptions& options) {
  int devices = cuda_device_count();
  if (devices == 0) throw Error("CUDA: no device found");
  if (options.max_devices > 0) devices = std::min(devices, options.max_devices);
  const std::vector<int> bounds = slab_bounds(grid, devices);
  Progress progress(options.progress, double(grid.n));
  std::once_flag outputs_ready;
  const std::string names = last_device_name(devices);
  const auto t0 = std::chrono::steady_clock::now();
  on_every_device(devices, [&](int d) {
    exact_on_device(d, bounds[size_t(d)], bounds[size_t(d) + 1], host_scene, grid, values, out,
                    options, progress, outputs_ready);
  });
  CudaRunReport report;
  report.device_count = devices;
  report.devices = "cuda:" + names + " x" + std::to_string(devices);
  report.kernel_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return report;
}

}  // namespace crepuscular::kernels
