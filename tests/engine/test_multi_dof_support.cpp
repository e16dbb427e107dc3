// What takes multi-DoF joints (a floating base, spherical joints) beyond the dynamics
// engines, and what refuses them. Kinematics: frame poses and Jacobians on the CPU
// engines against closed forms (the root link of a floating base is where q puts it)
// and central differences along q ⊕ v h (configuration.hpp); Pinocchio's free flyer
// checks the floating robots in scripts/check_pinocchio.py (ctest pinocchio_crosscheck).
// Refused, with the feature and the joint named: derivatives, hybrid dynamics, the
// forward-dynamics check when asked for, the SIMD path when forced, closed loops.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <string>
#include <vector>

#include "scandyn/algorithm/configuration.hpp"
#include "scandyn/algorithm/fd_check_batch.hpp"
#include "scandyn/algorithm/loops.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/spatial/quaternion.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

std::vector<Index> all_frames(const Model& m) {
  std::vector<Index> f;
  for (Index k = 0; k < Index(m.frames.size()); ++k) f.push_back(k);
  return f;
}

// poses (F x 12, the 3 x 4 top of each matrix) and J (F x 6 x nv) of one instance
void kinematics(const Model& m, const std::vector<double>& q, FrameReference ref, std::vector<double>& poses,
                std::vector<double>& J, BackendKind backend = BackendKind::Serial) {
  BackendOptions o;
  o.backend = backend;
  KinematicsOptions k;
  k.frames = all_frames(m);
  k.reference = ref;
  const auto e = make_kinematics(m, o, k);
  const Index F = Index(k.frames.size()), nv = m.nv();
  poses.assign(std::size_t(F * 16), 0.0);
  J.assign(std::size_t(F * 6 * nv), 0.0);
  e->compute(BatchView<const double>::aos(q.data(), m.nq(), 1), BatchView<double>::aos(poses.data(), F * 16, 1),
             BatchView<double>::aos(J.data(), F * 6 * nv, 1));
}

Mat3<double> rotation(const std::vector<double>& poses, Index k) {
  Mat3<double> R;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) R(r, c) = poses[std::size_t(k * 16 + 4 * r + c)];
  return R;
}

template <class F>
void expect_throws_naming(F f, const std::vector<std::string>& words) {
  try {
    f();
    ADD_FAILURE() << "no error";
  } catch (const std::exception& e) {
    for (const std::string& w : words) EXPECT_NE(std::string(e.what()).find(w), std::string::npos) << e.what();
  }
}

}  // namespace

// The root link of a floating base sits where q puts it: p = q[0..2], R = quat(q[3..6]).
TEST(MultiDofKinematics, FloatingRootLinkIsTheBasePose) {
  for (const char* spec : {"hyq", "atlas", "tree:20:3"}) {
    const Model m = test::load_floating(spec);
    std::mt19937_64 rng(7);
    const std::vector<double> q = test::random_q(m, rng);
    std::vector<double> poses, J;
    kinematics(m, q, FrameReference::World, poses, J);
    ASSERT_EQ(m.frame_names[0], m.root_link);
    const Mat3<double> R = quat_to_matrix(q.data() + 3), got = rotation(poses, 0);
    for (int r = 0; r < 3; ++r) {
      EXPECT_NEAR(poses[std::size_t(4 * r + 3)], q[std::size_t(r)], 1e-14) << spec;
      for (int c = 0; c < 3; ++c) EXPECT_NEAR(got(r, c), R(r, c), 1e-14) << spec;
    }
  }
}

// J v = the frame's [w; v] by central differences of its pose along q ⊕ v h, world
// axes (v of the frame's origin) and the frame's own axes; floating bases and ball joints.
TEST(MultiDofKinematics, JacobianIsTheDerivativeAlongTheManifold) {
  for (const char* spec : {"hyq", "tree:12:5", "ballrope:5"}) {
    const Model m = std::string(spec).rfind("ballrope", 0) == 0 ? load_model(spec) : test::load_floating(spec);
    SCOPED_TRACE(spec);
    std::mt19937_64 rng(11);
    const std::vector<double> q = test::random_q(m, rng);
    const std::vector<double> v = test::random_vector(rng, int(m.nv()), -1, 1);
    const double h = 1e-6;
    std::vector<double> qp = q, qm = q;
    integrate_configuration(m, qp.data(), v.data(), h);
    integrate_configuration(m, qm.data(), v.data(), -h);
    std::vector<double> P, Jw, Pp, Pm, Jl, scratch;
    kinematics(m, q, FrameReference::World, P, Jw);
    kinematics(m, q, FrameReference::Local, P, Jl);
    kinematics(m, qp, FrameReference::World, Pp, scratch);
    kinematics(m, qm, FrameReference::World, Pm, scratch);
    const Index nv = m.nv();
    for (Index k = 0; k < Index(m.frames.size()); ++k) {
      // world: w from R+ R-^T = exp(2h w^), v = dp/dt
      const Mat3<double> dR = rotation(Pp, k) * transpose(rotation(Pm, k));
      const Vec3<double> w_fd{(dR(2, 1) - dR(1, 2)) / (4 * h), (dR(0, 2) - dR(2, 0)) / (4 * h),
                              (dR(1, 0) - dR(0, 1)) / (4 * h)};
      double fd[6] = {w_fd.x, w_fd.y, w_fd.z, 0, 0, 0};
      for (int r = 0; r < 3; ++r)
        fd[3 + r] = (Pp[std::size_t(k * 16 + 4 * r + 3)] - Pm[std::size_t(k * 16 + 4 * r + 3)]) / (2 * h);
      double Jv[6] = {0, 0, 0, 0, 0, 0}, Jlv[6] = {0, 0, 0, 0, 0, 0};
      for (int r = 0; r < 6; ++r)
        for (Index j = 0; j < nv; ++j) {
          Jv[r] += Jw[std::size_t((k * 6 + r) * nv + j)] * v[std::size_t(j)];
          Jlv[r] += Jl[std::size_t((k * 6 + r) * nv + j)] * v[std::size_t(j)];
        }
      for (int r = 0; r < 6; ++r) EXPECT_NEAR(Jv[r], fd[r], 1e-6) << "frame " << m.frame_names[std::size_t(k)];
      // local = the world twist in the frame's axes: R^T w, R^T v
      const Mat3<double> R = rotation(P, k);
      for (int half = 0; half < 2; ++half)
        for (int r = 0; r < 3; ++r) {
          double x = 0;
          for (int c = 0; c < 3; ++c) x += R(c, r) * Jv[3 * half + c];
          EXPECT_NEAR(Jlv[3 * half + r], x, 1e-12);
        }
    }
  }
}

TEST(MultiDofSupport, RefusedWithTheFeatureAndTheJoint) {
  const Model m = test::load_floating("hyq");
  const BackendOptions serial;
  // (the first-order derivatives and the directional derivatives by aba take
  // multi-DoF joints on serial and OpenMP: tests/algorithm/test_derivatives_multi_dof.cpp,
  // test_directional_multi_dof.cpp; the second-order ones and the directional chain
  // scans do not)
  expect_throws_naming([&] { make_id_second_derivatives(m, serial); },
                       {"second-order inverse-dynamics derivatives", "root_joint"});
  BackendOptions scans = serial;
  scans.fd_method = FdMethod::Parallel;
  expect_throws_naming([&] { make_fd_directional_derivatives(m, scans); },
                       {"directional derivatives", "root_joint"});
  expect_throws_naming([&] { make_hybrid_dynamics(m, std::vector<unsigned char>(std::size_t(m.nv()), 0), serial); },
                       {"hybrid dynamics", "root_joint"});
  BackendOptions simd = serial;
  simd.simd = CpuSimd::On;
  expect_throws_naming([&] { make_inverse_dynamics(m, simd); }, {"simd", "root_joint"});
  expect_throws_naming([&] { generator_loops("fourbar", m); }, {"closed loops", "root_joint"});
  const Model ball = load_model("ballrope:3");
  expect_throws_naming([&] { make_id_second_derivatives(ball, serial); },
                       {"second-order inverse-dynamics derivatives", "spherical"});
}

// Auto leaves out the SIMD path (1-DoF joints only): the scalar recursion.
TEST(MultiDofSupport, AutoLeavesOutTheSimdPath) {
  const Model m = test::load_floating("hyq");
  const BackendOptions o;
  EXPECT_EQ(make_forward_dynamics(m, o)->strategy().find("simd"), std::string::npos);
  EXPECT_EQ(make_inverse_dynamics(m, o)->strategy().find("simd"), std::string::npos);
}

// The forward-dynamics check on multi-DoF models: clean results (float and double
// engines) pass; a result off by e at one DoF is estimated at e / max(1, |qdd|) and
// flagged at that DoF (delta = M^-1 (M qdd' + h - tau) = qdd' - qdd exactly).
TEST(MultiDofSupport, ForwardDynamicsCheck) {
  for (const char* spec : {"hyq", "ballrope:6"}) {
    SCOPED_TRACE(spec);
    const Model m = std::string(spec) == "hyq" ? test::load_floating(spec) : load_model(spec);
    std::mt19937_64 rng(5);
    const Index B = 8, nv = m.nv(), nq = m.nq();
    std::vector<double> q, qd = test::random_vector(rng, int(B * nv), -1, 1),
                           tau = test::random_vector(rng, int(B * nv), -1, 1), qdd(std::size_t(B * nv));
    for (Index b = 0; b < B; ++b) {
      const std::vector<double> qb = test::random_q(m, rng);
      q.insert(q.end(), qb.begin(), qb.end());
    }
    BackendOptions o;
    o.fd_check = FdCheckMode::On;
    o.max_batch = B;
    const auto fd = make_forward_dynamics(m, o);
    EXPECT_NE(fd->strategy().find("check"), std::string::npos);
    FdBatchIn<double> in{BatchView<const double>::aos(q.data(), nq, B), BatchView<const double>::aos(qd.data(), nv, B),
                         BatchView<const double>::aos(tau.data(), nv, B)};
    EXPECT_TRUE(fd->compute(in, BatchView<double>::aos(qdd.data(), nv, B)).ok());
    // float: checked in double against the float result
    const ModelTpl<float> mf = m.cast<float>();
    std::vector<float> qf(q.begin(), q.end()), qdf(qd.begin(), qd.end()), tf(tau.begin(), tau.end()),
        qddf(qdd.size());
    const auto fdf = make_forward_dynamics(mf, o);
    FdBatchIn<float> inf{BatchView<const float>::aos(qf.data(), nq, B), BatchView<const float>::aos(qdf.data(), nv, B),
                         BatchView<const float>::aos(tf.data(), nv, B)};
    EXPECT_TRUE(fdf->compute(inf, BatchView<float>::aos(qddf.data(), nv, B)).ok());
    // a perturbed result
    FdBatchCheck<double> check(m, o, FdMethod::Aba, 1);
    std::vector<double> bad(qdd.begin(), qdd.begin() + nv);
    const Index k = nv - 2;
    double top = 1;
    for (double x : bad) top = std::max(top, std::abs(x));
    const double e = 1e-6 * top;  // an error of 1e-6 (ball-joint ropes: |qdd| up to 1e5)
    bad[std::size_t(k)] += e;
    top = 1;
    for (double x : bad) top = std::max(top, std::abs(x));
    const auto out = check.settle(0, q.data(), qd.data(), tau.data(), nullptr, bad.data());
    EXPECT_NEAR(out.estimate, e / top, 1e-9 * e / top);
    EXPECT_EQ(out.failed_dof, int(k));
  }
}
