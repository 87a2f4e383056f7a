// One macro that marks the path-safety math as callable from host and device code.
#pragma once

#if defined(__CUDACC__)
#define CREPUSCULAR_HD __host__ __device__ inline
#else
#define CREPUSCULAR_HD inline
#endif
