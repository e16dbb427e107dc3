// scandyn/cuda/derivatives.hpp: the first-order derivatives of inverse and forward
// dynamics of a batch on a CUDA device, one thread per instance (models of up to
// kMaxThreadDofs DoF).
//
// Layers, as for the other CUDA engines:
//   rnea_derivatives_instance(), fd_derivatives_instance()
//                               __host__ __device__ (scandyn/instance/dynamics_derivatives.hpp):
//                               one instance, the serial reference's functions;
//   id_derivatives_lean_kernel / id_derivatives_kernel, fd_aba_kernel +
//   fd_derivatives_at_kernel / fd_derivatives_kernel
//                               one thread per instance (kernels/derivatives.cu). By
//                               default: inverse dynamics on unbranched chains of up to
//                               8 DoF (kPackedLtlCapacity) by the lean chain recursion
//                               (24 scalars of scratch per body), other models by
//                               rnea_derivatives_instance; forward dynamics runs
//                               aba_instance for qdd first, up to 8 DoF in a kernel of
//                               its own, then the derivatives (chains: the lean
//                               recursion) and the factor of M with L in registers,
//                               packed_fd_solve; beyond 8 DoF one fd_derivatives_kernel
//                               (the factor by the tree walks). For A/B, read at every
//                               launch: SCANDYN_DFD_KERNEL=packed (chains too take
//                               rnea_derivatives_instance) or tree (fd_derivatives_kernel
//                               at every capacity), SCANDYN_DID_KERNEL=recursion
//                               (id_derivatives_kernel on chains too);
//   launch_id_derivatives(), launch_fd_derivatives()
//                               host wrappers: device pointers, a stream, the launch's
//                               cudaError_t, never synchronise;
// and the engines CudaIdDerivatives / CudaFdDerivatives on top: compute() on HOST
// views (copies in, launches, copies out, synchronises), compute_async() on DEVICE
// views and a stream. Output layout: scandyn/engine.hpp (three nv * nv views; soa,
// the instance innermost, is the fast layout on the device).
//
// Per thread: nv DerivativeBody entries (72 scalars each; the lean chain recursion: 24)
// in per-thread local memory, plus the ABA's state for the forward dynamics (and, up
// to 8 DoF, L: 36 scalars in registers).
//
// Models with multi-DoF joints (a floating base, spherical joints; ModelTpl::multi_dof())
// of up to kMaxThreadDofs DoF take the general kernels instead, one thread per instance
// too: id_derivatives_general_kernel (rnea_derivatives_general_instance) and
// fd_derivatives_general_kernel (aba_general over a GeneralWork of per-thread arrays
// for qdd, then fd_derivatives_general_instance in the output blocks; the two
// scratches share their local memory), over GeneralDerivativeModel's parameter block
// of the smallest capacity C >= nv (8, 16, 32 or 64; the capacities a build compiles:
// visit_compiled_capacity). The engines pick them by the model (strategy "general").
// One instance's work: scandyn/cuda/derivatives_general.hpp (__host__ __device__).
#pragma once

#include <memory>
#include <string>
#include <variant>
#include <vector>

#include "scandyn/build_config.hpp"
#include "scandyn/engine.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

#include "scandyn/instance/thread_model.hpp"
#include "scandyn/model/model.hpp"

namespace scandyn {
namespace cuda {

namespace detail {
class StagingBuffer;  // kernels/staging.hpp
}  // namespace detail

// Threads per block of the derivative kernels.
inline constexpr int kDerivativesBlock = 64;

// out = the inverse-dynamics derivatives of the B = in.q.batch instances; DEVICE
// pointers, any strides. cudaErrorInvalidValue for batch sizes that disagree or a null
// pointer with B > 0; else the launch's error.
template <class S>
cudaError_t launch_id_derivatives(const ThreadModel<S>& model, const IdBatchIn<S>& in, const IdDerivativesOut<S>& out,
                                  cudaStream_t stream);

// out = the forward-dynamics derivatives (and qdd when out.qdd.data is set);
// failed_dof (B ints, device memory, or null): -1, or the DoF whose pivot failed.
template <class S>
cudaError_t launch_fd_derivatives(const ThreadModel<S>& model, const FdBatchIn<S>& in, const FdDerivativesOut<S>& out,
                                  int* failed_dof, cudaStream_t stream);

// ---- models with multi-DoF joints ------------------------------------------------

// The model as the general derivative kernels read it, for capacity C >= nv (the
// kernel parameter, __grid_constant__): the model's bodies in DoF order and the tree
// of its DoFs (dof_parents, dof_subtree_last, dof_runs of
// scandyn/instance/dynamics_derivatives.hpp). Entries past nb / nv unused.
template <class S, int C>
struct GeneralDerivativeParams {
  static constexpr int capacity = C;
  // q entries a thread holds: nq <= 4 nv / 3 (a spherical joint: 4 for 3 DoF; a free
  // joint 7 for 6; a 1-DoF joint 1 for 1)
  static constexpr int q_capacity = C + C / 3;
  Body<S> body[C];         // (nb <= nv) bodies in DoF order
  Index dof_parent[C];     // (nv) parent DoF of each DoF, -1 at the root
  Index dof_last[C];       // (nv) last DoF of each DoF's subtree
  Index dof_run[C];        // (nv) first DoF of each DoF's unbranched run
  Motion<S> a0;            // base_acceleration(gravity)
  Index nb, nv, nq;
};

// A model with multi-DoF joints prepared for the general derivative kernels: the
// parameter block of the smallest capacity that holds its nv DoF. Host memory only.
template <class S>
class GeneralDerivativeModel {
 public:
  using Params = std::variant<GeneralDerivativeParams<S, 8>, GeneralDerivativeParams<S, 16>,
                              GeneralDerivativeParams<S, 32>, GeneralDerivativeParams<S, 64>>;
  // Throws BackendError for more than kMaxThreadDofs DoF (naming the limit). The
  // launches refuse a capacity this build does not compile (visit_compiled_capacity;
  // SCANDYN_CUDA_ALL_CAPACITIES=OFF: 8 only), the engines at construction.
  explicit GeneralDerivativeModel(const ModelTpl<S>& model);
  Index nv() const { return nv_; }
  Index nq() const { return nq_; }
  Index nbodies() const { return nb_; }
  Index capacity() const { return capacity_; }  // 8, 16, 32 or 64
  const Params& params() const { return params_; }

 private:
  Index nv_ = 0, nq_ = 0, nb_ = 0, capacity_ = 0;
  Params params_;
};

// launch_id_derivatives / launch_fd_derivatives for a model with multi-DoF joints:
// q has nq entries per instance, fext (or null) nbodies wrenches per instance; the
// rest as above.
template <class S>
cudaError_t launch_id_derivatives(const GeneralDerivativeModel<S>& model, const IdBatchIn<S>& in,
                                  const IdDerivativesOut<S>& out, cudaStream_t stream);
template <class S>
cudaError_t launch_fd_derivatives(const GeneralDerivativeModel<S>& model, const FdBatchIn<S>& in,
                                  const FdDerivativesOut<S>& out, int* failed_dof, cudaStream_t stream);

// ---- the engines ------------------------------------------------------------------
// Any model of up to kMaxThreadDofs DoF: models of 1-DoF joints take the thread
// kernels above (strategy "thread"), models with multi-DoF joints the general ones
// (strategy "general").

template <class S>
class CudaIdDerivatives final : public IdDerivatives<S> {
 public:
  // Throws BackendError for a model beyond kMaxThreadDofs, no usable device, or
  // staging buffers (q, qd, qdd, fext and three nv x nv outputs per instance, for
  // max_batch instances) that do not fit.
  CudaIdDerivatives(const ModelTpl<S>& model, const BackendOptions& options);
  ~CudaIdDerivatives() override;
  void compute(const IdBatchIn<S>& in, const IdDerivativesOut<S>& out) override;
  cudaError_t compute_async(const IdBatchIn<S>& in, const IdDerivativesOut<S>& out, cudaStream_t stream);
  std::string strategy() const override { return general_ ? "general" : "thread"; }
  BackendKind backend() const override { return BackendKind::Cuda; }

 private:
  Index nv_ = 0, nq_ = 0, nb_ = 0, max_batch_ = 0;
  std::unique_ptr<ThreadModel<S>> thread_;              // models of 1-DoF joints
  std::unique_ptr<GeneralDerivativeModel<S>> general_;  // models with multi-DoF joints
  std::unique_ptr<detail::StagingBuffer> staging_;
};

template <class S>
class CudaFdDerivatives final : public FdDerivatives<S> {
 public:
  CudaFdDerivatives(const ModelTpl<S>& model, const BackendOptions& options);
  ~CudaFdDerivatives() override;
  BatchStatus compute(const FdBatchIn<S>& in, const FdDerivativesOut<S>& out) override;
  // failed_dof: B ints of device memory, or null
  cudaError_t compute_async(const FdBatchIn<S>& in, const FdDerivativesOut<S>& out, int* failed_dof,
                            cudaStream_t stream);
  std::string strategy() const override { return general_ ? "general" : "thread"; }
  BackendKind backend() const override { return BackendKind::Cuda; }

 private:
  Index nv_ = 0, nq_ = 0, nb_ = 0, max_batch_ = 0;
  std::unique_ptr<ThreadModel<S>> thread_;              // models of 1-DoF joints
  std::unique_ptr<GeneralDerivativeModel<S>> general_;  // models with multi-DoF joints
  std::unique_ptr<detail::StagingBuffer> staging_;
  std::vector<int> failed_host_;  // (max_batch) the failed DoFs of the last compute()
};

// The factories' CUDA branch (scandyn/engine.hpp: make_id_derivatives, make_fd_derivatives).
template <class S>
std::unique_ptr<IdDerivatives<S>> make_cuda_id_derivatives(const ModelTpl<S>& model, const BackendOptions& options);
template <class S>
std::unique_ptr<FdDerivatives<S>> make_cuda_fd_derivatives(const ModelTpl<S>& model, const BackendOptions& options);

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
