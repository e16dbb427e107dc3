// src/factor_graph/normal_equations.cpp: the equilibrated normal equations shared by
// the factor graph's sparse Cholesky solvers (scandyn/factor_graph/normal_equations.hpp).
#include "scandyn/factor_graph/normal_equations.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

namespace scandyn::factor_graph {

void NormalEquations::equilibrate(const SparseMatrix& At) {
  // unknown k's column of A to unit 2-norm (the system mixes unit kinematic entries
  // with inertias of any size; beta then acts relative to them)
  d_.assign(static_cast<std::size_t>(At.rows), 0.0);
  for (std::size_t t = 0; t < At.val.size(); ++t) d_[At.row_idx[t]] += At.val[t] * At.val[t];
  for (double& v : d_) v = v > 0 ? 1.0 / std::sqrt(v) : 1.0;
  scaled_.resize(At.val.size());
  for (std::size_t t = 0; t < At.val.size(); ++t) scaled_[t] = d_[At.row_idx[t]] * At.val[t];
}

void NormalEquations::scaled_rhs(const SparseMatrix& At, const double* r, double* rhs) const {
  std::fill(rhs, rhs + At.rows, 0.0);
  for (Index e = 0; e < At.cols; ++e)
    for (Index t = At.col_ptr[e]; t < At.col_ptr[e + 1]; ++t) rhs[At.row_idx[t]] += scaled_[t] * r[e];
}

void residual(const SparseMatrix& At, const std::vector<double>& b, const double* x, double* r) {
  for (Index e = 0; e < At.cols; ++e) {
    double s = b[e];
    for (Index t = At.col_ptr[e]; t < At.col_ptr[e + 1]; ++t) s -= At.val[t] * x[At.row_idx[t]];
    r[e] = s;
  }
}

void NormalEquations::solve(const SparseMatrix& At, const std::vector<double>& b, std::vector<double>& x,
                            int refine, const NormalSolve& solve_normal) {
  const std::size_t n = static_cast<std::size_t>(At.rows);
  rhs_.resize(n);
  y_.resize(n);
  r_.resize(static_cast<std::size_t>(At.cols));
  // x = D y, (D A^T A D + beta I) y = D A^T b
  scaled_rhs(At, b.data(), rhs_.data());
  solve_normal(rhs_.data(), y_.data());
  x.resize(n);
  for (std::size_t k = 0; k < n; ++k) x[k] = d_[k] * y_[k];
  // refinement on A x = b: x += D (D A^T A D + beta I)^{-1} D A^T (b - A x)
  for (int it = 0; it < refine; ++it) {
    residual(At, b, x.data(), r_.data());
    scaled_rhs(At, r_.data(), rhs_.data());
    solve_normal(rhs_.data(), y_.data());
    for (std::size_t k = 0; k < n; ++k) x[k] += d_[k] * y_[k];
  }
}

NormalMatrix::NormalMatrix(const SparseMatrix& At, const std::vector<Index>& order) : n_(At.rows) {
  const std::size_t n = static_cast<std::size_t>(n_);
  // the elimination order and its inverse
  if (order.empty()) {
    order_.resize(n);
    for (Index k = 0; k < n_; ++k) order_[k] = k;
  } else {
    if (order.size() != n)
      throw std::invalid_argument("NormalMatrix: the elimination order has " + std::to_string(order.size()) +
                                  " entries, the system " + std::to_string(n_) + " unknowns");
    order_ = order;
  }
  position_.assign(n, -1);
  for (Index k = 0; k < n_; ++k) {
    const Index u = order_[k];
    if (u < 0 || u >= n_ || position_[u] >= 0)
      throw std::invalid_argument("NormalMatrix: the elimination order is not a permutation of the " +
                                  std::to_string(n_) + " unknowns (entry " + std::to_string(k) + " is " +
                                  std::to_string(u) + ")");
    position_[u] = k;
  }
  // At by rows: the equations of each unknown, ascending
  eq_ptr_.assign(n + 1, 0);
  for (std::size_t t = 0; t < At.row_idx.size(); ++t) ++eq_ptr_[At.row_idx[t] + 1];
  for (std::size_t u = 0; u < n; ++u) eq_ptr_[u + 1] += eq_ptr_[u];
  eq_idx_.resize(At.row_idx.size());
  eq_slot_.resize(At.row_idx.size());
  std::vector<Index> fill(eq_ptr_.begin(), eq_ptr_.end() - 1);
  for (Index e = 0; e < At.cols; ++e)
    for (Index t = At.col_ptr[e]; t < At.col_ptr[e + 1]; ++t) {
      const Index p = fill[At.row_idx[t]]++;
      eq_idx_[p] = e;
      eq_slot_[p] = t;
    }
  // B's row k: the positions of every unknown sharing an equation with order[k],
  // and k itself (the diagonal carries beta)
  where_.assign(n, -1);  // here: the last row that holds a column
  row_ptr_.assign(n + 1, 0);
  col_idx_.clear();
  std::vector<Index> cols;
  for (Index k = 0; k < n_; ++k) {
    const Index u = order_[k];
    cols.clear();
    cols.push_back(k);
    where_[k] = k;
    for (Index p = eq_ptr_[u]; p < eq_ptr_[u + 1]; ++p) {
      const Index e = eq_idx_[p];
      for (Index t = At.col_ptr[e]; t < At.col_ptr[e + 1]; ++t) {
        const Index l = position_[At.row_idx[t]];
        if (where_[l] != k) {
          where_[l] = k;
          cols.push_back(l);
        }
      }
    }
    std::sort(cols.begin(), cols.end());
    if (col_idx_.size() + cols.size() > static_cast<std::size_t>(std::numeric_limits<Index>::max()))
      throw std::length_error("NormalMatrix: the normal matrix of " + std::to_string(n_) +
                              " unknowns has more than 2^31 - 1 entries");
    col_idx_.insert(col_idx_.end(), cols.begin(), cols.end());
    row_ptr_[k + 1] = static_cast<Index>(col_idx_.size());
  }
  val_.assign(col_idx_.size(), 0.0);
  where_.assign(n, -1);
}

void NormalMatrix::assemble(const SparseMatrix& At, const std::vector<double>& scaled, double beta) {
  for (Index k = 0; k < n_; ++k) {
    const Index u = order_[k];
    for (Index p = row_ptr_[k]; p < row_ptr_[k + 1]; ++p) {
      where_[col_idx_[p]] = p;
      val_[p] = 0.0;
    }
    // B(k, l) = sum over the equations e of u: (D A)(e, u) (D A)(e, order[l]), e ascending
    for (Index p = eq_ptr_[u]; p < eq_ptr_[u + 1]; ++p) {
      const Index e = eq_idx_[p];
      const double a = scaled[eq_slot_[p]];
      for (Index t = At.col_ptr[e]; t < At.col_ptr[e + 1]; ++t)
        val_[where_[position_[At.row_idx[t]]]] += a * scaled[t];
    }
    val_[where_[k]] += beta;
  }
}

}  // namespace scandyn::factor_graph
