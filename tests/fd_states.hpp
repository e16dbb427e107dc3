// tests/fd_states.hpp: random forward-dynamics states for the run-time check's tests
// (tests/engine/test_fd_check.cpp, tests/cuda/test_cuda_fd_check.cu).
#pragma once

#include <random>
#include <vector>

#include "scandyn/model/model.hpp"

namespace scandyn::test {

// B random states (nv x B, soa), every value exact in float: state k of kind k mod 4 as
// in bench/fd_residual_study.cpp: 0 q, qd, tau in [-1, 1] (q in [-qr, qr]); 1 tau = 0;
// 2 qd = tau = 0 (released from rest); 3 qd in [-3, 3], tau in [-10, 10].
struct FdStates {
  Index nv, B;
  std::vector<double> q, qd, tau;
  FdStates(Index nv_, Index B_, double qr, unsigned seed) : nv(nv_), B(B_) {
    const std::size_t n = static_cast<std::size_t>(nv * B);
    q.resize(n), qd.resize(n), tau.resize(n);
    std::mt19937_64 g(seed);
    std::uniform_real_distribution<double> U(-1, 1);
    for (Index b = 0; b < B; ++b) {
      const int kind = static_cast<int>(b % 4);
      for (Index i = 0; i < nv; ++i) {
        const std::size_t e = static_cast<std::size_t>(i * B + b);
        q[e] = float(qr * U(g));
        qd[e] = kind == 2 ? 0.f : float((kind == 3 ? 3.0 : 1.0) * U(g));
        tau[e] = kind == 1 || kind == 2 ? 0.f : float((kind == 3 ? 10.0 : 1.0) * U(g));
      }
    }
  }
  template <class S>
  std::vector<S> as(const std::vector<double>& v) const {
    return std::vector<S>(v.begin(), v.end());
  }
};

}  // namespace scandyn::test
