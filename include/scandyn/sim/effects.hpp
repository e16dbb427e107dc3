// scandyn/sim/effects.hpp: the effects a scene can declare, as a compile-time set.
//
// A scene names the effects present (gravity, joint damping, joint springs, joint
// limits, external link wrenches). The simulator's per-instance step is a template
// on that set (an `unsigned` of Effect bits): scandyn::sim::step_instance
// (scandyn/sim/integrators.hpp) is instantiated for every combination, and the
// scene picks one instantiation once, when the simulator is made. An effect that is
// absent is not computed at all (no branch, no load, no arithmetic); one declared
// with zero coefficients is computed and adds zero (the same trajectory; the
// effects benchmark measures the difference).
//
// How each effect enters the equations of motion M qdd + h = tau + tau_effects:
//   gravity   the model's gravity as the base acceleration -g (absent: zero base
//             acceleration, no gravity forces at all);
//   damping   tau_i -= d_i qd_i;
//   springs   tau_i -= k_i (q_i - q0_i);
//   limits    a one-sided penalty spring-damper where q_i leaves [lower_i, upper_i]:
//             tau_i += kl_i (lower_i - q_i) - dl_i qd_i below lower_i,
//             tau_i += kl_i (upper_i - q_i) - dl_i qd_i above upper_i, nothing inside;
//   external  body wrenches fext (body frames, [moment; force] about the body's
//             origin), passed to the forward dynamics as its fext argument;
//   contacts  spheres fixed on links against fixed world planes and spheres: a
//             compliant normal force and regularised Coulomb friction per touching
//             pair, entering as body wrenches added to fext (scandyn/sim/contacts.hpp).
// The implicit integrator treats damping, springs and the contacts' stiffness and
// damping implicitly (integrators.hpp, contacts.hpp).
//
// These functions are SCANDYN_HD: the CPU backends and the CUDA kernel call them.
#pragma once

#include <string>

#include "scandyn/config.hpp"

namespace scandyn {
namespace sim {

// One bit per effect; a set of effects is their bitwise or.
enum Effect : unsigned {
  kGravity = 1u,
  kDamping = 2u,
  kSprings = 4u,
  kLimits = 8u,
  kExternal = 16u,
  kContacts = 32u,
};
inline constexpr unsigned kAllEffects = 63u;
inline constexpr int kEffectSets = 64;  // every subset is instantiated on the host
// The effects that add a generalised force on each joint.
inline constexpr unsigned kJointEffects = kDamping | kSprings | kLimits;
// The effects the implicit integrator treats implicitly (an armature dt d + dt^2 k;
// the contacts' bound of contacts.hpp).
inline constexpr unsigned kImplicitEffects = kDamping | kSprings | kContacts;

// The effect set whose step the host (serial, OpenMP) instantiates for a scene's
// set e. By default e itself: 64 sets x 3 integrators per step table. Builds with
// SCANDYN_HOST_EFFECT_SETS=0 (CMake option SCANDYN_HOST_EFFECT_SETS=OFF, what
// scripts/test.sh builds on machines without a GPU and in its sanitizer stage)
// compile every joint effect and the external wrenches into each step, keeping
// only gravity and contacts apart: an
// undeclared effect then runs with its neutral coefficients (d = k = kl = dl = 0,
// limits -inf / +inf, no wrenches), which gives the same numbers as the absent
// effect (test_sim's ZeroCoefficientsEqualAbsentEffects) at the cost of a few
// per-DoF operations, and 4 sets instead of 64.
#if !defined(SCANDYN_HOST_EFFECT_SETS)
#define SCANDYN_HOST_EFFECT_SETS 1
#endif
constexpr unsigned host_step_set(unsigned e) {
  return SCANDYN_HOST_EFFECT_SETS ? e : (e | kJointEffects | kExternal);
}
// The same for the steps whose wrenches are not part of the set (the variational
// step, the engine path's joint forces): every joint effect compiled in.
constexpr unsigned host_joint_effect_set(unsigned e) { return SCANDYN_HOST_EFFECT_SETS ? e : (e | kJointEffects); }

// "gravity+damping+springs+limits+external+contacts" order, "none" for the empty set.
std::string effect_names(unsigned effects);

// The per-DoF coefficients of the joint effects (only those of declared effects
// are read).
template <class S>
struct JointCoefficients {
  S damping;          // d_i >= 0 (N m s / rad, or N s / m for a prismatic joint)
  S stiffness;        // k_i >= 0 (N m / rad, or N / m)
  S rest;             // q0_i, the springs' rest position (rad or m)
  S lower;            // joint-limit interval [lower_i, upper_i] (rad or m); -inf / +inf: none
  S upper;
  S limit_stiffness;  // kl_i >= 0 of the limits' penalty spring
  S limit_damping;    // dl_i >= 0 of the limits' penalty damper
};

// The generalised force of the declared joint effects on one DoF at (q, qd).
// lookahead h: the springs act at q + h qd (h = 0 for explicit integrators, dt for
// the implicit one, whose qd term moves to the left-hand side as the armature).
template <unsigned kEffects, class S>
SCANDYN_HD S joint_effect_force(const JointCoefficients<S>& c, S q, S qd, S h) {
  S f = S(0);
  if constexpr ((kEffects & kDamping) != 0) f -= c.damping * qd;
  if constexpr ((kEffects & kSprings) != 0) f -= c.stiffness * (q - c.rest + h * qd);
  if constexpr ((kEffects & kLimits) != 0) {
    if (q < c.lower) f += c.limit_stiffness * (c.lower - q) - c.limit_damping * qd;
    else if (q > c.upper) f += c.limit_stiffness * (c.upper - q) - c.limit_damping * qd;
  }
  (void)c, (void)q, (void)qd, (void)h;
  return f;
}

// The implicit integrator's armature of one DoF: dt d + dt^2 k of the declared
// damping and springs (0 when neither is declared).
template <unsigned kEffects, class S>
SCANDYN_HD S joint_armature(const JointCoefficients<S>& c, S dt) {
  S a = S(0);
  if constexpr ((kEffects & kDamping) != 0) a += dt * c.damping;
  if constexpr ((kEffects & kSprings) != 0) a += dt * dt * c.stiffness;
  (void)c, (void)dt;
  return a;
}

// The potential energy of the declared conservative joint effects on one DoF:
// 1/2 k (q - q0)^2 of a spring, 1/2 kl d^2 of a limit violated by d (a run-time
// set: energy is a diagnostic, not part of the step).
template <class S>
SCANDYN_HD S joint_effect_energy(unsigned effects, const JointCoefficients<S>& c, S q) {
  S e = S(0);
  if ((effects & kSprings) != 0) e += S(0.5) * c.stiffness * (q - c.rest) * (q - c.rest);
  if ((effects & kLimits) != 0) {
    const S d = q < c.lower ? c.lower - q : q > c.upper ? q - c.upper : S(0);
    e += S(0.5) * c.limit_stiffness * d * d;
  }
  return e;
}

}  // namespace sim
}  // namespace scandyn
