// cpu_fallback/step_derivatives.cpp: the serial and OpenMP derivatives of the
// simulator's step (scandyn/sim/step_derivatives.hpp): the step-Jacobian engine and
// the rollouts (forward, JVP, checkpointed VJP), threads over instances through the
// CPU engines' instance loop, each instance's step over the reference aba, its
// derivatives (fd_derivatives_instance) and directional derivatives (aba_jvp,
// aba_vjp).
#include <algorithm>
#include <array>
#include <cmath>
#include <utility>
#include <vector>

#include "instance_loop.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/cuda/rollout_derivatives.hpp"
#include "scandyn/cuda/step_derivatives.hpp"
#include "scandyn/algorithm/derivatives.hpp"
#include "scandyn/algorithm/directional_derivatives.hpp"
#include "scandyn/sim/manifold_step_derivatives.hpp"
#include "scandyn/sim/step_derivatives.hpp"

namespace scandyn {
namespace sim {
namespace {

// One thread's workspace.
template <class S>
struct StepWork {
  explicit StepWork(const SimSetup<S>& setup)
      : deriv(setup.model), directional(setup.model),
        scratch(setup.model.multi_dof()
                    ? std::max(step_jacobian_at_scratch(setup.model.nq(), setup.model.nv(), setup.integrator),
                               step_directional_at_scratch(setup.model.nq(), setup.model.nv()) +
                                   static_cast<std::size_t>(setup.model.nv()))
                    : std::max(step_jacobian_scratch(setup.model.nv(), setup.integrator),
                               step_directional_scratch(setup.model.nv()))),
        rows(rollout_rows(setup.model.nq(), setup.model.nv())) {}
  DerivativeDataTpl<S> deriv;       // the ABA's and the dense derivatives' scratch
  AbaJvpData<S> directional;        // aba_jvp / aba_vjp's scratch
  std::vector<S> scratch;           // the step functions' scratch
  std::vector<S> rows;              // (8 nv + nq) one instance's rows: the Jacobian's q (nq), qd, tau; the
                                    // rollout instance functions' (step_derivatives.hpp)
  std::vector<S> store;             // rollout vjp: checkpoints and one segment of states
};

// The step functions of one instance for joint-effect set E and integrator I over
// the reference aba, as the simulator's CpuInstanceStep::step_one calls them.
template <unsigned E, Integrator I, class S>
struct InstanceKernels {
  static auto fd(const SimSetup<S>& setup, StepWork<S>& w, const Force<S>* fext) {
    return [&setup, &w, fext](const S* qa, const S* qda, const S* t, const S* arm, S* qdd) -> Index {
      return aba(setup.model, w.deriv.aba, qa, qda, t, qdd, fext, arm).failed_dof;
    };
  }
  static Index step(const SimSetup<S>& setup, StepWork<S>& w, const Force<S>* fext, S* q, S* qd, const S* tau) {
    const Index n = setup.model.nv();
    S* const r = w.scratch.data();
    const StepScratch<S> sc{r, r + n, r + 2 * n, r + 3 * n, r + 4 * n, r + 5 * n};
    return step_instance<E, I>(n, setup.dt, setup.coef.data(), setup.armature.empty() ? nullptr : setup.armature.data(),
                               q, qd, tau, sc, fd(setup, w, fext));
  }
  static Index jacobian(const SimSetup<S>& setup, StepWork<S>& w, const Force<S>* fext, S* q, S* qd, const S* tau,
                        const StepJacobian<S>& J) {
    const ModelTpl<S>& model = setup.model;
    const Index n = model.nv();
    const Motion<S> a0 = base_acceleration(model.gravity);
    auto dfd = [&](const S* qa, const S* qda, const S* qdd, const S* arm, MatrixRef<S> Fq, MatrixRef<S> Fqd,
                   MatrixRef<S> Ft) -> Index {
      return fd_derivatives_instance(model.bodies.data(), n, a0, qa, qda, qdd, fext, w.deriv.work.data(), Fq, Fqd, Ft,
                                     arm);
    };
    return step_jacobian_instance<E, I>(n, setup.dt, setup.coef.data(),
                                        setup.armature.empty() ? nullptr : setup.armature.data(), q, qd, tau,
                                        w.scratch.data(), J, fd(setup, w, fext), dfd);
  }
  static Index jvp(const SimSetup<S>& setup, StepWork<S>& w, const Force<S>* fext, S* q, S* qd, const S* tau, S* dq,
                   S* dqd, const S* dtau) {
    auto fd_jvp = [&](const S* qa, const S* qda, const S* t, const S* dqa, const S* dqda, const S* dt,
                      const S* arm, S* dqdd, S* qdd) -> Index {
      return aba_jvp(setup.model, w.directional, qa, qda, t, fext, dqa, dqda, dt, dqdd, qdd, arm).failed_dof;
    };
    return step_jvp_instance<E, I>(setup.model.nv(), setup.dt, setup.coef.data(),
                                   setup.armature.empty() ? nullptr : setup.armature.data(), q, qd, tau, dq, dqd, dtau,
                                   w.scratch.data(), fd_jvp);
  }
  static Index vjp(const SimSetup<S>& setup, StepWork<S>& w, const Force<S>* fext, const S* q, const S* qd,
                   const S* tau, S* gq, S* gqd, S* gtau) {
    const Index n = setup.model.nv();
    S* const qdd = w.scratch.data() + 30 * static_cast<std::size_t>(n);  // past step_vjp_instance's rows
    auto fd_vjp = [&](const S* qa, const S* qda, const S* t, const S* arm, const S* wt, S* a, S* b, S* gt) -> Index {
      return aba_vjp(setup.model, w.directional, qa, qda, t, fext, wt, a, b, gt, qdd, arm).failed_dof;
    };
    return step_vjp_instance<E, I>(n, setup.dt, setup.coef.data(),
                                   setup.armature.empty() ? nullptr : setup.armature.data(), q, qd, tau, gq, gqd, gtau,
                                   w.scratch.data(), fd(setup, w, fext), fd_vjp);
  }
};

// The step functions of one instance of a model with multi-DoF joints (a floating
// base, spherical joints): step_instance_at over the reference aba, as the
// simulator's CpuInstanceStep::step_one_at; the Jacobian by
// step_jacobian_at_instance over fd_derivatives_general_instance; the JVP and VJP
// (the rollouts') by step_jvp_at_instance / step_vjp_at_instance over aba_jvp /
// aba_vjp, O(nv).
template <unsigned E, Integrator I, class S>
struct InstanceKernelsAt {
  static Index step(const SimSetup<S>& setup, StepWork<S>& w, const Force<S>* fext, S* q, S* qd, const S* tau) {
    const ModelTpl<S>& model = setup.model;
    const std::size_t n = static_cast<std::size_t>(model.nv());
    S* const r = w.scratch.data();
    const StepScratchAt<S> sc{r, r + n, r + 6 * n, r + 2 * n, r + 3 * n, r + 4 * n, r + 5 * n};
    return step_instance_at<E, I>(model.bodies.data(), model.nbodies(), model.nq(), model.nv(), setup.dt,
                                  setup.coef.data(), setup.armature.empty() ? nullptr : setup.armature.data(), q, qd,
                                  tau, sc, InstanceKernels<E, I, S>::fd(setup, w, fext));
  }
  static Index jacobian(const SimSetup<S>& setup, StepWork<S>& w, const Force<S>* fext, S* q, S* qd, const S* tau,
                        const StepJacobian<S>& J) {
    const ModelTpl<S>& model = setup.model;
    const Motion<S> a0 = base_acceleration(model.gravity);
    auto dfd = [&](const S* qa, const S* qda, const S* qdd, const S* arm, MatrixRef<S> Fq, MatrixRef<S> Fqd,
                   MatrixRef<S> Ft) -> Index {
      return fd_derivatives_general_instance(model.bodies.data(), model.nbodies(), model.nv(), a0, qa, qda, qdd, fext,
                                             w.deriv.dof_parent.data(), w.deriv.dof_last.data(), w.deriv.work.data(),
                                             Fq, Fqd, Ft, arm);
    };
    return step_jacobian_at_instance<E, I>(model.bodies.data(), model.nbodies(), model.nq(), model.nv(), setup.dt,
                                           setup.coef.data(), setup.armature.empty() ? nullptr : setup.armature.data(),
                                           q, qd, tau, w.scratch.data(), J, InstanceKernels<E, I, S>::fd(setup, w, fext),
                                           dfd);
  }
  // the JVP and VJP in O(nv): step_jvp_at_instance / step_vjp_at_instance over aba_jvp /
  // aba_vjp (their general path: the forward dynamics' directional derivatives of
  // multi-DoF joints)
  static Index jvp(const SimSetup<S>& setup, StepWork<S>& w, const Force<S>* fext, S* q, S* qd, const S* tau, S* dq,
                   S* dqd, const S* dtau) {
    const ModelTpl<S>& model = setup.model;
    auto fd_jvp = [&](const S* qa, const S* qda, const S* t, const S* dqa, const S* dqda, const S* dt,
                      const S* arm, S* dqdd, S* qdd) -> Index {
      return aba_jvp(model, w.directional, qa, qda, t, fext, dqa, dqda, dt, dqdd, qdd, arm).failed_dof;
    };
    return step_jvp_at_instance<E, I>(model.bodies.data(), model.nbodies(), model.nq(), model.nv(), setup.dt,
                                      setup.coef.data(), setup.armature.empty() ? nullptr : setup.armature.data(), q,
                                      qd, tau, dq, dqd, dtau, w.scratch.data(), fd_jvp);
  }
  static Index vjp(const SimSetup<S>& setup, StepWork<S>& w, const Force<S>* fext, const S* q, const S* qd,
                   const S* tau, S* gq, S* gqd, S* gtau) {
    const ModelTpl<S>& model = setup.model;
    // aba_vjp's qdd, past step_vjp_at_instance's rows
    S* const qdd = w.scratch.data() + step_directional_at_scratch(model.nq(), model.nv());
    auto fd_vjp = [&](const S* qa, const S* qda, const S* t, const S* arm, const S* wt, S* a, S* b, S* gt) -> Index {
      return aba_vjp(model, w.directional, qa, qda, t, fext, wt, a, b, gt, qdd, arm).failed_dof;
    };
    return step_vjp_at_instance<E, I>(model.bodies.data(), model.nbodies(), model.nq(), model.nv(), setup.dt,
                                      setup.coef.data(), setup.armature.empty() ? nullptr : setup.armature.data(), q,
                                      qd, tau, gq, gqd, gtau, w.scratch.data(), InstanceKernels<E, I, S>::fd(setup, w, fext),
                                      fd_vjp);
  }
};

template <class S>
struct KernelSet {
  Index (*step)(const SimSetup<S>&, StepWork<S>&, const Force<S>*, S*, S*, const S*);
  Index (*jacobian)(const SimSetup<S>&, StepWork<S>&, const Force<S>*, S*, S*, const S*, const StepJacobian<S>&);
  Index (*jvp)(const SimSetup<S>&, StepWork<S>&, const Force<S>*, S*, S*, const S*, S*, S*, const S*);
  Index (*vjp)(const SimSetup<S>&, StepWork<S>&, const Force<S>*, const S*, const S*, const S*, S*, S*, S*);
};

// Every (integrator, joint-effect set) instantiation, indexed integrator * 16 +
// (effects & kJointEffects): gravity and external wrenches are the forward
// dynamics' business (the model's gravity, the fext pointer), contacts are refused.
// (SCANDYN_HOST_EFFECT_SETS=0: every joint effect compiled into each, host_joint_effect_set.)
template <class S, std::size_t... K>
constexpr std::array<KernelSet<S>, sizeof...(K)> make_kernels(std::index_sequence<K...>) {
  return {KernelSet<S>{&InstanceKernels<host_joint_effect_set(unsigned(K % 16)) & kJointEffects, Integrator(K / 16), S>::step,
                       &InstanceKernels<host_joint_effect_set(unsigned(K % 16)) & kJointEffects, Integrator(K / 16), S>::jacobian,
                       &InstanceKernels<host_joint_effect_set(unsigned(K % 16)) & kJointEffects, Integrator(K / 16), S>::jvp,
                       &InstanceKernels<host_joint_effect_set(unsigned(K % 16)) & kJointEffects, Integrator(K / 16), S>::vjp}...};
}
template <class S, std::size_t... K>
constexpr std::array<KernelSet<S>, sizeof...(K)> make_kernels_at(std::index_sequence<K...>) {
  return {KernelSet<S>{&InstanceKernelsAt<host_joint_effect_set(unsigned(K % 16)) & kJointEffects, Integrator(K / 16), S>::step,
                       &InstanceKernelsAt<host_joint_effect_set(unsigned(K % 16)) & kJointEffects, Integrator(K / 16), S>::jacobian,
                       &InstanceKernelsAt<host_joint_effect_set(unsigned(K % 16)) & kJointEffects, Integrator(K / 16), S>::jvp,
                       &InstanceKernelsAt<host_joint_effect_set(unsigned(K % 16)) & kJointEffects, Integrator(K / 16), S>::vjp}...};
}
template <class S>
const KernelSet<S>& kernels_of(const SimSetup<S>& setup) {
  const std::size_t entry = static_cast<std::size_t>(setup.integrator) * 16 + (setup.effects & kJointEffects);
  if (setup.model.multi_dof()) {
    static const auto table_at = make_kernels_at<S>(std::make_index_sequence<kIntegrators * 16>{});
    return table_at[entry];
  }
  static const auto table = make_kernels<S>(std::make_index_sequence<kIntegrators * 16>{});
  return table[entry];
}

// Instance b's wrenches (one per body): the caller's per-step ones, the scene's
// constant ones, or null without the external effect.
template <class S>
const Force<S>* instance_wrenches(const SimSetup<S>& setup, const Force<S>* fext, Index b) {
  if (!(setup.effects & kExternal)) return nullptr;
  return fext ? fext + static_cast<std::size_t>(b) * setup.model.nbodies() : setup.wrenches.data();
}

// The status of a batch whose instance b failed at failed[b] >= 0 for reason what[b].
inline BatchStatus status_of(const std::vector<int>& failed, const std::vector<Failure>& what, Index B) {
  BatchStatus st;
  for (Index b = 0; b < B; ++b)
    if (failed[static_cast<std::size_t>(b)] >= 0)
      st.record(b, failed[static_cast<std::size_t>(b)], what[static_cast<std::size_t>(b)]);
  st.failed_dof = failed.data();
  return st;
}

template <class S>
void refuse_wrenches_without_effect(const SimSetup<S>& setup, const Force<S>* fext) {
  if (fext && !(setup.effects & kExternal))
    throw BackendError("the step derivatives: wrenches were given, but the scene declares no external effect");
}

template <class S>
class CpuStepDerivatives final : public StepDerivatives<S> {
 public:
  CpuStepDerivatives(const SimSetup<S>& setup, const BackendOptions& o)
      : setup_(setup),
        kind_(o.backend),
        threads_(cpu::instance_threads(cpu::engine_threads(o), o.max_batch)),
        max_batch_(o.max_batch),
        kernels_(kernels_of(setup_)), failed_(static_cast<std::size_t>(std::max<Index>(o.max_batch, 1)), -1) {
    for (int t = 0; t < threads_; ++t) work_.emplace_back(setup_);
  }
  std::string strategy() const override { return std::string("step-jacobian-") + to_string(setup_.integrator); }
  BackendKind backend() const override { return kind_; }
  const SimSetup<S>& setup() const override { return setup_; }

  BatchStatus compute(const FdBatchIn<S>& in, const StepDerivativesOut<S>& out) override {
    check_batch(in, FdDerivativesOut<S>{out.q_q, out.q_qd, out.q_tau, {}}, max_batch_);
    check_batch(in, FdDerivativesOut<S>{out.qd_q, out.qd_qd, out.qd_tau, {}}, max_batch_);
    for (const BatchView<S>* v : {&out.q_next, &out.qd_next})
      if (v->data && v->batch != in.q.batch)
        throw BackendError("the step derivatives: the new state's batch size " + std::to_string(v->batch) +
                           " is not q's " + std::to_string(in.q.batch));
    refuse_wrenches_without_effect(setup_, in.fext);
    const Index n = setup_.model.nv(), nq = setup_.model.nq(), B = in.q.batch;
    cpu::for_instance_blocks(threads_, B, [&](int t, Index begin, Index end) {
      StepWork<S>& w = work_[static_cast<std::size_t>(t)];
      S *q = w.rows.data(), *qd = q + nq, *tau = qd + n;
      for (Index b = begin; b < end; ++b) {
        for (Index i = 0; i < nq; ++i) q[i] = in.q.at(i, b);
        for (Index i = 0; i < n; ++i) qd[i] = in.qd.at(i, b), tau[i] = in.tau.at(i, b);
        const StepJacobian<S> J{instance_matrix(out.q_q, b, n),  instance_matrix(out.q_qd, b, n),
                                instance_matrix(out.q_tau, b, n), instance_matrix(out.qd_q, b, n),
                                instance_matrix(out.qd_qd, b, n), instance_matrix(out.qd_tau, b, n)};
        Index failed = kernels_.jacobian(setup_, w, instance_wrenches(setup_, in.fext, b), q, qd, tau, J);
        what_[static_cast<std::size_t>(b)] = Failure::ArticulatedPivot;
        if (failed < 0) {  // a state or derivative that is not finite is a failure, never a silent NaN
          const MatrixRef<S> blocks[6] = {J.q_q, J.q_qd, J.q_tau, J.qd_q, J.qd_qd, J.qd_tau};
          for (Index i = n; i < nq && failed < 0; ++i)
            if (!std::isfinite(q[i])) failed = i, what_[static_cast<std::size_t>(b)] = Failure::NonFinite;
          for (Index i = 0; i < n && failed < 0; ++i) {
            bool finite = std::isfinite(q[i]) && std::isfinite(qd[i]);
            for (int k = 0; k < 6; ++k)
              for (Index j = 0; j < n; ++j) finite = finite && std::isfinite(blocks[k](i, j));
            if (!finite) failed = i, what_[static_cast<std::size_t>(b)] = Failure::NonFinite;
          }
        }
        failed_[static_cast<std::size_t>(b)] = static_cast<int>(failed);
        for (Index i = 0; i < nq && failed < 0; ++i)
          if (out.q_next.data) out.q_next.at(i, b) = q[i];
        for (Index i = 0; i < n && failed < 0; ++i)
          if (out.qd_next.data) out.qd_next.at(i, b) = qd[i];
      }
    });
    return status_of(failed_, what_, B);
  }

 private:
  SimSetup<S> setup_;
  BackendKind kind_;
  int threads_;
  Index max_batch_;
  KernelSet<S> kernels_;
  std::vector<StepWork<S>> work_;  // (threads)
  std::vector<int> failed_;        // (max_batch) -1 or the failed DoF
  std::vector<Failure> what_ = std::vector<Failure>(failed_.size());  // (max_batch) why
};

}  // namespace

template <class S>
std::unique_ptr<StepDerivatives<S>> make_step_derivatives(const SimSetup<S>& setup, const BackendOptions& options) {
  require_differentiable_step(setup, "the step derivatives", options.backend);
  if (options.backend == BackendKind::Cuda) {
#if SCANDYN_HAS_CUDA
    return cuda::make_cuda_step_derivatives(setup, options);
#else
    throw BackendError("backend 'cuda' is not available in this build");
#endif
  }
  return std::make_unique<CpuStepDerivatives<S>>(setup, options);
}

// ---- rollouts ------------------------------------------------------------------------

template <class S>
struct RolloutDerivatives<S>::Impl {
  Impl(const SimSetup<S>& s, const BackendOptions& o, Index interval)
      : setup(s), threads(o.backend == BackendKind::Cuda ? 0 : cpu::engine_threads(o)), interval(interval),
        kernels(kernels_of(setup)) {
    if (o.backend == BackendKind::Cuda) {
#if SCANDYN_HAS_CUDA
      cuda = std::make_unique<cuda::CudaRolloutDerivatives<S>>(setup, o, interval);
#else
      throw BackendError("backend 'cuda' is not available in this build");
#endif
    }
    for (int t = 0; t < threads; ++t) work.emplace_back(setup);
  }
  SimSetup<S> setup;
  int threads;     // CPU threads over instances (0 on cuda)
  Index interval;  // 0: sqrt(T)
  KernelSet<S> kernels;
  std::vector<StepWork<S>> work;  // (threads)
#if SCANDYN_HAS_CUDA
  std::unique_ptr<cuda::CudaRolloutDerivatives<S>> cuda;  // backend cuda: every call runs there
#else
  std::unique_ptr<RolloutDerivatives<S>> cuda;  // (never set: no cuda in this build)
#endif
  std::vector<int> failed;        // (B)
  std::vector<Failure> what;      // (B)

  // body(w, b) per instance returns a failure code of the rollout instance functions
  // (-1, a failed pivot's DoF, or -2 - i for a result not finite at DoF i); the
  // status of the failures
  template <class F>
  BatchStatus instances(Index B, F&& body) {
    failed.assign(static_cast<std::size_t>(std::max<Index>(B, 1)), -1);
    what.assign(failed.size(), Failure::ArticulatedPivot);
    cpu::for_instance_blocks(threads, B, [&](int t, Index begin, Index end) {
      for (Index b = begin; b < end; ++b) {
        const Index code = body(work[static_cast<std::size_t>(t)], b);
        if (rollout_failure_nonfinite(code)) what[static_cast<std::size_t>(b)] = Failure::NonFinite;
        failed[static_cast<std::size_t>(b)] = static_cast<int>(rollout_failure_dof(code));
      }
    });
    return status_of(failed, what, B);
  }
};


template <class S>
RolloutDerivatives<S>::RolloutDerivatives(const SimSetup<S>& setup, const BackendOptions& options,
                                          Index checkpoint_interval) {
  require_differentiable_step(setup, "the rollout derivatives", options.backend);
  if (checkpoint_interval < 0)
    throw BackendError("the rollout derivatives: checkpoint interval " + std::to_string(checkpoint_interval) +
                       " is negative");
  impl_ = std::make_unique<Impl>(setup, options, checkpoint_interval);
}

template <class S>
RolloutDerivatives<S>::~RolloutDerivatives() = default;

template <class S>
const SimSetup<S>& RolloutDerivatives<S>::setup() const {
  return impl_->setup;
}

template <class S>
Index RolloutDerivatives<S>::checkpoint_interval(Index T) const {
  return rollout_checkpoint_interval(impl_->interval, T);
}

template <class S>
BatchStatus RolloutDerivatives<S>::rollout(const BatchView<const S>& q0, const BatchView<const S>& qd0,
                                           const StepSequence<const S>& tau, const StepSequence<S>& q,
                                           const StepSequence<S>& qd) {
  const Index B = q0.batch, T = tau.steps, n = impl_->setup.model.nv(), nq = impl_->setup.model.nq();
  require_rollout_state("qd0", qd0, B);
  require_rollout_sequence("tau", tau, T, B);
  require_rollout_sequence("q", q, T, B);
  require_rollout_sequence("qd", qd, T, B);
  if (impl_->cuda) return impl_->cuda->rollout(q0, qd0, tau, q, qd);
  const SimSetup<S>& setup = impl_->setup;
  return impl_->instances(B, [&](StepWork<S>& w, Index b) -> Index {
    const Force<S>* const fext = instance_wrenches<S>(setup, nullptr, b);
    return rollout_instance_at(nq, n, b, q0, qd0, tau, q, qd, w.rows.data(), [&](S* x, S* xd, const S* u) -> Index {
      return impl_->kernels.step(setup, w, fext, x, xd, u);
    });
  });
}

template <class S>
BatchStatus RolloutDerivatives<S>::jvp(const BatchView<const S>& q0, const BatchView<const S>& qd0,
                                       const StepSequence<const S>& tau, const BatchView<const S>& dq0,
                                       const BatchView<const S>& dqd0, const StepSequence<const S>& dtau,
                                       const StepSequence<S>& dq, const StepSequence<S>& dqd) {
  const Index B = q0.batch, T = tau.steps, n = impl_->setup.model.nv(), nq = impl_->setup.model.nq();
  require_rollout_state("qd0", qd0, B);
  require_rollout_state("dq0", dq0, B);
  require_rollout_state("dqd0", dqd0, B);
  require_rollout_sequence("tau", tau, T, B);
  require_rollout_sequence("dtau", dtau, T, B);
  require_rollout_sequence("dq", dq, T, B);
  require_rollout_sequence("dqd", dqd, T, B);
  if (impl_->cuda) return impl_->cuda->jvp(q0, qd0, tau, dq0, dqd0, dtau, dq, dqd);
  const SimSetup<S>& setup = impl_->setup;
  return impl_->instances(B, [&](StepWork<S>& w, Index b) -> Index {
    const Force<S>* const fext = instance_wrenches<S>(setup, nullptr, b);
    return rollout_jvp_instance_at(nq, n, b, q0, qd0, tau, dq0, dqd0, dtau, dq, dqd, w.rows.data(),
                                [&](S* x, S* xd, const S* u, S* dx, S* dxd, const S* du) -> Index {
                                  return impl_->kernels.jvp(setup, w, fext, x, xd, u, dx, dxd, du);
                                });
  });
}

template <class S>
BatchStatus RolloutDerivatives<S>::vjp(const BatchView<const S>& q0, const BatchView<const S>& qd0,
                                       const StepSequence<const S>& tau, const StepSequence<const S>& gq,
                                       const StepSequence<const S>& gqd, const BatchView<S>& gq0,
                                       const BatchView<S>& gqd0, const StepSequence<S>& gtau) {
  const Index B = q0.batch, T = tau.steps, n = impl_->setup.model.nv(), nq = impl_->setup.model.nq();
  require_rollout_state("qd0", qd0, B);
  require_rollout_state("gq0", gq0, B);
  require_rollout_state("gqd0", gqd0, B);
  require_rollout_sequence("tau", tau, T, B);
  require_rollout_sequence("gq", gq, T, B);
  require_rollout_sequence("gqd", gqd, T, B);
  require_rollout_sequence("gtau", gtau, T, B);
  if (impl_->cuda) return impl_->cuda->vjp(q0, qd0, tau, gq, gqd, gq0, gqd0, gtau);
  const SimSetup<S>& setup = impl_->setup;
  const Index K = checkpoint_interval(T);
  const std::size_t state = 2 * static_cast<std::size_t>(nq);  // rows of nq entries (qd's: the first n)
  for (StepWork<S>& w : impl_->work) w.store.resize(static_cast<std::size_t>(rollout_store_slots(T, K)) * state);
  return impl_->instances(B, [&](StepWork<S>& w, Index b) -> Index {
    const Force<S>* const fext = instance_wrenches<S>(setup, nullptr, b);
    return rollout_vjp_instance_at(
        nq, n, b, K, q0, qd0, tau, gq, gqd, gq0, gqd0, gtau, w.rows.data(), StateStore<S>{w.store.data(), nq, 1},
        [&](S* x, S* xd, const S* u) -> Index { return impl_->kernels.step(setup, w, fext, x, xd, u); },
        [&](const S* x, const S* xd, const S* u, S* lq, S* lqd, S* gu) -> Index {
          return impl_->kernels.vjp(setup, w, fext, x, xd, u, lq, lqd, gu);
        });
  });
}

#define SCANDYN_INSTANTIATE(S)                                                                                 \
  template std::unique_ptr<StepDerivatives<S>> make_step_derivatives(const SimSetup<S>&, const BackendOptions&); \
  template class RolloutDerivatives<S>;
SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)
#undef SCANDYN_INSTANTIATE

}  // namespace sim
}  // namespace scandyn
