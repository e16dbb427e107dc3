// scandyn/algorithm/second_derivatives.hpp: the second-order derivatives of inverse
// dynamics (the nv x nv x nv tensors Pinocchio 3 computes), serial, for robots.
//
// The recursions and their scratch: rnea_second_derivatives runs the analytical
// second-order recursion (Singh, Russell & Wensing, RA-L 2022: one forward and one
// backward pass over (body, ancestor, ancestor) triples;
// rnea_second_derivatives_analytic_instance,
// scandyn/instance/second_derivatives_analytic.hpp), as the engines
// (make_id_second_derivatives, scandyn/engine.hpp) do per instance on every backend.
// rnea_second_derivatives_dual runs the earlier forward-mode version
// (rnea_second_derivatives_instance, scandyn/instance/second_derivatives_instance.hpp:
// 2 nv dual passes of the first-order recursion rnea_derivatives_instance, each
// writing the eps parts of its blocks), kept as the independent reference of the
// tests and benchmarks. rnea_weighted_dq2 (the weighted contraction of d2tau/dq2)
// runs the analytical recursion's weighted variant
// (rnea_weighted_dq2_analytic_instance), rnea_weighted_dq2_dual its dual-pass
// reference (rnea_weighted_dq2_instance).
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
#include "scandyn/instance/second_derivatives_analytic.hpp"
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
  std::vector<S> block;  // (nv x nv, row-major) rnea_weighted_dq2_dual: d/dq_k of dtau/dq in one pass
  std::vector<DerivativeBody<S>> plain;       // (nv) the analytical recursion's world-frame body quantities
  std::vector<WeightedDq2Body<S>> sums;       // (nv) rnea_weighted_dq2: the weighted recursion's per-body sums
};

// The second derivatives of tau = ID(q, qd, qdd, fext) (tensors as above, every entry
// written; dM_dq optional, null: not written), gravity included: the analytical
// recursion (rnea_second_derivatives_analytic_instance) for models of 1-DoF joints,
// the dual passes (rnea_second_derivatives_dual) otherwise.
template <class S>
void rnea_second_derivatives(const ModelTpl<S>& model, SecondDerivativeData<S>& data, const S* q, const S* qd,
                             const S* qdd, const Force<S>* fext, S* d2tau_dq2, S* d2tau_dqd2, S* d2tau_dqdqd,
                             S* dM_dq = nullptr);

// The same tensors by 2 nv forward-mode dual passes of the first-order recursion
// (rnea_second_derivatives_instance): the reference the analytical recursion is
// tested against (O(nv^2 depth) work, 3-24x slower).
template <class S>
void rnea_second_derivatives_dual(const ModelTpl<S>& model, SecondDerivativeData<S>& data, const S* q, const S* qd,
                                  const S* qdd, const Force<S>* fext, S* d2tau_dq2, S* d2tau_dqd2, S* d2tau_dqdqd,
                                  S* dM_dq = nullptr);

// The contraction of d2tau_dq2 with a weight w on tau, without the nv^3 tensor:
// out(j, k) = sum_i w_i d^2 tau_i / dq_j dq_k (nv x nv, row-major, symmetric, every
// entry written), the q-Hessian of w^T ID(q, qd, qdd, fext) for fixed w, gravity
// included. Models of 1-DoF joints: the analytical recursion's weighted variant
// (rnea_weighted_dq2_analytic_instance, instance/second_derivatives_analytic.hpp:
// O(sum of depth) pairs, as the first-order recursion; no nv^3 entry formed), which the variational
// integrator's exact Newton Jacobian runs on every backend
// (scandyn/sim/variational_instance.hpp); other models: rnea_weighted_dq2_dual.
template <class S>
void rnea_weighted_dq2(const ModelTpl<S>& model, SecondDerivativeData<S>& data, const S* q, const S* qd,
                       const S* qdd, const Force<S>* fext, const S* w, S* out);

// The same contraction by nv dual passes of the first-order recursion seeded along
// q's e_k, each contracted with w (rnea_weighted_dq2_instance,
// instance/second_derivatives_instance.hpp; O(nv^2 depth) work): the reference the
// analytical variant is tested against.
template <class S>
void rnea_weighted_dq2_dual(const ModelTpl<S>& model, SecondDerivativeData<S>& data, const S* q, const S* qd,
                            const S* qdd, const Force<S>* fext, const S* w, S* out);

}  // namespace scandyn
