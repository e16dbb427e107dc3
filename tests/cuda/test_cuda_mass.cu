// The mass matrix on the GPU by the CRBA (crba_instance, mass_matrix_instance,
// launch_crba_instances, CudaMassMatrix) against the serial double scandyn::crba
// (the same algorithm) and, on the host, against the columns of the serial RNEA
// (M e_j = RNEA(q, 0, e_j) - RNEA(q, 0, 0), an independent truth).
//
// Errors are scandyn::rel_err per instance over its nv^2 entries, max |M - ref| /
// max(1, max |ref|), the worst over every instance of a batch. Tolerances:
//   double   host 1e-12 against crba (the same formulas in the same order on the same
//            host: measured 0, bit-identical); device 1e-11 (FMA contraction and the
//            device's sin/cos); 1e-9 against the RNEA columns (other arithmetic).
//   float    the reference runs on the float-rounded q, so only float arithmetic is
//            measured: max(1e-5, 10 x the serial float crba's own error on the same
//            inputs).
// Entries of pairs of bodies of which neither is an ancestor of the other must be
// exactly 0. Outputs start as NaN, so an entry never written fails; with strided
// layouts the gaps between entries hold a sentinel that must survive compute().
// Tests that need a device skip with "no CUDA device: ..."; the device function
// (run on the host) and the argument errors are checked on every machine, CI
// included.
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
#include "scandyn/cuda/mass_matrix.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

using test::aos;
using test::Layout;
using test::random_layout;
using test::soa;

constexpr double kHostTol = 1e-12;    // double, on the host, against crba
constexpr double kDeviceTol = 1e-11;  // double, on the device, against crba
constexpr double kRneaTol = 1e-9;     // double, against the RNEA's columns
constexpr double kFloatTol = 1e-5;    // float floor
constexpr double kSentinel = 12345.0;

using test::robot;

// Models of up to 64 DoF: the robots, chains at the capacities' edges, trees, and
// random trees with arbitrary axes and ~25% prismatic joints whose parents are drawn
// at random (subtrees not contiguous).
std::vector<std::pair<std::string, Model>> thread_models() {
  std::vector<std::pair<std::string, Model>> models;
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) models.emplace_back(file, robot(file));
  for (auto& m : test::thread_shape_models()) models.push_back(std::move(m));
  models.emplace_back("random_model(5)", test::random_model(5, 2));
  models.emplace_back("random_chain(20)", test::random_chain(20, 6));
  return models;
}

// Beyond 64 DoF (the block kernel).
std::vector<std::pair<std::string, Model>> block_models() {
  std::vector<std::pair<std::string, Model>> models;
  for (const char* spec : {"chain:65", "rope:80", "curtain:3:30", "tree:200:5"}) models.emplace_back(spec, load_model(spec));
  models.emplace_back("random_model(100)", test::random_model(100, 9));
  return models;
}

// B random joint positions of md (nv x B, entry (i, b) at i * B + b), exactly
// representable in S.
template <class S>
std::vector<double> random_q(const Model& md, Index B, unsigned seed) {
  std::mt19937_64 g(seed);
  std::vector<double> q = test::random_vector(g, md.nv() * B, -3.1, 3.1);
  for (double& x : q) x = double(S(x));
  return q;
}

std::vector<double> column(const std::vector<double>& v, Index nv, Index B, Index b) {
  std::vector<double> c(nv);
  for (Index i = 0; i < nv; ++i) c[i] = v[static_cast<std::size_t>(i) * B + b];
  return c;
}

// The serial crba of md in precision T on instance b of q: nv x nv row-major.
template <class T>
std::vector<T> serial_crba(const Model& md, const std::vector<double>& q, Index B, Index b) {
  const ModelTpl<T> m = md.cast<T>();
  DataTpl<T> d(m, false);
  const Index nv = m.nv();
  const std::vector<double> qb = column(q, nv, B, b);
  const std::vector<T> qt(qb.begin(), qb.end());
  std::vector<T> M(static_cast<std::size_t>(nv) * nv);
  crba(m, d, qt.data(), M.data());
  return M;
}

// The serial float crba's error on instance b against the serial double one.
double serial_float_error(const Model& md, const std::vector<double>& q, Index B, Index b) {
  const std::vector<float> f = serial_crba<float>(md, q, B, b);
  return test::max_rel_err(std::vector<double>(f.begin(), f.end()), serial_crba<double>(md, q, B, b));
}

void worsen(double& worst, double e) {
  if (!(e <= worst)) worst = e;  // NaN sticks
}

// True when neither body i nor j is an ancestor of the other (and i != j): M(i, j) = 0.
bool unrelated(const Model& md, Index i, Index j) {
  auto ancestor = [&](Index a, Index k) {
    for (Index p = md.parent(k); p >= 0; p = md.parent(p))
      if (p == a) return true;
    return false;
  };
  return i != j && !ancestor(i, j) && !ancestor(j, i);
}

// The worst instance error of the matrices at `out` (entry (i * nv + j, b) at
// out.at(i * nv + j, b)) against the serial double crba, and whether every entry of
// unrelated bodies is exactly zero.
template <class S>
double worst_error(const Model& md, const std::vector<double>& q, Index B, const std::vector<S>& buf,
                   const Layout& out) {
  const Index nv = md.nv();
  std::vector<bool> zero(static_cast<std::size_t>(nv) * nv);  // entries that must be exactly 0
  for (Index i = 0; i < nv; ++i)
    for (Index j = 0; j < nv; ++j) zero[i * nv + j] = unrelated(md, i, j);
  double worst = 0;
  std::vector<double> ours(static_cast<std::size_t>(nv) * nv);
  for (Index b = 0; b < B; ++b) {
    for (Index e = 0; e < nv * nv; ++e) ours[e] = double(buf[out.at(e, b)]);
    for (Index e = 0; e < nv * nv; ++e)
      if (zero[e]) EXPECT_EQ(ours[e], 0.0) << "M(" << e / nv << ", " << e % nv << "), instance " << b;
    worsen(worst, test::max_rel_err(ours, serial_crba<double>(md, q, B, b)));
  }
  return worst;
}

// The float tolerance for a batch: max(1e-5, 10 x the serial float crba's worst error).
double float_tol(const Model& md, const std::vector<double>& q, Index B) {
  double e = 0;
  for (Index b = 0; b < B; ++b) worsen(e, serial_float_error(md, q, B, b));
  return std::max(kFloatTol, 10 * e);
}

// ---- the device function on the host ------------------------------------------------

// mass_matrix_instance run on the host (it is __host__ __device__) over B instances
// of q (Batch of random_q<S>), M in aos layout; returns the worst error.
template <class S, bool kUnrolled>
double host_error(const Model& md, const std::vector<double>& q, Index B) {
  const ModelTpl<S> m = md.cast<S>();
  const cuda::ThreadModel<S> tm(m);
  const Index nv = m.nv();
  const Layout lq = aos(nv, B), lM = aos(nv * nv, B);
  const std::vector<S> qs = test::pack<S>(q, nv, B, lq, 0);
  std::vector<S> M(lM.size, std::numeric_limits<S>::quiet_NaN());
  for (Index b = 0; b < B; ++b) {
    std::visit(
        [&](const auto& p) {
          using P = std::decay_t<decltype(p)>;
          cuda::mass_matrix_instance<S, P::capacity, kUnrolled>(p, {qs.data() + lq.at(0, b), lq.ds},
                                                               {M.data() + lM.at(0, b), lM.ds});
        },
        tm.params());
  }
  return worst_error<S>(md, q, B, M, lM);
}

}  // namespace

// ---- runs everywhere ------------------------------------------------------------------

// Both kernel variants (loops unrolled over compile-time indices with the ancestor
// masks, or rolled walking the parents), in double and float, against the serial crba.
TEST(CudaMassModel, DeviceFunctionOnTheHost) {
  for (const auto& [name, md] : thread_models()) {
    SCOPED_TRACE(name);
    const Index B = 12;
    const std::vector<double> qd = random_q<double>(md, B, 7), qf = random_q<float>(md, B, 7);
    EXPECT_LE((host_error<double, true>(md, qd, B)), kHostTol);
    EXPECT_LE((host_error<double, false>(md, qd, B)), kHostTol);
    const double ftol = float_tol(md, qf, B);
    EXPECT_LE((host_error<float, true>(md, qf, B)), ftol);
    EXPECT_LE((host_error<float, false>(md, qf, B)), ftol);
  }
}

// An independent truth: column j of M is RNEA(q, 0, e_j) - RNEA(q, 0, 0) (gravity
// cancels), and M is symmetric positive definite (a Cholesky factorisation exists).
TEST(CudaMassModel, ColumnsOfTheRnea) {
  for (const auto& [name, md] : thread_models()) {
    SCOPED_TRACE(name);
    const Index nv = md.nv();
    const cuda::ThreadModel<double> tm(md);
    Data d(md, false);
    std::mt19937_64 g(13);
    for (int trial = 0; trial < 3; ++trial) {
      const std::vector<double> q = test::random_vector(g, nv, -3.1, 3.1);
      std::vector<double> M(static_cast<std::size_t>(nv) * nv, std::nan(""));
      std::visit(
          [&](const auto& p) {
            using P = std::decay_t<decltype(p)>;
            cuda::mass_matrix_instance<double, P::capacity>(p, {q.data(), 1}, {M.data(), 1});
          },
          tm.params());
      std::vector<double> zero(nv, 0.0), e(nv, 0.0), g0(nv), tau(nv), col(nv), ref(nv);
      rnea(md, d, q.data(), zero.data(), zero.data(), g0.data());
      double worst = 0;
      for (Index j = 0; j < nv; ++j) {
        e.assign(nv, 0.0);
        e[j] = 1;
        rnea(md, d, q.data(), zero.data(), e.data(), tau.data());
        for (Index i = 0; i < nv; ++i) col[i] = M[i * nv + j], ref[i] = tau[i] - g0[i];
        worsen(worst, test::max_rel_err(col, ref));
      }
      EXPECT_LE(worst, kRneaTol);
      // symmetric, and L L^T = M exists with positive pivots
      std::vector<double> L = M;
      for (Index i = 0; i < nv; ++i)
        for (Index j = 0; j < nv; ++j) ASSERT_EQ(M[i * nv + j], M[j * nv + i]) << i << ", " << j;
      for (Index k = 0; k < nv; ++k) {
        double dkk = L[k * nv + k];
        for (Index s = 0; s < k; ++s) dkk -= L[k * nv + s] * L[k * nv + s];
        ASSERT_GT(dkk, 0.0) << "pivot " << k;
        L[k * nv + k] = std::sqrt(dkk);
        for (Index i = k + 1; i < nv; ++i) {
          double x = L[i * nv + k];
          for (Index s = 0; s < k; ++s) x -= L[i * nv + s] * L[k * nv + s];
          L[i * nv + k] = x / L[k * nv + k];
        }
      }
    }
  }
}

// crba_instance's packed triangle: the tree's nonzeros M(k, j) (j = k or an ancestor
// of k) at tri(k, j), equal to crba's; armature adds to the diagonal and nothing else.
TEST(CudaMassModel, PackedTriangleAndArmature) {
  for (const char* file : {"iiwa.urdf", "atlas.urdf"}) {
    SCOPED_TRACE(file);
    const Model& md = robot(file);
    const Index nv = md.nv();
    const std::vector<double> q = random_q<double>(md, 1, 3);
    const std::vector<double> ref = serial_crba<double>(md, q, 1, 0);
    std::vector<double> arm(nv);
    for (Index i = 0; i < nv; ++i) arm[i] = 0.1 * (i + 1);
    std::visit(
        [&](const auto& p) {
          constexpr int C = std::decay_t<decltype(p)>::capacity;
          double M[C * (C + 1) / 2], Ma[C * (C + 1) / 2];
          cuda::crba_instance<double, C>(p, {q.data(), 1}, M);
          cuda::crba_instance<double, C>(p, {q.data(), 1}, Ma, arm.data());
          for (Index k = 0; k < nv; ++k) {
            for (Index j = 0; j <= k; ++j) {
              if (unrelated(md, k, j)) continue;  // not written
              const int t = cuda::fd_detail::tri(k, j);
              EXPECT_NEAR(M[t], ref[k * nv + j], kHostTol * std::max(1.0, std::fabs(ref[k * nv + j])));
              EXPECT_EQ(Ma[t], k == j ? M[t] + arm[k] : M[t]) << k << ", " << j;
            }
          }
        },
        cuda::ThreadModel<double>(md).params());
  }
}

TEST(CudaMassErrors, WithoutADevice) {
  // arguments are checked before the device: these hold on every machine
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 4;
  o.strategy = IdStrategy::ScanLocal;
  try {
    cuda::CudaMassMatrix<double> e(load_model("chain:3"), o);
    ADD_FAILURE() << "an engine was made with strategy scan-local";
  } catch (const BackendError& e) {
    EXPECT_NE(std::string(e.what()).find("strategy 'scan-local' is not available for the mass matrix"),
              std::string::npos)
        << e.what();
  }
  o.strategy = IdStrategy::Auto;
  o.max_batch = -1;
  EXPECT_THROW(cuda::CudaMassMatrix<double>(load_model("chain:3"), o), BackendError);
  // no device: a BackendError naming why, never a crash
  o.max_batch = 4;
  if (!test::no_device_reason().empty()) {
    for (const char* spec : {"chain:3", "chain:65"}) {
      try {
        cuda::CudaMassMatrix<float> e(load_model(spec).cast<float>(), o);
        ADD_FAILURE() << "an engine was made without a device";
      } catch (const BackendError& e) {
        EXPECT_NE(std::string(e.what()).find("no usable CUDA device"), std::string::npos) << e.what();
      }
    }
  } else {
    EXPECT_EQ(cuda::CudaMassMatrix<float>(load_model("chain:3").cast<float>(), o).strategy(), "crba_thread");
    EXPECT_EQ(cuda::CudaMassMatrix<float>(load_model("chain:65").cast<float>(), o).strategy(), "crba_block");
  }
}

// ---- on the device ----------------------------------------------------------------

namespace {

// The engine's host path: q in layout lq, M in lM (nv^2 entries per instance).
// Checks the gaps of M and returns the worst error.
template <class S>
double host_run(const Model& md, Index B, const Layout& lq, const Layout& lM, unsigned seed) {
  const ModelTpl<S> m = md.cast<S>();
  const Index nv = m.nv();
  const std::vector<double> q = random_q<S>(md, B, seed);
  const std::vector<S> qs = test::pack<S>(q, nv, B, lq, kSentinel);
  // entries NaN (never written shows), gaps the sentinel
  std::vector<S> M(lM.size, S(kSentinel));
  for (Index e = 0; e < nv * nv; ++e)
    for (Index b = 0; b < B; ++b) M[lM.at(e, b)] = std::numeric_limits<S>::quiet_NaN();
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B + 3;
  cuda::CudaMassMatrix<S> engine(m, o);
  EXPECT_EQ(engine.strategy(), nv <= cuda::kMaxThreadDofs ? "crba_thread" : "crba_block");
  engine.compute({qs.data() + lq.base, B, lq.ds, lq.bs}, {M.data() + lM.base, B, lM.ds, lM.bs});
  std::vector<bool> entry(lM.size, false);
  for (Index e = 0; e < nv * nv; ++e)
    for (Index b = 0; b < B; ++b) entry[lM.at(e, b)] = true;
  for (std::size_t k = 0; k < M.size(); ++k)
    if (!entry[k]) EXPECT_EQ(M[k], S(kSentinel)) << "gap " << k << " was written";
  return worst_error<S>(md, q, B, M, lM);
}

// The device path: q and M in device memory (layouts lq and lM), on a stream of its
// own. Entries start as NaN, gaps as the sentinel, which must survive.
template <class S>
double device_run(const Model& md, Index B, const Layout& lq, const Layout& lM, unsigned seed) {
  const ModelTpl<S> m = md.cast<S>();
  const Index nv = m.nv();
  const std::vector<double> q = random_q<S>(md, B, seed);
  const std::vector<S> qs = test::pack<S>(q, nv, B, lq, 0);
  std::vector<S> M(lM.size, S(kSentinel));
  std::vector<bool> entry(lM.size, false);
  for (Index e = 0; e < nv * nv; ++e)
    for (Index b = 0; b < B; ++b) M[lM.at(e, b)] = std::numeric_limits<S>::quiet_NaN(), entry[lM.at(e, b)] = true;
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  cuda::CudaMassMatrix<S> engine(m, o);
  test::DeviceArray<S> dq, dM;
  EXPECT_EQ(dq.alloc(lq.size), cudaSuccess);
  EXPECT_EQ(dM.alloc(lM.size), cudaSuccess);
  cudaStream_t stream = nullptr;
  EXPECT_EQ(cudaStreamCreate(&stream), cudaSuccess);
  EXPECT_EQ(cudaMemcpy(dq.ptr, qs.data(), lq.size * sizeof(S), cudaMemcpyHostToDevice), cudaSuccess);
  EXPECT_EQ(cudaMemcpy(dM.ptr, M.data(), lM.size * sizeof(S), cudaMemcpyHostToDevice), cudaSuccess);
  EXPECT_EQ(engine.compute_async({dq.ptr + lq.base, B, lq.ds, lq.bs}, {dM.ptr + lM.base, B, lM.ds, lM.bs}, stream),
            cudaSuccess);
  EXPECT_EQ(cudaStreamSynchronize(stream), cudaSuccess);
  EXPECT_EQ(cudaMemcpy(M.data(), dM.ptr, lM.size * sizeof(S), cudaMemcpyDeviceToHost), cudaSuccess);
  cudaStreamDestroy(stream);
  for (std::size_t k = 0; k < M.size(); ++k)
    if (!entry[k]) EXPECT_EQ(M[k], S(kSentinel)) << "gap " << k << " was written";
  return worst_error<S>(md, q, B, M, lM);
}

template <class S>
double device_run(const Model& md, Index B, bool soa_layout, unsigned seed) {
  const Index nv = md.nv();
  return soa_layout ? device_run<S>(md, B, soa(nv, B), soa(nv * nv, B), seed)
                    : device_run<S>(md, B, aos(nv, B), aos(nv * nv, B), seed);
}

}  // namespace

// Every model, float and double, batch sizes 1, 33, 129 and 300 (not multiples of
// the block size 128; 300 only up to 64 DoF: a random M layout of a 200-DoF model
// can take one strided copy per entry), M in the aos layout `scandyn eval` uses,
// soa, and random strided layouts (padded, reversed, interleaved) for q and M.
TEST(CudaMass, MatchesSerialCrba) {
  SKIP_WITHOUT_CUDA_DEVICE();
  std::mt19937_64 g(17);
  std::vector<std::pair<std::string, Model>> models = thread_models();
  for (auto& m : block_models()) models.push_back(std::move(m));
  for (const auto& [name, md] : models) {
    const Index nv = md.nv();
    for (Index B : {1, 33, 129, 300}) {
      if (B == 300 && nv > cuda::kMaxThreadDofs) continue;
      // q random unless B = 1 (aos) or 129 (soa); M random unless 33 (aos) or 129 (soa).
      // (Inputs broadcast over instances are not drawn: each instance has its own q.)
      auto random_q_layout = [&] {
        Layout l = random_layout(g, nv, B, false);
        while (l.bs == 0) l = random_layout(g, nv, B, false);
        return l;
      };
      const Layout lq = B == 1 ? aos(nv, B) : B == 129 ? soa(nv, B) : random_q_layout();
      const Layout lM = B == 33 ? aos(nv * nv, B) : B == 129 ? soa(nv * nv, B) : random_layout(g, nv * nv, B, true);
      SCOPED_TRACE(name + " B=" + std::to_string(B) + " q " + lq.name + " M " + lM.name);
      EXPECT_LE(host_run<double>(md, B, lq, lM, 100 + B), kDeviceTol);
      const std::vector<double> qf = random_q<float>(md, B, 100 + B);
      EXPECT_LE(host_run<float>(md, B, lq, lM, 100 + B), float_tol(md, qf, B));
    }
  }
}

// compute_async on device pointers: both layouts, both kernels, large batches.
TEST(CudaMass, DevicePointersOnAStream) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) {
    const Model& md = robot(file);
    for (Index B : {1, 129, 4097}) {
      for (bool s : {true, false}) {
        SCOPED_TRACE(std::string(file) + " B=" + std::to_string(B) + (s ? " soa" : " aos"));
        EXPECT_LE(device_run<double>(md, B, s, 3), kDeviceTol);
        const std::vector<double> qf = random_q<float>(md, B, 3);
        EXPECT_LE(device_run<float>(md, B, s, 3), float_tol(md, qf, B));
      }
    }
  }
  SCOPED_TRACE("iiwa B=100000");
  const std::vector<double> qf = random_q<float>(robot("iiwa.urdf"), 100000, 4);
  EXPECT_LE(device_run<float>(robot("iiwa.urdf"), 100000, true, 4), float_tol(robot("iiwa.urdf"), qf, 100000));
  for (const auto& [name, md] : block_models()) {
    SCOPED_TRACE(name);
    EXPECT_LE(device_run<double>(md, 5, true, 5), kDeviceTol);
  }
}

// compute_async into per-instance layouts (each instance's entries closer together than
// consecutive instances: the kernel that stages its stores through shared memory, as for
// a (B, nv, nv) array from Python): padded, reversed, interleaved, batches that end in
// a partial warp; soa-like layouts alongside (the direct stores).
TEST(CudaMass, DevicePointersStridedLayouts) {
  SKIP_WITHOUT_CUDA_DEVICE();
  std::mt19937_64 g(23);
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) {
    const Model& md = robot(file);
    const Index nv = md.nv();
    for (Index B : {2, 31, 33, 1000}) {
      for (int trial = 0; trial < 3; ++trial) {
        Layout lq = random_layout(g, nv, B, false);
        while (lq.bs == 0) lq = random_layout(g, nv, B, false);
        const Layout lM = random_layout(g, nv * nv, B, true);
        SCOPED_TRACE(std::string(file) + " B=" + std::to_string(B) + " q " + lq.name + " M " + lM.name);
        EXPECT_LE(device_run<double>(md, B, lq, lM, 40 + trial), kDeviceTol);
        const std::vector<double> qf = random_q<float>(md, B, 40 + trial);
        EXPECT_LE(device_run<float>(md, B, lq, lM, 40 + trial), float_tol(md, qf, B));
      }
    }
  }
  SCOPED_TRACE("iiwa B=100000 aos");
  const std::vector<double> qf = random_q<float>(robot("iiwa.urdf"), 100000, 6);
  EXPECT_LE(device_run<float>(robot("iiwa.urdf"), 100000, false, 6), float_tol(robot("iiwa.urdf"), qf, 100000));
}

TEST(CudaMass, ErrorsWithADevice) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model md = load_model("chain:4");
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 8;
  cuda::CudaMassMatrix<double> engine(md, o);
  EXPECT_EQ(engine.device_bytes(), (4u + 16u) * sizeof(double) * 8);
  std::vector<double> q(4 * 16, 0.1), M(16 * 16, 0.0);
  using V = BatchView<const double>;
  // max_batch exceeded
  try {
    engine.compute(V::soa(q.data(), 4, 9), BatchView<double>::soa(M.data(), 16, 9));
    ADD_FAILURE() << "a batch over max_batch was accepted";
  } catch (const BackendError& e) {
    EXPECT_NE(std::string(e.what()).find("max_batch"), std::string::npos) << e.what();
  }
  // batch sizes that disagree; null pointers; M entries that overlap
  EXPECT_THROW(engine.compute(V::soa(q.data(), 4, 8), BatchView<double>::soa(M.data(), 16, 7)), BackendError);
  EXPECT_THROW(engine.compute(V::soa(nullptr, 4, 8), BatchView<double>::soa(M.data(), 16, 8)), BackendError);
  EXPECT_THROW(engine.compute(V::soa(q.data(), 4, 8), BatchView<double>{M.data(), 8, 1, 0}), BackendError);
  EXPECT_THROW(engine.compute(V::soa(q.data(), 4, 8), BatchView<double>{M.data(), 8, 1, 2}), BackendError);
  // the device path reports argument errors as values (host pointers are never touched)
  EXPECT_EQ(engine.compute_async(V::soa(q.data(), 4, 8), BatchView<double>::soa(M.data(), 16, 7), nullptr),
            cudaErrorInvalidValue);
  EXPECT_EQ(engine.compute_async(V::soa(nullptr, 4, 8), BatchView<double>::soa(M.data(), 16, 8), nullptr),
            cudaErrorInvalidValue);
  // B = 0: nothing to do, null pointers allowed
  EXPECT_EQ(engine.compute_async(V::soa(nullptr, 4, 0), BatchView<double>::soa(nullptr, 16, 0), nullptr), cudaSuccess);
  EXPECT_NO_THROW(engine.compute(V::soa(nullptr, 4, 0), BatchView<double>::soa(nullptr, 16, 0)));
  // the block kernel: B <= max_batch on the device path too
  cuda::CudaMassMatrix<double> block(load_model("chain:65"), o);
  EXPECT_EQ(block.strategy(), "crba_block");
  std::vector<double> q65(65 * 9, 0.1);
  EXPECT_EQ(block.compute_async(V::soa(q65.data(), 65, 9), BatchView<double>::soa(M.data(), 65 * 65, 9), nullptr),
            cudaErrorInvalidValue);
  // more than the device holds: the message names the bytes needed and free
  o.max_batch = 2000000000;
  try {
    cuda::CudaMassMatrix<double> huge(load_model("chain:64"), o);
    ADD_FAILURE() << "an engine of " << huge.device_bytes() << " bytes was made";
  } catch (const BackendError& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find(std::to_string((64ull + 64 * 64) * 8 * 2000000000ull) + " bytes"), std::string::npos) << what;
    EXPECT_NE(what.find("bytes free"), std::string::npos) << what;
  }
  // the engine still works after the failures
  std::vector<double> out(16 * 8, std::nan(""));
  engine.compute(V::soa(q.data(), 4, 8), BatchView<double>::aos(out.data(), 16, 8));
  const std::vector<double> q1(4, 0.1);
  Data d(md, false);
  std::vector<double> ref(16);
  crba(md, d, q1.data(), ref.data());
  for (Index b = 0; b < 8; ++b)
    for (Index e = 0; e < 16; ++e)
      EXPECT_NEAR(out[b * 16 + e], ref[e], kDeviceTol * std::max(1.0, std::fabs(ref[e])));
}
