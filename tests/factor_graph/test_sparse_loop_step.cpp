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
#include "loop_solver_checks.hpp"
#include "scandyn/factor_graph/sparse_constrained_dynamics.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sim/simulator.hpp"
#include "scene_util.hpp"
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
    SparseConstrainedDynamics sparse(c.model, c.loops);
    for (int trial = 0; trial < 3; ++trial) {
      SCOPED_TRACE(c.spec + " state " + std::to_string(trial));
      test::ForwardDynamicsPair fd;
      ASSERT_NO_FATAL_FAILURE(fd.solve(c, rng, sparse));
      EXPECT_LE(max_diff(fd.qdd, fd.qdd_ref), 1e-9 * max_abs(fd.qdd_ref)) << "qdd";
      // the projections: qd at a closed q to 1e-12, positions off the loops closed to 1e-11
      test::expect_projections_equal_dense(c, fd.q, fd.qd, sparse, 1e-12, 1e-11);
    }
  }
}

TEST(SparseLoopStep, SimulatorStepEqualsTheDenseStep) {
  factor_graph::register_sparse_loop_solver();
  // measured: q within 1e-15, qd within 1.2e-13 (cloth:8:8, 50 steps, |qd| ~ 8 rad/s)
  test::expect_steps_equal_dense("sparse", 1e-12, 1e-11, 0.2);
}

TEST(SparseLoopStep, ClosureBoundedOverARollout) {
  factor_graph::register_sparse_loop_solver();
  std::vector<double> q, qd;
  double worst = 0;
  test::loop_rollout("cloth:8:8", "sparse", "rk4", 2e-4, 500, q, qd, &worst);
  EXPECT_LE(worst, 1e-11);
}

TEST(SparseLoopStep, SceneChoosesTheSolver) {
  factor_graph::register_sparse_loop_solver();
  // "sparse" with contacts is refused; an unknown value is a scene error
  const auto error_of = test::simulator_error;
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
    test::expect_rollout_equals_dense(model, "sparse", "rk4", 2e-4, 50, 1e-9, 1e-8);
  }
  factor_graph::register_sparse_loop_solver(false);
}
#endif
#else
TEST(SparseLoopStep, NeedsCholmod) { GTEST_SKIP() << "built without SuiteSparse CHOLMOD"; }
#endif

}  // namespace
}  // namespace scandyn
