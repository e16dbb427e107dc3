// Reference RNEA / CRBA / ABA / JSI against closed forms and against each other.
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <limits>
#include <random>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/model/load.hpp"
#include "identities.hpp"
#include "test_util.hpp"

using namespace scandyn;
using test::max_rel_err;
using test::check_identities;
using test::random_model;
using test::Tol;

namespace {

// Planar two-link arm in the xy plane, joints about z, gravity along -y.
struct TwoLink {
  double m1 = 1.3, m2 = 0.7, l1 = 0.9, lc1 = 0.4, lc2 = 0.35, I1 = 0.11, I2 = 0.05, g = 9.81;
  Model model() const {
    Model m;
    m.name = "two-link";
    m.gravity = {0, -g, 0};
    auto body = [](Index parent, double x, double mass, double lc, double Izz) {
      Body<double> b;
      b.parent = parent;
      b.type = JointType::Revolute;
      b.axis = {0, 0, 1};
      b.Xtree = Transform<double>::from_pose(Mat3<double>::identity(), {x, 0, 0});
      // Ixx, Iyy only matter out of plane; pick values satisfying the triangle inequality
      b.I = Inertia<double>::from_com(mass, {lc, 0, 0}, Sym3<double>{Izz, Izz, Izz, 0, 0, 0});
      return b;
    };
    m.bodies = {body(-1, 0, m1, lc1, I1), body(0, l1, m2, lc2, I2)};
    m.joint_names = {"j1", "j2"};
    m.link_names = {"l1", "l2"};
    return m;
  }
  Eigen::Matrix2d M(double q2) const {
    const double c2 = std::cos(q2);
    Eigen::Matrix2d o;
    o(0, 0) = I1 + I2 + m1 * lc1 * lc1 + m2 * (l1 * l1 + lc2 * lc2 + 2 * l1 * lc2 * c2);
    o(0, 1) = o(1, 0) = I2 + m2 * (lc2 * lc2 + l1 * lc2 * c2);
    o(1, 1) = I2 + m2 * lc2 * lc2;
    return o;
  }
  Eigen::Vector2d h(double q1, double q2, double qd1, double qd2) const {
    const double k = m2 * l1 * lc2 * std::sin(q2);
    const Eigen::Vector2d c(-k * (2 * qd1 * qd2 + qd2 * qd2), k * qd1 * qd1);
    const Eigen::Vector2d gr((m1 * lc1 + m2 * l1) * g * std::cos(q1) + m2 * lc2 * g * std::cos(q1 + q2),
                             m2 * lc2 * g * std::cos(q1 + q2));
    return c + gr;
  }
};

std::vector<std::string> robot_files() { return {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}; }

// Virtual work: with external wrenches f_i on bodies (body frames),
// tau_ext = RNEA(.., fext) - RNEA(.., 0) = -sum_i J_i^T f_i, so for any joint
// velocity qd, qd . (tau - tau_ext_free) = -sum_i v_i(qd) . f_i where v_i is the
// body velocity produced by qd (from RNEA's forward pass, body frames).
template <class S>
void check_virtual_work(const Model& model_d, unsigned seed) {
  const ModelTpl<S> model = model_d.template cast<S>();
  DataTpl<S> data(model);
  const int n = model.nv();
  std::mt19937_64 rng(seed);
  const auto q = test::cast_vector<S>(test::random_vector(rng, n, -2, 2));
  const auto qd = test::cast_vector<S>(test::random_vector(rng, n, -1, 1));
  const auto qdd = test::cast_vector<S>(test::random_vector(rng, n, -1, 1));
  const std::vector<Force<S>> fext = test::random_wrenches<S>(rng, n, 3);
  std::vector<S> t_free(n), t_ext(n);
  rnea(model, data, q.data(), qd.data(), qdd.data(), t_free.data());
  rnea(model, data, q.data(), qd.data(), qdd.data(), t_ext.data(), fext.data());
  // body velocities for the test velocity qd (data.v after the last call)
  double lhs = 0, rhs = 0, scale = 1;
  for (int i = 0; i < n; ++i) {
    lhs += double(qd[i]) * (double(t_ext[i]) - double(t_free[i]));
    rhs -= double(dot(data.v[i], fext[i]));
    scale += std::fabs(double(dot(data.v[i], fext[i])));
  }
  EXPECT_LT(std::fabs(lhs - rhs) / scale, Tol<S>(1e-12, 1e-5));
  // ABA with the same wrenches inverts RNEA with them
  std::vector<S> qdd_back(n);
  ASSERT_TRUE(aba(model, data, q.data(), qd.data(), t_ext.data(), qdd_back.data(), fext.data()).ok());
  EXPECT_LT(max_rel_err(qdd_back, qdd), Tol<S>(1e-9, 5e-2));
  std::vector<S> qdd_jsi(n);
  ASSERT_TRUE(fd_jsi(model, data, q.data(), qd.data(), t_ext.data(), qdd_jsi.data(), fext.data()).ok());
  EXPECT_LT(max_rel_err(qdd_jsi, qdd), Tol<S>(1e-9, 5e-2));
}

}  // namespace

TEST(ClosedForm, TwoLinkArm) {
  const TwoLink arm;
  const Model model = arm.model();
  Data data(model);
  std::mt19937_64 rng(7);
  for (int t = 0; t < 20; ++t) {
    const auto s = test::random_vector(rng, 6, -3, 3);
    const double q[2] = {s[0], s[1]}, qd[2] = {s[2], s[3]}, qdd[2] = {s[4], s[5]};
    const Eigen::Matrix2d M = arm.M(q[1]);
    const Eigen::Vector2d h = arm.h(q[0], q[1], qd[0], qd[1]);
    const Eigen::Vector2d tau = M * Eigen::Vector2d(qdd[0], qdd[1]) + h;

    double out[2];
    rnea(model, data, q, qd, qdd, out);
    EXPECT_NEAR(out[0], tau[0], 1e-12);
    EXPECT_NEAR(out[1], tau[1], 1e-12);
    bias_forces(model, data, q, qd, out);
    EXPECT_NEAR(out[0], h[0], 1e-12);
    EXPECT_NEAR(out[1], h[1], 1e-12);
    double Mo[4];
    crba(model, data, q, Mo);
    for (int k = 0; k < 4; ++k) EXPECT_NEAR(Mo[k], M(k / 2, k % 2), 1e-12);
    const double t2[2] = {tau[0], tau[1]};
    ASSERT_TRUE(aba(model, data, q, qd, t2, out).ok());
    EXPECT_NEAR(out[0], qdd[0], 1e-12);
    EXPECT_NEAR(out[1], qdd[1], 1e-12);
    ASSERT_TRUE(fd_jsi(model, data, q, qd, t2, out).ok());
    EXPECT_NEAR(out[0], qdd[0], 1e-12);
    EXPECT_NEAR(out[1], qdd[1], 1e-12);
  }
}

TEST(ClosedForm, PrismaticSlider) {
  // one prismatic joint along a random axis a: tau = m (qdd - g.a)
  Model m;
  m.name = "slider";
  Body<double> b;
  b.parent = -1;
  b.type = JointType::Prismatic;
  const double s = 1 / std::sqrt(3.0);
  b.axis = {s, -s, s};
  b.Xtree = Transform<double>::from_pose(rpy_matrix(0.3, -0.2, 1.1), {0.1, 0.2, 0.3});
  b.I = Inertia<double>::from_com(2.5, {0.1, -0.3, 0.2}, Sym3<double>{0.1, 0.1, 0.1, 0, 0, 0});
  m.bodies = {b};
  m.joint_names = {"p"};
  m.link_names = {"l"};
  Data data(m);
  // the axis in base coordinates: E^T a (E = R^T)
  const Vec3<double> a_base = mul_transpose(b.Xtree.E, b.axis);
  const double q = 0.7, qd = -1.2, qdd = 0.4;
  double tau;
  rnea(m, data, &q, &qd, &qdd, &tau);
  EXPECT_NEAR(tau, 2.5 * (qdd - dot(m.gravity, a_base)), 1e-12);
}

class RandomTrees : public ::testing::TestWithParam<int> {};

TEST_P(RandomTrees, IdentitiesDouble) {
  const int n = GetParam();
  for (unsigned seed = 1; seed <= 3; ++seed)
    check_identities<double>(random_model(n, seed * 101 + n), seed, "n=" + std::to_string(n));
}
TEST_P(RandomTrees, IdentitiesFloat) {
  const int n = GetParam();
  check_identities<float>(random_model(n, 5 * n + 1), 9, "n=" + std::to_string(n));
}
TEST_P(RandomTrees, VirtualWork) {
  const int n = GetParam();
  check_virtual_work<double>(random_model(n, 77 + n), 3);
}
INSTANTIATE_TEST_SUITE_P(Sizes, RandomTrees, ::testing::Values(1, 2, 3, 5, 8, 13, 30, 64, 120, 200));

TEST(Robots, Identities) {
  for (const auto& f : robot_files()) {
    const Model model = test::load_robot(f);
    check_identities<double>(model, 11, f + " double");
    check_identities<float>(model, 12, f + " float");
    check_virtual_work<double>(model, 13);
    check_virtual_work<float>(model, 14);
  }
}

TEST(Generated, Identities) {
  for (const char* spec : {"chain:7", "rope:50", "tree:40:3", "tree:200:9"})
    check_identities<double>(load_model(spec), 21, spec);
}

// float results against the double reference on the same inputs.
TEST(Precision, FloatVsDouble) {
  for (const auto& f : robot_files()) test::check_float_vs_double(test::load_robot(f), f);
}

TEST(Failure, SingularMassMatrixIsReported) {
  // a massless leaf body: its pivot is zero, so both FD routes must say so
  Model m = random_model(3, 4);
  m.bodies[2].I = Inertia<double>::zero();
  m.bodies[2].parent = 1;
  Data data(m);
  const double q[3] = {0.1, 0.2, 0.3}, qd[3] = {0, 0, 0}, tau[3] = {1, 1, 1};
  double qdd[3];
  const Status s1 = aba(m, data, q, qd, tau, qdd);
  EXPECT_EQ(s1.failed_dof, 2);
  const Status s2 = fd_jsi(m, data, q, qd, tau, qdd);
  EXPECT_EQ(s2.failed_dof, 2);
}

TEST(Steps, AlignedAxisRotationMatchesGeneral) {
  // joint_transform takes a two-row shortcut for axes along +-x, +-y, +-z
  const Mat3<double> E = rpy_matrix(0.4, -0.7, 2.1);
  for (int k = 0; k < 3; ++k)
    for (double sign : {1.0, -1.0}) {
      Vec3<double> a{0, 0, 0};
      (k == 0 ? a.x : k == 1 ? a.y : a.z) = sign;
      for (double q : {-2.5, 0.3, 1.7}) {
        const Mat3<double> fast = rotate_rows(a, std::sin(q), std::cos(q), E);
        const Mat3<double> general = mul_transpose(axis_angle(a, std::sin(q), std::cos(q)), E);
        for (int i = 0; i < 9; ++i) EXPECT_NEAR(fast.m[i], general.m[i], 1e-15) << "axis " << k << " sign " << sign;
      }
    }
}
