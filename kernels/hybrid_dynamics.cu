// kernels/hybrid_dynamics.cu: batched hybrid dynamics, one thread per instance.
//
// The layers of scandyn/cuda/hybrid_dynamics.hpp: hybrid_instance (aba_instance's
// passes with the prescribed joints' steps) -> hybrid_instances_kernel ->
// launch_hybrid_instances -> CudaHybridDynamics (host staging through
// kernels/staging.hpp for compute(), the plain launch for compute_async()). The
// compile-time choices are the ABA kernel's (kernels/forward_dynamics.cu): rolled
// loops, 128 registers in float.
#include <cuda_runtime.h>

#include <string>
#include <type_traits>

#include "scandyn/cuda/device.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/cuda/hybrid_dynamics.hpp"
#include "scandyn/instance/hybrid_instance.hpp"
#include "staging.hpp"

namespace scandyn {
namespace cuda {

using detail::check;
using detail::copy;
using detail::plan;
using detail::Staging;

unsigned long long prescribed_bits(const std::vector<unsigned char>& prescribed) {
  unsigned long long bits = 0;
  for (std::size_t i = 0; i < prescribed.size() && i < 64; ++i)
    if (prescribed[i]) bits |= 1ull << i;
  return bits;
}

// One thread per instance b < B: the hybrid dynamics of instance b (aba_instance's
// kSlots branch slots, as launch_aba_instances picks them).
template <class S, int C, int kSlots>
__global__ void __launch_bounds__(kFdInstancesBlock, sizeof(S) == 8 ? 1 : 4)
    hybrid_instances_kernel(const __grid_constant__ ThreadModelParams<S, C> model, const unsigned long long prescribed,
                            const HybridBatchIn<S> batch_in, const BatchView<S> qdd_out, const BatchView<S> tau_out,
                            int* const failed_dof_out) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= batch_in.q.batch) return;
  const Force<S>* fext = batch_in.fext ? batch_in.fext + b * model.nv : nullptr;
  const HybridColumns<S> hd{prescribed, instance_column(batch_in.qdd, b), instance_column(tau_out, b)};
  failed_dof_out[b] = hybrid_instance<S, C, false, false, kThreadTrig<S>, kSlots>(
      model, instance_column(batch_in.q, b), instance_column(batch_in.qd, b), instance_column(batch_in.tau, b), fext,
      instance_column(qdd_out, b), hd);
}

template <class S>
cudaError_t launch_hybrid_instances(const ThreadModel<S>& model, unsigned long long prescribed,
                                    const HybridBatchIn<S>& batch_in, const BatchView<S>& qdd_out,
                                    const BatchView<S>& tau_out, int* failed_dof_out, cudaStream_t stream) {
  const Index B = batch_in.q.batch;
  if (B < 0 || batch_in.qd.batch != B || batch_in.qdd.batch != B || batch_in.tau.batch != B || qdd_out.batch != B ||
      tau_out.batch != B)
    return cudaErrorInvalidValue;
  if (B == 0) return cudaSuccess;
  if (!failed_dof_out) return cudaErrorInvalidValue;
  if (model.nv() > 0 && (!batch_in.q.data || !batch_in.qd.data || !batch_in.qdd.data || !batch_in.tau.data ||
                         !qdd_out.data || !tau_out.data))
    return cudaErrorInvalidValue;
  const unsigned blocks = static_cast<unsigned>((static_cast<long long>(B) + kFdInstancesBlock - 1) / kFdInstancesBlock);
  visit_aba_kernel(model, [&](const auto& params, auto slots) {
    constexpr int C = std::decay_t<decltype(params)>::capacity;
    hybrid_instances_kernel<S, C, decltype(slots)::value><<<blocks, kFdInstancesBlock, 0, stream>>>(
        params, prescribed, batch_in, qdd_out, tau_out, failed_dof_out);
  });
  return cudaGetLastError();
}

// ---- the engine ----------------------------------------------------------------

template <class S>
CudaHybridDynamics<S>::CudaHybridDynamics(const ModelTpl<S>& model, const std::vector<unsigned char>& prescribed,
                                          const BackendOptions& options)
    : nv_(model.nv()), max_batch_(options.max_batch), prescribed_(prescribed), bits_(prescribed_bits(prescribed)) {
  if (nv_ > kMaxThreadDofs)
    throw BackendError("backend 'cuda': hybrid dynamics runs one thread per instance, for models of up to " +
                       std::to_string(kMaxThreadDofs) + " DoF; this model has " + std::to_string(nv_) +
                       " (use the serial or openmp backend)");
  // q, qd, qdd in, tau in (slots 0..3 of nv scalars), qdd out, tau out, fext (6) and a failed DoF
  staging_ = std::make_unique<detail::StagingBuffer>(
      max_batch_, nv_, sizeof(S) == 4 ? "float" : "double",
      "q, qd, qdd and tau in, qdd and tau out, fext and a failed DoF",
      12 * static_cast<std::size_t>(nv_) * sizeof(S) + sizeof(int));
  thread_ = std::make_unique<ThreadModel<S>>(model);
  failed_host_.resize(static_cast<std::size_t>(max_batch_));
  device_ = staging_->device();
}

template <class S>
CudaHybridDynamics<S>::~CudaHybridDynamics() = default;

template <class S>
cudaError_t CudaHybridDynamics<S>::compute_async(const HybridBatchIn<S>& in, const BatchView<S>& qdd,
                                                 const BatchView<S>& tau, int* failed_dof, cudaStream_t stream) {
  return launch_hybrid_instances(*thread_, bits_, in, qdd, tau, failed_dof, stream);
}

template <class S>
BatchStatus CudaHybridDynamics<S>::compute(const HybridBatchIn<S>& in, const BatchView<S>& qdd,
                                           const BatchView<S>& tau) {
  check_batch(in, qdd, tau, max_batch_);
  const Index B = in.q.batch, nv = nv_;
  int* const failed = failed_host_.data();
  BatchStatus status;
  status.failed_dof = failed;
  if (B == 0) return status;
  if (nv == 0) {
    for (Index b = 0; b < B; ++b) failed[b] = -1;
    return status;
  }
  // the buffer: q, qd, tau in (slots 0..2, stage_inputs), qdd out (slot 3), fext
  // (slots 4..9), qdd in (slot 10), tau out (slot 11), the failed DoFs
  const std::size_t cap = static_cast<std::size_t>(nv) * max_batch_;
  const cudaStream_t stream = staging_->stream();
  S* const buffer = static_cast<S*>(staging_->data());
  S* const dqdd = buffer + 3 * cap;
  S* const dqdd_in = buffer + 10 * cap;
  S* const dtau = buffer + 11 * cap;
  int* const dfailed = reinterpret_cast<int*>(buffer + 12 * cap);
  const Staging sqdd = plan(qdd, nv, cap, true, "qdd");
  const Staging stau = plan(tau, nv, cap, true, "tau");
  const detail::StagedInputs<S> d =
      detail::stage_inputs<S>({in.q, in.qd, in.tau}, {"q", "qd", "tau"}, in.fext, nv, cap, buffer, stream);
  const Staging sqdd_in = plan(in.qdd, nv, cap, false);
  check(copy(sqdd_in, in.qdd, nv, dqdd_in, cudaMemcpyHostToDevice, stream), "copying qdd to the device");
  const HybridBatchIn<S> din{d.in[0], d.in[1], sqdd_in.device_view<const S>(dqdd_in, B), d.in[2], d.fext};
  check(compute_async(din, sqdd.device_view(dqdd, B), stau.device_view(dtau, B), dfailed, stream),
        "launching the hybrid dynamics");
  check(cudaMemcpyAsync(failed, dfailed, static_cast<std::size_t>(B) * sizeof(int), cudaMemcpyDeviceToHost, stream),
        "copying the failed DoFs to the host");
  check(cudaStreamSynchronize(stream), "running the hybrid dynamics");
  status = summarize_failures(failed, B, Failure::ArticulatedPivot);
  // keep the failed instances' output entries (the device holds nothing for them)
  auto keep = [&](bool restore) {
    std::size_t k = 0;
    for (Index b = 0; b < B; ++b)
      if (failed[b] >= 0)
        for (Index i = 0; i < nv; ++i, k += 2) {
          if (restore) qdd.at(i, b) = kept_[k], tau.at(i, b) = kept_[k + 1];
          else kept_[k] = qdd.at(i, b), kept_[k + 1] = tau.at(i, b);
        }
  };
  if (status.failed > 0) {
    const std::size_t need = 2 * static_cast<std::size_t>(status.failed) * nv;
    if (kept_.size() < need) kept_.resize(need);
    keep(false);
  }
  check(copy(sqdd, qdd, nv, dqdd, cudaMemcpyDeviceToHost, stream), "copying qdd to the host");
  check(copy(stau, tau, nv, dtau, cudaMemcpyDeviceToHost, stream), "copying tau to the host");
  check(cudaStreamSynchronize(stream), "copying the hybrid dynamics' outputs to the host");
  if (status.failed > 0) keep(true);
  return status;
}

#define SCANDYN_INSTANTIATE(S)                                                                                      \
  template class CudaHybridDynamics<S>;                                                                             \
  template cudaError_t launch_hybrid_instances(const ThreadModel<S>&, unsigned long long, const HybridBatchIn<S>&, \
                                               const BatchView<S>&, const BatchView<S>&, int*, cudaStream_t);
SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)
#undef SCANDYN_INSTANTIATE

}  // namespace cuda
}  // namespace scandyn
