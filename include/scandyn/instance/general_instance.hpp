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
// its GeneralWork a slice of a device buffer).
#pragma once

#include "scandyn/algorithm/steps.hpp"

namespace scandyn {

// One instance's scratch for the general path: nb bodies, nv DoFs. Each algorithm
// uses some of the arrays (rnea: Xup v a f; crba: Xup Ic; aba: Xup v a c f IA U D u L).
template <class S>
struct GeneralWork {
  Transform<S>* Xup;  // (nb) parent -> body transform at the current q
  Motion<S>* v;       // (nb) body velocities, body frames
  Motion<S>* a;       // (nb) body accelerations (gravity included)
  Motion<S>* c;       // (nb) ABA velocity-product accelerations
  Force<S>* f;        // (nb) RNEA body forces / ABA bias forces pA
  Inertia<S>* Ic;     // (nb) CRBA composite inertias
  ABInertia<S>* IA;   // (nb) ABA articulated inertias
  Force<S>* U;        // (nv) ABA IA S per DoF (multi-DoF joints: Y = U L^-T)
  S* D;               // (nv) ABA S^T IA S per DoF of a 1-DoF joint
  S* u;               // (nv) ABA tau - S^T pA per DoF (multi-DoF joints: w = L^-1 u)
  S* L;               // (kMaxJointDofs nv) multi-DoF joints' Cholesky factors of S^T IA S:
                      // row k of the joint at DoF iv at (iv + k) * kMaxJointDofs
};

// tau = ID(q, qd, qdd, fext) (qdd null: the bias forces). q: nq entries, qd, qdd,
// tau: nv; fext: nb body wrenches or null; a0 = base_acceleration(gravity).
template <class S>
SCANDYN_HD void rnea_general(const Body<S>* body, Index nb, const Motion<S>& a0, const GeneralWork<S>& w, const S* q,
                             const S* qd, const S* qdd, S* tau, const Force<S>* fext) {
  for (Index i = 0; i < nb; ++i) {
    const Body<S>& b = body[i];
    const Index p = b.parent;
    w.Xup[i] = joint_transform_at(b, q + b.idx_q);
    const RneaForward<S> o = rnea_forward_step_at(b, w.Xup[i], p < 0 ? Motion<S>::zero() : w.v[p], p < 0 ? a0 : w.a[p],
                                                  qd + b.idx_v, qdd ? qdd + b.idx_v : static_cast<const S*>(nullptr));
    w.v[i] = o.v;
    w.a[i] = o.a;
    w.f[i] = fext ? o.f - fext[i] : o.f;
  }
  for (Index i = nb - 1; i >= 0; --i) {
    const Body<S>& b = body[i];
    joint_project_at(b, w.f[i], tau + b.idx_v);
    if (b.parent >= 0) w.f[b.parent] += w.Xup[i].apply_transpose(w.f[i]);
  }
}

// M(q), both triangles: M(r, c) is the S& the functor returns (nv x nv entries, each
// written once after the zeros).
template <class S, class MOut>
SCANDYN_HD void crba_general(const Body<S>* body, Index nb, Index nv, const GeneralWork<S>& w, const S* q,
                             const MOut& M) {
  for (Index i = 0; i < nb; ++i) {
    w.Xup[i] = joint_transform_at(body[i], q + body[i].idx_q);
    w.Ic[i] = body[i].I;
  }
  for (Index i = nb - 1; i >= 0; --i) {
    const Index p = body[i].parent;
    if (p >= 0) w.Ic[p] += crba_composite_step(w.Xup[i], w.Ic[i]);
  }
  for (Index r = 0; r < nv; ++r)
    for (Index c = 0; c < nv; ++c) M(r, c) = S(0);
  // the columns of body i's joint: F_k = Ic_i S_i e_k carried up the path to the root
  for (Index i = 0; i < nb; ++i) {
    const Body<S>& b = body[i];
    const int nj = joint_nv(b.type);
    for (int k = 0; k < nj; ++k) {
      const Index col = b.idx_v + k;
      Force<S> F = w.Ic[i] * joint_column(b, k);
      S Mcol[kMaxJointDofs] = {};  // joint_project_at writes nj entries (zeros: no maybe-uninitialized)
      joint_project_at(b, F, Mcol);
      for (int l = 0; l < nj; ++l) M(b.idx_v + l, col) = Mcol[l];
      Index j = i;
      while (body[j].parent >= 0) {
        F = crba_column_step(w.Xup[j], F);
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

// qdd = FD(q, qd, tau, fext) by the ABA (armature: nv joint-space inertias added to
// M's diagonal, or null). Returns the first DoF whose pivot is not positive and
// finite (qdd untouched), -1 when none.
template <class S>
SCANDYN_HD Index aba_general(const Body<S>* body, Index nb, const Motion<S>& a0, const GeneralWork<S>& w, const S* q,
                             const S* qd, const S* tau, S* qdd, const Force<S>* fext, const S* armature) {
  for (Index i = 0; i < nb; ++i) {
    const Body<S>& b = body[i];
    const Index p = b.parent;
    w.Xup[i] = joint_transform_at(b, q + b.idx_q);
    const AbaForward<S> o = aba_forward_step_at(b, w.Xup[i], p < 0 ? Motion<S>::zero() : w.v[p], qd + b.idx_v);
    w.v[i] = o.v;
    w.c[i] = o.c;
    w.f[i] = fext ? o.pA - fext[i] : o.pA;
    w.IA[i] = ABInertia<S>::from(b.I);
  }
  for (Index i = nb - 1; i >= 0; --i) {
    const Body<S>& b = body[i];
    const Index iv = b.idx_v;
    if (b.type == JointType::Revolute || b.type == JointType::Prismatic) {
      aba_joint_terms(b, w.IA[i], w.f[i], tau[iv], w.U[iv], w.D[iv], w.u[iv], armature ? armature[iv] : S(0));
      if (!pivot_ok(w.D[iv])) return iv;
      if (b.parent >= 0)
        aba_backward_to_parent(w.Xup[i], w.IA[i], w.f[i], w.c[i], w.U[iv], w.D[iv], w.u[iv], w.IA[b.parent],
                               w.f[b.parent]);
    } else {
      S* L = w.L + iv * kMaxJointDofs;
      const int k = aba_joint_terms_at(b, w.IA[i], w.f[i], tau + iv, w.U + iv, L, w.u + iv,
                                       armature ? armature + iv : static_cast<const S*>(nullptr));
      if (k >= 0) return iv + k;
      if (b.parent >= 0)
        aba_backward_to_parent_at(joint_nv(b.type), w.Xup[i], w.IA[i], w.f[i], w.c[i], w.U + iv, w.u + iv,
                                  w.IA[b.parent], w.f[b.parent]);
    }
  }
  for (Index i = 0; i < nb; ++i) {
    const Body<S>& b = body[i];
    const Index iv = b.idx_v;
    const Motion<S>& ap = b.parent < 0 ? a0 : w.a[b.parent];
    if (b.type == JointType::Revolute || b.type == JointType::Prismatic)
      qdd[iv] = aba_acceleration_step(b, w.Xup[i], ap, w.c[i], w.U[iv], w.D[iv], w.u[iv], w.a[i]);
    else
      aba_acceleration_step_at(b, w.Xup[i], ap, w.c[i], w.U + iv, w.L + iv * kMaxJointDofs, w.u + iv, qdd + iv,
                               w.a[i]);
  }
  return -1;
}

}  // namespace scandyn
