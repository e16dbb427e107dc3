// scandyn/cuda/fd_check.hpp: forward dynamics' run-time check on a CUDA device, one
// thread per instance (the device side of scandyn/algorithm/fd_check.hpp).
//
// For instance b whose failed_dof[b] is -1, in double whatever the result's precision
// (the model widened exactly):
//   r      = ID(q, qd, qdd) - tau                  rnea_instance (scandyn/instance/rnea_instance.hpp)
//   delta  = M(q)^-1 r                             aba_instance with qd = 0 and no gravity
//   estimate[b] = max_i |delta_i| / max(1, max_i |qdd_i|)
// (+inf when an articulated pivot of the second pass fails; NaN stays NaN), and an
// instance whose estimate is not at most the threshold is marked failed at the DoF
// of the largest |delta_i| (failed_dof[b]); instances that failed before the check
// get estimate -1. The same quantity as fd_check's error_estimate on the host,
// through the same step functions (the host's FdBatchCheck retries flagged ones). Models of up to kMaxThreadDofs
// DoF; CudaForwardDynamics runs it for its thread-per-instance engines
// (aba_thread, jsi_thread) and checks longer models on the host.
#pragma once

#include <memory>

#include "scandyn/build_config.hpp"
#include "scandyn/engine.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

namespace scandyn {
namespace cuda {

template <class T, class Bd>
class ThreadModel;

// Threads per block of the check kernel.
inline constexpr int kFdCheckBlock = 128;

template <class S>
class DeviceFdCheck {
 public:
  // The model widened to double, as a kernel parameter block and, without gravity,
  // in device memory (the second pass's). Throws BackendError beyond kMaxThreadDofs
  // DoF or when the device memory cannot be had.
  explicit DeviceFdCheck(const ModelTpl<S>& model);
  ~DeviceFdCheck();
  DeviceFdCheck(const DeviceFdCheck&) = delete;
  DeviceFdCheck& operator=(const DeviceFdCheck&) = delete;

  // estimate_out[b] for b < in.q.batch, and failed_dof[b] (read, then written for a
  // flagged instance) as above; every pointer a DEVICE pointer (views of any strides;
  // failed_dof, estimate_out dense). Queued on `stream`; no copy, allocation or
  // synchronisation. Returns cudaErrorInvalidValue for disagreeing batch sizes or
  // null pointers with B > 0, else the launch's error.
  cudaError_t launch(const FdBatchIn<S>& in, const BatchView<const S>& qdd, double threshold, int* failed_dof,
                     double* estimate_out, cudaStream_t stream) const;

 private:
  std::unique_ptr<ThreadModel<double, Body<double>>> model_;  // with gravity: the RNEA's
  void* free_params_ = nullptr;                 // device copy of its parameters without gravity
};

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
