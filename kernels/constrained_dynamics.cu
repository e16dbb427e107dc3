// kernels/constrained_dynamics.cu: forward dynamics of trees closed by loops, one
// thread per instance (scandyn/cuda/constrained_dynamics.hpp): crba_instance and
// rnea_instance for M and h, then loop_body_motion, loop_rows and
// constrained_fd_solve of scandyn/algorithm/loop_solver.hpp (the CPU engines'
// routines), in thread-local arrays of compile-time capacities.
#include <cuda_runtime.h>

#include <string>
#include <type_traits>
#include <variant>

#include "scandyn/algorithm/loops.hpp"
#include "scandyn/cuda/constrained_dynamics.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/instance/crba_instance.hpp"
#include "scandyn/instance/rnea_instance.hpp"
#include "staging.hpp"

namespace scandyn {
namespace cuda {

using detail::check;
using detail::copy;
using detail::plan;
using detail::Staging;

namespace {

constexpr int kLoopBlock = 128;

// Instance b's q and qd (and tau) as contiguous per-thread arrays.
template <class S, int C>
__device__ __forceinline__ void load(const BatchView<const S>& v, long long b, Index n, S (&x)[C]) {
  const DofColumn<const S> c = instance_column(v, b);
  for (Index i = 0; i < n; ++i) x[i] = c[i];
}

// The loops' rows of one instance: X0, v, a into the thread's arrays, then phi, J, gamma.
template <class S, int C>
__device__ __forceinline__ void instance_rows(const ThreadModelParams<S, C>& model, const LoopRow<S>* loops,
                                              Index nloops, const S* q, const S* qd, S* phi, S* J, S* gamma) {
  Transform<S> X0[C];
  Motion<S> v[C], a[C];
  loop_body_motion(model.body, model.nv, q, qd, X0, v, a);
  loop_rows(model.body, model.nv, loops, nloops, X0, v, a, phi, J, gamma);
}

template <class S, int C, int MC>
__global__ void __launch_bounds__(kLoopBlock)
    constrained_fd_kernel(const __grid_constant__ ThreadModelParams<S, C> model, const LoopRow<S>* const loops,
                          const Index nloops, const Index m, const FdBatchIn<S> in, const BatchView<S> qdd_out,
                          const BatchView<S> lambda_out, int* const failed_dof) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= in.q.batch) return;
  const Index n = model.nv;
  S q[C], qd[C], tau[C], zero[C];
  load(in.q, b, n, q);
  load(in.qd, b, n, qd);
  load(in.tau, b, n, tau);
  for (Index i = 0; i < C; ++i) zero[i] = S(0);
  S Mt[C * (C + 1) / 2];
  crba_instance<S, C>(model, DofColumn<const S>{q, 1}, Mt);
  S M[C * C];
  for_each_mass_entry<S, C>(model, Mt, [&](Index e, S x) { M[e] = x; });
  S h[C];
  const Force<S>* fext = in.fext ? in.fext + b * n : nullptr;
  rnea_instance<S, C>(model, DofColumn<const S>{q, 1}, DofColumn<const S>{qd, 1}, DofColumn<const S>{zero, 1}, fext,
                      DofColumn<S>{h, 1});
  S J[MC * C], gamma[MC];
  instance_rows(model, loops, nloops, q, qd, static_cast<S*>(nullptr), J, gamma);
  S x[C], lam[MC], work[constrained_fd_scratch(C, MC)];
  Index perm[MC];
  const LoopSolveStatus st = constrained_fd_solve(n, m, M, h, tau, J, gamma, x, lam, work, perm);
  failed_dof[b] = static_cast<int>(st.failed_dof);
  if (st.failed_dof >= 0) return;  // outputs unwritten
  const DofColumn<S> qo = instance_column(qdd_out, b), lo = instance_column(lambda_out, b);
  for (Index i = 0; i < n; ++i) qo[i] = x[i];
  for (Index k = 0; k < m; ++k) lo[k] = lam[k];
}

template <class S, int C, int MC>
__global__ void __launch_bounds__(kLoopBlock)
    loop_residual_kernel(const __grid_constant__ ThreadModelParams<S, C> model, const LoopRow<S>* const loops,
                         const Index nloops, const Index m, const BatchView<const S> qv, const BatchView<const S> qdv,
                         const BatchView<S> phi_out, const BatchView<S> vel_out) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= qv.batch) return;
  const Index n = model.nv;
  S q[C], qd[C], phi[MC], J[MC * C];
  load(qv, b, n, q);
  load(qdv, b, n, qd);
  instance_rows(model, loops, nloops, q, qd, phi, J, static_cast<S*>(nullptr));
  if (phi_out.data) {
    const DofColumn<S> o = instance_column(phi_out, b);
    for (Index k = 0; k < m; ++k) o[k] = phi[k];
  }
  if (vel_out.data) {
    const DofColumn<S> o = instance_column(vel_out, b);
    for (Index k = 0; k < m; ++k) {
      S s = S(0);
      for (Index j = 0; j < n; ++j) s += J[k * n + j] * qd[j];
      o[k] = s;
    }
  }
}

// launch(params, MC) for the model's capacity (8 or 16) and the rows' (6 or 12).
template <class S, class Launch>
void visit_loop_kernel(const ThreadModel<S>& model, Index m, Launch&& launch) {
  visit_compiled_capacity(model.params(), [&](const auto& params) {
    constexpr int C = std::decay_t<decltype(params)>::capacity;
    if constexpr (C <= kLoopMaxDofs) {
      if (m <= 6)
        launch(params, std::integral_constant<int, 6>{});
      else
        launch(params, std::integral_constant<int, static_cast<int>(kLoopMaxRows)>{});
    }
  });
}

unsigned blocks_for(Index B) {
  return static_cast<unsigned>((static_cast<long long>(B) + kLoopBlock - 1) / kLoopBlock);
}

}  // namespace

template <class S>
CudaConstrainedForwardDynamics<S>::CudaConstrainedForwardDynamics(const ModelTpl<S>& model, const LoopSet& loops,
                                                                  const BackendOptions& options)
    : nv_(model.nv()),
      m_(loops.rows()),
      nloops_(static_cast<Index>(loops.loops.size())),
      max_batch_(options.max_batch) {
  if (nv_ > kLoopMaxDofs || m_ > kLoopMaxRows)
    throw BackendError("backend 'cuda': closed-loop forward dynamics runs one thread per instance for models of up to " +
                       std::to_string(kLoopMaxDofs) + " DoF with up to " + std::to_string(kLoopMaxRows) +
                       " constraint rows; this one has " + std::to_string(nv_) + " DoF and " + std::to_string(m_) +
                       " rows (use the serial or openmp backend)");
  // q, qd, tau in (slots 0..2), qdd out (slot 3), fext (slots 4..9), then m per instance
  // for lambda (the residual's phi) and m for the residual's J qd, and a failed DoF
  staging_ = std::make_unique<detail::StagingBuffer>(
      max_batch_, nv_, sizeof(S) == 4 ? "float" : "double", "q, qd, tau, qdd, fext, lambda, J qd and a failed DoF",
      (10 * static_cast<std::size_t>(nv_) + 2 * static_cast<std::size_t>(m_)) * sizeof(S) + sizeof(int));
  device_ = staging_->device();
  thread_ = std::make_unique<ThreadModel<S>>(model);
  const std::vector<LoopRow<S>> rows = loop_rows_of<S>(loops);
  if (!rows.empty()) {
    check(cudaMalloc(reinterpret_cast<void**>(&loops_), rows.size() * sizeof(LoopRow<S>)), "allocating the loops");
    check(cudaMemcpy(loops_, rows.data(), rows.size() * sizeof(LoopRow<S>), cudaMemcpyHostToDevice),
          "copying the loops to the device");
  }
  failed_host_.resize(static_cast<std::size_t>(max_batch_));
}

template <class S>
CudaConstrainedForwardDynamics<S>::~CudaConstrainedForwardDynamics() {
  if (loops_) cudaFree(loops_);
}

template <class S>
cudaError_t CudaConstrainedForwardDynamics<S>::compute_async(const FdBatchIn<S>& in, const BatchView<S>& qdd,
                                                             const BatchView<S>& lambda, int* failed_dof,
                                                             cudaStream_t stream) {
  const Index B = in.q.batch;
  if (B < 0 || B > max_batch_ || in.qd.batch != B || in.tau.batch != B || qdd.batch != B || lambda.batch != B)
    return cudaErrorInvalidValue;
  if (B == 0) return cudaSuccess;
  if (!failed_dof || !in.q.data || !in.qd.data || !in.tau.data || !qdd.data || (m_ > 0 && !lambda.data))
    return cudaErrorInvalidValue;
  visit_loop_kernel(*thread_, m_, [&](const auto& params, auto mc) {
    constexpr int C = std::decay_t<decltype(params)>::capacity;
    constrained_fd_kernel<S, C, decltype(mc)::value>
        <<<blocks_for(B), kLoopBlock, 0, stream>>>(params, loops_, nloops_, m_, in, qdd, lambda, failed_dof);
  });
  return cudaGetLastError();
}

template <class S>
cudaError_t CudaConstrainedForwardDynamics<S>::residual_async(const BatchView<const S>& q, const BatchView<const S>& qd,
                                                              const BatchView<S>& phi, const BatchView<S>& velocity,
                                                              cudaStream_t stream) {
  const Index B = q.batch;
  if (B < 0 || B > max_batch_ || qd.batch != B || (phi.data && phi.batch != B) ||
      (velocity.data && velocity.batch != B))
    return cudaErrorInvalidValue;
  if (B == 0) return cudaSuccess;
  if (!q.data || !qd.data) return cudaErrorInvalidValue;
  visit_loop_kernel(*thread_, m_, [&](const auto& params, auto mc) {
    constexpr int C = std::decay_t<decltype(params)>::capacity;
    loop_residual_kernel<S, C, decltype(mc)::value>
        <<<blocks_for(B), kLoopBlock, 0, stream>>>(params, loops_, nloops_, m_, q, qd, phi, velocity);
  });
  return cudaGetLastError();
}

template <class S>
BatchStatus CudaConstrainedForwardDynamics<S>::compute(const FdBatchIn<S>& in, const BatchView<S>& qdd,
                                                       const BatchView<S>& lambda) {
  check_batch(in, qdd, lambda, max_batch_);
  const Index B = in.q.batch, nv = nv_;
  int* const failed = failed_host_.data();
  BatchStatus status;
  status.failed_dof = failed;
  if (B == 0) return status;
  const std::size_t cap = static_cast<std::size_t>(nv) * max_batch_;
  const std::size_t capm = static_cast<std::size_t>(m_) * max_batch_;
  const cudaStream_t stream = staging_->stream();
  S* const buffer = static_cast<S*>(staging_->data());
  S* const dqdd = buffer + 3 * cap;
  S* const dlambda = buffer + 10 * cap;
  int* const dfailed = reinterpret_cast<int*>(dlambda + 2 * capm);
  const Staging sqdd = plan(qdd, nv, cap, true, "qdd");
  const Staging slam = plan(lambda, m_, capm, true, "lambda");
  const detail::StagedInputs<S> d =
      detail::stage_inputs<S>({in.q, in.qd, in.tau}, {"q", "qd", "tau"}, in.fext, nv, cap, buffer, stream);
  // the outputs go over too: a failed instance's entries come back unchanged
  check(copy(sqdd, qdd, nv, dqdd, cudaMemcpyHostToDevice, stream), "copying qdd to the device");
  check(copy(slam, lambda, m_, dlambda, cudaMemcpyHostToDevice, stream), "copying lambda to the device");
  const FdBatchIn<S> din{d.in[0], d.in[1], d.in[2], d.fext};
  check(compute_async(din, sqdd.device_view(dqdd, B), slam.device_view(dlambda, B), dfailed, stream),
        "launching the closed-loop forward dynamics");
  check(cudaMemcpyAsync(failed, dfailed, static_cast<std::size_t>(B) * sizeof(int), cudaMemcpyDeviceToHost, stream),
        "copying the failed DoFs to the host");
  check(copy(sqdd, qdd, nv, dqdd, cudaMemcpyDeviceToHost, stream), "copying qdd to the host");
  check(copy(slam, lambda, m_, dlambda, cudaMemcpyDeviceToHost, stream), "copying lambda to the host");
  check(cudaStreamSynchronize(stream), "running the closed-loop forward dynamics");
  return summarize_failures(failed, B, Failure::MassMatrixPivot);
}

template <class S>
void CudaConstrainedForwardDynamics<S>::residual(const BatchView<const S>& q, const BatchView<const S>& qd,
                                                 const BatchView<S>& phi, const BatchView<S>& velocity) {
  const Index B = q.batch, nv = nv_;
  if (qd.batch != B || (phi.data && phi.batch != B) || (velocity.data && velocity.batch != B) || B > max_batch_)
    throw BackendError("loop residual: batch sizes disagree (q " + std::to_string(B) + ", qd " +
                       std::to_string(qd.batch) + ") or exceed max_batch " + std::to_string(max_batch_));
  if (B == 0) return;
  const std::size_t cap = static_cast<std::size_t>(nv) * max_batch_;
  const std::size_t capm = static_cast<std::size_t>(m_) * max_batch_;
  const cudaStream_t stream = staging_->stream();
  S* const buffer = static_cast<S*>(staging_->data());
  // q, qd in slots 0 and 1; phi in lambda's region, J qd after it
  S* const dphi = buffer + 10 * cap;
  S* const dvel = dphi + capm;
  Staging sq[2];
  BatchView<const S> dq[2];
  const BatchView<const S> hin[2] = {q, qd};
  for (int k = 0; k < 2; ++k) {
    sq[k] = plan(hin[k], nv, cap, false);
    check(copy(sq[k], hin[k], nv, buffer + k * cap, cudaMemcpyHostToDevice, stream), "copying q, qd to the device");
    dq[k] = sq[k].template device_view<const S>(buffer + k * cap, B);
  }
  Staging sphi{}, svel{};
  BatchView<S> dphi_v{}, dvel_v{};
  if (phi.data) {
    sphi = plan(phi, m_, capm, true, "phi");
    check(copy(sphi, phi, m_, dphi, cudaMemcpyHostToDevice, stream), "copying phi to the device");
    dphi_v = sphi.device_view(dphi, B);
  }
  if (velocity.data) {
    svel = plan(velocity, m_, capm, true, "velocity");
    check(copy(svel, velocity, m_, dvel, cudaMemcpyHostToDevice, stream), "copying velocity to the device");
    dvel_v = svel.device_view(dvel, B);
  }
  check(residual_async(dq[0], dq[1], dphi_v, dvel_v, stream), "launching the loop residual");
  if (phi.data) check(copy(sphi, phi, m_, dphi, cudaMemcpyDeviceToHost, stream), "copying phi to the host");
  if (velocity.data) check(copy(svel, velocity, m_, dvel, cudaMemcpyDeviceToHost, stream), "copying J qd to the host");
  check(cudaStreamSynchronize(stream), "running the loop residual");
}

template <class S>
std::unique_ptr<ConstrainedForwardDynamics<S>> make_constrained_forward_dynamics(const ModelTpl<S>& model,
                                                                                 const LoopSet& loops,
                                                                                 const BackendOptions& options) {
  return std::make_unique<CudaConstrainedForwardDynamics<S>>(model, loops, options);
}

#define SCANDYN_INSTANTIATE(S)                                                                  \
  template class CudaConstrainedForwardDynamics<S>;                                             \
  template std::unique_ptr<ConstrainedForwardDynamics<S>> make_constrained_forward_dynamics(    \
      const ModelTpl<S>&, const LoopSet&, const BackendOptions&);
SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)
#undef SCANDYN_INSTANTIATE

}  // namespace cuda
}  // namespace scandyn
