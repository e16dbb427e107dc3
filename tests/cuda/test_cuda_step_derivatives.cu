// The simulator step's Jacobian on CUDA (scandyn/cuda/step_derivatives.hpp) against
// the serial engine (scandyn/sim/step_derivatives.hpp), which the CPU tests check
// against central differences of the simulator's step. Tolerances per block,
// relative to the block's largest entry: double 1e-9, float 1e-3. Skips without a
// CUDA device.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>
#include <string>
#include <vector>

#include "cuda_test_util.hpp"
#include "scandyn/cuda/step_derivatives.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

template <class S>
std::vector<std::vector<S>> jacobians(const sim::SimSetup<S>& setup, BackendKind kind, const std::vector<S>& q,
                                      const std::vector<S>& qd, const std::vector<S>& tau, Index B) {
  const Index n = setup.model.nv();
  BackendOptions o;
  o.backend = kind;
  o.max_batch = B;
  auto engine = sim::make_step_derivatives(setup, o);
  std::vector<std::vector<S>> blocks(8, std::vector<S>(static_cast<std::size_t>(n) * n * B, S(NAN)));
  auto v = [&](int k) { return BatchView<S>::soa(blocks[k].data(), n * n, B); };
  using V = BatchView<const S>;
  const BatchStatus st = engine->compute(
      {V::aos(q.data(), n, B), V::aos(qd.data(), n, B), V::aos(tau.data(), n, B)},
      {v(0), v(1), v(2), v(3), v(4), v(5), BatchView<S>::aos(blocks[6].data(), n, B), BatchView<S>::aos(blocks[7].data(), n, B)});
  EXPECT_TRUE(st.ok()) << st.message();
  return blocks;
}

template <class S>
void compare(const char* json, double tau_scale, double tol) {
  SCOPED_TRACE(json);
  sim::Scene scene = sim::parse_scene(json, "t.json");
  scene.instances = 1;
  sim::Simulator<S> sim(scene, BackendKind::Serial);
  const Index n = scene.nv(), B = 300;
  std::mt19937_64 rng(3);
  std::vector<S> q, qd, tau;
  for (double x : test::random_vector(rng, n * B, -1, 1)) q.push_back(S(x));
  for (double x : test::random_vector(rng, n * B, -1, 1)) qd.push_back(S(x));
  for (double x : test::random_vector(rng, n * B, -tau_scale, tau_scale)) tau.push_back(S(x));
  const auto ref = jacobians(sim.setup(), BackendKind::Serial, q, qd, tau, B);
  const auto gpu = jacobians(sim.setup(), BackendKind::Cuda, q, qd, tau, B);
  for (int k = 0; k < 8; ++k) {
    double err = 0, scale = 0;
    for (std::size_t e = 0; e < ref[k].size(); ++e) {
      err = std::max(err, std::abs(double(gpu[k][e]) - double(ref[k][e])));
      scale = std::max(scale, std::abs(double(ref[k][e])));
    }
    EXPECT_LE(err, tol * scale) << "block " << k << " (6, 7: the new state)";
  }
}

const char* kScenes[] = {
    R"({"model": "iiwa.urdf", "dt": 5e-3, "integrator": "euler", "effects": {"gravity": true, "damping": 0.5,
        "springs": {"stiffness": 3}, "limits": {"stiffness": 50, "lower": -0.5, "upper": 0.5},
        "external": {"wrenches": [{"link": "iiwa_link_3", "wrench": [0.1, 0.2, 0.3, 1, 2, 3]}]}}})",
    R"({"model": "iiwa.urdf", "dt": 5e-3, "integrator": "rk4", "effects": {"gravity": true, "damping": 0.5}})",
    R"({"model": "iiwa.urdf", "dt": 5e-3, "integrator": "implicit", "effects": {"gravity": true, "damping": 0.5,
        "springs": {"stiffness": 3}}})",
    R"({"model": "hyq.urdf", "dt": 1e-3, "integrator": "rk4", "effects": {"gravity": true}})",
};

TEST(CudaStepDerivatives, EqualsTheSerialEngine) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (const char* json : kScenes) {
    compare<double>(json, 5, 1e-9);
    compare<float>(json, 5, 1e-3);
  }
}

TEST(CudaStepDerivatives, ANonFiniteResultIsAFailure) {
  SKIP_WITHOUT_CUDA_DEVICE();
  sim::Scene scene = sim::parse_scene(kScenes[0], "t.json");
  scene.instances = 1;
  sim::Simulator<double> sim(scene, BackendKind::Serial);
  const Index n = scene.nv(), B = 3;
  std::vector<double> q(n * B, 0.1), qd(n * B, 0.2), tau(n * B, 1.0), blocks(6 * n * n * B);
  tau[1 * n + 2] = NAN;
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  auto v = [&](int k) { return BatchView<double>::aos(blocks.data() + k * n * n * B, n * n, B); };
  using V = BatchView<const double>;
  const BatchStatus st = sim::make_step_derivatives(sim.setup(), o)->compute(
      {V::aos(q.data(), n, B), V::aos(qd.data(), n, B), V::aos(tau.data(), n, B)}, {v(0), v(1), v(2), v(3), v(4), v(5), {}, {}});
  EXPECT_EQ(st.failed, 1);
  EXPECT_EQ(st.first_instance, 1);
  EXPECT_EQ(st.failure, Failure::NonFinite);
}

TEST(CudaStepDerivatives, RefusesModelsBeyondTheThreadCapacity) {
  SKIP_WITHOUT_CUDA_DEVICE();
  sim::Simulator<double> sim(sim::parse_scene(R"({"model": "rope:65", "dt": 1e-5, "effects": {"gravity": true}})", "t.json"),
                             BackendKind::Serial);
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  try {
    sim::make_step_derivatives(sim.setup(), o);
    FAIL() << "no BackendError";
  } catch (const BackendError& e) {
    EXPECT_NE(std::string(e.what()).find("65 DoF"), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace scandyn
