// src/algorithm/second_derivatives.cpp: the second-order derivatives of inverse
// dynamics (scandyn/algorithm/second_derivatives.hpp) for float and double.
#include "scandyn/algorithm/second_derivatives.hpp"

namespace scandyn {

template <class S>
SecondDerivativeData<S>::SecondDerivativeData(const ModelTpl<S>& m)
    : work(static_cast<std::size_t>(m.nv())), wrenches(static_cast<std::size_t>(m.nv())),
      block(static_cast<std::size_t>(m.nv()) * m.nv()), plain(static_cast<std::size_t>(m.nv())),
      sums(static_cast<std::size_t>(m.nv())) {
  bodies.reserve(m.bodies.size());
  for (const Body<S>& b : m.bodies) bodies.push_back(b.template cast<Dual<S>>());
}

template <class S>
void rnea_second_derivatives(const ModelTpl<S>& model, SecondDerivativeData<S>& data, const S* q, const S* qd,
                             const S* qdd, const Force<S>* fext, S* d2tau_dq2, S* d2tau_dqd2, S* d2tau_dqdqd,
                             S* dM_dq) {
  if (model.multi_dof()) {
    rnea_second_derivatives_dual(model, data, q, qd, qdd, fext, d2tau_dq2, d2tau_dqd2, d2tau_dqdqd, dM_dq);
    return;
  }
  const Index n = model.nv();
  rnea_second_derivatives_analytic_instance(model.bodies.data(), n, base_acceleration(model.gravity), q, qd, qdd,
                                            fext, data.plain.data(), TensorRef<S>{d2tau_dq2, n, 1},
                                            TensorRef<S>{d2tau_dqd2, n, 1}, TensorRef<S>{d2tau_dqdqd, n, 1},
                                            TensorRef<S>{dM_dq, n, 1});
}

template <class S>
void rnea_second_derivatives_dual(const ModelTpl<S>& model, SecondDerivativeData<S>& data, const S* q, const S* qd,
                                  const S* qdd, const Force<S>* fext, S* d2tau_dq2, S* d2tau_dqd2, S* d2tau_dqdqd,
                                  S* dM_dq) {
  const Index n = model.nv();
  rnea_second_derivatives_instance(data.bodies.data(), n, base_acceleration(model.gravity), q, qd, qdd, fext,
                                   data.work.data(), data.wrenches.data(), TensorRef<S>{d2tau_dq2, n, 1},
                                   TensorRef<S>{d2tau_dqd2, n, 1}, TensorRef<S>{d2tau_dqdqd, n, 1},
                                   TensorRef<S>{dM_dq, n, 1});
}

template <class S>
void rnea_weighted_dq2(const ModelTpl<S>& model, SecondDerivativeData<S>& data, const S* q, const S* qd,
                       const S* qdd, const Force<S>* fext, const S* w, S* out) {
  if (model.multi_dof()) {
    rnea_weighted_dq2_dual(model, data, q, qd, qdd, fext, w, out);
    return;
  }
  const Index n = model.nv();
  rnea_weighted_dq2_analytic_instance(model.bodies.data(), n, base_acceleration(model.gravity), q, qd, qdd, fext, w,
                                      data.plain.data(), data.sums.data(), MatrixRef<S>{out, n, 1});
}

template <class S>
void rnea_weighted_dq2_dual(const ModelTpl<S>& model, SecondDerivativeData<S>& data, const S* q, const S* qd,
                            const S* qdd, const Force<S>* fext, const S* w, S* out) {
  const Index n = model.nv();
  rnea_weighted_dq2_instance(data.bodies.data(), n, base_acceleration(model.gravity), q, qd, qdd,
                             dual_wrenches(fext, n, data.wrenches.data()), w, data.work.data(),
                             MatrixRef<S>{data.block.data(), n, 1}, MatrixRef<S>{out, n, 1});
}

#define SCANDYN_INSTANTIATE(S)                                                                                    \
  template void rnea_weighted_dq2(const ModelTpl<S>&, SecondDerivativeData<S>&, const S*, const S*, const S*,      \
                                  const Force<S>*, const S*, S*);                                                  \
  template void rnea_weighted_dq2_dual(const ModelTpl<S>&, SecondDerivativeData<S>&, const S*, const S*, const S*, \
                                       const Force<S>*, const S*, S*);                                             \
  template struct SecondDerivativeData<S>;                                                                        \
  template void rnea_second_derivatives(const ModelTpl<S>&, SecondDerivativeData<S>&, const S*, const S*, const S*, \
                                        const Force<S>*, S*, S*, S*, S*);                                          \
  template void rnea_second_derivatives_dual(const ModelTpl<S>&, SecondDerivativeData<S>&, const S*, const S*,     \
                                             const S*, const Force<S>*, S*, S*, S*, S*);
SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)
#undef SCANDYN_INSTANTIATE

}  // namespace scandyn
