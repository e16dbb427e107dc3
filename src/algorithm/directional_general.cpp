// src/algorithm/directional_general.cpp: the general path of the serial directional
// derivatives (scandyn/algorithm/directional_derivatives.hpp), for models with
// multi-DoF joints (a floating base, spherical joints): rnea_jvp_at, rnea_vjp_at,
// aba_jvp_at, aba_vjp_at, to which rnea_jvp, rnea_vjp, aba_jvp and aba_vjp dispatch:
// the one-instance recursions of scandyn/instance/directional_general_instance.hpp over
// the scratch of RneaJvpData / AbaJvpData. A translation unit of its own, as the
// reference's general path (reference_general.cpp), so that the 1-DoF functions of
// derivatives.cpp are compiled as before.
#include "reference_general_impl.hpp"
#include "scandyn/algorithm/directional_derivatives.hpp"
#include "scandyn/instance/directional_general_instance.hpp"

namespace scandyn {

template <class S>
void rnea_jvp_at(const ModelTpl<S>& model, RneaJvpData<S>& data, const S* q, const S* qd, const S* qdd,
                 const Force<S>* fext, const S* dq, const S* dqd, const S* dqdd, S* dtau, S* tau) {
  rnea_jvp_general_instance(model.bodies.data(), model.nbodies(), base_acceleration(model.gravity), q, qd, qdd, fext,
                            dq, dqd, dqdd, general_work(data.rnea), data.t.data(), dtau, tau);
}

template <class S>
void rnea_vjp_at(const ModelTpl<S>& model, RneaJvpData<S>& data, const S* q, const S* qd, const S* qdd,
                 const Force<S>* fext, const S* w, S* gq, S* gqd, S* gqdd) {
  rnea_vjp_general_instance(model.bodies.data(), model.nbodies(), base_acceleration(model.gravity), q, qd, qdd, fext,
                            w, general_work(data.rnea), data.adj.data(), gq, gqd, gqdd);
}

namespace {
// The forward dynamics of aba_jvp_at / aba_vjp_at: the reference's general ABA with
// fext and gravity (fd), and at rest without gravity (m_inv: M^-1 x), in data.aba.
template <class S>
struct GeneralAba {
  const ModelTpl<S>& model;
  AbaJvpData<S>& data;
  const Force<S>* fext;
  auto fd() const {
    return [this](const S* q, const S* qd, const S* tau, const S* arm, S* qdd) -> Index {
      return aba_at(model, data.aba, q, qd, tau, qdd, fext, arm).failed_dof;
    };
  }
  auto m_inv() const {
    return [this](const S* q, const S* x, const S* arm, S* y) -> Index {
      return aba_at(data.at_rest, data.aba, q, static_cast<const S*>(data.zero.data()), x, y,
                    static_cast<const Force<S>*>(nullptr), arm)
          .failed_dof;
    };
  }
};
}  // namespace

template <class S>
Status aba_jvp_at(const ModelTpl<S>& model, AbaJvpData<S>& data, const S* q, const S* qd, const S* tau,
                  const Force<S>* fext, const S* dq, const S* dqd, const S* dtau, S* dqdd, S* qdd,
                  const S* armature) {
  const GeneralAba<S> f{model, data, fext};
  return Status{aba_jvp_general_instance(model.bodies.data(), model.nbodies(), model.nv(),
                                         base_acceleration(model.gravity), q, qd, tau, fext, dq, dqd, dtau, armature,
                                         general_work(data.id.rnea), data.id.t.data(), data.r0.data(), dqdd, qdd,
                                         f.fd(), f.m_inv())};
}

template <class S>
Status aba_vjp_at(const ModelTpl<S>& model, AbaJvpData<S>& data, const S* q, const S* qd, const S* tau,
                  const Force<S>* fext, const S* w, S* gq, S* gqd, S* gtau, S* qdd, const S* armature) {
  const GeneralAba<S> f{model, data, fext};
  return Status{aba_vjp_general_instance(model.bodies.data(), model.nbodies(), model.nv(),
                                         base_acceleration(model.gravity), q, qd, tau, fext, w, armature,
                                         general_work(data.id.rnea), data.id.adj.data(), data.r1.data(), gq, gqd,
                                         gtau, qdd, f.fd(), f.m_inv())};
}

#define SCANDYN_INSTANTIATE_DIRECTIONAL_GENERAL(S)                                                               \
  template void rnea_jvp_at(const ModelTpl<S>&, RneaJvpData<S>&, const S*, const S*, const S*, const Force<S>*,  \
                            const S*, const S*, const S*, S*, S*);                                               \
  template void rnea_vjp_at(const ModelTpl<S>&, RneaJvpData<S>&, const S*, const S*, const S*, const Force<S>*,  \
                            const S*, S*, S*, S*);                                                               \
  template Status aba_jvp_at(const ModelTpl<S>&, AbaJvpData<S>&, const S*, const S*, const S*, const Force<S>*,  \
                             const S*, const S*, const S*, S*, S*, const S*);                                    \
  template Status aba_vjp_at(const ModelTpl<S>&, AbaJvpData<S>&, const S*, const S*, const S*, const Force<S>*,  \
                             const S*, S*, S*, S*, S*, const S*);
SCANDYN_INSTANTIATE_DIRECTIONAL_GENERAL(float)
SCANDYN_INSTANTIATE_DIRECTIONAL_GENERAL(double)
#undef SCANDYN_INSTANTIATE_DIRECTIONAL_GENERAL

}  // namespace scandyn
