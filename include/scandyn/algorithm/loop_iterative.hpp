// scandyn/algorithm/loop_iterative.hpp: the tree passes of the matrix-free
// (iterative) closed-loop solver (scandyn/sim/iterative_loops.hpp; docs/loops.md,
// "The simulator's iterative loop path"), SCANDYN_HD and allocation-free on caller
// scratch, O(n + m) each: n bodies (1-DoF joints, DoF order, parent < index), m loop
// rows. Neither J (m x nv) nor M (nv x nv) is ever formed.
//
//   loop_aba_factor          the articulated-body algorithm's passes 1-3 (Featherstone
//                            2008, 7.3) with gravity, qd and tau: the tree's qdd0 =
//                            M^-1 (tau - h), and what M^-1 needs of the state at q:
//                            Xup_i, U_i = IA_i S_i and D_i = S_i^T IA_i S_i;
//   loop_point_wrenches      J^T lambda as body wrenches: lambda's rows act as point
//                            forces (and, weld, couples) on the loop's two links
//                            (loop_body_wrench: one body's, gathered from its loop
//                            sides without a scatter);
//   loop_tree_response       the response of a tree at zero velocity and without
//                            gravity to body wrenches f: M^-1 J^T lambda by the
//                            ABA's passes 2 and 3 with the articulated inertias of
//                            loop_aba_factor (only the bias forces and u_i change
//                            with f); with U null the "unit tree" (massless links, a
//                            unit joint-space inertia on every joint, D_i = 1): its
//                            qdd is J^T lambda itself;
//   loop_joint_forces        J^T lambda from those wrenches alone (the unit tree's
//                            backward pass);
//   loop_joint_motion        the body motions of joint rates x (a_i = Xup_i a_parent +
//                            S_i x_i: J x's motions, the ABA's pass 3 without terms);
//   loop_rows_apply          J x from those body motions (each loop point's velocity);
//   loop_response_blocks     Omega_i, body i's apparent inverse inertia (the
//                            acceleration of body i per unit wrench on it, the whole
//                            tree articulated), by the forward recursion
//                              Omega_i = P_i Xup_i Omega_p Xup_i^T P_i^T + S_i S_i^T / D_i,
//                              P_i = 1 - S_i U_i^T / D_i
//                            (Omega of the base 0; the unit tree: P_i = 1, D_i = 1);
//   loop_schur_block         loop k's diagonal block of A = J M^-1 J^T (or of J J^T)
//                            from Omega of its two links: exact when the two links have
//                            no moving ancestor in common (every loop of fivebar,
//                            fourbar and cloth:K:N), else the cross term through the
//                            common ancestors is left out (the block stays symmetric
//                            positive semi-definite: a preconditioner, not A);
//   loop_side_map            a loop side's rows of J per body motion (W below);
//   loop_child_response      Omega_{c,p}, the motion of a child c per unit wrench on
//                            its parent p: P_c Xup_c Omega_p (its transpose Omega_{p,c});
//   loop_pair_block          a share of the off-diagonal block (k, l) of A (or J J^T) of
//                            two loops with links on one body or on a child and its
//                            parent (the neighbour blocks of the preconditioners of
//                            scandyn/sim/iterative_loops.hpp: SSOR, symmetric block
//                            Gauss-Seidel, block-tridiagonal along the ropes, block
//                            DILU);
//   symmetric_eigen          a symmetric d x d (d <= 6) matrix's eigenvalues and vectors;
//   symmetric_pseudo_inverse the inverse of such a block (Jacobi eigenvalue iteration),
//                            as the solver's least-squares weights W with the
//                            eigenvalues raised to kLoopBlockFloor of the block's
//                            largest (bounded, positive definite weights; a zero row
//                            of J, e.g. of a loop at the first links of two ropes,
//                            is an eigenvector of its block, and J^T W leaves it out);
//                            without a floor, the pseudo-inverse.
//
// The conjugate gradients over these passes are host code (src/sim/iterative_loops.cpp);
// the CUDA solver (kernels/loop_iterative.cu) runs the passes one thread per chain
// (the *_range forms, below) and one thread per loop.
#pragma once

#include <cmath>

#include "scandyn/algorithm/loop_solver.hpp"
#include "scandyn/spatial/small_matrix.hpp"

namespace scandyn {

// The block weights' eigenvalue floor, relative to each block's largest
// (a nearly singular block, e.g. a loop point moved by two nearly parallel joint axes,
// is inverted as if its weak eigenvalues were this large: a pseudo-inverse would weigh
// those rows by up to 1e10, and the least squares would follow their rounding).
inline constexpr double kLoopBlockFloor = 1e-6;

// Passes 1-3 of the ABA (gravity, qd, tau; no external wrenches) writing what the
// zero-velocity responses reuse: Xup, U, D (n each) and the tree's qdd0 (n).
// Scratch (n each): v, c, a (motions), IA (articulated inertias), pA (forces), u.
// Returns -1, or the DoF whose articulated pivot D_i was not positive and finite.
//
// The *_range forms of the tree passes (loop_aba_factor_range, loop_tree_response_range,
// loop_joint_motion_range, loop_response_blocks_range; loop_body_motion_range in
// loop_solver.hpp) walk the bodies [begin, end) only, on the whole tree's arrays (global
// body indices): a range closed under the parent relation (every body's parent in the
// range or the base), e.g. one unbranched chain hanging from the base, as the CUDA
// iterative loop solver's threads walk them (scandyn/cuda/loop_iterative.hpp). Each
// body's arithmetic is the whole-tree pass's, in the same order: the composition over
// such ranges equals the whole-tree pass bit for bit (the whole-tree forms call them
// with [0, n)).
template <class S>
SCANDYN_HD Index loop_aba_factor_range(const Body<S>* bodies, Index begin, Index end, const Vec3<S>& gravity,
                                       const S* q, const S* qd, const S* tau, Transform<S>* Xup, Force<S>* U, S* D,
                                       S* qdd0, Motion<S>* v, Motion<S>* c, Motion<S>* a, ABInertia<S>* IA,
                                       Force<S>* pA, S* u) {
  for (Index i = begin; i < end; ++i) {  // pass 1: velocities, velocity products, bias forces
    const Body<S>& b = bodies[i];
    const Index p = b.parent;
    Xup[i] = joint_transform(b, q[i]);
    const AbaForward<S> o = aba_forward_step(b, Xup[i], p < 0 ? Motion<S>::zero() : v[p], qd[i]);
    v[i] = o.v, c[i] = o.c, pA[i] = o.pA;
    IA[i] = ABInertia<S>::from(b.I);
  }
  for (Index i = end - 1; i >= begin; --i) {  // pass 2: articulated inertias, leaves to root
    const Body<S>& b = bodies[i];
    aba_joint_terms(b, IA[i], pA[i], tau[i], U[i], D[i], u[i]);
    if (!pivot_ok(D[i])) return i;
    if (b.parent >= 0) aba_backward_to_parent(Xup[i], IA[i], pA[i], c[i], U[i], D[i], u[i], IA[b.parent], pA[b.parent]);
  }
  const Motion<S> a0 = base_acceleration(gravity);
  for (Index i = begin; i < end; ++i) {  // pass 3: accelerations
    const Body<S>& b = bodies[i];
    qdd0[i] = aba_acceleration_step(b, Xup[i], b.parent < 0 ? a0 : a[b.parent], c[i], U[i], D[i], u[i], a[i]);
  }
  return -1;
}
template <class S>
SCANDYN_HD Index loop_aba_factor(const Body<S>* bodies, Index n, const Vec3<S>& gravity, const S* q, const S* qd,
                                 const S* tau, Transform<S>* Xup, Force<S>* U, S* D, S* qdd0, Motion<S>* v,
                                 Motion<S>* c, Motion<S>* a, ABInertia<S>* IA, Force<S>* pA, S* u) {
  return loop_aba_factor_range(bodies, Index(0), n, gravity, q, qd, tau, Xup, U, D, qdd0, v, c, a, IA, pA, u);
}

// Xup_i at q alone (the unit tree's transforms, for the projection).
template <class S>
SCANDYN_HD void loop_joint_transforms(const Body<S>* bodies, Index n, const S* q, Transform<S>* Xup) {
  for (Index i = 0; i < n; ++i) Xup[i] = joint_transform(bodies[i], q[i]);
}

// f (n body wrenches, body frames) = the wrenches whose joint forces are J^T lambda:
// loop k's linear rows l act as the force +l at point a of link a and -l at point b
// of link b (base coordinates: E l on the body, moment p x E l about its origin); a
// weld's angular rows as the couples +-E l. A link -1 (the base) takes nothing.
// Loop l's wrench on its side `side`'s body (not the base), lambda_row: the loop's rows.
template <class S>
SCANDYN_HD Force<S> loop_side_wrench(const LoopRow<S>& l, int side, const Transform<S>* X0, const S* lambda_row) {
  const Index lin = l.weld ? 3 : 0;
  const Vec3<S> fl{lambda_row[lin], lambda_row[lin + 1], lambda_row[lin + 2]};
  const Index body = side == 0 ? l.body_a : l.body_b;
  const S sign = side == 0 ? S(1) : S(-1);
  const Vec3<S>& p = side == 0 ? l.point_a : l.point_b;
  const Vec3<S> fb = sign * (X0[body].E * fl);
  Vec3<S> nb = cross(p, fb);
  if (l.weld) nb += sign * (X0[body].E * Vec3<S>{lambda_row[0], lambda_row[1], lambda_row[2]});
  return Force<S>{nb, fb};
}

template <class S>
SCANDYN_HD void loop_point_wrenches(const LoopRow<S>* loops, Index nloops, Index n, const Transform<S>* X0,
                                    const S* lambda, Force<S>* f) {
  for (Index i = 0; i < n; ++i) f[i] = Force<S>::zero();
  Index row = 0;
  for (Index k = 0; k < nloops; ++k) {
    const LoopRow<S>& l = loops[k];
    for (int side = 0; side < 2; ++side) {
      const Index body = side == 0 ? l.body_a : l.body_b;
      if (body < 0) continue;
      f[body] += loop_side_wrench(l, side, X0, lambda + row);
    }
    row += l.rows();
  }
}

// Body `body`'s entry of loop_point_wrenches' f gathered from its loop sides (no
// scatter: what a thread per body or per chain computes without races): side_start
// (bodies + 1) and side (2 k + s: loop k's side s, per body in increasing order, as
// loop_body_sides builds them), row_of (loops): each loop's first row. The same sums
// in the same order as loop_point_wrenches: bit for bit its f[body].
template <class S>
SCANDYN_HD Force<S> loop_body_wrench(const LoopRow<S>* loops, const Index* row_of, const Index* side_start,
                                     const Index* side, Index body, const Transform<S>* X0, const S* lambda) {
  Force<S> f = Force<S>::zero();
  for (Index e = side_start[body]; e < side_start[body + 1]; ++e) {
    const Index k = side[e] >> 1;
    f += loop_side_wrench(loops[k], static_cast<int>(side[e] & 1), X0, lambda + row_of[k]);
  }
  return f;
}

// The tree's response at zero velocity and without gravity to the body wrenches f
// (external forces on the bodies): qdd = M^-1 S^T-sums of f, and the body
// accelerations a. Passes 2 and 3 of the ABA with the articulated inertias of
// loop_aba_factor (U, D): per body pA_i = -f_i + the children's Xup^T pa,
// u_i = -S_i^T pA_i, pa_i = pA_i + U_i u_i / D_i (c = 0 at zero velocity); then
// a'_i = Xup_i a_parent, qdd_i = (u_i - U_i^T a'_i) / D_i, a_i = a'_i + S_i qdd_i.
// U null: the unit tree (U = 0, D = 1): qdd_i = S_i^T (f summed over i's subtree),
// i.e. qdd = J^T lambda for loop_point_wrenches' f. Scratch pA (n forces).
template <class S>
SCANDYN_HD void loop_tree_response_range(const Body<S>* bodies, Index begin, Index end, const Transform<S>* Xup,
                                         const Force<S>* U, const S* D, const Force<S>* f, Force<S>* pA, S* qdd,
                                         Motion<S>* a) {
  for (Index i = begin; i < end; ++i) pA[i] = -f[i];
  for (Index i = end - 1; i >= begin; --i) {
    const Body<S>& b = bodies[i];
    const S u = -joint_project(b, pA[i]);
    qdd[i] = u;  // u_i until pass 3
    if (b.parent < 0) continue;
    const Force<S> pa = U ? pA[i] + (u / D[i]) * U[i] : pA[i];
    pA[b.parent] += Xup[i].apply_transpose(pa);
  }
  for (Index i = begin; i < end; ++i) {
    const Body<S>& b = bodies[i];
    const Motion<S> ap = b.parent < 0 ? Motion<S>::zero() : Xup[i].apply(a[b.parent]);
    if (U) qdd[i] = (qdd[i] - dot(ap, U[i])) / D[i];
    a[i] = add_joint_motion(b, ap, qdd[i]);
  }
}
template <class S>
SCANDYN_HD void loop_tree_response(const Body<S>* bodies, Index n, const Transform<S>* Xup, const Force<S>* U,
                                   const S* D, const Force<S>* f, Force<S>* pA, S* qdd, Motion<S>* a) {
  loop_tree_response_range(bodies, Index(0), n, Xup, U, D, f, pA, qdd, a);
}

// tau = J^T lambda from loop_point_wrenches' f: tau_i = S_i^T (the wrenches of i's
// subtree, summed in i's frame), the backward half of loop_tree_response's unit tree.
// Scratch F (n forces).
template <class S>
SCANDYN_HD void loop_joint_forces(const Body<S>* bodies, Index n, const Transform<S>* Xup, const Force<S>* f,
                                  Force<S>* F, S* tau) {
  for (Index i = 0; i < n; ++i) F[i] = f[i];
  for (Index i = n - 1; i >= 0; --i) {
    const Body<S>& b = bodies[i];
    tau[i] = joint_project(b, F[i]);
    if (b.parent >= 0) F[b.parent] += Xup[i].apply_transpose(F[i]);
  }
}

// The body motions of joint rates x: a_i = Xup_i a_parent + S_i x_i (J x's motions).
template <class S>
SCANDYN_HD void loop_joint_motion_range(const Body<S>* bodies, Index begin, Index end, const Transform<S>* Xup,
                                        const S* x, Motion<S>* a) {
  for (Index i = begin; i < end; ++i) {
    const Body<S>& b = bodies[i];
    a[i] = add_joint_motion(b, b.parent < 0 ? Motion<S>::zero() : Xup[i].apply(a[b.parent]), x[i]);
  }
}
template <class S>
SCANDYN_HD void loop_joint_motion(const Body<S>* bodies, Index n, const Transform<S>* Xup, const S* x, Motion<S>* a) {
  loop_joint_motion_range(bodies, Index(0), n, Xup, x, a);
}

// out (m) = J x from the body motions a of x (loop_joint_motion, or the response's
// accelerations): each loop's point velocity of a minus that of b (base
// coordinates), a weld's angular rows the angular velocities' difference.
template <class S>
SCANDYN_HD void loop_rows_apply(const LoopRow<S>* loops, Index nloops, const Transform<S>* X0, const Motion<S>* a,
                                S* out) {
  Index row = 0;
  for (Index k = 0; k < nloops; ++k) {
    const LoopRow<S>& l = loops[k];
    const Index lin = l.weld ? row + 3 : row;
    Vec3<S> dv = Vec3<S>::zero(), dw = Vec3<S>::zero();
    if (l.body_a >= 0) {
      dv += point_velocity(X0[l.body_a], a[l.body_a], l.point_a);
      if (l.weld) dw += to_world(X0[l.body_a], a[l.body_a].w);
    }
    if (l.body_b >= 0) {
      dv -= point_velocity(X0[l.body_b], a[l.body_b], l.point_b);
      if (l.weld) dw -= to_world(X0[l.body_b], a[l.body_b].w);
    }
    out[lin] = dv.x, out[lin + 1] = dv.y, out[lin + 2] = dv.z;
    if (l.weld) out[row] = dw.x, out[row + 1] = dw.y, out[row + 2] = dw.z;
    row += l.rows();
  }
}

// A B^T for 6x6 matrices.
template <class S>
SCANDYN_HD Mat6<S> mul_transpose_right(const Mat6<S>& A, const Mat6<S>& B) {
  Mat6<S> o;
  for (int r = 0; r < 6; ++r)
    for (int c = 0; c < 6; ++c) {
      S s = S(0);
      for (int k = 0; k < 6; ++k) s += A(r, k) * B(c, k);
      o(r, c) = s;
    }
  return o;
}

// Omega_i (n 6x6, body coordinates: motion per unit wrench) by the forward recursion
// of the header; U null: the unit tree's (J_i J_i^T of body i's Jacobian).
template <class S>
SCANDYN_HD void loop_response_blocks_range(const Body<S>* bodies, Index begin, Index end, const Transform<S>* Xup,
                                           const Force<S>* U, const S* D, Mat6<S>* Omega) {
  for (Index i = begin; i < end; ++i) {
    const Body<S>& b = bodies[i];
    Mat6<S> W = Mat6<S>::zero();
    if (b.parent >= 0) {
      const Mat6<S> X = to_mat6(Xup[i]);
      W = X * mul_transpose_right(Omega[b.parent], X);
    }
    const Motion<S> s = joint_motion(b, S(1));
    const S sv[6] = {s.w.x, s.w.y, s.w.z, s.v.x, s.v.y, s.v.z};
    S Dinv = S(1);
    if (U) {
      // P W P^T with P = 1 - s U^T / D: W - s (U^T W) / D - (W U) s^T / D + s s^T (U^T W U) / D^2
      Dinv = S(1) / D[i];
      const S uv[6] = {U[i].n.x, U[i].n.y, U[i].n.z, U[i].f.x, U[i].f.y, U[i].f.z};
      S WU[6], UWU = S(0);
      for (int r = 0; r < 6; ++r) {
        S t = S(0);
        for (int k = 0; k < 6; ++k) t += W(r, k) * uv[k];
        WU[r] = t;
        UWU += uv[r] * t;
      }
      for (int r = 0; r < 6; ++r)
        for (int k = 0; k < 6; ++k)
          W(r, k) += -(sv[r] * WU[k] + WU[r] * sv[k]) * Dinv + sv[r] * sv[k] * UWU * Dinv * Dinv;
    }
    for (int r = 0; r < 6; ++r)
      for (int k = 0; k < 6; ++k) W(r, k) += sv[r] * sv[k] * Dinv;
    Omega[i] = W;
  }
}
template <class S>
SCANDYN_HD void loop_response_blocks(const Body<S>* bodies, Index n, const Transform<S>* Xup, const Force<S>* U,
                                     const S* D, Mat6<S>* Omega) {
  loop_response_blocks_range(bodies, Index(0), n, Xup, U, D, Omega);
}

// The map from loop l's side `side` (0: a, 1: b) body's motion (body coordinates) to
// that side's rows of J (base coordinates): W = diag(E^T, E^T) [1 0; -[p]x 1], i.e.
// [w; v] -> [w; the velocity of point p]; the loop's rows are W's rows 3-5 (point) or
// 0-5 (weld), and its J is W_a (body a's motion) - W_b (body b's motion).
template <class S>
SCANDYN_HD Mat6<S> loop_side_map(const LoopRow<S>& l, int side, const Transform<S>* X0) {
  const Index body = side == 0 ? l.body_a : l.body_b;
  const Vec3<S>& p = side == 0 ? l.point_a : l.point_b;
  const Mat3<S>& E = X0[body].E;
  Mat6<S> W = Mat6<S>::zero();
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) {
      W(r, c) = E(c, r);
      W(r + 3, c + 3) = E(c, r);
      // (E^T (-[p]x))(r, c) = -sum_k E(k, r) [p]x(k, c)
      const Vec3<S> ec{E(0, r), E(1, r), E(2, r)};  // row r of E^T
      const Vec3<S> unit{S(c == 0), S(c == 1), S(c == 2)};
      W(r + 3, c) = -dot(ec, cross(p, unit));
    }
  return W;
}

// Loop l's diagonal block (d x d, d = l.rows(), row-major in out) of J Omega J^T from
// its links' Omega (see the header: the cross term through common ancestors is not
// included). A link's rows of J are loop_side_map's W applied to its body motion.
template <class S>
SCANDYN_HD void loop_schur_block(const LoopRow<S>& l, const Transform<S>* X0, const Mat6<S>* Omega, S* out) {
  const int d = l.rows();
  const int first = l.weld ? 0 : 3;  // rows of the 6 [angular; linear] kept
  for (int e = 0; e < d * d; ++e) out[e] = S(0);
  for (int side = 0; side < 2; ++side) {
    const Index body = side == 0 ? l.body_a : l.body_b;
    if (body < 0) continue;
    const Mat6<S> W = loop_side_map(l, side, X0);
    const Mat6<S> B = W * mul_transpose_right(Omega[body], W);
    for (int r = 0; r < d; ++r)
      for (int c = 0; c < d; ++c) out[r * d + c] += B(first + r, first + c);
  }
}

// Omega_{c,p}: the motion of body c (its coordinates) per unit wrench on its parent p
// (p's coordinates), the whole tree articulated: P_c Xup_c Omega_p (a wrench on p moves
// c through its joint's articulated response: a_c = P_c Xup_c a_p, P_c = 1 - S_c U_c^T /
// D_c; U null, the unit tree: P_c = 1). Its transpose is Omega_{p,c} (M^-1 is symmetric).
template <class S>
SCANDYN_HD Mat6<S> loop_child_response(const Body<S>& child, const Transform<S>& Xup_c, const Force<S>* U_c, S D_c,
                                       const Mat6<S>& Omega_p) {
  Mat6<S> R = to_mat6(Xup_c) * Omega_p;
  if (U_c) {
    const Motion<S> s = joint_motion(child, S(1));
    const S sv[6] = {s.w.x, s.w.y, s.w.z, s.v.x, s.v.y, s.v.z};
    const S uv[6] = {U_c->n.x, U_c->n.y, U_c->n.z, U_c->f.x, U_c->f.y, U_c->f.z};
    S UR[6];  // U^T R / D
    for (int c = 0; c < 6; ++c) {
      S t = S(0);
      for (int k = 0; k < 6; ++k) t += uv[k] * R(k, c);
      UR[c] = t / D_c;
    }
    for (int r = 0; r < 6; ++r)
      for (int c = 0; c < 6; ++c) R(r, c) -= sv[r] * UR[c];
  }
  return R;
}

// Adds loop l1's side s1 and loop l2's side s2's share of the off-diagonal block
// (l1, l2) of J Omega J^T (d1 x d2, row-major in out): sign_1 sign_2 W_1 Omega_12 W_2^T
// restricted to the loops' rows (sign +1 on side a, -1 on side b; Omega_12 the motion
// of side 1's body per unit wrench on side 2's: Omega of the body when they are one,
// loop_child_response or its transpose for a child and its parent).
template <class S>
SCANDYN_HD void loop_pair_block(const LoopRow<S>& l1, int s1, const LoopRow<S>& l2, int s2, const Transform<S>* X0,
                                const Mat6<S>& Omega12, S* out) {
  const int d1 = l1.rows(), d2 = l2.rows();
  const int f1 = l1.weld ? 0 : 3, f2 = l2.weld ? 0 : 3;
  const Mat6<S> W1 = loop_side_map(l1, s1, X0), W2 = loop_side_map(l2, s2, X0);
  S T[36];  // Omega12 W2^T, the loop's columns only (6 x d2)
  for (int r = 0; r < 6; ++r)
    for (int c = 0; c < d2; ++c) {
      S t = S(0);
      for (int k = 0; k < 6; ++k) t += Omega12(r, k) * W2(f2 + c, k);
      T[r * d2 + c] = t;
    }
  const S sign = (s1 == s2) ? S(1) : S(-1);
  for (int r = 0; r < d1; ++r)
    for (int c = 0; c < d2; ++c) {
      S t = S(0);
      for (int k = 0; k < 6; ++k) t += W1(f1 + r, k) * T[k * d2 + c];
      out[r * d2 + c] += sign * t;
    }
}

// The eigen-decomposition of a symmetric d x d matrix A (d <= 6, row-major) by cyclic
// Jacobi rotations: A = V diag(lam) V^T, V's columns the eigenvectors (row-major d x d).
template <class S>
SCANDYN_HD void symmetric_eigen(const S* A, int d, S* V, S* lam) {
  S a[36];
  for (int r = 0; r < d; ++r)
    for (int c = 0; c < d; ++c) V[r * d + c] = S(r == c), a[r * d + c] = A[r * d + c];
  for (int sweep = 0; sweep < 30; ++sweep) {
    S off = S(0), diag = S(0);
    for (int r = 0; r < d; ++r) {
      diag += a[r * d + r] * a[r * d + r];
      for (int c = r + 1; c < d; ++c) off += a[r * d + c] * a[r * d + c];
    }
    if (!(off > S(1e-30) * diag)) break;
    for (int p = 0; p < d; ++p)
      for (int q = p + 1; q < d; ++q) {
        const S apq = a[p * d + q];
        if (apq == S(0)) continue;
        const S theta = (a[q * d + q] - a[p * d + p]) / (S(2) * apq);
        const S t = (theta >= S(0) ? S(1) : S(-1)) / (std::fabs(theta) + std::sqrt(theta * theta + S(1)));
        const S cs = S(1) / std::sqrt(t * t + S(1)), sn = t * cs;
        for (int k = 0; k < d; ++k) {  // columns p, q
          const S akp = a[k * d + p], akq = a[k * d + q];
          a[k * d + p] = cs * akp - sn * akq, a[k * d + q] = sn * akp + cs * akq;
        }
        for (int k = 0; k < d; ++k) {  // rows p, q
          const S apk = a[p * d + k], aqk = a[q * d + k];
          a[p * d + k] = cs * apk - sn * aqk, a[q * d + k] = sn * apk + cs * aqk;
        }
        for (int k = 0; k < d; ++k) {
          const S vkp = V[k * d + p], vkq = V[k * d + q];
          V[k * d + p] = cs * vkp - sn * vkq, V[k * d + q] = sn * vkp + cs * vkq;
        }
      }
  }
  for (int k = 0; k < d; ++k) lam[k] = a[k * d + k];
}

// The inverse of a symmetric positive semi-definite d x d matrix (d <= 6, row-major,
// overwritten) by cyclic Jacobi rotations, its eigenvalues raised to at least `floor`
// times the largest: floor 0, the pseudo-inverse (eigenvalues at most 1e-10 times the
// largest, or not positive, count as zero); floor > 0, a bounded, positive definite
// inverse (the block-Jacobi weights: a nearly singular block would otherwise weigh
// its weak direction by up to 1e10). `scale` > 0: the floor is relative to it instead
// of the largest eigenvalue. A zero matrix stays zero.
template <class S>
SCANDYN_HD void symmetric_pseudo_inverse(S* A, int d, S floor = S(0), S scale = S(0)) {
  S V[36], lam[6];
  symmetric_eigen(A, d, V, lam);
  S big = S(0);
  for (int k = 0; k < d; ++k) big = lam[k] > big ? lam[k] : big;
  if (scale > S(0)) big = scale;
  for (int r = 0; r < d; ++r)
    for (int c = 0; c < d; ++c) {
      S s = S(0);
      for (int k = 0; k < d; ++k) {
        if (floor > S(0) && big > S(0)) s += V[r * d + k] * V[c * d + k] / (lam[k] > floor * big ? lam[k] : floor * big);
        else if (lam[k] > S(1e-10) * big) s += V[r * d + k] * V[c * d + k] / lam[k];
      }
      A[r * d + c] = s;
    }
}

}  // namespace scandyn
