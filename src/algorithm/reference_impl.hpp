// src/algorithm/reference_impl.hpp: the definitions of the serial reference
// algorithms (scandyn/algorithm/reference.hpp), included by the translation units
// that instantiate them: reference.cpp for float and double (the library), and
// src/truth/reference_wide.cpp for long double and __float128 (the
// high-precision truth, library scandyn_truth). One definition, every scalar.
#pragma once

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/instance/rnea_passes.hpp"

#include <cmath>
#include <stdexcept>

namespace scandyn {

template <class S>
DataTpl<S>::DataTpl(const ModelTpl<S>& model, bool mass_matrix) {
  const std::size_t nb = static_cast<std::size_t>(model.nbodies());
  const std::size_t n = static_cast<std::size_t>(model.nv());
  Xup.resize(nb);
  v.resize(nb);
  a.resize(nb);
  c.resize(nb);
  f.resize(nb);
  Ic.resize(nb);
  IA.resize(nb);
  U.resize(n);
  D.resize(n);
  u.resize(n);
  if (model.multi_dof()) L.resize(n * kMaxJointDofs);
  if (mass_matrix) M.resize(n * n);
  h.resize(n);
  lambda.resize(n);
  if (!model.multi_dof()) {
    for (std::size_t i = 0; i < n; ++i) lambda[i] = model.bodies[i].parent;
  } else {
    for (const Body<S>& b : model.bodies) {
      const Index first = b.idx_v, nj = joint_nv(b.type);
      lambda[first] = b.parent < 0 ? Index(-1)
                                   : model.bodies[b.parent].idx_v + joint_nv(model.bodies[b.parent].type) - 1;
      for (Index k = 1; k < nj; ++k) lambda[first + k] = first + k - 1;
    }
  }
  run_start.resize(n);
  for (std::size_t i = 0; i < n; ++i)
    run_start[i] = (i > 0 && lambda[i] == Index(i) - 1) ? run_start[i - 1] : Index(i);
}

template <class S>
void rnea(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, const S* qd, const S* qdd,
          S* tau, const Force<S>* fext) {
  if constexpr (!kIsPack<S>)  // packs: 1-DoF models only (cpu::simd_supported)
    if (model.multi_dof()) return rnea_at(model, data, q, qd, qdd, tau, fext);
  rnea_passes(model.bodies.data(), model.nv(), base_acceleration(model.gravity), q, qd, qdd, fext,
              RneaBodies<S>{data.Xup.data(), data.v.data(), data.a.data(), data.f.data()}, tau);
}

template <class S>
void bias_forces(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, const S* qd, S* h,
                 const Force<S>* fext) {
  rnea(model, data, q, qd, static_cast<const S*>(nullptr), h, fext);
}

template <class S>
void crba(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, S* M) {
  if constexpr (!kIsPack<S>)  // packs: 1-DoF models only (cpu::simd_supported)
    if (model.multi_dof()) return crba_at(model, data, q, M);
  const Index n = model.nv();
  for (Index i = 0; i < n; ++i) {
    data.Xup[i] = joint_transform(model.bodies[i], q[i]);
    data.Ic[i] = model.bodies[i].I;
  }
  // composite inertias, leaves to root
  for (Index i = n - 1; i >= 0; --i) {
    const Index p = model.bodies[i].parent;
    if (p >= 0) data.Ic[p] += crba_composite_step(data.Xup[i], data.Ic[i]);
  }
  const std::size_t nn = static_cast<std::size_t>(n);  // row stride; n * n overflows Index past 46340
  for (std::size_t k = 0; k < nn * nn; ++k) M[k] = S(0);
  // column i: F = Ic_i S_i carried up the path to the root
  for (Index i = 0; i < n; ++i) {
    const Body<S>& b = model.bodies[i];
    Force<S> F = crba_column_force(b, data.Ic[i]);
    M[i * nn + i] = joint_project(b, F);
    Index j = i;
    while (model.bodies[j].parent >= 0) {
      F = crba_column_step(data.Xup[j], F);
      j = model.bodies[j].parent;
      const S Mij = joint_project(model.bodies[j], F);
      M[i * nn + j] = Mij;
      M[j * nn + i] = Mij;
    }
  }
}

namespace detail {

// The articulated-body passes of aba and hybrid_dynamics. prescribed null: the ABA
// (every DoF's force given). Otherwise DoF i with prescribed[i] != 0 has its
// acceleration qdd_in[i] given (Featherstone 2008, 9.2: hybrid_prescribed_*) and its
// force written to tau_out[i]; every other DoF has its force tau[i] given, copied to
// tau_out[i], and its acceleration computed. The ABA's DoFs take exactly the ABA's
// arithmetic. Nothing is written before every pivot passed; each output entry i is
// written after its inputs i were read (the outputs may alias the inputs).
template <class S>
Status articulated_body_passes(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, const S* qd, const S* tau,
                               S* qdd, const Force<S>* fext, const S* armature, const unsigned char* prescribed,
                               const S* qdd_in, S* tau_out) {
  const Index n = model.nv();
  auto given = [&](Index i) { return prescribed && prescribed[i]; };
  // pass 1: kinematics, bias forces
  for (Index i = 0; i < n; ++i) {
    const Body<S>& b = model.bodies[i];
    const Index p = b.parent;
    data.Xup[i] = joint_transform(b, q[i]);
    const AbaForward<S> o = aba_forward_step(b, data.Xup[i], p < 0 ? Motion<S>::zero() : data.v[p], qd[i]);
    data.v[i] = o.v;
    data.c[i] = o.c;
    data.f[i] = fext ? o.pA - fext[i] : o.pA;
    data.IA[i] = ABInertia<S>::from(b.I);
  }
  // pass 2: articulated inertias, leaves to root
  for (Index i = n - 1; i >= 0; --i) {
    const Body<S>& b = model.bodies[i];
    if (given(i)) {
      aba_joint_terms(b, data.IA[i], data.f[i], S(0), data.U[i], data.D[i], data.u[i]);
      if (b.parent >= 0)
        hybrid_prescribed_to_parent(b, data.Xup[i], data.IA[i], data.f[i], data.c[i], qdd_in[i],
                                    data.IA[b.parent], data.f[b.parent]);
      continue;
    }
    if (armature)
      aba_joint_terms(b, data.IA[i], data.f[i], tau[i], data.U[i], data.D[i], data.u[i], armature[i]);
    else
      aba_joint_terms(b, data.IA[i], data.f[i], tau[i], data.U[i], data.D[i], data.u[i]);
    if (!pivot_ok(data.D[i])) return Status{i};
    if (b.parent >= 0)
      aba_backward_to_parent(data.Xup[i], data.IA[i], data.f[i], data.c[i], data.U[i], data.D[i],
                             data.u[i], data.IA[b.parent], data.f[b.parent]);
  }
  // pass 3: accelerations (and the prescribed joints' forces), root to leaves
  const Motion<S> a0 = base_acceleration(model.gravity);
  for (Index i = 0; i < n; ++i) {
    const Body<S>& b = model.bodies[i];
    const Motion<S>& ap = b.parent < 0 ? a0 : data.a[b.parent];
    if (given(i)) {
      const S qddi = qdd_in[i];
      tau_out[i] = hybrid_prescribed_acceleration_step(b, data.Xup[i], ap, data.c[i], data.U[i], data.u[i], qddi,
                                                       data.a[i]);
      qdd[i] = qddi;
      continue;
    }
    qdd[i] = aba_acceleration_step(b, data.Xup[i], ap, data.c[i], data.U[i], data.D[i], data.u[i], data.a[i]);
    if (tau_out) tau_out[i] = tau[i];
  }
  return Status{};
}

}  // namespace detail

template <class S>
Status aba(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, const S* qd, const S* tau,
           S* qdd, const Force<S>* fext, const S* armature) {
  if constexpr (!kIsPack<S>)  // packs: 1-DoF models only (cpu::simd_supported)
    if (model.multi_dof()) return aba_at(model, data, q, qd, tau, qdd, fext, armature);
  return detail::articulated_body_passes(model, data, q, qd, tau, qdd, fext, armature,
                                         static_cast<const unsigned char*>(nullptr), static_cast<const S*>(nullptr),
                                         static_cast<S*>(nullptr));
}

template <class S>
Status hybrid_dynamics(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, const S* qd,
                       const unsigned char* prescribed, const S* qdd_in, const S* tau_in, S* qdd_out, S* tau_out,
                       const Force<S>* fext, const S* armature) {
  if (model.multi_dof())  // the engines and the simulator refuse such models first
    throw std::invalid_argument("hybrid dynamics: model '" + model.name + "' has multi-DoF joints (joint '" +
                                first_multi_dof_joint(model) + "'); hybrid dynamics takes 1-DoF joints only");
  return detail::articulated_body_passes(model, data, q, qd, tau_in, qdd_out, fext, armature, prescribed, qdd_in,
                                         tau_out);
}

// Calls f(j) for every ancestor DoF j of DoF i and i itself, from i towards the root,
// walking contiguous chain runs as plain loops (vectorisable, no pointer chasing).
template <class S, class F>
inline void for_path(const DataTpl<S>& data, Index i, F f) {
  while (i >= 0) {
    const Index r = data.run_start[i];
    for (Index j = i; j >= r; --j) f(j);
    i = data.lambda[r];
  }
}

template <class S>
Status ltl_factor(const ModelTpl<S>& model, const DataTpl<S>& data, S* M) {
  const Index n = model.nv();
  const std::size_t nn = static_cast<std::size_t>(n);
  for (Index k = n - 1; k >= 0; --k) {
    S* Lk = M + k * nn;  // row k
    const S d = Lk[k];
    if (!pivot_ok(d)) return Status{k};
    const S Lkk = ScalarMath<S>::sqrt(d);
    Lk[k] = Lkk;
    const S inv = S(1) / Lkk;
    for_path(data, data.lambda[k], [&](Index i) { Lk[i] *= inv; });
    for_path(data, data.lambda[k], [&](Index i) {
      const S Lki = Lk[i];
      S* Mi = M + i * nn;
      for_path(data, i, [&](Index j) { Mi[j] -= Lki * Lk[j]; });
    });
  }
  return Status{};
}

template <class S>
void ltl_solve(const ModelTpl<S>& model, const DataTpl<S>& data, const S* L, S* x) {
  const Index n = model.nv();
  const std::size_t nn = static_cast<std::size_t>(n);
  // L^T y = b
  for (Index i = n - 1; i >= 0; --i) {
    const S* Li = L + i * nn;
    x[i] /= Li[i];
    const S xi = x[i];
    for_path(data, data.lambda[i], [&](Index j) { x[j] -= Li[j] * xi; });
  }
  // L x = y
  for (Index i = 0; i < n; ++i) {
    const S* Li = L + i * nn;
    S acc = x[i];
    for_path(data, data.lambda[i], [&](Index j) { acc -= Li[j] * x[j]; });
    x[i] = acc / Li[i];
  }
}

template <class S>
Status fd_jsi(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, const S* qd, const S* tau,
              S* qdd, const Force<S>* fext, const S* armature) {
  const Index n = model.nv();
  if (data.M.size() != static_cast<std::size_t>(n) * n)
    throw std::logic_error("fd_jsi: DataTpl was built without its mass-matrix workspace");
  crba(model, data, q, data.M.data());
  if (armature) {
    const std::size_t nn = static_cast<std::size_t>(n);
    for (Index i = 0; i < n; ++i) data.M[i * nn + i] += armature[i];
  }
  bias_forces(model, data, q, qd, data.h.data(), fext);
  const Status st = ltl_factor(model, data, data.M.data());
  if (!st.ok()) return st;
  for (Index i = 0; i < n; ++i) qdd[i] = tau[i] - data.h[i];
  ltl_solve(model, data, data.M.data(), qdd);
  return st;
}

}  // namespace scandyn

// Explicit instantiation of every reference algorithm for the scalar S.
#define SCANDYN_INSTANTIATE(S)                                                                    \
  template struct DataTpl<S>;                                                                     \
  template void rnea(const ModelTpl<S>&, DataTpl<S>&, const S*, const S*, const S*, S*,           \
                     const Force<S>*);                                                            \
  template void bias_forces(const ModelTpl<S>&, DataTpl<S>&, const S*, const S*, S*,              \
                            const Force<S>*);                                                     \
  template void crba(const ModelTpl<S>&, DataTpl<S>&, const S*, S*);                              \
  template Status aba(const ModelTpl<S>&, DataTpl<S>&, const S*, const S*, const S*, S*,          \
                      const Force<S>*, const S*);                                                 \
  template Status hybrid_dynamics(const ModelTpl<S>&, DataTpl<S>&, const S*, const S*, const unsigned char*,      \
                                  const S*, const S*, S*, S*, const Force<S>*, const S*);                      \
  template Status fd_jsi(const ModelTpl<S>&, DataTpl<S>&, const S*, const S*, const S*, S*,       \
                         const Force<S>*, const S*);                                              \
  template Status ltl_factor(const ModelTpl<S>&, const DataTpl<S>&, S*);                          \
  template void ltl_solve(const ModelTpl<S>&, const DataTpl<S>&, const S*, S*);
