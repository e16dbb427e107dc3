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
        w.tau[i] = tau[i] + joint_effect_force<kEffects>(coef[i], qa[i], qda[i], h);
      }
      return w.tau;
    }
  };

  if constexpr (kIntegrator == Integrator::Rk4) {
    // k_s = (qds, qdd) at the stage state (qs, qds); stages at 0, dt/2, dt/2, dt
    SCANDYN_SIM_UNROLL
    for (Index i = 0; i < m; ++i) {
      if (kLoop > 0 && i >= n) continue;
      w.qs[i] = q[i];
      w.qds[i] = qd[i];
      w.aq[i] = S(0);
      w.aqd[i] = S(0);
    }
    for (int s = 0; s < 4; ++s) {
      const Index failed = fd(w.qs, w.qds, forces(w.qs, w.qds, S(0)), static_cast<const S*>(nullptr), w.qdd);
      if (failed >= 0) return failed;
      const S weight = (s == 0 || s == 3) ? S(1) : S(2);
      const S c = s < 2 ? S(0.5) * dt : dt;  // the next stage's offset
      SCANDYN_SIM_UNROLL
      for (Index i = 0; i < m; ++i) {
        if (kLoop > 0 && i >= n) continue;
        const S v = w.qds[i], a = w.qdd[i];
        w.aq[i] += weight * v;
        w.aqd[i] += weight * a;
        w.qs[i] = q[i] + c * v;
        w.qds[i] = qd[i] + c * a;
      }
    }
    const S sixth = dt / S(6);
    SCANDYN_SIM_UNROLL
    for (Index i = 0; i < m; ++i) {
      if (kLoop > 0 && i >= n) continue;
      q[i] += sixth * w.aq[i];
      qd[i] += sixth * w.aqd[i];
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
      qd[i] += dt * w.qdd[i];
      q[i] += dt * qd[i];
    }
    return -1;
  }
}

}  // namespace sim
}  // namespace scandyn
