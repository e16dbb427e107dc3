// tests/identities.hpp: the dynamics identities the algorithm tests check on every
// model (test_algorithms.cpp, test_floating.cpp).
#pragma once

#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <limits>
#include <random>
#include <string>

#include "scandyn/algorithm/reference.hpp"
#include "test_util.hpp"

namespace scandyn::test {

// The identities every model satisfies, for one model and precision (q with unit
// quaternions for multi-DoF joints): ABA = CRBA + Cholesky, ID(FD(tau)) = tau,
// CRBA = RNEA columns, M symmetric positive definite, M qdd + h = tau.
template <class S>
void check_identities(const Model& model_d, unsigned seed, const std::string& what) {
  SCOPED_TRACE(what);
  const ModelTpl<S> model = model_d.template cast<S>();
  DataTpl<S> data(model);
  const int n = model.nv();
  std::mt19937_64 rng(seed);
  const auto q = cast_vector<S>(random_q(model_d, rng));
  const auto qd = cast_vector<S>(random_vector(rng, n, -2, 2));
  const auto tau = cast_vector<S>(random_vector(rng, n, -5, 5));
  const std::vector<S> zero(n, S(0));
  const S nan = std::numeric_limits<S>::quiet_NaN();

  // forward dynamics two ways
  std::vector<S> qdd_aba(n, nan), qdd_jsi(n, nan), tau_back(n, nan);
  ASSERT_TRUE(aba(model, data, q.data(), qd.data(), tau.data(), qdd_aba.data()).ok());
  ASSERT_TRUE(fd_jsi(model, data, q.data(), qd.data(), tau.data(), qdd_jsi.data()).ok());
  // conditioning grows with depth: scale the tolerance by the size of qdd
  EXPECT_LT(max_rel_err(qdd_jsi, qdd_aba), Tol<S>(1e-9, 2e-2)) << "ABA vs CRBA+Cholesky";
  // ID(q, qd, FD(q, qd, tau)) = tau
  rnea(model, data, q.data(), qd.data(), qdd_aba.data(), tau_back.data());
  EXPECT_LT(max_rel_err(tau_back, tau), Tol<S>(1e-10, 2e-3)) << "ID(FD(tau)) = tau";

  // CRBA = columns of RNEA(q, 0, e_i) - RNEA(q, 0, 0)
  std::vector<S> M(n * n, nan), g0(n, nan), col(n, nan), e(n, S(0));
  crba(model, data, q.data(), M.data());
  rnea(model, data, q.data(), zero.data(), zero.data(), g0.data());
  double worst = 0, scale = 1;
  for (int i = 0; i < n * n; ++i) scale = std::max(scale, std::fabs(double(M[i])));
  for (int j = 0; j < n; ++j) {
    e[j] = S(1);
    rnea(model, data, q.data(), zero.data(), e.data(), col.data());
    e[j] = S(0);
    for (int i = 0; i < n; ++i) worst = std::max(worst, std::fabs(double(col[i] - g0[i]) - double(M[i * n + j])));
  }
  EXPECT_LT(worst / scale, Tol<S>(1e-12, 1e-5)) << "CRBA vs RNEA columns";

  // M symmetric positive definite
  Eigen::MatrixXd Md(n, n);
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j) Md(i, j) = double(M[i * n + j]);
  EXPECT_EQ((Md - Md.transpose()).cwiseAbs().maxCoeff(), 0.0);
  EXPECT_EQ(Eigen::LLT<Eigen::MatrixXd>(Md).info(), Eigen::Success);

  // bias forces = RNEA(q, qd, 0); tau = M qdd + h
  std::vector<S> h(n, nan), tau_m(n, S(0));
  bias_forces(model, data, q.data(), qd.data(), h.data());
  for (int i = 0; i < n; ++i) {
    double acc = double(h[i]);
    for (int j = 0; j < n; ++j) acc += double(M[i * n + j]) * double(qdd_aba[j]);
    tau_m[i] = S(acc);
  }
  EXPECT_LT(max_rel_err(tau_m, tau), Tol<S>(1e-9, 5e-3)) << "M qdd + h = tau";
}

// float results against the double reference on the same inputs (10 random states,
// q drawn by random_q): RNEA and CRBA within 1e-5, ABA within 1e-3 (relative).
inline void check_float_vs_double(const Model& md, const std::string& what) {
  SCOPED_TRACE(what);
  const ModelTpl<float> mf = md.cast<float>();
  DataTpl<double> dd(md);
  DataTpl<float> df(mf);
  const int n = md.nv();
  std::mt19937_64 rng(5);
  for (int t = 0; t < 10; ++t) {
    const auto q = random_q(md, rng), qd = random_vector(rng, n, -2, 2), x = random_vector(rng, n, -5, 5);
    const auto qf = cast_vector<float>(q), qdf = cast_vector<float>(qd), xf = cast_vector<float>(x);
    std::vector<double> od(n);
    std::vector<float> of(n);
    rnea(md, dd, q.data(), qd.data(), x.data(), od.data());
    rnea(mf, df, qf.data(), qdf.data(), xf.data(), of.data());
    EXPECT_LT(max_rel_err(of, od), 1e-5) << "RNEA float";
    ASSERT_TRUE(aba(md, dd, q.data(), qd.data(), x.data(), od.data()).ok());
    ASSERT_TRUE(aba(mf, df, qf.data(), qdf.data(), xf.data(), of.data()).ok());
    EXPECT_LT(max_rel_err(of, od), 1e-3) << "ABA float";
    std::vector<double> Md(n * n);
    std::vector<float> Mf(n * n);
    crba(md, dd, q.data(), Md.data());
    crba(mf, df, qf.data(), Mf.data());
    EXPECT_LT(max_rel_err(Mf, Md), 1e-5) << "CRBA float";
  }
}

}  // namespace scandyn::test
