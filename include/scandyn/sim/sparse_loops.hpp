// scandyn/sim/sparse_loops.hpp: the simulator's sparse path for closed loops
// (docs/loops.md, "The simulator's sparse loop path").
//
// The dense loop step (constrained_forward_dynamics, project_to_loops: O(nv^3)) is
// right for five-bars and small grids; a large grid (cloth:100:100, 10^4 DoF) needs
// a sparse solver. That solver lives in the factor-graph library
// (scandyn_factor_graph, CHOLMOD: scandyn/factor_graph/sparse_constrained_dynamics.hpp),
// which links this library, so the simulator reaches it through this interface: a
// program that links scandyn_factor_graph calls
// factor_graph::register_sparse_loop_solver() once, and scenes with loops may then
// step through it (scene key "loop_solver": "dense", "sparse" or "auto").
#pragma once

#include <memory>

#include "scandyn/algorithm/loops.hpp"
#include "scandyn/model/model.hpp"

namespace scandyn::sim {

// One instance's closed-loop solves, in double, for one model and loop set; the
// symbolic analysis (the elimination ordering) is the object's, done once at
// construction, and every call repeats only the numeric factorisation.
class LoopSolver {
 public:
  virtual ~LoopSolver() = default;
  // constrained_forward_dynamics's contract (gravity of the model included, no
  // external wrenches): M qdd + h = tau + J^T lambda, J qdd + gamma = 0. lambda (m)
  // may be null. Throws LoopError when the factorisation fails.
  virtual void forward_dynamics(const double* q, const double* qd, const double* tau, double* qdd,
                                double* lambda) = 0;
  // project_to_loops's contract: Levenberg-Marquardt around Gauss-Newton (minimum-norm
  // steps) of scandyn/algorithm/loop_projection.hpp on phi(q) = 0 until max |phi| <=
  // tol or `iterations` linearisations, then qd's minimum-norm change with J qd = 0.
  // Returns the final max |phi|; info (may be null): max |J qd| after, the worst row,
  // the linearisations (factorisations) and trials. Throws LoopError when a
  // factorisation fails.
  virtual double project(double* q, double* qd, double tol, int iterations, LoopProjectionInfo* info = nullptr) = 0;
};

using LoopSolverFactory = std::unique_ptr<LoopSolver> (*)(const Model& model, const LoopSet& loops);

// The registered sparse loop solver (null until a program registers one).
void set_sparse_loop_solver(LoopSolverFactory factory);
LoopSolverFactory sparse_loop_solver();

// scene "loop_solver": "auto" picks the sparse solver from this many DoFs on (when
// one is registered and the scene has no contacts or external wrenches; else the
// iterative one, scandyn/sim/iterative_loops.hpp): the dense solve is O(nv^3) and the
// sparse one's analysis costs ~10 ms at 100 DoF (docs/loops.md's table).
inline constexpr Index kSparseLoopDofs = 200;

}  // namespace scandyn::sim
