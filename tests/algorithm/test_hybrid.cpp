// The reference hybrid dynamics (hybrid_dynamics, Featherstone 2008, 9.2) and its
// CPU engines: against an independent joint-space solution (CRBA's M and the bias
// forces h, the unknown accelerations from the partitioned system by Eigen's LLT),
// the identity tau = M qdd + h on every row, the given entries copied through,
// no DoF prescribed = aba bit for bit, every DoF prescribed = rnea, pivot failures,
// and the serial and OpenMP engines bit-identical to the reference in two layouts.
// Tolerances (double): 1e-10 relative to the largest entry of the compared vector
// (the models' M has condition numbers up to ~1e6).
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <limits>
#include <random>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

std::vector<std::pair<std::string, Model>> hybrid_models() {
  std::vector<std::pair<std::string, Model>> models = test::thread_shape_models();
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) models.emplace_back(file, test::load_robot(file));
  models.emplace_back("tree:120:7", load_model("tree:120:7"));
  return models;
}

std::vector<unsigned char> random_mask(std::mt19937_64& g, Index nv, double p) {
  std::vector<unsigned char> m(static_cast<std::size_t>(nv));
  for (auto& x : m) x = std::uniform_real_distribution<double>(0, 1)(g) < p;
  return m;
}

// max |a - b| / max(1, max |b|)
double scaled_err(const std::vector<double>& a, const std::vector<double>& b) {
  double e = 0, s = 1;
  for (std::size_t i = 0; i < b.size(); ++i) {
    e = std::max(e, std::fabs(a[i] - b[i]));
    s = std::max(s, std::fabs(b[i]));
  }
  return e / s;
}

// The hybrid dynamics by the joint-space equations: M_ff qdd_f = tau_f - h_f - M_fp
// qdd_p for the free DoFs f, then tau = M qdd + h (M, h from crba and bias_forces).
void jsi_hybrid(const Model& m, const std::vector<double>& q, const std::vector<double>& qd,
                const std::vector<unsigned char>& mask, const std::vector<double>& qdd_in,
                const std::vector<double>& tau_in, const Force<double>* fext, std::vector<double>& qdd,
                std::vector<double>& tau) {
  const Index n = m.nv();
  Data d(m);
  std::vector<double> M(static_cast<std::size_t>(n * n)), h(static_cast<std::size_t>(n));
  crba(m, d, q.data(), M.data());
  bias_forces(m, d, q.data(), qd.data(), h.data(), fext);
  const Eigen::Map<const Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>> Mm(M.data(), n, n);
  std::vector<Index> f, p;
  for (Index i = 0; i < n; ++i) (mask[i] ? p : f).push_back(i);
  Eigen::MatrixXd Mff(f.size(), f.size());
  Eigen::VectorXd rhs(f.size());
  for (std::size_t a = 0; a < f.size(); ++a) {
    rhs[a] = tau_in[f[a]] - h[f[a]];
    for (Index j : p) rhs[a] -= Mm(f[a], j) * qdd_in[j];
    for (std::size_t b = 0; b < f.size(); ++b) Mff(a, b) = Mm(f[a], f[b]);
  }
  const Eigen::VectorXd x = Mff.llt().solve(rhs);
  qdd.assign(static_cast<std::size_t>(n), 0.0);
  for (Index j : p) qdd[j] = qdd_in[j];
  for (std::size_t a = 0; a < f.size(); ++a) qdd[f[a]] = x[a];
  tau.assign(static_cast<std::size_t>(n), 0.0);
  for (Index i = 0; i < n; ++i) {
    tau[i] = h[i];
    for (Index j = 0; j < n; ++j) tau[i] += Mm(i, j) * qdd[j];
  }
}

}  // namespace

TEST(HybridDynamics, MatchesJointSpaceSolution) {
  std::mt19937_64 g(21);
  for (const auto& [name, m] : hybrid_models()) {
    SCOPED_TRACE(name);
    const Index n = m.nv();
    Data d(m, false);
    for (int trial = 0; trial < 6; ++trial) {
      const auto q = test::random_vector(g, n, -3, 3), qd = test::random_vector(g, n, -2, 2);
      const auto qdd_in = test::random_vector(g, n, -2, 2), tau_in = test::random_vector(g, n, -5, 5);
      const auto fext = test::random_wrenches<double>(g, n, 1.0);
      const auto mask = random_mask(g, n, trial == 0 ? 0.1 : trial == 1 ? 0.9 : 0.5);
      const Force<double>* fx = trial % 2 ? fext.data() : nullptr;
      std::vector<double> qdd(n, std::nan("")), tau(n, std::nan("")), qdd_ref, tau_ref;
      ASSERT_TRUE(hybrid_dynamics(m, d, q.data(), qd.data(), mask.data(), qdd_in.data(), tau_in.data(), qdd.data(),
                                  tau.data(), fx)
                      .ok());
      jsi_hybrid(m, q, qd, mask, qdd_in, tau_in, fx, qdd_ref, tau_ref);
      EXPECT_LE(scaled_err(qdd, qdd_ref), 1e-10);
      // tau = M qdd_hd + h on every row (tau_ref is M qdd + h of the jsi solution)
      EXPECT_LE(scaled_err(tau, tau_ref), 1e-10);
      for (Index i = 0; i < n; ++i) {
        if (mask[i]) EXPECT_EQ(qdd[i], qdd_in[i]) << "DoF " << i;
        else EXPECT_EQ(tau[i], tau_in[i]) << "DoF " << i;
      }
      // tau = M qdd + h with this qdd, through rnea
      std::vector<double> id(n);
      rnea(m, d, q.data(), qd.data(), qdd.data(), id.data(), fx);
      EXPECT_LE(scaled_err(tau, id), 1e-10);
    }
  }
}

TEST(HybridDynamics, NonePrescribedIsAbaBitForBit) {
  std::mt19937_64 g(5);
  for (const auto& [name, m] : hybrid_models()) {
    SCOPED_TRACE(name);
    const Index n = m.nv();
    Data d(m, false);
    const auto q = test::random_vector(g, n, -3, 3), qd = test::random_vector(g, n, -2, 2);
    const auto tau_in = test::random_vector(g, n, -5, 5);
    const std::vector<double> nan_qdd(n, std::nan(""));  // never read
    const std::vector<unsigned char> none(n, 0);
    std::vector<double> qdd(n), tau(n), ref(n);
    ASSERT_TRUE(hybrid_dynamics(m, d, q.data(), qd.data(), none.data(), nan_qdd.data(), tau_in.data(), qdd.data(),
                                tau.data())
                    .ok());
    ASSERT_TRUE(aba(m, d, q.data(), qd.data(), tau_in.data(), ref.data()).ok());
    for (Index i = 0; i < n; ++i) {
      EXPECT_EQ(qdd[i], ref[i]) << "DoF " << i;
      EXPECT_EQ(tau[i], tau_in[i]) << "DoF " << i;
    }
  }
}

TEST(HybridDynamics, AllPrescribedIsInverseDynamics) {
  std::mt19937_64 g(6);
  for (const auto& [name, m] : hybrid_models()) {
    SCOPED_TRACE(name);
    const Index n = m.nv();
    Data d(m, false);
    const auto q = test::random_vector(g, n, -3, 3), qd = test::random_vector(g, n, -2, 2);
    const auto qdd_in = test::random_vector(g, n, -2, 2);
    const auto fext = test::random_wrenches<double>(g, n, 1.0);
    const std::vector<double> nan_tau(n, std::nan(""));  // never read
    const std::vector<unsigned char> all(n, 1);
    std::vector<double> qdd(n), tau(n), ref(n);
    ASSERT_TRUE(hybrid_dynamics(m, d, q.data(), qd.data(), all.data(), qdd_in.data(), nan_tau.data(), qdd.data(),
                                tau.data(), fext.data())
                    .ok());
    rnea(m, d, q.data(), qd.data(), qdd_in.data(), ref.data(), fext.data());
    EXPECT_LE(scaled_err(tau, ref), 1e-12);
    for (Index i = 0; i < n; ++i) EXPECT_EQ(qdd[i], qdd_in[i]);
  }
}

// The outputs may be the inputs' own arrays.
TEST(HybridDynamics, OutputsMayAliasInputs) {
  const Model m = test::load_robot("iiwa.urdf");
  const Index n = m.nv();
  std::mt19937_64 g(8);
  Data d(m, false);
  const auto q = test::random_vector(g, n, -3, 3), qd = test::random_vector(g, n, -2, 2);
  auto qdd = test::random_vector(g, n, -2, 2), tau = test::random_vector(g, n, -5, 5);
  const auto mask = random_mask(g, n, 0.5);
  std::vector<double> qdd2(n), tau2(n);
  ASSERT_TRUE(hybrid_dynamics(m, d, q.data(), qd.data(), mask.data(), qdd.data(), tau.data(), qdd2.data(), tau2.data())
                  .ok());
  ASSERT_TRUE(
      hybrid_dynamics(m, d, q.data(), qd.data(), mask.data(), qdd.data(), tau.data(), qdd.data(), tau.data()).ok());
  for (Index i = 0; i < n; ++i) {
    EXPECT_EQ(qdd[i], qdd2[i]);
    EXPECT_EQ(tau[i], tau2[i]);
  }
}

// A massless subtree below a free joint fails at that joint's pivot (the DoF aba
// reports) and writes nothing; prescribing that joint's acceleration removes the
// pivot, and the model's remaining DoFs compute.
TEST(HybridDynamics, PivotFailureOnlyAtFreeDofs) {
  Model m = load_model("chain:4");
  m.bodies[3].I = Inertia<double>{};  // the last link massless: D_3 = 0
  const Index n = m.nv();
  Data d(m, false);
  const std::vector<double> q{0.1, 0.2, 0.3, 0.4}, qd{0.5, -0.2, 0.1, 0.3}, qdd_in{1, 2, 3, 4}, tau_in{1, 1, 1, 1};
  std::vector<double> qdd(n, -7.0), tau(n, -7.0);
  const std::vector<unsigned char> none(n, 0);
  const Status st =
      hybrid_dynamics(m, d, q.data(), qd.data(), none.data(), qdd_in.data(), tau_in.data(), qdd.data(), tau.data());
  EXPECT_EQ(st.failed_dof, 3);
  for (Index i = 0; i < n; ++i) {
    EXPECT_EQ(qdd[i], -7.0);
    EXPECT_EQ(tau[i], -7.0);
  }
  const std::vector<unsigned char> last{0, 0, 0, 1};
  ASSERT_TRUE(
      hybrid_dynamics(m, d, q.data(), qd.data(), last.data(), qdd_in.data(), tau_in.data(), qdd.data(), tau.data())
          .ok());
  EXPECT_EQ(qdd[3], 4.0);
  EXPECT_EQ(tau[3], 0.0);  // a massless body needs no force
}

// The serial and OpenMP engines: the reference per instance, bit for bit, in the
// soa and aos layouts; the mask's size checked.
TEST(HybridDynamicsEngine, CpuBackendsEqualReference) {
  std::vector<BackendKind> kinds{BackendKind::Serial};
  if (backend_unusable(BackendKind::OpenMP).empty()) kinds.push_back(BackendKind::OpenMP);
  std::mt19937_64 g(11);
  for (const char* spec : {"iiwa.urdf", "tree:30:1", "chain:17"}) {
    SCOPED_TRACE(spec);
    const Model m = std::string(spec).find(".urdf") != std::string::npos ? test::load_robot(spec) : load_model(spec);
    const Index n = m.nv(), B = 37;
    const auto mask = random_mask(g, n, 0.5);
    const auto q = test::random_vector(g, n * B, -3, 3), qd = test::random_vector(g, n * B, -2, 2);
    const auto qdd_in = test::random_vector(g, n * B, -2, 2), tau_in = test::random_vector(g, n * B, -5, 5);
    const auto fext = test::random_wrenches<double>(g, n * B, 1.0);
    // reference, instance-major rows (aos)
    std::vector<double> rq(n * B), rt(n * B);
    Data d(m, false);
    for (Index b = 0; b < B; ++b)
      ASSERT_TRUE(hybrid_dynamics(m, d, &q[b * n], &qd[b * n], mask.data(), &qdd_in[b * n], &tau_in[b * n], &rq[b * n],
                                  &rt[b * n], &fext[b * n])
                      .ok());
    for (BackendKind k : kinds) {
      for (bool soa : {false, true}) {
        SCOPED_TRACE(std::string(to_string(k)) + (soa ? " soa" : " aos"));
        BackendOptions o;
        o.backend = k;
        o.max_batch = B;
        o.threads = 3;
        auto e = make_hybrid_dynamics(m, mask, o);
        EXPECT_TRUE(e->exact());
        // the same data transposed for soa
        auto lay = [&](const std::vector<double>& v) {
          if (!soa) return v;
          std::vector<double> t(v.size());
          for (Index b = 0; b < B; ++b)
            for (Index i = 0; i < n; ++i) t[i * B + b] = v[b * n + i];
          return t;
        };
        const auto Q = lay(q), QD = lay(qd), QI = lay(qdd_in), TI = lay(tau_in);
        std::vector<double> QO(n * B, std::nan("")), TO(n * B, std::nan(""));
        using V = BatchView<const double>;
        auto view = [&](const std::vector<double>& v) { return soa ? V::soa(v.data(), n, B) : V::aos(v.data(), n, B); };
        auto out = [&](std::vector<double>& v) {
          return soa ? BatchView<double>::soa(v.data(), n, B) : BatchView<double>::aos(v.data(), n, B);
        };
        const BatchStatus st = e->compute({view(Q), view(QD), view(QI), view(TI), fext.data()}, out(QO), out(TO));
        ASSERT_TRUE(st.ok()) << st.message();
        for (Index b = 0; b < B; ++b)
          for (Index i = 0; i < n; ++i) {
            const std::size_t k2 = soa ? i * B + b : b * n + i;
            EXPECT_EQ(QO[k2], rq[b * n + i]);
            EXPECT_EQ(TO[k2], rt[b * n + i]);
          }
      }
    }
    BackendOptions o;
    EXPECT_THROW(make_hybrid_dynamics(m, std::vector<unsigned char>(n + 1, 0), o), BackendError);
  }
}

// A failing instance is reported and its outputs left unwritten; the others compute.
TEST(HybridDynamicsEngine, FailedInstanceReported) {
  Model m = load_model("chain:3");
  m.bodies[2].I = Inertia<double>{};
  const Index n = 3, B = 2;
  BackendOptions o;
  o.max_batch = B;
  auto e = make_hybrid_dynamics(m, std::vector<unsigned char>{1, 0, 0}, o);
  auto e_ok = make_hybrid_dynamics(m, std::vector<unsigned char>{0, 0, 1}, o);
  std::vector<double> q(n * B, 0.3), qd(n * B, 0.1), qi(n * B, 1.0), ti(n * B, 0.5), qo(n * B, -1), to(n * B, -1);
  using V = BatchView<const double>;
  const HybridBatchIn<double> in{V::aos(q.data(), n, B), V::aos(qd.data(), n, B), V::aos(qi.data(), n, B),
                                 V::aos(ti.data(), n, B)};
  const BatchStatus st = e->compute(in, BatchView<double>::aos(qo.data(), n, B), BatchView<double>::aos(to.data(), n, B));
  EXPECT_EQ(st.failed, 2);
  EXPECT_EQ(st.first_dof, 2);
  EXPECT_EQ(st.message(), "instance 0: articulated inertia pivot at DoF 2 is not positive (and 1 more instance)");
  for (double x : qo) EXPECT_EQ(x, -1);
  EXPECT_TRUE(e_ok->compute(in, BatchView<double>::aos(qo.data(), n, B), BatchView<double>::aos(to.data(), n, B)).ok());
  EXPECT_EQ(qo[2], 1.0);
}
