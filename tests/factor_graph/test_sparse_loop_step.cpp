// The simulator's sparse loop path (scandyn/factor_graph/sparse_constrained_dynamics.hpp,
// scene key "loop_solver"; docs/loops.md): its constrained forward dynamics and
// projection against the dense ones (constrained_forward_dynamics,
// project_to_loops), the sparse simulator step against the dense step on small
// grids and the five-bar, and the closure error over a rollout.
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>
#include <string>

#include "loop_cases.hpp"
#include "scandyn/factor_graph/sparse_constrained_dynamics.hpp"
#include "scandyn/io/csv.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sim/simulator.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

using test::max_abs;
using test::max_diff;

#if SCANDYN_HAS_CHOLMOD
using factor_graph::SparseConstrainedDynamics;

const std::vector<std::string> kCases = {"fivebar", "fivebar+weld", "fourbar", "cloth:4:4", "cloth:8:8"};

TEST(SparseLoopStep, ForwardDynamicsAndProjectionEqualTheDenseOnes) {
  std::mt19937_64 rng(21);
  for (const test::LoopCase& c : test::loop_cases(kCases)) {
    const Index nv = c.model.nv(), m = c.loops.rows();
    const double tau_scale = c.spec.rfind("cloth", 0) == 0 ? 1e-3 : 1.0;
    SparseConstrainedDynamics sparse(c.model, c.loops);
    for (int trial = 0; trial < 3; ++trial) {
      SCOPED_TRACE(c.spec + " state " + std::to_string(trial));
      std::vector<double> q, qd;
      ASSERT_LE(test::closed_state(c, rng, q, qd), 1e-12);
      const auto tau = test::random_vector(rng, nv, -tau_scale, tau_scale);
      std::vector<double> qdd_ref(nv), lambda_ref(m), qdd(nv), lambda(m);
      constrained_forward_dynamics(c.model, c.loops, q.data(), qd.data(), tau.data(), qdd_ref.data(),
                                   lambda_ref.data());
      sparse.forward_dynamics(q.data(), qd.data(), tau.data(), qdd.data(), lambda.data());
      EXPECT_LE(max_diff(qdd, qdd_ref), 1e-9 * max_abs(qdd_ref)) << "qdd";
      // velocities projected at a closed q: the same minimum-norm change (J qd = 0 is
      // consistent, J^+ unique)
      std::vector<double> qp = q, qdp = qd;
      for (Index i = 0; i < nv; ++i) qdp[i] += 1e-2 * std::cos(2.0 + i);
      std::vector<double> q_ref = qp, qd_ref = qdp;
      project_to_loops(c.model, c.loops, q_ref.data(), qd_ref.data(), 1e-12, 0);
      sparse.project(qp.data(), qdp.data(), 1e-12, 0);
      EXPECT_LE(max_diff(qdp, qd_ref), 1e-12 * std::max(1.0, max_abs(qd_ref))) << "projected qd";
      // positions off the loops: Gauss-Newton to |phi| <= 1e-12 and J qd = 0. The end
      // points agree to 1e-11 on the five-bars; on the cloths only up to the
      // directions J barely constrains (singular values ~1e-6 on cloth:4:4), where
      // |phi| <= 1e-12 leaves q undetermined by ~1e-12 / 1e-6, and an inconsistent
      // phi (not in J's range) makes the first step's least squares weigh the rows
      // differently (the graph's scaled equations, the dense solve's plain rows)
      for (Index i = 0; i < nv; ++i) qp[i] += 1e-4 * std::sin(1.0 + i), qdp[i] += 1e-2 * std::cos(2.0 + i);
      q_ref = qp, qd_ref = qdp;
      const double r_ref = project_to_loops(c.model, c.loops, q_ref.data(), qd_ref.data(), 1e-12, 10);
      const double r = sparse.project(qp.data(), qdp.data(), 1e-12, 10);
      EXPECT_LE(r, 1e-12);
      EXPECT_LE(r_ref, 1e-12);
      if (c.spec.rfind("cloth", 0) != 0) {
        EXPECT_LE(max_diff(qp, q_ref), 1e-11) << "projected q";
      }
      EXPECT_LE(loop_violation(c.model, c.loops, qp.data(), qdp.data()), 1e-11);
    }
  }
}

// The simulator's state after `steps` steps of the scene with the given loop solver.
void rollout(const std::string& model, const std::string& solver, const char* integrator, double dt, int steps,
             std::vector<double>& q, std::vector<double>& qd, double* worst_closure = nullptr) {
  // the same closed initial state for both solvers: q = 0.1, qd = 0.5 projected by
  // the dense solve (each solver's own projection from off the loops ends at a
  // different point of them: the least squares of an inconsistent phi differ)
  const Model mdl = load_model(model);
  const LoopSet loops = generator_loops(model, mdl);
  std::vector<double> q0(mdl.nv(), 0.1), qd0(mdl.nv(), 0.5);
  project_to_loops(mdl, loops, q0.data(), qd0.data());
  auto array = [](const std::vector<double>& x) { return io::number_array(x.data(), x.size()); };
  const sim::Scene scene = sim::parse_scene(std::string(R"({"model": ")") + model +
                                                R"(", "effects": {"gravity": true}, "integrator": ")" +
                                                integrator + R"(", "loop_solver": ")" + solver + R"(", "dt": )" +
                                                std::to_string(dt) + R"(, "initial": {"q": )" + array(q0) + R"(, "qd": )" + array(qd0) + "}}",
                                            "test.json");
  sim::Simulator<double> s(scene, BackendKind::Serial);
  const Index n = s.nv();
  q.resize(n), qd.resize(n);
  for (int k = 0; k < steps; ++k) {
    s.step();
    if (worst_closure) {
      s.read_state(q.data(), qd.data());
      *worst_closure = std::max(*worst_closure, loop_violation(scene.model, scene.loops, q.data(), qd.data()));
    }
  }
  ASSERT_TRUE(s.status().ok()) << sim::failure_message(s.status());
  s.read_state(q.data(), qd.data());
}

TEST(SparseLoopStep, SimulatorStepEqualsTheDenseStep) {
  factor_graph::register_sparse_loop_solver();
  struct Case {
    const char* model;
    const char* integrator;
    int steps;
    double dt;
  } cases[] = {{"fivebar", "rk4", 200, 1e-3}, {"fivebar", "euler", 200, 1e-3}, {"cloth:4:4", "rk4", 100, 2e-4},
               {"cloth:8:8", "rk4", 50, 2e-4}, {"cloth:8:8", "euler", 50, 2e-4}};
  for (const Case& c : cases) {
    SCOPED_TRACE(std::string(c.model) + " " + c.integrator);
    std::vector<double> q, qd, q_ref, qd_ref;
    rollout(c.model, "sparse", c.integrator, c.dt, c.steps, q, qd);
    rollout(c.model, "dense", c.integrator, c.dt, c.steps, q_ref, qd_ref);
    EXPECT_GT(max_diff(q_ref, std::vector<double>(q_ref.size(), 0.2)), 1e-3) << "the mechanism moved";
    // measured: q within 1e-15, qd within 1.2e-13 (cloth:8:8, 50 steps, |qd| ~ 8 rad/s)
    EXPECT_LE(max_diff(q, q_ref), 1e-12 * std::max(1.0, max_abs(q_ref))) << "q";
    EXPECT_LE(max_diff(qd, qd_ref), 1e-11 * std::max(1.0, max_abs(qd_ref))) << "qd";
  }
}

TEST(SparseLoopStep, ClosureBoundedOverARollout) {
  factor_graph::register_sparse_loop_solver();
  std::vector<double> q, qd;
  double worst = 0;
  rollout("cloth:8:8", "sparse", "rk4", 2e-4, 500, q, qd, &worst);
  EXPECT_LE(worst, 1e-11);
}

TEST(SparseLoopStep, SceneChoosesTheSolver) {
  factor_graph::register_sparse_loop_solver();
  // "sparse" with contacts is refused; an unknown value is a scene error
  auto error_of = [](const std::string& json) -> std::string {
    try {
      sim::Simulator<double> s(sim::parse_scene(json, "test.json"), BackendKind::Serial);
    } catch (const std::exception& e) {
      return e.what();
    }
    return "";
  };
  EXPECT_NE(error_of(R"({"model": "fivebar", "dt": 0.001, "loop_solver": "qr"})").find("loop_solver"),
            std::string::npos);
  EXPECT_EQ(error_of(R"({"model": "fivebar", "dt": 0.001, "loop_solver": "sparse"})"), "");
}
// Levenberg-Marquardt's damped step through the projection system with the loop
// rows' compliance mu: J^T (J J^T + mu I)^-1 r in the model's units, i.e. for point
// loops the dense J^T (J J^T + mu L^2 I)^-1 r (J from loop_kinematics, an LDL^T of the
// m x m matrix: an independent reference); mu = 0 is J^+ r (the projection's
// minimum-norm step, checked above).
TEST(SparseLoopStep, DampedStepEqualsTheDenseOne) {
  std::mt19937_64 rng(7);
  for (const test::LoopCase& c : test::loop_cases({"fivebar", "fourbar", "cloth:4:4"})) {
    const Index nv = c.model.nv(), m = c.loops.rows();
    SparseConstrainedDynamics sparse(c.model, c.loops);
    const double L = factor_graph::model_units(c.model).length;
    std::vector<double> q, qd;
    ASSERT_LE(test::closed_state(c, rng, q, qd), 1e-12);
    for (Index i = 0; i < nv; ++i) q[i] += 0.3 * std::sin(1.0 + i);  // off the loops: any q will do
    Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> J(m, nv);
    loop_kinematics(c.model, c.loops, q.data(), nullptr, nullptr, J.data(), nullptr);
    const auto r = test::random_vector(rng, m, -1e-2, 1e-2);
    const Eigen::Map<const Eigen::VectorXd> rv(r.data(), m);
    for (double mu : {1e-2, 1.0}) {
      SCOPED_TRACE(c.spec + " mu " + std::to_string(mu));
      const Eigen::MatrixXd A = J * J.transpose() + mu * L * L * Eigen::MatrixXd::Identity(m, m);
      const Eigen::VectorXd ref = J.transpose() * A.ldlt().solve(rv);
      std::vector<double> x(nv);
      sparse.min_norm_step(q.data(), r.data(), mu, x.data());
      std::vector<double> xr(ref.data(), ref.data() + nv);
      EXPECT_LE(max_diff(x, xr), 1e-9 * max_abs(xr));
    }
  }
}

// The sparse path's reset from far off the loops (Levenberg-Marquardt, each damping
// one factorisation) closes as the dense one does, and a step whose projection does
// not close is the instance's reported failure (SimLoops.StepProjectionFailureIsReported
// on the sparse path).
TEST(SparseLoopStep, FarResetClosesAndStepFailureIsReported) {
  factor_graph::register_sparse_loop_solver();
  {
    const sim::Scene scene = sim::parse_scene(R"({"model": "cloth:6:6", "dt": 0.001, "instances": 2,
        "loop_solver": "sparse", "initial": {"random": {"seed": 3, "q": 1.0}}})", "test.json");
    sim::Simulator<double> s(scene, BackendKind::Serial);
    const Index n = s.nv();
    std::vector<double> q(n * 2), qd(n * 2), qb(n), qdb(n);
    s.read_state(q.data(), qd.data());
    for (Index b = 0; b < 2; ++b) {
      for (Index i = 0; i < n; ++i) qb[i] = q[i * 2 + b], qdb[i] = qd[i * 2 + b];
      EXPECT_LE(loop_violation(scene.model, scene.loops, qb.data(), qdb.data()), 1e-12) << "instance " << b;
    }
  }
  const sim::Scene scene = sim::parse_scene(R"({"model": "cloth:4:4", "dt": 0.01, "integrator": "euler",
      "instances": 2, "loop_solver": "sparse", "initial": {"q": 0.3, "qd": 0.0}})", "test.json");
  sim::Simulator<double> s(scene, BackendKind::Serial);
  const Index n = s.nv();
  std::vector<double> tau(n * 2, 0.0), q(n * 2), qd(n * 2), before;
  for (Index i = 0; i < n; ++i) tau[i * 2 + 1] = 1e3 * std::cos(1.0 + i);
  for (int k = 0; k < 5 && s.status().ok(); ++k) {
    s.read_state(q.data(), qd.data());
    before = q;
    s.step(BatchView<const double>::soa(tau.data(), n, 2));
  }
  const BatchStatus st = s.status();
  ASSERT_FALSE(st.ok()) << "the driven instance's projection closed its loops every step";
  EXPECT_EQ(st.failed, 1);
  EXPECT_EQ(st.first_instance, 1);
  EXPECT_EQ(st.failure, Failure::LoopNotClosed);
  EXPECT_GT(st.estimate, kLoopStateTolerance) << sim::failure_message(st);
  s.read_state(q.data(), qd.data());
  for (Index i = 0; i < n; ++i) EXPECT_EQ(q[i * 2 + 1], before[i * 2 + 1]);  // kept its state
}

#if SCANDYN_HAS_FACTOR_GRAPH_GPU
// The GPU's factorisations (cuSOLVER under CHOLMOD's order) in the same step.
TEST(SparseLoopStep, GpuSolverStepEqualsTheDenseStep) {
  {
    const test::LoopCase c = test::loop_cases({"fivebar"})[0];
    SparseConstrainedDynamics probe(c.model, c.loops, factor_graph::Ordering::NESDIS, true);
    try {
      probe.forward_dynamics_stats();  // analyses, cuSOLVER's included: throws without a device
    } catch (const std::runtime_error& e) {
      GTEST_SKIP() << "no CUDA device: " << e.what();
    }
  }
  factor_graph::register_sparse_loop_solver(true);
  for (const char* model : {"fivebar", "cloth:8:8"}) {
    SCOPED_TRACE(model);
    std::vector<double> q, qd, q_ref, qd_ref;
    rollout(model, "sparse", "rk4", 2e-4, 50, q, qd);
    rollout(model, "dense", "rk4", 2e-4, 50, q_ref, qd_ref);
    EXPECT_LE(max_diff(q, q_ref), 1e-9 * std::max(1.0, max_abs(q_ref))) << "q";
    EXPECT_LE(max_diff(qd, qd_ref), 1e-8 * std::max(1.0, max_abs(qd_ref))) << "qd";
  }
  factor_graph::register_sparse_loop_solver(false);
}
#endif
#else
TEST(SparseLoopStep, NeedsCholmod) { GTEST_SKIP() << "built without SuiteSparse CHOLMOD"; }
#endif

}  // namespace
}  // namespace scandyn
