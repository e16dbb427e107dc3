// scandyn/factor_graph/sparse_cholesky.hpp: the factor graph's system A x = b solved
// by SuiteSparse CHOLMOD on the equilibrated normal equations
// (D A^T A D + beta I) y = D A^T b, x = D y (D: unit column norms of A), the
// multifrontal / supernodal Cholesky that factor-graph solvers eliminate with, under
// a chosen elimination ordering, plus iterative refinement on A x = b (the scaling,
// the products with A and the refinement: scandyn/factor_graph/normal_equations.hpp,
// shared with the GPU's solver, scandyn/factor_graph/gpu_sparse_cholesky.hpp).
//
// Built only when CMake finds CHOLMOD (SCANDYN_HAS_CHOLMOD in
// scandyn/factor_graph/factor_graph_config.hpp); without it this header declares
// nothing and the factor-graph tools say so.
#pragma once

#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "scandyn/factor_graph/dynamics_graph.hpp"
#include "scandyn/factor_graph/factor_graph_config.hpp"

#if SCANDYN_HAS_CHOLMOD
namespace scandyn::factor_graph {

enum class Ordering {
  Given,    // a permutation from the caller (tree_order, cyclic_reduction_order)
  Natural,  // unknowns in storage order
  AMD,      // approximate minimum degree on A^T A
  COLAMD,   // column approximate minimum degree on A
  METIS,    // METIS nested dissection on A^T A
  NESDIS,   // CHOLMOD's nested dissection (METIS partitions, CAMD on the separators)
};
const char* ordering_name(Ordering o);

// Symbolic statistics of one ordering.
struct EliminationStats {
  double nnz_A = 0;        // entries of A
  double nnz_L = 0;        // entries of the Cholesky factor L (fill: nnz_L - nnz(tril(A^T A)))
  double nnz_AtA = 0;      // entries of the lower triangle of A^T A
  double flops = 0;        // floating-point operations of the numeric factorisation
  int etree_height = 0;    // height of the elimination tree (the critical path, in eliminations)
  bool supernodal = false;
};

class SparseCholesky {
 public:
  // Symbolic analysis of At At^T (At: the graph's transposed system) under ordering
  // (given: the permutation when ordering == Given). beta: the diagonal added to
  // A^T A (0 for trees; a small proximal term for loops whose constraints are
  // redundant). Throws std::runtime_error when CHOLMOD fails.
  SparseCholesky(const SparseMatrix& At, Ordering ordering, const std::vector<Index>& given = {},
                 double beta = 0.0, bool simplicial = false);
  ~SparseCholesky();
  SparseCholesky(const SparseCholesky&) = delete;
  SparseCholesky& operator=(const SparseCholesky&) = delete;

  // Numeric factorisation for At's current values (same pattern as at analysis),
  // columns of A scaled to unit norm first.
  // Throws std::runtime_error when A^T A + beta I is not positive definite.
  void factorize(const SparseMatrix& At);
  // x = D (D A^T A D + beta I)^{-1} D A^T b, then `refine` steps of iterative refinement
  // on A x = b. x has At.rows entries.
  void solve(const SparseMatrix& At, const std::vector<double>& b, std::vector<double>& x,
             int refine = 1);

  const EliminationStats& stats() const { return stats_; }
  // The elimination order CHOLMOD uses (entry k: the k-th eliminated unknown; the
  // given one, or the ordering method's followed by its postorder).
  const std::vector<Index>& elimination_order() const;
  // The pattern of the factor L after factorize(): (row, column) of each entry, in
  // elimination positions (row >= column).
  std::vector<std::pair<Index, Index>> factor_pattern() const;
  // The elimination tree of L (parent of each eliminated position, -1 for roots),
  // in elimination order.
  std::vector<Index> etree() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
  EliminationStats stats_;
};

}  // namespace scandyn::factor_graph
#endif
