// scandyn/algorithm/loop_projection.hpp: moving a state onto its closed loops
// (docs/loops.md), the algorithm shared by the dense projection (project_to_loops,
// src/algorithm/loops.cpp) and the simulator's sparse one
// (factor_graph::SparseConstrainedDynamics::project):
//
//   positions   min |phi(q)|^2 by Levenberg-Marquardt: at each linearisation
//               J = d phi / dq the damped minimum-norm step
//                 p = -J^T (J J^T + mu I)^-1 phi   (mu = 0: Gauss-Newton's -J^+ phi),
//               accepted when the actual decrease of |phi|^2 is at least 1e-4 of
//               the decrease the linear model predicts (rho = actual / predicted);
//               mu adapts by rho (Nielsen's rule: accepted, mu *= max(1/3,
//               1 - (2 rho - 1)^3), and 0 below 1e-12 of the scale; rejected,
//               mu *= nu, nu *= 2; from mu = 0 a rejection starts at 1e-3 of the
//               solver's scale of J J^T). mu starts at 0 when the first
//               Gauss-Newton step moves no joint by more than 0.01 (rad or m), so
//               from close to the loops (a simulator step's drift) every step is
//               the plain Gauss-Newton step; else at 1e-3 of the scale. From far
//               off the iteration is
//               globally convergent in the usual sense (to a stationary point of
//               |phi|^2: a closed configuration, or a local minimum / an
//               infeasible loop set, which the caller then refuses). A rejected
//               trial costs one damped solve (the sparse solver: one more
//               factorisation) and one evaluation of phi, not a new Jacobian.
//   velocities  qd's minimum-norm change with J qd = 0 at the final q.
//
// Stops when max |phi| <= tol, after `linearisations` linearisations, when the
// predicted decrease vanishes (a stationary point), or when a rejected step is
// below 1e-14 (1 + max |q|) or mu exceeds 1e16 times the scale (no step decreases
// |phi|^2: rounding).
#pragma once

#include <algorithm>
#include <cmath>
#include <vector>

#include "scandyn/algorithm/loop_solver.hpp"

namespace scandyn {

// What a projection onto the loops did and left.
struct LoopProjectionInfo {
  double phi = 0;         // max |phi| at the final q (m, rad)
  double jqd = 0;         // max |J qd| after the velocity projection (m/s, rad/s)
  Index worst_row = -1;   // the row of max(|phi|, |J qd|), -1 without loops
  int linearisations = 0; // Jacobians factorised for position steps (each one factorisation)
  int trials = 0;         // trial points evaluated (accepted + rejected)
  bool converged = false; // max |phi| <= tol
  // max(|phi|, |J qd|): the state's violation of its loops (loop_violation's measure)
  double violation() const { return std::isnan(phi) || std::isnan(jqd) ? NAN : std::max(phi, jqd); }
};

// J v (out: m) and J^T r (out: n) of the loops at the body transforms X0 (from
// loop_body_motion), walking each loop's two paths to the base (J's columns as
// loop_rows writes them, without forming J).
inline void loop_jacobian_apply(const Body<double>* bodies, const LoopRow<double>* loops, Index nloops,
                                const Transform<double>* X0, const double* v, double* out) {
  const Transform<double> I{Mat3<double>::identity(), Vec3<double>::zero()};
  Index row = 0;
  for (Index k = 0; k < nloops; ++k) {
    const LoopRow<double>& l = loops[k];
    const Index lin = l.weld ? row + 3 : row;
    double acc[6] = {0, 0, 0, 0, 0, 0};  // linear, then angular
    for (int side = 0; side < 2; ++side) {
      const double sign = side == 0 ? 1.0 : -1.0;
      const Index body = side == 0 ? l.body_a : l.body_b;
      const Vec3<double> p = point_position(body < 0 ? I : X0[body], side == 0 ? l.point_a : l.point_b);
      for (Index j = body; j >= 0; j = bodies[j].parent) {
        Vec3<double> w, u;
        joint_point_column(bodies[j], X0[j], p, w, u);
        const double s = sign * v[j];
        acc[0] += s * u.x, acc[1] += s * u.y, acc[2] += s * u.z;
        acc[3] += s * w.x, acc[4] += s * w.y, acc[5] += s * w.z;
      }
    }
    for (int r = 0; r < 3; ++r) out[lin + r] = acc[r];
    if (l.weld)
      for (int r = 0; r < 3; ++r) out[row + r] = acc[3 + r];
    row += l.rows();
  }
}

// The projection of the header's comment over a problem's operations (n unknowns q,
// m rows phi):
//   bool residual(const double* q, double* phi)   phi at q; false when not finite
//   void factorize(const double* q)               linearise at q (the next two use it)
//   void solve(const double* r, double mu, double* x)
//                                                 x = J^T (J J^T + mu D)^-1 r, D > 0 the
//                                                 solver's diagonal weights; mu = 0: J^+ r
//                                                 (minimum norm, least squares)
//   void apply(const double* v, double* out)      out (m) = J v
//   double damping_scale()                        the size of J J^T in the solver's units
// q and qd are updated in place; returns max |phi| at the final q (info: the rest).
template <class Ops>
double project_onto_loops(Ops& ops, Index n, Index m, double* q, double* qd, double tol, int linearisations,
                          LoopProjectionInfo* info = nullptr) {
  LoopProjectionInfo out;
  if (m == 0) {
    if (info) *info = out;
    return 0;
  }
  using V = std::vector<double>;
  V phi(m), phit(m), p(n), qt(n), Jp(m);
  auto norm2 = [](const V& x) {
    double s = 0;
    for (double e : x) s += e * e;
    return s;
  };
  auto max_abs = [](const V& x) {
    double s = 0;
    for (double e : x) s = std::isnan(e) || std::isnan(s) ? NAN : std::max(s, std::fabs(e));
    return s;
  };
  const bool finite = ops.residual(q, phi.data());
  double f = norm2(phi), worst = max_abs(phi);
  double mu = 0, nu = 2, scale = 0;
  bool factored_at_q = false, stop = false;
  const int max_trials = 100 + 60 * std::max(linearisations, 0);
  while (finite && !stop && !(worst <= tol) && out.linearisations < linearisations) {
    ops.factorize(q);
    factored_at_q = true;
    ++out.linearisations;
    if (out.linearisations == 1) scale = ops.damping_scale();
    for (;;) {
      ops.solve(phi.data(), mu, p.data());
      for (double& e : p) e = -e;
      if (out.linearisations == 1 && out.trials == 0 && mu == 0 && scale > 0) {
        // far off the loops (the first Gauss-Newton step moves a joint by more than
        // 0.01 rad or m) start damped, as Levenberg-Marquardt does (Gauss-Newton's
        // first long step may land in another basin of |phi|^2)
        double big = 0;
        for (double e : p) big = std::max(big, std::fabs(e));
        if (!(big <= 1e-2)) {
          mu = 1e-3 * scale;
          continue;
        }
      }
      ops.apply(p.data(), Jp.data());
      // the linear model's decrease of |phi|^2: -(2 phi.Jp + |Jp|^2)
      double pred = 0;
      for (Index k = 0; k < m; ++k) pred -= (2 * phi[k] + Jp[k]) * Jp[k];
      double rho = -INFINITY;
      V* accepted = nullptr;
      if (pred > 0) {
        for (Index i = 0; i < n; ++i) qt[i] = q[i] + p[i];
        ++out.trials;
        const bool ok = ops.residual(qt.data(), phit.data());
        const double ft = norm2(phit);
        if (ok && std::isfinite(ft)) rho = (f - ft) / pred;
        if (rho > 1e-4) accepted = &phit;
      } else if (mu == 0 && !(scale > 0)) {
        stop = true;  // no decrease predicted by Gauss-Newton and no scale to damp by
        break;
      } else if (mu > 0) {
        stop = true;  // a damped step predicts no decrease: a stationary point of |phi|^2
        break;
      }
      if (accepted) {  // relinearise there
        std::copy(qt.begin(), qt.end(), q);
        phi.swap(phit);
        f = norm2(phi), worst = max_abs(phi);
        factored_at_q = false;
        if (mu > 0) {
          const double t = 2 * rho - 1;
          mu *= std::max(1.0 / 3.0, 1 - t * t * t);
          if (mu < 1e-12 * scale) mu = 0;  // back to Gauss-Newton
        }
        nu = 2;
        break;
      }
      mu = mu == 0 ? 1e-3 * scale : mu * nu;
      nu *= 2;
      // a rejected step below q's rounding: damping more cannot help (|phi| is at
      // its rounding floor)
      double step = 0, size = 0;
      for (Index i = 0; i < n; ++i) step = std::max(step, std::fabs(p[i])), size = std::max(size, std::fabs(q[i]));
      if (!(mu <= 1e16 * scale) || out.trials >= max_trials || step <= 1e-14 * (1 + size)) {
        stop = true;
        break;
      }
    }
  }
  out.phi = worst;
  out.converged = worst <= tol;
  // velocities: qd -= J^+ J qd at the final q
  if (!finite) {
    out.jqd = NAN;
  } else {
    if (!factored_at_q) ops.factorize(q);
    V r(m), dqd(n);
    ops.apply(qd, r.data());
    ops.solve(r.data(), 0.0, dqd.data());
    for (Index i = 0; i < n; ++i) qd[i] -= dqd[i];
    ops.apply(qd, r.data());
    out.jqd = max_abs(r);
    double w = -1;
    for (Index k = 0; k < m; ++k) {
      const double e = std::max(std::fabs(phi[k]), std::fabs(r[k]));
      if (std::isnan(e)) {
        out.worst_row = k;
        break;
      }
      if (e > w) w = e, out.worst_row = k;
    }
  }
  if (info) *info = out;
  return worst;
}

}  // namespace scandyn
