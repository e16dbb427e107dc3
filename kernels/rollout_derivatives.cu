// kernels/rollout_derivatives.cu: rollouts of the simulator's step and their
// derivatives on a CUDA device, one thread per instance
// (scandyn/cuda/rollout_derivatives.hpp): the serial engine's instance functions
// (rollout_instance, rollout_jvp_instance, rollout_vjp_instance of
// scandyn/sim/step_derivatives.hpp) over the fused step's forward dynamics
// (fused_forward_dynamics) and the directional derivatives of
// scandyn/instance/directional_instance.hpp.
#include <cuda_runtime.h>

#include <algorithm>
#include <string>
#include <type_traits>
#include <variant>

#include "scandyn/cuda/rollout_derivatives.hpp"
#include "scandyn/instance/directional_instance.hpp"
#include "scandyn/instance/thread_model.hpp"
#include "sim_fused.cuh"
#include "staging.hpp"

namespace scandyn {
namespace cuda {

using detail::check;
using sim::Integrator;
using sim::StepSequence;

template <class S>
struct CudaRolloutDerivatives<S>::Params {
  // user frames (Body): the step and the RNEA of the directional derivatives read one model
  std::variant<sim::detail::SimParams<S, 8, Body<S>>, sim::detail::SimParams<S, 16, Body<S>>,
               sim::detail::SimParams<S, 32, Body<S>>, sim::detail::SimParams<S, 64, Body<S>>>
      v;
};

namespace {

// The arguments of each kernel (device views).
template <class S>
struct RolloutArgs {
  BatchView<const S> q0, qd0;
  StepSequence<const S> tau;
  StepSequence<S> q, qd;
};
template <class S>
struct JvpArgs {
  BatchView<const S> q0, qd0;
  StepSequence<const S> tau;
  BatchView<const S> dq0, dqd0;
  StepSequence<const S> dtau;
  StepSequence<S> dq, dqd;
};
template <class S>
struct VjpArgs {
  BatchView<const S> q0, qd0;
  StepSequence<const S> tau, gq, gqd;
  BatchView<S> gq0, gqd0;
  StepSequence<S> gtau;
  Index K;   // checkpoint interval
  S* store;  // rollout_store_slots(T, K) * 2 nv * B scalars, the instance innermost
};

// One thread's step functions over the fused step's forward dynamics (capacity C,
// integrator I): the same composition as the serial engine's InstanceKernels
// (cpu_fallback/step_derivatives.cpp), with the thread's local scratch.
template <class S, int C, Integrator I>
struct ThreadSteps {
  using Model = ThreadModelParams<S, C, Body<S>>;
  const sim::detail::SimParams<S, C, Body<S>>& p;
  const Model& rest;      // the model without gravity: M^-1 x by the ABA at rest
  const Force<S>* fext;   // the scene's constant wrenches, or null
  S scratch[32 * C];      // the step functions' scratch (step_directional_scratch), fd's qdd at 30 C
  S zero[C];              // qd = 0 of the ABA at rest
  Transform<S> Xup[C];    // the RNEA's per-body values (directional derivatives)
  Motion<S> v[C], a[C];
  Force<S> f[C];

  __device__ ThreadSteps(const sim::detail::SimParams<S, C, Body<S>>& p_, const Model& rest_, const Force<S>* fext_)
      : p(p_), rest(rest_), fext(fext_) {
    for (int i = 0; i < C; ++i) zero[i] = S(0);
  }
  __device__ Index n() const { return p.model.nv; }
  __device__ auto fd() {
    return [this](const S* qa, const S* qda, const S* t, const S* arm, S* qdd) -> Index {
      return sim::detail::fused_forward_dynamics<S, C, C>(p.model, fext, qa, qda, t, arm, qdd);
    };
  }
  __device__ auto m_inv() {
    return [this](const S* qa, const S* x, const S* arm, S* y) -> Index {
      return sim::detail::fused_forward_dynamics<S, C, C>(rest, static_cast<const Force<S>*>(nullptr), qa,
                                                          static_cast<const S*>(zero), x, arm, y);
    };
  }
  __device__ RneaBodies<S> bodies() { return {Xup, v, a, f}; }
  // step_instance
  __device__ Index step(S* x, S* xd, const S* u) {
    const Index m = n();
    const sim::StepScratch<S> sc{scratch, scratch + m, scratch + 2 * m, scratch + 3 * m, scratch + 4 * m,
                                 scratch + 5 * m};
    return sim::step_instance<sim::kJointEffects, I, C>(m, p.dt, p.coef, p.armature, x, xd, u, sc, fd());
  }
};

__device__ inline long long thread_instance() {
  return static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
}

template <class S, int C, Integrator I>
__global__ void __launch_bounds__(kRolloutBlock)
    rollout_kernel(const __grid_constant__ sim::detail::SimParams<S, C, Body<S>> p,
                   const ThreadModelParams<S, C, Body<S>>* rest, const Force<S>* wrenches, const RolloutArgs<S> a,
                   int* failed_dof) {
  const long long b = thread_instance();
  if (b >= a.q0.batch) return;
  ThreadSteps<S, C, I> w(p, *rest, wrenches);
  S rows[8 * C];
  const Index code = sim::rollout_instance(w.n(), static_cast<Index>(b), a.q0, a.qd0, a.tau, a.q, a.qd, rows,
                                           [&](S* x, S* xd, const S* u) { return w.step(x, xd, u); });
  if (failed_dof) failed_dof[b] = static_cast<int>(code);
}

template <class S, int C, Integrator I>
__global__ void __launch_bounds__(kRolloutBlock)
    rollout_jvp_kernel(const __grid_constant__ sim::detail::SimParams<S, C, Body<S>> p,
                       const ThreadModelParams<S, C, Body<S>>* rest, const Force<S>* wrenches, const JvpArgs<S> a,
                       int* failed_dof) {
  const long long b = thread_instance();
  if (b >= a.q0.batch) return;
  ThreadSteps<S, C, I> w(p, *rest, wrenches);
  RneaTangent<S> t[C];
  S rows[8 * C];
  const Index n = w.n();
  auto fd_jvp = [&](const S* qa, const S* qda, const S* ta, const S* dqa, const S* dqda, const S* dta,
                    const S* arm, S* dqdd, S* qdd) -> Index {
    return aba_jvp_instance(p.model.body, n, p.model.a0, qa, qda, ta, wrenches, dqa, dqda, dta, arm, w.bodies(), t,
                            w.scratch + 31 * C, dqdd, qdd, w.fd(), w.m_inv());
  };
  const Index code = sim::rollout_jvp_instance(
      n, static_cast<Index>(b), a.q0, a.qd0, a.tau, a.dq0, a.dqd0, a.dtau, a.dq, a.dqd, rows,
      [&](S* x, S* xd, const S* u, S* dx, S* dxd, const S* du) {
        return sim::step_jvp_instance<sim::kJointEffects, I>(n, p.dt, p.coef, p.armature, x, xd, u, dx, dxd, du,
                                                             w.scratch, fd_jvp);
      });
  if (failed_dof) failed_dof[b] = static_cast<int>(code);
}

template <class S, int C, Integrator I>
__global__ void __launch_bounds__(kRolloutBlock)
    rollout_vjp_kernel(const __grid_constant__ sim::detail::SimParams<S, C, Body<S>> p,
                       const ThreadModelParams<S, C, Body<S>>* rest, const Force<S>* wrenches, const VjpArgs<S> a,
                       int* failed_dof) {
  const long long b = thread_instance();
  const Index B = a.q0.batch;
  if (b >= B) return;
  ThreadSteps<S, C, I> w(p, *rest, wrenches);
  RneaAdjoint<S> adj[C];
  S rows[8 * C];
  const Index n = w.n();
  S* const qdd = w.scratch + 30 * C;  // past step_vjp_instance's rows
  auto fd_vjp = [&](const S* qa, const S* qda, const S* ta, const S* arm, const S* wt, S* ga, S* gb,
                    S* gt) -> Index {
    return aba_vjp_instance(p.model.body, n, p.model.a0, qa, qda, ta, wrenches, wt, arm, w.bodies(), adj,
                            w.scratch + 31 * C, ga, gb, gt, qdd, w.fd(), w.m_inv());
  };
  const sim::StateStore<S> store{a.store + b, static_cast<std::ptrdiff_t>(n) * B, B};
  const Index code = sim::rollout_vjp_instance(
      n, static_cast<Index>(b), a.K, a.q0, a.qd0, a.tau, a.gq, a.gqd, a.gq0, a.gqd0, a.gtau, rows, store,
      [&](S* x, S* xd, const S* u) { return w.step(x, xd, u); },
      [&](const S* x, const S* xd, const S* u, S* lq, S* lqd, S* gu) {
        return sim::step_vjp_instance<sim::kJointEffects, I>(n, p.dt, p.coef, p.armature, x, xd, u, lq, lqd, gu,
                                                             w.scratch, w.fd(), fd_vjp);
      });
  if (failed_dof) failed_dof[b] = static_cast<int>(code);
}

// Launches kernel<S, C, I> for the setup's integrator: launch(kernel) with the
// kernel of each capacity and integrator (K<S, C, I> from a template).
template <class S, template <class, int, Integrator> class Launch, class Variant, class... A>
cudaError_t launch_for(const Variant& params, Integrator integrator, const void* rest, Index B, cudaStream_t stream,
                       A&&... args) {
  const unsigned blocks = static_cast<unsigned>((static_cast<long long>(B) + kRolloutBlock - 1) / kRolloutBlock);
  visit_compiled_capacity(params, [&](const auto& sp) {
    constexpr int C = std::decay_t<decltype(sp)>::capacity;
    const auto* r = static_cast<const ThreadModelParams<S, C, Body<S>>*>(rest);
    switch (integrator) {
      case Integrator::Euler:
        Launch<S, C, Integrator::Euler>::run(blocks, stream, sp, r, args...);
        break;
      case Integrator::Rk4:
        Launch<S, C, Integrator::Rk4>::run(blocks, stream, sp, r, args...);
        break;
      case Integrator::Implicit:
        Launch<S, C, Integrator::Implicit>::run(blocks, stream, sp, r, args...);
        break;
      default:
        break;  // refused at construction (require_differentiable_step)
    }
  });
  return cudaGetLastError();
}

template <class S, int C, Integrator I>
struct LaunchRollout {
  template <class... A>
  static void run(unsigned blocks, cudaStream_t stream, const A&... a) {
    rollout_kernel<S, C, I><<<blocks, kRolloutBlock, 0, stream>>>(a...);
  }
};
template <class S, int C, Integrator I>
struct LaunchJvp {
  template <class... A>
  static void run(unsigned blocks, cudaStream_t stream, const A&... a) {
    rollout_jvp_kernel<S, C, I><<<blocks, kRolloutBlock, 0, stream>>>(a...);
  }
};
template <class S, int C, Integrator I>
struct LaunchVjp {
  template <class... A>
  static void run(unsigned blocks, cudaStream_t stream, const A&... a) {
    rollout_vjp_kernel<S, C, I><<<blocks, kRolloutBlock, 0, stream>>>(a...);
  }
};

// The dense (T x nv x B) host copies of the host calls: a view's entries gathered to
// rows i * B + b, and scattered back.
template <class S>
void gather(const BatchView<const S>& v, Index n, S* dense) {
  const Index B = v.batch;
  for (Index i = 0; i < n; ++i)
    for (Index b = 0; b < B; ++b) dense[static_cast<std::size_t>(i) * B + b] = v.at(i, b);
}
template <class S>
void gather(const StepSequence<const S>& s, Index n, S* dense) {
  const std::size_t block = static_cast<std::size_t>(n) * s.first.batch;
  for (Index t = 0; t < s.steps; ++t) gather(s.at(t), n, dense + t * block);
}
template <class S>
void scatter(const S* dense, Index n, const BatchView<S>& v) {
  const Index B = v.batch;
  for (Index i = 0; i < n; ++i)
    for (Index b = 0; b < B; ++b) v.at(i, b) = dense[static_cast<std::size_t>(i) * B + b];
}
template <class S>
void scatter(const S* dense, Index n, const StepSequence<S>& s) {
  const std::size_t block = static_cast<std::size_t>(n) * s.first.batch;
  for (Index t = 0; t < s.steps; ++t) scatter(dense + t * block, n, s.at(t));
}

// Where the host calls' arrays lie in the dense buffers: consecutive blocks of nv x B
// scalars (a state: 1 block, a sequence of T steps: T blocks, a sequence not given:
// none), inputs first, so that one copy moves the inputs in and one the outputs out.
template <class S>
struct DenseLayout {
  std::size_t block = 0, used = 0;  // scalars per block, scalars so far
  Index B = 0, T = 0;
  std::size_t take(std::size_t blocks) {
    const std::size_t at = used;
    used += blocks * block;
    return at;
  }
  template <class V>
  BatchView<V> state(V* base, std::size_t at) const {
    return BatchView<V>::soa(base + at, 0, B);
  }
  template <class V>
  StepSequence<V> sequence(V* base, std::size_t at, bool given) const {
    if (!given) return {};
    return {BatchView<V>::soa(base + at, 0, B), static_cast<std::ptrdiff_t>(block), T};
  }
};

}  // namespace

template <class S>
CudaRolloutDerivatives<S>::CudaRolloutDerivatives(const sim::SimSetup<S>& setup, const BackendOptions& options,
                                                  Index checkpoint_interval)
    : setup_(setup), nv_(setup.model.nv()), interval_(checkpoint_interval) {
  (void)options;
  sim::require_differentiable_step(setup, "the rollout derivatives");
  if (checkpoint_interval < 0)
    throw BackendError("the rollout derivatives: checkpoint interval " + std::to_string(checkpoint_interval) +
                       " is negative");
  if (nv_ > kMaxThreadDofs)
    throw BackendError("backend 'cuda': model '" + setup.model.name + "' has " + std::to_string(nv_) +
                       " DoF; the rollout derivatives run a thread per instance, which takes at most " +
                       std::to_string(kMaxThreadDofs));
  const Result<int> count = device_count();
  if (!count) throw BackendError("backend 'cuda': " + count.error);
  if (count.value == 0) throw BackendError("backend 'cuda': no usable CUDA device: the CUDA runtime reports 0 devices");
  check(cudaGetDevice(&device_), "cudaGetDevice");
  check(cudaStreamCreateWithFlags(&stream_, cudaStreamNonBlocking), "cudaStreamCreateWithFlags");
  try {
    const std::size_t n = static_cast<std::size_t>(nv_);
    ModelTpl<S> at_rest = setup.model;
    at_rest.gravity = Vec3<S>::zero();
    const ThreadModel<S> tm(setup.model), tm_rest(at_rest);
    require_compiled_capacity(tm.capacity(), "the rollout derivatives", setup.model.name);
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
          const MP& rest = std::get<MP>(tm_rest.params());
          check(cudaMalloc(&rest_, sizeof(MP)), "allocating the model at rest");
          check(cudaMemcpy(rest_, &rest, sizeof(MP), cudaMemcpyHostToDevice), "copying the model at rest");
        },
        tm.params());
    if ((setup.effects & sim::kExternal) && !setup.wrenches.empty()) {
      check(cudaMalloc(&wrenches_, n * sizeof(Force<S>)), "allocating the scene's wrenches");
      check(cudaMemcpy(wrenches_, setup.wrenches.data(), n * sizeof(Force<S>), cudaMemcpyHostToDevice),
            "copying the scene's wrenches");
    }
  } catch (...) {
    if (rest_) cudaFree(rest_);
    if (wrenches_) cudaFree(wrenches_);
    cudaStreamDestroy(stream_);
    throw;
  }
}

template <class S>
CudaRolloutDerivatives<S>::~CudaRolloutDerivatives() {
  void* const owned[4] = {store_.ptr, io_.ptr, rest_, wrenches_};
  for (void* p : owned)
    if (p) cudaFree(p);
  if (stream_) cudaStreamDestroy(stream_);
}

template <class S>
void CudaRolloutDerivatives<S>::grow(Buffer& buf, std::size_t bytes, const char* what) {
  if (bytes <= buf.bytes) return;
  if (buf.ptr) {
    check(cudaDeviceSynchronize(), "finishing the calls that use the buffer");  // (any stream's)
    check(cudaFree(buf.ptr), "freeing a buffer");
    buf = Buffer{};
  }
  buf.ptr = detail::device_malloc(bytes, [&](std::size_t free_bytes, std::size_t total_bytes) {
    return "backend 'cuda': the rollout derivatives of model '" + setup_.model.name + "' (" + std::to_string(nv_) +
           " DoF, " + (sizeof(S) == 4 ? "float" : "double") + ") need " + std::to_string(bytes) +
           " bytes of device memory for " + what + "; device " + std::to_string(device_) + " has " +
           std::to_string(free_bytes) + " bytes free of " + std::to_string(total_bytes);
  });
  buf.bytes = bytes;
}

template <class S>
std::size_t CudaRolloutDerivatives<S>::store_bytes(Index T, Index B) const {
  return static_cast<std::size_t>(sim::rollout_store_slots(T, checkpoint_interval(T))) * 2 *
         static_cast<std::size_t>(nv_) * static_cast<std::size_t>(B) * sizeof(S);
}

template <class S>
void CudaRolloutDerivatives<S>::reserve(Index T, Index B) {
  grow(store_, store_bytes(T, B), "the checkpoint store ((ceil(T / K) + K) x 2 nv scalars per instance)");
}

template <class S>
cudaError_t CudaRolloutDerivatives<S>::rollout_async(const BatchView<const S>& q0, const BatchView<const S>& qd0,
                                                     const StepSequence<const S>& tau, const StepSequence<S>& q,
                                                     const StepSequence<S>& qd, int* failed_dof,
                                                     cudaStream_t stream) {
  const Index B = q0.batch, T = tau.steps;
  sim::require_rollout_state("q0", q0, B);
  sim::require_rollout_state("qd0", qd0, B);
  sim::require_rollout_sequence("tau", tau, T, B);
  sim::require_rollout_sequence("q", q, T, B);
  sim::require_rollout_sequence("qd", qd, T, B);
  if (B == 0) return cudaSuccess;
  return launch_for<S, LaunchRollout>(params_->v, setup_.integrator, rest_, B, stream, wrenches_,
                                      RolloutArgs<S>{q0, qd0, tau, q, qd}, failed_dof);
}

template <class S>
cudaError_t CudaRolloutDerivatives<S>::jvp_async(const BatchView<const S>& q0, const BatchView<const S>& qd0,
                                                 const StepSequence<const S>& tau, const BatchView<const S>& dq0,
                                                 const BatchView<const S>& dqd0, const StepSequence<const S>& dtau,
                                                 const StepSequence<S>& dq, const StepSequence<S>& dqd,
                                                 int* failed_dof, cudaStream_t stream) {
  const Index B = q0.batch, T = tau.steps;
  sim::require_rollout_state("q0", q0, B);
  sim::require_rollout_state("qd0", qd0, B);
  sim::require_rollout_state("dq0", dq0, B);
  sim::require_rollout_state("dqd0", dqd0, B);
  sim::require_rollout_sequence("tau", tau, T, B);
  sim::require_rollout_sequence("dtau", dtau, T, B);
  sim::require_rollout_sequence("dq", dq, T, B);
  sim::require_rollout_sequence("dqd", dqd, T, B);
  if (B == 0) return cudaSuccess;
  return launch_for<S, LaunchJvp>(params_->v, setup_.integrator, rest_, B, stream, wrenches_,
                                  JvpArgs<S>{q0, qd0, tau, dq0, dqd0, dtau, dq, dqd}, failed_dof);
}

template <class S>
cudaError_t CudaRolloutDerivatives<S>::vjp_async(const BatchView<const S>& q0, const BatchView<const S>& qd0,
                                                 const StepSequence<const S>& tau, const StepSequence<const S>& gq,
                                                 const StepSequence<const S>& gqd, const BatchView<S>& gq0,
                                                 const BatchView<S>& gqd0, const StepSequence<S>& gtau,
                                                 int* failed_dof, cudaStream_t stream) {
  const Index B = q0.batch, T = tau.steps;
  sim::require_rollout_state("q0", q0, B);
  sim::require_rollout_state("qd0", qd0, B);
  sim::require_rollout_state("gq0", gq0, B);
  sim::require_rollout_state("gqd0", gqd0, B);
  sim::require_rollout_sequence("tau", tau, T, B);
  sim::require_rollout_sequence("gq", gq, T, B);
  sim::require_rollout_sequence("gqd", gqd, T, B);
  sim::require_rollout_sequence("gtau", gtau, T, B);
  if (B == 0) return cudaSuccess;
  reserve(T, B);
  return launch_for<S, LaunchVjp>(
      params_->v, setup_.integrator, rest_, B, stream, wrenches_,
      VjpArgs<S>{q0, qd0, tau, gq, gqd, gq0, gqd0, gtau, checkpoint_interval(T), static_cast<S*>(store_.ptr)},
      failed_dof);
}

template <class S>
BatchStatus CudaRolloutDerivatives<S>::status_of(Index B) {
  return summarize_step_failures(failed_host_.data(), B);
}

// The host calls: the caller gathers every array into host_ (inputs first: `inputs`
// scalars of `total`); here one copy in, the launch (launch(dev, dfailed) on
// stream_), one copy of the outputs and the failed DoFs back; the caller scatters.
template <class S>
template <class Launch>
BatchStatus CudaRolloutDerivatives<S>::host_call(std::size_t inputs, std::size_t total, Index B, const char* kernel,
                                                 Launch&& launch) {
  grow(io_, total * sizeof(S) + static_cast<std::size_t>(B) * sizeof(int), "the host call's arrays");
  S* const dev = static_cast<S*>(io_.ptr);
  int* const dfailed = reinterpret_cast<int*>(dev + total);
  check(cudaMemcpyAsync(dev, host_.data(), inputs * sizeof(S), cudaMemcpyHostToDevice, stream_),
        "copying the inputs to the device");
  check(launch(dev, dfailed), (std::string("launching ") + kernel).c_str());
  failed_host_.resize(static_cast<std::size_t>(B));
  check(cudaMemcpyAsync(host_.data() + inputs, dev + inputs, (total - inputs) * sizeof(S), cudaMemcpyDeviceToHost,
                        stream_),
        "copying the results to the host");
  check(cudaMemcpyAsync(failed_host_.data(), dfailed, static_cast<std::size_t>(B) * sizeof(int),
                        cudaMemcpyDeviceToHost, stream_),
        "copying the failed DoFs to the host");
  check(cudaStreamSynchronize(stream_), (std::string("running ") + kernel).c_str());
  return status_of(B);
}

template <class S>
BatchStatus CudaRolloutDerivatives<S>::rollout(const BatchView<const S>& q0, const BatchView<const S>& qd0,
                                               const StepSequence<const S>& tau, const StepSequence<S>& q,
                                               const StepSequence<S>& qd) {
  const Index B = q0.batch, T = tau.steps, n = nv_;
  sim::require_rollout_state("qd0", qd0, B);
  if (B == 0) return BatchStatus{};
  DenseLayout<S> L{static_cast<std::size_t>(n) * B, 0, B, T};
  const std::size_t o_q0 = L.take(1), o_qd0 = L.take(1), o_tau = L.take(T), inputs = L.used;
  const std::size_t o_q = L.take(q.first.data ? T : 0), o_qd = L.take(qd.first.data ? T : 0);
  host_.resize(L.used);
  gather(q0, n, host_.data() + o_q0);
  gather(qd0, n, host_.data() + o_qd0);
  gather(tau, n, host_.data() + o_tau);
  const BatchStatus st = host_call(inputs, L.used, B, "rollout_kernel", [&](S* dev, int* dfailed) {
    const S* const in = dev;
    return rollout_async(L.state(in, o_q0), L.state(in, o_qd0), L.sequence(in, o_tau, true),
                         L.sequence(dev, o_q, q.first.data), L.sequence(dev, o_qd, qd.first.data), dfailed, stream_);
  });
  if (q.first.data) scatter(host_.data() + o_q, n, q);
  if (qd.first.data) scatter(host_.data() + o_qd, n, qd);
  return st;
}

template <class S>
BatchStatus CudaRolloutDerivatives<S>::jvp(const BatchView<const S>& q0, const BatchView<const S>& qd0,
                                           const StepSequence<const S>& tau, const BatchView<const S>& dq0,
                                           const BatchView<const S>& dqd0, const StepSequence<const S>& dtau,
                                           const StepSequence<S>& dq, const StepSequence<S>& dqd) {
  const Index B = q0.batch, T = tau.steps, n = nv_;
  sim::require_rollout_state("qd0", qd0, B);
  sim::require_rollout_state("dq0", dq0, B);
  sim::require_rollout_state("dqd0", dqd0, B);
  if (B == 0) return BatchStatus{};
  DenseLayout<S> L{static_cast<std::size_t>(n) * B, 0, B, T};
  const std::size_t o_q0 = L.take(1), o_qd0 = L.take(1), o_tau = L.take(T), o_dq0 = L.take(1), o_dqd0 = L.take(1),
                    o_dtau = L.take(dtau.first.data ? T : 0), inputs = L.used;
  const std::size_t o_dq = L.take(dq.first.data ? T : 0), o_dqd = L.take(dqd.first.data ? T : 0);
  host_.resize(L.used);
  gather(q0, n, host_.data() + o_q0);
  gather(qd0, n, host_.data() + o_qd0);
  gather(tau, n, host_.data() + o_tau);
  gather(dq0, n, host_.data() + o_dq0);
  gather(dqd0, n, host_.data() + o_dqd0);
  if (dtau.first.data) gather(dtau, n, host_.data() + o_dtau);
  const BatchStatus st = host_call(inputs, L.used, B, "rollout_jvp_kernel", [&](S* dev, int* dfailed) {
    const S* const in = dev;
    return jvp_async(L.state(in, o_q0), L.state(in, o_qd0), L.sequence(in, o_tau, true), L.state(in, o_dq0),
                     L.state(in, o_dqd0), L.sequence(in, o_dtau, dtau.first.data), L.sequence(dev, o_dq, dq.first.data),
                     L.sequence(dev, o_dqd, dqd.first.data), dfailed, stream_);
  });
  if (dq.first.data) scatter(host_.data() + o_dq, n, dq);
  if (dqd.first.data) scatter(host_.data() + o_dqd, n, dqd);
  return st;
}

template <class S>
BatchStatus CudaRolloutDerivatives<S>::vjp(const BatchView<const S>& q0, const BatchView<const S>& qd0,
                                           const StepSequence<const S>& tau, const StepSequence<const S>& gq,
                                           const StepSequence<const S>& gqd, const BatchView<S>& gq0,
                                           const BatchView<S>& gqd0, const StepSequence<S>& gtau) {
  const Index B = q0.batch, T = tau.steps, n = nv_;
  sim::require_rollout_state("qd0", qd0, B);
  sim::require_rollout_state("gq0", gq0, B);
  sim::require_rollout_state("gqd0", gqd0, B);
  if (B == 0) return BatchStatus{};
  DenseLayout<S> L{static_cast<std::size_t>(n) * B, 0, B, T};
  const std::size_t o_q0 = L.take(1), o_qd0 = L.take(1), o_tau = L.take(T), o_gq = L.take(gq.first.data ? T : 0),
                    o_gqd = L.take(gqd.first.data ? T : 0), inputs = L.used;
  const std::size_t o_gq0 = L.take(1), o_gqd0 = L.take(1), o_gtau = L.take(gtau.first.data ? T : 0);
  host_.resize(L.used);
  gather(q0, n, host_.data() + o_q0);
  gather(qd0, n, host_.data() + o_qd0);
  gather(tau, n, host_.data() + o_tau);
  if (gq.first.data) gather(gq, n, host_.data() + o_gq);
  if (gqd.first.data) gather(gqd, n, host_.data() + o_gqd);
  const BatchStatus st = host_call(inputs, L.used, B, "rollout_vjp_kernel", [&](S* dev, int* dfailed) {
    const S* const in = dev;
    return vjp_async(L.state(in, o_q0), L.state(in, o_qd0), L.sequence(in, o_tau, true),
                     L.sequence(in, o_gq, gq.first.data), L.sequence(in, o_gqd, gqd.first.data), L.state(dev, o_gq0),
                     L.state(dev, o_gqd0), L.sequence(dev, o_gtau, gtau.first.data), dfailed, stream_);
  });
  scatter(host_.data() + o_gq0, n, gq0);
  scatter(host_.data() + o_gqd0, n, gqd0);
  if (gtau.first.data) scatter(host_.data() + o_gtau, n, gtau);
  return st;
}

template class CudaRolloutDerivatives<float>;
template class CudaRolloutDerivatives<double>;

}  // namespace cuda
}  // namespace scandyn
