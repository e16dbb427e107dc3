// scandyn/algorithm/fd_check.hpp: a run-time accuracy check of a forward dynamics
// result, per instance: the residual r = ID(q, qd, qdd) - tau and, from it, an
// estimate of qdd's error.
//
// Given q, qd, tau (and fext, armature) and a computed qdd, from any engine:
//
//   r       = ID(q, qd, qdd) - tau                 one RNEA (the reference rnea)
//   delta   = M(q)^-1 r                            ABA's passes 2 and 3 without
//                                                  velocity terms or gravity, on the
//                                                  RNEA's transforms (no CRBA, no nv^2)
//   error_estimate    = max_i |delta_i| / max(1, max_i |qdd_i|)
//   relative_residual = max_i |r_i| / max(max_i |tau_i|, max_i |ID_i|, max_i load_i)
//
// qdd - delta is one step of iterative refinement: delta is, to first order in the
// error, qdd minus the exact FD(q, qd, tau) (M^-1 is linear, and a relative error
// e of the solver's M^-1 changes delta by e delta only), so error_estimate
// estimates the error in the metric the accuracy report uses (scandyn::rel_err:
// max_i |qdd_i - truth_i| / max(1, max_i |truth_i|)). The residual alone cannot: it
// measures how well qdd satisfies the equations (backward error), and the mass
// matrix of a long chain turns a backward error of 1e-7 into a forward error of
// 1e-1 (cond(M) grows like n^4): float CRBA + Cholesky (JSI) is backward stable and
// still 0.2 off on chain:64; docs/accuracy.md has the measured ranges of both
// quantities and why the threshold is on error_estimate.
//
// Precision: the check runs in R, the model's scalar, on inputs in S (converted to
// R exactly when R is at least as wide). For a float result run it in double
// (ModelTpl<double>): the error a float engine makes on a long chain comes largely
// from rounding the model and the joint transforms to float, which a float RNEA
// shares and so cannot see (float ABA on rope:10^4: true error 9e-4, estimated 1e-5
// by a float check, 9e-4 by a double one).
//
// Cost: one RNEA plus ABA's articulated-inertia and acceleration passes, in R;
// measured against one ABA / JSI call in docs/accuracy.md (bench/fd_residual_cost.cpp).
//
// Loads: load_i is the size of the wrench joint i transmits (RNEA's F_i, the
// constraint components included): |n_i| for a revolute joint, |f_i| for a
// prismatic one. It keeps relative_residual meaningful for rows whose torques are
// zero or far smaller than the forces inside the tree (free fall, gravity-dominated
// poses).
#pragma once

#include "scandyn/algorithm/reference.hpp"

namespace scandyn {

// ---- per-DoF core (host and device) --------------------------------------------

// Running maxima over the DoFs of one instance.
template <class S>
struct FdCheckNorms {
  S residual = S(0);  // max_i |ID_i - tau_i|
  S scale = S(0);     // max_i max(|tau_i|, |ID_i|, load_i)
  S delta = S(0);     // max_i |delta_i|
  S qdd = S(1);       // max(1, max_i |qdd_i|)
};

// The joint load of a wrench F transmitted by body b's joint: |n| (revolute), |f| (prismatic).
template <class S>
SCANDYN_HD S joint_load(const Body<S>& b, const Force<S>& F) {
  const Vec3<S>& x = b.type == JointType::Revolute ? F.n : F.f;
  return ScalarMath<S>::sqrt(dot(x, x));
}

// Folds DoF i's ID_i, tau_i and load_i in; returns r_i = ID_i - tau_i.
template <class S>
SCANDYN_HD S fd_check_residual(FdCheckNorms<S>& n, S id_i, S tau_i, S load_i) {
  using M = ScalarMath<S>;
  const S r = id_i - tau_i;
  const S a = M::abs(r), t = M::abs(tau_i), d = M::abs(id_i);
  // comparisons written so that a NaN propagates into the maxima
  if (!(a <= n.residual)) n.residual = a;
  if (t > n.scale) n.scale = t;
  if (d > n.scale) n.scale = d;
  if (load_i > n.scale) n.scale = load_i;
  return r;
}

// Folds DoF i's correction delta_i and result qdd_i in.
template <class S>
SCANDYN_HD void fd_check_delta(FdCheckNorms<S>& n, S delta_i, S qdd_i) {
  using M = ScalarMath<S>;
  const S a = M::abs(delta_i), q = M::abs(qdd_i);
  if (!(a <= n.delta)) n.delta = a;
  if (!(q <= n.qdd)) n.qdd = q;
}

// max_i |delta_i| / max(1, max_i |qdd_i|): the estimated error (NaN stays NaN).
template <class S>
SCANDYN_HD S fd_error_estimate(const FdCheckNorms<S>& n) {
  return n.delta / n.qdd;
}

// max_i |r_i| / scale (0 for an all-zero row: nothing to compare with).
template <class S>
SCANDYN_HD S fd_relative_residual(const FdCheckNorms<S>& n) {
  return n.scale > S(0) ? n.residual / n.scale : (n.residual == S(0) ? S(0) : n.residual);
}

// The default threshold on error_estimate for a result computed in S: the accuracy
// report's budget for S (float 1e-4, double 1e-10), so that a flag means "error
// above the budget". Measured by bench/fd_residual_study.cpp (docs/accuracy.md;
// 10^4 random states per robot, 2500 per rope of 10..300 links, chain:64,
// tree:100:7, ropes to 10^5 links; the check in double): on float results the
// estimate equals the true error to two digits wherever that is above 10 epsilon
// (on float JSI's bad rows, errors of 1e-2..1, within a factor 0.005..1.3: still
// far above the threshold); on double results it is within 0.01..4 of it (below on
// long ropes, whose double error, < 2e-13, is far under the budget). Hence 0 false
// positives on 77011 clean float and 82540 clean double results, and all 7711 float
// and 3584 double results beyond the budget caught.
template <class S>
constexpr double fd_check_threshold() {
  return sizeof(S) <= sizeof(float) ? 1e-4 : 1e-10;
}

// ---- the check on the host (the reference level) ---------------------------------

// Outcome of fd_check.
template <class R>
struct FdCheck {
  R error_estimate = R(0);     // max_i |delta_i| / max(1, max_i |qdd_i|), delta = M^-1 (ID - tau)
  R relative_residual = R(0);  // max_i |ID_i - tau_i| / max(|tau|, |ID|, joint loads)
  R residual = R(0);           // max_i |ID_i - tau_i| (N m or N)
  Index failed_dof = -1;       // an articulated pivot that was not positive and finite
                               // (error_estimate is then +inf)
  // true when the estimate is at most threshold (NaN and +inf fail)
  bool ok(double threshold) const { return error_estimate <= R(threshold); }
};

// Checks qdd against FD(q, qd, tau) as described above, in the model's scalar R;
// inputs (nv each; fext nv wrenches or null; armature nv joint inertias or null, as
// given to aba) in S. delta_out, when not null, receives M^-1 r (nv entries, in R):
// qdd - delta is the refined result. Uses data's scratch (Xup, v, a, f, IA, U, D, u,
// h); allocates nothing.
template <class R, class S>
FdCheck<R> fd_check(const ModelTpl<R>& model, DataTpl<R>& data, const S* q, const S* qd, const S* tau,
                    const S* qdd, const Force<S>* fext = nullptr, const S* armature = nullptr,
                    R* delta_out = nullptr) {
  const Index n = model.nv();
  // inputs in R: q in u, qd in D, qdd in h (scratch the RNEA does not touch)
  for (Index i = 0; i < n; ++i) {
    data.u[i] = R(q[i]);
    data.D[i] = R(qd[i]);
    data.h[i] = R(qdd[i]);
  }
  // fext in R: through the ABA's U vector, free until pass 2 below
  if (fext)
    for (Index i = 0; i < n; ++i) data.U[i] = fext[i].template cast<R>();
  // r = ID(q, qd, qdd) - tau (+ armature qdd), into data.h after its qdd is read
  rnea(model, data, data.u.data(), data.D.data(), data.h.data(), data.h.data(), fext ? data.U.data() : nullptr);
  // data.h now holds ID; data.f the joint wrenches F_i; data.Xup the transforms at q
  FdCheckNorms<R> norms;
  for (Index i = 0; i < n; ++i) {
    R id = data.h[i];
    if (armature) id += R(armature[i]) * R(qdd[i]);
    data.h[i] = fd_check_residual(norms, id, R(tau[i]), joint_load(model.bodies[i], data.f[i]));
  }
  // delta = M^-1 r: ABA's pass 2 with v = 0, c = 0, no gravity, pA from r alone
  FdCheck<R> out;
  for (Index i = 0; i < n; ++i) {
    data.IA[i] = ABInertia<R>::from(model.bodies[i].I);
    data.f[i] = Force<R>::zero();
  }
  const Motion<R> zero = Motion<R>::zero();
  for (Index i = n - 1; i >= 0; --i) {
    const Body<R>& b = model.bodies[i];
    aba_joint_terms(b, data.IA[i], data.f[i], data.h[i], data.U[i], data.D[i], data.u[i],
                    armature ? R(armature[i]) : R(0));
    if (!pivot_ok(data.D[i])) {
      out.failed_dof = i;
      out.error_estimate = R(1) / R(0);
      out.residual = norms.residual;
      out.relative_residual = fd_relative_residual(norms);
      return out;
    }
    if (b.parent >= 0)
      aba_backward_to_parent(data.Xup[i], data.IA[i], data.f[i], zero, data.U[i], data.D[i], data.u[i],
                             data.IA[b.parent], data.f[b.parent]);
  }
  // pass 3 from a zero base acceleration
  for (Index i = 0; i < n; ++i) {
    const Body<R>& b = model.bodies[i];
    const R d = aba_acceleration_step(b, data.Xup[i], b.parent < 0 ? zero : data.a[b.parent], zero, data.U[i],
                                      data.D[i], data.u[i], data.a[i]);
    fd_check_delta(norms, d, R(qdd[i]));
    if (delta_out) delta_out[i] = d;
  }
  out.error_estimate = fd_error_estimate(norms);
  out.residual = norms.residual;
  out.relative_residual = fd_relative_residual(norms);
  return out;
}

}  // namespace scandyn
