// scandyn/algorithm/chain_directional.hpp: the directional derivative (JVP) and the
// adjoint (VJP) of forward dynamics of unbranched chains as chunked associative
// scans over the links, on the chain forward dynamics' machinery
// (scandyn/algorithm/chain_fd.hpp: Affine6 elements, chunk aggregates, level scans,
// walks). The recursions are those of rnea_jvp_instance / rnea_vjp_instance and
// aba_jvp_instance / aba_vjp_instance (scandyn/instance/directional_instance.hpp),
// whose step functions the walks below call; Featherstone's notation (RBDA ch. 5, 7):
// X_i = Xup of link i (parent p = i - 1), s = S_i the joint's motion subspace (6x1),
// F_i the subtree force at qdd = FD, and x / x* the motion / force cross products.
//
// At qdd = FD(q, qd, tau, fext), with the chain FD's passes 0-3 done (v, U, D, the
// body accelerations a, pass 1's articulated inertias IA and pass 2's articulated bias
// forces pA stored):
//   F   locally   F_i = IA_i a_i + pA_i, the subtree force (the RNEA's
//                 F_i = I a_i + v_i x* I v_i - fext_i + X_{i+1}^T F_{i+1}) by the ABA's
//                 identity f = IA a + pA: no scan
// JVP (dq, dqd, dtau) -> dqdd = M^-1 (dtau - r), r = (dtau/dq) dq + (dtau/dqd) dqd:
//   dv  forward   dv_i = X_i dv_p + s dqd_i - dq_i s x (X_i v_p)             (M = X_i)
//   da  forward   da_i = X_i da_p - dq_i s x (X_i a_p) + dv_i x s qd_i + v_i x s dqd_i
//                 df_i = I da_i + dv_i x* I v_i + v_i x* I dv_i             (M = X_i)
//   dF  backward  dF_i = df_i + X_{i+1}^T (dF_{i+1} + dq_{i+1} s_{i+1} x* F_{i+1})
//                 r_i = s . dF_i                                             (M = X_{i+1}^T)
//   M^-1          the chain FD's passes 2 and 3 at rest (v = 0, w = Ia c = 0, a0 = 0,
//                 no fext, tau = dtau - r), on pass 1's U and D: pass 1 is not rerun.
// VJP (w) -> gq = (dqdd/dq)^T w, gqd = (dqdd/dqd)^T w, gtau = u = M^-1 w (rnea_vjp_instance's
// recursions at the weight u, signs flipped):
//   M^-1          u as above (tau = w), its pass 2 keeping the articulated bias forces
//                 pA_i of the problem at rest, its pass 3 the accelerations: these are
//                 Fbar_i = X_i Fbar_p + s u_i
//   locally       RA_i = IA_i Fbar_i + pA_i (the subtree force of the problem at rest,
//                 by the ABA's identity f = IA a + pA, IA from pass 1: no scan of
//                 ra_i = I Fbar_i, whose partial sums cancel badly in float), and
//                 gq_i = (X_i Fbar_p) . (s x* F_i), rv_i = -(Fbar_i x* I v_i + I (v_i x Fbar_i))
//   RV  backward  RV_i = rv_i + qd_i s x RA_i + X_{i+1}^T RV_{i+1}           (M = X_{i+1}^T)
//                 gqd_i = -((v_i x s) . RA_i + s . RV_i),
//                 gq_i = -(gq_i - (s x X_i a_p) . RA_i - (s x X_i v_p) . RV_i)
// Every pass is an Affine6 scan: a chunk's aggregate built by the previous pass's walk
// where its elements need that walk's values, the levels scanned, and the walk from
// the chunk's carry running the serial step functions. Cost beyond one FD (whose
// passes store a, IA and pA): the JVP 5 Affine6 scans (dv, da, dF, the rest solve's
// two), the VJP 3 (the rest solve's two, RV); neither reruns the Riccati scan of
// pass 1, the expensive one.
//
// Chains as the chain FD's (unbranched chains from the base, several instances, link
// g = b n + i); a floating base is refused (BackendError).
#pragma once

#include <vector>

#include "scandyn/algorithm/chain_fd.hpp"
#include "scandyn/instance/directional_instance.hpp"

namespace scandyn {

// A JVP's or VJP's chain: the FD's (fd, with a stored) and the same chain at rest for
// M^-1 x (rest: v = w = fext = a = null, a0 = 0, its tau the right-hand side x (AoS,
// n x B) or the VJP's weight, its qdd dqdd (JVP) or the link array x (VJP); U, D, u
// and failed shared with fd), the directions and outputs, and the per-link scratch.
template <class S>
struct ChainDirectionalData {
  ChainFdData<S> fd;                 // the forward dynamics' chain and scratch (a set)
  ChainFdData<S> rest;               // the chain at rest (see above)
  BatchView<const S> dq, dqd, dtau;  // (n x B) JVP directions
  BatchView<S> gq, gqd, gtau;        // (n x B) VJP outputs
  Force<S>* F = nullptr;             // (B n) pass 2's pA_i (fd.pA_out), then the subtree forces F_i
  Motion<S>* dv = nullptr;           // (B n) JVP: dv_i; VJP: Fbar_i
  Force<S>* df = nullptr;            // (B n) JVP: df_i; VJP: the rest pass 2's pA_i, then RA_i
  S* x = nullptr;                    // (B n) JVP: dtau - r; VJP: u = M^-1 w, then gq's first term

  SCANDYN_HD Index count() const { return fd.count(); }
  SCANDYN_HD bool ok(Index g) const { return fd.failed[g / fd.n] < 0; }
  SCANDYN_HD S in(const BatchView<const S>& x_in, Index g) const { return x_in.at(g % fd.n, g / fd.n); }
  // the parent's velocity and acceleration (0 and a0 at a chain's first link)
  SCANDYN_HD Motion<S> v_parent(Index g) const { return fd.has_parent(g) ? fd.v[g - 1] : Motion<S>::zero(); }
  SCANDYN_HD Motion<S> a_parent(Index g) const { return fd.has_parent(g) ? fd.a[g - 1] : fd.a0; }
};

// ---- elements -----------------------------------------------------------------

// Identity aggregate (an empty chunk's).
template <class S>
SCANDYN_HD Affine6<S> affine_identity() {
  return {Mat6<S>::identity(), Vec6<S>::zero(), false};
}

// A forward (root to leaf) element of link g: x_g = X_g x_p + b, constant b at a
// chain's first link (no parent).
template <class S>
SCANDYN_HD Affine6<S> motion_element(const ChainFdData<S>& d, Index g, const Transform<S>& X, const Vec6<S>& b) {
  return d.has_parent(g) ? Affine6<S>{to_mat6(X), b, false} : Affine6<S>::make_constant(b);
}

// A backward (leaf to root) element of link g: y_g = X_{g+1}^T y_{g+1} + b, constant
// b at a chain's last link (no child; Xnext then unused).
template <class S>
SCANDYN_HD Affine6<S> force_element(const ChainFdData<S>& d, Index g, const Transform<S>& Xnext, const Vec6<S>& b) {
  return d.has_child(g) ? Affine6<S>{transpose(to_mat6(Xnext)), b, false} : Affine6<S>::make_constant(b);
}

// The next link's transform X_{g+1} (the identity past a chain's last link, unused there).
template <class S>
SCANDYN_HD Transform<S> next_transform(const ChainFdData<S>& d, Index g) {
  return d.has_child(g) ? d.Xup(g + 1) : Transform<S>::identity();
}

// The rest solve's pass-2 element of link g with right-hand side tau (pass 1's U, D).
template <class S>
SCANDYN_HD Affine6<S> rest_bias_element(const ChainFdData<S>& d, Index g, const Transform<S>& Xnext, S tau) {
  return bias_element(d.body_of(g), d.has_child(g), Xnext, d.U[g], S(1) / d.D[g], Force<S>::zero(), Force<S>::zero(),
                      tau);
}

// ---- the subtree forces F (both) ------------------------------------------------

// F_i = IA_i a_i + pA_i for links s..e: the force across joint i at qdd = FD (the
// RNEA's subtree force I a + v x* I v - fext summed over the subtree) by the ABA's
// own identity, from pass 1's IA (fd.IA_out), pass 3's a and pass 2's articulated
// bias force pA, which fd.pA_out = F holds: local, no scan.
template <class S>
SCANDYN_HD void subtree_force_local(const ChainDirectionalData<S>& d, Index s, Index e) {
  for (Index g = s; g <= e; ++g) d.F[g] = d.fd.IA_out[g] * d.fd.a[g] + d.F[g];
}

// ---- JVP ------------------------------------------------------------------------

// dv's aggregate of links s..e: dv_e as a map of dv_{s-1}.
template <class S>
SCANDYN_HD Affine6<S> jvp_velocity_aggregate(const ChainDirectionalData<S>& d, Index s, Index e) {
  const ChainFdData<S>& c = d.fd;
  Affine6<S> agg = affine_identity<S>();
  for (Index g = s; g <= e; ++g) {
    const Transform<S> X = c.Xup(g);
    const Motion<S> b = rnea_tangent_velocity_step(c.body_of(g), X, d.v_parent(g), Motion<S>::zero(), d.in(d.dq, g),
                                                   d.in(d.dqd, g));
    agg = Affine6<S>::compose(motion_element(c, g, X, to_vec6(b)), agg);
  }
  return agg;
}

// dv's walk from dv_{s-1}: stores dv; returns da's aggregate, da_e as a map of da_{s-1}.
template <class S>
SCANDYN_HD Affine6<S> jvp_velocity_walk(const ChainDirectionalData<S>& d, Index s, Index e, const Vec6<S>& dv_in) {
  const ChainFdData<S>& c = d.fd;
  Motion<S> dvp = to_motion(dv_in);
  Affine6<S> agg = affine_identity<S>();
  for (Index g = s; g <= e; ++g) {
    const Body<S>& b = c.body_of(g);
    const Transform<S> X = c.Xup(g);
    const S dq = d.in(d.dq, g), dqd = d.in(d.dqd, g);
    const Motion<S> dv =
        rnea_tangent_velocity_step(b, X, d.v_parent(g), c.has_parent(g) ? dvp : Motion<S>::zero(), dq, dqd);
    d.dv[g] = dv;
    dvp = dv;
    const Motion<S> da0 = rnea_tangent_acceleration_step(b, X, d.a_parent(g), Motion<S>::zero(), c.v[g], dv,
                                                         c.qd_of(g), dq, dqd, S(0));
    agg = Affine6<S>::compose(motion_element(c, g, X, to_vec6(da0)), agg);
  }
  return agg;
}

// da's walk from da_{s-1}: stores df; returns dF's aggregate, dF_s as a map of dF_{e+1}
// (F stored).
template <class S>
SCANDYN_HD Affine6<S> jvp_acceleration_walk(const ChainDirectionalData<S>& d, Index s, Index e, const Vec6<S>& da_in) {
  const ChainFdData<S>& c = d.fd;
  Motion<S> dap = to_motion(da_in);
  Affine6<S> agg = affine_identity<S>();
  for (Index g = s; g <= e; ++g) {
    const Body<S>& b = c.body_of(g);
    const Transform<S> X = c.Xup(g);
    const Motion<S> da =
        rnea_tangent_acceleration_step(b, X, d.a_parent(g), c.has_parent(g) ? dap : Motion<S>::zero(), c.v[g],
                                       d.dv[g], c.qd_of(g), d.in(d.dq, g), d.in(d.dqd, g), S(0));
    dap = da;
    const Force<S> df = rnea_tangent_force_step(b, c.v[g], d.dv[g], da);
    d.df[g] = df;
    // dF_g = df_g + X_{g+1}^T (dq_{g+1} s_{g+1} x* F_{g+1}) + X_{g+1}^T dF_{g+1}
    Force<S> off = df;
    const bool child = c.has_child(g);
    const Transform<S> Xn = child ? c.Xup(g + 1) : X;
    if (child)
      off += Xn.apply_transpose(
          rnea_tangent_subtree_force(c.body_of(g + 1), Force<S>::zero(), d.in(d.dq, g + 1), d.F[g + 1]));
    agg = Affine6<S>::compose(agg, force_element(c, g, Xn, to_vec6(off)));
  }
  return agg;
}

// dF's walk from dF_{e+1}: stores x = dtau - s . dF; returns the rest solve's pass-2
// aggregate (right-hand side x), z_s as a map of z_{e+1}.
template <class S>
SCANDYN_HD Affine6<S> jvp_force_walk(const ChainDirectionalData<S>& d, Index s, Index e, const Vec6<S>& dF_in) {
  const ChainFdData<S>& c = d.fd;
  Force<S> dF = to_force(dF_in);  // dF of link g + 1
  Affine6<S> agg = affine_identity<S>();
  for (Index g = e; g >= s; --g) {
    const Body<S>& b = c.body_of(g);
    const Transform<S> Xn = next_transform(c, g);
    dF = c.has_child(g)
             ? d.df[g] + Xn.apply_transpose(rnea_tangent_subtree_force(c.body_of(g + 1), dF, d.in(d.dq, g + 1), d.F[g + 1]))
             : d.df[g];
    const S rhs = d.in(d.dtau, g) - joint_project(b, dF);
    d.x[g] = rhs;
    agg = Affine6<S>::compose(rest_bias_element(c, g, Xn, rhs), agg);
  }
  return agg;
}

// ---- VJP ------------------------------------------------------------------------

// The rest solve's pass-2 aggregate of links s..e for u = M^-1 w: z_s as a map of
// z_{e+1}.
template <class S>
SCANDYN_HD Affine6<S> vjp_rest_bias_aggregate(const ChainDirectionalData<S>& d, Index s, Index e) {
  Affine6<S> agg = affine_identity<S>();
  for (Index g = s; g <= e; ++g)
    agg = Affine6<S>::compose(agg, rest_bias_element(d.fd, g, next_transform(d.fd, g), d.rest.tau_of(g)));
  return agg;
}

// After the rest solve's walk of pass 3 over links s..e (u = M^-1 w in x, the rest
// accelerations Fbar_i = X_i Fbar_p + s u_i in dv, the rest pass 2's pA in df; Fbar_in:
// Fbar_{s-1}, the carry that walk started from): gtau = u (instances not failed),
// RA_i = IA_i Fbar_i + pA_i in df (the subtree force of the rest problem by the ABA's
// own identity, f = IA a + pA, local: no scan), gq's first term
// (X_i Fbar_p) . (s x* F_i) in x; returns RV's aggregate, RV_s as a map of RV_{e+1}.
template <class S>
SCANDYN_HD Affine6<S> vjp_adjoint_walk(const ChainDirectionalData<S>& d, Index s, Index e, const Vec6<S>& Fbar_in) {
  const ChainFdData<S>& c = d.fd;
  Motion<S> Fbar_p = to_motion(Fbar_in);
  Affine6<S> agg = affine_identity<S>();
  for (Index g = s; g <= e; ++g) {
    const Body<S>& b = c.body_of(g);
    const Motion<S> from_parent = c.has_parent(g) ? c.Xup(g).apply(Fbar_p) : Motion<S>::zero();
    const S u = d.x[g];
    if (d.ok(g)) d.gtau.at(g % c.n, g / c.n) = u;
    const RneaAdjoint<S> r = rnea_adjoint_body_terms(b, d.dv[g], c.v[g]);
    const Force<S> RA = c.IA_out[g] * r.F + d.df[g];
    d.df[g] = RA;
    d.x[g] = dot(from_parent, cross(joint_motion(b, S(1)), d.F[g]));
    const Force<S> off = r.v + rnea_adjoint_velocity_from_acceleration(b, c.qd_of(g), RA);
    agg = Affine6<S>::compose(agg, force_element(c, g, next_transform(c, g), to_vec6(off)));
    Fbar_p = r.F;
  }
  return agg;
}

// RV's walk from RV_{e+1}: gq and gqd (instances not failed).
template <class S>
SCANDYN_HD void vjp_rv_walk(const ChainDirectionalData<S>& d, Index s, Index e, const Vec6<S>& RV_in) {
  const ChainFdData<S>& c = d.fd;
  Force<S> RV = to_force(RV_in);  // of link g + 1
  for (Index g = e; g >= s; --g) {
    const Body<S>& b = c.body_of(g);
    const Transform<S> X = c.Xup(g);
    const RneaAdjoint<S> r = rnea_adjoint_body_terms(b, d.dv[g], c.v[g]);
    const Force<S> RA = d.df[g];
    const Force<S> own = r.v + rnea_adjoint_velocity_from_acceleration(b, c.qd_of(g), RA);
    RV = c.has_child(g) ? own + c.Xup(g + 1).apply_transpose(RV) : own;
    S gq = d.x[g], gqd, gqdd;
    rnea_adjoint_gradients(b, X, d.a_parent(g), d.v_parent(g), c.v[g], RA, RV, gq, gqd, gqdd);
    if (d.ok(g)) {
      d.gq.at(g % c.n, g / c.n) = -gq;
      d.gqd.at(g % c.n, g / c.n) = -gqd;
    }
  }
}

// ---- the CPU engine --------------------------------------------------------------

// The JVP and VJP of forward dynamics of B instances of unbranched chains from the
// base by the scans above, on the host with OpenMP threads (1: serial); the chain FD's
// chunking (ChainForwardDynamics). Owns all scratch for max_batch instances; calls
// allocate nothing. A floating base (a free rope) is refused with a BackendError.
template <class S>
class ChainFdDirectional {
 public:
  ChainFdDirectional(const ModelTpl<S>& model, Index max_batch, int threads = 0, Index chunk = 0);

  // qdd = FD(in) and dqdd = (dqdd/dq) dq + (dqdd/dqd) dqd + M^-1 dtau (n x B views,
  // B = in.q.batch). Returns the number of failed instances (articulated pivot D not
  // positive and finite; their qdd and dqdd are left unwritten); failed, when not
  // null, receives B entries: -1 or the first failed DoF.
  Index jvp(const FdBatchIn<S>& in, const BatchView<const S>& dq, const BatchView<const S>& dqd,
            const BatchView<const S>& dtau, const BatchView<S>& qdd, const BatchView<S>& dqdd, int* failed = nullptr);

  // qdd = FD(in) and, for the weight w on qdd, gq = (dqdd/dq)^T w, gqd = (dqdd/dqd)^T w,
  // gtau = M^-1 w. Failures as jvp (outputs of a failed instance unwritten).
  Index vjp(const FdBatchIn<S>& in, const BatchView<const S>& w, const BatchView<S>& qdd, const BatchView<S>& gq,
            const BatchView<S>& gqd, const BatchView<S>& gtau, int* failed = nullptr);

  Index links() const { return n_; }
  Index max_batch() const { return max_batch_; }
  int threads() const { return threads_; }
  Index chunk() const { return chunk_; }

 private:
  ChainDirectionalData<S> bind(const FdBatchIn<S>& in, const BatchView<S>& qdd);  // fd passes' data
  Index finish(Index B, int* failed) const;

  Index n_ = 0, max_batch_ = 0, chunk_ = 0;
  int threads_ = 1;
  Motion<S> a0_;
  ChainBodies<S> bodies_;
  std::vector<Motion<S>> v_, a_, dv_;
  std::vector<Force<S>> U_, w_, F_, df_;
  std::vector<ABInertia<S>> IA_;  // (links) pass 1's IA
  std::vector<S> D_, u_, x_;
  std::vector<int> failed_;
  ChainLevels<Affine6<S>> aff_;
  ChainLevels<DualRiccati<DualScalar>> dual_;
};

}  // namespace scandyn
