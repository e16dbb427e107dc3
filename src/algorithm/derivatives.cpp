// src/algorithm/derivatives.cpp: the serial reference derivatives
// (scandyn/algorithm/derivatives.hpp) for float and double.
#include "scandyn/algorithm/derivatives.hpp"

namespace scandyn {

template <class S>
void rnea_derivatives(const ModelTpl<S>& model, DerivativeDataTpl<S>& data, const S* q, const S* qd,
                      const S* qdd, const Force<S>* fext, MatrixRef<S> dtau_dq, MatrixRef<S> dtau_dqd,
                      MatrixRef<S> M, S* tau) {
  const Motion<S> a0 = base_acceleration(model.gravity);
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
                       MatrixRef<S> dqdd_dtau) {
  const Status st = aba(model, data.aba, q, qd, tau, qdd, fext);
  if (!st.ok()) return st;
  const Index failed = fd_derivatives_instance(model.bodies.data(), model.nv(), base_acceleration(model.gravity), q,
                                               qd, static_cast<const S*>(qdd), fext, data.work.data(), dqdd_dq,
                                               dqdd_dqd, dqdd_dtau);
  return Status{failed};
}

#define SCANDYN_INSTANTIATE_DERIVATIVES(S)                                                                     \
  template void rnea_derivatives(const ModelTpl<S>&, DerivativeDataTpl<S>&, const S*, const S*, const S*,     \
                                 const Force<S>*, MatrixRef<S>, MatrixRef<S>, MatrixRef<S>, S*);               \
  template Status aba_derivatives(const ModelTpl<S>&, DerivativeDataTpl<S>&, const S*, const S*, const S*,    \
                                  const Force<S>*, S*, MatrixRef<S>, MatrixRef<S>, MatrixRef<S>);
SCANDYN_INSTANTIATE_DERIVATIVES(float)
SCANDYN_INSTANTIATE_DERIVATIVES(double)
#undef SCANDYN_INSTANTIATE_DERIVATIVES

}  // namespace scandyn
