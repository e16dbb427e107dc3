// src/algorithm/derivatives.cpp: the serial reference derivatives
// (scandyn/algorithm/derivatives.hpp) for float and double.
#include "scandyn/algorithm/derivatives.hpp"
#include "scandyn/algorithm/directional_derivatives.hpp"

namespace scandyn {

template <class S>
void rnea_derivatives(const ModelTpl<S>& model, DerivativeDataTpl<S>& data, const S* q, const S* qd,
                      const S* qdd, const Force<S>* fext, MatrixRef<S> dtau_dq, MatrixRef<S> dtau_dqd,
                      MatrixRef<S> M, S* tau) {
  const Motion<S> a0 = base_acceleration(model.gravity);
  if (model.multi_dof()) {
    if (tau)
      rnea_derivatives_general_instance(model.bodies.data(), model.nbodies(), model.nv(), a0, q, qd, qdd, fext,
                                        data.work.data(), dtau_dq, dtau_dqd, M, tau);
    else
      rnea_derivatives_general_instance(model.bodies.data(), model.nbodies(), model.nv(), a0, q, qd, qdd, fext,
                                        data.work.data(), dtau_dq, dtau_dqd, M, nullptr);
    return;
  }
  if (tau)
    rnea_derivatives_instance(model.bodies.data(), model.nv(), a0, q, qd, qdd, fext, data.work.data(), dtau_dq,
                              dtau_dqd, M, tau);
  else
    rnea_derivatives_instance(model.bodies.data(), model.nv(), a0, q, qd, qdd, fext, data.work.data(), dtau_dq,
                              dtau_dqd, M, nullptr);
}

template <class S>
Status aba_derivatives(const ModelTpl<S>& model, DerivativeDataTpl<S>& data, const S* q, const S* qd,
                       const S* tau, const Force<S>* fext, S* qdd, MatrixRef<S> dqdd_dq, MatrixRef<S> dqdd_dqd,
                       MatrixRef<S> dqdd_dtau, const S* armature) {
  const Status st = aba(model, data.aba, q, qd, tau, qdd, fext, armature);
  if (!st.ok()) return st;
  if (model.multi_dof())
    return Status{fd_derivatives_general_instance(model.bodies.data(), model.nbodies(), model.nv(),
                                                  base_acceleration(model.gravity), q, qd, static_cast<const S*>(qdd),
                                                  fext, data.dof_parent.data(), data.dof_last.data(), data.dof_run.data(),
                                                  data.work.data(), dqdd_dq, dqdd_dqd,
                                                  dqdd_dtau, armature)};
  const Index failed = fd_derivatives_instance(model.bodies.data(), model.nv(), base_acceleration(model.gravity), q,
                                               qd, static_cast<const S*>(qdd), fext, data.work.data(), dqdd_dq,
                                               dqdd_dqd, dqdd_dtau, armature);
  return Status{failed};
}

namespace {
template <class S>
RneaBodies<S> bodies_of(DataTpl<S>& d) {
  return {d.Xup.data(), d.v.data(), d.a.data(), d.f.data()};
}
}  // namespace

template <class S>
void rnea_jvp(const ModelTpl<S>& model, RneaJvpData<S>& data, const S* q, const S* qd, const S* qdd,
              const Force<S>* fext, const S* dq, const S* dqd, const S* dqdd, S* dtau, S* tau) {
  if (model.multi_dof()) return rnea_jvp_at(model, data, q, qd, qdd, fext, dq, dqd, dqdd, dtau, tau);
  rnea_jvp_instance(model.bodies.data(), model.nv(), base_acceleration(model.gravity), q, qd, qdd, fext, dq, dqd,
                    dqdd, bodies_of(data.rnea), data.t.data(), dtau, tau);
}

template <class S>
void rnea_vjp(const ModelTpl<S>& model, RneaJvpData<S>& data, const S* q, const S* qd, const S* qdd,
              const Force<S>* fext, const S* w, S* gq, S* gqd, S* gqdd) {
  if (model.multi_dof()) return rnea_vjp_at(model, data, q, qd, qdd, fext, w, gq, gqd, gqdd);
  rnea_vjp_instance(model.bodies.data(), model.nv(), base_acceleration(model.gravity), q, qd, qdd, fext, w,
                    bodies_of(data.rnea), data.adj.data(), gq, gqd, gqdd);
}

template <class S>
AbaJvpData<S>::AbaJvpData(const ModelTpl<S>& model)
    : id(model), at_rest(model), aba(model, /*mass_matrix=*/false), zero(model.nv(), S(0)), r0(model.nv()),
      r1(model.nv()) {
  at_rest.gravity = Vec3<S>::zero();
}

namespace {
// The serial forward dynamics of aba_jvp_instance / aba_vjp_instance: the reference
// aba with fext and gravity (fd), and at rest without gravity (m_inv: M^-1 x).
template <class S>
struct SerialAba {
  const ModelTpl<S>& model;
  AbaJvpData<S>& data;
  const Force<S>* fext;
  auto fd() const {
    return [this](const S* q, const S* qd, const S* tau, const S* arm, S* qdd) -> Index {
      return aba(model, data.aba, q, qd, tau, qdd, fext, arm).failed_dof;
    };
  }
  auto m_inv() const {
    return [this](const S* q, const S* x, const S* arm, S* y) -> Index {
      return aba(data.at_rest, data.aba, q, static_cast<const S*>(data.zero.data()), x, y,
                 static_cast<const Force<S>*>(nullptr), arm)
          .failed_dof;
    };
  }
};
}  // namespace

template <class S>
Status aba_jvp(const ModelTpl<S>& model, AbaJvpData<S>& data, const S* q, const S* qd, const S* tau,
               const Force<S>* fext, const S* dq, const S* dqd, const S* dtau, S* dqdd, S* qdd, const S* armature) {
  if (model.multi_dof()) return aba_jvp_at(model, data, q, qd, tau, fext, dq, dqd, dtau, dqdd, qdd, armature);
  const SerialAba<S> f{model, data, fext};
  return Status{aba_jvp_instance(model.bodies.data(), model.nv(), base_acceleration(model.gravity), q, qd, tau, fext,
                                 dq, dqd, dtau, armature, bodies_of(data.id.rnea), data.id.t.data(), data.r0.data(),
                                 dqdd, qdd, f.fd(), f.m_inv())};
}

template <class S>
Status aba_vjp(const ModelTpl<S>& model, AbaJvpData<S>& data, const S* q, const S* qd, const S* tau,
               const Force<S>* fext, const S* w, S* gq, S* gqd, S* gtau, S* qdd, const S* armature) {
  if (model.multi_dof()) return aba_vjp_at(model, data, q, qd, tau, fext, w, gq, gqd, gtau, qdd, armature);
  const SerialAba<S> f{model, data, fext};
  return Status{aba_vjp_instance(model.bodies.data(), model.nv(), base_acceleration(model.gravity), q, qd, tau, fext,
                                 w, armature, bodies_of(data.id.rnea), data.id.adj.data(), data.r1.data(), gq, gqd,
                                 gtau, qdd, f.fd(), f.m_inv())};
}

#define SCANDYN_INSTANTIATE_DERIVATIVES(S)                                                                     \
  template void rnea_derivatives(const ModelTpl<S>&, DerivativeDataTpl<S>&, const S*, const S*, const S*,     \
                                 const Force<S>*, MatrixRef<S>, MatrixRef<S>, MatrixRef<S>, S*);               \
  template Status aba_derivatives(const ModelTpl<S>&, DerivativeDataTpl<S>&, const S*, const S*, const S*,    \
                                  const Force<S>*, S*, MatrixRef<S>, MatrixRef<S>, MatrixRef<S>, const S*);     \
  template void rnea_jvp(const ModelTpl<S>&, RneaJvpData<S>&, const S*, const S*, const S*, const Force<S>*,    \
                         const S*, const S*, const S*, S*, S*);                                        \
  template void rnea_vjp(const ModelTpl<S>&, RneaJvpData<S>&, const S*, const S*, const S*, const Force<S>*,    \
                         const S*, S*, S*, S*);                                                        \
  template struct AbaJvpData<S>;                                                                               \
  template Status aba_jvp(const ModelTpl<S>&, AbaJvpData<S>&, const S*, const S*, const S*, const Force<S>*,    \
                          const S*, const S*, const S*, S*, S*, const S*);                                     \
  template Status aba_vjp(const ModelTpl<S>&, AbaJvpData<S>&, const S*, const S*, const S*, const Force<S>*,    \
                          const S*, S*, S*, S*, S*, const S*);
SCANDYN_INSTANTIATE_DERIVATIVES(float)
SCANDYN_INSTANTIATE_DERIVATIVES(double)
#undef SCANDYN_INSTANTIATE_DERIVATIVES

}  // namespace scandyn
