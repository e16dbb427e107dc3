// tests/second_order_tensors.hpp: the outputs of the second-order derivative engines
// (make_id_second_derivatives; IdSecondDerivativesOut in scandyn/engine.hpp) for the
// tests: the four tensors of B instances in one layout.
#pragma once

#include <cmath>
#include <cstddef>
#include <vector>

#include "scandyn/engine.hpp"

namespace scandyn::test {

// The four tensors of B instances, nv^3 entries each, in one layout (soa or aos); NaN
// until written.
template <class S>
struct SecondOrderTensors {
  Index n3, B;
  bool soa;
  std::vector<S> data;
  SecondOrderTensors(Index nv, Index B_, bool soa_)
      : n3(nv * nv * nv), B(B_), soa(soa_), data(4 * static_cast<std::size_t>(n3) * B_, S(NAN)) {}
  BatchView<S> view(int t) {
    S* p = data.data() + static_cast<std::size_t>(t) * n3 * B;
    return soa ? BatchView<S>::soa(p, n3, B) : BatchView<S>::aos(p, n3, B);
  }
  IdSecondDerivativesOut<S> out() { return {view(0), view(1), view(2), view(3)}; }
  // entry e of tensor t of instance b
  S at(int t, Index e, Index b) { return view(t).at(e, b); }
};

}  // namespace scandyn::test
