// The parallel chain hybrid dynamics on the device (cuda::ChainHybridPlan, and the
// engine API's CudaChainHybridDynamics behind make_hybrid_dynamics) against the serial
// double hybrid_dynamics and the host ChainHybridDynamics: random chains (revolute and
// prismatic joints, arbitrary axes), chains hanging from the base, a curtain, ropes of
// 10^3 and 10^5 links with 0 / 30 / 70 % of the DoFs prescribed at random and the host
// test's patterns (none, all, random 50 / 10 / 90 %, a run at the base, at the tip,
// alternating, one long run in the middle: tests/algorithm/test_chain_hybrid.cpp),
// several instances, chunk sizes 1, 3 and 8, with and without external wrenches; runs
// of prescribed DoFs many chunks long, their composites scanned and walked.
// Bounds: double 1e-9 relative to max(1, |x|) (the host test's); float 1e-2 (the host
// test's float bound) on every case but rope:10^5, whose float error is recorded and
// bounded by 1e-1 only. The given entries are copied through exactly; a failed instance
// is reported and its outputs left unwritten. Tests that need a device skip with
// "no CUDA device: ...".
#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>
#include <string>
#include <vector>

#include "cuda_test_util.hpp"
#include "scandyn/algorithm/chain_hybrid.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/cuda/chain_hybrid.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "prescribed_masks.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

using Mask = test::PrescribedMask;

// inputs (SoA, n x B) and the serial double reference of [qdd, tau]
struct Case {
  std::vector<double> q, qd, qdd_in, tau_in, ref_qdd, ref_tau;
  std::vector<Force<double>> fext;  // (B x n) or empty
};

Case make_case(const Model& model, const Mask& mask, Index B, unsigned seed, bool with_fext) {
  std::mt19937_64 rng(seed);
  const Index n = model.nv();
  Case c;
  c.q = test::random_vector(rng, n * B, -3, 3);
  c.qd = test::random_vector(rng, n * B, -1, 1);
  c.qdd_in = test::random_vector(rng, n * B, -2, 2);
  c.tau_in = test::random_vector(rng, n * B, -2, 2);
  if (with_fext) c.fext = test::random_wrenches<double>(rng, n * B, 1.0);
  c.ref_qdd.resize(c.q.size());
  c.ref_tau.resize(c.q.size());
  Data data(model, false);
  std::vector<double> qi(n), qdi(n), ai(n), ti(n), ao(n), to(n);
  for (Index b = 0; b < B; ++b) {
    for (Index i = 0; i < n; ++i)
      qi[i] = c.q[i * B + b], qdi[i] = c.qd[i * B + b], ai[i] = c.qdd_in[i * B + b], ti[i] = c.tau_in[i * B + b];
    const Status st = hybrid_dynamics(model, data, qi.data(), qdi.data(), mask.data(), ai.data(), ti.data(), ao.data(),
                                      to.data(), with_fext ? c.fext.data() + b * n : nullptr);
    EXPECT_TRUE(st.ok());
    for (Index i = 0; i < n; ++i) c.ref_qdd[i * B + b] = ao[i], c.ref_tau[i * B + b] = to[i];
  }
  return c;
}

template <class S>
std::vector<S> cast(const std::vector<double>& x) {
  return test::cast_vector<S>(x);
}

template <class S>
S* to_device(test::DeviceArray<S>& d, const std::vector<S>& h) {
  EXPECT_EQ(d.alloc(h.size()), cudaSuccess);
  EXPECT_EQ(cudaMemcpy(d.ptr, h.data(), h.size() * sizeof(S), cudaMemcpyHostToDevice), cudaSuccess);
  return d.ptr;
}

// The plan on device buffers (SoA): [qdd, tau] into qdd_out / tau_out (host, n x B),
// failed per instance; the given entries checked to be copied through.
template <class S>
void run_plan(const Model& model, const Mask& mask, Index B, const Case& c, Index chunk, std::vector<S>& qdd_out,
              std::vector<S>& tau_out, std::vector<int>& failed, Index fan_in = 0, bool scan_runs = true) {
  const Index n = model.nv();
  const ModelTpl<S> m = model.cast<S>();
  cuda::ChainHybridPlan<S> plan(m, B, chunk, fan_in);
  plan.set_scan_runs(scan_runs);
  test::DeviceArray<S> dq, dqd, da, dt, dqo, dto;
  test::DeviceArray<Force<S>> df;
  test::DeviceArray<unsigned char> dmask;
  test::DeviceArray<int> dfailed;
  const std::vector<S> q = cast<S>(c.q), qd = cast<S>(c.qd), a = cast<S>(c.qdd_in), t = cast<S>(c.tau_in);
  std::vector<Force<S>> fext;
  for (const auto& f : c.fext) fext.push_back(f.template cast<S>());
  qdd_out.assign(q.size(), S(NAN));
  tau_out.assign(q.size(), S(NAN));
  using V = BatchView<const S>;
  const HybridBatchIn<S> in{V::soa(to_device(dq, q), n, B), V::soa(to_device(dqd, qd), n, B),
                            V::soa(to_device(da, a), n, B), V::soa(to_device(dt, t), n, B),
                            fext.empty() ? nullptr : to_device(df, fext)};
  to_device(dqo, qdd_out);
  to_device(dto, tau_out);
  to_device(dmask, mask);
  ASSERT_EQ(dfailed.alloc(B), cudaSuccess);
  ASSERT_EQ(plan.launch(in, dmask.ptr, BatchView<S>::soa(dqo.ptr, n, B), BatchView<S>::soa(dto.ptr, n, B),
                        dfailed.ptr, nullptr),
            cudaSuccess);
  ASSERT_EQ(cudaDeviceSynchronize(), cudaSuccess);
  failed.assign(B, 7);
  ASSERT_EQ(cudaMemcpy(qdd_out.data(), dqo.ptr, q.size() * sizeof(S), cudaMemcpyDeviceToHost), cudaSuccess);
  ASSERT_EQ(cudaMemcpy(tau_out.data(), dto.ptr, q.size() * sizeof(S), cudaMemcpyDeviceToHost), cudaSuccess);
  ASSERT_EQ(cudaMemcpy(failed.data(), dfailed.ptr, B * sizeof(int), cudaMemcpyDeviceToHost), cudaSuccess);
  for (Index i = 0; i < n; ++i)
    for (Index b = 0; b < B; ++b) {
      if (failed[b] >= 0) continue;  // unwritten
      if (mask[i]) EXPECT_EQ(qdd_out[i * B + b], a[i * B + b]) << "DoF " << i;
      else EXPECT_EQ(tau_out[i * B + b], t[i * B + b]) << "DoF " << i;
    }
}

// max relative error of the plan's [qdd, tau] against the serial double hybrid
template <class S>
double plan_error(const Model& model, const Mask& mask, Index B, const Case& c, Index chunk = 0,
                  bool scan_runs = true) {
  std::vector<S> qdd, tau;
  std::vector<int> failed;
  run_plan<S>(model, mask, B, c, chunk, qdd, tau, failed, 0, scan_runs);
  for (Index b = 0; b < B; ++b) EXPECT_EQ(failed[b], -1) << "instance " << b;
  return std::max(test::max_rel_err(qdd, c.ref_qdd), test::max_rel_err(tau, c.ref_tau));
}

using test::prescribed_masks;
using test::random_prescribed_mask;

}  // namespace

TEST(CudaChainHybrid, RandomChainsEveryPattern) {
  SKIP_WITHOUT_CUDA_DEVICE();
  std::mt19937_64 g(3);
  for (unsigned seed : {1u, 2u}) {
    const Model m = test::random_chain(41, seed);
    int k = 0;
    for (const auto& mask : prescribed_masks(m.nv(), g)) {
      const Case c = make_case(m, mask, 3, seed + 10 * k, seed == 2);
      for (Index chunk : {1, 3, 8}) {
        EXPECT_LT(plan_error<double>(m, mask, 3, c, chunk), 1e-9) << "seed " << seed << " mask " << k << " chunk " << chunk;
        EXPECT_LT(plan_error<float>(m, mask, 3, c, chunk), 1e-2) << "seed " << seed << " mask " << k << " chunk " << chunk;
      }
      ++k;
    }
  }
}

TEST(CudaChainHybrid, ChainsFromTheBase) {
  SKIP_WITHOUT_CUDA_DEVICE();
  std::mt19937_64 g(4);
  const Model forest = test::random_chains_from_base(40, 5, {1, 3, 10, 23});
  const Model curtain = make_generated("curtain:4:30");
  for (const Model* m : {&forest, &curtain}) {
    int k = 0;
    for (const auto& mask : prescribed_masks(m->nv(), g)) {
      const Case c = make_case(*m, mask, 3, 6 + k, m == &curtain);
      for (Index chunk : {1, 5, 8}) EXPECT_LT(plan_error<double>(*m, mask, 3, c, chunk), 1e-9) << m->name << " mask " << k;
      EXPECT_LT(plan_error<float>(*m, mask, 3, c), 1e-2) << m->name << " mask " << k;
      ++k;
    }
  }
}

// rope:1000 (3 instances) and rope:10^5 (2 instances), 0 / 30 / 70 % prescribed;
// rope:1000 also every pattern. Also against the host ChainHybridDynamics (double).
TEST(CudaChainHybrid, RopesWithPrescribedSets) {
  SKIP_WITHOUT_CUDA_DEVICE();
  std::mt19937_64 g(5);
  for (int n : {1000, 100000}) {
    const Model m = make_generated("rope:" + std::to_string(n));
    const Index B = n == 1000 ? 3 : 2;
    std::vector<Mask> ms;
    for (double p : {0.0, 0.3, 0.7}) ms.push_back(random_prescribed_mask(n, p, g));
    if (n == 1000)
      for (auto& mk : prescribed_masks(n, g)) ms.push_back(mk);
    for (std::size_t k = 0; k < ms.size(); ++k) {
      const Mask& mask = ms[k];
      const Case c = make_case(m, mask, B, 8 + static_cast<unsigned>(k), false);
      const double ed = plan_error<double>(m, mask, B, c), ef = plan_error<float>(m, mask, B, c);
      const std::string what = "rope:" + std::to_string(n) + (k < 3 ? " " + std::to_string(int(k == 0 ? 0 : k == 1 ? 30 : 70)) + "%" : " pattern " + std::to_string(k - 3));
      EXPECT_LT(ed, 1e-9) << what;
      EXPECT_LT(ef, n == 1000 ? 1e-2 : 1e-1) << what;
      std::printf("%s prescribed: device chain hybrid max rel err double %.2e, float %.2e\n", what.c_str(), ed, ef);
      RecordProperty(what, std::to_string(ed) + " / " + std::to_string(ef));
      if (k < 3) {  // the host ChainHybridDynamics on the same inputs
        ChainHybridDynamics<double> host(m, mask, B, 2);
        std::vector<double> hq(c.q.size(), NAN), ht(c.q.size(), NAN);
        using V = BatchView<const double>;
        const HybridBatchIn<double> in{V::soa(c.q.data(), n, B), V::soa(c.qd.data(), n, B),
                                       V::soa(c.qdd_in.data(), n, B), V::soa(c.tau_in.data(), n, B), nullptr};
        EXPECT_EQ(host.compute(in, BatchView<double>::soa(hq.data(), n, B), BatchView<double>::soa(ht.data(), n, B)), 0);
        std::vector<double> dq, dt;
        std::vector<int> failed;
        run_plan<double>(m, mask, B, c, 0, dq, dt, failed);
        EXPECT_LT(std::max(test::max_rel_err(dq, hq), test::max_rel_err(dt, ht)), 1e-9) << what << " vs host";
      }
    }
  }
}

// Prescribed runs much longer than a chunk (tests/algorithm/test_chain_hybrid.cpp,
// LongPrescribedRuns): rope:2000, two instances, test::long_run_masks; chunks of 3 and
// 8; the runs' composites scanned (the plan's default) and walked (set_scan_runs(false));
// double within 1e-9, float within each mask's bound. The engine scans by its mask
// (hybrid_scans_runs).
TEST(CudaChainHybrid, LongPrescribedRuns) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Index n = 2000, B = 2;
  const Model m = make_generated("rope:" + std::to_string(n));
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  o.fd_method = FdMethod::Parallel;
  unsigned seed = 21;
  for (const auto& [name, mask, float_bound] : test::long_run_masks(n)) {
    const Case c = make_case(m, mask, B, seed, seed % 2 == 0);
    ++seed;
    double ed = 0, ef = 0;
    for (Index chunk : {3, 8})
      for (bool scan : {true, false}) {
        const std::string what = name + ", chunk " + std::to_string(chunk) + (scan ? ", scanned" : ", walked");
        const double d = plan_error<double>(m, mask, B, c, chunk, scan);
        const double f = plan_error<float>(m, mask, B, c, chunk, scan);
        EXPECT_LT(d, 1e-9) << what;
        EXPECT_LT(f, float_bound) << what;
        ed = std::max(ed, d);
        ef = std::max(ef, f);
      }
    std::printf("rope:2000 x 2, %s: device chain hybrid max rel err double %.2e, float %.2e\n", name.c_str(), ed, ef);
    // the engine (chunks of 8): a run beyond kScanRunChunks chunks is scanned
    auto engine = make_hybrid_dynamics(m, mask, o);
    auto* chain = dynamic_cast<cuda::CudaChainHybridDynamics<double>*>(engine.get());
    ASSERT_NE(chain, nullptr) << name;
    EXPECT_EQ(chain->plan().scans_runs(), name != "alternating") << name;
  }
}

// A NaN joint position in instance 1: its pivots fail, it is reported and its outputs
// stay unwritten; instances 0 and 2 are right (the plan and the engine API).
TEST(CudaChainHybrid, FailedInstanceIsReportedOthersWritten) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model m = make_generated("rope:300");
  std::mt19937_64 g(6);
  const Mask mask = random_prescribed_mask(300, 0.3, g);
  const Index B = 3;
  const Case good = make_case(m, mask, B, 4, false);
  Case bad = good;
  bad.q[150 * B + 1] = NAN;
  std::vector<double> qdd, tau;
  std::vector<int> failed;
  run_plan<double>(m, mask, B, bad, 0, qdd, tau, failed);
  EXPECT_EQ(failed[0], -1);
  EXPECT_GE(failed[1], 0);
  EXPECT_EQ(failed[2], -1);
  // 1e-9 relative to the largest reference entry (and at least 1), as max_rel_err
  double scale = 1;
  for (double x : good.ref_qdd) scale = std::max(scale, std::fabs(x));
  for (double x : good.ref_tau) scale = std::max(scale, std::fabs(x));
  const double tol = 1e-9 * scale;
  for (Index i = 0; i < 300; ++i)
    for (Index b : {0, 2}) {
      EXPECT_NEAR(qdd[i * B + b], good.ref_qdd[i * B + b], tol);
      EXPECT_NEAR(tau[i * B + b], good.ref_tau[i * B + b], tol);
    }
  for (Index i = 0; i < 300; ++i)
    if (!mask[i]) EXPECT_TRUE(std::isnan(qdd[i * B + 1]));  // unwritten (NaN-filled before)

  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  auto e = make_hybrid_dynamics(m, mask, o);
  EXPECT_EQ(e->strategy(), "parallel");
  std::vector<double> qo(300 * B, 123.0), to(300 * B, 123.0);
  using V = BatchView<const double>;
  const BatchStatus st = e->compute({V::soa(bad.q.data(), 300, B), V::soa(bad.qd.data(), 300, B),
                                     V::soa(bad.qdd_in.data(), 300, B), V::soa(bad.tau_in.data(), 300, B), nullptr},
                                    BatchView<double>::soa(qo.data(), 300, B), BatchView<double>::soa(to.data(), 300, B));
  EXPECT_EQ(st.failed, 1);
  EXPECT_EQ(st.first_instance, 1);
  for (Index i = 0; i < 300; ++i) {
    EXPECT_EQ(qo[i * B + 1], 123.0);
    EXPECT_EQ(to[i * B + 1], 123.0);
    EXPECT_NEAR(qo[i * B], good.ref_qdd[i * B], tol);
    EXPECT_NEAR(to[i * B + 2], good.ref_tau[i * B + 2], tol);
  }
}

// The engine API on cuda: beyond 64 DoF an unbranched chain takes the chain scans
// ("parallel"), fd_method Parallel forces them on short chains, up to 64 DoF the thread
// kernels; AoS host views with external wrenches agree with the serial hybrid.
TEST(CudaChainHybrid, EngineTakesTheScansBeyondTheThreadKernels) {
  SKIP_WITHOUT_CUDA_DEVICE();
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 2;
  const Model rope = make_generated("rope:500");
  std::mt19937_64 g(7);
  const Mask mask = random_prescribed_mask(500, 0.4, g);
  auto e = make_hybrid_dynamics(rope, mask, o);
  EXPECT_EQ(e->strategy(), "parallel");
  EXPECT_EQ(make_hybrid_dynamics(make_generated("chain:20"), Mask(20, 0), o)->strategy(), "aba_thread");
  BackendOptions p = o;
  p.fd_method = FdMethod::Parallel;
  EXPECT_EQ(make_hybrid_dynamics(make_generated("chain:20"), Mask(20, 1), p)->strategy(), "parallel");
  for (int precision = 0; precision < 2; ++precision) {
    const Index n = 500, B = 2;
    const Case c = make_case(rope, mask, B, 11, true);
    // AoS copies of the SoA case
    auto aos = [&](const std::vector<double>& x) {
      std::vector<double> y(x.size());
      for (Index i = 0; i < n; ++i)
        for (Index b = 0; b < B; ++b) y[b * n + i] = x[i * B + b];
      return y;
    };
    const auto q = aos(c.q), qd = aos(c.qd), a = aos(c.qdd_in), t = aos(c.tau_in), rq = aos(c.ref_qdd),
               rt = aos(c.ref_tau);
    if (precision == 0) {
      std::vector<double> qo(n * B, NAN), to(n * B, NAN);
      using V = BatchView<const double>;
      const BatchStatus st = e->compute({V::aos(q.data(), n, B), V::aos(qd.data(), n, B), V::aos(a.data(), n, B),
                                         V::aos(t.data(), n, B), c.fext.data()},
                                        BatchView<double>::aos(qo.data(), n, B), BatchView<double>::aos(to.data(), n, B));
      EXPECT_TRUE(st.ok()) << st.message();
      EXPECT_LT(std::max(test::max_rel_err(qo, rq), test::max_rel_err(to, rt)), 1e-9);
    } else {
      auto ef = make_hybrid_dynamics(rope.cast<float>(), mask, o);
      EXPECT_EQ(ef->strategy(), "parallel");
      const auto qf = cast<float>(q), qdf = cast<float>(qd), af = cast<float>(a), tf = cast<float>(t);
      std::vector<Force<float>> ff;
      for (const auto& f : c.fext) ff.push_back(f.cast<float>());
      std::vector<float> qo(n * B, NAN), to(n * B, NAN);
      using V = BatchView<const float>;
      const BatchStatus st = ef->compute({V::aos(qf.data(), n, B), V::aos(qdf.data(), n, B), V::aos(af.data(), n, B),
                                          V::aos(tf.data(), n, B), ff.data()},
                                         BatchView<float>::aos(qo.data(), n, B), BatchView<float>::aos(to.data(), n, B));
      EXPECT_TRUE(st.ok()) << st.message();
      EXPECT_LT(std::max(test::max_rel_err(qo, rq), test::max_rel_err(to, rt)), 1e-2);
    }
  }
}

// Refused beyond the thread kernels: a branched tree of more than 64 DoF, and fd_method
// Aba on a chain of more than 64 DoF (the messages: tests/algorithm/test_chain_hybrid.cpp,
// which runs without a device).
TEST(CudaChainHybrid, OtherShapesBeyond64DofAreRefused) {
  SKIP_WITHOUT_CUDA_DEVICE();
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  const Model tree = make_generated("tree:80:1");
  ASSERT_GE(first_branching_body(tree), 0);
  EXPECT_THROW(make_hybrid_dynamics(tree, Mask(tree.nv(), 0), o), BackendError);
  o.fd_method = FdMethod::Aba;
  EXPECT_THROW(make_hybrid_dynamics(make_generated("rope:100"), Mask(100, 0), o), BackendError);
  o.fd_method = FdMethod::Parallel;
  EXPECT_THROW(make_hybrid_dynamics(tree, Mask(tree.nv(), 0), o), BackendError);
}
