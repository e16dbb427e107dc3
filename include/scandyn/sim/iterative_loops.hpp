// scandyn/sim/iterative_loops.hpp: the simulator's iterative (matrix-free) loop
// solver, scene "loop_solver": "iterative" (docs/loops.md, "The simulator's iterative
// loop path"). In the core library: no external dependency (no CHOLMOD), so it is
// there in every build and in the wheels.
//
// forward_dynamics: M qdd + h = tau + J^T lambda, J qdd + gamma = 0 through the Schur
// complement A = J M^-1 J^T:  A lambda = b,  b = -gamma - J qdd0,  qdd0 = M^-1 (tau - h),
// qdd = qdd0 + x,  x = M^-1 J^T lambda. A is applied matrix-free by the O(n) tree passes
// of scandyn/algorithm/loop_iterative.hpp (J^T lambda as point forces on the links, M^-1
// by the articulated-body passes at zero velocity without gravity, J x from the links'
// accelerations), and solved by conjugate gradients on the normal equations in M's
// metric, weighted by the preconditioner's weights W (CGLS: min ||J x - b||_W over x =
// M^-1 J^T lambda; one application of A per iteration), warm-started from this solver's
// previous lambda (the previous stage or step of the instances the solver serves). A is
// symmetric positive semi-definite: redundant rows (a planar loop closed by a 3D point,
// a cloth's dependent rows) leave it singular, and rounding puts part of b outside its
// range, where CG on A diverges; CGLS's residual decreases monotonically, x is tracked
// directly (qdd is unique; lambda is a solution, not necessarily the minimum-norm one:
// J^T lambda is unique).
//
// Converged: ||J qdd + gamma||_2 <= tolerance (||gamma||_2 + ||J qdd0||_2) + 1e-12 L_J ||qdd0||_2,
// L_J = sqrt of the largest diagonal entry of J J^T at q = 0 (a length; the second term
// keeps the target above rounding, and above the part of b that a state's loop
// violation at rounding level puts outside J's range, where gamma and J qdd0 cancel:
// ropes that move alike), checked on the true residual; or, b partly outside the
// range, the normal residual at rounding level and the true residual the recurrence's.
// Not converged within max_iterations, or a non-finite value: LoopSolveNotConverged
// naming the iterations and the residual (the simulator's step then fails for that
// instance: Failure::LoopNotClosed), never a silent wrong answer.
//
// project: project_onto_loops (scandyn/algorithm/loop_projection.hpp) with each step
// x = J^T (J J^T + mu D)^-1 r (D = W^-1 of J J^T, below: the Levenberg-Marquardt
// weights; mu = 0: the minimum-norm J^+ r) by CGLS on (J^T W J + mu I) x = J^T W r,
// W = D^-1, over the "unit tree" (massless links, a unit joint-space inertia per joint:
// J p and J^T W q by O(n) passes), from 0. mu is at least kLoopRankTolerance (the dense
// solve's rank threshold's role: a right-hand side at rounding level is not "solved"
// along J's near-null directions). CGLS stops at ||r - J x||_2 <= tolerance ||r||_2 +
// 1e-12 L_J max(||q||_2, ||qd||_2) (by its recurrence), or at the damped normal residual
// at tolerance of its first value (then restarted from the true residual while that
// halves, at most 4 rounds); a solve is converged only on its TRUE residual r - J x,
// computed at the end: within that target, or, stopped at the damped normal residual,
// within sqrt(kLoopRankTolerance) L_J ||qd||_2 + the same floor (the part of J qd along
// J's directions of singular value below 1e-5 L_J, which the damping leaves as the dense
// rank threshold does). The velocity projection's solve must converge, else
// LoopSolveNotConverged naming ||J qd||_2 after and before, the iterations and both
// bounds (the normal residual alone is no test: J J^T's small singular values can leave
// r - J x far above it). A position step's solve, converged or not (counted in
// proj_unconverged), is judged by the Levenberg-Marquardt acceptance test on the true
// phi at the trial point, and the caller judges max |phi|: no wrong q either.
//
// Preconditioner (IterativeLoopOptions::preconditioner): the weights W, an approximate
// inverse of A (of J J^T), symmetric positive definite, O(n + m) to build and apply:
// - BlockJacobi: loop k's diagonal block of A from the links' apparent inverse inertias
//   (loop_response_blocks, an O(n) recursion), inverted with its eigenvalues floored at
//   kLoopBlockFloor of its largest;
// - the neighbour-block preconditioners, over A_nb: A's diagonal blocks and its blocks
//   (k, l) of every two loops with links on one body or on a child and its parent
//   (loop_pair_block; for cloth:K:N the 8 neighbours of loop (k, j) on the grid, each
//   block exact), L_nb its strictly lower part in the loops' order, and W^-1 =
//   (Dt + L_nb) Dt^-1 (Dt + L_nb)^T (symmetric positive definite for any symmetric
//   positive definite block diagonal Dt; one forward and one backward block sweep):
//   - SymmetricGaussSeidel: Dt = A's diagonal blocks (symmetric block Gauss-Seidel);
//   - Ssor (the default): the same with L_nb scaled by relaxation (omega = 0.5): SSOR,
//     the preconditioner with the fewest iterations and seconds measured (docs/loops.md,
//     "Preconditioner"); also the projection's weights of J J^T;
//   - BlockDilu: Dt_k = A_kk - sum_{l < k} A_kl Dt_l^-1 A_lk over the neighbours (block
//     diagonal incomplete LU: the incomplete factorisation whose product has A_nb's
//     diagonal blocks and lower part);
//   - BlockTridiagonal: BlockDilu over the "line" neighbours only: two loops whose both
//     links are on one body or on a child and its parent (for a cloth the loops of one
//     pair of ropes, consecutive in the loops' order), where it is the exact block LDL^T
//     factorisation of A's block-tridiagonal part along each pair of ropes;
//   Dt_k is inverted with its eigenvalues floored at kLoopBlockFloor of A_kk's largest;
//   a Dt_k with more eigenvalues below that floor than A_kk is replaced by A_kk (the
//   incomplete factorisation broke down there; counted in IterativeLoopStats);
//   SymmetricGaussSeidel, BlockTridiagonal and BlockDilu project with block Jacobi's
//   weights (theirs of J J^T are ill-conditioned: the velocity projection stopped far
//   from J qd = 0), and need more iterations than block Jacobi from cloth:50:50 on;
// - None: W = 1.
// One application of W per CGLS iteration (W times the residual by its recurrence).
#pragma once

#include <cmath>
#include <memory>
#include <string>
#include <vector>

#include "scandyn/algorithm/loop_iterative.hpp"
#include "scandyn/sim/sparse_loops.hpp"

namespace scandyn::sim {

// The iterative loop solver's relative residual tolerance and iteration cap (per
// solve), the defaults of IterativeLoopOptions.
inline constexpr double kIterativeLoopTolerance = 1e-10;
inline constexpr int kIterativeLoopMaxIterations = 20000;
// The forward dynamics' absolute floor on ||J qdd + gamma||_2, relative to L_J ||qdd0||_2.
inline constexpr double kIterativeLoopFloor = 1e-12;

// A solve of the iterative loop solver that did not converge within its iteration cap
// (or met a non-finite value): what() names the solve, its residual and iterations. The
// simulator's step records it as the instance's Failure::LoopNotClosed (estimate
// infinite).
class LoopSolveNotConverged : public LoopError {
 public:
  using LoopError::LoopError;
};

// When conjugate gradients on normal equations (CGLS) stop short of their residual
// target: the residual ||b - J x|| has reached the part of b outside J's range (no x
// removes it), i.e. the normal residual relative to its first value is at rounding
// level (`rounding`); or the residual has not decreased by 0.1 % in 200 iterations and
// the relative normal residual is below `stagnant`. Double's thresholds by default
// (the CPU solver's); the GPU solver's float uses 1e-6 and 1e-4.
struct LeastSquaresStop {
  double rounding = 1e-14, stagnant = 1e-12;
  double best = INFINITY;  // the smallest residual so far
  int since = 0;           // iterations since it last decreased by 0.1 %
  bool least_squares(double residual, double relative_normal) {
    if (residual < (1 - 1e-3) * best) best = residual, since = 0;
    else ++since;
    return relative_normal <= rounding || (since >= 200 && relative_normal <= stagnant);
  }
};

enum class LoopPreconditioner { None, BlockJacobi, SymmetricGaussSeidel, Ssor, BlockTridiagonal, BlockDilu };

// "none", "block-jacobi", "symmetric-gauss-seidel", "ssor", "block-tridiagonal", "block-dilu".
// (Inline, as the next: the scene parser, in the parsers' library without the solver,
// checks a scene's "loop_preconditioner" with them.)
inline const char* loop_preconditioner_name(LoopPreconditioner p) {
  switch (p) {
    case LoopPreconditioner::None: return "none";
    case LoopPreconditioner::BlockJacobi: return "block-jacobi";
    case LoopPreconditioner::SymmetricGaussSeidel: return "symmetric-gauss-seidel";
    case LoopPreconditioner::Ssor: return "ssor";
    case LoopPreconditioner::BlockTridiagonal: return "block-tridiagonal";
    case LoopPreconditioner::BlockDilu: return "block-dilu";
  }
  return "?";
}
// The inverse of loop_preconditioner_name; throws LoopError naming the choices.
inline LoopPreconditioner parse_loop_preconditioner(const std::string& name) {
  for (LoopPreconditioner p : {LoopPreconditioner::None, LoopPreconditioner::BlockJacobi,
                               LoopPreconditioner::SymmetricGaussSeidel, LoopPreconditioner::Ssor,
                               LoopPreconditioner::BlockTridiagonal, LoopPreconditioner::BlockDilu})
    if (name == loop_preconditioner_name(p)) return p;
  throw LoopError("unknown loop preconditioner '" + name +
                  "' (expected none, block-jacobi, symmetric-gauss-seidel, ssor, block-tridiagonal or block-dilu)");
}

struct IterativeLoopOptions {
  double tolerance = kIterativeLoopTolerance;
  int max_iterations = kIterativeLoopMaxIterations;
  LoopPreconditioner preconditioner = LoopPreconditioner::Ssor;
  bool warm_start = true;  // start each forward dynamics' CG from the previous lambda
  // Ssor's relaxation omega: W^-1 proportional to (D + omega L_nb) D^-1 (D + omega L_nb)^T
  // (1: SymmetricGaussSeidel; 0: BlockJacobi)
  double relaxation = 0.5;
};

// What the solver did since its construction (or reset_stats).
struct IterativeLoopStats {
  long fd_solves = 0, fd_iterations = 0;        // forward dynamics: CG solves, iterations
  long proj_solves = 0, proj_iterations = 0;    // projection: CG solves, iterations
  long proj_unconverged = 0;                    // projection position steps that did not converge
  int last_iterations = 0;                      // the last CG solve's iterations
  double last_residual = 0;                     // and its relative residual (projection, mu = 0: the true one)
  double fd_seconds = 0, proj_seconds = 0;      // wall time in forward_dynamics / project
  long dilu_fallbacks = 0;                      // Dt_k replaced by A_kk (BlockDilu, BlockTridiagonal)
  long applies = 0;                             // applications of A or J J^T (tree passes)
  double apply_seconds = 0;                     // their time
};

class IterativeLoopSolver : public LoopSolver {
 public:
  // Throws LoopError for a model with multi-DoF joints (the loops' routines take 1-DoF joints).
  IterativeLoopSolver(const Model& model, const LoopSet& loops, const IterativeLoopOptions& options = {});
  void forward_dynamics(const double* q, const double* qd, const double* tau, double* qdd, double* lambda) override;
  double project(double* q, double* qd, double tol, int iterations, LoopProjectionInfo* info = nullptr) override;

  const IterativeLoopStats& stats() const { return stats_; }
  void reset_stats() { stats_ = {}; }
  const IterativeLoopOptions& options() const { return options_; }
  // z (m) = W r (m): the preconditioner as last built (by forward_dynamics: of A at its
  // state; by project: of J J^T at its last linearisation, block Jacobi for every
  // preconditioner but None and Ssor); the identity before.
  void apply_weights(const double* r, double* z) const { apply_preconditioner(r, z); }

 private:
  struct Projection;
  void invert_blocks(LoopPreconditioner kind);
  void add_to_totals(const IterativeLoopStats& before) const;
  void schur_response(const double* w, double* Js);
  bool fd_solve(double target, int& it, double& rnorm);
  void build_preconditioner(const Force<double>* U, const double* D, LoopPreconditioner kind);
  void apply_preconditioner(const double* r, double* z) const;
  void unit_solve(const double* r, double mu, double floor, double allowance, double* x, bool& converged);
  static bool neighbour_blocks(LoopPreconditioner p);
  void build_pattern();

  Model model_;
  LoopSet loops_;
  std::vector<LoopRow<double>> rows_;
  IterativeLoopOptions options_;
  IterativeLoopStats stats_;
  Index n_ = 0, m_ = 0;
  // per body
  std::vector<Transform<double>> Xup_, X0_;
  std::vector<Force<double>> U_, f_, pA_;
  std::vector<double> D_, u_, qdd0_, tmp_n_, xbest_, dx_, px_;
  std::vector<Motion<double>> v_, c_, a_, acc_;
  // project's trial points (Levenberg-Marquardt's phi at q + p): their poses and motions
  std::vector<Transform<double>> trial_X0_;
  std::vector<Motion<double>> trial_v_, trial_a_;
  std::vector<ABInertia<double>> IA_;
  std::vector<Mat6<double>> Omega_;
  // per row
  std::vector<double> lambda_, b_, gamma_, r_, z_, p_, Ap_, best_, tmp_m_;
  std::vector<double> blocks_, block_inv_;  // per loop: d x d raw blocks and their pseudo-inverses (6x6 slots)
  // the neighbour blocks (neighbour_blocks()): per pair of loops (hi, lo), lo < hi, in
  // rows by hi: pair_start_ (loops + 1), pair_lo_, pair_line_ (both links neighbours),
  // pair_off_ into pair_vals_ (d_hi x d_lo, row-major); the shares that make them
  struct PairTerm {
    Index pair, hi, lo;
    int s_hi, s_lo;
    int rel;  // 0: one body; 1: hi's body the child of lo's; 2: lo's the child of hi's
  };
  std::vector<PairTerm> terms_;
  std::vector<Index> pair_start_, pair_lo_, loop_row_;
  std::vector<std::size_t> pair_off_;
  std::vector<char> pair_line_;
  std::vector<double> pair_vals_;
  mutable std::vector<double> pre_acc_;
  bool all_points_ = false;  // every loop a point loop (3 rows): the sweeps' 3 x 3 path
  LoopPreconditioner weights_ = LoopPreconditioner::None;  // the weights as last built (None: W = 1)
  bool unit_factored_ = false;
  // the last projection solve's ||r||_2, its target, its allowance (+ floor) and its true
  // residual ||r - J x||_2 (mu = 0; else the recurrence's): the velocity projection's error
  double last_r0_ = 0, last_target_ = 0, last_allowance_ = 0, last_residual_abs_ = 0;
  double unit_scale_ = 1;
  double jscale_ = 1;  // L_J: sqrt of the largest diagonal entry of J J^T at q = 0 (m)
};

std::unique_ptr<LoopSolver> make_iterative_loop_solver(const Model& model, const LoopSet& loops);
// The factory of iterative loop solvers with the preconditioner p and the other options'
// defaults (the scene's "loop_preconditioner").
LoopSolverFactory iterative_loop_solver_factory(LoopPreconditioner p);

// The sums of every iterative loop solver's IterativeLoopStats counters in this process
// since it started (or since reset_iterative_loop_totals): solves, iterations,
// applications and their seconds (what a benchmark reads around the simulator's
// steps, whose solvers are its threads'). Thread-safe.
IterativeLoopStats iterative_loop_totals();
void reset_iterative_loop_totals();

}  // namespace scandyn::sim
