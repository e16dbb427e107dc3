// The CUDA engines' two host paths (SCANDYN_HOST_STAGING, read at construction):
// the pinned chunked pipeline (kernels/host_pipeline.hpp) against the pageable
// copies (kernels/staging.hpp) bit for bit, and both against the serial engine to a
// tolerance, for CudaInverseDynamics (thread) and CudaForwardDynamics (jsi_thread,
// aba_thread, the device check on): batches that are not a multiple of the chunk
// (1, chunk - 1, chunk + 1, 3.5 chunks, with SCANDYN_HOST_CHUNK_INSTANCES=64, and
// ~2.7 default chunks), strided host views (padded, negative strides, interleaved,
// a broadcast input; output gaps hold a sentinel that must survive), with and
// without fext; the pinned ring reused by a second call; a refused view leaves the
// engine usable. Tests that need a device skip with "no CUDA device: ...".
#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <cmath>
#include <cstdlib>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "cuda_test_util.hpp"
#include "floating_models.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"
#include "scandyn/engine.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

using test::Layout;
using test::make_layout;

constexpr Index kChunk = 64;  // SCANDYN_HOST_CHUNK_INSTANCES of the small cases
constexpr double kSentinel = 12345.0;

// Sets an environment variable for a scope, restoring it after.
class ScopedEnv {
 public:
  ScopedEnv(const char* name, const char* value) : name_(name) {
    const char* old = std::getenv(name);
    had_ = old != nullptr;
    if (had_) old_ = old;
    if (value) setenv(name, value, 1);
    else unsetenv(name);
  }
  ~ScopedEnv() {
    if (had_) setenv(name_.c_str(), old_.c_str(), 1);
    else unsetenv(name_.c_str());
  }

 private:
  std::string name_, old_;
  bool had_ = false;
};

// An engine made under SCANDYN_HOST_STAGING=mode (and the chunk, when given).
template <class E, class... A>
std::unique_ptr<E> make_engine(const char* mode, const char* chunk, const A&... args) {
  ScopedEnv m("SCANDYN_HOST_STAGING", mode);
  ScopedEnv c("SCANDYN_HOST_CHUNK_INSTANCES", chunk);
  return std::make_unique<E>(args...);
}

// The layouts of the inputs (three arrays of widths w[k]) and the output of case c.
struct Layouts {
  Layout in[3];
  Layout out;
  std::string name() const { return in[0].name + "/" + in[1].name + "/" + in[2].name + "->" + out.name; }
};
Layouts layouts(int c, const Index (&w)[3], Index nv, Index B) {
  Layouts L;
  switch (c % 4) {
    case 0:  // the command's: aos, dense
      for (int k = 0; k < 3; ++k) L.in[k] = make_layout("aos", w[k], B, 1, w[k]);
      L.out = make_layout("aos", nv, B, 1, nv);
      break;
    case 1:  // soa padded, negative strides
      for (int k = 0; k < 3; ++k) L.in[k] = make_layout("soa-neg", w[k], B, -(B + 3), -1);
      L.out = make_layout("soa+2", nv, B, B + 2, 1);
      break;
    case 2:  // both strides > 1: interleaved
      for (int k = 0; k < 3; ++k) L.in[k] = make_layout("interleaved", w[k], B, 2, -2 * (w[k] + 1));
      L.out = make_layout("soa-interleaved", nv, B, 2 * B, 2);
      break;
    default:  // aos padded backwards, soa, a broadcast third input; aos padded out
      L.in[0] = make_layout("aos-neg+2", w[0], B, 1, -(w[0] + 2));
      L.in[1] = make_layout("soa", w[1], B, B, 1);
      L.in[2] = make_layout("broadcast", w[2], B, 1, 0);
      L.out = make_layout("aos+1", nv, B, 1, nv + 1);
      break;
  }
  return L;
}

// Random inputs of B instances (widths w, soa, exactly representable in S), laid
// out in buffers of the case's layouts, and wrenches.
template <class S>
struct Inputs {
  std::vector<S> buf[3];
  std::vector<Force<S>> fext;
  Inputs(const Index (&w)[3], Index B, Index nbodies, const Layouts& L, unsigned seed) {
    std::mt19937_64 g(seed);
    std::uniform_real_distribution<double> u(-2.0, 2.0);
    for (int k = 0; k < 3; ++k) {
      std::vector<double> v(static_cast<std::size_t>(w[k]) * B);
      for (double& x : v) x = double(S(u(g)));
      buf[k] = test::pack<S>(v, w[k], B, L.in[k], kSentinel);
    }
    fext.resize(static_cast<std::size_t>(B) * nbodies);
    for (auto& f : fext) {
      auto r = [&] { return S(0.5 * u(g)); };
      f.n = {r(), r(), r()};
      f.f = {r(), r(), r()};
    }
  }
  BatchView<const S> view(int k, const Layout& l, Index B) const { return {buf[k].data() + l.base, B, l.ds, l.bs}; }
  // array k of instance b as a dense column
  std::vector<S> column(int k, const Layout& l, Index w, Index b) const {
    std::vector<S> c(w);
    for (Index i = 0; i < w; ++i) c[i] = buf[k][l.at(i, b)];
    return c;
  }
};

template <class S>
double tolerance() {
  return sizeof(S) == 4 ? 1e-4 : 1e-9;
}

// max over instances of max |x - ref| / max(1, max |ref|)
template <class S>
double worst(const std::vector<S>& out, const Layout& l, const std::vector<S>& ref_soa, Index nv, Index B) {
  double w = 0;
  for (Index b = 0; b < B; ++b) {
    double scale = 1, e = 0;
    for (Index i = 0; i < nv; ++i) scale = std::max(scale, std::abs(double(ref_soa[static_cast<std::size_t>(i) * B + b])));
    for (Index i = 0; i < nv; ++i)
      e = std::max(e, std::abs(double(out[l.at(i, b)]) - double(ref_soa[static_cast<std::size_t>(i) * B + b])));
    if (!(e / scale <= w)) w = e / scale;  // NaN sticks
  }
  return w;
}

// The serial engine's outputs (soa) on the same inputs, gathered into dense soa.
template <class S, class Run>
std::vector<S> serial_soa(const Inputs<S>& in, const Layouts& L, const Index (&w)[3], Index nv, Index B,
                          Run&& run) {
  std::vector<S> dense[3];
  for (int k = 0; k < 3; ++k) {
    dense[k].resize(static_cast<std::size_t>(w[k]) * B);
    for (Index b = 0; b < B; ++b)
      for (Index i = 0; i < w[k]; ++i) dense[k][static_cast<std::size_t>(i) * B + b] = in.buf[k][L.in[k].at(i, b)];
  }
  std::vector<S> out(static_cast<std::size_t>(nv) * B, S(kSentinel));
  run(dense, out);
  return out;
}

const Model& iiwa() {
  static const Model m = test::load_robot("iiwa.urdf");
  return m;
}

// ---- inverse dynamics -----------------------------------------------------------

template <class S>
void check_id(const Model& md, bool against_serial) {
  const ModelTpl<S> ms = md.template cast<S>();
  const Index nv = md.nv(), nq = md.nq(), nb = md.nbodies();
  const Index w[3] = {nq, nv, nv};
  const Index Bmax = kChunk * 7 / 2;
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.strategy = IdStrategy::Recursion;
  o.max_batch = Bmax;
  const std::string chunk = std::to_string(kChunk);
  auto pinned = make_engine<cuda::CudaInverseDynamics<S>>("pinned", chunk.c_str(), ms, o);
  auto pageable = make_engine<cuda::CudaInverseDynamics<S>>("pageable", nullptr, ms, o);
  ASSERT_EQ(pinned->host_staging(), "pinned");
  ASSERT_EQ(pageable->host_staging(), "pageable");
  BackendOptions so;
  so.max_batch = Bmax;
  auto serial = make_inverse_dynamics<S>(ms, so);
  int c = 0;
  for (Index B : {Index(1), kChunk - 1, kChunk + 1, Bmax})
    for (bool fx : {false, true}) {
      const Layouts L = layouts(c++, w, nv, B);
      SCOPED_TRACE(md.name + " B=" + std::to_string(B) + (fx ? " fext " : " ") + L.name());
      const Inputs<S> in(w, B, nb, L, 17 + c);
      const IdBatchIn<S> bin{in.view(0, L.in[0], B), in.view(1, L.in[1], B), in.view(2, L.in[2], B),
                             fx ? in.fext.data() : nullptr};
      std::vector<S> a(L.out.size, S(kSentinel)), b(L.out.size, S(kSentinel));
      pinned->compute(bin, {a.data() + L.out.base, B, L.out.ds, L.out.bs});
      pageable->compute(bin, {b.data() + L.out.base, B, L.out.ds, L.out.bs});
      ASSERT_EQ(0, std::memcmp(a.data(), b.data(), a.size() * sizeof(S))) << "pinned and pageable differ";
      for (std::size_t k = 0; k < a.size(); ++k)
        if (a[k] == S(kSentinel)) continue;
        else ASSERT_TRUE(std::isfinite(double(a[k]))) << "entry " << k;
      if (!against_serial) continue;
      const std::vector<S> ref = serial_soa<S>(in, L, w, nv, B, [&](std::vector<S>(&d)[3], std::vector<S>& out) {
        using V = BatchView<const S>;
        serial->compute(IdBatchIn<S>{V::soa(d[0].data(), nq, B), V::soa(d[1].data(), nv, B),
                                     V::soa(d[2].data(), nv, B), fx ? in.fext.data() : nullptr},
                        BatchView<S>::soa(out.data(), nv, B));
      });
      EXPECT_LE(worst(a, L.out, ref, nv, B), tolerance<S>());
    }
  // the ring is sized at the first call for full chunks (without fext: B = 1 first)
  // and grown once by the first call with fext; no later call allocates
  EXPECT_EQ(pinned->host_ring_allocations(), 2) << "the first call, and the first with fext";
  EXPECT_GT(pinned->host_ring_bytes(), 0u);
  EXPECT_EQ(pageable->host_ring_allocations(), 0);
}

TEST(CudaHostStaging, InverseDynamicsPinnedMatchesPageableAndSerial) {
  SKIP_WITHOUT_CUDA_DEVICE();
  check_id<double>(iiwa(), true);
  check_id<float>(iiwa(), true);
  check_id<double>(test::load_robot("hyq.urdf"), true);
}

TEST(CudaHostStaging, InverseDynamicsFloatingBasePinnedMatchesPageable) {
  SKIP_WITHOUT_CUDA_DEVICE();
  // nq = nv + 1 and fext over nbodies != nv (serial comparison elsewhere: the
  // random quaternions here are not normalised)
  // 10 joints past the base: within the floating-base kernels of every build (those
  // without the effect sets compile 9 to 16 of them only)
  const Model m = test::random_free_chain(11, 3);
  check_id<float>(m, false);
  check_id<double>(m, false);
}

TEST(CudaHostStaging, InverseDynamicsRingReusedAndDefaultChunk) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const ModelTpl<float> ms = iiwa().cast<float>();
  const Index nv = ms.nv();
  const Index w[3] = {nv, nv, nv};
  // ~2.7 default chunks with fext (16 MiB / 280 bytes per instance: 59918)
  const Index B = 160000;
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  auto pinned = make_engine<cuda::CudaInverseDynamics<float>>("pinned", nullptr, ms, o);
  auto pageable = make_engine<cuda::CudaInverseDynamics<float>>("pageable", nullptr, ms, o);
  ASSERT_EQ(pinned->strategy(), "thread");
  ASSERT_EQ(pinned->host_ring_allocations(), 0) << "nothing allocated before the first call";
  const Layouts L = layouts(0, w, nv, B);
  const Inputs<float> in(w, B, nv, L, 5);
  const IdBatchIn<float> bin{in.view(0, L.in[0], B), in.view(1, L.in[1], B), in.view(2, L.in[2], B), in.fext.data()};
  std::vector<float> a(L.out.size, float(kSentinel)), a2(L.out.size, float(kSentinel)), b(L.out.size);
  const BatchView<float> va{a.data(), B, 1, nv};
  pinned->compute(bin, va);
  EXPECT_EQ(pinned->host_ring_allocations(), 1);
  const std::size_t bytes = pinned->host_ring_bytes();
  EXPECT_GT(bytes, 0u);
  EXPECT_LE(bytes, 3 * ((std::size_t(16) << 20) + 5 * 256)) << "three slots of about 16 MiB";
  pinned->compute(bin, {a2.data(), B, 1, nv});  // the second call reuses the ring
  EXPECT_EQ(pinned->host_ring_allocations(), 1);
  EXPECT_EQ(pinned->host_ring_bytes(), bytes);
  pageable->compute(bin, {b.data(), B, 1, nv});
  EXPECT_EQ(0, std::memcmp(a.data(), b.data(), a.size() * sizeof(float)));
  EXPECT_EQ(0, std::memcmp(a2.data(), b.data(), a.size() * sizeof(float)));
  // a smaller batch and one without fext: still the same ring
  pinned->compute(IdBatchIn<float>{bin.q, bin.qd, bin.qdd, nullptr}, va);
  pinned->compute(IdBatchIn<float>{{bin.q.data, 1, 1, nv}, {bin.qd.data, 1, 1, nv}, {bin.qdd.data, 1, 1, nv}, nullptr},
                  {a.data(), 1, 1, nv});
  EXPECT_EQ(pinned->host_ring_allocations(), 1);
}

TEST(CudaHostStaging, InverseDynamicsRefusedViewLeavesEngineUsable) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const ModelTpl<double> ms = iiwa();
  const Index nv = ms.nv(), B = 100;
  const Index w[3] = {nv, nv, nv};
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  auto pinned = make_engine<cuda::CudaInverseDynamics<double>>("pinned", "16", ms, o);
  auto pageable = make_engine<cuda::CudaInverseDynamics<double>>("pageable", nullptr, ms, o);
  const Layouts L = layouts(1, w, nv, B);
  const Inputs<double> in(w, B, nv, L, 9);
  const IdBatchIn<double> bin{in.view(0, L.in[0], B), in.view(1, L.in[1], B), in.view(2, L.in[2], B), nullptr};
  std::vector<double> a(L.out.size, kSentinel), b(L.out.size, kSentinel);
  EXPECT_THROW(pinned->compute(bin, {a.data(), B, 0, 1}), BackendError);  // tau's entries overlap
  EXPECT_THROW(pinned->compute(bin, {a.data(), B, nv, 0}), BackendError);
  std::fill(a.begin(), a.end(), kSentinel);
  pinned->compute(bin, {a.data() + L.out.base, B, L.out.ds, L.out.bs});
  pageable->compute(bin, {b.data() + L.out.base, B, L.out.ds, L.out.bs});
  EXPECT_EQ(0, std::memcmp(a.data(), b.data(), a.size() * sizeof(double)));
}

TEST(CudaHostStaging, BadSwitchesAreBackendErrors) {
  SKIP_WITHOUT_CUDA_DEVICE();
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 4;
  EXPECT_THROW((make_engine<cuda::CudaInverseDynamics<double>>("pinnned", nullptr, iiwa(), o)), BackendError);
  EXPECT_THROW((make_engine<cuda::CudaInverseDynamics<double>>("pinned", "0", iiwa(), o)), BackendError);
  EXPECT_THROW((make_engine<cuda::CudaForwardDynamics<double>>("pinned", "many", iiwa(), o)), BackendError);
  // the scan strategy keeps the pageable path
  o.strategy = IdStrategy::ScanLocal;
  EXPECT_EQ((make_engine<cuda::CudaInverseDynamics<double>>("pinned", nullptr, iiwa(), o))->host_staging(),
            "pageable");
}

// ---- forward dynamics -----------------------------------------------------------

template <class S>
void check_fd(FdMethod method, FdCheckMode check_mode, bool against_serial) {
  const Model& md = iiwa();
  const ModelTpl<S> ms = md.template cast<S>();
  const Index nv = md.nv();
  const Index w[3] = {nv, nv, nv};
  const Index Bmax = kChunk * 7 / 2;
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.fd_method = method;
  o.fd_check = check_mode;
  o.max_batch = Bmax;
  const std::string chunk = std::to_string(kChunk);
  auto pinned = make_engine<cuda::CudaForwardDynamics<S>>("pinned", chunk.c_str(), ms, o);
  auto pageable = make_engine<cuda::CudaForwardDynamics<S>>("pageable", nullptr, ms, o);
  ASSERT_EQ(pinned->host_staging(), "pinned") << pinned->strategy();
  BackendOptions so;
  so.fd_method = method;
  so.max_batch = Bmax;
  auto serial = make_forward_dynamics<S>(ms, so);
  int c = 0;
  for (Index B : {Index(1), kChunk - 1, kChunk + 1, Bmax})
    for (bool fx : {false, true}) {
      const Layouts L = layouts(c++, w, nv, B);
      SCOPED_TRACE(pinned->strategy() + " B=" + std::to_string(B) + (fx ? " fext " : " ") + L.name());
      const Inputs<S> in(w, B, nv, L, 31 + c);
      const FdBatchIn<S> bin{in.view(0, L.in[0], B), in.view(1, L.in[1], B), in.view(2, L.in[2], B),
                             fx ? in.fext.data() : nullptr};
      std::vector<S> a(L.out.size, S(kSentinel)), b(L.out.size, S(kSentinel));
      std::vector<int> fa(B, -7), fb(B, -7);
      const BatchStatus sa = pinned->compute(bin, {a.data() + L.out.base, B, L.out.ds, L.out.bs}, fa.data());
      std::vector<double> ea, eb;
      auto estimates = [&](const cuda::CudaForwardDynamics<S>& e, std::vector<double>& out) {
        if (!e.device_estimates()) return;
        out.resize(B);
        ASSERT_CUDA(cudaMemcpy(out.data(), e.device_estimates(), B * sizeof(double), cudaMemcpyDeviceToHost));
      };
      estimates(*pinned, ea);
      const BatchStatus sb = pageable->compute(bin, {b.data() + L.out.base, B, L.out.ds, L.out.bs}, fb.data());
      estimates(*pageable, eb);
      ASSERT_EQ(0, std::memcmp(a.data(), b.data(), a.size() * sizeof(S))) << "pinned and pageable differ";
      EXPECT_EQ(fa, fb);
      EXPECT_EQ(ea, eb);
      EXPECT_EQ(sa.failed, sb.failed);
      EXPECT_EQ(sa.ok(), sb.ok());
      if (!against_serial) continue;
      const std::vector<S> ref = serial_soa<S>(in, L, w, nv, B, [&](std::vector<S>(&d)[3], std::vector<S>& out) {
        using V = BatchView<const S>;
        serial->compute(FdBatchIn<S>{V::soa(d[0].data(), nv, B), V::soa(d[1].data(), nv, B),
                                     V::soa(d[2].data(), nv, B), fx ? in.fext.data() : nullptr},
                        BatchView<S>::soa(out.data(), nv, B));
      });
      EXPECT_LE(worst(a, L.out, ref, nv, B), 1e-7);
    }
  EXPECT_EQ(pinned->host_ring_allocations(), 2) << "the first call, and the first with fext";
}

TEST(CudaHostStaging, ForwardDynamicsPinnedMatchesPageable) {
  SKIP_WITHOUT_CUDA_DEVICE();
  check_fd<double>(FdMethod::Jsi, FdCheckMode::Auto, true);
  check_fd<double>(FdMethod::Aba, FdCheckMode::Auto, true);
  check_fd<float>(FdMethod::Jsi, FdCheckMode::Auto, false);
  check_fd<float>(FdMethod::Aba, FdCheckMode::Auto, false);
  // the device check's estimates travel with each chunk
  check_fd<float>(FdMethod::Jsi, FdCheckMode::On, false);
  check_fd<double>(FdMethod::Aba, FdCheckMode::On, false);
}

}  // namespace
