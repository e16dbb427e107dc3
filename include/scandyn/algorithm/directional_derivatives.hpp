// scandyn/algorithm/directional_derivatives.hpp: the directional derivative (a
// Jacobian-vector product) of inverse dynamics and its adjoint (a vector-Jacobian
// product), O(nv) each, for models whose nv x nv derivative matrices do not fit
// (ropes of 10^5 links).
//
// Forward mode through the RNEA's recursions in body frames: every quantity x of the
// RNEA gets its tangent dx = (d x / d(q, qd, qdd)) (dq, dqd, dqdd), and each step's
// tangent is the derivative of the step (steps.hpp). With dXup/dq_i = -crm(S_i) Xup
// for body i's joint (the joint moves the body frame):
//   dv_i = Xup dv_p - dq_i S_i x (Xup v_p) + S_i dqd_i
//   da_i = Xup da_p - dq_i S_i x (Xup a_p) + S_i dqdd_i + dv_i x S_i qd_i + v_i x S_i dqd_i
//   df_i = I_i da_i + dv_i x* I_i v_i + v_i x* I_i dv_i        (fext fixed in body frames)
//   dF_p += Xup^T (dF_i + dq_i S_i x* F_i),   dtau_i = S_i . dF_i
// The forward part is the tangent of the scan elements (v, a) -> (Xup v + S qd, ...):
// the pair (value, tangent) composes as the element does.
//
// The functions below are the serial entry points (a model and host scratch); the
// recursions themselves are the __host__ __device__ functions of
// scandyn/instance/directional_instance.hpp, which the CUDA rollout kernels run too
// (models of 1-DoF joints), and for multi-DoF joints those of
// scandyn/instance/directional_general_instance.hpp (serial and OpenMP).
#pragma once

#include <vector>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/instance/directional_instance.hpp"

namespace scandyn {

// Scratch for rnea_jvp and rnea_vjp (no allocation in a call).
template <class S>
struct RneaJvpData {
  explicit RneaJvpData(const ModelTpl<S>& model)
      : rnea(model, /*mass_matrix=*/false), t(model.nv()), adj(model.nv()) {}
  DataTpl<S> rnea;                  // the RNEA's values (Xup, v, a, f)
  std::vector<RneaTangent<S>> t;    // (nv) tangents (rnea_jvp)
  std::vector<RneaAdjoint<S>> adj;  // (nv) adjoints (rnea_vjp)
};

// dtau = (d ID / d q) dq + (d ID / d qd) dqd + M dqdd at (q, qd, qdd, fext), in
// O(nv); tau (optional) = ID(q, qd, qdd, fext). Every array has nv entries (q: nq);
// fext: one wrench per body (body frames) or null.
template <class S>
void rnea_jvp(const ModelTpl<S>& model, RneaJvpData<S>& data, const S* q, const S* qd, const S* qdd,
              const Force<S>* fext, const S* dq, const S* dqd, const S* dqdd, S* dtau, S* tau = nullptr);

// The vector-Jacobian product (adjoint) of inverse dynamics in O(nv): for a weight w
// on tau, gq = (dtau/dq)^T w, gqd = (dtau/dqd)^T w, gqdd = M w. Reverse mode through
// the same recursions: the adjoint of the subtree forces runs root to leaves
// (Fbar_i = w_i S_i + Xup_i Fbar_p), those of the accelerations and velocities leaves
// to root (abar_p += Xup^T abar_i): the scans of rnea_jvp, reversed.
template <class S>
void rnea_vjp(const ModelTpl<S>& model, RneaJvpData<S>& data, const S* q, const S* qd, const S* qdd,
              const Force<S>* fext, const S* w, S* gq, S* gqd, S* gqdd);  // gqdd holds tau meanwhile

// ---- forward dynamics ----------------------------------------------------------
// At qdd = FD(q, qd, tau, fext): dqdd = M^-1 (dtau - dtau/dq dq - dtau/dqd dqd), and
// the adjoint of a weight w on qdd is u = M^-1 w: gq = -(dtau/dq)^T u, gqd =
// -(dtau/dqd)^T u, gtau = u. M^-1 x costs one ABA of the model without gravity at rest
// (qdd = M^-1 tau there), so both are O(nv).

// Scratch for aba_jvp and aba_vjp: the inverse dynamics' scratch, the model again
// without gravity (made once), the ABA's scratch and three nv rows.
template <class S>
struct AbaJvpData {
  explicit AbaJvpData(const ModelTpl<S>& model);
  RneaJvpData<S> id;
  ModelTpl<S> at_rest;    // the model with gravity 0: aba(at_rest, q, 0, x) = M^-1 x
  DataTpl<S> aba;
  std::vector<S> zero, r0, r1;  // (nv) zeros, then two rows of scratch
};

// dqdd = (dqdd/dq) dq + (dqdd/dqd) dqd + M^-1 dtau at (q, qd, tau, fext); qdd (nv
// entries, written) = FD(q, qd, tau, fext). Reports the ABA's failed pivot.
// armature (nv, or null): joint-space inertia on M's diagonal, as aba's (then M
// reads M + diag(armature) above, in both functions).
template <class S>
Status aba_jvp(const ModelTpl<S>& model, AbaJvpData<S>& data, const S* q, const S* qd, const S* tau,
               const Force<S>* fext, const S* dq, const S* dqd, const S* dtau, S* dqdd, S* qdd,
               const S* armature = nullptr);

// gq = (dqdd/dq)^T w, gqd = (dqdd/dqd)^T w, gtau = M^-1 w at (q, qd, tau, fext); qdd
// (written) = FD(q, qd, tau, fext).
template <class S>
Status aba_vjp(const ModelTpl<S>& model, AbaJvpData<S>& data, const S* q, const S* qd, const S* tau,
               const Force<S>* fext, const S* w, S* gq, S* gqd, S* gtau, S* qdd, const S* armature = nullptr);

// ---- multi-DoF joints ------------------------------------------------------------
// The four functions above take models with a floating base and spherical joints too
// (ModelTpl::multi_dof): q has nq entries, its tangent dq and the gradient gq nv, in
// the dense derivatives' tangent convention (a joint's increment q (+) d = q exp(d) in
// the child's frame; docs/derivatives.md). They dispatch to these (the recursions of
// scandyn/instance/directional_general_instance.hpp; src/algorithm/directional_general.cpp),
// whose arguments are theirs.
template <class S>
void rnea_jvp_at(const ModelTpl<S>& model, RneaJvpData<S>& data, const S* q, const S* qd, const S* qdd,
                 const Force<S>* fext, const S* dq, const S* dqd, const S* dqdd, S* dtau, S* tau);
template <class S>
void rnea_vjp_at(const ModelTpl<S>& model, RneaJvpData<S>& data, const S* q, const S* qd, const S* qdd,
                 const Force<S>* fext, const S* w, S* gq, S* gqd, S* gqdd);
template <class S>
Status aba_jvp_at(const ModelTpl<S>& model, AbaJvpData<S>& data, const S* q, const S* qd, const S* tau,
                  const Force<S>* fext, const S* dq, const S* dqd, const S* dtau, S* dqdd, S* qdd,
                  const S* armature);
template <class S>
Status aba_vjp_at(const ModelTpl<S>& model, AbaJvpData<S>& data, const S* q, const S* qd, const S* tau,
                  const Force<S>* fext, const S* w, S* gq, S* gqd, S* gtau, S* qdd, const S* armature);

}  // namespace scandyn
