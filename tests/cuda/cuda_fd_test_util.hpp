// tests/cuda/cuda_fd_test_util.hpp: what the parts of the test_cuda_fd program share.
// The program is compiled from tests/cuda/test_cuda_fd.cu (the engine on the device, the
// argument checks, the model's masks and slots) and tests/cuda/test_cuda_fd.<part>.cu (the
// device functions run on the host, one translation unit per group of
// instantiations, so that a parallel build compiles them side by side: see
// tests/CMakeLists.txt).
// Errors, tolerances and what runs where: the opening comment of tests/cuda/test_cuda_fd.cu.
#pragma once

#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <random>
#include <string>
#include <type_traits>
#include <utility>
#include <variant>
#include <vector>

#include "cuda_test_util.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

namespace scandyn::test::fd {

using test::aos;
using test::Layout;
using test::pack;
using test::random_layout;
using test::robot;
using test::soa;

inline constexpr double kDoubleTol = 1e-10;  // vs fd_jsi
inline constexpr double kAbaTol = 1e-9;      // double vs aba
inline constexpr double kFloatTol = 1e-4;    // float on the robots; floor elsewhere
inline constexpr double kSentinel = 12345.0;

// ---- one batch against the references ----------------------------------------------

// B random instances of md: inputs as doubles exactly representable in S.
template <class S>
struct Batch {
  Index nv, B;
  std::vector<double> q, qd, tau;     // (nv x B), entry (i, b) at i * B + b
  std::vector<Force<double>> fext;    // (B x nv)
  Batch(const Model& md, Index B_, unsigned seed) : nv(md.nv()), B(B_) {
    test::random_exact_batch<S>(nv, B, seed, q, qd, tau, fext);
  }
  // every instance takes instance 0's state (for broadcast layouts)
  void broadcast() {
    for (auto* v : {&q, &qd, &tau})
      for (Index i = 0; i < nv; ++i)
        for (Index b = 0; b < B; ++b) (*v)[at(i, b)] = (*v)[at(i, 0)];
  }
  std::size_t at(Index i, Index b) const { return static_cast<std::size_t>(i) * B + b; }
  std::vector<double> column(const std::vector<double>& v, Index b) const {
    std::vector<double> c(nv);
    for (Index i = 0; i < nv; ++i) c[i] = v[at(i, b)];
    return c;
  }
  const Force<double>* wrenches(Index b, bool with_fext) const {
    return with_fext ? fext.data() + static_cast<std::size_t>(b) * nv : nullptr;
  }
  // instance b's qdd by fd_jsi (status returned) and by aba
  Status reference(const Model& md, Data& d, Index b, bool with_fext, std::vector<double>& jsi,
                   std::vector<double>& ab) const {
    const std::vector<double> qi = column(q, b), qdi = column(qd, b), ti = column(tau, b);
    jsi.assign(nv, 0.0);
    ab.assign(nv, 0.0);
    const Status s = fd_jsi(md, d, qi.data(), qdi.data(), ti.data(), jsi.data(), wrenches(b, with_fext));
    aba(md, d, qi.data(), qdi.data(), ti.data(), ab.data(), wrenches(b, with_fext));
    return s;
  }
};

struct Errors {
  double jsi = 0;  // worst instance error against fd_jsi
  double aba = 0;  // ... against aba
};

inline void worsen(double& worst, double e) {
  if (!(e <= worst)) worst = e;  // NaN sticks
}

// The worst instance errors of qdd (entries at `out`) against the references.
template <class S>
Errors worst_errors(const Model& md, const Batch<S>& batch, bool with_fext, const std::vector<S>& qdd_buf,
                    const Layout& out) {
  Data d(md);
  Errors worst;
  std::vector<double> jsi, ab, ours(batch.nv);
  for (Index b = 0; b < batch.B; ++b) {
    EXPECT_TRUE(batch.reference(md, d, b, with_fext, jsi, ab).ok()) << "reference failed on instance " << b;
    for (Index i = 0; i < batch.nv; ++i) ours[i] = double(qdd_buf[out.at(i, b)]);
    worsen(worst.jsi, test::max_rel_err(ours, jsi));
    worsen(worst.aba, test::max_rel_err(ours, ab));
  }
  return worst;
}

// The serial float fd_jsi's (with_aba: aba's) error on the same inputs
// (Batch<float>(md, B, seed)), against the double reference of the same algorithm:
// the scale of float rounding for a model.
inline double cpu_float_error(const Model& md, Index B, bool with_fext, unsigned seed, bool with_aba = false) {
  const ModelTpl<float> m = md.cast<float>();
  const Index nv = m.nv();
  Batch<float> batch(md, B, seed);
  DataTpl<float> d(m);
  std::vector<float> qdd_buf(static_cast<std::size_t>(nv) * B);
  const Layout l = aos(nv, B);
  for (Index b = 0; b < B; ++b) {
    const std::vector<double> qi = batch.column(batch.q, b), qdi = batch.column(batch.qd, b),
                              ti = batch.column(batch.tau, b);
    std::vector<float> qf(qi.begin(), qi.end()), qdf(qdi.begin(), qdi.end()), tf(ti.begin(), ti.end());
    std::vector<Force<float>> ff;
    if (with_fext)
      for (Index i = 0; i < nv; ++i) ff.push_back(batch.wrenches(b, true)[i].cast<float>());
    if (with_aba)
      aba(m, d, qf.data(), qdf.data(), tf.data(), qdd_buf.data() + l.at(0, b), with_fext ? ff.data() : nullptr);
    else
      fd_jsi(m, d, qf.data(), qdf.data(), tf.data(), qdd_buf.data() + l.at(0, b), with_fext ? ff.data() : nullptr);
  }
  const Errors e = worst_errors<float>(md, batch, with_fext, qdd_buf, l);
  return with_aba ? e.aba : e.jsi;
}

// The double tolerance against fd_jsi on a model: 1e-10, or 10x what two exact
// algorithms (serial fd_jsi and aba, double) disagree by on it when its mass matrix
// is ill-conditioned (a 64-link chain: 8e-11; the GPU's FMA contractions then move
// its JSI result by up to 5e-10).
inline double jsi_tol(const Model& md) {
  std::mt19937_64 g(3);
  Data d(md);
  const Index nv = md.nv();
  double spread = 0;
  for (int k = 0; k < 8; ++k) {
    const std::vector<double> q = test::random_vector(g, nv, -3.1, 3.1), qd = test::random_vector(g, nv, -2, 2),
                              tau = test::random_vector(g, nv, -2, 2);
    std::vector<double> a(nv), b(nv);
    if (!fd_jsi(md, d, q.data(), qd.data(), tau.data(), a.data()).ok() ||
        !aba(md, d, q.data(), qd.data(), tau.data(), b.data()).ok())
      continue;
    spread = std::max(spread, test::max_rel_err(a, b));
  }
  return std::max(kDoubleTol, 10 * spread);
}

inline double float_tol(const Model& md, Index B, bool with_fext, unsigned seed) {
  return std::max(kFloatTol, 10 * cpu_float_error(md, B, with_fext, seed));
}

// The float tolerance of the ABA against the serial double aba: max(1e-4, 10 x the
// serial float aba's own error on the same inputs).
inline double aba_float_tol(const Model& md, Index B, bool with_fext, unsigned seed) {
  return std::max(kFloatTol, 10 * cpu_float_error(md, B, with_fext, seed, true));
}

// ---- the device function on the host ------------------------------------------------

// fd_jsi_instance run on the host (it is __host__ __device__) over a batch in aos
// layout (inputs Batch<S>(md, B, kHostSeed)); every instance must succeed.
inline constexpr unsigned kHostSeed = 11;

// kAba: aba_instance instead of fd_jsi_instance, with kSlots branch slots (-1: the
// capacity, aba_instance's default, for any model).
template <class S, bool kKeepXup, bool kUnrolled, bool kAba = false, int kSlots = -1>
Errors host_instance_errors(const Model& md, Index B, bool with_fext) {
  const ModelTpl<S> m = md.cast<S>();
  const cuda::ThreadModel<S> tm(m);
  const Index nv = m.nv();
  Batch<S> batch(md, B, kHostSeed);
  const Layout l = aos(nv, B);  // each instance contiguous
  const std::vector<S> q = pack<S>(batch.q, nv, B, l, 0), qd = pack<S>(batch.qd, nv, B, l, 0),
                       tau = pack<S>(batch.tau, nv, B, l, 0);
  std::vector<Force<S>> fext = test::cast_wrenches<S>(batch.fext);
  std::vector<S> qdd(l.size, std::numeric_limits<S>::quiet_NaN());
  for (Index b = 0; b < B; ++b) {
    const std::size_t o = static_cast<std::size_t>(b) * nv;
    const Force<S>* f = with_fext ? fext.data() + o : nullptr;
    const Index failed = std::visit(
        [&](const auto& p) {
          using P = std::decay_t<decltype(p)>;
          if constexpr (kAba) {
            constexpr int kAbaSlots = kSlots < 0 ? P::capacity : kSlots;
            return cuda::aba_instance<S, P::capacity, kKeepXup, kUnrolled, Trig::Library, kAbaSlots>(
                p, {q.data() + o, 1}, {qd.data() + o, 1}, {tau.data() + o, 1}, f, {qdd.data() + o, 1});
          } else
            return cuda::fd_jsi_instance<S, P::capacity, kKeepXup, kUnrolled>(
                p, {q.data() + o, 1}, {qd.data() + o, 1}, {tau.data() + o, 1}, f, {qdd.data() + o, 1});
        },
        tm.params());
    EXPECT_EQ(failed, -1) << "instance " << b;
  }
  return worst_errors<S>(md, batch, with_fext, qdd, l);
}

inline std::vector<std::pair<std::string, Model>> generated_models() { return test::thread_shape_models(); }

// A model whose mass matrix is singular: chain:N with its last body massless
// (M(N-1, N-1) = 0: the factorisation stops at DoF N-1 for every state).
inline Model massless_leaf(int n) {
  Model md = load_model("chain:" + std::to_string(n));
  md.bodies.back().I = Inertia<double>::zero();
  return md;
}

}  // namespace scandyn::test::fd
