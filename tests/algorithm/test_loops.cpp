// Closed kinematic loops (scandyn/algorithm/loops.hpp): the generators' loops closed at
// q = 0; J and gamma = Jdot qd against central differences of phi and of J qd; the
// constrained forward dynamics on random closed states (projected onto the loops):
// J qdd + gamma = 0 to 1e-10, the equations of motion through rnea, and qdd against an
// independent null-space solution (N^T M N y = N^T (tau - h - M qdd_p)); redundant
// rows (planar loops closed by 3D points) give rank < m and no NaN; the inverse
// dynamics with actuated sets (unique and redundant actuation); loop-file errors.
// Tolerances: double, relative to max(1, max |qdd|); differences with step 1e-6.
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <random>

#include "scandyn/algorithm/loops.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

using MatX = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

struct Loopy {
  std::string spec;
  Model model;
  LoopSet loops;
  explicit Loopy(const std::string& s) : spec(s), model(load_model(s)), loops(generator_loops(s, model)) {}
};

std::vector<Loopy> loopy_models() {
  std::vector<Loopy> v;
  for (const char* s : {"fourbar", "fivebar", "cloth:3:4", "cloth:4:6"}) v.emplace_back(s);
  // a weld loop too: fivebar's distal links welded (6 equations on 4 DoF; the random
  // states are projected onto it)
  Loopy w("fivebar");
  w.spec = "fivebar+weld";
  w.loops.loops[0].type = LoopType::Weld;
  w.loops.loops[0].point_b = w.loops.loops[0].point_a;
  v.push_back(w);
  return v;
}

// A random closed state near q = 0: small random q and qd, projected onto the loops.
void closed_state(const Loopy& L, std::mt19937_64& g, std::vector<double>& q, std::vector<double>& qd) {
  const Index n = L.model.nv();
  q = test::random_vector(g, n, -0.2, 0.2);
  qd = test::random_vector(g, n, -1, 1);
  const double r = project_to_loops(L.model, L.loops, q.data(), qd.data());
  ASSERT_LE(r, 1e-12) << L.spec;
}

}  // namespace

TEST(Loops, GeneratorsAreClosedAtZero) {
  for (const auto& L : loopy_models()) {
    if (L.spec == "fivebar+weld") continue;
    SCOPED_TRACE(L.spec);
    const std::vector<double> q(L.model.nv(), 0.0), qd(L.model.nv(), 0.0);
    EXPECT_GT(L.loops.rows(), 0);
    EXPECT_LE(loop_violation(L.model, L.loops, q.data(), qd.data()), 1e-15);
  }
  // cloth:K:N: (K - 1) N point loops between link j of rope k and rope k + 1
  const Loopy c("cloth:3:4");
  ASSERT_EQ(c.loops.loops.size(), 8u);
  EXPECT_EQ(c.loops.loops[5].link_a, "link_1_1");
  EXPECT_EQ(c.loops.loops[5].link_b, "link_2_1");
}

// loop_violation (phi and J qd by the points' velocities, O(nv + m)) equals max(|phi|,
// |J qd|) with J formed by loop_kinematics, and names the worst loop, on random states
// off the loops (point and weld loops; 1e-13 absolute, rounding of the two summations).
TEST(Loops, ViolationEqualsTheFormedJacobians) {
  std::mt19937_64 g(41);
  for (const Loopy& L : loopy_models()) {
    const Index n = L.model.nv(), m = L.loops.rows();
    for (int trial = 0; trial < 5; ++trial) {
      const std::vector<double> q = test::random_vector(g, n, -1, 1), qd = test::random_vector(g, n, -1, 1);
      std::vector<double> phi(m), J(static_cast<std::size_t>(m * n));
      loop_kinematics(L.model, L.loops, q.data(), qd.data(), phi.data(), J.data(), nullptr);
      double worst = 0;
      Index worst_loop = -1, row = 0;
      for (Index k = 0; k < static_cast<Index>(L.loops.loops.size()); ++k) {
        for (Index r = row; r < row + L.loops.loops[k].rows(); ++r) {
          double jqd = 0;
          for (Index j = 0; j < n; ++j) jqd += J[r * n + j] * qd[j];
          const double e = std::max(std::fabs(phi[r]), std::fabs(jqd));
          if (worst_loop < 0 || e > worst) worst = e, worst_loop = k;
        }
        row += L.loops.loops[k].rows();
      }
      Index loop = -2;
      const double v = loop_violation(L.model, L.loops, q.data(), qd.data(), &loop);
      EXPECT_NEAR(v, worst, 1e-13) << L.spec;
      if (std::fabs(v - worst) < 1e-13 && worst > 1e-9) {
        EXPECT_GE(loop, 0) << L.spec;
      }
    }
  }
}

TEST(Loops, AccelerationClosureEqualsTheFormedMatrices) {
  std::mt19937_64 g(43);
  for (const Loopy& L : loopy_models()) {
    SCOPED_TRACE(L.spec);
    const Index n = L.model.nv(), m = L.loops.rows();
    const auto q = test::random_vector(g, n, -1, 1), qd = test::random_vector(g, n, -1, 1),
               tau = test::random_vector(g, n, -1, 1), qdd = test::random_vector(g, n, -1, 1);
    const LoopAccelerationClosure c =
        loop_acceleration_closure(L.model, L.loops, q.data(), qd.data(), tau.data(), qdd.data());
    // the same norms from J, gamma (loop_kinematics) and qdd0 = M^-1 (tau - h) (crba, bias_forces)
    std::vector<double> J(m * n), gamma(m);
    loop_kinematics(L.model, L.loops, q.data(), qd.data(), nullptr, J.data(), gamma.data());
    const Eigen::Map<const MatX> Jm(J.data(), m, n);
    const Eigen::Map<const Eigen::VectorXd> gv(gamma.data(), m), x(qdd.data(), n), t(tau.data(), n);
    Data d(L.model);
    MatX M(n, n);
    Eigen::VectorXd h(n);
    crba(L.model, d, q.data(), M.data());
    bias_forces(L.model, d, q.data(), qd.data(), h.data());
    const Eigen::VectorXd qdd0 = M.ldlt().solve(t - h);
    EXPECT_NEAR(c.residual, (Jm * x + gv).norm(), 1e-10 * std::max(1.0, c.residual));
    EXPECT_NEAR(c.gamma, gv.norm(), 1e-12 * std::max(1.0, c.gamma));
    EXPECT_NEAR(c.qdd0, qdd0.norm(), 1e-9 * std::max(1.0, c.qdd0));
    EXPECT_NEAR(c.jqdd0, (Jm * qdd0).norm(), 1e-9 * std::max(1.0, c.jqdd0));
  }
}

TEST(Loops, JacobianAndBiasAgainstDifferences) {
  std::mt19937_64 g(1);
  for (const auto& L : loopy_models()) {
    SCOPED_TRACE(L.spec);
    const Index n = L.model.nv(), m = L.loops.rows();
    const auto q = test::random_vector(g, n, -1, 1), qd = test::random_vector(g, n, -1, 1);
    std::vector<double> J(m * n), gamma(m), pp(m), pm(m), Jp(m * n), Jm(m * n);
    loop_kinematics(L.model, L.loops, q.data(), qd.data(), nullptr, J.data(), gamma.data());
    const double e = 1e-6;
    // J qd = d/dt phi(q + t qd)
    std::vector<double> qp(n), qm(n);
    for (Index i = 0; i < n; ++i) qp[i] = q[i] + e * qd[i], qm[i] = q[i] - e * qd[i];
    loop_kinematics(L.model, L.loops, qp.data(), nullptr, pp.data(), Jp.data(), nullptr);
    loop_kinematics(L.model, L.loops, qm.data(), nullptr, pm.data(), Jm.data(), nullptr);
    for (Index r = 0; r < m; ++r) {
      double jqd = 0, dj = 0;
      for (Index j = 0; j < n; ++j) jqd += J[r * n + j] * qd[j], dj += (Jp[r * n + j] - Jm[r * n + j]) * qd[j];
      const bool weld_angular = L.spec == "fivebar+weld" && r < 3;  // phi's small-angle form: first order only
      if (!weld_angular) {
        EXPECT_NEAR(jqd, (pp[r] - pm[r]) / (2 * e), 1e-7) << "row " << r;
      }
      EXPECT_NEAR(gamma[r], dj / (2 * e), 1e-6) << "row " << r;  // gamma = Jdot qd
    }
  }
}

TEST(Loops, ConstrainedForwardDynamics) {
  std::mt19937_64 g(2);
  for (const auto& L : loopy_models()) {
    SCOPED_TRACE(L.spec);
    const Index n = L.model.nv(), m = L.loops.rows();
    for (int trial = 0; trial < 5; ++trial) {
      std::vector<double> q, qd;
      closed_state(L, g, q, qd);
      const auto tau = test::random_vector(g, n, -1, 1);
      std::vector<double> qdd(n), lambda(m);
      const LoopSolveInfo info =
          constrained_forward_dynamics(L.model, L.loops, q.data(), qd.data(), tau.data(), qdd.data(), lambda.data());
      // 1e-10 relative to max(1, max |qdd|) (the cloth's 10 g links reach |qdd| ~ 3e5)
      const double scale = std::max(1.0, Eigen::Map<Eigen::VectorXd>(qdd.data(), n).cwiseAbs().maxCoeff());
      EXPECT_LE(info.residual, 1e-10 * scale) << "rank " << info.rank << " of " << m;
      EXPECT_LT(info.rank, m + 1);
      for (double x : qdd) ASSERT_TRUE(std::isfinite(x));
      // J qdd + gamma = 0, recomputed
      std::vector<double> J(m * n), gamma(m);
      loop_kinematics(L.model, L.loops, q.data(), qd.data(), nullptr, J.data(), gamma.data());
      const Eigen::Map<const MatX> Jm(J.data(), m, n);
      const Eigen::Map<const Eigen::VectorXd> x(qdd.data(), n), lam(lambda.data(), m), t(tau.data(), n);
      EXPECT_LE((Jm * x + Eigen::Map<const Eigen::VectorXd>(gamma.data(), m)).cwiseAbs().maxCoeff(), 1e-10 * scale);
      // M qdd + h = tau + J^T lambda, through rnea
      Data d(L.model);
      Eigen::VectorXd id(n);
      rnea(L.model, d, q.data(), qd.data(), qdd.data(), id.data());
      EXPECT_LE((id - t - Jm.transpose() * lam).cwiseAbs().maxCoeff(), 1e-9 * scale);
      // the null-space solution: qdd = qdd_p + N y
      MatX M(n, n);
      Eigen::VectorXd h(n);
      crba(L.model, d, q.data(), M.data());
      bias_forces(L.model, d, q.data(), qd.data(), h.data());
      Eigen::JacobiSVD<Eigen::MatrixXd> svd(Jm, Eigen::ComputeThinU | Eigen::ComputeFullV);
      svd.setThreshold(1e-10);
      const Eigen::MatrixXd N = svd.matrixV().rightCols(n - svd.rank());
      const Eigen::VectorXd qddp = svd.solve(-Eigen::Map<const Eigen::VectorXd>(gamma.data(), m));
      const Eigen::VectorXd y = (N.transpose() * M * N).ldlt().solve(N.transpose() * (t - h - M * qddp));
      const Eigen::VectorXd ref = qddp + N * y;
      EXPECT_LE((x - ref).cwiseAbs().maxCoeff(), 1e-9 * std::max(1.0, ref.cwiseAbs().maxCoeff()));
    }
  }
}

TEST(Loops, RedundantRowsAreHandled) {
  // planar loops closed by 3D points: the z rows of J are zero
  for (const char* spec : {"fourbar", "fivebar"}) {
    const Loopy L(spec);
    const Index n = L.model.nv();
    const std::vector<double> q(n, 0.0), qd(n, 0.0), tau(n, 0.3);
    std::vector<double> qdd(n), lambda(3);
    const LoopSolveInfo info =
        constrained_forward_dynamics(L.model, L.loops, q.data(), qd.data(), tau.data(), qdd.data(), lambda.data());
    EXPECT_EQ(info.rank, 2) << spec;
    EXPECT_EQ(lambda[2], 0.0) << spec;  // the minimum-norm force has no component along the zero row
    EXPECT_LE(info.residual, 1e-12);
  }
}

TEST(Loops, ConstrainedInverseDynamics) {
  std::mt19937_64 g(3);
  const Loopy L("fivebar");
  const Index n = L.model.nv(), m = L.loops.rows();
  for (int trial = 0; trial < 5; ++trial) {
    std::vector<double> q, qd;
    closed_state(L, g, q, qd);
    // the motion the proximal motors produce
    std::vector<double> tau_in(n, 0.0), qdd(n), lam(m);
    tau_in[0] = 0.7, tau_in[2] = -0.4;  // joint_l0, joint_r0 (DoF order: l0, l1, r0, r1)
    constrained_forward_dynamics(L.model, L.loops, q.data(), qd.data(), tau_in.data(), qdd.data(), lam.data());
    // two actuators for two DoF of mobility: exactly those torques back
    const std::vector<unsigned char> prox{1, 0, 1, 0};
    std::vector<double> tau(n), lam2(m);
    LoopSolveInfo info = constrained_inverse_dynamics(L.model, L.loops, q.data(), qd.data(), qdd.data(), prox.data(),
                                                      tau.data(), lam2.data());
    EXPECT_LE(info.residual, 1e-10);
    for (Index i = 0; i < n; ++i) EXPECT_NEAR(tau[i], tau_in[i], 1e-9) << i;
    // all four actuated (redundant): a minimum-norm tau that produces the same motion
    const std::vector<unsigned char> all(n, 1);
    info = constrained_inverse_dynamics(L.model, L.loops, q.data(), qd.data(), qdd.data(), all.data(), tau.data(),
                                        lam2.data());
    EXPECT_LE(info.residual, 1e-10);
    EXPECT_LE(Eigen::Map<Eigen::VectorXd>(tau.data(), n).norm(), Eigen::Map<Eigen::VectorXd>(tau_in.data(), n).norm() + 1e-12);
    std::vector<double> qdd2(n);
    constrained_forward_dynamics(L.model, L.loops, q.data(), qd.data(), tau.data(), qdd2.data(), lam.data());
    for (Index i = 0; i < n; ++i) EXPECT_NEAR(qdd2[i], qdd[i], 1e-9) << i;
  }
}

TEST(Loops, LoopFileErrors) {
  const Model m = load_model("fivebar");
  const std::string ok =
      R"({"loops": [{"type": "point", "link_a": "left_distal", "point_a": [0.15, 0.15, 0], "link_b": "right_distal", "point_b": [-0.15, 0.15, 0]}]})";
  const LoopSet s = parse_loops(ok, "l.json", m);
  ASSERT_EQ(s.loops.size(), 1u);
  EXPECT_EQ(s.loops[0].body_a, 1);
  EXPECT_EQ(loops_json(parse_loops(loops_json(s), "again", m)), loops_json(s));  // the writer reads back
  struct Case {
    std::string text, message;
  } cases[] = {
      {R"({"loops": [{"type": "point", "link_a": "nope", "point_a": [0,0,0], "link_b": "right_distal", "point_b": [0,0,0]}]})",
       "l.json: loops[0].link_a: unknown link 'nope'"},
      {R"({"loops": [{"type": "point", "link_a": "left_distal", "point_a": [0,0,0], "link_b": "left_distal", "point_b": [0,0,0]}]})",
       "l.json: loops[0]: a loop between link 'left_distal' and itself"},
      {R"({"loops": [{"type": "hinge", "link_a": "left_distal", "point_a": [0,0,0], "link_b": "ground", "point_b": [0,0,0]}]})",
       "l.json: loops[0].type: expected \"point\" or \"weld\""},
      {R"({"loops": [{"type": "point", "link_a": "left_distal", "point_a": [0,0], "link_b": "ground", "point_b": [0,0,0]}]})",
       "l.json: loops[0].point_a: expected [x, y, z]"},
      {R"({"loops": [{"type": "point", "link_a": "left_distal", "point_a": [0,0,0], "link_b": "ground"}]})",
       "l.json: loops[0].point_b: missing"},
      {R"({"loops": [{"type": "point", "color": 1}]})", "l.json: loops[0].color: unknown key"},
      {R"({"loop": []})", "l.json: loops: expected an object with one key"},
      {R"(nonsense)", "l.json: not valid JSON"},
  };
  for (const Case& c : cases) {
    try {
      parse_loops(c.text, "l.json", m);
      ADD_FAILURE() << "accepted: " << c.text;
    } catch (const LoopError& e) {
      EXPECT_NE(std::string(e.what()).find(c.message), std::string::npos) << e.what();
    }
  }
  // the base (root link) may close a loop
  const LoopSet base = parse_loops(
      R"({"loops": [{"type": "point", "link_a": "left_distal", "point_a": [0.15, 0.15, 0], "link_b": "ground", "point_b": [0.15, 0.4, 0]}]})",
      "l.json", m);
  EXPECT_EQ(base.loops[0].body_b, -1);
  const std::vector<double> q(4, 0.0), qd(4, 0.0);
  EXPECT_LE(loop_violation(m, base, q.data(), qd.data()), 1e-15);
}

// project_to_loops from far off the loops (Levenberg-Marquardt,
// scandyn/algorithm/loop_projection.hpp) ends where a globally convergent method may:
// closed (max |phi| <= 1e-12 and J qd = 0), or at a stationary point of |phi|^2 (a
// local minimum of a tangled cloth: |J^T phi| <= 1e-6 |J| |phi| from the dense J at
// the end, an independent check), or at the bound on linearisations; never NaN.
// Starts: cloth:4:4 and cloth:6:6 with q drawn in +-2 rad, fivebar in +-3 rad.
TEST(Loops, FarProjectionEndsClosedOrStationary) {
  std::mt19937_64 rng(11);
  for (const char* spec : {"fivebar", "cloth:4:4", "cloth:6:6"}) {
    const Model model = load_model(spec);
    const LoopSet loops = generator_loops(spec, model);
    const Index n = model.nv(), m = loops.rows();
    const double amp = std::string(spec) == "fivebar" ? 3.0 : 2.0;
    int closed = 0;
    for (int t = 0; t < 10; ++t) {
      SCOPED_TRACE(std::string(spec) + " start " + std::to_string(t));
      std::uniform_real_distribution<double> u(-amp, amp);
      std::vector<double> q(n), qd(n);
      for (Index i = 0; i < n; ++i) q[i] = u(rng), qd[i] = u(rng);
      LoopProjectionInfo info;
      const double r = project_to_loops(model, loops, q.data(), qd.data(), 1e-13, 100, &info);
      ASSERT_TRUE(std::isfinite(r) && std::isfinite(info.jqd));
      MatX J(m, n);
      Eigen::VectorXd phi(m);
      loop_kinematics(model, loops, q.data(), nullptr, phi.data(), J.data(), nullptr);
      EXPECT_EQ(phi.cwiseAbs().maxCoeff(), r);
      EXPECT_LE((J * Eigen::Map<Eigen::VectorXd>(qd.data(), n)).cwiseAbs().maxCoeff(), 1e-12 * (1 + amp));
      if (r <= 1e-12) {
        ++closed;
        continue;
      }
      const double g = (J.transpose() * phi).norm();
      EXPECT_TRUE(g <= 1e-6 * J.norm() * phi.norm() || info.linearisations == 100)
          << "max |phi| " << r << ", |J^T phi| " << g << " after " << info.linearisations << " linearisations";
    }
    EXPECT_GE(closed, 5) << spec;
  }
}

