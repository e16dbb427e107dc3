// The derivatives of the simulator's step (scandyn/sim/step_derivatives.hpp) and of
// whole rollouts. Truths: central finite differences of the Simulator's own step and
// rollouts (the serial backend, double); the identity <vjp(g), v> = <g, jvp(v)>;
// the dense Jacobian against the directional derivatives; OpenMP equal to serial.
// Tolerances (double): the Jacobian 1e-6 relative per block against central
// differences (steps 1e-6 for q and qd, 1e-2 N m for tau, where the step is linear
// to 1e-10); the rollout gradient 1e-6 relative; the exact identities 1e-10.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>
#include <string>
#include <vector>

#include "scandyn/build_config.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"
#include "scandyn/sim/step_derivatives.hpp"
#include "step_derivatives_util.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

using sim::Scene;
using sim::Simulator;
using sim::StepSequence;

struct Case {
  std::string name;
  std::string json;
  double tau_scale = 5;  // torques drawn in [-tau_scale, tau_scale] (N m)
};

std::string scene_json(const std::string& model, const std::string& integrator, const std::string& effects,
                       double dt) {
  return "{\"model\": \"" + model + "\", \"integrator\": \"" + integrator + "\", \"dt\": " + std::to_string(dt) +
         ", \"effects\": {" + effects + "}}";
}

const char* kRopeEffects = "\"gravity\": true, \"damping\": 1e-6, \"springs\": {\"stiffness\": 1e-4}";
const char* kIiwaEffects =
    "\"gravity\": true, \"damping\": 0.5, \"springs\": {\"stiffness\": 3, \"rest\": 0.1}, "
    "\"limits\": {\"stiffness\": 50, \"damping\": 2, \"lower\": -0.5, \"upper\": 0.5}, "
    "\"external\": {\"wrenches\": [{\"link\": \"iiwa_link_3\", \"wrench\": [0.1, 0.2, 0.3, 1, 2, 3]}]}";

std::vector<Case> cases() {
  std::vector<Case> c;
  for (const char* integrator : {"euler", "rk4", "implicit"}) {
    c.push_back({std::string("iiwa ") + integrator, scene_json("iiwa.urdf", integrator, kIiwaEffects, 5e-3)});
    // a rope of 1 cm, 10 g links: 1e-4 s steps, torques of the order of the links' weights
    c.push_back({std::string("rope:20 ") + integrator,
                 scene_json("rope:20", integrator, kRopeEffects, 1e-4), 1e-4});
  }
  c.push_back({"iiwa euler, gravity only", scene_json("iiwa.urdf", "euler", "\"gravity\": true", 5e-3)});
  return c;
}

Scene scene_of(const Case& c, Index B) {
  Scene s = sim::parse_scene(c.json, c.name + ".json");
  s.instances = B;
  return s;
}

struct State {
  std::vector<double> q, qd, tau;  // (nv) each
};

State random_state(Index n, unsigned seed, double tau_scale) {
  std::mt19937_64 rng(seed);
  return {test::random_vector(rng, n, -1, 1), test::random_vector(rng, n, -1, 1),
          test::random_vector(rng, n, -tau_scale, tau_scale)};
}

// Central differences of the simulator's step at s: J (2n x 3n, row-major; rows q',
// qd'; columns q, qd, tau).
std::vector<double> step_by_differences(const Case& c, const State& s) {
  const Index n = static_cast<Index>(s.q.size()), P = 3 * n, B = 2 * P;
  std::vector<double> q, qd, tau;
  for (Index b = 0; b < B; ++b) {
    q.insert(q.end(), s.q.begin(), s.q.end());
    qd.insert(qd.end(), s.qd.begin(), s.qd.end());
    tau.insert(tau.end(), s.tau.begin(), s.tau.end());
  }
  auto h_of = [&](Index k) { return k < 2 * n ? 1e-6 : 2e-3 * c.tau_scale; };
  for (Index k = 0; k < P; ++k) {
    std::vector<double>& v = k < n ? q : k < 2 * n ? qd : tau;
    for (int sign : {0, 1}) v[(2 * k + sign) * n + k % n] += sign ? -h_of(k) : h_of(k);
  }
  test::simulate_rows(scene_of(c, B), q, qd, {tau});
  std::vector<double> J(2 * n * P);
  for (Index k = 0; k < P; ++k)
    for (Index r = 0; r < 2 * n; ++r) {
      const std::vector<double>& x = r < n ? q : qd;
      J[r * P + k] = (x[2 * k * n + r % n] - x[(2 * k + 1) * n + r % n]) / (2 * h_of(k));
    }
  return J;
}

using Jacobians = test::StepJacobians;

Jacobians step_jacobians(const Case& c, const std::vector<double>& q, const std::vector<double>& qd,
                         const std::vector<double>& tau, BackendKind kind, int threads = 1) {
  return test::step_jacobians_of(scene_of(c, 1), q, qd, tau, kind, threads);
}

TEST(StepDerivatives, JacobianMatchesCentralDifferencesOfTheSimulatorsStep) {
  for (const Case& c : cases()) {
    SCOPED_TRACE(c.name);
    const Index n = scene_of(c, 1).nv();
    const State s = random_state(n, 11 + static_cast<unsigned>(n), c.tau_scale);
    const std::vector<double> fd = step_by_differences(c, s);
    const Jacobians J = step_jacobians(c, s.q, s.qd, s.tau, BackendKind::Serial);
    for (int rb = 0; rb < 2; ++rb)
      for (int cb = 0; cb < 3; ++cb) {
        double err = 0, scale = 0;
        for (Index i = 0; i < n; ++i)
          for (Index j = 0; j < n; ++j) {
            const double ref = fd[(rb * n + i) * 3 * n + cb * n + j];
            err = std::max(err, std::abs(J.at(0, rb * n + i, cb * n + j) - ref));
            scale = std::max(scale, std::abs(ref));
          }
        EXPECT_LT(err, 1e-6 * scale) << "block d" << (rb ? "qd'" : "q'") << "/d" << (cb == 0 ? "q" : cb == 1 ? "qd" : "tau")
                                     << " scale " << scale;
      }
    // the new state is the simulator's, bit for bit
    std::vector<double> q = s.q, qd = s.qd;
    test::simulate_rows(scene_of(c, 1), q, qd, {s.tau});
    for (Index i = 0; i < n; ++i) {
      EXPECT_EQ(J.q[i], q[i]);
      EXPECT_EQ(J.qd[i], qd[i]);
    }
  }
}

TEST(StepDerivatives, OpenMPEqualsSerialAndFloatFollowsDouble) {
  for (const Case& c : cases()) {
    SCOPED_TRACE(c.name);
    const Index n = scene_of(c, 1).nv(), B = 5;
    std::vector<double> q, qd, tau;
    for (Index b = 0; b < B; ++b) {
      const State s = random_state(n, 3 + static_cast<unsigned>(b), c.tau_scale);
      q.insert(q.end(), s.q.begin(), s.q.end());
      qd.insert(qd.end(), s.qd.begin(), s.qd.end());
      tau.insert(tau.end(), s.tau.begin(), s.tau.end());
    }
    const Jacobians serial = step_jacobians(c, q, qd, tau, BackendKind::Serial);
    if (backend_unusable(BackendKind::OpenMP).empty()) {
      const Jacobians omp = step_jacobians(c, q, qd, tau, BackendKind::OpenMP, 3);
      for (int k = 0; k < 6; ++k) EXPECT_EQ(omp.blocks[k], serial.blocks[k]);
    }
    // float: 1e-3 relative per block (the blocks' entries lose ~1e-5 to float ABA + factorisation)
    Simulator<float> basef(scene_of(c, 1), BackendKind::Serial);
    BackendOptions o;
    o.max_batch = B;
    auto engine = sim::make_step_derivatives(basef.setup(), o);
    std::vector<float> qf(q.begin(), q.end()), qdf(qd.begin(), qd.end()), tauf(tau.begin(), tau.end());
    std::vector<std::vector<float>> blocks(6, std::vector<float>(n * n * B));
    auto v = [&](int k) { return BatchView<float>::aos(blocks[k].data(), n * n, B); };
    using V = BatchView<const float>;
    ASSERT_TRUE(engine->compute({V::aos(qf.data(), n, B), V::aos(qdf.data(), n, B), V::aos(tauf.data(), n, B)},
                                {v(0), v(1), v(2), v(3), v(4), v(5), {}, {}})
                    .ok());
    for (int k = 0; k < 6; ++k) {
      double err = 0, scale = 0;
      for (std::size_t e = 0; e < blocks[k].size(); ++e) {
        err = std::max(err, std::abs(double(blocks[k][e]) - serial.blocks[k][e]));
        scale = std::max(scale, std::abs(serial.blocks[k][e]));
      }
      EXPECT_LT(err, 1e-3 * scale) << "block " << k;
    }
  }
}

// ---- rollouts ----------------------------------------------------------------------

struct Rollout {
  Index n, B, T;
  std::vector<double> q0, qd0;               // (B x n)
  std::vector<double> tau;                   // (T x B x n)
  std::vector<double> cq, cqd;               // (T x B x n): the loss L = sum_t cq_t . q_{t+1} + cqd_t . qd_{t+1}
  StepSequence<const double> seq(const std::vector<double>& v) const {
    return {BatchView<const double>::aos(v.data(), n, B), B * n, T};
  }
  BatchView<const double> view(const std::vector<double>& v) const { return BatchView<const double>::aos(v.data(), n, B); }
};

Rollout random_rollout(Index n, Index B, Index T, unsigned seed, double tau_scale) {
  std::mt19937_64 rng(seed);
  Rollout r{n, B, T, {}, {}, {}, {}, {}};
  r.q0 = test::random_vector(rng, n * B, -0.4, 0.4);
  r.qd0 = test::random_vector(rng, n * B, -0.5, 0.5);
  r.tau = test::random_vector(rng, T * B * n, -tau_scale, tau_scale);
  r.cq = test::random_vector(rng, T * B * n, -1, 1);
  r.cqd = test::random_vector(rng, T * B * n, -0.1, 0.1);
  return r;
}

// L of instance 0's rollout with one variable perturbed, by the simulator: k < n: q0_k,
// k < 2n: qd0_k, else tau at (step, DoF) = ((k - 2n) / n, (k - 2n) % n); central
// differences with step h for each of the listed variables.
std::vector<double> loss_gradient_by_differences(const Case& c, const Rollout& r, const std::vector<Index>& vars,
                                                 double h_state, double h_tau) {
  const Index n = r.n, P = static_cast<Index>(vars.size()), B = 2 * P;
  std::vector<double> q, qd;
  std::vector<std::vector<double>> tau(r.T);
  for (Index b = 0; b < B; ++b) {
    q.insert(q.end(), r.q0.begin(), r.q0.begin() + n);
    qd.insert(qd.end(), r.qd0.begin(), r.qd0.begin() + n);
    for (Index t = 0; t < r.T; ++t)
      tau[t].insert(tau[t].end(), r.tau.begin() + t * r.B * n, r.tau.begin() + t * r.B * n + n);
  }
  std::vector<double> h(P);
  for (Index p = 0; p < P; ++p) {
    const Index k = vars[p];
    h[p] = k < 2 * n ? h_state : h_tau;
    for (int sign : {0, 1}) {
      const double d = sign ? -h[p] : h[p];
      const Index b = 2 * p + sign;
      if (k < n) q[b * n + k] += d;
      else if (k < 2 * n) qd[b * n + k - n] += d;
      else tau[(k - 2 * n) / n][b * n + (k - 2 * n) % n] += d;
    }
  }
  // L accumulated step by step
  Scene scene = scene_of(c, B);
  Simulator<double> sim(scene, BackendKind::Serial);
  for (Index b = 0; b < B; ++b)
    for (Index i = 0; i < n; ++i) sim.q().at(i, b) = q[b * n + i], sim.qd().at(i, b) = qd[b * n + i];
  std::vector<double> L(B, 0.0);
  for (Index t = 0; t < r.T; ++t) {
    sim.step(BatchView<const double>::aos(tau[t].data(), n, B));
    for (Index b = 0; b < B; ++b)
      for (Index i = 0; i < n; ++i)
        L[b] += r.cq[t * r.B * n + i] * sim.q().at(i, b) + r.cqd[t * r.B * n + i] * sim.qd().at(i, b);
  }
  EXPECT_TRUE(sim.status().ok());
  std::vector<double> g(P);
  for (Index p = 0; p < P; ++p) g[p] = (L[2 * p] - L[2 * p + 1]) / (2 * h[p]);
  return g;
}

struct Gradient {
  std::vector<double> gq0, gqd0, gtau;
};

Gradient rollout_gradient(const sim::SimSetup<double>& setup, const Rollout& r, Index interval, BackendKind kind) {
  BackendOptions o;
  o.backend = kind;
  o.threads = 2;
  sim::RolloutDerivatives<double> rd(setup, o, interval);
  Gradient g{std::vector<double>(r.n * r.B), std::vector<double>(r.n * r.B), std::vector<double>(r.T * r.B * r.n)};
  const BatchStatus st = rd.vjp(r.view(r.q0), r.view(r.qd0), r.seq(r.tau), r.seq(r.cq), r.seq(r.cqd),
                                BatchView<double>::aos(g.gq0.data(), r.n, r.B), BatchView<double>::aos(g.gqd0.data(), r.n, r.B),
                                {BatchView<double>::aos(g.gtau.data(), r.n, r.B), r.B * r.n, r.T});
  EXPECT_TRUE(st.ok()) << st.message();
  return g;
}

std::vector<Case> rollout_cases() {
  return {{"iiwa euler", scene_json("iiwa.urdf", "euler", kIiwaEffects, 2e-3), 2},
          {"iiwa rk4", scene_json("iiwa.urdf", "rk4", kIiwaEffects, 5e-3), 2},
          {"iiwa implicit", scene_json("iiwa.urdf", "implicit", kIiwaEffects, 5e-3), 2},
          {"rope:20 euler", scene_json("rope:20", "euler", kRopeEffects, 1e-4), 1e-4},
          {"rope:20 rk4", scene_json("rope:20", "rk4", kRopeEffects, 2e-4), 1e-4},
          {"rope:20 implicit", scene_json("rope:20", "implicit", kRopeEffects, 1e-4), 1e-4}};
}

TEST(RolloutDerivatives, GradientMatchesCentralDifferencesOfTheSimulatorsRollout) {
  for (const Case& c : rollout_cases()) {
    SCOPED_TRACE(c.name);
    const Index n = scene_of(c, 1).nv(), T = 40;
    const Rollout r = random_rollout(n, 2, T, 7 + static_cast<unsigned>(n), c.tau_scale);
    Simulator<double> base(scene_of(c, 1), BackendKind::Serial);
    // every initial-state entry, and the torques of steps 0, T/2 and T-1
    std::vector<Index> vars;
    for (Index k = 0; k < 2 * n; ++k) vars.push_back(k);
    for (Index t : {Index(0), T / 2, T - 1})
      for (Index i = 0; i < n; ++i) vars.push_back(2 * n + t * n + i);
    const std::vector<double> fd = loss_gradient_by_differences(c, r, vars, 1e-6, 1e-3 * c.tau_scale);
    std::vector<Gradient> grads;
    for (Index interval : {Index(1), Index(0), Index(7), T}) {
      SCOPED_TRACE("checkpoint interval " + std::to_string(interval));
      grads.push_back(rollout_gradient(base.setup(), r, interval, BackendKind::Serial));
      const Gradient& g = grads.back();
      double err = 0, scale = 0;
      for (std::size_t p = 0; p < vars.size(); ++p) {
        const Index k = vars[p];
        const double an = k < n ? g.gq0[k] : k < 2 * n ? g.gqd0[k - n] : g.gtau[((k - 2 * n) / n) * r.B * n + (k - 2 * n) % n];
        err = std::max(err, std::abs(an - fd[p]));
        scale = std::max(scale, std::abs(fd[p]));
      }
      EXPECT_LT(err, 1e-6 * scale) << "scale " << scale;
    }
    // every checkpoint interval: the same arithmetic, the same gradient
    for (const Gradient& g : grads) {
      EXPECT_EQ(g.gq0, grads[0].gq0);
      EXPECT_EQ(g.gtau, grads[0].gtau);
    }
    if (backend_unusable(BackendKind::OpenMP).empty()) {
      const Gradient g = rollout_gradient(base.setup(), r, 0, BackendKind::OpenMP);
      EXPECT_EQ(g.gq0, grads[0].gq0);
      EXPECT_EQ(g.gqd0, grads[0].gqd0);
      EXPECT_EQ(g.gtau, grads[0].gtau);
    }
  }
}

TEST(RolloutDerivatives, AdjointIsTheTransposeOfTheForwardModeProduct) {
  for (const Case& c : rollout_cases()) {
    SCOPED_TRACE(c.name);
    const Index n = scene_of(c, 1).nv(), T = 25, B = 3;
    const Rollout r = random_rollout(n, B, T, 21, c.tau_scale);
    std::mt19937_64 rng(5);
    const std::vector<double> dq0 = test::random_vector(rng, n * B, -1, 1), dqd0 = test::random_vector(rng, n * B, -1, 1),
                              dtau = test::random_vector(rng, T * B * n, -1, 1);
    Simulator<double> base(scene_of(c, 1), BackendKind::Serial);
    sim::RolloutDerivatives<double> rd(base.setup(), BackendOptions{});
    std::vector<double> dq(T * B * n), dqd(T * B * n);
    ASSERT_TRUE(rd.jvp(r.view(r.q0), r.view(r.qd0), r.seq(r.tau), r.view(dq0), r.view(dqd0), r.seq(dtau),
                       {BatchView<double>::aos(dq.data(), n, B), B * n, T}, {BatchView<double>::aos(dqd.data(), n, B), B * n, T})
                    .ok());
    const Gradient g = rollout_gradient(base.setup(), r, 0, BackendKind::Serial);
    for (Index b = 0; b < B; ++b) {
      double lhs = 0, rhs = 0, scale = 0;
      for (Index i = 0; i < n; ++i) lhs += g.gq0[b * n + i] * dq0[b * n + i] + g.gqd0[b * n + i] * dqd0[b * n + i];
      for (Index t = 0; t < T; ++t)
        for (Index i = 0; i < n; ++i) {
          const std::size_t e = (t * B + b) * n + i;
          lhs += g.gtau[e] * dtau[e];
          rhs += r.cq[e] * dq[e] + r.cqd[e] * dqd[e];
          scale += std::abs(r.cq[e] * dq[e]) + std::abs(r.cqd[e] * dqd[e]);
        }
      EXPECT_NEAR(lhs, rhs, 1e-10 * scale) << "instance " << b;
    }
    // the rollout's states are the simulator's, bit for bit
    std::vector<double> q(T * B * n), qd(T * B * n);
    ASSERT_TRUE(rd.rollout(r.view(r.q0), r.view(r.qd0), r.seq(r.tau), {BatchView<double>::aos(q.data(), n, B), B * n, T},
                           {BatchView<double>::aos(qd.data(), n, B), B * n, T})
                    .ok());
    std::vector<double> sq = r.q0, sqd = r.qd0;
    std::vector<std::vector<double>> taus(T);
    for (Index t = 0; t < T; ++t) taus[t].assign(r.tau.begin() + t * B * n, r.tau.begin() + (t + 1) * B * n);
    test::simulate_rows(scene_of(c, B), sq, sqd, taus);
    for (Index e = 0; e < B * n; ++e) {
      EXPECT_EQ(q[(T - 1) * B * n + e], sq[e]);
      EXPECT_EQ(qd[(T - 1) * B * n + e], sqd[e]);
    }
  }
}

TEST(StepDerivatives, OneStepDirectionalDerivativesAreTheDenseJacobiansProducts) {
  for (const Case& c : cases()) {
    SCOPED_TRACE(c.name);
    const Index n = scene_of(c, 1).nv();
    const Rollout r = random_rollout(n, 1, 1, 33, c.tau_scale);
    const Jacobians J = step_jacobians(c, r.q0, r.qd0, r.tau, BackendKind::Serial);
    Simulator<double> base(scene_of(c, 1), BackendKind::Serial);
    sim::RolloutDerivatives<double> rd(base.setup(), BackendOptions{});
    std::mt19937_64 rng(9);
    const std::vector<double> v = test::random_vector(rng, 3 * n, -1, 1);
    std::vector<double> dq(n), dqd(n);
    ASSERT_TRUE(rd.jvp(r.view(r.q0), r.view(r.qd0), r.seq(r.tau), r.view(std::vector<double>(v.begin(), v.begin() + n)),
                       r.view(std::vector<double>(v.begin() + n, v.begin() + 2 * n)),
                       r.seq(std::vector<double>(v.begin() + 2 * n, v.end())),
                       {BatchView<double>::aos(dq.data(), n, 1), n, 1}, {BatchView<double>::aos(dqd.data(), n, 1), n, 1})
                    .ok());
    const Gradient g = rollout_gradient(base.setup(), r, 0, BackendKind::Serial);
    for (Index row = 0; row < 2 * n; ++row) {
      double Jv = 0, scale = 0;
      for (Index k = 0; k < 3 * n; ++k) Jv += J.at(0, row, k) * v[k], scale += std::abs(J.at(0, row, k) * v[k]);
      EXPECT_NEAR(row < n ? dq[row] : dqd[row - n], Jv, 1e-12 * scale) << "row " << row;
    }
    for (Index k = 0; k < 3 * n; ++k) {
      double gJ = 0, scale = 0;
      for (Index row = 0; row < 2 * n; ++row) {
        const double w = row < n ? r.cq[row] : r.cqd[row - n];
        gJ += w * J.at(0, row, k), scale += std::abs(w * J.at(0, row, k));
      }
      const double an = k < n ? g.gq0[k] : k < 2 * n ? g.gqd0[k - n] : g.gtau[k - 2 * n];
      EXPECT_NEAR(an, gJ, 1e-12 * scale + 1e-300) << "column " << k;
    }
  }
}

TEST(StepDerivatives, ANonFiniteResultIsAFailureNeverASilentNaN) {
  const Case c = cases()[0];
  const Index n = scene_of(c, 1).nv(), B = 3;
  std::vector<double> q(n * B, 0.1), qd(n * B, 0.2), tau(n * B, 1.0);
  tau[1 * n + 2] = NAN;  // instance 1
  Simulator<double> base(scene_of(c, 1), BackendKind::Serial);
  BackendOptions o;
  o.max_batch = B;
  using V = BatchView<const double>;
  Jacobians J(n, n, B);
  const BatchStatus st =
      sim::make_step_derivatives(base.setup(), o)->compute({V::aos(q.data(), n, B), V::aos(qd.data(), n, B), V::aos(tau.data(), n, B)}, J.out());
  EXPECT_EQ(st.failed, 1);
  EXPECT_EQ(st.first_instance, 1);
  EXPECT_EQ(st.failure, Failure::NonFinite);
  sim::RolloutDerivatives<double> rd(base.setup(), o);
  std::vector<double> qs(2 * n * B), qds(2 * n * B), taus(2 * n * B, 1.0);
  taus[n * B + 2 * n] = INFINITY;  // step 1, instance 2
  const BatchStatus rs = rd.rollout(V::aos(q.data(), n, B), V::aos(qd.data(), n, B), {V::aos(taus.data(), n, B), n * B, 2},
                                    {BatchView<double>::aos(qs.data(), n, B), n * B, 2},
                                    {BatchView<double>::aos(qds.data(), n, B), n * B, 2});
  EXPECT_EQ(rs.failed, 1);
  EXPECT_EQ(rs.first_instance, 2);
  EXPECT_EQ(rs.failure, Failure::NonFinite);
}

TEST(StepDerivatives, RefusesWhatItDoesNotCoverByName) {
  auto message = [](const std::string& json, BackendKind kind) -> std::string {
    try {
      Simulator<double> s(sim::parse_scene(json, "t.json"), BackendKind::Serial);
      BackendOptions o;
      o.backend = kind;
      sim::make_step_derivatives(s.setup(), o);
    } catch (const BackendError& e) {
      return e.what();
    }
    return "";
  };
  const std::string contacts = R"({"model": "rope:3", "dt": 1e-3, "effects": {"gravity": true, "contacts": {"stiffness": 1000,
      "points": [{"link": "link_1", "position": [0, 0, 0]}], "planes": [{"normal": [0, 0, 1], "offset": -5}]}}})";
  EXPECT_NE(message(contacts, BackendKind::Serial).find("contacts"), std::string::npos)
      << message(contacts, BackendKind::Serial);
  const std::string plain = R"({"model": "chain:3", "dt": 1e-3, "effects": {"gravity": true}})";
  EXPECT_EQ(message(plain, BackendKind::Serial), "");
  // the rollouts on cuda: built where a device is usable (tests/cuda/test_cuda_rollout_derivatives.cu
  // checks them), otherwise refused naming the backend
  Simulator<double> s(sim::parse_scene(plain, "t.json"), BackendKind::Serial);
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  if (backend_unusable(BackendKind::Cuda).empty()) {
    EXPECT_NO_THROW(sim::RolloutDerivatives<double>(s.setup(), o));
  } else {
    try {
      sim::RolloutDerivatives<double> rd(s.setup(), o);
      ADD_FAILURE() << "no BackendError";
    } catch (const BackendError& e) {
      EXPECT_NE(std::string(e.what()).find("cuda"), std::string::npos) << e.what();
    }
  }
  // and on every backend the rollouts refuse what the step derivatives refuse, by name
  for (BackendKind kind : {BackendKind::Serial, BackendKind::Cuda}) {
    Simulator<double> c(sim::parse_scene(contacts, "t.json"), BackendKind::Serial);
    BackendOptions oc;
    oc.backend = kind;
    try {
      sim::RolloutDerivatives<double> rd(c.setup(), oc);
      ADD_FAILURE() << "no BackendError on " << to_string(kind);
    } catch (const BackendError& e) {
      EXPECT_NE(std::string(e.what()).find("contacts"), std::string::npos) << e.what();
    }
  }
}

}  // namespace
}  // namespace scandyn
