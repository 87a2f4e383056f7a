// The card's trilinear sampling rate on a 512^3 float volume, with rays as coherent as the path
// safety kernel's (neighbouring threads march from neighbouring voxels toward one target):
// 3D texture with hardware filtering, and float filtering from global memory (GridSampler).
#include <cuda_runtime.h>

#include <cstdio>
#include <vector>

#include "kernels/path_safety_math.hpp"

using namespace crepuscular::kernels;

constexpr int kN = 512;
constexpr int kSteps = 512;

template <typename Sampler>
__global__ void march(Sampler sampler, float* out, float tx, float ty, float tz) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  const int j = blockIdx.y * blockDim.y + threadIdx.y;
  const int k = blockIdx.z * blockDim.z + threadIdx.z;
  const Vec3<float> p = {float(i) * 4.0f, float(j) * 4.0f, float(k) * 4.0f};
  const Vec3<float> d = {(tx - p.x) / kSteps, (ty - p.y) / kSteps, (tz - p.z) / kSteps};
  float acc = 0.0f;
  for (int s = 1; s <= kSteps; ++s) acc += sampler(Vec3<float>{p.x + s * d.x, p.y + s * d.y, p.z + s * d.z});
  out[(size_t(k) * 128 + j) * 128 + i] = acc;
}

struct Tex {
  cudaTextureObject_t t;
  __device__ float operator()(Vec3<float> q) const { return tex3D<float>(t, q.x + 0.5f, q.y + 0.5f, q.z + 0.5f); }
};

int main() {
  const size_t n = size_t(kN) * kN * kN;
  std::vector<float> host(n);
  for (size_t i = 0; i < n; ++i) host[i] = float((i * 2654435761u) % 1000) / 1000.0f;
  float* vol;
  cudaMalloc(&vol, n * sizeof(float));
  cudaMemcpy(vol, host.data(), n * sizeof(float), cudaMemcpyHostToDevice);
  cudaArray_t arr;
  cudaChannelFormatDesc desc = cudaCreateChannelDesc<float>();
  cudaMalloc3DArray(&arr, &desc, make_cudaExtent(kN, kN, kN));
  cudaMemcpy3DParms c = {};
  c.srcPtr = make_cudaPitchedPtr(host.data(), kN * sizeof(float), kN, kN);
  c.dstArray = arr;
  c.extent = make_cudaExtent(kN, kN, kN);
  c.kind = cudaMemcpyHostToDevice;
  cudaMemcpy3D(&c);
  cudaResourceDesc res = {};
  res.resType = cudaResourceTypeArray;
  res.res.array.array = arr;
  cudaTextureDesc td = {};
  td.addressMode[0] = td.addressMode[1] = td.addressMode[2] = cudaAddressModeBorder;
  td.filterMode = cudaFilterModeLinear;
  cudaTextureObject_t tex;
  cudaCreateTextureObject(&tex, &res, &td, nullptr);
  float* out;
  cudaMalloc(&out, 128 * 128 * 128 * sizeof(float));
  BlockingGrid<float> g{vol, kN, kN, kN, {}, nullptr, 0, 0, 0};
  const dim3 block(8, 8, 4), blocks(16, 16, 32);
  const double samples = 128.0 * 128 * 128 * kSteps;
  cudaEvent_t a, b;
  cudaEventCreate(&a);
  cudaEventCreate(&b);
  for (int mode = 0; mode < 2; ++mode) {
    float best = 1e30f;
    for (int rep = 0; rep < 4; ++rep) {
      const float tx = 200.0f + rep * 13.0f, ty = 260.0f - rep * 7.0f, tz = 240.0f + rep * 5.0f;
      cudaEventRecord(a);
      if (mode == 0) march<<<blocks, block>>>(Tex{tex}, out, tx, ty, tz);
      else march<<<blocks, block>>>(GridSampler<float>{g}, out, tx, ty, tz);
      cudaEventRecord(b);
      cudaEventSynchronize(b);
      float ms;
      cudaEventElapsedTime(&ms, a, b);
      if (rep > 0 && ms < best) best = ms;
    }
    cudaDeviceProp prop;
    cudaGetDeviceProperties(&prop, 0);
    std::printf("{\"device\":\"%s\",\"sampler\":\"%s\",\"samples\":%.4g,\"ms\":%.3f,\"samples_per_second\":%.4g}\n",
                prop.name, mode == 0 ? "texture (hardware trilinear)" : "global (float trilinear)",
                samples, best, samples / (best * 1e-3));
  }
  const cudaError_t e = cudaGetLastError();
  if (e != cudaSuccess) { std::printf("CUDA error: %s\n", cudaGetErrorString(e)); return 1; }
  return 0;
}
