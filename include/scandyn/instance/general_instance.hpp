// scandyn/instance/general_instance.hpp: the general path of the reference
// algorithms, for models with multi-DoF joints (a floating base, spherical joints):
// RNEA, CRBA and ABA of one instance over joints of 1, 3 and 6 DoFs (the *_at steps
// of steps.hpp), as plain SCANDYN_HD code over a body array in DoF order and a
// GeneralWork.
//
// The one routine behind every backend's general path: the serial reference's
// rnea_at / crba_at / aba_at (src/algorithm/reference_general_impl.hpp, their
// GeneralWork over DataTpl's vectors; the OpenMP engines call those per instance)
// and the CUDA general kernels (kernels/general_dynamics.cu: one thread per instance,
// its GeneralWorkOf arrays interleaved with the other threads' in a device buffer,
// scandyn/instance/interleaved.hpp, so that a warp's loads coalesce).
//
// The routines are templates over the scratch (W: GeneralWork<S> of plain pointers,
// or a GeneralWorkOf<S, StridedArray> / <S, ScalarInterleavedArray>) and over the
// arrays of q, qd, tau and the result (plain pointers or StridedArray<S>). They read
// a scratch element into a local and write or add whole elements, and hand a joint's
// entries to the *_at steps through joint_run (the plain pointer itself on the host:
// the serial reference computes what it computed before, value for value).
#pragma once

#include "scandyn/algorithm/steps.hpp"
#include "scandyn/instance/interleaved.hpp"

namespace scandyn {

// One instance's scratch for the general path: nb bodies, nv DoFs. Each algorithm
// uses some of the arrays (rnea: Xup v a f; crba: Xup Ic; aba: Xup v a c f IA U D u L).
// A<T>: the array type of elements T (T*: the serial reference, GeneralWork<S>).
template <class S, template <class> class A>
struct GeneralWorkOf {
  A<Transform<S>> Xup;  // (nb) parent -> body transform at the current q
  A<Motion<S>> v;       // (nb) body velocities, body frames
  A<Motion<S>> a;       // (nb) body accelerations (gravity included)
  A<Motion<S>> c;       // (nb) ABA velocity-product accelerations
  A<Force<S>> f;        // (nb) RNEA body forces / ABA bias forces pA
  A<Inertia<S>> Ic;     // (nb) CRBA composite inertias
  A<ABInertia<S>> IA;   // (nb) ABA articulated inertias
  A<Force<S>> U;        // (nv) ABA IA S per DoF (multi-DoF joints: Y = U L^-T)
  A<S> D;               // (nv) ABA S^T IA S per DoF of a 1-DoF joint
  A<S> u;               // (nv) ABA tau - S^T pA per DoF (multi-DoF joints: w = L^-1 u)
  A<S> L;               // (kMaxJointDofs nv) multi-DoF joints' Cholesky factors of S^T IA S:
                        // row k of the joint at DoF iv at (iv + k) * kMaxJointDofs
};

template <class T>
using PlainArray = T*;

// The scratch of plain pointers (the serial reference, the variational step).
template <class S>
using GeneralWork = GeneralWorkOf<S, PlainArray>;

// The lower triangle of a multi-DoF joint's factor L (nj rows from DoF iv) between
// the scratch array and a local copy (no-ops for a plain pointer: joint_run).
template <class A, class S>
SCANDYN_HD void load_joint_factor(const A& L, Index iv, int nj, S* tmp) {
  if constexpr (!std::is_pointer<A>::value)
    for (int k = 0; k < nj; ++k)
      for (int m = 0; m <= k; ++m) tmp[k * kMaxJointDofs + m] = L[(iv + k) * kMaxJointDofs + m];
  (void)L, (void)iv, (void)nj, (void)tmp;
}
template <class A, class S>
SCANDYN_HD void store_joint_factor(const A& L, Index iv, int nj, const S* tmp) {
  if constexpr (!std::is_pointer<A>::value)
    for (int k = 0; k < nj; ++k)
      for (int m = 0; m <= k; ++m) L[(iv + k) * kMaxJointDofs + m] = tmp[k * kMaxJointDofs + m];
  (void)L, (void)iv, (void)nj, (void)tmp;
}

// tau = ID(q, qd, qdd, fext) (qdd null: the bias forces). q: nq entries, qd, qdd,
// tau: nv; fext: nb body wrenches or null; a0 = base_acceleration(gravity).
template <class S, class W>
SCANDYN_HD void rnea_general(const Body<S>* body, Index nb, const Motion<S>& a0, const W& w, const S* q,
                             const S* qd, const S* qdd, S* tau, const Force<S>* fext) {
  for (Index i = 0; i < nb; ++i) {
    const Body<S>& b = body[i];
    const Index p = b.parent;
    const Transform<S> X = joint_transform_at(b, q + b.idx_q);
    const RneaForward<S> o =
        rnea_forward_step_at(b, X, p < 0 ? Motion<S>::zero() : Motion<S>(w.v[p]), p < 0 ? a0 : Motion<S>(w.a[p]),
                             qd + b.idx_v, qdd ? qdd + b.idx_v : static_cast<const S*>(nullptr));
    w.Xup[i] = X;
    w.v[i] = o.v;
    w.a[i] = o.a;
    w.f[i] = fext ? o.f - fext[i] : o.f;
  }
  for (Index i = nb - 1; i >= 0; --i) {
    const Body<S>& b = body[i];
    const Force<S> f = w.f[i];
    joint_project_at(b, f, tau + b.idx_v);
    if (b.parent >= 0) w.f[b.parent] += Transform<S>(w.Xup[i]).apply_transpose(f);
  }
}

// M(q), both triangles: M(r, c) is the S& the functor returns (nv x nv entries, each
// written once after the zeros). q: nq entries (a plain pointer or StridedArray).
template <class S, class W, class Q, class MOut>
SCANDYN_HD void crba_general(const Body<S>* body, Index nb, Index nv, const W& w, const Q& q, const MOut& M) {
  for (Index i = 0; i < nb; ++i) {
    S qj[7];  // a free joint's 7 entries at most
    load_run(q, body[i].idx_q, joint_nq(body[i].type), qj);
    w.Xup[i] = joint_transform_at(body[i], joint_run(q, body[i].idx_q, qj));
    w.Ic[i] = body[i].I;
  }
  for (Index i = nb - 1; i >= 0; --i) {
    const Index p = body[i].parent;
    if (p >= 0) w.Ic[p] += crba_composite_step(Transform<S>(w.Xup[i]), Inertia<S>(w.Ic[i]));
  }
  for (Index r = 0; r < nv; ++r)
    for (Index c = 0; c < nv; ++c) M(r, c) = S(0);
  // the columns of body i's joint: F_k = Ic_i S_i e_k carried up the path to the root
  for (Index i = 0; i < nb; ++i) {
    const Body<S>& b = body[i];
    const int nj = joint_nv(b.type);
    const Inertia<S> Ic = w.Ic[i];
    for (int k = 0; k < nj; ++k) {
      const Index col = b.idx_v + k;
      Force<S> F = Ic * joint_column(b, k);
      S Mcol[kMaxJointDofs] = {};  // joint_project_at writes nj entries (zeros: no maybe-uninitialized)
      joint_project_at(b, F, Mcol);
      for (int l = 0; l < nj; ++l) M(b.idx_v + l, col) = Mcol[l];
      Index j = i;
      while (body[j].parent >= 0) {
        F = crba_column_step(Transform<S>(w.Xup[j]), F);
        j = body[j].parent;
        const Body<S>& bj = body[j];
        joint_project_at(bj, F, Mcol);
        for (int l = 0; l < joint_nv(bj.type); ++l) {
          const Index row = bj.idx_v + l;
          M(row, col) = Mcol[l];
          M(col, row) = Mcol[l];
        }
      }
    }
  }
}

// The ABA of the general path, one body at a time: the serial-order aba_general
// below runs these steps in DoF order; the CUDA level kernel (kernels/general_dynamics.cu,
// aba_levels_kernel) runs a tree level's bodies on the lanes of a warp, level after
// level, with the same arithmetic in the same order. Each step takes the values it
// depends on as arguments (the parent's velocity or acceleration, the body's own
// articulated inertia and bias force), so that a caller can hand them over in
// registers along a chain instead of through the scratch.

// Pass 1, body i: Xup, v, c, pA = v x* I v - fext and IA = I into the scratch; v_parent:
// its parent's velocity (zero at the base). Returns v.
template <class S, class W, class Q, class QD>
SCANDYN_HD Motion<S> aba_general_forward(const Body<S>* body, Index i, const Motion<S>& v_parent, const W& w,
                                         const Q& q, const QD& qd, const Force<S>* fext) {
  const Body<S>& b = body[i];
  S qj[7], qdj[kMaxJointDofs];  // the joint's q and qd entries (unused for plain pointers)
  load_run(q, b.idx_q, joint_nq(b.type), qj);
  load_run(qd, b.idx_v, joint_nv(b.type), qdj);
  const Transform<S> X = joint_transform_at(b, joint_run(q, b.idx_q, qj));
  const AbaForward<S> o = aba_forward_step_at(b, X, v_parent, joint_run(qd, b.idx_v, qdj));
  w.Xup[i] = X;
  w.v[i] = o.v;
  w.c[i] = o.c;
  w.f[i] = fext ? o.pA - fext[i] : o.pA;
  w.IA[i] = ABInertia<S>::from(b.I);
  return o.v;
}

// Pass 2, the joint terms of body i from its final articulated inertia IA and bias
// force pA: U, D, u of a 1-DoF joint, Y, L, w of a multi-DoF one, into the scratch.
// Returns the first DoF whose pivot is not positive and finite, -1 when none.
template <class S, class W, class Tau>
SCANDYN_HD Index aba_general_joint(const Body<S>* body, Index i, const ABInertia<S>& IA, const Force<S>& pA,
                                   const W& w, const Tau& tau, const S* armature) {
  const Body<S>& b = body[i];
  const Index iv = b.idx_v;
  if (b.type == JointType::Revolute || b.type == JointType::Prismatic) {
    Force<S> U;
    S D, u;
    aba_joint_terms(b, IA, pA, S(tau[iv]), U, D, u, armature ? armature[iv] : S(0));
    w.U[iv] = U;
    w.D[iv] = D;
    w.u[iv] = u;
    return pivot_ok(D) ? Index(-1) : iv;
  }
  const int nj = joint_nv(b.type);
  S tj[kMaxJointDofs], Lj[kMaxJointDofs * kMaxJointDofs], wj[kMaxJointDofs];
  Force<S> Yj[kMaxJointDofs];
  load_run(tau, iv, nj, tj);
  Force<S>* const Y = joint_run(w.U, iv, Yj);
  S* const L = joint_run(w.L, iv * kMaxJointDofs, Lj);
  S* const wv = joint_run(w.u, iv, wj);
  const int k = aba_joint_terms_at(b, IA, pA, joint_run(tau, iv, tj), Y, L, wv,
                                   armature ? armature + iv : static_cast<const S*>(nullptr));
  store_run(w.U, iv, nj, Y);
  store_joint_factor(w.L, iv, nj, L);
  store_run(w.u, iv, nj, wv);
  return k >= 0 ? iv + k : Index(-1);
}

// Pass 2, body i's share handed to its parent (IA, pA: body i's; its joint terms in
// the scratch): IAp += Xup^T Ia Xup, pAp += Xup^T pa.
template <class S, class W>
SCANDYN_HD void aba_general_to_parent(const Body<S>* body, Index i, const ABInertia<S>& IA, const Force<S>& pA,
                                      const W& w, ABInertia<S>& IAp, Force<S>& pAp) {
  const Body<S>& b = body[i];
  const Index iv = b.idx_v;
  if (b.type == JointType::Revolute || b.type == JointType::Prismatic) {
    aba_backward_to_parent(Transform<S>(w.Xup[i]), IA, pA, Motion<S>(w.c[i]), Force<S>(w.U[iv]), S(w.D[iv]),
                           S(w.u[iv]), IAp, pAp);
    return;
  }
  const int nj = joint_nv(b.type);
  S wj[kMaxJointDofs];
  Force<S> Yj[kMaxJointDofs];
  load_run(w.U, iv, nj, Yj);
  load_run(w.u, iv, nj, wj);
  aba_backward_to_parent_at(nj, Transform<S>(w.Xup[i]), IA, pA, Motion<S>(w.c[i]), joint_run(w.U, iv, Yj),
                            joint_run(w.u, iv, wj), IAp, pAp);
}

// Pass 3, body i: qdd of its joint and its acceleration a (into the scratch, and
// returned); a_parent: its parent's acceleration (a0 at the base).
template <class S, class W, class Qdd>
SCANDYN_HD Motion<S> aba_general_acceleration(const Body<S>* body, Index i, const Motion<S>& a_parent, const W& w,
                                              const Qdd& qdd) {
  const Body<S>& b = body[i];
  const Index iv = b.idx_v;
  const Transform<S> X = w.Xup[i];
  const Motion<S> c = w.c[i];
  Motion<S> a;
  if (b.type == JointType::Revolute || b.type == JointType::Prismatic) {
    qdd[iv] = aba_acceleration_step(b, X, a_parent, c, Force<S>(w.U[iv]), S(w.D[iv]), S(w.u[iv]), a);
  } else {
    const int nj = joint_nv(b.type);
    S Lj[kMaxJointDofs * kMaxJointDofs], wj[kMaxJointDofs], qddj[kMaxJointDofs];
    Force<S> Yj[kMaxJointDofs];
    load_run(w.U, iv, nj, Yj);
    load_joint_factor(w.L, iv, nj, Lj);
    load_run(w.u, iv, nj, wj);
    auto* const out = joint_run(qdd, iv, qddj);
    aba_acceleration_step_at(b, X, a_parent, c, joint_run(w.U, iv, Yj), joint_run(w.L, iv * kMaxJointDofs, Lj),
                             joint_run(w.u, iv, wj), out, a);
    store_run(qdd, iv, nj, out);
  }
  w.a[i] = a;
  return a;
}

// qdd = FD(q, qd, tau, fext) by the ABA (armature: nv joint-space inertias added to
// M's diagonal, or null). q (nq entries), qd, tau, qdd (nv): plain pointers or
// StridedArrays. Returns the first DoF whose pivot is not positive and finite (qdd
// untouched), -1 when none. Along a chain (body i's parent is i - 1, as in most of a
// tree in DoF order) the parent's velocity and acceleration and the body's own
// articulated inertia and bias force are handed from one step to the next in
// registers, not through the scratch (a GPU thread's dependent round trip through
// memory per body); a branch reads them from the scratch, where they are also kept.
template <class S, class W, class Q, class QD, class Tau, class Qdd>
SCANDYN_HD Index aba_general(const Body<S>* body, Index nb, const Motion<S>& a0, const W& w, const Q& q,
                             const QD& qd, const Tau& tau, const Qdd& qdd, const Force<S>* fext, const S* armature) {
  // pass 1, root to leaves: Xup, v, c, pA, IA = I
  Motion<S> v = Motion<S>::zero();  // body i - 1's
  for (Index i = 0; i < nb; ++i) {
    const Index p = body[i].parent;
    v = aba_general_forward(body, i, p < 0 ? Motion<S>::zero() : p == i - 1 ? v : Motion<S>(w.v[p]), w, q, qd, fext);
  }
  // pass 2, leaves to root: the joint terms, IA and pA handed to the parent
  ABInertia<S> IA;
  Force<S> pA;
  bool carried = false;  // IA, pA hold body i's (its parent was i + 1's)
  for (Index i = nb - 1; i >= 0; --i) {
    if (!carried) IA = w.IA[i], pA = w.f[i];
    const Index failed = aba_general_joint(body, i, IA, pA, w, tau, armature);
    if (failed >= 0) return failed;
    const Index p = body[i].parent;
    carried = p >= 0 && p == i - 1;
    if (p < 0) continue;
    ABInertia<S> IAp = w.IA[p];
    Force<S> pAp = w.f[p];
    aba_general_to_parent(body, i, IA, pA, w, IAp, pAp);
    if (carried) {
      IA = IAp, pA = pAp;
    } else {
      w.IA[p] = IAp;
      w.f[p] = pAp;
    }
  }
  // pass 3, root to leaves: the accelerations
  Motion<S> a = a0;  // body i - 1's
  for (Index i = 0; i < nb; ++i) {
    const Index p = body[i].parent;
    a = aba_general_acceleration(body, i, p < 0 ? a0 : p == i - 1 ? a : Motion<S>(w.a[p]), w, qdd);
  }
  return -1;
}

}  // namespace scandyn
