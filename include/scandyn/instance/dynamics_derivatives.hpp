// scandyn/instance/dynamics_derivatives.hpp: first-order analytical derivatives of
// inverse and forward dynamics for one instance, __host__ __device__: the serial
// reference (scandyn/algorithm/derivatives.hpp), the OpenMP engine and the CUDA
// kernel (kernels/derivatives.cu) all run these functions.
//
// The recursions of Carpentier & Mansard, "Analytical derivatives of rigid body
// dynamics algorithms", RSS 2018 (the ones Pinocchio's computeRNEADerivatives and
// computeABADerivatives implement), in scandyn's conventions ([angular; linear],
// Featherstone's names). Everything below is expressed in the world (= base) frame
// 0, where composite quantities are plain sums over subtrees. For body i with
// parent p = lambda(i), joint motion S_i (world), x the motion cross product and x*
// the force cross product:
//   v_i = v_p + S_i qd_i,  a_i = a_p + S_i qdd_i + (v_i x S_i) qd_i      (a_base = -g)
//   f_i = I_i a_i + v_i x* I_i v_i - fext_i,     F_i = sum of f_k over subtree(i)
//   tau_i = S_i . F_i
// Joint j moves its subtree rigidly (dS_k/dq_j = S_j x S_k, dI_k/dq_j = S_j x* I_k -
// I_k S_j x for j an ancestor of k, or k itself), which leaves per joint j
//   dV_j = v_p x S_j                     (the non-rigid part of dv_k/dq_j)
//   dA_j = a_p x S_j + v_p x dV_j        (the non-rigid part of da_k/dq_j is dA_j + dV_j x v_k)
// and per body the matrix B_k m = v_k x* (I_k m) - I_k (v_k x m) + m x* (I_k v_k)
// (C&M's "B", the derivative of the body force's velocity terms; VelocityDerivative
// stores its 12 non-zero parameters), summed over subtrees into Bc_i next to the
// composite inertia Ic_i. Then, for j an ancestor of
// i or i itself (and the transposed entries for i an ancestor of j):
//   dtau_i/dq_j  = S_i . (Ic_i dA_j + Bc_i dV_j)          dtau_j/dq_i  = S_j . Phi_i
//   dtau_i/dqd_j = S_i . (2 Ic_i dV_j + Bc_i S_j)         dtau_j/dqd_i = S_j . Psi_i
//   M_ij         = S_i . Ic_i S_j                         (M_ji = M_ij)
// with Phi_i = S_i x* F_i + Ic_i dA_i + Bc_i dV_i and Psi_i = 2 Ic_i dV_i + Bc_i S_i;
// entries of bodies on different branches are 0. External wrenches (constant in
// their body's frame) rotate with the body and enter only through F. One forward
// pass (O(nv)) and one backward pass over every (body, ancestor) pair (O(nv depth)).
//
// Forward dynamics: qdd = FD(q, qd, tau, fext) satisfies ID(q, qd, qdd, fext) = tau,
// so at that qdd
//   dqdd/dq = -M^-1 dtau/dq,  dqdd/dqd = -M^-1 dtau/dqd,  dqdd/dtau = M^-1
// (C&M section IV): fd_derivatives_instance evaluates the inverse-dynamics
// derivatives at the caller's qdd (from the ABA), factors M = L^T L in place with
// the tree's sparsity and solves, all in the output blocks (or, given a compile-time
// capacity of up to 8 DoF, with L in registers: packed_fd_solve).
#pragma once

#include <cstddef>
#include <type_traits>

#include "scandyn/algorithm/steps.hpp"
#include "scandyn/batch.hpp"

namespace scandyn {

// An nv x nv matrix of one instance: entry (i, j) at data[(i * n + j) * stride]
// (stride 1: row-major; a batch's instance-innermost layout: stride B).
template <class S>
struct MatrixRef {
  S* data;
  Index n;
  std::ptrdiff_t stride;
  SCANDYN_HD S& operator()(Index i, Index j) const {
    return data[(static_cast<std::ptrdiff_t>(i) * n + j) * stride];
  }
};

// Instance b's matrix in a batch view of nv * nv entries per instance (entry i * nv
// + j: (i, j); the engines' output layout, scandyn/engine.hpp).
template <class S>
SCANDYN_HD MatrixRef<S> instance_matrix(const BatchView<S>& v, long long b, Index nv) {
  return {v.data + b * v.batch_stride, nv, v.dof_stride};
}

// C&M's B for a body of inertia I moving with v (world frame), B m = v x* (I m) -
// I (v x m) + m x* (I v), or a sum of them over a subtree. B vanishes on linear
// motions: with p = I v = [n; f] (f = m v_lin + w x h) the linear columns are
// [(w x h + m v_lin - f) x; 0] = 0, so B = [Bw 0; -2 [f]x 0] and a subtree's sum is
// its sum of Bw and of the linear momenta f (12 scalars, not 36):
//   Bw = [w]x Ibar + ([w]x Ibar)^T - (v h^T + h v^T) + 2 (v . h) 1 - [n]x
// (h = m c, Ibar the rotational inertia about the frame origin).
template <class S>
struct VelocityDerivative {
  Mat3<S> Bw;  // the angular-angular block
  Vec3<S> P;   // linear momentum: the angular-to-linear block is -2 [P]x

  SCANDYN_HD static VelocityDerivative of(const Inertia<S>& I, const Motion<S>& v) {
    const Force<S> p = I * v;
    const Mat3<S> WI = skew(v.w) * I.I.full();
    const Mat3<S> N = skew(p.n);
    const S vh2 = S(2) * dot(v.v, I.h);
    VelocityDerivative o;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c)
        o.Bw.m[3 * r + c] = WI.m[3 * r + c] + WI.m[3 * c + r] - (v.v[r] * I.h[c] + I.h[r] * v.v[c]) -
                            N.m[3 * r + c] + (r == c ? vh2 : S(0));
    o.P = p.f;
    return o;
  }
  // B m
  SCANDYN_HD Force<S> apply(const Motion<S>& m) const { return {Bw * m.w, S(-2) * cross(P, m.w)}; }
  // B^T m, as a force (paired with motions by dot)
  SCANDYN_HD Force<S> apply_transpose(const Motion<S>& m) const {
    return {mul_transpose(Bw, m.w) + S(2) * cross(P, m.v), Vec3<S>::zero()};
  }
  SCANDYN_HD VelocityDerivative& operator+=(const VelocityDerivative& o) {
    Bw = Bw + o.Bw;
    P += o.P;
    return *this;
  }
};

// Body i's quantities between the two passes of rnea_derivatives_instance (world
// frame; 72 scalars).
template <class S>
struct DerivativeBody {
  Transform<S> X;  // body frame <- world (i_X_0)
  Motion<S> J;     // joint motion subspace S_i in the world frame (C&M: the Jacobian column)
  Motion<S> v, a;  // body velocity and acceleration (gravity included), world
  Motion<S> dV;    // v_parent x S_i
  Motion<S> dA;    // a_parent x S_i + v_parent x dV_i
  Force<S> F;      // body force, then (backward pass) the sum over the subtree
  Inertia<S> Ic;   // spatial inertia in the world frame, then the subtree's (composite)
  VelocityDerivative<S> Bc;  // B_i, then the subtree's sum
  S d, t;          // fd_derivatives_instance's scratch: the diagonal entry of L^-1 (M =
                   // L^T L), and an entry of a row of L^-1
};

// Forward step of the derivatives: body i's world-frame quantities from its
// parent's (parent null: the base, at rest with acceleration a0). fext: body i's
// external wrench in its own frame, or null.
template <class S>
SCANDYN_HD void derivative_forward_step(const Body<S>& b, S q, S qd, S qdd, const Force<S>* fext,
                                        const DerivativeBody<S>* parent, const Motion<S>& a0,
                                        DerivativeBody<S>& o) {
  const Transform<S> Xup = joint_transform(b, q);
  o.X = parent ? Xup * parent->X : Xup;
  const Motion<S> vp = parent ? parent->v : Motion<S>::zero();
  const Motion<S> ap = parent ? parent->a : a0;
  o.J = o.X.apply_inverse(joint_motion(b, S(1)));
  o.v = vp + qd * o.J;
  o.a = ap + qdd * o.J + qd * cross(o.v, o.J);
  o.dV = cross(vp, o.J);
  o.dA = cross(ap, o.J) + cross(vp, o.dV);
  o.Ic = b.I.transform_transpose(o.X);
  o.F = o.Ic * o.a + cross(o.v, o.Ic * o.v);
  if (fext) o.F -= o.X.apply_transpose(*fext);
  o.Bc = VelocityDerivative<S>::of(o.Ic, o.v);
}

// The derivative recursions' forward pass (first and second order): body i's
// world-frame kinematics, body force, inertia and B into work[i], bodies in DoF order.
// Returns whether the model is one unbranched chain (body i's parent i - 1): then
// every pair (and triple) of DoF lies on the one path and the backward passes write
// every entry; otherwise the entries of DoF on different branches are zeros the
// caller writes.
template <class S, class V>
SCANDYN_HD bool derivative_forward_pass(const Body<S>* body, Index nv, const Motion<S>& a0, V q, V qd, V qdd,
                                        const Force<S>* fext, DerivativeBody<S>* work) {
  bool chain = true;
  for (Index i = 0; i < nv; ++i) {
    const Index p = body[i].parent;
    derivative_forward_step(body[i], S(q[i]), S(qd[i]), S(qdd[i]), fext ? fext + i : nullptr,
                            p < 0 ? nullptr : work + p, a0, work[i]);
    chain = chain && p == i - 1;
  }
  return chain;
}

// Inverse-dynamics derivatives of one instance: dtau_dq, dtau_dqd and M (nv x nv
// each; every entry written) at (q, qd, qdd, fext), gravity included; tau (optional,
// else null) = ID(q, qd, qdd, fext). body: the nv bodies in DoF order; a0: the base
// acceleration (-g); fext: nv body wrenches in body frames, or null; V: anything
// indexable by DoF (a pointer, a DofColumn); T: likewise, or decltype(nullptr);
// work: nv DerivativeBody entries of scratch; Mat: MatrixRef<S>, or any type whose
// (i, j) can be assigned an S (the blocks are only written: the second derivatives'
// dual passes keep just the derivative parts, DualPartRef in
// scandyn/instance/second_derivatives_instance.hpp).
template <class S, class V, class T, class Mat>
SCANDYN_HD void rnea_derivatives_instance(const Body<S>* body, Index nv, const Motion<S>& a0, V q, V qd, V qdd,
                                          const Force<S>* fext, DerivativeBody<S>* work, Mat dtau_dq, Mat dtau_dqd,
                                          Mat M, T tau) {
  // forward: world-frame kinematics, body forces, inertias and B; then the zeros of
  // DoF on different branches (none on an unbranched chain)
  if (!derivative_forward_pass(body, nv, a0, q, qd, qdd, fext, work))
    for (Index i = 0; i < nv; ++i)
      for (Index j = 0; j < nv; ++j) dtau_dq(i, j) = dtau_dqd(i, j) = M(i, j) = S(0);
  // backward: composite sums, then row j's entries against its ancestors (and the
  // transposed entries)
  for (Index j = nv - 1; j >= 0; --j) {
    const DerivativeBody<S>& w = work[j];
    if constexpr (!std::is_same<T, decltype(nullptr)>::value) tau[j] = dot(w.J, w.F);
    const Force<S> psi = w.Ic * w.J;            // Ic_j S_j
    const Force<S> rho = w.Bc.apply_transpose(w.J);  // Bc_j^T S_j
    const Force<S> Phi = cross(w.J, w.F) + w.Ic * w.dA + w.Bc.apply(w.dV);
    const Force<S> Psi = w.Ic * (S(2) * w.dV) + w.Bc.apply(w.J);
    for (Index i = j; i >= 0; i = body[i].parent) {
      const DerivativeBody<S>& a = work[i];
      dtau_dq(j, i) = dot(a.dA, psi) + dot(a.dV, rho);
      dtau_dqd(j, i) = S(2) * dot(a.dV, psi) + dot(a.J, rho);
      const S Mji = dot(a.J, psi);
      M(j, i) = Mji;
      if (i != j) {
        dtau_dq(i, j) = dot(a.J, Phi);
        dtau_dqd(i, j) = dot(a.J, Psi);
        M(i, j) = Mji;
      }
    }
    const Index p = body[j].parent;
    if (p >= 0) {
      work[p].F += w.F;
      work[p].Ic += w.Ic;
      work[p].Bc += w.Bc;
    }
  }
}

// ---- multi-DoF joints (a floating base, spherical joints) ----------------------
// The same recursions for a model with joints of 1, 3 and 6 DoFs (ModelTpl::
// multi_dof()). Body i's joint has nj = joint_nv columns S_ik (k < nj; world frame:
// S_ik = X_i^-1 joint_column(b, k), constant in body i's frame), at DoFs idx_v + k;
// q holds nq entries (b.idx_q's run per joint). The increment of a multi-DoF joint is
// local, q (+) d = q exp(d) in the child (base) frame as Pinocchio's: to first order
// that is what scandyn's integrators do (joint_integrate: quat exp(w h / 2) on the
// right; a free joint's p += R v h), and it moves body i and its subtree rigidly by
// the world twist S_ik d_k. Hence, for every pair of columns l, k of one joint (not
// only l before k, as for 1-DoF joints in DoF order):
//   dS_ik/dq_il = S_il x S_ik            (S_ik is fixed in body i's frame)
// and for every column l of joint j, with p = lambda(j), v_j = v_p + S_j qd_j,
// a_j = a_p + S_j qdd_j + v_j x (S_j qd_j), and m in the subtree of j (j included):
//   dv_m/dq_jl  = S_jl x (v_m - v_p)                     = S_jl x v_m + dV_jl,
//                 dV_jl = v_p x S_jl
//   da_m/dq_jl  = S_jl x (a_m - a_p) + dV_jl x (v_m - v_p) = S_jl x a_m + dA_jl + dV_jl x v_m,
//                 dA_jl = a_p x S_jl + v_p x dV_jl
// (the second by the Jacobi identity on d(v_n x S_n) = (S_jl x v_n + dV_jl) x S_n +
// v_n x (S_jl x S_n) over the columns n on the path, the joint's own included): the
// per-column dV and dA of the 1-DoF recursion. The velocity derivative picks up the
// joint's own columns differently:
//   da_m/dqd_jl = S_jl x v_m + dAv_jl,   dAv_jl = v_p x S_jl + v_j x S_jl
//               = 2 dV_jl + (S_j qd_j) x S_jl
// (d(v_j x S_j qd_j)/dqd_jl = S_jl x (S_j qd_j) + v_j x S_jl, plus S_jl x (v_m - v_j)
// from the columns below j); for a 1-DoF joint S_j qd_j x S_j = 0 and dAv = 2 dV. With
// the body forces' derivatives df_m/dq_jl = S_jl x* f_m + I_m dA_jl + B_m dV_jl and
// df_m/dqd_jl = I_m dAv_jl + B_m S_jl (B as above), summed over subtrees:
//   joint j an ancestor of joint i, or j = i (every column pair of the joint):
//     dtau_ik/dq_jl  = S_ik . (Ic_i dA_jl + Bc_i dV_jl)     (S_ik turns with S_jl: the
//                                                           S_jl x* F_i terms cancel)
//     dtau_ik/dqd_jl = S_ik . (Ic_i dAv_jl + Bc_i S_jl)
//   joint i a proper ancestor of joint j (S_ik does not move):
//     dtau_ik/dq_jl  = S_ik . Phi_jl,  Phi_jl = S_jl x* F_j + Ic_j dA_jl + Bc_j dV_jl
//     dtau_ik/dqd_jl = S_ik . Psi_jl,  Psi_jl = Ic_j dAv_jl + Bc_j S_jl
//   M_ik,jl = S_ik . Ic_i S_jl (i in the subtree of j).
// At the root's free joint p is the world at rest: dV = 0, dA = a0 x S (gravity turns
// with the base).
//
// Work layout: nv DerivativeBody entries indexed by DoF. Body i's quantities (X, v,
// a, F, Ic, Bc) live in entry idx_v (its first DoF), column k's (J, dV, dA) in entry
// idx_v + k; d and t stay per DoF (the forward-dynamics solve's scratch). A 1-DoF body
// uses one entry as in rnea_derivatives_instance.

// The forward pass of the general recursion: body quantities and per-column J, dV,
// dA (layout above). q: nq entries; qd, qdd: nv; fext: nb body wrenches or null.
// Returns whether the bodies form one unbranched chain (then so do the DoFs).
template <class S>
SCANDYN_HD bool derivative_forward_pass_general(const Body<S>* body, Index nb, const Motion<S>& a0, const S* q,
                                                const S* qd, const S* qdd, const Force<S>* fext,
                                                DerivativeBody<S>* work) {
  bool chain = true;
  for (Index i = 0; i < nb; ++i) {
    const Body<S>& b = body[i];
    const Index p = b.parent, iv = b.idx_v;
    const DerivativeBody<S>* parent = p < 0 ? nullptr : work + body[p].idx_v;
    chain = chain && p == i - 1;
    DerivativeBody<S>& o = work[iv];
    if (b.type == JointType::Revolute || b.type == JointType::Prismatic) {
      derivative_forward_step(b, q[b.idx_q], qd[iv], qdd[iv], fext ? fext + i : nullptr, parent, a0, o);
      continue;
    }
    const Transform<S> Xup = joint_transform_at(b, q + b.idx_q);
    o.X = parent ? Xup * parent->X : Xup;
    const Motion<S> vp = parent ? parent->v : Motion<S>::zero();
    const Motion<S> ap = parent ? parent->a : a0;
    const Motion<S> vJ = o.X.apply_inverse(joint_motion_at(b, qd + iv));  // S_j qd_j
    o.v = vp + vJ;
    o.a = ap + o.X.apply_inverse(joint_motion_at(b, qdd + iv)) + cross(o.v, vJ);
    const int nj = joint_nv(b.type);
    for (int k = 0; k < nj; ++k) {
      DerivativeBody<S>& c = work[iv + k];
      c.J = o.X.apply_inverse(joint_column(b, k));
      c.dV = cross(vp, c.J);
      c.dA = cross(ap, c.J) + cross(vp, c.dV);
    }
    o.Ic = b.I.transform_transpose(o.X);
    o.F = o.Ic * o.a + cross(o.v, o.Ic * o.v);
    if (fext) o.F -= o.X.apply_transpose(fext[i]);
    o.Bc = VelocityDerivative<S>::of(o.Ic, o.v);
  }
  return chain;
}

// dAv of column c (DoF) of body b, whose body quantities are in `body_entry`: 2 dV for
// a 1-DoF joint, dV + v_j x S_jl for a multi-DoF one.
template <class S>
SCANDYN_HD Motion<S> column_dAv(const Body<S>& b, const DerivativeBody<S>& body_entry, const DerivativeBody<S>& c) {
  if (b.type == JointType::Revolute || b.type == JointType::Prismatic) return S(2) * c.dV;
  return c.dV + cross(body_entry.v, c.J);
}

// rnea_derivatives_instance for a model with multi-DoF joints: nb bodies, nv DoFs,
// q of nq entries (plain arrays), fext nb body wrenches in body frames or null, work
// nv entries (layout above); the three nv x nv blocks (every entry written) and tau
// (nv, or null) as rnea_derivatives_instance's. Also exact for 1-DoF joints (the
// same formulas), but those models take rnea_derivatives_instance.
template <class S, class T, class Mat>
SCANDYN_HD void rnea_derivatives_general_instance(const Body<S>* body, Index nb, Index nv, const Motion<S>& a0,
                                                  const S* q, const S* qd, const S* qdd, const Force<S>* fext,
                                                  DerivativeBody<S>* work, Mat dtau_dq, Mat dtau_dqd, Mat M, T tau) {
  if (!derivative_forward_pass_general(body, nb, a0, q, qd, qdd, fext, work))
    for (Index i = 0; i < nv; ++i)
      for (Index j = 0; j < nv; ++j) dtau_dq(i, j) = dtau_dqd(i, j) = M(i, j) = S(0);
  for (Index j = nb - 1; j >= 0; --j) {
    const Body<S>& bj = body[j];
    const Index jv = bj.idx_v;
    const DerivativeBody<S>& w = work[jv];
    for (int l = 0; l < joint_nv(bj.type); ++l) {  // column c = jv + l: row c, and column c above
      const Index c = jv + l;
      const DerivativeBody<S>& col = work[c];
      if constexpr (!std::is_same<T, decltype(nullptr)>::value) tau[c] = dot(col.J, w.F);
      const Force<S> psi = w.Ic * col.J;               // Ic_j S_jl
      const Force<S> rho = w.Bc.apply_transpose(col.J);  // Bc_j^T S_jl
      const Force<S> Phi = cross(col.J, w.F) + w.Ic * col.dA + w.Bc.apply(col.dV);
      const Force<S> Psi = w.Ic * column_dAv(bj, w, col) + w.Bc.apply(col.J);
      for (Index i = j; i >= 0; i = body[i].parent) {
        const Body<S>& bi = body[i];
        const DerivativeBody<S>& wi = work[bi.idx_v];
        for (int k = 0; k < joint_nv(bi.type); ++k) {
          const Index r = bi.idx_v + k;
          const DerivativeBody<S>& a = work[r];
          dtau_dq(c, r) = dot(a.dA, psi) + dot(a.dV, rho);
          dtau_dqd(c, r) = dot(column_dAv(bi, wi, a), psi) + dot(a.J, rho);
          const S Mcr = dot(a.J, psi);
          M(c, r) = Mcr;
          if (i != j) {
            dtau_dq(r, c) = dot(a.J, Phi);
            dtau_dqd(r, c) = dot(a.J, Psi);
            M(r, c) = Mcr;
          }
        }
      }
    }
    const Index p = bj.parent;
    if (p >= 0) {
      DerivativeBody<S>& wp = work[body[p].idx_v];
      wp.F += w.F;
      wp.Ic += w.Ic;
      wp.Bc += w.Bc;
    }
  }
}

// ---- M = L^T L with the tree's sparsity (Featherstone (2008) 6.5) ---------------
// L is lower triangular with L_ij != 0 only for j an ancestor of i or i itself (the
// branch-induced sparsity of M: no fill-in), as the serial ltl_factor / ltl_solve
// (src/algorithm/reference_impl.hpp), here on a MatrixRef and the tree of DoFs given
// by Tree: anything whose (i) is the parent DoF of DoF i (-1 at the root).
// BodyTree: a model of 1-DoF joints, DoF i = body i. DofTree: a model with multi-DoF
// joints, whose DoFs form a tree too: a joint's DoFs are a chain (DoF idx_v + k's
// parent is idx_v + k - 1) hanging from the last DoF of the parent body's joint
// (dof_parents), so M's sparsity, L's and L^-1's are again those of ancestors.
template <class S>
struct BodyTree {
  const Body<S>* body;
  SCANDYN_HD Index operator()(Index i) const { return body[i].parent; }
};
struct DofTree {
  const Index* parent;  // (nv) parent DoF of each DoF, -1 at the root
  const Index* last;    // (nv) largest DoF of each DoF's subtree (dof_subtree_last): the
                        // subtree of DoF k lies in k..last[k] (is that range, for the
                        // loader's preorder; its other DoFs have zeros in L^-1's column k)
  const Index* run;     // (nv) first DoF of each DoF's unbranched run (dof_runs), or null: the DoFs
                        // run[i]..i are each the parent of the next, so they are all
                        // ancestors of i (or i): the ancestors of i are the contiguous
                        // ranges run[j]..j for j = parent[i], then j = parent[run[j]], ...
                        // (a floating base's six DoFs and a limb's chain are one range each)
  SCANDYN_HD Index operator()(Index i) const { return parent[i]; }
};

// run[i] for the nv DoFs of a tree given by parent (parent[i] < i): i's run starts where
// the chain of DoFs each the parent of the next (parent[t] = t - 1) that ends at i starts.
SCANDYN_HD void dof_runs(const Index* parent, Index nv, Index* run) {
  for (Index i = 0; i < nv; ++i) run[i] = i > 0 && parent[i] == i - 1 ? run[i - 1] : i;
}

// last[k] for the nv DoFs of a tree given by parent (parent[i] < i): the largest DoF of
// k's subtree.
SCANDYN_HD void dof_subtree_last(const Index* parent, Index nv, Index* last) {
  for (Index i = 0; i < nv; ++i) last[i] = i;
  for (Index i = nv - 1; i > 0; --i)
    if (parent[i] >= 0 && last[i] > last[parent[i]]) last[parent[i]] = last[i];
}

// parent[c] for the nv DoFs c of a model of nb bodies (any joint types): the DoF
// before c in its joint, or the last DoF of the parent body's joint, or -1.
template <class S>
SCANDYN_HD void dof_parents(const Body<S>* body, Index nb, Index* parent) {
  for (Index i = 0; i < nb; ++i) {
    const Body<S>& b = body[i];
    const Index p = b.parent;
    parent[b.idx_v] = p < 0 ? Index(-1) : body[p].idx_v + joint_nv(body[p].type) - 1;
    for (int k = 1; k < joint_nv(b.type); ++k) parent[b.idx_v + k] = b.idx_v + k - 1;
  }
}

// In place: A's lower triangle (M) becomes L, M = L^T L. Returns -1, or the DoF whose
// pivot was not positive and finite. The strict upper triangle is not touched.
template <class S, class Tree>
SCANDYN_HD Index tree_ltl_factor(Tree parent, MatrixRef<S> A) {
  for (Index k = A.n - 1; k >= 0; --k) {
    const S d = A(k, k);
    if (!pivot_ok(d)) return k;
    const S Lkk = ScalarMath<S>::sqrt(d);
    A(k, k) = Lkk;
    const S inv = S(1) / Lkk;
    for (Index i = parent(k); i >= 0; i = parent(i)) A(k, i) *= inv;
    for (Index i = parent(k); i >= 0; i = parent(i)) {
      const S Lki = A(k, i);
      for (Index j = i; j >= 0; j = parent(j)) A(i, j) -= Lki * A(k, j);
    }
  }
  return -1;
}

// tree_ltl_factor over the tree of DoFs on a row-major A (stride 1), the ancestors
// taken as DoFTree's contiguous runs: the row updates A(i, anc) -= L_ki A(k, anc) are
// contiguous segments (the compiler vectorises them) instead of one tree walk per
// entry. The same operations on every entry as tree_ltl_factor (bit-identical).
template <class S>
SCANDYN_HD Index dof_ltl_factor(DofTree tree, MatrixRef<S> A) {
  const Index n = A.n;
  for (Index k = n - 1; k >= 0; --k) {
    const S d = A(k, k);
    if (!pivot_ok(d)) return k;
    const S Lkk = ScalarMath<S>::sqrt(d);
    A(k, k) = Lkk;
    const S inv = S(1) / Lkk;
    S* __restrict__ rk = &A(k, 0);
    for (Index j = tree(k); j >= 0; j = tree(tree.run[j]))
      for (Index i = tree.run[j]; i <= j; ++i) rk[i] *= inv;
    for (Index j = tree(k); j >= 0; j = tree(tree.run[j]))
      for (Index i = j; i >= tree.run[j]; --i) {  // ancestor i of k: row i -= L_ki row k on i's ancestors
        const S Lki = rk[i];
        S* __restrict__ ri = &A(i, 0);
        for (Index h = i; h >= 0; h = tree(tree.run[h]))
          for (Index c = tree.run[h]; c <= h; ++c) ri[c] -= Lki * rk[c];
      }
  }
  return -1;
}

// X and Y become -(L^T L)^-1 X and -(L^T L)^-1 Y (L from tree_ltl_factor), by row
// operations on all their columns at once: one walk up the tree per row, and
// contiguous (vectorisable) rows when the matrices are row-major.
template <class S, class Tree>
SCANDYN_HD void tree_ltl_negated_solve(Tree parent, MatrixRef<S> L, MatrixRef<S> X, MatrixRef<S> Y) {
  const Index n = L.n;
  // row r of both *= a; row r += b * row s (r != s). Row-major blocks (stride 1, the
  // host's layout) take plain pointer loops the compiler vectorises; the arithmetic
  // per entry is the same either way.
  const bool contiguous = X.stride == 1 && Y.stride == 1;
  auto scale = [&](Index r, S a) {
    if (contiguous) {
      S* x = &X(r, 0);
      S* y = &Y(r, 0);
      for (Index c = 0; c < n; ++c) x[c] *= a;
      for (Index c = 0; c < n; ++c) y[c] *= a;
      return;
    }
    for (Index c = 0; c < n; ++c) {
      X(r, c) *= a;
      Y(r, c) *= a;
    }
  };
  auto axpy = [&](Index r, Index s, S b) {
    if (contiguous) {
      S* __restrict__ xr = &X(r, 0);
      const S* __restrict__ xs = &X(s, 0);
      for (Index c = 0; c < n; ++c) xr[c] += b * xs[c];
      S* __restrict__ yr = &Y(r, 0);
      const S* __restrict__ ys = &Y(s, 0);
      for (Index c = 0; c < n; ++c) yr[c] += b * ys[c];
      return;
    }
    for (Index c = 0; c < n; ++c) {
      X(r, c) += b * X(s, c);
      Y(r, c) += b * Y(s, c);
    }
  };
  for (Index i = n - 1; i >= 0; --i) {  // L^T y = -x (row i holds x_i + sum of L_ki y_k when reached)
    scale(i, S(-1) / L(i, i));
    for (Index j = parent(i); j >= 0; j = parent(j)) axpy(j, i, L(i, j));
  }
  for (Index i = 0; i < n; ++i) {  // L z = y
    for (Index j = parent(i); j >= 0; j = parent(j)) axpy(i, j, -L(i, j));
    scale(i, S(1) / L(i, i));
  }
}

// One row of dof_ltl_negated_solve, W columns from c0 at a time: out[c] = s (out[c] +
// sum of the source rows' terms), the W sums held in registers while the source rows
// stream past (one store per entry instead of one per source row).
// Backward sweep: the sources are rows k = e down to i + 1 with coefficient L(k, i).
template <int W, class S>
SCANDYN_HD void dof_gather_subtree(const S* __restrict__ L, S* __restrict__ M, Index n, Index i, Index e, Index c0,
                                   S s) {
  S acc[W];
  S* out = M + static_cast<std::ptrdiff_t>(i) * n + c0;
  for (int w = 0; w < W; ++w) acc[w] = out[w];
  for (Index k = e; k > i; --k) {
    const S l = L[static_cast<std::ptrdiff_t>(k) * n + i];
    const S* src = M + static_cast<std::ptrdiff_t>(k) * n + c0;
    for (int w = 0; w < W; ++w) acc[w] += l * src[w];
  }
  for (int w = 0; w < W; ++w) out[w] = acc[w] * s;
}
// Forward sweep: the sources are the ancestors j of i, nearest first, with
// coefficient -L(i, j) (li: row i of L).
template <int W, class S>
SCANDYN_HD void dof_gather_ancestors(DofTree tree, const S* __restrict__ li, S* __restrict__ M, Index n, Index i,
                                     Index c0, S s) {
  S acc[W];
  S* out = M + static_cast<std::ptrdiff_t>(i) * n + c0;
  for (int w = 0; w < W; ++w) acc[w] = out[w];
  for (Index j = tree(i); j >= 0; j = tree(tree.run[j]))
    for (Index m = j; m >= tree.run[j]; --m) {
      const S l = li[m];
      const S* src = M + static_cast<std::ptrdiff_t>(m) * n + c0;
      for (int w = 0; w < W; ++w) acc[w] -= l * src[w];
    }
  for (int w = 0; w < W; ++w) out[w] = acc[w] * s;
}
// Columns 0..len-1 of one row in blocks of 12, 8, 4, 2, 1 (12 sums: six SSE2 registers
// of two doubles, enough independent additions to cover the adder's latency).
template <class Block>
SCANDYN_HD void dof_gather_row(Index len, Block&& block) {
  Index c = 0;
  for (; c + 12 <= len; c += 12) block(std::integral_constant<int, 12>{}, c);
  if (c + 8 <= len) block(std::integral_constant<int, 8>{}, c), c += 8;
  if (c + 4 <= len) block(std::integral_constant<int, 4>{}, c), c += 4;
  if (c + 2 <= len) block(std::integral_constant<int, 2>{}, c), c += 2;
  if (c < len) block(std::integral_constant<int, 1>{}, c);
}

// tree_ltl_negated_solve over the tree of DoFs on row-major blocks (all strides 1),
// each row computed once from its sources instead of updated once per source: L^T y =
// -x from the last row (y_i = -(x_i + sum of L_ki y_k over k's subtree, k > i) / L_ii,
// the subtree k = i+1..last[i]), then L z = y from the first (z_i = (y_i - sum of L_ij
// z_j over i's ancestors j) / L_ii, the ancestors by runs). The terms are added in the
// order tree_ltl_negated_solve adds them (bit-identical). In the first sweep row i
// stops at column last[i]: a row of dtau/dq or dtau/dqd is zero in the columns of DoFs
// that are neither ancestors nor descendants (the columns past last[i] are such), and
// so is y_i there.
template <class S>
SCANDYN_HD void dof_ltl_negated_solve(DofTree tree, MatrixRef<S> L, MatrixRef<S> X, MatrixRef<S> Y) {
  const Index n = L.n;
  const S* Ld = L.data;
  S* const mats[2] = {X.data, Y.data};
  for (Index i = n - 1; i >= 0; --i) {
    const Index e = tree.last[i];
    const S s = S(-1) / L(i, i);
    for (S* M : mats)
      dof_gather_row(e + 1, [&](auto w, Index c0) { dof_gather_subtree<decltype(w)::value>(Ld, M, n, i, e, c0, s); });
  }
  for (Index i = 0; i < n; ++i) {
    const S s = S(1) / L(i, i);
    const S* li = &L(i, 0);
    for (S* M : mats)
      dof_gather_row(n, [&](auto w, Index c0) { dof_gather_ancestors<decltype(w)::value>(tree, li, M, n, i, c0, s); });
  }
}

// In place: A's lower triangle (L from tree_ltl_factor) becomes M^-1 = L^-1 L^-T,
// both triangles written. L^-1 has L's sparsity (ancestor relations compose), so it
// replaces L column by column; the diagonal of L^-1 waits in diag (n scalars) while
// the upper triangle receives M^-1, which is dense where M is not. row: n scalars of
// scratch.
template <class S, class Tree, class Scratch>
SCANDYN_HD void tree_ltl_inverse(Tree parent, MatrixRef<S> A, Scratch diag, Scratch row) {
  const Index n = A.n;
  for (Index k = 0; k < n; ++k) {  // column k of L^-1 (columns > k still hold L)
    A(k, k) = S(1) / A(k, k);
    for (Index i = k + 1; i < n; ++i) {
      S s = S(0);
      Index m = parent(i);
      for (; m > k; m = parent(m)) s += A(i, m) * A(m, k);
      if (m != k) continue;  // k is not an ancestor of i: the entry stays 0
      s += A(i, k) * A(k, k);
      A(i, k) = -s / A(i, i);
    }
  }
  for (Index i = 0; i < n; ++i) diag[i] = A(i, i), row[i] = S(0);
  // (M^-1)_ij = sum of L^-1_ik L^-1_jk over the common ancestors k (and i or j): row
  // j of L^-1 scattered into `row`, then each i <= j walks its own ancestors
  auto linv = [&](Index r, Index k) { return r == k ? S(diag[r]) : A(r, k); };
  for (Index j = 0; j < n; ++j) {
    for (Index k = j; k >= 0; k = parent(k)) row[k] = linv(j, k);
    for (Index i = 0; i <= j; ++i) {
      S s = S(0);
      for (Index k = i; k >= 0; k = parent(k)) s += linv(i, k) * row[k];
      A(i, j) = s;
    }
    for (Index k = j; k >= 0; k = parent(k)) row[k] = S(0);
  }
  for (Index i = 0; i < n; ++i)
    for (Index j = i + 1; j < n; ++j) A(j, i) = A(i, j);
}

// tree_ltl_inverse over the tree of DoFs (a multi-DoF model's; each subtree within the
// range k..tree.last[k]): L^-1 column by column over that range only (a DoF in it that
// is not k's descendant sums zeros), then M^-1 = L^-1 L^-T as the sum over k of the
// outer products of L^-1's column k with itself (non-zero on k's subtree: within the
// square block of rows and columns k..last[k]),
// accumulated into the upper triangle with contiguous row segments (row-major A: loops
// the compiler vectorises), then mirrored. A floating base makes every DoF a
// descendant of the base's six, so M^-1 is dense: this is O(sum of subtree sizes^2)
// streaming work instead of a tree walk per entry. diag, row: n scalars of scratch.
template <class S, class Scratch>
SCANDYN_HD void tree_ltl_inverse(DofTree tree, MatrixRef<S> A, Scratch diag, Scratch row) {
  const Index n = A.n;
  for (Index k = 0; k < n; ++k) {  // column k of L^-1 (columns > k still hold L)
    A(k, k) = S(1) / A(k, k);
    for (Index i = k + 1; i <= tree.last[k]; ++i) {  // k's descendants (the others stay 0)
      S s = S(0);
      // the ancestors m > k of i, nearest first (with the runs, a run at a time: no tree
      // walk per term)
      if (tree.run) {
        for (Index j = tree(i); j > k; j = tree(tree.run[j])) {
          const Index lo = tree.run[j] > k ? tree.run[j] : k + 1;
          for (Index m = j; m >= lo; --m) s += A(i, m) * A(m, k);
        }
      } else {
        for (Index m = tree(i); m > k; m = tree(m)) s += A(i, m) * A(m, k);
      }
      s += A(i, k) * A(k, k);
      A(i, k) = -s / A(i, i);
    }
  }
  for (Index i = 0; i < n; ++i) {
    diag[i] = A(i, i);
    for (Index j = i; j < n; ++j) A(i, j) = S(0);
  }
  for (Index k = 0; k < n; ++k) {
    const Index e = tree.last[k];
    row[k] = diag[k];
    for (Index c = k + 1; c <= e; ++c) row[c] = A(c, k);  // L^-1's column k (strict lower triangle)
    for (Index r = k; r <= e; ++r) {
      const S vr = row[r];
      if (A.stride == 1) {
        S* a = &A(r, 0);
        for (Index c = r; c <= e; ++c) a[c] += vr * row[c];
      } else {
        for (Index c = r; c <= e; ++c) A(r, c) += vr * row[c];
      }
    }
  }
  for (Index i = 0; i < n; ++i)
    for (Index j = i + 1; j < n; ++j) A(j, i) = A(i, j);
}

// ---- the same for a model of at most C DoF, C known at compile time ---------------
// (fd_derivatives_instance<C> for 0 < C <= kPackedLtlCapacity: the CUDA kernels')
// L is held in a packed lower triangle of C (C + 1) / 2 scalars that the loops below,
// unrolled over the capacity, index with constants only, so that a GPU thread keeps
// L (and the column being solved) in registers instead of walking the tree over the
// output blocks in global memory. The loops are dense over i, j < n: the tree's
// zeros of M stay exact zeros of L (row k's update touches only pairs of ancestors
// of k, Featherstone 6.5), and every non-zero entry sees the same operations in the
// same order as in tree_ltl_factor / tree_ltl_negated_solve. Rows and columns past
// n are skipped by tests on n, which is the same for every thread of a launch.

// Largest capacity of the packed path: 8 gives 36 + 8 scalars of L and 1 / L_ii
// (registers); 16 would be 136 + 16, more than a thread's registers next to the rest.
inline constexpr int kPackedLtlCapacity = 8;

// Loop unrolling of the packed path: nvcc's pragma (GCC's on the host, whose
// optimiser then keeps the small arrays in registers too).
#if defined(__CUDACC__)
#define SCANDYN_PACKED_UNROLL _Pragma("unroll")
#define SCANDYN_PACKED_NO_UNROLL _Pragma("unroll 1")
#elif defined(__GNUC__) && !defined(__clang__)
#define SCANDYN_PACKED_UNROLL _Pragma("GCC unroll 16")
#define SCANDYN_PACKED_NO_UNROLL
#else
#define SCANDYN_PACKED_UNROLL
#define SCANDYN_PACKED_NO_UNROLL
#endif

template <class S, int C>
struct PackedLtl {
  static constexpr SCANDYN_HD int at(int i, int j) { return i * (i + 1) / 2 + j; }  // L_ij, j <= i
  S L[C * (C + 1) / 2];
  S inv_diag[C];  // 1 / L_ii
};

// f.L = L of M + diag(armature) = L^T L, M's lower triangle read from A (A is not
// written; armature: n entries, or null). Returns -1, or the DoF whose pivot was not
// positive and finite.
template <class S, int C>
SCANDYN_HD Index packed_ltl_factor(MatrixRef<S> A, const S* armature, PackedLtl<S, C>& f) {
  using P = PackedLtl<S, C>;
  const Index n = A.n;
SCANDYN_PACKED_UNROLL
  for (int i = 0; i < C; ++i) {
    if (i < n) {
SCANDYN_PACKED_UNROLL
      for (int j = 0; j <= i; ++j) f.L[P::at(i, j)] = A(i, j);
      if (armature) f.L[P::at(i, i)] += armature[i];
    }
  }
SCANDYN_PACKED_UNROLL
  for (int k = C - 1; k >= 0; --k) {
    if (k >= n) continue;
    const S d = f.L[P::at(k, k)];
    if (!pivot_ok(d)) return k;
    const S Lkk = ScalarMath<S>::sqrt(d);
    f.L[P::at(k, k)] = Lkk;
    const S inv = S(1) / Lkk;
    f.inv_diag[k] = inv;
SCANDYN_PACKED_UNROLL
    for (int i = k - 1; i >= 0; --i) f.L[P::at(k, i)] *= inv;
SCANDYN_PACKED_UNROLL
    for (int i = k - 1; i >= 0; --i) {
      const S Lki = f.L[P::at(k, i)];
SCANDYN_PACKED_UNROLL
      for (int j = i; j >= 0; --j) f.L[P::at(i, j)] -= Lki * f.L[P::at(k, j)];
    }
  }
  return -1;
}

// x (entries 0..n-1) becomes -(L^T L)^-1 x: L^T y = -x right-looking from the last
// row, then L z = y from the first (tree_ltl_negated_solve's order on one column).
template <class S, int C>
SCANDYN_HD void packed_ltl_negated_solve(const PackedLtl<S, C>& f, Index n, S (&x)[C]) {
  using P = PackedLtl<S, C>;
SCANDYN_PACKED_UNROLL
  for (int i = C - 1; i >= 0; --i) {
    if (i >= n) continue;
    x[i] *= -f.inv_diag[i];
SCANDYN_PACKED_UNROLL
    for (int j = i - 1; j >= 0; --j) x[j] += f.L[P::at(i, j)] * x[i];
  }
SCANDYN_PACKED_UNROLL
  for (int i = 0; i < C; ++i) {
    if (i >= n) break;
SCANDYN_PACKED_UNROLL
    for (int j = i - 1; j >= 0; --j) x[i] -= f.L[P::at(i, j)] * x[j];
    x[i] *= f.inv_diag[i];
  }
}

// The forward-dynamics solve of fd_derivatives_instance<C> on the inverse-dynamics
// derivatives in the three blocks (dtau/dq, dtau/dqd, M in, dqdd/dq, dqdd/dqd, M^-1
// out): L in registers, then column by column (each column read once and written
// once) dqdd/dq = -M^-1 dtau/dq, dqdd/dqd = -M^-1 dtau/dqd, and M^-1 from the
// columns of -(L^T L)^-1 (-e_c), its entries (i, c), i >= c, mirrored to (c, i) (M^-1
// stays exactly symmetric). Returns as tree_ltl_factor.
template <int C, class S>
SCANDYN_HD Index packed_fd_solve(MatrixRef<S> dq, MatrixRef<S> dqd, MatrixRef<S> dtau, const S* armature) {
  static_assert(C > 0 && C <= kPackedLtlCapacity, "the packed factor is for capacities up to kPackedLtlCapacity");
  const Index n = dtau.n;
  PackedLtl<S, C> f{};  // (entries past n stay 0)
  const Index failed = packed_ltl_factor(dtau, armature, f);
  if (failed >= 0) return failed;
  S x[C] = {};
SCANDYN_PACKED_NO_UNROLL
  for (Index c = 0; c < 2 * n; ++c) {
    const MatrixRef<S> X = c < n ? dq : dqd;
    const Index col = c < n ? c : c - n;
SCANDYN_PACKED_UNROLL
    for (int i = 0; i < C; ++i)
      if (i < n) x[i] = X(i, col);
    packed_ltl_negated_solve(f, n, x);
SCANDYN_PACKED_UNROLL
    for (int i = 0; i < C; ++i)
      if (i < n) X(i, col) = x[i];
  }
SCANDYN_PACKED_NO_UNROLL
  for (Index c = 0; c < n; ++c) {
SCANDYN_PACKED_UNROLL
    for (int i = 0; i < C; ++i) x[i] = i == c ? S(-1) : S(0);
    packed_ltl_negated_solve(f, n, x);
SCANDYN_PACKED_UNROLL
    for (int i = 0; i < C; ++i)
      if (i >= c && i < n) dtau(i, c) = dtau(c, i) = x[i];
  }
  return -1;
}

// tree_ltl_inverse with its two scratch vectors in the d and t fields of work (nv entries).
template <class S, class Tree>
SCANDYN_HD void tree_ltl_inverse_on_work(Tree parent, MatrixRef<S> L_to_Minv, DerivativeBody<S>* work) {
  struct Field {  // one scalar field of the work array
    DerivativeBody<S>* w;
    S DerivativeBody<S>::*f;
    SCANDYN_HD S& operator[](Index i) const { return w[i].*f; }
  };
  tree_ltl_inverse(parent, L_to_Minv, Field{work, &DerivativeBody<S>::d}, Field{work, &DerivativeBody<S>::t});
}

// The forward-dynamics solve by the tree walks on the inverse-dynamics derivatives
// in the three blocks (dtau/dq, dtau/dqd, M + diag(armature) in; dqdd/dq, dqdd/dqd,
// M^-1 out), over the tree of DoFs `parent` (BodyTree or DofTree); work: nv entries
// whose d and t fields are scratch. Returns -1, or the DoF whose pivot failed.
template <class S, class Tree>
SCANDYN_HD Index tree_fd_solve(Tree parent, Index nv, DerivativeBody<S>* work, MatrixRef<S> dqdd_dq,
                               MatrixRef<S> dqdd_dqd, MatrixRef<S> dqdd_dtau, const S* armature) {
  if (armature)
    for (Index i = 0; i < nv; ++i) dqdd_dtau(i, i) += armature[i];
  const Index failed = tree_ltl_factor(parent, dqdd_dtau);
  if (failed >= 0) return failed;
  tree_ltl_negated_solve(parent, dqdd_dtau, dqdd_dq, dqdd_dqd);
  tree_ltl_inverse_on_work(parent, dqdd_dtau, work);
  return -1;
}

// Forward-dynamics derivatives of one instance at qdd = FD(q, qd, tau, fext) (the
// caller's, e.g. from the ABA): dqdd_dq, dqdd_dqd, dqdd_dtau = M^-1 (nv x nv each,
// every entry written). Returns -1, or the DoF whose pivot of M = L^T L was not
// positive and finite (the outputs then hold partial values). Arguments as
// rnea_derivatives_instance; armature (nv entries, or null): a joint-space inertia
// added to M's diagonal, as the ABA's armature argument (the simulator's implicit
// integrator): then qdd solves (M + diag(armature)) qdd = tau - h, and the
// derivatives are those of that solve, dqdd/dtau = (M + diag(armature))^-1.
// C: 0 (the default: the tree walks of tree_ltl_factor, tree_ltl_negated_solve and
// tree_ltl_inverse over the output blocks, any nv), or a compile-time capacity
// nv <= C; for C <= kPackedLtlCapacity the factor and solves run on L in registers
// (packed_fd_solve; the same results up to the rounding of M^-1, which it gets
// from solves rather than from L^-1).
template <int C = 0, class S, class V>
SCANDYN_HD Index fd_derivatives_instance(const Body<S>* body, Index nv, const Motion<S>& a0, V q, V qd, V qdd,
                                         const Force<S>* fext, DerivativeBody<S>* work, MatrixRef<S> dqdd_dq,
                                         MatrixRef<S> dqdd_dqd, MatrixRef<S> dqdd_dtau,
                                         const S* armature = nullptr) {
  rnea_derivatives_instance(body, nv, a0, q, qd, qdd, fext, work, dqdd_dq, dqdd_dqd, dqdd_dtau, nullptr);
  if constexpr (C > 0 && C <= kPackedLtlCapacity) {
    return packed_fd_solve<C>(dqdd_dq, dqdd_dqd, dqdd_dtau, armature);
  } else {
    return tree_fd_solve(BodyTree<S>{body}, nv, work, dqdd_dq, dqdd_dqd, dqdd_dtau, armature);
  }
}

// fd_derivatives_instance for a model with multi-DoF joints (arguments as
// rnea_derivatives_general_instance; qdd: the caller's FD(q, qd, tau, fext), nv
// entries; dof_parent, dof_last, dof_run: the nv DoF parents, subtree ends and run
// starts, dof_parents, dof_subtree_last and dof_runs): M = L^T L factored with the
// tree sparsity at the DoF level (a multi-DoF joint's DoFs form a chain), in the
// output blocks. Returns as fd_derivatives_instance.
template <class S>
SCANDYN_HD Index fd_derivatives_general_instance(const Body<S>* body, Index nb, Index nv, const Motion<S>& a0,
                                                 const S* q, const S* qd, const S* qdd, const Force<S>* fext,
                                                 const Index* dof_parent, const Index* dof_last,
                                                 const Index* dof_run, DerivativeBody<S>* work,
                                                 MatrixRef<S> dqdd_dq, MatrixRef<S> dqdd_dqd, MatrixRef<S> dqdd_dtau,
                                                 const S* armature = nullptr) {
  rnea_derivatives_general_instance(body, nb, nv, a0, q, qd, qdd, fext, work, dqdd_dq, dqdd_dqd, dqdd_dtau,
                                    nullptr);
  const DofTree tree{dof_parent, dof_last, dof_run};
  if (dqdd_dq.stride != 1 || dqdd_dqd.stride != 1 || dqdd_dtau.stride != 1)
    return tree_fd_solve(tree, nv, work, dqdd_dq, dqdd_dqd, dqdd_dtau, armature);
  // row-major blocks (the host's layout): the factor and the solves over the DoF tree's
  // runs, each row of the solves computed once (dof_ltl_factor, dof_ltl_negated_solve;
  // the same results as tree_fd_solve, bit for bit)
  if (armature)
    for (Index i = 0; i < nv; ++i) dqdd_dtau(i, i) += armature[i];
  const Index failed = dof_ltl_factor(tree, dqdd_dtau);
  if (failed >= 0) return failed;
  dof_ltl_negated_solve(tree, dqdd_dtau, dqdd_dq, dqdd_dqd);
  tree_ltl_inverse_on_work(tree, dqdd_dtau, work);
  return -1;
}

// The same without the DoFs' runs (dof_parent, dof_last only): the factor and the
// solves by the tree walks of tree_fd_solve, on any layout (the same results).
template <class S>
SCANDYN_HD Index fd_derivatives_general_instance(const Body<S>* body, Index nb, Index nv, const Motion<S>& a0,
                                                 const S* q, const S* qd, const S* qdd, const Force<S>* fext,
                                                 const Index* dof_parent, const Index* dof_last,
                                                 DerivativeBody<S>* work,
                                                 MatrixRef<S> dqdd_dq, MatrixRef<S> dqdd_dqd, MatrixRef<S> dqdd_dtau,
                                                 const S* armature = nullptr) {
  rnea_derivatives_general_instance(body, nb, nv, a0, q, qd, qdd, fext, work, dqdd_dq, dqdd_dqd, dqdd_dtau,
                                    nullptr);
  return tree_fd_solve(DofTree{dof_parent, dof_last, nullptr}, nv, work, dqdd_dq, dqdd_dqd, dqdd_dtau, armature);
}

}  // namespace scandyn
