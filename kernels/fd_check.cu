// kernels/fd_check.cu: forward dynamics' run-time check, one thread per instance
// (scandyn/cuda/fd_check.hpp): rnea_instance and aba_instance in double over the
// step functions the host's fd_check uses, its norms (FdCheckNorms).
#include <cuda_runtime.h>

#include <string>
#include <type_traits>
#include <variant>

#include "scandyn/algorithm/fd_check.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/cuda/fd_check.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"
#include "scandyn/instance/aba_instance.hpp"
#include "scandyn/instance/rnea_instance.hpp"
#include "staging.hpp"

namespace scandyn {
namespace cuda {

// One thread per instance b: estimate_out[b], and failed_dof[b] for a flagged one
// (see the header). model: the widened model with gravity (the RNEA's); free_model:
// the same without gravity, in device memory (the ABA's M^-1 r). Per thread, in
// local memory: q, qd, qdd, r and delta in double (5 C doubles) and, for float with
// wrenches, the wrenches.
template <class S, int C>
__global__ void __launch_bounds__(kFdCheckBlock)
    fd_check_kernel(const __grid_constant__ ThreadModelParams<double, C> model,
                    const ThreadModelParams<double, C>* __restrict__ free_model, const FdBatchIn<S> in,
                    const BatchView<const S> qdd, const double threshold, int* __restrict__ failed_dof,
                    double* __restrict__ estimate_out) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= in.q.batch) return;
  if (failed_dof[b] >= 0) {
    estimate_out[b] = -1;
    return;
  }
  const Index n = model.nv;
  double q[C], qd[C], a[C], r[C], delta[C];  // (nv) inputs, result, residual, correction
  for (Index i = 0; i < n; ++i) {
    q[i] = double(in.q.at(i, b));
    qd[i] = double(in.qd.at(i, b));
    a[i] = double(qdd.at(i, b));
  }
  // wrenches in double: the caller's when S is double, else converted
  const Force<S>* fext = in.fext ? in.fext + b * n : nullptr;
  const Force<double>* fx = nullptr;
  Force<double> wide[std::is_same_v<S, double> ? 1 : C];
  if constexpr (std::is_same_v<S, double>) {
    fx = fext;
  } else {
    if (fext) {
      for (Index i = 0; i < n; ++i) wide[i] = fext[i].template cast<double>();
      fx = wide;
    }
  }
  using Col = DofColumn<const double>;
  // r = ID(q, qd, qdd) - tau
  rnea_instance<double, C, false, false, Trig::Library>(model, Col{q, 1}, Col{qd, 1}, Col{a, 1}, fx,
                                                        DofColumn<double>{r, 1});
  FdCheckNorms<double> norms;
  for (Index i = 0; i < n; ++i) {
    r[i] = fd_check_residual(norms, r[i], double(in.tau.at(i, b)), 0.0);
    qd[i] = 0;  // the second pass runs from rest
  }
  // delta = M^-1 r: the ABA from rest, without gravity or wrenches
  const Index failed = aba_instance<double, C, false, false, Trig::Library, C>(
      *free_model, Col{q, 1}, Col{qd, 1}, Col{r, 1}, nullptr, DofColumn<double>{delta, 1});
  if (failed >= 0) {
    estimate_out[b] = __longlong_as_double(0x7ff0000000000000LL);  // +inf
    failed_dof[b] = static_cast<int>(failed);
    return;
  }
  Index worst = 0;
  for (Index i = 0; i < n; ++i) {
    fd_check_delta(norms, delta[i], a[i]);
    if (!(fabs(delta[i]) <= fabs(delta[worst]))) worst = i;
  }
  const double estimate = fd_error_estimate(norms);
  estimate_out[b] = estimate;
  if (!(estimate <= threshold)) failed_dof[b] = static_cast<int>(worst);
}

template <class S>
DeviceFdCheck<S>::DeviceFdCheck(const ModelTpl<S>& model) {
  if (model.nv() > kMaxThreadDofs)
    throw BackendError("backend 'cuda': the device forward-dynamics check runs one thread per instance, for models "
                       "of up to " + std::to_string(kMaxThreadDofs) + " DoF; this model has " +
                       std::to_string(model.nv()));
  model_ = std::make_unique<ThreadModel<double>>(model.template cast<double>());
  std::visit(
      [&](const auto& params) {
        auto free = params;
        free.a0 = Motion<double>::zero();
        detail::check(cudaMalloc(&free_params_, sizeof(free)), "allocating the forward-dynamics check's model");
        detail::check(cudaMemcpy(free_params_, &free, sizeof(free), cudaMemcpyHostToDevice),
                      "copying the forward-dynamics check's model");
      },
      model_->params());
}

template <class S>
DeviceFdCheck<S>::~DeviceFdCheck() {
  if (free_params_) cudaFree(free_params_);
}

template <class S>
cudaError_t DeviceFdCheck<S>::launch(const FdBatchIn<S>& in, const BatchView<const S>& qdd, double threshold,
                                     int* failed_dof, double* estimate_out, cudaStream_t stream) const {
  const Index B = in.q.batch;
  if (B < 0 || in.qd.batch != B || in.tau.batch != B || qdd.batch != B) return cudaErrorInvalidValue;
  if (B == 0) return cudaSuccess;
  if (!failed_dof || !estimate_out || !in.q.data || !in.qd.data || !in.tau.data || !qdd.data)
    return cudaErrorInvalidValue;
  const unsigned blocks = static_cast<unsigned>((static_cast<long long>(B) + kFdCheckBlock - 1) / kFdCheckBlock);
  visit_compiled_capacity(model_->params(), [&](const auto& params) {
    using P = std::decay_t<decltype(params)>;
    fd_check_kernel<S, P::capacity><<<blocks, kFdCheckBlock, 0, stream>>>(params, static_cast<const P*>(free_params_),
                                                                          in, qdd, threshold, failed_dof, estimate_out);
  });
  return cudaGetLastError();
}

template class DeviceFdCheck<float>;
template class DeviceFdCheck<double>;

}  // namespace cuda
}  // namespace scandyn
