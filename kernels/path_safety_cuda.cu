// CUDA launchers of the path safety values: one thread per output voxel, 8x8x4 voxel blocks,
// every visible GPU taking a slab of z-slices. The math is kernels/path_safety_math.hpp.
#include "kernels/path_safety_cuda.hpp"

#include <cuda_runtime.h>

#include <algorithm>
#include <cmath>
#include <atomic>
#include <chrono>
#include <exception>
#include <limits>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "foundation/error.hpp"
#include "kernels/path_safety_fast.hpp"
#include "kernels/value_set.hpp"

namespace crepuscular::kernels {

namespace {

void check(cudaError_t status, const char* what) {
  if (status != cudaSuccess) {
    throw Error(std::string("CUDA: ") + what + " failed: " + cudaGetErrorString(status));
  }
}

template <typename T>
struct DeviceBuffer {
  T* ptr = nullptr;
  DeviceBuffer() = default;
  explicit DeviceBuffer(size_t count) { allocate(count); }
  void allocate(size_t count) {
    check(cudaMalloc(&ptr, std::max<size_t>(count, 1) * sizeof(T)), "cudaMalloc");
  }
  ~DeviceBuffer() {
    if (ptr) cudaFree(ptr);
  }
  DeviceBuffer(const DeviceBuffer&) = delete;
  DeviceBuffer& operator=(const DeviceBuffer&) = delete;
};

Affine<float> to_float(const Affine<double>& a) {
  Affine<float> f{};
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) f.m[r][c] = float(a.m[r][c]);
  return f;
}

// Hardware-filtered blocking lookups: unnormalised coordinates, voxel centres at +0.5, border 0.
struct TextureSampler {
  cudaTextureObject_t texture;
  BlockingGrid<float> grid;  // for its bricks: empty-space skipping as in sample_blocking
  __device__ float operator()(Vec3<float> q) const {
    if (empty_brick(grid, int(floorf(q.x)), int(floorf(q.y)), int(floorf(q.z)))) return 0.0f;
    return tex3D<float>(texture, q.x + 0.5f, q.y + 0.5f, q.z + 0.5f);
  }
};

struct SlabGrid {
  double origin[3];
  double axes[3][3];
  int n;
  int z_begin, z_end;  // slices of this launch, global indices
  int z_slab;          // first slice of this device's slab
  int half;
  long long max_sq;
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
  float res[kValueCount] = {0.0f, 0.0f, 0.0f, 0.0f};
  path_safety_at<float, Values>(scene, p, res, sampler);
  const size_t off = (size_t(k - grid.z_slab) * grid.n + j) * grid.n + i;
  if constexpr ((Values & kSvv) != 0) out0[off] = res[0];
  if constexpr ((Values & kIsbv) != 0) out1[off] = res[1];
  if constexpr ((Values & kIvbv) != 0) out2[off] = res[2];
  if constexpr ((Values & kBvv) != 0) out3[off] = res[3];
}

// Everything one device needs, uploaded once.
struct DeviceScene {
  DeviceBuffer<float> blocking;
  DeviceBuffer<uint8_t> bricks;
  DeviceBuffer<uint8_t> tumor;
  DeviceBuffer<SurfacePoint<double>> surface;
  cudaArray_t array = nullptr;
  cudaTextureObject_t texture = 0;
  PathSafetyScene<float> scene{};

  DeviceScene(const PathSafetyScene<double>& host, BlockingStorage storage)
      : tumor(size_t(host.tumor.nx) * host.tumor.ny * host.tumor.nz),
        surface(size_t(std::max(host.surface_count, 1))) {
    const size_t nb = size_t(host.blocking.nx) * host.blocking.ny * host.blocking.nz;
    const size_t nt = size_t(host.tumor.nx) * host.tumor.ny * host.tumor.nz;
    scene.blocking.nx = host.blocking.nx;
    scene.blocking.ny = host.blocking.ny;
    scene.blocking.nz = host.blocking.nz;
    scene.blocking.physical_to_index = to_float(host.blocking.physical_to_index);
    scene.blocking.bricks = nullptr;
    if (host.blocking.bricks) {
      const size_t count = size_t(host.blocking.bx) * host.blocking.by * host.blocking.bz;
      bricks.allocate(count);
      check(cudaMemcpy(bricks.ptr, host.blocking.bricks, count, cudaMemcpyHostToDevice),
            "upload bricks");
      scene.blocking.bricks = bricks.ptr;
      scene.blocking.bx = host.blocking.bx;
      scene.blocking.by = host.blocking.by;
      scene.blocking.bz = host.blocking.bz;
    }
    if (storage == BlockingStorage::kGlobal) {
      blocking.allocate(nb);
      check(cudaMemcpy(blocking.ptr, host.blocking.values, nb * sizeof(float),
                       cudaMemcpyHostToDevice),
            "upload blocking volume");
      scene.blocking.values = blocking.ptr;
    } else {
      const cudaChannelFormatDesc desc = cudaCreateChannelDesc<float>();
      const cudaExtent extent = make_cudaExtent(size_t(host.blocking.nx),
                                                size_t(host.blocking.ny),
                                                size_t(host.blocking.nz));
      check(cudaMalloc3DArray(&array, &desc, extent), "cudaMalloc3DArray");
      cudaMemcpy3DParms copy = {};
      copy.srcPtr = make_cudaPitchedPtr(const_cast<float*>(host.blocking.values),
                                        size_t(host.blocking.nx) * sizeof(float),
                                        size_t(host.blocking.nx), size_t(host.blocking.ny));
      copy.dstArray = array;
      copy.extent = extent;
      copy.kind = cudaMemcpyHostToDevice;
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
      scene.blocking.values = nullptr;
    }
    check(cudaMemcpy(tumor.ptr, host.tumor.mask, nt, cudaMemcpyHostToDevice), "upload tumor");
    scene.tumor.mask = tumor.ptr;
    scene.tumor.nx = host.tumor.nx;
    scene.tumor.ny = host.tumor.ny;
    scene.tumor.nz = host.tumor.nz;
    scene.tumor.physical_to_index = host.tumor.physical_to_index;
    for (int a = 0; a < 3; ++a) {
      scene.tumor.lo[a] = host.tumor.lo[a];
      scene.tumor.hi[a] = host.tumor.hi[a];
    }
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
  }
  ~DeviceScene() {
    if (texture) cudaDestroyTextureObject(texture);
    if (array) cudaFreeArray(array);
  }
};

// Fast mode: the direction tables of a batch of surface points, one per slot.
struct TableBatch {
  DirectionTable<float> first;  // slot 0; slot s is offset by s * stride
  size_t value_stride;          // floats between slots of c0/c1/c2
  size_t cell_stride;           // cells between slots of crossing
};

__device__ DirectionTable<float> slot_table(const TableBatch& b, int slot) {
  DirectionTable<float> t = b.first;
  t.c0 += slot * b.value_stride;
  if (t.c1) {
    t.c1 += slot * b.value_stride;
    t.c2 += slot * b.value_stride;
  }
  t.crossing += slot * b.cell_stride;
  return t;
}

template <typename Sampler>
__global__ void cast_directions_kernel(PathSafetyScene<float> scene, TableBatch batch,
                                       int first_point, int count, Sampler sampler) {
  const int64_t cell = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  const int slot = blockIdx.y;
  const int m = batch.first.m;
  if (cell >= int64_t(m) * m || slot >= count) return;
  cast_direction(scene, scene.surface[first_point + slot], slot_table(batch, slot), int(cell % m),
                 int(cell / m), sampler);
}

// Voxel v of the cube in tiled order: tiles of 8 x 8 x 4 voxels (one thread block each), so that
// the threads of a block look up neighbouring directions and distances of the tables. Returns
// false outside the grid or the ball.
__device__ bool tiled_voxel(const SlabGrid& grid, int64_t v, int& i, int& j, int& k) {
  const int n = grid.n;
  const int tiles_x = (n + 7) / 8, tiles_y = (n + 7) / 8;
  const int64_t tile = v >> 8;
  const int w = int(v & 255);
  i = int(tile % tiles_x) * 8 + (w & 7);
  j = int((tile / tiles_x) % tiles_y) * 8 + ((w >> 3) & 7);
  k = int(tile / (int64_t(tiles_x) * tiles_y)) * 4 + (w >> 6);
  if (i >= n || j >= n || k >= n) return false;
  const long long di = i - grid.half, dj = j - grid.half, dk = k - grid.half;
  return di * di + dj * dj + dk * dk <= grid.max_sq;
}

int64_t tiled_count(int n) {
  return int64_t((n + 7) / 8) * ((n + 7) / 8) * ((n + 3) / 4) * 256;
}

template <unsigned Values>
__global__ void combine_tables_kernel(PathSafetyScene<float> scene, TableBatch batch,
                                      int first_point, int count, SlabGrid grid,
                                      VoxelState<float>* __restrict__ states) {
  int i, j, k;
  if (!tiled_voxel(grid, int64_t(blockIdx.x) * blockDim.x + threadIdx.x, i, j, k)) return;
  const Vec3<float> p = vec_cast<float>(grid_point(grid.origin, grid.axes, i, j, k));
  const size_t off = (size_t(k) * grid.n + j) * grid.n + i;
  VoxelState<float> state = states[off];
  for (int slot = 0; slot < count; ++slot) {
    combine_from_table<float, Values>(state, scene, scene.surface[first_point + slot],
                                      slot_table(batch, slot), p);
  }
  states[off] = state;
}

// FINALIZEVALUE of every voxel of the ball; the outputs were set to NaN beforehand.
__global__ void finalize_kernel(SlabGrid grid, unsigned values, float s2,
                                const VoxelState<float>* __restrict__ states,
                                float* __restrict__ out0, float* __restrict__ out1,
                                float* __restrict__ out2, float* __restrict__ out3) {
  int i, j, k;
  if (!tiled_voxel(grid, int64_t(blockIdx.x) * blockDim.x + threadIdx.x, i, j, k)) return;
  const size_t off = (size_t(k) * grid.n + j) * grid.n + i;
  float res[kValueCount] = {0.0f, 0.0f, 0.0f, 0.0f};
  finalize_values(states[off], values, s2, res);
  if (out0) out0[off] = res[0];
  if (out1) out1[off] = res[1];
  if (out2) out2[off] = res[2];
  if (out3) out3[off] = res[3];
}

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
    if (cudaSetDevice(d) == cudaSuccess) cudaFree(nullptr);
  }
  cudaGetLastError();
  return count;
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

CudaRunReport run_fast(const PathSafetyScene<double>& host_scene, const OutputGridDesc& grid,
                       unsigned values, float* const out[kValueCount],
                       const CudaRunOptions& options, int devices) {
  const int n = grid.n;
  const size_t voxels = size_t(n) * n * n;
  const int64_t threads_total = tiled_count(n);
  const int points = host_scene.surface_count;
  const int m = options.fast_cells, radial = options.fast_radial;
  const size_t cells = size_t(m) * size_t(m);
  const bool moments = (values & kBvv) != 0;
  const float h = float(std::sqrt(grid.axes[0][0] * grid.axes[0][0] +
                                  grid.axes[0][1] * grid.axes[0][1] +
                                  grid.axes[0][2] * grid.axes[0][2]));
  // One device finalizes in place; several download their per-voxel sums and the host adds them.
  std::vector<std::vector<VoxelState<float>>> partial(static_cast<size_t>(devices));
  std::vector<std::exception_ptr> errors(static_cast<size_t>(devices));
  std::atomic<int> points_done{0};
  std::mutex progress_mutex;
  double setup_s = 0, cast_s = 0, combine_s = 0, finish_s = 0;
  const auto t0 = std::chrono::steady_clock::now();
  const auto work = [&](int d) {
    try {
      const auto td = std::chrono::steady_clock::now();
      check(cudaSetDevice(d), "cudaSetDevice");
      const int p0 = int(int64_t(points) * d / devices), p1 = int(int64_t(points) * (d + 1) / devices);
      if (p1 <= p0) return;
      DeviceScene ds(host_scene, options.storage);
      DeviceBuffer<VoxelState<float>> states{voxels};
      check(cudaMemset(states.ptr, 0, voxels * sizeof(VoxelState<float>)), "cudaMemset");
      // As many tables at once as half the free memory holds (at most 16, or as asked).
      size_t free_bytes = 0, total_bytes = 0;
      check(cudaMemGetInfo(&free_bytes, &total_bytes), "cudaMemGetInfo");
      const size_t per_slot = cells * size_t(radial) * sizeof(float) * (moments ? 3 : 1) +
                              cells * sizeof(DirectionCrossing);
      const size_t max_slots = options.fast_slots > 0 ? size_t(options.fast_slots) : 16;
      const int slots =
          int(std::max<size_t>(1, std::min<size_t>(max_slots, free_bytes / 2 / per_slot)));
      DeviceBuffer<float> c0(cells * radial * slots), c1, c2;
      if (moments) {
        c1.allocate(cells * radial * slots);
        c2.allocate(cells * radial * slots);
      }
      DeviceBuffer<DirectionCrossing> crossing(cells * slots);
      TableBatch batch{};
      batch.first = {m,      radial, int64_t(cells), h, 0.5f * h, c0.ptr, c1.ptr,
                     c2.ptr, crossing.ptr};
      batch.value_stride = cells * size_t(radial);
      batch.cell_stride = cells;
      SlabGrid g{};
      for (int a = 0; a < 3; ++a) {
        g.origin[a] = grid.origin[a];
        for (int b = 0; b < 3; ++b) g.axes[a][b] = grid.axes[a][b];
      }
      g.n = n;
      g.half = grid.half;
      g.max_sq = grid.max_sq;
      check(cudaDeviceSynchronize(), "fast mode setup");
      if (d == 0) setup_s = seconds_since(td);
      EventPair cast_events, combine_events;
      double cast_ms = 0, combine_ms = 0;
      with_value_set(values, [&](auto tag) {
        constexpr unsigned kValues = decltype(tag)::value;
        for (int p = p0; p < p1; p += slots) {
          const int count = std::min(slots, p1 - p);
          const dim3 cast_blocks(unsigned((cells + 255) / 256), unsigned(count));
          check(cudaEventRecord(cast_events.begin), "cudaEventRecord");
          if (options.storage == BlockingStorage::kTexture) {
            cast_directions_kernel<<<cast_blocks, 256>>>(
                ds.scene, batch, p, count, TextureSampler{ds.texture, ds.scene.blocking});
          } else {
            cast_directions_kernel<<<cast_blocks, 256>>>(ds.scene, batch, p, count,
                                                         GridSampler<float>{ds.scene.blocking});
          }
          check(cudaGetLastError(), "cast kernel launch");
          check(cudaEventRecord(cast_events.end), "cudaEventRecord");
          check(cudaEventRecord(combine_events.begin), "cudaEventRecord");
          combine_tables_kernel<kValues><<<unsigned(threads_total / 256), 256>>>(
              ds.scene, batch, p, count, g, states.ptr);
          check(cudaGetLastError(), "combine kernel launch");
          check(cudaEventRecord(combine_events.end), "cudaEventRecord");
          check(cudaDeviceSynchronize(), "fast path safety kernels");
          cast_ms += event_ms(cast_events.begin, cast_events.end);
          combine_ms += event_ms(combine_events.begin, combine_events.end);
          const int done = points_done += count;
          if (options.progress) {
            std::lock_guard<std::mutex> lock(progress_mutex);
            options.progress(double(done) / double(points));
          }
        }
      });
      if (d == 0) {
        cast_s = cast_ms * 1e-3;
        combine_s = combine_ms * 1e-3;
      }
      const auto tf = std::chrono::steady_clock::now();
      if (devices == 1) {
        DeviceBuffer<float> results[kValueCount];
        float* dev_out[kValueCount] = {nullptr, nullptr, nullptr, nullptr};
        for (int v = 0; v < kValueCount; ++v) {
          if (!(values & (1u << v))) continue;
          results[v].allocate(voxels);
          dev_out[v] = results[v].ptr;
          check(cudaMemset(dev_out[v], 0xFF, voxels * sizeof(float)), "cudaMemset");  // NaN
        }
        finalize_kernel<<<unsigned(threads_total / 256), 256>>>(
            g, values, float(host_scene.s2), states.ptr, dev_out[0], dev_out[1], dev_out[2],
            dev_out[3]);
        check(cudaGetLastError(), "finalize kernel launch");
        check(cudaDeviceSynchronize(), "finalize kernel");
        if (options.wait_for_outputs) options.wait_for_outputs();
        for (int v = 0; v < kValueCount; ++v) {
          if (!dev_out[v]) continue;
          check(cudaMemcpy(out[v], dev_out[v], voxels * sizeof(float), cudaMemcpyDeviceToHost),
                "download results");
        }
      } else {
        partial[size_t(d)].resize(voxels);
        check(cudaMemcpy(partial[size_t(d)].data(), states.ptr,
                         voxels * sizeof(VoxelState<float>), cudaMemcpyDeviceToHost),
              "download states");
      }
      if (d == 0) finish_s = seconds_since(tf);
    } catch (...) {
      errors[size_t(d)] = std::current_exception();
    }
  };
  std::vector<std::thread> threads;
  for (int d = 0; d < devices; ++d) threads.emplace_back(work, d);
  for (auto& t : threads) t.join();
  for (auto& e : errors) {
    if (e) std::rethrow_exception(e);
  }
  if (devices > 1) {
    // Sum the devices' partial states (counts and sums add), finalize.
    const auto tf = std::chrono::steady_clock::now();
    if (options.wait_for_outputs) options.wait_for_outputs();
    const float nan = std::numeric_limits<float>::quiet_NaN();
    for (int k = 0; k < n; ++k) {
      for (int j = 0; j < n; ++j) {
        for (int i = 0; i < n; ++i) {
          const size_t off = (size_t(k) * n + j) * n + i;
          const int64_t di = i - grid.half, dj = j - grid.half, dk = k - grid.half;
          const bool inside = di * di + dj * dj + dk * dk <= grid.max_sq;
          VoxelState<float> sum{};
          for (const auto& part : partial) {
            if (part.empty() || !inside) continue;
            const VoxelState<float>& s = part[off];
            sum.svv.visible += s.svv.visible;
            sum.svv.clear += s.svv.clear;
            sum.isbv.sum += s.isbv.sum;
            sum.ivbv.sum += s.ivbv.sum;
            sum.bvv.sum += s.bvv.sum;
          }
          float res[kValueCount] = {nan, nan, nan, nan};
          if (inside) finalize_values(sum, values, float(host_scene.s2), res);
          for (int v = 0; v < kValueCount; ++v) {
            if (out[v]) out[v][off] = res[v];
          }
        }
      }
    }
    finish_s += seconds_since(tf);
  }
  CudaRunReport report;
  report.device_count = devices;
  report.devices = "cuda:" + device_name(0) + " x" + std::to_string(devices);
  report.kernel_seconds = seconds_since(t0);
  report.phases = {{"setup", setup_s}, {"cast", cast_s}, {"combine", combine_s},
                   {"finish", finish_s}};
  return report;
}

}  // namespace

CudaRunReport run_path_safety_cuda(const PathSafetyScene<double>& host_scene,
                                   const OutputGridDesc& grid, unsigned values,
                                   float* const out[kValueCount], const CudaRunOptions& options) {
  int devices = cuda_device_count();
  if (devices == 0) throw Error("CUDA: no device found");
  if (options.max_devices > 0) devices = std::min(devices, options.max_devices);
  if (options.fast_cells > 0) return run_fast(host_scene, grid, values, out, options, devices);
  const int n = grid.n;
  // Slabs: whole slices, balanced by the number of ball voxels rather than by slice count.
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

  std::atomic<int64_t> slices_done{0};
  std::once_flag outputs_ready;
  std::mutex progress_mutex;
  std::vector<std::exception_ptr> errors(static_cast<size_t>(devices));
  std::string names;
  for (int d = 0; d < devices; ++d) {
    cudaDeviceProp prop{};
    if (cudaGetDeviceProperties(&prop, d) == cudaSuccess) names = prop.name;
  }
  const auto t0 = std::chrono::steady_clock::now();
  const auto work = [&](int d) {
    try {
      check(cudaSetDevice(d), "cudaSetDevice");
      const int z0 = bounds[size_t(d)], z1 = bounds[size_t(d) + 1];
      if (z1 <= z0) return;
      DeviceScene ds(host_scene, options.storage);
      const size_t slab = size_t(z1 - z0) * size_t(n) * size_t(n);
      DeviceBuffer<float> buffers[kValueCount];
      float* dev_out[kValueCount] = {nullptr, nullptr, nullptr, nullptr};
      for (int v = 0; v < kValueCount; ++v) {
        if (values & (1u << v)) {
          buffers[v].allocate(slab);
          dev_out[v] = buffers[v].ptr;
          // All bits set is a NaN: voxels outside the ball stay "not computed".
          check(cudaMemset(dev_out[v], 0xFF, slab * sizeof(float)), "cudaMemset");
        }
      }
      SlabGrid g{};
      for (int a = 0; a < 3; ++a) {
        g.origin[a] = grid.origin[a];
        for (int b = 0; b < 3; ++b) g.axes[a][b] = grid.axes[a][b];
      }
      g.n = n;
      g.z_slab = z0;
      g.half = grid.half;
      g.max_sq = grid.max_sq;
      const dim3 block(8, 8, 4);
      constexpr int kSlicesPerLaunch = 8;
      with_value_set(values, [&](auto tag) {
        constexpr unsigned kValues = decltype(tag)::value;
        for (int z = z0; z < z1; z += kSlicesPerLaunch) {
          g.z_begin = z;
          g.z_end = std::min(z + kSlicesPerLaunch, z1);
          const dim3 blocks((n + 7) / 8, (n + 7) / 8, (g.z_end - g.z_begin + 3) / 4);
          if (options.storage == BlockingStorage::kTexture) {
            path_safety_kernel<kValues><<<blocks, block>>>(ds.scene, g, TextureSampler{ds.texture, ds.scene.blocking},
                                                           dev_out[0], dev_out[1], dev_out[2],
                                                           dev_out[3]);
          } else {
            path_safety_kernel<kValues><<<blocks, block>>>(
                ds.scene, g, GridSampler<float>{ds.scene.blocking}, dev_out[0], dev_out[1],
                dev_out[2], dev_out[3]);
          }
          check(cudaGetLastError(), "kernel launch");
          check(cudaDeviceSynchronize(), "path safety kernel");
          const int64_t done = slices_done += (g.z_end - g.z_begin);
          if (options.progress) {
            std::lock_guard<std::mutex> lock(progress_mutex);
            options.progress(double(done) / double(n));
          }
        }
      });
      if (options.wait_for_outputs) std::call_once(outputs_ready, options.wait_for_outputs);
      for (int v = 0; v < kValueCount; ++v) {
        if (!dev_out[v]) continue;
        check(cudaMemcpy(out[v] + size_t(z0) * size_t(n) * size_t(n), dev_out[v],
                         slab * sizeof(float), cudaMemcpyDeviceToHost),
              "download results");
      }
    } catch (...) {
      errors[size_t(d)] = std::current_exception();
    }
  };
  std::vector<std::thread> threads;
  for (int d = 0; d < devices; ++d) threads.emplace_back(work, d);
  for (auto& t : threads) t.join();
  for (auto& e : errors) {
    if (e) std::rethrow_exception(e);
  }
  CudaRunReport report;
  report.device_count = devices;
  report.devices = "cuda:" + names + " x" + std::to_string(devices);
  report.kernel_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return report;
}

}  // namespace crepuscular::kernels
