// kernels/simulator_step.cu: the simulator's CUDA backend (scandyn/sim/simulator.hpp).
//
// The state (q, qd: nv x B, q[i * B + b]) lives in device memory for the
// simulator's lifetime; a step never touches the host.
//   models of up to 64 DoF  one fused kernel per step (kernels/sim_fused.cuh): one
//                           thread per instance runs the whole step_instance
//                           (effects, aba_instance, integration) in registers /
//                           per-thread memory (strategy "fused-aba"); a floating
//                           base with up to 64 revolute / prismatic joints past it:
//                           sim_fused_floating_kernel (step_instance_at on the
//                           configuration manifold; q has nq rows); with contact
//                           points that walk their paths (a robot's feet) and one
//                           forward dynamics per step (euler, implicit), the contacts
//                           first in sim_floating_contacts_kernel (generalized forces
//                           and the implicit diagonal into contact_tau_ / contact_arm_);
//   beyond 64 DoF           per forward dynamics: an elementwise kernel adding the
//                           joint effects' forces, CudaForwardDynamics::compute_async
//                           (its Auto choice: the parallel chain forward dynamics for
//                           chains, jsi_dense for trees), an elementwise integration
//                           kernel (strategy "engine-<that choice>"). euler and rk4
//                           only: neither takes an armature yet. With contacts, a
//                           kernel of one thread per instance runs the contact
//                           pass (contacts.hpp) into (B x nv) wrenches before each
//                           forward dynamics; for a chain (ropes) one block per
//                           instance, its bodies in runs scanned in parallel
//                           (chain_contacts_kernel).
//   "integrator": "variational", models of up to 64 DoF: one thread per instance
//                           runs the host step's Newton (variational_dense_step,
//                           kernels/sim_variational.cuh; strategy "variational");
//                           beyond: refused (BackendError naming the limit).
#include <cub/block/block_scan.cuh>
#include <cuda_runtime.h>

#include <algorithm>
#include <limits>
#include <memory>
#include <string>
#include <variant>
#include <vector>

#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/sim/simulator.hpp"
#include "sim_fused.cuh"
#include "sim_variational.cuh"
#include "staging.hpp"

namespace scandyn {
namespace sim {
namespace detail {
namespace {

using cuda::detail::check;

constexpr int kElementBlock = 256;

unsigned element_blocks(long long count) {
  return static_cast<unsigned>((count + kElementBlock - 1) / kElementBlock);
}

// ---- the engine path's elementwise kernels (entry k = i * B + b) ---------------------

// tau_out = tau + the joint effects' forces at (qs, qds)
template <class S, unsigned E>
__global__ void forces_kernel(const JointCoefficients<S>* coef, const S* qs, const S* qds,
                              const BatchView<const S> tau, S* tau_out, Index nv, Index B) {
  const long long k = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (k >= static_cast<long long>(nv) * B) return;
  const Index i = static_cast<Index>(k / B), b = static_cast<Index>(k % B);
  const S t = tau.data ? tau.at(i, b) : S(0);
  tau_out[k] = effect_forces<E>(t, coef[i], qs[k], qds[k], S(0));
}

// A run of a chain's bodies as the map it applies to the pose and twist of the body
// before it: (X, v) -> (T X, T v + w), T the product of the run's Xup, w the run's
// joint motions carried to its last body. Composed by ComposeChainRuns (associative,
// not commutative: a then b); the identity is (I, 0).
template <class S>
struct ChainRun {
  Transform<S> T;
  Motion<S> w;
};
template <class S>
struct ComposeChainRuns {
  __device__ ChainRun<S> operator()(const ChainRun<S>& a, const ChainRun<S>& b) const {
    return {b.T * a.T, b.T.apply(a.w) + b.w};
  }
};
inline constexpr int kChainContactThreads = 256;

// The engine path's contact pass for a chain (every body's parent the one before it:
// ropes), one block per instance b, the bodies in runs of ceil(nv / threads), one
// per thread: each thread composes its run (ChainRun), a block scan gives every run
// the pose and twist of the body before it, and each thread walks its run again,
// adding the contact wrenches of the points on its bodies (point_start: (nv + 1)
// offsets into point_index, the points of body i by index) to the external wrenches
// (base + b * base_stride, or zeros) into fext (B x nv); readings (B x P) or null. The
// same quantities as contacts_kernel, the poses associated by runs: one long chain's
// contacts no longer walk it in one thread.
template <class S>
__global__ void __launch_bounds__(kChainContactThreads)
    chain_contacts_kernel(const Body<S>* bodies, Index nv, const ContactSet<S> cs, const Index* point_start,
                          const Index* point_index, const S* qs, const S* qds, Index B, const Force<S>* base,
                          long long base_stride, Force<S>* fext, ContactReading<S>* readings) {
  using Scan = cub::BlockScan<ChainRun<S>, kChainContactThreads, cub::BLOCK_SCAN_WARP_SCANS>;
  __shared__ typename Scan::TempStorage temp;
  const long long b = blockIdx.x;
  const Index per = (nv + kChainContactThreads - 1) / kChainContactThreads;
  const Index lo = min(nv, Index(threadIdx.x) * per), hi = min(nv, lo + per);
  const ContactBodyPath<false, S, Body<S>> path{bodies, qs + b, qds + b, B};
  ChainRun<S> run{Transform<S>::identity(), Motion<S>::zero()};
  for (Index i = lo; i < hi; ++i) {
    const Transform<S> Xup = path.xup(i);
    run = {Xup * run.T, Xup.apply(run.w) + path.motion(i)};
  }
  ChainRun<S> before;
  Scan(temp).ExclusiveScan(run, before, ChainRun<S>{Transform<S>::identity(), Motion<S>::zero()}, ComposeChainRuns<S>{});
  Transform<S> X = before.T;  // body lo - 1 <- world
  Motion<S> v = before.w;
  for (Index i = lo; i < hi; ++i) {
    const Transform<S> Xup = path.xup(i);
    X = Xup * X;
    v = Xup.apply(v) + path.motion(i);
    Force<S> f = base ? base[b * base_stride + i] : Force<S>::zero();
    for (Index k = point_start[i]; k < point_start[i + 1]; ++k) {
      const Index pk = point_index[k];
      add_contact_point_wrench(cs, cs.points[pk], X, v, readings ? readings + b * cs.npoints + pk : nullptr, f);
    }
    fext[b * nv + i] = f;
  }
}

// The engine path's contact pass, one thread per instance b: fext (B x nv) = the
// external wrenches (base + b * base_stride, or zeros when base is null) plus the
// contact wrenches at (qs, qds) (nv x B); X, v: (B x nv) scratch; readings (B x P)
// or null.
template <class S>
__global__ void contacts_kernel(const Body<S>* bodies, Index nv, const ContactSet<S> cs, const S* qs, const S* qds,
                                Index B, const Force<S>* base, long long base_stride, Transform<S>* X, Motion<S>* v,
                                Force<S>* fext, ContactReading<S>* readings) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= B) return;
  const long long off = b * nv;
  for (Index i = 0; i < nv; ++i) fext[off + i] = base ? base[b * base_stride + i] : Force<S>::zero();
  contact_pass_any(cs, bodies, nv, qs + b, qds + b, B, S(0), X + off, v + off, fext + off, static_cast<S*>(nullptr),
                   readings ? readings + b * cs.npoints : nullptr);
}

// The end of a step: where the instance's forward dynamics succeeded (failed[b] <
// 0; rk4: in every stage), euler_update with qdd = x, or rk4_finish with the sums
// (x, y); failures recorded once per instance (by the DoF-0 entries).
template <class S, bool kRk4>
__global__ void finish_kernel(S* q, S* qd, const S* x, const S* y, const int* failed, S dt, Index nv, Index B,
                              StepStatus* status, int* nonfinite) {
  const long long k = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (k >= static_cast<long long>(nv) * B) return;
  const Index b = static_cast<Index>(k % B);
  if (failed[b] >= 0) {
    if (k < B) record_step_failure(status, b, failed[b]);
    return;
  }
  if constexpr (kRk4) rk4_finish(dt, x[k], y[k], q[k], qd[k]);
  else euler_update(dt, x[k], q[k], qd[k]);
  // a state entry that is not finite: recorded once per instance (nonfinite[b], B
  // ints cleared before the step), with the DoF of the entry that got there first
  if (!(isfinite(q[k]) && isfinite(qd[k])) && atomicExch(&nonfinite[b], 1) == 0)
    record_step_failure(status, b, static_cast<Index>(k / B) | kNonFiniteDof);
}

// rk4, before the stages: rk4_begin, no failure yet
template <class S>
__global__ void rk4_init_kernel(const S* q, const S* qd, S* qs, S* qds, S* aq, S* aqd, int* bad, Index nv, Index B) {
  const long long k = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (k >= static_cast<long long>(nv) * B) return;
  rk4_begin(q[k], qd[k], qs[k], qds[k], aq[k], aqd[k]);
  if (k < B) bad[k] = -1;
}

// rk4, after stage s's forward dynamics: rk4_stage; bad keeps the DoF of an
// instance's first failed stage
template <class S>
__global__ void rk4_stage_kernel(const S* q, const S* qd, S* qs, S* qds, const S* qdd, S* aq, S* aqd,
                                 const int* failed, int* bad, int s, S dt, Index nv, Index B) {
  const long long k = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (k >= static_cast<long long>(nv) * B) return;
  if (k < B && failed[k] >= 0 && bad[k] < 0) bad[k] = failed[k];
  rk4_stage(s, dt, q[k], qd[k], qdd[k], qs[k], qds[k], aq[k], aqd[k]);
}

// reset: rows (count x nq of q, count x nv of qd; row r for instance idx[r]) into
// the SoA state (nq >= nv: q's extra entries by the threads of the first nq - nv)
template <class S>
__global__ void scatter_kernel(S* q, S* qd, const int* idx, const S* q_rows, const S* qd_rows, Index count, Index nq,
                               Index nv, Index B) {
  const long long k = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (k >= static_cast<long long>(count) * nq) return;
  const long long r = k / nq;
  const Index i = static_cast<Index>(k % nq);
  const long long at = static_cast<long long>(i) * B + idx[r];
  q[at] = q_rows[k];
  if (i < nv) qd[at] = qd_rows[r * nv + i];
}

// ---- the backend ------------------------------------------------------------------------

template <class S>
using ParamsVariant = std::variant<SimParams<S, 8>, SimParams<S, 16>, SimParams<S, 32>, SimParams<S, 64>>;

template <class S>
class CudaSimBackend final : public SimBackend<S> {
 public:
  explicit CudaSimBackend(const SimSetup<S>& setup) : setup_(setup) {
    const Index nv = setup.model.nv(), B = setup.batch;
    const std::size_t n = static_cast<std::size_t>(nv);
    const std::size_t nq = static_cast<std::size_t>(setup.model.nq());
    const std::size_t nb = static_cast<std::size_t>(setup.model.nbodies());
    floating_ = setup.model.floating_base();
    // the variational integrator: its own kernel (sim_variational.cuh); the Simulator
    // refuses the rest first, a direct caller meets the same refusal
    variational_ = setup.integrator == Integrator::Variational;
    if (variational_ && (setup.model.multi_dof() || (setup.effects & ~kVariationalEffects) != 0 ||
                         !setup.prescribed.empty() || !setup.loops.empty()))
      throw BackendError("backend 'cuda': the variational integrator takes 1-DoF models without contacts, closed "
                         "loops or prescribed motion");
    if (variational_) VariationalSimPlan<S>::require_capacity(setup);
    // models with multi-DoF joints that the thread kernels do not take: the general step
    general_ = !variational_ && cuda::takes_general_path(setup.model);
    fused_ = !variational_ && !general_ && (floating_ ? setup.model.nbodies() - 1 : nv) <= cuda::kMaxThreadDofs;
    engine_ = !variational_ && !fused_ && !general_;
    if (engine_ && setup.integrator == Integrator::Implicit)
      throw BackendError("backend 'cuda': the implicit integrator runs on the GPU for models of up to " +
                         std::to_string(cuda::kMaxThreadDofs) + " DoF; this model has " + std::to_string(nv) +
                         " (the dense forward dynamics beyond takes no armature yet): use euler or rk4, or the "
                         "serial or openmp backend");
    // q, qd; the per-step wrenches; the engine path's tau + effects, qdd, rk4 stages and three failure flags
    const std::size_t per_instance = (nq + n) * sizeof(S) + (setup.wrenches_per_step ? nb * sizeof(Force<S>) : 0) +
                                     (engine_ ? 6 * n * sizeof(S) + 3 * sizeof(int) : 0);
    const char* what = engine_ ? "q, qd, per-step wrenches, tau, qdd, rk4 stages, flags" : "q, qd (and per-step wrenches)";
    state_ = std::make_unique<cuda::detail::StagingBuffer>(B, nv, sizeof(S) == 4 ? "float" : "double", what,
                                                            per_instance);
    stream_ = state_->stream();
    char* p = static_cast<char*>(state_->data());
    const std::size_t cap = n * static_cast<std::size_t>(B);
    auto take = [&](std::size_t bytes) {
      char* r = p;
      p += bytes;
      return r;
    };
    q_ = reinterpret_cast<S*>(take(nq * static_cast<std::size_t>(B) * sizeof(S)));
    qd_ = reinterpret_cast<S*>(take(cap * sizeof(S)));
    if (setup.wrenches_per_step)
      step_wrenches_ = reinterpret_cast<Force<S>*>(take(nb * static_cast<std::size_t>(B) * sizeof(Force<S>)));
    if (engine_) {
      S** arrays[] = {&tau_, &qdd_, &qs_, &qds_, &aq_, &aqd_};
      for (S** a : arrays) *a = reinterpret_cast<S*>(take(cap * sizeof(S)));
      failed_ = reinterpret_cast<int*>(take(static_cast<std::size_t>(B) * sizeof(int)));
      bad_ = reinterpret_cast<int*>(take(static_cast<std::size_t>(B) * sizeof(int)));
      nonfinite_ = reinterpret_cast<int*>(take(static_cast<std::size_t>(B) * sizeof(int)));
    }
    // the general step's bodies and per-thread scratch (the plan's own device copy of the bodies)
    if (general_)
      general_plan_ = std::make_unique<cuda::GeneralPlan<S>>(
          setup.model, B, GeneralSimScalars<S>::extra_bytes(setup.model.nbodies(), setup.model.nq(), nv));
    // small constants: status, the constant (or zero) wrenches, the coefficients; with a
    // floating base or the general step also the implicit armature and, for the fused
    // floating kernel, the bodies (FloatingArgs)
    const bool manifold = floating_ || general_;
    const bool own_bodies = manifold && !general_;
    const std::size_t small = sizeof(StepStatus) + n * sizeof(Force<S>) + n * sizeof(JointCoefficients<S>) +
                              (manifold ? n * sizeof(S) : 0) + (own_bodies ? nb * sizeof(Body<S>) : 0);
    check(cudaMalloc(&small_, small), "allocating the simulator's constants");
    status_ = static_cast<StepStatus*>(small_);
    wrenches_ = reinterpret_cast<Force<S>*>(static_cast<char*>(small_) + sizeof(StepStatus));
    coef_ = reinterpret_cast<JointCoefficients<S>*>(reinterpret_cast<char*>(wrenches_) + n * sizeof(Force<S>));
    if (manifold) {
      char* const after = reinterpret_cast<char*>(coef_) + n * sizeof(JointCoefficients<S>);
      const Body<S>* bodies = general_ ? general_plan_->args().bodies : reinterpret_cast<const Body<S>*>(after);
      auto* armature = reinterpret_cast<S*>(after + (own_bodies ? nb * sizeof(Body<S>) : 0));
      if (own_bodies)
        check(cudaMemcpy(after, setup.model.bodies.data(), nb * sizeof(Body<S>), cudaMemcpyHostToDevice),
              "copying the bodies");
      std::vector<S> arm(n, S(0));
      for (std::size_t i = 0; i < n && i < setup.armature.size(); ++i) arm[i] = setup.armature[i];
      check(cudaMemcpy(armature, arm.data(), n * sizeof(S), cudaMemcpyHostToDevice), "copying the armature");
      floating_args_ = {bodies, coef_, setup.integrator == Integrator::Implicit ? armature : nullptr};
    }
    std::vector<Force<S>> w = setup.wrenches;
    w.resize(n, Force<S>::zero());  // zeros for the all-effects kernels of scenes without wrenches
    check(cudaMemcpy(wrenches_, w.data(), n * sizeof(Force<S>), cudaMemcpyHostToDevice), "copying the wrenches");
    check(cudaMemcpy(coef_, setup.coef.data(), n * sizeof(JointCoefficients<S>), cudaMemcpyHostToDevice),
          "copying the joint coefficients");
    for (Index b = 0; b < B && step_wrenches_; ++b)
      check(cudaMemcpy(step_wrenches_ + static_cast<std::size_t>(b) * nb, w.data(), nb * sizeof(Force<S>),
                       cudaMemcpyHostToDevice),
            "initialising the per-step wrenches");
    clear_status();
    if (setup.effects & kContacts) setup_contacts();

    if (variational_) {
      variational_plan_ = std::make_unique<VariationalSimPlan<S>>(setup);
    } else if (fused_) {
      const cuda::ZThreadModel<S> tm(setup.model);
      cuda::require_floating_capacity(tm, setup.model.name);
      std::visit(
          [&](const auto& mp) {
            using MP = std::decay_t<decltype(mp)>;
            SimParams<S, MP::capacity> sp{};
            sp.model = mp;
            // (a floating base: the kernel reads them in full from FloatingArgs)
            for (Index i = 0; i < mp.nv; ++i) {
              sp.coef[i] = setup.coef[i];
              sp.armature[i] = setup.armature.empty() ? S(0) : setup.armature[i];
            }
            sp.dt = setup.dt;
            sp.branch_slots = tm.branch_slots();
            params_ = sp;
          },
          tm.params());
    } else if (!general_) {
      BackendOptions o;
      o.backend = BackendKind::Cuda;
      o.max_batch = B;
      fd_ = std::make_unique<cuda::CudaForwardDynamics<S>>(setup.model, o);
    }
  }

  ~CudaSimBackend() override {
    if (contacts_raw_) cudaFree(contacts_raw_);
    if (small_) cudaFree(small_);
    if (rows_) cudaFree(rows_);
    if (expanded_raw_) cudaFree(expanded_raw_);
    if (device_tau_) cudaFree(device_tau_);
  }

  void step(const BatchView<const S>& tau) override {
    const Index B = setup_.batch, nv = setup_.model.nv();
    if (tau.data && tau.batch != B)
      throw BackendError("Simulator::step: torques for " + std::to_string(tau.batch) + " instances, the simulator has " +
                         std::to_string(B));
    if (B == 0) return;
    const Force<S>* wrenches = step_wrenches_ ? step_wrenches_ : wrenches_;
    const long long stride = step_wrenches_ ? setup_.model.nbodies() : 0;
    if (variational_) {
      const FusedArgs<S> args{q_, qd_, tau, wrenches, stride, B, status_, contacts_, nullptr, nullptr, nullptr};
      check(variational_plan_->launch(args, stream_), "launching the variational step");
      return;
    }
    if (general_) {
      const FusedArgs<S> args{q_, qd_, tau, wrenches, stride, B, status_, contacts_, readings_, nullptr, nullptr};
      const cuda::GeneralArgs<S>& g = general_plan_->args();
      const unsigned blocks = g.blocks(B);
      constexpr int kBlock = cuda::kGeneralBlock;
      const auto launch = [&](auto scalars) {
        constexpr bool kScalars = decltype(scalars)::value;
        switch (setup_.integrator) {
          case Integrator::Euler: sim_general_kernel<S, Integrator::Euler, kScalars><<<blocks, kBlock, 0, stream_>>>(g, args, floating_args_, setup_.dt); break;
          case Integrator::Rk4: sim_general_kernel<S, Integrator::Rk4, kScalars><<<blocks, kBlock, 0, stream_>>>(g, args, floating_args_, setup_.dt); break;
          case Integrator::Implicit: sim_general_kernel<S, Integrator::Implicit, kScalars><<<blocks, kBlock, 0, stream_>>>(g, args, floating_args_, setup_.dt); break;
          default: break;
        }
      };
      if (g.interleave == cuda::GeneralInterleave::Scalars) launch(std::true_type{});
      else launch(std::false_type{});
      check(cudaGetLastError(), "launching the general simulator step");
      return;
    }
    if (fused_) {
      const FusedArgs<S> args{q_, qd_, tau, wrenches, stride, B, status_, contacts_, readings_, contact_tau_, contact_arm_};
      cudaError_t err = cudaSuccess;
      cuda::visit_compiled_capacity(params_, [&](const auto& sp) {
        using P = std::decay_t<decltype(sp)>;
        if (floating_) {
          switch (setup_.integrator) {
            case Integrator::Euler:
              err = launch_fused_floating<S, Integrator::Euler, P::capacity>(sp, args, floating_args_, stream_);
              break;
            case Integrator::Rk4:
              err = launch_fused_floating<S, Integrator::Rk4, P::capacity>(sp, args, floating_args_, stream_);
              break;
            case Integrator::Implicit:
              err = launch_fused_floating<S, Integrator::Implicit, P::capacity>(sp, args, floating_args_, stream_);
              break;
          }
          return;
        }
        switch (setup_.integrator) {
          case Integrator::Euler:
            err = launch_fused<S, Integrator::Euler, P::capacity>(sp, setup_.effects, args, stream_);
            break;
          case Integrator::Rk4:
            err = launch_fused<S, Integrator::Rk4, P::capacity>(sp, setup_.effects, args, stream_);
            break;
          case Integrator::Implicit:
            err = launch_fused<S, Integrator::Implicit, P::capacity>(sp, setup_.effects, args, stream_);
            break;
        }
      });
      check(err, "launching the fused simulator step");
      return;
    }
    // the engine path
    const long long count = static_cast<long long>(nv) * B;
    const unsigned blocks = element_blocks(count);
    const BatchView<const S> qs_view = BatchView<const S>::soa(setup_.integrator == Integrator::Rk4 ? qs_ : q_, nv, B);
    const BatchView<const S> qds_view =
        BatchView<const S>::soa(setup_.integrator == Integrator::Rk4 ? qds_ : qd_, nv, B);
    const bool contacts = (setup_.effects & kContacts) != 0;
    const FdBatchIn<S> in{qs_view, qds_view, BatchView<const S>::soa(tau_, nv, B),
                          contacts                       ? contact_fext_
                          : (setup_.effects & kExternal) ? wrenches_for_engine(wrenches)
                                                         : nullptr};
    check(cudaMemsetAsync(nonfinite_, 0, static_cast<std::size_t>(B) * sizeof(int), stream_), "cudaMemsetAsync");
    ContactReading<S>* readings = readings_;  // rk4: the first stage's
    auto forces = [&] {
      launch_forces(qs_view.data, qds_view.data, tau);
      if (contacts) {
        if (chain_points_)
          chain_contacts_kernel<S><<<static_cast<unsigned>(B), kChainContactThreads, 0, stream_>>>(
              contact_bodies_, nv, contacts_, chain_points_, chain_points_ + nv + 1, qs_view.data, qds_view.data, B,
              (setup_.effects & kExternal) ? wrenches : nullptr, stride, contact_fext_, readings);
        else
          contacts_kernel<S><<<element_blocks(B), kElementBlock, 0, stream_>>>(
              contact_bodies_, nv, contacts_, qs_view.data, qds_view.data, B,
              (setup_.effects & kExternal) ? wrenches : nullptr, stride, contact_X_, contact_v_, contact_fext_, readings);
        readings = nullptr;
      }
      check(fd_->compute_async(in, BatchView<S>::soa(qdd_, nv, B), failed_, stream_), "running the forward dynamics");
    };
    if (setup_.integrator == Integrator::Euler) {
      forces();
      finish_kernel<S, false><<<blocks, kElementBlock, 0, stream_>>>(q_, qd_, qdd_, nullptr, failed_, setup_.dt, nv, B,
                                                                      status_, nonfinite_);
    } else {
      rk4_init_kernel<S><<<blocks, kElementBlock, 0, stream_>>>(q_, qd_, qs_, qds_, aq_, aqd_, bad_, nv, B);
      for (int s = 0; s < 4; ++s) {
        forces();
        rk4_stage_kernel<S><<<blocks, kElementBlock, 0, stream_>>>(q_, qd_, qs_, qds_, qdd_, aq_, aqd_, failed_, bad_,
                                                                   s, setup_.dt, nv, B);
      }
      finish_kernel<S, true><<<blocks, kElementBlock, 0, stream_>>>(q_, qd_, aq_, aqd_, bad_, setup_.dt, nv, B, status_,
                                                                    nonfinite_);
    }
    check(cudaGetLastError(), "launching the simulator's integration kernels");
  }

  // tau in host memory (a shard of a simulator across devices): packed into (nv x B)
  // here, copied on the stream (pageable memory: the call returns once the rows are
  // staged, so the next step may repack them), then the step on the device's copy
  void step_host(const BatchView<const S>& tau) override {
    if (!tau.data) return step(tau);
    const Index B = setup_.batch, nv = setup_.model.nv();
    if (tau.batch != B)
      throw BackendError("Simulator::step: torques for " + std::to_string(tau.batch) + " instances, the simulator has " +
                         std::to_string(B));
    const std::size_t count = static_cast<std::size_t>(nv) * static_cast<std::size_t>(B);
    host_tau_.resize(count);
    for (Index i = 0; i < nv; ++i)
      for (Index b = 0; b < B; ++b) host_tau_[static_cast<std::size_t>(i) * B + b] = tau.at(i, b);
    if (!device_tau_) check(cudaMalloc(reinterpret_cast<void**>(&device_tau_), count * sizeof(S)), "allocating the torques");
    check(cudaMemcpyAsync(device_tau_, host_tau_.data(), count * sizeof(S), cudaMemcpyHostToDevice, stream_),
          "copying the torques to the device");
    step(BatchView<const S>::soa(device_tau_, nv, B));
  }

  BatchView<S> q() override { return BatchView<S>::soa(q_, setup_.model.nq(), setup_.batch); }
  BatchView<S> qd() override { return BatchView<S>::soa(qd_, setup_.model.nv(), setup_.batch); }
  Force<S>* wrenches() override { return step_wrenches_; }
  ContactReading<S>* contact_forces() override { return readings_; }
  void read_contact_forces(ContactReading<S>* host) override {
    if (!readings_) return;
    const std::size_t bytes = static_cast<std::size_t>(setup_.batch) * setup_.contact_count() * sizeof(ContactReading<S>);
    check(cudaMemcpyAsync(host, readings_, bytes, cudaMemcpyDeviceToHost, stream_), "copying the contact forces");
    check(cudaStreamSynchronize(stream_), "copying the contact forces");
  }

  void write_instances(const Index* instances, Index count, const S* q_rows, const S* qd_rows) override {
    if (count == 0) return;
    const std::size_t n = static_cast<std::size_t>(setup_.model.nv()), nq = static_cast<std::size_t>(setup_.model.nq());
    const std::size_t bytes = static_cast<std::size_t>(count) * (sizeof(int) + (nq + n) * sizeof(S)) + sizeof(S);
    if (bytes > rows_bytes_) {
      check(cudaStreamSynchronize(stream_), "resetting instances");
      if (rows_) cudaFree(rows_);
      rows_ = nullptr;
      check(cudaMalloc(&rows_, bytes), "allocating the reset buffer");
      rows_bytes_ = bytes;
    }
    int* idx = static_cast<int*>(rows_);
    // rows after the indices, aligned to S
    const std::size_t off = (static_cast<std::size_t>(count) * sizeof(int) + sizeof(S) - 1) / sizeof(S) * sizeof(S);
    S* qr = reinterpret_cast<S*>(static_cast<char*>(rows_) + off);
    S* qdr = qr + static_cast<std::size_t>(count) * nq;
    static_assert(sizeof(Index) == sizeof(int), "Index is int");
    check(cudaMemcpyAsync(idx, instances, count * sizeof(int), cudaMemcpyHostToDevice, stream_), "resetting instances");
    check(cudaMemcpyAsync(qr, q_rows, count * nq * sizeof(S), cudaMemcpyHostToDevice, stream_), "resetting instances");
    check(cudaMemcpyAsync(qdr, qd_rows, count * n * sizeof(S), cudaMemcpyHostToDevice, stream_), "resetting instances");
    scatter_kernel<S><<<element_blocks(static_cast<long long>(count) * nq), kElementBlock, 0, stream_>>>(
        q_, qd_, idx, qr, qdr, count, static_cast<Index>(nq), static_cast<Index>(n), setup_.batch);
    check(cudaGetLastError(), "resetting instances");
    // the host rows are the caller's scratch, reused after we return
    check(cudaStreamSynchronize(stream_), "resetting instances");
  }

  void read_state(S* q_host, S* qd_host) override {
    const std::size_t bytes = static_cast<std::size_t>(setup_.model.nv()) * setup_.batch * sizeof(S);
    const std::size_t q_bytes = static_cast<std::size_t>(setup_.model.nq()) * setup_.batch * sizeof(S);
    check(cudaMemcpyAsync(q_host, q_, q_bytes, cudaMemcpyDeviceToHost, stream_), "copying q to the host");
    check(cudaMemcpyAsync(qd_host, qd_, bytes, cudaMemcpyDeviceToHost, stream_), "copying qd to the host");
    check(cudaStreamSynchronize(stream_), "copying the state to the host");
  }

  BatchStatus status() override {
    StepStatus s;
    check(cudaMemcpyAsync(&s, status_, sizeof s, cudaMemcpyDeviceToHost, stream_), "reading the step status");
    check(cudaStreamSynchronize(stream_), "running the simulator's steps");
    BatchStatus st;
    if (s.failed == 0) return st;
    // the forward dynamics the failures came from names the pivot
    const Index dof = static_cast<Index>(s.first & 0xffffffffull);
    st.record(static_cast<Index>(s.first >> 32), dof & ~(kNonFiniteDof | kNotConvergedDof),
              (dof & kNonFiniteDof)      ? Failure::NonFinite
              : (dof & kNotConvergedDof) ? Failure::NotConverged
              : !engine_                 ? Failure::ArticulatedPivot
                                         : pivot_failure(fd_->method()));
    st.failed = static_cast<Index>(std::min<unsigned long long>(s.failed, std::numeric_limits<Index>::max()));
    return st;
  }
  void clear_status() override {
    const StepStatus zero = kStepStatusClear;
    check(cudaMemcpyAsync(status_, &zero, sizeof zero, cudaMemcpyHostToDevice, stream_), "clearing the step status");
    check(cudaStreamSynchronize(stream_), "clearing the step status");
  }
  void synchronize() override { check(cudaStreamSynchronize(stream_), "running the simulator's steps"); }
  bool on_device() const override { return true; }
  std::string strategy() const override {
    return variational_ ? "variational" : general_ ? "general-aba" : fused_ ? "fused-aba" : "engine-" + fd_->strategy();
  }
  void* stream() const override { return stream_; }

 private:
  // The contacts in device memory: points, planes, spheres, the readings (zeros),
  // and for the engine path the bodies and the contact pass's scratch.
  void setup_contacts() {
    const std::size_t n = static_cast<std::size_t>(setup_.model.nv()), B = static_cast<std::size_t>(setup_.batch);
    const std::size_t P = static_cast<std::size_t>(setup_.contact_count());
    const std::size_t np = setup_.contact_planes.size(), ns = setup_.contact_spheres.size();
    const std::size_t a = 16;  // alignment of each array
    auto up = [&](std::size_t x) { return (x + a - 1) / a * a; };
    std::size_t bytes = up(P * sizeof(ContactPoint<S>)) + up(np * sizeof(ContactPlane<S>)) +
                        up(ns * sizeof(ContactSphere<S>)) + up(B * P * sizeof(ContactReading<S>));
    const bool split = fused_ && floating_;  // launch_fused_floating's contacts kernel: its two outputs
    if (split) bytes += 2 * up(B * n * sizeof(S));
    // the engine path on a chain (chain_contacts_kernel): the points by body
    bool chain = engine_ && !setup_.model.multi_dof();
    for (std::size_t i = 0; chain && i < n; ++i) chain = setup_.model.bodies[i].parent == static_cast<Index>(i) - 1;
    if (chain) bytes += up((n + 1 + P) * sizeof(Index));
    if (engine_) bytes += up(n * sizeof(Body<S>)) + B * n * (sizeof(Transform<S>) + sizeof(Motion<S>) + sizeof(Force<S>));
    check(cudaMalloc(&contacts_raw_, bytes), "allocating the contacts");
    char* p = static_cast<char*>(contacts_raw_);
    auto take = [&](std::size_t b) {
      char* r = p;
      p += up(b);
      return r;
    };
    auto copy = [&](void* dst, const void* src, std::size_t b) {
      if (b) check(cudaMemcpy(dst, src, b, cudaMemcpyHostToDevice), "copying the contacts");
    };
    auto* points = reinterpret_cast<ContactPoint<S>*>(take(P * sizeof(ContactPoint<S>)));
    auto* planes = reinterpret_cast<ContactPlane<S>*>(take(np * sizeof(ContactPlane<S>)));
    auto* spheres = reinterpret_cast<ContactSphere<S>*>(take(ns * sizeof(ContactSphere<S>)));
    readings_ = reinterpret_cast<ContactReading<S>*>(take(B * P * sizeof(ContactReading<S>)));
    if (chain) {  // point_start (n + 1), then point_index (P): a counting sort of the points by body
      chain_points_ = reinterpret_cast<Index*>(take((n + 1 + P) * sizeof(Index)));
      std::vector<Index> start(n + 1, 0), index(P);
      for (const ContactPoint<S>& cp : setup_.contact_points) ++start[static_cast<std::size_t>(cp.body) + 1];
      for (std::size_t i = 0; i < n; ++i) start[i + 1] += start[i];
      std::vector<Index> next(start.begin(), start.end() - 1);
      for (std::size_t k = 0; k < P; ++k)
        index[static_cast<std::size_t>(next[static_cast<std::size_t>(setup_.contact_points[k].body)]++)] = static_cast<Index>(k);
      copy(chain_points_, start.data(), (n + 1) * sizeof(Index));
      copy(chain_points_ + n + 1, index.data(), P * sizeof(Index));
    }
    if (split) {
      contact_tau_ = reinterpret_cast<S*>(take(B * n * sizeof(S)));
      contact_arm_ = reinterpret_cast<S*>(take(B * n * sizeof(S)));
    }
    if (fused_) {  // the fused kernels' bodies (and a floating base's bodies past it) are z-axis frames
                   // (ZThreadModel): the points in them
      const ZAxisModel<S> zm = z_axis_model(setup_.model);
      std::vector<ContactPoint<S>> turned = setup_.contact_points;
      for (ContactPoint<S>& cp : turned) cp.position = zm.to_z_frame(cp.body, cp.position);
      copy(points, turned.data(), P * sizeof(ContactPoint<S>));
    } else {
      copy(points, setup_.contact_points.data(), P * sizeof(ContactPoint<S>));
    }
    copy(planes, setup_.contact_planes.data(), np * sizeof(ContactPlane<S>));
    copy(spheres, setup_.contact_spheres.data(), ns * sizeof(ContactSphere<S>));
    check(cudaMemset(readings_, 0, B * P * sizeof(ContactReading<S>)), "clearing the contact forces");
    contacts_ = setup_.contact_set();
    contacts_.points = points, contacts_.planes = planes, contacts_.spheres = spheres;
    if (engine_) {
      contact_bodies_ = reinterpret_cast<Body<S>*>(take(n * sizeof(Body<S>)));
      copy(contact_bodies_, setup_.model.bodies.data(), n * sizeof(Body<S>));
      contact_X_ = reinterpret_cast<Transform<S>*>(p);
      contact_v_ = reinterpret_cast<Motion<S>*>(p + B * n * sizeof(Transform<S>));
      contact_fext_ = reinterpret_cast<Force<S>*>(p + B * n * (sizeof(Transform<S>) + sizeof(Motion<S>)));
    }
  }

  // the engine takes (B x nv) wrenches, one row per instance: the per-step buffer,
  // or the constant row expanded once into a per-instance buffer
  const Force<S>* wrenches_for_engine(const Force<S>* w) {
    if (step_wrenches_ || setup_.batch == 1) return w;
    if (!expanded_) {
      const std::size_t n = static_cast<std::size_t>(setup_.model.nv());
      check(cudaMalloc(&expanded_raw_, n * setup_.batch * sizeof(Force<S>)), "allocating the wrenches");
      expanded_ = static_cast<Force<S>*>(expanded_raw_);
      for (Index b = 0; b < setup_.batch; ++b)
        check(cudaMemcpy(expanded_ + b * n, wrenches_, n * sizeof(Force<S>), cudaMemcpyDeviceToDevice),
              "expanding the wrenches");
    }
    return expanded_;
  }

  // tau_ = tau + joint effects at (qs, qds), for the scene's joint effects
  void launch_forces(const S* qs, const S* qds, const BatchView<const S>& tau) {
    const Index nv = setup_.model.nv(), B = setup_.batch;
    const unsigned blocks = element_blocks(static_cast<long long>(nv) * B);
    switch (setup_.effects & kJointEffects) {
#define SCANDYN_FORCES_CASE(E) \
  case E: forces_kernel<S, E><<<blocks, kElementBlock, 0, stream_>>>(coef_, qs, qds, tau, tau_, nv, B); break;
      SCANDYN_FORCES_CASE(0u)
      SCANDYN_FORCES_CASE(kDamping)
      SCANDYN_FORCES_CASE(kSprings)
      SCANDYN_FORCES_CASE(kDamping | kSprings)
      SCANDYN_FORCES_CASE(kLimits)
      SCANDYN_FORCES_CASE(kLimits | kDamping)
      SCANDYN_FORCES_CASE(kLimits | kSprings)
      SCANDYN_FORCES_CASE(kLimits | kDamping | kSprings)
#undef SCANDYN_FORCES_CASE
    }
  }

  const SimSetup<S>& setup_;  // the Simulator's, which outlives its backend
  bool fused_ = true;
  bool floating_ = false;                 // a floating base (sim_fused_floating_kernel)
  bool general_ = false;                  // joints of any type (sim_general_kernel over general_plan_)
  bool engine_ = false;                   // the engine path (neither fused nor general)
  bool variational_ = false;              // the variational integrator (variational_plan_)
  std::unique_ptr<VariationalSimPlan<S>> variational_plan_;  // its kernel's model, coefficients, matrices
  FloatingArgs<S> floating_args_{};       // floating / general: bodies, coefficients, armature (in small_)
  std::unique_ptr<cuda::GeneralPlan<S>> general_plan_;  // the general step's bodies and per-thread scratch
  std::unique_ptr<cuda::detail::StagingBuffer> state_;  // the device, the stream, the state buffer
  cudaStream_t stream_ = nullptr;
  S* q_ = nullptr;                        // (nq x B) device
  S* qd_ = nullptr;                       // (nv x B) device
  Force<S>* step_wrenches_ = nullptr;     // (B x nbodies) per-step wrenches, or null
  S *tau_ = nullptr, *qdd_ = nullptr, *qs_ = nullptr, *qds_ = nullptr, *aq_ = nullptr, *aqd_ = nullptr;  // engine path
  int* failed_ = nullptr;                 // (B) the engine's failed DoF per instance
  int* bad_ = nullptr;                    // (B) rk4: any stage failed
  int* nonfinite_ = nullptr;              // (B) this step: the instance's state is not finite (recorded once)
  void* small_ = nullptr;                 // status, wrenches_, coef_
  StepStatus* status_ = nullptr;          // failed instance-steps, the lowest failed instance and its DoF
  Force<S>* wrenches_ = nullptr;          // (nv) constant wrenches (zeros when none)
  JointCoefficients<S>* coef_ = nullptr;  // (nv)
  void* rows_ = nullptr;                  // reset staging
  std::size_t rows_bytes_ = 0;
  void* expanded_raw_ = nullptr;
  Force<S>* expanded_ = nullptr;          // (B x nv) constant wrenches for the engine
  std::vector<S> host_tau_;               // (nv x B) step_host: the torques packed
  S* device_tau_ = nullptr;               // (nv x B) step_host: their device copy
  ParamsVariant<S> params_;
  std::unique_ptr<cuda::CudaForwardDynamics<S>> fd_;
  // contacts (setup_contacts), one allocation
  void* contacts_raw_ = nullptr;
  ContactSet<S> contacts_;                 // device pointers
  ContactReading<S>* readings_ = nullptr;  // (B x P) device, or null without contacts
  Body<S>* contact_bodies_ = nullptr;      // (nv) engine path
  Transform<S>* contact_X_ = nullptr;      // (B x nv) engine path: poses
  Motion<S>* contact_v_ = nullptr;         // (B x nv) engine path: twists
  Force<S>* contact_fext_ = nullptr;       // (B x nv) engine path: external + contact wrenches
  Index* chain_points_ = nullptr;          // engine path on a chain: (nv + 1) offsets, then (P) point indices by body
  S* contact_tau_ = nullptr;               // (nv x B) floating fused step: the contacts' generalized forces
  S* contact_arm_ = nullptr;               // (B x nv) floating fused step, implicit: armature + contacts' diagonal
};

}  // namespace

template <class S>
std::unique_ptr<SimBackend<S>> make_cuda_sim_backend(const SimSetup<S>& setup) {
  return std::make_unique<CudaSimBackend<S>>(setup);
}

template std::unique_ptr<SimBackend<float>> make_cuda_sim_backend(const SimSetup<float>&);
template std::unique_ptr<SimBackend<double>> make_cuda_sim_backend(const SimSetup<double>&);

}  // namespace detail
}  // namespace sim
}  // namespace scandyn
