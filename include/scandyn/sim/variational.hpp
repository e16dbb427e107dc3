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
// kVariationalExactMaxDofs DoFs drop the H term (quasi-Newton: linear convergence
// with contraction of order dt^2 |qd|^2 |d2M| / lambda_min(M), negligible for
// ropes at their stable dt; 0.3 on iiwa spinning at 35 rad/s at dt = 2e-3, which is
// why the smaller models keep it).
// The unknown is the mean velocity v (q1 = q0 + dt v), so Newton solves with dt J
// (= M + dt/2 (D - D^T) + ...): v keeps its relative precision where q1 - q0 would
// cancel (float). The dense matrix is factored by LU with partial pivoting: O(nv^3)
// per iteration (the cost of a long chain; tests and bench/variational_cost.cpp).
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
#include "scandyn/algorithm/second_derivatives.hpp"
#include "scandyn/sim/step_derivatives.hpp"

namespace scandyn {
namespace sim {

// The effects the variational integrator takes (contacts are refused: their force
// switches with the contact set).
inline constexpr unsigned kVariationalEffects = kGravity | kDamping | kSprings | kLimits | kExternal;
inline constexpr int kVariationalMaxIterations = 50;
// Models of up to this many DoFs get the exact Newton Jacobian (the dt^2/8 H term
// by nv dual passes, rnea_weighted_dq2); larger ones drop it (quasi-Newton).
inline constexpr Index kVariationalExactMaxDofs = 64;
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
};

// One thread's scratch (made once per model).
template <class S>
struct VariationalWork {
  explicit VariationalWork(const ModelTpl<S>& model)
      : at_rest(model), deriv(model), data(model, false), n(static_cast<std::size_t>(model.nv())) {
    at_rest.gravity = Vec3<S>{S(0), S(0), S(0)};
    for (std::vector<S>* a : {&zero, &q1, &qm, &v, &p0, &tau_m, &tau_g, &f, &eq, &eqd, &r, &work})
      a->assign(n, S(0));
    for (std::vector<S>* a : {&D, &K, &M, &J, &unused}) a->assign(n * n, S(0));
    piv.assign(n, 0);
    if (model.nv() <= kVariationalExactMaxDofs) {
      dual = std::make_unique<SecondDerivativeData<S>>(at_rest);
      H.assign(n * n, S(0));
    }
  }
  ModelTpl<S> at_rest;          // the model with zero gravity: ID(at_rest, q, 0, a) = M(q) a
  DerivativeDataTpl<S> deriv;   // rnea_derivatives' scratch
  DataTpl<S> data;              // rnea / aba scratch
  std::size_t n;
  std::vector<S> zero, q1, qm, v, p0, tau_m, tau_g, f, eq, eqd, r, work;  // (nv)
  std::vector<S> D, K, M, J, unused;                                      // (nv x nv) row-major
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
  constexpr bool kPotential = (kEffects & (kGravity | kExternal)) != 0;
  VariationalResult out;
  const MatrixRef<S> D{w.D.data(), n, 1}, K{w.K.data(), n, 1}, M{w.M.data(), n, 1}, unused{w.unused.data(), n, 1};
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
  for (Index i = 0; i < n; ++i) w.v[i] = qd[i] + S(0.5) * dt * w.work[i];
  const S half = S(0.5) * dt, quarter = S(0.25) * dt * dt, tol = variational_tolerance<S>();
  const S root_eps = std::sqrt(std::numeric_limits<S>::epsilon());
  S speed = S(0);  // the velocity scale of the convergence test
  for (Index i = 0; i < n; ++i) speed = std::max(speed, std::abs(qd[i]));
  bool converged = false;
  Index worst = 0;
  for (int it = 0; it < kVariationalMaxIterations && !converged; ++it) {
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
    // -r = -(M v - dt/2 (1/2 D^T v - (g - J^T fext) + F) - p_k): Newton's right-hand side
    // and its rounding floor: 64 eps of the sum of its terms' magnitudes
    S residual = S(0), floor = S(0);
    for (Index j = 0; j < n; ++j) {
      S dtv = S(0);
      for (Index i = 0; i < n; ++i) dtv += D(i, j) * w.v[i];
      const S g = kPotential ? w.tau_g[j] : S(0);
      w.r[j] = -(w.tau_m[j] - half * (S(0.5) * dtv - g + w.f[j]) - w.p0[j]);
      residual = std::max(residual, std::abs(w.r[j]));
      floor = std::max(floor, std::abs(w.tau_m[j]) + std::abs(w.p0[j]) +
                                  half * (std::abs(S(0.5) * dtv) + std::abs(g) + std::abs(w.f[j])));
    }
    if (it > 0 && residual <= S(64) * std::numeric_limits<S>::epsilon() * floor) {
      converged = true;  // the residual is rounding: v is the solution to working precision
      break;
    }
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
    if (!finite || !detail::lu_factor(n, w.J.data(), w.piv.data())) break;
    detail::lu_solve(n, w.J.data(), w.piv.data(), w.r.data());
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
    if (!std::isfinite(step)) break;
    // converged: the update is within the tolerance; or, once it is within sqrt(eps),
    // the next one predicted from the contraction (step / previous) is, or the
    // updates stopped shrinking (the residual's rounding floor: M's small pivots
    // amplify it past 16 eps on robots)
    converged = step <= tol * scale || step < std::numeric_limits<S>::min() ||
                (it > 0 && step <= root_eps * scale && (step * step <= tol * scale * previous || step >= S(0.5) * previous));
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
