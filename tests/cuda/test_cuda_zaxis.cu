// The z-axis thread-per-instance model (ZThreadModel: every joint frame turned so that
// its axis is +z, scandyn/model/joint_frames.hpp) against the serial double reference
// in the user's frames, on models whose joints have arbitrary axes (tree:N:SEED:
// revolute and prismatic, slanted axes, fixed links merged), coordinate axes other
// than +z (point_mass, the URDF of test_joint_frames), and the robots:
//   - on the host (the instance functions are __host__ __device__): rnea_instance,
//     mass_matrix_instance, aba_instance (chains, register slots, any tree) and
//     fd_jsi_instance, with and without external wrenches given in the user's frames;
//     double within 1e-12 (the JSI 1e-11), float within max(1e-4, 2x the same
//     functions' error on the user's frames) (relative to max(1, max |ref|));
//   - on the device (skipped, with the reason, without one): the engines that run
//     on it (inverse dynamics, bias forces, mass matrix, forward dynamics by the ABA
//     and by the joint-space inertia), double within 1e-10, float within
//     max(1e-4, 10x the host's error: the device's sin/cos is the SFU's).
#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <string>
#include <type_traits>
#include <variant>
#include <vector>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"
#include "scandyn/cuda/mass_matrix.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "cuda_test_util.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

std::vector<std::pair<std::string, Model>> models() {
  std::vector<std::pair<std::string, Model>> out;
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf", "point_mass.urdf"})
    out.emplace_back(file, test::load_robot(file));
  for (const char* spec : {"tree:7:1", "tree:20:3", "tree:40:5", "tree:64:2"}) out.emplace_back(spec, load_model(spec));
  out.emplace_back("random_model(12)", test::random_model(12, 3));
  out.emplace_back("random_model(30)", test::random_model(30, 6));
  return out;
}

// Random inputs for B instances, exactly representable in S (so that float and
// double see the same values): (nv x B) arrays, entry (i, b) at i * B + b.
struct Inputs {
  Index nv, B;
  std::vector<double> q, qd, u;
  std::vector<Force<double>> fext;  // (B x nv), user frames
  template <class S>
  static Inputs make(const Model& md, Index B, unsigned seed) {
    Inputs in{md.nv(), B, {}, {}, {}, {}};
    test::random_exact_batch<S>(in.nv, B, seed, in.q, in.qd, in.u, in.fext);
    return in;
  }
  std::vector<double> column(const std::vector<double>& v, Index b) const {
    std::vector<double> c(nv);
    for (Index i = 0; i < nv; ++i) c[i] = v[static_cast<std::size_t>(i) * B + b];
    return c;
  }
  const Force<double>* wrenches(Index b, bool fx) const {
    return fx ? fext.data() + static_cast<std::size_t>(b) * nv : nullptr;
  }
};

// The reference of instance b: tau = RNEA(q, qd, u), qdd = ABA(q, qd, u), M(q).
struct Reference {
  std::vector<double> tau, qdd, M;
};
Reference reference(const Model& md, const Inputs& in, Index b, bool fx) {
  Data d(md, false);
  const Index n = md.nv();
  Reference r{std::vector<double>(n), std::vector<double>(n), std::vector<double>(n * n)};
  const std::vector<double> q = in.column(in.q, b), qd = in.column(in.qd, b), u = in.column(in.u, b);
  rnea(md, d, q.data(), qd.data(), u.data(), r.tau.data(), in.wrenches(b, fx));
  EXPECT_TRUE(aba(md, d, q.data(), qd.data(), u.data(), r.qdd.data(), in.wrenches(b, fx)).ok());
  crba(md, d, q.data(), r.M.data());
  return r;
}

// The worst errors of the instance functions over a few instances, with and without
// external wrenches: rnea_instance, mass_matrix_instance, aba_instance (any tree;
// chains when the model has no branch children) and fd_jsi_instance.
struct HostErrors {
  double tau = 0, M = 0, aba_tree = 0, aba_chains = 0, jsi = 0;
};
void worst(double& w, double e) { w = (e <= w) ? w : e; }  // NaN sticks

template <class S, class Params>
HostErrors host_errors(const Model& md, const Params& p, Index slots) {
  constexpr int C = Params::capacity;
  const Index n = md.nv(), B = 6;
  const Inputs in = Inputs::make<S>(md, B, 17);
  const std::vector<Force<S>> fext = test::cast_wrenches<S>(in.fext);
  const std::vector<S> q(in.q.begin(), in.q.end()), qd(in.qd.begin(), in.qd.end()), u(in.u.begin(), in.u.end());
  const S nan = std::numeric_limits<S>::quiet_NaN();
  HostErrors e;
  for (bool fx : {false, true}) {
    for (Index b = 0; b < B; ++b) {
      const Reference r = reference(md, in, b, fx);
      const Force<S>* f = fx ? fext.data() + static_cast<std::size_t>(b) * n : nullptr;
      const cuda::DofColumn<const S> qc{q.data() + b, B}, qdc{qd.data() + b, B}, uc{u.data() + b, B};
      std::vector<S> tau(n, nan), qdd(n, nan), qdd_jsi(n, nan), M(n * n, nan);
      cuda::rnea_instance<S, C>(p, qc, qdc, uc, f, {tau.data(), 1});
      worst(e.tau, test::max_rel_err(tau, r.tau));
      cuda::mass_matrix_instance<S, C>(p, qc, {M.data(), 1});
      worst(e.M, test::max_rel_err(M, r.M));
      EXPECT_EQ((cuda::aba_instance<S, C, false, false, cuda::kThreadTrig<S>, C>(p, qc, qdc, uc, f, {qdd.data(), 1})), -1);
      worst(e.aba_tree, test::max_rel_err(qdd, r.qdd));
      if (slots == 0) {
        std::fill(qdd.begin(), qdd.end(), nan);
        EXPECT_EQ((cuda::aba_instance<S, C, false, false, cuda::kThreadTrig<S>, 0>(p, qc, qdc, uc, f, {qdd.data(), 1})),
                  -1);
        worst(e.aba_chains, test::max_rel_err(qdd, r.qdd));
      }
      EXPECT_EQ((cuda::fd_jsi_instance<S, C>(p, qc, qdc, uc, f, {qdd_jsi.data(), 1})), -1);
      worst(e.jsi, test::max_rel_err(qdd_jsi, r.qdd));
    }
  }
  return e;
}

template <class S, class Bd>
HostErrors host_errors(const Model& md) {
  const cuda::ThreadModel<S, Bd> tm(md.cast<S>());
  return std::visit([&](const auto& p) { return host_errors<S>(md, p, tm.branch_slots()); }, tm.params());
}

// Double: within 1e-12 of the reference. Float: within 1e-4, or within twice the
// error of the same functions on the user's frames (no accuracy lost by turning).
template <class S>
void check_host_model(const std::string& name, const Model& md) {
  SCOPED_TRACE(name + (sizeof(S) == 4 ? " float" : " double"));
  const HostErrors z = host_errors<S, ZJointBody<S>>(md);
  HostErrors tol;
  if (sizeof(S) == 8) {
    tol = {1e-12, 1e-12, 1e-12, 1e-12, 1e-11};
  } else {
    const HostErrors u = host_errors<S, Body<S>>(md);
    auto t = [](double user) { return std::max(1e-4, 2 * user); };
    tol = {t(u.tau), t(u.M), t(u.aba_tree), t(u.aba_chains), t(u.jsi)};
  }
  EXPECT_LE(z.tau, tol.tau) << "rnea_instance";
  EXPECT_LE(z.M, tol.M) << "mass_matrix_instance";
  EXPECT_LE(z.aba_tree, tol.aba_tree) << "aba_instance (tree)";
  EXPECT_LE(z.aba_chains, tol.aba_chains) << "aba_instance (chains)";
  EXPECT_LE(z.jsi, tol.jsi) << "fd_jsi_instance";
}

}  // namespace

TEST(CudaZAxisHost, InstanceFunctionsMatchTheReference) {
  for (const auto& [name, md] : models()) {
    check_host_model<double>(name, md);
    check_host_model<float>(name, md);
  }
}

TEST(CudaZAxisHost, ModelIsTurnedWhereTheAxisIsNotZ) {
  const Model md = load_model("tree:20:3");
  const ZAxisModel<double> zm = z_axis_model(md);
  const cuda::ZThreadModel<double> tm(md);
  const auto& p = std::get<cuda::ThreadModelParams<double, 32, ZJointBody<double>>>(tm.params());
  int turned = 0;
  for (Index i = 0; i < md.nv(); ++i) {
    EXPECT_EQ((p.flags[i] & cuda::kTurned) != 0, bool(zm.turned[i])) << i;
    turned += zm.turned[i];
    EXPECT_EQ(p.body[i].parent, md.bodies[i].parent);
    EXPECT_EQ(p.body[i].type, md.bodies[i].type);
  }
  EXPECT_EQ(turned, md.nv());  // the generator's axes have no zero component
  // iiwa: every axis is +z already, nothing turned, the bodies as loaded
  const Model iiwa = test::load_robot("iiwa.urdf");
  const cuda::ZThreadModel<double> ti(iiwa);
  const auto& pi = std::get<cuda::ThreadModelParams<double, 8, ZJointBody<double>>>(ti.params());
  for (Index i = 0; i < iiwa.nv(); ++i) {
    EXPECT_EQ(pi.flags[i] & cuda::kTurned, 0);
    for (int k = 0; k < 9; ++k) EXPECT_EQ(pi.body[i].Xtree.E.m[k], iiwa.bodies[i].Xtree.E.m[k]);
  }
  // a floating base is held apart (its joint is not turned: the kernels' bodies are
  // those past it); spherical joints are refused by name
  const cuda::ZThreadModel<double> tf(test::load_floating("iiwa.urdf"));
  EXPECT_TRUE(tf.floating());
  EXPECT_EQ(tf.capacity(), 8);
  const Model ball = load_model("ballrope:4");
  try {
    cuda::ZThreadModel<double> bad(ball);
    ADD_FAILURE() << "a spherical joint was accepted";
  } catch (const BackendError& e) {
    EXPECT_NE(std::string(e.what()).find("spherical joint '" + first_multi_dof_joint(ball) + "'"), std::string::npos)
        << e.what();
  }
}

// ---- device: the engines -----------------------------------------------------------

namespace {

template <class S>
void check_engines(const std::string& name, const Model& md) {
  const ModelTpl<S> m = md.cast<S>();
  const Index n = m.nv(), B = 300;
  const HostErrors host = host_errors<S, ZJointBody<S>>(md);
  const Inputs in = Inputs::make<S>(md, B, 5);
  const Inputs& ind = in;
  const std::vector<S> q(in.q.begin(), in.q.end()), qd(in.qd.begin(), in.qd.end()), u(in.u.begin(), in.u.end());
  const std::vector<Force<S>> fext = test::cast_wrenches<S>(in.fext);
  using V = BatchView<const S>;
  const V vq = V::soa(q.data(), n, B), vqd = V::soa(qd.data(), n, B), vu = V::soa(u.data(), n, B);
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  auto id = make_inverse_dynamics<S>(m, o);
  auto bias = make_bias_forces<S>(m, o);
  auto mass = make_mass_matrix<S>(m, o);
  BackendOptions oa = o, oj = o;
  oa.fd_method = FdMethod::Aba;
  oj.fd_method = FdMethod::Jsi;
  auto aba_engine = make_forward_dynamics<S>(m, oa);
  auto jsi_engine = make_forward_dynamics<S>(m, oj);
  const std::vector<S> zeros(static_cast<std::size_t>(n) * B, S(0));
  for (bool fx : {false, true}) {
    SCOPED_TRACE(name + (fx ? " with fext" : ""));
    const Force<S>* f = fx ? fext.data() : nullptr;
    std::vector<S> tau(n * B), h(n * B), qdd(n * B), qdd_jsi(n * B), M(n * n * B);
    id->compute({vq, vqd, vu, f}, BatchView<S>::soa(tau.data(), n, B));
    bias->compute({vq, vqd, f}, BatchView<S>::soa(h.data(), n, B));
    mass->compute(vq, BatchView<S>::soa(M.data(), n * n, B));
    EXPECT_EQ(aba_engine->compute({vq, vqd, vu, f}, BatchView<S>::soa(qdd.data(), n, B)).failed, 0);
    EXPECT_EQ(jsi_engine->compute({vq, vqd, vu, f}, BatchView<S>::soa(qdd_jsi.data(), n, B)).failed, 0);
    Data d(md, false);
    double worst_tau = 0, worst_h = 0, worst_M = 0, worst_qdd = 0, worst_jsi = 0;
    auto col = [&](const std::vector<S>& v, Index b, Index rows) {
      std::vector<double> c(rows);
      for (Index i = 0; i < rows; ++i) c[i] = double(v[static_cast<std::size_t>(i) * B + b]);
      return c;
    };
    for (Index b = 0; b < B; ++b) {
      const Reference r = reference(md, ind, b, fx);
      std::vector<double> href(n);
      const std::vector<double> qb = ind.column(ind.q, b), qdb = ind.column(ind.qd, b);
      bias_forces(md, d, qb.data(), qdb.data(), href.data(), ind.wrenches(b, fx));
      worst(worst_tau, test::max_rel_err(col(tau, b, n), r.tau));
      worst(worst_h, test::max_rel_err(col(h, b, n), href));
      worst(worst_M, test::max_rel_err(col(M, b, n * n), r.M));
      worst(worst_qdd, test::max_rel_err(col(qdd, b, n), r.qdd));
      worst(worst_jsi, test::max_rel_err(col(qdd_jsi, b, n), r.qdd));
    }
    // double 1e-10; float 1e-4, or 10x the same functions' error on the host (the
    // device's float sin/cos is the SFU's, the host's the library's)
    auto tol = [&](double host) { return sizeof(S) == 8 ? 1e-10 : std::max(1e-4, 10 * host); };
    EXPECT_LE(worst_tau, tol(host.tau)) << "inverse dynamics";
    EXPECT_LE(worst_h, tol(host.tau)) << "bias forces";
    EXPECT_LE(worst_M, tol(host.M)) << "mass matrix";
    EXPECT_LE(worst_qdd, tol(host.aba_tree)) << "forward dynamics (ABA)";
    EXPECT_LE(worst_jsi, 10 * tol(host.jsi)) << "forward dynamics (JSI)";
  }
}

}  // namespace

TEST(CudaZAxisDevice, EnginesMatchTheReference) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (const auto& [name, md] : models()) {
    check_engines<double>(name, md);
    check_engines<float>(name, md);
  }
}
