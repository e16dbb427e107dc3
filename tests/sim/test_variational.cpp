// Tests of the variational integrator (scandyn/sim/variational.hpp, "integrator":
// "variational"): the scene value and its refusals, bounded energy error without
// drift over 10^5 steps (a double pendulum: rope:2; iiwa) where rk4 drifts, second
// order against a fine rk4 reference, Newton's convergence, failures reported (never
// NaN), serial == OpenMP bit for bit, float.
// Long runs (rope:1000, energy plots) are bench/variational_cost.cpp's.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>
#include <tuple>
#include <vector>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/algorithm/second_derivatives.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"
#include "scandyn/sim/variational.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

using sim::Integrator;
using sim::Scene;
using sim::Simulator;

Scene scene_of(const std::string& model, const std::string& integrator, double dt, const std::string& extra = "") {
  char b[64];
  std::snprintf(b, sizeof b, "%.17g", dt);  // dt exactly (std::to_string keeps 6 decimals)
  return sim::parse_scene("{\"model\": \"" + model + "\", \"integrator\": \"" + integrator +
                              "\", \"dt\": " + b + extra + "}",
                          "test.json", test::models_dir());
}

// A swinging start: the double pendulum (rope:2) from 1 rad and 0.5 rad, iiwa
// from a bent pose with joint speeds, both with gravity only.
const char* const kPendulum =
    ", \"effects\": {\"gravity\": true}, \"initial\": {\"q\": [1.0, 0.5], \"qd\": [0, 0]}";
const char* const kIiwa =
    ", \"effects\": {\"gravity\": true}, \"initial\": {\"q\": [0.3, 0.8, -0.2, -1.0, 0.4, 0.6, 0.1], "
    "\"qd\": [0.5, -0.3, 0.4, 0.2, -0.6, 0.3, 0.8]}";

std::string message_of(const Scene& scene, BackendKind backend) {
  try {
    Simulator<double> sim(scene, backend);
  } catch (const BackendError& e) {
    return e.what();
  }
  return "";
}

TEST(SimVariational, SceneValueAndRefusals) {
  Integrator i{};
  ASSERT_TRUE(sim::parse_integrator("variational", i));
  EXPECT_EQ(i, Integrator::Variational);
  EXPECT_STREQ(sim::to_string(Integrator::Variational), "variational");
  EXPECT_EQ(scene_of("rope:2", "variational", 1e-3, kPendulum).integrator, Integrator::Variational);
  // the CUDA backend beyond its 64 DoFs (the limit named), multi-DoF joints, contacts: refused by name
  const std::string cuda =
      message_of(scene_of("rope:65", "variational", 1e-3, ", \"effects\": {\"gravity\": true}"), BackendKind::Cuda);
  EXPECT_NE(cuda.find("variational"), std::string::npos) << cuda;
  EXPECT_NE(cuda.find("up to 64 DoF"), std::string::npos) << cuda;
  EXPECT_NE(message_of(scene_of("ballrope:2", "variational", 1e-3), BackendKind::Serial).find("1-DoF joints"),
            std::string::npos);
  const Scene contacts = scene_of("rope:2", "variational", 1e-3,
                                  ", \"effects\": {\"gravity\": true, \"contacts\": {\"points\": [{\"link\": "
                                  "\"link_1\", \"radius\": 0.01}], \"planes\": [{\"normal\": [0, 0, 1], "
                                  "\"offset\": -1}], \"stiffness\": 1e4}}");
  EXPECT_NE(message_of(contacts, BackendKind::Serial).find("contacts"), std::string::npos);
}

// Max |E - E0| / (E0 - E_rest) over the first and the last tenth of n steps
// (every 100 steps).
struct EnergyRun {
  double first = 0, last = 0, worst = 0, relative_to_e0 = 0;
  bool ok = true;
  std::string failure;
};
EnergyRun energy_run(const Scene& scene, int n) {
  Simulator<double> sim(scene, BackendKind::Serial);
  const std::vector<double> zero(scene.nv(), 0.0);
  const double rest = sim::mechanical_energy(scene.model, scene.effects, scene.joints.data(), zero.data(), zero.data());
  const double e0 = sim.energy()[0];
  EnergyRun r;
  for (int s = 0; s < n; ++s) {
    sim.step();
    if (s % 100 != 99) continue;
    const double e = sim.energy()[0];
    const double err = std::abs(e - e0) / std::abs(e0 - rest);
    if (!std::isfinite(err)) r.ok = false, r.failure = "energy not finite at step " + std::to_string(s);
    r.worst = std::max(r.worst, err);
    r.relative_to_e0 = std::max(r.relative_to_e0, std::abs(e - e0) / std::abs(e0));
    if (s < n / 10) r.first = std::max(r.first, err);
    if (s >= n - n / 10) r.last = std::max(r.last, err);
  }
  r.ok = r.ok && sim.status().ok();
  if (!sim.status().ok()) r.failure = sim::failure_message(sim.status());
  return r;
}

// The double pendulum at dt = 1e-2 (rope:2: links of 1 cm, periods of ~0.2 s) for
// 10^5 steps (1000 s): the variational step's energy error stays bounded (measured
// 3.2e-3 of E0 - E_rest in the first tenth and in the last) and the last tenth is
// no worse than the first;
// rk4 at the same dt drifts (measured: 0.055 in the first tenth, 0.35 in the last).
TEST(SimVariational, DoublePendulumEnergyBoundedWhereRk4Drifts) {
  const EnergyRun vi = energy_run(scene_of("rope:2", "variational", 1e-2, kPendulum), 100000);
  const EnergyRun rk4 = energy_run(scene_of("rope:2", "rk4", 1e-2, kPendulum), 100000);
  std::printf("rope:2 dt 1e-2, 1e5 steps: variational first %.3g last %.3g worst %.3g (|E0| %.3g); rk4 first %.3g "
              "last %.3g\n",
              vi.first, vi.last, vi.worst, vi.relative_to_e0, rk4.first, rk4.last);
  ASSERT_TRUE(vi.ok) << vi.failure;
  EXPECT_LE(vi.worst, 2e-2);
  EXPECT_LE(vi.last, 2 * vi.first + 1e-9);
  EXPECT_GE(rk4.last, 3 * rk4.first);
  EXPECT_GE(rk4.last, 30 * vi.worst);
}

// iiwa at dt = 2e-3 for 10^5 steps (200 s): bounded, no trend. The motion is
// chaotic (a joint ends up spinning at ~35 rad/s), so the errors depend on rounding
// (the states visited): measured worst 2.0e-3..6.7e-3 of E0 - E_rest over three
// builds of the Newton solve; first / last tenths 1.5e-3 / 1.5e-3, 2.2e-3 / 1.8e-3,
// 0.8e-3 / 2.0e-3 (hence the factor 4; the double pendulum's test and the plots
// carry the no-drift comparison with rk4).
TEST(SimVariational, IiwaEnergyBoundedFor1e5Steps) {
  const EnergyRun vi = energy_run(scene_of("iiwa.urdf", "variational", 2e-3, kIiwa), 100000);
  std::printf("iiwa dt 2e-3, 1e5 steps: variational first %.3g last %.3g worst %.3g (|E0| %.3g)\n", vi.first,
              vi.last, vi.worst, vi.relative_to_e0);
  ASSERT_TRUE(vi.ok) << vi.failure;
  EXPECT_LE(vi.worst, 2e-2);
  EXPECT_LE(vi.last, 4 * vi.first + 1e-9);
}

// The state after T = 0.2 s against rk4 at dt / 64: halving dt cuts the error by
// about 4 (second order).
TEST(SimVariational, SecondOrder) {
  auto final_state = [](const std::string& model, const char* extra, const std::string& integrator, double dt) {
    const Scene s = scene_of(model, integrator, dt, extra);
    Simulator<double> sim(s, BackendKind::Serial);
    const int n = static_cast<int>(std::lround(0.2 / dt));
    for (int k = 0; k < n; ++k) sim.step();
    std::vector<double> q(s.nq()), qd(s.nv());
    sim.read_state(q.data(), qd.data());
    q.insert(q.end(), qd.begin(), qd.end());
    return q;
  };
  for (const auto& [model, extra, dt] : {std::tuple<std::string, const char*, double>{"rope:2", kPendulum, 4e-3},
                                         {"iiwa.urdf", kIiwa, 1e-2}}) {
    const std::vector<double> ref = final_state(model, extra, "rk4", dt / 64);
    double err[3];
    for (int k = 0; k < 3; ++k) {
      const std::vector<double> x = final_state(model, extra, "variational", dt / double(1 << k));
      err[k] = 0;
      for (std::size_t i = 0; i < x.size(); ++i) err[k] = std::max(err[k], std::abs(x[i] - ref[i]));
    }
    std::printf("%s: errors %.3g %.3g %.3g, ratios %.2f %.2f\n", model.c_str(), err[0], err[1], err[2],
                err[0] / err[1], err[1] / err[2]);
    EXPECT_NEAR(err[0] / err[1], 4.0, 0.6) << model;
    EXPECT_NEAR(err[1] / err[2], 4.0, 0.6) << model;
  }
}

// The index order of the Lagrangian's q-gradient: with D = d(M(q) a)/dq at a = v
// (rnea_derivatives of the model without gravity at (q, 0, v)), (D^T v)_j = v^T
// (dM/dq_j) v, against central differences of v^T M(q) v; and rnea_weighted_dq2's
// H = d(D^T v)/dq against central differences of D^T v (iiwa, double).
TEST(SimVariational, LagrangianGradientAndHessianMatchCentralDifferences) {
  const Scene scene = scene_of("iiwa.urdf", "variational", 1e-3, kIiwa);
  Model rest = scene.model;
  rest.gravity = Vec3<double>{0, 0, 0};
  const Index n = rest.nv();
  const std::vector<double> q = scene.initial.q, v = scene.initial.qd, zero(n, 0.0);
  DerivativeDataTpl<double> dd(rest);
  Data data(rest);
  std::vector<double> D(n * n), B(n * n), M(n * n);
  auto dtv = [&](const std::vector<double>& qq) {  // D(qq)^T v
    rnea_derivatives(rest, dd, qq.data(), zero.data(), v.data(), static_cast<const Force<double>*>(nullptr),
                     MatrixRef<double>{D.data(), n, 1}, MatrixRef<double>{B.data(), n, 1},
                     MatrixRef<double>{M.data(), n, 1});
    std::vector<double> g(n, 0.0);
    for (Index j = 0; j < n; ++j)
      for (Index i = 0; i < n; ++i) g[j] += D[i * n + j] * v[i];
    return g;
  };
  auto vmv = [&](const std::vector<double>& qq) {  // v^T M(qq) v
    crba(rest, data, qq.data(), M.data());
    double e = 0;
    for (Index i = 0; i < n; ++i)
      for (Index j = 0; j < n; ++j) e += v[i] * M[i * n + j] * v[j];
    return e;
  };
  const std::vector<double> g = dtv(q);
  SecondDerivativeData<double> sd(rest);
  std::vector<double> H(n * n);
  rnea_weighted_dq2(rest, sd, q.data(), zero.data(), v.data(), static_cast<const Force<double>*>(nullptr), v.data(),
                    H.data());
  const double h = 1e-5;
  for (Index j = 0; j < n; ++j) {
    std::vector<double> qp = q, qm = q;
    qp[j] += h, qm[j] -= h;
    EXPECT_NEAR(g[j], (vmv(qp) - vmv(qm)) / (2 * h), 1e-7 * (1 + std::abs(g[j]))) << j;
    const std::vector<double> gp = dtv(qp), gm = dtv(qm);
    for (Index i = 0; i < n; ++i)
      EXPECT_NEAR(H[i * n + j], (gp[i] - gm[i]) / (2 * h), 1e-6 * (1 + std::abs(H[i * n + j]))) << i << "," << j;
  }
}

// The reference Newton of the exact Jacobian with H by the nv dual passes
// (rnea_weighted_dq2_dual, what the step ran before the analytical recursion's
// weighted contraction): solve_dense's loop, step for step, as
// variational_step_instance's solve.
struct DualHessianNewton {
  const Model* rest;                 // the model without gravity
  SecondDerivativeData<double>* sd;  // the dual passes' scratch
  std::vector<double>* H;            // (nv x nv)
  double* h_term;                    // the largest |dt^2/8 H_ij| seen
  template <unsigned kEffects>
  bool solve(const sim::VariationalModel<double>& model, const sim::VariationalScratch<double>& w, double dt,
             const sim::JointCoefficients<double>* coef, const double* q, const double* tau, const Force<double>* fx,
             double speed, sim::VariationalResult& out, Index& worst) const {
    const Index n = model.nv;
    const double half = 0.5 * dt, quarter = 0.25 * dt * dt, eighth = 0.125 * dt * dt;
    for (int it = 0; it < sim::kVariationalMaxIterations; ++it) {
      for (Index i = 0; i < n; ++i) w.qm[i] = q[i] + half * w.v[i];
      rnea_derivatives_instance(model.body, n, model.a0_rest, static_cast<const double*>(w.qm),
                                static_cast<const double*>(w.zero), static_cast<const double*>(w.v),
                                static_cast<const Force<double>*>(nullptr), w.deriv, w.D, w.unused, w.M, w.tau_m);
      rnea_derivatives_instance(model.body, n, model.a0, static_cast<const double*>(w.qm),
                                static_cast<const double*>(w.zero), static_cast<const double*>(w.zero), fx, w.deriv,
                                w.K, w.unused, w.unused, w.tau_g);
      sim::stage_forces<kEffects>(n, coef, tau, w.qm, w.v, 0.0, w.f, w.eq, w.eqd);
      for (Index j = 0; j < n; ++j) {
        double dtv = 0;
        for (Index i = 0; i < n; ++i) dtv += w.D(i, j) * w.v[i];
        w.dtv[j] = dtv;
      }
      const sim::detail::ResidualNorm<double> norm = sim::detail::negative_residual<true>(w, n, half);
      if (it > 0 && norm.residual <= norm.floor) return true;
      rnea_weighted_dq2_dual(*rest, *sd, w.qm, w.zero, w.v, static_cast<const Force<double>*>(nullptr), w.v,
                             H->data());
      for (Index e = 0; e < n * n; ++e) *h_term = std::max(*h_term, eighth * std::abs((*H)[e]));
      for (Index i = 0; i < n; ++i) {
        for (Index j = 0; j < n; ++j)
          w.J(i, j) = w.M(i, j) + half * (w.D(i, j) - w.D(j, i)) + quarter * w.K(i, j) - eighth * (*H)[i * n + j];
        w.J(i, i) -= quarter * w.eq[i] + half * w.eqd[i];
      }
      if (!sim::detail::lu_factor(w.J, w.piv)) return false;
      sim::detail::lu_solve(w.J, w.piv, w.r);
      const sim::detail::Update u = sim::detail::take_update(w, n, speed, it, false, out, worst);
      if (u != sim::detail::Update::Continue) return u == sim::detail::Update::Converged;
    }
    return false;
  }
};

// The step with H by the analytical weighted contraction (variational_step) against
// the same step with H by the dual passes (DualHessianNewton), from the same state at
// every step of a run: iiwa with gravity, damping, springs and a wrench on its last
// link at 10x the test speeds, and tree:12:2 (random tree, 4 prismatic joints). The
// two H agree to rounding (SecondDerivatives.WeightedContractionMatchesTheDualPasses),
// so the steps do: the same Newton updates, q and qd within 1e-12 of their scale
// (measured: bit-identical; H's rounding differences are far below J's last bits).
TEST(SimVariational, AnalyticHessianStepEqualsTheDualPassesStep) {
  for (const char* model_name : {"iiwa.urdf", "tree:12:2"}) {
    const bool iiwa = std::string(model_name) == "iiwa.urdf";
    const std::string link = iiwa ? "iiwa_link_7" : "link_09";  // (tree:12:2: a leaf)
    const Scene scene = scene_of(model_name, "variational", 2e-3,
                                 ", \"effects\": {\"gravity\": true, \"damping\": 0.05, \"springs\": {\"stiffness\": "
                                 "0.5, \"rest\": 0.1}, \"external\": {\"wrenches\": [{\"link\": \"" + link +
                                     "\", \"wrench\": [0.01, 0, 0, 0, 0.2, 0]}]}}, \"initial\": {\"random\": "
                                     "{\"seed\": 3, \"q\": 1.0, \"qd\": 5.0}}");
    const Model& model = scene.model;
    const Index n = model.nv();
    int prismatic = 0;
    for (const auto& b : model.bodies) prismatic += b.type == JointType::Prismatic;
    SCOPED_TRACE(std::string(model_name) + " (" + std::to_string(prismatic) + " prismatic)");
    sim::VariationalWork<double> w(model), ref(model);
    SecondDerivativeData<double> sd(ref.at_rest);
    std::vector<double> H(static_cast<std::size_t>(n) * n);
    double h_term = 0;
    const DualHessianNewton newton{&ref.at_rest, &sd, &H, &h_term};
    const std::vector<sim::JointCoefficients<double>> coef(scene.joints.begin(), scene.joints.end());
    std::vector<double> q(n), qd(n), tau(n, 0.0);
    Simulator<double> start(scene, BackendKind::Serial);
    start.read_state(q.data(), qd.data());  // the drawn start
    const std::vector<Force<double>> fx = start.setup().wrenches;
    ASSERT_EQ(fx.size(), static_cast<std::size_t>(model.nbodies()));
    constexpr unsigned kEffects = sim::kGravity | sim::kDamping | sim::kSprings | sim::kExternal;
    double worst = 0;
    int updates = 0;
    for (int s = 0; s < 200; ++s) {
      std::vector<double> qr = q, qdr = qd;
      const sim::VariationalResult a =
          sim::variational_step<kEffects>(model, w, 2e-3, coef.data(), q.data(), qd.data(), tau.data(), fx.data());
      const sim::VariationalResult b = sim::variational_step_instance<kEffects>(
          ref.instance_model(), ref.scratch, 2e-3, coef.data(), qr.data(), qdr.data(), tau.data(), fx.data(),
          [&](auto&&... args) { return newton.solve<kEffects>(args...); });
      ASSERT_EQ(a.failed_dof, -1) << "step " << s;
      ASSERT_EQ(b.failed_dof, -1) << "step " << s;
      EXPECT_EQ(a.iterations, b.iterations) << "step " << s;
      updates = std::max(updates, a.iterations);
      double scale = 1;
      for (Index i = 0; i < n; ++i) scale = std::max({scale, std::abs(qr[i]), std::abs(qdr[i])});
      for (Index i = 0; i < n; ++i)
        worst = std::max({worst, std::abs(q[i] - qr[i]) / scale, std::abs(qd[i] - qdr[i]) / scale});
      q = qr, qd = qdr;  // both continue from the reference's state
    }
    std::printf("%s: 200 steps, at most %d updates, largest |dt^2/8 H_ij| %.3g, analytic H vs dual passes per step "
                "%.3g\n", model_name, updates, h_term, worst);
    EXPECT_GT(h_term, 1e-9);  // the term compared is there
    EXPECT_LE(worst, 1e-12);
  }
}

// Newton: at most 2 updates at dt = 1e-3 on iiwa (the residual then at its rounding
// floor); at joint speeds of up to 32 rad/s and dt = 2e-3, where dropping the
// Jacobian's second-order term H made the iteration linear with contraction ~0.3
// (20+ iterations), the exact Jacobian still converges in at most 4 (measured 3: the
// updates ~1.9, ~3e-3, then the rounding floor).
TEST(SimVariational, NewtonConvergesInFewIterations) {
  const Scene scene = scene_of("iiwa.urdf", "variational", 1e-3, kIiwa);
  const Model& model = scene.model;
  sim::VariationalWork<double> w(model);
  const std::vector<sim::JointCoefficients<double>> coef(scene.joints.begin(), scene.joints.end());
  for (const double speed : {1.0, 40.0}) {
    const double dt = speed > 1 ? 2e-3 : 1e-3;
    std::vector<double> q = scene.initial.q, qd = scene.initial.qd, tau(7, 0.0);
    for (double& v : qd) v *= speed;
    int most = 0;
    for (int k = 0; k < 20; ++k) {
      const sim::VariationalResult r = sim::variational_step<sim::kGravity>(
          model, w, dt, coef.data(), q.data(), qd.data(), tau.data(), static_cast<const Force<double>*>(nullptr));
      ASSERT_EQ(r.failed_dof, -1) << speed;
      most = std::max(most, r.iterations);
      if (speed == 1.0 && r.iterations >= 2) {  // the second update far below the first
        EXPECT_LE(r.iterations == 2 ? r.last_update : r.previous_update, 1e-3 * r.first_update) << speed;
      }
    }
    std::printf("speed x%g: at most %d Newton updates\n", speed, most);
    EXPECT_LE(most, speed > 1 ? 4 : 2) << speed;
  }
}

// Damping and springs (forces at the midpoint): damping removes energy at every
// step (springs' energy included), and with neither the step is reversible:
// stepping back with -qd returns to the start.
TEST(SimVariational, DampingDissipatesAndTheStepIsReversible) {
  {
    Simulator<double> sim(scene_of("chain:4", "variational", 1e-3,
                                   ", \"effects\": {\"gravity\": true, \"damping\": 0.05, \"springs\": {\"stiffness\": "
                                   "2, \"rest\": 0.1}}, \"initial\": {\"q\": 0.5, \"qd\": 1.0}"));
    double e = sim.energy()[0];
    for (int s = 0; s < 2000; ++s) {
      sim.step();
      const double next = sim.energy()[0];
      ASSERT_LT(next, e + 1e-12) << "step " << s;
      e = next;
    }
    ASSERT_TRUE(sim.status().ok());
  }
  const Scene scene = scene_of("iiwa.urdf", "variational", 5e-3, kIiwa);
  Simulator<double> sim(scene, BackendKind::Serial);
  for (int s = 0; s < 100; ++s) sim.step();
  std::vector<double> q(7), qd(7);
  sim.read_state(q.data(), qd.data());
  for (Index i = 0; i < 7; ++i) sim.qd().at(i, 0) = -qd[i];
  for (int s = 0; s < 100; ++s) sim.step();
  sim.read_state(q.data(), qd.data());
  for (int i = 0; i < 7; ++i) {
    EXPECT_NEAR(q[i], scene.initial.q[i], 1e-9) << i;
    EXPECT_NEAR(-qd[i], scene.initial.qd[i], 1e-9) << i;
  }
}

// A step Newton cannot solve (dt = 0.5 s on a fast double pendulum) fails as
// Failure::NotConverged: the instance keeps its state, nothing becomes NaN.
TEST(SimVariational, NonConvergenceIsAFailureNotNaN) {
  Simulator<double> sim(scene_of("rope:2", "variational", 0.5,
                                 ", \"effects\": {\"gravity\": true}, \"initial\": {\"q\": [1.0, 0.5], \"qd\": [300, "
                                 "-400]}"));
  std::vector<double> q(2), qd(2), q1(2), qd1(2);
  sim.read_state(q.data(), qd.data());
  sim.step();
  sim.read_state(q1.data(), qd1.data());
  const BatchStatus st = sim.status();
  ASSERT_FALSE(st.ok());
  EXPECT_EQ(st.failure, Failure::NotConverged);
  EXPECT_EQ(q1, q);
  EXPECT_EQ(qd1, qd);
  EXPECT_NE(sim::failure_message(st).find("variational"), std::string::npos);
}

// The dense LU with partial pivoting (whole rows exchanged) solves systems that need
// the exchanges: a permutation, and a random 40 x 40 matrix with a zero diagonal.
TEST(SimVariational, LuWithPivoting) {
  {
    std::vector<double> A{0, 1, 1, 0}, x{2, 3};
    std::vector<Index> piv(2);
    ASSERT_TRUE(sim::detail::lu_factor<double>(2, A.data(), piv.data()));
    sim::detail::lu_solve<double>(2, A.data(), piv.data(), x.data());
    EXPECT_EQ(x, (std::vector<double>{3, 2}));
  }
  const Index n = 40;
  std::vector<double> A(n * n), b(n, 0.0), x(n);
  unsigned state = 12345;
  auto next = [&] { return (state = state * 1103515245u + 12345u) / 4294967296.0 - 0.5; };
  for (Index i = 0; i < n; ++i) {
    x[i] = next();
    for (Index j = 0; j < n; ++j) A[i * n + j] = i == j ? 0.0 : next();
  }
  for (Index i = 0; i < n; ++i)
    for (Index j = 0; j < n; ++j) b[i] += A[i * n + j] * x[j];
  std::vector<Index> piv(n);
  ASSERT_TRUE(sim::detail::lu_factor<double>(n, A.data(), piv.data()));
  sim::detail::lu_solve<double>(n, A.data(), piv.data(), b.data());
  for (Index i = 0; i < n; ++i) EXPECT_NEAR(b[i], x[i], 1e-10) << i;
}

// Above kVariationalExactMaxDofs (rope:100: the O(nv) chord iteration): 300 steps
// converge, the energy error stays small.
TEST(SimVariational, LongChainQuasiNewton) {
  const EnergyRun vi =
      energy_run(scene_of("rope:100", "variational", 5e-5,
                          ", \"effects\": {\"gravity\": true}, \"initial\": {\"random\": {\"seed\": 2, \"q\": 0.05}}"),
                 300);
  std::printf("rope:100 dt 5e-5, 300 steps: worst %.3g\n", vi.worst);
  ASSERT_TRUE(vi.ok) << vi.failure;
  EXPECT_LE(vi.worst, 1e-2);
}

// Steps of a model beyond kVariationalExactMaxDofs by the chord iteration and by the
// dense quasi-Newton Jacobian (forced: chord = false), each from the same state: the
// same equations, so each step's results agree to the iterations' stopping error:
// both converge linearly (neither has H) and stop once an update within sqrt(eps) of
// the speed no longer halves (taken as the rounding floor), up to ~1e-8 short of the
// solution (rope:100 with gravity, damping and springs, whose diagonal the chord's
// preconditioner takes as armature; measured 6.4e-9 relative, bound 3e-8); the chord
// iteration never falls back there. With chord_max_iterations = 1 every step goes on
// to Newton-Krylov (GMRES on the exact Jacobian's products by central differences of
// the residual), which solves it too, to the same bound and without the dense
// fallback.
TEST(SimVariational, ChordIterationSolvesWhatTheDenseJacobianSolves) {
  const Scene scene = scene_of("rope:100", "variational", 1e-4,
                               ", \"effects\": {\"gravity\": true, \"damping\": 0.02, \"springs\": {\"stiffness\": "
                               "0.05, \"rest\": 0.0}}, \"initial\": {\"random\": {\"seed\": 4, \"q\": 0.3, \"qd\": 0.3}}");
  const Model& model = scene.model;
  const Index n = model.nv();
  const std::vector<sim::JointCoefficients<double>> coef(scene.joints.begin(), scene.joints.end());
  constexpr unsigned kEffects = sim::kGravity | sim::kDamping | sim::kSprings;
  for (const int cap : {sim::kVariationalMaxIterations, 1}) {
    sim::VariationalWork<double> chord(model), dense(model);
    ASSERT_TRUE(chord.chord);
    chord.chord_max_iterations = cap;
    dense.chord = false;
    std::vector<double> q(n), qd(n), tau(n, 0.0);
    Simulator<double>(scene, BackendKind::Serial).read_state(q.data(), qd.data());  // the drawn start
    int most = 0;
    double worst = 0;
    for (int k = 0; k < 40; ++k) {
      std::vector<double> qb = q, qdb = qd;
      const sim::VariationalResult a = sim::variational_step<kEffects>(
          model, chord, 1e-4, coef.data(), q.data(), qd.data(), tau.data(), static_cast<const Force<double>*>(nullptr));
      const sim::VariationalResult b = sim::variational_step<kEffects>(
          model, dense, 1e-4, coef.data(), qb.data(), qdb.data(), tau.data(), static_cast<const Force<double>*>(nullptr));
      ASSERT_EQ(a.failed_dof, -1) << "step " << k;
      ASSERT_EQ(b.failed_dof, -1) << "step " << k;
      EXPECT_EQ(a.krylov, cap == 1) << "step " << k;
      EXPECT_FALSE(a.dense_fallback) << "step " << k;
      EXPECT_FALSE(b.dense_fallback);
      most = std::max(most, a.iterations);
      for (Index i = 0; i < n; ++i) {
        worst = std::max(worst, std::abs(q[i] - qb[i]) / std::max(1.0, std::abs(qb[i])));
        worst = std::max(worst, std::abs(qd[i] - qdb[i]) / std::max(1.0, std::abs(qdb[i])));
      }
    }
    std::printf("rope:100, cap %d: at most %d updates, chord vs dense per step %.3g\n", cap, most, worst);
    EXPECT_LE(worst, 3e-8) << cap;
    EXPECT_LE(most, 12) << cap;
  }
}

// rope:1000 from rest at dt = 2e-5 with gravity: 60 steps, the first ones by the
// chord iteration, those from about step 35 (where it stalls) by Newton-Krylov; never
// the dense fallback and no nv x nv scratch; energy within 1e-8 of the swinging
// energy. (The 10^5-step run: bench/variational_cost.cpp energy.)
TEST(SimVariational, Rope1000ByChordAndNewtonKrylov) {
  const Scene scene = scene_of("rope:1000", "variational", 2e-5,
                               ", \"effects\": {\"gravity\": true}, \"initial\": {\"random\": {\"seed\": 1, \"q\": 0.05}}");
  const Model& model = scene.model;
  sim::VariationalWork<double> w(model);
  ASSERT_TRUE(w.chord);
  const std::vector<sim::JointCoefficients<double>> coef(scene.joints.begin(), scene.joints.end());
  std::vector<double> q(model.nv()), qd(model.nv()), tau(model.nv(), 0.0);
  Simulator<double>(scene, BackendKind::Serial).read_state(q.data(), qd.data());  // the drawn start
  const std::vector<double> zero(model.nv(), 0.0);
  const double rest = sim::mechanical_energy(model, scene.effects, scene.joints.data(), zero.data(), zero.data());
  const double e0 = sim::mechanical_energy(model, scene.effects, scene.joints.data(), q.data(), qd.data());
  int most = 0, krylov = 0;
  for (int k = 0; k < 60; ++k) {
    const sim::VariationalResult r = sim::variational_step<sim::kGravity>(
        model, w, 2e-5, coef.data(), q.data(), qd.data(), tau.data(), static_cast<const Force<double>*>(nullptr));
    ASSERT_EQ(r.failed_dof, -1) << "step " << k;
    ASSERT_FALSE(r.dense_fallback) << "step " << k;
    if (k < 20) {
      EXPECT_FALSE(r.krylov) << "step " << k;
    }
    krylov += r.krylov;
    most = std::max(most, r.iterations);
  }
  EXPECT_TRUE(w.D.empty());  // no nv x nv scratch was made
  const double e = sim::mechanical_energy(model, scene.effects, scene.joints.data(), q.data(), qd.data());
  std::printf("rope:1000 dt 2e-5, 60 steps: %d by Newton-Krylov, at most %d updates, energy error %.3g\n", krylov,
              most, std::abs(e - e0) / std::abs(e0 - rest));
  EXPECT_GT(krylov, 0);
  EXPECT_LE(most, 12);
  EXPECT_LE(std::abs(e - e0) / std::abs(e0 - rest), 1e-8);
}

// Serial and OpenMP step every instance by the same code: bit-identical.
TEST(SimVariational, SerialEqualsOpenMP) {
  Scene scene = scene_of("iiwa.urdf", "variational", 2e-3,
                         ", \"effects\": {\"gravity\": true, \"damping\": 0.1}, \"initial\": {\"random\": {\"seed\": "
                         "3, \"q\": 0.5, \"qd\": 0.5}}");
  scene.instances = 5;
  scene.threads = 2;
  Simulator<double> serial(scene, BackendKind::Serial), omp(scene, BackendKind::OpenMP);
  for (int s = 0; s < 200; ++s) serial.step(), omp.step();
  std::vector<double> q0(35), qd0(35), q1(35), qd1(35);
  serial.read_state(q0.data(), qd0.data());
  omp.read_state(q1.data(), qd1.data());
  EXPECT_EQ(q0, q1);
  EXPECT_EQ(qd0, qd1);
}

// float: iiwa for 10^4 steps at dt = 2e-3 keeps its energy within 5e-3 of the
// swinging energy (measured 2.2e-3: double's truncation error, 1.8e-3 over 10^5
// steps, dominates float's rounding).
TEST(SimVariational, FloatBounded) {
  const Scene scene = scene_of("iiwa.urdf", "variational", 2e-3, kIiwa);
  Simulator<float> sim(scene, BackendKind::Serial);
  const std::vector<double> zero(scene.nv(), 0.0);
  const double rest = sim::mechanical_energy(scene.model, scene.effects, scene.joints.data(), zero.data(), zero.data());
  const double e0 = sim.energy()[0];
  double worst = 0;
  for (int s = 0; s < 10000; ++s) {
    sim.step();
    if (s % 100 == 99) worst = std::max(worst, std::abs(sim.energy()[0] - e0) / std::abs(e0 - rest));
  }
  std::printf("iiwa float dt 2e-3, 1e4 steps: worst %.3g\n", worst);
  ASSERT_TRUE(sim.status().ok()) << sim::failure_message(sim.status());
  EXPECT_LE(worst, 5e-3);
}

}  // namespace
}  // namespace scandyn
