// scandyn/algorithm/loop_solver.hpp: one instance's closed-loop kinematics and its
// dense constrained forward dynamics, SCANDYN_HD (host and device), allocation-free
// on caller scratch: what the loop engines of every backend run per instance
// (cpu_fallback/constrained_dynamics.cpp, kernels/constrained_dynamics.cu), and
// what loop_kinematics (src/algorithm/loops.cpp) runs on the host.
//
//   loop_body_motion        per body X0 (body <- base), v and a with qdd = 0 and no
//                           gravity (a: the velocity-product accelerations), from
//                           the shared rnea_forward_step;
//   loop_rows               phi (m), J (m x nv, row-major), gamma = Jdot qd (m) of
//                           the loops from those (point_kinematics.hpp);
//   constrained_fd_solve    qdd and lambda from M, h, tau, J, gamma:
//                             M qdd + h = tau + J^T lambda,  J qdd + gamma = 0,
//                           by the Schur complement A = J M^-1 J^T, factored by a
//                           rank-revealing LDL^T with diagonal pivoting (a pivot below
//                           loop_rank_tolerance<S>() times the largest ends the
//                           factor: redundant rows, e.g. a planar loop closed by a 3D
//                           point, are dropped), lambda of minimum norm (its
//                           component in A's null space removed), one step of
//                           iterative refinement on J qdd + gamma = 0.
//
// qdd is unique whatever lambda among the solutions (J^T lambda is); lambda is the
// minimum-norm one, as the Eigen reference constrained_forward_dynamics
// (scandyn/algorithm/loops.hpp, complete orthogonal decomposition) returns: the
// reference is the independent truth the engines are tested against.
#pragma once

#include <cmath>

#include "scandyn/algorithm/point_kinematics.hpp"

namespace scandyn {

// A loop closure as the per-instance routines read it (plain data, host or device):
// scandyn::LoopClosure without its names.
template <class S>
struct LoopRow {
  int weld = 0;                     // 0: point (3 rows), 1: weld (6 rows: 3 angular, 3 linear)
  Index body_a = -1, body_b = -1;   // bodies (DoF index), -1: the base
  Vec3<S> point_a, point_b;         // in each body's frame (m)
  SCANDYN_HD int rows() const { return weld ? 6 : 3; }
};

// Relative rank threshold of the Schur complement's pivots: kLoopRankTolerance
// (1e-10) in double, 1e-5 in float (the float rounding of A's entries, ~1e-7
// relative, stays below it).
template <class S>
SCANDYN_HD constexpr double loop_rank_tolerance() {
  return sizeof(S) <= sizeof(float) ? 1e-5 : 1e-10;
}

// X0, v, a of every body (n bodies in DoF order, parent < index).
// loop_body_motion_range: the bodies [begin, end) only, a range closed under the parent
// relation (scandyn/algorithm/loop_iterative.hpp's *_range passes), bit for bit the
// whole pass's values there.
template <class S>
SCANDYN_HD void loop_body_motion_range(const Body<S>* bodies, Index begin, Index end, const S* q, const S* qd,
                                       Transform<S>* X0, Motion<S>* v, Motion<S>* a) {
  for (Index i = begin; i < end; ++i) {
    const Body<S>& b = bodies[i];
    const Index p = b.parent;
    const Transform<S> Xup = joint_transform(b, q[i]);
    X0[i] = world_transform_step(Xup, p < 0 ? nullptr : &X0[p]);
    const RneaForward<S> o = rnea_forward_step(b, Xup, p < 0 ? Motion<S>::zero() : v[p],
                                               p < 0 ? Motion<S>::zero() : a[p], qd ? qd[i] : S(0), S(0));
    v[i] = o.v, a[i] = o.a;
  }
}
template <class S>
SCANDYN_HD void loop_body_motion(const Body<S>* bodies, Index n, const S* q, const S* qd, Transform<S>* X0,
                                 Motion<S>* v, Motion<S>* a) {
  loop_body_motion_range(bodies, Index(0), n, q, qd, X0, v, a);
}

// phi, J, gamma of the loops (any may be null); X0, v, a from loop_body_motion (v, a
// read only for gamma).
template <class S>
SCANDYN_HD void loop_rows(const Body<S>* bodies, Index n, const LoopRow<S>* loops, Index nloops,
                          const Transform<S>* X0, const Motion<S>* v, const Motion<S>* a, S* phi, S* J, S* gamma) {
  Index m = 0;
  for (Index k = 0; k < nloops; ++k) m += loops[k].rows();
  if (J)
    for (Index e = 0; e < m * n; ++e) J[e] = S(0);
  const Transform<S> I{Mat3<S>::identity(), Vec3<S>::zero()};
  Index row = 0;
  for (Index k = 0; k < nloops; ++k) {
    const LoopRow<S>& l = loops[k];
    const Index lin = l.weld ? row + 3 : row;  // the linear rows
    const Transform<S>& Xa = l.body_a < 0 ? I : X0[l.body_a];
    const Transform<S>& Xb = l.body_b < 0 ? I : X0[l.body_b];
    const Vec3<S> pa = point_position(Xa, l.point_a), pb = point_position(Xb, l.point_b);
    auto put = [](S* dst, Index r, const Vec3<S>& x) { dst[r] = x.x, dst[r + 1] = x.y, dst[r + 2] = x.z; };
    if (phi) {
      put(phi, lin, pa - pb);
      if (l.weld) {  // 1/2 vee(C - C^T), C = R_a^T R_b in the base frame's terms (E = R^T)
        const Mat3<S> C = mul_transpose(Xa.E, Xb.E);
        put(phi, row, Vec3<S>{S(0.5) * (C(2, 1) - C(1, 2)), S(0.5) * (C(0, 2) - C(2, 0)),
                              S(0.5) * (C(1, 0) - C(0, 1))});
      }
    }
    if (gamma) {
      const Vec3<S> z = Vec3<S>::zero();
      const Vec3<S> ga = l.body_a < 0 ? z : point_acceleration(Xa, v[l.body_a], a[l.body_a], l.point_a);
      const Vec3<S> gb = l.body_b < 0 ? z : point_acceleration(Xb, v[l.body_b], a[l.body_b], l.point_b);
      put(gamma, lin, ga - gb);
      if (l.weld) {
        const Vec3<S> wa = l.body_a < 0 ? z : to_world(Xa, a[l.body_a].w);
        const Vec3<S> wb = l.body_b < 0 ? z : to_world(Xb, a[l.body_b].w);
        put(gamma, row, wa - wb);
      }
    }
    if (J) {
      // joint j's column on the paths to the base: + for body a, - for body b
      for (int side = 0; side < 2; ++side) {
        const S sign = side == 0 ? S(1) : S(-1);
        const Vec3<S> p = side == 0 ? pa : pb;
        for (Index j = side == 0 ? l.body_a : l.body_b; j >= 0; j = bodies[j].parent) {
          Vec3<S> w, u;
          joint_point_column(bodies[j], X0[j], p, w, u);
          const S c[3] = {u.x, u.y, u.z}, d[3] = {w.x, w.y, w.z};
          for (int r = 0; r < 3; ++r) {
            J[(lin + r) * n + j] += sign * c[r];
            if (l.weld) J[(row + r) * n + j] += sign * d[r];
          }
        }
      }
    }
    row += l.rows();
  }
}

// ---- dense solves ---------------------------------------------------------------

// In-place Cholesky A = L L^T of an n x n SPD matrix (row-major; L in the lower
// triangle). Returns -1, or the first row whose pivot is not positive and finite.
template <class S>
SCANDYN_HD Index dense_cholesky(S* A, Index n) {
  using std::sqrt;
  for (Index j = 0; j < n; ++j) {
    S d = A[j * n + j];
    for (Index k = 0; k < j; ++k) d -= A[j * n + k] * A[j * n + k];
    if (!(d > S(0)) || !(d < S(INFINITY))) return j;
    d = sqrt(d);
    A[j * n + j] = d;
    for (Index i = j + 1; i < n; ++i) {
      S s = A[i * n + j];
      for (Index k = 0; k < j; ++k) s -= A[i * n + k] * A[j * n + k];
      A[i * n + j] = s / d;
    }
  }
  return -1;
}

// x <- (L L^T)^-1 x for the factor of dense_cholesky; x has `cols` columns, entry
// (i, c) at x[i * cols + c].
template <class S>
SCANDYN_HD void dense_cholesky_solve(const S* L, Index n, S* x, Index cols) {
  for (Index c = 0; c < cols; ++c) {
    for (Index i = 0; i < n; ++i) {
      S s = x[i * cols + c];
      for (Index k = 0; k < i; ++k) s -= L[i * n + k] * x[k * cols + c];
      x[i * cols + c] = s / L[i * n + i];
    }
    for (Index i = n - 1; i >= 0; --i) {
      S s = x[i * cols + c];
      for (Index k = i + 1; k < n; ++k) s -= L[k * n + i] * x[k * cols + c];
      x[i * cols + c] = s / L[i * n + i];
    }
  }
}

// The rank-revealing LDL^T of a symmetric positive semidefinite m x m matrix A
// (row-major, overwritten): P^T A P = L D L^T with diagonal pivoting; the first
// `rank` pivots are those above tol times the largest. Afterwards A holds L (unit,
// strictly lower, first `rank` columns) and D (diagonal); perm[k] is the row of A
// at position k.
template <class S>
SCANDYN_HD Index pivoted_ldlt(S* A, Index m, Index* perm, double tol) {
  using std::fabs;
  for (Index k = 0; k < m; ++k) perm[k] = k;
  S dmax = S(0);
  for (Index k = 0; k < m; ++k) {
    Index p = k;
    for (Index i = k + 1; i < m; ++i)
      if (A[i * m + i] > A[p * m + p]) p = i;
    const S d = A[p * m + p];
    if (k == 0) dmax = d;
    if (!(d > S(tol) * dmax) || !(dmax > S(0))) return k;
    if (p != k) {  // symmetric swap of rows and columns k and p
      for (Index j = 0; j < m; ++j) {
        const S t = A[k * m + j];
        A[k * m + j] = A[p * m + j], A[p * m + j] = t;
      }
      for (Index i = 0; i < m; ++i) {
        const S t = A[i * m + k];
        A[i * m + k] = A[i * m + p], A[i * m + p] = t;
      }
      const Index t = perm[k];
      perm[k] = perm[p], perm[p] = t;
    }
    // Schur complement of the trailing block; column k of L below the pivot
    for (Index i = k + 1; i < m; ++i) {
      const S lik = A[i * m + k] / d;
      for (Index j = k + 1; j <= i; ++j) A[i * m + j] -= lik * A[k * m + j];  // row k: still unscaled
      for (Index j = k + 1; j <= i; ++j) A[j * m + i] = A[i * m + j];
      A[i * m + k] = lik;
    }
  }
  return m;
}

// The minimum-norm x with A x = b for the factor of pivoted_ldlt (rank r; b in the
// range of A; x and b may be the same array). Scratch: w of r * (m - r) + (m - r)^2
// + m scalars.
template <class S>
SCANDYN_HD void pivoted_ldlt_solve(const S* F, Index m, const Index* perm, Index r, const S* b, S* x, S* w) {
  S* y = w;  // (m) the permuted solution
  for (Index k = 0; k < m; ++k) y[k] = b[perm[k]];
  // basic solution: L11 D L11^T y1 = b1, y2 = 0
  for (Index i = 0; i < r; ++i)
    for (Index k = 0; k < i; ++k) y[i] -= F[i * m + k] * y[k];
  for (Index i = 0; i < r; ++i) y[i] /= F[i * m + i];
  for (Index i = r - 1; i >= 0; --i)
    for (Index k = i + 1; k < r; ++k) y[i] -= F[k * m + i] * y[k];
  for (Index i = r; i < m; ++i) y[i] = S(0);
  const Index nr = m - r;
  if (nr > 0 && r > 0) {
    // null space N = [-Wt; I] with L11^T Wt = L21^T (r x nr); remove y's component in it:
    // y -= N t, (I + Wt^T Wt) t = N^T y = -Wt^T y1
    S* Wt = w + m;        // (r x nr)
    S* G = Wt + r * nr;   // (nr x nr)
    for (Index c = 0; c < nr; ++c) {
      for (Index i = r - 1; i >= 0; --i) {
        S s = F[(r + c) * m + i];
        for (Index k = i + 1; k < r; ++k) s -= F[k * m + i] * Wt[k * nr + c];
        Wt[i * nr + c] = s;
      }
    }
    for (Index a = 0; a < nr; ++a)
      for (Index c = 0; c < nr; ++c) {
        S s = a == c ? S(1) : S(0);
        for (Index k = 0; k < r; ++k) s += Wt[k * nr + a] * Wt[k * nr + c];
        G[a * nr + c] = s;
      }
    S* t = y + r;  // y2 = 0: t takes its place, y2 -= t afterwards
    for (Index a = 0; a < nr; ++a) {
      S s = S(0);
      for (Index k = 0; k < r; ++k) s -= Wt[k * nr + a] * y[k];
      t[a] = s;
    }
    dense_cholesky(G, nr);  // I + Wt^T Wt: SPD, pivots >= 1
    dense_cholesky_solve(G, nr, t, 1);
    for (Index k = 0; k < r; ++k)
      for (Index a = 0; a < nr; ++a) y[k] += Wt[k * nr + a] * t[a];
    for (Index a = 0; a < nr; ++a) t[a] = -t[a];
  }
  for (Index k = 0; k < m; ++k) x[perm[k]] = y[k];
}

// Scalars of scratch constrained_fd_solve takes for nv DoF and m constraint rows,
// and the Index entries (the pivot order).
SCANDYN_HD constexpr Index constrained_fd_scratch(Index nv, Index m) {
  return nv * nv + 2 * nv * m + m * m + 2 * m + (m / 2 + 1) * m + m * m + m + nv;
}

// Outcome of constrained_fd_solve.
struct LoopSolveStatus {
  Index failed_dof = -1;  // -1, or the row of M's Cholesky whose pivot failed (qdd, lambda not meaningful)
  Index rank = 0;         // numerical rank of A = J M^-1 J^T
};

// qdd (nv) and lambda (m) from M (nv x nv, row-major), h, tau (nv), J (m x nv) and
// gamma (m): M qdd + h = tau + J^T lambda, J qdd + gamma = 0. work: the scratch of
// constrained_fd_scratch(nv, m) scalars; perm: m Index entries. M, J, gamma are read
// only; the outputs may not alias the inputs.
template <class S>
SCANDYN_HD LoopSolveStatus constrained_fd_solve(Index nv, Index m, const S* M, const S* h, const S* tau, const S* J,
                                                const S* gamma, S* qdd, S* lambda, S* work, Index* perm) {
  LoopSolveStatus st;
  S* L = work;                 // (nv x nv) Cholesky factor of M
  S* MinvJt = L + nv * nv;     // (nv x m) M^-1 J^T
  S* A = MinvJt + nv * m;      // (m x m) J M^-1 J^T, then its factor
  S* rhs = A + m * m;          // (m)
  S* dlam = rhs + m;           // (m)
  S* w = dlam + m;             // pivoted_ldlt_solve's scratch
  for (Index e = 0; e < nv * nv; ++e) L[e] = M[e];
  st.failed_dof = dense_cholesky(L, nv);
  if (st.failed_dof >= 0) return st;
  for (Index i = 0; i < nv; ++i) qdd[i] = tau[i] - h[i];
  dense_cholesky_solve(L, nv, qdd, 1);  // the tree's qdd0
  if (m == 0) return st;
  for (Index i = 0; i < nv; ++i)
    for (Index k = 0; k < m; ++k) MinvJt[i * m + k] = J[k * nv + i];
  dense_cholesky_solve(L, nv, MinvJt, m);
  for (Index a = 0; a < m; ++a)
    for (Index c = 0; c <= a; ++c) {
      S s = S(0);
      for (Index i = 0; i < nv; ++i) s += J[a * nv + i] * MinvJt[i * m + c];
      A[a * m + c] = A[c * m + a] = s;
    }
  st.rank = pivoted_ldlt(A, m, perm, loop_rank_tolerance<S>());
  for (Index k = 0; k < m; ++k) lambda[k] = S(0);
  // lambda from -(J qdd + gamma), then once more from the residual (refinement)
  for (int pass = 0; pass < 2; ++pass) {
    for (Index a = 0; a < m; ++a) {
      S s = gamma[a];
      for (Index i = 0; i < nv; ++i) s += J[a * nv + i] * qdd[i];
      rhs[a] = -s;
    }
    pivoted_ldlt_solve(A, m, perm, st.rank, rhs, dlam, w);
    for (Index a = 0; a < m; ++a) lambda[a] += dlam[a];
    for (Index i = 0; i < nv; ++i) {
      S s = S(0);
      for (Index a = 0; a < m; ++a) s += MinvJt[i * m + a] * dlam[a];
      qdd[i] += s;
    }
  }
  return st;
}

}  // namespace scandyn
