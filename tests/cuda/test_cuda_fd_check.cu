// The run-time check of forward dynamics on the cuda backend (BackendOptions::fd_check):
// the device check of the thread engines (DeviceFdCheck, kernels/fd_check.cu) against
// the host's fd_check on the same results, flags against the serial engine's, the
// fallbacks, compute_async marking flagged instances, jsi_dense and parallel checked
// on the host, and the check off leaving results as they were. Skipped with the
// reason when no device is usable.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "cuda_test_util.hpp"
#include "scandyn/algorithm/fd_check.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "fd_states.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

using States = test::FdStates;

template <class S>
struct FdRun {
  BatchStatus status;
  std::vector<S> qdd;
  std::vector<int> failed;
  std::string strategy;
};

template <class S>
FdRun<S> run(const ModelTpl<S>& m, BackendOptions o, const States& s) {
  o.max_batch = s.B;
  auto fd = make_forward_dynamics<S>(m, o);
  FdRun<S> r;
  r.strategy = fd->strategy();
  const std::vector<S> q(s.q.begin(), s.q.end()), qd(s.qd.begin(), s.qd.end()), tau(s.tau.begin(), s.tau.end());
  r.qdd.assign(q.size(), S(0));
  using V = BatchView<const S>;
  r.status = fd->compute(FdBatchIn<S>{V::soa(q.data(), s.nv, s.B), V::soa(qd.data(), s.nv, s.B),
                                      V::soa(tau.data(), s.nv, s.B)},
                         BatchView<S>::soa(r.qdd.data(), s.nv, s.B));
  r.failed.assign(r.status.failed_dof, r.status.failed_dof + s.B);
  r.status.failed_dof = nullptr;
  return r;
}

// The host's estimate for instance b of a result (fd_check in double on the widened model).
template <class S>
double host_estimate(const ModelTpl<S>& m, const States& s, const std::vector<S>& qdd, Index b) {
  const Model md = m.template cast<double>();
  Data d(md, false);
  std::vector<S> q(s.nv), qd(s.nv), tau(s.nv), a(s.nv);
  for (Index i = 0; i < s.nv; ++i) {
    const std::size_t e = static_cast<std::size_t>(i * s.B + b);
    q[i] = S(s.q[e]), qd[i] = S(s.qd[e]), tau[i] = S(s.tau[e]), a[i] = qdd[e];
  }
  return fd_check(md, d, q.data(), qd.data(), tau.data(), a.data()).error_estimate;
}

BackendOptions cuda_options(FdMethod method, FdCheckMode check) {
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.fd_method = method;
  o.fd_check = check;
  return o;
}

// float jsi_thread on chain:64: the device check flags every state (as the serial
// engine's does), with the host's estimate; the fallbacks fix them.
TEST(CudaFdCheck, FloatJsiOnChain64FlaggedOnTheDevice) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model md = load_model("chain:64");
  const ModelTpl<float> mf = md.cast<float>();
  const States s(64, 8, 1.0, 3);
  const FdRun<float> r = run(mf, cuda_options(FdMethod::Jsi, FdCheckMode::On), s);
  EXPECT_EQ(r.strategy, "jsi_thread+check");
  EXPECT_EQ(r.status.failed, 8) << r.status.message();
  EXPECT_EQ(r.status.failure, Failure::ResidualTooLarge);
  for (Index b = 0; b < 8; ++b) EXPECT_GE(r.failed[b], 0) << b;
  // the message's estimate is the host's on the device's result, to rounding
  const double host = host_estimate(mf, s, r.qdd, 0);
  EXPECT_NEAR(r.status.estimate, host, 1e-6 * host);
  // the flagged results are the unchecked engine's
  const FdRun<float> off = run(mf, cuda_options(FdMethod::Jsi, FdCheckMode::Off), s);
  EXPECT_TRUE(off.status.ok());
  EXPECT_EQ(r.qdd, off.qdd);
  // --fallback aba,double: every instance passes after its retries
  BackendOptions fb = cuda_options(FdMethod::Jsi, FdCheckMode::On);
  fb.fallback_aba = true;
  fb.fallback_double = true;
  const FdRun<float> fixed = run(mf, fb, s);
  EXPECT_TRUE(fixed.status.ok()) << fixed.status.message();
  EXPECT_EQ(fixed.status.retried, 8);
  EXPECT_EQ(fixed.strategy, "jsi_thread+aba+check");
  for (Index b = 0; b < 8; ++b) EXPECT_LE(host_estimate(mf, s, fixed.qdd, b), 1e-4) << b;
}

// No flag on the robots' clean results, 10^4 states each, float and double, aba and
// jsi; the device's estimates equal the host's to rounding.
template <class S>
void expect_clean_robot(const std::string& file, FdMethod method) {
  const Model md = test::load_robot(file);
  const ModelTpl<S> m = md.template cast<S>();
  const States s(md.nv(), 10000, 3.14, 17);
  BackendOptions o = cuda_options(method, FdCheckMode::On);
  o.max_batch = s.B;
  cuda::CudaForwardDynamics<S> fd(m, o);
  const std::vector<S> q(s.q.begin(), s.q.end()), qd(s.qd.begin(), s.qd.end()), tau(s.tau.begin(), s.tau.end());
  std::vector<S> qdd(q.size());
  using V = BatchView<const S>;
  const BatchStatus st = fd.compute(FdBatchIn<S>{V::soa(q.data(), s.nv, s.B), V::soa(qd.data(), s.nv, s.B),
                                                 V::soa(tau.data(), s.nv, s.B)},
                                    BatchView<S>::soa(qdd.data(), s.nv, s.B));
  const std::string what = file + " " + to_string(method) + (sizeof(S) == 4 ? " float" : " double");
  EXPECT_TRUE(st.ok()) << what << ": " << st.message();
  std::vector<double> est(static_cast<std::size_t>(s.B));
  ASSERT_EQ(cudaMemcpy(est.data(), fd.device_estimates(), est.size() * sizeof(double), cudaMemcpyDeviceToHost),
            cudaSuccess);
  for (Index b = 0; b < s.B; b += 97) {
    const double h = host_estimate(m, s, qdd, b);
    // agreement to 0.1%, or to 0.1% of the threshold for estimates at rounding level
    // (1e-15 in double, where device and host round differently)
    EXPECT_NEAR(est[b], h, 1e-3 * (h + fd_check_threshold<S>())) << what << " instance " << b;
  }
}

TEST(CudaFdCheck, NoFalsePositivesOnRobots) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (const char* robot : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"})
    for (FdMethod method : {FdMethod::Aba, FdMethod::Jsi}) {
      expect_clean_robot<double>(robot, method);
      if (!(std::string(robot) == "atlas.urdf" && method == FdMethod::Jsi))  // 4 in 10^4 truly beyond 1e-4
        expect_clean_robot<float>(robot, method);
    }
}

// compute_async marks the flagged instances in failed_dof, on the device.
TEST(CudaFdCheck, ComputeAsyncMarksFlaggedInstances) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model md = load_model("chain:64");
  const ModelTpl<float> mf = md.cast<float>();
  const States s(64, 8, 1.0, 3);
  BackendOptions o = cuda_options(FdMethod::Jsi, FdCheckMode::On);
  o.max_batch = s.B;
  cuda::CudaForwardDynamics<float> fd(mf, o);
  const std::size_t n = s.q.size();
  std::vector<float> host(3 * n);
  for (std::size_t k = 0; k < n; ++k) host[k] = float(s.q[k]), host[n + k] = float(s.qd[k]), host[2 * n + k] = float(s.tau[k]);
  float* d = nullptr;
  int* failed = nullptr;
  ASSERT_EQ(cudaMalloc(&d, 4 * n * sizeof(float)), cudaSuccess);
  ASSERT_EQ(cudaMalloc(&failed, s.B * sizeof(int)), cudaSuccess);
  ASSERT_EQ(cudaMemcpy(d, host.data(), 3 * n * sizeof(float), cudaMemcpyHostToDevice), cudaSuccess);
  using V = BatchView<const float>;
  ASSERT_EQ(fd.compute_async(FdBatchIn<float>{V::soa(d, 64, s.B), V::soa(d + n, 64, s.B), V::soa(d + 2 * n, 64, s.B)},
                             BatchView<float>::soa(d + 3 * n, 64, s.B), failed, nullptr),
            cudaSuccess);
  std::vector<int> f(s.B);
  ASSERT_EQ(cudaMemcpy(f.data(), failed, s.B * sizeof(int), cudaMemcpyDeviceToHost), cudaSuccess);
  for (Index b = 0; b < s.B; ++b) EXPECT_GE(f[b], 0) << b;
  cudaFree(d);
  cudaFree(failed);
}

// jsi_dense (rope:100 float) and parallel (rope:10^4 float) are checked on the host:
// the same flags as the serial engine's check of the same method.
TEST(CudaFdCheck, DenseAndParallelCheckedOnTheHost) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (const auto& [spec, method, B] : {std::tuple<const char*, FdMethod, Index>{"rope:100", FdMethod::Jsi, 8},
                                        {"rope:10000", FdMethod::Parallel, 2}}) {
    const Model md = load_model(spec);
    const ModelTpl<float> mf = md.cast<float>();
    const States s(md.nv(), B, 1.0, 5);
    const FdRun<float> r = run(mf, cuda_options(method, FdCheckMode::On), s);
    EXPECT_NE(r.strategy.find("+check"), std::string::npos) << spec;
    for (Index b = 0; b < B; ++b) {
      const double h = host_estimate(mf, s, r.qdd, b);
      EXPECT_EQ(r.failed[b] >= 0, !(h <= 1e-4)) << spec << " instance " << b << " estimate " << h;
    }
    if (method == FdMethod::Jsi) EXPECT_GE(r.status.failed, 1) << spec;  // float jsi at 100 links: 1e-2 off
  }
}

}  // namespace
