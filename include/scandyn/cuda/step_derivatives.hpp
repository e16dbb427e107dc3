// scandyn/cuda/step_derivatives.hpp: the simulator step's Jacobian
// (scandyn/sim/step_derivatives.hpp) for a batch on a CUDA device, one thread per
// instance (models of up to kMaxThreadDofs DoF): step_jacobian_instance over the
// fused simulator step's forward dynamics (aba_instance with the implicit armature)
// and fd_derivatives_instance, the serial engine's functions.
//
// Per thread: nv DerivativeBody entries (70 scalars each) and the state in local
// memory, and step_jacobian_scratch(nv, integrator) scalars of global memory (8 nv +
// 3 nv^2, rk4 8 nv + 12 nv^2) in the engine's staging buffer, next to the inputs,
// the wrenches, the six nv x nv outputs and the new state (max_batch instances).
// The joint effects run as one instantiation of all of them (kJointEffects): the
// coefficients of undeclared effects are zero (limits +-inf), which adds exact zeros.
#pragma once

#include <memory>
#include <vector>

#include "scandyn/build_config.hpp"
#include "scandyn/sim/step_derivatives.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

namespace scandyn {
namespace cuda {

namespace detail {
class StagingBuffer;  // kernels/staging.hpp
}  // namespace detail

// Threads per block of the step-Jacobian kernel.
inline constexpr int kStepJacobianBlock = 64;

template <class S>
class CudaStepDerivatives final : public sim::StepDerivatives<S> {
 public:
  // Throws BackendError for a model beyond kMaxThreadDofs, no usable device, or a
  // staging buffer that does not fit.
  CudaStepDerivatives(const sim::SimSetup<S>& setup, const BackendOptions& options);
  ~CudaStepDerivatives() override;
  // Host views: copies in, launches, copies out, synchronises.
  BatchStatus compute(const FdBatchIn<S>& in, const sim::StepDerivativesOut<S>& out) override;
  // DEVICE views (inputs, outputs, in.fext or null for the scene's constant
  // wrenches) on `stream`; failed_dof: B ints of device memory, or null: -1, the
  // DoF whose pivot failed, or -2 - i when the new state or a derivative in row i
  // is not finite. Scratch: the engine's (one call at a time per engine).
  cudaError_t compute_async(const FdBatchIn<S>& in, const sim::StepDerivativesOut<S>& out, int* failed_dof,
                            cudaStream_t stream);
  std::string strategy() const override { return std::string("thread-step-jacobian-") + sim::to_string(setup_.integrator); }
  BackendKind backend() const override { return BackendKind::Cuda; }
  const sim::SimSetup<S>& setup() const override { return setup_; }

 private:
  struct Params;  // the kernel parameter of the model's capacity (kernels/step_derivatives.cu)
  sim::SimSetup<S> setup_;
  Index nv_ = 0, max_batch_ = 0;
  std::size_t scratch_per_instance_ = 0;  // scalars
  std::unique_ptr<Params> params_;
  std::unique_ptr<detail::StagingBuffer> staging_;
  Force<S>* wrenches_ = nullptr;  // (nv) the scene's constant wrenches on the device, or null
  std::vector<int> failed_host_;
};

template <class S>
std::unique_ptr<sim::StepDerivatives<S>> make_cuda_step_derivatives(const sim::SimSetup<S>& setup,
                                                                    const BackendOptions& options);

}  // namespace cuda
}  // namespace scandyn
#endif
