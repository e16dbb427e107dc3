// scandyn/instance/second_derivatives_instance.hpp: the second-order derivatives of
// inverse dynamics of one instance by dual-number passes, __host__ __device__: the
// reference of the analytical recursion (rnea_second_derivatives_analytic_instance,
// scandyn/instance/second_derivatives_analytic.hpp, what rnea_second_derivatives and
// the engines run for models of 1-DoF joints) through rnea_second_derivatives_dual
// (scandyn/algorithm/second_derivatives.hpp), the CPU engines' path for other models,
// and the reference of the weighted contraction (rnea_weighted_dq2_instance, through
// rnea_weighted_dq2_dual; the variational integrator runs the analytical
// rnea_weighted_dq2_analytic_instance).
// Also the tensor types (TensorRef) both share.
//
// Forward mode over the analytical first-order derivatives: the recursions of
// rnea_derivatives_instance (Carpentier & Mansard 2018;
// scandyn/instance/dynamics_derivatives.hpp) run in the dual numbers Dual<S> = S +
// S eps (eps^2 = 0) with q (or qd) seeded along e_k, so that the eps part of each
// first-order entry is its derivative along e_k, exactly (no step, no truncation):
// one pass per k and per variable, 2 nv passes of the first-order recursion
// (O(nv^2 depth) work in total). Each pass writes only the eps parts of its blocks,
// straight into slice k of the output tensors (DualPartRef): no nv x nv block of
// dual numbers is kept.
//
// Tensors: nv x nv x nv, entry (i, j, k) at data[((i * nv + j) * nv + k) * stride]
// (TensorRef):
//   d2tau_dq2(i, j, k)    = d^2 tau_i / dq_j dq_k    (symmetric in j, k)
//   d2tau_dqd2(i, j, k)   = d^2 tau_i / dqd_j dqd_k  (symmetric in j, k)
//   d2tau_dqdqd(i, j, k)  = d^2 tau_i / dq_j dqd_k
//   dM_dq(i, j, k)        = d M_ij / dq_k            (d tau / d qdd = M(q) depends on q only)
//
// Scratch per instance (what one GPU thread keeps in local memory): nv
// DerivativeBody<Dual<S>> (144 scalars each) and, with external wrenches, nv
// Force<Dual<S>> (12 scalars each): 156 nv scalars. The model in dual numbers
// (Body<Dual<S>>, every derivative part 0) is the caller's, made once per model.
#pragma once

#include <cstddef>

#include "scandyn/instance/dynamics_derivatives.hpp"

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

// An nv x nv x nv tensor of one instance: entry (i, j, k) at data[((i * n + j) * n +
// k) * stride] (stride 1: the serial function's dense layout; a batch's
// instance-innermost layout: stride B). data null: not written.
template <class S>
struct TensorRef {
  S* data;
  Index n;
  std::ptrdiff_t stride;
  SCANDYN_HD S& operator()(Index i, Index j, Index k) const {
    return data[((static_cast<std::ptrdiff_t>(i) * n + j) * n + k) * stride];
  }
  // The nv x nv matrix of the entries (i, j, k) at this k (data null stays null).
  SCANDYN_HD MatrixRef<S> slice(Index k) const {
    return {data ? data + static_cast<std::ptrdiff_t>(k) * stride : nullptr, n, static_cast<std::ptrdiff_t>(n) * stride};
  }
};

// Instance b's tensor in a batch view of nv^3 entries per instance (entry (i * nv +
// j) * nv + k: (i, j, k); the engine's output layout, scandyn/engine.hpp). A view
// with null data gives a null tensor.
template <class S>
SCANDYN_HD TensorRef<S> instance_tensor(const BatchView<S>& v, long long b, Index nv) {
  return {v.data ? v.data + b * v.batch_stride : nullptr, nv, v.dof_stride};
}

// An nv x nv block of dual numbers of which only the eps parts are kept: assigning
// entry (i, j) writes its derivative part to out(i, j) (out.data null: dropped).
// What rnea_derivatives_instance writes its blocks through in a dual pass.
template <class S>
struct DualPartRef {
  MatrixRef<S> out;
  struct Entry {
    S* p;  // the entry's place in out, or null
    SCANDYN_HD Dual<S> operator=(const Dual<S>& x) const {
      if (p) *p = x.d;
      return x;
    }
  };
  SCANDYN_HD Entry operator()(Index i, Index j) const { return {out.data ? &out(i, j) : nullptr}; }
};

// Entry i of x as a dual number whose derivative part is 1 at i = k (the seed
// direction e_k) and 0 elsewhere (k = -1: no seed). V: anything indexable by DoF.
template <class S, class V>
struct SeededVector {
  V x;
  Index k;
  SCANDYN_HD Dual<S> operator[](Index i) const { return {S(x[i]), i == k ? S(1) : S(0)}; }
};

// The body wrenches in dual numbers (derivative parts 0), into out (nv entries);
// returns out, or null without wrenches (fext null).
template <class S>
SCANDYN_HD const Force<Dual<S>>* dual_wrenches(const Force<S>* fext, Index nv, Force<Dual<S>>* out) {
  if (!fext) return nullptr;
  for (Index i = 0; i < nv; ++i) out[i] = fext[i].template cast<Dual<S>>();
  return out;
}

// One pass of the first-order recursion in dual numbers with q (seed 0) or qd (seed
// 1) seeded along e_k: the derivatives along it of dtau/dq, dtau/dqd and M (the eps
// parts of the pass's blocks) are written to d_dq, d_dqd, d_M (nv x nv each, every
// entry; a null data: not written). body: the nv bodies in dual numbers; a0: the
// base acceleration (-g); q, qd, qdd: indexable by DoF (values); fext: the body
// wrenches in dual numbers (dual_wrenches) or null; work: nv entries of scratch.
template <class S, class V>
SCANDYN_HD void seeded_derivative_pass(const Body<Dual<S>>* body, Index nv, const Motion<Dual<S>>& a0, V q, V qd,
                                       V qdd, const Force<Dual<S>>* fext, DerivativeBody<Dual<S>>* work, int seed,
                                       Index k, MatrixRef<S> d_dq, MatrixRef<S> d_dqd, MatrixRef<S> d_M) {
  using Seeded = SeededVector<S, V>;
  rnea_derivatives_instance(body, nv, a0, Seeded{q, seed == 0 ? k : Index(-1)}, Seeded{qd, seed == 1 ? k : Index(-1)},
                            Seeded{qdd, Index(-1)}, fext, work, DualPartRef<S>{d_dq}, DualPartRef<S>{d_dqd},
                            DualPartRef<S>{d_M}, nullptr);
}

// The second derivatives of tau = ID(q, qd, qdd, fext) of one instance, gravity
// included: the three tensors above, every entry written, and dM_dq when its data is
// not null. body: the nv bodies in dual numbers (Body::cast<Dual<S>>, made once per
// model); a0: the base acceleration (-g); q, qd, qdd: indexable by DoF (a pointer, a
// DofColumn); fext: nv body wrenches in body frames, or null; work: nv entries of
// scratch; wrenches: nv entries of scratch (not read when fext is null).
template <class S, class V>
SCANDYN_HD void rnea_second_derivatives_instance(const Body<Dual<S>>* body, Index nv, const Motion<S>& a0, V q, V qd,
                                                 V qdd, const Force<S>* fext, DerivativeBody<Dual<S>>* work,
                                                 Force<Dual<S>>* wrenches, TensorRef<S> d2tau_dq2,
                                                 TensorRef<S> d2tau_dqd2, TensorRef<S> d2tau_dqdqd,
                                                 TensorRef<S> dM_dq) {
  const Force<Dual<S>>* const f = dual_wrenches(fext, nv, wrenches);
  const Motion<Dual<S>> a0d = a0.template cast<Dual<S>>();
  const MatrixRef<S> none{nullptr, nv, 0};
  // pass k along q: d/dq_k of dtau_i/dq_j and of M_ij
  for (Index k = 0; k < nv; ++k)
    seeded_derivative_pass(body, nv, a0d, q, qd, qdd, f, work, 0, k, d2tau_dq2.slice(k), none, dM_dq.slice(k));
  // pass k along qd: d/dqd_k of dtau_i/dq_j and of dtau_i/dqd_j
  for (Index k = 0; k < nv; ++k)
    seeded_derivative_pass(body, nv, a0d, q, qd, qdd, f, work, 1, k, d2tau_dqdqd.slice(k), d2tau_dqd2.slice(k), none);
}

// The contraction of d2tau_dq2 with a weight w on tau, without the nv^3 tensor:
// out(j, k) = sum_i w_i d^2 tau_i / dq_j dq_k (nv x nv, symmetric), the q-Hessian of
// w^T ID(q, qd, qdd, fext) for fixed w: nv dual passes seeded along q's e_k
// (seeded_derivative_pass), each contracted with w. body: the nv bodies in dual
// numbers; a0: the base acceleration (-g); fext: the body wrenches in dual numbers
// (dual_wrenches) or null; work: nv entries of scratch; block: an nv x nv matrix of
// scratch (one pass's d/dq_k of dtau/dq). The reference of
// rnea_weighted_dq2_analytic_instance (scandyn/instance/second_derivatives_analytic.hpp).
template <class S, class V>
SCANDYN_HD void rnea_weighted_dq2_instance(const Body<Dual<S>>* body, Index nv, const Motion<S>& a0, V q, V qd,
                                           V qdd, const Force<Dual<S>>* fext, const S* w,
                                           DerivativeBody<Dual<S>>* work, MatrixRef<S> block, MatrixRef<S> out) {
  const Motion<Dual<S>> a0d = a0.template cast<Dual<S>>();
  const MatrixRef<S> none{nullptr, nv, 0};
  for (Index k = 0; k < nv; ++k) {
    seeded_derivative_pass(body, nv, a0d, q, qd, qdd, fext, work, 0, k, block, none, none);
    for (Index j = 0; j < nv; ++j) {  // sum_i w_i d/dq_k of dtau_i/dq_j
      S s = S(0);
      for (Index i = 0; i < nv; ++i) s += w[i] * block(i, j);
      out(j, k) = s;
    }
  }
}

}  // namespace scandyn
