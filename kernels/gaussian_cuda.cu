#include "kernels/gaussian_cuda.hpp"

#include <cuda_runtime.h>

#include <algorithm>

#include "kernels/cuda_memory.cuh"

namespace crepuscular::kernels {
namespace {

using cuda::check;
using cuda::OwnStream;
using cuda::StreamBuffer;

struct Box {
  long long lo[3], m[3], n[3];
};

// One pass along `axis`: out(x) = sum_q taps[q] in(clamp(x + q - r)) over q in order, the input
// 0 outside the box; one thread per box voxel.
__global__ void gaussian_pass(const float* __restrict__ in, float* __restrict__ out, Box box,
                              int axis, const double* __restrict__ taps, int count) {
  const long long v = (long long)blockIdx.x * blockDim.x + threadIdx.x;
  const long long total = box.m[0] * box.m[1] * box.m[2];
  if (v >= total) return;
  long long c[3] = {v % box.m[0], (v / box.m[0]) % box.m[1], v / (box.m[0] * box.m[1])};
  const long long stride = axis == 0 ? 1 : axis == 1 ? box.m[0] : box.m[0] * box.m[1];
  const long long at = c[axis] + box.lo[axis];  // image index along the axis
  const long long row = v - c[axis] * stride;   // the box voxel at local index 0 on this line
  const int r = count / 2;
  const long long b0 = box.lo[axis], b1 = box.lo[axis] + box.m[axis] - 1, edge = box.n[axis] - 1;
  double acc = 0.0;
  for (int q = 0; q < count; ++q) {
    long long x = at + q - r;
    x = x < 0 ? 0 : x > edge ? edge : x;
    if (x < b0 || x > b1) continue;  // 0 there: adds nothing
    acc = __dadd_rn(acc, __dmul_rn(taps[q], double(in[row + (x - b0) * stride])));
  }
  out[v] = __double2float_rn(acc);
}

// The level's mask over its box: 1 where codes holds `code`, else 0.
__global__ void level_mask(const uint8_t* __restrict__ codes, float* __restrict__ out, Box box,
                           uint8_t code) {
  const long long v = (long long)blockIdx.x * blockDim.x + threadIdx.x;
  const long long total = box.m[0] * box.m[1] * box.m[2];
  if (v >= total) return;
  const long long i = v % box.m[0] + box.lo[0], j = (v / box.m[0]) % box.m[1] + box.lo[1],
                  k = v / (box.m[0] * box.m[1]) + box.lo[2];
  out[v] = codes[(k * box.n[1] + j) * box.n[0] + i] == code ? 1.0f : 0.0f;
}

// b = max(b, coeff * max(mask, smoothed)) over the box; smoothed null: no margin (0).
__global__ void level_max(const uint8_t* __restrict__ codes, const float* __restrict__ smoothed,
                          float* __restrict__ b, Box box, uint8_t code, float coeff) {
  const long long v = (long long)blockIdx.x * blockDim.x + threadIdx.x;
  const long long total = box.m[0] * box.m[1] * box.m[2];
  if (v >= total) return;
  const long long i = v % box.m[0] + box.lo[0], j = (v / box.m[0]) % box.m[1] + box.lo[1],
                  k = v / (box.m[0] * box.m[1]) + box.lo[2];
  const long long at = (k * box.n[1] + j) * box.n[0] + i;
  const float m = codes[at] == code ? 1.0f : 0.0f;
  const float s = smoothed ? smoothed[v] : 0.0f;
  // The host's std::max(b, c * std::max(m, s)), no NaN: one rounded product.
  b[at] = fmaxf(b[at], __fmul_rn(coeff, fmaxf(m, s)));
}

Box box_of(const int64_t lo[3], const int64_t dims[3], const int64_t image[3]) {
  Box box{};
  for (int a = 0; a < 3; ++a) {
    box.lo[a] = lo[a];
    box.m[a] = dims[a];
    box.n[a] = image[a];
  }
  return box;
}

}  // namespace

bool blocking_levels_cuda(const uint8_t* codes, const int64_t image[3],
                          const std::vector<MarginLevel>& levels, float* b) {
  int devices = 0;
  if (cudaGetDeviceCount(&devices) != cudaSuccess || devices == 0) {
    cudaGetLastError();
    return false;
  }
  check(cudaSetDevice(0), "cudaSetDevice");
  const size_t voxels = size_t(image[0]) * size_t(image[1]) * size_t(image[2]);
  size_t box_voxels = 0, tap_count = 0;
  for (const MarginLevel& level : levels) {
    if (level.taps[0].empty()) continue;
    box_voxels = std::max(box_voxels, size_t(level.dims[0]) * size_t(level.dims[1]) *
                                          size_t(level.dims[2]));
    for (int a = 0; a < 3; ++a) tap_count += level.taps[a].size();
  }
  // On a stream of its own: a phase's blocking volume is made beside another phase's rays.
  const OwnStream own;
  const cudaStream_t st = own.stream;
  StreamBuffer<uint8_t> c(st);
  StreamBuffer<float> volume(st), s0(st), s1(st);
  StreamBuffer<double> t(st);
  if (!c.try_allocate(voxels) || !volume.try_allocate(voxels) || !s0.try_allocate(box_voxels) ||
      !s1.try_allocate(box_voxels) || !t.try_allocate(tap_count)) {
    return false;
  }
  check(cudaMemcpyAsync(c.ptr, codes, voxels, cudaMemcpyHostToDevice, st), "upload level map");
  check(cudaMemsetAsync(volume.ptr, 0, voxels * sizeof(float), st), "clear blocking volume");
  const unsigned threads = 256;
  size_t at = 0;
  for (const MarginLevel& level : levels) {
    const Box box = box_of(level.lo, level.dims, image);
    const size_t n = size_t(level.dims[0]) * size_t(level.dims[1]) * size_t(level.dims[2]);
    if (n == 0) continue;
    const unsigned blocks = unsigned((n + threads - 1) / threads);
    if (level.taps[0].empty()) {
      level_max<<<blocks, threads, 0, st>>>(c.ptr, nullptr, volume.ptr, box, level.code,
                                            level.coeff);
      continue;
    }
    double* taps[3];
    for (int a = 0; a < 3; ++a) {
      taps[a] = t.ptr + at;
      check(cudaMemcpyAsync(taps[a], level.taps[a].data(), level.taps[a].size() * sizeof(double),
                            cudaMemcpyHostToDevice, st),
            "upload taps");
      at += level.taps[a].size();
    }
    level_mask<<<blocks, threads, 0, st>>>(c.ptr, s0.ptr, box, level.code);
    // z, then y, then x, as the host.
    gaussian_pass<<<blocks, threads, 0, st>>>(s0.ptr, s1.ptr, box, 2, taps[2],
                                              int(level.taps[2].size()));
    gaussian_pass<<<blocks, threads, 0, st>>>(s1.ptr, s0.ptr, box, 1, taps[1],
                                              int(level.taps[1].size()));
    gaussian_pass<<<blocks, threads, 0, st>>>(s0.ptr, s1.ptr, box, 0, taps[0],
                                              int(level.taps[0].size()));
    level_max<<<blocks, threads, 0, st>>>(c.ptr, s1.ptr, volume.ptr, box, level.code, level.coeff);
  }
  check(cudaGetLastError(), "blocking levels");
  check(cudaMemcpyAsync(b, volume.ptr, voxels * sizeof(float), cudaMemcpyDeviceToHost, st),
        "download blocking volume");
  check(cudaStreamSynchronize(st), "blocking levels");
  return true;
}

bool gaussian_box_cuda(const float* in, const int64_t lo[3], const int64_t dims[3],
                       const int64_t image[3], const std::vector<double> taps[3], float* out) {
  int devices = 0;
  if (cudaGetDeviceCount(&devices) != cudaSuccess || devices == 0) {
    cudaGetLastError();  // clear the sticky "no driver" error
    return false;
  }
  check(cudaSetDevice(0), "cudaSetDevice");
  const Box box = box_of(lo, dims, image);
  const size_t voxels = size_t(dims[0]) * size_t(dims[1]) * size_t(dims[2]);
  if (voxels == 0) return true;
  const OwnStream own;
  const cudaStream_t st = own.stream;
  StreamBuffer<float> a(st), b(st);
  a.allocate(voxels);
  b.allocate(voxels);
  size_t tap_count = 0;
  for (int axis = 0; axis < 3; ++axis) tap_count += taps[axis].size();
  StreamBuffer<double> t(st);
  t.allocate(tap_count);
  size_t offset[3] = {0, 0, 0};
  for (int axis = 0, at = 0; axis < 3; at += int(taps[axis].size()), ++axis) {
    offset[axis] = size_t(at);
    check(cudaMemcpyAsync(t.ptr + at, taps[axis].data(), taps[axis].size() * sizeof(double),
                          cudaMemcpyHostToDevice, st),
          "upload taps");
  }
  check(cudaMemcpyAsync(a.ptr, in, voxels * sizeof(float), cudaMemcpyHostToDevice, st),
        "upload box");
  const unsigned threads = 256;
  const unsigned blocks = unsigned((voxels + threads - 1) / threads);
  // z, then y, then x, as the host.
  gaussian_pass<<<blocks, threads, 0, st>>>(a.ptr, b.ptr, box, 2, t.ptr + offset[2],
                                            int(taps[2].size()));
  gaussian_pass<<<blocks, threads, 0, st>>>(b.ptr, a.ptr, box, 1, t.ptr + offset[1],
                                            int(taps[1].size()));
  gaussian_pass<<<blocks, threads, 0, st>>>(a.ptr, b.ptr, box, 0, t.ptr + offset[0],
                                            int(taps[0].size()));
  check(cudaGetLastError(), "Gaussian passes");
  check(cudaMemcpyAsync(out, b.ptr, voxels * sizeof(float), cudaMemcpyDeviceToHost, st),
        "download box");
  check(cudaStreamSynchronize(st), "Gaussian passes");
  return true;
}

}  // namespace crepuscular::kernels
