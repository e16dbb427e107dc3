// The closed-loop forward-dynamics engines (ConstrainedForwardDynamics, serial and
// OpenMP; loop_solver.hpp's rank-revealing dense solve) against the Eigen reference
// constrained_forward_dynamics (complete orthogonal decomposition): qdd and the
// minimum-norm lambda on random closed states of the four-bar, the five-bar (planar
// loops closed by 3D points: a redundant row each), a weld-closed five-bar and cloth
// grids, in every layout; J qdd + gamma = 0; the residual against loop_kinematics;
// float engines within float tolerances; a failed mass matrix reported.
// Tolerances (double): qdd 1e-10 and lambda 1e-8 relative to max(1, max |x|) (the
// cloth's Schur complement is ill-conditioned: its lambda carries cond(A) eps).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>

#include "scandyn/algorithm/loops.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "loop_cases.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

using Case = test::LoopCase;

std::vector<Case> cases() {
  return test::loop_cases({"fourbar", "fivebar", "cloth:3:4", "cloth:4:6", "fivebar+weld"});
}

// B random closed states (projected onto the loops), instance-major (B x nv) each.
void closed_states(const Case& c, Index B, std::mt19937_64& g, std::vector<double>& q, std::vector<double>& qd,
                   std::vector<double>& tau) {
  const Index n = c.model.nv();
  q.assign(B * n, 0), qd.assign(B * n, 0), tau.assign(B * n, 0);
  for (Index b = 0; b < B; ++b) {
    std::vector<double> qb, qdb;
    ASSERT_LE(test::closed_state(c, g, qb, qdb), 1e-12);
    auto tb = test::random_vector(g, n, -1, 1);
    std::copy(qb.begin(), qb.end(), q.begin() + b * n);
    std::copy(qdb.begin(), qdb.end(), qd.begin() + b * n);
    std::copy(tb.begin(), tb.end(), tau.begin() + b * n);
  }
}

double max_abs(const double* x, Index n) {
  double m = 0;
  for (Index i = 0; i < n; ++i) m = std::max(m, std::fabs(x[i]));
  return m;
}

}  // namespace

TEST(ConstrainedDynamicsEngine, MatchesTheReference) {
  std::mt19937_64 g(5);
  const Index B = 7;
  for (const Case& c : cases()) {
    SCOPED_TRACE(c.spec);
    const Index n = c.model.nv(), m = c.loops.rows();
    std::vector<double> q, qd, tau;
    closed_states(c, B, g, q, qd, tau);
    std::vector<double> ref_qdd(B * n), ref_lam(B * m);
    for (Index b = 0; b < B; ++b)
      constrained_forward_dynamics(c.model, c.loops, &q[b * n], &qd[b * n], &tau[b * n], &ref_qdd[b * n],
                                   &ref_lam[b * m]);
    for (BackendKind kind : {BackendKind::Serial, BackendKind::OpenMP}) {
      if (!backend_unusable(kind).empty()) continue;
      for (bool soa : {false, true}) {
        SCOPED_TRACE(std::string(to_string(kind)) + (soa ? " soa" : " aos"));
        BackendOptions o;
        o.backend = kind;
        o.max_batch = B;
        o.threads = 2;
        auto e = make_constrained_forward_dynamics<double>(c.model, c.loops, o);
        EXPECT_EQ(e->rows(), m);
        // soa: DoF-major copies (instance innermost)
        auto lay = [&](const std::vector<double>& x, Index w) {
          if (!soa) return x;
          std::vector<double> y(x.size());
          for (Index b = 0; b < B; ++b)
            for (Index i = 0; i < w; ++i) y[i * B + b] = x[b * w + i];
          return y;
        };
        auto view = [&](const double* p, Index w) {
          return soa ? BatchView<const double>::soa(p, w, B) : BatchView<const double>::aos(p, w, B);
        };
        const auto qs = lay(q, n), qds = lay(qd, n), taus = lay(tau, n);
        std::vector<double> qdd(B * n, NAN), lam(B * m, NAN);
        FdBatchIn<double> in;
        in.q = view(qs.data(), n), in.qd = view(qds.data(), n), in.tau = view(taus.data(), n);
        const BatchView<double> qv = soa ? BatchView<double>::soa(qdd.data(), n, B) : BatchView<double>::aos(qdd.data(), n, B);
        const BatchView<double> lv = soa ? BatchView<double>::soa(lam.data(), m, B) : BatchView<double>::aos(lam.data(), m, B);
        const BatchStatus st = e->compute(in, qv, lv);
        ASSERT_TRUE(st.ok()) << st.message();
        std::vector<double> J(m * n), gamma(m), phi(B * m), vel(B * m);
        e->residual(in.q, in.qd, soa ? BatchView<double>::soa(phi.data(), m, B) : BatchView<double>::aos(phi.data(), m, B),
                    soa ? BatchView<double>::soa(vel.data(), m, B) : BatchView<double>::aos(vel.data(), m, B));
        for (Index b = 0; b < B; ++b) {
          const double sq = std::max(1.0, max_abs(&ref_qdd[b * n], n));
          const double sl = std::max(1.0, max_abs(&ref_lam[b * m], m));
          for (Index i = 0; i < n; ++i) EXPECT_NEAR(qv.at(i, b), ref_qdd[b * n + i], 1e-10 * sq) << b << " " << i;
          for (Index k = 0; k < m; ++k) EXPECT_NEAR(lv.at(k, b), ref_lam[b * m + k], 1e-8 * sl) << b << " " << k;
          // J qdd + gamma = 0
          std::vector<double> phib(m);
          loop_kinematics(c.model, c.loops, &q[b * n], &qd[b * n], phib.data(), J.data(), gamma.data());
          for (Index k = 0; k < m; ++k) {
            double r = gamma[k], jqd = 0;
            for (Index j = 0; j < n; ++j) r += J[k * n + j] * qv.at(j, b), jqd += J[k * n + j] * qd[b * n + j];
            EXPECT_LE(std::fabs(r), 1e-10 * sq) << "row " << k;
            const Index e_k = soa ? k * B + b : b * m + k;
            EXPECT_EQ(phi[e_k], phib[k]);
            EXPECT_NEAR(vel[e_k], jqd, 1e-15 * std::max(1.0, std::fabs(jqd)));
          }
        }
      }
    }
  }
}

TEST(ConstrainedDynamicsEngine, FloatWithinFloatTolerance) {
  std::mt19937_64 g(6);
  const Index B = 16;
  for (const Case& c : cases()) {
    if (c.spec.rfind("cloth", 0) == 0) continue;  // 10 g links: |qdd| ~ 1e5, ill-conditioned for float
    SCOPED_TRACE(c.spec);
    const Index n = c.model.nv(), m = c.loops.rows();
    std::vector<double> q, qd, tau;
    closed_states(c, B, g, q, qd, tau);
    const ModelTpl<float> mf = c.model.cast<float>();
    BackendOptions o;
    o.max_batch = B;
    auto e = make_constrained_forward_dynamics<float>(mf, c.loops, o);
    std::vector<float> qf(q.begin(), q.end()), qdf(qd.begin(), qd.end()), tf(tau.begin(), tau.end());
    std::vector<float> qdd(B * n), lam(B * m);
    FdBatchIn<float> in;
    in.q = BatchView<const float>::aos(qf.data(), n, B);
    in.qd = BatchView<const float>::aos(qdf.data(), n, B);
    in.tau = BatchView<const float>::aos(tf.data(), n, B);
    ASSERT_TRUE(e->compute(in, BatchView<float>::aos(qdd.data(), n, B), BatchView<float>::aos(lam.data(), m, B)).ok());
    for (Index b = 0; b < B; ++b) {
      std::vector<double> rq(n), rl(m);
      constrained_forward_dynamics(c.model, c.loops, &q[b * n], &qd[b * n], &tau[b * n], rq.data(), rl.data());
      const double sq = std::max(1.0, max_abs(rq.data(), n)), sl = std::max(1.0, max_abs(rl.data(), m));
      for (Index i = 0; i < n; ++i) EXPECT_NEAR(qdd[b * n + i], rq[i], 2e-3 * sq);
      for (Index k = 0; k < m; ++k) EXPECT_NEAR(lam[b * m + k], rl[k], 2e-3 * sl);
    }
  }
}

TEST(ConstrainedDynamicsEngine, ErrorsAndLimits) {
  const Model m = load_model("fivebar");
  const LoopSet loops = generator_loops("fivebar", m);
  BackendOptions o;
  o.max_batch = 2;
  auto e = make_constrained_forward_dynamics<double>(m, loops, o);
  std::vector<double> x(2 * m.nv(), 0.0), qdd(2 * m.nv()), lam(2 * loops.rows());
  FdBatchIn<double> in;
  in.q = in.qd = in.tau = BatchView<const double>::aos(x.data(), m.nv(), 2);
  // a lambda view of another batch size
  EXPECT_THROW(e->compute(in, BatchView<double>::aos(qdd.data(), m.nv(), 2), BatchView<double>::aos(lam.data(), 3, 1)),
               BackendError);
  // loops of another model
  const Model c = load_model("cloth:3:4");
  EXPECT_THROW(make_constrained_forward_dynamics<double>(m, generator_loops("cloth:3:4", c), o), BackendError);
  // a multi-DoF model
  const Model ball = load_model("ballrope:3");
  EXPECT_THROW(make_constrained_forward_dynamics<double>(ball, LoopSet{}, o), BackendError);
  // no loops: the tree's forward dynamics
  auto free_tree = make_constrained_forward_dynamics<double>(m, LoopSet{}, o);
  EXPECT_EQ(free_tree->rows(), 0);
  ASSERT_TRUE(free_tree->compute(in, BatchView<double>::aos(qdd.data(), m.nv(), 2), BatchView<double>::aos(lam.data(), 0, 2)).ok());
  std::vector<double> ref(m.nv());
  Data d(m);
  aba(m, d, x.data(), x.data(), x.data(), ref.data());
  for (Index i = 0; i < m.nv(); ++i) EXPECT_NEAR(qdd[i], ref[i], 1e-12 * std::max(1.0, max_abs(ref.data(), m.nv())));
}
