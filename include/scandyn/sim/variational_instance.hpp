// scandyn/sim/variational_instance.hpp: the variational integrator's step of one
// instance with the exact Newton Jacobian (models of up to kVariationalExactMaxDofs
// DoFs), __host__ __device__ over caller scratch: the serial and OpenMP simulators
// (variational_step, scandyn/sim/variational.hpp, whose header explains the method)
// and the CUDA simulator (kernels/sim_variational.cu, one thread per instance) run
// these functions.
//
// The step: p_k = M(q_k) qd_k (rnea_general at rest), the first guess of the mean
// velocity v from one ABA (aba_general), Newton on r(v) = 0 with the dense Jacobian
// dr/dv = M + dt/2 (D - D^T) + dt^2/4 K - diag(dt^2/4 de/dq + dt/2 de/dv) - dt^2/8 H
// (rnea_derivatives_instance for D, M and K; H by the analytical second-order
// recursion's weighted contraction, rnea_weighted_dq2_analytic_instance; LU with
// partial pivoting), then q_{k+1} = q_k + dt v
// and qd_{k+1} = M(q_{k+1})^-1 (2 M(qm) v - p_k) (rnea_general, aba_general at rest).
// The chord and Newton-Krylov iterations of long chains (variational.hpp) are host
// code that plugs into the same step (variational_step_instance's solve) and reuses
// negative_residual, take_update and, for their dense fallback, solve_dense without H.
#pragma once

#include <cstddef>
#include <limits>
#include <string>

#include "scandyn/batch.hpp"
#include "scandyn/instance/general_instance.hpp"
#include "scandyn/instance/second_derivatives_analytic.hpp"
#include "scandyn/sim/step_derivatives.hpp"

namespace scandyn {
namespace sim {

// The effects the variational integrator takes (contacts are refused: their force
// switches with the contact set).
inline constexpr unsigned kVariationalEffects = kGravity | kDamping | kSprings | kLimits | kExternal;
inline constexpr int kVariationalMaxIterations = 50;
// Models of up to this many DoFs get the exact Newton Jacobian (the dt^2/8 H term
// by rnea_weighted_dq2_analytic_instance, O(nv depth)); larger ones the
// O(nv depth) chord iteration (host only).
inline constexpr Index kVariationalExactMaxDofs = 64;
// The chord iteration's fallback, the dense quasi-Newton Jacobian (nv x nv, LU),
// up to this many DoFs (5 nv^2 numbers of scratch, O(nv^3) per update); beyond it a
// step the chord iteration does not solve fails with Failure::NotConverged.
inline constexpr Index kVariationalDenseMaxDofs = 2048;
// The CUDA step's models (one thread per instance, the exact Jacobian): at most
// this many DoFs (the thread kernels' capacity, kMaxThreadDofs).
inline constexpr Index kVariationalCudaMaxDofs = 64;
// The refusal of a longer model on the CUDA backend (the Simulator's and the CUDA
// step's own, for direct callers).
inline std::string variational_cuda_refusal(const std::string& model, Index nv) {
  return "backend 'cuda': the variational integrator runs on the GPU for models of up to " +
         std::to_string(kVariationalCudaMaxDofs) +
         " DoF (one thread per instance, the exact Newton Jacobian); model '" + model + "' has " +
         std::to_string(nv) + ": use the serial or openmp backend (the chord and Newton-Krylov iterations)";
}
template <class S>
SCANDYN_HD constexpr S variational_tolerance() {
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

// The model as the step reads it (1-DoF joints, parent[i] < i).
template <class S>
struct VariationalModel {
  const Body<S>* body;        // (nv) the bodies in DoF order
  Index nv;
  Motion<S> a0;               // base_acceleration(gravity): -g, the model's (zero without gravity)
  Motion<S> a0_rest;          // base_acceleration(0): the model at rest, ID(q, 0, a) = M(q) a
  bool hessian;               // the exact Jacobian's H term; false: no H (the chord's dense
                              // quasi-Newton fallback)
};

// One instance's scratch, the caller's memory (host vectors; a CUDA thread's local
// arrays for the vectors and per-body values, and global memory for the matrices).
template <class S>
struct VariationalScratch {
  S* zero;   // (nv) zeros: the at-rest model's qd
  S* q1;     // (nv) q_{k+1} = q_k + dt v
  S* qm;     // (nv) the midpoint q_k + dt/2 v
  S* v;      // (nv) the unknown: the step's mean velocity (q_{k+1} - q_k) / dt
  S* p0;     // (nv) p_k = M(q_k) qd_k
  S* tau_m;  // (nv) M(qm) v
  S* tau_g;  // (nv) g(qm) - J^T fext (with gravity or external wrenches)
  S* f;      // (nv) F = tau + e(qm, v); the first guess's forces; p_{k+1}
  S* eq;     // (nv) de/dq, the joint effects' diagonal partials
  S* eqd;    // (nv) de/dv
  S* r;      // (nv) -r(v), then the update dv
  S* work;   // (nv) the ABA's results
  S* dtv;    // (nv) D^T v
  MatrixRef<S> D, K, M, J;  // (nv x nv) d(M v)/dq, d(g - J^T fext)/dq, M, the Jacobian (LU in place)
  MatrixRef<S> unused;      // (nv x nv) the derivatives' blocks not read
  MatrixRef<S> H;           // (nv x nv) d(D^T v)/dq at fixed v (read only where model.hessian is set)
  Index* piv;               // (nv) LU's row exchanges
  DerivativeBody<S>* deriv;            // (nv) rnea_derivatives_instance's and H's bodies
  WeightedDq2Body<S>* hsums;           // (nv) H's per-body sums (where model.hessian is set)
  GeneralWork<S> general;              // rnea_general / aba_general: Xup v a c f IA (nv), U D u (nv)
};

namespace detail {

template <class S>
SCANDYN_HD S vmax(S a, S b) {
  return a < b ? b : a;
}

// In place LU with partial pivoting of the n x n matrix A; false on a zero or
// non-finite pivot (piv[k]: the row swapped with k).
template <class S>
SCANDYN_HD bool lu_factor(MatrixRef<S> A, Index* piv) {
  const Index n = A.n;
  for (Index k = 0; k < n; ++k) {
    Index p = k;
    S best = ScalarMath<S>::abs(A(k, k));
    for (Index i = k + 1; i < n; ++i)
      if (ScalarMath<S>::abs(A(i, k)) > best) best = ScalarMath<S>::abs(A(i, k)), p = i;
    piv[k] = p;
    if (!(best > S(0)) || !ScalarMath<S>::isfinite(best)) return false;
    if (p != k)
      for (Index j = 0; j < n; ++j) {
        const S t = A(k, j);
        A(k, j) = A(p, j);
        A(p, j) = t;
      }
    const S inv = S(1) / A(k, k);
    for (Index i = k + 1; i < n; ++i) {
      const S l = A(i, k) * inv;
      A(i, k) = l;
      if (l == S(0)) continue;
      for (Index j = k + 1; j < n; ++j) A(i, j) -= l * A(k, j);
    }
  }
  return true;
}
// x = A^-1 x with lu_factor's factors (whole rows were swapped, L's multipliers
// included: the row exchanges apply to x first, then L y = P x, then U x = y).
template <class S>
SCANDYN_HD void lu_solve(MatrixRef<S> A, const Index* piv, S* x) {
  const Index n = A.n;
  for (Index k = 0; k < n; ++k) {
    const S t = x[k];
    x[k] = x[piv[k]];
    x[piv[k]] = t;
  }
  for (Index k = 0; k < n; ++k)
    for (Index i = k + 1; i < n; ++i) x[i] -= A(i, k) * x[k];
  for (Index k = n - 1; k >= 0; --k) {
    S s = x[k];
    for (Index j = k + 1; j < n; ++j) s -= A(k, j) * x[j];
    x[k] = s / A(k, k);
  }
}
// The same on a dense row-major n x n array.
template <class S>
bool lu_factor(Index n, S* A, Index* piv) {
  return lu_factor(MatrixRef<S>{A, n, 1}, piv);
}
template <class S>
void lu_solve(Index n, const S* A, const Index* piv, S* x) {
  lu_solve(MatrixRef<S>{const_cast<S*>(A), n, 1}, piv, x);
}

// Entry j of the residual r(u) = M u - dt/2 (1/2 D^T u - (g - J^T fext) + F) - p_k
// from its terms (half = dt/2).
template <class S>
SCANDYN_HD S residual_entry(S Mu, S DTu, S g, S F, S p0, S half) {
  return Mu - half * (S(0.5) * DTu - g + F) - p0;
}

// |r|_inf and its rounding floor.
template <class S>
struct ResidualNorm {
  S residual, floor;
};

// Newton's right-hand side -r(v) into w.r, from w.tau_m (M v), w.dtv (D^T v), w.tau_g
// (g - J^T fext, read when kPotential), w.f (F) and w.p0; returns |r|_inf and its
// rounding floor (64 eps of the largest sum of a row's terms' magnitudes).
template <bool kPotential, class S>
SCANDYN_HD ResidualNorm<S> negative_residual(const VariationalScratch<S>& w, Index n, S half) {
  S residual = S(0), floor = S(0);
  for (Index j = 0; j < n; ++j) {
    const S g = kPotential ? w.tau_g[j] : S(0);
    w.r[j] = -residual_entry(w.tau_m[j], w.dtv[j], g, w.f[j], w.p0[j], half);
    residual = vmax(residual, ScalarMath<S>::abs(w.r[j]));
    floor = vmax(floor, ScalarMath<S>::abs(w.tau_m[j]) + ScalarMath<S>::abs(w.p0[j]) +
                            half * (ScalarMath<S>::abs(S(0.5) * w.dtv[j]) + ScalarMath<S>::abs(g) +
                                    ScalarMath<S>::abs(w.f[j])));
  }
  return {residual, S(64) * std::numeric_limits<S>::epsilon() * floor};
}

// What an update did: the iteration goes on, has converged, or has failed (a
// non-finite update; for the chord iteration also one that grows).
enum class Update { Continue, Converged, Failed };

// v += dv (dv in w.r), recorded in out (iterations, updates) and worst (the DoF of
// the largest correction); the stopping rule of variational.hpp: the update within
// the tolerance, or, once within sqrt(eps) of the speed, the next one predicted
// from the contraction within it or the updates no longer shrinking (the residual's
// rounding floor: M's small pivots amplify it past 16 eps on robots). stall_fails:
// from the third update on, one above half the one before it (and above sqrt(eps))
// fails: the chord iteration contracts too slowly there to be worth going on.
template <class S>
SCANDYN_HD Update take_update(const VariationalScratch<S>& w, Index n, S speed, int it, bool stall_fails,
                              VariationalResult& out, Index& worst) {
  const S tol = variational_tolerance<S>(), root_eps = ScalarMath<S>::sqrt(std::numeric_limits<S>::epsilon());
  S step = S(0), scale = speed;
  for (Index i = 0; i < n; ++i) {
    w.v[i] += w.r[i];
    if (ScalarMath<S>::abs(w.r[i]) > step || !ScalarMath<S>::isfinite(w.r[i])) step = ScalarMath<S>::abs(w.r[i]), worst = i;
    scale = vmax(scale, ScalarMath<S>::abs(w.v[i]));
  }
  const S previous = S(out.last_update);
  out.iterations = it + 1;
  out.previous_update = out.last_update;
  out.last_update = double(step);
  if (it == 0) out.first_update = double(step);
  if (!ScalarMath<S>::isfinite(step)) return Update::Failed;
  if (step <= tol * scale || step < std::numeric_limits<S>::min() ||
      (it > 0 && step <= root_eps * scale && (step * step <= tol * scale * previous || step >= S(0.5) * previous)))
    return Update::Converged;
  if (stall_fails && it > 1 && step > S(0.5) * previous) return Update::Failed;
  return Update::Continue;
}

// Newton on the dense Jacobian dr/dv = M + dt/2 (D - D^T) + dt^2/4 K - diag(dt^2/4
// de/dq + dt/2 de/dv) - dt^2/8 H (H where model.hessian is set), LU per update; v from
// w.v. True when converged.
template <unsigned kEffects, class S>
SCANDYN_HD bool solve_dense(const VariationalModel<S>& model, const VariationalScratch<S>& w, S dt,
                            const JointCoefficients<S>* coef, const S* q, const S* tau, const Force<S>* fx, S speed,
                            VariationalResult& out, Index& worst) {
  constexpr bool kPotential = (kEffects & (kGravity | kExternal)) != 0;
  const Index n = model.nv;
  const MatrixRef<S> D = w.D, K = w.K, M = w.M, J = w.J, unused = w.unused;
  const S half = S(0.5) * dt, quarter = S(0.25) * dt * dt;
  for (int it = 0; it < kVariationalMaxIterations; ++it) {
    for (Index i = 0; i < n; ++i) w.qm[i] = q[i] + half * w.v[i];
    // M v, D = d(M v)/dq, M at qm
    rnea_derivatives_instance(model.body, n, model.a0_rest, static_cast<const S*>(w.qm),
                              static_cast<const S*>(w.zero), static_cast<const S*>(w.v),
                              static_cast<const Force<S>*>(nullptr), w.deriv, D, unused, M, w.tau_m);
    // g - J^T fext and K = its q-derivative at qm
    if constexpr (kPotential)
      rnea_derivatives_instance(model.body, n, model.a0, static_cast<const S*>(w.qm), static_cast<const S*>(w.zero),
                                static_cast<const S*>(w.zero), fx, w.deriv, K, unused, unused, w.tau_g);
    // F = tau + e(qm, v), its diagonal partials
    stage_forces<kEffects>(n, coef, tau, w.qm, w.v, S(0), w.f, w.eq, w.eqd);
    for (Index j = 0; j < n; ++j) {
      S dtv = S(0);
      for (Index i = 0; i < n; ++i) dtv += D(i, j) * w.v[i];
      w.dtv[j] = dtv;
    }
    const ResidualNorm<S> norm = negative_residual<kPotential>(w, n, half);
    if (it > 0 && norm.residual <= norm.floor) return true;  // the residual is rounding: v is the solution to working precision
    // dr/dv = dt dr/dq1 = M + dt/2 (D - D^T) + dt^2/4 K - diag(dt^2/4 de/dq + dt/2 de/dv)
    for (Index i = 0; i < n; ++i) {
      for (Index j = 0; j < n; ++j) {
        const S k = kPotential ? K(i, j) : S(0);
        J(i, j) = M(i, j) + half * (D(i, j) - D(j, i)) + quarter * k;
      }
      J(i, i) -= quarter * w.eq[i] + half * w.eqd[i];
    }
    // the exact Jacobian's last term: - dt^2/8 H, H = d(D^T v)/dq at qm (v fixed) =
    // sum_i v_i d^2 tau_i / dq dq of the model at rest at (qm, 0, v) (ID = M(q) v);
    // its forward pass overwrites w.deriv, whose D, M and K are in J already
    if (model.hessian) {
      rnea_weighted_dq2_analytic_instance(model.body, n, model.a0_rest, static_cast<const S*>(w.qm),
                                          static_cast<const S*>(w.zero), static_cast<const S*>(w.v),
                                          static_cast<const Force<S>*>(nullptr), static_cast<const S*>(w.v), w.deriv,
                                          w.hsums, w.H);
      const S eighth = S(0.125) * dt * dt;
      for (Index i = 0; i < n; ++i)
        for (Index j = 0; j < n; ++j) J(i, j) -= eighth * w.H(i, j);
    }
    bool finite = true;
    for (Index i = 0; i < n; ++i) finite = finite && ScalarMath<S>::isfinite(w.r[i]);
    if (!finite || !lu_factor(J, w.piv)) return false;
    lu_solve(J, w.piv, w.r);
    const Update u = take_update(w, n, speed, it, false, out, worst);
    if (u != Update::Continue) return u == Update::Converged;
  }
  return false;
}

// The dense solve as variational_step_instance's solve.
template <unsigned kEffects, class S>
struct DenseSolve {
  SCANDYN_HD bool operator()(const VariationalModel<S>& model, const VariationalScratch<S>& w, S dt,
                             const JointCoefficients<S>* coef, const S* q, const S* tau, const Force<S>* fx, S speed,
                             VariationalResult& out, Index& worst) const {
    return solve_dense<kEffects>(model, w, dt, coef, q, tau, fx, speed, out, worst);
  }
};

}  // namespace detail

// One variational step of one instance: q, qd (nv each) advanced by dt in place
// under tau (nv, held over the step); coef the joints' coefficients (read for the
// declared joint effects); fx nv body wrenches or null. solve(model, w, dt, coef, q,
// tau, fx, speed, out, worst) finds v from its first guess in w.v (true: converged;
// worst: the DoF of the largest correction). On a failure q and qd are left as they
// were (out.failure: ArticulatedPivot for the ABAs' pivots, NotConverged).
template <unsigned kEffects, class S, class Solve>
SCANDYN_HD VariationalResult variational_step_instance(const VariationalModel<S>& model,
                                                       const VariationalScratch<S>& w, S dt,
                                                       const JointCoefficients<S>* coef, S* q, S* qd, const S* tau,
                                                       const Force<S>* fx, Solve&& solve) {
  static_assert((kEffects & ~kVariationalEffects) == 0, "variational_step: contacts are not taken");
  const Index n = model.nv;
  VariationalResult out;
  // p_k = M(q_k) qd_k
  rnea_general(model.body, n, model.a0_rest, w.general, q, w.zero, qd, w.p0, static_cast<const Force<S>*>(nullptr));
  // the first guess: q1 = q + dt (qd + dt/2 qdd), qdd = FD(q, qd, tau + e(q, qd))
  stage_forces<kEffects>(n, coef, tau, q, qd, S(0), w.f, static_cast<S*>(nullptr), static_cast<S*>(nullptr));
  const Index guess = aba_general(model.body, n, model.a0, w.general, q, qd, w.f, w.work, fx,
                                  static_cast<const S*>(nullptr));
  if (guess >= 0) {
    out.failed_dof = guess;
    out.failure = Failure::ArticulatedPivot;
    return out;
  }
  // the unknown is the step's mean velocity v = (q1 - q) / dt (q1 = q + dt v: v keeps
  // its relative precision where q1 - q would cancel); first guess v = qd + dt/2 qdd
  const S half = S(0.5) * dt;
  for (Index i = 0; i < n; ++i) w.v[i] = qd[i] + half * w.work[i];
  S speed = S(0);  // the velocity scale of the convergence test
  for (Index i = 0; i < n; ++i) speed = detail::vmax(speed, ScalarMath<S>::abs(qd[i]));
  Index worst = 0;
  if (!solve(model, w, dt, coef, q, tau, fx, speed, out, worst)) {
    out.failed_dof = worst;
    out.failure = Failure::NotConverged;
    return out;
  }
  // q1 = q + dt v, p_{k+1} = 2 M(qm) v - p_k at the converged v, qd_{k+1} = M(q1)^-1 p_{k+1}
  for (Index i = 0; i < n; ++i) {
    w.qm[i] = q[i] + half * w.v[i];
    w.q1[i] = q[i] + dt * w.v[i];
  }
  rnea_general(model.body, n, model.a0_rest, w.general, w.qm, w.zero, w.v, w.tau_m,
               static_cast<const Force<S>*>(nullptr));
  for (Index i = 0; i < n; ++i) w.f[i] = S(2) * w.tau_m[i] - w.p0[i];
  const Index velocity = aba_general(model.body, n, model.a0_rest, w.general, w.q1, w.zero, w.f, w.work,
                                     static_cast<const Force<S>*>(nullptr), static_cast<const S*>(nullptr));
  if (velocity >= 0) {
    out.failed_dof = velocity;
    out.failure = Failure::ArticulatedPivot;
    return out;
  }
  for (Index i = 0; i < n; ++i) q[i] = w.q1[i], qd[i] = w.work[i];
  return out;
}

// The step with the exact Newton Jacobian (model.hessian set, nv <= kVariationalExactMaxDofs).
template <unsigned kEffects, class S>
SCANDYN_HD VariationalResult variational_dense_step(const VariationalModel<S>& model, const VariationalScratch<S>& w,
                                                    S dt, const JointCoefficients<S>* coef, S* q, S* qd,
                                                    const S* tau, const Force<S>* fx) {
  return variational_step_instance<kEffects>(model, w, dt, coef, q, qd, tau, fx, detail::DenseSolve<kEffects, S>{});
}

}  // namespace sim
}  // namespace scandyn
