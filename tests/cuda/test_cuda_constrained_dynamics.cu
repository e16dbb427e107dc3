// The CUDA closed-loop forward dynamics (CudaConstrainedForwardDynamics: one thread
// per instance, the CPU engines' loop_solver.hpp routines) against the serial engine:
// qdd and lambda on 1000 random closed states of the five-bar, the four-bar and the
// weld-closed five-bar, host (compute) and device (compute_async) paths, float and
// double; the residual; models beyond the thread kernel's capacity refused. Skipped,
// with the reason, without a usable device.
// Tolerances relative to max(1, max |x|): double 1e-9 (the device's sin/cos and FMA
// differ from the host's), float 2e-3.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>

#include "cuda_test_util.hpp"
#include "scandyn/algorithm/loops.hpp"
#include "scandyn/cuda/constrained_dynamics.hpp"
#include "scandyn/model/load.hpp"
#include "loop_cases.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

using Case = test::LoopCase;

std::vector<Case> cases() { return test::loop_cases({"fivebar", "fourbar", "fivebar+weld"}); }

template <class S>
void check_case(const Case& c) {
  SCOPED_TRACE(c.spec + (sizeof(S) == 4 ? " float" : " double"));
  const Index n = c.model.nv(), m = c.loops.rows(), B = 1000;
  std::mt19937_64 g(3);
  std::vector<S> q(B * n), qd(B * n), tau(B * n);
  for (Index b = 0; b < B; ++b) {
    std::vector<double> qb, qdb;
    ASSERT_LE(test::closed_state(c, g, qb, qdb), 1e-12);
    const auto tb = test::random_vector(g, n, -1, 1);
    for (Index i = 0; i < n; ++i) q[b * n + i] = S(qb[i]), qd[b * n + i] = S(qdb[i]), tau[b * n + i] = S(tb[i]);
  }
  const ModelTpl<S> ms = c.model.cast<S>();
  BackendOptions o;
  o.max_batch = B;
  auto serial = make_constrained_forward_dynamics<S>(ms, c.loops, o);
  o.backend = BackendKind::Cuda;
  auto gpu = make_constrained_forward_dynamics<S>(ms, c.loops, o);
  EXPECT_EQ(gpu->strategy(), "dense_thread");
  using V = BatchView<const S>;
  const FdBatchIn<S> in{V::aos(q.data(), n, B), V::aos(qd.data(), n, B), V::aos(tau.data(), n, B), nullptr};
  std::vector<S> rq(B * n), rl(B * m), gq(B * n), gl(B * m);
  ASSERT_TRUE(serial->compute(in, BatchView<S>::aos(rq.data(), n, B), BatchView<S>::aos(rl.data(), m, B)).ok());
  ASSERT_TRUE(gpu->compute(in, BatchView<S>::aos(gq.data(), n, B), BatchView<S>::aos(gl.data(), m, B)).ok());
  const double tol = sizeof(S) == 4 ? 2e-3 : 1e-9;
  for (Index b = 0; b < B; ++b) {
    double sq = 1, sl = 1;
    for (Index i = 0; i < n; ++i) sq = std::max(sq, std::fabs(double(rq[b * n + i])));
    for (Index k = 0; k < m; ++k) sl = std::max(sl, std::fabs(double(rl[b * m + k])));
    for (Index i = 0; i < n; ++i) ASSERT_NEAR(gq[b * n + i], rq[b * n + i], tol * sq) << "instance " << b;
    for (Index k = 0; k < m; ++k) ASSERT_NEAR(gl[b * m + k], rl[b * m + k], tol * sl) << "instance " << b;
  }
  // the residual of closed states: phi and J qd vanish
  std::vector<S> phi(B * m), vel(B * m);
  gpu->residual(in.q, in.qd, BatchView<S>::aos(phi.data(), m, B), BatchView<S>::aos(vel.data(), m, B));
  const double rtol = sizeof(S) == 4 ? 1e-5 : 1e-11;
  for (Index e = 0; e < B * m; ++e) {
    ASSERT_LE(std::fabs(double(phi[e])), rtol);
    ASSERT_LE(std::fabs(double(vel[e])), 10 * rtol);
  }
  // the device path on device buffers (soa)
  auto* ce = dynamic_cast<cuda::CudaConstrainedForwardDynamics<S>*>(gpu.get());
  ASSERT_NE(ce, nullptr);
  S* d = nullptr;
  int* df = nullptr;
  const std::size_t cn = q.size(), cm = rl.size();
  ASSERT_CUDA(cudaMalloc(&d, (4 * cn + cm) * sizeof(S)));
  ASSERT_CUDA(cudaMalloc(&df, B * sizeof(int)));
  std::vector<S> soa(cn);
  const std::vector<S>* src[3] = {&q, &qd, &tau};
  for (int a = 0; a < 3; ++a) {
    for (Index b = 0; b < B; ++b)
      for (Index i = 0; i < n; ++i) soa[i * B + b] = (*src[a])[b * n + i];
    ASSERT_CUDA(cudaMemcpy(d + a * cn, soa.data(), cn * sizeof(S), cudaMemcpyHostToDevice));
  }
  const FdBatchIn<S> din{V::soa(d, n, B), V::soa(d + cn, n, B), V::soa(d + 2 * cn, n, B), nullptr};
  ASSERT_CUDA(ce->compute_async(din, BatchView<S>::soa(d + 3 * cn, n, B), BatchView<S>::soa(d + 4 * cn, m, B), df,
                                nullptr));
  ASSERT_CUDA(cudaDeviceSynchronize());
  std::vector<S> dq(cn), dl(cm);
  std::vector<int> f(B);
  ASSERT_CUDA(cudaMemcpy(dq.data(), d + 3 * cn, cn * sizeof(S), cudaMemcpyDeviceToHost));
  ASSERT_CUDA(cudaMemcpy(dl.data(), d + 4 * cn, cm * sizeof(S), cudaMemcpyDeviceToHost));
  ASSERT_CUDA(cudaMemcpy(f.data(), df, B * sizeof(int), cudaMemcpyDeviceToHost));
  for (Index b = 0; b < B; ++b) {
    ASSERT_EQ(f[b], -1);
    for (Index i = 0; i < n; ++i) ASSERT_EQ(dq[i * B + b], gq[b * n + i]) << "compute_async = compute";
    for (Index k = 0; k < m; ++k) ASSERT_EQ(dl[k * B + b], gl[b * m + k]);
  }
  cudaFree(d);
  cudaFree(df);
}

}  // namespace

TEST(CudaConstrainedDynamics, MatchesTheSerialEngine) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (const Case& c : cases()) {
    check_case<double>(c);
    check_case<float>(c);
  }
}

TEST(CudaConstrainedDynamics, RefusesLargeSystems) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model m = load_model("cloth:4:6");  // 24 DoF, 54 rows
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  try {
    make_constrained_forward_dynamics<double>(m, generator_loops("cloth:4:6", m), o);
    FAIL() << "no error";
  } catch (const BackendError& e) {
    EXPECT_NE(std::string(e.what()).find("use the serial or openmp backend"), std::string::npos) << e.what();
  }
}
