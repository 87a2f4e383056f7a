#include "kernels/gaussian_cuda.hpp"

#include <cuda_runtime.h>

#include "kernels/cuda_memory.cuh"

namespace crepuscular::kernels {
namespace {

using cuda::check;
using cuda::DeviceBuffer;

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

}  // namespace

bool gaussian_box_cuda(const float* in, const int64_t lo[3], const int64_t dims[3],
                       const int64_t image[3], const std::vector<double> taps[3], float* out) {
  int devices = 0;
  if (cudaGetDeviceCount(&devices) != cudaSuccess || devices == 0) {
    cudaGetLastError();  // clear the sticky "no driver" error
    return false;
  }
  check(cudaSetDevice(0), "cudaSetDevice");
  Box box{};
  for (int a = 0; a < 3; ++a) {
    box.lo[a] = lo[a];
    box.m[a] = dims[a];
    box.n[a] = image[a];
  }
  const size_t voxels = size_t(dims[0]) * size_t(dims[1]) * size_t(dims[2]);
  if (voxels == 0) return true;
  DeviceBuffer<float> a(voxels), b(voxels);
  size_t tap_count = 0;
  for (int axis = 0; axis < 3; ++axis) tap_count += taps[axis].size();
  DeviceBuffer<double> t(tap_count);
  size_t offset[3] = {0, 0, 0};
  for (int axis = 0, at = 0; axis < 3; at += int(taps[axis].size()), ++axis) {
    offset[axis] = size_t(at);
    check(cudaMemcpy(t.ptr + at, taps[axis].data(), taps[axis].size() * sizeof(double),
                     cudaMemcpyHostToDevice),
          "upload taps");
  }
  check(cudaMemcpy(a.ptr, in, voxels * sizeof(float), cudaMemcpyHostToDevice), "upload box");
  const unsigned threads = 256;
  const unsigned blocks = unsigned((voxels + threads - 1) / threads);
  // z, then y, then x, as the host.
  gaussian_pass<<<blocks, threads>>>(a.ptr, b.ptr, box, 2, t.ptr + offset[2], int(taps[2].size()));
  gaussian_pass<<<blocks, threads>>>(b.ptr, a.ptr, box, 1, t.ptr + offset[1], int(taps[1].size()));
  gaussian_pass<<<blocks, threads>>>(a.ptr, b.ptr, box, 0, t.ptr + offset[0], int(taps[0].size()));
  check(cudaGetLastError(), "Gaussian passes");
  check(cudaMemcpy(out, b.ptr, voxels * sizeof(float), cudaMemcpyDeviceToHost), "download box");
  return true;
}

}  // namespace crepuscular::kernels
