// kernels/step_derivatives.cu: the simulator step's Jacobian on a CUDA device, one
// thread per instance (scandyn/cuda/step_derivatives.hpp): step_jacobian_instance
// over the fused step's forward dynamics (fused_forward_dynamics) and
// fd_derivatives_instance.
#include <cuda_runtime.h>

#include <string>
#include <type_traits>
#include <variant>

#include "scandyn/cuda/step_derivatives.hpp"
#include "scandyn/instance/dynamics_derivatives.hpp"
#include "scandyn/instance/thread_model.hpp"
#include "sim_fused.cuh"
#include "staging.hpp"

namespace scandyn {
namespace cuda {

using detail::check;
using detail::copy;
using detail::plan;
using detail::Staging;
using sim::Integrator;

template <class S>
struct CudaStepDerivatives<S>::Params {
  // user frames (Body): the step and its derivatives (fd_derivatives_instance) read one model
  std::variant<sim::detail::SimParams<S, 8, Body<S>>, sim::detail::SimParams<S, 16, Body<S>>,
               sim::detail::SimParams<S, 32, Body<S>>, sim::detail::SimParams<S, 64, Body<S>>>
      v;
};

// One thread per instance b < B: the step of instance b and its Jacobian.
template <class S, int C, Integrator I>
__global__ void __launch_bounds__(kStepJacobianBlock)
    step_jacobian_kernel(const __grid_constant__ sim::detail::SimParams<S, C, Body<S>> p, const FdBatchIn<S> in,
                         const Force<S>* wrenches, const sim::StepDerivativesOut<S> out, S* scratch,
                         std::size_t per_instance, int* failed_dof) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= in.q.batch) return;
  const Index n = p.model.nv;
  S q[C], qd[C], tau[C];
  for (Index i = 0; i < n; ++i) q[i] = in.q.at(i, b), qd[i] = in.qd.at(i, b), tau[i] = in.tau.at(i, b);
  const Force<S>* const fext = in.fext ? in.fext + b * n : wrenches;
  DerivativeBody<S> work[C];  // per-thread local memory
  auto fd = [&](const S* qa, const S* qda, const S* t, const S* arm, S* qdd) -> Index {
    return sim::detail::fused_forward_dynamics<S, C, C>(p.model, fext, qa, qda, t, arm, qdd);
  };
  auto dfd = [&](const S* qa, const S* qda, const S* qdd, const S* arm, MatrixRef<S> Fq, MatrixRef<S> Fqd,
                 MatrixRef<S> Ft) -> Index {
    return fd_derivatives_instance(p.model.body, n, p.model.a0, qa, qda, qdd, fext, work, Fq, Fqd, Ft, arm);
  };
  const sim::StepJacobian<S> J{instance_matrix(out.q_q, b, n),  instance_matrix(out.q_qd, b, n),
                               instance_matrix(out.q_tau, b, n), instance_matrix(out.qd_q, b, n),
                               instance_matrix(out.qd_qd, b, n), instance_matrix(out.qd_tau, b, n)};
  Index failed = sim::step_jacobian_instance<sim::kJointEffects, I>(
      n, p.dt, p.coef, p.armature, q, qd, tau, scratch + static_cast<std::size_t>(b) * per_instance, J, fd, dfd);
  // a state or derivative that is not finite: -2 - its DoF (compute() reports it, never a silent NaN)
  const MatrixRef<S> blocks[6] = {J.q_q, J.q_qd, J.q_tau, J.qd_q, J.qd_qd, J.qd_tau};
  for (Index i = 0; i < n && failed < 0; ++i) {
    bool finite = isfinite(q[i]) && isfinite(qd[i]);
    for (int k = 0; k < 6; ++k)
      for (Index j = 0; j < n; ++j) finite = finite && isfinite(blocks[k](i, j));
    if (!finite) failed = -2 - i;
  }
  if (failed == -1)
    for (Index i = 0; i < n; ++i) {
      if (out.q_next.data) out.q_next.at(i, b) = q[i];
      if (out.qd_next.data) out.qd_next.at(i, b) = qd[i];
    }
  if (failed_dof) failed_dof[b] = static_cast<int>(failed);
}

// ---- the engine -----------------------------------------------------------------------
//
// Staging buffer for max_batch instances (cap = nv x max_batch scalars): q, qd, tau in
// slots 0..2, slot 3 unused, the wrenches (6 slots, detail::stage_inputs' layout),
// q' and qd' (2 slots), the six nv x nv outputs (nv slots each), the scratch, then
// max_batch ints of failed DoFs.

namespace {
constexpr std::size_t kInputSlots = 10;  // q, qd, tau, (unused), fext (6)
}

template <class S>
CudaStepDerivatives<S>::CudaStepDerivatives(const sim::SimSetup<S>& setup, const BackendOptions& options)
    : setup_(setup), nv_(setup.model.nv()), max_batch_(options.max_batch),
      failed_host_(static_cast<std::size_t>(std::max<Index>(options.max_batch, 1))) {
  if (nv_ > kMaxThreadDofs)
    throw BackendError("backend 'cuda': model '" + setup.model.name + "' has " + std::to_string(nv_) +
                       " DoF; the step derivatives run a thread per instance, which takes at most " +
                       std::to_string(kMaxThreadDofs));
  const std::size_t n = static_cast<std::size_t>(nv_);
  scratch_per_instance_ = sim::step_jacobian_scratch(nv_, setup.integrator);
  staging_ = std::make_unique<detail::StagingBuffer>(
      max_batch_, nv_, sizeof(S) == 4 ? "float" : "double",
      "q, qd, tau, fext, the new state, six nv x nv derivatives and the step's scratch",
      ((kInputSlots + 2 + 6 * n) * n + scratch_per_instance_) * sizeof(S) + sizeof(int));
  const ThreadModel<S> tm(setup.model);
  require_compiled_capacity(tm.capacity(), "the step derivatives", setup.model.name);
  params_ = std::make_unique<Params>();
  std::visit(
      [&](const auto& mp) {
        using MP = std::decay_t<decltype(mp)>;
        sim::detail::SimParams<S, MP::capacity, Body<S>> sp{};
        sp.model = mp;
        for (Index i = 0; i < nv_; ++i) {
          sp.coef[i] = setup.coef[i];
          sp.armature[i] = setup.armature.empty() ? S(0) : setup.armature[i];
        }
        sp.dt = setup.dt;
        sp.branch_slots = tm.branch_slots();
        params_->v = sp;
      },
      tm.params());
  if ((setup.effects & sim::kExternal) && !setup.wrenches.empty()) {
    check(cudaMalloc(&wrenches_, n * sizeof(Force<S>)), "allocating the scene's wrenches");
    check(cudaMemcpy(wrenches_, setup.wrenches.data(), n * sizeof(Force<S>), cudaMemcpyHostToDevice),
          "copying the scene's wrenches");
  }
}

template <class S>
CudaStepDerivatives<S>::~CudaStepDerivatives() {
  if (wrenches_) cudaFree(wrenches_);
}

template <class S>
cudaError_t CudaStepDerivatives<S>::compute_async(const FdBatchIn<S>& in, const sim::StepDerivativesOut<S>& out,
                                                  int* failed_dof, cudaStream_t stream) {
  const Index B = in.q.batch;
  if (B < 0 || B > max_batch_ || in.qd.batch != B || in.tau.batch != B) return cudaErrorInvalidValue;
  if (B == 0 || nv_ == 0) return cudaSuccess;
  const std::size_t cap = static_cast<std::size_t>(nv_) * max_batch_;
  S* const scratch = static_cast<S*>(staging_->data()) + (kInputSlots + 2 + 6 * static_cast<std::size_t>(nv_)) * cap;
  const Force<S>* const wrenches = (setup_.effects & sim::kExternal) ? wrenches_ : nullptr;
  const FdBatchIn<S> args{in.q, in.qd, in.tau, (setup_.effects & sim::kExternal) ? in.fext : nullptr};
  const unsigned blocks = static_cast<unsigned>((static_cast<long long>(B) + kStepJacobianBlock - 1) / kStepJacobianBlock);
  visit_compiled_capacity(params_->v, [&](const auto& sp) {
    using SP = std::decay_t<decltype(sp)>;
    constexpr int C = SP::capacity;
    switch (setup_.integrator) {
      case Integrator::Euler:
        step_jacobian_kernel<S, C, Integrator::Euler><<<blocks, kStepJacobianBlock, 0, stream>>>(
            sp, args, wrenches, out, scratch, scratch_per_instance_, failed_dof);
        break;
      case Integrator::Rk4:
        step_jacobian_kernel<S, C, Integrator::Rk4><<<blocks, kStepJacobianBlock, 0, stream>>>(
            sp, args, wrenches, out, scratch, scratch_per_instance_, failed_dof);
        break;
      case Integrator::Implicit:
        step_jacobian_kernel<S, C, Integrator::Implicit><<<blocks, kStepJacobianBlock, 0, stream>>>(
            sp, args, wrenches, out, scratch, scratch_per_instance_, failed_dof);
        break;
    }
  });
  return cudaGetLastError();
}

template <class S>
BatchStatus CudaStepDerivatives<S>::compute(const FdBatchIn<S>& in, const sim::StepDerivativesOut<S>& out) {
  check_batch(in, FdDerivativesOut<S>{out.q_q, out.q_qd, out.q_tau, {}}, max_batch_);
  check_batch(in, FdDerivativesOut<S>{out.qd_q, out.qd_qd, out.qd_tau, {}}, max_batch_);
  if (in.fext && !(setup_.effects & sim::kExternal))
    throw BackendError("the step derivatives: wrenches were given, but the scene declares no external effect");
  const Index B = in.q.batch, nv = nv_;
  if (B == 0 || nv == 0) return BatchStatus{};
  const std::size_t cap = static_cast<std::size_t>(nv) * max_batch_, mcap = static_cast<std::size_t>(nv) * cap;
  S* const buffer = static_cast<S*>(staging_->data());
  const cudaStream_t stream = staging_->stream();
  static const char* const kNames[6] = {"q_q", "q_qd", "q_tau", "qd_q", "qd_qd", "qd_tau"};
  const BatchView<S> host[6] = {out.q_q, out.q_qd, out.q_tau, out.qd_q, out.qd_qd, out.qd_tau};
  S* const mats = buffer + (kInputSlots + 2) * cap;
  Staging st[6];
  BatchView<S> dev[6];
  for (int k = 0; k < 6; ++k) {
    st[k] = plan(host[k], nv * nv, cap, true, kNames[k]);
    dev[k] = st[k].device_view(mats + k * mcap, B);
  }
  const BatchView<S> host_state[2] = {out.q_next, out.qd_next};
  Staging sst[2];
  BatchView<S> dstate[2] = {};
  for (int k = 0; k < 2; ++k)
    if (host_state[k].data) {
      sst[k] = plan(host_state[k], nv, cap, true, k ? "qd_next" : "q_next");
      dstate[k] = sst[k].device_view(buffer + (kInputSlots + k) * cap, B);
    }
  int* const dfailed = reinterpret_cast<int*>(mats + 6 * mcap + scratch_per_instance_ * max_batch_);
  const detail::StagedInputs<S> d =
      detail::stage_inputs<S>({in.q, in.qd, in.tau}, {"q", "qd", "tau"}, in.fext, nv, cap, buffer, stream);
  check(compute_async(FdBatchIn<S>{d.in[0], d.in[1], d.in[2], d.fext},
                      sim::StepDerivativesOut<S>{dev[0], dev[1], dev[2], dev[3], dev[4], dev[5], dstate[0], dstate[1]},
                      dfailed, stream),
        "launching step_jacobian_kernel");
  for (int k = 0; k < 6; ++k)
    check(copy(st[k], host[k], nv * nv, mats + k * mcap, cudaMemcpyDeviceToHost, stream),
          (std::string("copying ") + kNames[k] + " to the host").c_str());
  for (int k = 0; k < 2; ++k)
    if (host_state[k].data)
      check(copy(sst[k], host_state[k], nv, buffer + (kInputSlots + k) * cap, cudaMemcpyDeviceToHost, stream),
            "copying the new state to the host");
  check(cudaMemcpyAsync(failed_host_.data(), dfailed, static_cast<std::size_t>(B) * sizeof(int), cudaMemcpyDeviceToHost,
                        stream),
        "copying the failed DoFs to the host");
  check(cudaStreamSynchronize(stream), "running step_jacobian_kernel");
  return summarize_step_failures(failed_host_.data(), B);
}

template <class S>
std::unique_ptr<sim::StepDerivatives<S>> make_cuda_step_derivatives(const sim::SimSetup<S>& setup,
                                                                    const BackendOptions& options) {
  return std::make_unique<CudaStepDerivatives<S>>(setup, options);
}

#define SCANDYN_INSTANTIATE(S)                \
  template class CudaStepDerivatives<S>;      \
  template std::unique_ptr<sim::StepDerivatives<S>> make_cuda_step_derivatives(const sim::SimSetup<S>&, \
                                                                               const BackendOptions&);
SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)
#undef SCANDYN_INSTANTIATE

}  // namespace cuda
}  // namespace scandyn
