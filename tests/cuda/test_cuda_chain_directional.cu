// The JVP and VJP of forward dynamics of chains on the device (ChainFdPlan's
// launch_jvp / launch_vjp, scandyn/algorithm/chain_directional.hpp's walks) against
// the serial double aba_jvp / aba_vjp, to the tolerances of the host driver's test
// (tests/chain_directional_cases.hpp: from each case's conditioning), and the host
// driver ChainFdDirectional. Tests that need a device skip with "no CUDA device: ...".
#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <cmath>
#include <string>
#include <vector>

#include "chain_directional_cases.hpp"
#include "cuda_test_util.hpp"
#include "scandyn/cuda/chain_fd.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

using namespace scandyn;
using namespace scandyn::test::chain_dir;

namespace {

#define CUDA_OK(x) ASSERT_EQ((x), cudaSuccess) << #x

template <class T>
void upload(test::DeviceArray<T>& d, const std::vector<T>& h) {
  CUDA_OK(d.alloc(h.size()));
  if (!h.empty()) CUDA_OK(cudaMemcpy(d.ptr, h.data(), h.size() * sizeof(T), cudaMemcpyHostToDevice));
}

template <class T>
void download(std::vector<T>& h, const test::DeviceArray<T>& d) {
  CUDA_OK(cudaMemcpy(h.data(), d.ptr, h.size() * sizeof(T), cudaMemcpyDeviceToHost));
}

// launch_jvp and launch_vjp of a directional plan on device copies of the case (SoA).
template <class S>
void run_device(const Model& model, const Case& c, Result<S>& r, Index chunk = 0) {
  const Index n = c.n, B = c.B;
  cuda::ChainFdPlan<S> plan(model.cast<S>(), B, chunk, 0, /*directional=*/true);
  ASSERT_TRUE(plan.directional());
  const Inputs<S> x(c);
  test::DeviceArray<S> q, qd, tau, dq, dqd, dtau, w, qdd_j, dqdd, qdd_v, gq, gqd, gtau;
  test::DeviceArray<Force<S>> f;
  test::DeviceArray<int> failed;
  upload(q, x.q);
  upload(qd, x.qd);
  upload(tau, x.tau);
  upload(dq, x.dq);
  upload(dqd, x.dqd);
  upload(dtau, x.dtau);
  upload(w, x.w);
  upload(f, x.fext);
  for (auto* o : {&qdd_j, &dqdd, &qdd_v, &gq, &gqd, &gtau}) CUDA_OK(o->alloc(c.q.size()));
  CUDA_OK(failed.alloc(static_cast<std::size_t>(B)));
  using V = BatchView<const S>;
  using O = BatchView<S>;
  const FdBatchIn<S> in{V::soa(q.ptr, n, B), V::soa(qd.ptr, n, B), V::soa(tau.ptr, n, B),
                        x.fext.empty() ? nullptr : f.ptr};
  CUDA_OK(plan.launch_jvp(in, V::soa(dq.ptr, n, B), V::soa(dqd.ptr, n, B), V::soa(dtau.ptr, n, B),
                          O::soa(qdd_j.ptr, n, B), O::soa(dqdd.ptr, n, B), failed.ptr, nullptr));
  CUDA_OK(cudaDeviceSynchronize());
  std::vector<int> fl(static_cast<std::size_t>(B));
  download(fl, failed);
  for (int x : fl) EXPECT_EQ(x, -1);
  CUDA_OK(plan.launch_vjp(in, V::soa(w.ptr, n, B), O::soa(qdd_v.ptr, n, B), O::soa(gq.ptr, n, B),
                          O::soa(gqd.ptr, n, B), O::soa(gtau.ptr, n, B), failed.ptr, nullptr));
  CUDA_OK(cudaDeviceSynchronize());
  download(fl, failed);
  for (int x : fl) EXPECT_EQ(x, -1);
  r = Result<S>::nan(c.q.size());
  download(r.qdd_j, qdd_j);
  download(r.dqdd, dqdd);
  download(r.qdd_v, qdd_v);
  download(r.gq, gq);
  download(r.gqd, gqd);
  download(r.gtau, gtau);
}

void check_model(const std::string& spec, Index B, double q_scale = 1) {
  const Model model = load_model(spec);
  for_each_case(model, spec, B, q_scale, [&](const Case& c, const Errors& es, bool with_fext) {
    Result<double> rd;
    Result<float> rf;
    run_device(model, c, rd);
    run_device(model, c, rf);
    expect_within(errors(rd, c), es, false, "cuda double");
    expect_within(errors(rf, c), es, true, "cuda float");
    ::testing::Test::RecordProperty(spec + (with_fext ? "_fext" : ""),
                                    "double " + str(errors(rd, c)) + "; float " + str(errors(rf, c)));
  });
}

TEST(CudaChainDirectional, MatchesSerialOnShortRope) {
  SKIP_WITHOUT_CUDA_DEVICE();
  check_model("rope:10", 3);
}

TEST(CudaChainDirectional, MatchesSerialOnLongRope) {
  SKIP_WITHOUT_CUDA_DEVICE();
  check_model("rope:1000", 2);
  check_model("rope:1000", 1, 0.01);
}

TEST(CudaChainDirectional, MatchesSerialOnCurtain) {
  SKIP_WITHOUT_CUDA_DEVICE();
  check_model("curtain:3:50", 3);
}

// The bench's size: one instance of rope:10^5 (levels 0..4 of the scans).
TEST(CudaChainDirectional, MatchesSerialOnRopeOf100000Links) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model model = load_model("rope:100000");
  const Case c = make_case(model, 1, 5, false);
  const Errors es = serial_float_errors(model, c);
  Result<double> rd;
  run_device(model, c, rd);
  expect_within(errors(rd, c), es, false, "cuda double");
  ::testing::Test::RecordProperty("rope100000", "double " + str(errors(rd, c)) + "; serial float " + str(es));
}

// One chunk per instance is the serial recursion on one thread: the JVP equals the
// serial aba_jvp to rounding of the device's arithmetic (fused multiply-adds).
TEST(CudaChainDirectional, OneChunkIsTheSerialRecursion) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model model = load_model("rope:200");
  const Case c = make_case(model, 1, 21, true);
  Result<double> r;
  run_device(model, c, r, 1000);
  for (int k = 0; k < 5; ++k) EXPECT_LT(errors(r, c)[k], 1e-11) << kField[k] << ": " << str(errors(r, c));
}

// <w, dqdd(v)> = <(gq, gqd, gtau)(w), (dq, dqd, dtau)> on the device.
TEST(CudaChainDirectional, AdjointIdentity) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model model = load_model("curtain:3:50");
  const Case c = make_case(model, 2, 11, true);
  Result<double> r;
  run_device(model, c, r);
  const AdjointSums a = adjoint_sums(c, r);
  EXPECT_LE(std::fabs(a.lhs - a.rhs), 1e-10 * a.scale) << a.lhs << " vs " << a.rhs;
}

TEST(CudaChainDirectional, RefusalsAndMisuse) {
  SKIP_WITHOUT_CUDA_DEVICE();
  EXPECT_THROW(cuda::ChainFdPlan<double>(test::load_floating("rope:20"), 1, 0, 0, true), BackendError);
  // a plan without the directional scratch
  cuda::ChainFdPlan<double> plan(load_model("rope:20"), 1);
  EXPECT_FALSE(plan.directional());
  FdBatchIn<double> in{BatchView<const double>::soa(nullptr, 20, 1), BatchView<const double>::soa(nullptr, 20, 1),
                       BatchView<const double>::soa(nullptr, 20, 1)};
  const BatchView<const double> x = BatchView<const double>::soa(nullptr, 20, 1);
  const BatchView<double> y = BatchView<double>::soa(nullptr, 20, 1);
  EXPECT_EQ(plan.launch_jvp(in, x, x, x, y, y, nullptr, nullptr), cudaErrorNotSupported);
  EXPECT_EQ(plan.launch_vjp(in, x, y, y, y, y, nullptr, nullptr), cudaErrorNotSupported);
}

}  // namespace

namespace {

// The engine API on cuda (make_fd_directional_derivatives: a directional plan behind
// host views), strided host views, against the serial references.
TEST(CudaChainDirectional, Engine) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model model = load_model("curtain:3:50");
  const Case c = make_case(model, 3, 41, true);
  const Errors es = serial_float_errors(model, c);
  const Index n = c.n, B = c.B;
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  auto eng = make_fd_directional_derivatives(model, o);
  EXPECT_EQ(eng->strategy(), "parallel");
  using V = BatchView<const double>;
  using O = BatchView<double>;
  const FdBatchIn<double> in{V::soa(c.q.data(), n, B), V::soa(c.qd.data(), n, B), V::soa(c.tau.data(), n, B),
                             c.fext.data()};
  Result<double> r = Result<double>::nan(c.q.size());
  // outputs instance-major (aos) while the inputs are SoA
  std::vector<double> a(c.q.size()), g[3] = {a, a, a};
  EXPECT_TRUE(eng->jvp(in, V::soa(c.dq.data(), n, B), V::soa(c.dqd.data(), n, B), V::soa(c.dtau.data(), n, B),
                       O::soa(r.qdd_j.data(), n, B), O::aos(a.data(), n, B))
                  .ok());
  EXPECT_TRUE(eng->vjp(in, V::soa(c.w.data(), n, B), O::soa(r.qdd_v.data(), n, B), O::aos(g[0].data(), n, B),
                       O::aos(g[1].data(), n, B), O::aos(g[2].data(), n, B))
                  .ok());
  for (Index i = 0; i < n; ++i)
    for (Index b = 0; b < B; ++b) {
      r.dqdd[i * B + b] = a[b * n + i];
      r.gq[i * B + b] = g[0][b * n + i];
      r.gqd[i * B + b] = g[1][b * n + i];
      r.gtau[i * B + b] = g[2][b * n + i];
    }
  expect_within(errors(r, c), es, false, "cuda engine");
  o.fd_method = FdMethod::Aba;
  EXPECT_THROW(make_fd_directional_derivatives(model, o), BackendError);
}

}  // namespace
