// The stability suite: hard models and states for every CPU inverse- and
// forward-dynamics variant, in float and double, against the double serial
// reference (rnea for inverse dynamics, aba for forward dynamics).
//
// Each case asserts that the outputs are finite and within a stated per-precision
// bound of the reference, or, where the method cannot cope, that it reports the
// failure (a pivot that is not positive: Status / failed link) and leaves its
// output unwritten. The bounds are the measured errors (in the comments: the
// value this suite measured on x86-64, g++ 12, -O3) with a margin; the measured
// errors are also recorded as test properties (`--gtest_output=json:FILE`, keys
// <problem>.<method>.<precision>), which
// scripts/accuracy_report turns into the hard-case table of docs/accuracy.md.
//
// Variants: inverse dynamics by the recursion (rnea), the local-frame scan and the
// world-frame scan (the batched engine, serial backend); forward dynamics by aba,
// by the joint-space inertia (fd_jsi) and by scans over links
// (ChainForwardDynamics, "parallel", chunks of 64 links so that the aggregate
// scans are exercised).
//
// The cases (models, states, references) and the recording are shared with the
// GPU variant, tests/test_cuda_stability.cu, through tests/stability_cases.hpp.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <string>
#include <vector>

#include "scandyn/accuracy.hpp"
#include "scandyn/algorithm/chain_fd.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "stability_cases.hpp"
#include "test_util.hpp"

using namespace scandyn;
using namespace scandyn::stability;

namespace {

enum class Method { Rnea, ScanLocal, ScanWorld, Aba, Jsi, Parallel };

const char* method_name(Method m) {
  switch (m) {
    case Method::Rnea: return "id-recursion";
    case Method::ScanLocal: return "id-scan-local";
    case Method::ScanWorld: return "id-scan-world";
    case Method::Aba: return "fd-aba";
    case Method::Jsi: return "fd-jsi";
    case Method::Parallel: return "fd-parallel";
  }
  return "?";
}
bool is_id(Method m) { return m == Method::Rnea || m == Method::ScanLocal || m == Method::ScanWorld; }

template <class S>
Outcome run(const Problem& p, Method method) {
  const ModelTpl<S> m = p.model.cast<S>();
  const Index n = m.nv();
  const auto q = test::cast_vector<S>(p.q), qd = test::cast_vector<S>(p.qd), u = test::cast_vector<S>(p.u);
  std::vector<S> out(static_cast<std::size_t>(n), std::numeric_limits<S>::quiet_NaN());
  Outcome o;
  switch (method) {
    case Method::Rnea: {
      DataTpl<S> data(m, false);
      rnea(m, data, q.data(), qd.data(), u.data(), out.data());
      break;
    }
    case Method::ScanLocal:
    case Method::ScanWorld: {
      BackendOptions bo;
      bo.backend = BackendKind::Serial;
      bo.strategy = method == Method::ScanLocal ? IdStrategy::ScanLocal : IdStrategy::ScanWorld;
      bo.threads = 1;
      auto id = make_inverse_dynamics<S>(m, bo);
      using View = BatchView<const S>;
      id->compute({View::soa(q.data(), n, 1), View::soa(qd.data(), n, 1), View::soa(u.data(), n, 1)},
                  BatchView<S>::soa(out.data(), n, 1));
      break;
    }
    case Method::Aba: {
      DataTpl<S> data(m, false);
      o.failed_dof = aba(m, data, q.data(), qd.data(), u.data(), out.data()).failed_dof;
      break;
    }
    case Method::Jsi: {
      DataTpl<S> data(m, true);
      o.failed_dof = fd_jsi(m, data, q.data(), qd.data(), u.data(), out.data()).failed_dof;
      break;
    }
    case Method::Parallel: {
      ChainForwardDynamics<S> fd(m, 1, 1, 64);
      using View = BatchView<const S>;
      int failed = -2;
      fd.compute({View::soa(q.data(), n, 1), View::soa(qd.data(), n, 1), View::soa(u.data(), n, 1)},
                 BatchView<S>::soa(out.data(), n, 1), &failed);
      o.failed_dof = failed;
      break;
    }
  }
  measure(out, is_id(method) ? p.ref_id : p.ref_fd, o);
  // the measurement, for scripts/accuracy_report: property "<problem>.<method>.<precision>"
  record<S>(p, method_name(method), o);
  return o;
}

// Finite, not reported, and within bound of the reference.
template <class S>
void expect_bounded(const Problem& p, Method method, double bound) {
  const Outcome o = run<S>(p, method);
  SCOPED_TRACE(p.name + " " + method_name(method) + " " + precision_name<S>());
  EXPECT_FALSE(o.reported()) << "pivot at DoF " << o.failed_dof;
  EXPECT_TRUE(o.finite);
  EXPECT_LE(o.err, bound);
}

// The failure is reported and the output left unwritten (NaN-filled, untouched).
template <class S>
void expect_reported(const Problem& p, Method method) {
  const Outcome o = run<S>(p, method);
  SCOPED_TRACE(p.name + " " + method_name(method) + " " + precision_name<S>());
  EXPECT_TRUE(o.reported()) << "no failure reported; error " << o.err;
  EXPECT_TRUE(o.untouched);
}

// The expectation for one method and precision: finite and within a bound of the
// reference, or a reported failure.
constexpr double kReported = -1;
template <class S>
void expect(const Problem& p, Method method, double bound_or_reported) {
  if (bound_or_reported == kReported) expect_reported<S>(p, method);
  else expect_bounded<S>(p, method, bound_or_reported);
}

// Per-method expectations of one case, {double, float}; JSI's only where it runs.
struct Expected {
  double rnea[2], scan_local[2], scan_world[2], aba[2], parallel[2];
  double jsi[2] = {NAN, NAN};  // NaN: not run
};

void expect_case(const Problem& p, const Expected& e) {
  const std::pair<Method, const double*> rows[] = {
      {Method::Rnea, e.rnea},        {Method::ScanLocal, e.scan_local}, {Method::ScanWorld, e.scan_world},
      {Method::Aba, e.aba},          {Method::Parallel, e.parallel},    {Method::Jsi, e.jsi}};
  for (const auto& [method, b] : rows) {
    if (std::isnan(b[0])) continue;
    expect<double>(p, method, b[0]);
    expect<float>(p, method, b[1]);
  }
}

}  // namespace

// ---- long ropes -------------------------------------------------------------------

// JSI is not run on ropes of 10^4 links and more: its nv x nv matrix (800 MB in
// double at 10^4 links, 80 GB at 10^5) and its O(nv^3) factorisation of a chain
// (~10^11 operations at 10^4 links) are beyond a test; RopeJsi covers it to 10^3.
TEST(StabilityRope, Rope10k) {
  const Problem p = make_problem("rope:10000", rope(10000), 1);
  // measured (double / float): rnea 0 / 6.5e-06, scan-local 6.8e-15 / 8.0e-06,
  // scan-world 2.0e-14 / 4.1e-06, aba 0 / 1.8e-06, parallel 5.0e-15 / 2.9e-06
  expect_case(p, {{0, 5e-5}, {1e-13, 5e-5}, {2e-13, 5e-5}, {0, 5e-5}, {1e-13, 5e-5}});
}

TEST(StabilityRope, Rope100k) {
  const Problem p = make_problem("rope:100000", rope(100000), 2);
  // measured (double / float): rnea 0 / 1.5e-05, scan-local 3.5e-14 / 1.2e-05,
  // scan-world 7.3e-14 / 2.6e-05, aba 0 / 5.9e-05, parallel 1.6e-13 / 6.6e-05
  expect_case(p, {{0, 3e-4}, {1e-12, 3e-4}, {1e-12, 3e-4}, {0, 5e-4}, {2e-12, 5e-4}});
}

// JSI on ropes: double loses accuracy as cond(M) grows (~nv^4); float fails its
// factorisation at 10^3 links, which it reports (the pivot, qdd unwritten).
TEST(StabilityRope, RopeJsi) {
  // measured double errors: rope:30 6.7e-13, rope:100 3.1e-11, rope:300 1.9e-10, rope:1000 2.7e-08
  const std::pair<int, double> double_bound[] = {{30, 1e-11}, {100, 5e-10}, {300, 3e-9}, {1000, 5e-7}};
  for (const auto& [n, bound] : double_bound) {
    const Problem p = make_problem("rope:" + std::to_string(n), rope(n), 3);
    expect<double>(p, Method::Jsi, bound);
    if (n == 1000) expect<float>(p, Method::Jsi, kReported);  // measured: pivot at DoF 660
  }
}

// FINDING (documented, not hidden): float JSI loses accuracy on ropes long before
// its factorisation fails, and reports nothing: 1.6e-3 at 30 links, 2.0e-2 at 100,
// 0.23 at 300 (against 2e-7..1e-6 for float ABA on the same states); only at 10^3
// links is a pivot reported. The pivot test cannot see it: M is still numerically
// positive definite, just too ill-conditioned for float. When JSI gains a
// condition estimate or a residual check that reports this, these cases become
// expect_reported.
TEST(StabilityRope, FloatJsiDegradesWithoutReport) {
  for (int n : {100, 300}) {
    const Problem p = make_problem("rope:" + std::to_string(n), rope(n), 3);
    const Outcome jsi = run<float>(p, Method::Jsi), ab = run<float>(p, Method::Aba);
    SCOPED_TRACE("rope:" + std::to_string(n));
    EXPECT_FALSE(jsi.reported());
    EXPECT_TRUE(jsi.finite);
    EXPECT_GT(jsi.err, 1e-2);    // measured 2.0e-2 (100), 0.23 (300)
    EXPECT_LT(jsi.err, 1.0);
    EXPECT_LT(ab.err, 1e-5);     // measured 6.8e-7 (100), 3.4e-7 (300)
  }
}

// ---- hard models and states (10^3 links, every method) -----------------------------

// Neighbouring links differ in mass by 10^6 (links of 10 g and 10 kg alternate).
TEST(StabilityHard, MassRatio1e6) {
  const Problem p = make_problem("rope-mass-ratio-1e6:1000", mass_ratio_rope(1000, 1e6), 4);
  // measured (double / float): rnea 0 / 3.4e-06, scan-local 4.6e-15 / 2.7e-06,
  // scan-world 5.0e-15 / 5.9e-06, aba 0 / 2.9e-05, parallel 1.0e-08 / 2.4e-05,
  // jsi 9.0e-09 / reported (see FloatParallelOnMassRatios).
  Expected e{{0, 5e-5}, {1e-13, 5e-5}, {1e-13, 5e-5}, {0, 3e-4}, {1e-7, 3e-4}};
  e.jsi[0] = 1e-7, e.jsi[1] = kReported;
  expect_case(p, e);
}

// The inverse ratio: links of 10 g and 10 mg alternate.
TEST(StabilityHard, MassRatioInverse1e6) {
  const Problem p = make_problem("rope-mass-ratio-1e-6:1000", mass_ratio_rope(1000, 1e-6), 4);
  // measured (double / float): rnea 0 / 2.9e-06, scan-local 2.4e-15 / 2.4e-06,
  // scan-world 6.3e-15 / 6.3e-06, aba 0 / 5.8e-08, parallel 2.5e-13 / 5.7e-08,
  // jsi 9.0e-12 / reported
  Expected e{{0, 5e-5}, {1e-13, 5e-5}, {1e-13, 5e-5}, {0, 1e-6}, {1e-11, 1e-6}};
  e.jsi[0] = 1e-10, e.jsi[1] = kReported;
  expect_case(p, e);
}

// The float chain forward dynamics ("parallel") on ropes whose neighbouring masses
// differ by 10^6, spanning several chunks: pass 1's dual Riccati maps mix the
// mobilities of neighbours (W = Q_b + R_a differ by the mass ratio), which float
// cannot hold (before those maps ran in double whatever the precision, DualScalar,
// it returned qdd off by 1.8 without a report at 128 links, and reported a false
// failure at 1000). Now it is as accurate as float aba.
TEST(StabilityHard, FloatParallelOnMassRatios) {
  for (int n : {128, 1000})
    for (double ratio : {1e6, 1e5, 1e-6}) {
      const Problem p = make_problem("rope-mass-ratio:" + std::to_string(n), mass_ratio_rope(n, ratio), 4);
      SCOPED_TRACE(p.name + " ratio " + std::to_string(ratio));
      const Outcome par = run<float>(p, Method::Parallel), ab = run<float>(p, Method::Aba);
      EXPECT_FALSE(par.reported());
      EXPECT_TRUE(par.finite);
      EXPECT_LE(par.err, 3 * ab.err + 1e-6);  // measured 128 links, 10^6: 2.3e-5 (aba 2.5e-5)
      expect<double>(p, Method::Parallel, 1e-7);  // measured 1.8e-09
    }
}

// Near point masses: rotational inertia 1e-9 kg m^2 about the centre of mass.
TEST(StabilityHard, TinyInertia) {
  const Problem p = make_problem("rope-tiny-inertia:1000", tiny_inertia_rope(1000), 5);
  // measured (double / float): rnea 0 / 1.8e-06, scan-local 5.5e-15 / 2.3e-06,
  // scan-world 3.9e-15 / 3.2e-06, aba 0 / 1.1e-06, parallel 9.2e-14 / 3.8e-05,
  // jsi 9.4e-08 / reported
  Expected e{{0, 5e-5}, {1e-13, 5e-5}, {1e-13, 5e-5}, {0, 5e-5}, {1e-12, 3e-4}};
  e.jsi[0] = 1e-6, e.jsi[1] = kReported;
  expect_case(p, e);
}

// Singular configuration: every joint axis parallel (a planar chain), fully
// stretched (q = 0: the links hang in one straight line).
TEST(StabilityHard, ParallelAxesStretched) {
  const Problem p = make_problem("rope-parallel-axes-stretched:1000", parallel_axes_rope(1000), 6, 1.0, true);
  // measured (double / float): rnea 0 / 1.5e-06, scan-local 7.6e-16 / 1.8e-06,
  // scan-world 3.7e-14 / 1.7e-05, aba 0 / 7.5e-07, parallel 7.3e-16 / 7.8e-07,
  // jsi 6.3e-05 (double!) / reported
  Expected e{{0, 5e-5}, {1e-13, 5e-5}, {5e-13, 2e-4}, {0, 5e-5}, {1e-13, 5e-5}};
  e.jsi[0] = 5e-4, e.jsi[1] = kReported;
  expect_case(p, e);
}

// The same stretched state on the ordinary rope (axes alternating x/y).
TEST(StabilityHard, Stretched) {
  const Problem p = make_problem("rope-stretched:1000", rope(1000), 6, 1.0, true);
  // measured (double / float): rnea 0 / 1.5e-06, scan-local 2.5e-15 / 9.5e-07,
  // scan-world 3.8e-14 / 3.2e-05, aba 0 / 7.1e-07, parallel 9.2e-16 / 7.5e-07,
  // jsi 3.3e-06 / reported
  Expected e{{0, 5e-5}, {1e-13, 5e-5}, {5e-13, 3e-4}, {0, 5e-5}, {1e-13, 5e-5}};
  e.jsi[0] = 3e-5, e.jsi[1] = kReported;
  expect_case(p, e);
}

// Joint velocities of up to 10^3 rad/s.
TEST(StabilityHard, HugeVelocity) {
  const Problem p = make_problem("rope-qd-1e3:1000", rope(1000), 7, 1e3);
  // measured (double / float): rnea 0 / 1.9e-06, scan-local 2.1e-15 / 1.7e-06,
  // scan-world 8.8e-15 / 2.3e-06, aba 0 / 5.5e-05, parallel 1.1e-13 / 6.1e-05,
  // jsi 5.8e-09 / reported
  Expected e{{0, 5e-5}, {1e-13, 5e-5}, {1e-13, 5e-5}, {0, 5e-4}, {1e-12, 5e-4}};
  e.jsi[0] = 1e-7, e.jsi[1] = kReported;
  expect_case(p, e);
}

// ---- JSI with the fallback to ABA --------------------------------------------------

// Float JSI fails its factorisation on rope:1000; with the engine's aba fallback the
// instance is recomputed by aba (bit for bit the float aba) and counted as such;
// without it the failure is returned and qdd stays unwritten.
TEST(StabilityJsiFallback, FloatLongRope) {
  const Problem p = make_problem("rope:1000", rope(1000), 3);
  const ModelTpl<float> m = p.model.cast<float>();
  const Index nv = m.nv();
  const auto q = test::cast_vector<float>(p.q), qd = test::cast_vector<float>(p.qd), tau = test::cast_vector<float>(p.u);
  DataTpl<float> data(m, true);
  std::vector<float> qdd(q.size(), NAN), qdd_aba(q.size(), NAN);
  ASSERT_TRUE(aba(m, data, q.data(), qd.data(), tau.data(), qdd_aba.data()).ok());
  const Status jsi = fd_jsi(m, data, q.data(), qd.data(), tau.data(), qdd.data());
  ASSERT_FALSE(jsi.ok());
  for (float x : qdd) ASSERT_TRUE(std::isnan(x));

  using V = BatchView<const float>;
  const FdBatchIn<float> in{V::soa(q.data(), nv, 1), V::soa(qd.data(), nv, 1), V::soa(tau.data(), nv, 1)};
  BackendOptions o;
  o.fd_method = FdMethod::Jsi;
  auto off = make_forward_dynamics<float>(m, o);
  const BatchStatus st_off = off->compute(in, BatchView<float>::soa(qdd.data(), nv, 1));
  EXPECT_EQ(st_off.failed, 1);
  EXPECT_EQ(st_off.first_dof, jsi.failed_dof);
  EXPECT_EQ(st_off.fell_back, 0);
  for (float x : qdd) ASSERT_TRUE(std::isnan(x));

  o.fallback_aba = true;
  auto on = make_forward_dynamics<float>(m, o);
  const BatchStatus st_on = on->compute(in, BatchView<float>::soa(qdd.data(), nv, 1));
  EXPECT_TRUE(st_on.ok());
  EXPECT_EQ(st_on.fell_back, 1);
  EXPECT_EQ(qdd, qdd_aba);
  EXPECT_LT(rel_err(qdd.data(), p.ref_fd.data(), qdd.size()), 1e-5);  // float aba, measured 6.2e-07
}

// Where JSI succeeds the fallback changes nothing: the result is fd_jsi's.
TEST(StabilityJsiFallback, NoFallbackWhenJsiSucceeds) {
  const Problem p = make_problem("rope:100", rope(100), 3);
  const Index nv = p.model.nv();
  Data data(p.model, true);
  std::vector<double> qdd(p.q.size(), NAN), qdd_jsi(p.q.size(), NAN);
  ASSERT_TRUE(fd_jsi(p.model, data, p.q.data(), p.qd.data(), p.u.data(), qdd_jsi.data()).ok());
  BackendOptions o;
  o.fd_method = FdMethod::Jsi;
  o.fallback_aba = true;
  using V = BatchView<const double>;
  const BatchStatus st = make_forward_dynamics<double>(p.model, o)->compute(
      {V::soa(p.q.data(), nv, 1), V::soa(p.qd.data(), nv, 1), V::soa(p.u.data(), nv, 1)},
      BatchView<double>::soa(qdd.data(), nv, 1));
  EXPECT_TRUE(st.ok());
  EXPECT_EQ(st.fell_back, 0);
  EXPECT_EQ(qdd, qdd_jsi);
}
