// scandyn/sim/variational.hpp: the variational integrator of the simulator
// (Integrator::Variational, "variational"): the host step (the serial and OpenMP
// backends) over the per-instance routines of scandyn/sim/variational_instance.hpp,
// which the CUDA backend runs too (up to kVariationalExactMaxDofs DoFs; the chord
// and Newton-Krylov iterations of longer chains below are host only).
//
// Discrete mechanics (Marsden & West, Acta Numerica 2001), the midpoint discrete
// Lagrangian of L(q, qd) = 1/2 qd^T M(q) qd - V(q):
//   L_d(q0, q1) = dt L(qm, v),  qm = (q0 + q1) / 2,  v = (q1 - q0) / dt,
//   D1 L_d = dt/2 L_q(qm, v) - L_v(qm, v),   D2 L_d = dt/2 L_q(qm, v) + L_v(qm, v),
// with L_v = M(qm) v (the momentum) and L_q = 1/2 D^T v - g(qm), where D = d(M(q) a)/dq
// at a = v (so (D^T v)_j = v^T (dM/dq_j) v) and g = dV/dq the gravity forces.
// Forcing (the discrete Lagrange-d'Alembert principle, forces at the midpoint):
//   f_d^- = f_d^+ = dt/2 F(qm, v),  F = tau + e(qm, v) + J(qm)^T fext,
// tau the applied torques (held over the step), e the joint effects (damping
// -d v, springs -k (qm - q0), limits' penalty at qm: joint_effect_force with h = 0)
// and the external body wrenches (constant in their body frames) at qm.
// Springs and gravity are conservative: their midpoint force is exactly the
// midpoint discrete Lagrangian's potential term. With G = L_q + F the position-
// momentum form of the forced discrete Euler-Lagrange equations is
//   p_k     = -D1 L_d - f_d^- = M(qm) v - dt/2 G(qm, v)    (solved for q_{k+1})
//   p_{k+1} =  D2 L_d + f_d^+ = M(qm) v + dt/2 G(qm, v) = 2 M(qm) v - p_k.
// The simulator's state is (q, qd): p_k = M(q_k) qd_k on entry (the continuous
// Legendre transform), qd_{k+1} = M(q_{k+1})^-1 p_{k+1} on exit (the ABA of the
// model without gravity at rest). Both are the same q-dependent change of
// coordinates at every step, so the map (q, qd) -> (q', qd') is conjugate to the
// symplectic (q, p) map: its energy error stays bounded (no drift) for conservative
// scenes, it is second order, and it conserves momentum maps of symmetries.
//
// All the dynamics come from inverse dynamics and its analytical derivatives
// (rnea_derivatives, Carpentier & Mansard 2018), with ID(q, 0, a) = M(q) a + g(q)
// - J^T fext:
//   ID(at_rest, qm, 0, v) = M v   (at_rest: the model without gravity), its
//                           q-derivative D and dtau/dqdd = M;
//   ID(model, qm, 0, 0, fext) = g - J^T fext, its q-derivative K.
// Residual r = M v - dt/2 (1/2 D^T v - (g - J^T fext) + tau + e) - p_k and its
// exact Jacobian in the unknown v (q1 = q0 + dt v, qm = q0 + dt/2 v)
//   dr/dv = M + dt/2 (D - D^T) + dt^2/4 K - diag(dt^2/4 de/dq + dt/2 de/dv) - dt^2/8 H,
// H = d(D^T v)/dq at fixed v (= the q-Hessian of v^T M(q) v: second derivatives of
// M, by the analytical second-order recursion's weighted contraction sum_i v_i
// d^2 tau_i / dq dq of the model at rest at (qm, 0, v), rnea_weighted_dq2_analytic_instance
// in scandyn/instance/second_derivatives_analytic.hpp, O(nv depth) and no nv^3
// tensor). Models of more than
// kVariationalExactMaxDofs DoFs do not form the Jacobian at all: they iterate with
// its dominant part P = M(qm) + diag(-dt^2/4 de/dq - dt/2 de/dv) (the chord method),
// dv = P^-1 r by one ABA of the model without gravity at rest with the diagonal as
// its armature, the residual's M v and D^T v from one reverse pass of inverse
// dynamics (rnea_vjp with weight v: gq = D^T v, gqdd = M v) and g - J^T fext from one
// RNEA: O(nv depth) per iteration, no nv x nv matrix. Linear convergence, contraction
// of order |P^-1 (dt/2 (D - D^T) + dt^2/4 K - dt^2/8 H)|: dt |qd| and dt^2 g / l for
// ropes moving slowly (rope:100 at dt = 5e-5 from rest: a few updates per step); the
// gyroscopic term dt/2 (D - D^T) grows with the speeds against M's small eigenvalues
// (rope:1000 at dt = 2e-5 contracts by ~0.3 at 1 rad/s and stalls by 3 rad/s). Where
// it does not contract (from the third update on, one above half the one before
// it), the step starts again from its first guess by Newton-Krylov: each update
// solves J dv = r by GMRES (at most 40 vectors, to 1e-6 of |r|), right-preconditioned
// by P (one ABA per vector), J x (H included) by central differences of the
// residual along x (two residuals: O(nv depth) per vector, accurate to ~eps^(2/3)).
// Where that fails too, the dense quasi-Newton Jacobian (all terms but H, LU), up to
// kVariationalDenseMaxDofs DoFs.
// The unknown is the mean velocity v (q1 = q0 + dt v), so Newton solves with dt J
// (= M + dt/2 (D - D^T) + ...): v keeps its relative precision where q1 - q0 would
// cancel (float). The dense matrix is factored by LU with partial pivoting: O(nv^3)
// per iteration (up to 64 DoFs, and the fallback above).
//
// Stopping: the residual at its rounding floor (|r|_inf <= 64 eps max_j of the sum of
// the magnitudes of r_j's terms; checked from the second iteration on, before its
// solve); or |dv|_inf <= variational_tolerance<S>() max(|v|_inf, |qd_k|_inf) (16
// epsilons of S relative to the step's speed); or, with |dv|_inf within sqrt(eps) of
// that speed, when the next update predicted from the contraction (|dv|^2 /
// |dv_previous|) is within the tolerance, or when the updates stop shrinking (|dv| >=
// |dv_previous| / 2: the rounding floor of the residual, which M's small pivots
// amplify past 16 eps on robots); at most
// kVariationalMaxIterations iterations; otherwise (or on a zero / non-finite LU
// pivot, or a non-finite residual) the step fails with Failure::NotConverged and the
// instance keeps its state (Simulator's failures; never NaN silently).
#pragma once

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#include <memory>

#include "scandyn/algorithm/derivatives.hpp"
#include "scandyn/algorithm/directional_derivatives.hpp"
#include "scandyn/sim/step_derivatives.hpp"
#include "scandyn/sim/variational_instance.hpp"

namespace scandyn {
namespace sim {

// One thread's scratch (made once per model; the dense matrices of a chord model
// only when its fallback first needs them).
template <class S>
struct VariationalWork {
  explicit VariationalWork(const ModelTpl<S>& model)
      : at_rest(model), deriv(model), data(model, false), n(static_cast<std::size_t>(model.nv())),
        chord(model.nv() > kVariationalExactMaxDofs), a0(base_acceleration(model.gravity)) {
    at_rest.gravity = Vec3<S>{S(0), S(0), S(0)};
    jvp = std::make_unique<RneaJvpData<S>>(at_rest);
    for (std::vector<S>* a : {&zero, &q1, &qm, &v, &p0, &tau_m, &tau_g, &f, &eq, &eqd, &r, &work, &dtv, &diag, &gqd, &v0})
      a->assign(n, S(0));
    if (!chord) {
      hessian = true;
      H.assign(n * n, S(0));
      hsums.resize(n);
      allocate_dense();
    }
    point_scratch();
  }
  void allocate_krylov() {
    if (kv.size() == (kKrylovDim + 1) * n) return;
    kv.assign((kKrylovDim + 1) * n, S(0));
    kz.assign(kKrylovDim * n, S(0));
    hess.assign((kKrylovDim + 1) * kKrylovDim, S(0));
    for (std::vector<S>* a : {&k1, &k2, &k3, &k4, &k5, &k6, &k7}) a->assign(n, S(0));
    for (std::vector<S>* a : {&kcs, &ksn, &ky}) a->assign(kKrylovDim, S(0));
    kg.assign(kKrylovDim + 1, S(0));
  }
  static constexpr std::size_t kKrylovDim = 40;  // GMRES's basis (no restart)
  void allocate_dense() {
    if (D.size() == n * n) return;
    for (std::vector<S>* a : {&D, &K, &M, &J, &unused}) a->assign(n * n, S(0));
    piv.assign(n, 0);
    point_scratch();
  }
  // The model as variational_instance.hpp's routines read it (H where hessian is set).
  VariationalModel<S> instance_model() const {
    return {at_rest.bodies.data(), at_rest.nv(), a0, base_acceleration(at_rest.gravity), hessian};
  }
  ModelTpl<S> at_rest;          // the model with zero gravity: ID(at_rest, q, 0, a) = M(q) a
  DerivativeDataTpl<S> deriv;   // rnea_derivatives' scratch
  DataTpl<S> data;              // rnea / aba scratch
  std::size_t n;
  // true: the chord iteration (models of more than kVariationalExactMaxDofs DoFs), its
  // dense fallback up to kVariationalDenseMaxDofs; false: Newton with the exact Jacobian
  bool chord;
  int chord_max_iterations = kVariationalMaxIterations;  // (tests lower it to reach the fallback)
  std::unique_ptr<RneaJvpData<S>> jvp;  // rnea_vjp's scratch (the chord iteration's residual)
  std::vector<S> zero, q1, qm, v, p0, tau_m, tau_g, f, eq, eqd, r, work;  // (nv)
  // (nv) D^T v; the chord's armature; rnea_vjp's qd adjoint (unused); the first guess of v
  std::vector<S> dtv, diag, gqd, v0;
  // Newton-Krylov: GMRES's basis V ((kKrylovDim + 1) x nv), its preconditioned
  // vectors Z (kKrylovDim x nv), the Hessenberg matrix ((kKrylovDim + 1) x
  // kKrylovDim, row-major), seven (nv) rows of scratch, the Givens rotations' cosines
  // and sines, the rotated right-hand side and the solution in the basis
  // (kKrylovDim each, kg one more); empty until a step needs them
  std::vector<S> kv, kz, hess, k1, k2, k3, k4, k5, k6, k7, kcs, ksn, kg, ky;
  std::vector<S> D, K, M, J, unused;                                      // (nv x nv) row-major, or empty
  std::vector<Index> piv;
  bool hessian = false;  // the exact Jacobian's H term (models of up to kVariationalExactMaxDofs DoFs)
  std::vector<S> H;      // (nv x nv) d(D^T v)/dq, or empty
  std::vector<WeightedDq2Body<S>> hsums;  // (nv) H's per-body sums, or empty
  Motion<S> a0;                                   // the model's base acceleration, -g
  VariationalScratch<S> scratch{};                // views of the vectors above (point_scratch)

 private:
  // scratch's pointers at the vectors (again whenever the dense matrices are made)
  void point_scratch() {
    const Index nv = static_cast<Index>(n);
    auto mat = [&](std::vector<S>& m) { return MatrixRef<S>{m.empty() ? nullptr : m.data(), nv, 1}; };
    scratch = {zero.data(), q1.data(), qm.data(), v.data(), p0.data(), tau_m.data(), tau_g.data(), f.data(),
               eq.data(), eqd.data(), r.data(), work.data(), dtv.data(), mat(D), mat(K), mat(M), mat(J), mat(unused),
               mat(H), piv.empty() ? nullptr : piv.data(), deriv.work.data(), hsums.empty() ? nullptr : hsums.data(),
               GeneralWork<S>{data.Xup.data(), data.v.data(), data.a.data(), data.c.data(), data.f.data(),
                              data.Ic.data(), data.IA.data(), data.U.data(), data.D.data(), data.u.data(),
                              data.L.empty() ? nullptr : data.L.data()}};
  }
};

namespace detail {

// The terms of the residual at u, qm = q + dt/2 u (into qm): Mu = M(qm) u and DTu =
// D(qm)^T u by one rnea_vjp (weight u), g = g(qm) - J^T fext by one RNEA (written only
// with gravity or external wrenches), F = tau + e(qm, u) and, when eq and eqd are
// given, e's diagonal partials: O(nv depth), no matrix.
template <unsigned kEffects, class S>
void residual_terms(const ModelTpl<S>& model, VariationalWork<S>& w, S half, const JointCoefficients<S>* coef,
                    const S* q, const S* tau, const Force<S>* fx, const S* u, S* qm, S* Mu, S* DTu, S* g, S* F,
                    S* eq, S* eqd) {
  const Index n = model.nv();
  for (Index i = 0; i < n; ++i) qm[i] = q[i] + half * u[i];
  rnea_vjp(w.at_rest, *w.jvp, qm, w.zero.data(), u, static_cast<const Force<S>*>(nullptr), u, DTu, w.gqd.data(), Mu);
  if constexpr ((kEffects & (kGravity | kExternal)) != 0)
    rnea(model, w.data, qm, w.zero.data(), w.zero.data(), g, fx);
  stage_forces<kEffects>(n, coef, tau, qm, u, S(0), F, eq, eqd);
}

// The residual r(u) at qm = q + dt/2 u into out, its terms in w.k1..w.k5 (w's outer
// iterate untouched); O(nv depth).
template <unsigned kEffects, class S>
void residual_at(const ModelTpl<S>& model, VariationalWork<S>& w, S half, const JointCoefficients<S>* coef,
                 const S* q, const S* tau, const Force<S>* fx, const S* u, S* out) {
  constexpr bool kPotential = (kEffects & (kGravity | kExternal)) != 0;
  residual_terms<kEffects>(model, w, half, coef, q, tau, fx, u, w.k1.data(), w.k3.data(), w.k2.data(), w.k4.data(),
                           w.k5.data(), static_cast<S*>(nullptr), static_cast<S*>(nullptr));
  for (Index j = 0; j < model.nv(); ++j)
    out[j] = residual_entry(w.k3[j], w.k2[j], kPotential ? w.k4[j] : S(0), w.k5[j], w.p0[j], half);
}

// y = J x, J = dr/dv the exact Jacobian (H included), by central differences of
// residual_at along x (step cbrt(eps) relative to v): two residuals, O(nv depth), no
// matrix; accurate to ~eps^(2/3), what the inexact Newton of solve_matrix_free needs.
template <unsigned kEffects, class S>
void jacobian_product(const ModelTpl<S>& model, VariationalWork<S>& w, S half, const JointCoefficients<S>* coef,
                      const S* q, const S* tau, const Force<S>* fx, const S* x, S* y) {
  const Index n = model.nv();
  S vmax = S(1), xmax = S(0);
  for (Index i = 0; i < n; ++i) vmax = std::max(vmax, std::abs(w.v[i])), xmax = std::max(xmax, std::abs(x[i]));
  if (!(xmax > S(0))) {
    std::fill(y, y + n, S(0));
    return;
  }
  const S h = std::cbrt(std::numeric_limits<S>::epsilon()) * vmax / xmax;
  S* const u = w.k6.data();
  for (Index i = 0; i < n; ++i) u[i] = w.v[i] + h * x[i];
  residual_at<kEffects>(model, w, half, coef, q, tau, fx, u, y);
  for (Index i = 0; i < n; ++i) u[i] = w.v[i] - h * x[i];
  residual_at<kEffects>(model, w, half, coef, q, tau, fx, u, w.k7.data());
  for (Index i = 0; i < n; ++i) y[i] = (y[i] - w.k7[i]) / (S(2) * h);
}

// dv = J^-1 r (r in w.r, dv written there) by GMRES with right preconditioning by P
// (the chord's M + diag, one ABA at rest per vector), at most kKrylovDim vectors, to a
// residual of 1e-6 |r| (the outer iteration takes it from there: rope:1000 at 2e-5 ran
// 400 steps in 11.4 s with 1e-6, 14.5 s with 1e-4, and stalled by step 285 with 1e-2).
// False on a failed ABA pivot or a breakdown before any progress.
template <unsigned kEffects, class S>
bool gmres(const ModelTpl<S>& model, VariationalWork<S>& w, S half, const JointCoefficients<S>* coef, const S* q,
           const S* tau, const Force<S>* fx) {
  const Index n = model.nv();
  const std::size_t m = VariationalWork<S>::kKrylovDim, nn = w.n;
  w.allocate_krylov();
  auto V = [&](std::size_t k) { return w.kv.data() + k * nn; };
  auto Z = [&](std::size_t k) { return w.kz.data() + k * nn; };
  auto Hm = [&](std::size_t i, std::size_t j) -> S& { return w.hess[i * m + j]; };
  S beta = S(0);
  for (Index i = 0; i < n; ++i) beta += w.r[i] * w.r[i];
  beta = std::sqrt(beta);
  if (!(beta > S(0))) {
    std::fill(w.r.begin(), w.r.end(), S(0));
    return std::isfinite(beta);
  }
  for (Index i = 0; i < n; ++i) V(0)[i] = w.r[i] / beta;
  std::vector<S>&cs = w.kcs, &sn = w.ksn, &g = w.kg, &y = w.ky;
  std::fill(g.begin(), g.end(), S(0));
  g[0] = beta;
  const S target = S(1e-6) * beta;
  std::size_t k = 0;
  for (; k < m; ++k) {
    if (!aba(w.at_rest, w.data, w.qm.data(), w.zero.data(), V(k), Z(k), static_cast<const Force<S>*>(nullptr),
             w.diag.data())
             .ok())
      return false;
    S* const u = V(k + 1);
    jacobian_product<kEffects>(model, w, half, coef, q, tau, fx, Z(k), u);
    for (std::size_t j = 0; j <= k; ++j) {  // modified Gram-Schmidt
      S h = S(0);
      for (Index i = 0; i < n; ++i) h += u[i] * V(j)[i];
      Hm(j, k) = h;
      for (Index i = 0; i < n; ++i) u[i] -= h * V(j)[i];
    }
    S norm = S(0);
    for (Index i = 0; i < n; ++i) norm += u[i] * u[i];
    norm = std::sqrt(norm);
    Hm(k + 1, k) = norm;
    if (!std::isfinite(norm)) return false;
    if (norm > S(0))
      for (Index i = 0; i < n; ++i) u[i] /= norm;
    for (std::size_t j = 0; j < k; ++j) {  // the earlier rotations on the new column
      const S a = Hm(j, k), b = Hm(j + 1, k);
      Hm(j, k) = cs[j] * a + sn[j] * b;
      Hm(j + 1, k) = -sn[j] * a + cs[j] * b;
    }
    const S a = Hm(k, k), b = Hm(k + 1, k), rr = std::hypot(a, b);
    cs[k] = rr > S(0) ? a / rr : S(1);
    sn[k] = rr > S(0) ? b / rr : S(0);
    Hm(k, k) = rr;
    Hm(k + 1, k) = S(0);
    g[k + 1] = -sn[k] * g[k];
    g[k] = cs[k] * g[k];
    if (std::abs(g[k + 1]) <= target || norm == S(0)) {
      ++k;
      break;
    }
  }
  if (k == 0) return false;
  // y = R^-1 g (R: the rotated Hessenberg's upper triangle), dv = Z y
  for (std::size_t i = k; i-- > 0;) {
    S t = g[i];
    for (std::size_t j = i + 1; j < k; ++j) t -= Hm(i, j) * y[j];
    if (!(Hm(i, i) != S(0))) return false;
    y[i] = t / Hm(i, i);
  }
  std::fill(w.r.begin(), w.r.end(), S(0));
  for (std::size_t j = 0; j < k; ++j)
    for (Index i = 0; i < n; ++i) w.r[i] += y[j] * Z(j)[i];
  return true;
}

// The iterations without a matrix, for models of more than kVariationalExactMaxDofs
// DoFs, from v in w.v; each update's residual from one rnea_vjp (weight v: gq = D^T v,
// gqdd = M v), one RNEA (g - J^T fext) and the joint effects, O(nv depth):
// - krylov false, the chord iteration: dv = P^-1 r, P = M(qm) + diag(-dt^2/4 de/dq -
//   dt/2 de/dv) by one ABA at rest (the diagonal as armature); false when it does not
//   contract (take_update's stall) within w.chord_max_iterations updates;
// - krylov true, Newton-Krylov: dv = J^-1 r by gmres (P as its preconditioner, J's
//   products by jacobian_product).
// True when converged.
template <unsigned kEffects, class S>
bool solve_matrix_free(const ModelTpl<S>& model, VariationalWork<S>& w, S dt, const JointCoefficients<S>* coef,
                       const S* q, const S* tau, const Force<S>* fx, S speed, bool krylov, VariationalResult& out,
                       Index& worst) {
  constexpr bool kPotential = (kEffects & (kGravity | kExternal)) != 0;
  const Index n = model.nv();
  const S half = S(0.5) * dt, quarter = S(0.25) * dt * dt;
  const int most = krylov ? kVariationalMaxIterations : w.chord_max_iterations;
  for (int it = 0; it < most; ++it) {
    residual_terms<kEffects>(model, w, half, coef, q, tau, fx, w.v.data(), w.qm.data(), w.tau_m.data(), w.dtv.data(),
                             w.tau_g.data(), w.f.data(), w.eq.data(), w.eqd.data());
    const ResidualNorm<S> norm = negative_residual<kPotential>(w.scratch, n, half);
    if (it > 0 && norm.residual <= norm.floor) return true;  // the residual is rounding
    bool finite = true;
    for (Index i = 0; i < n; ++i) {
      finite = finite && std::isfinite(w.r[i]);
      w.diag[i] = -(quarter * w.eq[i] + half * w.eqd[i]);
    }
    if (!finite) return false;
    if (krylov) {
      if (!gmres<kEffects>(model, w, half, coef, q, tau, fx)) return false;
    } else {
      if (!aba(w.at_rest, w.data, w.qm.data(), w.zero.data(), w.r.data(), w.work.data(),
               static_cast<const Force<S>*>(nullptr), w.diag.data())
               .ok())
        return false;
      std::copy(w.work.begin(), w.work.end(), w.r.begin());
    }
    const Update u = take_update(w.scratch, n, speed, it, !krylov, out, worst);
    if (u != Update::Continue) return u == Update::Converged;
  }
  return false;
}

}  // namespace detail

// One variational step of one instance of a model of 1-DoF joints: q, qd (nv each)
// advanced by dt in place under tau (nv, held over the step); coef the joints'
// coefficients (read for declared joint effects); fext nbodies body wrenches or null
// (read only with kExternal). On a failure q and qd are left as they were. The
// step of variational_instance.hpp: its dense Newton up to kVariationalExactMaxDofs
// DoFs, beyond them the chord iteration, Newton-Krylov, then the dense quasi-Newton.
template <unsigned kEffects, class S>
VariationalResult variational_step(const ModelTpl<S>& model, VariationalWork<S>& w, S dt,
                                   const JointCoefficients<S>* coef, S* q, S* qd, const S* tau,
                                   const Force<S>* fext) {
  const Index n = model.nv();
  const Force<S>* const fx = (kEffects & kExternal) ? fext : nullptr;
  if (!w.chord) {
    w.allocate_dense();  // (made at construction, unless a caller turned the chord off: then no H)
    return variational_dense_step<kEffects>(w.instance_model(), w.scratch, dt, coef, q, qd, tau, fx);
  }
  auto chord = [&](const VariationalModel<S>& m, const VariationalScratch<S>&, S, const JointCoefficients<S>*,
                   const S*, const S*, const Force<S>*, S speed, VariationalResult& out, Index& worst) {
    std::copy(w.v.begin(), w.v.end(), w.v0.begin());  // the first guess
    bool converged = detail::solve_matrix_free<kEffects>(model, w, dt, coef, q, tau, fx, speed, false, out, worst);
    if (!converged) {  // again from the first guess, Newton-Krylov
      std::copy(w.v0.begin(), w.v0.end(), w.v.begin());
      out = VariationalResult{};
      out.krylov = true;
      converged = detail::solve_matrix_free<kEffects>(model, w, dt, coef, q, tau, fx, speed, true, out, worst);
    }
    if (!converged && n <= kVariationalDenseMaxDofs) {  // again, dense (no H)
      std::copy(w.v0.begin(), w.v0.end(), w.v.begin());
      out = VariationalResult{};
      out.dense_fallback = true;
      w.allocate_dense();
      converged = detail::solve_dense<kEffects>(m, w.scratch, dt, coef, q, tau, fx, speed, out, worst);
    }
    return converged;
  };
  return variational_step_instance<kEffects>(w.instance_model(), w.scratch, dt, coef, q, qd, tau, fx, chord);
}

}  // namespace sim
}  // namespace scandyn
