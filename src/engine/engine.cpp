// src/engine/engine.cpp: the engine API's factories (one dispatch on the backend for
// every algorithm), its Auto choices and batch checks (the names and parsers of its
// enums and backend_unusable: names.cpp; BatchStatus: batch_status.cpp).
#include "scandyn/engine.hpp"

#include <algorithm>

#include "scandyn/algorithm/chain_fd.hpp"
#include "scandyn/algorithm/loops.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/sharded.hpp"
#include "../../cpu_fallback/cpu_engines.hpp"
#if SCANDYN_HAS_CUDA
#include "scandyn/cuda/device.hpp"
#include "scandyn/cuda/chain_fd.hpp"
#include "scandyn/cuda/chain_hybrid.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/cuda/hybrid_dynamics.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"
#include "scandyn/cuda/mass_matrix.hpp"
#include "scandyn/cuda/derivatives.hpp"
#include "scandyn/cuda/second_derivatives.hpp"
#include "scandyn/cuda/kinematics.hpp"
#include "scandyn/cuda/constrained_dynamics.hpp"
#endif

namespace scandyn {

bool fd_check_enabled(FdCheckMode mode, BackendKind backend, FdMethod method, Index nv) {
  if (mode != FdCheckMode::Auto) return mode == FdCheckMode::On;
  return backend != BackendKind::Cuda && method == FdMethod::Jsi && nv >= 200;
}

// ---- batch checks ---------------------------------------------------------------

namespace {

// Throws unless every named view has B instances (B <= max_batch) and data when B > 0.
void check_views(std::initializer_list<std::pair<const char*, std::pair<Index, const void*>>> views, Index max_batch) {
  const Index B = views.begin()->second.first;
  std::string sizes;
  bool agree = true;
  for (const auto& [name, v] : views) {
    sizes += (sizes.empty() ? "" : ", ") + std::string(name) + " " + std::to_string(v.first);
    agree = agree && v.first == B;
  }
  if (!agree) throw BackendError("batch sizes disagree: " + sizes);
  if (B < 0) throw BackendError("negative batch size " + std::to_string(B));
  if (B > max_batch)
    throw BackendError("batch of " + std::to_string(B) + " instances exceeds the engine's max_batch " +
                       std::to_string(max_batch));
  if (B > 0)
    for (const auto& [name, v] : views)
      if (!v.second) throw BackendError("null data pointer in a batch of " + std::to_string(B) + " instances");
}

template <class V>
std::pair<Index, const void*> info(const V& v) {
  return {v.batch, v.data};
}

}  // namespace

template <class S>
void check_batch(const IdBatchIn<S>& in, const BatchView<S>& tau, Index max_batch) {
  check_views({{"q", info(in.q)}, {"qd", info(in.qd)}, {"qdd", info(in.qdd)}, {"tau", info(tau)}}, max_batch);
}
template <class S>
void check_batch(const FdBatchIn<S>& in, const BatchView<S>& qdd, Index max_batch) {
  check_views({{"q", info(in.q)}, {"qd", info(in.qd)}, {"tau", info(in.tau)}, {"qdd", info(qdd)}}, max_batch);
}
template <class S>
void check_batch(const BiasBatchIn<S>& in, const BatchView<S>& h, Index max_batch) {
  check_views({{"q", info(in.q)}, {"qd", info(in.qd)}, {"h", info(h)}}, max_batch);
}
template <class S>
void check_batch(const BatchView<const S>& q, const BatchView<S>& M, Index max_batch) {
  check_views({{"q", info(q)}, {"M", info(M)}}, max_batch);
}
template <class S>
void check_batch(const HybridBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& tau, Index max_batch) {
  check_views({{"q", info(in.q)}, {"qd", info(in.qd)}, {"qdd", info(in.qdd)}, {"tau", info(in.tau)},
               {"qdd out", info(qdd)}, {"tau out", info(tau)}},
              max_batch);
}

// ---- Auto choices ---------------------------------------------------------------

IdStrategy choose_id_strategy(BackendKind backend, Index nv, Index batch, int threads) {
  // CUDA: a GPU thread per instance (the recursion) up to kMaxThreadDofs DoF, the
  // link scans beyond
  if (backend == BackendKind::Cuda) return nv <= cuda::kMaxThreadDofs ? IdStrategy::Recursion : IdStrategy::ScanLocal;
  // Instances are independent: splitting them costs nothing. Scans over links pay
  // 1.5-3x the arithmetic of the recursion, so they only win when there are fewer
  // instances than threads and enough links to give every thread long runs: from
  // about 10^4 links on 16 threads for ropes, curtains and random trees alike
  // (docs/accuracy-id-scan.md).
  if (threads <= 1 || batch >= threads || nv < 4096) return IdStrategy::Recursion;
  return IdStrategy::ScanLocal;
}

template <class S>
bool is_chain_from_base(const ModelTpl<S>& model) {
  // the parallel chain forward dynamics takes 1-DoF joints and a floating base (a free rope)
  return model.nv() > 0 && first_branching_body(model) < 0 && first_unsupported_chain_joint(model) < 0;
}

// Auto on cuda beyond the thread kernels (nv > cuda::kMaxThreadDofs): up to how many
// DoFs the ABA of the general path (strategy "aba_general": one thread per instance,
// O(nv) each, its scratch interleaved across threads) is chosen instead of the
// parallel chain forward dynamics (unbranched chains from the base, a free rope
// included) or jsi_dense (CRBA + cuSOLVER's dense batched Cholesky: trees).
// Measured on the H200 (float, 10^4 instances, device-resident, 2026-11-29;
// docs/benchmarks.md, "The general path"): rope:100 aba_general 0.77 ms against
// parallel 2.75 ms and jsi_dense 5.4 ms; tree:1000:1 aba_general 47 ms against
// jsi_dense 393 ms (whose B nv^2 matrices also outgrow memory first). Chains: up to
// 128 DoF (the parallel forward dynamics' O(log n) depth wins on long chains);
// trees: always. Auto does not see the batch size: the points hold for the batches
// measured.
constexpr Index kCudaGeneralAbaMaxChainDofs = 128;
constexpr Index kCudaGeneralAbaMaxTreeDofs = std::numeric_limits<Index>::max();

template <class S>
FdMethod choose_fd_method(BackendKind backend, const ModelTpl<S>& model, Index batch, int threads) {
  // multi-DoF joints: aba, or a free rope's parallel chain forward dynamics
  if (model.multi_dof() && !is_chain_from_base(model)) return FdMethod::Aba;
  switch (backend) {
    case BackendKind::Serial: return FdMethod::Aba;
    case BackendKind::OpenMP:
      // the chain scans pay once enough threads share each instance
      // (kChainFdThreadsPerInstance, measured); else the ABA over the instances
      return is_chain_from_base(model) && model.nv() >= 4096 &&
                     static_cast<long long>(threads) >=
                         static_cast<long long>(kChainFdThreadsPerInstance) * std::max<Index>(batch, 1)
                 ? FdMethod::Parallel
                 : FdMethod::Aba;
    case BackendKind::Cuda:
      // measured on the H100 (bench_cuda_fd, 10^7 instances, ms, float / double):
      // iiwa ABA 3.3 / 7.5 against JSI 4.5 / 8.9, hyq 6.0 / 13.8 against 7.5 / 14.8,
      // atlas 22.8 / 52.9 against 47.8 / 94.8
      if (model.nv() <= cuda::kMaxThreadDofs) return FdMethod::Aba;
      if (is_chain_from_base(model))
        return model.nv() <= kCudaGeneralAbaMaxChainDofs ? FdMethod::Aba : FdMethod::Parallel;
      return model.nv() <= kCudaGeneralAbaMaxTreeDofs ? FdMethod::Aba : FdMethod::Jsi;
  }
  return FdMethod::Aba;
}

template <class S>
FdMethod choose_hybrid_method(BackendKind backend, const ModelTpl<S>& model, FdMethod requested, Index batch,
                              int threads) {
  if (requested != FdMethod::Auto && requested != FdMethod::Aba && requested != FdMethod::Parallel)
    throw BackendError(std::string("hybrid dynamics: method '") + to_string(requested) +
                       "' is not offered (auto, aba or parallel)");
  if (backend != BackendKind::Cuda) {
    if (requested != FdMethod::Auto) return requested;
    return choose_fd_method(backend, model, batch, threads) == FdMethod::Parallel ? FdMethod::Parallel
                                                                                    : FdMethod::Aba;
  }
  // cuda: the thread-per-instance kernels up to kMaxThreadDofs DoF, the chain scans
  // (kernels/chain_hybrid.cu) for longer unbranched chains (no general-path hybrid)
  const Index nv = model.nv();
  if (requested == FdMethod::Parallel) return FdMethod::Parallel;
  if (nv <= cuda::kMaxThreadDofs) return FdMethod::Aba;
  const std::string dofs = "model '" + model.name + "' has " + std::to_string(nv) + " DoF";
  if (requested == FdMethod::Aba)
    throw BackendError("backend 'cuda': hybrid dynamics by aba runs one thread per instance, for models of up to " +
                       std::to_string(cuda::kMaxThreadDofs) + " DoF; " + dofs +
                       " (method auto or parallel takes unbranched chains hanging from the base; or use the serial "
                       "or openmp backend)");
  const Index k = first_branching_body(model);
  if (k >= 0)
    throw BackendError("backend 'cuda': hybrid dynamics runs one thread per instance for models of up to " +
                       std::to_string(cuda::kMaxThreadDofs) +
                       " DoF and the parallel chain scans for unbranched chains hanging from the base; " + dofs +
                       " and is not a chain: body " + std::to_string(k) + " (joint '" + model.joint_names[k] +
                       "') has parent " + std::to_string(model.parent(k)) + " (use the serial or openmp backend)");
  return FdMethod::Parallel;
}

// ---- factories ------------------------------------------------------------------

namespace {

// Throws BackendError when the backend is not in this build (cuda's device check is
// the engines' own, which name the device).
void require_built(BackendKind backend) {
  if (backend == BackendKind::Cuda && !SCANDYN_HAS_CUDA)
    throw BackendError(backend_unusable(backend));
  if (backend == BackendKind::OpenMP) {
    const std::string why = backend_unusable(backend);
    if (!why.empty()) throw BackendError(why);
  }
}
// The same, and a device list only on cuda.
void require_built(const BackendOptions& o) {
  require_built(o.backend);
  if (!o.devices.empty() && o.backend != BackendKind::Cuda)
    throw BackendError("devices " + devices_string(o.devices) + ": only the cuda backend runs on devices (backend '" +
                       to_string(o.backend) + "')");
}

// True when o asks the cuda backend for a device other than the current one, or several.
[[maybe_unused]] bool sharded(const BackendOptions& o) { return o.backend == BackendKind::Cuda && spans_devices(o.devices); }

// One engine per entry of o.devices, each made by make(options of one shard: no devices,
// max_batch its share) with that device current; BackendError "device D: ..." for a
// device that cannot be made current or an engine that cannot be made there.
template <class E, class Make>
std::vector<std::unique_ptr<E>> per_device(const BackendOptions& o, Make&& make) {
  BackendOptions one = o;
  one.devices.clear();
  one.max_batch = shard_capacity(o.max_batch, static_cast<int>(o.devices.size()));
  std::vector<std::unique_ptr<E>> engines;
  for (const int d : o.devices) {
    const std::string label = "device " + std::to_string(d) + ": ";
    cuda::DeviceScope scope(d);
    if (!scope.ok()) throw BackendError(label + scope.error());
    try {
      engines.push_back(make(one));
    } catch (const BackendError& e) {
      throw BackendError(label + e.what());
    }
  }
  return engines;
}

// Throws BackendError for a model with multi-DoF joints (a floating base, spherical
// joints) on what does not take them: the hybrid chain forward dynamics. what:
// "inverse dynamics", ... (The link scans take every joint type, the parallel chain
// forward dynamics a free rope (ChainBodies::from names what it refuses), the cuda
// thread kernels a floating base with 1-DoF joints past it (ThreadModel says what it
// refuses).)
template <class S>
void require_joint_support(const ModelTpl<S>& model, const BackendOptions& o, const char* what) {
  if (!model.multi_dof()) return;
  if (o.fd_method == FdMethod::Hybrid)
    throw BackendError("model '" + model.name + "' has multi-DoF joints (a floating base or spherical joints): " +
                       std::string(what) + " by the method " + to_string(o.fd_method) +
                       " does not take them; use aba, jsi or parallel (a free rope)");
}


}  // namespace

template <class S>
void require_one_dof_joints(const ModelTpl<S>& model, const char* what) {
  if (!model.multi_dof()) return;
  throw BackendError(std::string(what) + ": model '" + model.name + "' has the multi-DoF joint '" +
                     first_multi_dof_joint(model) + "' (" +
                     (model.floating_base() ? "the floating base" : "a spherical joint") +
                     "), and this takes revolute and prismatic joints only");
}

template void require_one_dof_joints(const ModelTpl<float>&, const char*);
template void require_one_dof_joints(const ModelTpl<double>&, const char*);

// The first-order derivatives take multi-DoF joints (a floating base, spherical joints)
// on every backend: serial and OpenMP by rnea_derivatives_general_instance /
// fd_derivatives_general_instance, cuda by its general derivative kernels (the same
// functions, one thread per instance, up to kMaxThreadDofs DoF;
// scandyn/cuda/derivatives.hpp).

template <class S>
std::unique_ptr<InverseDynamics<S>> make_inverse_dynamics(const ModelTpl<S>& model, const BackendOptions& o) {
  require_built(o);
  require_joint_support(model, o, "inverse dynamics");
#if SCANDYN_HAS_CUDA
  if (o.backend == BackendKind::Cuda) {
    if (sharded(o))
      return std::make_unique<ShardedInverseDynamics<S>>(
          per_device<InverseDynamics<S>>(o, [&](const BackendOptions& one) { return make_inverse_dynamics(model, one); }), o.devices, true,
          model.nbodies());
    return std::make_unique<cuda::CudaInverseDynamics<S>>(model, o);
  }
#endif
  return cpu::make_inverse_dynamics(model, o);
}

template <class S>
std::unique_ptr<BiasForces<S>> make_bias_forces(const ModelTpl<S>& model, const BackendOptions& o) {
  require_built(o);
  require_joint_support(model, o, "bias forces");
#if SCANDYN_HAS_CUDA
  if (o.backend == BackendKind::Cuda) {
    if (sharded(o))
      return std::make_unique<ShardedBiasForces<S>>(
          per_device<BiasForces<S>>(o, [&](const BackendOptions& one) { return make_bias_forces(model, one); }), o.devices, true,
          model.nbodies());
    return std::make_unique<cuda::CudaBiasForces<S>>(model, o);
  }
#endif
  return cpu::make_bias_forces(model, o);
}

template <class S>
std::unique_ptr<MassMatrix<S>> make_mass_matrix(const ModelTpl<S>& model, const BackendOptions& o) {
  require_built(o);
  require_joint_support(model, o, "the mass matrix");
#if SCANDYN_HAS_CUDA
  if (o.backend == BackendKind::Cuda) {
    if (sharded(o))
      return std::make_unique<ShardedMassMatrix<S>>(
          per_device<MassMatrix<S>>(o, [&](const BackendOptions& one) { return make_mass_matrix(model, one); }), o.devices, true,
          model.nbodies());
    return std::make_unique<cuda::CudaMassMatrix<S>>(model, o);
  }
#endif
  return cpu::make_mass_matrix(model, o);
}

template <class S>
std::unique_ptr<ForwardDynamics<S>> make_forward_dynamics(const ModelTpl<S>& model, const BackendOptions& o) {
  require_built(o);
  require_joint_support(model, o, "forward dynamics");
#if SCANDYN_HAS_CUDA
  if (o.backend == BackendKind::Cuda) {
    if (sharded(o))
      return std::make_unique<ShardedForwardDynamics<S>>(
          per_device<ForwardDynamics<S>>(o, [&](const BackendOptions& one) { return make_forward_dynamics(model, one); }),
          o.devices, true, model.nbodies(), o.max_batch);
    return std::make_unique<cuda::CudaForwardDynamics<S>>(model, o);
  }
#endif
  return cpu::make_forward_dynamics(model, o);
}

// ---- derivatives ------------------------------------------------------------------

template <class S>
void check_batch(const IdBatchIn<S>& in, const IdDerivativesOut<S>& out, Index max_batch) {
  check_views({{"q", info(in.q)}, {"qd", info(in.qd)}, {"qdd", info(in.qdd)}, {"dtau_dq", info(out.dtau_dq)},
               {"dtau_dqd", info(out.dtau_dqd)}, {"M", info(out.M)}},
              max_batch);
}
template <class S>
void check_batch(const FdBatchIn<S>& in, const FdDerivativesOut<S>& out, Index max_batch) {
  check_views({{"q", info(in.q)}, {"qd", info(in.qd)}, {"tau", info(in.tau)}, {"dqdd_dq", info(out.dqdd_dq)},
               {"dqdd_dqd", info(out.dqdd_dqd)}, {"dqdd_dtau", info(out.dqdd_dtau)}},
              max_batch);
  if (out.qdd.data && out.qdd.batch != in.q.batch)
    throw BackendError("batch sizes disagree: q " + std::to_string(in.q.batch) + ", qdd " +
                       std::to_string(out.qdd.batch));
}

template <class S>
std::unique_ptr<IdDerivatives<S>> make_id_derivatives(const ModelTpl<S>& model, const BackendOptions& o) {
  require_built(o);
  if (o.strategy != IdStrategy::Auto)
    throw BackendError(std::string("strategy '") + to_string(o.strategy) +
                       "' is not available for the inverse-dynamics derivatives (use auto)");
#if SCANDYN_HAS_CUDA
  if (o.backend == BackendKind::Cuda) {
    if (sharded(o))
      return std::make_unique<ShardedIdDerivatives<S>>(
          per_device<IdDerivatives<S>>(o, [&](const BackendOptions& one) { return make_id_derivatives(model, one); }),
          o.devices, true, model.nbodies());
    return cuda::make_cuda_id_derivatives(model, o);
  }
#endif
  return cpu::make_id_derivatives(model, o);
}

template <class S>
std::unique_ptr<FdDerivatives<S>> make_fd_derivatives(const ModelTpl<S>& model, const BackendOptions& o) {
  require_built(o);
  if (o.fd_method != FdMethod::Auto && o.fd_method != FdMethod::Aba)
    throw BackendError(std::string("forward-dynamics method '") + to_string(o.fd_method) +
                       "' is not available for the forward-dynamics derivatives (use auto or aba)");
#if SCANDYN_HAS_CUDA
  if (o.backend == BackendKind::Cuda) {
    if (sharded(o))
      return std::make_unique<ShardedFdDerivatives<S>>(
          per_device<FdDerivatives<S>>(o, [&](const BackendOptions& one) { return make_fd_derivatives(model, one); }),
          o.devices, true, model.nbodies(), o.max_batch);
    return cuda::make_cuda_fd_derivatives(model, o);
  }
#endif
  return cpu::make_fd_derivatives(model, o);
}

template <class S>
std::unique_ptr<FdDirectionalDerivatives<S>> make_fd_directional_derivatives(const ModelTpl<S>& model,
                                                                             const BackendOptions& o) {
  require_built(o);
  if (o.fd_method != FdMethod::Auto && o.fd_method != FdMethod::Aba && o.fd_method != FdMethod::Parallel)
    throw BackendError(std::string("forward-dynamics method '") + to_string(o.fd_method) +
                       "' is not available for the directional derivatives (use auto, aba or parallel)");
  // multi-DoF joints: aba_jvp / aba_vjp over the general ABA (serial, openmp); the
  // chain scans and the cuda engine take 1-DoF joints only
  if (model.multi_dof() && (o.backend == BackendKind::Cuda || o.fd_method == FdMethod::Parallel))
    throw BackendError(std::string("the directional derivatives of forward dynamics") +
                       (o.backend == BackendKind::Cuda ? " on backend 'cuda'" : " by the method 'parallel'") +
                       ": model '" + model.name + "' has the multi-DoF joint '" + first_multi_dof_joint(model) +
                       "' (" + (model.floating_base() ? "the floating base" : "a spherical joint") +
                       "), and the chain scans take revolute and prismatic joints only; use backend serial or "
                       "openmp with the method aba (or auto)");
#if SCANDYN_HAS_CUDA
  if (o.backend == BackendKind::Cuda) {
    if (o.fd_method == FdMethod::Aba)
      throw BackendError("forward-dynamics method 'aba' of the directional derivatives is offered on serial and "
                         "openmp; cuda runs the chain scans (parallel)");
    if (sharded(o)) throw BackendError("the directional derivatives of forward dynamics run on one device");
    return cuda::make_cuda_fd_directional_derivatives(model, o);
  }
#endif
  const bool chain = first_branching_body(model) < 0 && !model.multi_dof();
  if (o.fd_method == FdMethod::Parallel && !chain)
    throw BackendError("forward-dynamics method 'parallel' of the directional derivatives needs unbranched chains "
                       "hanging from a fixed base (" +
                       (model.floating_base() ? std::string("body 0 is a floating base")
                                              : "body " + std::to_string(first_branching_body(model)) + " branches off") +
                       "; use aba)");
  // auto: the scans where forward dynamics takes them (openmp, long chains, enough
  // threads per instance: kChainFdThreadsPerInstance), else aba_jvp / aba_vjp
  const bool scans = o.fd_method == FdMethod::Parallel ||
                     (o.fd_method == FdMethod::Auto && chain &&
                      choose_fd_method(o.backend, model, o.max_batch, backend_threads(o.backend, o.threads)) ==
                          FdMethod::Parallel);
  return cpu::make_fd_directional_derivatives(model, o, scans);
}

template <class S>
void check_batch(const IdBatchIn<S>& in, const IdSecondDerivativesOut<S>& out, Index max_batch) {
  check_views({{"q", info(in.q)}, {"qd", info(in.qd)}, {"qdd", info(in.qdd)}, {"d2tau_dq2", info(out.d2tau_dq2)},
               {"d2tau_dqd2", info(out.d2tau_dqd2)}, {"d2tau_dqdqd", info(out.d2tau_dqdqd)}},
              max_batch);
  if (out.dM_dq.data && out.dM_dq.batch != in.q.batch)
    throw BackendError("batch sizes disagree: q " + std::to_string(in.q.batch) + ", dM_dq " +
                       std::to_string(out.dM_dq.batch));
}

template <class S>
std::unique_ptr<IdSecondDerivatives<S>> make_id_second_derivatives(const ModelTpl<S>& model, const BackendOptions& o) {
  require_built(o);
  require_one_dof_joints(model, "the second-order inverse-dynamics derivatives");
  if (o.strategy != IdStrategy::Auto)
    throw BackendError(std::string("strategy '") + to_string(o.strategy) +
                       "' is not available for the second-order inverse-dynamics derivatives (use auto)");
#if SCANDYN_HAS_CUDA
  if (o.backend == BackendKind::Cuda) {
    if (sharded(o))
      return std::make_unique<ShardedIdSecondDerivatives<S>>(
          per_device<IdSecondDerivatives<S>>(
              o, [&](const BackendOptions& one) { return make_id_second_derivatives(model, one); }),
          o.devices, true, model.nbodies());
    return cuda::make_cuda_id_second_derivatives(model, o);
  }
#endif
  return cpu::make_id_second_derivatives(model, o);
}

#define SCANDYN_INSTANTIATE_DERIVATIVES(S)                                                                     \
  template void check_batch(const IdBatchIn<S>&, const IdDerivativesOut<S>&, Index);                          \
  template void check_batch(const IdBatchIn<S>&, const IdSecondDerivativesOut<S>&, Index);                    \
  template std::unique_ptr<IdSecondDerivatives<S>> make_id_second_derivatives(const ModelTpl<S>&,              \
                                                                              const BackendOptions&);          \
  template void check_batch(const FdBatchIn<S>&, const FdDerivativesOut<S>&, Index);                          \
  template std::unique_ptr<IdDerivatives<S>> make_id_derivatives(const ModelTpl<S>&, const BackendOptions&);   \
  template std::unique_ptr<FdDerivatives<S>> make_fd_derivatives(const ModelTpl<S>&, const BackendOptions&);     \
  template std::unique_ptr<FdDirectionalDerivatives<S>> make_fd_directional_derivatives(const ModelTpl<S>&,    \
                                                                                        const BackendOptions&);
SCANDYN_INSTANTIATE_DERIVATIVES(float)
SCANDYN_INSTANTIATE_DERIVATIVES(double)
#undef SCANDYN_INSTANTIATE_DERIVATIVES
// ---- kinematics -------------------------------------------------------------------

template <class S>
void check_kinematics_options(const ModelTpl<S>& model, const KinematicsOptions& k) {
  const Index n = static_cast<Index>(model.frames.size());
  for (std::size_t i = 0; i < k.frames.size(); ++i)
    if (k.frames[i] < 0 || k.frames[i] >= n)
      throw BackendError("kinematics: frame " + std::to_string(i) + " of the selection has index " +
                         std::to_string(k.frames[i]) + ", outside the model's " + std::to_string(n) + " frames");
}

template <class S>
void check_batch(const BatchView<const S>& q, const BatchView<S>& poses, const BatchView<S>& J, Index max_batch) {
  if (poses.data && J.data) check_views({{"q", info(q)}, {"poses", info(poses)}, {"J", info(J)}}, max_batch);
  else if (poses.data) check_views({{"q", info(q)}, {"poses", info(poses)}}, max_batch);
  else if (J.data) check_views({{"q", info(q)}, {"J", info(J)}}, max_batch);
  else check_views({{"q", info(q)}}, max_batch);
}

template <class S>
std::unique_ptr<Kinematics<S>> make_kinematics(const ModelTpl<S>& model, const BackendOptions& o,
                                               const KinematicsOptions& k) {
  require_built(o);
  check_kinematics_options(model, k);
#if SCANDYN_HAS_CUDA
  if (o.backend == BackendKind::Cuda) {
    if (sharded(o))
      return std::make_unique<ShardedKinematics<S>>(
          per_device<Kinematics<S>>(o, [&](const BackendOptions& one) { return make_kinematics(model, one, k); }),
          o.devices, true, model.nbodies());
    return std::make_unique<cuda::CudaKinematics<S>>(model, o, k);
  }
#endif
  return cpu::make_kinematics(model, o, k);
}

#define SCANDYN_INSTANTIATE_KINEMATICS(S)                                                                      \
  template void check_kinematics_options(const ModelTpl<S>&, const KinematicsOptions&);                       \
  template void check_batch(const BatchView<const S>&, const BatchView<S>&, const BatchView<S>&, Index);       \
  template std::unique_ptr<Kinematics<S>> make_kinematics(const ModelTpl<S>&, const BackendOptions&,           \
                                                          const KinematicsOptions&);
SCANDYN_INSTANTIATE_KINEMATICS(float)
SCANDYN_INSTANTIATE_KINEMATICS(double)
#undef SCANDYN_INSTANTIATE_KINEMATICS

template <class S>
std::unique_ptr<HybridDynamics<S>> make_hybrid_dynamics(const ModelTpl<S>& model,
                                                        const std::vector<unsigned char>& prescribed,
                                                        const BackendOptions& o) {
  require_built(o);
  require_one_dof_joints(model, "hybrid dynamics");
  if (prescribed.size() != static_cast<std::size_t>(model.nv()))
    throw BackendError("hybrid dynamics: the prescribed mask has " + std::to_string(prescribed.size()) +
                       " entries for a model of " + std::to_string(model.nv()) + " DoF");
#if SCANDYN_HAS_CUDA
  if (o.backend == BackendKind::Cuda) {
    if (sharded(o))
      return std::make_unique<ShardedHybridDynamics<S>>(
          per_device<HybridDynamics<S>>(
              o, [&](const BackendOptions& one) { return make_hybrid_dynamics(model, prescribed, one); }),
          o.devices, true, model.nbodies(), o.max_batch);
    if (choose_hybrid_method(o.backend, model, o.fd_method, o.max_batch, 1) == FdMethod::Parallel)
      return std::make_unique<cuda::CudaChainHybridDynamics<S>>(model, prescribed, o);
    return std::make_unique<cuda::CudaHybridDynamics<S>>(model, prescribed, o);
  }
#endif
  return cpu::make_hybrid_dynamics(model, prescribed, o);
}

#define SCANDYN_INSTANTIATE(S)                                                                                  \
  template void check_batch(const HybridBatchIn<S>&, const BatchView<S>&, const BatchView<S>&, Index);         \
  template std::unique_ptr<HybridDynamics<S>> make_hybrid_dynamics(const ModelTpl<S>&,                          \
                                                                   const std::vector<unsigned char>&,           \
                                                                   const BackendOptions&);                      \
  template void check_batch(const IdBatchIn<S>&, const BatchView<S>&, Index);                                  \
  template void check_batch(const FdBatchIn<S>&, const BatchView<S>&, Index);                                  \
  template void check_batch(const BiasBatchIn<S>&, const BatchView<S>&, Index);                                \
  template void check_batch(const BatchView<const S>&, const BatchView<S>&, Index);                            \
  template bool is_chain_from_base(const ModelTpl<S>&);                                                         \
  template FdMethod choose_fd_method(BackendKind, const ModelTpl<S>&, Index, int);                              \
  template FdMethod choose_hybrid_method(BackendKind, const ModelTpl<S>&, FdMethod, Index, int);                \
  template std::unique_ptr<InverseDynamics<S>> make_inverse_dynamics(const ModelTpl<S>&, const BackendOptions&); \
  template std::unique_ptr<BiasForces<S>> make_bias_forces(const ModelTpl<S>&, const BackendOptions&);           \
  template std::unique_ptr<MassMatrix<S>> make_mass_matrix(const ModelTpl<S>&, const BackendOptions&);           \
  template std::unique_ptr<ForwardDynamics<S>> make_forward_dynamics(const ModelTpl<S>&, const BackendOptions&);
SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)
#undef SCANDYN_INSTANTIATE

// ---- closed loops ------------------------------------------------------------------

template <class S>
void check_batch(const FdBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& lambda, Index max_batch) {
  check_views({{"q", info(in.q)}, {"qd", info(in.qd)}, {"tau", info(in.tau)}, {"qdd", info(qdd)},
               {"lambda", info(lambda)}},
              max_batch);
}

template <class S>
std::unique_ptr<ConstrainedForwardDynamics<S>> make_constrained_forward_dynamics(const ModelTpl<S>& model,
                                                                                 const LoopSet& loops,
                                                                                 const BackendOptions& o) {
  require_built(o);
  require_one_dof_joints(model, "closed loops");
  for (const LoopClosure& l : loops.loops)
    for (Index body : {l.body_a, l.body_b})
      if (body < -1 || body >= model.nv())
        throw BackendError("closed loops: a loop names body " + std::to_string(body) + " of a model of " +
                           std::to_string(model.nv()) + " bodies (the loops were made for another model)");
#if SCANDYN_HAS_CUDA
  if (o.backend == BackendKind::Cuda) {
    if (sharded(o))
      return std::make_unique<ShardedConstrainedForwardDynamics<S>>(
          per_device<ConstrainedForwardDynamics<S>>(
              o, [&](const BackendOptions& one) { return make_constrained_forward_dynamics(model, loops, one); }),
          o.devices, true, model.nbodies(), o.max_batch);
    return cuda::make_constrained_forward_dynamics(model, loops, o);
  }
#endif
  return cpu::make_constrained_forward_dynamics(model, loops, o);
}

#define SCANDYN_INSTANTIATE(S)                                                                                 \
  template void check_batch(const FdBatchIn<S>&, const BatchView<S>&, const BatchView<S>&, Index);            \
  template std::unique_ptr<ConstrainedForwardDynamics<S>> make_constrained_forward_dynamics(                   \
      const ModelTpl<S>&, const LoopSet&, const BackendOptions&);
SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)
#undef SCANDYN_INSTANTIATE

}  // namespace scandyn
