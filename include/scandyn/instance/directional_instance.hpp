// scandyn/instance/directional_instance.hpp: the directional derivatives (JVP) and
// adjoints (VJP) of inverse and forward dynamics of one instance over arrays of
// bodies and caller scratch, __host__ __device__: the serial rnea_jvp / rnea_vjp /
// aba_jvp / aba_vjp (scandyn/algorithm/directional_derivatives.hpp, which states the
// recursions) are calls of these functions, and so are the CUDA rollout kernels
// (kernels/rollout_derivatives.cu). Models of 1-DoF joints; O(nv) each.
#pragma once

#include "scandyn/instance/rnea_passes.hpp"

namespace scandyn {

// Tangents of one body's RNEA quantities (body frame).
template <class S>
struct RneaTangent {
  Motion<S> v, a;  // dv, da
  Force<S> f;      // df, then (backward) the subtree's dF
};

// The tangent of rnea_forward_step, in three parts that the chain scans
// (scandyn/algorithm/chain_directional.hpp) run as separate passes:
//   dv = Xup dv_p - dq s x (Xup v_p) + s dqd
template <class S, class Bd>
SCANDYN_HD Motion<S> rnea_tangent_velocity_step(const Bd& b, const Transform<S>& Xup, const Motion<S>& v_parent,
                                                const Motion<S>& dv_parent, S dq, S dqd) {
  const Motion<S> s = joint_motion(b, S(1));
  return add_joint_motion(b, Xup.apply(dv_parent) - dq * cross(s, Xup.apply(v_parent)), dqd);
}
//   da = Xup da_p - dq s x (Xup a_p) + s dqdd + dv x s qd + v x s dqd
template <class S, class Bd>
SCANDYN_HD Motion<S> rnea_tangent_acceleration_step(const Bd& b, const Transform<S>& Xup, const Motion<S>& a_parent,
                                                    const Motion<S>& da_parent, const Motion<S>& v,
                                                    const Motion<S>& dv, S qd, S dq, S dqd, S dqdd) {
  const Motion<S> s = joint_motion(b, S(1));
  return add_joint_motion(b, Xup.apply(da_parent) - dq * cross(s, Xup.apply(a_parent)), dqdd) +
         cross_joint_motion(b, dv, qd) + cross_joint_motion(b, v, dqd);
}
//   df = I da + dv x* I v + v x* I dv   (fext fixed in the body frame)
template <class S, class Bd>
SCANDYN_HD Force<S> rnea_tangent_force_step(const Bd& b, const Motion<S>& v, const Motion<S>& dv,
                                            const Motion<S>& da) {
  return b.I * da + cross(dv, b.I * v) + cross(v, b.I * dv);
}
// What body i's subtree passes to its parent's dF, in body i's frame (the parent
// adds Xup^T of it): dF_i + dq_i s_i x* F_i, F_i the subtree force.
template <class S, class Bd>
SCANDYN_HD Force<S> rnea_tangent_subtree_force(const Bd& b, const Force<S>& dF, S dq, const Force<S>& F) {
  return dF + dq * cross(joint_motion(b, S(1)), F);
}

// The tangent of rnea_forward_step: body i's (dv, da, df) from its parent's (dv_p,
// da_p) and the parent's values (v_p, a_p); v: the body's velocity
// (rnea_forward_step's v).
template <class S, class Bd>
SCANDYN_HD RneaTangent<S> rnea_tangent_forward_step(const Bd& b, const Transform<S>& Xup,
                                                    const Motion<S>& v_parent, const Motion<S>& a_parent,
                                                    const Motion<S>& dv_parent, const Motion<S>& da_parent,
                                                    const Motion<S>& v, S qd, S dq, S dqd, S dqdd) {
  RneaTangent<S> t;
  t.v = rnea_tangent_velocity_step(b, Xup, v_parent, dv_parent, dq, dqd);
  t.a = rnea_tangent_acceleration_step(b, Xup, a_parent, da_parent, v, t.v, qd, dq, dqd, dqdd);
  t.f = rnea_tangent_force_step(b, v, t.v, t.a);
  return t;
}

// Adjoints of one body's RNEA quantities (body frame), rnea_vjp's.
template <class S>
struct RneaAdjoint {
  Motion<S> F;     // adjoint of the subtree force (pairs with forces)
  Force<S> a, v;   // adjoints of the acceleration and velocity (pair with motions)
};

// The adjoints a body's own force terms take from Fbar (the adjoint of its subtree
// force): abar = I Fbar, vbar = -(Fbar x* I v + I (v x Fbar)); RneaAdjoint's F = Fbar.
template <class S, class Bd>
SCANDYN_HD RneaAdjoint<S> rnea_adjoint_body_terms(const Bd& b, const Motion<S>& Fbar, const Motion<S>& v) {
  RneaAdjoint<S> r;
  r.F = Fbar;
  r.a = b.I * Fbar;
  r.v = -(cross(Fbar, b.I * v) + b.I * cross(v, Fbar));
  return r;
}

// The adjoint of the velocity product v x s qd for the acceleration adjoint abar
// (complete: the subtree's included), which vbar receives: qd s x abar.
template <class S, class Bd>
SCANDYN_HD Force<S> rnea_adjoint_velocity_from_acceleration(const Bd& b, S qd, const Force<S>& abar) {
  return qd * cross(joint_motion(b, S(1)), abar);
}

// Body i's gradients from its complete adjoints (abar, vbar, subtree sums, vbar with
// rnea_adjoint_velocity_from_acceleration added): gqdd = s.abar, gqd = (v x s).abar +
// s.vbar, and gq -= (s x Xup a_p).abar + (s x Xup v_p).vbar (a_p = a0, v_p = 0 at
// the base).
template <class S, class Bd>
SCANDYN_HD void rnea_adjoint_gradients(const Bd& b, const Transform<S>& X, const Motion<S>& a_parent,
                                       const Motion<S>& v_parent, const Motion<S>& v, const Force<S>& abar,
                                       const Force<S>& vbar, S& gq, S& gqd, S& gqdd) {
  const Motion<S> s = joint_motion(b, S(1));
  const Motion<S> Xa = X.apply(a_parent), Xv = X.apply(v_parent);
  gqdd = dot(s, abar);
  gqd = dot(cross(v, s), abar);
  gq -= dot(cross(s, Xa), abar) + dot(cross(s, Xv), vbar);
  gqd += dot(s, vbar);
}

// dtau = (d ID / d q) dq + (d ID / d qd) dqd + M dqdd at (q, qd, qdd, fext): the RNEA's
// passes (rnea_passes; tau, optional, = ID), then the tangents forward (t, n
// entries) and backward. dqdd null: zero. Every array has n entries.
template <class S, class Bd>
SCANDYN_HD void rnea_jvp_instance(const Bd* bodies, Index n, const Motion<S>& a0, const S* q, const S* qd,
                                  const S* qdd, const Force<S>* fext, const S* dq, const S* dqd, const S* dqdd,
                                  const RneaBodies<S>& d, RneaTangent<S>* t, S* dtau, S* tau) {
  rnea_passes(bodies, n, a0, q, qd, qdd, fext, d, tau);
  // forward: the tangents of the velocities, accelerations and body forces
  for (Index i = 0; i < n; ++i) {
    const Bd& b = bodies[i];
    const Index p = b.parent;
    const Motion<S> vp = p < 0 ? Motion<S>::zero() : d.v[p], ap = p < 0 ? a0 : d.a[p];
    const Motion<S> dvp = p < 0 ? Motion<S>::zero() : t[p].v, dap = p < 0 ? Motion<S>::zero() : t[p].a;
    t[i] = rnea_tangent_forward_step(b, d.Xup[i], vp, ap, dvp, dap, d.v[i], qd[i], dq[i], dqd[i],
                                     dqdd ? dqdd[i] : S(0));
  }
  // backward: the subtree forces' tangents (d.f: the subtree forces)
  for (Index i = n - 1; i >= 0; --i) {
    const Bd& b = bodies[i];
    dtau[i] = joint_project(b, t[i].f);
    if (b.parent < 0) continue;
    t[b.parent].f += d.Xup[i].apply_transpose(rnea_tangent_subtree_force(b, t[i].f, dq[i], d.f[i]));
  }
}

// The adjoint of inverse dynamics for a weight w on tau: gq = (dtau/dq)^T w, gqd =
// (dtau/dqd)^T w, gqdd = M w (gqdd holds tau meanwhile). adj: n entries of scratch.
template <class S, class Bd>
SCANDYN_HD void rnea_vjp_instance(const Bd* bodies, Index n, const Motion<S>& a0, const S* q, const S* qd,
                                  const S* qdd, const Force<S>* fext, const S* w, const RneaBodies<S>& d,
                                  RneaAdjoint<S>* adj, S* gq, S* gqd, S* gqdd) {
  rnea_passes(bodies, n, a0, q, qd, qdd, fext, d, gqdd);  // Xup, v, a and the subtree forces F
  // root to leaves: Fbar, and the body force's own adjoints
  for (Index i = 0; i < n; ++i) {
    const Bd& b = bodies[i];
    const Motion<S> s = joint_motion(b, S(1));
    RneaAdjoint<S>& r = adj[i];
    const Motion<S> from_parent = b.parent < 0 ? Motion<S>::zero() : d.Xup[i].apply(adj[b.parent].F);
    r = rnea_adjoint_body_terms(b, w[i] * s + from_parent, d.v[i]);
    gq[i] = dot(from_parent, cross(s, d.f[i]));
  }
  // leaves to root: the acceleration and velocity adjoints, to the parents
  for (Index i = n - 1; i >= 0; --i) {
    const Bd& b = bodies[i];
    const Index p = b.parent;
    const Transform<S>& X = d.Xup[i];
    RneaAdjoint<S>& r = adj[i];
    r.v += rnea_adjoint_velocity_from_acceleration(b, qd[i], r.a);
    rnea_adjoint_gradients(b, X, p < 0 ? a0 : d.a[p], p < 0 ? Motion<S>::zero() : d.v[p], d.v[i], r.a, r.v, gq[i],
                           gqd[i], gqdd[i]);
    if (p >= 0) {
      adj[p].a += X.apply_transpose(r.a);
      adj[p].v += X.apply_transpose(r.v);
    }
  }
}

// ---- forward dynamics -------------------------------------------------------------
// Both take the instance's forward dynamics as functors, so that each backend runs
// its own ABA (the serial aba, the CUDA aba_instance):
//   fd(q, qd, tau, armature, qdd) -> Index       qdd = FD(q, qd, tau) with fext and
//                                                  gravity (-1, or the failed DoF)
//   m_inv(q, x, armature, y) -> Index            y = (M + diag(armature))^-1 x: the
//                                                  ABA of the model without gravity
//                                                  at rest (qd = 0, no fext)

// dqdd = (dqdd/dq) dq + (dqdd/dqd) dqd + M^-1 dtau at (q, qd, tau, fext); qdd
// (written) = FD(q, qd, tau, fext). r: n scalars of scratch. Returns -1 or the
// failed DoF.
template <class S, class Bd, class Fd, class MInv>
SCANDYN_HD Index aba_jvp_instance(const Bd* bodies, Index n, const Motion<S>& a0, const S* q, const S* qd,
                                  const S* tau, const Force<S>* fext, const S* dq, const S* dqd, const S* dtau,
                                  const S* armature, const RneaBodies<S>& d, RneaTangent<S>* t, S* r, S* dqdd,
                                  S* qdd, Fd&& fd, MInv&& m_inv) {
  const Index failed = fd(q, qd, tau, armature, qdd);
  if (failed >= 0) return failed;
  // r = dtau/dq dq + dtau/dqd dqd (the JVP of ID with dqdd = 0), then dtau - r
  rnea_jvp_instance(bodies, n, a0, q, qd, static_cast<const S*>(qdd), fext, dq, dqd, static_cast<const S*>(nullptr),
                    d, t, r, static_cast<S*>(nullptr));
  for (Index i = 0; i < n; ++i) r[i] = dtau[i] - r[i];
  return m_inv(q, static_cast<const S*>(r), armature, dqdd);
}

// gq = (dqdd/dq)^T w, gqd = (dqdd/dqd)^T w, gtau = M^-1 w at (q, qd, tau, fext); qdd
// (written) = FD(q, qd, tau, fext). r: n scalars of scratch. Returns -1 or the
// failed DoF.
template <class S, class Bd, class Fd, class MInv>
SCANDYN_HD Index aba_vjp_instance(const Bd* bodies, Index n, const Motion<S>& a0, const S* q, const S* qd,
                                  const S* tau, const Force<S>* fext, const S* w, const S* armature,
                                  const RneaBodies<S>& d, RneaAdjoint<S>* adj, S* r, S* gq, S* gqd, S* gtau,
                                  S* qdd, Fd&& fd, MInv&& m_inv) {
  Index failed = fd(q, qd, tau, armature, qdd);
  if (failed >= 0) return failed;
  failed = m_inv(q, w, armature, gtau);  // u = M^-1 w
  if (failed >= 0) return failed;
  rnea_vjp_instance(bodies, n, a0, q, qd, static_cast<const S*>(qdd), fext, static_cast<const S*>(gtau), d, adj, gq,
                    gqd, r);
  for (Index i = 0; i < n; ++i) gq[i] = -gq[i], gqd[i] = -gqd[i];
  return -1;
}

}  // namespace scandyn
