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

enum class Integrator : int { Euler = 0, Rk4 = 1, Implicit = 2 };
inline constexpr int kIntegrators = 3;

const char* to_string(Integrator integrator);  // "euler", "rk4", "implicit"
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

}  // namespace sim
}  // namespace scandyn
