// scandyn/instance/second_derivatives_analytic.hpp: the second-order derivatives of
// inverse dynamics of one instance by the analytical second-order recursion,
// __host__ __device__: what rnea_second_derivatives (scandyn/algorithm/
// second_derivatives.hpp), the CPU engines (cpu_fallback/second_derivatives.cpp) and
// the CUDA kernel (kernels/second_derivatives.cu) run for models of 1-DoF joints
// (revolute, prismatic) on a fixed base; and its weighted contraction
// (rnea_weighted_dq2_analytic_instance, at the end: sum_i w_i d2tau_i/dq dq in
// O(nv depth), the variational integrator's Newton Jacobian term). The dual-number
// passes of scandyn/instance/second_derivatives_instance.hpp stay as the independent
// reference of both.
//
// The algorithm is the second-order IDSVA recursion of S. Singh, R. P. Russell and
// P. M. Wensing, "Efficient Analytical Derivatives of Rigid-Body Dynamics Using
// Spatial Vector Algebra", IEEE Robotics and Automation Letters 7(2), 2022 (the one
// Pinocchio 3's computeRNEASecondOrderDerivatives implements): one forward pass of
// world-frame kinematics, then one backward pass that, for every body c (leaves to
// root, once its subtree's composite quantities are complete) and every pair of
// ancestors a <= b <= c on its path to the root, writes all entries of the four
// tensors whose three indices are {a, b, c}; triples not on one root-to-leaf path are
// 0. Work O(sum over bodies of depth^2) triples of 6-vector dot products.
//
// Derivation, in this file's notation (scandyn's first-order world-frame recursion,
// scandyn/instance/dynamics_derivatives.hpp, differentiated once more; all vectors in
// the world frame, x: motion cross product, x*: force cross product, "y <= x": y an
// ancestor of x or x itself, lambda: the parent). For body m: S_m, v_m, a_m,
// dV_m = v_lambda(m) x S_m, dA_m = a_lambda(m) x S_m + v_lambda(m) x dV_m; for the
// subtree of m: Ic_m (composite inertia), Bc_m (sum of C&M's B, B(I, u) w =
// u x* (I w) - I (u x w) + w x* (I u)), F_m (composite body force). Moving joint z
// (z <= m) turns everything of the subtree of m rigidly, plus non-rigid parts:
//   d S_m/dq_z  = S_z x S_m
//   d dV_m/dq_z = S_z x dV_m + dV_z x S_m                      (z < m; 0 for z = m)
//   d dA_m/dq_z = S_z x dA_m + dA_z x S_m + 2 dV_z x dV_m      (z < m; 0 for z = m)
//   d dV_m/dqd_z = S_z x S_m,  d dA_m/dqd_z = 2 (dV_z x S_m + S_z x dV_m)    (z < m)
//   d Ic_m/dq_z = S_z x* Ic_m - Ic_m S_z x                    (z <= m; z > m: that of Ic_z)
//   d Bc_m/dq_z = S_z x* Bc_m - Bc_m S_z x + B(Ic_m, dV_z)     (z <= m; z > m: that of Bc_z)
//   d Bc_m/dqd_z = B(Ic_m, S_z)                                (z <= m; z > m: B(Ic_z, S_z))
//   d F_m/dq_z  = S_z x* F_m + Ic_m dA_z + Bc_m dV_z            (z <= m; z > m: Phi_z)
//   d F_m/dqd_z = 2 Ic_m dV_z + Bc_m S_z                        (z <= m; z > m: Psi_z)
// with Phi_z = S_z x* F_z + Ic_z dA_z + Bc_z dV_z and Psi_z = 2 Ic_z dV_z + Bc_z S_z.
// Applied to the first-order entries (dtau_x/dq_y = S_x . (Ic_x dA_y + Bc_x dV_y) for
// y <= x, S_x . Phi_y for x < y; likewise dtau/dqd with 2 Ic dV + Bc S and Psi; M_xy =
// S_x . Ic_x S_y for y <= x), the rigid parts cancel in the scalar products wherever
// z is an ancestor of every body involved, and for a <= b <= c everything left is a
// product of the per-body vectors S_a, dV_a, dA_a with 6-vectors of the pair (b, c)
// (composites of c only), e.g.
//   d2tau_c/dq_b dq_a = dA_a . (S_b x* Ic_c S_c) + dV_a . P2(b, c)
//   d2tau_a/dq_c dq_b = S_a . K(b, c)
//   d2tau_b/dq_a dq_c = dA_a . Q1(b, c) + dV_a . Q2(b, c)
// (the full list in rnea_second_derivatives_analytic_instance below, each with the
// case it comes from). The formulas are this file's own derivation in scandyn's
// conventions ([angular; linear], Featherstone's x and x*); they are checked entry by
// entry against the dual-number passes and, in bench/pinocchio_second_order, against
// Pinocchio.
//
// Tensors: as in scandyn/instance/second_derivatives_instance.hpp (TensorRef):
//   d2tau_dq2(i, j, k) = d^2 tau_i / dq_j dq_k, d2tau_dqd2(i, j, k) = d^2 tau_i /
//   dqd_j dqd_k, d2tau_dqdqd(i, j, k) = d^2 tau_i / dq_j dqd_k, dM_dq(i, j, k) =
//   d M_ij / dq_k; every entry written (dM_dq only when its data is not null).
//
// Scratch per instance: nv DerivativeBody<S> (72 scalars each), the first-order
// recursion's (no dual numbers, no model copy).
#pragma once

#include <cstddef>

#include "scandyn/instance/dynamics_derivatives.hpp"
#include "scandyn/instance/second_derivatives_instance.hpp"

namespace scandyn {

namespace detail {

// Every entry of an nv x nv x nv tensor set to 0 (data null: nothing).
template <class S>
SCANDYN_HD void zero_tensor(TensorRef<S> t) {
  if (!t.data) return;
  const std::ptrdiff_t n3 = static_cast<std::ptrdiff_t>(t.n) * t.n * t.n;
  if (t.stride == 1) {
    for (std::ptrdiff_t e = 0; e < n3; ++e) t.data[e] = S(0);
  } else {
    for (std::ptrdiff_t e = 0; e < n3; ++e) t.data[e * t.stride] = S(0);
  }
}

}  // namespace detail

// The second derivatives of tau = ID(q, qd, qdd, fext) of one instance, gravity
// included, by the analytical second-order recursion (see the top of this file):
// the three tensors, every entry written, and dM_dq when its data is not null.
// body: the nv bodies in DoF order (1-DoF joints, fixed base: parent < index, as the
// model builder makes them); a0: the base acceleration (-g); q, qd, qdd: indexable by
// DoF (a pointer, a DofColumn); fext: nv body wrenches in body frames, or null; work:
// nv DerivativeBody entries of scratch.
template <class S, class V>
SCANDYN_HD void rnea_second_derivatives_analytic_instance(const Body<S>* body, Index nv, const Motion<S>& a0, V q,
                                                          V qd, V qdd, const Force<S>* fext, DerivativeBody<S>* work,
                                                          TensorRef<S> d2tau_dq2, TensorRef<S> d2tau_dqd2,
                                                          TensorRef<S> d2tau_dqdqd, TensorRef<S> dM_dq) {
  // forward: world-frame S, v, a, dV, dA, body inertias, forces and B (the first-order
  // recursion's pass); then the zero entries of DoF on different branches (none on an
  // unbranched chain: every triple lies on the one path)
  if (!derivative_forward_pass(body, nv, a0, q, qd, qdd, fext, work)) {
    detail::zero_tensor(d2tau_dq2);
    detail::zero_tensor(d2tau_dqd2);
    detail::zero_tensor(d2tau_dqdqd);
    detail::zero_tensor(dM_dq);
  }
  const TensorRef<S>& T = d2tau_dq2;    // T(x, y, z) = d2 tau_x / dq_y dq_z
  const TensorRef<S>& U = d2tau_dqd2;   // U(x, y, z) = d2 tau_x / dqd_y dqd_z
  const TensorRef<S>& W = d2tau_dqdqd;  // W(x, y, z) = d2 tau_x / dq_y dqd_z
  const std::ptrdiff_t nn = nv, n2 = static_cast<std::ptrdiff_t>(nv) * nv;
  // entry e = (x n + y) n + z of a tensor
  auto put = [](const TensorRef<S>& t, std::ptrdiff_t e, S value) { t.data[e * t.stride] = value; };
  const bool with_dM = dM_dq.data != nullptr;
  // backward: body c (the deepest index of the triples it closes), then its
  // ancestors b <= c and their ancestors a <= b
  for (Index c = nv - 1; c >= 0; --c) {
    const DerivativeBody<S>& wc = work[c];
    const Inertia<S>& Ic = wc.Ic;              // composite inertia of c's subtree
    const VelocityDerivative<S>& Bc = wc.Bc;   // composite B of c's subtree
    const Motion<S>& Sc = wc.J;
    const Motion<S>& dVc = wc.dV;
    const Force<S> f1 = Ic * Sc;                     // Ic_c S_c
    const Force<S> g1 = Bc.apply_transpose(Sc);      // Bc_c^T S_c
    const Force<S> hc = Ic * dVc;                    // Ic_c dV_c
    const Force<S> Phi = cross(Sc, wc.F) + Ic * wc.dA + Bc.apply(dVc);  // d F/dq_c of an ancestor's F
    const Force<S> Psi = S(2) * hc + Bc.apply(Sc);                      // d F/dqd_c of an ancestor's F
    // B(Ic_c, dV_c), for the pairs b < c only
    const VelocityDerivative<S> Bv = body[c].parent < 0 ? VelocityDerivative<S>{} : VelocityDerivative<S>::of(Ic, dVc);
    for (Index b = c; b >= 0; b = body[b].parent) {
      const DerivativeBody<S>& wb = work[b];
      const Motion<S>& Sb = wb.J;
      const Motion<S>& dVb = wb.dV;
      const Motion<S>& dAb = wb.dA;
      const bool bc = b == c;
      const Force<S> hb = Ic * dVb;          // Ic_c dV_b
      const Force<S> ISb = Ic * Sb;          // Ic_c S_b
      const Motion<S> ScSb = cross(Sc, Sb);  // S_c x S_b (0 for b = c)
      const Force<S> IScdVb = Ic * cross(Sc, dVb);  // Ic_c (S_c x dV_b)
      const Force<S> Y = cross(dVb, f1);               // dV_b x* Ic_c S_c
      const Force<S> Z = cross(Sc, hb) - IScdVb;       // S_c x* Ic_c dV_b - Ic_c (S_c x dV_b)
      // the pair's 6-vectors (forces, paired with S_a, dV_a, dA_a below):
      // P1 = S_b x* Ic_c S_c
      const Force<S> P1 = cross(Sb, f1);
      // P2: d2tau_c/dq_b dq_a = dA_a . P1 + dV_a . P2 (the dA_b, dV_b and Bc_c
      // derivatives along q_a); also d2tau_c/dq_b dqd_a = 2 dV_a . P1 + S_a . P2
      const Force<S> P2 = Y + cross(Sb, g1) - Z;
      // Q1 = (S_c x* Ic_c - Ic_c S_c x)^T S_b: d Ic_c/dq_c seen from S_b. With P1 it
      // gives B(Ic_c, S_b)^T S_c = P1 - Q1 and 2 Ic_c (S_b x S_c) + B(Ic_c, S_b) S_c =
      // d Psi_c/dqd_b = P1 + Q1
      const Force<S> Q1 = cross(Sc, ISb) - Ic * ScSb;
      // K = d Phi_c / dq_b (c's force as an ancestor sees it, moved by joint b)
      const Force<S> K = cross(Sb, Phi) + cross(Sc, Ic * dAb + Bc.apply(dVb)) +
                         Ic * (cross(dAb, Sc) + cross(dVb, dVc)) + Bc.apply(cross(dVb, Sc)) + cross(dVb, hc) +
                         cross(dVc, hb);
      // K2 = d Phi_c / dqd_b
      const Force<S> K2 = cross(Sc, S(2) * hb + Bc.apply(Sb)) + Ic * cross(Sb, dVc) - S(2) * IScdVb -
                          Bc.apply(ScSb) + cross(Sb, hc) + cross(dVc, ISb);
      // for b < c only:
      // Q2 = (S_c x* Bc_c - Bc_c S_c x + B(Ic_c, dV_c))^T S_b: d Bc_c/dq_c seen from S_b
      // K3 = S_b x* Psi_c + B(Ic_c, S_c) dV_b = d Phi_b / dqd_c (c in b's subtree), with
      //   B(Ic_c, S_c) dV_b = S_c x* Ic_c dV_b - Ic_c (S_c x dV_b) + dV_b x* Ic_c S_c = Z + Y
      // (and d Bc_c/dqd_c seen from S_b, B(Ic_c, S_c)^T S_b = -(P1 - Q1): s . B(I, u) m =
      // -u . B(I, s) m, B's antisymmetry in its velocity and the motion it is paired with)
      Force<S> Q2 = Force<S>::zero(), K3 = Force<S>::zero();
      if (!bc) {
        Q2 = cross(Sc, Bc.apply_transpose(Sb)) - Bc.apply_transpose(ScSb) + Bv.apply_transpose(Sb);
        K3 = cross(Sb, Psi) + Z + Y;
      }
      // entry (x, y, z) is at x n^2 + y n + z: the six orders of (a, b, c) as an offset
      // of the pair plus a, a n or a n^2
      const std::ptrdiff_t o_cba = c * n2 + b * nn, o_cab = c * n2 + b, o_acb = c * nn + b, o_abc = b * nn + c,
                           o_bac = b * n2 + c, o_bca = b * n2 + c * nn;
      for (Index a = b; a >= 0; a = body[a].parent) {
        const DerivativeBody<S>& wa = work[a];
        const Motion<S> Sa = wa.J, dVa = wa.dV, dAa = wa.dA;  // copies: the stores below may not alias them
        const bool ab = a == b;
        const std::ptrdiff_t a1 = a, an = a * nn, an2 = a * n2;
        const S SaP1 = dot(Sa, P1), SaQ1 = dot(Sa, Q1);
        const S dVaP1 = dot(dVa, P1), dVaQ1 = dot(dVa, Q1);
        const S SaP2 = dot(Sa, P2);
        // tau_c (the deepest): its derivatives along the ancestors a <= b
        const S t_cba = dot(dAa, P1) + dot(dVa, P2);
        put(T, o_cba + a1, t_cba);  // T(c, b, a)
        put(T, o_cab + an, t_cba);  // T(c, a, b)
        const S u_cba = SaP1 - SaQ1;  // S_c . B(Ic_c, S_b) S_a
        put(U, o_cba + a1, u_cba);
        put(U, o_cab + an, u_cba);
        put(W, o_cba + a1, S(2) * dVaP1 + SaP2);  // W(c, b, a)
        const S w_cab = dVaP1 - dVaQ1;              // S_c . B(Ic_c, S_b) dV_a
        if (!ab) put(W, o_cab + an, w_cab);         // W(c, a, b)
        // tau_a (the shallowest, a < c): d Phi_c and d Psi_c along joint b
        if (!(ab && bc)) {
          const S t_acb = dot(Sa, K);
          put(T, o_acb + an2, t_acb);  // T(a, c, b)
          put(T, o_abc + an2, t_acb);  // T(a, b, c)
          const S u_acb = SaP1 + SaQ1;
          put(U, o_acb + an2, u_acb);
          put(U, o_abc + an2, u_acb);
        }
        if (!ab) put(W, o_acb + an2, dot(Sa, K2));  // W(a, c, b)
        // tau_b (the middle one, b < c): Ic_b and Bc_b moved by joint c
        if (!bc) {
          const S SaQ2 = dot(Sa, Q2);
          if (!ab) {
            const S t_bac = dot(dAa, Q1) + dot(dVa, Q2);
            put(T, o_bac + an, t_bac);  // T(b, a, c)
            put(T, o_bca + a1, t_bac);  // T(b, c, a)
            const S u_bac = -u_cba;     // S_b . B(Ic_c, S_c) S_a
            put(U, o_bac + an, u_bac);
            put(U, o_bca + a1, u_bac);
            put(W, o_abc + an2, dot(Sa, K3));  // W(a, b, c)
          }
          put(W, o_bac + an, -w_cab);                 // W(b, a, c) = S_b . B(Ic_c, S_c) dV_a
          put(W, o_bca + a1, S(2) * dVaQ1 + SaQ2);    // W(b, c, a)
        }
        if (with_dM) {
          // d M_bc / dq_a = 0 (a is an ancestor of both: rigid); d M_ac / dq_b =
          // S_c . Ic_c (S_a x S_b) = S_a . P1; d M_ab / dq_c = S_a . Q1
          put(dM_dq, o_cba + a1, S(0));
          put(dM_dq, o_bca + a1, S(0));
          if (!ab) {
            put(dM_dq, o_acb + an2, SaP1);
            put(dM_dq, o_cab + an, SaP1);
          }
          if (!bc) {
            put(dM_dq, o_abc + an2, SaQ1);
            put(dM_dq, o_bac + an, SaQ1);
          }
        }
      }
    }
    const Index p = body[c].parent;
    if (p >= 0) {
      work[p].F += wc.F;
      work[p].Ic += wc.Ic;
      work[p].Bc += wc.Bc;
    }
  }
}

// The weighted recursion's per-body sums (rnea_weighted_dq2_analytic_instance's
// scratch, 28 scalars per body).
template <class S>
struct WeightedDq2Body {
  Motion<S> Pi;   // sum over the path root..i of w_y S_y
  Force<S> s1;    // sum over i's subtree of w_c Ic_c S_c
  Force<S> s2;    // sum over i's subtree of w_c Bc_c^T S_c
  Inertia<S> N;   // sum over i's subtree of w_c (S_c x* Ic_c - Ic_c S_c x) (inertia_rate)
};

// S x* I - I S x as an inertia (m, h, Ibar): the rate of the inertia I of a body
// moving with the twist S = (w, u) (mass rate 0, h' = w x h + m u, Ibar' = [w]x Ibar -
// Ibar [w]x - (u h^T + h u^T) + 2 (u . h) 1), what Ic_c turns by per unit q_c; a
// symmetric operator on motions, summed over subtrees like an inertia.
template <class S>
SCANDYN_HD Inertia<S> inertia_rate(const Motion<S>& s, const Inertia<S>& I) {
  const Mat3<S> WI = skew(s.w) * I.I.full();
  Sym3<S> Ib{S(2) * WI.m[0], S(2) * WI.m[4], S(2) * WI.m[8], WI.m[1] + WI.m[3], WI.m[2] + WI.m[6], WI.m[5] + WI.m[7]};
  Ib = Ib - sym_outer2(s.v, I.h);
  const S uh = S(2) * dot(s.v, I.h);
  Ib.xx += uh;
  Ib.yy += uh;
  Ib.zz += uh;
  return {S(0), cross(s.w, I.h) + I.m * s.v, Ib};
}

// The contraction of d2tau_dq2 with a weight w on tau, by the same recursion without
// the nv^3 tensor: out(j, k) = sum_i w_i d^2 tau_i / dq_j dq_k (nv x nv, symmetric,
// every entry written), the q-Hessian of w^T ID(q, qd, qdd, fext) for fixed w (the
// variational integrator's H, scandyn/sim/variational_instance.hpp). Arguments as
// rnea_second_derivatives_analytic_instance's, plus w (nv); work: nv DerivativeBody
// entries of scratch (the first-order recursion's), sums: nv WeightedDq2Body.
//
// Of the triple (a, b, c), a <= b <= c, only the d2tau_dq2 entries count, each
// weighted by the w of its first index and added to out's entry of its other two
// (out's lower triangle: row >= column, the deeper DoF first):
//   w_c (dA_a . P1(b, c) + dV_a . P2(b, c))  -> out(b, a)   (T(c, b, a) = T(c, a, b))
//   w_a (S_a . K(b, c))                       -> out(c, b)   (T(a, c, b); not for a = b = c)
//   w_b (dA_a . Q1(b, c) + dV_a . Q2(b, c))  -> out(c, a)   (T(b, a, c); a < b < c only)
// with the pair vectors of rnea_second_derivatives_analytic_instance. Each sum over
// the third index collapses into per-body sums, since P1, P2 are linear in c's
// composites and Q1, Q2 in S_b:
//   sum_c w_c P1(b, c) = S_b x* s1_b,
//   sum_c w_c P2(b, c) = dV_b x* s1_b + S_b x* s2_b - N_b dV_b   (c over b's subtree),
//   sum_{a<b<c} w_b Q1(b, c) = N'_c d,  sum w_b Q2(b, c) = R_c d,  d = Pi_lambda(c) - Pi_a,
//   sum_{a<=b} w_a S_a . K(b, c) = Pi_b . K(b, c)   (Pi_lambda(c) for b = c),
// where s1, s2, N (WeightedDq2Body) are subtree sums of w_c Ic_c S_c, w_c Bc_c^T S_c and
// w_c N'_c, N'_c = S_c x* Ic_c - Ic_c S_c x (inertia_rate), R_c m = S_c x* Bc_c^T m -
// Bc_c^T (S_c x m) + B(Ic_c, dV_c)^T m, and Pi_y the path sums of w S. So entry (x, y),
// y an ancestor of x or x, is complete at x's turn of the backward pass:
//   out(x, y) = dA_y . (S_x x* s1_x) + dV_y . (dV_x x* s1_x + S_x x* s2_x - N_x dV_x)
//             + Pi'_y . K(y, x) + [y < x] (dA_y . N'_x d + dV_y . R_x d),  d = Pi_lambda(x) - Pi_y.
// Work: O(sum over bodies of depth) pairs (the first-order recursion's count), no
// triples, no tensor, no dual numbers.
template <class S, class V>
SCANDYN_HD void rnea_weighted_dq2_analytic_instance(const Body<S>* body, Index nv, const Motion<S>& a0, V q, V qd,
                                                    V qdd, const Force<S>* fext, const S* w, DerivativeBody<S>* work,
                                                    WeightedDq2Body<S>* sums, MatrixRef<S> out) {
  // forward: world-frame S, v, a, dV, dA, body inertias, forces and B; the path sums Pi
  const bool chain = derivative_forward_pass(body, nv, a0, q, qd, qdd, fext, work);
  for (Index i = 0; i < nv; ++i) {
    const Index p = body[i].parent;
    sums[i].Pi = (p < 0 ? Motion<S>::zero() : sums[p].Pi) + w[i] * work[i].J;
    sums[i].s1 = sums[i].s2 = Force<S>::zero();
    sums[i].N = Inertia<S>::zero();
  }
  if (!chain)  // the entries of DoF on different branches
    for (Index i = 0; i < nv; ++i)
      for (Index j = 0; j <= i; ++j) out(i, j) = S(0);
  // backward: body x (its subtree's composites and sums complete), then its ancestors y <= x
  for (Index x = nv - 1; x >= 0; --x) {
    const DerivativeBody<S>& wx = work[x];
    WeightedDq2Body<S>& e = sums[x];
    const Inertia<S>& Ic = wx.Ic;             // composite inertia of x's subtree
    const VelocityDerivative<S>& Bc = wx.Bc;  // composite B of x's subtree
    const Motion<S>& Sx = wx.J;
    const Motion<S>& dVx = wx.dV;
    const Index px = body[x].parent;
    const S w_x = w[x];
    const Force<S> f1 = Ic * Sx;  // Ic_x S_x
    const Force<S> hc = Ic * dVx; // Ic_x dV_x
    e.s1 += w_x * f1;
    e.s2 += w_x * Bc.apply_transpose(Sx);
    e.N += inertia_rate(w_x * Sx, Ic);  // (linear in the twist)
    // the sums over x's subtree of w_c P1(x, c) and w_c P2(x, c)
    const Force<S> X1 = cross(Sx, e.s1);
    const Force<S> X2 = cross(dVx, e.s1) + cross(Sx, e.s2) - e.N * dVx;
    const Force<S> Phi = cross(Sx, wx.F) + Ic * wx.dA + Bc.apply(dVx);  // d F/dq_x of an ancestor's F
    const VelocityDerivative<S> Bv = px < 0 ? VelocityDerivative<S>{} : VelocityDerivative<S>::of(Ic, dVx);
    const Motion<S> Pl = px < 0 ? Motion<S>::zero() : sums[px].Pi;  // Pi_lambda(x)
    for (Index y = x; y >= 0; y = body[y].parent) {
      const DerivativeBody<S>& wy = work[y];
      const Motion<S> Sy = wy.J, dVy = wy.dV, dAy = wy.dA;  // copies: the store below may not alias them
      const Force<S> hb = Ic * dVy;  // Ic_x dV_y
      // K = d Phi_x / dq_y
      const Force<S> K = cross(Sy, Phi) + cross(Sx, Ic * dAy + Bc.apply(dVy)) +
                         Ic * (cross(dAy, Sx) + cross(dVy, dVx)) + Bc.apply(cross(dVy, Sx)) + cross(dVy, hc) +
                         cross(dVx, hb);
      S value = dot(dAy, X1) + dot(dVy, X2);
      if (y == x) {
        value += dot(Pl, K);
      } else {
        const Motion<S> Piy = sums[y].Pi;
        value += dot(Piy, K);
        const Motion<S> d = Pl - Piy;  // sum of w_b S_b over y < b < x
        const Motion<S> Sxd = cross(Sx, d);
        const Force<S> Nd = cross(Sx, Ic * d) - Ic * Sxd;
        const Force<S> Rd = cross(Sx, Bc.apply_transpose(d)) - Bc.apply_transpose(Sxd) + Bv.apply_transpose(d);
        value += dot(dAy, Nd) + dot(dVy, Rd);
      }
      out(x, y) = value;
    }
    if (px >= 0) {
      work[px].F += wx.F;
      work[px].Ic += wx.Ic;
      work[px].Bc += wx.Bc;
      sums[px].s1 += e.s1;
      sums[px].s2 += e.s2;
      sums[px].N += e.N;
    }
  }
  // the upper triangle
  for (Index i = 0; i < nv; ++i)
    for (Index j = 0; j < i; ++j) out(j, i) = out(i, j);
}

}  // namespace scandyn
