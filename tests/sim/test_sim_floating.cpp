// Tests of the simulator with a floating base and ball joints (scene "base":
// "floating", ballrope:N): integration on the configuration manifold
// (scandyn/sim/integrators.hpp, step_instance_at). Truths: conservation of linear
// and angular momentum (from the CRBA's base rows, a second algorithm) and of
// energy without gravity; Euler's equations of a free rigid body (the
// intermediate-axis flip); RK4's fourth order on the manifold; serial = OpenMP
// bitwise; float against double; unit quaternions; the scene's errors.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <string>

#include <unistd.h>
#include <vector>

#include "scandyn/algorithm/configuration.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/sim/contacts.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"
#include "scene_util.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

using sim::Scene;
using sim::SceneError;
using sim::Simulator;

using test::scene_error;
using test::scene_from;


// One instance's state in double (q: nq, qd: nv).
struct State {
  std::vector<double> q, qd;
};
template <class S>
State state_of(Simulator<S>& sim, Index b = 0) {
  const std::size_t nq = static_cast<std::size_t>(sim.nq()), nv = static_cast<std::size_t>(sim.nv());
  const std::size_t B = static_cast<std::size_t>(sim.batch());
  std::vector<S> q(nq * B), qd(nv * B);
  sim.read_state(q.data(), qd.data());
  State s{std::vector<double>(nq), std::vector<double>(nv)};
  for (std::size_t i = 0; i < nq; ++i) s.q[i] = double(q[i * B + static_cast<std::size_t>(b)]);
  for (std::size_t i = 0; i < nv; ++i) s.qd[i] = double(qd[i * B + static_cast<std::size_t>(b)]);
  return s;
}

// A URDF of one free link (the floating base alone): mass m, principal inertia
// (ixx, iyy, izz) about its origin, the centre of mass there. Written once per name.
std::string one_body_urdf(const std::string& name, double m, double ixx, double iyy, double izz) {
  const std::string path = ::testing::TempDir() + "/scandyn_" + name + "_" + std::to_string(::getpid()) + ".urdf";  // per process: ctest -j runs tests that write the same name at once
  std::ofstream f(path);
  f << "<robot name=\"" << name << "\"><link name=\"" << name << "\"><inertial><origin xyz=\"0 0 0\"/>"
    << "<mass value=\"" << m << "\"/><inertia ixx=\"" << ixx << "\" ixy=\"0\" ixz=\"0\" iyy=\"" << iyy
    << "\" iyz=\"0\" izz=\"" << izz << "\"/></inertial></link></robot>\n";
  return path;
}

// The system's momentum in the world frame: linear P, angular about the world
// origin L_O and about the centre of mass L_c. From the CRBA: the base rows of
// M(q) qd are the spatial momentum [n; f] in the base frame about its origin.
struct Momentum {
  Vec3<double> P, L_origin, L_com;
  Vec3<double> com;  // the centre of mass (world)
  double mass;
};
Momentum momentum(const Model& model, const State& s) {
  const Index nv = model.nv();
  Data data(model);
  std::vector<double> M(static_cast<std::size_t>(nv * nv));
  crba(model, data, s.q.data(), M.data());
  double h[6] = {0, 0, 0, 0, 0, 0};
  for (int r = 0; r < 6; ++r)
    for (Index c = 0; c < nv; ++c) h[r] += M[r * nv + c] * s.qd[c];
  const Mat3<double> R = quat_to_matrix(s.q.data() + 3);
  const Vec3<double> p{s.q[0], s.q[1], s.q[2]};
  Momentum out;
  out.P = R * Vec3<double>{h[3], h[4], h[5]};
  out.L_origin = R * Vec3<double>{h[0], h[1], h[2]} + cross(p, out.P);
  // the centre of mass from the bodies' world poses
  std::vector<Transform<double>> X(static_cast<std::size_t>(model.nbodies()));
  std::vector<Motion<double>> v(X.size());
  sim::contact_kinematics_at(model.bodies.data(), model.nbodies(), s.q.data(), s.qd.data(), X.data(), v.data());
  double mass = 0;
  Vec3<double> mc = Vec3<double>::zero();
  for (Index i = 0; i < model.nbodies(); ++i) {
    const Inertia<double>& I = model.bodies[i].I;
    mass += I.m;
    mc += I.m * (mul_transpose(X[i].E, (1.0 / I.m) * I.h) + X[i].r);
  }
  out.com = (1.0 / mass) * mc;
  out.mass = mass;
  out.L_com = out.L_origin - cross(out.com, out.P);
  return out;
}

double norm(const Vec3<double>& a) { return std::sqrt(dot(a, a)); }

// A free system in zero gravity tumbling from a random state: over 10^4 RK4 steps
// in double, linear momentum, angular momentum about the centre of mass (and about
// the origin) and energy drift by at most 1e-9 relative.
void expect_conserved(const std::string& model_spec, double dt, double qd_spread) {
  // the base spins and drifts; the joints start bent at random with random rates
  const Scene probe = scene_from(R"({"model": ")" + model_spec + R"(", "allow_nonphysical_inertia": true, "base": "floating", "dt": 1})");
  std::string qd = "[0.5, -0.3, 0.2, 0.1, 0.05, -0.02", spread = "[0, 0, 0, 0, 0, 0";
  for (Index i = 6; i < probe.nv(); ++i) qd += ", 0", spread += ", " + std::to_string(qd_spread);
  const Scene scene = scene_from(R"({"model": ")" + model_spec + R"(", "allow_nonphysical_inertia": true, "base": "floating", "dt": )" +
                                 std::to_string(dt) + R"(, "integrator": "rk4", "backend": "serial",
      "initial": {"qd": )" + qd + R"(], "random": {"seed": 3, "q": 0.3, "qd": )" + spread + "]}}}");
  ASSERT_TRUE(scene.model.floating_base());
  Simulator<double> sim(scene);
  const Momentum m0 = momentum(scene.model, state_of(sim));
  const double e0 = sim.energy()[0];
  ASSERT_GT(norm(m0.P), 1e-3);
  ASSERT_GT(norm(m0.L_com), 1e-3);
  for (int s = 0; s < 10000; ++s) sim.step();
  ASSERT_TRUE(sim.status().ok()) << sim::failure_message(sim.status());
  const State st = state_of(sim);
  const Momentum m1 = momentum(scene.model, st);
  const double e1 = sim.energy()[0];
  EXPECT_LE(std::abs(e1 - e0), 1e-9 * e0) << model_spec << ": energy " << e0 << " -> " << e1;
  EXPECT_LE(norm(m1.P - m0.P), 1e-9 * norm(m0.P)) << model_spec;
  EXPECT_LE(norm(m1.L_com - m0.L_com), 1e-9 * norm(m0.L_com)) << model_spec;
  EXPECT_LE(norm(m1.L_origin - m0.L_origin), 1e-9 * norm(m0.L_origin)) << model_spec;
  // it moved: the base travelled and turned
  EXPECT_GT(std::hypot(st.q[0], st.q[1], st.q[2]), 1e-2);
  for (Index i = 0; i < scene.model.nbodies(); ++i) {
    const Body<double>& b = scene.model.bodies[i];
    if (joint_nq(b.type) == 1) continue;
    const double* quat = st.q.data() + b.idx_q + (b.type == JointType::Free ? 3 : 0);
    EXPECT_NEAR(quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3], 1.0, 1e-14);
  }
}

TEST(SimFloatingConservation, FreeRope100) { expect_conserved("rope:100", 1.5e-4, 0.1); }
TEST(SimFloatingConservation, FreeBallrope100) { expect_conserved("ballrope:100", 1.5e-4, 0.1); }
TEST(SimFloatingConservation, FloatingAtlas) { expect_conserved("atlas.urdf", 5e-4, 0.3); }

// Euler's equations of a torque-free rigid body with principal inertia I (body
// frame): I w' = (I w) x w, integrated by RK4 at a tiny step (the truth).
Vec3<double> euler_equations(const Vec3<double>& I, Vec3<double> w, double T, int steps) {
  const double h = T / steps;
  auto f = [&](const Vec3<double>& x) {
    const Vec3<double> Iw{I.x * x.x, I.y * x.y, I.z * x.z};
    const Vec3<double> t = cross(Iw, x);
    return Vec3<double>{t.x / I.x, t.y / I.y, t.z / I.z};
  };
  for (int s = 0; s < steps; ++s) {
    const Vec3<double> k1 = f(w), k2 = f(w + 0.5 * h * k1), k3 = f(w + 0.5 * h * k2), k4 = f(w + h * k3);
    w = w + (h / 6) * (k1 + 2.0 * k2 + 2.0 * k3 + k4);
  }
  return w;
}

// An asymmetric free body (I = 1, 2, 3) spinning near its intermediate axis flips:
// its body-frame angular velocity follows Euler's equations through the flip (w_y
// from +2 to about -2 and back), its world-frame angular momentum stays put.
TEST(SimFloatingRigidBody, IntermediateAxisFlipFollowsEulersEquations) {
  const std::string urdf = one_body_urdf("tbar", 1.0, 1.0, 2.0, 3.0);
  const Vec3<double> I{1, 2, 3};
  const Vec3<double> w0{0.01, 2.0, 0.01};
  const Scene scene = scene_from(R"({"model": ")" + urdf + R"(", "base": "floating", "dt": 1e-3,
      "integrator": "rk4", "initial": {"qd": [0.01, 2.0, 0.01, 0.3, 0, 0]}})");
  ASSERT_EQ(scene.nq(), 7);
  ASSERT_EQ(scene.nv(), 6);
  Simulator<double> sim(scene);
  const Momentum m0 = momentum(scene.model, state_of(sim));
  bool flipped = false;
  for (int k = 1; k <= 20; ++k) {  // 20 s, compared every second
    for (int s = 0; s < 1000; ++s) sim.step();
    const State st = state_of(sim);
    const Vec3<double> w = euler_equations(I, w0, k * 1.0, k * 20000);
    EXPECT_NEAR(st.qd[0], w.x, 1e-7) << "t = " << k;
    EXPECT_NEAR(st.qd[1], w.y, 1e-7) << "t = " << k;
    EXPECT_NEAR(st.qd[2], w.z, 1e-7) << "t = " << k;
    flipped = flipped || st.qd[1] < -1.9;
    const Momentum m = momentum(scene.model, st);
    EXPECT_LE(norm(m.L_com - m0.L_com), 1e-10 * norm(m0.L_com));
    // the linear velocity stays (0.3, 0, 0) in the world: the body frame's v turns
    const Mat3<double> R = quat_to_matrix(st.q.data() + 3);
    const Vec3<double> vw = R * Vec3<double>{st.qd[3], st.qd[4], st.qd[5]};
    EXPECT_NEAR(vw.x, 0.3, 1e-10);
    EXPECT_NEAR(st.q[0], 0.3 * k, 1e-9);
  }
  EXPECT_TRUE(flipped) << "no flip of the intermediate axis in 20 s";
}

// RK4 is fourth order on the manifold (the stages' slopes combined in the tangent
// space through Jr^-1): halving dt divides the error at t = 1 s by about 16; euler
// is first order (about 2).
TEST(SimFloatingRigidBody, Rk4IsFourthOrderEulerFirstOnTheManifold) {
  const std::string urdf = one_body_urdf("brick", 2.0, 0.5, 1.5, 1.8);
  auto final_state = [&](const char* integrator, double dt) {
    const Scene scene = scene_from(R"({"model": ")" + urdf + R"(", "base": "floating", "dt": )" +
                                   std::to_string(dt) + R"(, "integrator": ")" + integrator + R"(",
        "effects": {"external": {"wrenches": [{"link": "brick", "wrench": [0.3, -0.2, 0.1, 1, 0, 0.5]}]}},
        "initial": {"qd": [1.0, 3.0, -2.0, 0.5, 0.2, -0.1]}})");
    Simulator<double> sim(scene);
    const int steps = static_cast<int>(std::lround(1.0 / dt));
    for (int s = 0; s < steps; ++s) sim.step();
    return state_of(sim);
  };
  auto error = [&](const State& a, const State& b) {
    double e = 0;
    for (std::size_t i = 0; i < a.q.size(); ++i) e = std::max(e, std::abs(a.q[i] - b.q[i]));
    for (std::size_t i = 0; i < a.qd.size(); ++i) e = std::max(e, std::abs(a.qd[i] - b.qd[i]));
    return e;
  };
  const State ref = final_state("rk4", 1.0 / 8000);
  const double e1 = error(final_state("rk4", 1.0 / 100), ref), e2 = error(final_state("rk4", 1.0 / 200), ref);
  EXPECT_GT(e1 / e2, 13.0) << e1 << " " << e2;
  EXPECT_LT(e1 / e2, 19.0) << e1 << " " << e2;
  const double u1 = error(final_state("euler", 1.0 / 1000), ref), u2 = error(final_state("euler", 1.0 / 2000), ref);
  EXPECT_GT(u1 / u2, 1.8) << u1 << " " << u2;
  EXPECT_LT(u1 / u2, 2.2) << u1 << " " << u2;
}

// ---- backends, precision ----------------------------------------------------------

// Floating hyq with every effect that applies (gravity, joint damping, springs,
// limits, contacts) from a random state: openmp equals serial bitwise, per
// integrator.
TEST(SimFloatingBackends, OpenMPEqualsSerialBitwise) {
  for (const char* integrator : {"euler", "rk4", "implicit"}) {
    const std::string json = R"({"model": "hyq.urdf", "base": "floating", "dt": 1e-3, "instances": 7,
        "integrator": ")" + std::string(integrator) + R"(", "threads": 3,
        "effects": {"gravity": true, "damping": 2, "springs": {"stiffness": 50},
                    "limits": {"stiffness": 1000, "damping": 5, "lower": -0.5, "upper": 0.5},
                    "contacts": {"planes": [{"normal": [0, 0, 1], "offset": -0.6}], "all_links": {"radius": 0.05},
                                 "stiffness": 1e4, "damping": 100, "friction": 0.7}},
        "initial": {"random": {"seed": 5, "q": 0.3, "qd": 0.5}}})";
    const Scene scene = scene_from(json);
    Simulator<double> serial(scene, BackendKind::Serial);
    Simulator<double> omp(scene, BackendKind::OpenMP);
    for (int s = 0; s < 200; ++s) serial.step(), omp.step();
    ASSERT_TRUE(serial.status().ok()) << integrator;
    for (Index b = 0; b < scene.instances; ++b) {
      const State a = state_of(serial, b), c = state_of(omp, b);
      EXPECT_EQ(a.q, c.q) << integrator << " instance " << b;
      EXPECT_EQ(a.qd, c.qd) << integrator << " instance " << b;
    }
  }
}

// Float follows double on floating atlas with gravity for 0.2 s (rk4, dt = 0.5 ms):
// positions within 1e-3 (a free fall of 0.2 m plus joint motion: float's 1e-7
// relative rounding grows over 400 steps of a 36-DoF chaotic system); the
// quaternion stays unit to float's precision.
TEST(SimFloatingPrecision, FloatFollowsDouble) {
  const Scene scene = scene_from(R"({"model": "atlas.urdf", "base": "floating", "dt": 5e-4, "integrator": "rk4",
      "allow_nonphysical_inertia": true, "effects": {"gravity": true, "damping": 1},
      "initial": {"random": {"seed": 9, "q": 0.1, "qd": 0.2}}})");
  Simulator<double> d(scene);
  Simulator<float> f(scene);
  const Momentum m0 = momentum(scene.model, state_of(d));
  for (int s = 0; s < 400; ++s) d.step(), f.step();
  ASSERT_TRUE(d.status().ok()) << sim::failure_message(d.status());
  ASSERT_TRUE(f.status().ok()) << sim::failure_message(f.status());
  const State a = state_of(d), b = state_of(f);
  for (std::size_t i = 0; i < a.q.size(); ++i) EXPECT_NEAR(a.q[i], b.q[i], 1e-3) << "q_" << i;
  for (std::size_t i = 0; i < a.qd.size(); ++i) EXPECT_NEAR(a.qd[i], b.qd[i], 2e-2 * (1 + std::abs(a.qd[i]))) << "qd_" << i;
  const double n = b.q[3] * b.q[3] + b.q[4] * b.q[4] + b.q[5] * b.q[5] + b.q[6] * b.q[6];
  EXPECT_NEAR(n, 1.0, 1e-6);
  // gravity is the only external force: the centre of mass falls as a point does
  const Momentum m1 = momentum(scene.model, a);
  const double T = 0.2;
  EXPECT_NEAR(m1.com.z, m0.com.z + m0.P.z / m0.mass * T - 0.5 * 9.81 * T * T, 1e-8);
  EXPECT_NEAR(m1.com.x, m0.com.x + m0.P.x / m0.mass * T, 1e-8);
}

// The implicit integrator with stiff joint damping on a hanging ballrope (ball
// joints' damping on their three rates) is stable at a dt where euler diverges
// (dt d / m far above 2) and brings the rope to rest hanging.
TEST(SimFloatingImplicit, StiffBallJointDampingIsStable) {
  auto make = [&](const char* integrator) {
    return scene_from(R"({"model": "ballrope:20", "dt": 1e-2, "integrator": ")" + std::string(integrator) +
                      R"(", "effects": {"gravity": true, "damping": 50},
        "initial": {"random": {"seed": 1, "q": 0.5, "qd": 1.0}}})");
  };
  Simulator<double> implicit(make("implicit"));
  const double e0 = implicit.energy()[0];
  for (int s = 0; s < 3000; ++s) implicit.step();
  ASSERT_TRUE(implicit.status().ok());
  EXPECT_LT(implicit.energy()[0], e0);
  for (double v : state_of(implicit).qd) EXPECT_LT(std::abs(v), 1e-2);  // from rates up to 1 rad/s
  Simulator<double> euler(make("euler"));
  for (int s = 0; s < 500 && euler.status().ok(); ++s) euler.step();
  EXPECT_FALSE(euler.status().ok()) << "explicit euler was expected to diverge at dt d / m >> 2";
}

// ---- contacts with a floating base (issue 20's free-body cases) ---------------------

std::string box_scene(const std::string& integrator, double dt, const std::string& law, const std::string& initial) {
  const std::string urdf = one_body_urdf("box", 1.0, 1.0 / 150, 1.0 / 150, 1.0 / 150);  // a 0.2 m cube, 1 kg
  std::string points;
  for (const char* c : {"[0.1, 0.1, -0.1]", "[0.1, -0.1, -0.1]", "[-0.1, 0.1, -0.1]", "[-0.1, -0.1, -0.1]"})
    points += std::string(points.empty() ? "" : ", ") + R"({"link": "box", "position": )" + c + "}";
  return R"({"model": ")" + urdf + R"(", "base": "floating", "dt": )" + std::to_string(dt) + R"(, "integrator": ")" +
         integrator + R"(", "effects": {"gravity": true, "contacts": {"planes": [{"normal": [0, 0, 1]}], "points": [)" +
         points + "], " + law + "}}, \"initial\": " + initial + "}";
}

// A free box on its four bottom corners dropped flat from 5 cm comes to rest at the
// penetration m g / (4 k) and stays: no drift between 10^4 and 2 10^4 steps, no
// tilt. Implicit at dt = 1 ms, k = 1e5 (the contacts' armature on the free joint's
// six DoFs), double and float.
template <class S>
void free_box_rests() {
  const double m = 1, k = 1e5, g = 9.81;
  const Scene scene = scene_from(box_scene("implicit", 1e-3, R"("stiffness": 1e5, "damping": 300, "friction": 0.8)",
                                           R"({"q": [0, 0, 0.15, 0, 0, 0, 1], "qd": [0, 0, 0, 0, 0, -0.2]})"));
  Simulator<S> sim(scene);
  for (int s = 0; s < 10000; ++s) sim.step();
  const State a = state_of(sim);
  for (int s = 0; s < 10000; ++s) sim.step();
  ASSERT_TRUE(sim.status().ok()) << sim::failure_message(sim.status());
  const State b = state_of(sim);
  const bool fl = sizeof(S) == 4;
  const double expect = m * g / (4 * k);
  EXPECT_NEAR(0.1 - b.q[2], expect, (fl ? 2e-3 : 1e-9) * expect);
  EXPECT_LE(std::abs(b.q[2] - a.q[2]), fl ? 1e-7 : 1e-12);
  EXPECT_NEAR(b.q[6], 1.0, fl ? 1e-6 : 1e-12);  // flat: the quaternion stays the identity
  std::vector<sim::ContactReading<S>> r(4);
  sim.read_contact_forces(r.data());
  for (const auto& c : r) {
    EXPECT_EQ(c.in_contact, 1);
    EXPECT_NEAR(double(c.force.z), m * g / 4, (fl ? 2e-3 : 1e-9) * m * g);
  }
}
TEST(SimFloatingContacts, FreeBoxRestsAtMgOver4kDouble) { free_box_rests<double>(); }
TEST(SimFloatingContacts, FreeBoxRestsAtMgOver4kFloat) { free_box_rests<float>(); }

// A free box sliding on its four corners at v0 = 1 m/s stops after v0^2 / (2 mu g)
// (within 2%): every corner slides, so the friction totals mu m g whatever the
// pitching moment does to the normal forces. Euler at dt = 0.1 ms.
TEST(SimFloatingContacts, FreeBoxSlidingStopsAfterV0SquaredOver2MuG) {
  const double k = 1e4, mu = 0.5, v0 = 1, g = 9.81;
  const double z = 0.1 - g / (4 * k);
  const Scene scene = scene_from(box_scene("euler", 1e-4, R"("stiffness": 1e4, "damping": 100, "friction": 0.5)",
                                           "{\"q\": [0, 0, " + std::to_string(z) + ", 0, 0, 0, 1], \"qd\": [0, 0, 0, 1, 0, 0]}"));
  Simulator<double> sim(scene);
  for (int s = 0; s < 5000; ++s) sim.step();  // 0.5 s; it stops at 0.2 s
  ASSERT_TRUE(sim.status().ok()) << sim::failure_message(sim.status());
  const State st = state_of(sim);
  const double expect = v0 * v0 / (2 * mu * g);
  EXPECT_NEAR(st.q[0], expect, 0.02 * expect);
  const Mat3<double> R = quat_to_matrix(st.q.data() + 3);
  EXPECT_LT(norm(R * Vec3<double>{st.qd[3], st.qd[4], st.qd[5]}), 1e-3);  // at rest (creeping below v_s at most)
  EXPECT_NEAR(st.q[6], 1.0, 1e-4);  // it did not tip
}

// scenes/hyq_stand.json: the floating hyq on four foot points under the joints' PD
// controller (springs to the standing pose + damping), implicit at dt = 1 ms in
// float, 10 s: after it settles (1 s) the base height stays within 1 mm and the
// feet sink at most 2 mm.
TEST(SimFloatingContacts, HyqStandsOnFourFeetFor10s) {
  Scene scene = sim::load_scene(std::string(SCANDYN_SOURCE_DIR) + "/scenes/hyq_stand.json");
  ASSERT_TRUE(scene.model.floating_base());
  ASSERT_EQ(scene.precision, Precision::Float);
  ASSERT_EQ(scene.dt, 1e-3);
  scene.instances = 3;
  scene.backend = BackendKind::Serial;
  Simulator<float> sim(scene);
  double lo = 1e9, hi = -1e9, depth = 0;
  std::vector<sim::ContactReading<float>> r(static_cast<std::size_t>(3 * sim.contact_count()));
  for (int s = 1; s <= 10000; ++s) {
    sim.step();
    if (s < 1000) continue;
    for (Index b = 0; b < 3; ++b) {
      const State st = state_of(sim, b);
      lo = std::min(lo, st.q[2]), hi = std::max(hi, st.q[2]);
    }
    sim.read_contact_forces(r.data());
    for (const auto& c : r) depth = std::max(depth, double(c.depth));
  }
  ASSERT_TRUE(sim.status().ok()) << sim::failure_message(sim.status());
  EXPECT_LE(hi - lo, 1e-3) << "base height in [" << lo << ", " << hi << "]";
  EXPECT_GT(lo, 0.5);
  EXPECT_LE(depth, 2e-3);
  for (const auto& c : r) EXPECT_EQ(c.in_contact, 1);
}

// ---- scenes and their errors ------------------------------------------------------

TEST(SimFloatingScene, FloatingBaseAndBallJoints) {
  const Scene s = scene_from(R"({"model": "hyq.urdf", "base": "floating", "dt": 1e-3})");
  EXPECT_EQ(s.nv(), 18);
  EXPECT_EQ(s.nq(), 19);
  ASSERT_EQ(s.initial.q.size(), 19u);
  EXPECT_EQ(s.initial.q[6], 1.0);  // the identity quaternion's w
  const Scene r = scene_from(R"({"model": "ballrope:3", "dt": 1e-3, "effects": {"damping": 0.5}})");
  EXPECT_EQ(r.nv(), 9);
  EXPECT_EQ(r.nq(), 12);
  for (Index i = 0; i < 9; ++i) EXPECT_EQ(r.joints[i].damping, 0.5);
  // a scalar damping skips the floating base's DoFs; springs apply to 1-DoF joints only
  const Scene h = scene_from(R"({"model": "hyq.urdf", "base": "floating", "dt": 1e-3,
      "effects": {"damping": 2, "springs": {"stiffness": 30, "rest": 0.1}, "limits": {"stiffness": 1}}})");
  for (Index i = 0; i < 6; ++i) {
    EXPECT_EQ(h.joints[i].damping, 0.0);
    EXPECT_EQ(h.joints[i].stiffness, 0.0);
    EXPECT_EQ(h.joints[i].rest, 0.0);
    EXPECT_EQ(h.joints[i].lower, -HUGE_VAL);
  }
  EXPECT_EQ(h.joints[6].damping, 2.0);
  EXPECT_EQ(h.joints[6].stiffness, 30.0);
  EXPECT_EQ(h.joints[6].lower, h.model.q_lower[1]);  // the URDF's limit of body 1
  for (const char* file : {"hyq_floating.json", "hyq_floating_rl.json", "atlas_floating.json", "rope_free_1000.json",
                           "ballrope_1000.json"}) {
    const Scene sc = sim::load_scene(std::string(SCANDYN_SOURCE_DIR) + "/scenes/" + file);
    EXPECT_TRUE(sc.model.multi_dof()) << file;
    Scene small = sc;
    small.instances = 2;
    small.backend = BackendKind::Serial;
    Simulator<float> sim(small);
    for (int s = 0; s < 5; ++s) sim.step();
    EXPECT_TRUE(sim.status().ok()) << file << ": " << sim::failure_message(sim.status());
  }
}

TEST(SimFloatingScene, ErrorsNameTheKey) {
  // a quaternion off unit: the entries and the joint
  EXPECT_EQ(scene_error(R"({"model": "rope:2", "base": "floating", "dt": 1e-3,
      "initial": {"q": [0, 0, 0, 0, 0, 0, 2, 0]}})"),
            "test.json: initial.q[3..6]: the quaternion (x, y, z, w) of joint 'root_joint' has norm 2; expected a "
            "unit quaternion (within 1e-06 relative)");
  // within the tolerance it is normalised
  const Scene ok = scene_from(R"({"model": "rope:2", "base": "floating", "dt": 1e-3,
      "initial": {"q": [0, 0, 0, 0, 0, 0, 1.0000005, 0]}})");
  EXPECT_EQ(ok.initial.q[6], 1.0);
  // nv entries where nq are needed
  EXPECT_NE(scene_error(R"({"model": "rope:2", "base": "floating", "dt": 1e-3, "initial": {"q": [0, 0, 0, 0, 0, 0, 0]}})")
                .find("test.json: initial.q: expected 8 entries (nq"),
            std::string::npos);
  EXPECT_NE(scene_error(R"({"model": "ballrope:2", "dt": 1e-3, "initial": {"q": 0}})").find("initial.q: expected an array of 8"),
            std::string::npos);
  // velocities: nv
  EXPECT_EQ(scene_error(R"({"model": "rope:2", "base": "floating", "dt": 1e-3, "initial": {"qd": [0, 0, 0, 0, 0, 0, 0, 0]}})"),
            "test.json: initial.qd: expected 7 entries (one per DoF), got 8");
  // effects that do not apply to the base or to ball joints
  EXPECT_EQ(scene_error(R"({"model": "rope:2", "base": "floating", "dt": 1e-3,
      "effects": {"damping": [1, 0, 0, 0, 0, 0, 1]}})"),
            "test.json: effects.damping[0]: DoF 0 belongs to the floating base ('root_joint'), which takes no joint "
            "damping (expected 0 there)");
  EXPECT_NE(scene_error(R"({"model": "ballrope:2", "dt": 1e-3, "effects": {"springs": {"stiffness": [0, 0, 0, 0, 5, 0]}}})")
                .find("test.json: effects.springs.stiffness[4]: DoF 4 belongs to the ball joint"),
            std::string::npos);
  EXPECT_NE(scene_error(R"({"model": "ballrope:2", "dt": 1e-3, "effects": {"limits": {"stiffness": 1, "upper": [1, null, null, null, null, null]}}})")
                .find("test.json: effects.limits.upper[0]: DoF 0 belongs to the ball joint"),
            std::string::npos);
  EXPECT_NE(scene_error(R"({"model": "hyq.urdf", "base": "floating", "dt": 1e-3,
      "prescribed": {"joints": [6], "trajectory": [{"sine": {"amplitude": 1}}]}})")
                .find("test.json: prescribed: the model has the multi-DoF joint 'root_joint'"),
            std::string::npos);
  EXPECT_EQ(scene_error(R"({"model": "rope:2", "base": "wobbly", "dt": 1e-3})"),
            "test.json: base: expected \"fixed\" or \"floating\", got \"wobbly\"");
}

// A Scene made in code with nv initial positions where nq are needed.
TEST(SimFloatingScene, SimulatorRefusesInitialStatesOfTheWrongSize) {
  Scene scene = scene_from(R"({"model": "chain:2", "base": "floating", "dt": 1e-3})");
  scene.initial.q.resize(static_cast<std::size_t>(scene.nv()));
  try {
    Simulator<double> sim(scene);
    FAIL() << "expected std::invalid_argument";
  } catch (const std::invalid_argument& e) {
    EXPECT_STREQ(e.what(), "Simulator: the scene's initial.q has 7 entries, the model takes 8 (nq)");
  }
}

TEST(SimFloatingScene, RandomInitialStatesStayOnTheManifold) {
  const Scene scene = scene_from(R"({"model": "ballrope:4", "base": "floating", "dt": 1e-3, "instances": 5,
      "initial": {"random": {"seed": 2, "q": 1.0, "qd": 0.1}}})");
  Simulator<float> sim(scene);
  for (Index b = 0; b < 5; ++b) {
    const State st = state_of(sim, b);
    for (Index i = 0; i < scene.model.nbodies(); ++i) {
      const Body<double>& body = scene.model.bodies[i];
      const double* quat = st.q.data() + body.idx_q + (body.type == JointType::Free ? 3 : 0);
      EXPECT_NEAR(quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3], 1.0, 1e-6);
      EXPECT_LT(quat[3], 1.0 - 1e-4);  // drawn away from the identity
    }
  }
  // a reset draws again, continuing the generator
  const State before = state_of(sim, 3);
  sim.reset({3});
  EXPECT_NE(state_of(sim, 3).q, before.q);
}

}  // namespace
}  // namespace scandyn
