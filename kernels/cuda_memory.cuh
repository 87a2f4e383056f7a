// What every CUDA translation unit of the kernels shares: a failed call as an Error, and a device
// array freed with its owner.
#pragma once

#include <cuda_runtime.h>

#include <algorithm>
#include <string>

#include "foundation/error.hpp"

namespace crepuscular::kernels::cuda {

inline void check(cudaError_t status, const char* what) {
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
  // The same, reporting an exhausted device as false (for a caller that can fall back).
  bool try_allocate(size_t count) {
    const cudaError_t status = cudaMalloc(&ptr, std::max<size_t>(count, 1) * sizeof(T));
    if (status == cudaErrorMemoryAllocation) {
      ptr = nullptr;
      cudaGetLastError();
      return false;
    }
    check(status, "cudaMalloc");
    return true;
  }
  ~DeviceBuffer() {
    if (ptr) cudaFree(ptr);
  }
  DeviceBuffer(const DeviceBuffer&) = delete;
  DeviceBuffer& operator=(const DeviceBuffer&) = delete;
};

}  // namespace crepuscular::kernels::cuda
