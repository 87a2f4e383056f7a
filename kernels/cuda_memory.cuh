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

// A stream that neither waits for a default stream nor makes it wait: work on it runs beside the
// path safety kernels launched on the same thread's default stream (the kernels are compiled with
// per-thread default streams, so other threads' kernels run beside it anyway).
struct OwnStream {
  cudaStream_t stream = nullptr;
  OwnStream() { check(cudaStreamCreateWithFlags(&stream, cudaStreamNonBlocking), "cudaStreamCreate"); }
  ~OwnStream() {
    if (stream) {
      cudaStreamSynchronize(stream);
      cudaStreamDestroy(stream);
    }
  }
  OwnStream(const OwnStream&) = delete;
  OwnStream& operator=(const OwnStream&) = delete;
};

// A device array allocated and freed in the order of a stream (cudaMallocAsync): freeing it does
// not wait for the whole device, as cudaFree does.
template <typename T>
struct StreamBuffer {
  T* ptr = nullptr;
  cudaStream_t stream;
  explicit StreamBuffer(cudaStream_t s) : stream(s) {}
  // False for an exhausted device (for a caller that can fall back).
  bool try_allocate(size_t count) {
    const cudaError_t status =
        cudaMallocAsync(reinterpret_cast<void**>(&ptr), std::max<size_t>(count, 1) * sizeof(T), stream);
    if (status == cudaErrorMemoryAllocation) {
      ptr = nullptr;
      cudaGetLastError();
      return false;
    }
    check(status, "cudaMallocAsync");
    return true;
  }
  void allocate(size_t count) {
    if (!try_allocate(count)) check(cudaErrorMemoryAllocation, "cudaMallocAsync");
  }
  ~StreamBuffer() {
    if (ptr) cudaFreeAsync(ptr, stream);
  }
  StreamBuffer(const StreamBuffer&) = delete;
  StreamBuffer& operator=(const StreamBuffer&) = delete;
};

}  // namespace crepuscular::kernels::cuda
