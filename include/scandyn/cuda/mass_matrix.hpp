// scandyn/cuda/mass_matrix.hpp: the joint-space inertia (mass) matrix M(q) of a
// batch on a CUDA device, by the composite-rigid-body algorithm (CRBA).
//
// Layers, as for inverse and forward dynamics:
//   crba_instance()          __host__ __device__ (scandyn/instance/crba_instance.hpp): one
//                            instance's M as a packed lower triangle in per-thread
//                            arrays; the same function builds fd_jsi_instance's M;
//   mass_matrix_instance()   __host__ __device__: crba_instance, then the full nv x nv
//                            matrix written out (scandyn/instance/crba_instance.hpp);
//   crba_instances_kernel    one thread per instance (kernels/mass_matrix.cu);
//   launch_crba_instances()  host wrapper: device pointers, a stream, returns the
//                            cudaError_t of the launch, never synchronises.
// and the engine CudaMassMatrix on top:
//     compute()        HOST pointers: copies q in, launches, copies M out, synchronises;
//     compute_async()  DEVICE pointers and your stream: one launch, no copy, no
//                      synchronisation, no allocation; returns the cudaError_t.
//
// Layout of M: a BatchView with nv * nv entries per instance, entry e = i * nv + j
// of instance b holding M(i, j): M.at(i * nv + j, b). Every entry is written, both
// triangles, zeros where neither body is an ancestor of the other (M is symmetric,
// so reading it column-major gives the same). Both usual layouts store coalesced:
// BatchView::soa(M, nv * nv, B), M[(i * nv + j) * B + b], each thread writing its
// own entries (a warp's 32 threads write 32 consecutive scalars); and
// BatchView::aos(M, nv * nv, B), M[b * nv * nv + i * nv + j], each instance's matrix
// contiguous and row-major (what scandyn::crba writes per instance, `scandyn eval
// --algo mass` prints as columns M_<i>_<j>, and Python's (B, nv, nv) arrays are),
// which the kernel stages a warp's 32 matrices at a time through shared memory and
// stores instance by instance (any layout whose |dof_stride| < |batch_stride|).
// q is (nv x B) as for the other engines, any strides.
//
// Strategies: "crba_thread", one thread per instance, models of up to kMaxThreadDofs
// DoF (kernels for capacities 8, 16, 32 and 64, the model as a __grid_constant__
// parameter, as the inverse and forward dynamics); "crba_block" beyond, one thread
// block per instance (the kernel DenseJsiPlan builds its mass matrices with,
// kernels/crba_block.hpp): the transforms in parallel over bodies, the composite
// inertias leaves to root on one thread, then a thread per column.
//
// Accuracy: the serial crba's formulas and order of summation (on the host
// mass_matrix_instance is bit-identical to it, measured in double and float); on the
// device, FMA contraction and the device's sin/cos (the library's, in float too)
// make the difference.
#pragma once

#include <cstddef>
#include <memory>
#include <string>

#include "scandyn/algorithm/steps.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/cuda/general_dynamics.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"
#include "scandyn/instance/crba_instance.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

namespace scandyn {
namespace cuda {

namespace detail {
template <class S>
class CrbaBlocks;  // kernels/crba_block.hpp: the CRBA with a thread block per instance
}  // namespace detail

// Threads per block of crba_instances_kernel.
inline constexpr int kMassInstancesBlock = 128;

// M_out (nv * nv entries x B, M(i, j) at entry i * nv + j) = M(q) for the B =
// q.batch instances: one launch of crba_instances_kernel on `stream`. Every
// pointer is a DEVICE pointer (views with any strides); nothing is copied,
// allocated or synchronised. Returns cudaErrorInvalidValue when the batch sizes
// disagree or a pointer is null with B > 0, else the launch's error (kernel faults
// surface later, at your synchronisation). B = 0 launches nothing.
template <class S, class Bd>
cudaError_t launch_crba_instances(const ThreadModel<S, Bd>& model, const BatchView<const S>& q, const BatchView<S>& M_out,
                                  cudaStream_t stream);

// The batched mass-matrix engine on one CUDA device (the device current at
// construction).
template <class S>
class CudaMassMatrix final : public MassMatrix<S> {
 public:
  // Prepares the model and allocates the device buffers compute() stages through:
  // q and M for options.max_batch instances, (nv + nv^2) * sizeof(S) * max_batch
  // bytes (compute_async needs none of them); beyond kMaxThreadDofs DoF also the
  // block kernel's scratch (the bodies, and each instance's transforms and
  // composite inertias: nv * (sizeof(Transform) + sizeof(Inertia)) per instance).
  // options.strategy must be Auto or Recursion (inverse dynamics' choice; the mass
  // matrix has one algorithm). Throws BackendError when there is no usable device,
  // or the buffers do not fit in device memory (the message gives the bytes needed
  // and the bytes free).
  CudaMassMatrix(const ModelTpl<S>& model, const BackendOptions& options);
  ~CudaMassMatrix() override;
  CudaMassMatrix(const CudaMassMatrix&) = delete;
  CudaMassMatrix& operator=(const CudaMassMatrix&) = delete;

  // HOST pointers, any strides: q (nv x B), M (nv * nv entries x B, see the layout
  // above). Copies q to the device, runs the kernel, copies M back (writing only M's
  // entries: gaps between strided entries keep their contents) and waits for all
  // of it on the engine's own stream. Throws BackendError for B > max_batch, views
  // whose batch sizes disagree, a null pointer with B > 0, an M view whose entries
  // overlap, or any CUDA error.
  void compute(const BatchView<const S>& q, const BatchView<S>& M) override;

  // DEVICE pointers, any strides, on `stream`. Asynchronous: returns after queuing
  // the kernel, with no hidden synchronisation, copy or allocation.
  //   crba_thread: launch_crba_instances with this engine's model; not limited by
  //                max_batch; safe from several host threads on different streams;
  //   crba_block:  B <= max_batch (else cudaErrorInvalidValue); the engine's
  //                scratch, so one stream at a time.
  cudaError_t compute_async(const BatchView<const S>& q, const BatchView<S>& M, cudaStream_t stream);

  // "crba_thread" (one thread per instance, up to kMaxThreadDofs DoF),
  // "crba_block" (one thread block per instance, beyond) or "crba_general" (joints
  // of any type: spherical, a floating base beyond the thread kernels; one thread
  // per instance, scandyn/cuda/general_dynamics.hpp)
  std::string strategy() const override {
    return general_ ? "crba_general" : blocks_ ? "crba_block" : "crba_thread";
  }
  BackendKind backend() const override { return BackendKind::Cuda; }

  const ZThreadModel<S>* thread_model() const { return thread_.get(); }  // null for crba_block
  Index nv() const { return nv_; }
  Index max_batch() const { return max_batch_; }
  int device() const { return device_; }
  std::size_t device_bytes() const { return bytes_; }  // staging buffers and the block kernel's scratch

 private:
  Index nv_ = 0;
  Index nq_ = 0;  // entries of q (nv + 1 with a floating base)
  Index nb_ = 0;  // bodies (entries of fext)
  Index max_batch_ = 0;
  int device_ = 0;
  std::size_t bytes_ = 0;
  std::unique_ptr<ZThreadModel<S>> thread_;              // crba_thread
  std::unique_ptr<detail::CrbaBlocks<S>> blocks_;       // crba_block
  std::unique_ptr<GeneralPlan<S>> general_;             // crba_general
  // compute()'s stream and its one allocation: q (nv x max_batch), then M (nv^2 x max_batch)
  std::unique_ptr<detail::StagingBuffer> staging_;
};

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
