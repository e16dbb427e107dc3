// z_axis_model (scandyn/model/joint_frames.hpp): every 1-DoF joint's frame turned so
// that its axis is +z. The re-expressed model must have the same joint-space dynamics
// (tau, h, M, qdd by the serial reference, double, relative 1e-12), its per-body
// quantities must be the user-frame ones turned by Q_i (velocities, accelerations),
// attached frames must stay where they were in the world, and Q_i must be a rotation
// taking the axis to +z, exact (identity or a signed permutation) for coordinate axes.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <string>
#include <vector>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/model/joint_frames.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

// A URDF with fixed joints (merged links, frames on moving bodies) and joint axes
// along +-x, +-y, -z, a slanted axis and a prismatic joint.
const char* kAxesUrdf = R"(<robot name="axes">
  <link name="base"/>
  <link name="a"><inertial><origin xyz="0.1 0 0.2" rpy="0.3 0 0"/><mass value="1.5"/>
    <inertia ixx="0.02" ixy="0.001" ixz="0" iyy="0.03" iyz="0.002" izz="0.04"/></inertial></link>
  <link name="b"><inertial><origin xyz="0 0.1 0.1"/><mass value="1.0"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.015"/></inertial></link>
  <link name="b_tool"><inertial><origin xyz="0.05 0 0"/><mass value="0.3"/>
    <inertia ixx="0.001" ixy="0" ixz="0" iyy="0.001" iyz="0" izz="0.001"/></inertial></link>
  <link name="c"><inertial><origin xyz="0 0 0.1"/><mass value="0.8"/>
    <inertia ixx="0.01" ixy="0" ixz="0.001" iyy="0.01" iyz="0" izz="0.015"/></inertial></link>
  <link name="d"><inertial><origin xyz="0.02 0.03 0.04"/><mass value="0.6"/>
    <inertia ixx="0.004" ixy="0" ixz="0" iyy="0.005" iyz="0" izz="0.006"/></inertial></link>
  <link name="e"><inertial><origin xyz="0 0 -0.1"/><mass value="0.5"/>
    <inertia ixx="0.003" ixy="0" ixz="0" iyy="0.003" iyz="0" izz="0.002"/></inertial></link>
  <link name="f"><inertial><origin xyz="0.1 0 0"/><mass value="0.4"/>
    <inertia ixx="0.002" ixy="0" ixz="0" iyy="0.003" iyz="0" izz="0.002"/></inertial></link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="a"/>
    <origin xyz="0 0 0.3" rpy="0.1 0.2 0.3"/><axis xyz="1 0 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j2" type="continuous"><parent link="a"/><child link="b"/>
    <origin xyz="0.1 0.2 0.3" rpy="-0.4 0.5 0.1"/><axis xyz="0 -1 0"/></joint>
  <joint name="tool" type="fixed"><parent link="b"/><child link="b_tool"/><origin xyz="0.2 0 0" rpy="0 1.0 0"/></joint>
  <joint name="j3" type="prismatic"><parent link="b_tool"/><child link="c"/>
    <origin xyz="0 0.1 0" rpy="0.3 0 -0.2"/><axis xyz="0 0 -1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="j4" type="continuous"><parent link="b"/><child link="d"/>
    <origin xyz="0 0 0.2" rpy="0 0 0.7"/><axis xyz="0.6 0 0.8"/></joint>
  <joint name="j5" type="prismatic"><parent link="a"/><child link="e"/>
    <origin xyz="0.3 0 0" rpy="1.0 0 0"/><axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="j6" type="continuous"><parent link="e"/><child link="f"/>
    <origin xyz="0 0 0.1"/><axis xyz="0 0 1"/></joint>
</robot>)";

std::vector<std::pair<std::string, Model>> models() {
  std::vector<std::pair<std::string, Model>> out;
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) out.emplace_back(file, test::load_robot(file));
  out.emplace_back("axes", build_model(parse_urdf(kAxesUrdf, "axes.urdf")));
  out.emplace_back("random_model(12)", test::random_model(12, 3));
  out.emplace_back("random_model(40)", test::random_model(40, 4));
  out.emplace_back("tree:20:3", load_model("tree:20:3"));
  return out;
}

double rel(const std::vector<double>& a, const std::vector<double>& b) { return test::max_rel_err(a, b); }

}  // namespace

TEST(JointFrames, RotationTakesTheAxisToZ) {
  std::mt19937_64 g(7);
  std::vector<Vec3<double>> axes = {{1, 0, 0}, {-1, 0, 0}, {0, 1, 0}, {0, -1, 0}, {0, 0, 1}, {0, 0, -1}};
  for (int k = 0; k < 50; ++k) {
    Vec3<double> a{std::normal_distribution<double>()(g), std::normal_distribution<double>()(g),
                   std::normal_distribution<double>()(g)};
    axes.push_back((1.0 / std::sqrt(dot(a, a))) * a);
  }
  for (std::size_t k = 0; k < axes.size(); ++k) {
    const Vec3<double>& a = axes[k];
    const Mat3<double> Q = z_axis_rotation(a);
    const Vec3<double> z = Q * a;
    EXPECT_NEAR(z.x, 0, 1e-15);
    EXPECT_NEAR(z.y, 0, 1e-15);
    EXPECT_NEAR(z.z, 1, 1e-15);
    const Mat3<double> QQt = Q * transpose(Q);
    for (int i = 0; i < 9; ++i) EXPECT_NEAR(QQt.m[i], i % 4 == 0 ? 1.0 : 0.0, 1e-15) << "axis " << k;
    const double det = Q.m[0] * (Q.m[4] * Q.m[8] - Q.m[5] * Q.m[7]) - Q.m[1] * (Q.m[3] * Q.m[8] - Q.m[5] * Q.m[6]) +
                       Q.m[2] * (Q.m[3] * Q.m[7] - Q.m[4] * Q.m[6]);
    EXPECT_NEAR(det, 1.0, 1e-15);
    if (k < 6) {  // coordinate axes: exact, entries 0 and +-1 only, in float too
      for (int i = 0; i < 9; ++i) EXPECT_TRUE(Q.m[i] == 0 || Q.m[i] == 1 || Q.m[i] == -1) << "axis " << k;
      const Mat3<float> Qf = z_axis_rotation(a.cast<float>());
      for (int i = 0; i < 9; ++i) EXPECT_EQ(double(Qf.m[i]), Q.m[i]);
    }
  }
  for (int i = 0; i < 9; ++i) EXPECT_EQ(z_axis_rotation(Vec3<double>{0, 0, 1}).m[i], i % 4 == 0 ? 1.0 : 0.0);
}

TEST(JointFrames, SameJointSpaceDynamics) {
  for (const auto& [name, md] : models()) {
    SCOPED_TRACE(name);
    const ZAxisModel<double> zm = z_axis_model(md);
    const Model& mz = zm.model;
    const Index n = md.nv();
    ASSERT_EQ(mz.nv(), n);
    for (Index i = 0; i < n; ++i) {
      const Body<double>& b = mz.bodies[i];
      EXPECT_EQ(b.axis.x, 0.0);
      EXPECT_EQ(b.axis.y, 0.0);
      EXPECT_EQ(b.axis.z, 1.0);
      if (!zm.turned[i]) {  // an axis on +z already: the body is left exactly as it was
        EXPECT_EQ(md.bodies[i].axis.z, 1.0);
        EXPECT_EQ(b.I.m, md.bodies[i].I.m);
        EXPECT_EQ(b.I.h.x, md.bodies[i].I.h.x);
      }
    }
    Data d(md, false), dz(mz, false);
    std::mt19937_64 g(11);
    for (int trial = 0; trial < 5; ++trial) {
      const std::vector<double> q = test::random_vector(g, int(n), -3, 3), qd = test::random_vector(g, int(n), -2, 2),
                                qdd = test::random_vector(g, int(n), -2, 2), tau_in = test::random_vector(g, int(n), -2, 2);
      const std::vector<Force<double>> fext = test::random_wrenches<double>(g, int(n), 1.0);
      std::vector<Force<double>> fz(n);
      for (Index i = 0; i < n; ++i) fz[i] = zm.to_z_frame(i, fext[i]);
      std::vector<double> tau(n), tauz(n), M(n * n), Mz(n * n), a(n), az(n);
      // inverse dynamics with external wrenches
      rnea(md, d, q.data(), qd.data(), qdd.data(), tau.data(), fext.data());
      rnea(mz, dz, q.data(), qd.data(), qdd.data(), tauz.data(), fz.data());
      EXPECT_LE(rel(tauz, tau), 1e-12);
      // per-body quantities: the user's turned by Q_i
      for (Index i = 0; i < n; ++i) {
        const Motion<double> v = zm.to_user_frame(i, dz.v[i]), acc = zm.to_user_frame(i, dz.a[i]);
        const std::vector<double> got{v.w.x, v.w.y, v.w.z, v.v.x, v.v.y, v.v.z, acc.w.x, acc.w.y, acc.w.z,
                                      acc.v.x, acc.v.y, acc.v.z};
        const Motion<double>&vu = d.v[i], &au = d.a[i];
        const std::vector<double> want{vu.w.x, vu.w.y, vu.w.z, vu.v.x, vu.v.y, vu.v.z,
                                       au.w.x, au.w.y, au.w.z, au.v.x, au.v.y, au.v.z};
        EXPECT_LE(rel(got, want), 1e-12) << "body " << i;
      }
      // mass matrix
      crba(md, d, q.data(), M.data());
      crba(mz, dz, q.data(), Mz.data());
      EXPECT_LE(rel(Mz, M), 1e-12);
      // forward dynamics (ABA) with external wrenches
      ASSERT_TRUE(aba(md, d, q.data(), qd.data(), tau_in.data(), a.data(), fext.data()).ok());
      ASSERT_TRUE(aba(mz, dz, q.data(), qd.data(), tau_in.data(), az.data(), fz.data()).ok());
      EXPECT_LE(rel(az, a), 1e-12);
    }
  }
}

TEST(JointFrames, AttachedFramesStayInPlace) {
  const Model md = build_model(parse_urdf(kAxesUrdf, "axes.urdf"));
  const ZAxisModel<double> zm = z_axis_model(md);
  ASSERT_EQ(zm.model.frames.size(), md.frames.size());
  Data d(md, false), dz(zm.model, false);
  std::mt19937_64 g(3);
  const Index n = md.nv();
  const std::vector<double> q = test::random_vector(g, int(n), -3, 3), zero(n, 0.0);
  std::vector<double> tau(n);
  rnea(md, d, q.data(), zero.data(), zero.data(), tau.data());
  rnea(zm.model, dz, q.data(), zero.data(), zero.data(), tau.data());
  // world -> body transforms from the parent -> body ones
  auto world = [&](const Model& m, const Data& data) {
    std::vector<Transform<double>> X0(n);
    for (Index i = 0; i < n; ++i)
      X0[i] = m.bodies[i].parent < 0 ? data.Xup[i] : data.Xup[i] * X0[m.bodies[i].parent];
    return X0;
  };
  const std::vector<Transform<double>> X0 = world(md, d), X0z = world(zm.model, dz);
  int turned_frames = 0;
  for (std::size_t k = 0; k < md.frames.size(); ++k) {
    const FramePlacement<double>& f = md.frames[k];
    const FramePlacement<double>& fz = zm.model.frames[k];
    ASSERT_EQ(fz.body, f.body);
    if (f.body < 0) continue;
    turned_frames += zm.turned[f.body];
    const Transform<double> a = f.X * X0[f.body], b = fz.X * X0z[f.body];
    std::vector<double> va(a.E.m, a.E.m + 9), vb(b.E.m, b.E.m + 9);
    for (const Vec3<double>& r : {a.r}) va.insert(va.end(), {r.x, r.y, r.z});
    for (const Vec3<double>& r : {b.r}) vb.insert(vb.end(), {r.x, r.y, r.z});
    EXPECT_LE(rel(vb, va), 1e-12) << md.frame_names[k];
  }
  EXPECT_GT(turned_frames, 0);  // b_tool rides on the turned body of j2
}

TEST(JointFrames, NonUnitAxisIsRefused) {
  Model md = test::random_model(3, 1);
  md.bodies[1].axis = Vec3<double>{0, 0, 2};
  try {
    z_axis_model(md);
    ADD_FAILURE() << "an axis of length 2 was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("'j1'"), std::string::npos) << e.what();
  }
}
