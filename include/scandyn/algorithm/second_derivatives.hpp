// scandyn/algorithm/second_derivatives.hpp: the second-order derivatives of inverse
// dynamics (the nv x nv x nv tensors Pinocchio 3 computes), serial, for robots.
//
// Forward mode over the analytical first-order derivatives: the recursions of
// rnea_derivatives_instance (Carpentier & Mansard 2018; scandyn/instance/
// dynamics_derivatives.hpp) run in the dual numbers Dual<S> = S + S eps (eps^2 = 0)
// with q (or qd) seeded along e_k, so that the eps part of each first-order entry is
// its derivative along e_k, exactly (no step, no truncation): one pass per k and per
// variable, 2 nv passes of the first-order recursion (O(nv^2 depth) work in total).
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

namespace scandyn {

// A dual number v + d eps, eps^2 = 0: the value and its derivative along one
// direction. Comparisons look at the value (the branch the value takes).
template <class S>
struct Dual {
  S v = S(0), d = S(0);
  SCANDYN_HD Dual() = default;
  SCANDYN_HD Dual(S value) : v(value) {}  // NOLINT: constants are duals with d = 0
  SCANDYN_HD Dual(S value, S derivative) : v(value), d(derivative) {}
  SCANDYN_HD explicit operator S() const { return v; }

  SCANDYN_HD friend Dual operator+(const Dual& a, const Dual& b) { return {a.v + b.v, a.d + b.d}; }
  SCANDYN_HD friend Dual operator-(const Dual& a, const Dual& b) { return {a.v - b.v, a.d - b.d}; }
  SCANDYN_HD friend Dual operator*(const Dual& a, const Dual& b) { return {a.v * b.v, a.d * b.v + a.v * b.d}; }
  SCANDYN_HD friend Dual operator/(const Dual& a, const Dual& b) {
    return {a.v / b.v, (a.d * b.v - a.v * b.d) / (b.v * b.v)};
  }
  SCANDYN_HD friend Dual operator-(const Dual& a) { return {-a.v, -a.d}; }
  SCANDYN_HD Dual& operator+=(const Dual& b) { return *this = *this + b; }
  SCANDYN_HD Dual& operator-=(const Dual& b) { return *this = *this - b; }
  SCANDYN_HD Dual& operator*=(const Dual& b) { return *this = *this * b; }
  SCANDYN_HD Dual& operator/=(const Dual& b) { return *this = *this / b; }
  SCANDYN_HD friend bool operator<(const Dual& a, const Dual& b) { return a.v < b.v; }
  SCANDYN_HD friend bool operator>(const Dual& a, const Dual& b) { return a.v > b.v; }
  SCANDYN_HD friend bool operator<=(const Dual& a, const Dual& b) { return a.v <= b.v; }
  SCANDYN_HD friend bool operator>=(const Dual& a, const Dual& b) { return a.v >= b.v; }
  SCANDYN_HD friend bool operator==(const Dual& a, const Dual& b) { return a.v == b.v; }
  SCANDYN_HD friend bool operator!=(const Dual& a, const Dual& b) { return a.v != b.v; }
};

template <class S>
struct ScalarMath<Dual<S>> {
  using D = Dual<S>;
  SCANDYN_HD static D sqrt(D x) {
    const S r = ScalarMath<S>::sqrt(x.v);
    return {r, x.d / (S(2) * r)};
  }
  SCANDYN_HD static D sin(D x) { return {ScalarMath<S>::sin(x.v), ScalarMath<S>::cos(x.v) * x.d}; }
  SCANDYN_HD static D cos(D x) { return {ScalarMath<S>::cos(x.v), -ScalarMath<S>::sin(x.v) * x.d}; }
  SCANDYN_HD static D abs(D x) { return x.v < S(0) ? -x : x; }
  SCANDYN_HD static bool isfinite(D x) { return ScalarMath<S>::isfinite(x.v) && ScalarMath<S>::isfinite(x.d); }
  SCANDYN_HD static constexpr D epsilon() { return D(ScalarMath<S>::epsilon()); }
};

// Scratch for rnea_second_derivatives: the model in dual numbers and the passes' rows
// and matrices (made once per model).
template <class S>
struct SecondDerivativeData {
  explicit SecondDerivativeData(const ModelTpl<S>& model);
  ModelTpl<Dual<S>> model;                 // the model, every derivative part 0
  std::vector<DerivativeBody<Dual<S>>> work;  // (nv)
  std::vector<Dual<S>> q, qd, qdd;         // (nv) the seeded state
  std::vector<Dual<S>> a, b, m;            // (nv x nv) the first-order blocks of one pass
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
// the first-order recursion seeded along q's e_k (O(nv^2 depth) work). The
// variational integrator's exact Newton Jacobian (scandyn/sim/variational.hpp).
template <class S>
void rnea_weighted_dq2(const ModelTpl<S>& model, SecondDerivativeData<S>& data, const S* q, const S* qd,
                       const S* qdd, const Force<S>* fext, const S* w, S* out);

}  // namespace scandyn
