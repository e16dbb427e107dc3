// cpu_fallback/simulator_step.cpp: the simulator's serial and OpenMP step
// (simulator_step.hpp): per instance through the instance loop, or for a few long
// chains per forward dynamics through the parallel chain forward dynamics.
#include "simulator_step.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <utility>
#include <vector>

#include "instance_loop.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/sim/contacts.hpp"
#include "scandyn/sim/integrators.hpp"
#include "scandyn/sim/iterative_loops.hpp"
#include "scandyn/sim/variational.hpp"

namespace scandyn {
namespace cpu {
namespace {

using sim::Integrator;
using sim::JointCoefficients;
using sim::SimSetup;
using sim::StepScratch;

// What both CPU steps keep: the resident state (q: nq x B, qd: nv x B, q[i * B +
// b]), the per-step wrenches, the status of the steps since the last clear.
template <class S>
class CpuSimState : public sim::detail::SimBackend<S> {
 public:
  CpuSimState(const SimSetup<S>& setup, BackendKind backend, int threads)
      : setup_(setup), backend_(backend), threads_(threads) {
    const std::size_t nv = static_cast<std::size_t>(setup.model.nv());
    const std::size_t nq = static_cast<std::size_t>(setup.model.nq());
    const std::size_t nb = static_cast<std::size_t>(setup.model.nbodies());
    const std::size_t B = static_cast<std::size_t>(setup.batch);
    q_.assign(nq * B, S(0));
    qd_.assign(nv * B, S(0));
    if (setup.wrenches_per_step) {
      wrenches_.resize(B * nb);
      for (std::size_t b = 0; b < B; ++b)
        std::copy(setup.wrenches.begin(), setup.wrenches.end(), wrenches_.begin() + b * nb);
    }
    if (setup.effects & sim::kContacts)
      readings_.assign(B * static_cast<std::size_t>(setup.contact_count()), sim::ContactReading<S>{});
  }

  BatchView<S> q() override { return BatchView<S>::soa(q_.data(), setup_.model.nq(), setup_.batch); }
  BatchView<S> qd() override { return BatchView<S>::soa(qd_.data(), setup_.model.nv(), setup_.batch); }
  Force<S>* wrenches() override { return wrenches_.empty() ? nullptr : wrenches_.data(); }
  sim::ContactReading<S>* contact_forces() override { return readings_.empty() ? nullptr : readings_.data(); }
  void read_contact_forces(sim::ContactReading<S>* host) override { std::copy(readings_.begin(), readings_.end(), host); }

  void write_instances(const Index* instances, Index count, const S* q_rows, const S* qd_rows) override {
    const std::size_t n = static_cast<std::size_t>(setup_.model.nv()), B = static_cast<std::size_t>(setup_.batch);
    const std::size_t nq = static_cast<std::size_t>(setup_.model.nq());
    for (Index k = 0; k < count; ++k) {
      for (std::size_t i = 0; i < nq; ++i) q_[i * B + static_cast<std::size_t>(instances[k])] = q_rows[k * nq + i];
      for (std::size_t i = 0; i < n; ++i) qd_[i * B + static_cast<std::size_t>(instances[k])] = qd_rows[k * n + i];
    }
  }
  void read_state(S* q_host, S* qd_host) override {
    std::copy(q_.begin(), q_.end(), q_host);
    std::copy(qd_.begin(), qd_.end(), qd_host);
  }
  BatchStatus status() override { return status_; }
  void clear_status() override { status_ = {}; }
  void synchronize() override {}
  bool on_device() const override { return false; }

 protected:
  void check_torques(const BatchView<const S>& tau) const {
    if (tau.data && tau.batch != setup_.batch)
      throw BackendError("Simulator::step: torques for " + std::to_string(tau.batch) + " instances, the simulator has " +
                         std::to_string(setup_.batch));
  }
  // the wrenches of instance b (B x nbodies per step, or the constant nbodies), null without them
  const Force<S>* instance_wrenches(Index b) const {
    if (!wrenches_.empty()) return wrenches_.data() + static_cast<std::size_t>(b) * setup_.model.nbodies();
    return setup_.wrenches.empty() ? nullptr : setup_.wrenches.data();
  }

  const SimSetup<S>& setup_;  // the Simulator's, which outlives its backend
  BackendKind backend_;
  int threads_;
  std::vector<S> q_, qd_;           // (nq x B), (nv x B) state, q[i * B + b]
  std::vector<Force<S>> wrenches_;  // (B x nbodies) per-step wrenches, or empty
  std::vector<sim::ContactReading<S>> readings_;  // (B x P) the last step's contacts, or empty
  BatchStatus status_;              // the steps' failures since the last clear
};

// ---- per instance -----------------------------------------------------------------

template <class S>
class CpuInstanceStep final : public CpuSimState<S> {
  using Base = CpuSimState<S>;
  using Base::setup_, Base::threads_, Base::q_, Base::qd_, Base::status_, Base::readings_;

 public:
  CpuInstanceStep(const SimSetup<S>& setup, BackendKind backend, int threads) : Base(setup, backend, threads) {
    const std::size_t nv = static_cast<std::size_t>(setup.model.nv());
    for (int t = 0; t < threads; ++t) work_.emplace_back(setup_, nv, static_cast<std::size_t>(setup.model.nq()));
    failed_.assign(static_cast<std::size_t>(std::max<Index>(setup.batch, 1)), -1);
    nonfinite_ = failed_;
    what_.assign(failed_.size(), Failure::ArticulatedPivot);
    estimate_.assign(failed_.size(), 0.0);
    if (setup.integrator == Integrator::Variational) {
      // the Simulator refuses the rest first (simulator.cpp); a direct caller meets the same
      if (setup.model.multi_dof() || (setup.effects & ~sim::kVariationalEffects) != 0 || !setup.prescribed.empty() ||
          !setup.loops.empty())
        throw BackendError("the variational integrator takes 1-DoF models without contacts, closed loops or "
                           "prescribed motion");
      step_ = variational_table()[setup.effects];
      return;
    }
    const int entry = static_cast<int>(setup.integrator) * sim::kEffectSets + static_cast<int>(setup.effects);
    step_ = setup.model.multi_dof()                              ? manifold_table()[entry]
            : setup.prescribed.empty() && setup.loops.empty() ? table()[entry]
                                                              : constrained_table()[entry];
  }

  void step(const BatchView<const S>& tau) override {
    this->check_torques(tau);
    const Index B = setup_.batch, n = setup_.model.nv(), nq = setup_.model.nq();
    S* const q = q_.data();
    S* const qd = qd_.data();
    Index failures = 0;
    for_instance_blocks(threads_, B, [&](int t, Index begin, Index end) {
      Work& w = work_[static_cast<std::size_t>(t)];
      Index local = 0;
      for (Index b = begin; b < end; ++b) {
        for (Index i = 0; i < n; ++i) {
          w.q[i] = q[static_cast<std::size_t>(i) * B + b];
          w.qd[i] = qd[static_cast<std::size_t>(i) * B + b];
          w.tau[i] = tau.data ? tau.at(i, b) : S(0);
        }
        for (Index i = n; i < nq; ++i) w.q[i] = q[static_cast<std::size_t>(i) * B + b];
        const Index dof = step_(setup_, w, w.q.data(), w.qd.data(), w.tau.data(), this->instance_wrenches(b),
                                readings_.empty() ? nullptr : readings_.data() + static_cast<std::size_t>(b) * setup_.contact_count());
        failed_[static_cast<std::size_t>(b)] = static_cast<int>(dof);
        what_[static_cast<std::size_t>(b)] = w.failure;
        estimate_[static_cast<std::size_t>(b)] = w.failure_estimate;
        w.failure = Failure::ArticulatedPivot;
        nonfinite_[static_cast<std::size_t>(b)] = -1;
        if (dof >= 0) {  // the instance keeps its state for this step
          ++local;
          continue;
        }
        for (Index i = 0; i < n; ++i) {
          q[static_cast<std::size_t>(i) * B + b] = w.q[i];
          qd[static_cast<std::size_t>(i) * B + b] = w.qd[i];
          if (nonfinite_[static_cast<std::size_t>(b)] < 0 && !(std::isfinite(w.q[i]) && std::isfinite(w.qd[i]))) {
            nonfinite_[static_cast<std::size_t>(b)] = static_cast<int>(i);
            ++local;
          }
        }
        for (Index i = n; i < nq; ++i) {  // quaternion models: q's last nq - nv entries
          q[static_cast<std::size_t>(i) * B + b] = w.q[i];
          if (nonfinite_[static_cast<std::size_t>(b)] < 0 && !std::isfinite(w.q[i])) {
            nonfinite_[static_cast<std::size_t>(b)] = static_cast<int>(i);
            ++local;
          }
        }
      }
      if (local > 0) {
#pragma omp atomic
        failures += local;
      }
    });
    if (failures > 0) {
      BatchStatus st;  // each failed instance with its kind (a pivot; the variational step's own)
      for (Index b = 0; b < B; ++b)
        if (failed_[static_cast<std::size_t>(b)] >= 0)
          st.record(b, failed_[static_cast<std::size_t>(b)], what_[static_cast<std::size_t>(b)]);
      if (st.failure == Failure::LoopNotClosed) {  // the first one's violation and the tolerance
        st.estimate = estimate_[static_cast<std::size_t>(st.first_instance)];
        st.threshold = kLoopStateTolerance;
      }
      sim::add_step_failures(status_, st);
      sim::add_step_failures(status_, summarize_failures(nonfinite_.data(), B, Failure::NonFinite));
    }
  }

  std::string strategy() const override { return this->backend_ == BackendKind::OpenMP ? "openmp-aba" : "serial-aba"; }

 private:
  // One thread's workspace: the ABA's scratch, the step's arrays, the contact pass's.
  // n = nv, nq: the model's (nq > n with quaternions).
  struct Work {
    Work(const SimSetup<S>& setup, std::size_t n, std::size_t nq)
        : data(setup.model, false), q(nq), qd(n), tau(n), buffer(nq > n ? 6 * n + nq : 6 * n),
          scratch{buffer.data(), buffer.data() + n, buffer.data() + 2 * n, buffer.data() + 3 * n,
                  buffer.data() + 4 * n, buffer.data() + 5 * n},
          scratch_at{buffer.data(), buffer.data() + n, buffer.data() + 6 * n, buffer.data() + 3 * n,
                     buffer.data() + 4 * n, buffer.data() + 5 * n, buffer.data() + 2 * n},
          contacts(setup.contact_set()),
          driven(4 * n), loop_q(n), loop_qd(n), loop_tau(n), loop_qdd(n), loop_lambda(0) {
      if (setup.effects & sim::kContacts) X.resize(n), v.resize(n), fext.resize(n), armature.resize(n);
      if (setup.integrator == Integrator::Variational)
        variational = std::make_unique<sim::VariationalWork<S>>(setup.model);
    }
    Work(Work&& o) noexcept = default;
    DataTpl<S> data;
    std::vector<S> q, qd, tau;  // (nq), (n), (n) the instance's state and torques
    std::vector<S> buffer;      // (6 n, + nq with quaternions) StepScratch's arrays
    StepScratch<S> scratch;     // 1-DoF models
    sim::StepScratchAt<S> scratch_at;  // models with multi-DoF joints (over the same buffer; qs its last nq)
    sim::ContactSet<S> contacts;    // over the setup's vectors
    std::vector<Transform<S>> X;    // (n) contacts: body <- world
    std::vector<Motion<S>> v;       // (n) contacts: body twists
    std::vector<Force<S>> fext;     // (n) contacts: external + contact wrenches
    std::vector<S> armature;        // (n) contacts, implicit: the armature + the contacts' bound
    std::vector<S> driven;          // (4 n) prescribed motion: the stage's q, qd, qdd in and tau out
    std::vector<double> loop_q, loop_qd, loop_tau, loop_qdd, loop_lambda;  // closed loops: a stage in double
    std::vector<Force<double>> loop_fext;  // closed loops: the stage's external + contact wrenches, or empty
    std::unique_ptr<sim::LoopSolver> loop_sparse;  // closed loops, sparse path: made at the first step, kept
    std::unique_ptr<sim::VariationalWork<S>> variational;  // the variational integrator's scratch, or null
    Failure failure = Failure::ArticulatedPivot;  // what a failed step failed at (the variational step sets it)
    double failure_estimate = 0;  // LoopNotClosed: the state's loop violation after the projection
  };

  using StepFn = Index (*)(const SimSetup<S>&, Work&, S*, S*, const S*, const Force<S>*, sim::ContactReading<S>*);

  // What one forward dynamics at (qa, qda) receives besides the torques: the
  // external wrenches (fext, null without kExternal) and the implicit armature (null
  // unless implicit). With contacts (effect set E), the contact pass adds the
  // contact wrenches to work.fext and, implicit, the contacts' linearised diagonal
  // bound to work.armature, and writes the readings (then nulled: an rk4 step
  // reports its first stage's contacts).
  // kMultiDof: a model with multi-DoF joints (q with nq entries, fext per body).
  template <unsigned E, bool kMultiDof = false>
  static std::pair<const Force<S>*, const S*> with_contacts(const SimSetup<S>& setup, Work& work, const S* qa,
                                                            const S* qda, const Force<S>* fext, const S* armature,
                                                            sim::ContactReading<S>*& readings) {
    const Force<S>* f = (E & sim::kExternal) ? fext : nullptr;
    if constexpr ((E & sim::kContacts) == 0) {
      (void)setup, (void)work, (void)qa, (void)qda, (void)readings;
      return {f, armature};
    } else {
      sim::add_contact_wrenches<kMultiDof>(work.contacts, setup.model.bodies.data(), setup.model.nbodies(),
                                           setup.model.nv(), setup.dt, qa, qda, f, armature, work.X.data(),
                                           work.v.data(), work.fext.data(), work.armature.data(), readings);
      return {f, armature};
    }
  }

  // One instance's step for effect set E and integrator I: step_instance over the
  // ABA, each forward dynamics with the contact pass's wrenches (with_contacts).
  template <unsigned E, Integrator I>
  static Index step_one(const SimSetup<S>& setup, Work& work, S* q, S* qd, const S* tau, const Force<S>* fext,
                        sim::ContactReading<S>* readings) {
    const ModelTpl<S>& model = setup.model;
    auto fd = [&](const S* qa, const S* qda, const S* t, const S* armature, S* qdd) -> Index {
      const auto [f, a] = with_contacts<E>(setup, work, qa, qda, fext, armature, readings);
      return aba(model, work.data, qa, qda, t, qdd, f, a).failed_dof;
    };
    return sim::step_instance<E, I>(model.nv(), setup.dt, setup.coef.data(),
                                    setup.armature.empty() ? nullptr : setup.armature.data(), q, qd, tau, work.scratch, fd);
  }

  // One instance's step of a model with multi-DoF joints (a floating base, ball
  // joints): step_instance_at on the configuration manifold over the ABA.
  template <unsigned E, Integrator I>
  static Index step_one_at(const SimSetup<S>& setup, Work& work, S* q, S* qd, const S* tau, const Force<S>* fext,
                           sim::ContactReading<S>* readings) {
    const ModelTpl<S>& model = setup.model;
    auto fd = [&](const S* qa, const S* qda, const S* t, const S* armature, S* qdd) -> Index {
      const auto [f, a] = with_contacts<E, true>(setup, work, qa, qda, fext, armature, readings);
      return aba(model, work.data, qa, qda, t, qdd, f, a).failed_dof;
    };
    return sim::step_instance_at<E, I>(model.bodies.data(), model.nbodies(), model.nq(), model.nv(), setup.dt,
                                       setup.coef.data(), setup.armature.empty() ? nullptr : setup.armature.data(), q,
                                       qd, tau, work.scratch_at, fd);
  }
  template <std::size_t... K>
  static constexpr std::array<StepFn, sizeof...(K)> make_manifold_table(std::index_sequence<K...>) {
    return {&step_one_at<sim::host_step_set(unsigned(K % sim::kEffectSets)), Integrator(K / sim::kEffectSets)>...};
  }
  static const std::array<StepFn, sim::kIntegrators * sim::kEffectSets>& manifold_table() {
    static const auto t = make_manifold_table(std::make_index_sequence<sim::kIntegrators * sim::kEffectSets>{});
    return t;
  }

  // Every (integrator, effect set) instantiation, indexed integrator * 32 + effects.
  template <std::size_t... K>
  static constexpr std::array<StepFn, sizeof...(K)> make_table(std::index_sequence<K...>) {
    return {&step_one<sim::host_step_set(unsigned(K % sim::kEffectSets)), Integrator(K / sim::kEffectSets)>...};
  }
  static const std::array<StepFn, sim::kIntegrators * sim::kEffectSets>& table() {
    static const auto t = make_table(std::make_index_sequence<sim::kIntegrators * sim::kEffectSets>{});
    return t;
  }

  // One instance's variational step (scandyn/sim/variational.hpp) for effect set E;
  // sets work.failure on a failure. Effect sets it does not take are refused at
  // construction and never run.
  template <unsigned E>
  static Index variational_step_one(const SimSetup<S>& setup, Work& work, S* q, S* qd, const S* tau,
                                    const Force<S>* fext, sim::ContactReading<S>*) {
    if constexpr ((E & ~sim::kVariationalEffects) != 0) {
      (void)setup, (void)q, (void)qd, (void)tau, (void)fext;
      work.failure = Failure::NotConverged;
      return 0;
    } else {
      const sim::VariationalResult r =
          sim::variational_step<E>(setup.model, *work.variational, setup.dt, setup.coef.data(), q, qd, tau, fext);
      if (r.failed_dof >= 0) work.failure = r.failure;
      return r.failed_dof;
    }
  }
  template <std::size_t... K>
  static constexpr std::array<StepFn, sizeof...(K)> make_variational_table(std::index_sequence<K...>) {
    return {&variational_step_one<sim::host_joint_effect_set(unsigned(K))>...};
  }
  static const std::array<StepFn, sim::kEffectSets>& variational_table() {
    static const auto t = make_variational_table(std::make_index_sequence<sim::kEffectSets>{});
    return t;
  }

  // ---- prescribed joint motion and closed loops ----

  // The step of a scene with closed loops or prescribed joints (never both).
  template <unsigned E, Integrator I>
  static Index constrained_step_one(const SimSetup<S>& setup, Work& w, S* q, S* qd, const S* tau,
                                    const Force<S>* fext, sim::ContactReading<S>* readings) {
    return setup.loops.empty() ? driven_step_one<E, I>(setup, w, q, qd, tau, fext, readings)
                               : loop_step_one<E, I>(setup, w, q, qd, tau, fext, readings);
  }

  // Writes the driven DoFs' q, qd and qdd at time t (q, qd: the instance's arrays;
  // qdd: hybrid_dynamics's qdd_in).
  static void drive(const SimSetup<S>& setup, double t, S* q, S* qd, S* qdd) {
    for (std::size_t j = 0; j < setup.prescribed.dofs.size(); ++j) {
      double pq, pqd, pqdd;
      setup.prescribed.trajectory[j].eval(t, pq, pqd, pqdd);
      const Index i = setup.prescribed.dofs[j];
      q[i] = S(pq), qd[i] = S(pqd);
      if (qdd) qdd[i] = S(pqdd);
    }
  }

  // One instance's step with closed loops: step_instance over the constrained forward
  // dynamics (double), then the state projected onto the loops (positions by
  // Levenberg-Marquardt around Gauss-Newton to 1e-12, at most 10 linearisations:
  // Gauss-Newton from a step's drift; velocities to J qd = 0, minimum-norm changes):
  // dense, or through the setup's sparse loop solver (scandyn/sim/sparse_loops.hpp).
  // A projection that leaves the state more than kLoopStateTolerance off its loops
  // fails the step (Failure::LoopNotClosed).
  template <unsigned E, Integrator I>
  static Index loop_step_one(const SimSetup<S>& setup, Work& w, S* q, S* qd, const S* tau, const Force<S>* fext,
                             sim::ContactReading<S>* readings) {
    const Model& model = setup.loop_model;
    const Index n = model.nv();
    std::vector<Force<double>>& f = w.loop_fext;
    w.loop_lambda.resize(static_cast<std::size_t>(setup.loops.rows()));
    // the sparse path: this thread's solver, its symbolic analysis done once
    if (setup.loop_solver && !w.loop_sparse) w.loop_sparse = setup.loop_solver(model, setup.loops);
    auto fd = [&](const S* qa, const S* qda, const S* t, const S*, S* qdd) -> Index {
      // the external and contact wrenches at the stage (no armature: loops refuse implicit)
      const Force<S>* const fs = with_contacts<E>(setup, w, qa, qda, fext, nullptr, readings).first;
      f.clear();
      if (fs)
        for (Index i = 0; i < n; ++i) f.push_back(fs[i].template cast<double>());
      for (Index i = 0; i < n; ++i) w.loop_q[i] = qa[i], w.loop_qd[i] = qda[i], w.loop_tau[i] = t[i];
      try {
        if (w.loop_sparse)  // no wrenches here: the simulator gives the sparse path none
          w.loop_sparse->forward_dynamics(w.loop_q.data(), w.loop_qd.data(), w.loop_tau.data(), w.loop_qdd.data(),
                                          w.loop_lambda.data());
        else
          constrained_forward_dynamics(model, setup.loops, w.loop_q.data(), w.loop_qd.data(), w.loop_tau.data(),
                                       w.loop_qdd.data(), w.loop_lambda.data(), f.empty() ? nullptr : f.data());
      } catch (const sim::LoopSolveNotConverged&) {  // the iterative solver's CG (LoopNotClosed)
        w.failure = Failure::LoopNotClosed;
        w.failure_estimate = INFINITY;
        return 0;
      } catch (const LoopError&) {
        return 0;  // the mass matrix is not positive definite
      }
      for (Index i = 0; i < n; ++i) qdd[i] = S(w.loop_qdd[i]);
      return -1;
    };
    const Index failed =
        sim::step_instance<E, I>(n, setup.dt, setup.coef.data(), static_cast<const S*>(nullptr), q, qd, tau, w.scratch, fd);
    if (failed >= 0) return failed;
    for (Index i = 0; i < n; ++i) w.loop_q[i] = q[i], w.loop_qd[i] = qd[i];
    LoopProjectionInfo info;
    try {
      if (w.loop_sparse) w.loop_sparse->project(w.loop_q.data(), w.loop_qd.data(), 1e-12, 10, &info);
      else project_to_loops(model, setup.loops, w.loop_q.data(), w.loop_qd.data(), 1e-12, 10, &info);
    } catch (const LoopError&) {  // the projection's factorisation failed
      w.failure = Failure::LoopNotClosed;
      w.failure_estimate = INFINITY;  // (the status says so rather than naming a loop)
      return 0;
    }
    // a projection that leaves the state off its loops (max |phi|, |J qd| above
    // kLoopStateTolerance, the tolerance a reset or `eval --loops` refuses a state
    // by; or not finite) fails the step: the instance keeps its state, the status
    // names it and its worst loop
    const double off = info.violation();
    if (!(off <= kLoopStateTolerance)) {
      w.failure = Failure::LoopNotClosed;
      w.failure_estimate = off;
      Index loop = 0;
      for (Index row = 0; loop < static_cast<Index>(setup.loops.loops.size()); ++loop) {
        row += setup.loops.loops[loop].rows();
        if (info.worst_row < row) break;
      }
      return loop;
    }
    for (Index i = 0; i < n; ++i) q[i] = S(w.loop_q[i]), qd[i] = S(w.loop_qd[i]);
    return -1;
  }

  // One instance's step with driven DoFs: step_instance over the hybrid dynamics.
  // Each forward dynamics (rk4: its stages at t, t + dt/2, t + dt/2, t + dt) sees the
  // driven DoFs on their trajectories at the stage's time, with their trajectory's
  // acceleration; the other DoFs integrate as without driving. After the step the
  // driven DoFs are put on their trajectories at t + dt exactly.
  template <unsigned E, Integrator I>
  static Index driven_step_one(const SimSetup<S>& setup, Work& work, S* q, S* qd, const S* tau, const Force<S>* fext,
                               sim::ContactReading<S>* readings) {
    const ModelTpl<S>& model = setup.model;
    const Index n = model.nv();
    DataTpl<S>& data = work.data;
    const StepScratch<S>& w = work.scratch;
    S* const driven = work.driven.data();
    S* const qs = driven;          // the stage state with the driven DoFs on their trajectories
    S* const qds = driven + n;
    S* const qdd_in = driven + 2 * n;
    S* const tau_out = driven + 3 * n;
    const double dt = double(setup.dt);
    int stage = 0;
    auto fd = [&](const S* qa, const S* qda, const S* t, const S* armature, S* qdd) -> Index {
      const double offset = I == Integrator::Rk4 ? (stage == 0 ? 0.0 : stage == 3 ? dt : 0.5 * dt) : 0.0;
      ++stage;
      std::copy(qa, qa + n, qs);
      std::copy(qda, qda + n, qds);
      drive(setup, setup.time + offset, qs, qds, qdd_in);
      // the contacts where the driven DoFs are
      const auto [f, a] = with_contacts<E>(setup, work, qs, qds, fext, armature, readings);
      return hybrid_dynamics(model, data, qs, qds, setup.prescribed_mask.data(), qdd_in, t, qdd, tau_out, f, a)
          .failed_dof;
    };
    const Index failed = sim::step_instance<E, I>(n, setup.dt, setup.coef.data(),
                                                  setup.armature.empty() ? nullptr : setup.armature.data(), q, qd,
                                                  tau, w, fd);
    if (failed < 0) drive(setup, setup.time + dt, q, qd, nullptr);
    return failed;
  }

  template <std::size_t... K>
  static constexpr std::array<StepFn, sizeof...(K)> make_constrained_table(std::index_sequence<K...>) {
    return {&constrained_step_one<sim::host_step_set(unsigned(K % sim::kEffectSets)), Integrator(K / sim::kEffectSets)>...};
  }
  static const std::array<StepFn, sim::kIntegrators * sim::kEffectSets>& constrained_table() {
    static const auto t = make_constrained_table(std::make_index_sequence<sim::kIntegrators * sim::kEffectSets>{});
    return t;
  }

  std::vector<Work> work_;   // one per thread
  std::vector<int> failed_;     // (B) this step's failed DoF per instance, -1: none
  std::vector<int> nonfinite_;  // (B) the first DoF whose new state is not finite, -1: none
  std::vector<Failure> what_;   // (B) what this step's failure of the instance was
  std::vector<double> estimate_;  // (B) LoopNotClosed: the instance's loop violation after the projection
  StepFn step_ = nullptr;  // the effect set's and integrator's step (constrained_step_one with prescribed motion or loops)
};

// ---- per forward dynamics ---------------------------------------------------------

// The steps of kernels/simulator_step.cu's engine path on the host: the per-DoF formulas
// of scandyn/sim/integrators.hpp over entries k = i * B + b, split over the
// threads in blocks, around the forward-dynamics engine's batched compute().
template <class S>
class CpuEngineStep final : public CpuSimState<S> {
  using Base = CpuSimState<S>;
  using Base::setup_, Base::threads_, Base::q_, Base::qd_, Base::wrenches_, Base::status_;

 public:
  CpuEngineStep(const SimSetup<S>& setup, BackendKind backend, int threads) : Base(setup, backend, threads) {
    if (setup.integrator == Integrator::Implicit)
      throw BackendError(std::string("backend '") + to_string(backend) +
                         "': the simulator's step through the forward-dynamics engine runs euler and rk4 (the "
                         "parallel chain forward dynamics takes no armature); implicit steps per instance");
    BackendOptions o;
    o.backend = backend;
    o.fd_method = FdMethod::Parallel;
    o.threads = threads;
    o.max_batch = std::max<Index>(setup.batch, 1);
    fd_ = make_forward_dynamics<S>(setup.model, o);
    const std::size_t count = static_cast<std::size_t>(setup.model.nv()) * static_cast<std::size_t>(setup.batch);
    tau_.assign(count, S(0));
    qdd_.assign(count, S(0));
    if (setup.integrator == Integrator::Rk4) {
      for (std::vector<S>* a : {&qs_, &qds_, &aq_, &aqd_}) a->assign(count, S(0));
      bad_.assign(static_cast<std::size_t>(setup.batch), -1);
    }
    // the engine takes (B x nv) wrenches: the constant ones once per instance
    if ((setup.effects & sim::kExternal) && !setup.wrenches_per_step && setup.batch > 1) {
      expanded_.reserve(count);
      for (Index b = 0; b < setup.batch; ++b) expanded_.insert(expanded_.end(), setup.wrenches.begin(), setup.wrenches.end());
    }
    forces_ = forces_table()[setup.effects & sim::kJointEffects];
  }

  void step(const BatchView<const S>& tau) override {
    this->check_torques(tau);
    const Index B = setup_.batch, nv = setup_.model.nv();
    if (B == 0) return;
    const Index count = nv * B;
    const S dt = setup_.dt;
    const bool rk4 = setup_.integrator == Integrator::Rk4;
    S* const q = q_.data();
    S* const qd = qd_.data();
    S* const qs = rk4 ? qs_.data() : q;
    S* const qds = rk4 ? qds_.data() : qd;
    const S* const qdd = qdd_.data();
    // the effects at (qs, qds) into tau_, then the forward dynamics of the batch
    auto forward_dynamics = [&]() {
      forces_(*this, qs, qds, tau);
      const FdBatchIn<S> in{BatchView<const S>::soa(qs, nv, B), BatchView<const S>::soa(qds, nv, B),
                            BatchView<const S>::soa(tau_.data(), nv, B), fext()};
      return fd_->compute(in, BatchView<S>::soa(qdd_.data(), nv, B));
    };
    auto entries = [&](auto&& f) {  // f(k, b) for every entry k = i * B + b
      for_instance_blocks(threads_, count, [&](int, Index begin, Index end) {
        for (Index k = begin; k < end; ++k) f(k, k % B);
      });
    };
    if (!rk4) {
      const BatchStatus st = forward_dynamics();
      const int* failed = st.failed_dof;
      entries([&](Index k, Index b) {
        if (st.ok() || failed[b] < 0) sim::euler_update(dt, qdd[k], q[k], qd[k]);
      });
      if (!st.ok()) sim::add_step_failures(status_, st);
      record_non_finite(st.ok() ? nullptr : failed);
      return;
    }
    entries([&](Index k, Index) { sim::rk4_begin(q[k], qd[k], qs[k], qds[k], aq_[k], aqd_[k]); });
    std::fill(bad_.begin(), bad_.end(), -1);
    Failure failure = Failure::None;
    for (int s = 0; s < 4; ++s) {
      const BatchStatus st = forward_dynamics();
      if (!st.ok()) {  // an instance's first failing stage names its DoF
        for (Index b = 0; b < B; ++b)
          if (st.failed_dof[b] >= 0 && bad_[b] < 0) bad_[b] = st.failed_dof[b];
        failure = st.failure;
      }
      entries([&](Index k, Index) { sim::rk4_stage(s, dt, q[k], qd[k], qdd[k], qs[k], qds[k], aq_[k], aqd_[k]); });
    }
    const bool any = failure != Failure::None;
    entries([&](Index k, Index b) {
      if (!any || bad_[b] < 0) sim::rk4_finish(dt, aq_[k], aqd_[k], q[k], qd[k]);
    });
    if (any) sim::add_step_failures(status_, summarize_failures(bad_.data(), B, failure));
    record_non_finite(any ? bad_.data() : nullptr);
  }

  std::string strategy() const override { return std::string(to_string(this->backend_)) + "-engine-" + fd_->strategy(); }

 private:
  // After a step: each instance whose state has an entry that is not finite, with
  // its first such DoF, into the status (Failure::NonFinite); instances whose forward
  // dynamics failed (failed[b] >= 0, failed may be null) kept their state and are
  // already recorded.
  void record_non_finite(const int* failed) {
    const Index B = setup_.batch, nv = setup_.model.nv();
    const S* const q = q_.data();
    const S* const qd = qd_.data();
    nonfinite_.assign(static_cast<std::size_t>(B), -1);
    Index found = 0;
    for_instance_blocks(threads_, B, [&](int, Index begin, Index end) {
      Index local = 0;
      for (Index b = begin; b < end; ++b)
        for (Index i = 0; i < nv && !(failed && failed[b] >= 0); ++i) {
          const std::size_t k = static_cast<std::size_t>(i) * B + b;
          if (!(std::isfinite(q[k]) && std::isfinite(qd[k]))) {
            nonfinite_[static_cast<std::size_t>(b)] = static_cast<int>(i);
            ++local;
            break;
          }
        }
      if (local > 0) {
#pragma omp atomic
        found += local;
      }
    });
    if (found > 0) sim::add_step_failures(status_, summarize_failures(nonfinite_.data(), B, Failure::NonFinite));
  }

  // the (B x nv) wrenches the engine reads, null without external wrenches
  const Force<S>* fext() const {
    if (!(setup_.effects & sim::kExternal)) return nullptr;
    if (!wrenches_.empty()) return wrenches_.data();
    return expanded_.empty() ? setup_.wrenches.data() : expanded_.data();
  }

  // tau_ = tau + the joint effects' forces at (qs, qds), effect set E
  template <unsigned E>
  static void forces(CpuEngineStep& self, const S* qs, const S* qds, const BatchView<const S>& tau) {
    const Index B = self.setup_.batch, count = self.setup_.model.nv() * B;
    const JointCoefficients<S>* coef = self.setup_.coef.data();
    S* const out = self.tau_.data();
    for_instance_blocks(self.threads_, count, [&](int, Index begin, Index end) {
      for (Index k = begin; k < end; ++k) {
        const Index i = k / B, b = k % B;
        out[k] = sim::effect_forces<E>(tau.data ? tau.at(i, b) : S(0), coef[i], qs[k], qds[k], S(0));
      }
    });
  }
  using ForcesFn = void (*)(CpuEngineStep&, const S*, const S*, const BatchView<const S>&);
  // every joint-effect set (effects & kJointEffects: 8 values of the bits 2, 4, 8)
  template <std::size_t... K>
  static constexpr std::array<ForcesFn, sizeof...(K)> make_forces_table(std::index_sequence<K...>) {
    return {&forces<sim::host_joint_effect_set(unsigned(K)) & sim::kJointEffects>...};
  }
  static const std::array<ForcesFn, sim::kJointEffects + 1>& forces_table() {
    static const auto t = make_forces_table(std::make_index_sequence<sim::kJointEffects + 1>{});
    return t;
  }

  std::unique_ptr<ForwardDynamics<S>> fd_;  // the parallel chain forward dynamics
  ForcesFn forces_ = nullptr;
  std::vector<S> tau_, qdd_;                // (nv x B) tau + effects, the forward dynamics' result
  std::vector<S> qs_, qds_, aq_, aqd_;      // (nv x B) rk4: stage state, weighted sums
  std::vector<int> bad_;                    // (B) rk4: the DoF of an instance's first failed stage, -1: none
  std::vector<int> nonfinite_;            // (B) the first DoF whose new state is not finite, -1: none
  std::vector<Force<S>> expanded_;          // (B x nv) the constant wrenches per instance (B > 1)
};

}  // namespace

template <class S>
bool steps_per_forward_dynamics(const SimSetup<S>& setup, BackendKind backend, int threads) {
  // models with multi-DoF joints step per instance (step_instance_at; the engine
  // path integrates per DoF in R^n)
  return backend == BackendKind::OpenMP && setup.integrator != Integrator::Implicit &&
         setup.integrator != Integrator::Variational && (setup.effects & sim::kContacts) == 0 &&
         setup.prescribed.empty() && setup.loops.empty() &&
         !setup.model.multi_dof() &&  // CpuEngineStep integrates per DoF (a free rope's FD is parallel too)
         choose_fd_method(backend, setup.model, setup.batch, threads) == FdMethod::Parallel;
}

template <class S>
std::unique_ptr<sim::detail::SimBackend<S>> make_simulator_step(const SimSetup<S>& setup, BackendKind backend) {
  BackendOptions o;
  o.backend = backend;
  o.threads = setup.threads;
  const int threads = engine_threads(o);
  if (steps_per_forward_dynamics(setup, backend, threads))
    return std::make_unique<CpuEngineStep<S>>(setup, backend, threads);
  // no more threads than instances: each thread steps whole instances
  return std::make_unique<CpuInstanceStep<S>>(setup, backend, std::max(1, std::min<int>(threads, std::max<Index>(1, setup.batch))));
}

#define SCANDYN_INSTANTIATE(S)                                                                          \
  template bool steps_per_forward_dynamics(const SimSetup<S>&, BackendKind, int);                      \
  template std::unique_ptr<sim::detail::SimBackend<S>> make_simulator_step(const SimSetup<S>&, BackendKind);
SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)
#undef SCANDYN_INSTANTIATE

}  // namespace cpu
}  // namespace scandyn
