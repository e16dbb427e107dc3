// Prescribed joint motion in the simulator (scene key "prescribed", docs/scenes.md):
// the trajectories (sine: closed form; table: a clamped cubic spline through the
// knots, checked by finite differences), the scene's checks, driven DoFs on their
// trajectories after every step, and the other DoFs against an independent
// integration of the same ODE (the joint-space hybrid equations M_ff qdd_f = tau_f -
// h_f - M_fp qdd_p by Eigen, the same RK4 / semi-implicit Euler stages): 1e-9 over
// 400 steps in double.
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <cmath>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sim/simulator.hpp"
#include "scene_util.hpp"
#include "test_util.hpp"

using namespace scandyn;
using namespace scandyn::sim;

namespace {

using test::scene_from;

}  // namespace

TEST(PrescribedTrajectory, SineIsClosedForm) {
  const JointTrajectory s = sine_trajectory(0.5, 2.0, 0.3, 0.1);
  double q, qd, qdd;
  s.eval(0.7, q, qd, qdd);
  const double w = 4 * M_PI;
  EXPECT_NEAR(q, 0.1 + 0.5 * std::sin(w * 0.7 + 0.3), 1e-15);
  EXPECT_NEAR(qd, 0.5 * w * std::cos(w * 0.7 + 0.3), 1e-13);
  EXPECT_NEAR(qdd, -0.5 * w * w * std::sin(w * 0.7 + 0.3), 1e-12);
}

TEST(PrescribedTrajectory, TableSplineThroughKnotsWithDerivatives) {
  const std::vector<double> t{0, 0.4, 1.0, 1.3, 2.5}, qk{0.2, -0.5, 0.7, 0.7, -1.0};
  const JointTrajectory s = table_trajectory(t, qk);
  double q, qd, qdd;
  for (std::size_t k = 0; k < t.size(); ++k) {
    s.eval(t[k] + (k + 1 == t.size() ? 0.0 : 1e-14), q, qd, qdd);
    EXPECT_NEAR(q, qk[k], 1e-12) << "knot " << k;
  }
  // zero velocity at the ends; held outside
  s.eval(1e-9, q, qd, qdd);
  EXPECT_NEAR(qd, 0, 1e-7);
  s.eval(2.5 - 1e-9, q, qd, qdd);
  EXPECT_NEAR(qd, 0, 1e-7);
  s.eval(-1, q, qd, qdd);
  EXPECT_EQ(q, 0.2);
  EXPECT_EQ(qd, 0);
  s.eval(9, q, qd, qdd);
  EXPECT_EQ(q, -1.0);
  // qd and qdd are the derivatives (central differences), across knots too
  for (double x : {0.1, 0.39, 0.41, 0.9, 1.2, 2.0}) {
    const double h = 1e-6;
    double qp, qm, dp, dm, a;
    s.eval(x + h, qp, dp, a);
    s.eval(x - h, qm, dm, a);
    s.eval(x, q, qd, qdd);
    EXPECT_NEAR(qd, (qp - qm) / (2 * h), 1e-6) << x;
    EXPECT_NEAR(qdd, (dp - dm) / (2 * h), 1e-5) << x;
  }
  EXPECT_THROW(table_trajectory({0, 0}, {1, 2}), std::invalid_argument);
  EXPECT_THROW(table_trajectory({0}, {1}), std::invalid_argument);
}

TEST(PrescribedScene, ErrorsNameTheKey) {
  const std::string head = R"({"model": "chain:3", "dt": 0.001, "prescribed": )";
  struct Case {
    std::string body, message;
  } cases[] = {
      {R"({"joints": ["nope"], "trajectory": [{"sine": {}}]})", "prescribed.joints[0]: unknown joint 'nope'"},
      {R"({"joints": [0, 0], "trajectory": [{"sine": {}}, {"sine": {}}]})", "prescribed.joints[1]: DoF 0 is listed twice"},
      {R"({"joints": [3], "trajectory": [{"sine": {}}]})", "prescribed.joints[0]: expected an integer from 0 to 2"},
      {R"({"joints": [0], "trajectory": []})", "prescribed.trajectory: expected an array of 1 trajectories"},
      {R"({"joints": [0], "trajectory": [{"table": [[0, 1], [0, 2]]}]})",
       "prescribed.trajectory[0].table[1]: times must increase strictly"},
      {R"({"joints": [0], "trajectory": [{"sine": {"freq": 1}}]})", "prescribed.trajectory[0].sine.freq: unknown key"},
      {R"({"joints": [0], "trajectory": [{"sine": {"frequency": -1}}]})",
       "prescribed.trajectory[0].sine.frequency: expected a non-negative number"},
      {R"({"joints": [0]})", "prescribed.trajectory: missing"},
  };
  for (const Case& c : cases) {
    try {
      scene_from(head + c.body + "}");
      ADD_FAILURE() << "accepted: " << c.body;
    } catch (const SceneError& e) {
      EXPECT_NE(std::string(e.what()).find("test.json: " + c.message), std::string::npos) << e.what();
    }
  }
  const Scene ok = scene_from(head + R"({"joints": ["joint_2", 0], "trajectory": [{"sine": {"amplitude": 1}},
                                       {"table": [[0, 0], [1, 1]]}]})" + "}");
  ASSERT_EQ(ok.prescribed.dofs.size(), 2u);
  EXPECT_EQ(ok.prescribed.dofs[0], 2);
  EXPECT_EQ(ok.prescribed.dofs[1], 0);
}

namespace {

// The independent integration: the free DoFs' ODE by the joint-space hybrid
// equations (crba, bias_forces, Eigen), the driven DoFs on their trajectories.
struct JointSpaceHybrid {
  const Model& m;
  const PrescribedMotion& p;
  std::vector<unsigned char> mask;
  Data d;
  JointSpaceHybrid(const Model& model, const PrescribedMotion& pm) : m(model), p(pm), mask(pm.mask(model.nv())), d(model) {}

  // qdd of every DoF at time t for state (q, qd) of the free DoFs (driven entries overwritten)
  std::vector<double> qdd(double t, std::vector<double> q, std::vector<double> qd) {
    const Index n = m.nv();
    std::vector<double> a(n, 0.0);
    for (std::size_t j = 0; j < p.dofs.size(); ++j) {
      double x, v, acc;
      p.trajectory[j].eval(t, x, v, acc);
      q[p.dofs[j]] = x, qd[p.dofs[j]] = v, a[p.dofs[j]] = acc;
    }
    std::vector<double> M(n * n), h(n);
    crba(m, d, q.data(), M.data());
    bias_forces(m, d, q.data(), qd.data(), h.data());
    std::vector<Index> f;
    for (Index i = 0; i < n; ++i)
      if (!mask[i]) f.push_back(i);
    Eigen::MatrixXd Mff(f.size(), f.size());
    Eigen::VectorXd r(f.size());
    for (std::size_t x = 0; x < f.size(); ++x) {
      r[x] = -h[f[x]];
      for (Index j : p.dofs) r[x] -= M[f[x] * n + j] * a[j];
      for (std::size_t y = 0; y < f.size(); ++y) Mff(x, y) = M[f[x] * n + f[y]];
    }
    const Eigen::VectorXd s = Mff.ldlt().solve(r);
    for (std::size_t x = 0; x < f.size(); ++x) a[f[x]] = s[x];
    return a;
  }
};

}  // namespace

// A pendulum chain whose first joint is driven by a sine and whose third follows a
// table: driven DoFs on their trajectories after every step; the others as the
// independent integration (rk4 and euler, zero torques, gravity).
TEST(PrescribedSimulation, DrivenJointsFollowAndTheRestMatchesHybridOde) {
  for (const char* integrator : {"rk4", "euler"}) {
    SCOPED_TRACE(integrator);
    const Scene scene = scene_from(std::string(R"({"model": "chain:5", "effects": {"gravity": true}, "integrator": ")") +
                                   integrator + R"(", "dt": 0.002, "instances": 2, "initial": {"q": [0, 0.3, 0, -0.2, 0.1]},
        "prescribed": {"joints": [0, 2], "trajectory": [{"sine": {"amplitude": 0.8, "frequency": 0.5, "offset": 0.1}},
                                                      {"table": [[0, 0], [0.3, 0.6], [0.8, -0.4]]}]}})");
    for (BackendKind backend : {BackendKind::Serial, BackendKind::OpenMP}) {
      if (!backend_unusable(backend).empty()) continue;
      Simulator<double> s(scene, backend);
      const Index n = s.nv(), B = s.batch();
      JointSpaceHybrid ref(scene.model, scene.prescribed);
      std::vector<double> q(scene.initial.q), qd(n, 0.0);
      std::vector<double> sq(n * B), sqd(n * B);
      const double dt = scene.dt;
      for (int k = 0; k < 400; ++k) {
        const double t = k * dt;
        if (std::string(integrator) == "rk4") {
          auto deriv = [&](double ts, const std::vector<double>& x, const std::vector<double>& v) {
            return ref.qdd(ts, x, v);
          };
          std::vector<double> k1v = qd, k1a = deriv(t, q, qd), x(n), v(n);
          for (Index i = 0; i < n; ++i) x[i] = q[i] + 0.5 * dt * k1v[i], v[i] = qd[i] + 0.5 * dt * k1a[i];
          std::vector<double> k2v = v, k2a = deriv(t + 0.5 * dt, x, v);
          for (Index i = 0; i < n; ++i) x[i] = q[i] + 0.5 * dt * k2v[i], v[i] = qd[i] + 0.5 * dt * k2a[i];
          std::vector<double> k3v = v, k3a = deriv(t + 0.5 * dt, x, v);
          for (Index i = 0; i < n; ++i) x[i] = q[i] + dt * k3v[i], v[i] = qd[i] + dt * k3a[i];
          std::vector<double> k4v = v, k4a = deriv(t + dt, x, v);
          for (Index i = 0; i < n; ++i) {
            q[i] += dt / 6 * (k1v[i] + 2 * k2v[i] + 2 * k3v[i] + k4v[i]);
            qd[i] += dt / 6 * (k1a[i] + 2 * k2a[i] + 2 * k3a[i] + k4a[i]);
          }
        } else {
          const std::vector<double> a = ref.qdd(t, q, qd);
          for (Index i = 0; i < n; ++i) qd[i] += dt * a[i], q[i] += dt * qd[i];
        }
        for (std::size_t j = 0; j < scene.prescribed.dofs.size(); ++j) {
          double a;
          scene.prescribed.trajectory[j].eval(t + dt, q[scene.prescribed.dofs[j]], qd[scene.prescribed.dofs[j]], a);
        }
        s.step();
        ASSERT_TRUE(s.status().ok()) << failure_message(s.status());
        s.read_state(sq.data(), sqd.data());
        for (Index b = 0; b < B; ++b)
          for (Index i = 0; i < n; ++i) {
            if (std::find(scene.prescribed.dofs.begin(), scene.prescribed.dofs.end(), i) !=
                scene.prescribed.dofs.end()) {
              ASSERT_EQ(sq[i * B + b], q[i]) << "driven DoF " << i << " step " << k;
              ASSERT_EQ(sqd[i * B + b], qd[i]) << "driven DoF " << i << " step " << k;
            } else {
              ASSERT_NEAR(sq[i * B + b], q[i], 1e-9) << "DoF " << i << " step " << k;
              ASSERT_NEAR(sqd[i * B + b], qd[i], 1e-8) << "DoF " << i << " step " << k;
            }
          }
      }
      // the driven motion moved the free joints
      EXPECT_GT(std::fabs(q[1] - 0.3), 1e-2);
    }
  }
}
