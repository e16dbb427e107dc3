// scandyn/instance/rnea_passes.hpp: the two passes of the RNEA of one instance over
// arrays of bodies, keeping every body's values, __host__ __device__: the serial
// reference rnea (models of 1-DoF joints) and the directional derivatives
// (scandyn/instance/directional_instance.hpp: rnea_jvp / rnea_vjp, and on them
// aba_jvp / aba_vjp, serial and in the CUDA rollout kernels) run this one function.
#pragma once

#include "scandyn/algorithm/steps.hpp"

namespace scandyn {

// The RNEA's per-body values of one instance (body frames), the caller's memory
// (host vectors, or a CUDA thread's local arrays), nv entries each.
template <class S>
struct RneaBodies {
  Transform<S>* Xup;  // (nv) parent -> body transform at q
  Motion<S>* v;       // (nv) body velocities
  Motion<S>* a;       // (nv) body accelerations (gravity included)
  Force<S>* f;        // (nv) body forces I a + v x* I v - fext, then (backward) the subtree's
};

// tau = ID(q, qd, qdd, fext) of a model of n 1-DoF joints (bodies[i].parent < i),
// base acceleration a0 = -g: forward, each body's transform, velocity, acceleration
// and force (rnea_forward_step); backward, the subtree forces accumulated into the
// parents and projected on the joints. qdd null: zero; fext (n wrenches, body
// frames) null: none; tau null: not written (d.f still gets the subtree forces).
template <class S, class Bd>
SCANDYN_HD void rnea_passes(const Bd* bodies, Index n, const Motion<S>& a0, const S* q, const S* qd,
                            const S* qdd, const Force<S>* fext, const RneaBodies<S>& d, S* tau) {
  // forward: kinematics and body forces
  for (Index i = 0; i < n; ++i) {
    const Bd& b = bodies[i];
    const Index p = b.parent;
    d.Xup[i] = joint_transform(b, q[i]);
    const RneaForward<S> o = rnea_forward_step(b, d.Xup[i], p < 0 ? Motion<S>::zero() : d.v[p],
                                               p < 0 ? a0 : d.a[p], qd[i], qdd ? qdd[i] : S(0));
    d.v[i] = o.v;
    d.a[i] = o.a;
    d.f[i] = fext ? o.f - fext[i] : o.f;
  }
  // backward: joint torques, forces accumulated into parents
  for (Index i = n - 1; i >= 0; --i) {
    const Bd& b = bodies[i];
    if (tau) tau[i] = joint_project(b, d.f[i]);
    if (b.parent >= 0) d.f[b.parent] += d.Xup[i].apply_transpose(d.f[i]);
  }
}

}  // namespace scandyn
