// The CPU engines' SIMD path (BackendOptions::simd, cpu_fallback/simd_batch.hpp)
// against the same engines without it (the serial reference per instance): every
// algorithm it takes (id, bias, mass, aba), float and double, SoA and AoS, batches of
// one instance, of a multiple of the pack width and of a remainder, serial and
// OpenMP; a failed pivot or NaN input in one lane reported for that instance only.
// Bit-identical where the engine says exact() (a build without FMA: -march=native
// off); else within 1e-12 (double) / 1e-4 (float) of the instance's largest output
// entry (at least 1): FMA contraction may differ between the scalar and the vector
// code, one rounding per multiply-add, amplified by the model's conditioning (float
// atlas aba: 1.3e-5 measured).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <string>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

// the CPU engines' models, and a second random tree (revolute and prismatic joints)
std::vector<std::pair<std::string, Model>> models() {
  auto m = test::engine_test_models();
  m.emplace_back("tree:24:3", load_model("tree:24:3"));
  return m;
}

template <class S>
constexpr double tolerance() {
  return sizeof(S) == sizeof(double) ? 1e-12 : 1e-4;
}

// a == b bit for bit when exact, else within tolerance<S>() of scale; NaN == NaN.
template <class S>
void expect_same(S a, S b, bool exact, double scale, const std::string& where) {
  if (std::isnan(b)) {
    ASSERT_TRUE(std::isnan(a)) << where;
    return;
  }
  if (exact) ASSERT_EQ(a, b) << where;
  else ASSERT_LE(std::abs(double(a) - double(b)), tolerance<S>() * scale) << where;
}

template <class S>
BatchView<S> view(S* p, Index n, Index B, bool soa) {
  return soa ? BatchView<S>::soa(p, n, B) : BatchView<S>::aos(p, n, B);
}

template <class S>
void expect_simd_equals_scalar(const Model& md, BackendKind backend, int threads, Index B, bool soa,
                               Index nan_instance = -1) {
  const ModelTpl<S> m = md.cast<S>();
  const Index nv = m.nv();
  std::mt19937_64 g(static_cast<unsigned>(nv * 7 + B));
  const std::size_t n = static_cast<std::size_t>(nv * B);
  std::vector<S> q = test::cast_vector<S>(test::random_vector(g, static_cast<int>(n), -1, 1));
  const std::vector<S> qd = test::cast_vector<S>(test::random_vector(g, static_cast<int>(n), -1, 1));
  const std::vector<S> x = test::cast_vector<S>(test::random_vector(g, static_cast<int>(n), -1, 1));
  const std::vector<Force<S>> fext = test::random_wrenches<S>(g, static_cast<int>(n), 0.5);
  const auto Q = view<const S>(q.data(), nv, B, soa), QD = view<const S>(qd.data(), nv, B, soa),
             X = view<const S>(x.data(), nv, B, soa);
  if (nan_instance >= 0) const_cast<S&>(Q.at(nv / 2, nan_instance)) = std::numeric_limits<S>::quiet_NaN();

  BackendOptions on, off;
  on.backend = off.backend = backend;
  on.threads = off.threads = threads;
  on.max_batch = off.max_batch = B;
  on.simd = CpuSimd::On;
  off.simd = CpuSimd::Off;
  const S sentinel = S(12345);
  std::vector<S> a(n, sentinel), b(n, sentinel);
  const auto A = view<S>(a.data(), nv, B, soa), Bv = view<S>(b.data(), nv, B, soa);
  const auto compare = [&](const std::string& what, bool exact, Index entries, const BatchView<S>& P,
                           const BatchView<S>& R) {
    for (Index k = 0; k < B; ++k) {
      double scale = 1;  // the instance's largest finite output entry, at least 1
      for (Index i = 0; i < entries; ++i)
        if (std::isfinite(R.at(i, k))) scale = std::max(scale, std::abs(double(R.at(i, k))));
      for (Index i = 0; i < entries; ++i)
        expect_same(P.at(i, k), R.at(i, k), exact, scale,
                    what + " instance " + std::to_string(k) + " entry " + std::to_string(i));
    }
  };

  auto id_on = make_inverse_dynamics<S>(m, on), id_off = make_inverse_dynamics<S>(m, off);
  // the SIMD workspaces only where a call can fill a group of W instances (W: the
  // library's pack width, read from the strategy of an engine for a large batch)
  BackendOptions wide = on;
  wide.max_batch = 64;
  const std::string ws = make_inverse_dynamics<S>(m, wide)->strategy();
  ASSERT_NE(ws.find("-simd"), std::string::npos) << ws;
  const Index W = std::stoi(ws.substr(ws.find("-simd") + 5));
  EXPECT_EQ(id_on->strategy().find("simd") != std::string::npos, B >= W) << id_on->strategy() << " W " << W;
  EXPECT_EQ(id_off->strategy().find("simd"), std::string::npos);
  id_on->compute({Q, QD, X, fext.data()}, A);
  id_off->compute({Q, QD, X, fext.data()}, Bv);
  compare("id", id_on->exact(), nv, A, Bv);

  auto h_on = make_bias_forces<S>(m, on), h_off = make_bias_forces<S>(m, off);
  h_on->compute({Q, QD, nullptr}, A);
  h_off->compute({Q, QD, nullptr}, Bv);
  compare("bias", h_on->exact(), nv, A, Bv);

  on.fd_method = off.fd_method = FdMethod::Aba;
  auto fd_on = make_forward_dynamics<S>(m, on), fd_off = make_forward_dynamics<S>(m, off);
  std::fill(a.begin(), a.end(), sentinel);
  std::fill(b.begin(), b.end(), sentinel);
  const BatchStatus s_on = fd_on->compute({Q, QD, X, fext.data()}, A);
  const BatchStatus s_off = fd_off->compute({Q, QD, X, fext.data()}, Bv);
  EXPECT_EQ(s_on.failed, s_off.failed);
  EXPECT_EQ(s_on.first_instance, s_off.first_instance);
  EXPECT_EQ(s_on.first_dof, s_off.first_dof);
  for (Index k = 0; k < B; ++k) EXPECT_EQ(s_on.failed_dof[k], s_off.failed_dof[k]) << "instance " << k;
  if (nan_instance >= 0) {
    EXPECT_EQ(s_on.failed, 1);  // NaN in one lane: that instance only, left unwritten
    EXPECT_EQ(s_on.first_instance, nan_instance);
    for (Index i = 0; i < nv; ++i) EXPECT_EQ(A.at(i, nan_instance), sentinel);
  }
  compare("aba", fd_on->exact(), nv, A, Bv);

  // with the run-time check on, the SIMD groups' results are checked as the scalar ones
  // are: with a threshold no estimate meets, every instance flagged on both paths (a
  // result is written, flagged or not), and the same results
  BackendOptions con = on, coff = off;
  con.fd_check = coff.fd_check = FdCheckMode::On;
  con.fd_check_tol_float = coff.fd_check_tol_float = 1e-300;
  con.fd_check_tol_double = coff.fd_check_tol_double = 1e-300;
  auto fc_on = make_forward_dynamics<S>(m, con), fc_off = make_forward_dynamics<S>(m, coff);
  EXPECT_EQ(fc_on->strategy().find("simd") != std::string::npos, B >= W) << fc_on->strategy();
  std::fill(a.begin(), a.end(), sentinel);
  std::fill(b.begin(), b.end(), sentinel);
  const BatchStatus c_on = fc_on->compute({Q, QD, X, fext.data()}, A);
  const BatchStatus c_off = fc_off->compute({Q, QD, X, fext.data()}, Bv);
  EXPECT_EQ(c_on.failed, B);
  EXPECT_EQ(c_off.failed, B);
  for (Index k = 0; k < B; ++k) {
    EXPECT_GE(c_on.failed_dof[k], 0) << "instance " << k;
    if (k != nan_instance) {
      EXPECT_EQ(c_on.failed_dof[k] >= 0, c_off.failed_dof[k] >= 0) << "instance " << k;
    }
  }
  compare("aba+check", fd_on->exact(), nv, A, Bv);

  std::vector<S> Ma(n * nv, sentinel), Mb(n * nv, sentinel);
  const auto MA = view<S>(Ma.data(), nv * nv, B, soa), MB = view<S>(Mb.data(), nv * nv, B, soa);
  auto mm_on = make_mass_matrix<S>(m, on);
  mm_on->compute(Q, MA);
  make_mass_matrix<S>(m, off)->compute(Q, MB);
  compare("mass", mm_on->exact(), nv * nv, MA, MB);
}

std::vector<std::pair<BackendKind, int>> backends() {
  std::vector<std::pair<BackendKind, int>> b{{BackendKind::Serial, 1}};
  if (backend_unusable(BackendKind::OpenMP).empty()) {
    b.push_back({BackendKind::OpenMP, 1});
    b.push_back({BackendKind::OpenMP, 2});
  }
  return b;
}

}  // namespace

TEST(SimdBatch, EqualsTheScalarEnginesOnEveryModelLayoutAndBatchShape) {
  for (const auto& [name, model] : models())
    for (const auto& [backend, threads] : backends())
      for (Index B : {1, 2, 16, 37})
        for (bool soa : {true, false}) {
          SCOPED_TRACE(name + " " + to_string(backend) + " threads " + std::to_string(threads) + " B " +
                       std::to_string(B) + (soa ? " soa" : " aos"));
          expect_simd_equals_scalar<double>(model, backend, threads, B, soa);
          expect_simd_equals_scalar<float>(model, backend, threads, B, soa);
        }
}

// A NaN joint position in one instance: aba reports that instance only (its pivot is
// not finite) and leaves its qdd unwritten; the group's other lanes get their own
// results; id, bias and mass give NaN for that instance only.
TEST(SimdBatch, ANaNInOneLaneFailsThatInstanceOnly) {
  const Model iiwa = test::load_robot("iiwa.urdf");
  for (const auto& [backend, threads] : backends())
    for (Index bad : {0, 5, 17}) {
      SCOPED_TRACE(std::string(to_string(backend)) + " instance " + std::to_string(bad));
      expect_simd_equals_scalar<double>(iiwa, backend, threads, 32, true, bad);
      expect_simd_equals_scalar<float>(iiwa, backend, threads, 32, false, bad);
    }
}

TEST(SimdBatch, ModesParseAndOffIsTheScalarPath) {
  EXPECT_EQ(parse_cpu_simd("on"), CpuSimd::On);
  EXPECT_EQ(parse_cpu_simd("off"), CpuSimd::Off);
  EXPECT_EQ(parse_cpu_simd("auto"), CpuSimd::Auto);
  EXPECT_THROW(parse_cpu_simd("avx"), BackendError);
  const Model iiwa = test::load_robot("iiwa.urdf");
  BackendOptions o;
  o.simd = CpuSimd::Off;
  EXPECT_EQ(make_inverse_dynamics<double>(iiwa, o)->strategy(), "recursion");
  EXPECT_EQ(make_mass_matrix<double>(iiwa, o)->strategy(), "crba");
  EXPECT_TRUE(make_forward_dynamics<double>(iiwa, o)->exact());
}

// The SIMD workspaces of inverse and forward dynamics hold nv packs per entry, not
// nv x nv (the mass matrix's): a 10^5-link rope's engines are made and run (its
// nv x nv workspace would be 1.6e11 bytes), with the result of the reference.
TEST(SimdBatch, LongChainEnginesReserveLinearWorkspaces) {
  const Model m = make_generated("rope:100000");
  const Index nv = m.nv(), B = 2;
  std::mt19937 g(5);
  std::uniform_real_distribution<double> u(-0.3, 0.3);
  std::vector<double> q(nv * B), qd(nv * B), qdd(nv * B), tau(nv * B), ref(nv);
  for (auto* v : {&q, &qd, &qdd})
    for (double& x : *v) x = u(g);
  BackendOptions o;
  o.max_batch = B;
  o.simd = CpuSimd::Auto;
  o.strategy = IdStrategy::Recursion;
  using V = BatchView<const double>;
  make_inverse_dynamics<double>(m, o)->compute(
      {V::soa(q.data(), nv, B), V::soa(qd.data(), nv, B), V::soa(qdd.data(), nv, B)},
      BatchView<double>::soa(tau.data(), nv, B));
  Data data(m, false);
  std::vector<double> q0(nv), qd0(nv), qdd0(nv);
  for (Index i = 0; i < nv; ++i) q0[i] = q[i * B], qd0[i] = qd[i * B], qdd0[i] = qdd[i * B];
  rnea(m, data, q0.data(), qd0.data(), qdd0.data(), ref.data());
  std::vector<double> tau0(nv);
  for (Index i = 0; i < nv; ++i) tau0[i] = tau[i * B];
  EXPECT_LT(test::max_rel_err(tau0, ref), 1e-12);
  o.fd_method = FdMethod::Aba;
  o.fd_check = FdCheckMode::Off;
  EXPECT_NO_THROW(make_forward_dynamics<double>(m, o));
}

// A one-instance engine keeps one workspace, whatever its threads: a 10^5-link rope's
// inverse and forward dynamics on 64 OpenMP threads with max_batch 1 (a workspace per
// thread, SIMD ones included, would be 64 x ~0.4 GB: the accuracy report's 10^6-link
// rows were killed for it on a 16-core machine), with the result of the reference.
TEST(SimdBatch, OneInstanceEnginesKeepOneWorkspace) {
  if (!backend_unusable(BackendKind::OpenMP).empty()) GTEST_SKIP() << backend_unusable(BackendKind::OpenMP);
  const Model m = make_generated("rope:100000");
  const Index nv = m.nv();
  std::mt19937 g(6);
  std::uniform_real_distribution<double> u(-0.3, 0.3);
  std::vector<double> q(nv), qd(nv), qdd(nv), tau(nv), ref(nv), back(nv);
  for (auto* v : {&q, &qd, &qdd})
    for (double& x : *v) x = u(g);
  BackendOptions o;
  o.backend = BackendKind::OpenMP;
  o.threads = 64;
  o.max_batch = 1;
  o.simd = CpuSimd::On;
  o.strategy = IdStrategy::Recursion;
  o.fd_method = FdMethod::Aba;
  o.fd_check = FdCheckMode::Off;
  using V = BatchView<const double>;
  const auto id = make_inverse_dynamics<double>(m, o);
  EXPECT_EQ(id->strategy(), "recursion");  // no SIMD group can be filled by one instance
  id->compute({V::soa(q.data(), nv, 1), V::soa(qd.data(), nv, 1), V::soa(qdd.data(), nv, 1)},
              BatchView<double>::soa(tau.data(), nv, 1));
  Data data(m, false);
  rnea(m, data, q.data(), qd.data(), qdd.data(), ref.data());
  EXPECT_LT(test::max_rel_err(tau, ref), 1e-12);
  // forward dynamics of those torques, against the reference ABA (not against qdd: M of
  // a 10^5-link chain is too ill-conditioned for the round trip)
  const BatchStatus s = make_forward_dynamics<double>(m, o)->compute(
      {V::soa(q.data(), nv, 1), V::soa(qd.data(), nv, 1), V::soa(tau.data(), nv, 1)},
      BatchView<double>::soa(back.data(), nv, 1));
  EXPECT_TRUE(s.ok());
  ASSERT_TRUE(aba(m, data, q.data(), qd.data(), tau.data(), ref.data()).ok());
  EXPECT_LT(test::max_rel_err(back, ref), 1e-12);
}
