// The thread-per-instance kernels with a floating base (ThreadModelParams::floating:
// rnea_instance, aba_instance, crba_instance / mass_matrix_instance with kFloating):
//   - the device functions run on the host (no device needed) against the serial
//     reference's general path (rnea, aba, crba through rnea_at, aba_at, crba_at);
//   - the cuda engines (make_inverse_dynamics, make_bias_forces,
//     make_forward_dynamics, make_mass_matrix) on a device against the serial engines,
//     through compute() (q with nq columns staged) and compute_async on device buffers;
//   - the general path (GeneralPlan) for the models they do not take: spherical
//     joints, a floating base with more than 64 bodies past it.
// Models: hyq and atlas on a floating base, random trees and a random chain on a free
// root (1-DoF joints past it), a single free body.
// Tolerances (relative to the largest entry of the reference):
//   double: 1e-11 on the host (the same steps in the same order; only FMA contraction
//           differs), 1e-9 on a device (its own contraction and math library);
//   float:  against the serial float reference, 2e-4 for the robots and trees (the
//           serial float path's own error against double is ~1e-5 on these states).
#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <string>
#include <variant>
#include <vector>

#include "cuda_test_util.hpp"
#include "floating_models.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/cuda/general_dynamics.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"
#include "scandyn/cuda/mass_matrix.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

using test::max_abs;

Model floating_robot(const std::string& name) {
  BuildOptions o;
  o.require_physical_inertia = false;  // GRiD's atlas.urdf
  o.floating_base = true;
  return load_urdf(test::model_path(name + ".urdf"), o);
}

// A random tree on a free root with 1-DoF joints past it (what the thread kernels take).
Model floating_tree(int n, unsigned seed) { return test::random_floating_model(n, seed, 0.0); }

std::vector<std::pair<std::string, Model>> floating_models() {
  std::vector<std::pair<std::string, Model>> v;
  v.emplace_back("hyq floating", floating_robot("hyq"));
  v.emplace_back("atlas floating", floating_robot("atlas"));
  v.emplace_back("random floating tree 9", floating_tree(9, 3));
  v.emplace_back("random floating tree 20", floating_tree(20, 11));
  v.emplace_back("random free chain 12", test::random_free_chain(12, 5));
  v.emplace_back("single free body", floating_tree(1, 7));
  return v;
}

// max |a - b| / max(1, max |b|); NaN anywhere counts as infinite.
template <class T>
double rel_err(const std::vector<T>& a, const std::vector<double>& b) {
  double e = 0;
  for (std::size_t i = 0; i < b.size(); ++i) {
    const double d = std::abs(double(a[i]) - b[i]);
    if (!(d == d)) return INFINITY;
    e = std::max(e, d);
  }
  return e / std::max(1.0, max_abs(b));
}

// One state of a model: q (nq), qd, u (nv), fext (nbodies), random.
struct State {
  std::vector<double> q, qd, u;
  std::vector<Force<double>> fext;
};
State random_state(const Model& m, unsigned seed) {
  const test::SoaStates x = test::random_soa_states(m, 1, seed, true);
  return {x.q, x.qd, x.u, x.fext};
}

template <class S>
std::vector<S> cast(const std::vector<double>& v) {
  return std::vector<S>(v.begin(), v.end());
}
template <class S>
std::vector<Force<S>> cast(const std::vector<Force<double>>& v) {
  std::vector<Force<S>> r;
  for (const auto& f : v) r.push_back(f.template cast<S>());
  return r;
}

// The serial reference in precision S of one state: tau (rnea), qdd (aba) and M (crba,
// row-major), each as double.
template <class S>
struct Reference {
  std::vector<double> tau, qdd, M;
};
template <class S>
Reference<S> reference(const Model& md, const State& x, bool with_fext) {
  const ModelTpl<S> m = md.template cast<S>();
  DataTpl<S> d(m);
  const Index nv = m.nv();
  const auto q = cast<S>(x.q), qd = cast<S>(x.qd), u = cast<S>(x.u);
  const auto f = cast<S>(x.fext);
  const Force<S>* fp = with_fext ? f.data() : nullptr;
  std::vector<S> tau(nv), qdd(nv), M(static_cast<std::size_t>(nv * nv));
  rnea(m, d, q.data(), qd.data(), u.data(), tau.data(), fp);
  EXPECT_TRUE(aba(m, d, q.data(), qd.data(), u.data(), qdd.data(), fp).ok());
  crba(m, d, q.data(), M.data());
  return {std::vector<double>(tau.begin(), tau.end()), std::vector<double>(qdd.begin(), qdd.end()),
          std::vector<double>(M.begin(), M.end())};
}

// The device functions on the host (z-axis bodies, what the engines run), kFloating.
template <class S>
Reference<S> host_instances(const Model& md, const State& x, bool with_fext, bool unrolled_rnea) {
  const ModelTpl<S> m = md.template cast<S>();
  const cuda::ZThreadModel<S> tm(m);
  EXPECT_TRUE(tm.floating());
  const Index nv = m.nv();
  const auto q = cast<S>(x.q), qd = cast<S>(x.qd), u = cast<S>(x.u);
  const auto f = cast<S>(x.fext);
  const Force<S>* fp = with_fext ? f.data() : nullptr;
  std::vector<S> tau(nv, S(NAN)), qdd(nv, S(NAN)), M(static_cast<std::size_t>(nv * nv), S(NAN));
  Index failed = -2;
  std::visit(
      [&](const auto& p) {
        using P = std::decay_t<decltype(p)>;
        constexpr int C = P::capacity;
        using Bd = ZJointBody<S>;
        if (unrolled_rnea)
          cuda::rnea_instance<S, C, false, true, Trig::Library, Bd, true>(p, {q.data(), 1}, {qd.data(), 1},
                                                                          {u.data(), 1}, fp, {tau.data(), 1});
        else
          cuda::rnea_instance<S, C, true, false, Trig::Library, Bd, true>(p, {q.data(), 1}, {qd.data(), 1},
                                                                          {u.data(), 1}, fp, {tau.data(), 1});
        // the ABA's kernel for this shape (chains: no slots), and any tree's
        if (tm.branch_slots() == 0)
          failed = cuda::aba_instance<S, C, false, false, Trig::Library, 0, false, Bd, true>(
              p, {q.data(), 1}, {qd.data(), 1}, {u.data(), 1}, fp, {qdd.data(), 1});
        else
          failed = cuda::aba_instance<S, C, false, false, Trig::Library, C, false, Bd, true>(
              p, {q.data(), 1}, {qd.data(), 1}, {u.data(), 1}, fp, {qdd.data(), 1});
        cuda::mass_matrix_instance<S, C, false, Trig::Library, Bd, true>(p, {q.data(), 1}, {M.data(), 1});
      },
      tm.params());
  EXPECT_EQ(failed, -1);
  return {std::vector<double>(tau.begin(), tau.end()), std::vector<double>(qdd.begin(), qdd.end()),
          std::vector<double>(M.begin(), M.end())};
}

}  // namespace

TEST(CudaFloatingThreads, DeviceFunctionsOnTheHostDouble) {
  for (const auto& [name, md] : floating_models()) {
    SCOPED_TRACE(name);
    for (unsigned seed : {1u, 2u, 3u}) {
      const State x = random_state(md, seed);
      for (bool fx : {false, true}) {
        const Reference<double> ref = reference<double>(md, x, fx);
        for (bool unrolled : {false, true}) {
          const Reference<double> got = host_instances<double>(md, x, fx, unrolled);
          EXPECT_LE(rel_err(got.tau, ref.tau), 1e-11) << "rnea_instance, fext " << fx << ", unrolled " << unrolled;
          EXPECT_LE(rel_err(got.qdd, ref.qdd), 1e-11) << "aba_instance, fext " << fx;
          EXPECT_LE(rel_err(got.M, ref.M), 1e-11) << "mass_matrix_instance";
        }
      }
    }
  }
}

TEST(CudaFloatingThreads, DeviceFunctionsOnTheHostFloat) {
  for (const auto& [name, md] : floating_models()) {
    SCOPED_TRACE(name);
    const State x = random_state(md, 4);
    const Reference<float> ref = reference<float>(md, x, true);
    const Reference<float> got = host_instances<float>(md, x, true, false);
    EXPECT_LE(rel_err(got.tau, ref.tau), 2e-4);
    EXPECT_LE(rel_err(got.qdd, ref.qdd), 2e-4);
    EXPECT_LE(rel_err(got.M, ref.M), 2e-4);
  }
}

// The kernels hold the base apart: capacity from the bodies past it, offsets 7 / 6 / 1.
TEST(CudaFloatingThreads, ThreadModelShape) {
  const Model hyq = floating_robot("hyq");
  const cuda::ZThreadModel<double> tm(hyq);
  EXPECT_EQ(tm.nv(), 18);
  EXPECT_EQ(tm.nq(), 19);
  EXPECT_EQ(tm.capacity(), 16);
  EXPECT_EQ(tm.branch_slots(), 0);  // four legs hanging from the base
  std::visit(
      [](const auto& p) {
        EXPECT_EQ(p.nv, 12);
        EXPECT_EQ(p.floating, 1);
        EXPECT_EQ(cuda::q_offset(p), 7);
        EXPECT_EQ(cuda::v_offset(p), 6);
        EXPECT_EQ(cuda::model_nbodies(p), 13);
      },
      tm.params());
  // a spherical joint past the base, and the user-frame kernels: refused by name
  const Model ball = test::random_floating_model(8, 3, 1.0);
  try {
    cuda::ZThreadModel<double>{ball};
    ADD_FAILURE() << "a spherical joint was taken";
  } catch (const BackendError& e) {
    EXPECT_NE(std::string(e.what()).find("spherical joint"), std::string::npos) << e.what();
  }
  EXPECT_THROW(cuda::ThreadModel<double>{hyq}, BackendError);
}

// ---- the engines on a device ------------------------------------------------------

namespace {

// B random states (SoA: entry (i, b) at i * B + b) through the cuda engines' compute()
// and compute_async, against the serial engines, precision S.
template <class S>
void check_engines(const Model& md, Index B, double tol) {
  const ModelTpl<S> m = md.template cast<S>();
  const test::SoaStates x = test::random_soa_states(md, B, 17, true);
  const Index nv = x.nv, nq = x.nq;
  const auto q = cast<S>(x.q), qd = cast<S>(x.qd), u = cast<S>(x.u);
  const auto f = cast<S>(x.fext);
  using V = BatchView<const S>;
  const V vq = V::soa(q.data(), nq, B), vqd = V::soa(qd.data(), nv, B), vu = V::soa(u.data(), nv, B);
  BackendOptions serial, gpu;
  serial.backend = BackendKind::Serial;
  gpu.backend = BackendKind::Cuda;
  serial.max_batch = gpu.max_batch = B;
  const auto run = [&](const BackendOptions& o, std::vector<S>& tau, std::vector<S>& h, std::vector<S>& qdd,
                       std::vector<S>& M) {
    tau.assign(static_cast<std::size_t>(nv * B), S(NAN));
    h = qdd = tau;
    M.assign(static_cast<std::size_t>(nv * nv * B), S(NAN));
    make_inverse_dynamics(m, o)->compute({vq, vqd, vu, f.data()}, BatchView<S>::soa(tau.data(), nv, B));
    make_bias_forces(m, o)->compute({vq, vqd, f.data()}, BatchView<S>::soa(h.data(), nv, B));
    const BatchStatus st = make_forward_dynamics(m, o)->compute({vq, vqd, vu, f.data()},
                                                                 BatchView<S>::soa(qdd.data(), nv, B));
    EXPECT_EQ(st.failed, 0);
    // M row-major per instance: (B, nv, nv)
    make_mass_matrix(m, o)->compute(vq, BatchView<S>::aos(M.data(), nv * nv, B));
  };
  std::vector<S> tau_s, h_s, qdd_s, M_s, tau_g, h_g, qdd_g, M_g;
  run(serial, tau_s, h_s, qdd_s, M_s);
  run(gpu, tau_g, h_g, qdd_g, M_g);
  const auto as_double = [](const std::vector<S>& v) { return std::vector<double>(v.begin(), v.end()); };
  EXPECT_LE(rel_err(tau_g, as_double(tau_s)), tol) << "inverse dynamics";
  EXPECT_LE(rel_err(h_g, as_double(h_s)), tol) << "bias forces";
  EXPECT_LE(rel_err(qdd_g, as_double(qdd_s)), tol) << "forward dynamics";
  EXPECT_LE(rel_err(M_g, as_double(M_s)), tol) << "mass matrix";

  // compute_async on device buffers: the thread kernels straight from device memory
  test::DeviceArray<S> dq, dqd, du, dout;
  test::DeviceArray<Force<S>> df;
  const auto up = [](auto& d, const auto& h) {
    EXPECT_EQ(d.alloc(h.size()), cudaSuccess);
    EXPECT_EQ(cudaMemcpy(d.ptr, h.data(), h.size() * sizeof(h[0]), cudaMemcpyHostToDevice), cudaSuccess);
    return d.ptr;
  };
  const V dvq = V::soa(up(dq, q), nq, B), dvqd = V::soa(up(dqd, qd), nv, B), dvu = V::soa(up(du, u), nv, B);
  const Force<S>* dfp = up(df, f);
  ASSERT_EQ(dout.alloc(static_cast<std::size_t>(nv * nv * B)), cudaSuccess);
  std::vector<S> back(static_cast<std::size_t>(nv * B));
  auto id = cuda::CudaInverseDynamics<S>(m, gpu);
  ASSERT_EQ(id.compute_async({dvq, dvqd, dvu, dfp}, BatchView<S>::soa(dout.ptr, nv, B), nullptr), cudaSuccess);
  ASSERT_EQ(cudaMemcpy(back.data(), dout.ptr, back.size() * sizeof(S), cudaMemcpyDeviceToHost), cudaSuccess);
  EXPECT_LE(rel_err(back, as_double(tau_s)), tol) << "inverse dynamics, device buffers";
  cuda::CudaForwardDynamics<S> fd(m, gpu);
  test::DeviceArray<int> dfailed;
  ASSERT_EQ(dfailed.alloc(static_cast<std::size_t>(B)), cudaSuccess);
  ASSERT_EQ(fd.compute_async({dvq, dvqd, dvu, dfp}, BatchView<S>::soa(dout.ptr, nv, B), dfailed.ptr, nullptr),
            cudaSuccess);
  ASSERT_EQ(cudaMemcpy(back.data(), dout.ptr, back.size() * sizeof(S), cudaMemcpyDeviceToHost), cudaSuccess);
  EXPECT_LE(rel_err(back, as_double(qdd_s)), tol) << "forward dynamics, device buffers";
  cuda::CudaMassMatrix<S> mass(m, gpu);
  std::vector<S> Mb(static_cast<std::size_t>(nv * nv * B));
  ASSERT_EQ(mass.compute_async(dvq, BatchView<S>::soa(dout.ptr, nv * nv, B), nullptr), cudaSuccess);
  ASSERT_EQ(cudaMemcpy(Mb.data(), dout.ptr, Mb.size() * sizeof(S), cudaMemcpyDeviceToHost), cudaSuccess);
  std::vector<S> Mt(Mb.size());  // SoA (entry e of instance b at e * B + b) -> (B, nv, nv)
  for (Index b = 0; b < B; ++b)
    for (Index e = 0; e < nv * nv; ++e) Mt[static_cast<std::size_t>(b * nv * nv + e)] = Mb[static_cast<std::size_t>(e * B + b)];
  EXPECT_LE(rel_err(Mt, as_double(M_s)), tol) << "mass matrix, device buffers (unstaged kernel)";
}

}  // namespace

TEST(CudaFloatingThreads, EnginesAgainstSerial) {
  SKIP_WITHOUT_CUDA_DEVICE();
  std::string left_out;  // models whose floating-base kernels the library's build leaves out (its engines say so)
  for (const auto& [name, md] : floating_models()) {
    SCOPED_TRACE(name);
    try {
      BackendOptions o;
      o.backend = BackendKind::Cuda;
      (void)make_forward_dynamics(md, o);
    } catch (const BackendError& e) {
      if (std::string(e.what()).find("compiles the floating-base kernels for") == std::string::npos) throw;
      left_out += std::string(left_out.empty() ? "" : "; ") + e.what();
      continue;
    }
    check_engines<double>(md, 37, 1e-9);
    check_engines<float>(md, 37, 2e-4);
  }
  if (!left_out.empty()) GTEST_SKIP() << "the other models passed; left out by this build: " << left_out;
}

// Models the thread kernels do not take run the general path (GeneralPlan: aba_general,
// crba_general per thread; inverse dynamics and bias forces by the link scans):
// spherical joints on a floating or a fixed root, and a floating tree of 70 bodies
// (beyond the kernels' 64). Against the serial engines as above; float 1e-3 for the
// 70-body tree (its float conditioning: the serial float and device float paths
// round differently over 70 bodies).
TEST(CudaFloatingThreads, GeneralPathAgainstSerial) {
  SKIP_WITHOUT_CUDA_DEVICE();
  std::vector<std::pair<std::string, Model>> cases;
  cases.emplace_back("random floating tree 10, spherical joints", test::random_floating_model(10, 5, 0.5));
  cases.emplace_back("random floating tree 24, spherical joints", test::random_floating_model(24, 4, 0.3));
  cases.emplace_back("ballrope:6", load_model("ballrope:6"));
  cases.emplace_back("random floating tree 70", test::random_floating_model(70, 9, 0.0));
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  for (const auto& [name, md] : cases) {
    SCOPED_TRACE(name);
    EXPECT_EQ(make_forward_dynamics(md, o)->strategy().rfind("aba_general", 0), 0u);
    EXPECT_EQ(make_mass_matrix(md, o)->strategy(), "crba_general");
    check_engines<double>(md, 37, 1e-9);
    check_engines<float>(md, 37, md.nbodies() > 64 ? 1e-3 : 2e-4);
  }
}

// FdMethod::Aba on models of 1-DoF joints beyond the thread kernels' kMaxThreadDofs
// runs the general path too (aba_general; issue 22): a fixed-base chain and trees of
// 100 and 300 DoFs against the serial engines, in every scratch layout
// (GeneralInterleave) and both ways of running an instance (GeneralAba: a thread, or
// a warp over the tree's levels).
TEST(CudaFloatingThreads, GeneralAbaBeyondTheThreadKernels) {
  SKIP_WITHOUT_CUDA_DEVICE();
  EXPECT_EQ(cuda::general_aba_from_env(), cuda::GeneralAba::Thread);
  for (const char* spec : {"rope:100", "tree:100:4", "tree:300:7"}) {
    SCOPED_TRACE(spec);
    const Model md = load_model(spec);
    const Index B = 67, nv = md.nv();
    const test::SoaStates x = test::random_soa_states(md, B, 5, true);
    using V = BatchView<const double>;
    const FdBatchIn<double> in{V::soa(x.q.data(), nv, B), V::soa(x.qd.data(), nv, B), V::soa(x.u.data(), nv, B),
                               x.fext.data()};
    BackendOptions o;
    o.backend = BackendKind::Serial;
    o.max_batch = B;
    std::vector<double> ref(static_cast<std::size_t>(nv * B));
    ASSERT_EQ(make_forward_dynamics(md, o)->compute(in, BatchView<double>::soa(ref.data(), nv, B)).failed, 0);
    o.backend = BackendKind::Cuda;
    o.fd_method = FdMethod::Aba;
    for (const char* aba : {"thread", "levels"})
      for (const char* layout : {"instance", "structs", "scalars"}) {
        SCOPED_TRACE(std::string(aba) + " " + layout);
        setenv("SCANDYN_GENERAL_ABA", aba, 1);
        setenv("SCANDYN_GENERAL_INTERLEAVE", layout, 1);
        const auto e = make_forward_dynamics(md, o);
        EXPECT_EQ(e->strategy().rfind("aba_general", 0), 0u);
        std::vector<double> qdd(ref.size(), NAN);
        EXPECT_EQ(e->compute(in, BatchView<double>::soa(qdd.data(), nv, B)).failed, 0);
        EXPECT_LE(rel_err(qdd, ref), 1e-9);
      }
    unsetenv("SCANDYN_GENERAL_INTERLEAVE");
    unsetenv("SCANDYN_GENERAL_ABA");
  }
}


namespace {
// qdd and the failed DoFs of B instances x by plan.launch_aba.
void general_plan_aba(const cuda::GeneralPlan<double>& plan, const test::SoaStates& x, Index B,
                      std::vector<double>& qdd, std::vector<int>& failed) {
  test::DeviceArray<double> dq, dqd, du, dqdd;
  test::DeviceArray<Force<double>> df;
  test::DeviceArray<int> dfailed;
  const auto up = [](auto& d, const auto& h) {
    EXPECT_EQ(d.alloc(h.size()), cudaSuccess);
    EXPECT_EQ(cudaMemcpy(d.ptr, h.data(), h.size() * sizeof(h[0]), cudaMemcpyHostToDevice), cudaSuccess);
    return d.ptr;
  };
  using V = BatchView<const double>;
  const FdBatchIn<double> in{V::soa(up(dq, x.q), x.nq, B), V::soa(up(dqd, x.qd), x.nv, B), V::soa(up(du, x.u), x.nv, B),
                             up(df, x.fext)};
  ASSERT_EQ(dqdd.alloc(x.qd.size()), cudaSuccess);
  ASSERT_EQ(cudaMemset(dqdd.ptr, 0, x.qd.size() * sizeof(double)), cudaSuccess);
  ASSERT_EQ(dfailed.alloc(static_cast<std::size_t>(B)), cudaSuccess);
  ASSERT_EQ(plan.launch_aba(in, BatchView<double>::soa(dqdd.ptr, x.nv, B), dfailed.ptr, nullptr), cudaSuccess);
  qdd.assign(x.qd.size(), 0);
  failed.assign(static_cast<std::size_t>(B), 0);
  ASSERT_EQ(cudaMemcpy(qdd.data(), dqdd.ptr, qdd.size() * sizeof(double), cudaMemcpyDeviceToHost), cudaSuccess);
  ASSERT_EQ(cudaMemcpy(failed.data(), dfailed.ptr, failed.size() * sizeof(int), cudaMemcpyDeviceToHost), cudaSuccess);
}
}  // namespace

// GeneralAba::Levels on a floating base with spherical joints (multi-DoF joints in
// the levels), with fewer warp slots than instances; and a failed pivot: a massless
// leaf makes the serial ABA stop at that leaf's DoF, and the level kernel reports the
// same DoF (the highest that fails) and leaves that instance's qdd unwritten.
TEST(CudaFloatingThreads, GeneralAbaLevels) {
  SKIP_WITHOUT_CUDA_DEVICE();
  Model md = test::random_floating_model(40, 11, 0.3);
  const Index B = 300;
  const test::SoaStates x = test::random_soa_states(md, B, 6, true);
  const std::size_t slice = cuda::GeneralLayout<double>::make(md.nbodies(), md.nv(), md.nq() + 3 * md.nv(), 0).bytes;
  std::vector<double> qdd;
  std::vector<int> failed;
  {
    const cuda::GeneralPlan<double> plan(md, B, 0, 0, 70 * slice, cuda::GeneralInterleave::Scalars,
                                         cuda::GeneralAba::Levels);
    ASSERT_EQ(plan.args().slots, 70);
    ASSERT_EQ(plan.args().interleave, cuda::GeneralInterleave::Instance);
    general_plan_aba(plan, x, B, qdd, failed);
    EXPECT_EQ(std::count(failed.begin(), failed.end(), -1), B);
    EXPECT_LE(rel_err(qdd, test::soa_reference(md, x, true)), 1e-9);
  }
  // a massless 1-DoF leaf: its pivot D = S^T I S = 0
  Index leaf = -1;
  for (Index i = md.nbodies() - 1; i > 0 && leaf < 0; --i) {
    bool has_child = false;
    for (const auto& b : md.bodies) has_child = has_child || b.parent == i;
    if (!has_child && joint_nv(md.bodies[static_cast<std::size_t>(i)].type) == 1) leaf = i;
  }
  ASSERT_GE(leaf, 0);
  md.bodies[static_cast<std::size_t>(leaf)].I = Inertia<double>::zero();
  const cuda::GeneralPlan<double> plan(md, B, 0, 0, 0, cuda::GeneralInterleave::Scalars, cuda::GeneralAba::Levels);
  general_plan_aba(plan, x, B, qdd, failed);
  const Index dof = md.bodies[static_cast<std::size_t>(leaf)].idx_v;
  EXPECT_EQ(std::count(failed.begin(), failed.end(), static_cast<int>(dof)), B);
  EXPECT_EQ(*std::max_element(qdd.begin(), qdd.end()), 0.0);
  EXPECT_EQ(*std::min_element(qdd.begin(), qdd.end()), 0.0);
}

// The three scratch layouts give the general path the same results: ballrope:6's fd
// and mass matrix against the serial engines in each.
TEST(CudaFloatingThreads, GeneralPathEveryInterleave) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model md = load_model("ballrope:6");
  for (const char* layout : {"instance", "structs", "scalars"}) {
    SCOPED_TRACE(layout);
    setenv("SCANDYN_GENERAL_INTERLEAVE", layout, 1);
    check_engines<double>(md, 37, 1e-9);
    check_engines<float>(md, 37, 2e-4);
  }
  unsetenv("SCANDYN_GENERAL_INTERLEAVE");
}

// A GeneralPlan with fewer slots than instances (a small budget): each thread takes
// instances t, t + slots, ...; every instance's qdd equals the serial ABA's.
TEST(CudaFloatingThreads, GeneralPlanThreadsTakeSeveralInstances) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model md = test::random_floating_model(30, 8, 0.3);
  const Index B = 1000;
  const test::SoaStates x = test::random_soa_states(md, B, 4, true);
  const std::size_t slice = cuda::GeneralLayout<double>::make(md.nbodies(), md.nv(), md.nq() + 3 * md.nv(), 0).bytes;
  const cuda::GeneralPlan<double> plan(md, B, 0, 0, 50 * slice);
  ASSERT_EQ(plan.args().slots, 50);
  std::vector<double> qdd;
  std::vector<int> failed;
  general_plan_aba(plan, x, B, qdd, failed);
  EXPECT_EQ(std::count(failed.begin(), failed.end(), -1), B);
  EXPECT_LE(rel_err(qdd, test::soa_reference(md, x, true)), 1e-9);
}
