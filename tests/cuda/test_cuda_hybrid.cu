// The CUDA hybrid dynamics (scandyn/cuda/hybrid_dynamics.hpp): hybrid_instance run on
// the host in its variants (runs in CI without a device) against the serial
// hybrid_dynamics, and the engine on the device (skipped, with the reason, without
// one) against the serial engine in the soa and aos layouts, its failures and
// compute_async.
// Tolerances: the host function is the reference's arithmetic (bit-identical up to
// FMA contraction): 1e-12 scaled error in double. On the device (FMA, the SFU's
// sin/cos in float): double 1e-9, float max(1e-4, 10 x the serial float hybrid's
// own error on the same inputs); errors are max |x - ref| / max(1, max |ref|) over
// [qdd, tau] of an instance.
#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <limits>
#include <random>
#include <variant>

#include "cuda_test_util.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/cuda/hybrid_dynamics.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/instance/hybrid_instance.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

std::vector<std::pair<std::string, Model>> models() {
  auto m = test::thread_shape_models();
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) m.emplace_back(file, test::load_robot(file));
  return m;
}

std::vector<unsigned char> random_mask(std::mt19937_64& g, Index nv) {
  std::vector<unsigned char> m(static_cast<std::size_t>(nv));
  for (auto& x : m) x = g() % 2;
  return m;
}

// B instances, instance-major (aos): inputs in double exactly representable in S
struct States {
  Index nv, B;
  std::vector<double> q, qd, qdd, tau;
  std::vector<Force<double>> fext;
  States(Index nv_, Index B_, unsigned seed) : nv(nv_), B(B_) {
    std::vector<double> u;
    test::random_exact_batch<float>(nv, B, seed, q, qd, qdd, fext);
    std::vector<Force<double>> unused;
    test::random_exact_batch<float>(nv, B, seed + 1, u, u, tau, unused);
  }
};

// [qdd, tau] of every instance by the serial hybrid_dynamics in S (aos, 2 nv per instance)
template <class S>
std::vector<double> reference(const Model& md, const std::vector<unsigned char>& mask, const States& s, bool fx) {
  const ModelTpl<S> m = md.cast<S>();
  DataTpl<S> d(m, false);
  const std::size_t n = static_cast<std::size_t>(s.nv);
  std::vector<double> out(2 * n * s.B);
  std::vector<S> q(n), qd(n), qdd(n), tau(n), oq(n), ot(n);
  std::vector<Force<S>> f(n);
  for (Index b = 0; b < s.B; ++b) {
    for (std::size_t i = 0; i < n; ++i) {
      q[i] = S(s.q[b * n + i]), qd[i] = S(s.qd[b * n + i]), qdd[i] = S(s.qdd[b * n + i]), tau[i] = S(s.tau[b * n + i]);
      f[i] = s.fext[b * n + i].cast<S>();
    }
    EXPECT_TRUE(hybrid_dynamics(m, d, q.data(), qd.data(), mask.data(), qdd.data(), tau.data(), oq.data(), ot.data(),
                                fx ? f.data() : nullptr)
                    .ok());
    for (std::size_t i = 0; i < n; ++i) out[2 * n * b + i] = oq[i], out[2 * n * b + n + i] = ot[i];
  }
  return out;
}

double worst_err(const std::vector<double>& x, const std::vector<double>& ref, Index nv, Index B) {
  double worst = 0;
  const std::size_t w = 2 * static_cast<std::size_t>(nv);
  for (Index b = 0; b < B; ++b) {
    double e = 0, s = 1;
    for (std::size_t j = 0; j < w; ++j) {
      e = std::max(e, std::fabs(x[b * w + j] - ref[b * w + j]));
      s = std::max(s, std::fabs(ref[b * w + j]));
      if (std::isnan(x[b * w + j])) return std::numeric_limits<double>::quiet_NaN();
    }
    worst = std::max(worst, e / s);
  }
  return worst;
}

// hybrid_instance<S, C, kKeepXup, kUnrolled, Library, kSlots (-1: C)> on the host
template <class S, bool kKeepXup, bool kUnrolled, int kSlots = -1>
std::vector<double> host_run(const Model& md, const std::vector<unsigned char>& mask, const States& s, bool fx) {
  const ModelTpl<S> m = md.cast<S>();
  const cuda::ThreadModel<S> tm(m);
  const unsigned long long bits = cuda::prescribed_bits(mask);
  const std::size_t n = static_cast<std::size_t>(s.nv);
  std::vector<double> out(2 * n * s.B);
  std::vector<S> q(n), qd(n), qdd(n), tau(n), oq(n), ot(n);
  std::vector<Force<S>> f(n);
  for (Index b = 0; b < s.B; ++b) {
    for (std::size_t i = 0; i < n; ++i) {
      q[i] = S(s.q[b * n + i]), qd[i] = S(s.qd[b * n + i]), qdd[i] = S(s.qdd[b * n + i]), tau[i] = S(s.tau[b * n + i]);
      f[i] = s.fext[b * n + i].cast<S>();
    }
    std::fill(oq.begin(), oq.end(), std::numeric_limits<S>::quiet_NaN());
    std::fill(ot.begin(), ot.end(), std::numeric_limits<S>::quiet_NaN());
    const Index failed = std::visit(
        [&](const auto& p) {
          using P = std::decay_t<decltype(p)>;
          constexpr int C = P::capacity;
          const cuda::HybridColumns<S> hd{bits, {qdd.data(), 1}, {ot.data(), 1}};
          return cuda::hybrid_instance<S, C, kKeepXup, kUnrolled, Trig::Library, (kSlots < 0 ? C : kSlots)>(
              p, {q.data(), 1}, {qd.data(), 1}, {tau.data(), 1}, fx ? f.data() : nullptr, {oq.data(), 1}, hd);
        },
        tm.params());
    EXPECT_EQ(failed, -1);
    for (std::size_t i = 0; i < n; ++i) out[2 * n * b + i] = oq[i], out[2 * n * b + n + i] = ot[i];
  }
  return out;
}

}  // namespace

TEST(CudaHybridHost, DeviceFunctionOnTheHostEqualsReference) {
  std::mt19937_64 g(4);
  for (const auto& [name, md] : models()) {
    SCOPED_TRACE(name);
    const Index B = 6;
    const States s(md.nv(), B, 31);
    const bool chains = cuda::ThreadModel<double>(md).branch_slots() == 0;
    for (bool fx : {false, true}) {
      const auto mask = random_mask(g, md.nv());
      const auto ref = reference<double>(md, mask, s, fx);
      EXPECT_LE(worst_err(host_run<double, false, false>(md, mask, s, fx), ref, md.nv(), B), 1e-12);
      EXPECT_LE(worst_err(host_run<double, true, false>(md, mask, s, fx), ref, md.nv(), B), 1e-12);
      EXPECT_LE(worst_err(host_run<double, false, true>(md, mask, s, fx), ref, md.nv(), B), 1e-12);
      if (chains) EXPECT_LE(worst_err(host_run<double, false, false, 0>(md, mask, s, fx), ref, md.nv(), B), 1e-12);
      const double ftol = std::max(1e-4, 10 * worst_err(reference<float>(md, mask, s, fx), ref, md.nv(), B));
      EXPECT_LE(worst_err(host_run<float, false, false>(md, mask, s, fx), ref, md.nv(), B), ftol);
      if (cuda::ThreadModel<double>(md).branch_slots() <= cuda::kAbaRegisterSlots)  // (the variant's limit)
        EXPECT_LE(
            worst_err(host_run<float, false, false, int(cuda::kAbaRegisterSlots)>(md, mask, s, fx), ref, md.nv(), B),
            ftol);
    }
    // none prescribed: aba's qdd; all prescribed: rnea's tau
    const std::vector<unsigned char> none(md.nv(), 0), all(md.nv(), 1);
    for (const auto* mask : {&none, &all})
      EXPECT_LE(worst_err(host_run<double, false, false>(md, *mask, s, false), reference<double>(md, *mask, s, false),
                          md.nv(), B),
                1e-12);
  }
}

// ---- on the device --------------------------------------------------------------

class CudaHybridDevice : public ::testing::Test {
 protected:
  void SetUp() override {
    const std::string why = test::no_device_reason();
    if (!why.empty()) GTEST_SKIP() << "no usable CUDA device: " << why;
  }
};

template <class S>
void check_engine(const Model& md, const std::vector<unsigned char>& mask, bool soa, bool fx, double tol_double) {
  const ModelTpl<S> m = md.cast<S>();
  const Index nv = m.nv(), B = 1000;
  const std::size_t n = static_cast<std::size_t>(nv);
  const States s(nv, B, 77);
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  auto e = make_hybrid_dynamics(m, mask, o);
  EXPECT_EQ(e->strategy(), "aba_thread");
  auto lay = [&](const std::vector<double>& v) {
    std::vector<S> t(v.size());
    for (Index b = 0; b < B; ++b)
      for (std::size_t i = 0; i < n; ++i) t[soa ? i * B + b : b * n + i] = S(v[b * n + i]);
    return t;
  };
  const auto Q = lay(s.q), QD = lay(s.qd), QI = lay(s.qdd), TI = lay(s.tau);
  std::vector<Force<S>> F(s.fext.size());
  for (std::size_t k = 0; k < F.size(); ++k) F[k] = s.fext[k].cast<S>();
  std::vector<S> QO(n * B, std::numeric_limits<S>::quiet_NaN()), TO(QO);
  using V = BatchView<const S>;
  auto view = [&](const std::vector<S>& v) { return soa ? V::soa(v.data(), nv, B) : V::aos(v.data(), nv, B); };
  auto out = [&](std::vector<S>& v) { return soa ? BatchView<S>::soa(v.data(), nv, B) : BatchView<S>::aos(v.data(), nv, B); };
  const BatchStatus st = e->compute({view(Q), view(QD), view(QI), view(TI), fx ? F.data() : nullptr}, out(QO), out(TO));
  ASSERT_TRUE(st.ok()) << st.message();
  std::vector<double> got(2 * n * B);
  for (Index b = 0; b < B; ++b)
    for (std::size_t i = 0; i < n; ++i) {
      const std::size_t k = soa ? i * B + b : b * n + i;
      got[2 * n * b + i] = QO[k], got[2 * n * b + n + i] = TO[k];
    }
  const auto ref = reference<double>(md, mask, s, fx);
  const double tol =
      std::is_same<S, double>::value ? tol_double : std::max(1e-4, 10 * worst_err(reference<float>(md, mask, s, fx), ref, nv, B));
  EXPECT_LE(worst_err(got, ref, nv, B), tol);
  for (Index b = 0; b < B; ++b)
    for (std::size_t i = 0; i < n; ++i) {
      if (mask[i]) EXPECT_EQ(got[2 * n * b + i], double(S(s.qdd[b * n + i])));
      else EXPECT_EQ(got[2 * n * b + n + i], double(S(s.tau[b * n + i])));
    }
}

TEST_F(CudaHybridDevice, EngineMatchesSerial) {
  std::mt19937_64 g(9);
  for (const auto& [name, md] : models()) {
    SCOPED_TRACE(name);
    const auto mask = random_mask(g, md.nv());
    for (bool soa : {true, false}) {
      check_engine<double>(md, mask, soa, soa, 1e-9);
      check_engine<float>(md, mask, soa, !soa, 0);
    }
  }
}

TEST_F(CudaHybridDevice, FailedInstanceLeavesOutputs) {
  Model md = load_model("chain:3");
  md.bodies[2].I = Inertia<double>{};
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 2;
  auto e = make_hybrid_dynamics(md, std::vector<unsigned char>{1, 0, 0}, o);
  std::vector<double> q(6, 0.3), qd(6, 0.1), qi(6, 1.0), ti(6, 0.5), qo(6, -1), to(6, -1);
  using V = BatchView<const double>;
  const BatchStatus st = e->compute({V::aos(q.data(), 3, 2), V::aos(qd.data(), 3, 2), V::aos(qi.data(), 3, 2),
                                     V::aos(ti.data(), 3, 2)},
                                    BatchView<double>::aos(qo.data(), 3, 2), BatchView<double>::aos(to.data(), 3, 2));
  EXPECT_EQ(st.failed, 2);
  EXPECT_EQ(st.first_dof, 2);
  for (double x : qo) EXPECT_EQ(x, -1);
  for (double x : to) EXPECT_EQ(x, -1);
}

// Beyond 64 DoF the thread kernels refuse: an unbranched chain takes the chain scans
// instead (strategy "parallel", tests/cuda/test_cuda_chain_hybrid.cu), fd_method aba
// and a branched tree are refused.
TEST_F(CudaHybridDevice, TooManyDofsIsRefused) {
  const Model md = load_model("chain:65");
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  EXPECT_EQ(make_hybrid_dynamics(md, std::vector<unsigned char>(65, 0), o)->strategy(), "parallel");
  const Model tree = load_model("tree:80:1");
  EXPECT_THROW(make_hybrid_dynamics(tree, std::vector<unsigned char>(tree.nv(), 0), o), BackendError);
  o.fd_method = FdMethod::Aba;
  EXPECT_THROW(make_hybrid_dynamics(md, std::vector<unsigned char>(65, 0), o), BackendError);
}
