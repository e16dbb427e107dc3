// scandyn/cuda/rollout_derivatives.hpp: rollouts of the simulator's step and their
// derivatives (scandyn/sim/step_derivatives.hpp: the rollout, its forward-mode
// product and the checkpointed adjoint) for a batch on a CUDA device, one thread per
// instance (models of up to kMaxThreadDofs DoF). Each thread runs the serial
// engine's instance functions (rollout_instance, rollout_jvp_instance,
// rollout_vjp_instance over step_instance, step_jvp_instance, step_vjp_instance)
// with the fused simulator step's forward dynamics (aba_instance, user frames) and,
// for M^-1 x, aba_instance on the model without gravity at rest (aba_jvp_instance,
// aba_vjp_instance): the serial engine's order of operations, so results agree with
// it to rounding (the tests: double 1e-9 relative).
//
// Memory, per instance:
//   - per thread, local memory (capacity C = 8, 16, 32 or 64 >= nv): 8 C rows of the
//     instance functions, 32 C scalars of step scratch, and the RNEA's per-body values
//     and tangents or adjoints (Xup, v, a, f and RneaAdjoint / RneaTangent: 48 C
//     scalars);
//   - vjp: the checkpoint store in global memory, rollout_store_slots(T, K) * 2 nv
//     scalars (ceil(T / K) checkpoints and one segment of K states, (ceil(T / K) + K)
//     * 2 nv; K = ceil(sqrt(T)) by default), laid out with the instance innermost
//     (entry (row, i) of instance b at (row * nv + i) * B + b: coalesced);
//     store_bytes(T, B) says how much; it grows to the largest call (reserve());
//   - host views only: dense device copies of the inputs and outputs (T steps of nv x
//     B each), grown to the largest call.
// The joint effects run as one instantiation of all of them (kJointEffects), the
// undeclared ones with zero coefficients (exact zeros added), as in the CUDA step
// Jacobian; the scene's constant external wrenches are read from device memory.
#pragma once

#include <memory>
#include <vector>

#include "scandyn/build_config.hpp"
#include "scandyn/sim/step_derivatives.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

namespace scandyn {
namespace cuda {

// Threads per block of the rollout kernels.
inline constexpr int kRolloutBlock = 64;

template <class S>
class CudaRolloutDerivatives {
 public:
  // checkpoint_interval: K of the adjoint (0: ceil(sqrt(T))). Throws BackendError
  // naming what is not covered (require_differentiable_step), a model beyond
  // kMaxThreadDofs, a negative interval, or no usable device.
  CudaRolloutDerivatives(const sim::SimSetup<S>& setup, const BackendOptions& options, Index checkpoint_interval = 0);
  ~CudaRolloutDerivatives();
  CudaRolloutDerivatives(const CudaRolloutDerivatives&) = delete;
  CudaRolloutDerivatives& operator=(const CudaRolloutDerivatives&) = delete;

  // HOST views, as sim::RolloutDerivatives' calls (which forward here on backend
  // cuda): copies in, launches on stream(), copies out, synchronises.
  BatchStatus rollout(const BatchView<const S>& q0, const BatchView<const S>& qd0,
                      const sim::StepSequence<const S>& tau, const sim::StepSequence<S>& q,
                      const sim::StepSequence<S>& qd);
  BatchStatus vjp(const BatchView<const S>& q0, const BatchView<const S>& qd0, const sim::StepSequence<const S>& tau,
                  const sim::StepSequence<const S>& gq, const sim::StepSequence<const S>& gqd,
                  const BatchView<S>& gq0, const BatchView<S>& gqd0, const sim::StepSequence<S>& gtau);
  BatchStatus jvp(const BatchView<const S>& q0, const BatchView<const S>& qd0, const sim::StepSequence<const S>& tau,
                  const BatchView<const S>& dq0, const BatchView<const S>& dqd0,
                  const sim::StepSequence<const S>& dtau, const sim::StepSequence<S>& dq,
                  const sim::StepSequence<S>& dqd);

  // DEVICE views (any strides; the sequences' time strides too) on `stream`, the
  // same arguments as the host calls; failed_dof: B ints of device memory, or null:
  // -1, the DoF whose pivot failed, or -2 - i when a result at DoF i is not finite.
  // Shapes are checked (BackendError naming the view); launch errors are returned.
  // vjp_async first reserves the store (reserve(T, B): an allocation, synchronising
  // the device, only when it grows). One call at a time per object.
  cudaError_t rollout_async(const BatchView<const S>& q0, const BatchView<const S>& qd0,
                            const sim::StepSequence<const S>& tau, const sim::StepSequence<S>& q,
                            const sim::StepSequence<S>& qd, int* failed_dof, cudaStream_t stream);
  cudaError_t vjp_async(const BatchView<const S>& q0, const BatchView<const S>& qd0,
                        const sim::StepSequence<const S>& tau, const sim::StepSequence<const S>& gq,
                        const sim::StepSequence<const S>& gqd, const BatchView<S>& gq0, const BatchView<S>& gqd0,
                        const sim::StepSequence<S>& gtau, int* failed_dof, cudaStream_t stream);
  cudaError_t jvp_async(const BatchView<const S>& q0, const BatchView<const S>& qd0,
                        const sim::StepSequence<const S>& tau, const BatchView<const S>& dq0,
                        const BatchView<const S>& dqd0, const sim::StepSequence<const S>& dtau,
                        const sim::StepSequence<S>& dq, const sim::StepSequence<S>& dqd, int* failed_dof,
                        cudaStream_t stream);

  // The adjoint's checkpoint store for T steps of B instances: its bytes, and
  // growing it (BackendError when the device cannot hold it, naming the bytes).
  std::size_t store_bytes(Index T, Index B) const;
  void reserve(Index T, Index B);

  Index checkpoint_interval(Index T) const { return sim::rollout_checkpoint_interval(interval_, T); }
  const sim::SimSetup<S>& setup() const { return setup_; }
  cudaStream_t stream() const { return stream_; }  // the host calls' stream

 private:
  struct Params;  // the kernel parameters of the model's capacity (kernels/rollout_derivatives.cu)
  // A device allocation that grows (freed and allocated again, larger).
  struct Buffer {
    void* ptr = nullptr;
    std::size_t bytes = 0;
  };
  void grow(Buffer& b, std::size_t bytes, const char* what);
  BatchStatus status_of(Index B);
  template <class Launch>
  BatchStatus host_call(std::size_t inputs, std::size_t total, Index B, const char* kernel, Launch&& launch);

  sim::SimSetup<S> setup_;
  Index nv_ = 0, interval_ = 0;
  int device_ = 0;
  cudaStream_t stream_ = nullptr;
  std::unique_ptr<Params> params_;
  void* rest_ = nullptr;          // the model without gravity (a ThreadModelParams of the capacity), device memory
  Force<S>* wrenches_ = nullptr;  // (nv) the scene's constant wrenches on the device, or null
  Buffer store_;                  // the adjoint's checkpoint store
  Buffer io_;                     // host calls: the dense device copies of inputs and outputs, and failed DoFs
  std::vector<S> host_;           // host calls: the dense host copies
  std::vector<int> failed_host_;  // (B) the failed DoFs of the last host call
};

}  // namespace cuda
}  // namespace scandyn
#endif
