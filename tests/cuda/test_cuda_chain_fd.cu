// The chain forward dynamics on the device (parallel and hybrid, ChainFdPlan through
// CudaForwardDynamics) against the serial double ABA. Tests that need a device
// skip with "no CUDA device: ...".
#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <string>
#include <vector>

#include "cuda_test_util.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

struct Case {
  std::vector<double> q, qd, tau, ref;  // SoA (n x B)
  std::vector<Force<double>> fext;      // (B x n) or empty
};

Case make_case(const Model& model, Index B, unsigned seed, bool with_fext) {
  std::mt19937_64 rng(seed);
  const Index n = model.nv();
  Case c;
  c.q = test::random_vector(rng, n * B, -3, 3);
  c.qd = test::random_vector(rng, n * B, -1, 1);
  c.tau = test::random_vector(rng, n * B, -2, 2);
  if (with_fext) c.fext = test::random_wrenches<double>(rng, n * B, 1.0);
  c.ref.resize(c.q.size());
  Data data(model, false);
  std::vector<double> qi(n), qdi(n), ti(n), qddi(n);
  for (Index b = 0; b < B; ++b) {
    for (Index i = 0; i < n; ++i) qi[i] = c.q[i * B + b], qdi[i] = c.qd[i * B + b], ti[i] = c.tau[i * B + b];
    EXPECT_TRUE(aba(model, data, qi.data(), qdi.data(), ti.data(), qddi.data(),
                    with_fext ? c.fext.data() + b * n : nullptr).ok());
    for (Index i = 0; i < n; ++i) c.ref[i * B + b] = qddi[i];
  }
  return c;
}

template <class S>
double device_error(const Model& model, Index B, FdMethod algo, const Case& c,
                    std::vector<cuda::ChainTimelineEvent>* timeline = nullptr) {
  const Index n = model.nv();
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  cuda::CudaForwardDynamics<S> fd(model.cast<S>(), o, algo);
  EXPECT_EQ(fd.method(), algo);
  fd.record_timeline(timeline != nullptr);
  const auto q = test::cast_vector<S>(c.q), qd = test::cast_vector<S>(c.qd), tau = test::cast_vector<S>(c.tau);
  std::vector<Force<S>> fext;
  for (const auto& f : c.fext) fext.push_back(f.cast<S>());
  std::vector<S> qdd(q.size(), S(NAN));
  FdBatchIn<S> in{BatchView<const S>::soa(q.data(), n, B), BatchView<const S>::soa(qd.data(), n, B),
                  BatchView<const S>::soa(tau.data(), n, B), fext.empty() ? nullptr : fext.data()};
  const auto status = fd.compute(in, BatchView<S>::soa(qdd.data(), n, B));
  EXPECT_TRUE(status.ok()) << status.message();
  if (timeline) *timeline = fd.timeline();
  return test::max_rel_err(qdd, c.ref);
}

}  // namespace

TEST(CudaChainFd, RandomChainsParallelAndHybrid) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (unsigned seed : {1u, 2u}) {
    const Model m = test::random_chain(97, seed);
    const Case c = make_case(m, 3, seed, seed == 2);
    for (auto algo : {FdMethod::Parallel, FdMethod::Hybrid}) {
      EXPECT_LT(device_error<double>(m, 3, algo, c), 1e-9) << "seed " << seed;
      EXPECT_LT(device_error<float>(m, 3, algo, c), 1e-3) << "seed " << seed;
    }
  }
}

// Chains hanging from the base: independent chains inside one instance (their
// first and last links absorb as instance boundaries do), in every driver.
TEST(CudaChainFd, ChainsFromTheBaseParallelAndHybrid) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model forest = test::random_chains_from_base(90, 3, {1, 3, 10, 41, 77});
  const Model curtain = make_generated("curtain:20:40");
  for (const Model* m : {&forest, &curtain}) {
    const Case c = make_case(*m, 3, 5, m == &forest);
    for (auto algo : {FdMethod::Parallel, FdMethod::Hybrid}) {
      EXPECT_LT(device_error<double>(*m, 3, algo, c), 1e-9) << m->name;
      EXPECT_LT(device_error<float>(*m, 3, algo, c), 1e-3) << m->name;
    }
  }
}

TEST(CudaChainFd, RopesToOneHundredThousandLinks) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (int n : {10, 1000, 100000}) {
    const Model m = make_generated("rope:" + std::to_string(n));
    const Case c = make_case(m, 1, 7, false);
    for (auto algo : {FdMethod::Parallel, FdMethod::Hybrid}) {
      const double ed = device_error<double>(m, 1, algo, c), ef = device_error<float>(m, 1, algo, c);
      EXPECT_LT(ed, 1e-9) << "rope:" << n;
      EXPECT_LT(ef, 1e-3) << "rope:" << n;
      RecordProperty("rope" + std::to_string(n) + (algo == FdMethod::Hybrid ? "_hybrid" : "_parallel"),
                     std::to_string(ed) + " / " + std::to_string(ef));
    }
  }
}

// (choose_fd_method: the thread kernels up to 64 DoF, the general path's ABA for chains
// of up to 128 DoF and for larger trees, the parallel forward dynamics beyond)
TEST(CudaChainFd, AutoPicksParallelForLongChainsOnly) {
  SKIP_WITHOUT_CUDA_DEVICE();
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 2;
  EXPECT_EQ(cuda::CudaForwardDynamics<float>(make_generated("rope:200").cast<float>(), o).strategy(), "parallel");
  EXPECT_EQ(cuda::CudaForwardDynamics<float>(make_generated("rope:100").cast<float>(), o).strategy(), "aba_general");
  EXPECT_EQ(cuda::CudaForwardDynamics<float>(make_generated("rope:20").cast<float>(), o).strategy(), "aba_thread");
  EXPECT_EQ(cuda::CudaForwardDynamics<float>(make_generated("curtain:10:20").cast<float>(), o).strategy(), "parallel");
  EXPECT_EQ(cuda::CudaForwardDynamics<float>(make_generated("tree:80:3").cast<float>(), o).strategy(), "aba_general");
  EXPECT_THROW(cuda::CudaForwardDynamics<float>(test::random_model(80, 1).cast<float>(), o, FdMethod::Parallel),
               BackendError);
}

TEST(CudaChainFd, HybridOverlapsHostAndDevice) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model m = make_generated("rope:200000");
  const Case c = make_case(m, 1, 3, false);
  std::vector<cuda::ChainTimelineEvent> tl;
  EXPECT_LT(device_error<float>(m, 1, FdMethod::Hybrid, c, &tl), 1e-3);
  // some device group's walks finish before the host's work does; the device's walks
  // are busy intervals (one kernel each, in stream order: none overlaps the next), and
  // every chunk is walked once on each side
  double host_end = 0, first_gpu_walk_end = -1, prev_end = 0;
  Index host_walked = 0, gpu_walked = 0;
  for (const auto& e : tl) {
    EXPECT_LE(e.start_ms, e.end_ms) << e.what;
    if (e.what.rfind("cpu", 0) == 0) host_end = std::max(host_end, e.end_ms);
    if (e.what == "cpu walk") host_walked += e.c_hi - e.c_lo;
    if (e.what == "gpu walk") {
      if (first_gpu_walk_end < 0) first_gpu_walk_end = e.end_ms;
      EXPECT_GE(e.start_ms, prev_end);
      prev_end = e.end_ms;
      gpu_walked += e.c_hi - e.c_lo;
    }
  }
  ASSERT_GT(tl.size(), 4u);
  EXPECT_LT(first_gpu_walk_end, host_end);
  const Index chunks = (200000 + cuda::ChainFdPlan<float>::kDefaultChunk - 1) / cuda::ChainFdPlan<float>::kDefaultChunk;
  EXPECT_EQ(host_walked, chunks);
  EXPECT_EQ(gpu_walked, chunks);
}

// The hybrid's host part on 1, 2 and 4 threads (BackendOptions::threads): the same
// qdd as the serial ABA within the tolerances of the other tests.
TEST(CudaChainFd, HybridOnHostThreads) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model m = make_generated("rope:100000");
  const Case c = make_case(m, 1, 5, false);
  for (int threads : {1, 2, 4}) {
    BackendOptions o;
    o.backend = BackendKind::Cuda;
    o.max_batch = 1;
    o.threads = threads;
    cuda::CudaForwardDynamics<double> fd(m, o, FdMethod::Hybrid);
    std::vector<double> qdd(c.q.size(), NAN);
    FdBatchIn<double> in{BatchView<const double>::soa(c.q.data(), 100000, 1),
                         BatchView<const double>::soa(c.qd.data(), 100000, 1),
                         BatchView<const double>::soa(c.tau.data(), 100000, 1), nullptr};
    const auto st = fd.compute(in, BatchView<double>::soa(qdd.data(), 100000, 1));
    EXPECT_TRUE(st.ok()) << st.message();
    EXPECT_LT(test::max_rel_err(qdd, c.ref), 1e-9) << threads << " threads";
  }
}

TEST(CudaChainFd, FailedPivotIsReportedNotNaN) {
  SKIP_WITHOUT_CUDA_DEVICE();
  Model m = make_generated("rope:300");
  const Case c = make_case(m, 2, 4, false);
  // a NaN joint position in instance 1 makes its articulated pivots non-finite
  Case bad = c;
  bad.q[150 * 2 + 1] = NAN;
  // parallel, and the hybrid with its host part on 1 and 2 threads
  for (int run = 0; run < 3; ++run) {
    BackendOptions o;
    o.backend = BackendKind::Cuda;
    o.max_batch = 2;
    o.threads = run == 2 ? 2 : 1;
    cuda::CudaForwardDynamics<double> fd(m, o, run == 0 ? FdMethod::Parallel : FdMethod::Hybrid);
    std::vector<double> qdd(bad.q.size(), 123.0);
    FdBatchIn<double> in{BatchView<const double>::soa(bad.q.data(), 300, 2),
                         BatchView<const double>::soa(bad.qd.data(), 300, 2),
                         BatchView<const double>::soa(bad.tau.data(), 300, 2), nullptr};
    std::vector<int> failed(2, 9);
    const auto st = fd.compute(in, BatchView<double>::soa(qdd.data(), 300, 2), failed.data());
    EXPECT_EQ(st.failed, 1) << fd.strategy() << " run " << run;
    EXPECT_EQ(failed[0], -1) << run;
    EXPECT_GE(failed[1], 0) << run;
    for (Index i = 0; i < 300; ++i) {
      EXPECT_EQ(qdd[i * 2 + 1], 123.0) << run;  // unwritten
      EXPECT_NEAR(qdd[i * 2], c.ref[i * 2], 1e-9 * 100) << run;
    }
  }
}
