// scandyn/factor_graph/gpu_sparse_cholesky.hpp: the factor graph's system A x = b
// solved on a CUDA device by cuSOLVER's sparse Cholesky (the low-level csrchol
// routines: symbolic analysis, numeric factorisation, solve), with the contract of
// SparseCholesky (scandyn/factor_graph/sparse_cholesky.hpp): the equilibrated normal
// equations (D A^T A D + beta I) y = D A^T b, x = D y, then iterative refinement on
// A x = b, both by the shared host code of scandyn/factor_graph/normal_equations.hpp.
//
// cuSOLVER's csrchol does not reorder: the normal matrix is assembled on the host
// already permuted by the caller's elimination order (NormalMatrix: B = P N P^T), so
// that with the order CHOLMOD computed (SparseCholesky::elimination_order()) both
// factor the same permuted matrix. Double precision. The factor lives on the
// device; each factorisation uploads B's values, each normal solve one right-hand
// side (the scaling, the products with A and the refinement run on the host).
//
// Built only with the CUDA backend and cuSOLVER (SCANDYN_HAS_FACTOR_GRAPH_GPU in
// scandyn/factor_graph/factor_graph_config.hpp); without them this header declares
// nothing. cuDSS, NVIDIA's successor of these routines, is not used.
#pragma once

#include <cstddef>
#include <memory>
#include <vector>

#include "scandyn/factor_graph/dynamics_graph.hpp"
#include "scandyn/factor_graph/factor_graph_config.hpp"

#if SCANDYN_HAS_FACTOR_GRAPH_GPU
namespace scandyn::factor_graph {

// Sizes of one analysed system on the device.
struct GpuCholeskyStats {
  Index n = 0;                      // unknowns: B's order
  Index nnz_B = 0;                  // entries of B, both triangles (the uploaded pattern)
  std::size_t internal_bytes = 0;   // cuSOLVER's storage of the factor L
  std::size_t workspace_bytes = 0;  // cuSOLVER's workspace of factorisation and solve
};

class GpuSparseCholesky {
 public:
  // Symbolic analysis on the current CUDA device of B = P (D A^T A D + beta I) P^T
  // for At's pattern (At: the graph's transposed system); order: the elimination
  // order (entry k: the k-th eliminated unknown), empty for the storage order;
  // beta: the diagonal added to the normal matrix (0 for trees, a small proximal
  // term for redundant loops). Throws std::invalid_argument for an order that is
  // not a permutation of the unknowns, std::runtime_error naming the failing CUDA /
  // cuSOLVER call and the matrix size (no device, out of device memory).
  GpuSparseCholesky(const SparseMatrix& At, const std::vector<Index>& order = {}, double beta = 0.0);
  ~GpuSparseCholesky();
  GpuSparseCholesky(const GpuSparseCholesky&) = delete;
  GpuSparseCholesky& operator=(const GpuSparseCholesky&) = delete;

  // Numeric factorisation for At's current values (same pattern as at analysis):
  // columns of A scaled to unit norm, B assembled on the host and uploaded, factored
  // on the device; returns when the factor is complete. Throws std::runtime_error
  // when B is not positive definite (naming the pivot's position) or a CUDA /
  // cuSOLVER call fails.
  void factorize(const SparseMatrix& At);
  // x = D (D A^T A D + beta I)^{-1} D A^T b, then `refine` steps of iterative
  // refinement on A x = b. x has At.rows entries.
  void solve(const SparseMatrix& At, const std::vector<double>& b, std::vector<double>& x, int refine = 1);

  const GpuCholeskyStats& stats() const { return stats_; }
  // The normal matrix B as factored (values of the last factorize()).
  const std::vector<Index>& row_ptr() const;
  const std::vector<Index>& col_idx() const;
  const std::vector<double>& val() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
  GpuCholeskyStats stats_;
};

}  // namespace scandyn::factor_graph
#endif
