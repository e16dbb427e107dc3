// src/algorithm/reference_general_impl.hpp: the general path of the serial
// reference algorithms, for models with multi-DoF joints (a floating base,
// spherical joints): rnea_at, crba_at, aba_at (scandyn/algorithm/reference.hpp),
// to which rnea, crba and aba dispatch: the one-instance routines of
// scandyn/instance/general_instance.hpp over DataTpl's vectors. A translation unit of their own
// (reference_general.cpp for float and double, src/truth/reference_wide.cpp for the
// wide scalars): inlined next to the 1-DoF loops, they used up the compiler's
// inlining budget of reference.cpp and left the 1-DoF loops' step functions as
// calls (iiwa's aba and rnea 30-40% slower).
#pragma once

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/instance/general_instance.hpp"

namespace scandyn {

// The general path's scratch in DataTpl's vectors.
template <class S>
GeneralWork<S> general_work(DataTpl<S>& data) {
  return {data.Xup.data(), data.v.data(), data.a.data(), data.c.data(), data.f.data(), data.Ic.data(),
          data.IA.data(), data.U.data(), data.D.data(), data.u.data(), data.L.data()};
}

template <class S>
void rnea_at(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, const S* qd, const S* qdd,
             S* tau, const Force<S>* fext) {
  rnea_general(model.bodies.data(), model.nbodies(), base_acceleration(model.gravity), general_work(data), q, qd, qdd,
               tau, fext);
}

template <class S>
void crba_at(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, S* M) {
  const Index nv = model.nv();
  crba_general(model.bodies.data(), model.nbodies(), nv, general_work(data), q,
               [M, nv](Index r, Index c) -> S& { return M[r * nv + c]; });
}

template <class S>
Status aba_at(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, const S* qd, const S* tau,
              S* qdd, const Force<S>* fext, const S* armature) {
  return Status{aba_general(model.bodies.data(), model.nbodies(), base_acceleration(model.gravity),
                            general_work(data), q, qd, tau, qdd, fext, armature)};
}

}  // namespace scandyn

// Explicit instantiation of the general path for the scalar S.
#define SCANDYN_INSTANTIATE_GENERAL(S)                                                            \
  template void rnea_at(const ModelTpl<S>&, DataTpl<S>&, const S*, const S*, const S*, S*,        \
                        const Force<S>*);                                                         \
  template void crba_at(const ModelTpl<S>&, DataTpl<S>&, const S*, S*);                           \
  template Status aba_at(const ModelTpl<S>&, DataTpl<S>&, const S*, const S*, const S*, S*,       \
                         const Force<S>*, const S*);
