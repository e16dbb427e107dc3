// The parallel chain hybrid dynamics (ChainHybridDynamics, scandyn/algorithm/
// chain_hybrid.hpp) against the serial hybrid_dynamics: random chains (revolute and
// prismatic joints, arbitrary axes), chains hanging from the base, ropes of 10^3 and
// 10^5 links, random prescribed sets (none, all, half, runs at the base, at the tip,
// across chunks), every chunk size, with and without external wrenches; qdd and tau
// (the full vectors) to 1e-9 relative in double (the scans' rounding, as the chain
// forward dynamics'), 1e-2 in float; the given entries copied through exactly. Long
// prescribed runs (many chunks long) with the runs' composites scanned and walked.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <random>

#include "scandyn/algorithm/chain_hybrid.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "prescribed_masks.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

// max relative error of [qdd, tau] against the serial hybrid, B instances, SoA.
// serial_error, when not null: the same error of the serial hybrid_dynamics in S (no
// fext), the recursion's own rounding in that precision.
template <class S>
double hybrid_error(const Model& model, const std::vector<unsigned char>& mask, Index B, unsigned seed, int threads,
                    Index chunk, bool with_fext, HybridRunScan runs = HybridRunScan::Auto,
                    double* serial_error = nullptr) {
  std::mt19937_64 rng(seed);
  const Index n = model.nv();
  const auto q = test::random_vector(rng, n * B, -3, 3);
  const auto qd = test::random_vector(rng, n * B, -1, 1);
  const auto qdd_in = test::random_vector(rng, n * B, -2, 2);
  const auto tau_in = test::random_vector(rng, n * B, -2, 2);
  std::vector<Force<double>> fext;
  if (with_fext) fext = test::random_wrenches<double>(rng, n * B, 1.0);
  // the reference, instance by instance
  Data data(model, false);
  std::vector<double> ref_qdd(q.size()), ref_tau(q.size()), qi(n), qdi(n), ai(n), ti(n), ao(n), to(n);
  std::vector<Force<double>> fi(n);
  for (Index b = 0; b < B; ++b) {
    for (Index i = 0; i < n; ++i)
      qi[i] = q[i * B + b], qdi[i] = qd[i * B + b], ai[i] = qdd_in[i * B + b], ti[i] = tau_in[i * B + b];
    if (with_fext)
      for (Index i = 0; i < n; ++i) fi[i] = fext[b * n + i];
    const Status st = hybrid_dynamics(model, data, qi.data(), qdi.data(), mask.data(), ai.data(), ti.data(), ao.data(),
                                      to.data(), with_fext ? fi.data() : nullptr);
    EXPECT_TRUE(st.ok());
    for (Index i = 0; i < n; ++i) ref_qdd[i * B + b] = ao[i], ref_tau[i * B + b] = to[i];
  }
  const ModelTpl<S> m = model.cast<S>();
  ChainHybridDynamics<S> hd(m, mask, B, threads, chunk, runs);
  if (runs != HybridRunScan::Auto) {
    EXPECT_EQ(hd.scans_runs(), runs == HybridRunScan::On);
  }
  const auto qs = test::cast_vector<S>(q), qds = test::cast_vector<S>(qd), as = test::cast_vector<S>(qdd_in),
             ts = test::cast_vector<S>(tau_in);
  std::vector<Force<S>> fs;
  for (const auto& f : fext) fs.push_back(f.cast<S>());
  std::vector<S> qdd(q.size(), S(NAN)), tau(q.size(), S(NAN));
  using V = BatchView<const S>;
  const HybridBatchIn<S> in{V::soa(qs.data(), n, B), V::soa(qds.data(), n, B), V::soa(as.data(), n, B),
                            V::soa(ts.data(), n, B), with_fext ? fs.data() : nullptr};
  EXPECT_EQ(hd.compute(in, BatchView<S>::soa(qdd.data(), n, B), BatchView<S>::soa(tau.data(), n, B)), 0);
  for (Index i = 0; i < n; ++i)
    for (Index b = 0; b < B; ++b) {
      if (mask[i]) EXPECT_EQ(qdd[i * B + b], as[i * B + b]);
      else EXPECT_EQ(tau[i * B + b], ts[i * B + b]);
    }
  // qdd and tau, each relative to its own scale
  const double eq = test::max_rel_err(qdd, ref_qdd), et = test::max_rel_err(tau, ref_tau);
  if (serial_error) {
    DataTpl<S> ds(m, false);
    std::vector<S> sq(q.size()), st(q.size()), qi_s(n), qdi_s(n), ai_s(n), ti_s(n), ao_s(n), to_s(n);
    for (Index b = 0; b < B; ++b) {
      for (Index i = 0; i < n; ++i)
        qi_s[i] = qs[i * B + b], qdi_s[i] = qds[i * B + b], ai_s[i] = as[i * B + b], ti_s[i] = ts[i * B + b];
      EXPECT_TRUE(hybrid_dynamics(m, ds, qi_s.data(), qdi_s.data(), mask.data(), ai_s.data(), ti_s.data(),
                                  ao_s.data(), to_s.data())
                      .ok());
      for (Index i = 0; i < n; ++i) sq[i * B + b] = ao_s[i], st[i * B + b] = to_s[i];
    }
    *serial_error = std::max(test::max_rel_err(sq, ref_qdd), test::max_rel_err(st, ref_tau));
  }
  return std::max(eq, et);
}

using test::prescribed_masks;
using test::random_prescribed_mask;

}  // namespace

TEST(ChainHybrid, RandomChainsMatchSerialHybrid) {
  std::mt19937_64 g(3);
  for (unsigned seed : {1u, 2u}) {
    const Model m = test::random_chain(41, seed);
    for (const auto& mask : prescribed_masks(m.nv(), g))
      for (Index chunk : {1, 3, 8, 64}) {
        EXPECT_LT(hybrid_error<double>(m, mask, 3, seed, 2, chunk, false), 1e-9) << "seed " << seed << " chunk " << chunk;
        EXPECT_LT(hybrid_error<double>(m, mask, 2, seed, 1, chunk, true), 1e-9) << "fext, seed " << seed;
      }
  }
}

TEST(ChainHybrid, ChainsFromTheBase) {
  std::mt19937_64 g(4);
  const Model m = test::random_chains_from_base(40, 5, {1, 3, 10, 23});
  for (const auto& mask : prescribed_masks(m.nv(), g))
    for (Index chunk : {1, 2, 5, 64}) EXPECT_LT(hybrid_error<double>(m, mask, 3, 6, 2, chunk, false), 1e-9) << chunk;
  const Model curtain = make_generated("curtain:4:30");
  for (const auto& mask : prescribed_masks(curtain.nv(), g)) EXPECT_LT(hybrid_error<double>(curtain, mask, 2, 7, 2, 0, true), 1e-9);
}

TEST(ChainHybrid, RopesWithRandomPrescribedSets) {
  std::mt19937_64 g(5);
  for (int n : {1000, 100000}) {
    const Model m = make_generated("rope:" + std::to_string(n));
    for (double p : {0.0, 0.3, 0.7}) {
      const auto mask = random_prescribed_mask(n, p, g);
      const double ed = hybrid_error<double>(m, mask, 1, 8, 2, 0, false);
      EXPECT_LT(ed, 1e-9) << "rope:" << n << " p " << p;
      std::printf("rope:%d, %.0f%% prescribed: chain hybrid max rel err (double) %.2e\n", n, 100 * p, ed);
      if (n == 1000) {
        const double ef = hybrid_error<float>(m, mask, 1, 8, 2, 0, false);
        EXPECT_LT(ef, 1e-2) << "rope:" << n << " p " << p;
      }
    }
  }
}

// Prescribed runs much longer than a chunk (their composites scanned, or walked per
// chunk boundary: both agree with the serial hybrid): rope:2000, two instances (a run
// of every DoF crosses the instance boundary), test::long_run_masks (a run in the
// middle, every DoF, runs at the chain's start and end, runs of 300, alternating); 1 and
// 3 threads, chunks of 3, 8 and the default; the run scan on, off (the walks) and by the
// mask; double within 1e-9, float within each mask's bound.
TEST(ChainHybrid, LongPrescribedRuns) {
  const Index n = 2000;
  const Model m = make_generated("rope:" + std::to_string(n));
  for (const auto& [name, mask, float_bound] : test::long_run_masks(n)) {
    // Auto scans exactly the masks whose longest run passes kScanRunChunks chunks
    EXPECT_EQ(ChainHybridDynamics<double>(m, mask, 2, 1, 8).scans_runs(), name != "alternating") << name;
    double ed = 0, ef = 0, es = 0;  // the largest errors: double, float, the serial float recursion's
    for (int threads : {1, 3})
      for (Index chunk : {3, 8, 0}) {
        const std::string what = name + ", " + std::to_string(threads) + " threads, chunk " + std::to_string(chunk);
        std::vector<std::pair<HybridRunScan, bool>> runs{{HybridRunScan::Auto, false}, {HybridRunScan::On, true}};
        if (chunk != 3) runs.push_back({HybridRunScan::Off, false});  // the walks: O(run^2 / chunk)
        for (const auto& [mode, fext] : runs) {
          const char* how = mode == HybridRunScan::Auto ? "auto" : mode == HybridRunScan::On ? "on" : "off";
          const double d = hybrid_error<double>(m, mask, 2, 11, threads, chunk, fext, mode);
          double serial = 0;
          const double f = hybrid_error<float>(m, mask, 2, 12, threads, chunk, false, mode, &serial);
          EXPECT_LT(d, 1e-9) << what << ", " << how;
          EXPECT_LT(f, float_bound) << what << ", " << how << ", float (serial float " << serial << ")";
          ed = std::max(ed, d);
          ef = std::max(ef, f);
          es = std::max(es, serial);
        }
      }
    std::printf("rope:2000 x 2, %s: chain hybrid max rel err double %.2e, float %.2e (serial float hybrid %.2e)\n",
                name.c_str(), ed, ef, es);
  }
}

// The engine API: openmp takes the chain scans where forward dynamics would (chains of
// 4096 links and more, kChainFdThreadsPerInstance threads per instance), fd_method Parallel forces them (also on serial), Aba keeps the
// recursion; the results agree with the recursion engine.
TEST(ChainHybrid, EngineChoosesTheScansForLongChains) {
  const Model m = make_generated("rope:5000");
  std::mt19937_64 g(9);
  const auto mask = random_prescribed_mask(m.nv(), 0.4, g);
  BackendOptions o;
  o.max_batch = 2;
  auto recursion = make_hybrid_dynamics<double>(m, mask, o);
  EXPECT_EQ(recursion->strategy(), "recursion");
  o.fd_method = FdMethod::Parallel;
  auto forced = make_hybrid_dynamics<double>(m, mask, o);
  EXPECT_EQ(forced->strategy(), "parallel");
  o.fd_method = FdMethod::Jsi;
  EXPECT_THROW(make_hybrid_dynamics<double>(m, mask, o), BackendError);
  o.fd_method = FdMethod::Auto;
  if (backend_unusable(BackendKind::OpenMP).empty()) {
    o.backend = BackendKind::OpenMP;
    o.threads = kChainFdThreadsPerInstance * static_cast<int>(o.max_batch);  // (constructed only)
    EXPECT_EQ(make_hybrid_dynamics<double>(m, mask, o)->strategy(), "parallel");
    o.threads = kChainFdThreadsPerInstance * static_cast<int>(o.max_batch) - 1;
    EXPECT_EQ(make_hybrid_dynamics<double>(m, mask, o)->strategy(), "recursion");
  }
  const Index n = m.nv(), B = 2;
  const auto q = test::random_vector(g, n * B, -1, 1), qd = test::random_vector(g, n * B, -1, 1),
             a = test::random_vector(g, n * B, -1, 1), t = test::random_vector(g, n * B, -1, 1);
  using V = BatchView<const double>;
  const HybridBatchIn<double> in{V::aos(q.data(), n, B), V::aos(qd.data(), n, B), V::aos(a.data(), n, B),
                                 V::aos(t.data(), n, B), nullptr};
  std::vector<double> q1(n * B), t1(n * B), q2(n * B), t2(n * B);
  ASSERT_TRUE(recursion->compute(in, BatchView<double>::aos(q1.data(), n, B), BatchView<double>::aos(t1.data(), n, B)).ok());
  ASSERT_TRUE(forced->compute(in, BatchView<double>::aos(q2.data(), n, B), BatchView<double>::aos(t2.data(), n, B)).ok());
  EXPECT_LT(test::max_rel_err(q2, q1), 1e-9);
  EXPECT_LT(test::max_rel_err(t2, t1), 1e-9);
}

// choose_hybrid_method, the engine's choice (no device needed): on the CPU backends as
// forward dynamics' parallel method; on cuda the thread kernels up to 64 DoF, the chain
// scans (kernels/chain_hybrid.cu) for longer unbranched chains, and the refusals with
// their messages.
TEST(ChainHybrid, ChooseHybridMethodByBackendAndShape) {
  auto message = [](auto&& f) {
    try {
      f();
    } catch (const BackendError& e) {
      return std::string(e.what());
    }
    return std::string("(no BackendError)");
  };
  const Model rope = make_generated("rope:5000"), chain64 = make_generated("chain:64"),
              chain65 = make_generated("chain:65"), tree = make_generated("tree:80:1");
  ASSERT_GE(first_branching_body(tree), 0);
  const int kT = kChainFdThreadsPerInstance;  // threads per instance from which the scans pay
  // serial and openmp
  EXPECT_EQ(choose_hybrid_method(BackendKind::Serial, rope, FdMethod::Auto, 1, kT), FdMethod::Aba);
  EXPECT_EQ(choose_hybrid_method(BackendKind::OpenMP, rope, FdMethod::Auto, 1, kT), FdMethod::Parallel);
  EXPECT_EQ(choose_hybrid_method(BackendKind::OpenMP, rope, FdMethod::Auto, 2, 2 * kT - 1), FdMethod::Aba);
  EXPECT_EQ(choose_hybrid_method(BackendKind::OpenMP, chain64, FdMethod::Auto, 1, kT), FdMethod::Aba);
  EXPECT_EQ(choose_hybrid_method(BackendKind::Serial, rope, FdMethod::Parallel, 1, kT), FdMethod::Parallel);
  EXPECT_EQ(choose_hybrid_method(BackendKind::OpenMP, rope, FdMethod::Aba, 1, kT), FdMethod::Aba);
  EXPECT_EQ(message([&] { choose_hybrid_method(BackendKind::Serial, rope, FdMethod::Jsi, 1, kT); }),
            "hybrid dynamics: method 'jsi' is not offered (auto, aba or parallel)");
  // cuda
  EXPECT_EQ(choose_hybrid_method(BackendKind::Cuda, chain64, FdMethod::Auto, 1, 1), FdMethod::Aba);
  EXPECT_EQ(choose_hybrid_method(BackendKind::Cuda, chain65, FdMethod::Auto, 1, 1), FdMethod::Parallel);
  EXPECT_EQ(choose_hybrid_method(BackendKind::Cuda, make_generated("rope:100000"), FdMethod::Auto, 1, 1), FdMethod::Parallel);
  EXPECT_EQ(choose_hybrid_method(BackendKind::Cuda, chain64, FdMethod::Parallel, 1, 1), FdMethod::Parallel);
  EXPECT_EQ(choose_hybrid_method(BackendKind::Cuda, chain64, FdMethod::Aba, 1, 1), FdMethod::Aba);
  EXPECT_EQ(choose_hybrid_method(BackendKind::Cuda, make_generated("tree:40:1"), FdMethod::Auto, 1, 1), FdMethod::Aba);
  EXPECT_EQ(message([&] { choose_hybrid_method(BackendKind::Cuda, chain65, FdMethod::Hybrid, 1, 1); }),
            "hybrid dynamics: method 'hybrid' is not offered (auto, aba or parallel)");
  const std::string aba = message([&] { choose_hybrid_method(BackendKind::Cuda, chain65, FdMethod::Aba, 1, 1); });
  EXPECT_NE(aba.find("backend 'cuda': hybrid dynamics by aba runs one thread per instance, for models of up to 64 "
                     "DoF; model 'chain:65' has 65 DoF"),
            std::string::npos)
      << aba;
  const std::string branched = message([&] { choose_hybrid_method(BackendKind::Cuda, tree, FdMethod::Auto, 1, 1); });
  EXPECT_NE(branched.find("the parallel chain scans for unbranched chains hanging from the base; model 'tree:80:1' "
                          "has 80 DoF and is not a chain: body "),
            std::string::npos)
      << branched;
  EXPECT_NE(branched.find("(use the serial or openmp backend)"), std::string::npos) << branched;
}
