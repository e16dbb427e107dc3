// scandyn/config.hpp: compilation macros shared by host and device code.
#pragma once

// SCANDYN_HD marks functions that run on both the host and a CUDA device.
// Under nvcc they become __host__ __device__; elsewhere they are plain inline.
#if defined(__CUDACC__)
#define SCANDYN_HD __host__ __device__ __forceinline__
#else
#define SCANDYN_HD inline
#endif

namespace scandyn {

// Index type for bodies and degrees of freedom.
using Index = int;

}  // namespace scandyn
