// scandyn/instance/traversal.hpp: walks of the tree inside one thread, shared by the instance functions
// (rnea_instance, crba_instance / fd_jsi_instance, aba_instance).
#pragma once

#include "scandyn/build_config.hpp"
#include "scandyn/instance/thread_model.hpp"

#if SCANDYN_HAS_CUDA
namespace scandyn {
namespace cuda {

#if defined(__CUDACC__)
namespace fd_detail {

// Is body j a proper ancestor of body k?
template <class S, int C>
__host__ __device__ __forceinline__ bool is_ancestor(const ThreadModelParams<S, C>& m, Index j, Index k) {
  return (m.ancestors[k] >> j) & 1ull;
}

// Calls f(j) for every proper ancestor j of body k, nearest first (the order of the
// reference's for_path). Unrolled: a loop of compile-time indices (once k is one)
// over the ancestor bits, so that arrays indexed by j stay in registers; otherwise
// the walk up the parents.
template <bool kUnrolled, class S, int C, class F>
__host__ __device__ __forceinline__ void for_ancestors(const ThreadModelParams<S, C>& m, Index k, F&& f) {
  if constexpr (kUnrolled) {
#pragma unroll
    for (Index j = C - 2; j >= 0; --j)
      if (j < k && is_ancestor(m, j, k)) f(j);
  } else {
    for (Index j = m.body[k].parent; j >= 0; j = m.body[j].parent) f(j);
  }
}

// Calls f(k) for every proper descendant k of body i (any order; ascending here).
template <bool kUnrolled, class S, int C, class F>
__host__ __device__ __forceinline__ void for_descendants(const ThreadModelParams<S, C>& m, Index i, F&& f) {
#pragma unroll(kUnrolled ? C : 1)
  for (Index k = 1; k < C; ++k)
    if (k > i && k < m.nv && is_ancestor(m, i, k)) f(k);
}

}  // namespace fd_detail
#endif  // __CUDACC__

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
