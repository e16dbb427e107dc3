// The dense routines of scandyn/algorithm/loop_solver.hpp on their own: the
// rank-revealing pivoted LDL^T and its minimum-norm solve against Eigen's
// pseudo-inverse on random positive semidefinite matrices of every rank (m = 1..12,
// consistent right-hand sides), the Cholesky and its failure row, and
// constrained_fd_solve's equations on random SPD M and rank-deficient J.
// Tolerances: double 1e-10 relative to max(1, |x|); float 1e-3.
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <random>
#include <vector>

#include "scandyn/algorithm/loop_solver.hpp"

using namespace scandyn;

namespace {

using MatX = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

// A random m x m PSD matrix of rank r (G G^T, G m x r) and b = A y in its range.
void psd(std::mt19937_64& g, Index m, Index r, MatX& A, Eigen::VectorXd& b) {
  std::normal_distribution<double> n(0, 1);
  MatX G(m, r);
  for (Index i = 0; i < m; ++i)
    for (Index k = 0; k < r; ++k) G(i, k) = n(g);
  A = G * G.transpose();
  Eigen::VectorXd y(m);
  for (Index i = 0; i < m; ++i) y[i] = n(g);
  b = A * y;
}

}  // namespace

TEST(LoopSolver, PivotedLdltMinimumNorm) {
  std::mt19937_64 g(11);
  for (Index m = 1; m <= 12; ++m) {
    for (Index r = 0; r <= m; ++r) {
      MatX A;
      Eigen::VectorXd b;
      psd(g, m, r, A, b);
      const Eigen::VectorXd ref = A.completeOrthogonalDecomposition().pseudoInverse() * b;
      MatX F = A;
      std::vector<Index> perm(m);
      const Index rank = pivoted_ldlt(F.data(), m, perm.data(), loop_rank_tolerance<double>());
      EXPECT_EQ(rank, r) << "m " << m;
      std::vector<double> x(m), w(m + m * m + m * m);
      pivoted_ldlt_solve(F.data(), m, perm.data(), rank, b.data(), x.data(), w.data());
      const double scale = std::max(1.0, ref.cwiseAbs().maxCoeff());
      for (Index i = 0; i < m; ++i) EXPECT_NEAR(x[i], ref[i], 1e-9 * scale) << "m " << m << " r " << r;
    }
  }
}

TEST(LoopSolver, CholeskyReportsTheFailedRow) {
  MatX A(3, 3);
  A << 4, 2, 0, 2, 1, 0, 0, 0, 1;  // the second pivot is 1 - 1 = 0
  EXPECT_EQ(dense_cholesky(A.data(), 3), 1);
  MatX B(2, 2);
  B << 4, 2, 2, 3;
  EXPECT_EQ(dense_cholesky(B.data(), 2), -1);
  std::vector<double> x = {1, 2};
  dense_cholesky_solve(B.data(), 2, x.data(), 1);
  EXPECT_NEAR(4 * x[0] + 2 * x[1], 1, 1e-15);
  EXPECT_NEAR(2 * x[0] + 3 * x[1], 2, 1e-15);
}

template <class S>
void check_solve(double tol) {
  std::mt19937_64 g(12);
  std::normal_distribution<double> n(0, 1);
  for (Index nv : {1, 4, 9}) {
    for (Index m : {0, 3, 7}) {
      // M = G G^T + I (SPD); J with a zero row and a repeated row (rank deficient)
      MatX G(nv, nv), J = MatX::Zero(m, nv);
      for (Index i = 0; i < nv; ++i)
        for (Index k = 0; k < nv; ++k) G(i, k) = n(g);
      const MatX M = G * G.transpose() + MatX::Identity(nv, nv);
      for (Index a = 0; a + 2 < m; ++a)
        for (Index i = 0; i < nv; ++i) J(a, i) = n(g);
      if (m >= 3) J.row(m - 1) = J.row(0);  // row m - 2 stays zero
      Eigen::VectorXd h(nv), tau(nv), x0(nv);
      for (Index i = 0; i < nv; ++i) h[i] = n(g), tau[i] = n(g), x0[i] = n(g);
      const Eigen::VectorXd gamma = -(J * x0);  // consistent: J x0 + gamma = 0
      std::vector<S> Ms(M.data(), M.data() + nv * nv), hs(h.data(), h.data() + nv), ts(tau.data(), tau.data() + nv),
          Js(J.data(), J.data() + m * nv), gs(gamma.data(), gamma.data() + m), qdd(nv), lam(m),
          work(constrained_fd_scratch(nv, m));
      std::vector<Index> perm(m);
      const LoopSolveStatus st = constrained_fd_solve<S>(nv, m, Ms.data(), hs.data(), ts.data(), Js.data(), gs.data(),
                                                         qdd.data(), lam.data(), work.data(), perm.data());
      ASSERT_EQ(st.failed_dof, -1);
      // the reference: the KKT system's minimum-norm solution
      Eigen::VectorXd xq(nv), xl(m);
      for (Index i = 0; i < nv; ++i) xq[i] = qdd[i];
      for (Index k = 0; k < m; ++k) xl[k] = lam[k];
      const MatX Minv = M.inverse();
      const MatX A = J * Minv * J.transpose();
      const Eigen::VectorXd q0 = Minv * (tau - h);
      const Eigen::VectorXd lref =
          m > 0 ? Eigen::VectorXd(A.completeOrthogonalDecomposition().pseudoInverse() * (-gamma - J * q0))
                : Eigen::VectorXd(0);
      const Eigen::VectorXd qref = q0 + Minv * J.transpose() * lref;
      const double sq = std::max(1.0, qref.cwiseAbs().maxCoeff());
      const double sl = m > 0 ? std::max(1.0, lref.cwiseAbs().maxCoeff()) : 1.0;
      EXPECT_LE((xq - qref).cwiseAbs().maxCoeff(), tol * sq) << "nv " << nv << " m " << m;
      if (m > 0) {
        EXPECT_LE((xl - lref).cwiseAbs().maxCoeff(), tol * sl) << "nv " << nv << " m " << m;
      }
      if (m >= 3) {
        EXPECT_LE(st.rank, m - 2);
      }
    }
  }
}

TEST(LoopSolver, ConstrainedSolveIsTheMinimumNormKktSolution) {
  check_solve<double>(1e-10);
  check_solve<float>(1e-3);
}
