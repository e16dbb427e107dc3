// src/algorithm/second_derivatives.cpp: the second-order derivatives of inverse
// dynamics (scandyn/algorithm/second_derivatives.hpp) for float and double.
#include "scandyn/algorithm/second_derivatives.hpp"

namespace scandyn {

template <class S>
SecondDerivativeData<S>::SecondDerivativeData(const ModelTpl<S>& m)
    : model(m.template cast<Dual<S>>()), work(static_cast<std::size_t>(m.nv())), q(m.nv()), qd(m.nv()), qdd(m.nv()),
      a(static_cast<std::size_t>(m.nv()) * m.nv()), b(a.size()), m(a.size()) {}

namespace {

// The body wrenches in dual numbers (none without fext).
template <class S>
std::vector<Force<Dual<S>>> dual_wrenches(const Force<S>* fext, Index n) {
  std::vector<Force<Dual<S>>> wrenches;
  if (fext)
    for (Index i = 0; i < n; ++i) wrenches.push_back(fext[i].template cast<Dual<S>>());
  return wrenches;
}

// One pass of the first-order recursion in dual numbers with q (seed 0) or qd (seed 1)
// seeded along e_k: the eps parts of data.a, data.b, data.m are then the derivatives
// along it of dtau/dq, dtau/dqd and M.
template <class S>
void seeded_pass(SecondDerivativeData<S>& data, Index n, const S* q, const S* qd, const S* qdd,
                 const std::vector<Force<Dual<S>>>& wrenches, int seed, Index k) {
  using D = Dual<S>;
  for (Index i = 0; i < n; ++i) {
    data.q[i] = D(q[i], seed == 0 && i == k ? S(1) : S(0));
    data.qd[i] = D(qd[i], seed == 1 && i == k ? S(1) : S(0));
    data.qdd[i] = D(qdd[i]);
  }
  rnea_derivatives_instance(data.model.bodies.data(), n, base_acceleration(data.model.gravity), data.q.data(),
                            data.qd.data(), data.qdd.data(), wrenches.empty() ? nullptr : wrenches.data(),
                            data.work.data(), MatrixRef<D>{data.a.data(), n, 1}, MatrixRef<D>{data.b.data(), n, 1},
                            MatrixRef<D>{data.m.data(), n, 1}, nullptr);
}

}  // namespace

template <class S>
void rnea_second_derivatives(const ModelTpl<S>& model, SecondDerivativeData<S>& data, const S* q, const S* qd,
                             const S* qdd, const Force<S>* fext, S* d2tau_dq2, S* d2tau_dqd2, S* d2tau_dqdqd,
                             S* dM_dq) {
  const Index n = model.nv();
  const std::vector<Force<Dual<S>>> wrenches = dual_wrenches(fext, n);
  const std::size_t nn = static_cast<std::size_t>(n);
  auto at = [&](Index i, Index j, Index k) { return (static_cast<std::size_t>(i) * nn + j) * nn + k; };
  // pass k of variable `seed` (0: q, 1: qd): the eps parts of the first-order blocks
  for (int seed = 0; seed < 2; ++seed)
    for (Index k = 0; k < n; ++k) {
      seeded_pass(data, n, q, qd, qdd, wrenches, seed, k);
      for (Index i = 0; i < n; ++i)
        for (Index j = 0; j < n; ++j) {
          const std::size_t e = static_cast<std::size_t>(i) * nn + j;
          if (seed == 0) {
            d2tau_dq2[at(i, j, k)] = data.a[e].d;  // d/dq_k of dtau_i/dq_j
            if (dM_dq) dM_dq[at(i, j, k)] = data.m[e].d;
          } else {
            d2tau_dqd2[at(i, j, k)] = data.b[e].d;   // d/dqd_k of dtau_i/dqd_j
            d2tau_dqdqd[at(i, j, k)] = data.a[e].d;  // d/dqd_k of dtau_i/dq_j
          }
        }
    }
}

template <class S>
void rnea_weighted_dq2(const ModelTpl<S>& model, SecondDerivativeData<S>& data, const S* q, const S* qd,
                       const S* qdd, const Force<S>* fext, const S* w, S* out) {
  const Index n = model.nv();
  const std::vector<Force<Dual<S>>> wrenches = dual_wrenches(fext, n);
  for (Index k = 0; k < n; ++k) {
    seeded_pass(data, n, q, qd, qdd, wrenches, 0, k);
    for (Index j = 0; j < n; ++j) {  // sum_i w_i d/dq_k of dtau_i/dq_j
      S s = S(0);
      for (Index i = 0; i < n; ++i) s += w[i] * data.a[static_cast<std::size_t>(i) * n + j].d;
      out[static_cast<std::size_t>(j) * n + k] = s;
    }
  }
}

#define SCANDYN_INSTANTIATE(S)                                                                                    \
  template void rnea_weighted_dq2(const ModelTpl<S>&, SecondDerivativeData<S>&, const S*, const S*, const S*,      \
                                  const Force<S>*, const S*, S*);                                                  \
  template struct SecondDerivativeData<S>;                                                                        \
  template void rnea_second_derivatives(const ModelTpl<S>&, SecondDerivativeData<S>&, const S*, const S*, const S*, \
                                        const Force<S>*, S*, S*, S*, S*);
SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)
#undef SCANDYN_INSTANTIATE

}  // namespace scandyn
