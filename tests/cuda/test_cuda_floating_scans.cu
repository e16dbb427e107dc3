// The CUDA link scans with multi-DoF joints (IdScanPlan: a floating base, spherical
// joints) and the CUDA parallel chain forward dynamics of a free rope (ChainFdPlan),
// on device buffers, against the serial reference's general path (rnea_at, aba_at
// through rnea and aba) in double. Tests that need a device skip with the reason.
#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>
#include <string>
#include <vector>

#include "cuda_test_util.hpp"
#include "floating_models.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/cuda/chain_fd.hpp"
#include "scandyn/cuda/id_scan.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

using test::random_soa_states;
using States = test::SoaStates;

template <class T>
T* to_device(test::DeviceArray<T>& d, const std::vector<T>& h) {
  EXPECT_EQ(d.alloc(h.size()), cudaSuccess);
  if (!h.empty()) EXPECT_EQ(cudaMemcpy(d.ptr, h.data(), h.size() * sizeof(T), cudaMemcpyHostToDevice), cudaSuccess);
  return d.ptr;
}

// The device result (inverse dynamics by IdScanPlan, or forward dynamics by
// ChainFdPlan) in precision S against the double reference; failed: the chain's
// failed DoFs (forward dynamics), checked to be -1.
template <class S>
double device_error(const Model& model, const States& x, bool forward, Index chunk = 0) {
  const ModelTpl<S> m = model.cast<S>();
  const auto ref = test::soa_reference(model, x, forward);
  const auto q = test::cast_vector<S>(x.q), qd = test::cast_vector<S>(x.qd), u = test::cast_vector<S>(x.u);
  std::vector<Force<S>> fext;
  for (const auto& f : x.fext) fext.push_back(f.template cast<S>());
  test::DeviceArray<S> dq, dqd, du, dout;
  test::DeviceArray<Force<S>> df;
  test::DeviceArray<int> dfailed;
  using V = BatchView<const S>;
  const V vq = V::soa(to_device(dq, q), x.nq, x.B), vqd = V::soa(to_device(dqd, qd), x.nv, x.B),
          vu = V::soa(to_device(du, u), x.nv, x.B);
  const Force<S>* f = fext.empty() ? nullptr : to_device(df, fext);
  std::vector<S> out(x.qd.size(), S(NAN));
  const BatchView<S> vout = BatchView<S>::soa(to_device(dout, out), x.nv, x.B);
  if (forward) {
    cuda::ChainFdPlan<S> plan(m, x.B, chunk);
    EXPECT_EQ(dfailed.alloc(static_cast<std::size_t>(x.B)), cudaSuccess);
    EXPECT_EQ(plan.launch(FdBatchIn<S>{vq, vqd, vu, f}, vout, dfailed.ptr, nullptr), cudaSuccess);
    std::vector<int> failed(static_cast<std::size_t>(x.B), 9);
    EXPECT_EQ(cudaMemcpy(failed.data(), dfailed.ptr, failed.size() * sizeof(int), cudaMemcpyDeviceToHost), cudaSuccess);
    for (int k : failed) EXPECT_EQ(k, -1);
  } else {
    cuda::IdScanPlan<S> plan(m, x.B);
    EXPECT_EQ(plan.launch(IdBatchIn<S>{vq, vqd, vu, f}, vout, nullptr), cudaSuccess);
  }
  EXPECT_EQ(cudaDeviceSynchronize(), cudaSuccess);
  EXPECT_EQ(cudaMemcpy(out.data(), dout.ptr, out.size() * sizeof(S), cudaMemcpyDeviceToHost), cudaSuccess);
  return test::max_rel_err(out, ref);
}

// The serial float recursion's own error against the double reference on the same
// inputs (rnea or aba of the float model, instance by instance).
double serial_float_error(const Model& model, const States& x, bool forward) {
  const auto ref = test::soa_reference(model, x, forward);
  const ModelTpl<float> m = model.cast<float>();
  DataTpl<float> data(m, false);
  std::vector<float> out(x.qd.size()), qi(x.nq), qdi(x.nv), ui(x.nv), oi(x.nv);
  std::vector<Force<float>> fi(static_cast<std::size_t>(x.nb));
  for (Index b = 0; b < x.B; ++b) {
    for (Index i = 0; i < x.nq; ++i) qi[i] = float(x.q[i * x.B + b]);
    for (Index i = 0; i < x.nv; ++i) qdi[i] = float(x.qd[i * x.B + b]), ui[i] = float(x.u[i * x.B + b]);
    for (Index i = 0; !x.fext.empty() && i < x.nb; ++i) fi[i] = x.fext[b * x.nb + i].cast<float>();
    const Force<float>* f = x.fext.empty() ? nullptr : fi.data();
    if (forward) EXPECT_TRUE(aba(m, data, qi.data(), qdi.data(), ui.data(), oi.data(), f).ok());
    else rnea(m, data, qi.data(), qdi.data(), ui.data(), oi.data(), f);
    for (Index i = 0; i < x.nv; ++i) out[i * x.B + b] = oi[i];
  }
  return test::max_rel_err(out, ref);
}

// Float tolerance: within 10x of the serial float recursion on the same inputs, and
// never below 1e-4 (as test_cuda_id.cu's scan_float_tol).
double float_tol(const Model& model, const States& x, bool forward) {
  return std::max(1e-4, 10 * serial_float_error(model, x, forward));
}

}  // namespace

// Tolerances: double 1e-10 (inverse dynamics), 1e-9 (forward dynamics), as for the
// fixed-base models (test_cuda_id.cu, test_cuda_chain_fd.cu); float: float_tol.

TEST(CudaFloatingIdScan, FloatingTreesBallRopesAndRobots) {
  SKIP_WITHOUT_CUDA_DEVICE();
  std::vector<Model> models = {test::load_floating("rope:1"),   test::load_floating("rope:200"),
                               load_model("ballrope:100"),      test::load_floating("ballrope:100"),
                               test::load_floating("hyq"),      test::load_floating("atlas"),
                               test::load_floating("tree:300:5"), test::random_floating_model(60, 3),
                               test::random_floating_model(400, 8)};
  for (const Model& m : models)
    for (Index B : {1, 33, 300}) {
      SCOPED_TRACE(m.name + " B=" + std::to_string(B));
      const States x = random_soa_states(m, B, 5 + static_cast<unsigned>(B), B == 33);
      EXPECT_LE(device_error<double>(m, x, false), 1e-10);
      EXPECT_LE(device_error<float>(m, x, false), float_tol(m, x, false));
    }
}

// Equal links share one entry of the device body table whatever their rows in q and
// qd: a rope's links are three classes (the first, at the origin; then axes y and x
// in turn), a free rope's three (the base; y, x).
TEST(CudaFloatingIdScan, EqualLinksShareOneBodyClass) {
  SKIP_WITHOUT_CUDA_DEVICE();
  EXPECT_EQ(cuda::IdScanPlan<double>(load_model("rope:1000"), 1).body_classes(), 3);
  EXPECT_EQ(cuda::IdScanPlan<float>(test::load_floating("rope:1000").cast<float>(), 1).body_classes(), 3);
}

TEST(CudaFloatingIdScan, LongFreeRopes) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (const char* spec : {"rope:10000", "rope:100000"}) {
    const Model m = test::load_floating(spec);
    SCOPED_TRACE(spec);
    const States x = random_soa_states(m, 1, 3, true);
    EXPECT_LE(device_error<double>(m, x, false), 1e-10);
    EXPECT_LE(device_error<float>(m, x, false), float_tol(m, x, false));
  }
}

TEST(CudaFloatingChainFd, RandomFreeChainsAndFreeBodies) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (unsigned seed : {1u, 2u}) {
    const Model m = test::random_free_chain(41, seed);
    for (Index chunk : {1, 3, 8, 64}) {  // chunks across instances, the base inside a chunk
      SCOPED_TRACE("seed " + std::to_string(seed) + " chunk " + std::to_string(chunk));
      EXPECT_LE(device_error<double>(m, random_soa_states(m, 5, seed, chunk % 2 == 1), true, chunk), 1e-9);
    }
    const States x = random_soa_states(m, 5, seed, true);
    EXPECT_LE(device_error<float>(m, x, true), float_tol(m, x, true));
  }
  for (int n : {1, 2, 3}) {
    const Model m = test::random_free_chain(n, 60 + n);
    SCOPED_TRACE("free chain of " + std::to_string(n));
    EXPECT_LE(device_error<double>(m, random_soa_states(m, 100, 4, true), true, 2), 1e-10);
  }
}

TEST(CudaFloatingChainFd, FreeRopes) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (const auto& [spec, B] : std::vector<std::pair<std::string, Index>>{
           {"rope:10", 1000}, {"rope:1000", 10}, {"rope:20000", 1}, {"rope:100000", 1}}) {
    const Model m = test::load_floating(spec);
    SCOPED_TRACE(spec + " B=" + std::to_string(B));
    const States x = random_soa_states(m, B, 7, false);
    EXPECT_LE(device_error<double>(m, x, true), 1e-9);
    EXPECT_LE(device_error<float>(m, x, true), float_tol(m, x, true));
  }
}

// What the device chain does not take: spherical joints (named), and the hybrid
// launch of a free rope (not supported: the engine refuses hybrid for it).
TEST(CudaFloatingChainFd, Refusals) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model ball = test::load_floating("ballrope:10");
  try {
    cuda::ChainFdPlan<double> plan(ball, 1);
    ADD_FAILURE() << "a ball rope was accepted";
  } catch (const BackendError& e) {
    EXPECT_NE(std::string(e.what()).find("spherical joint"), std::string::npos) << e.what();
  }
  const Model m = test::load_floating("rope:20");
  cuda::ChainFdPlan<double> plan(m, 1);
  const States x = random_soa_states(m, 1, 2, false);
  using V = BatchView<const double>;
  const V q = V::soa(x.q.data(), x.nq, 1);
  EXPECT_EQ(plan.launch_hybrid(q, FdBatchIn<double>{q, q, q, nullptr}, BatchView<double>{}, nullptr, nullptr),
            cudaErrorNotSupported);
}
