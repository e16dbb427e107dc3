// scandyn/cuda/loop_iterative.hpp: the iterative (matrix-free) closed-loop forward
// dynamics of scandyn/sim/iterative_loops.hpp on a CUDA device, one instance, for a
// tree of unbranched chains hanging from the fixed base, each contiguous in DoF order
// (curtain:K:N / cloth:K:N, whose ropes are the chains; fivebar, fourbar): the same
// equations and the same CGLS with the same convergence test as
// sim::IterativeLoopSolver::forward_dynamics (read its header), with the block-Jacobi
// preconditioner or none (SSOR's sweeps are sequential: not here), in double or float.
//
// What runs where (kernels/loop_iterative.cu):
//   - the tree passes, one thread per chain, each walking its chain with the SCANDYN_HD
//     *_range passes of scandyn/algorithm/loop_iterative.hpp (loop_body_motion_range,
//     loop_aba_factor_range, loop_tree_response_range, loop_joint_motion_range,
//     loop_response_blocks_range): per body the CPU's arithmetic;
//   - J^T lambda's body wrenches gathered per body (loop_body_wrench over the body's
//     loop sides, scandyn/algorithm/loop_chains.hpp) inside the chain thread: no
//     scatter, no atomics (a cloth's link carries the sides of two loops);
//   - the loop rows (gamma, J x, the diagonal blocks of A and their floored inverses,
//     W r), one thread per loop;
//   - the CGLS vectors on the device; dot products in double by a two-kernel block
//     reduction (fixed order: the same result every run); one host synchronisation per
//     iteration (the iteration's step length, residual and next gamma come back
//     together, the next application of A computed speculatively before the
//     convergence test), a few per solve.
// The host passes in q, qd, tau and reads back qdd, lambda (double, converted to S);
// lambda stays on the device between calls for the warm start.
//
// Float: the same algorithm in float (dot products accumulated in double); the default
// tolerance kCudaIterativeLoopToleranceFloat (1e-5), the floor 1e-6 L_J ||qdd0||, and
// the least-squares stop at a relative normal residual of 1e-6 (1e-4 stalled): float
// rounding (~1e-7) leaves the double thresholds out of reach.
//
// project() (the LoopSolver interface): in double on the device, the same as
// sim::IterativeLoopSolver::project with this solver's preconditioner (block Jacobi's
// weights of J J^T, or none): project_onto_loops' Levenberg-Marquardt steps and
// acceptance on the host around device solves (unit_solve's CGLS on
// (J^T W J + mu I) x = J^T W r over the unit tree: J p by loop_joint_motion_range per
// chain, J^T W q by the bodies' gathered wrenches and loop_joint_forces' backward pass
// per chain; the same rounds, stops, true-residual acceptance and errors, with the
// tolerance of this solver's double: 1e-10), phi at the trial points one thread per
// loop; phi, J p and the steps cross to the host per evaluation (project_onto_loops'
// O(n + m) host work). Float, or options.project_on_host: on the host, a
// sim::IterativeLoopSolver with this solver's preconditioner (the reference), made on
// first use.
#pragma once

#include <memory>
#include <string>

#include "scandyn/algorithm/loop_chains.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/sim/iterative_loops.hpp"

namespace scandyn::cuda {

inline constexpr double kCudaIterativeLoopToleranceFloat = 1e-5;
inline constexpr double kCudaIterativeLoopFloorFloat = 1e-6;

struct CudaIterativeLoopOptions {
  double tolerance = 0;  // 0: sim::kIterativeLoopTolerance (double), kCudaIterativeLoopToleranceFloat (float)
  int max_iterations = sim::kIterativeLoopMaxIterations;
  // BlockJacobi or None (others: LoopError at construction)
  sim::LoopPreconditioner preconditioner = sim::LoopPreconditioner::BlockJacobi;
  bool warm_start = true;  // start each solve from the previous lambda
  int device = 0;
  // project() on the host (sim::IterativeLoopSolver, this preconditioner) instead of the
  // device (double; float always projects on the host)
  bool project_on_host = false;
};

struct CudaIterativeLoopStats {
  long fd_solves = 0, fd_iterations = 0;
  int last_iterations = 0;
  double last_residual = 0;  // ||J qdd + gamma|| / (||gamma|| + ||J qdd0||) of the last solve
  double fd_seconds = 0;     // wall time in forward_dynamics (copies included)
  long applies = 0;          // applications of A (tree passes)
  long syncs = 0;            // host synchronisations
  // project() on the device: CGLS solves, iterations, position steps not converged,
  // wall time (copies and the host's Levenberg-Marquardt included)
  long proj_solves = 0, proj_iterations = 0, proj_unconverged = 0;
  double proj_seconds = 0;
};

// Why the simulator cannot use this solver for the model's loops with preconditioner p
// (scene "loop_solver": "iterative-cuda"), or "" when it can: a build without CUDA, no
// usable device, a tree that is not a set of unbranched chains from the base
// (loop_chain_layout's message), a preconditioner other than block-jacobi and none, or
// multi-DoF joints. Checks no device memory; the tree and the preconditioner before
// the device.
inline std::string cuda_iterative_loop_refusal(const Model& model, const LoopSet& loops, sim::LoopPreconditioner p) {
  const std::string who = "\"loop_solver\": \"iterative-cuda\": ";
#if !SCANDYN_HAS_CUDA
  (void)model, (void)loops, (void)p;
  return who + "this build has no CUDA (SCANDYN_CUDA=OFF); \"iterative\" is the host's iterative solver";
#else
  if (p != sim::LoopPreconditioner::BlockJacobi && p != sim::LoopPreconditioner::None)
    return who + "\"loop_preconditioner\": \"" + sim::loop_preconditioner_name(p) +
           "\" is not on the GPU (its sweeps are sequential): use \"block-jacobi\" (its default) or \"none\"";
  try {
    (void)loop_chain_layout(model, loop_rows_of<double>(loops));
  } catch (const LoopError& e) {
    return who + e.what();
  }
  const Result<int> count = device_count();
  if (!count) return who + count.error;
  if (count.value == 0) return who + "no usable CUDA device (0 visible)";
  return "";
#endif
}

#if SCANDYN_HAS_CUDA

template <class S>
class CudaIterativeLoopSolver final : public sim::LoopSolver {
 public:
  // Copies the model and loops to the device. Throws LoopError for a tree that is not a
  // set of unbranched chains from the base (loop_chain_layout's message), an
  // unsupported preconditioner, no usable device, or too little device memory.
  CudaIterativeLoopSolver(const Model& model, const LoopSet& loops, const CudaIterativeLoopOptions& options = {});
  ~CudaIterativeLoopSolver() override;
  CudaIterativeLoopSolver(const CudaIterativeLoopSolver&) = delete;
  CudaIterativeLoopSolver& operator=(const CudaIterativeLoopSolver&) = delete;

  // sim::IterativeLoopSolver::forward_dynamics's contract (host arrays, double): throws
  // LoopError for a failed pivot, sim::LoopSolveNotConverged when CGLS does not converge
  // within max_iterations or meets a non-finite value.
  void forward_dynamics(const double* q, const double* qd, const double* tau, double* qdd, double* lambda) override;
  double project(double* q, double* qd, double tol, int iterations, LoopProjectionInfo* info = nullptr) override;

  const CudaIterativeLoopStats& stats() const;
  void reset_stats();
  const CudaIterativeLoopOptions& options() const;
  // L_J (sim::IterativeLoopSolver's jscale: sqrt of J J^T's largest diagonal entry at q = 0).
  double jscale() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// LoopSolverFactory-shaped makers (default options): double and float.
std::unique_ptr<sim::LoopSolver> make_cuda_iterative_loop_solver(const Model& model, const LoopSet& loops);
std::unique_ptr<sim::LoopSolver> make_cuda_iterative_loop_solver_float(const Model& model, const LoopSet& loops);
// The double solver's maker with preconditioner p (BlockJacobi or None; others: LoopError).
sim::LoopSolverFactory cuda_iterative_loop_solver_factory(sim::LoopPreconditioner p);

#endif  // SCANDYN_HAS_CUDA

}  // namespace scandyn::cuda
