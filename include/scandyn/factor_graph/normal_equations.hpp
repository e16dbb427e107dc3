// scandyn/factor_graph/normal_equations.hpp: the equilibrated normal equations of
// the factor graph's system A x = b, shared by its sparse Cholesky solvers (CHOLMOD
// on the host, scandyn/factor_graph/sparse_cholesky.hpp; cuSOLVER on the GPU,
// scandyn/factor_graph/gpu_sparse_cholesky.hpp):
//
//   (D A^T A D + beta I) y = D A^T b,   x = D y,
//
// D the diagonal scaling each column of A to unit 2-norm, beta >= 0 a proximal term
// for singular (redundant) loop systems, then iterative refinement on A x = b:
//   r = b - A x,  (D A^T A D + beta I) dy = D A^T r,  x += D dy.
// A solver supplies only the solve with its factor of D A^T A D + beta I; the
// scaling, the products with A and the refinement are these functions.
//
// Compiled always (no SuiteSparse or CUDA needed).
#pragma once

#include <functional>
#include <vector>

#include "scandyn/factor_graph/dynamics_graph.hpp"

namespace scandyn::factor_graph {

// Loop systems: the proximal term beta of the equilibrated normal equations
// (redundant loop equations make A singular: the planar five-bar's out-of-plane
// row, a cloth grid's over-constrained rows) and the refinement steps on A x = b
// that remove its bias from the consistent equations (bench_factor_graph, the tests).
// Each step multiplies the error along a singular value sigma of the scaled A by
// beta / (sigma^2 + beta); beta is 1e-14 of the unit diagonal, a few hundred times
// the rounding of the factorisation's pivots (cloth:30:30, bench_factor_graph
// --accuracy: with 1e-12, 3 steps left 3e-8 of max |qdd|, with 1e-14 2e-13).
inline constexpr double kLoopBeta = 1e-14;
inline constexpr int kLoopRefine = 3;

// The equilibration of one set of values of A and the refined solve through a
// solver's factor. At: the graph's transposed system (unknowns x equations, CSC).
class NormalEquations {
 public:
  // d (unknowns): d_k = 1 / |column k of A|_2, 1 for an empty column; scaled
  // (nnz(A)): the values of D At on At's pattern (entry t: d[At.row_idx[t]] At.val[t]).
  void equilibrate(const SparseMatrix& At);
  const std::vector<double>& d() const { return d_; }
  const std::vector<double>& scaled() const { return scaled_; }

  // rhs (unknowns) = D A^T r, r (equations); equilibrate() first.
  void scaled_rhs(const SparseMatrix& At, const double* r, double* rhs) const;

  // Solves (D A^T A D + beta I) y = rhs (both of `unknowns` entries, y written).
  using NormalSolve = std::function<void(const double* rhs, double* y)>;

  // x (unknowns) = D y for (D A^T A D + beta I) y = D A^T b by solve_normal, then
  // `refine` steps of iterative refinement on A x = b (b: equations). The values
  // of At must be those of the last equilibrate() and of the solver's factor.
  void solve(const SparseMatrix& At, const std::vector<double>& b, std::vector<double>& x, int refine,
             const NormalSolve& solve_normal);

 private:
  std::vector<double> d_;       // (unknowns) column scaling of A
  std::vector<double> scaled_;  // (nnz(A)) values of D At
  std::vector<double> rhs_;     // (unknowns) D A^T b or D A^T r
  std::vector<double> y_;       // (unknowns) the normal solve's result
  std::vector<double> r_;       // (equations) residual b - A x
};

// r (equations) = b - A x, x (unknowns): the residual of the factor graph's system.
void residual(const SparseMatrix& At, const std::vector<double>& b, const double* x, double* r);

// The normal matrix under an elimination order, assembled explicitly in compressed
// sparse row form for solvers that take the matrix (the GPU's cuSOLVER); CHOLMOD
// forms the same matrix implicitly from D At.
//
//   B = P (D A^T A D + beta I) P^T,  B(k, l) = N(order[k], order[l]),
//
// N = D A^T A D + beta I, so that the k-th eliminated unknown is B's row k and a
// Cholesky factorisation of B in its natural order eliminates in `order`. The full
// symmetric pattern is stored (both triangles, the diagonal always present, the
// columns ascending within a row); entries B(k, l) and B(l, k) are the same sums in
// the same order, so B is exactly symmetric.
class NormalMatrix {
 public:
  // Symbolic: the pattern of B for At's pattern. order: a permutation of the
  // unknowns (entry k: the k-th eliminated unknown, as
  // SparseCholesky::elimination_order()); empty: the storage order. Throws
  // std::invalid_argument when order is not a permutation of [0, At.rows), and
  // std::length_error when B has more than 2^31 - 1 entries.
  NormalMatrix(const SparseMatrix& At, const std::vector<Index>& order);

  // Numeric: B's values for the equilibrated values of At (NormalEquations::scaled(),
  // At's pattern as at construction) and beta.
  void assemble(const SparseMatrix& At, const std::vector<double>& scaled, double beta);

  Index n() const { return n_; }
  Index nnz() const { return static_cast<Index>(col_idx_.size()); }
  const std::vector<Index>& row_ptr() const { return row_ptr_; }  // (n + 1)
  const std::vector<Index>& col_idx() const { return col_idx_; }  // (nnz) elimination positions
  const std::vector<double>& val() const { return val_; }         // (nnz)
  const std::vector<Index>& order() const { return order_; }      // (n) position -> unknown
  const std::vector<Index>& position() const { return position_; }  // (n) unknown -> position

 private:
  Index n_ = 0;
  std::vector<Index> row_ptr_, col_idx_;
  std::vector<double> val_;
  std::vector<Index> order_, position_;
  // At by rows (the equations of each unknown): unknown u's entries are
  // eq_ptr_[u] .. eq_ptr_[u + 1] - 1, equation eq_idx_[p], At entry eq_slot_[p].
  std::vector<Index> eq_ptr_, eq_idx_, eq_slot_;
  std::vector<Index> where_;  // (n) workspace: column position -> entry of the current row
};

}  // namespace scandyn::factor_graph
