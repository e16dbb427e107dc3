// scandyn/factor_graph/sparse_constrained_dynamics.hpp: the simulator's sparse path
// for closed loops (scandyn/sim/sparse_loops.hpp; docs/loops.md, "The simulator's
// sparse loop path"): one instance's constrained forward dynamics and its projection
// onto the loops through the factor graph's system (DynamicsGraph) and CHOLMOD
// (SparseCholesky), with the symbolic analysis (the elimination ordering and the
// factor's pattern) done once per system and only the numeric factorisation
// repeated per call.
//
// Two systems of the same pattern family, each analysed once:
//   forward dynamics  DynamicsGraph(model, loops), all tau given: Featherstone's
//                     constrained forward dynamics M qdd + h = tau + J^T lambda,
//                     J qdd + gamma = 0 (qdd unique; lambda one solution, not
//                     necessarily the minimum-norm one);
//   projection        the same tree with zero link inertias, no gravity and one
//                     armature c on every joint (the joint-space inertia c I) at
//                     qd = 0, its loop rows' right-hand side replaced by r: the
//                     solution is qdd = J^T mu with J qdd = r, the minimum-norm
//                     solution J^+ r of project_to_loops's steps (r = -phi for a
//                     Gauss-Newton step, r = -J qd for the velocity projection).
//                     The position steps are Levenberg-Marquardt's
//                     (scandyn/algorithm/loop_projection.hpp; Gauss-Newton from close
//                     to the loops): a damped step J^T (J J^T + mu I)^-1 r is the same
//                     system with the compliance mu on the loop rows' multipliers
//                     (J qdd + mu lambda = r; DynamicsGraph's loop_compliance), one
//                     more factorisation per damping tried; J v by walking the loops'
//                     paths.
//                     It is stored in the model's units (those of the forward
//                     dynamics, c = M L^2): in SI a cloth's 1 cm lengths leave J's
//                     weakly constrained directions (singular values ~1e-6) below
//                     the proximal term, and the steps 30% off J^+ r there.
// Why the per-link factor graph, not tree coordinates: a cloth's ropes are chains,
// whose joint-space inertia M (and its L^T L factor, Featherstone's sparse
// factorisation, which has no fill only beyond the ancestor pattern) is dense per
// rope, N^2 entries for N links (10^9 for cloth:1000:1000), and so is M^-1 J^T; the
// per-link system has O(links + loop rows) entries, and its factor's fill is the
// ordering's (CHOLMOD's nested dissection).
#pragma once

#include <memory>
#include <vector>

#include "scandyn/factor_graph/sparse_cholesky.hpp"
#include "scandyn/sim/sparse_loops.hpp"

#if SCANDYN_HAS_CHOLMOD
namespace scandyn::factor_graph {

class SparseConstrainedDynamics final : public sim::LoopSolver {
 public:
  // The model (1-DoF joints) and loops are copied. Each system's symbolic analysis
  // runs at its first use (ordering: CHOLMOD's nested dissection by default). gpu:
  // the numeric factorisations and solves on the current CUDA device
  // (GpuSparseCholesky, cuSOLVER, under CHOLMOD's elimination order; needs
  // SCANDYN_HAS_FACTOR_GRAPH_GPU, else std::runtime_error at the first use).
  SparseConstrainedDynamics(const Model& model, const LoopSet& loops, Ordering ordering = Ordering::NESDIS,
                            bool gpu = false);
  ~SparseConstrainedDynamics() override;

  void forward_dynamics(const double* q, const double* qd, const double* tau, double* qdd, double* lambda) override;
  double project(double* q, double* qd, double tol, int iterations, LoopProjectionInfo* info = nullptr) override;

  // x (nv) = J^T (J J^T + mu I)^-1 r at q (r: m loop rows), J and I in the projection
  // system's units (the model's: J's rows divided by their unit, L for a point's and
  // a weld's linear rows, 1 for a weld's angular ones; for point loops the dense
  // damping mu L^2); mu = 0: J^+ r. factor: assemble and factorise at q (also done
  // when mu differs from the last factorisation's), else the last factorisation, which
  // must be at q. The projection's (Levenberg-Marquardt's) step.
  void min_norm_step(const double* q, const double* r, double mu, double* x, bool factor = true);

  // Accumulated wall time (s) and counts since construction or reset_timing().
  struct Timing {
    double analysis = 0, assemble = 0, factorize = 0, solve = 0;  // seconds
    long factorizations = 0, solves = 0;
  };
  const Timing& timing() const { return timing_; }
  void reset_timing() { timing_ = Timing{}; }
  // The systems' symbolic statistics (nnz(L), flops, ...); analyses them if not yet done.
  const EliminationStats& forward_dynamics_stats();
  const EliminationStats& projection_stats();
  Index forward_dynamics_unknowns() const;

 private:
  struct System;
  System& fd();
  System& projection();
  // x (nv) = J(q)^+ r (r: m loop rows); factor: assemble and factorise at q first
  // (else the last factorisation, which must be at q)
  void solve_projection(const double* q, const double* r, double* x, bool factor);
  // s's numeric factorisation (a failure: LoopError beginning with `what`) and its
  // solve of b into x_, each timed into timing_
  void factorize_timed(System& s, const char* what);
  void solve_timed(System& s, const std::vector<double>& b);

  Model model_, kinematic_model_;
  LoopSet loops_;
  std::vector<LoopRow<double>> rows_;
  Ordering ordering_;
  bool gpu_ = false;
  std::unique_ptr<System> fd_, projection_;
  Timing timing_;
  double factored_mu_ = 0;  // the projection system's compliance at its last factorisation
  std::vector<Transform<double>> X0_, X0_lin_;  // at the last evaluated q, at the projection's factorised q
  std::vector<Motion<double>> v_, a_, zero_;
  std::vector<double> phi_, r_, dx_, b_, x_;
};

// A SparseConstrainedDynamics (CHOLMOD; the GPU's: cuSOLVER), as the simulator's
// sim::LoopSolverFactory.
std::unique_ptr<sim::LoopSolver> make_sparse_loop_solver(const Model& model, const LoopSet& loops);
std::unique_ptr<sim::LoopSolver> make_gpu_sparse_loop_solver(const Model& model, const LoopSet& loops);
// Registers one of them with the simulator (sim::set_sparse_loop_solver); gpu
// without the GPU solver built throws std::runtime_error.
void register_sparse_loop_solver(bool gpu = false);

}  // namespace scandyn::factor_graph
#endif
