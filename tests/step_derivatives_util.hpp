// tests/step_derivatives_util.hpp: what the tests of the simulator's step derivatives
// (tests/sim/test_step_derivatives*.cpp) share: the simulator stepped on per-instance
// states (their truth), and the step-derivative engine's outputs
// (sim::make_step_derivatives; scandyn/sim/step_derivatives.hpp), the six blocks of B
// instances and the new state, from the engine run on per-instance states.
#pragma once

#include <gtest/gtest.h>

#include <cmath>
#include <vector>

#include "scandyn/sim/simulator.hpp"
#include "scandyn/sim/step_derivatives.hpp"

namespace scandyn::test {

// The simulator (serial) of `scene` (B = scene.instances) from per-instance states, q in
// rows of nq and qd in rows of nv, `tau_steps.size()` steps under tau_steps[t] (rows of
// nv), in place.
inline void simulate_rows(const sim::Scene& scene, std::vector<double>& q, std::vector<double>& qd,
                          const std::vector<std::vector<double>>& tau_steps) {
  sim::Simulator<double> sim(scene, BackendKind::Serial);
  const Index nq = scene.model.nq(), n = scene.nv(), B = scene.instances;
  for (Index b = 0; b < B; ++b) {
    for (Index i = 0; i < nq; ++i) sim.q().at(i, b) = q[b * nq + i];
    for (Index i = 0; i < n; ++i) sim.qd().at(i, b) = qd[b * n + i];
  }
  for (const std::vector<double>& u : tau_steps) sim.step(BatchView<const double>::aos(u.data(), n, B));
  ASSERT_TRUE(sim.status().ok()) << sim::failure_message(sim.status());
  for (Index b = 0; b < B; ++b) {
    for (Index i = 0; i < nq; ++i) q[b * nq + i] = sim.q().at(i, b);
    for (Index i = 0; i < n; ++i) qd[b * n + i] = sim.qd().at(i, b);
  }
}

// The engine's six blocks (n x n each) of B instances, read as one 2n x 3n row-major
// matrix per instance, and the new state q' (nq), qd' (n); NaN until written.
struct StepJacobians {
  StepJacobians(Index n, Index nq, Index B)
      : n(n), nq(nq), B(B), blocks(6, std::vector<double>(n * n * B, NAN)), q(nq * B, NAN), qd(n * B, NAN) {}
  Index n, nq, B;
  std::vector<std::vector<double>> blocks;
  std::vector<double> q, qd;
  sim::StepDerivativesOut<double> out() {
    auto v = [&](int k) { return BatchView<double>::aos(blocks[k].data(), n * n, B); };
    return {v(0), v(1), v(2), v(3), v(4), v(5), BatchView<double>::aos(q.data(), nq, B),
            BatchView<double>::aos(qd.data(), n, B)};
  }
  double at(Index b, Index r, Index c) const {
    const int k = (r < n ? 0 : 3) + static_cast<int>(c / n);
    return blocks[k][b * n * n + (r % n) * n + c % n];
  }
};

// The engine (backend kind, `threads` threads) of `scene` (one instance) on per-instance
// states: q (rows of nq), qd and tau (rows of nv); its status expected ok.
inline StepJacobians step_jacobians_of(const sim::Scene& scene, const std::vector<double>& q,
                                       const std::vector<double>& qd, const std::vector<double>& tau,
                                       BackendKind kind, int threads = 1) {
  const Index n = scene.nv(), nq = scene.model.nq(), B = static_cast<Index>(qd.size()) / n;
  sim::Simulator<double> base(scene, BackendKind::Serial);
  BackendOptions o;
  o.backend = kind;
  o.threads = threads;
  o.max_batch = B;
  auto engine = sim::make_step_derivatives(base.setup(), o);
  StepJacobians J(n, nq, B);
  using V = BatchView<const double>;
  const BatchStatus st =
      engine->compute({V::aos(q.data(), nq, B), V::aos(qd.data(), n, B), V::aos(tau.data(), n, B), nullptr}, J.out());
  EXPECT_TRUE(st.ok()) << st.message();
  return J;
}

}  // namespace scandyn::test
