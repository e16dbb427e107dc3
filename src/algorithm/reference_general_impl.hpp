// src/algorithm/reference_general_impl.hpp: the general path of the serial
// reference algorithms, for models with multi-DoF joints (a floating base,
// spherical joints): rnea_at, crba_at, aba_at (scandyn/algorithm/reference.hpp),
// to which rnea, crba and aba dispatch. A translation unit of their own
// (reference_general.cpp for float and double, src/truth/reference_wide.cpp for the
// wide scalars): inlined next to the 1-DoF loops, they used up the compiler's
// inlining budget of reference.cpp and left the 1-DoF loops' step functions as
// calls (iiwa's aba and rnea 30-40% slower).
#pragma once

#include "scandyn/algorithm/reference.hpp"

namespace scandyn {


template <class S>
void rnea_at(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, const S* qd, const S* qdd,
             S* tau, const Force<S>* fext) {
  const Index n = model.nbodies();
  const Motion<S> a0 = base_acceleration(model.gravity);
  for (Index i = 0; i < n; ++i) {
    const Body<S>& b = model.bodies[i];
    const Index p = b.parent;
    data.Xup[i] = joint_transform_at(b, q + b.idx_q);
    const RneaForward<S> o = rnea_forward_step_at(b, data.Xup[i], p < 0 ? Motion<S>::zero() : data.v[p],
                                                  p < 0 ? a0 : data.a[p], qd + b.idx_v,
                                                  qdd ? qdd + b.idx_v : static_cast<const S*>(nullptr));
    data.v[i] = o.v;
    data.a[i] = o.a;
    data.f[i] = fext ? o.f - fext[i] : o.f;
  }
  for (Index i = n - 1; i >= 0; --i) {
    const Body<S>& b = model.bodies[i];
    joint_project_at(b, data.f[i], tau + b.idx_v);
    if (b.parent >= 0) data.f[b.parent] += data.Xup[i].apply_transpose(data.f[i]);
  }
}

template <class S>
void crba_at(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, S* M) {
  const Index n = model.nbodies();
  for (Index i = 0; i < n; ++i) {
    data.Xup[i] = joint_transform_at(model.bodies[i], q + model.bodies[i].idx_q);
    data.Ic[i] = model.bodies[i].I;
  }
  for (Index i = n - 1; i >= 0; --i) {
    const Index p = model.bodies[i].parent;
    if (p >= 0) data.Ic[p] += crba_composite_step(data.Xup[i], data.Ic[i]);
  }
  const std::size_t nn = static_cast<std::size_t>(model.nv());
  for (std::size_t k = 0; k < nn * nn; ++k) M[k] = S(0);
  // the columns of body i's joint: F_k = Ic_i S_i e_k carried up the path to the root
  for (Index i = 0; i < n; ++i) {
    const Body<S>& b = model.bodies[i];
    const int nj = joint_nv(b.type);
    for (int k = 0; k < nj; ++k) {
      const std::size_t col = static_cast<std::size_t>(b.idx_v + k);
      Force<S> F = data.Ic[i] * joint_column(b, k);
      S Mcol[kMaxJointDofs] = {};  // joint_project_at writes nj entries (zeros: no maybe-uninitialized)
      joint_project_at(b, F, Mcol);
      for (int l = 0; l < nj; ++l) M[(b.idx_v + l) * nn + col] = Mcol[l];
      Index j = i;
      while (model.bodies[j].parent >= 0) {
        F = crba_column_step(data.Xup[j], F);
        j = model.bodies[j].parent;
        const Body<S>& bj = model.bodies[j];
        joint_project_at(bj, F, Mcol);
        for (int l = 0; l < joint_nv(bj.type); ++l) {
          const std::size_t row = static_cast<std::size_t>(bj.idx_v + l);
          M[row * nn + col] = Mcol[l];
          M[col * nn + row] = Mcol[l];
        }
      }
    }
  }
}

template <class S>
Status aba_at(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, const S* qd, const S* tau,
              S* qdd, const Force<S>* fext, const S* armature) {
  const Index n = model.nbodies();
  for (Index i = 0; i < n; ++i) {
    const Body<S>& b = model.bodies[i];
    const Index p = b.parent;
    data.Xup[i] = joint_transform_at(b, q + b.idx_q);
    const AbaForward<S> o = aba_forward_step_at(b, data.Xup[i], p < 0 ? Motion<S>::zero() : data.v[p], qd + b.idx_v);
    data.v[i] = o.v;
    data.c[i] = o.c;
    data.f[i] = fext ? o.pA - fext[i] : o.pA;
    data.IA[i] = ABInertia<S>::from(b.I);
  }
  for (Index i = n - 1; i >= 0; --i) {
    const Body<S>& b = model.bodies[i];
    const Index iv = b.idx_v;
    if (b.type == JointType::Revolute || b.type == JointType::Prismatic) {
      aba_joint_terms(b, data.IA[i], data.f[i], tau[iv], data.U[iv], data.D[iv], data.u[iv],
                      armature ? armature[iv] : S(0));
      if (!pivot_ok(data.D[iv])) return Status{iv};
      if (b.parent >= 0)
        aba_backward_to_parent(data.Xup[i], data.IA[i], data.f[i], data.c[i], data.U[iv], data.D[iv],
                               data.u[iv], data.IA[b.parent], data.f[b.parent]);
    } else {
      S* L = data.L.data() + static_cast<std::size_t>(iv) * kMaxJointDofs;
      const int k = aba_joint_terms_at(b, data.IA[i], data.f[i], tau + iv, data.U.data() + iv, L,
                                       data.u.data() + iv, armature ? armature + iv : static_cast<const S*>(nullptr));
      if (k >= 0) return Status{iv + k};
      if (b.parent >= 0)
        aba_backward_to_parent_at(joint_nv(b.type), data.Xup[i], data.IA[i], data.f[i], data.c[i],
                                  data.U.data() + iv, data.u.data() + iv, data.IA[b.parent], data.f[b.parent]);
    }
  }
  const Motion<S> a0 = base_acceleration(model.gravity);
  for (Index i = 0; i < n; ++i) {
    const Body<S>& b = model.bodies[i];
    const Index iv = b.idx_v;
    const Motion<S>& ap = b.parent < 0 ? a0 : data.a[b.parent];
    if (b.type == JointType::Revolute || b.type == JointType::Prismatic)
      qdd[iv] = aba_acceleration_step(b, data.Xup[i], ap, data.c[i], data.U[iv], data.D[iv], data.u[iv], data.a[i]);
    else
      aba_acceleration_step_at(b, data.Xup[i], ap, data.c[i], data.U.data() + iv,
                               data.L.data() + static_cast<std::size_t>(iv) * kMaxJointDofs,
                               data.u.data() + iv, qdd + iv, data.a[i]);
  }
  return Status{};
}

}  // namespace scandyn

// Explicit instantiation of the general path for the scalar S.
#define SCANDYN_INSTANTIATE_GENERAL(S)                                                            \
  template void rnea_at(const ModelTpl<S>&, DataTpl<S>&, const S*, const S*, const S*, S*,        \
                        const Force<S>*);                                                         \
  template void crba_at(const ModelTpl<S>&, DataTpl<S>&, const S*, S*);                           \
  template Status aba_at(const ModelTpl<S>&, DataTpl<S>&, const S*, const S*, const S*, S*,       \
                         const Force<S>*, const S*);
