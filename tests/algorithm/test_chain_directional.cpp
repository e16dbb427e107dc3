// The JVP and VJP of forward dynamics of chains by the chunked scans
// (scandyn/algorithm/chain_directional.hpp, ChainFdDirectional on OpenMP threads)
// against the serial per-instance aba_jvp / aba_vjp (scandyn/algorithm/
// directional_derivatives.hpp), the adjoint identity, and threads 1 against 2.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <random>
#include <string>
#include <vector>

#include "scandyn/algorithm/chain_directional.hpp"
#include "chain_directional_cases.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

using namespace scandyn;
using namespace scandyn::test::chain_dir;

namespace {

// Host SoA views (n x B) of a case's inputs x and of the results r, as the drivers'
// jvp (in, dq, dqd, dtau -> qdd_j, dqdd) and vjp (in, w -> qdd_v, gq, gqd, gtau) take them.
template <class S>
struct Views {
  FdBatchIn<S> in;
  BatchView<const S> dq, dqd, dtau, w;
  BatchView<S> qdd_j, dqdd, qdd_v, gq, gqd, gtau;

  Views(const Inputs<S>& x, Result<S>& r, Index n, Index B) {
    auto v = [&](const std::vector<S>& a) { return BatchView<const S>::soa(a.data(), n, B); };
    auto o = [&](std::vector<S>& a) { return BatchView<S>::soa(a.data(), n, B); };
    in = {v(x.q), v(x.qd), v(x.tau), x.fext.empty() ? nullptr : x.fext.data()};
    dq = v(x.dq);
    dqd = v(x.dqd);
    dtau = v(x.dtau);
    w = v(x.w);
    qdd_j = o(r.qdd_j);
    dqdd = o(r.dqdd);
    qdd_v = o(r.qdd_v);
    gq = o(r.gq);
    gqd = o(r.gqd);
    gtau = o(r.gtau);
  }
};

template <class S>
Result<S> run(const Model& model, const Case& c, int threads, Index chunk = 0) {
  ChainFdDirectional<S> eng(model.cast<S>(), c.B, threads, chunk);
  const Inputs<S> x(c);
  Result<S> r = Result<S>::nan(c.q.size());
  const Views<S> v(x, r, c.n, c.B);
  std::vector<int> failed(static_cast<std::size_t>(c.B), 7);
  EXPECT_EQ(eng.jvp(v.in, v.dq, v.dqd, v.dtau, v.qdd_j, v.dqdd, failed.data()), 0);
  for (int f : failed) EXPECT_EQ(f, -1);
  EXPECT_EQ(eng.vjp(v.in, v.w, v.qdd_v, v.gq, v.gqd, v.gtau), 0);
  return r;
}

// Every output against the serial double aba_jvp / aba_vjp, relative to
// max(1, max |reference|) (scandyn::rel_err), per output, to the tolerance the case's
// conditioning gives (chain_directional_cases.hpp: tolerance): double on 1 and 2
// threads, float.
void check_model(const std::string& spec, Index B, double q_scale = 1) {
  const Model model = load_model(spec);
  for_each_case(model, spec, B, q_scale, [&](const Case& c, const Errors& es, bool with_fext) {
    Errors ed{};
    for (int threads : {1, 2}) {
      ed = errors(run<double>(model, c, threads), c);
      expect_within(ed, es, false, "double, threads " + std::to_string(threads));
    }
    const Errors ef = errors(run<float>(model, c, 2), c);
    expect_within(ef, es, true, "float");
    ::testing::Test::RecordProperty(spec + (with_fext ? "_fext" : "") + (q_scale != 1 ? "_near_rest" : ""),
                                    "double " + str(ed) + "; float " + str(ef) + "; serial float " + str(es));
  });
}

TEST(ChainDirectional, MatchesSerialOnShortRope) { check_model("rope:10", 3); }
TEST(ChainDirectional, MatchesSerialOnLongRope) { check_model("rope:1000", 2); }
TEST(ChainDirectional, MatchesSerialOnLongRopeNearRest) { check_model("rope:1000", 1, 0.01); }
TEST(ChainDirectional, MatchesSerialOnCurtain) { check_model("curtain:3:50", 3); }

// One chunk is the serial recursion itself (the walks are the serial steps): qdd and
// M^-1 w equal the serial aba_jvp / aba_vjp bit for bit; the derivatives differ by
// the subtree forces F (and the VJP's RA), which the scans take from the ABA's
// identity IA a + pA instead of the RNEA's sums: to rounding.
TEST(ChainDirectional, OneChunkIsTheSerialRecursion) {
  const Model model = load_model("rope:200");
  const Case c = make_case(model, 1, 21, true);
  const Result<double> r = run<double>(model, c, 1, 1000);
  EXPECT_EQ(r.qdd_j, c.qdd);
  EXPECT_EQ(r.gtau, c.gtau);
  const Errors e = errors(r, c);
  for (int k = 0; k < 5; ++k) EXPECT_LT(e[k], 1e-12) << kField[k] << ": " << str(e);
}

// Random chains of mixed revolute and prismatic joints hanging from the base.
TEST(ChainDirectional, MatchesSerialOnChainsFromTheBase) {
  const Model forest = test::random_chains_from_base(60, 3, {1, 3, 10, 41});
  for (bool with_fext : {false, true}) {
    const Case c = make_case(forest, 3, 17 + with_fext, with_fext);
    const Errors ed = errors(run<double>(forest, c, 2, 8), c);
    for (int k = 0; k < 5; ++k) EXPECT_LT(ed[k], 1e-9) << kField[k] << ": " << str(ed);
  }
}

// <w, dqdd(v)> = <(gq, gqd, gtau)(w), (dq, dqd, dtau)>, both from the chain scans, to
// 1e-10 of the sum of the products' magnitudes.
TEST(ChainDirectional, AdjointIdentity) {
  for (const char* spec : {"rope:10", "rope:1000", "curtain:3:50"}) {
    const Model model = load_model(spec);
    const Case c = make_case(model, 2, 11, true);
    const AdjointSums a = adjoint_sums(c, run<double>(model, c, 2));
    EXPECT_LE(std::fabs(a.lhs - a.rhs), 1e-10 * a.scale) << spec << ": " << a.lhs << " vs " << a.rhs;
  }
}

// The same chunks on 1 and 2 threads give the same bits.
TEST(ChainDirectional, ThreadsDoNotChangeTheResult) {
  const Model model = load_model("curtain:3:50");
  const Case c = make_case(model, 3, 5, true);
  const Result<double> a = run<double>(model, c, 1, 8), b = run<double>(model, c, 2, 8);
  EXPECT_EQ(a.dqdd, b.dqdd);
  EXPECT_EQ(a.gq, b.gq);
  EXPECT_EQ(a.gqd, b.gqd);
  EXPECT_EQ(a.gtau, b.gtau);
  EXPECT_EQ(a.qdd_j, b.qdd_j);
}

TEST(ChainDirectional, RefusesFloatingBaseAndBranches) {
  EXPECT_THROW(ChainFdDirectional<double>(test::load_floating("rope:20"), 1), BackendError);
  EXPECT_THROW(ChainFdDirectional<double>(test::random_model(20, 1), 1), BackendError);
  try {
    ChainFdDirectional<double>(test::load_floating("rope:20"), 1);
  } catch (const BackendError& e) {
    EXPECT_NE(std::string(e.what()).find("floating base"), std::string::npos) << e.what();
  }
}

// A NaN joint position in one instance fails that instance only; the other's outputs
// are the serial ones.
TEST(ChainDirectional, FailedInstanceIsReported) {
  const Model model = load_model("rope:40");
  Case c = make_case(model, 2, 9, false);
  std::vector<double> q = c.q;
  for (Index i = 0; i < c.n; ++i) c.q[i * 2 + 1] = NAN;
  ChainFdDirectional<double> eng(model, 2, 2);
  using V = BatchView<const double>;
  using O = BatchView<double>;
  const Index n = c.n;
  const FdBatchIn<double> in{V::soa(c.q.data(), n, 2), V::soa(c.qd.data(), n, 2), V::soa(c.tau.data(), n, 2)};
  std::vector<double> qdd(2 * n, -5), dqdd(2 * n, -5);
  std::vector<int> failed(2);
  EXPECT_EQ(eng.jvp(in, V::soa(c.dq.data(), n, 2), V::soa(c.dqd.data(), n, 2), V::soa(c.dtau.data(), n, 2),
                    O::soa(qdd.data(), n, 2), O::soa(dqdd.data(), n, 2), failed.data()),
            1);
  EXPECT_EQ(failed[0], -1);
  EXPECT_GE(failed[1], 0);
  for (Index i = 0; i < n; ++i) {
    EXPECT_EQ(dqdd[i * 2 + 1], -5);  // unwritten
    EXPECT_NEAR(dqdd[i * 2], c.dqdd[i * 2], 1e-9 * std::fmax(1.0, std::fabs(c.dqdd[i * 2])));
  }
}

}  // namespace

namespace {

// The engine (make_fd_directional_derivatives) on serial and openmp, aba_jvp per
// instance and the scans, against the serial references (SoA views).
template <class S>
Result<S> run_engine(const Model& model, const Case& c, BackendKind kind, FdMethod method, std::string* strategy) {
  BackendOptions o;
  o.backend = kind;
  o.max_batch = c.B;
  o.fd_method = method;
  const ModelTpl<S> m = model.cast<S>();
  auto eng = make_fd_directional_derivatives(m, o);
  *strategy = eng->strategy();
  const Inputs<S> x(c);
  Result<S> r = Result<S>::nan(c.q.size());
  const Views<S> v(x, r, c.n, c.B);
  EXPECT_TRUE(eng->jvp(v.in, v.dq, v.dqd, v.dtau, v.qdd_j, v.dqdd).ok());
  EXPECT_TRUE(eng->vjp(v.in, v.w, v.qdd_v, v.gq, v.gqd, v.gtau).ok());
  return r;
}

TEST(ChainDirectional, Engine) {
  const Model curtain = load_model("curtain:3:50");
  const Case c = make_case(curtain, 3, 31, true);
  const Errors es = serial_float_errors(curtain, c);
  std::vector<BackendKind> kinds{BackendKind::Serial};
  if (backend_unusable(BackendKind::OpenMP).empty()) kinds.push_back(BackendKind::OpenMP);
  for (BackendKind kind : kinds) {
    for (FdMethod method : {FdMethod::Auto, FdMethod::Aba, FdMethod::Parallel}) {
      std::string strategy;
      const Errors e = errors(run_engine<double>(curtain, c, kind, method, &strategy), c);
      // Auto picks the scans from 4096 links and kChainFdThreadsPerInstance threads per
      // instance (openmp): aba_jvp on a curtain of 150
      EXPECT_EQ(strategy, method == FdMethod::Parallel ? "parallel" : "aba_jvp");
      if (strategy == "aba_jvp") {
        for (int k = 0; k < 5; ++k) EXPECT_EQ(e[k], 0.0) << kField[k];  // the serial functions themselves
      }
      expect_within(e, es, false, std::string(to_string(method)) + " on " + to_string(kind));
      expect_within(errors(run_engine<float>(curtain, c, kind, method, &strategy), c), es, true,
                    std::string("float, ") + to_string(method));
    }
  }
  // Auto on one long chain: the scans where forward dynamics takes them (openmp, 4096
  // links, kChainFdThreadsPerInstance threads per instance; engines constructed only)
  {
    const Model rope = load_model("rope:4096");
    BackendOptions a;
    a.fd_method = FdMethod::Auto;
    EXPECT_EQ(make_fd_directional_derivatives(rope, a)->strategy(), "aba_jvp");  // serial
    if (backend_unusable(BackendKind::OpenMP).empty()) {
      a.backend = BackendKind::OpenMP;
      a.threads = kChainFdThreadsPerInstance;
      EXPECT_EQ(make_fd_directional_derivatives(rope, a)->strategy(), "parallel");
      a.threads = kChainFdThreadsPerInstance - 1;
      EXPECT_EQ(make_fd_directional_derivatives(rope, a)->strategy(), "aba_jvp");
    }
  }
  // a branching model: aba_jvp, and no scans
  const Model tree = test::random_model(12, 3);
  const Case t = make_case(tree, 2, 4, false);
  std::string strategy;
  const Errors e = errors(run_engine<double>(tree, t, BackendKind::Serial, FdMethod::Auto, &strategy), t);
  EXPECT_EQ(strategy, "aba_jvp");
  for (int k = 0; k < 5; ++k) EXPECT_EQ(e[k], 0.0) << kField[k];
  BackendOptions o;
  o.fd_method = FdMethod::Parallel;
  EXPECT_THROW(make_fd_directional_derivatives(tree, o), BackendError);
  o.fd_method = FdMethod::Jsi;
  EXPECT_THROW(make_fd_directional_derivatives(curtain, o), BackendError);
  EXPECT_THROW(make_fd_directional_derivatives(test::load_floating("rope:20"), o), BackendError);
  o.fd_method = FdMethod::Parallel;
  EXPECT_THROW(make_fd_directional_derivatives(test::load_floating("rope:20"), o), BackendError);
  // cuda: the scans only (a branching model: refused, with or without a device)
  o.fd_method = FdMethod::Auto;
  o.backend = BackendKind::Cuda;
  EXPECT_THROW(make_fd_directional_derivatives(tree, o), BackendError);
}

}  // namespace
