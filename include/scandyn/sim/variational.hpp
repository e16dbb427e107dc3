// scandyn/sim/variational.hpp: the variational integrator of the simulator
// (Integrator::Variational, "variational"), host only (the serial and OpenMP
// backends; the CUDA backend refuses it).
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
// M, by nv dual passes of the first-order recursion, rnea_weighted_dq2 in
// scandyn/algorithm/second_derivatives.hpp, O(nv^2 depth)). Models of more than
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
#include "scandyn/algorithm/second_derivatives.hpp"
#include "scandyn/sim/step_derivatives.hpp"

namespace scandyn {
namespace sim {

// The effects the variational integrator takes (contacts are refused: their force
// switches with the contact set).
inline constexpr unsigned kVariationalEffects = kGravity | kDamping | kSprings | kLimits | kExternal;
inline constexpr int kVariationalMaxIterations = 50;
// Models of up to this many DoFs get the exact Newton Jacobian (the dt^2/8 H term
// by nv dual passes, rnea_weighted_dq2); larger ones the O(nv) chord iteration.
inline constexpr Index kVariationalExactMaxDofs = 64;
// The chord iteration's fallback, the dense quasi-Newton Jacobian (nv x nv, LU),
// up to this many DoFs (5 nv^2 numbers of scratch, O(nv^3) per update); beyond it a
// step the chord iteration does not solve fails with Failure::NotConverged.
inline constexpr Index kVariationalDenseMaxDofs = 2048;
template <class S>
constexpr S variational_tolerance() {
  return S(16) * std::numeric_limits<S>::epsilon();
}

// One step's outcome.
struct VariationalResult {
  Index failed_dof = -1;      // -1: converged; else the DoF of the largest correction (or failed pivot)
  Failure failure = Failure::None;
  int iterations = 0;         // Newton updates taken (an iteration that stops on the residual makes none)
  double first_update = 0;    // |dv|_inf of the first and the last iterations
  double last_update = 0;
  double previous_update = 0; // |dv|_inf of the iteration before the last
  bool krylov = false;         // the chord iteration did not contract: solved by Newton-Krylov
  bool dense_fallback = false; // neither did Newton-Krylov: solved by the dense quasi-Newton
};

// One thread's scratch (made once per model; the dense matrices of a chord model
// only when its fallback first needs them).
template <class S>
struct VariationalWork {
  explicit VariationalWork(const ModelTpl<S>& model)
      : at_rest(model), deriv(model), data(model, false), n(static_cast<std::size_t>(model.nv())),
        chord(model.nv() > kVariationalExactMaxDofs) {
    at_rest.gravity = Vec3<S>{S(0), S(0), S(0)};
    jvp = std::make_unique<RneaJvpData<S>>(at_rest);
    for (std::vector<S>* a : {&zero, &q1, &qm, &v, &p0, &tau_m, &tau_g, &f, &eq, &eqd, &r, &work, &dtv, &diag, &gqd, &v0})
      a->assign(n, S(0));
    if (!chord) {
      allocate_dense();
      dual = std::make_unique<SecondDerivativeData<S>>(at_rest);
      H.assign(n * n, S(0));
    }
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
  std::unique_ptr<SecondDerivativeData<S>> dual;  // the exact Jacobian's dual passes, or null
  std::vector<S> H;                               // (nv x nv) d(D^T v)/dq, or empty
};

namespace detail {
// In place LU with partial pivoting of the n x n row-major A; false on a zero or
// non-finite pivot (piv[k]: the row swapped with k).
template <class S>
bool lu_factor(Index n, S* A, Index* piv) {
  for (Index k = 0; k < n; ++k) {
    Index p = k;
    S best = std::abs(A[k * n + k]);
    for (Index i = k + 1; i < n; ++i)
      if (std::abs(A[i * n + k]) > best) best = std::abs(A[i * n + k]), p = i;
    piv[k] = p;
    if (!(best > S(0)) || !std::isfinite(best)) return false;
    if (p != k)
      for (Index j = 0; j < n; ++j) std::swap(A[k * n + j], A[p * n + j]);
    const S inv = S(1) / A[k * n + k];
    for (Index i = k + 1; i < n; ++i) {
      S* const row = A + i * n;
      const S l = row[k] * inv;
      row[k] = l;
      if (l == S(0)) continue;
      const S* const pivot_row = A + k * n;
      for (Index j = k + 1; j < n; ++j) row[j] -= l * pivot_row[j];
    }
  }
  return true;
}
// x = A^-1 x with lu_factor's factors (whole rows were swapped, L's multipliers
// included: the row exchanges apply to x first, then L y = P x, then U x = y).
template <class S>
void lu_solve(Index n, const S* A, const Index* piv, S* x) {
  for (Index k = 0; k < n; ++k) std::swap(x[k], x[piv[k]]);
  for (Index k = 0; k < n; ++k)
    for (Index i = k + 1; i < n; ++i) x[i] -= A[i * n + k] * x[k];
  for (Index k = n - 1; k >= 0; --k) {
    S s = x[k];
    for (Index j = k + 1; j < n; ++j) s -= A[k * n + j] * x[j];
    x[k] = s / A[k * n + k];
  }
}

// Entry j of the residual r(u) = M u - dt/2 (1/2 D^T u - (g - J^T fext) + F) - p_k
// from its terms (half = dt/2).
template <class S>
S residual_entry(S Mu, S DTu, S g, S F, S p0, S half) {
  return Mu - half * (S(0.5) * DTu - g + F) - p0;
}

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

// Newton's right-hand side -r(v) into w.r, from w.tau_m (M v), w.dtv (D^T v), w.tau_g
// (g - J^T fext, read when kPotential), w.f (F) and w.p0; returns |r|_inf and its
// rounding floor (64 eps of the largest sum of a row's terms' magnitudes).
template <bool kPotential, class S>
std::pair<S, S> negative_residual(VariationalWork<S>& w, Index n, S half) {
  S residual = S(0), floor = S(0);
  for (Index j = 0; j < n; ++j) {
    const S g = kPotential ? w.tau_g[j] : S(0);
    w.r[j] = -residual_entry(w.tau_m[j], w.dtv[j], g, w.f[j], w.p0[j], half);
    residual = std::max(residual, std::abs(w.r[j]));
    floor = std::max(floor, std::abs(w.tau_m[j]) + std::abs(w.p0[j]) +
                                half * (std::abs(S(0.5) * w.dtv[j]) + std::abs(g) + std::abs(w.f[j])));
  }
  return {residual, S(64) * std::numeric_limits<S>::epsilon() * floor};
}

// What an update did: the iteration goes on, has converged, or has failed (a
// non-finite update; for the chord iteration also one that grows).
enum class Update { Continue, Converged, Failed };

// v += dv (dv in w.r), recorded in out (iterations, updates) and worst (the DoF of
// the largest correction); the stopping rule of the header: the update within the
// tolerance, or, once within sqrt(eps) of the speed, the next one predicted from the
// contraction within it or the updates no longer shrinking (the residual's rounding
// floor: M's small pivots amplify it past 16 eps on robots). stall_fails: from the
// third update on, one above half the one before it (and above sqrt(eps)) fails: the
// chord iteration contracts too slowly there to be worth going on.
template <class S>
Update take_update(VariationalWork<S>& w, Index n, S speed, int it, bool stall_fails, VariationalResult& out,
                   Index& worst) {
  const S tol = variational_tolerance<S>(), root_eps = std::sqrt(std::numeric_limits<S>::epsilon());
  S step = S(0), scale = speed;
  for (Index i = 0; i < n; ++i) {
    w.v[i] += w.r[i];
    if (std::abs(w.r[i]) > step || !std::isfinite(w.r[i])) step = std::abs(w.r[i]), worst = i;
    scale = std::max(scale, std::abs(w.v[i]));
  }
  const S previous = S(out.last_update);
  out.iterations = it + 1;
  out.previous_update = out.last_update;
  out.last_update = double(step);
  if (it == 0) out.first_update = double(step);
  if (!std::isfinite(step)) return Update::Failed;
  if (step <= tol * scale || step < std::numeric_limits<S>::min() ||
      (it > 0 && step <= root_eps * scale && (step * step <= tol * scale * previous || step >= S(0.5) * previous)))
    return Update::Converged;
  if (stall_fails && it > 1 && step > S(0.5) * previous) return Update::Failed;
  return Update::Continue;
}

// Newton on the dense Jacobian dr/dv = M + dt/2 (D - D^T) + dt^2/4 K - diag(dt^2/4
// de/dq + dt/2 de/dv) - dt^2/8 H (H where w.dual is made: up to
// kVariationalExactMaxDofs DoFs), LU per update; v from w.v. True when converged.
template <unsigned kEffects, class S>
bool solve_dense(const ModelTpl<S>& model, VariationalWork<S>& w, S dt, const JointCoefficients<S>* coef,
                 const S* q, const S* tau, const Force<S>* fx, S speed, VariationalResult& out, Index& worst) {
  constexpr bool kPotential = (kEffects & (kGravity | kExternal)) != 0;
  const Index n = model.nv();
  w.allocate_dense();
  const MatrixRef<S> D{w.D.data(), n, 1}, K{w.K.data(), n, 1}, M{w.M.data(), n, 1}, unused{w.unused.data(), n, 1};
  const S half = S(0.5) * dt, quarter = S(0.25) * dt * dt;
  for (int it = 0; it < kVariationalMaxIterations; ++it) {
    for (Index i = 0; i < n; ++i) w.qm[i] = q[i] + half * w.v[i];
    // M v, D = d(M v)/dq, M at qm
    rnea_derivatives(w.at_rest, w.deriv, w.qm.data(), w.zero.data(), w.v.data(), static_cast<const Force<S>*>(nullptr),
                     D, unused, M, w.tau_m.data());
    // g - J^T fext and K = its q-derivative at qm
    if constexpr (kPotential)
      rnea_derivatives(model, w.deriv, w.qm.data(), w.zero.data(), w.zero.data(), fx, K, unused, unused,
                       w.tau_g.data());
    // F = tau + e(qm, v), its diagonal partials
    stage_forces<kEffects>(n, coef, tau, w.qm.data(), w.v.data(), S(0), w.f.data(), w.eq.data(), w.eqd.data());
    for (Index j = 0; j < n; ++j) {
      S dtv = S(0);
      for (Index i = 0; i < n; ++i) dtv += D(i, j) * w.v[i];
      w.dtv[j] = dtv;
    }
    const auto [residual, floor] = negative_residual<kPotential>(w, n, half);
    if (it > 0 && residual <= floor) return true;  // the residual is rounding: v is the solution to working precision
    // dr/dv = dt dr/dq1 = M + dt/2 (D - D^T) + dt^2/4 K - diag(dt^2/4 de/dq + dt/2 de/dv)
    for (Index i = 0; i < n; ++i) {
      S* const row = w.J.data() + static_cast<std::size_t>(i) * w.n;
      for (Index j = 0; j < n; ++j) {
        const S k = kPotential ? K(i, j) : S(0);
        row[j] = M(i, j) + half * (D(i, j) - D(j, i)) + quarter * k;
      }
      row[i] -= quarter * w.eq[i] + half * w.eqd[i];
    }
    // the exact Jacobian's last term: - dt^2/8 H, H = d(D^T v)/dq at qm (v fixed)
    if (w.dual) {
      rnea_weighted_dq2(w.at_rest, *w.dual, w.qm.data(), w.zero.data(), w.v.data(),
                        static_cast<const Force<S>*>(nullptr), w.v.data(), w.H.data());
      const S eighth = S(0.125) * dt * dt;
      for (std::size_t e = 0; e < w.n * w.n; ++e) w.J[e] -= eighth * w.H[e];
    }
    bool finite = true;
    for (Index i = 0; i < n; ++i) finite = finite && std::isfinite(w.r[i]);
    if (!finite || !lu_factor(n, w.J.data(), w.piv.data())) return false;
    lu_solve(n, w.J.data(), w.piv.data(), w.r.data());
    const Update u = take_update(w, n, speed, it, false, out, worst);
    if (u != Update::Continue) return u == Update::Converged;
  }
  return false;
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
    const auto [residual, floor] = negative_residual<kPotential>(w, n, half);
    if (it > 0 && residual <= floor) return true;  // the residual is rounding
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
    const Update u = take_update(w, n, speed, it, !krylov, out, worst);
    if (u != Update::Continue) return u == Update::Converged;
  }
  return false;
}

}  // namespace detail

// One variational step of one instance of a model of 1-DoF joints: q, qd (nv each)
// advanced by dt in place under tau (nv, held over the step); coef the joints'
// coefficients (read for declared joint effects); fext nbodies body wrenches or null
// (read only with kExternal). On a failure q and qd are left as they were.
template <unsigned kEffects, class S>
VariationalResult variational_step(const ModelTpl<S>& model, VariationalWork<S>& w, S dt,
                                   const JointCoefficients<S>* coef, S* q, S* qd, const S* tau,
                                   const Force<S>* fext) {
  static_assert((kEffects & ~kVariationalEffects) == 0, "variational_step: contacts are not taken");
  const Index n = model.nv();
  const Force<S>* const fx = (kEffects & kExternal) ? fext : nullptr;
  VariationalResult out;
  // p_k = M(q_k) qd_k
  rnea(w.at_rest, w.data, q, w.zero.data(), qd, w.p0.data());
  // the first guess: q1 = q + dt (qd + dt/2 qdd), qdd = FD(q, qd, tau + e(q, qd))
  stage_forces<kEffects>(n, coef, tau, q, qd, S(0), w.f.data(), static_cast<S*>(nullptr), static_cast<S*>(nullptr));
  const Status guess = aba(model, w.data, q, qd, w.f.data(), w.work.data(), fx);
  if (!guess.ok()) {
    out.failed_dof = guess.failed_dof;
    out.failure = Failure::ArticulatedPivot;
    return out;
  }
  // the unknown is the step's mean velocity v = (q1 - q) / dt (q1 = q + dt v: v keeps
  // its relative precision where q1 - q would cancel); first guess v = qd + dt/2 qdd
  const S half = S(0.5) * dt;
  for (Index i = 0; i < n; ++i) w.v[i] = qd[i] + half * w.work[i];
  if (w.chord) std::copy(w.v.begin(), w.v.end(), w.v0.begin());
  S speed = S(0);  // the velocity scale of the convergence test
  for (Index i = 0; i < n; ++i) speed = std::max(speed, std::abs(qd[i]));
  Index worst = 0;
  bool converged;
  if (!w.chord) {
    converged = detail::solve_dense<kEffects>(model, w, dt, coef, q, tau, fx, speed, out, worst);
  } else {
    converged = detail::solve_matrix_free<kEffects>(model, w, dt, coef, q, tau, fx, speed, false, out, worst);
    if (!converged) {  // again from the first guess, Newton-Krylov
      std::copy(w.v0.begin(), w.v0.end(), w.v.begin());
      out = VariationalResult{};
      out.krylov = true;
      converged = detail::solve_matrix_free<kEffects>(model, w, dt, coef, q, tau, fx, speed, true, out, worst);
    }
    if (!converged && n <= kVariationalDenseMaxDofs) {  // again, dense
      std::copy(w.v0.begin(), w.v0.end(), w.v.begin());
      out = VariationalResult{};
      out.dense_fallback = true;
      converged = detail::solve_dense<kEffects>(model, w, dt, coef, q, tau, fx, speed, out, worst);
    }
  }
  if (!converged) {
    out.failed_dof = worst;
    out.failure = Failure::NotConverged;
    return out;
  }
  // q1 = q + dt v, p_{k+1} = 2 M(qm) v - p_k at the converged v, qd_{k+1} = M(q1)^-1 p_{k+1}
  for (Index i = 0; i < n; ++i) {
    w.qm[i] = q[i] + half * w.v[i];
    w.q1[i] = q[i] + dt * w.v[i];
  }
  rnea(w.at_rest, w.data, w.qm.data(), w.zero.data(), w.v.data(), w.tau_m.data());
  for (Index i = 0; i < n; ++i) w.f[i] = S(2) * w.tau_m[i] - w.p0[i];
  const Status velocity = aba(w.at_rest, w.data, w.q1.data(), w.zero.data(), w.f.data(), w.work.data());
  if (!velocity.ok()) {
    out.failed_dof = velocity.failed_dof;
    out.failure = Failure::ArticulatedPivot;
    return out;
  }
  for (Index i = 0; i < n; ++i) q[i] = w.q1[i], qd[i] = w.work[i];
  return out;
}

}  // namespace sim
}  // namespace scandyn
