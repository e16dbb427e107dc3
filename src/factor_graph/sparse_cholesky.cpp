// src/factor_graph/sparse_cholesky.cpp: CHOLMOD on the factor graph's normal
// equations (scandyn/factor_graph/sparse_cholesky.hpp).
#include "scandyn/factor_graph/sparse_cholesky.hpp"

#if SCANDYN_HAS_CHOLMOD
#include <cholmod.h>

#include "scandyn/factor_graph/normal_equations.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace scandyn::factor_graph {

const char* ordering_name(Ordering o) {
  switch (o) {
    case Ordering::Given: return "given";
    case Ordering::Natural: return "natural";
    case Ordering::AMD: return "amd";
    case Ordering::COLAMD: return "colamd";
    case Ordering::METIS: return "metis";
    case Ordering::NESDIS: return "nesdis";
  }
  return "?";
}

struct SparseCholesky::Impl {
  cholmod_common c;
  cholmod_factor* L = nullptr;
  cholmod_sparse At;      // view of the caller's At (no copy)
  double beta[2] = {0, 0};
  cholmod_dense* rhs = nullptr;   // unknowns x 1
  cholmod_dense* x = nullptr;     // unknowns x 1 (solve2 output)
  cholmod_dense* Y = nullptr;     // solve2 workspaces
  cholmod_dense* E = nullptr;
  std::vector<Index> perm;        // elimination order after analysis
  NormalEquations ne;             // the column scaling D, D At's values, the refined solve
  cholmod_sparse DAt;             // view of At's pattern with the scaled values (ne.scaled())

  void view(const SparseMatrix& M) {
    At.nrow = static_cast<std::size_t>(M.rows);
    At.ncol = static_cast<std::size_t>(M.cols);
    At.nzmax = M.val.size();
    At.p = const_cast<Index*>(M.col_ptr.data());
    At.i = const_cast<Index*>(M.row_idx.data());
    At.nz = nullptr;
    At.x = const_cast<double*>(M.val.data());
    At.z = nullptr;
    At.stype = 0;
    At.itype = CHOLMOD_INT;
    At.xtype = CHOLMOD_REAL;
    At.dtype = CHOLMOD_DOUBLE;
    At.sorted = 1;
    At.packed = 1;
  }
  ~Impl() {
    cholmod_free_factor(&L, &c);
    cholmod_free_dense(&rhs, &c);
    cholmod_free_dense(&x, &c);
    cholmod_free_dense(&Y, &c);
    cholmod_free_dense(&E, &c);
    cholmod_finish(&c);
  }
};

SparseCholesky::SparseCholesky(const SparseMatrix& At, Ordering ordering, const std::vector<Index>& given,
                               double beta, bool simplicial)
    : impl_(std::make_unique<Impl>()) {
  Impl& m = *impl_;
  cholmod_start(&m.c);
  m.c.print = 0;
  m.c.error_handler = nullptr;
  m.beta[0] = beta;
  m.c.supernodal = simplicial ? CHOLMOD_SIMPLICIAL : CHOLMOD_AUTO;
  m.c.nmethods = 1;
  m.c.postorder = ordering == Ordering::Given ? 0 : 1;  // keep a given order exactly
  switch (ordering) {
    case Ordering::Given: m.c.method[0].ordering = CHOLMOD_GIVEN; break;
    case Ordering::Natural: m.c.method[0].ordering = CHOLMOD_NATURAL; break;
    case Ordering::AMD: m.c.method[0].ordering = CHOLMOD_AMD; break;
    case Ordering::COLAMD: m.c.method[0].ordering = CHOLMOD_COLAMD; break;
    case Ordering::METIS: m.c.method[0].ordering = CHOLMOD_METIS; break;
    case Ordering::NESDIS: m.c.method[0].ordering = CHOLMOD_NESDIS; break;
  }
  if (ordering == Ordering::Given && static_cast<Index>(given.size()) != At.rows)
    throw std::invalid_argument("SparseCholesky: the given ordering has " + std::to_string(given.size()) +
                                " entries, the system " + std::to_string(At.rows) + " unknowns");
  m.view(At);
  m.L = ordering == Ordering::Given
            ? cholmod_analyze_p(&m.At, const_cast<Index*>(given.data()), nullptr, 0, &m.c)
            : cholmod_analyze(&m.At, &m.c);
  if (!m.L || m.c.status < 0)
    throw std::runtime_error(std::string("SparseCholesky: CHOLMOD analysis failed (") + ordering_name(ordering) + ")");
  stats_.nnz_A = static_cast<double>(At.val.size());
  stats_.nnz_L = m.c.lnz;
  stats_.flops = m.c.fl;
  stats_.supernodal = m.L->is_super != 0;
  const Index n = At.rows;
  m.perm.assign(static_cast<const Index*>(m.L->Perm), static_cast<const Index*>(m.L->Perm) + n);
  const std::vector<Index> parent = etree();
  std::vector<int> depth(static_cast<std::size_t>(n), 1);
  int height = 0;
  for (Index k = n - 1; k >= 0; --k) {  // parents come after children
    if (parent[k] >= 0) depth[k] = depth[parent[k]] + 1;
    height = std::max(height, depth[k]);
  }
  stats_.etree_height = height;
  m.rhs = cholmod_zeros(static_cast<std::size_t>(n), 1, CHOLMOD_REAL, &m.c);
}

SparseCholesky::~SparseCholesky() = default;

const std::vector<Index>& SparseCholesky::elimination_order() const { return impl_->perm; }

std::vector<std::pair<Index, Index>> SparseCholesky::factor_pattern() const {
  Impl& m = *impl_;
  cholmod_factor* F = cholmod_copy_factor(m.L, &m.c);
  cholmod_sparse* S = F ? cholmod_factor_to_sparse(F, &m.c) : nullptr;
  cholmod_free_factor(&F, &m.c);
  if (!S) throw std::runtime_error("SparseCholesky: cannot read the factor's pattern (factorize first)");
  std::vector<std::pair<Index, Index>> out;
  const Index* p = static_cast<const Index*>(S->p);
  const Index* ri = static_cast<const Index*>(S->i);
  for (Index j = 0; j < static_cast<Index>(S->ncol); ++j)
    for (Index t = p[j]; t < p[j + 1]; ++t) out.emplace_back(ri[t], j);
  cholmod_free_sparse(&S, &m.c);
  return out;
}

// The elimination tree of A^T A under the analysed permutation (Liu's algorithm on
// the rows of A, as CSparse's cs_etree with ata = 1).
std::vector<Index> SparseCholesky::etree() const {
  const Impl& m = *impl_;
  const Index n = static_cast<Index>(m.At.nrow), neq = static_cast<Index>(m.At.ncol);
  const Index* p = static_cast<const Index*>(m.At.p);
  const Index* ri = static_cast<const Index*>(m.At.i);
  // equations of each unknown (rows of At)
  std::vector<Index> start(static_cast<std::size_t>(n) + 1, 0), eqs(static_cast<std::size_t>(p[neq]));
  for (Index e = 0; e < neq; ++e)
    for (Index t = p[e]; t < p[e + 1]; ++t) ++start[ri[t] + 1];
  for (Index k = 0; k < n; ++k) start[k + 1] += start[k];
  std::vector<Index> fill(start.begin(), start.end() - 1);
  for (Index e = 0; e < neq; ++e)
    for (Index t = p[e]; t < p[e + 1]; ++t) eqs[fill[ri[t]]++] = e;
  std::vector<Index> parent(static_cast<std::size_t>(n), -1), ancestor(static_cast<std::size_t>(n), -1),
      prev(static_cast<std::size_t>(neq), -1);
  for (Index k = 0; k < n; ++k) {
    const Index u = m.perm[k];
    for (Index t = start[u]; t < start[u + 1]; ++t) {
      const Index e = eqs[t];
      for (Index i = prev[e]; i != -1 && i < k;) {
        const Index next = ancestor[i];
        ancestor[i] = k;
        if (next == -1) { parent[i] = k; break; }
        i = next;
      }
      prev[e] = k;
    }
  }
  return parent;
}

void SparseCholesky::factorize(const SparseMatrix& At) {
  Impl& m = *impl_;
  m.view(At);
  // factor D A^T A D + beta I (D: unit column norms of A, NormalEquations)
  m.ne.equilibrate(At);
  m.DAt = m.At;
  m.DAt.x = const_cast<double*>(m.ne.scaled().data());
  cholmod_factorize_p(&m.DAt, m.beta, nullptr, 0, m.L, &m.c);
  if (m.c.status == CHOLMOD_NOT_POSDEF || m.L->minor < m.L->n)
    throw std::runtime_error("SparseCholesky: A^T A + beta I is not positive definite (column " +
                             std::to_string(m.L->minor) + " of the ordered system): the factor graph's "
                             "system is singular (redundant loop constraints need beta > 0)");
  if (m.c.status < 0) throw std::runtime_error("SparseCholesky: CHOLMOD factorisation failed");
}

void SparseCholesky::solve(const SparseMatrix& At, const std::vector<double>& b, std::vector<double>& x,
                           int refine) {
  Impl& m = *impl_;
  m.view(At);
  const std::size_t n = static_cast<std::size_t>(At.rows);
  m.ne.solve(At, b, x, refine, [&](const double* rhs, double* y) {
    std::copy(rhs, rhs + n, static_cast<double*>(m.rhs->x));
    cholmod_solve2(CHOLMOD_A, m.L, m.rhs, nullptr, &m.x, nullptr, &m.Y, &m.E, &m.c);
    if (!m.x || m.c.status < 0) throw std::runtime_error("SparseCholesky: CHOLMOD solve failed");
    const double* xs = static_cast<const double*>(m.x->x);
    std::copy(xs, xs + n, y);
  });
}

}  // namespace scandyn::factor_graph
#endif
