// scandyn/sim/step_derivatives.hpp: derivatives of the simulator's step, for
// differentiable simulation: the step's Jacobian d(q, qd)_{t+1} / d(q, qd, tau)_t,
// its directional derivative (JVP) and adjoint (VJP), and the adjoint of a whole
// rollout (the gradient of a loss on the trajectory with respect to the initial
// state and every torque).
//
// The step differentiated is the simulator's own (scandyn/sim/integrators.hpp):
//   euler     qdd = FD(q, qd, tau + tau_e(q, qd)), qd' = qd + dt qdd, q' = q + dt qd'
//   implicit  the same with the armature dt d + dt^2 k on M's diagonal and the springs
//             looking h = dt ahead
//   rk4       four stages x_s = x + c_s k_{s-1}, k_s = (qd_s, qdd(x_s)), x' = x +
//             dt/6 (k1 + 2 k2 + 2 k3 + k4)
// Every integrator formula is linear in (q, qd, qdd, stage values), so the tangent
// of a step applies the SAME formulas (euler_update, rk4_begin / rk4_stage /
// rk4_finish) to the tangents, with the tangent of qdd from the forward-dynamics
// derivatives (Carpentier & Mansard 2018; scandyn/instance/dynamics_derivatives.hpp):
//   dqdd = A_q dq + A_qd dqd + A_tau dtau,
//   A_tau = (M + diag(armature))^-1, A_q = dqdd/dq + A_tau diag(de/dq),
//   A_qd = dqdd/dqd + A_tau diag(de/dqd)
// (e: the joint effects' force, joint_effect_force; its partials are diagonal,
// joint_effect_partials). The dense Jacobian applies them to the columns of the
// identity (step_jacobian_instance); the JVP to one tangent (step_jvp_instance);
// the VJP is the transposed recursion (step_vjp_instance: the stages in reverse).
//
// What is covered: every integrator (euler, rk4, implicit), the effects gravity,
// damping, springs, limits (the derivative of the branch the state is on: exact away
// from the limit itself, where the penalty force has a kink) and external wrenches
// (constant in their body frames over the step, not differentiated). Joints:
// revolute and prismatic on every backend (serial, openmp and cuda: the Jacobian
// scandyn/cuda/step_derivatives.hpp, the rollouts scandyn/cuda/rollout_derivatives.hpp,
// models of up to 64 DoF); multi-DoF joints (a floating base, spherical joints) on
// serial and openmp: the step on the configuration manifold (step_instance_at) and
// its Jacobian in the tangent of local increments, q ⊕ d = q exp(d)
// (step_jacobian_at_instance, scandyn/sim/manifold_step_derivatives.hpp); their
// rollouts' JVP and VJP in O(nv) per step (step_jvp_at_instance / step_vjp_at_instance,
// the same header, over aba_jvp / aba_vjp's general path). Refused by name
// (BackendError from the factories and constructors): contacts, prescribed joint
// motion, closed loops, and multi-DoF joints on cuda.
#pragma once

#include <cmath>
#include <memory>
#include <string>
#include <vector>

#include "scandyn/instance/dynamics_derivatives.hpp"
#include "scandyn/sim/simulator.hpp"

namespace scandyn {
namespace sim {

// ---- per DoF -------------------------------------------------------------------

// The partial derivatives of joint_effect_force<kEffects>(c, q, qd, h) (effects.hpp)
// with respect to q (dq) and qd (dqd): -k and -d - h k of springs and damping, and
// -kl, -dl of a limit the joint is beyond.
template <unsigned kEffects, class S>
SCANDYN_HD void joint_effect_partials(const JointCoefficients<S>& c, S q, S qd, S h, S& dq, S& dqd) {
  dq = S(0);
  dqd = S(0);
  if constexpr ((kEffects & kDamping) != 0) dqd -= c.damping;
  if constexpr ((kEffects & kSprings) != 0) {
    dq -= c.stiffness;
    dqd -= h * c.stiffness;
  }
  if constexpr ((kEffects & kLimits) != 0) {
    if (q < c.lower || q > c.upper) {
      dq -= c.limit_stiffness;
      dqd -= c.limit_damping;
    }
  }
  (void)c, (void)q, (void)qd, (void)h;
}

// The forces the forward dynamics of one stage receives, tau_out = tau + e(q, qd)
// (effect_forces, the simulator's), and when eq is not null the partials of e.
template <unsigned kEffects, class S>
SCANDYN_HD void stage_forces(Index n, const JointCoefficients<S>* coef, const S* tau, const S* q, const S* qd, S h,
                             S* tau_out, S* eq, S* eqd) {
  for (Index i = 0; i < n; ++i) {
    tau_out[i] = (kEffects & kJointEffects) != 0 ? effect_forces<kEffects>(tau[i], coef[i], q[i], qd[i], h) : tau[i];
    if (eq) joint_effect_partials<kEffects>(coef[i], q[i], qd[i], h, eq[i], eqd[i]);
  }
}

// The adjoint of rk4_stage (integrators.hpp) for stage s: given the adjoints of
// what the stage wrote (gaq, gaqd of the weighted sums, unchanged by the stage;
// gqs, gqds of the next stage's state, consumed), adds the adjoints of what it
// read: gq, gqd (the step's start state) += gqs, gqds; returns through gv and ga the
// adjoints of the stage's slope (qds_s, qdd_s).
template <class S>
SCANDYN_HD void rk4_stage_adjoint(int s, S dt, S gaq, S gaqd, S gqs, S gqds, S& gq, S& gqd, S& gv, S& ga) {
  const S weight = (s == 0 || s == 3) ? S(1) : S(2);
  const S c = s < 2 ? S(0.5) * dt : dt;
  gq += gqs;
  gqd += gqds;
  gv = weight * gaq + c * gqs;
  ga = weight * gaqd + c * gqds;
}

// ---- the dense step Jacobian of one instance ------------------------------------

// The six nv x nv blocks of d(q', qd') / d(q, qd, tau).
template <class S>
struct StepJacobian {
  MatrixRef<S> q_q, q_qd, q_tau;     // d q' / d q, d q' / d qd, d q' / d tau
  MatrixRef<S> qd_q, qd_qd, qd_tau;  // d qd' / d q, ...
};

// A stage's forward-dynamics derivatives through the joint effects' forces: the stage's
// forward dynamics reads tau + e(q, qd), so A_q += A_tau diag(eq) and A_qd += A_tau
// diag(eqd) (eq, eqd: e's diagonal partials, stage_forces / stage_forces_at). A: A_q,
// A_qd, A_tau (n x n each).
template <unsigned kEffects, class S>
SCANDYN_HD void add_effect_partials(Index n, const MatrixRef<S>* A, const S* eq, const S* eqd) {
  if constexpr ((kEffects & kJointEffects) != 0)
    for (Index i = 0; i < n; ++i)
      for (Index j = 0; j < n; ++j) {
        A[0](i, j) += A[2](i, j) * eq[j];
        A[1](i, j) += A[2](i, j) * eqd[j];
      }
  (void)n, (void)A, (void)eq, (void)eqd;
}

// Scalars of scratch step_jacobian_instance needs for n DoF.
inline std::size_t step_jacobian_scratch(Index n, Integrator integrator) {
  const std::size_t m = static_cast<std::size_t>(n);
  return 8 * m + (integrator == Integrator::Rk4 ? 12 : 3) * m * m;
}

// One step of one instance with its Jacobian: q and qd (n each) advance by dt in
// place under tau exactly as step_instance advances them (the same functions in
// the same order), and J receives d(q', qd') / d(q, qd, tau) at the start state.
// fd(q, qd, tau, armature, qdd) -> Index as step_instance's; dfd(q, qd, qdd,
// armature, Fq, Fqd, Ft) -> Index writes the forward-dynamics derivatives at qdd
// (fd_derivatives_instance). scratch: step_jacobian_scratch(n, kIntegrator)
// scalars. Returns -1, or the DoF whose pivot failed (q, qd then unchanged).
template <unsigned kEffects, Integrator kIntegrator, class S, class Fd, class Dfd>
SCANDYN_HD Index step_jacobian_instance(Index n, S dt, const JointCoefficients<S>* coef, const S* armature, S* q,
                                        S* qd, const S* tau, S* scratch, const StepJacobian<S>& J, Fd&& fd,
                                        Dfd&& dfd) {
  const std::size_t m = static_cast<std::size_t>(n), nn = m * m;
  S* const tau_s = scratch;
  S* const qdd = scratch + m;
  S* const qs = scratch + 2 * m;
  S* const qds = scratch + 3 * m;
  S* const aq = scratch + 4 * m;
  S* const aqd = scratch + 5 * m;
  S* const eq = scratch + 6 * m;
  S* const eqd = scratch + 7 * m;
  S* const mat = scratch + 8 * m;
  // A[0..2]: A_q, A_qd, A_tau of a stage (row-major)
  const MatrixRef<S> A[3] = {{mat, n, 1}, {mat + nn, n, 1}, {mat + 2 * nn, n, 1}};
  auto one = [](Index i, Index j) { return i == j ? S(1) : S(0); };
  // the stage's forward dynamics and A at (qa, qda): returns the failed DoF or -1
  auto stage = [&](const S* qa, const S* qda, S h, const S* arm) -> Index {
    stage_forces<kEffects>(n, coef, tau, qa, qda, h, tau_s, eq, eqd);
    Index failed = fd(qa, qda, static_cast<const S*>(tau_s), arm, qdd);
    if (failed >= 0) return failed;
    failed = dfd(qa, qda, static_cast<const S*>(qdd), arm, A[0], A[1], A[2]);
    if (failed >= 0) return failed;
    add_effect_partials<kEffects>(n, A, eq, eqd);
    return -1;
  };
  const MatrixRef<S> Jq[3] = {J.q_q, J.q_qd, J.q_tau}, Jqd[3] = {J.qd_q, J.qd_qd, J.qd_tau};

  if constexpr (kIntegrator == Integrator::Rk4) {
    // the stage state's derivatives D (dqs/dz, dqds/dz) and the stage's dqdd/dz (K),
    // z = (q, qd, tau): three n x n blocks each; the weighted sums in J
    S* const dmat = mat + 3 * nn;
    MatrixRef<S> Dq[3], Dqd[3], K[3];
    for (int b = 0; b < 3; ++b) {
      Dq[b] = {dmat + b * nn, n, 1};
      Dqd[b] = {dmat + (3 + b) * nn, n, 1};
      K[b] = {dmat + (6 + b) * nn, n, 1};
    }
    for (Index i = 0; i < n; ++i) rk4_begin(q[i], qd[i], qs[i], qds[i], aq[i], aqd[i]);
    for (int b = 0; b < 3; ++b)
      for (Index i = 0; i < n; ++i)
        for (Index j = 0; j < n; ++j)
          rk4_begin(b == 0 ? one(i, j) : S(0), b == 1 ? one(i, j) : S(0), Dq[b](i, j), Dqd[b](i, j), Jq[b](i, j),
                    Jqd[b](i, j));
    for (int s = 0; s < 4; ++s) {
      const Index failed = stage(qs, qds, S(0), static_cast<const S*>(nullptr));
      if (failed >= 0) return failed;
      // K_b = A_q Dq_b + A_qd Dqd_b (+ A_tau for b = tau), by rows (contiguous, vectorised);
      // at stage 0 (Dq, Dqd) = ([1 0 0], [0 1 0]): K_b = A_b exactly
      for (int b = 0; b < 3; ++b)
        for (Index i = 0; i < n; ++i) {
          for (Index j = 0; j < n; ++j) K[b](i, j) = (s == 0 || b == 2) ? A[b](i, j) : S(0);
          if (s == 0) continue;
          for (Index l = 0; l < n; ++l) {
            const S a0 = A[0](i, l), a1 = A[1](i, l);
            for (Index j = 0; j < n; ++j) K[b](i, j) += a0 * Dq[b](l, j) + a1 * Dqd[b](l, j);
          }
        }
      for (int b = 0; b < 3; ++b)
        for (Index i = 0; i < n; ++i)
          for (Index j = 0; j < n; ++j)
            rk4_stage(s, dt, b == 0 ? one(i, j) : S(0), b == 1 ? one(i, j) : S(0), K[b](i, j), Dq[b](i, j),
                      Dqd[b](i, j), Jq[b](i, j), Jqd[b](i, j));
      for (Index i = 0; i < n; ++i) rk4_stage(s, dt, q[i], qd[i], qdd[i], qs[i], qds[i], aq[i], aqd[i]);
    }
    for (int b = 0; b < 3; ++b)
      for (Index i = 0; i < n; ++i)
        for (Index j = 0; j < n; ++j) {
          S sq = Jq[b](i, j), sqd = Jqd[b](i, j);
          Jq[b](i, j) = b == 0 ? one(i, j) : S(0);
          Jqd[b](i, j) = b == 1 ? one(i, j) : S(0);
          rk4_finish(dt, sq, sqd, Jq[b](i, j), Jqd[b](i, j));
        }
    for (Index i = 0; i < n; ++i) rk4_finish(dt, aq[i], aqd[i], q[i], qd[i]);
    return -1;
  } else {
    constexpr bool kImplicit = kIntegrator == Integrator::Implicit && (kEffects & kImplicitEffects) != 0;
    const Index failed = stage(q, qd, kImplicit ? dt : S(0), kImplicit ? armature : static_cast<const S*>(nullptr));
    if (failed >= 0) return failed;
    for (int b = 0; b < 3; ++b)
      for (Index i = 0; i < n; ++i)
        for (Index j = 0; j < n; ++j) {
          Jq[b](i, j) = b == 0 ? one(i, j) : S(0);
          Jqd[b](i, j) = b == 1 ? one(i, j) : S(0);
          euler_update(dt, A[b](i, j), Jq[b](i, j), Jqd[b](i, j));
        }
    for (Index i = 0; i < n; ++i) euler_update(dt, qdd[i], q[i], qd[i]);
    return -1;
  }
}

// ---- directional derivatives of one instance's step (O(nv) each) ------------------

// Scalars of scratch step_jvp_instance and step_vjp_instance need for n DoF.
inline std::size_t step_directional_scratch(Index n) { return 32 * static_cast<std::size_t>(n); }

// One step with its tangent: (q, qd) advance as step_instance advances them, and
// (dq, dqd) (n each, in place) become the tangent of the new state along (dq, dqd,
// dtau). fd_jvp(q, qd, tau, dq, dqd, dtau, armature, dqdd, qdd) -> Index writes
// qdd = FD(q, qd, tau) (the step's forward dynamics) and its tangent dqdd (aba_jvp).
// Returns -1 or the failed DoF.
template <unsigned kEffects, Integrator kIntegrator, class S, class FdJvp>
SCANDYN_HD Index step_jvp_instance(Index n, S dt, const JointCoefficients<S>* coef, const S* armature, S* q, S* qd,
                        const S* tau, S* dq, S* dqd, const S* dtau, S* scratch, FdJvp&& fd_jvp) {
  const std::size_t m = static_cast<std::size_t>(n);
  S* const r = scratch;
  S *tau_s = r, *qdd = r + m, *qs = r + 2 * m, *qds = r + 3 * m, *aq = r + 4 * m, *aqd = r + 5 * m, *eq = r + 6 * m,
    *eqd = r + 7 * m, *dtau_s = r + 8 * m, *dqdd = r + 9 * m, *dqs = r + 10 * m, *dqds = r + 11 * m,
    *daq = r + 12 * m, *daqd = r + 13 * m;
  // the stage's qdd and dqdd at (qa, qda) with tangent (dqa, dqda)
  auto stage = [&](const S* qa, const S* qda, const S* dqa, const S* dqda, S h, const S* arm) -> Index {
    stage_forces<kEffects>(n, coef, tau, qa, qda, h, tau_s, eq, eqd);
    for (Index i = 0; i < n; ++i) dtau_s[i] = dtau[i] + eq[i] * dqa[i] + eqd[i] * dqda[i];
    return fd_jvp(qa, qda, static_cast<const S*>(tau_s), dqa, dqda, static_cast<const S*>(dtau_s), arm, dqdd, qdd);
  };
  if constexpr (kIntegrator == Integrator::Rk4) {
    for (Index i = 0; i < n; ++i) {
      rk4_begin(q[i], qd[i], qs[i], qds[i], aq[i], aqd[i]);
      rk4_begin(dq[i], dqd[i], dqs[i], dqds[i], daq[i], daqd[i]);
    }
    for (int s = 0; s < 4; ++s) {
      const Index failed = stage(qs, qds, dqs, dqds, S(0), nullptr);
      if (failed >= 0) return failed;
      for (Index i = 0; i < n; ++i) {
        rk4_stage(s, dt, q[i], qd[i], qdd[i], qs[i], qds[i], aq[i], aqd[i]);
        rk4_stage(s, dt, dq[i], dqd[i], dqdd[i], dqs[i], dqds[i], daq[i], daqd[i]);
      }
    }
    for (Index i = 0; i < n; ++i) {
      rk4_finish(dt, aq[i], aqd[i], q[i], qd[i]);
      rk4_finish(dt, daq[i], daqd[i], dq[i], dqd[i]);
    }
  } else {
    constexpr bool kImplicit = kIntegrator == Integrator::Implicit && (kEffects & kImplicitEffects) != 0;
    const Index failed = stage(q, qd, dq, dqd, kImplicit ? dt : S(0), kImplicit ? armature : nullptr);
    if (failed >= 0) return failed;
    for (Index i = 0; i < n; ++i) {
      euler_update(dt, qdd[i], q[i], qd[i]);
      euler_update(dt, dqdd[i], dq[i], dqd[i]);
    }
  }
  return -1;
}

// The adjoint of one step at (q, qd, tau): gq, gqd (n each, in place) hold the
// adjoints of the new state (q', qd') and become those of (q, qd); gtau (n) gets the
// torques' (written, not accumulated). q and qd are not changed. fd(q, qd, tau,
// armature, qdd) -> Index as step_instance's (the stages are run forward first);
// fd_vjp(q, qd, tau, armature, w, gq, gqd, gtau) -> Index writes the adjoint of
// qdd = FD(q, qd, tau) for the weight w on qdd (aba_vjp). Returns -1 or the failed DoF.
template <unsigned kEffects, Integrator kIntegrator, class S, class Fd, class FdVjp>
SCANDYN_HD Index step_vjp_instance(Index n, S dt, const JointCoefficients<S>* coef, const S* armature, const S* q,
                        const S* qd, const S* tau, S* gq, S* gqd, S* gtau, S* scratch, Fd&& fd, FdVjp&& fd_vjp) {
  const std::size_t m = static_cast<std::size_t>(n);
  S* const r = scratch;
  // stage states (rk4: 4 of them), the forward's rows, the reverse's rows
  S *stq = r, *stqd = r + 4 * m, *tau_s = r + 8 * m, *qdd = r + 9 * m, *aq = r + 10 * m, *aqd = r + 11 * m,
    *eq = r + 12 * m, *eqd = r + 13 * m, *w = r + 14 * m, *a = r + 15 * m, *b = r + 16 * m, *gt = r + 17 * m,
    *gqs = r + 18 * m, *gqds = r + 19 * m, *gv = r + 20 * m, *qn = r + 21 * m, *qdn = r + 22 * m,
    *gaq = r + 23 * m, *gaqd = r + 24 * m;
  // the adjoint of one stage's qdd = FD(qa, qda, tau + e(qa, qda)) for weight w:
  // adds to the stage state's adjoints (ga, gda) and to gtau
  auto stage_adjoint = [&](const S* qa, const S* qda, S h, const S* arm, S* ga, S* gda) -> Index {
    stage_forces<kEffects>(n, coef, tau, qa, qda, h, tau_s, eq, eqd);
    const Index failed = fd_vjp(qa, qda, static_cast<const S*>(tau_s), arm, static_cast<const S*>(w), a, b, gt);
    if (failed >= 0) return failed;
    for (Index i = 0; i < n; ++i) {
      ga[i] += a[i] + eq[i] * gt[i];
      gda[i] += b[i] + eqd[i] * gt[i];
      gtau[i] += gt[i];
    }
    return -1;
  };
  for (Index i = 0; i < n; ++i) gtau[i] = S(0);
  if constexpr (kIntegrator == Integrator::Rk4) {
    // forward: the four stage states
    for (Index i = 0; i < n; ++i) rk4_begin(q[i], qd[i], stq[i], stqd[i], aq[i], aqd[i]);
    for (int s = 0; s < 3; ++s) {
      S* const q_s = stq + s * m;
      S* const qd_s = stqd + s * m;
      stage_forces<kEffects>(n, coef, tau, q_s, qd_s, S(0), tau_s, static_cast<S*>(nullptr), static_cast<S*>(nullptr));
      const Index failed = fd(static_cast<const S*>(q_s), static_cast<const S*>(qd_s), static_cast<const S*>(tau_s),
                              static_cast<const S*>(nullptr), qdd);
      if (failed >= 0) return failed;
      for (Index i = 0; i < n; ++i) {
        qn[i] = q_s[i], qdn[i] = qd_s[i];
        rk4_stage(s, dt, q[i], qd[i], qdd[i], qn[i], qdn[i], aq[i], aqd[i]);
        stq[(s + 1) * m + i] = qn[i], stqd[(s + 1) * m + i] = qdn[i];
      }
    }
    // reverse: rk4_finish, then the stages 3..0 (gaq, gaqd: dt/6 of the new state's adjoints)
    const S sixth = dt / S(6);
    for (Index i = 0; i < n; ++i) {
      gaq[i] = sixth * gq[i];
      gaqd[i] = sixth * gqd[i];
      gqs[i] = gqds[i] = S(0);
    }
    for (int s = 3; s >= 0; --s) {
      for (Index i = 0; i < n; ++i) {
        rk4_stage_adjoint(s, dt, gaq[i], gaqd[i], gqs[i], gqds[i], gq[i], gqd[i], gv[i], w[i]);
        gqs[i] = S(0);
        gqds[i] = gv[i];
      }
      const Index failed = stage_adjoint(stq + s * m, stqd + s * m, S(0), nullptr, gqs, gqds);
      if (failed >= 0) return failed;
    }
    for (Index i = 0; i < n; ++i) gq[i] += gqs[i], gqd[i] += gqds[i];  // stage 0's state is (q, qd)
  } else {
    // qd' = qd + dt qdd, q' = q + dt qd': the adjoint of qd' is gqd + dt gq
    constexpr bool kImplicit = kIntegrator == Integrator::Implicit && (kEffects & kImplicitEffects) != 0;
    for (Index i = 0; i < n; ++i) {
      gqd[i] += dt * gq[i];
      w[i] = dt * gqd[i];
    }
    const Index failed = stage_adjoint(q, qd, kImplicit ? dt : S(0), kImplicit ? armature : nullptr, gq, gqd);
    if (failed >= 0) return failed;
  }
  return -1;
}

// ---- engines ---------------------------------------------------------------------

// The step Jacobian's outputs: six nv x nv matrices per instance, each a BatchView
// of nv * nv entries with entry i * nv + j = d y_i / d x_j (the derivative engines'
// layout, scandyn/engine.hpp), and optionally the new state.
template <class S>
struct StepDerivativesOut {
  BatchView<S> q_q, q_qd, q_tau;     // (nv * nv x B) d q' / d q, d q' / d qd, d q' / d tau
  BatchView<S> qd_q, qd_qd, qd_tau;  // (nv * nv x B) d qd' / d q, ...
  BatchView<S> q_next, qd_next;      // optional (nv x B): the new state (data null: not written)
};

// The Jacobian of one simulator step for every instance.
template <class S>
class StepDerivatives : public Engine {
 public:
  // in: the state (q, qd) and torques tau of every instance (nv x B); in.fext: the
  // (B x nbodies; nbodies = nv for 1-DoF joints) body wrenches of a scene whose external wrenches are per step, or null
  // for the scene's constant ones. An instance whose forward dynamics fails is
  // reported in the status, its outputs not meaningful.
  virtual BatchStatus compute(const FdBatchIn<S>& in, const StepDerivativesOut<S>& out) = 0;
  virtual const SimSetup<S>& setup() const = 0;
};

// The step derivatives of a simulator's setup (Simulator::setup(); copied) on
// options.backend: serial or openmp (threads over instances), or cuda (one thread
// per instance, models of up to cuda::kMaxThreadDofs DoF; scandyn/cuda/
// step_derivatives.hpp). Throws BackendError naming what is not covered (see the
// header comment).
template <class S>
std::unique_ptr<StepDerivatives<S>> make_step_derivatives(const SimSetup<S>& setup, const BackendOptions& options);

// Throws BackendError naming `what` and the first of the setup's features the step
// derivatives do not cover on `backend` (contacts, prescribed motion, loops; on cuda,
// the default: the CUDA engines' own check, multi-DoF joints too, naming the joint).
template <class S>
void require_differentiable_step(const SimSetup<S>& setup, const char* what, BackendKind backend = BackendKind::Cuda);

// A sequence of T per-step batches: step t's view is `first` moved by t *
// time_stride elements. A (T, B, nv) C array is {BatchView::aos(p, nv, B), B * nv, T}.
template <class T>
struct StepSequence {
  BatchView<T> first;
  std::ptrdiff_t time_stride = 0;
  Index steps = 0;  // T
  SCANDYN_HD BatchView<T> at(Index t) const {
    BatchView<T> v = first;
    v.data = first.data + t * time_stride;
    return v;
  }
};

// ---- rollouts of one instance ----------------------------------------------------------
// The instance loops of RolloutDerivatives: the serial / OpenMP engine (per-thread
// rows and store) and the CUDA kernels (per-thread local rows, a global store with
// the instance innermost; scandyn/cuda/rollout_derivatives.hpp) run these functions.
// Each returns -1, the DoF whose pivot failed (>= 0; the instance's outputs then
// partly written), or -2 - i when entry i of a result is not finite
// (rollout_failure_dof, Failure::NonFinite). rows: 8 n scalars of the caller's
// contiguous per-thread memory (the current state, the torques, tangents and
// adjoints of one step).

// n entries of instance b of v into row (converted; zeros where v is null), and back.
template <class S, class T>
SCANDYN_HD void load_instance_row(const BatchView<T>& v, Index b, Index n, S* row) {
  for (Index i = 0; i < n; ++i) row[i] = v.data ? S(v.at(i, b)) : S(0);
}
template <class S>
SCANDYN_HD void store_instance_row(const S* row, const BatchView<S>& v, Index b, Index n) {
  for (Index i = 0; i < n; ++i) v.at(i, b) = row[i];
}

// -1, or -2 - i for the lowest DoF i at which one of the rows (n entries each) is not finite.
template <class S, int kRows>
SCANDYN_HD Index rollout_nonfinite(const S* const (&rows)[kRows], Index n) {
  for (Index i = 0; i < n; ++i)
    for (int r = 0; r < kRows; ++r)
      if (!ScalarMath<S>::isfinite(rows[r][i])) return -2 - i;
  return -1;
}
// The DoF of a failure code of the functions below, and whether it is a result that is not finite.
inline Index rollout_failure_dof(Index code) { return code <= -2 ? -2 - code : code; }
inline bool rollout_failure_nonfinite(Index code) { return code <= -2; }

// The states a rollout's adjoint keeps per instance: 2 rows (q, qd) of n entries per
// state slot, row r's entry i at data[r * row_stride + i * dof_stride]. Slots 0 ..
// S-1: the checkpoints x_{kK} (S = ceil(T / K)); slots S .. S+K-1: one segment's
// states recomputed. The CPU: a thread's contiguous buffer (row_stride n, dof_stride
// 1); CUDA: a global buffer with the instance innermost (row_stride n B, dof_stride B,
// data offset by b).
template <class S>
struct StateStore {
  S* data;
  std::ptrdiff_t row_stride, dof_stride;
  SCANDYN_HD S& at(std::ptrdiff_t row, Index i) const { return data[row * row_stride + i * dof_stride]; }
  SCANDYN_HD void put(std::ptrdiff_t slot, const S* q, const S* qd, Index n) const {
    for (Index i = 0; i < n; ++i) at(2 * slot, i) = q[i], at(2 * slot + 1, i) = qd[i];
  }
  SCANDYN_HD void get(std::ptrdiff_t slot, S* q, S* qd, Index n) const {
    for (Index i = 0; i < n; ++i) q[i] = at(2 * slot, i), qd[i] = at(2 * slot + 1, i);
  }
  // a model with multi-DoF joints: q with nq entries (row_stride >= nq), qd with n
  SCANDYN_HD void put(std::ptrdiff_t slot, const S* q, const S* qd, Index nq, Index n) const {
    for (Index i = 0; i < nq; ++i) at(2 * slot, i) = q[i];
    for (Index i = 0; i < n; ++i) at(2 * slot + 1, i) = qd[i];
  }
  SCANDYN_HD void get(std::ptrdiff_t slot, S* q, S* qd, Index nq, Index n) const {
    for (Index i = 0; i < nq; ++i) q[i] = at(2 * slot, i);
    for (Index i = 0; i < n; ++i) qd[i] = at(2 * slot + 1, i);
  }
};

// Number of state slots of a rollout adjoint's store for T steps and checkpoint
// interval K: ceil(T / K) checkpoints and K segment states.
inline Index rollout_store_slots(Index T, Index K) { return (T + K - 1) / K + K; }

// The checkpoint interval K of a rollout adjoint over T steps for the interval asked
// for (0: ceil(sqrt(T)), which minimises the store; otherwise at most T).
inline Index rollout_checkpoint_interval(Index interval, Index T) {
  const Index t = T > 1 ? T : 1;
  if (interval > 0) return interval < t ? interval : t;
  Index k = static_cast<Index>(std::ceil(std::sqrt(static_cast<double>(t))));
  return k > 1 ? k : 1;
}

// Throw BackendError naming the view of a rollout call (T steps of B instances) whose
// shape does not fit: a state view (nv x B, required) or a step sequence (T steps of
// nv x B; null: not given, accepted).
template <class S>
void require_rollout_state(const char* name, const BatchView<S>& v, Index B) {
  if (!v.data || v.batch != B)
    throw BackendError(std::string("the rollout derivatives: ") + name + " must hold " + std::to_string(B) +
                       " instances");
}
template <class S>
void require_rollout_sequence(const char* name, const StepSequence<S>& s, Index T, Index B) {
  if (!s.first.data) return;
  if (s.steps != T || s.first.batch != B)
    throw BackendError(std::string("the rollout derivatives: ") + name + " has " + std::to_string(s.steps) +
                       " steps of " + std::to_string(s.first.batch) + " instances, expected " + std::to_string(T) +
                       " of " + std::to_string(B));
}

// Instance b's rollout from (q0, qd0) under tau (T = tau.steps): q.at(t), qd.at(t) =
// x_{t+1} (null sequences: not written). step(x, xd, u) -> Index advances (x, xd)
// in place (the simulator's step).
// rollout_instance_at: a model with multi-DoF joints, q (q0 and the q sequence)
// with nq entries per instance, rows 8 n + nq scalars (rollout_rows).
template <class S, class Step>
SCANDYN_HD Index rollout_instance_at(Index nq, Index n, Index b, const BatchView<const S>& q0,
                                     const BatchView<const S>& qd0, const StepSequence<const S>& tau,
                                     const StepSequence<S>& q, const StepSequence<S>& qd, S* rows, Step&& step) {
  S *x = rows, *xd = rows + nq, *u = rows + nq + n;
  load_instance_row(q0, b, nq, x), load_instance_row(qd0, b, n, xd);
  for (Index t = 0; t < tau.steps; ++t) {
    load_instance_row(tau.at(t), b, n, u);
    const Index failed = step(x, xd, static_cast<const S*>(u));
    if (failed >= 0) return failed;
    if (const Index bad = rollout_nonfinite<S, 2>({x, xd}, n); bad != -1) return bad;
    if (q.first.data) store_instance_row(static_cast<const S*>(x), q.at(t), b, nq);
    if (qd.first.data) store_instance_row(static_cast<const S*>(xd), qd.at(t), b, n);
  }
  return -1;
}
template <class S, class Step>
SCANDYN_HD Index rollout_instance(Index n, Index b, const BatchView<const S>& q0, const BatchView<const S>& qd0,
                                  const StepSequence<const S>& tau, const StepSequence<S>& q,
                                  const StepSequence<S>& qd, S* rows, Step&& step) {
  return rollout_instance_at(n, n, b, q0, qd0, tau, q, qd, rows, static_cast<Step&&>(step));
}

// Scalars of rows the rollout instance functions need (nq: the positions).
inline std::size_t rollout_rows(Index nq, Index n) {
  return 8 * static_cast<std::size_t>(n) + static_cast<std::size_t>(nq);
}

// Instance b's trajectory tangents along (dq0, dqd0, dtau) (null dtau: zero):
// dq.at(t), dqd.at(t) = dx_{t+1}. jvp(x, xd, u, dx, dxd, du) -> Index advances the
// state and its tangent in place (step_jvp_instance).
// (rollout_jvp_instance_at: q0 with nq entries, the tangents dq0, dq with n.)
template <class S, class Jvp>
SCANDYN_HD Index rollout_jvp_instance_at(Index nq, Index n, Index b, const BatchView<const S>& q0,
                                         const BatchView<const S>& qd0, const StepSequence<const S>& tau,
                                         const BatchView<const S>& dq0, const BatchView<const S>& dqd0,
                                         const StepSequence<const S>& dtau, const StepSequence<S>& dq,
                                         const StepSequence<S>& dqd, S* rows, Jvp&& jvp) {
  S *x = rows, *xd = rows + nq, *u = xd + n, *dx = xd + 2 * n, *dxd = xd + 3 * n, *du = xd + 4 * n;
  load_instance_row(q0, b, nq, x), load_instance_row(qd0, b, n, xd);
  load_instance_row(dq0, b, n, dx), load_instance_row(dqd0, b, n, dxd);
  for (Index t = 0; t < tau.steps; ++t) {
    load_instance_row(tau.at(t), b, n, u);
    load_instance_row(dtau.first.data ? dtau.at(t) : BatchView<const S>{}, b, n, du);
    const Index failed = jvp(x, xd, static_cast<const S*>(u), dx, dxd, static_cast<const S*>(du));
    if (failed >= 0) return failed;
    if (const Index bad = rollout_nonfinite<S, 2>({dx, dxd}, n); bad != -1) return bad;
    if (dq.first.data) store_instance_row(static_cast<const S*>(dx), dq.at(t), b, n);
    if (dqd.first.data) store_instance_row(static_cast<const S*>(dxd), dqd.at(t), b, n);
  }
  return -1;
}
template <class S, class Jvp>
SCANDYN_HD Index rollout_jvp_instance(Index n, Index b, const BatchView<const S>& q0, const BatchView<const S>& qd0,
                                      const StepSequence<const S>& tau, const BatchView<const S>& dq0,
                                      const BatchView<const S>& dqd0, const StepSequence<const S>& dtau,
                                      const StepSequence<S>& dq, const StepSequence<S>& dqd, S* rows, Jvp&& jvp) {
  return rollout_jvp_instance_at(n, n, b, q0, qd0, tau, dq0, dqd0, dtau, dq, dqd, rows, static_cast<Jvp&&>(jvp));
}

// Instance b's adjoint of the loss sum_t l_t(x_{t+1}) with gradients gq.at(t),
// gqd.at(t) (null: zero), checkpointed every K steps: forward, x_t stored for t a
// multiple of K (x_T is not needed); then segment by segment from the last, the
// segment's states again from its checkpoint (slots S.. of the store), and the
// steps' adjoints from its last step to its first: gtau.at(t) (null: not written),
// finally gq0, gqd0. step(x, xd, u) -> Index as rollout_instance's; vjp(x, xd, u,
// lq, lqd, gu) -> Index turns the adjoints (lq, lqd) of x_{t+1} into those of x_t
// and writes gu (step_vjp_instance). store: rollout_store_slots(T, K) slots.
// (rollout_vjp_instance_at: q0 and the stored positions with nq entries, the
// adjoints gq, gq0 with n: the tangents'.)
template <class S, class Step, class Vjp>
SCANDYN_HD Index rollout_vjp_instance_at(Index nq, Index n, Index b, Index K, const BatchView<const S>& q0,
                                         const BatchView<const S>& qd0, const StepSequence<const S>& tau,
                                         const StepSequence<const S>& gq, const StepSequence<const S>& gqd,
                                         const BatchView<S>& gq0, const BatchView<S>& gqd0,
                                         const StepSequence<S>& gtau, S* rows, const StateStore<S>& store,
                                         Step&& step, Vjp&& vjp) {
  const Index T = tau.steps, segments = (T + K - 1) / K;
  S *x = rows, *xd = rows + nq, *u = xd + n, *lq = xd + 2 * n, *lqd = xd + 3 * n, *gu = xd + 4 * n, *g = xd + 5 * n;
  // forward: the checkpoints
  load_instance_row(q0, b, nq, x), load_instance_row(qd0, b, n, xd);
  for (Index t = 0; t < T; ++t) {
    if (t % K == 0) store.put(t / K, x, xd, nq, n);
    if (t + 1 == T) break;  // the last state is not needed
    load_instance_row(tau.at(t), b, n, u);
    const Index failed = step(x, xd, static_cast<const S*>(u));
    if (failed >= 0) return failed;
  }
  // reverse: segment by segment, the segment's states again from its checkpoint
  for (Index i = 0; i < n; ++i) lq[i] = S(0), lqd[i] = S(0);
  for (Index k = segments - 1; k >= 0; --k) {
    const Index t0 = k * K, t1 = T < t0 + K ? T : t0 + K;
    store.get(k, x, xd, nq, n);
    store.put(segments, x, xd, nq, n);
    for (Index t = t0; t + 1 < t1; ++t) {
      load_instance_row(tau.at(t), b, n, u);
      const Index failed = step(x, xd, static_cast<const S*>(u));
      if (failed >= 0) return failed;
      store.put(segments + (t + 1 - t0), x, xd, nq, n);
    }
    for (Index t = t1 - 1; t >= t0; --t) {
      // the loss's gradient at x_{t+1}, then the step's adjoint at x_t
      if (gq.first.data) {
        load_instance_row(gq.at(t), b, n, g);
        for (Index i = 0; i < n; ++i) lq[i] += g[i];
      }
      if (gqd.first.data) {
        load_instance_row(gqd.at(t), b, n, g);
        for (Index i = 0; i < n; ++i) lqd[i] += g[i];
      }
      store.get(segments + (t - t0), x, xd, nq, n);
      load_instance_row(tau.at(t), b, n, u);
      const Index failed = vjp(static_cast<const S*>(x), static_cast<const S*>(xd), static_cast<const S*>(u), lq, lqd, gu);
      if (failed >= 0) return failed;
      if (const Index bad = rollout_nonfinite<S, 3>({lq, lqd, gu}, n); bad != -1) return bad;
      if (gtau.first.data) store_instance_row(static_cast<const S*>(gu), gtau.at(t), b, n);
    }
  }
  store_instance_row(static_cast<const S*>(lq), gq0, b, n);
  store_instance_row(static_cast<const S*>(lqd), gqd0, b, n);
  return -1;
}
template <class S, class Step, class Vjp>
SCANDYN_HD Index rollout_vjp_instance(Index n, Index b, Index K, const BatchView<const S>& q0,
                                      const BatchView<const S>& qd0, const StepSequence<const S>& tau,
                                      const StepSequence<const S>& gq, const StepSequence<const S>& gqd,
                                      const BatchView<S>& gq0, const BatchView<S>& gqd0, const StepSequence<S>& gtau,
                                      S* rows, const StateStore<S>& store, Step&& step, Vjp&& vjp) {
  return rollout_vjp_instance_at(n, n, b, K, q0, qd0, tau, gq, gqd, gq0, gqd0, gtau, rows, store,
                                 static_cast<Step&&>(step), static_cast<Vjp&&>(vjp));
}

// Rollouts of the simulator's step and their derivatives: x_{t+1} = step(x_t, tau_t),
// t = 0..T-1, from x_0 = (q0, qd0), for every instance (threads over instances; on
// backend cuda every call runs cuda::CudaRolloutDerivatives, a thread per instance,
// host views copied in and out).
// The loss is the caller's: L = sum over t = 1..T of l_t(q_t, qd_t); vjp takes its
// gradients dL/dq_t, dL/dqd_t and returns dL/dq0, dL/dqd0 and dL/dtau_t by the
// reverse (adjoint) recursion of step_vjp_instance, O(nv) per step.
//
// Memory (checkpointing): the reverse pass needs x_t at every step, in reverse
// order. Per thread it keeps every K-th state of the instance it works on (the
// checkpoints, ceil(T / K) states) and, while it walks back through one segment, the
// segment's K states recomputed from its checkpoint: (ceil(T / K) + K) * 2 nv
// scalars, minimal at K = sqrt(T) (the default, checkpoint_interval 0), at the cost
// of one more forward step per step. K = T stores nothing but x_0 and the segment
// (2 forward passes), K = 1 every state (no recomputation).
template <class S>
class RolloutDerivatives {
 public:
  RolloutDerivatives(const SimSetup<S>& setup, const BackendOptions& options, Index checkpoint_interval = 0);
  ~RolloutDerivatives();

  // q0, qd0: (nv x B); tau: T steps of (nv x B) torques; q, qd (outputs): T steps,
  // q.at(t) = q_{t+1}. The same states the simulator reaches (serial-aba and
  // openmp-aba bit for bit).
  BatchStatus rollout(const BatchView<const S>& q0, const BatchView<const S>& qd0, const StepSequence<const S>& tau,
                      const StepSequence<S>& q, const StepSequence<S>& qd);
  // The gradient of L: gq, gqd (T steps: dL/dq_{t+1}, dL/dqd_{t+1}; a null sequence
  // is zero) -> gq0, gqd0 (nv x B) and gtau (T steps of nv x B).
  BatchStatus vjp(const BatchView<const S>& q0, const BatchView<const S>& qd0, const StepSequence<const S>& tau,
                  const StepSequence<const S>& gq, const StepSequence<const S>& gqd, const BatchView<S>& gq0,
                  const BatchView<S>& gqd0, const StepSequence<S>& gtau);
  // The forward-mode product: the tangents (dq, dqd: T steps) of the trajectory
  // along (dq0, dqd0, dtau) (a null dtau is zero).
  BatchStatus jvp(const BatchView<const S>& q0, const BatchView<const S>& qd0, const StepSequence<const S>& tau,
                  const BatchView<const S>& dq0, const BatchView<const S>& dqd0, const StepSequence<const S>& dtau,
                  const StepSequence<S>& dq, const StepSequence<S>& dqd);

  const SimSetup<S>& setup() const;
  Index checkpoint_interval(Index T) const;  // K for a horizon of T steps

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace sim
}  // namespace scandyn
