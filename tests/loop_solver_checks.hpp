// tests/loop_solver_checks.hpp: the checks of a loop solver against the dense one that
// the sparse and the iterative solvers share (tests/factor_graph/test_sparse_loop_step.cpp,
// tests/sim/test_iterative_loops.cpp): their projections onto the loops, and simulator
// rollouts of a closed-loop generator model under a named loop solver (scene key
// "loop_solver": "dense", "sparse", "iterative").
#pragma once

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <string>
#include <vector>

#include "loop_cases.hpp"
#include "scandyn/algorithm/loops.hpp"
#include "scandyn/io/csv.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sim/simulator.hpp"
#include "test_util.hpp"

namespace scandyn::test {

// A loop solver's forward dynamics next to the dense one (constrained_forward_dynamics)
// at a random closed state of c (closed_state) under random torques (within 1, or 1e-3
// on the cloths, whose links are small): the state, the torques, and both solutions.
struct ForwardDynamicsPair {
  std::vector<double> q, qd, tau, qdd, lambda, qdd_ref, lambda_ref;

  template <class Solver>
  void solve(const LoopCase& c, std::mt19937_64& rng, Solver& solver) {
    const Index nv = c.model.nv(), m = c.loops.rows();
    const double tau_scale = c.spec.rfind("cloth", 0) == 0 ? 1e-3 : 1.0;
    ASSERT_LE(closed_state(c, rng, q, qd), 1e-12);
    tau = random_vector(rng, nv, -tau_scale, tau_scale);
    qdd_ref.resize(nv), lambda_ref.resize(m), qdd.resize(nv), lambda.resize(m);
    constrained_forward_dynamics(c.model, c.loops, q.data(), qd.data(), tau.data(), qdd_ref.data(),
                                 lambda_ref.data());
    solver.forward_dynamics(q.data(), qd.data(), tau.data(), qdd.data(), lambda.data());
  }
};

// A loop solver's projections, solver.project(q, qd, tol, iterations) (as
// project_to_loops), against the dense ones from a closed state (q, qd) of c. The
// velocities, qd disturbed at the closed q: the same minimum-norm change (J qd = 0 is
// consistent, J^+ unique), within qd_tol relative to max(1, max |qd|). The positions off
// the loops, q and qd disturbed: Gauss-Newton to |phi| <= 1e-12 and J qd = 0 for both,
// loop_violation within closure_tol. The end points agree to 1e-11 on the five-bars; on
// the cloths only up to the directions J barely constrains (singular values ~1e-6 on
// cloth:4:4), where |phi| <= 1e-12 leaves q undetermined by ~1e-12 / 1e-6, and an
// inconsistent phi (not in J's range) makes the first step's least squares weigh the
// rows differently (e.g. the graph's scaled equations, the dense solve's plain rows), so
// q is compared on the others only. Returns the velocity projection's error relative to
// max(1, max |qd|).
template <class Solver>
double expect_projections_equal_dense(const LoopCase& c, const std::vector<double>& q, const std::vector<double>& qd,
                                      Solver& solver, double qd_tol, double closure_tol) {
  const Index nv = c.model.nv();
  std::vector<double> qp = q, qdp = qd;
  for (Index i = 0; i < nv; ++i) qdp[i] += 1e-2 * std::cos(2.0 + i);
  std::vector<double> q_ref = qp, qd_ref = qdp;
  project_to_loops(c.model, c.loops, q_ref.data(), qd_ref.data(), 1e-12, 0);
  solver.project(qp.data(), qdp.data(), 1e-12, 0);
  const double qd_err = max_diff(qdp, qd_ref) / std::max(1.0, max_abs(qd_ref));
  EXPECT_LE(max_diff(qdp, qd_ref), qd_tol * std::max(1.0, max_abs(qd_ref))) << "projected qd";
  for (Index i = 0; i < nv; ++i) qp[i] += 1e-4 * std::sin(1.0 + i), qdp[i] += 1e-2 * std::cos(2.0 + i);
  q_ref = qp, qd_ref = qdp;
  const double r_ref = project_to_loops(c.model, c.loops, q_ref.data(), qd_ref.data(), 1e-12, 10);
  const double r = solver.project(qp.data(), qdp.data(), 1e-12, 10);
  EXPECT_LE(r, 1e-12);
  EXPECT_LE(r_ref, 1e-12);
  if (c.spec.rfind("cloth", 0) != 0) {
    EXPECT_LE(max_diff(qp, q_ref), 1e-11) << "projected q";
  }
  EXPECT_LE(loop_violation(c.model, c.loops, qp.data(), qdp.data()), closure_tol);
  return qd_err;
}

// The simulator's state after `steps` steps (serial, gravity) of `model` with the given
// loop solver and integrator, from q = 0.1, qd = 0.5 projected by the dense solve: the
// same closed start for every solver (each solver's own projection from off the loops
// ends at a different point of them: the least squares of an inconsistent phi differ).
// worst_closure, when given, takes the largest loop_violation after any step.
inline void loop_rollout(const std::string& model, const std::string& solver, const char* integrator, double dt,
                         int steps, std::vector<double>& q, std::vector<double>& qd, double* worst_closure = nullptr) {
  const Model mdl = load_model(model);
  const LoopSet loops = generator_loops(model, mdl);
  std::vector<double> q0(mdl.nv(), 0.1), qd0(mdl.nv(), 0.5);
  project_to_loops(mdl, loops, q0.data(), qd0.data());
  auto array = [](const std::vector<double>& x) { return io::number_array(x.data(), x.size()); };
  const sim::Scene scene = sim::parse_scene(std::string(R"({"model": ")") + model +
                                                R"(", "effects": {"gravity": true}, "integrator": ")" +
                                                integrator + R"(", "loop_solver": ")" + solver + R"(", "dt": )" +
                                                std::to_string(dt) + R"(, "initial": {"q": )" + array(q0) +
                                                R"(, "qd": )" + array(qd0) + "}}",
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

// `model` rolled out with `solver` and with the dense solver (loop_rollout): q within
// q_tol and qd within qd_tol of the dense rollout's, relative to max(1, max |dense|).
// Returns the dense rollout's q.
inline std::vector<double> expect_rollout_equals_dense(const std::string& model, const std::string& solver,
                                                       const char* integrator, double dt, int steps, double q_tol,
                                                       double qd_tol) {
  std::vector<double> q, qd, q_ref, qd_ref;
  loop_rollout(model, solver, integrator, dt, steps, q, qd);
  loop_rollout(model, "dense", integrator, dt, steps, q_ref, qd_ref);
  EXPECT_LE(max_diff(q, q_ref), q_tol * std::max(1.0, max_abs(q_ref))) << "q";
  EXPECT_LE(max_diff(qd, qd_ref), qd_tol * std::max(1.0, max_abs(qd_ref))) << "qd";
  return q_ref;
}

// The step comparisons: expect_rollout_equals_dense on the five-bar (rk4, euler; 200
// steps of 1 ms) and the cloths (4x4 rk4, 100 steps; 8x8 rk4 and euler, 50 steps; 0.2 ms
// steps for their small links), and the mechanism moved (the dense q at least 1e-3 from
// `moved_from` somewhere).
inline void expect_steps_equal_dense(const std::string& solver, double q_tol, double qd_tol, double moved_from) {
  struct Case {
    const char* model;
    const char* integrator;
    int steps;
    double dt;
  } cases[] = {{"fivebar", "rk4", 200, 1e-3}, {"fivebar", "euler", 200, 1e-3}, {"cloth:4:4", "rk4", 100, 2e-4},
               {"cloth:8:8", "rk4", 50, 2e-4}, {"cloth:8:8", "euler", 50, 2e-4}};
  for (const Case& c : cases) {
    SCOPED_TRACE(std::string(c.model) + " " + c.integrator);
    const std::vector<double> q_ref =
        expect_rollout_equals_dense(c.model, solver, c.integrator, c.dt, c.steps, q_tol, qd_tol);
    EXPECT_GT(max_diff(q_ref, std::vector<double>(q_ref.size(), moved_from)), 1e-3) << "the mechanism moved";
  }
}

}  // namespace scandyn::test
