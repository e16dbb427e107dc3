// kernels/second_derivatives.cu: the batched second-order derivatives of inverse
// dynamics, one thread per instance (scandyn/cuda/second_derivatives.hpp): the
// analytical second-order recursion of scandyn/instance/second_derivatives_analytic.hpp
// (the serial rnea_second_derivatives' function).
#include <cuda_runtime.h>

#include <string>
#include <type_traits>

#include "scandyn/cuda/second_derivatives.hpp"
#include "scandyn/instance/dof_column.hpp"
#include "scandyn/instance/thread_model.hpp"
#include "staging.hpp"

namespace scandyn {
namespace cuda {

using detail::check;
using detail::copy;
using detail::plan;
using detail::Staging;

static_assert(sizeof(SecondOrderModelParams<double, 64>) + sizeof(IdBatchIn<double>) +
                      sizeof(IdSecondDerivativesOut<double>) <=
                  32764,
              "the kernel's parameters must fit the 32764 bytes CUDA allows");

// ---- the model ----------------------------------------------------------------------

namespace {

template <int C, class S>
SecondOrderModelParams<S, C> make_params(const ModelTpl<S>& model) {
  SecondOrderModelParams<S, C> p{};
  for (Index i = 0; i < model.nv(); ++i) p.body[i] = model.bodies[static_cast<std::size_t>(i)];
  p.a0 = base_acceleration(model.gravity);
  p.nv = model.nv();
  return p;
}

}  // namespace

template <class S>
SecondOrderThreadModel<S>::SecondOrderThreadModel(const ModelTpl<S>& model) : nv_(model.nv()) {
  if (model.multi_dof())
    throw BackendError("backend 'cuda': model '" + model.name +
                       "' has a multi-DoF joint; the second-order derivatives take revolute and prismatic joints only");
  if (nv_ > kMaxThreadDofs)
    throw BackendError("backend 'cuda': model '" + model.name + "' has " + std::to_string(nv_) +
                       " DoF; the second-order derivatives run a thread per instance, which takes at most " +
                       std::to_string(kMaxThreadDofs));
  if (nv_ <= 8) capacity_ = 8, params_ = make_params<8>(model);
  else if (nv_ <= 16) capacity_ = 16, params_ = make_params<16>(model);
  else if (nv_ <= 32) capacity_ = 32, params_ = make_params<32>(model);
  else capacity_ = 64, params_ = make_params<64>(model);
  require_compiled_capacity(capacity_, "the second-order derivatives", model.name);
}

// ---- the kernel and its launch --------------------------------------------------------

// One thread per instance b < B: the three tensors (and dM/dq) of instance b.
template <class S, int C>
__global__ void __launch_bounds__(kSecondDerivativesBlock)
    id_second_derivatives_kernel(const __grid_constant__ SecondOrderModelParams<S, C> model, const IdBatchIn<S> in,
                                 const IdSecondDerivativesOut<S> out) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= in.q.batch) return;
  const Index nv = model.nv;
  DerivativeBody<S> work[C];  // per-thread local memory: 72 C scalars
  rnea_second_derivatives_analytic_instance(model.body, nv, model.a0, instance_column(in.q, b),
                                            instance_column(in.qd, b), instance_column(in.qdd, b),
                                            in.fext ? in.fext + b * nv : nullptr, work,
                                            instance_tensor(out.d2tau_dq2, b, nv), instance_tensor(out.d2tau_dqd2, b, nv),
                                            instance_tensor(out.d2tau_dqdqd, b, nv), instance_tensor(out.dM_dq, b, nv));
}

template <class S>
cudaError_t launch_id_second_derivatives(const SecondOrderThreadModel<S>& model, const IdBatchIn<S>& in,
                                         const IdSecondDerivativesOut<S>& out, cudaStream_t stream) {
  const Index B = in.q.batch;
  if (B < 0 || in.qd.batch != B || in.qdd.batch != B || out.d2tau_dq2.batch != B || out.d2tau_dqd2.batch != B ||
      out.d2tau_dqdqd.batch != B || (out.dM_dq.data && out.dM_dq.batch != B))
    return cudaErrorInvalidValue;
  if (B == 0 || model.nv() == 0) return cudaSuccess;
  if (!in.q.data || !in.qd.data || !in.qdd.data || !out.d2tau_dq2.data || !out.d2tau_dqd2.data ||
      !out.d2tau_dqdqd.data)
    return cudaErrorInvalidValue;
  const unsigned blocks =
      static_cast<unsigned>((static_cast<long long>(B) + kSecondDerivativesBlock - 1) / kSecondDerivativesBlock);
  visit_compiled_capacity(model.params(), [&](const auto& params) {
    using P = std::decay_t<decltype(params)>;
    id_second_derivatives_kernel<S, P::capacity><<<blocks, kSecondDerivativesBlock, 0, stream>>>(params, in, out);
  });
  return cudaGetLastError();
}

// ---- the engine ---------------------------------------------------------------------
//
// Staging buffer for max_batch instances (cap = nv x max_batch scalars): the three
// inputs in slots 0..2 (slot 3 unused), the wrenches (6 slots, detail::stage_inputs'
// layout), then the four nv^3 tensors (nv^2 slots each: d2tau_dq2, d2tau_dqd2,
// d2tau_dqdqd, dM_dq).

namespace {

constexpr std::size_t kInputSlots = 10;  // q, qd, qdd, (unused), fext (6)
constexpr int kTensors = 4;

}  // namespace

template <class S>
CudaIdSecondDerivatives<S>::CudaIdSecondDerivatives(const ModelTpl<S>& model, const BackendOptions& options)
    : nv_(model.nv()), max_batch_(options.max_batch) {
  model_ = std::make_unique<SecondOrderThreadModel<S>>(model);
  const std::size_t n = static_cast<std::size_t>(nv_);
  staging_ = std::make_unique<detail::StagingBuffer>(max_batch_, nv_, sizeof(S) == 4 ? "float" : "double",
                                                     "q, qd, qdd, fext and four nv^3 tensors",
                                                     (kInputSlots + kTensors * n * n) * n * sizeof(S));
}
template <class S>
CudaIdSecondDerivatives<S>::~CudaIdSecondDerivatives() = default;

template <class S>
cudaError_t CudaIdSecondDerivatives<S>::compute_async(const IdBatchIn<S>& in, const IdSecondDerivativesOut<S>& out,
                                                      cudaStream_t stream) {
  return launch_id_second_derivatives(*model_, in, out, stream);
}

template <class S>
void CudaIdSecondDerivatives<S>::compute(const IdBatchIn<S>& in, const IdSecondDerivativesOut<S>& out) {
  check_batch(in, out, max_batch_);
  const Index B = in.q.batch, nv = nv_;
  if (B == 0 || nv == 0) return;
  const std::size_t cap = static_cast<std::size_t>(nv) * max_batch_;
  const std::size_t tcap = static_cast<std::size_t>(nv) * nv * cap;  // one tensor's scalars
  const Index width = nv * nv * nv;
  S* const buffer = static_cast<S*>(staging_->data());
  S* const tensors = buffer + kInputSlots * cap;
  const cudaStream_t stream = staging_->stream();
  static const char* const kNames[kTensors] = {"d2tau_dq2", "d2tau_dqd2", "d2tau_dqdqd", "dM_dq"};
  const BatchView<S> host[kTensors] = {out.d2tau_dq2, out.d2tau_dqd2, out.d2tau_dqdqd, out.dM_dq};
  Staging st[kTensors];
  BatchView<S> dev[kTensors];
  for (int k = 0; k < kTensors; ++k)
    if (host[k].data) {
      st[k] = plan(host[k], width, tcap, true, kNames[k]);
      dev[k] = st[k].device_view(tensors + k * tcap, B);
    }
  const detail::StagedInputs<S> d =
      detail::stage_inputs<S>({in.q, in.qd, in.qdd}, {"q", "qd", "qdd"}, in.fext, nv, cap, buffer, stream);
  check(compute_async(IdBatchIn<S>{d.in[0], d.in[1], d.in[2], d.fext},
                      IdSecondDerivativesOut<S>{dev[0], dev[1], dev[2], dev[3]}, stream),
        "launching id_second_derivatives_kernel");
  for (int k = 0; k < kTensors; ++k)
    if (host[k].data)
      check(copy(st[k], host[k], width, tensors + k * tcap, cudaMemcpyDeviceToHost, stream),
            (std::string("copying ") + kNames[k] + " to the host").c_str());
  check(cudaStreamSynchronize(stream), "running id_second_derivatives_kernel");
}

template <class S>
std::unique_ptr<IdSecondDerivatives<S>> make_cuda_id_second_derivatives(const ModelTpl<S>& model,
                                                                        const BackendOptions& options) {
  return std::make_unique<CudaIdSecondDerivatives<S>>(model, options);
}

#define SCANDYN_INSTANTIATE(S)                                                                                       \
  template class SecondOrderThreadModel<S>;                                                                                \
  template class CudaIdSecondDerivatives<S>;                                                                        \
  template cudaError_t launch_id_second_derivatives(const SecondOrderThreadModel<S>&, const IdBatchIn<S>&,                 \
                                                    const IdSecondDerivativesOut<S>&, cudaStream_t);                \
  template std::unique_ptr<IdSecondDerivatives<S>> make_cuda_id_second_derivatives(const ModelTpl<S>&,              \
                                                                                   const BackendOptions&);
SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)
#undef SCANDYN_INSTANTIATE

}  // namespace cuda
}  // namespace scandyn
