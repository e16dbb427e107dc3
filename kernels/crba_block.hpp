// kernels/crba_block.hpp (internal): the CRBA with one thread block per instance,
// for models beyond the thread-per-instance kernels (more than kMaxThreadDofs DoF).
// Defined in kernels/fd_dense.cu; used by DenseJsiPlan (forward dynamics,
// scandyn/cuda/fd_dense.hpp) and CudaMassMatrix (scandyn/cuda/mass_matrix.hpp), so
// both run the same kernel. Not installed: it is no part of the public API.
//
// Per instance (one block): the joint transforms Xup_i in parallel over the bodies,
// the composite inertias Ic_i from the leaves to the root on one thread (the serial
// crba's order of summation), then one thread per column i carrying F_i = Ic_i S_i
// to the root, M(i, j) = M(j, i) = S_j^T F (the crba_* step functions of
// scandyn/algorithm/steps.hpp, as scandyn::crba).
#pragma once

#include <cuda_runtime.h>

#include <cstddef>

#include "scandyn/engine.hpp"

namespace scandyn {
namespace cuda {
namespace detail {

// Threads per block of the CRBA kernel.
inline constexpr int kCrbaBlock = 128;

// The model's bodies and parents in device memory, and per-instance scratch for
// max_batch instances: each instance's transforms Xup (nv) and composite inertias
// Ic (nv).
template <class S>
class CrbaBlocks {
 public:
  // Device bytes a CrbaBlocks of an nv-DoF model for max_batch instances holds.
  static std::size_t bytes_needed(Index nv, Index max_batch);

  // Copies the model to the device (synchronising once) and allocates the scratch.
  // Throws BackendError when cudaMalloc or a copy fails.
  CrbaBlocks(const ModelTpl<S>& model, Index max_batch);
  ~CrbaBlocks();
  CrbaBlocks(const CrbaBlocks&) = delete;
  CrbaBlocks& operator=(const CrbaBlocks&) = delete;

  // M(q) of the B = q.batch instances on `stream`, one block per instance. M is a
  // view of nv * nv entries per instance: entry (i * nv + j, b) receives M(i, j) of
  // instance b, both triangles, zeros included (row- and column-major agree: M is
  // symmetric). Device pointers. Returns cudaErrorInvalidValue for B > max_batch or
  // disagreeing batch sizes, else the launch's error; B = 0 launches nothing.
  cudaError_t launch(const BatchView<const S>& q, const BatchView<S>& M, cudaStream_t stream) const;

  // The same, and the forward dynamics' right-hand side rhs[b * nv + i] =
  // tau(i, b) - h[i * B + b] (h: nv x B, structure of arrays) in the same kernel.
  cudaError_t launch_with_rhs(const BatchView<const S>& q, const BatchView<S>& M, const BatchView<const S>& tau,
                              const S* h, S* rhs, cudaStream_t stream) const;

  Index nv() const { return nv_; }
  Index max_batch() const { return max_batch_; }
  std::size_t device_bytes() const { return bytes_; }

 private:
  Index nv_ = 0;
  Index max_batch_ = 0;
  std::size_t bytes_ = 0;
  void* block_ = nullptr;           // one allocation holding the four arrays below
  Body<S>* body_ = nullptr;         // (nv) the bodies
  int* parent_ = nullptr;           // (nv) their parents, -1 for the base
  Transform<S>* Xup_ = nullptr;     // (max_batch x nv) parent -> body transforms
  Inertia<S>* Ic_ = nullptr;        // (max_batch x nv) composite inertias
};

}  // namespace detail
}  // namespace cuda
}  // namespace scandyn
