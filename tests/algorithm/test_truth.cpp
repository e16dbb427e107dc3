// The high-precision truth (scandyn/truth/truth.hpp: the reference algorithms in
// long double and __float128) and the forward-dynamics check
// (scandyn/algorithm/fd_check.hpp).
//
// Tolerances. eps_d = 2^-52, eps_ld = 2^-63, eps_q = 2^-112. Errors are
// scandyn::rel_err's (max_i |x_i - ref_i| / max(1, max_i |ref_i|)), differences
// taken in binary128 (truth::rel_err).
//   - ID, bias forces, M: the double reference within 8 nv eps_d of the truth, long
//     double within 8 nv eps_ld of binary128 (a rounding per term of a sum over the
//     tree; measured at most 1.3 nv eps).
//   - forward dynamics (ABA, JSI): within 8 nv eps kappa, kappa = cond_2(M) from the
//     truth's own M (the textbook bound of a backward-stable solve, which JSI meets;
//     ABA is far inside it); long double against binary128 the same with eps_ld.
//   - identities in binary128: ID(FD(tau)) = tau within 1e-30 (relative to
//     max(1, |tau|)) times kappa / 1e3 at least 1; CRBA = RNEA columns within 1e-30;
//     M exactly symmetric and positive definite (its L^T L factorisation succeeds).
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <random>
#include <string>
#include <vector>

#include "scandyn/algorithm/fd_check.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/truth/truth.hpp"
#include "floating_models.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

constexpr double kEpsD = 2.220446049250313e-16;
constexpr double kEpsLd = 1.0842021724855044e-19;

struct Case {
  std::string name;
  Model model;
};

std::vector<Case> models() {
  std::vector<Case> out;
  for (const char* f : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) out.push_back({f, test::load_robot(f)});
  for (const char* spec : {"tree:20:1", "tree:60:2", "tree:120:3", "chain:16", "rope:40"})
    out.push_back({spec, load_model(spec)});
  out.push_back({"random_model(30)", test::random_model(30, 8)});
  return out;
}

// Models with multi-DoF joints (the reference's general path): the robots on a
// floating base, random trees on a free root with spherical joints, a free rope, a
// rope of ball joints, and both at once.
std::vector<Case> multi_dof_models() {
  std::vector<Case> out;
  for (const char* spec : {"iiwa", "hyq", "atlas", "rope:40", "ballrope:30", "tree:40:3"})
    out.push_back({std::string("floating ") + spec, test::load_floating(spec)});
  out.push_back({"ballrope:20", load_model("ballrope:20")});
  for (int n : {6, 25}) out.push_back({"random_floating_model(" + std::to_string(n) + ")",
                                       test::random_floating_model(n, 11u * n + 3)});
  return out;
}

// cond_2(M) of a binary128 mass matrix (eigenvalues in double: plenty for a factor).
double condition(const std::vector<float128>& M, int n) {
  Eigen::MatrixXd A(n, n);
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j) A(i, j) = double(M[static_cast<std::size_t>(i * n + j)]);
  const Eigen::VectorXd ev = Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd>(A).eigenvalues();
  return ev.maxCoeff() / ev.minCoeff();
}

struct State {
  std::vector<double> q, qd, x;
};
// q (nq: quaternions unit, test::random_q), qd and a third vector (qdd or tau, nv).
State random_state(const Model& m, std::mt19937_64& g) {
  const int n = m.nv();
  return {test::random_q(m, g, -3.1, 3.1), test::random_vector(g, n, -2, 2), test::random_vector(g, n, -5, 5)};
}

}  // namespace

// The double reference against the binary128 truth, and long double against
// binary128, on every algorithm.
static void check_agreement(const Case& c) {
  {
    SCOPED_TRACE(c.name);
    const int n = c.model.nv();
    truth::Truth<float128> tq(c.model);
    truth::Truth<long double> tl(c.model);
    Data d(c.model);
    std::mt19937_64 g(17);
    double worst_d = 0, worst_ld = 0, worst_fd_d = 0, worst_fd_ld = 0;
    for (int k = 0; k < 20; ++k) {
      const State s = random_state(c.model, g);
      std::vector<float128> xq(static_cast<std::size_t>(n) * n);
      std::vector<long double> xl(static_cast<std::size_t>(n) * n);
      std::vector<double> xd(static_cast<std::size_t>(n) * n);
      const double tol_d = 2 * n * kEpsD, tol_ld = 2 * n * kEpsLd;
      auto check = [&](const char* what, std::size_t len) {
        const double ed = truth::rel_err(xd.data(), xq.data(), len);
        const double el = truth::rel_err(xl.data(), xq.data(), len);
        EXPECT_LE(ed, tol_d) << what << " double";
        EXPECT_LE(el, tol_ld) << what << " long double";
        worst_d = std::max(worst_d, ed / (n * kEpsD));
        worst_ld = std::max(worst_ld, el / (n * kEpsLd));
      };
      rnea(c.model, d, s.q.data(), s.qd.data(), s.x.data(), xd.data());
      tq.id(s.q.data(), s.qd.data(), s.x.data(), xq.data());
      tl.id(s.q.data(), s.qd.data(), s.x.data(), xl.data());
      check("rnea", n);
      bias_forces(c.model, d, s.q.data(), s.qd.data(), xd.data());
      tq.bias(s.q.data(), s.qd.data(), xq.data());
      tl.bias(s.q.data(), s.qd.data(), xl.data());
      check("bias", n);
      crba(c.model, d, s.q.data(), xd.data());
      tq.mass(s.q.data(), xq.data());
      tl.mass(s.q.data(), xl.data());
      check("crba", static_cast<std::size_t>(n) * n);
      const double kappa = condition(xq, n);

      // forward dynamics: the truth by ABA; double ABA and JSI, long double ABA
      std::vector<float128> fq(n), fq_jsi(n);
      std::vector<long double> fl(n);
      std::vector<double> fa(n), fj(n);
      ASSERT_TRUE(tq.fd(s.q.data(), s.qd.data(), s.x.data(), fq.data()).ok());
      ASSERT_TRUE(tq.fd_jsi(s.q.data(), s.qd.data(), s.x.data(), fq_jsi.data()).ok());
      ASSERT_TRUE(tl.fd(s.q.data(), s.qd.data(), s.x.data(), fl.data()).ok());
      ASSERT_TRUE(aba(c.model, d, s.q.data(), s.qd.data(), s.x.data(), fa.data()).ok());
      ASSERT_TRUE(fd_jsi(c.model, d, s.q.data(), s.qd.data(), s.x.data(), fj.data()).ok());
      const double e_aba = truth::rel_err(fa.data(), fq.data(), n), e_jsi = truth::rel_err(fj.data(), fq.data(), n);
      const double e_ld = truth::rel_err(fl.data(), fq.data(), n);
      EXPECT_LE(e_aba, n * kEpsD * kappa) << "aba, cond " << kappa;
      EXPECT_LE(e_jsi, n * kEpsD * kappa) << "fd_jsi, cond " << kappa;
      EXPECT_LE(e_ld, n * kEpsLd * kappa) << "long double aba, cond " << kappa;
      worst_fd_d = std::max({worst_fd_d, e_aba / (n * kEpsD * kappa), e_jsi / (n * kEpsD * kappa)});
      worst_fd_ld = std::max(worst_fd_ld, e_ld / (n * kEpsLd * kappa));
      // the two binary128 routes agree far below double's rounding
      EXPECT_LE(truth::rel_err(fq_jsi.data(), fq.data(), n), 1e-30 * std::max(1.0, kappa));
    }
    // the measured constants (in units of nv eps and nv eps kappa)
    ::testing::Test::RecordProperty(c.name + ".id_bias_mass.double", std::to_string(worst_d));
    ::testing::Test::RecordProperty(c.name + ".id_bias_mass.longdouble", std::to_string(worst_ld));
    ::testing::Test::RecordProperty(c.name + ".fd.double", std::to_string(worst_fd_d));
    ::testing::Test::RecordProperty(c.name + ".fd.longdouble", std::to_string(worst_fd_ld));
  }
}

// Identities in binary128.
static void check_float128_identities(const Case& c) {
  {
    SCOPED_TRACE(c.name);
    const int n = c.model.nv();
    truth::Truth<float128> t(c.model);
    std::mt19937_64 g(29);
    for (int k = 0; k < 5; ++k) {
      const State s = random_state(c.model, g);
      // M symmetric, positive definite, = columns of RNEA(q, 0, e_j) - RNEA(q, 0, 0)
      std::vector<float128> M(static_cast<std::size_t>(n) * n), g0(n), col(n), L;
      t.mass(s.q.data(), M.data());
      for (int i = 0; i < n; ++i)
        for (int j = 0; j < n; ++j) EXPECT_TRUE(M[i * n + j] == M[j * n + i]) << i << "," << j;
      const std::vector<double> zero(n, 0.0);
      std::vector<double> e(n, 0.0);
      t.id(s.q.data(), zero.data(), zero.data(), g0.data());
      float128 worst = 0, scale = 1;
      for (int j = 0; j < n; ++j) {
        e[j] = 1;
        t.id(s.q.data(), zero.data(), e.data(), col.data());
        e[j] = 0;
        for (int i = 0; i < n; ++i) {
          worst = std::max(worst, ScalarMath<float128>::abs(col[i] - g0[i] - M[i * n + j]));
          scale = std::max(scale, ScalarMath<float128>::abs(M[i * n + j]));
        }
      }
      EXPECT_LE(double(worst / scale), 1e-30) << "CRBA vs RNEA columns";
      L = M;
      DataTpl<float128> data(t.model());
      EXPECT_TRUE(ltl_factor(t.model(), data, L.data()).ok()) << "M positive definite";
      const double kappa = condition(M, n);

      // ID(FD(tau)) = tau
      std::vector<float128> qdd(n), back(n);
      ASSERT_TRUE(t.fd(s.q.data(), s.qd.data(), s.x.data(), qdd.data()).ok());
      const std::vector<float128> qq = t.q();  // the q fd used (quaternions unit in binary128)
      std::vector<float128> qdq(n);
      for (int i = 0; i < n; ++i) qdq[i] = s.qd[i];
      rnea(t.model(), data, qq.data(), qdq.data(), qdd.data(), back.data());
      EXPECT_LE(truth::rel_err(back.data(), s.x.data(), n), 1e-30 * std::max(1.0, kappa / 1e3))
          << "ID(FD(tau)), cond " << kappa;
    }
  }
}

TEST(Truth, AgreesWithDoubleAndLongDouble) {
  for (const Case& c : models()) check_agreement(c);
}
TEST(Truth, Float128Identities) {
  for (const Case& c : models()) check_float128_identities(c);
}
// The same on models with a floating base and spherical joints: q with nq entries,
// the quaternions normalised again in binary128 / long double by the truth (the
// double reference reads the double ones as they are, unit to ~1e-16: within its
// tolerances above).
TEST(Truth, MultiDofAgreesWithDoubleAndLongDouble) {
  for (const Case& c : multi_dof_models()) check_agreement(c);
}
TEST(Truth, MultiDofFloat128Identities) {
  for (const Case& c : multi_dof_models()) check_float128_identities(c);
}

// ---- the forward-dynamics check ---------------------------------------------------

// A correct result passes; a result off by a known delta is estimated to be off by it,
// and the refined result qdd - delta is the truth again.
TEST(FdCheck, EstimatesAKnownError) {
  for (const Case& c : models()) {
    SCOPED_TRACE(c.name);
    const int n = c.model.nv();
    Data d(c.model);
    std::mt19937_64 g(31);
    for (int k = 0; k < 5; ++k) {
      const State s = random_state(c.model, g);
      std::vector<double> qdd(n), delta(n), off(n);
      ASSERT_TRUE(aba(c.model, d, s.q.data(), s.qd.data(), s.x.data(), qdd.data()).ok());
      const FdCheck<double> ok = fd_check(c.model, d, s.q.data(), s.qd.data(), s.x.data(), qdd.data());
      EXPECT_LE(ok.error_estimate, 1e-13);
      EXPECT_TRUE(ok.ok(fd_check_threshold<double>()));
      EXPECT_LE(ok.relative_residual, 1e-13);
      // perturb by 1e-6 of the scale on every DoF
      double scale = 1;
      for (double x : qdd) scale = std::max(scale, std::fabs(x));
      const auto p = test::random_vector(g, n, -1e-6, 1e-6);
      for (int i = 0; i < n; ++i) off[i] = qdd[i] + p[i] * scale;
      double true_err = 0, off_scale = 1;
      for (int i = 0; i < n; ++i) true_err = std::max(true_err, std::fabs(p[i]) * scale);
      for (double x : off) off_scale = std::max(off_scale, std::fabs(x));
      const FdCheck<double> bad = fd_check(c.model, d, s.q.data(), s.qd.data(), s.x.data(), off.data(),
                                           static_cast<const Force<double>*>(nullptr), static_cast<const double*>(nullptr),
                                           delta.data());
      EXPECT_NEAR(bad.error_estimate, true_err / off_scale, 1e-9 * true_err / off_scale);
      EXPECT_FALSE(bad.ok(fd_check_threshold<double>()));
      for (int i = 0; i < n; ++i) EXPECT_NEAR(off[i] - delta[i], qdd[i], 1e-12 * scale);
    }
  }
}

// External wrenches and armature enter the residual as they enter aba.
TEST(FdCheck, ExternalWrenchesAndArmature) {
  for (const char* spec : {"tree:40:5", "chain:9"}) {
    SCOPED_TRACE(spec);
    const Model m = load_model(spec);
    const int n = m.nv();
    Data d(m);
    std::mt19937_64 g(37);
    const State s = random_state(m, g);
    const auto fext = test::random_wrenches<double>(g, n, 2.0);
    const auto arm = test::random_vector(g, n, 0.0, 0.5);
    std::vector<double> qdd(n);
    ASSERT_TRUE(aba(m, d, s.q.data(), s.qd.data(), s.x.data(), qdd.data(), fext.data(), arm.data()).ok());
    EXPECT_LE(fd_check(m, d, s.q.data(), s.qd.data(), s.x.data(), qdd.data(), fext.data(), arm.data()).error_estimate,
              1e-13);
    // without them the same qdd is wrong
    EXPECT_GT(fd_check(m, d, s.q.data(), s.qd.data(), s.x.data(), qdd.data()).error_estimate, 1e-3);
  }
}

// Zero torques and rest under gravity: a correct result is not flagged, and its
// relative residual is at rounding level (the scale includes the joint loads).
TEST(FdCheck, ZeroTorqueRows) {
  for (const Case& c : models()) {
    SCOPED_TRACE(c.name);
    const int n = c.model.nv();
    Data d(c.model);
    std::mt19937_64 g(41);
    const State s = random_state(c.model, g);
    const std::vector<double> zero(n, 0.0);
    std::vector<double> qdd(n);
    for (const std::vector<double>* qd : {&s.qd, &zero}) {
      ASSERT_TRUE(aba(c.model, d, s.q.data(), qd->data(), zero.data(), qdd.data()).ok());
      const FdCheck<double> r = fd_check(c.model, d, s.q.data(), qd->data(), zero.data(), qdd.data());
      EXPECT_LE(r.relative_residual, 1e-13);
      EXPECT_LE(r.error_estimate, 1e-13);
    }
  }
}

// The silent float cases: float JSI on chain:64 and on ropes of 30 and 100 links is
// flagged exactly where its true error exceeds the float budget (by a check in
// double, as fd_check.hpp recommends); float ABA on the robots is not flagged.
TEST(FdCheck, FlagsSilentFloatJsi) {
  for (const char* spec : {"chain:64", "rope:30", "rope:100"}) {
    SCOPED_TRACE(spec);
    const Model md = load_model(spec);
    const ModelTpl<float> mf = md.cast<float>();
    DataTpl<float> df(mf);
    Data d(md, false);
    truth::Truth<float128> t(md, false);
    const int n = md.nv();
    std::mt19937_64 g(43);
    int flagged = 0, bad = 0;
    for (int k = 0; k < 8; ++k) {
      std::vector<float> q(n), qd(n), tau(n), qdd(n);
      for (auto* v : {&q, &qd, &tau})
        for (float& x : *v) x = float(std::uniform_real_distribution<double>(-1, 1)(g));
      if (!fd_jsi(mf, df, q.data(), qd.data(), tau.data(), qdd.data()).ok()) continue;  // reported, not silent
      const std::vector<double> q_d(q.begin(), q.end()), qd_d(qd.begin(), qd.end()), tau_d(tau.begin(), tau.end());
      std::vector<float128> tr(n);
      ASSERT_TRUE(t.fd(q_d.data(), qd_d.data(), tau_d.data(), tr.data()).ok());
      const double err = truth::rel_err(qdd.data(), tr.data(), n);
      const double est = fd_check(md, d, q.data(), qd.data(), tau.data(), qdd.data()).error_estimate;
      bad += err > 1e-4;
      flagged += est > fd_check_threshold<float>();
      // the estimate is the error to first order: within 10% while the error is
      // small enough for the first order to hold (the study measures 1.00 there)
      if (err > 1e-4 && err < 1e-2) {
        EXPECT_NEAR(est / err, 1.0, 0.1) << "state " << k;
      }
    }
    EXPECT_GT(bad, 0);
    EXPECT_EQ(flagged, bad);
  }
  for (const char* f : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) {
    SCOPED_TRACE(f);
    const Model md = test::load_robot(f);
    const ModelTpl<float> mf = md.cast<float>();
    DataTpl<float> df(mf);
    Data d(md, false);
    const int n = md.nv();
    std::mt19937_64 g(47);
    for (int k = 0; k < 50; ++k) {
      std::vector<float> q(n), qd(n), tau(n), qdd(n);
      for (auto* v : {&q, &qd, &tau})
        for (float& x : *v) x = float(std::uniform_real_distribution<double>(-3, 3)(g));
      ASSERT_TRUE(aba(mf, df, q.data(), qd.data(), tau.data(), qdd.data()).ok());
      EXPECT_TRUE(fd_check(md, d, q.data(), qd.data(), tau.data(), qdd.data()).ok(fd_check_threshold<float>()));
    }
  }
}

// A pivot that is not positive is reported, and the estimate is +inf (fails any threshold).
TEST(FdCheck, ReportsAFailedPivot) {
  Model m = test::random_model(3, 4);
  m.bodies[2].I = Inertia<double>::zero();
  m.bodies[2].parent = 1;
  Data d(m);
  const double q[3] = {0.1, 0.2, 0.3}, qd[3] = {0, 0, 0}, tau[3] = {1, 1, 1}, qdd[3] = {0, 0, 0};
  const FdCheck<double> r = fd_check(m, d, q, qd, tau, qdd);
  EXPECT_EQ(r.failed_dof, 2);
  EXPECT_FALSE(r.ok(1e300));
}
