// scandyn/instance/directional_general_instance.hpp: the directional derivatives (JVP)
// and adjoints (VJP) of inverse and forward dynamics of one instance of a model with
// multi-DoF joints (a floating base, spherical joints), O(nv) each: the recursions of
// scandyn/instance/directional_instance.hpp with a joint's motion S x (x: the joint's
// nj entries of a rate, a tangent or a weight) where the 1-DoF recursions have s x.
//
// q has nq entries; its tangent dq and the gradient gq have nv, in the tangent
// convention of the dense first-order derivatives (rnea_derivatives_general_instance):
// a joint's increment is local, q (+) d = q exp(d) in the child's frame, so the child's
// frame moves by the body-frame twist S d and Xup(q (+) d) = (1 - crm(S d)) Xup(q) to
// first order (Featherstone's dXup/dq = -crm(S) Xup, for each column of S). S is constant in the body frame (a spherical joint's [1; 0], a free joint's
// identity), so the RNEA's forward step v = Xup v_p + S qd, a = Xup a_p + S qdd + v x S
// qd (rnea_forward_step_at) has the tangent
//   dv = Xup dv_p - (S dq) x (Xup v_p) + S dqd
//   da = Xup da_p - (S dq) x (Xup a_p) + S dqdd + dv x (S qd) + v x (S dqd)
//   df = I da + dv x* I v + v x* I dv                      (fext fixed in body frames)
//   dF_p += Xup^T (dF + (S dq) x* F),   dtau_joint = S^T dF
// and the adjoints run the two passes reversed (rnea_vjp_general_instance). Forward
// dynamics by the identity at qdd = FD(q, qd, tau, fext): dqdd = M^-1 (dtau - dtau/dq dq
// - dtau/dqd dqd), and for a weight w, u = M^-1 w: gq = -(dtau/dq)^T u, gqd =
// -(dtau/dqd)^T u, gtau = u; M^-1 x is one ABA of the model at rest without gravity
// (aba_general with a0 = 0, qd = 0, no fext).
#pragma once

#include "scandyn/instance/directional_instance.hpp"
#include "scandyn/instance/general_instance.hpp"

namespace scandyn {

// dtau = (d ID / d q) dq + (d ID / d qd) dqd + M dqdd at (q, qd, qdd, fext) of nb bodies
// (nv DoFs): the RNEA's passes into w (rnea_general: Xup, v, a and, after its backward
// pass, the subtree forces in w.f; tau, when not null, = ID), then the tangents forward
// (t, nb entries) and backward. dqdd null: zero. q: nq entries; qd, qdd, dq, dqd, dqdd,
// dtau, tau: nv; fext: nb body wrenches or null. tau null: dtau holds ID meanwhile.
template <class S>
SCANDYN_HD void rnea_jvp_general_instance(const Body<S>* body, Index nb, const Motion<S>& a0, const S* q,
                                          const S* qd, const S* qdd, const Force<S>* fext, const S* dq,
                                          const S* dqd, const S* dqdd, const GeneralWork<S>& w, RneaTangent<S>* t,
                                          S* dtau, S* tau) {
  rnea_general(body, nb, a0, w, q, qd, qdd, tau ? tau : dtau, fext);
  // forward: the tangents of the velocities, accelerations and body forces
  for (Index i = 0; i < nb; ++i) {
    const Body<S>& b = body[i];
    const Index p = b.parent, iv = b.idx_v;
    const Transform<S>& X = w.Xup[i];
    const Motion<S> Xv = p < 0 ? Motion<S>::zero() : X.apply(w.v[p]), Xa = X.apply(p < 0 ? a0 : w.a[p]);
    const Motion<S> Sdq = joint_motion_at(b, dq + iv), Sdqd = joint_motion_at(b, dqd + iv);
    RneaTangent<S>& ti = t[i];
    ti.v = (p < 0 ? Motion<S>::zero() : X.apply(t[p].v)) - cross(Sdq, Xv) + Sdqd;
    ti.a = (p < 0 ? Motion<S>::zero() : X.apply(t[p].a)) - cross(Sdq, Xa) + cross(ti.v, joint_motion_at(b, qd + iv)) +
           cross(w.v[i], Sdqd);
    if (dqdd) ti.a = ti.a + joint_motion_at(b, dqdd + iv);
    ti.f = rnea_tangent_force_step(b, w.v[i], ti.v, ti.a);
  }
  // backward: the subtree forces' tangents (w.f: the subtree forces)
  for (Index i = nb - 1; i >= 0; --i) {
    const Body<S>& b = body[i];
    joint_project_at(b, t[i].f, dtau + b.idx_v);
    if (b.parent < 0) continue;
    t[b.parent].f += w.Xup[i].apply_transpose(t[i].f + cross(joint_motion_at(b, dq + b.idx_v), w.f[i]));
  }
}

// The adjoint of inverse dynamics for a weight wt on tau (nv): gq = (dtau/dq)^T wt, gqd =
// (dtau/dqd)^T wt, gqdd = M wt (gqdd holds tau meanwhile); arrays as
// rnea_jvp_general_instance's, adj: nb entries of scratch. Per body (RneaAdjoint: Fbar,
// abar, vbar):
//   root to leaves   Fbar = S wt + Xup Fbar_p,   gq_k = (Xup Fbar_p) . (S_k x* F)
//   (own terms)      abar = I Fbar,   vbar = -(Fbar x* I v + I (v x Fbar))
//   leaves to root   vbar += (S qd) x* abar,   abar_p += Xup^T abar,   vbar_p += Xup^T vbar
//                    gqdd_k = S_k . abar,   gqd_k = (v x S_k) . abar + S_k . vbar,
//                    gq_k -= (S_k x Xup a_p) . abar + (S_k x Xup v_p) . vbar
template <class S>
SCANDYN_HD void rnea_vjp_general_instance(const Body<S>* body, Index nb, const Motion<S>& a0, const S* q,
                                          const S* qd, const S* qdd, const Force<S>* fext, const S* wt,
                                          const GeneralWork<S>& w, RneaAdjoint<S>* adj, S* gq, S* gqd, S* gqdd) {
  rnea_general(body, nb, a0, w, q, qd, qdd, gqdd, fext);  // Xup, v, a and the subtree forces F
  // root to leaves: Fbar, and the body force's own adjoints
  for (Index i = 0; i < nb; ++i) {
    const Body<S>& b = body[i];
    const Index iv = b.idx_v;
    const Motion<S> from_parent = b.parent < 0 ? Motion<S>::zero() : w.Xup[i].apply(adj[b.parent].F);
    adj[i] = rnea_adjoint_body_terms(b, joint_motion_at(b, wt + iv) + from_parent, w.v[i]);
    for (int k = 0; k < joint_nv(b.type); ++k) gq[iv + k] = dot(from_parent, cross(joint_column(b, k), w.f[i]));
  }
  // leaves to root: the acceleration and velocity adjoints, to the parents
  for (Index i = nb - 1; i >= 0; --i) {
    const Body<S>& b = body[i];
    const Index p = b.parent, iv = b.idx_v;
    const Transform<S>& X = w.Xup[i];
    RneaAdjoint<S>& r = adj[i];
    r.v += cross(joint_motion_at(b, qd + iv), r.a);
    const Motion<S> Xa = X.apply(p < 0 ? a0 : w.a[p]), Xv = p < 0 ? Motion<S>::zero() : X.apply(w.v[p]);
    for (int k = 0; k < joint_nv(b.type); ++k) {
      const Motion<S> s = joint_column(b, k);
      gqdd[iv + k] = dot(s, r.a);
      gqd[iv + k] = dot(cross(w.v[i], s), r.a) + dot(s, r.v);
      gq[iv + k] -= dot(cross(s, Xa), r.a) + dot(cross(s, Xv), r.v);
    }
    if (p >= 0) {
      adj[p].a += X.apply_transpose(r.a);
      adj[p].v += X.apply_transpose(r.v);
    }
  }
}

// ---- forward dynamics -------------------------------------------------------------
// fd and m_inv as aba_jvp_instance's (the caller's general ABA: aba_general with fext
// and gravity, and at rest without gravity for y = (M + diag(armature))^-1 x); they may
// use w as their scratch (each call's values are consumed before the next).

// dqdd = (dqdd/dq) dq + (dqdd/dqd) dqd + M^-1 dtau at (q, qd, tau, fext); qdd (written)
// = FD(q, qd, tau, fext). r: nv scalars of scratch. Returns -1 or the failed DoF.
template <class S, class Fd, class MInv>
SCANDYN_HD Index aba_jvp_general_instance(const Body<S>* body, Index nb, Index nv, const Motion<S>& a0, const S* q,
                                          const S* qd, const S* tau, const Force<S>* fext, const S* dq,
                                          const S* dqd, const S* dtau, const S* armature, const GeneralWork<S>& w,
                                          RneaTangent<S>* t, S* r, S* dqdd, S* qdd, Fd&& fd, MInv&& m_inv) {
  const Index failed = fd(q, qd, tau, armature, qdd);
  if (failed >= 0) return failed;
  // r = dtau/dq dq + dtau/dqd dqd (the JVP of ID with dqdd = 0), then dtau - r
  rnea_jvp_general_instance(body, nb, a0, q, qd, static_cast<const S*>(qdd), fext, dq, dqd,
                            static_cast<const S*>(nullptr), w, t, r, static_cast<S*>(nullptr));
  for (Index i = 0; i < nv; ++i) r[i] = dtau[i] - r[i];
  return m_inv(q, static_cast<const S*>(r), armature, dqdd);
}

// gq = (dqdd/dq)^T wt, gqd = (dqdd/dqd)^T wt, gtau = M^-1 wt at (q, qd, tau, fext); qdd
// (written) = FD(q, qd, tau, fext). r: nv scalars of scratch. Returns -1 or the failed
// DoF.
template <class S, class Fd, class MInv>
SCANDYN_HD Index aba_vjp_general_instance(const Body<S>* body, Index nb, Index nv, const Motion<S>& a0, const S* q,
                                          const S* qd, const S* tau, const Force<S>* fext, const S* wt,
                                          const S* armature, const GeneralWork<S>& w, RneaAdjoint<S>* adj, S* r,
                                          S* gq, S* gqd, S* gtau, S* qdd, Fd&& fd, MInv&& m_inv) {
  Index failed = fd(q, qd, tau, armature, qdd);
  if (failed >= 0) return failed;
  failed = m_inv(q, wt, armature, gtau);  // u = M^-1 wt
  if (failed >= 0) return failed;
  rnea_vjp_general_instance(body, nb, a0, q, qd, static_cast<const S*>(qdd), fext, static_cast<const S*>(gtau), w,
                            adj, gq, gqd, r);
  for (Index i = 0; i < nv; ++i) gq[i] = -gq[i], gqd[i] = -gqd[i];
  return -1;
}

}  // namespace scandyn
