// One macro that marks the path-safety math as callable from host and device code.
#pragma once

#if defined(__CUDACC__)
#define CREPUSCULAR_HD __host__ __device__ inline
#else
#define CREPUSCULAR_HD inline
#endif

// The same, inlined into its caller whatever the compiler's estimate: for the per-sample functions
// of the ray march, where a call costs as much as the work.
#if defined(__CUDACC__)
#define CREPUSCULAR_HD_INLINE __host__ __device__ __forceinline__
#elif defined(__GNUC__)
#define CREPUSCULAR_HD_INLINE inline __attribute__((always_inline))
#else
#define CREPUSCULAR_HD_INLINE inline
#endif
