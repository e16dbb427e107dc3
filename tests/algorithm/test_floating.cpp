// Multi-DoF joints (free floating base, spherical joints): the reference
// algorithms' general path against closed forms (a single free body), identities on
// random floating trees and the floating robots, float against double, the CPU
// engines against the reference, and the loader's errors. Pinocchio's free flyer
// is the independent check of scripts/check_pinocchio.py (ctest pinocchio_crosscheck).
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <random>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "floating_models.hpp"
#include "identities.hpp"
#include "test_util.hpp"

using namespace scandyn;
using test::check_identities;
using test::max_rel_err;
using test::random_floating_model;
using test::random_q;
using test::Tol;

namespace {

BuildOptions floating_options() {
  BuildOptions o;
  o.require_physical_inertia = false;  // GRiD's atlas.urdf
  o.floating_base = true;
  return o;
}

}  // namespace

TEST(FloatingModel, Dimensions) {
  const Model hyq = load_model("hyq", floating_options());
  EXPECT_EQ(hyq.nv(), 18);
  EXPECT_EQ(hyq.nq(), 19);
  EXPECT_EQ(hyq.nbodies(), 13);
  EXPECT_TRUE(hyq.floating_base());
  EXPECT_EQ(hyq.bodies[0].type, JointType::Free);
  EXPECT_EQ(hyq.bodies[1].idx_q, 7);
  EXPECT_EQ(hyq.bodies[1].idx_v, 6);
  EXPECT_EQ(hyq.link_names[0], hyq.root_link);
  const Model fixed = load_model("hyq");
  EXPECT_FALSE(fixed.multi_dof());
  EXPECT_EQ(fixed.nq(), fixed.nv());

  const Model ball = load_model("ballrope:5");
  EXPECT_EQ(ball.nv(), 15);
  EXPECT_EQ(ball.nq(), 20);
  EXPECT_FALSE(ball.floating_base());
  BuildOptions o;
  o.floating_base = true;
  const Model free_ball = load_model("ballrope:5", o);  // the first link free, 4 ball joints
  EXPECT_EQ(free_ball.nv(), 6 + 12);
  EXPECT_EQ(free_ball.nq(), 7 + 16);
  const Model free_rope = load_model("rope:100", o);
  EXPECT_EQ(free_rope.nbodies(), 100);
  EXPECT_EQ(free_rope.nv(), 6 + 99);
  const ModelTpl<float> f = free_rope.cast<float>();
  EXPECT_EQ(f.nq(), free_rope.nq());
  EXPECT_EQ(f.bodies[50].idx_v, free_rope.bodies[50].idx_v);
}

TEST(FloatingModel, Errors) {
  BuildOptions o;
  o.floating_base = true;
  // a root that is the world frame (the robot is bolted to it)
  RawTree t = generate_tree("chain:2");
  t.links[0].name = "world";
  t.joints[0].parent = "world";
  try {
    build_model(t, o);
    FAIL() << "expected ModelError";
  } catch (const ModelError& e) {
    EXPECT_NE(std::string(e.what()).find("link 'world'"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("world frame"), std::string::npos) << e.what();
  }
  // a massless floating base
  try {
    load_model("curtain:2:3", o);
    FAIL() << "expected ModelError";
  } catch (const ModelError& e) {
    EXPECT_NE(std::string(e.what()).find("link 'rod'"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("no mass"), std::string::npos) << e.what();
  }
  // URDF floating joints stay unsupported (the free joint comes from the option)
  RawTree u = generate_tree("chain:2");
  u.joints[1].type = RawJointType::Floating;
  u.joints[1].type_name = "floating";
  EXPECT_THROW(build_model(u, o), ModelError);
}

// A single free body with its origin at the centre of mass and principal axes along
// the body frame: Euler's equations I wd = (I w) x w and, with no force, the origin's
// acceleration zero, i.e. the body-frame derivative vd = -w x v; with gravity, at
// rest, vd = R^T g.
TEST(FloatingClosedForm, SingleFreeBody) {
  const Vec3<double> Id{0.3, 0.5, 0.9};
  Model m = test::free_body_model(2.0, {0, 0, 0}, Id);
  ASSERT_EQ(m.nv(), 6);
  ASSERT_EQ(m.nq(), 7);
  Data data(m);
  std::vector<double> qv = {0.3, -1.0, 2.0, 0.2, -0.5, 0.4, 0.7};  // quaternion normalised below
  const double nq = std::sqrt(qv[3] * qv[3] + qv[4] * qv[4] + qv[5] * qv[5] + qv[6] * qv[6]);
  for (int k = 3; k < 7; ++k) qv[k] /= nq;
  const double qd[6] = {0.7, -1.3, 2.1, 0.4, 0.9, -0.2};
  const double tau[6] = {0, 0, 0, 0, 0, 0};
  double qdd[6];
  ASSERT_TRUE(aba(m, data, qv.data(), qd, tau, qdd).ok());
  const Vec3<double> w{qd[0], qd[1], qd[2]}, v{qd[3], qd[4], qd[5]};
  const Vec3<double> Iw{Id.x * w.x, Id.y * w.y, Id.z * w.z};
  const Vec3<double> c = cross(Iw, w);
  const Vec3<double> wd{c.x / Id.x, c.y / Id.y, c.z / Id.z};
  const Vec3<double> vd = -cross(w, v);
  for (int k = 0; k < 3; ++k) {
    EXPECT_NEAR(qdd[k], wd[k], 1e-14) << "Euler's equations, component " << k;
    EXPECT_NEAR(qdd[3 + k], vd[k], 1e-14) << "force-free origin, component " << k;
  }
  // at rest under gravity: vd = R^T g, no rotation
  m.gravity = {0.3, -0.4, -9.81};
  const double rest[6] = {0, 0, 0, 0, 0, 0};
  ASSERT_TRUE(aba(m, data, qv.data(), rest, tau, qdd).ok());
  const Vec3<double> g_body = mul_transpose(quat_to_matrix(qv.data() + 3), m.gravity);
  for (int k = 0; k < 3; ++k) {
    EXPECT_NEAR(qdd[k], 0.0, 1e-14);
    EXPECT_NEAR(qdd[3 + k], g_body[k], 1e-14);
  }
  // inverse dynamics of a body held still against gravity: the wrench m (-R^T g)
  double tau_hold[6];
  rnea(m, data, qv.data(), rest, rest, tau_hold);
  for (int k = 0; k < 3; ++k) {
    EXPECT_NEAR(tau_hold[k], 0.0, 1e-13);
    EXPECT_NEAR(tau_hold[3 + k], -2.0 * g_body[k], 1e-13);
  }
}

class RandomFloatingTrees : public ::testing::TestWithParam<int> {};

TEST_P(RandomFloatingTrees, IdentitiesDouble) {
  const int n = GetParam();
  for (unsigned seed = 1; seed <= 3; ++seed)
    check_identities<double>(test::random_floating_model(n, seed * 31 + n), seed, "n=" + std::to_string(n));
}
TEST_P(RandomFloatingTrees, IdentitiesFloat) {
  const int n = GetParam();
  check_identities<float>(test::random_floating_model(n, 3 * n + 2), 7, "n=" + std::to_string(n));
}
INSTANTIATE_TEST_SUITE_P(Sizes, RandomFloatingTrees, ::testing::Values(1, 2, 3, 5, 8, 13, 30, 64));

TEST(FloatingRobots, Identities) {
  for (const char* f : {"iiwa", "hyq", "atlas"}) {
    const Model m = load_model(f, floating_options());
    check_identities<double>(m, 11, std::string(f) + " floating double");
    check_identities<float>(m, 12, std::string(f) + " floating float");
  }
  BuildOptions o;
  o.floating_base = true;
  for (const char* spec : {"rope:50", "ballrope:20", "tree:40:3", "chain:7"})
    check_identities<double>(load_model(spec, o), 21, std::string(spec) + " floating");
  check_identities<double>(load_model("ballrope:20"), 22, "ballrope:20");
}

// float results against the double reference on the same inputs (floating robots).
TEST(FloatingPrecision, FloatVsDouble) {
  for (const char* f : {"hyq", "atlas"}) test::check_float_vs_double(load_model(f, floating_options()), f);
}

// External wrenches: ABA with them inverts RNEA with them (fext per body).
TEST(FloatingExternalForces, AbaInvertsRnea) {
  const Model m = test::random_floating_model(13, 5);
  Data data(m);
  std::mt19937_64 rng(3);
  const auto q = random_q(m, rng);
  const auto qd = test::random_vector(rng, m.nv(), -1, 1), qdd = test::random_vector(rng, m.nv(), -1, 1);
  const auto fext = test::random_wrenches<double>(rng, m.nbodies(), 3);
  std::vector<double> tau(m.nv()), back(m.nv()), armature(m.nv(), 0.25), tau_arm(m.nv());
  rnea(m, data, q.data(), qd.data(), qdd.data(), tau.data(), fext.data());
  ASSERT_TRUE(aba(m, data, q.data(), qd.data(), tau.data(), back.data(), fext.data()).ok());
  EXPECT_LT(max_rel_err(back, qdd), 1e-10);
  // armature: (M + diag(a)) qdd + h = tau
  for (Index i = 0; i < m.nv(); ++i) tau_arm[i] = tau[i] + armature[i] * qdd[i];
  ASSERT_TRUE(aba(m, data, q.data(), qd.data(), tau_arm.data(), back.data(), fext.data(), armature.data()).ok());
  EXPECT_LT(max_rel_err(back, qdd), 1e-10) << "aba with armature";
  ASSERT_TRUE(fd_jsi(m, data, q.data(), qd.data(), tau_arm.data(), back.data(), fext.data(), armature.data()).ok());
  EXPECT_LT(max_rel_err(back, qdd), 1e-10) << "fd_jsi with armature";
}

// A massless spherical leaf: a pivot of its joint fails (ABA factors the joint's
// 3x3 D from its first DoF, the L^T L factorisation of M runs from the last DoF).
TEST(FloatingFailure, SingularPivotIsReported) {
  Model m = test::random_floating_model(4, 9);
  m.bodies[3].type = JointType::Spherical;
  m.bodies[3].I = Inertia<double>::zero();
  m.bodies[3].parent = 2;
  set_joint_offsets(m);
  Data data(m);
  std::mt19937_64 rng(1);
  const auto q = random_q(m, rng);
  const std::vector<double> qd(m.nv(), 0.0), tau(m.nv(), 1.0);
  std::vector<double> qdd(m.nv());
  EXPECT_EQ(aba(m, data, q.data(), qd.data(), tau.data(), qdd.data()).failed_dof, m.bodies[3].idx_v);
  const Index failed = fd_jsi(m, data, q.data(), qd.data(), tau.data(), qdd.data()).failed_dof;
  EXPECT_GE(failed, m.bodies[3].idx_v);
  EXPECT_LT(failed, m.bodies[3].idx_v + 3);
}

// The CPU engines (serial and OpenMP) compute exactly the reference on a floating
// model, in both layouts (the link scans to rounding); what they do not take is a
// BackendError.
TEST(FloatingEngines, CpuEnginesMatchReference) {
  const Model m = load_model("hyq", floating_options());
  const Index B = 37, nq = m.nq(), nv = m.nv();
  std::mt19937_64 rng(4);
  std::vector<double> q, qd = test::random_vector(rng, nv * B, -2, 2), u = test::random_vector(rng, nv * B, -5, 5);
  for (Index b = 0; b < B; ++b) {
    const auto qb = random_q(m, rng);
    q.insert(q.end(), qb.begin(), qb.end());
  }
  Data data(m);
  std::vector<double> ref_fd(nv * B), ref_id(nv * B), ref_M(nv * nv * B);
  for (Index b = 0; b < B; ++b) {
    ASSERT_TRUE(aba(m, data, &q[b * nq], &qd[b * nv], &u[b * nv], &ref_fd[b * nv]).ok());
    rnea(m, data, &q[b * nq], &qd[b * nv], &u[b * nv], &ref_id[b * nv]);
    crba(m, data, &q[b * nq], &ref_M[b * nv * nv]);
  }
  using V = BatchView<const double>;
  for (BackendKind kind : {BackendKind::Serial, BackendKind::OpenMP}) {
    SCOPED_TRACE(to_string(kind));
    BackendOptions o;
    o.backend = kind;
    o.max_batch = B;
    o.threads = 3;
    std::vector<double> out(nv * B), M(nv * nv * B);
    auto fd = make_forward_dynamics<double>(m, o);
    EXPECT_EQ(fd->method(), FdMethod::Aba);
    ASSERT_TRUE(fd->compute(FdBatchIn<double>{V::aos(q.data(), nq, B), V::aos(qd.data(), nv, B), V::aos(u.data(), nv, B)},
                            BatchView<double>::aos(out.data(), nv, B)).ok());
    EXPECT_EQ(out, ref_fd);
    auto id = make_inverse_dynamics<double>(m, o);
    id->compute(IdBatchIn<double>{V::aos(q.data(), nq, B), V::aos(qd.data(), nv, B), V::aos(u.data(), nv, B)},
                BatchView<double>::aos(out.data(), nv, B));
    EXPECT_EQ(out, ref_id);
    // structure of arrays: entry (i, b) at i * B + b
    std::vector<double> q_soa(q.size());
    for (Index b = 0; b < B; ++b)
      for (Index i = 0; i < nq; ++i) q_soa[i * B + b] = q[b * nq + i];
    auto mass = make_mass_matrix<double>(m, o);
    std::vector<double> M_soa(nv * nv * B);
    mass->compute(V::soa(q_soa.data(), nq, B), BatchView<double>::soa(M_soa.data(), nv * nv, B));
    for (Index b = 0; b < B; ++b)
      for (Index k = 0; k < nv * nv; ++k) ASSERT_EQ(M_soa[k * B + b], ref_M[b * nv * nv + k]);
    BackendOptions scan = o;  // the link scans take the floating base (tests/scan/test_scan_floating.cpp)
    scan.strategy = IdStrategy::ScanLocal;
    make_inverse_dynamics<double>(m, scan)->compute(
        IdBatchIn<double>{V::aos(q.data(), nq, B), V::aos(qd.data(), nv, B), V::aos(u.data(), nv, B)},
        BatchView<double>::aos(out.data(), nv, B));
    EXPECT_LT(max_rel_err(out, ref_id), 1e-10);
    BackendOptions par = o;  // hyq is a tree: the parallel chain forward dynamics refuses it
    par.fd_method = FdMethod::Parallel;
    EXPECT_THROW(make_forward_dynamics<double>(m, par), BackendError);
  }
}

// The cuda backend with spherical joints: forward dynamics and the mass matrix by the
// general path, inverse dynamics and bias forces by the link scans, where a device is
// usable (results: tests/cuda/test_cuda_floating_threads.cu); else (no device, or a
// build without CUDA) every factory throws a BackendError saying why.
TEST(FloatingEngines, CudaSphericalJoints) {
  const Model m = load_model("ballrope:3");
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  if (!backend_unusable(BackendKind::Cuda).empty()) {  // no device (or no CUDA build): every factory says so
    EXPECT_THROW(make_forward_dynamics<double>(m, o), BackendError);
    EXPECT_THROW(make_mass_matrix<double>(m, o), BackendError);
    EXPECT_THROW(make_inverse_dynamics<double>(m, o), BackendError);
    EXPECT_THROW(make_bias_forces<float>(m.cast<float>(), o), BackendError);
    return;
  }
  // the general path (test_cuda_floating_threads checks its results)
  EXPECT_EQ(make_forward_dynamics<double>(m, o)->strategy().rfind("aba_general", 0), 0u);
  EXPECT_EQ(make_mass_matrix<double>(m, o)->strategy(), "crba_general");
}
