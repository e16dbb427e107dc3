// scandyn/sim/integrators.hpp: one time step of one instance, shared by every
// simulator backend (serial and OpenMP call it per instance on the host, the CUDA
// kernel per thread).
//
// Integrators (x = (q, qd), the torques tau held over the step):
//   euler     semi-implicit (symplectic) Euler:
//               qdd = FD(q, qd, tau + tau_e(q, qd)),  qd += dt qdd,  q += dt qd
//             (the new velocity moves the position: symplectic for conservative
//             forces, energy error bounded instead of drifting);
//   rk4       the classical fourth-order Runge-Kutta method on x' = (qd, qdd(x));
//             four forward dynamics per step;
//   implicit  semi-implicit Euler with damping and springs backward in time:
//               (M + dt D + dt^2 K) qdd = tau - h - D qd - K (q - q0 + dt qd) + tau_l,
//             then qd += dt qdd, q += dt qd, with D = diag(d), K = diag(k); i.e.
//             M qdd + h = tau - D qd' - K (q' - q0) at the step's end state
//             qd' = qd + dt qdd, q' = q + dt qd', the stiff terms linearised
//             exactly (they are linear). Stable for any d, k >= 0 at any dt (the
//             damped oscillator's amplification factor stays below 1), where
//             explicit Euler needs dt d / m < 2 and dt^2 k / m < 4. The armature
//             dt d + dt^2 k enters the forward dynamics as extra joint-space inertia
//             on M's diagonal (fd_jsi's / aba's armature argument). Limits and
//             external wrenches stay explicit.
// Models with quaternion positions (a floating base, ball joints: nq > nv) step on
// the configuration manifold (step_instance_at below): the velocity update is the
// same, the position update is q ⊕ dt qd (scandyn/algorithm/configuration.hpp:
// the quaternion exponential, renormalised), and rk4 combines its stages' slopes in
// the tangent space at q (the stage positions q ⊕ theta_s; Munthe-Kaas). 1-DoF
// models keep step_instance unchanged.
// tau_e(q, qd) = joint_effect_force (scandyn/sim/effects.hpp) of the declared
// joint effects; gravity and external wrenches live inside FD.
//
// The formulas are written once, per DoF, below ("the integrators' formulas"):
// step_instance (one instance: the serial and OpenMP instance loop, the CUDA fused
// kernel) and the engine paths (every DoF of every instance at once around a
// batched forward dynamics: the CUDA elementwise kernels of kernels/simulator_step.cu
// and the OpenMP "engine-parallel" step of cpu_fallback/simulator_step.cpp) call
// the same functions in the same order.
#pragma once

#include <string>

#include "scandyn/algorithm/configuration.hpp"
#include "scandyn/sim/effects.hpp"

#if defined(__CUDA_ARCH__)
// Device loops over DoFs: unrolled for small compile-time capacities (arrays in
// registers), rolled otherwise.
#define SCANDYN_SIM_UNROLL _Pragma("unroll((C > 0 && C <= 8) ? C : 1)")
#else
#define SCANDYN_SIM_UNROLL
#endif

namespace scandyn {
namespace sim {

// Variational (the midpoint discrete Lagrangian solved by Newton,
// scandyn/sim/variational.hpp) runs per instance outside the step tables below (the
// serial and OpenMP backends; CUDA up to 64 DoFs, kernels/sim_variational.cu):
// kIntegrators counts the three explicit / semi-implicit integrators that every
// backend instantiates.
enum class Integrator : int { Euler = 0, Rk4 = 1, Implicit = 2, Variational = 3 };
inline constexpr int kIntegrators = 3;

const char* to_string(Integrator integrator);  // "euler", "rk4", "implicit", "variational"
bool parse_integrator(const std::string& name, Integrator& integrator);

// The effects that make an integrator differ from euler: implicit without damping
// and springs IS semi-implicit Euler, and the simulator runs it as such.
constexpr Integrator effective_integrator(Integrator integrator, unsigned effects) {
  return integrator == Integrator::Implicit && (effects & kImplicitEffects) == 0 ? Integrator::Euler
                                                                                 : integrator;
}

// ---- the integrators' formulas, one DoF at a time --------------------------------

// The generalised force the forward dynamics receives on one DoF: the applied tau
// plus the declared joint effects' force at (q, qd), springs looking h ahead (h =
// dt for implicit, else 0).
template <unsigned kEffects, class S>
SCANDYN_HD S effect_forces(S tau, const JointCoefficients<S>& c, S q, S qd, S h) {
  return tau + joint_effect_force<kEffects>(c, q, qd, h);
}

// euler (and implicit, whose qdd already holds the implicit terms): the new
// velocity moves the position.
template <class S>
SCANDYN_HD void euler_update(S dt, S qdd, S& q, S& qd) {
  qd += dt * qdd;
  q += dt * qd;
}

// rk4 before the stages: the stage state (qs, qds) starts at (q, qd), the weighted
// sums (aq, aqd) at zero.
template <class S>
SCANDYN_HD void rk4_begin(S q, S qd, S& qs, S& qds, S& aq, S& aqd) {
  qs = q;
  qds = qd;
  aq = S(0);
  aqd = S(0);
}

// rk4 after stage s's forward dynamics (qdd at the stage state (qs, qds); stages at
// 0, dt/2, dt/2, dt): the stage's slope (qds, qdd) joins the weighted sums with
// weight 1, 2, 2, 1, and (qs, qds) moves to the next stage's state.
template <class S>
SCANDYN_HD void rk4_stage(int s, S dt, S q, S qd, S qdd, S& qs, S& qds, S& aq, S& aqd) {
  const S weight = (s == 0 || s == 3) ? S(1) : S(2);
  const S c = s < 2 ? S(0.5) * dt : dt;  // the next stage's offset
  const S v = qds, a = qdd;
  aq += weight * v;
  aqd += weight * a;
  qs = q + c * v;
  qds = qd + c * a;
}

// rk4 after the four stages: x += dt / 6 (k1 + 2 k2 + 2 k3 + k4).
template <class S>
SCANDYN_HD void rk4_finish(S dt, S aq, S aqd, S& q, S& qd) {
  const S sixth = dt / S(6);
  q += sixth * aq;
  qd += sixth * aqd;
}

// ---- one instance's step -------------------------------------------------------------

// Scratch arrays of one instance's step (n entries each; the caller's memory:
// per-thread vectors on the host, per-thread arrays in the CUDA kernel). euler and
// implicit use tau and qdd; rk4 all of them.
template <class S>
struct StepScratch {
  S* tau;  // (n) tau + the joint effects' forces
  S* qdd;  // (n) forward dynamics' result
  S* qs;   // (n) rk4: the stage's position
  S* qds;  // (n) rk4: the stage's velocity
  S* aq;   // (n) rk4: weighted sum of the stages' velocities
  S* aqd;  // (n) rk4: weighted sum of the stages' accelerations
};

// One step of one instance: q and qd (n entries each, contiguous) are advanced by
// dt in place under the torques tau (n); coef: the n joints' coefficients (read
// only for declared joint effects); armature: n entries dt d + dt^2 k for the
// implicit integrator (joint_armature), null otherwise.
//
// fd(q, qd, tau, armature, qdd) -> Index is the forward dynamics of the instance
// (gravity and the external wrenches are its business): it writes qdd (n) and
// returns -1, or the DoF whose pivot failed. On a failure the step returns that
// DoF and leaves q and qd as they were; otherwise it returns -1.
//
// C > 0: a compile-time bound on n (the CUDA kernels' capacity: loops over C with
// indices past n skipped, so they unroll); C = 0: loops over n.
template <unsigned kEffects, Integrator kIntegrator, int C = 0, class S, class Fd>
SCANDYN_HD Index step_instance(Index n, S dt, const JointCoefficients<S>* coef, const S* armature, S* q,
                               S* qd, const S* tau, const StepScratch<S>& w, Fd&& fd) {
  constexpr bool kJoint = (kEffects & kJointEffects) != 0;
  constexpr int kLoop = C > 0 ? C : 0;
  const Index m = kLoop > 0 ? Index(kLoop) : n;
  (void)coef;
  // tau + the joint effects' forces at (qa, qda), springs looking h ahead
  auto forces = [&](const S* qa, const S* qda, S h) -> const S* {
    if constexpr (!kJoint) {
      (void)qa, (void)qda, (void)h;
      return tau;
    } else {
      SCANDYN_SIM_UNROLL
      for (Index i = 0; i < m; ++i) {
        if (kLoop > 0 && i >= n) continue;
        w.tau[i] = effect_forces<kEffects>(tau[i], coef[i], qa[i], qda[i], h);
      }
      return w.tau;
    }
  };

  if constexpr (kIntegrator == Integrator::Rk4) {
    SCANDYN_SIM_UNROLL
    for (Index i = 0; i < m; ++i) {
      if (kLoop > 0 && i >= n) continue;
      rk4_begin(q[i], qd[i], w.qs[i], w.qds[i], w.aq[i], w.aqd[i]);
    }
    for (int s = 0; s < 4; ++s) {
      const Index failed = fd(w.qs, w.qds, forces(w.qs, w.qds, S(0)), static_cast<const S*>(nullptr), w.qdd);
      if (failed >= 0) return failed;
      SCANDYN_SIM_UNROLL
      for (Index i = 0; i < m; ++i) {
        if (kLoop > 0 && i >= n) continue;
        rk4_stage(s, dt, q[i], qd[i], w.qdd[i], w.qs[i], w.qds[i], w.aq[i], w.aqd[i]);
      }
    }
    SCANDYN_SIM_UNROLL
    for (Index i = 0; i < m; ++i) {
      if (kLoop > 0 && i >= n) continue;
      rk4_finish(dt, w.aq[i], w.aqd[i], q[i], qd[i]);
    }
    return -1;
  } else {
    constexpr bool kImplicit =
        kIntegrator == Integrator::Implicit && (kEffects & kImplicitEffects) != 0;
    const S h = kImplicit ? dt : S(0);
    const Index failed = fd(q, qd, forces(q, qd, h), kImplicit ? armature : static_cast<const S*>(nullptr), w.qdd);
    if (failed >= 0) return failed;
    SCANDYN_SIM_UNROLL
    for (Index i = 0; i < m; ++i) {
      if (kLoop > 0 && i >= n) continue;
      euler_update(dt, w.qdd[i], q[i], qd[i]);
    }
    return -1;
  }
}

// ---- one instance's step on the configuration manifold --------------------------
//
// For models with multi-DoF joints (ModelTpl::multi_dof(): the floating base, ball
// joints): q has nq entries, qd, tau and qdd nv. Per integrator:
//   euler     qdd = FD(q, qd, tau + tau_e),  qd += dt qdd,  q = q ⊕ dt qd;
//   implicit  the same with the armature dt d + dt^2 k and the springs looking dt
//             ahead: the stiff terms are linear in the tangent space (damping on
//             the joints' rates, springs on 1-DoF joints' positions), so the
//             1-DoF linearisation holds as it is;
//   rk4       stage s at (q ⊕ theta_s, qd + c_s qdd_{s-1}); its position slope
//             in the tangent space at q is tangent_slope(theta_s, qd_s)
//             (configuration.hpp; Jr^-1 on the rotations), the next stage's
//             offset theta_{s+1} = c_{s+1} slope_s; after the four stages
//             q = q ⊕ dt/6 (k1 + 2 k2 + 2 k3 + k4), qd as in step_instance.
//             Fourth order on the manifold (the quaternions stay unit).
// The joint effects act per DoF: damping on every joint DoF (ball joints' three
// rates), springs and limits on 1-DoF joints (at q[idx_q]); the scene gives the
// floating base's six DoFs and the ball joints' springs and limits zero
// coefficients (docs/scenes.md), so a DoF of a multi-DoF joint reads q = 0.

// Scratch of step_instance_at (the caller's memory).
template <class S>
struct StepScratchAt {
  S* tau;    // (nv) tau + the joint effects' forces
  S* qdd;    // (nv) forward dynamics' result
  S* qs;     // (nq) rk4: the stage's position q ⊕ theta
  S* qds;    // (nv) rk4: the stage's velocity
  S* aq;     // (nv) rk4: weighted sum of the stages' tangent slopes
  S* aqd;    // (nv) rk4: weighted sum of the stages' accelerations
  S* theta;  // (nv) rk4: the stage's tangent offset, then (in place) its slope
};

// The joint effects' forces tau + tau_e(q, qd) (nv) into out, springs looking h
// ahead, over the bodies (1-DoF joints at q[idx_q], the others' DoFs at q = 0).
template <unsigned kEffects, class S>
SCANDYN_HD void effect_forces_at(const Body<S>* bodies, Index nb, const JointCoefficients<S>* coef, const S* tau,
                                 const S* q, const S* qd, S h, S* out) {
  for (Index i = 0; i < nb; ++i) {
    const Body<S>& b = bodies[i];
    const Index k = b.idx_v;
    if (b.type == JointType::Revolute || b.type == JointType::Prismatic) {
      out[k] = effect_forces<kEffects>(tau[k], coef[k], q[b.idx_q], qd[k], h);
      continue;
    }
    for (int j = 0; j < joint_nv(b.type); ++j)
      out[k + j] = effect_forces<kEffects>(tau[k + j], coef[k + j], S(0), qd[k + j], h);
  }
}

// One step of one instance of a model with multi-DoF joints: q (nq) and qd (nv),
// contiguous, advanced by dt in place under tau (nv); bodies[0..nb) with idx_q /
// idx_v set. coef, armature and fd as for step_instance (fd reads q with nq
// entries). Returns -1, or the failed DoF (q and qd then as they were).
template <unsigned kEffects, Integrator kIntegrator, class S, class Fd>
SCANDYN_HD Index step_instance_at(const Body<S>* bodies, Index nb, Index nq, Index nv, S dt,
                                  const JointCoefficients<S>* coef, const S* armature, S* q, S* qd, const S* tau,
                                  const StepScratchAt<S>& w, Fd&& fd) {
  constexpr bool kJoint = (kEffects & kJointEffects) != 0;
  auto forces = [&](const S* qa, const S* qda, S h) -> const S* {
    if constexpr (!kJoint) {
      (void)qa, (void)qda, (void)h, (void)coef;
      return tau;
    } else {
      effect_forces_at<kEffects>(bodies, nb, coef, tau, qa, qda, h, w.tau);
      return w.tau;
    }
  };
  if constexpr (kIntegrator == Integrator::Rk4) {
    for (Index i = 0; i < nq; ++i) w.qs[i] = q[i];
    for (Index i = 0; i < nv; ++i) w.qds[i] = qd[i], w.theta[i] = S(0), w.aq[i] = S(0), w.aqd[i] = S(0);
    for (int s = 0; s < 4; ++s) {
      const Index failed = fd(w.qs, w.qds, forces(w.qs, w.qds, S(0)), static_cast<const S*>(nullptr), w.qdd);
      if (failed >= 0) return failed;
      // the stage's position slope in the tangent space at q (over theta: its offset)
      for (Index i = 0; i < nb; ++i) {  // theta_s -> slope_s, joint by joint
        const Index k = bodies[i].idx_v;
        S slope[kMaxJointDofs];
        joint_tangent_slope(bodies[i], w.theta + k, w.qds + k, slope);
        for (int j = 0; j < joint_nv(bodies[i].type); ++j) w.theta[k + j] = slope[j];
      }
      const S weight = (s == 0 || s == 3) ? S(1) : S(2);
      const S c = s < 2 ? S(0.5) * dt : dt;  // the next stage's offset
      for (Index i = 0; i < nv; ++i) {
        w.aq[i] += weight * w.theta[i];
        w.aqd[i] += weight * w.qdd[i];
        w.theta[i] *= c;
        w.qds[i] = qd[i] + c * w.qdd[i];
      }
      for (Index i = 0; i < nq; ++i) w.qs[i] = q[i];
      integrate_bodies(bodies, nb, w.qs, w.theta, S(1));
    }
    const S sixth = dt / S(6);
    integrate_bodies(bodies, nb, q, w.aq, sixth);
    for (Index i = 0; i < nv; ++i) qd[i] += sixth * w.aqd[i];
    return -1;
  } else {
    constexpr bool kImplicit = kIntegrator == Integrator::Implicit && (kEffects & kImplicitEffects) != 0;
    const S h = kImplicit ? dt : S(0);
    const Index failed = fd(q, qd, forces(q, qd, h), kImplicit ? armature : static_cast<const S*>(nullptr), w.qdd);
    if (failed >= 0) return failed;
    for (Index i = 0; i < nv; ++i) qd[i] += dt * w.qdd[i];
    integrate_bodies(bodies, nb, q, qd, dt);
    return -1;
  }
}

}  // namespace sim
}  // namespace scandyn
