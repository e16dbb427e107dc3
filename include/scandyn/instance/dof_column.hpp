// scandyn/instance/dof_column.hpp: one instance's entries of a batch array, as the instance functions
// (rnea_instance, crba_instance, fd_jsi_instance, aba_instance) read and write them.
#pragma once

#include <cstddef>
#include "scandyn/batch.hpp"
#include "scandyn/build_config.hpp"

#if SCANDYN_HAS_CUDA
namespace scandyn {
namespace cuda {

#if defined(__CUDACC__)
// ---- device API --------------------------------------------------------------

// One instance's entries of a strided batch array: DoF i at data[i * stride].
template <class T>
struct DofColumn {
  T* data;
  std::ptrdiff_t stride;
  __host__ __device__ __forceinline__ T& operator[](Index i) const { return data[i * stride]; }
};

// The column from entry k on (a floating base's entries skipped: ThreadModelParams::floating).
template <class T>
__host__ __device__ __forceinline__ DofColumn<T> column_from(DofColumn<T> c, Index k) {
  return {c.data + k * c.stride, c.stride};
}

// Instance b's entries of a batch view.
template <class T>
__host__ __device__ __forceinline__ DofColumn<T> instance_column(const BatchView<T>& v, long long b) {
  return {v.data + b * v.batch_stride, v.dof_stride};
}
#endif  // __CUDACC__

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
