// scandyn/algorithm/second_derivatives.hpp: the second-order derivatives of inverse
// dynamics (the nv x nv x nv tensors Pinocchio 3 computes), serial, for robots.
//
// The recursion and its scratch: scandyn/instance/second_derivatives_instance.hpp
// (rnea_second_derivatives_instance, 2 nv dual passes of the first-order recursion
// rnea_derivatives_instance, each writing the eps parts of its blocks), which these
// functions run on the host; the engines (make_id_second_derivatives,
// scandyn/engine.hpp) run it per instance on every backend.
//
// Tensors: nv x nv x nv, entry (i, j, k) at data[(i * nv + j) * nv + k]:
//   d2tau_dq2(i, j, k)    = d^2 tau_i / dq_j dq_k    (symmetric in j, k)
//   d2tau_dqd2(i, j, k)   = d^2 tau_i / dqd_j dqd_k  (symmetric in j, k)
//   d2tau_dqdqd(i, j, k)  = d^2 tau_i / dq_j dqd_k
// (d tau / d qdd = M(q) does not depend on qdd or qd: d M_ij / dq_k is the
// eps part of M along e_k, written to dM_dq when not null.)
#pragma once

#include <vector>

#include "scandyn/algorithm/derivatives.hpp"
#include "scandyn/instance/second_derivatives_instance.hpp"

namespace scandyn {

// Scratch for rnea_second_derivatives and rnea_weighted_dq2: the model in dual
// numbers and the passes' scratch (made once per model).
template <class S>
struct SecondDerivativeData {
  explicit SecondDerivativeData(const ModelTpl<S>& model);
  std::vector<Body<Dual<S>>> bodies;          // (nv) the model's bodies, every derivative part 0
  std::vector<DerivativeBody<Dual<S>>> work;  // (nv) one pass's world-frame body quantities
  std::vector<Force<Dual<S>>> wrenches;       // (nv) the body wrenches in dual numbers
  std::vector<S> block;  // (nv x nv, row-major) rnea_weighted_dq2: d/dq_k of dtau/dq in one pass
};

// The second derivatives of tau = ID(q, qd, qdd, fext) (tensors as above, every entry
// written; dM_dq optional, null: not written), gravity included.
template <class S>
void rnea_second_derivatives(const ModelTpl<S>& model, SecondDerivativeData<S>& data, const S* q, const S* qd,
                             const S* qdd, const Force<S>* fext, S* d2tau_dq2, S* d2tau_dqd2, S* d2tau_dqdqd,
                             S* dM_dq = nullptr);

// The contraction of d2tau_dq2 with a weight w on tau, without the nv^3 tensor:
// out(j, k) = sum_i w_i d^2 tau_i / dq_j dq_k (nv x nv, row-major, symmetric), the
// q-Hessian of w^T ID(q, qd, qdd, fext) for fixed w. The same nv dual passes of
// the first-order recursion seeded along q's e_k (O(nv^2 depth) work), by
// rnea_weighted_dq2_instance (instance/second_derivatives_instance.hpp), which the
// variational integrator's exact Newton Jacobian runs on every backend
// (scandyn/sim/variational_instance.hpp).
template <class S>
void rnea_weighted_dq2(const ModelTpl<S>& model, SecondDerivativeData<S>& data, const S* q, const S* qd,
                       const S* qdd, const Force<S>* fext, const S* w, S* out);

}  // namespace scandyn
