// Model loading: DoF order, fixed-joint merging, validation messages, generators.
//
// Expected transforms and inertias are computed here independently, as dense 6x6
// Eigen matrices (Pluecker transforms X = [E 0; -E[r]x E], rigid inertias
// [Ic + m[c]x[c]x^T, m[c]x; m[c]x^T, m 1]), never with the library's spatial code.
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <console_bridge/console.h>
#include <cstdio>
#include <fstream>
#include <functional>
#include <limits>
#include <map>
#include <random>
#include <string>
#include <vector>
#include <unistd.h>

#include "scandyn/model/load.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

using Mat3d = Eigen::Matrix3d;
using Mat6d = Eigen::Matrix<double, 6, 6>;
using V3d = Eigen::Vector3d;
const double kNaN = std::numeric_limits<double>::quiet_NaN();
const double kInf = std::numeric_limits<double>::infinity();

// ---- independent spatial algebra -------------------------------------------------
Mat3d skew3(const V3d& v) {
  Mat3d S;
  S << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return S;
}
Mat3d rpy_rot(double r, double p, double y) {
  return (Eigen::AngleAxisd(y, V3d::UnitZ()) * Eigen::AngleAxisd(p, V3d::UnitY()) *
          Eigen::AngleAxisd(r, V3d::UnitX()))
      .toRotationMatrix();
}
// child_X_parent for a child frame with pose (R, p) in the parent
Mat6d plucker(const Mat3d& R, const V3d& p) {
  Mat6d X = Mat6d::Zero();
  X.topLeftCorner<3, 3>() = R.transpose();
  X.bottomRightCorner<3, 3>() = R.transpose();
  X.bottomLeftCorner<3, 3>() = -R.transpose() * skew3(p);
  return X;
}
Mat6d origin(double x, double y, double z, double r, double p, double w) {
  return plucker(rpy_rot(r, p, w), V3d(x, y, z));
}
Mat6d rigid_inertia(double m, const V3d& c, const Mat3d& Ic) {
  Mat6d I;
  const Mat3d C = skew3(c);
  I << Ic + m * C * C.transpose(), m * C, m * C.transpose(), m * Mat3d::Identity();
  return I;
}
// URDF <inertial>: origin (xyz, rpy), mass, tensor about the COM in inertial axes
Mat6d link_inertia6(double m, const V3d& xyz, const V3d& rpy, const Mat3d& Ic) {
  const Mat3d R = rpy_rot(rpy.x(), rpy.y(), rpy.z());
  return rigid_inertia(m, xyz, R * Ic * R.transpose());
}
// the library's types as dense matrices
Mat6d dense(const Transform<double>& X) {
  Mat3d E;
  for (int i = 0; i < 9; ++i) E(i / 3, i % 3) = X.E.m[i];
  Mat6d M = Mat6d::Zero();
  M.topLeftCorner<3, 3>() = E;
  M.bottomRightCorner<3, 3>() = E;
  M.bottomLeftCorner<3, 3>() = -E * skew3(V3d(X.r.x, X.r.y, X.r.z));
  return M;
}
Mat6d dense(const Inertia<double>& I) {
  Mat3d Ib;
  Ib << I.I.xx, I.I.xy, I.I.xz, I.I.xy, I.I.yy, I.I.yz, I.I.xz, I.I.yz, I.I.zz;
  const Mat3d H = skew3(V3d(I.h.x, I.h.y, I.h.z));
  Mat6d M;
  M << Ib, H, H.transpose(), I.m * Mat3d::Identity();
  return M;
}
double maxabs(const Mat6d& A) { return A.cwiseAbs().maxCoeff(); }
V3d v3(const Vec3<double>& v) { return {v.x, v.y, v.z}; }

// Every number of two models, compared exactly.
void expect_identical(const Model& a, const Model& b) {
  ASSERT_EQ(a.nv(), b.nv());
  EXPECT_EQ(a.root_link, b.root_link);
  EXPECT_EQ(a.joint_names, b.joint_names);
  EXPECT_EQ(a.link_names, b.link_names);
  for (Index i = 0; i < a.nv(); ++i) {
    const Body<double>&x = a.bodies[i], &y = b.bodies[i];
    EXPECT_EQ(x.parent, y.parent) << i;
    EXPECT_EQ(x.type, y.type) << i;
    EXPECT_EQ(0.0, (v3(x.axis) - v3(y.axis)).cwiseAbs().maxCoeff()) << i;
    EXPECT_EQ(0.0, maxabs(dense(x.Xtree) - dense(y.Xtree))) << i;
    EXPECT_EQ(0.0, maxabs(dense(x.I) - dense(y.I))) << i;
  }
}
void expect_parent_before_child(const Model& m) {
  for (Index i = 0; i < m.nv(); ++i) {
    EXPECT_GE(m.parent(i), -1) << m.source << " body " << i;
    EXPECT_LT(m.parent(i), i) << m.source << " body " << i;
  }
}

// Runs f, expects a ModelError whose one-line message contains every needle.
void expect_error(const std::function<void()>& f, const std::vector<std::string>& needles) {
  try {
    f();
    ADD_FAILURE() << "no ModelError; expected one containing '" << needles.front() << "'";
  } catch (const ModelError& e) {
    const std::string msg = e.what();
    EXPECT_EQ(msg.find('\n'), std::string::npos) << msg;
    for (const auto& n : needles) EXPECT_NE(msg.find(n), std::string::npos) << "'" << n << "' not in: " << msg;
  }
}

BuildOptions lenient(std::vector<std::string>* warnings = nullptr) {
  BuildOptions o;
  o.require_physical_inertia = false;
  o.warnings = warnings;
  return o;
}

// ---- the three robots -------------------------------------------------------------

TEST(Robots, SizesAndDofOrder) {
  const std::vector<std::string> iiwa = {"iiwa_joint_1", "iiwa_joint_2", "iiwa_joint_3", "iiwa_joint_4",
                                         "iiwa_joint_5", "iiwa_joint_6", "iiwa_joint_7"};
  // base_link_0 -> four legs, children sorted by joint name
  const std::vector<std::string> hyq = {"lf_haa_joint", "lf_hfe_joint", "lf_kfe_joint", "lh_haa_joint",
                                        "lh_hfe_joint", "lh_kfe_joint", "rf_haa_joint", "rf_hfe_joint",
                                        "rf_kfe_joint", "rh_haa_joint", "rh_hfe_joint", "rh_kfe_joint"};
  // pelvis -> back_bkz, l_leg_hpz, r_leg_hpz; utorso -> l_arm_shz, neck_ay, r_arm_shz
  const std::vector<std::string> atlas = {
      "back_bkz",  "back_bky",  "back_bkx",  "l_arm_shz", "l_arm_shx", "l_arm_ely",
      "l_arm_elx", "l_arm_uwy", "l_arm_mwx", "l_arm_lwy", "neck_ay",   "r_arm_shz",
      "r_arm_shx", "r_arm_ely", "r_arm_elx", "r_arm_uwy", "r_arm_mwx", "r_arm_lwy",
      "l_leg_hpz", "l_leg_hpx", "l_leg_hpy", "l_leg_kny", "l_leg_aky", "l_leg_akx",
      "r_leg_hpz", "r_leg_hpx", "r_leg_hpy", "r_leg_kny", "r_leg_aky", "r_leg_akx"};
  const std::vector<Index> atlas_parent = {-1, 0,  1,  2,  3,  4,  5,  6,  7,  8,  2,  2,  11, 12, 13,
                                           14, 15, 16, -1, 18, 19, 20, 21, 22, -1, 24, 25, 26, 27, 28};

  const Model mi = load_urdf(test::model_path("iiwa.urdf"));
  EXPECT_EQ(mi.nv(), 7);
  EXPECT_EQ(mi.joint_names, iiwa);
  EXPECT_EQ(mi.root_link, "base");
  EXPECT_EQ(mi.link_names.front(), "iiwa_link_1");
  for (Index i = 0; i < 7; ++i) EXPECT_EQ(mi.parent(i), i - 1);

  const Model mh = load_model(test::model_path("hyq.urdf"));
  EXPECT_EQ(mh.nv(), 12);
  EXPECT_EQ(mh.joint_names, hyq);
  for (Index i = 0; i < 12; ++i) EXPECT_EQ(mh.parent(i), i % 3 == 0 ? -1 : i - 1);

  const Model ma = load_urdf(test::model_path("atlas.urdf"), lenient());
  EXPECT_EQ(ma.nv(), 30);
  EXPECT_EQ(ma.joint_names, atlas);
  for (Index i = 0; i < 30; ++i) EXPECT_EQ(ma.parent(i), atlas_parent[i]) << i;
  EXPECT_EQ(ma.name, "atlas");
  EXPECT_EQ(ma.root_link, "pelvis");

  for (const Model* m : {&mi, &mh, &ma}) {
    expect_parent_before_child(*m);
    ASSERT_EQ(m->joint_names.size(), m->bodies.size());
    ASSERT_EQ(m->link_names.size(), m->bodies.size());
    for (const auto& b : m->bodies) EXPECT_NEAR(dot(b.axis, b.axis), 1.0, 1e-15);
  }
}

// GRiD's atlas.urdf has four link inertias no rigid body can have; the default
// (strict) build names one, the lenient build lists them all.
TEST(Robots, AtlasInertiasAreNotPhysical) {
  expect_error([] { load_urdf(test::model_path("atlas.urdf")); },
               {"atlas.urdf: link 'l_foot': ", "not positive definite"});
  std::vector<std::string> w;
  load_model(test::model_path("atlas.urdf"), lenient(&w));
  ASSERT_EQ(w.size(), 4u);
  EXPECT_NE(w[0].find("link 'l_foot'"), std::string::npos) << w[0];
  EXPECT_NE(w[1].find("link 'l_lglut'"), std::string::npos) << w[1];
  EXPECT_NE(w[1].find("triangle inequality"), std::string::npos) << w[1];
  EXPECT_NE(w[2].find("link 'r_foot'"), std::string::npos) << w[2];
  EXPECT_NE(w[3].find("link 'utorso'"), std::string::npos) << w[3];
}

// Spot check against the file (hand-read): iiwa_joint_2 origin xyz="0 0 0.2025"
// rpy="1.570796326794897 0 3.141592653589793", child link mass 6.35 at xyz="0.0003 0.059 0.042".
TEST(Robots, IiwaBodyFromFile) {
  const Model m = load_urdf(test::model_path("iiwa.urdf"));
  const Body<double>& b = m.bodies[1];
  EXPECT_EQ(b.type, JointType::Revolute);
  EXPECT_LT(maxabs(dense(b.Xtree) - origin(0, 0, 0.2025, 1.570796326794897, 0, 3.141592653589793)), 1e-15);
  EXPECT_DOUBLE_EQ(b.I.m, 6.35);
  EXPECT_NEAR(b.I.h.y, 6.35 * 0.059, 1e-14);
}

TEST(Robots, LoadUrdfEqualsParseThenBuild) {
  const std::string path = test::model_path("hyq.urdf");
  std::ifstream f(path);
  const std::string xml((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  expect_identical(load_urdf(path), build_model(parse_urdf(xml, path)));
}

// ---- fixed-joint merging and frames -------------------------------------------------

// A tree with a fixed base plate (dropped), a chain of fixed links under body 'arm'
// (one with pitch exactly pi/2, one massless), rotated inertial frames, a prismatic
// joint hanging below the fixed chain and a continuous joint.
const char* kMergeUrdf = R"(<?xml version="1.0"?>
<robot name="merge">
  <link name="world"/>
  <link name="plate">
    <inertial><origin xyz="0.3 0.1 0" rpy="0 0 0"/><mass value="3"/>
      <inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial>
  </link>
  <joint name="f_plate" type="fixed"><parent link="world"/><child link="plate"/>
    <origin xyz="0.1 0 0.2" rpy="0 0 0.3"/></joint>
  <link name="arm">
    <inertial><origin xyz="0.05 -0.02 0.1" rpy="0.3 -0.2 0.5"/><mass value="2"/>
      <inertia ixx="0.04" iyy="0.05" izz="0.03" ixy="0.001" ixz="-0.002" iyz="0.003"/></inertial>
  </link>
  <joint name="j_arm" type="revolute"><parent link="plate"/><child link="arm"/>
    <origin xyz="0 0.1 0.05" rpy="0.2 0.1 -0.4"/><axis xyz="0 0 2"/>
    <limit effort="10" velocity="1" lower="-1" upper="1"/></joint>
  <link name="tool">
    <inertial><origin xyz="0.01 0.02 -0.03" rpy="-0.4 0.7 0.1"/><mass value="0.5"/>
      <inertia ixx="0.002" iyy="0.003" izz="0.004" ixy="0.0001" ixz="0" iyz="-0.0002"/></inertial>
  </link>
  <joint name="f_tool" type="fixed"><parent link="arm"/><child link="tool"/>
    <origin xyz="0.3 0 0" rpy="1.2 0 0.5"/></joint>
  <link name="tip">
    <inertial><origin xyz="0 0 0.02"/><mass value="0.2"/>
      <inertia ixx="0.0001" iyy="0.0001" izz="0.0001" ixy="0" ixz="0" iyz="0"/></inertial>
  </link>
  <joint name="f_tip" type="fixed"><parent link="tool"/><child link="tip"/>
    <origin xyz="0 0.05 0" rpy="0.25 1.5707963267948966 -0.6"/></joint>
  <link name="sensor"/>
  <joint name="f_sensor" type="fixed"><parent link="tip"/><child link="sensor"/>
    <origin xyz="0.01 0 0" rpy="0.1 0.2 0.3"/></joint>
  <link name="slider">
    <inertial><origin xyz="0 0 0.05" rpy="0 0.4 0"/><mass value="0.7"/>
      <inertia ixx="0.001" iyy="0.002" izz="0.0025" ixy="0" ixz="0" iyz="0"/></inertial>
  </link>
  <joint name="j_slide" type="prismatic"><parent link="sensor"/><child link="slider"/>
    <origin xyz="0 0 0.1" rpy="0.5 -0.3 0.2"/><axis xyz="1 1 0"/>
    <limit effort="10" velocity="1" lower="-1" upper="1"/></joint>
  <link name="wheel">
    <inertial><origin xyz="0 0 0"/><mass value="1.5"/>
      <inertia ixx="0.01" iyy="0.02" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>
  </link>
  <joint name="j_wheel" type="continuous"><parent link="arm"/><child link="wheel"/>
    <origin xyz="-0.1 0 0" rpy="0 0 1"/><axis xyz="0 1 0"/></joint>
</robot>
)";

struct MergeExpect {
  Mat6d X[3], I[3];
};
MergeExpect merge_expected() {
  MergeExpect e;
  Mat3d Ic;
  const Mat6d X_plate = origin(0.1, 0, 0.2, 0, 0, 0.3);
  const Mat6d X_arm = origin(0, 0.1, 0.05, 0.2, 0.1, -0.4);
  const Mat6d X_tool = origin(0.3, 0, 0, 1.2, 0, 0.5);
  const Mat6d X_tip = origin(0, 0.05, 0, 0.25, M_PI / 2, -0.6);
  const Mat6d X_sensor = origin(0.01, 0, 0, 0.1, 0.2, 0.3);
  const Mat6d X_slide = origin(0, 0, 0.1, 0.5, -0.3, 0.2);
  const Mat6d X_wheel = origin(-0.1, 0, 0, 0, 0, 1);
  Ic << 0.04, 0.001, -0.002, 0.001, 0.05, 0.003, -0.002, 0.003, 0.03;
  const Mat6d I_arm = link_inertia6(2, V3d(0.05, -0.02, 0.1), V3d(0.3, -0.2, 0.5), Ic);
  Ic << 0.002, 0.0001, 0, 0.0001, 0.003, -0.0002, 0, -0.0002, 0.004;
  const Mat6d I_tool = link_inertia6(0.5, V3d(0.01, 0.02, -0.03), V3d(-0.4, 0.7, 0.1), Ic);
  const Mat6d I_tip = link_inertia6(0.2, V3d(0, 0, 0.02), V3d::Zero(), 1e-4 * Mat3d::Identity());
  const Mat6d I_slider =
      link_inertia6(0.7, V3d(0, 0, 0.05), V3d(0, 0.4, 0), V3d(0.001, 0.002, 0.0025).asDiagonal());
  const Mat6d I_wheel = link_inertia6(1.5, V3d::Zero(), V3d::Zero(), V3d(0.01, 0.02, 0.01).asDiagonal());
  // body 0 'arm' carries tool and tip (sensor is massless), merged as X^T I X
  const Mat6d tool_X_arm = X_tool, tip_X_arm = X_tip * X_tool;
  e.X[0] = X_arm * X_plate;
  e.I[0] = I_arm + tool_X_arm.transpose() * I_tool * tool_X_arm + tip_X_arm.transpose() * I_tip * tip_X_arm;
  // body 1 'slider' hangs below the fixed chain; body 2 'wheel' comes after (f_tool < j_wheel)
  e.X[1] = X_slide * X_sensor * X_tip * X_tool;
  e.I[1] = I_slider;
  e.X[2] = X_wheel;
  e.I[2] = I_wheel;
  return e;
}

TEST(Merge, FixedLinksMatchDenseExpectation) {
  const Model m = build_model(parse_urdf(kMergeUrdf, "merge.urdf"));
  ASSERT_EQ(m.nv(), 3);
  EXPECT_EQ(m.joint_names, (std::vector<std::string>{"j_arm", "j_slide", "j_wheel"}));
  EXPECT_EQ(m.link_names, (std::vector<std::string>{"arm", "slider", "wheel"}));
  EXPECT_EQ(m.root_link, "world");
  EXPECT_EQ(m.name, "merge");
  EXPECT_EQ(m.source, "merge.urdf");
  EXPECT_EQ(m.parent(0), -1);
  EXPECT_EQ(m.parent(1), 0);
  EXPECT_EQ(m.parent(2), 0);
  EXPECT_EQ(m.bodies[0].type, JointType::Revolute);
  EXPECT_EQ(m.bodies[1].type, JointType::Prismatic);
  EXPECT_EQ(m.bodies[2].type, JointType::Revolute);  // continuous
  EXPECT_LT((v3(m.bodies[0].axis) - V3d(0, 0, 1)).norm(), 1e-15);
  EXPECT_LT((v3(m.bodies[1].axis) - V3d(1, 1, 0).normalized()).norm(), 1e-15);
  EXPECT_LT((v3(m.bodies[2].axis) - V3d(0, 1, 0)).norm(), 1e-15);
  const MergeExpect e = merge_expected();
  for (int i = 0; i < 3; ++i) {
    EXPECT_LT(maxabs(dense(m.bodies[i].Xtree) - e.X[i]), 1e-14) << "Xtree " << i;
    EXPECT_LT(maxabs(dense(m.bodies[i].I) - e.I[i]), 1e-14) << "I " << i;
  }
  // total mass: the base plate is dropped, the massless sensor adds nothing
  EXPECT_NEAR(m.bodies[0].I.m, 2.7, 1e-15);
}

std::string num(double x) {
  char b[40];
  std::snprintf(b, sizeof b, "%.17g", x);
  return b;
}
std::string triple(const V3d& v) { return num(v.x()) + " " + num(v.y()) + " " + num(v.z()); }
// <origin> of the pose whose child_X_parent is X
std::string origin_xml(const Mat6d& X) {
  const Mat3d R = X.topLeftCorner<3, 3>().transpose();
  const Mat3d ES = -X.bottomLeftCorner<3, 3>();  // E [p]x
  const Mat3d S = R * ES;
  const V3d p(S(2, 1), S(0, 2), S(1, 0));
  const V3d ypr = R.eulerAngles(2, 1, 0);  // R = Rz(y) Ry(p) Rx(r)
  return "<origin xyz=\"" + triple(p) + "\" rpy=\"" + num(ypr[2]) + " " + num(ypr[1]) + " " +
         num(ypr[0]) + "\"/>";
}
// <inertial> (origin with rpy 0) of a rigid inertia
std::string inertial_xml(const Mat6d& I) {
  const double m = I(3, 3);
  const Mat3d H = I.topRightCorner<3, 3>();
  const V3d c = V3d(H(2, 1), H(0, 2), H(1, 0)) / m;
  const Mat3d Ic = I.topLeftCorner<3, 3>() - m * skew3(c) * skew3(c).transpose();
  return "<inertial><origin xyz=\"" + triple(c) + "\" rpy=\"0 0 0\"/><mass value=\"" + num(m) +
         "\"/><inertia ixx=\"" + num(Ic(0, 0)) + "\" iyy=\"" + num(Ic(1, 1)) + "\" izz=\"" +
         num(Ic(2, 2)) + "\" ixy=\"" + num(Ic(0, 1)) + "\" ixz=\"" + num(Ic(0, 2)) + "\" iyz=\"" +
         num(Ic(1, 2)) + "\"/></inertial>";
}

// The same robot with the fixed links merged by hand into a URDF without fixed joints.
TEST(Merge, SameAsHandMergedUrdf) {
  const MergeExpect e = merge_expected();
  const std::string lim = "<limit effort=\"10\" velocity=\"1\" lower=\"-1\" upper=\"1\"/>";
  const std::string xml =
      "<robot name=\"merged\"><link name=\"world\"/>"
      "<link name=\"arm\">" + inertial_xml(e.I[0]) + "</link>"
      "<link name=\"slider\">" + inertial_xml(e.I[1]) + "</link>"
      "<link name=\"wheel\">" + inertial_xml(e.I[2]) + "</link>"
      "<joint name=\"j_arm\" type=\"revolute\"><parent link=\"world\"/><child link=\"arm\"/>" +
      origin_xml(e.X[0]) + "<axis xyz=\"0 0 1\"/>" + lim + "</joint>"
      "<joint name=\"j_slide\" type=\"prismatic\"><parent link=\"arm\"/><child link=\"slider\"/>" +
      origin_xml(e.X[1]) + "<axis xyz=\"1 1 0\"/>" + lim + "</joint>"
      "<joint name=\"j_wheel\" type=\"continuous\"><parent link=\"arm\"/><child link=\"wheel\"/>" +
      origin_xml(e.X[2]) + "<axis xyz=\"0 1 0\"/></joint></robot>";
  const Model a = build_model(parse_urdf(kMergeUrdf, "merge.urdf"));
  const Model b = build_model(parse_urdf(xml, "merged.urdf"));
  ASSERT_EQ(b.nv(), 3);
  EXPECT_EQ(a.joint_names, b.joint_names);
  for (int i = 0; i < 3; ++i) {
    EXPECT_EQ(a.parent(i), b.parent(i));
    EXPECT_EQ(a.bodies[i].type, b.bodies[i].type);
    EXPECT_LT((v3(a.bodies[i].axis) - v3(b.bodies[i].axis)).norm(), 1e-15);
    EXPECT_LT(maxabs(dense(a.bodies[i].Xtree) - dense(b.bodies[i].Xtree)), 1e-13) << i;
    EXPECT_LT(maxabs(dense(a.bodies[i].I) - dense(b.bodies[i].I)), 1e-13) << i;
  }
}

// urdfdom keeps only quaternions; a pitch of exactly pi/2 must survive (urdf::Rotation::
// getRPY would snap nearby pitches to pi/2 and lose ~1e-3 rad).
TEST(Merge, OrientationsNearPitchHalfPi) {
  for (double pitch : {M_PI / 2, 1.5708, 1.57, -1.5707, 3.0}) {
    const std::string xml =
        "<robot name=\"r\"><link name=\"a\"/><link name=\"b\"><inertial><mass value=\"1\"/>"
        "<origin xyz=\"0 0 0\" rpy=\"0.3 " + num(pitch) + " -0.2\"/>"
        "<inertia ixx=\"1\" iyy=\"2\" izz=\"2.5\" ixy=\"0\" ixz=\"0\" iyz=\"0\"/></inertial></link>"
        "<joint name=\"j\" type=\"continuous\"><parent link=\"a\"/><child link=\"b\"/>"
        "<origin xyz=\"1 2 3\" rpy=\"0.7 " + num(pitch) + " 0.4\"/></joint></robot>";
    const Model m = build_model(parse_urdf(xml, "p.urdf"));
    EXPECT_LT(maxabs(dense(m.bodies[0].Xtree) - origin(1, 2, 3, 0.7, pitch, 0.4)), 1e-14) << pitch;
    const Mat6d I = link_inertia6(1, V3d::Zero(), V3d(0.3, pitch, -0.2), V3d(1, 2, 2.5).asDiagonal());
    EXPECT_LT(maxabs(dense(m.bodies[0].I) - I), 1e-14) << pitch;
  }
}

// ---- DoF order rules ------------------------------------------------------------------

std::string joint_xml(const std::string& name, const std::string& type, const std::string& parent,
                      const std::string& child) {
  return "<joint name=\"" + name + "\" type=\"" + type + "\"><parent link=\"" + parent +
         "\"/><child link=\"" + child + "\"/>" +
         (type == "revolute" || type == "prismatic"
              ? "<limit effort=\"1\" velocity=\"1\" lower=\"0\" upper=\"1\"/>"
              : "") +
         "</joint>";
}

TEST(DofOrder, ByteWiseJointNamesAndFixedSubtreesInPlace) {
  // root children by joint name, byte-wise: "B" < "Z_fix" < "_x" < "a"; the fixed
  // link under "Z_fix" is transparent, so its moving children come right there,
  // in their own name order ("m1" < "m2"), and before "_x".
  std::string xml = "<robot name=\"order\"><link name=\"root\"/>";
  for (const char* l : {"lB", "lfix", "lx", "la", "lm1", "lm2", "lBchild"})
    xml += std::string("<link name=\"") + l + "\"/>";
  xml += joint_xml("a", "continuous", "root", "la");
  xml += joint_xml("_x", "continuous", "root", "lx");
  xml += joint_xml("m2", "revolute", "lfix", "lm2");
  xml += joint_xml("Z_fix", "fixed", "root", "lfix");
  xml += joint_xml("m1", "prismatic", "lfix", "lm1");
  xml += joint_xml("B", "revolute", "root", "lB");
  xml += joint_xml("B2", "continuous", "lB", "lBchild");
  xml += "</robot>";
  const Model m = build_model(parse_urdf(xml, "order.urdf"));
  EXPECT_EQ(m.joint_names, (std::vector<std::string>{"B", "B2", "m1", "m2", "_x", "a"}));
  EXPECT_EQ(m.link_names, (std::vector<std::string>{"lB", "lBchild", "lm1", "lm2", "lx", "la"}));
  const std::vector<Index> parents = {-1, 0, -1, -1, -1, -1};
  for (Index i = 0; i < m.nv(); ++i) EXPECT_EQ(m.parent(i), parents[i]);
}

TEST(DofOrder, EmptyModelIsAllowed) {
  const Model one = build_model(parse_urdf("<robot name=\"r\"><link name=\"a\"/></robot>", "one.urdf"));
  EXPECT_EQ(one.nv(), 0);
  EXPECT_EQ(one.root_link, "a");
  std::string xml = "<robot name=\"r\"><link name=\"a\"/><link name=\"b\"><inertial><mass value=\"1\"/>"
                    "<inertia ixx=\"1\" iyy=\"1\" izz=\"1\" ixy=\"0\" ixz=\"0\" iyz=\"0\"/></inertial></link>" +
                    joint_xml("f", "fixed", "a", "b") + "</robot>";
  EXPECT_EQ(build_model(parse_urdf(xml, "fixed.urdf")).nv(), 0);
}

// The order of links and joints in the input does not matter.
TEST(DofOrder, IndependentOfInputOrder) {
  std::vector<RawTree> trees = {generate_tree("tree:60:5"), parse_urdf(kMergeUrdf, "merge.urdf")};
  {
    const std::string path = test::model_path("atlas.urdf");
    std::ifstream f(path);
    trees.push_back(parse_urdf(std::string(std::istreambuf_iterator<char>(f), {}), path));
  }
  std::mt19937_64 rng(3);
  for (const RawTree& t : trees) {
    SCOPED_TRACE(t.source);
    const Model ref = build_model(t, lenient());
    for (int rep = 0; rep < 4; ++rep) {
      RawTree s = t;
      std::shuffle(s.links.begin(), s.links.end(), rng);
      std::shuffle(s.joints.begin(), s.joints.end(), rng);
      expect_identical(build_model(s, lenient()), ref);
    }
  }
}

// ---- validation ---------------------------------------------------------------------------

// base -> j1 (revolute) -> l1 -> j2 (prismatic) -> l2
RawTree small_tree() {
  RawTree t;
  t.name = "small";
  t.source = "raw.urdf";
  t.links.resize(3);
  t.links[0].name = "base";
  for (int i = 1; i <= 2; ++i) {
    RawLink& l = t.links[i];
    l.name = "l" + std::to_string(i);
    l.has_inertial = true;
    l.mass = 1;
    l.com_xyz = {0, 0, 0.1};
    l.inertia = {0.01, 0.012, 0.015, 0, 0, 0};
  }
  t.joints.resize(2);
  t.joints[0] = {"j1", RawJointType::Revolute, "revolute", "base", "l1", {0, 0, 0.1}, {0, 0, 0}, false, {}, {0, 0, 1}};
  t.joints[1] = {"j2", RawJointType::Prismatic, "prismatic", "l1", "l2", {0, 0, 0.2}, {0, 0, 0}, false, {}, {1, 0, 0}};
  return t;
}

void expect_raw_error(const std::function<void(RawTree&)>& edit, const std::vector<std::string>& needles) {
  RawTree t = small_tree();
  edit(t);
  std::vector<std::string> n = needles;
  n.insert(n.begin(), "raw.urdf: ");
  expect_error([&] { build_model(t); }, n);
}

RawLink link_named(const std::string& name) {
  RawLink l;
  l.name = name;
  return l;
}
RawJoint joint_named(const std::string& name, const std::string& parent, const std::string& child) {
  RawJoint j;
  j.name = name;
  j.type = RawJointType::Revolute;
  j.type_name = "revolute";
  j.parent = parent;
  j.child = child;
  return j;
}

TEST(Validation, SmallTreeIsValid) {
  const Model m = build_model(small_tree());
  ASSERT_EQ(m.nv(), 2);
  EXPECT_EQ(m.bodies[1].type, JointType::Prismatic);
}

TEST(Validation, LinkNumbers) {
  expect_raw_error([](RawTree& t) { t.links[1].mass = -1; }, {"link 'l1': ", "mass -1 is not positive"});
  expect_raw_error([](RawTree& t) { t.links[2].mass = 0; }, {"link 'l2': ", "not positive"});
  expect_raw_error([](RawTree& t) { t.links[1].mass = kNaN; }, {"link 'l1': ", "not finite"});
  expect_raw_error([](RawTree& t) { t.links[1].mass = kInf; }, {"link 'l1': ", "not finite"});
  expect_raw_error([](RawTree& t) { t.links[1].com_xyz.y = kNaN; }, {"link 'l1': ", "non-finite"});
  expect_raw_error([](RawTree& t) { t.links[1].com_rpy.z = -kInf; }, {"link 'l1': ", "non-finite"});
  expect_raw_error([](RawTree& t) { t.links[2].inertia.xz = kNaN; }, {"link 'l2': ", "non-finite"});
  // a massless link's numbers must still be finite
  expect_raw_error([](RawTree& t) { t.links[0].com_xyz.x = kNaN; }, {"link 'base': ", "non-finite"});
}

TEST(Validation, InertiaPhysical) {
  expect_raw_error([](RawTree& t) { t.links[1].inertia = {0.01, 0.01, -0.01, 0, 0, 0}; },
                   {"link 'l1': ", "not positive definite"});
  expect_raw_error([](RawTree& t) { t.links[1].inertia = {0, 0, 0, 0, 0, 0}; },  // point mass
                   {"link 'l1': ", "not positive definite"});
  expect_raw_error([](RawTree& t) { t.links[2].inertia = {1, 1, 1, 2, 0, 0}; },  // indefinite
                   {"link 'l2': ", "not positive definite"});
  expect_raw_error([](RawTree& t) { t.links[2].inertia = {0.01, 0.01, 0.03, 0, 0, 0}; },
                   {"link 'l2': ", "triangle inequality"});
  // rotated tensor violating the triangle inequality (non-diagonal path)
  expect_raw_error(
      [](RawTree& t) {
        const Mat3d R = rpy_rot(0.3, 0.2, 0.1);
        const Mat3d A = R * V3d(1, 1, 2.01).asDiagonal() * R.transpose();
        t.links[1].inertia = {A(0, 0), A(1, 1), A(2, 2), A(0, 1), A(0, 2), A(1, 2)};
      },
      {"link 'l1': ", "triangle inequality"});
  // exact equalities pass: thin plates and rods' limits, rotated or not
  for (const V3d& d : {V3d(1, 2, 3), V3d(1, 1, 2), V3d(2, 1, 1), V3d(1e-3, 1, 1)}) {
    for (const bool rotate : {false, true}) {
      RawTree t = small_tree();
      const Mat3d R = rotate ? rpy_rot(0.3, -1.1, 2.0) : Mat3d::Identity();
      const Mat3d A = R * d.asDiagonal() * R.transpose();
      t.links[1].inertia = {A(0, 0), A(1, 1), A(2, 2), A(0, 1), A(0, 2), A(1, 2)};
      EXPECT_NO_THROW(build_model(t)) << d.transpose() << " rotate " << rotate;
    }
  }
  // lenient build: waived with a warning, mass still checked
  RawTree t = small_tree();
  t.links[1].inertia = {0.01, 0.01, -0.01, 0, 0, 0};
  std::vector<std::string> w;
  EXPECT_EQ(build_model(t, lenient(&w)).nv(), 2);
  ASSERT_EQ(w.size(), 1u);
  EXPECT_NE(w[0].find("raw.urdf: link 'l1': "), std::string::npos) << w[0];
  t.links[1].mass = 0;
  expect_error([&] { build_model(t, lenient()); }, {"raw.urdf: link 'l1': ", "not positive"});
}

TEST(Validation, JointNumbersAndTypes) {
  expect_raw_error([](RawTree& t) { t.joints[0].axis = {0, 0, 0}; }, {"joint 'j1': ", "axis"});
  expect_raw_error([](RawTree& t) { t.joints[1].axis.y = kNaN; }, {"joint 'j2': ", "axis", "non-finite"});
  expect_raw_error([](RawTree& t) { t.joints[0].xyz.z = kInf; }, {"joint 'j1': ", "origin"});
  expect_raw_error([](RawTree& t) { t.joints[1].rpy.x = kNaN; }, {"joint 'j2': ", "origin"});
  expect_raw_error(
      [](RawTree& t) { t.joints[0].type = RawJointType::Floating, t.joints[0].type_name = "floating"; },
      {"joint 'j1': ", "'floating'", "not supported"});
  expect_raw_error(
      [](RawTree& t) { t.joints[1].type = RawJointType::Planar, t.joints[1].type_name = "planar"; },
      {"joint 'j2': ", "'planar'"});
  expect_raw_error(
      [](RawTree& t) { t.joints[1].type = RawJointType::Unknown, t.joints[1].type_name = "banana"; },
      {"joint 'j2': ", "'banana'"});
  // a fixed joint's axis is irrelevant, zero is fine
  RawTree t = small_tree();
  t.joints[1].type = RawJointType::Fixed;
  t.joints[1].axis = {0, 0, 0};
  EXPECT_EQ(build_model(t).nv(), 1);
}

TEST(Validation, Structure) {
  expect_raw_error([](RawTree& t) { t.joints[1].parent = "nope"; }, {"joint 'j2': ", "'nope'", "does not exist"});
  expect_raw_error([](RawTree& t) { t.joints[1].child = "nope"; }, {"joint 'j2': ", "'nope'", "does not exist"});
  expect_raw_error([](RawTree& t) { t.links.push_back(t.links[2]); }, {"link 'l2': ", "duplicate"});
  expect_raw_error(
      [](RawTree& t) {
        t.links.push_back(link_named("l3"));
        t.joints.push_back(joint_named("j2", "l2", "l3"));
      },
      {"joint 'j2': ", "duplicate"});
  expect_raw_error([](RawTree& t) { t.joints.push_back(joint_named("j3", "base", "l2")); },
                   {"link 'l2': ", "two parent joints", "'j2'", "'j3'"});
  expect_raw_error([](RawTree& t) { t.links.push_back(link_named("extra")); },
                   {"link 'extra': ", "root", "'base'"});
  // every link has a parent: no root
  expect_raw_error([](RawTree& t) { t.joints.push_back(joint_named("j0", "l2", "base")); },
                   {"link 'base': ", "no root", "cycle"});
  // a cycle off to the side: c1 -> c2 -> c1
  expect_raw_error(
      [](RawTree& t) {
        t.links.push_back(link_named("c1"));
        t.links.push_back(link_named("c2"));
        t.joints.push_back(joint_named("jc1", "c1", "c2"));
        t.joints.push_back(joint_named("jc2", "c2", "c1"));
      },
      {"link 'c1': ", "not connected", "cycle"});
  expect_raw_error(
      [](RawTree& t) {
        t.links.push_back(link_named("x"));
        t.joints.push_back(joint_named("jx", "x", "x"));
      },
      {"joint 'jx': ", "itself"});
  expect_raw_error([](RawTree& t) { t.links.clear(), t.joints.clear(); }, {"no links"});
}

const char* kHead = "<robot name=\"r\"><link name=\"a\"/>";
std::string urdf(const std::string& body) { return kHead + body + "</robot>"; }
const std::string kLinkB = "<link name=\"b\"/>";

void expect_urdf_error(const std::string& xml, const std::vector<std::string>& needles) {
  std::vector<std::string> n = needles;
  n.insert(n.begin(), "robot.urdf: ");
  expect_error([&] { build_model(parse_urdf(xml, "robot.urdf")); }, n);
}

TEST(Validation, ThroughUrdf) {
  // urdfdom's own messages, file named
  expect_urdf_error(urdf(kLinkB + "<joint name=\"j1\" type=\"banana\"><parent link=\"a\"/><child link=\"b\"/></joint>"),
                    {"Joint [j1] has no known type [banana]"});
  expect_urdf_error("<robot name=\"x\"><link name=\"a\"></robot>", {});
  expect_urdf_error("", {"empty"});
  expect_urdf_error(urdf(kLinkB + "<joint name=\"j1\" type=\"continuous\"><parent link=\"a\"/><child link=\"b\"/>"
                                  "<origin xyz=\"0 nan 0\"/></joint>"),
                    {"[nan]", "joint [j1]"});
  expect_urdf_error(urdf(kLinkB + "<joint name=\"j1\" type=\"continuous\"><parent link=\"a\"/><child link=\"b\"/>"
                                  "<axis xyz=\"inf 0 1\"/></joint>"),
                    {"[inf]", "joint [j1]"});
  expect_urdf_error(urdf("<link name=\"b\"><inertial><mass value=\"nan\"/><inertia ixx=\"1\" iyy=\"1\" izz=\"1\" "
                         "ixy=\"0\" ixz=\"0\" iyz=\"0\"/></inertial></link>" +
                         joint_xml("j1", "continuous", "a", "b")),
                    {"Link [b]"});
  expect_urdf_error(urdf(kLinkB + joint_xml("j1", "continuous", "a", "zz")), {"[zz]", "[j1]"});
  expect_urdf_error(urdf(kLinkB + "<link name=\"c\"/>" + joint_xml("j1", "continuous", "a", "b")), {"root"});
  expect_urdf_error(urdf(kLinkB + joint_xml("j1", "continuous", "a", "b") + joint_xml("j1", "continuous", "b", "a")),
                    {"j1"});
  expect_urdf_error(urdf(kLinkB + kLinkB + joint_xml("j1", "continuous", "a", "b")), {"'b'"});
  // ours: what urdfdom accepts
  expect_urdf_error(urdf(kLinkB + joint_xml("j1", "floating", "a", "b")), {"joint 'j1': ", "floating"});
  expect_urdf_error(urdf(kLinkB + joint_xml("j1", "planar", "a", "b")), {"joint 'j1': ", "planar"});
  expect_urdf_error(urdf(kLinkB + joint_xml("j1", "continuous", "a", "b") + joint_xml("j2", "continuous", "a", "b")),
                    {"link 'b': ", "two parent joints"});
  expect_urdf_error(urdf(kLinkB + "<joint name=\"j1\" type=\"continuous\"><parent link=\"a\"/><child link=\"b\"/>"
                                  "<axis xyz=\"0 0 0\"/></joint>"),
                    {"joint 'j1': ", "<axis> is zero"});
  expect_urdf_error(urdf("<link name=\"b\"><inertial><mass value=\"-2\"/><inertia ixx=\"1\" iyy=\"1\" izz=\"1\" "
                         "ixy=\"0\" ixz=\"0\" iyz=\"0\"/></inertial></link>" +
                         joint_xml("j1", "continuous", "a", "b")),
                    {"link 'b': ", "mass -2 is not positive"});
  expect_urdf_error(urdf("<link name=\"b\"><inertial><mass value=\"2\"/><inertia ixx=\"1\" iyy=\"1\" izz=\"3\" "
                         "ixy=\"0\" ixz=\"0\" iyz=\"0\"/></inertial></link>" +
                         joint_xml("j1", "continuous", "a", "b")),
                    {"link 'b': ", "triangle inequality"});
}

// Parsing installs its own console_bridge handler and puts the caller's back.
TEST(Validation, ConsoleHandlerRestored) {
  console_bridge::OutputHandler* before = console_bridge::getOutputHandler();
  const console_bridge::LogLevel level = console_bridge::getLogLevel();
  EXPECT_THROW(parse_urdf("<robot", "x.urdf"), ModelError);
  parse_urdf(urdf(""), "y.urdf");
  EXPECT_EQ(console_bridge::getOutputHandler(), before);
  EXPECT_EQ(console_bridge::getLogLevel(), level);
}

TEST(Validation, FilesAndSpecs) {
  expect_error([] { load_urdf("/nonexistent/dir/robot.urdf"); }, {"/nonexistent/dir/robot.urdf: cannot open file: No such file or directory"});
  expect_error([] { load_model("/nonexistent/robot.urdf"); }, {"/nonexistent/robot.urdf: cannot open file: No such file or directory"});
  const std::string dir = ::testing::TempDir();
  expect_error([&] { load_model(dir); }, {dir + ": not a regular file (a directory)"});
  // per process: two build trees' tests may run at once on one machine
  const std::string path = dir + "/scandyn_test_model_empty_" + std::to_string(::getpid()) + ".urdf";
  { std::ofstream f(path); }
  expect_error([&] { load_urdf(path); }, {path + ": ", "empty"});
  {
    std::ofstream f(path);
    f << urdf(kLinkB + joint_xml("j1", "continuous", "a", "b"));
  }
  EXPECT_EQ(load_model(path).nv(), 1);
  EXPECT_EQ(load_model(path).source, path);
  std::remove(path.c_str());

  for (const char* spec : {"rope:", "rope:-3", "rope:abc", "rope:+3", "rope: 3", "rope:3x", "rope:1.5",
                           "tree:5", "tree:5:", "tree:5:x", "tree:5:-1", "tree:0:1", "chain:0", "rope:0",
                           "curtain:3", "curtain:0:4", "curtain:4:0", "rope:3:4", "chain:",
                           "rope:99999999999", "rope:10000001", "curtain:10000:10000",
                           "tree:3:99999999999999999999999"}) {
    expect_error([&] { load_model(spec); }, {std::string(spec) + ": "});
    expect_error([&] { make_generated(spec); }, {std::string(spec) + ": "});
  }
  expect_error([] { make_generated("rope:0"); }, {"rope:0: N must be >= 1"});
  expect_error([] { make_generated("curtain:0:3"); }, {"curtain:0:3: K must be >= 1"});
  expect_error([] { make_generated("rope:abc"); }, {"rope:abc: N must be a positive integer, got 'abc'"});
  expect_error([] { make_generated("banana:3"); }, {"banana:3: unknown generator"});
  EXPECT_TRUE(is_generator_spec("rope:3"));
  EXPECT_TRUE(is_generator_spec("curtain:"));
  EXPECT_FALSE(is_generator_spec("banana:3"));
  EXPECT_FALSE(is_generator_spec("./rope:3.urdf"));
  EXPECT_FALSE(is_generator_spec("rope"));
}

// A generated tree goes through the same validator: errors name the spec.
TEST(Validation, GeneratedTreesAreValidatedToo) {
  RawTree t = generate_tree("rope:5");
  t.links[3].mass = kNaN;
  expect_error([&] { build_model(t); }, {"rope:5: link 'link_2': ", "not finite"});
}

// ---- generators ----------------------------------------------------------------------------

TEST(Generators, Chain) {
  const Model m = make_generated("chain:12");
  ASSERT_EQ(m.nv(), 12);
  EXPECT_EQ(m.name, "chain:12");
  EXPECT_EQ(m.source, "chain:12");
  EXPECT_EQ(m.root_link, "base");
  EXPECT_EQ(m.joint_names[0], "joint_00");
  EXPECT_EQ(m.joint_names[11], "joint_11");
  EXPECT_EQ(m.link_names[3], "link_03");
  const Mat6d I = rigid_inertia(1, V3d(0, 0, 0.15), V3d(0.0075, 0.0075, 1e-3).asDiagonal());
  for (Index i = 0; i < 12; ++i) {
    const Body<double>& b = m.bodies[i];
    EXPECT_EQ(b.parent, i - 1);
    EXPECT_EQ(b.type, JointType::Revolute);
    EXPECT_EQ(v3(b.axis), i % 2 == 0 ? V3d(0, 0, 1) : V3d(0, 1, 0));
    EXPECT_LT(maxabs(dense(b.Xtree) - origin(0, 0, i == 0 ? 0 : 0.3, 0, 0, 0)), 1e-16);
    EXPECT_LT(maxabs(dense(b.I) - I), 1e-16);
  }
}

TEST(Generators, Rope3Geometry) {
  const Model m = make_generated("rope:3");
  ASSERT_EQ(m.nv(), 3);
  EXPECT_EQ(m.joint_names, (std::vector<std::string>{"joint_0", "joint_1", "joint_2"}));
  // solid cylinder, m = 0.01 kg, L = 1 cm, r = 2 mm, along -z
  const double mass = 0.01, L = 0.01, r = 0.002;
  const double side = mass * (3 * r * r + L * L) / 12, axial = mass * r * r / 2;
  EXPECT_NEAR(side, 9.3333333333333333e-8, 1e-22);
  const Mat6d I = rigid_inertia(mass, V3d(0, 0, -L / 2), V3d(side, side, axial).asDiagonal());
  for (Index i = 0; i < 3; ++i) {
    const Body<double>& b = m.bodies[i];
    EXPECT_EQ(b.parent, i - 1);
    EXPECT_EQ(v3(b.axis), i % 2 == 0 ? V3d(1, 0, 0) : V3d(0, 1, 0));
    EXPECT_LT(maxabs(dense(b.Xtree) - origin(0, 0, i == 0 ? 0 : -0.01, 0, 0, 0)), 1e-18);
    EXPECT_LT(maxabs(dense(b.I) - I), 1e-20);
  }
  // about the joint: Ibar_xx = side + m (L/2)^2
  EXPECT_NEAR(m.bodies[0].I.I.xx, side + mass * 0.005 * 0.005, 1e-22);
  EXPECT_NEAR(m.bodies[0].I.h.z, -mass * 0.005, 1e-20);
}

TEST(Generators, LargeRope) {
  const Model m = make_generated("rope:100000");
  ASSERT_EQ(m.nv(), 100000);
  for (Index i = 0; i < m.nv(); ++i) ASSERT_EQ(m.parent(i), i - 1);
  EXPECT_EQ(m.joint_names[0], "joint_00000");
  EXPECT_EQ(m.joint_names[99999], "joint_99999");
  EXPECT_TRUE(std::is_sorted(m.joint_names.begin(), m.joint_names.end()));
  EXPECT_EQ(m.bodies[99999].Xtree.r.z, -0.01);
}

TEST(Generators, Curtain) {
  const Model m = make_generated("curtain:12:5");  // two-digit rope index: padding keeps the order
  ASSERT_EQ(m.nv(), 60);
  EXPECT_EQ(m.root_link, "rod");
  for (Index k = 0; k < 12; ++k)
    for (Index i = 0; i < 5; ++i) {
      const Index b = 5 * k + i;
      char name[32];
      std::snprintf(name, sizeof name, "joint_%02d_%d", k, i);
      EXPECT_EQ(m.joint_names[b], name);
      EXPECT_EQ(m.parent(b), i == 0 ? -1 : b - 1);
      EXPECT_EQ(v3(m.bodies[b].axis), i % 2 == 0 ? V3d(1, 0, 0) : V3d(0, 1, 0));
      const V3d r = i == 0 ? V3d(0.02 * k, 0, 0) : V3d(0, 0, -0.01);
      EXPECT_LT(maxabs(dense(m.bodies[b].Xtree) - plucker(Mat3d::Identity(), r)), 1e-16);
      EXPECT_DOUBLE_EQ(m.bodies[b].I.m, 0.01);
    }
  EXPECT_EQ(make_generated("curtain:1:7").nv(), 7);
}

// Preorder DFS written recursively, as an independent statement of the DoF order.
void preorder(const RawTree& t, const std::string& link, std::vector<std::string>& out) {
  std::vector<const RawJoint*> kids;
  for (const auto& j : t.joints)
    if (j.parent == link) kids.push_back(&j);
  std::sort(kids.begin(), kids.end(), [](const RawJoint* a, const RawJoint* b) { return a->name < b->name; });
  for (const RawJoint* j : kids) {
    if (j->type != RawJointType::Fixed) out.push_back(j->name);
    preorder(t, j->child, out);
  }
}

TEST(Generators, RandomTree) {
  const RawTree raw = generate_tree("tree:200:11");
  const Model m = build_model(raw);
  ASSERT_EQ(m.nv(), 200);
  expect_parent_before_child(m);
  // 40 fixed links (every 5th body), all with mass
  int fixed = 0;
  double raw_mass = 0, model_mass = 0;
  for (const auto& j : raw.joints) fixed += j.type == RawJointType::Fixed;
  for (const auto& l : raw.links) raw_mass += l.has_inertial ? l.mass : 0;
  for (const auto& b : m.bodies) model_mass += b.I.m;
  EXPECT_EQ(fixed, 40);
  EXPECT_EQ(raw.links.size(), 241u);
  EXPECT_NEAR(model_mass, raw_mass, 1e-12);
  // DoF order
  std::vector<std::string> expected;
  preorder(raw, "base", expected);
  EXPECT_EQ(m.joint_names, expected);
  // joints: ~20% prismatic, axes unit and not axis-aligned, masses in range
  int prismatic = 0;
  for (const auto& b : m.bodies) {
    prismatic += b.type == JointType::Prismatic;
    EXPECT_NEAR(dot(b.axis, b.axis), 1.0, 1e-14);
    EXPECT_GE(std::fmin(std::fabs(b.axis.x), std::fmin(std::fabs(b.axis.y), std::fabs(b.axis.z))), 0.1);
  }
  EXPECT_GT(prismatic, 20);
  EXPECT_LT(prismatic, 60);
  for (const auto& l : raw.links) {
    if (!l.has_inertial) continue;
    EXPECT_GE(l.mass, 0.5);
    EXPECT_LE(l.mass, 2.0);
    EXPECT_LE(v3(l.com_xyz).cwiseAbs().maxCoeff(), 0.1);
  }
  // some fixed links carry moving children (the fixed subtree is visited in place)
  int under_fixed = 0;
  for (const auto& j : raw.joints)
    under_fixed += j.parent.size() > 6 && j.parent.compare(j.parent.size() - 6, 6, "_fixed") == 0;
  EXPECT_GT(under_fixed, 0);
}

TEST(Generators, RandomTreeDeterminism) {
  const Model a = make_generated("tree:50:7"), b = make_generated("tree:50:7");
  expect_identical(a, b);
  const Model c = make_generated("tree:50:8");
  ASSERT_EQ(c.nv(), 50);
  double diff = 0;
  for (Index i = 0; i < 50; ++i) diff += maxabs(dense(a.bodies[i].Xtree) - dense(c.bodies[i].Xtree));
  EXPECT_GT(diff, 1.0);
  // the random stream is std::mt19937_64 through our own integer -> double mapping, so
  // these values (recorded once) are the same on every platform
  const RawTree g = generate_tree("tree:6:42");
  ASSERT_EQ(g.links.size(), 8u);
  EXPECT_EQ(g.links[1].name, "link_0");
  EXPECT_EQ(g.links[1].mass, 0.51857415669802198);
  EXPECT_EQ(g.links[2].mass, 1.6177482621394603);
  EXPECT_EQ(g.links[6].name, "link_4_fixed");
  EXPECT_EQ(g.links[6].mass, 1.5802037701304095);
  EXPECT_EQ(g.links[7].mass, 1.7283040311208886);
  EXPECT_EQ(g.joints[1].parent, "link_0");
  EXPECT_EQ(g.joints[1].type, RawJointType::Prismatic);
  EXPECT_EQ(g.joints[5].name, "joint_4_fixed");
  EXPECT_EQ(g.joints[6].parent, "link_2");
}

}  // namespace
}  // namespace scandyn
