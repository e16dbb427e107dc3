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
#include "scandyn/algorithm/directional_derivatives.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

// B instances (SoA, n x B) of random states and directions, and the serial double
// aba_jvp / aba_vjp of each.
struct Case {
  Index n = 0, B = 0;
  std::vector<double> q, qd, tau, dq, dqd, dtau, w;
  std::vector<Force<double>> fext;  // (B x n) or empty
  std::vector<double> qdd, dqdd, gq, gqd, gtau;  // the serial references
};

Case make_case(const Model& model, Index B, unsigned seed, bool with_fext, double q_scale = 1) {
  std::mt19937_64 rng(seed);
  const Index n = model.nv();
  Case c;
  c.n = n;
  c.B = B;
  const int nb = static_cast<int>(n * B);
  c.q = test::random_vector(rng, nb, -3 * q_scale, 3 * q_scale);
  c.qd = test::random_vector(rng, nb, -1, 1);
  c.tau = test::random_vector(rng, nb, -2, 2);
  c.dq = test::random_vector(rng, nb, -1, 1);
  c.dqd = test::random_vector(rng, nb, -1, 1);
  c.dtau = test::random_vector(rng, nb, -1, 1);
  c.w = test::random_vector(rng, nb, -1, 1);
  if (with_fext) c.fext = test::random_wrenches<double>(rng, nb, 1.0);
  for (auto* v : {&c.qdd, &c.dqdd, &c.gq, &c.gqd, &c.gtau}) v->assign(c.q.size(), NAN);
  AbaJvpData<double> jd(model);
  std::vector<double> x[7], out[5];
  for (auto& o : out) o.resize(n);
  for (Index b = 0; b < B; ++b) {
    const std::vector<double>* in[7] = {&c.q, &c.qd, &c.tau, &c.dq, &c.dqd, &c.dtau, &c.w};
    for (int k = 0; k < 7; ++k) {
      x[k].resize(n);
      for (Index i = 0; i < n; ++i) x[k][i] = (*in[k])[i * B + b];
    }
    const Force<double>* f = with_fext ? c.fext.data() + b * n : nullptr;
    EXPECT_TRUE(aba_jvp(model, jd, x[0].data(), x[1].data(), x[2].data(), f, x[3].data(), x[4].data(), x[5].data(),
                        out[1].data(), out[0].data())
                    .ok());
    EXPECT_TRUE(aba_vjp(model, jd, x[0].data(), x[1].data(), x[2].data(), f, x[6].data(), out[2].data(),
                        out[3].data(), out[4].data(), out[0].data())
                    .ok());
    std::vector<double>* ref[5] = {&c.qdd, &c.dqdd, &c.gq, &c.gqd, &c.gtau};
    for (int k = 0; k < 5; ++k)
      for (Index i = 0; i < n; ++i) (*ref[k])[i * B + b] = out[k][i];
  }
  return c;
}

// The driver's results in precision S, SoA.
template <class S>
struct Result {
  std::vector<S> qdd_j, dqdd, qdd_v, gq, gqd, gtau;
};

template <class S>
Result<S> run(const Model& model, const Case& c, int threads, Index chunk = 0) {
  const Index n = c.n, B = c.B;
  ChainFdDirectional<S> eng(model.cast<S>(), B, threads, chunk);
  const auto q = test::cast_vector<S>(c.q), qd = test::cast_vector<S>(c.qd), tau = test::cast_vector<S>(c.tau),
             dq = test::cast_vector<S>(c.dq), dqd = test::cast_vector<S>(c.dqd), dtau = test::cast_vector<S>(c.dtau),
             w = test::cast_vector<S>(c.w);
  std::vector<Force<S>> fext;
  for (const auto& f : c.fext) fext.push_back(f.template cast<S>());
  using V = BatchView<const S>;
  using O = BatchView<S>;
  const FdBatchIn<S> in{V::soa(q.data(), n, B), V::soa(qd.data(), n, B), V::soa(tau.data(), n, B),
                        fext.empty() ? nullptr : fext.data()};
  Result<S> r;
  for (auto* v : {&r.qdd_j, &r.dqdd, &r.qdd_v, &r.gq, &r.gqd, &r.gtau}) v->assign(q.size(), S(NAN));
  std::vector<int> failed(static_cast<std::size_t>(B), 7);
  EXPECT_EQ(eng.jvp(in, V::soa(dq.data(), n, B), V::soa(dqd.data(), n, B), V::soa(dtau.data(), n, B),
                    O::soa(r.qdd_j.data(), n, B), O::soa(r.dqdd.data(), n, B), failed.data()),
            0);
  for (int f : failed) EXPECT_EQ(f, -1);
  EXPECT_EQ(eng.vjp(in, V::soa(w.data(), n, B), O::soa(r.qdd_v.data(), n, B), O::soa(r.gq.data(), n, B),
                    O::soa(r.gqd.data(), n, B), O::soa(r.gtau.data(), n, B)),
            0);
  return r;
}

struct Errors {
  double qdd, dqdd, gq, gqd, gtau;
  double operator[](int k) const { return k == 0 ? qdd : k == 1 ? dqdd : k == 2 ? gq : k == 3 ? gqd : gtau; }
};
const char* const kField[5] = {"qdd", "dqdd", "gq", "gqd", "gtau"};

template <class S>
Errors errors(const Result<S>& r, const Case& c) {
  return {std::fmax(test::max_rel_err(r.qdd_j, c.qdd), test::max_rel_err(r.qdd_v, c.qdd)),
          test::max_rel_err(r.dqdd, c.dqdd), test::max_rel_err(r.gq, c.gq), test::max_rel_err(r.gqd, c.gqd),
          test::max_rel_err(r.gtau, c.gtau)};
}

std::string str(const Errors& e) {
  char buf[160];
  std::snprintf(buf, sizeof buf, "qdd %.2e dqdd %.2e gq %.2e gqd %.2e gtau %.2e", e.qdd, e.dqdd, e.gq, e.gqd, e.gtau);
  return buf;
}

// The serial aba_jvp / aba_vjp in float on the same inputs against the double
// references: the error float itself makes, whatever the algorithm.
Errors serial_float_errors(const Model& model, const Case& c) {
  const Model mf = model;
  const ModelTpl<float> m = model.cast<float>();
  const Index n = c.n, B = c.B;
  AbaJvpData<float> jd(m);
  Result<float> r;
  for (auto* v : {&r.qdd_j, &r.dqdd, &r.qdd_v, &r.gq, &r.gqd, &r.gtau}) v->assign(c.q.size(), NAN);
  std::vector<float> x[7], out[5];
  for (auto& o : out) o.resize(n);
  for (Index b = 0; b < B; ++b) {
    const std::vector<double>* in[7] = {&c.q, &c.qd, &c.tau, &c.dq, &c.dqd, &c.dtau, &c.w};
    for (int k = 0; k < 7; ++k) {
      x[k].resize(n);
      for (Index i = 0; i < n; ++i) x[k][i] = static_cast<float>((*in[k])[i * B + b]);
    }
    std::vector<Force<float>> f;
    for (Index i = 0; i < n && !c.fext.empty(); ++i) f.push_back(c.fext[b * n + i].cast<float>());
    const Force<float>* fp = f.empty() ? nullptr : f.data();
    (void)aba_jvp(m, jd, x[0].data(), x[1].data(), x[2].data(), fp, x[3].data(), x[4].data(), x[5].data(),
                  out[1].data(), out[0].data());
    (void)aba_vjp(m, jd, x[0].data(), x[1].data(), x[2].data(), fp, x[6].data(), out[2].data(), out[3].data(),
                  out[4].data(), out[0].data());
    std::vector<float>* res[5] = {&r.qdd_j, &r.dqdd, &r.gq, &r.gqd, &r.gtau};
    for (int k = 0; k < 5; ++k)
      for (Index i = 0; i < n; ++i) (*res[k])[i * B + b] = out[k][i];
  }
  r.qdd_v = r.qdd_j;
  (void)mf;
  return errors(r, c);
}

// Every output against the serial double aba_jvp / aba_vjp, relative to
// max(1, max |reference|) (scandyn::rel_err), per output. The tolerance follows the
// conditioning of the case, measured independently: es, the error of the serial
// float aba_jvp / aba_vjp on the same inputs, says how much this case amplifies a
// rounding error (dqdd = M^-1 (dtau - r) on a rope of 1000 links: es ~ 0.5 at random
// configurations, ~10 near rest, where cond(M) grows like n^4). Double: 1e-9, or 10x
// the serial double's own error so estimated (es x 2^-29, the ratio of the two
// precisions' epsilons), whichever is larger; float (the inputs rounded to float):
// 1e-5, or 10x es. Threads 1 and 2.
void check_model(const std::string& spec, Index B, double q_scale = 1) {
  const Model model = load_model(spec);
  for (bool with_fext : {false, true}) {
    SCOPED_TRACE(spec + (with_fext ? " with fext" : "") + ", q in +-" + std::to_string(3 * q_scale));
    const Case c = make_case(model, B, 3 + static_cast<unsigned>(model.nv()) + with_fext, with_fext, q_scale);
    const Errors es = serial_float_errors(model, c);
    for (int threads : {1, 2}) {
      const Errors ed = errors(run<double>(model, c, threads), c);
      for (int k = 0; k < 5; ++k)
        EXPECT_LT(ed[k], std::fmax(1e-9, 10 * es[k] * std::ldexp(1.0, -29)))
            << kField[k] << ", double, threads " << threads << ": " << str(ed) << "; serial float " << str(es);
    }
    const Errors ef = errors(run<float>(model, c, 2), c);
    for (int k = 0; k < 5; ++k)
      EXPECT_LT(ef[k], std::fmax(1e-5, 10 * es[k])) << kField[k] << ", float: " << str(ef) << "; serial float " << str(es);
    ::testing::Test::RecordProperty(spec + (with_fext ? "_fext" : ""),
                                    "float " + str(ef) + "; serial float " + str(es));
  }
}

TEST(ChainDirectional, MatchesSerialOnShortRope) { check_model("rope:10", 3); }
TEST(ChainDirectional, MatchesSerialOnLongRope) { check_model("rope:1000", 2); }
TEST(ChainDirectional, MatchesSerialOnLongRopeNearRest) { check_model("rope:1000", 1, 0.01); }
TEST(ChainDirectional, MatchesSerialOnCurtain) { check_model("curtain:3:50", 3); }

// One chunk is the serial recursion itself (the walks are the serial steps): the JVP
// and M^-1 w equal the serial aba_jvp / aba_vjp bit for bit (gq, gqd: RA by the
// ABA's identity IA Fbar + pA instead of the serial sum, to rounding).
TEST(ChainDirectional, OneChunkIsTheSerialRecursion) {
  const Model model = load_model("rope:200");
  const Case c = make_case(model, 1, 21, true);
  const Result<double> r = run<double>(model, c, 1, 1000);
  EXPECT_EQ(r.qdd_j, c.qdd);
  EXPECT_EQ(r.dqdd, c.dqdd);
  EXPECT_EQ(r.gtau, c.gtau);
  EXPECT_LT(test::max_rel_err(r.gq, c.gq), 1e-12);
  EXPECT_LT(test::max_rel_err(r.gqd, c.gqd), 1e-12);
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
    const Result<double> r = run<double>(model, c, 2);
    double lhs = 0, rhs = 0, scale = 0;
    for (std::size_t k = 0; k < c.q.size(); ++k) {
      lhs += c.w[k] * r.dqdd[k];
      scale += std::fabs(c.w[k] * r.dqdd[k]);
      const double t[3] = {r.gq[k] * c.dq[k], r.gqd[k] * c.dqd[k], r.gtau[k] * c.dtau[k]};
      for (double x : t) rhs += x, scale += std::fabs(x);
    }
    EXPECT_LE(std::fabs(lhs - rhs), 1e-10 * scale) << spec << ": " << lhs << " vs " << rhs;
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
