// Rollouts and their derivatives on CUDA (scandyn/cuda/rollout_derivatives.hpp:
// the checkpointed adjoint, the forward-mode product, the rollout) against the
// serial engine (sim::RolloutDerivatives, which tests/sim/test_step_derivatives.cpp
// checks against central differences of the simulator's rollouts). T = 40 steps, B
// instances with different states and torques (B not a multiple of the block size),
// checkpoint intervals 1, the default (ceil(sqrt(T)) = 7) and T; iiwa with gravity,
// damping, springs, limits and an external wrench, and rope:20, for euler, rk4 and
// implicit. Tolerances per output array, relative to the array's largest serial
// entry: double 1e-9 (the same operations in the same order; rounding differs in the
// sines and cosines and in the kernels' fused multiply-adds), float 1e-4 (a float
// rollout of 40 steps against another float rollout of other rounding: the serial
// float adjoint is within 5e-7 of the double one on these cases). Host views
// (through sim::RolloutDerivatives on backend cuda) and device views (the _async
// calls on (T, B, nv) arrays). SCANDYN_TEST_ROLLOUT_B sets B (default 70; the
// memcheck run takes fewer). Skips without a CUDA device.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <random>
#include <string>
#include <vector>

#include "cuda_test_util.hpp"
#include "scandyn/cuda/rollout_derivatives.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

using sim::StepSequence;

struct Case {
  std::string name, json;
  double tau_scale;  // torques in [-tau_scale, tau_scale]
};

std::string scene_json(const std::string& model, const std::string& integrator, const std::string& effects,
                       double dt) {
  return "{\"model\": \"" + model + "\", \"integrator\": \"" + integrator + "\", \"dt\": " + std::to_string(dt) +
         ", \"effects\": {" + effects + "}}";
}

std::vector<Case> cases() {
  const std::string iiwa =
      "\"gravity\": true, \"damping\": 0.5, \"springs\": {\"stiffness\": 3, \"rest\": 0.1}, "
      "\"limits\": {\"stiffness\": 50, \"damping\": 2, \"lower\": -0.5, \"upper\": 0.5}, "
      "\"external\": {\"wrenches\": [{\"link\": \"iiwa_link_3\", \"wrench\": [0.1, 0.2, 0.3, 1, 2, 3]}]}";
  const std::string rope = "\"gravity\": true, \"damping\": 1e-6, \"springs\": {\"stiffness\": 1e-4}";
  std::vector<Case> c;
  for (const char* integrator : {"euler", "rk4", "implicit"}) {
    c.push_back({std::string("iiwa ") + integrator, scene_json("iiwa.urdf", integrator, iiwa, 5e-3), 2});
    c.push_back({std::string("rope:20 ") + integrator, scene_json("rope:20", integrator, rope, 1e-4), 1e-4});
  }
  return c;
}

Index batch() {
  const char* e = std::getenv("SCANDYN_TEST_ROLLOUT_B");
  return e ? std::max(1, std::atoi(e)) : 70;
}

constexpr Index kSteps = 40;

// A rollout's inputs, (T, B, nv) and (B, nv) C arrays (AoS per step), in double.
struct Problem {
  Index n, B, T;
  std::vector<double> q0, qd0, tau, gq, gqd, dq0, dqd0, dtau;
};

Problem problem(Index n, Index B, double tau_scale, unsigned seed) {
  std::mt19937_64 rng(seed);
  Problem p{n, B, kSteps, {}, {}, {}, {}, {}, {}, {}, {}};
  p.q0 = test::random_vector(rng, n * B, -0.4, 0.4);
  p.qd0 = test::random_vector(rng, n * B, -0.5, 0.5);
  p.tau = test::random_vector(rng, kSteps * B * n, -tau_scale, tau_scale);
  p.gq = test::random_vector(rng, kSteps * B * n, -1, 1);
  p.gqd = test::random_vector(rng, kSteps * B * n, -0.1, 0.1);
  p.dq0 = test::random_vector(rng, n * B, -1, 1);
  p.dqd0 = test::random_vector(rng, n * B, -1, 1);
  p.dtau = test::random_vector(rng, kSteps * B * n, -tau_scale, tau_scale);
  return p;
}

// The results of one engine: the adjoint's (gq0, gqd0, gtau), the tangents (dq, dqd)
// and the states (q, qd), in the problem's layouts.
template <class S>
struct Results {
  std::vector<S> gq0, gqd0, gtau, dq, dqd, q, qd;
};

template <class S>
std::vector<S> as(const std::vector<double>& v) {
  return std::vector<S>(v.begin(), v.end());
}

// Every result through sim::RolloutDerivatives (host views) on `kind`.
template <class S>
Results<S> host_results(const sim::SimSetup<S>& setup, const Problem& p, BackendKind kind, Index interval) {
  BackendOptions o;
  o.backend = kind;
  sim::RolloutDerivatives<S> rd(setup, o, interval);
  const Index n = p.n, B = p.B, T = p.T;
  const std::vector<S> q0 = as<S>(p.q0), qd0 = as<S>(p.qd0), tau = as<S>(p.tau), gq = as<S>(p.gq),
                       gqd = as<S>(p.gqd), dq0 = as<S>(p.dq0), dqd0 = as<S>(p.dqd0), dtau = as<S>(p.dtau);
  using CV = BatchView<const S>;
  auto view = [&](const std::vector<S>& v) { return CV::aos(v.data(), n, B); };
  auto seq = [&](const std::vector<S>& v) { return StepSequence<const S>{CV::aos(v.data(), n, B), B * n, T}; };
  auto out = [&](std::vector<S>& v) { return StepSequence<S>{BatchView<S>::aos(v.data(), n, B), B * n, T}; };
  Results<S> r;
  for (std::vector<S>* v : {&r.gq0, &r.gqd0}) v->assign(static_cast<std::size_t>(n * B), S(NAN));
  for (std::vector<S>* v : {&r.gtau, &r.dq, &r.dqd, &r.q, &r.qd}) v->assign(static_cast<std::size_t>(T * B * n), S(NAN));
  BatchStatus st = rd.vjp(view(q0), view(qd0), seq(tau), seq(gq), seq(gqd), BatchView<S>::aos(r.gq0.data(), n, B),
                          BatchView<S>::aos(r.gqd0.data(), n, B), out(r.gtau));
  EXPECT_TRUE(st.ok()) << "vjp on " << to_string(kind) << ": " << st.message();
  st = rd.jvp(view(q0), view(qd0), seq(tau), view(dq0), view(dqd0), seq(dtau), out(r.dq), out(r.dqd));
  EXPECT_TRUE(st.ok()) << "jvp on " << to_string(kind) << ": " << st.message();
  st = rd.rollout(view(q0), view(qd0), seq(tau), out(r.q), out(r.qd));
  EXPECT_TRUE(st.ok()) << "rollout on " << to_string(kind) << ": " << st.message();
  return r;
}

// max |a - b| <= tol * max |b| (NaN in a fails)
template <class S>
void expect_close(const std::vector<S>& a, const std::vector<S>& b, double tol, const char* what) {
  ASSERT_EQ(a.size(), b.size()) << what;
  double err = 0, scale = 0;
  std::size_t worst = 0;
  for (std::size_t e = 0; e < a.size(); ++e) {
    const double d = std::abs(double(a[e]) - double(b[e]));
    if (!(d <= err)) err = d, worst = e;  // (NaN is kept)
    scale = std::max(scale, std::abs(double(b[e])));
  }
  EXPECT_LE(err, tol * scale) << what << ": worst entry " << worst << " (" << double(a[worst]) << " against "
                              << double(b[worst]) << "), scale " << scale;
}

template <class S>
void compare_host(const Case& c, double tol) {
  SCOPED_TRACE(c.name + (sizeof(S) == 4 ? " float" : " double"));
  sim::Scene scene = sim::parse_scene(c.json, "t.json");
  scene.instances = 1;
  sim::Simulator<S> sim(scene, BackendKind::Serial);
  const Problem p = problem(scene.nv(), batch(), c.tau_scale, 17);
  for (Index interval : {Index(1), Index(0), kSteps}) {
    SCOPED_TRACE("checkpoint interval " + std::to_string(interval));
    const Results<S> ref = host_results(sim.setup(), p, BackendKind::Serial, interval);
    const Results<S> gpu = host_results(sim.setup(), p, BackendKind::Cuda, interval);
    expect_close(gpu.gq0, ref.gq0, tol, "gq0");
    expect_close(gpu.gqd0, ref.gqd0, tol, "gqd0");
    expect_close(gpu.gtau, ref.gtau, tol, "gtau");
    if (interval != 0) continue;  // (the interval only changes the adjoint)
    expect_close(gpu.dq, ref.dq, tol, "dq");
    expect_close(gpu.dqd, ref.dqd, tol, "dqd");
    expect_close(gpu.q, ref.q, tol, "q");
    expect_close(gpu.qd, ref.qd, tol, "qd");
  }
}

TEST(CudaRolloutDerivatives, HostViewsEqualTheSerialEngine) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (const Case& c : cases()) {
    compare_host<double>(c, 1e-9);
    compare_host<float>(c, 1e-4);
  }
}

// The _async calls on device memory: (T, B, nv) arrays as PyTorch's contiguous
// tensors, the loss's gradient on qd not given (zero), against the serial engine.
template <class S>
void compare_device(const Case& c, double tol) {
  SCOPED_TRACE(c.name + (sizeof(S) == 4 ? " float" : " double"));
  sim::Scene scene = sim::parse_scene(c.json, "t.json");
  scene.instances = 1;
  sim::Simulator<S> sim(scene, BackendKind::Serial);
  const Index n = scene.nv(), B = batch(), T = kSteps;
  const Problem p = problem(n, B, c.tau_scale, 29);
  const std::vector<S> q0 = as<S>(p.q0), qd0 = as<S>(p.qd0), tau = as<S>(p.tau), gq = as<S>(p.gq);
  using CV = BatchView<const S>;
  // the serial truth
  sim::RolloutDerivatives<S> serial(sim.setup(), BackendOptions{});
  std::vector<S> gq0(n * B), gqd0(n * B), gtau(T * B * n);
  ASSERT_TRUE(serial
                  .vjp(CV::aos(q0.data(), n, B), CV::aos(qd0.data(), n, B), {CV::aos(tau.data(), n, B), B * n, T},
                       {CV::aos(gq.data(), n, B), B * n, T}, {}, BatchView<S>::aos(gq0.data(), n, B),
                       BatchView<S>::aos(gqd0.data(), n, B), {BatchView<S>::aos(gtau.data(), n, B), B * n, T})
                  .ok());
  // the device: inputs, outputs (NaN first), failed DoFs
  cuda::CudaRolloutDerivatives<S> engine(sim.setup(), BackendOptions{});
  const std::size_t state = static_cast<std::size_t>(n) * B, seq = state * T;
  test::DeviceArray<S> d;
  test::DeviceArray<int> dfailed;
  ASSERT_EQ(d.alloc(4 * state + 3 * seq), cudaSuccess);
  ASSERT_EQ(dfailed.alloc(B), cudaSuccess);
  S *dq0 = d.ptr, *dqd0 = dq0 + state, *dtau = dqd0 + state, *dgq = dtau + seq, *dgq0 = dgq + seq,
    *dgqd0 = dgq0 + state, *dgtau = dgqd0 + state;
  const std::vector<S> nan(2 * state + seq, S(NAN));
  ASSERT_EQ(cudaMemcpy(dq0, q0.data(), state * sizeof(S), cudaMemcpyHostToDevice), cudaSuccess);
  ASSERT_EQ(cudaMemcpy(dqd0, qd0.data(), state * sizeof(S), cudaMemcpyHostToDevice), cudaSuccess);
  ASSERT_EQ(cudaMemcpy(dtau, tau.data(), seq * sizeof(S), cudaMemcpyHostToDevice), cudaSuccess);
  ASSERT_EQ(cudaMemcpy(dgq, gq.data(), seq * sizeof(S), cudaMemcpyHostToDevice), cudaSuccess);
  ASSERT_EQ(cudaMemcpy(dgq0, nan.data(), nan.size() * sizeof(S), cudaMemcpyHostToDevice), cudaSuccess);
  ASSERT_EQ(engine.vjp_async(CV::aos(dq0, n, B), CV::aos(dqd0, n, B), {CV::aos(dtau, n, B), B * n, T},
                             {CV::aos(dgq, n, B), B * n, T}, {}, BatchView<S>::aos(dgq0, n, B),
                             BatchView<S>::aos(dgqd0, n, B), {BatchView<S>::aos(dgtau, n, B), B * n, T}, dfailed.ptr,
                             nullptr),
            cudaSuccess);
  ASSERT_EQ(cudaDeviceSynchronize(), cudaSuccess);
  std::vector<S> out(2 * state + seq);
  std::vector<int> failed(B);
  ASSERT_EQ(cudaMemcpy(out.data(), dgq0, out.size() * sizeof(S), cudaMemcpyDeviceToHost), cudaSuccess);
  ASSERT_EQ(cudaMemcpy(failed.data(), dfailed.ptr, B * sizeof(int), cudaMemcpyDeviceToHost), cudaSuccess);
  EXPECT_EQ(std::count(failed.begin(), failed.end(), -1), B);
  expect_close(std::vector<S>(out.begin(), out.begin() + state), gq0, tol, "gq0");
  expect_close(std::vector<S>(out.begin() + state, out.begin() + 2 * state), gqd0, tol, "gqd0");
  expect_close(std::vector<S>(out.begin() + 2 * state, out.end()), gtau, tol, "gtau");
  // the store: (ceil(T / K) + K) states of 2 nv scalars per instance
  const Index K = engine.checkpoint_interval(T);
  EXPECT_EQ(K, 7);
  EXPECT_EQ(engine.store_bytes(T, B), static_cast<std::size_t>((T + K - 1) / K + K) * 2 * n * B * sizeof(S));
}

TEST(CudaRolloutDerivatives, DeviceViewsEqualTheSerialEngine) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const std::vector<Case> c = cases();
  for (const Case& k : {c[0], c[3]}) {  // iiwa euler, rope:20 rk4
    compare_device<double>(k, 1e-9);
    compare_device<float>(k, 1e-4);
  }
}

TEST(CudaRolloutDerivatives, ANonFiniteResultIsAFailure) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Case c = cases()[0];
  sim::Scene scene = sim::parse_scene(c.json, "t.json");
  scene.instances = 1;
  sim::Simulator<double> sim(scene, BackendKind::Serial);
  const Index n = scene.nv(), B = 3, T = 4;
  std::vector<double> q0(n * B, 0.1), qd0(n * B, 0.2), tau(T * B * n, 1.0), g(T * B * n, 1.0), gq0(n * B),
      gqd0(n * B), gtau(T * B * n);
  tau[((T - 1) * B + 1) * n + 3] = NAN;  // the last step, instance 1: its qdd, then the adjoints, not finite
  using CV = BatchView<const double>;
  for (BackendKind kind : {BackendKind::Serial, BackendKind::Cuda}) {
    SCOPED_TRACE(to_string(kind));
    BackendOptions o;
    o.backend = kind;
    sim::RolloutDerivatives<double> rd(sim.setup(), o);
    const BatchStatus st =
        rd.vjp(CV::aos(q0.data(), n, B), CV::aos(qd0.data(), n, B), {CV::aos(tau.data(), n, B), B * n, T},
               {CV::aos(g.data(), n, B), B * n, T}, {}, BatchView<double>::aos(gq0.data(), n, B),
               BatchView<double>::aos(gqd0.data(), n, B), {BatchView<double>::aos(gtau.data(), n, B), B * n, T});
    EXPECT_EQ(st.failed, 1);
    EXPECT_EQ(st.first_instance, 1);
    EXPECT_EQ(st.failure, Failure::NonFinite);
  }
}

TEST(CudaRolloutDerivatives, RefusesModelsBeyondTheThreadCapacityAndBadViews) {
  SKIP_WITHOUT_CUDA_DEVICE();
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  {
    sim::Simulator<double> big(
        sim::parse_scene(R"({"model": "rope:65", "dt": 1e-5, "effects": {"gravity": true}})", "t.json"),
        BackendKind::Serial);
    try {
      sim::RolloutDerivatives<double> rd(big.setup(), o);
      ADD_FAILURE() << "no BackendError";
    } catch (const BackendError& e) {
      EXPECT_NE(std::string(e.what()).find("65 DoF"), std::string::npos) << e.what();
    }
  }
  sim::Simulator<double> sim(sim::parse_scene(cases()[0].json, "t.json"), BackendKind::Serial);
  cuda::CudaRolloutDerivatives<double> engine(sim.setup(), o);
  const Index n = sim.setup().model.nv();
  std::vector<double> x(n * 4);
  using CV = BatchView<const double>;
  try {  // tau of 2 instances for a batch of 4
    engine.rollout_async(CV::aos(x.data(), n, 4), CV::aos(x.data(), n, 4), {CV::aos(x.data(), n, 2), n * 2, 2}, {},
                         {}, nullptr, nullptr);
    ADD_FAILURE() << "no BackendError";
  } catch (const BackendError& e) {
    EXPECT_NE(std::string(e.what()).find("tau"), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace scandyn
