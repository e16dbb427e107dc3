// The engine API (scandyn/engine.hpp) on the CPU backends, through the factories:
// every engine bit-identical to the serial reference function it runs, in every
// layout; failures recorded per instance; the aba fallback; the Auto choices; names
// and errors. The CUDA engines through the same factories when a device exists.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <random>

#include "scandyn/accuracy.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "stability_cases.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

constexpr Index kB = 9;  // instances: more than the threads, not a multiple of them

std::vector<BackendKind> cpu_backends() {
  std::vector<BackendKind> b{BackendKind::Serial};
  if (backend_unusable(BackendKind::OpenMP).empty()) b.push_back(BackendKind::OpenMP);
  return b;
}

std::vector<std::pair<std::string, Model>> models() { return test::engine_test_models(); }

// Three layouts of one (nv x B) array: structure of arrays, instance rows, and a
// strided one with gaps (every entry twice as far apart as in aos).
enum class Layout { Soa, Aos, Strided };
template <class T>
BatchView<T> view(T* p, Index n, Index B, Layout l) {
  if (l == Layout::Soa) return BatchView<T>::soa(p, n, B);
  if (l == Layout::Aos) return BatchView<T>::aos(p, n, B);
  return BatchView<T>{p, B, 2, 2 * n};
}
std::size_t storage(Index n, Index B, Layout l) {
  return static_cast<std::size_t>(n) * B * (l == Layout::Strided ? 2 : 1);
}

// Instance b's n entries of v.
template <class T>
std::vector<std::remove_const_t<T>> row(const BatchView<T>& v, Index b, Index n) {
  std::vector<std::remove_const_t<T>> r(static_cast<std::size_t>(n));
  for (Index i = 0; i < n; ++i) r[i] = v.at(i, b);
  return r;
}

template <class S>
struct Inputs {
  std::vector<S> q, qd, x;  // x: qdd for id, tau for fd
  std::vector<Force<S>> fext;
  Inputs(Index nv, Layout l, unsigned seed) {
    std::mt19937_64 g(seed);
    const std::size_t n = storage(nv, kB, l);
    q = test::cast_vector<S>(test::random_vector(g, static_cast<int>(n), -1, 1));
    qd = test::cast_vector<S>(test::random_vector(g, static_cast<int>(n), -1, 1));
    x = test::cast_vector<S>(test::random_vector(g, static_cast<int>(n), -1, 1));
    fext = test::random_wrenches<S>(g, static_cast<int>(nv * kB), 0.5);
  }
};

template <class S>
void expect_engines_equal_reference(const Model& md, BackendKind backend, Layout l, bool with_fext) {
  const ModelTpl<S> m = md.cast<S>();
  const Index nv = m.nv();
  Inputs<S> in(nv, l, static_cast<unsigned>(nv * 31 + static_cast<int>(l)));
  const Force<S>* fext = with_fext ? in.fext.data() : nullptr;
  const auto Q = view<const S>(in.q.data(), nv, kB, l), QD = view<const S>(in.qd.data(), nv, kB, l),
             X = view<const S>(in.x.data(), nv, kB, l);
  BackendOptions o;
  o.backend = backend;
  o.threads = 2;
  o.max_batch = kB;
  o.simd = CpuSimd::Off;  // the scalar path; the SIMD path against it: test_simd_batch.cpp
  DataTpl<S> data(m);
  const S nan = std::numeric_limits<S>::quiet_NaN();
  std::vector<S> out(storage(nv, kB, l), nan), ref(static_cast<std::size_t>(nv * nv));
  const auto O = view<S>(out.data(), nv, kB, l);
  const auto instance_fext = [&](Index b) { return fext ? fext + b * nv : nullptr; };

  // inverse dynamics and bias forces
  auto id = make_inverse_dynamics<S>(m, o);
  EXPECT_TRUE(id->exact());
  id->compute(IdBatchIn<S>{Q, QD, X, fext}, O);
  for (Index b = 0; b < kB; ++b) {
    rnea(m, data, row(Q, b, nv).data(), row(QD, b, nv).data(), row(X, b, nv).data(), ref.data(), instance_fext(b));
    for (Index i = 0; i < nv; ++i) ASSERT_EQ(O.at(i, b), ref[i]) << "id instance " << b << " dof " << i;
  }
  std::fill(out.begin(), out.end(), nan);
  make_bias_forces<S>(m, o)->compute(BiasBatchIn<S>{Q, QD, fext}, O);
  for (Index b = 0; b < kB; ++b) {
    bias_forces(m, data, row(Q, b, nv).data(), row(QD, b, nv).data(), ref.data(), instance_fext(b));
    for (Index i = 0; i < nv; ++i) ASSERT_EQ(O.at(i, b), ref[i]) << "bias instance " << b << " dof " << i;
  }
  // forward dynamics by aba and jsi
  for (FdMethod method : {FdMethod::Aba, FdMethod::Jsi}) {
    o.fd_method = method;
    auto fd = make_forward_dynamics<S>(m, o);
    EXPECT_EQ(fd->method(), method);
    std::fill(out.begin(), out.end(), nan);
    const BatchStatus st = fd->compute(FdBatchIn<S>{Q, QD, X, fext}, O);
    ASSERT_TRUE(st.ok()) << st.message();
    ASSERT_NE(st.failed_dof, nullptr);
    for (Index b = 0; b < kB; ++b) {
      EXPECT_EQ(st.failed_dof[b], -1);
      const Status rs = method == FdMethod::Aba
                            ? aba(m, data, row(Q, b, nv).data(), row(QD, b, nv).data(), row(X, b, nv).data(),
                                  ref.data(), instance_fext(b))
                            : fd_jsi(m, data, row(Q, b, nv).data(), row(QD, b, nv).data(), row(X, b, nv).data(),
                                     ref.data(), instance_fext(b));
      ASSERT_TRUE(rs.ok());
      for (Index i = 0; i < nv; ++i)
        ASSERT_EQ(O.at(i, b), ref[i]) << to_string(method) << " instance " << b << " dof " << i;
    }
  }
  // the mass matrix: nv * nv entries per instance
  std::vector<S> M(storage(nv * nv, kB, l), nan);
  const auto MV = view<S>(M.data(), nv * nv, kB, l);
  make_mass_matrix<S>(m, o)->compute(Q, MV);
  for (Index b = 0; b < kB; ++b) {
    crba(m, data, row(Q, b, nv).data(), ref.data());
    for (Index e = 0; e < nv * nv; ++e) ASSERT_EQ(MV.at(e, b), ref[e]) << "mass instance " << b << " entry " << e;
  }
}

}  // namespace

TEST(Engines, EveryCpuEngineIsTheReferenceBitForBitInEveryLayout) {
  for (const auto& [name, model] : models())
    for (BackendKind backend : cpu_backends())
      for (Layout l : {Layout::Soa, Layout::Aos, Layout::Strided}) {
        SCOPED_TRACE(name + " " + to_string(backend) + " layout " + std::to_string(static_cast<int>(l)));
        expect_engines_equal_reference<double>(model, backend, l, l == Layout::Aos);
        expect_engines_equal_reference<float>(model, backend, l, l != Layout::Aos);
      }
}

// The parallel chain forward dynamics agrees with the ABA to rounding (tolerance per
// precision: measured 1e-13 / 2e-6 on rope:200), and records nothing on a clean batch.
TEST(Engines, ParallelForwardDynamicsOfAChainMatchesAba) {
  const Model md = load_model("rope:200");
  for (BackendKind backend : cpu_backends()) {
    const Index nv = md.nv();
    Inputs<double> in(nv, Layout::Soa, 5);
    BackendOptions o;
    o.backend = backend;
    o.max_batch = kB;
    const auto V = [&](const std::vector<double>& v) { return BatchView<const double>::soa(v.data(), nv, kB); };
    std::vector<double> a(nv * kB), p(nv * kB);
    o.fd_method = FdMethod::Aba;
    ASSERT_TRUE(make_forward_dynamics<double>(md, o)
                    ->compute({V(in.q), V(in.qd), V(in.x)}, BatchView<double>::soa(a.data(), nv, kB))
                    .ok());
    o.fd_method = FdMethod::Parallel;
    auto par = make_forward_dynamics<double>(md, o);
    EXPECT_EQ(par->strategy(), "parallel");
    ASSERT_TRUE(par->compute({V(in.q), V(in.qd), V(in.x)}, BatchView<double>::soa(p.data(), nv, kB)).ok());
    EXPECT_LT(test::max_rel_err(p, a), 1e-10) << to_string(backend);
  }
}

// A rope with a heavy tip (stability_cases.hpp): the float JSI's factorisation
// fails on many random states (cond(M) beyond float), the ABA's on none. Failures
// are recorded per instance, the failed instances' qdd left unwritten; with the
// fallback they get the ABA's qdd.
TEST(Engines, FailuresAreRecordedPerInstanceAndTheFallbackRecomputesThem) {
  const ModelTpl<float> m = stability::heavy_tip_rope(64, 3e4).cast<float>();
  const Index nv = m.nv(), B = 32;
  std::mt19937_64 g(11);
  const std::vector<float> q = test::cast_vector<float>(test::random_vector(g, static_cast<int>(nv * B), -3, 3));
  const std::vector<float> qd = test::cast_vector<float>(test::random_vector(g, static_cast<int>(nv * B), -1, 1));
  const std::vector<float> tau = test::cast_vector<float>(test::random_vector(g, static_cast<int>(nv * B), -1, 1));
  for (BackendKind backend : cpu_backends()) {
    SCOPED_TRACE(to_string(backend));
    BackendOptions o;
    o.backend = backend;
    o.max_batch = B;
    o.fd_method = FdMethod::Jsi;
    using V = BatchView<const float>;
    const FdBatchIn<float> in{V::aos(q.data(), nv, B), V::aos(qd.data(), nv, B), V::aos(tau.data(), nv, B)};
    std::vector<float> qdd(nv * B, std::numeric_limits<float>::quiet_NaN());
    auto fd = make_forward_dynamics<float>(m, o);  // (owns st.failed_dof)
    const BatchStatus st = fd->compute(in, BatchView<float>::aos(qdd.data(), nv, B));
    // which rows fail is the reference's verdict, row by row
    DataTpl<float> data(m);
    std::vector<float> ref(nv);
    Index failed = 0;
    for (Index b = 0; b < B; ++b) {
      const Status rs = fd_jsi(m, data, q.data() + b * nv, qd.data() + b * nv, tau.data() + b * nv, ref.data());
      EXPECT_EQ(st.failed_dof[b], rs.failed_dof) << b;
      if (!rs.ok()) {
        ++failed;
        EXPECT_TRUE(std::isnan(qdd[b * nv])) << "failed instance " << b << " was written";
      }
    }
    ASSERT_GT(failed, 0) << "the heavy tip no longer makes the float JSI fail";
    EXPECT_EQ(st.failed, failed);
    EXPECT_EQ(st.failure, Failure::MassMatrixPivot);
    EXPECT_EQ(st.message().rfind("instance " + std::to_string(st.first_instance) + ": mass matrix pivot at DoF ", 0),
              0u)
        << st.message();
    // with the fallback: the ABA's qdd on exactly those rows
    o.fallback_aba = true;
    auto fb = make_forward_dynamics<float>(m, o);
    EXPECT_EQ(fb->strategy(), "jsi+aba");
    const BatchStatus sf = fb->compute(in, BatchView<float>::aos(qdd.data(), nv, B));
    EXPECT_TRUE(sf.ok()) << sf.message();
    EXPECT_EQ(sf.fell_back, failed);
    for (Index b = 0; b < B; ++b) {
      const float* qb = q.data() + b * nv;
      Status rs = fd_jsi(m, data, qb, qd.data() + b * nv, tau.data() + b * nv, ref.data());
      if (!rs.ok()) rs = aba(m, data, qb, qd.data() + b * nv, tau.data() + b * nv, ref.data());
      ASSERT_TRUE(rs.ok());
      for (Index i = 0; i < nv; ++i) ASSERT_EQ(qdd[b * nv + i], ref[i]) << b << " " << i;
    }
  }
}

TEST(Engines, StatusMessages) {
  BatchStatus st;
  EXPECT_TRUE(st.ok());
  EXPECT_EQ(st.message(), "");
  st.record(7, 2, Failure::ArticulatedPivot);
  st.record(3, 5, Failure::ArticulatedPivot);
  EXPECT_EQ(st.message(), "instance 3: articulated inertia pivot at DoF 5 is not positive (and 1 more instance)");
  BatchStatus jsi;
  jsi.record(0, 1, Failure::BothPivots);
  EXPECT_EQ(jsi.reason(),
            "mass matrix pivot not positive, and by the aba fallback the articulated inertia pivot at DoF 1 is not "
            "positive");
  st.merge(jsi);
  EXPECT_EQ(st.failed, 3);
  EXPECT_EQ(st.first_instance, 0);
  EXPECT_EQ(st.failure, Failure::BothPivots);
  const int failed_dof[] = {-1, 4, -1, 0};
  const BatchStatus s = summarize_failures(failed_dof, 4, Failure::MassMatrixPivot);
  EXPECT_EQ(s.failed, 2);
  EXPECT_EQ(s.first_instance, 1);
  EXPECT_EQ(s.first_dof, 4);
  EXPECT_EQ(s.message(), "instance 1: mass matrix pivot at DoF 4 is not positive (and 1 more instance)");
}

TEST(Engines, AutoChoicesFollowBackendAndShape) {
  const Model iiwa = test::load_robot("iiwa.urdf");
  const Model rope = load_model("rope:5000"), tree = load_model("tree:100:3");
  const int kT = kChainFdThreadsPerInstance;
  EXPECT_EQ(choose_fd_method(BackendKind::Serial, rope, 1, 64), FdMethod::Aba);
  EXPECT_EQ(choose_fd_method(BackendKind::OpenMP, iiwa, 1, 64), FdMethod::Aba);
  // openmp: the chain scans for one long chain from kT threads per instance on
  EXPECT_EQ(choose_fd_method(BackendKind::OpenMP, rope, 1, kT), FdMethod::Parallel);
  EXPECT_EQ(choose_fd_method(BackendKind::OpenMP, rope, 2, 2 * kT), FdMethod::Parallel);
  EXPECT_EQ(choose_fd_method(BackendKind::OpenMP, rope, 1, kT - 1), FdMethod::Aba);
  EXPECT_EQ(choose_fd_method(BackendKind::OpenMP, rope, 2, 2 * kT - 1), FdMethod::Aba);
  EXPECT_EQ(choose_fd_method(BackendKind::OpenMP, rope, 1, 2), FdMethod::Aba);
  EXPECT_EQ(choose_fd_method(BackendKind::OpenMP, load_model("rope:4095"), 1, 64), FdMethod::Aba);
  EXPECT_EQ(choose_fd_method(BackendKind::Cuda, iiwa, 1, 1), FdMethod::Aba);
  EXPECT_EQ(choose_fd_method(BackendKind::Cuda, rope, 1, 1), FdMethod::Parallel);
  EXPECT_EQ(choose_fd_method(BackendKind::Cuda, load_model("rope:129"), 1, 1), FdMethod::Parallel);
  EXPECT_EQ(choose_fd_method(BackendKind::Cuda, load_model("rope:128"), 1, 1), FdMethod::Aba);  // aba_general
  EXPECT_EQ(choose_fd_method(BackendKind::Cuda, tree, 1, 1), FdMethod::Aba);                    // aba_general
  EXPECT_TRUE(is_chain_from_base(rope));
  EXPECT_FALSE(is_chain_from_base(tree));
  EXPECT_EQ(choose_id_strategy(BackendKind::OpenMP, 7, 1000000, 16), IdStrategy::Recursion);
  EXPECT_EQ(choose_id_strategy(BackendKind::OpenMP, 1000000, 1, 16), IdStrategy::ScanLocal);
  EXPECT_EQ(choose_id_strategy(BackendKind::Serial, 1000000, 1, 1), IdStrategy::Recursion);
  EXPECT_EQ(choose_id_strategy(BackendKind::Cuda, 64, 1, 1), IdStrategy::Recursion);
  EXPECT_EQ(choose_id_strategy(BackendKind::Cuda, 65, 1, 1), IdStrategy::ScanLocal);
  // the openmp engine takes the choice for its max_batch and threads (constructed only)
  if (backend_unusable(BackendKind::OpenMP).empty()) {
    BackendOptions o;
    o.backend = BackendKind::OpenMP;
    o.threads = kT;
    EXPECT_EQ(make_forward_dynamics<double>(rope, o)->method(), FdMethod::Parallel);
    o.max_batch = 2;
    EXPECT_EQ(make_forward_dynamics<double>(rope, o)->method(), FdMethod::Aba);
    o.threads = 2;
    o.max_batch = 1;
    EXPECT_EQ(make_forward_dynamics<double>(rope, o)->method(), FdMethod::Aba);
  }
}

TEST(Engines, NamesParseAndPrint) {
  for (BackendKind b : {BackendKind::Serial, BackendKind::OpenMP, BackendKind::Cuda})
    EXPECT_EQ(parse_backend(to_string(b)), b);
  for (FdMethod m : {FdMethod::Auto, FdMethod::Aba, FdMethod::Jsi, FdMethod::Parallel, FdMethod::Hybrid})
    EXPECT_EQ(parse_fd_method(to_string(m)), m);
  for (IdStrategy s : {IdStrategy::Auto, IdStrategy::Recursion, IdStrategy::ScanLocal, IdStrategy::ScanWorld})
    EXPECT_EQ(parse_strategy(to_string(s)), s);
  for (Precision p : {Precision::Double, Precision::Float}) EXPECT_EQ(parse_precision(to_string(p)), p);
  try {
    parse_backend("gpu");
    FAIL() << "no BackendError";
  } catch (const BackendError& e) {
    EXPECT_STREQ(e.what(), "unknown backend 'gpu' (expected serial, openmp or cuda)");
  }
  EXPECT_THROW(parse_fd_method("fast"), BackendError);
}

TEST(Engines, ErrorsNameWhatIsWrong) {
  const Model m = load_model("chain:3");
  BackendOptions o;
  o.max_batch = 2;
  o.fd_method = FdMethod::Hybrid;
  EXPECT_THROW(make_forward_dynamics<double>(m, o), BackendError);  // cuda only
  o.fd_method = FdMethod::Aba;
  o.fallback_aba = true;
  EXPECT_THROW(make_forward_dynamics<double>(m, o), BackendError);  // jsi only
  o.fallback_aba = false;
  o.fd_method = FdMethod::Parallel;
  EXPECT_THROW(make_forward_dynamics<double>(load_model("tree:10:1"), o), BackendError);  // chains only
  o.fd_method = FdMethod::Auto;
  auto fd = make_forward_dynamics<double>(m, o);
  std::vector<double> x(9, 0), y(9);
  using V = BatchView<const double>;
  try {  // 3 instances > max_batch 2
    fd->compute({V::soa(x.data(), 3, 3), V::soa(x.data(), 3, 3), V::soa(x.data(), 3, 3)},
                BatchView<double>::soa(y.data(), 3, 3));
    FAIL() << "no BackendError";
  } catch (const BackendError& e) {
    EXPECT_STREQ(e.what(), "batch of 3 instances exceeds the engine's max_batch 2");
  }
  try {  // tau of 2 instances
    fd->compute({V::soa(x.data(), 3, 1), V::soa(x.data(), 3, 1), V::soa(x.data(), 3, 2)},
                BatchView<double>::soa(y.data(), 3, 1));
    FAIL() << "no BackendError";
  } catch (const BackendError& e) {
    EXPECT_STREQ(e.what(), "batch sizes disagree: q 1, qd 1, tau 2, qdd 1");
  }
#if !SCANDYN_HAS_CUDA
  o.backend = BackendKind::Cuda;
  EXPECT_THROW(make_inverse_dynamics<double>(m, o), BackendError);
#endif
}

// The CUDA engines through the same factories, against the serial engines in the
// same precision. Tolerances (relative to max(1, max |row|), per precision): another
// compiler and FMA contraction; the mass matrix is the serial crba's arithmetic;
// the forward dynamics is Auto's method (aba up to 64 DoF, parallel for the
// 65-link rope, dense jsi for the 90-body tree) against the serial aba.
template <class S>
void expect_cuda_matches_serial(const Model& md) {
  const ModelTpl<S> m = md.cast<S>();
  const Index nv = m.nv();
  Inputs<S> in(nv, Layout::Aos, 9);
  const auto V = [&](const std::vector<S>& v) { return BatchView<const S>::aos(v.data(), nv, kB); };
  BackendOptions serial, cuda;
  serial.max_batch = cuda.max_batch = kB;
  cuda.backend = BackendKind::Cuda;
  const double tol = test::Tol<S>(1e-10, 1e-4), fd_tol = test::Tol<S>(1e-8, 2e-3);
  std::vector<S> a(nv * kB), b(nv * kB), Ma(nv * nv * kB), Mb(nv * nv * kB);
  const auto O = [&](std::vector<S>& v, Index w) { return BatchView<S>::aos(v.data(), w, kB); };
  const auto err = [&](const std::vector<S>& x, const std::vector<S>& y, Index w) {
    double e = 0;
    for (Index k = 0; k < kB; ++k)
      e = std::max(e, rel_err(x.data() + k * w, y.data() + k * w, static_cast<std::size_t>(w)));
    return e;
  };
  auto id = make_inverse_dynamics<S>(m, cuda);
  EXPECT_EQ(id->backend(), BackendKind::Cuda);
  make_inverse_dynamics<S>(m, serial)->compute({V(in.q), V(in.qd), V(in.x), in.fext.data()}, O(a, nv));
  id->compute({V(in.q), V(in.qd), V(in.x), in.fext.data()}, O(b, nv));
  EXPECT_LT(err(b, a, nv), tol) << "id";
  make_bias_forces<S>(m, serial)->compute({V(in.q), V(in.qd)}, O(a, nv));
  make_bias_forces<S>(m, cuda)->compute({V(in.q), V(in.qd)}, O(b, nv));
  EXPECT_LT(err(b, a, nv), tol) << "bias";
  make_mass_matrix<S>(m, serial)->compute(V(in.q), O(Ma, nv * nv));
  make_mass_matrix<S>(m, cuda)->compute(V(in.q), O(Mb, nv * nv));
  EXPECT_LT(err(Mb, Ma, nv * nv), test::Tol<S>(1e-12, 1e-5)) << "mass";
  ASSERT_TRUE(make_forward_dynamics<S>(m, serial)->compute({V(in.q), V(in.qd), V(in.x)}, O(a, nv)).ok());
  auto fd = make_forward_dynamics<S>(m, cuda);
  EXPECT_EQ(fd->method(), choose_fd_method(BackendKind::Cuda, m, 1, 1));
  const BatchStatus st = fd->compute({V(in.q), V(in.qd), V(in.x)}, O(b, nv));
  ASSERT_TRUE(st.ok()) << st.message();
  EXPECT_LT(err(b, a, nv), fd_tol) << "fd by " << to_string(fd->method());
}

TEST(Engines, CudaEnginesFromTheFactoriesMatchSerial) {
  if (const std::string why = backend_unusable(BackendKind::Cuda); !why.empty()) GTEST_SKIP() << why;
  for (const char* spec : {"iiwa", "hyq", "rope:64", "rope:65", "tree:90:3"}) {
    SCOPED_TRACE(spec);
    const Model md = load_model(spec);
    expect_cuda_matches_serial<double>(md);
    expect_cuda_matches_serial<float>(md);
  }
}
