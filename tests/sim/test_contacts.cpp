// Tests of the contact effect (scandyn/sim/contacts.hpp) on fixed-base models:
// the scene keys and their errors, the per-pair law, and closed forms on the CPU
// simulator: a point mass (models/point_mass.urdf: prismatic z, y, x) resting at
// d = m g / k, bouncing to the height the clamped spring-damper predicts, sliding
// v0^2 / (2 mu g), sticking on a plane tilted below atan(mu) and accelerating at
// g (sin - mu cos) above; a hinged rod whose tip rests on a plane at the depth its
// moment balance gives; rope:200 draped over a sphere (float and double); serial
// equals OpenMP; the contact pass's two kinematics (a walk per point, or every
// body into scratch) agree on random trees, fixed and floating.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include "scandyn/algorithm/loops.hpp"
#include "scandyn/sim/contacts.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"
#include "floating_models.hpp"
#include "scene_util.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

using sim::ContactReading;
using sim::Scene;
using sim::SceneError;
using sim::Simulator;

constexpr double kG = 9.81;

// scenes whose files (meshes, models) are found from the shipped models
Scene scene_from(const std::string& json) { return test::scene_from(json, SCANDYN_SOURCE_DIR "/models"); }
std::string scene_error(const std::string& json) { return test::scene_error(json, SCANDYN_SOURCE_DIR "/models"); }


// A point_mass scene: the ball (radius 0.1) on the plane with the given normal
// through the origin; law and the rest of the scene's keys spliced in.
std::string ball_scene(const std::string& integrator, double dt, const std::string& law, const std::string& initial,
                       const std::string& normal = "[0, 0, 1]") {
  return R"({"model": "point_mass.urdf", "dt": )" + std::to_string(dt) + R"(, "integrator": ")" + integrator +
         R"(", "effects": {"gravity": true, "contacts": {"planes": [{"normal": )" + normal +
         R"(, "offset": 0}], "points": [{"link": "ball", "radius": 0.1}], )" + law + R"(}}, "initial": )" + initial +
         "}";
}

// The state of instance 0: q then qd (double).
struct State {
  std::vector<double> q, qd;
};
template <class S>
State state0(Simulator<S>& sim) {
  const std::size_t n = static_cast<std::size_t>(sim.nv()), B = static_cast<std::size_t>(sim.batch());
  std::vector<S> q(n * B), qd(n * B);
  sim.read_state(q.data(), qd.data());
  State s{std::vector<double>(n), std::vector<double>(n)};
  for (std::size_t i = 0; i < n; ++i) s.q[i] = double(q[i * B]), s.qd[i] = double(qd[i * B]);
  return s;
}

template <class S>
std::vector<ContactReading<S>> readings(Simulator<S>& sim) {
  std::vector<ContactReading<S>> r(static_cast<std::size_t>(sim.batch() * sim.contact_count()));
  sim.read_contact_forces(r.data());
  return r;
}

// ---- scene keys ----------------------------------------------------------------------

TEST(SimContactsScene, ParsesEveryKey) {
  const Scene s = scene_from(R"({"model": "rope:3", "dt": 1e-3, "effects": {"contacts": {
      "planes": [{"normal": [0, 0, 1], "offset": -0.5}], "spheres": [{"center": [0.3, 0, 0.5], "radius": 0.2}],
      "points": [{"link": "link_1", "position": [0, 0, -0.01], "radius": 0.02}], "all_links": {"radius": 0.005},
      "stiffness": 1e5, "damping": 1e3, "friction": 0.8, "creep_speed": 1e-4}}})");
  EXPECT_EQ(s.effects, unsigned(sim::kContacts));
  const sim::SceneContacts& c = s.contacts;
  ASSERT_EQ(c.planes.size(), 1u);
  EXPECT_EQ(c.planes[0].offset, -0.5);
  EXPECT_EQ(c.planes[0].normal.z, 1.0);
  ASSERT_EQ(c.spheres.size(), 1u);
  EXPECT_EQ(c.spheres[0].radius, 0.2);
  EXPECT_EQ(c.spheres[0].center.x, 0.3);
  ASSERT_EQ(c.points.size(), 4u);  // the listed point, then one per link
  EXPECT_EQ(c.points[0].body, 1);
  EXPECT_EQ(c.points[0].position.z, -0.01);
  EXPECT_EQ(c.points[0].radius, 0.02);
  for (int i = 0; i < 3; ++i) {
    EXPECT_EQ(c.points[1 + i].body, i);
    EXPECT_EQ(c.points[1 + i].radius, 0.005);
  }
  EXPECT_EQ(c.law.stiffness, 1e5);
  EXPECT_EQ(c.law.damping, 1e3);
  EXPECT_EQ(c.law.friction, 0.8);
  EXPECT_EQ(c.law.creep_speed, 1e-4);
  EXPECT_EQ(sim::effect_names(s.effects), "contacts");
}

TEST(SimContactsScene, ErrorsNameTheKey) {
  auto with = [](const std::string& contacts) {
    return R"({"model": "rope:3", "dt": 1e-3, "effects": {"contacts": )" + contacts + "}}";
  };
  const std::string plane = R"("planes": [{"normal": [0, 0, 1]}])";
  const std::string point = R"("points": [{"link": "link_0"}])";
  struct Case {
    std::string json, message;
  };
  const std::vector<Case> cases = {
      {with("{" + plane + ", " + point + "}"),
       "test.json: effects.contacts.stiffness: missing (the normal stiffness k, N/m)"},
      {with(R"({"stiffness": 1, "points": [{"link": "nope"}], )" + plane + "}"),
       "test.json: effects.contacts.points[0].link: no moving link named 'nope' in the model"},
      {with(R"({"stiffness": 1, "points": [{"link": "link_0", "radius": -1}], )" + plane + "}"),
       "test.json: effects.contacts.points[0].radius: expected a non-negative number, got -1"},
      {with(R"({"stiffness": 1, "planes": [{"normal": [0, 0, 2]}], )" + point + "}"),
       "test.json: effects.contacts.planes[0].normal: expected a unit vector, got [0,0,2] (length 2.000000)"},
      {with(R"({"stiffness": 1, "planes": [{"normal": [0, 0, 0]}], )" + point + "}"),
       "test.json: effects.contacts.planes[0].normal: expected a unit vector, got [0,0,0] (length 0.000000)"},
      {with(R"({"stiffness": 1, "planes": [{"offset": 0}], )" + point + "}"),
       "test.json: effects.contacts.planes[0].normal: missing"},
      {with(R"({"stiffness": 1, "spheres": [{"center": [0, 0, 0], "radius": 0}], )" + point + "}"),
       "test.json: effects.contacts.spheres[0].radius: expected a positive number, got 0"},
      {with(R"({"stiffness": 1, "points": [{"position": [0, 0, 0]}], )" + plane + "}"),
       "test.json: effects.contacts.points[0].link: missing"},
      {with(R"({"stiffness": 1, )" + plane + "}"),
       "test.json: effects.contacts: no contact points (give \"points\" or \"all_links\")"},
      {with(R"({"stiffness": 1, )" + point + "}"),
       "test.json: effects.contacts: no obstacles (give \"planes\" or \"spheres\")"},
      {with(R"({"stiffness": -1, )" + point + ", " + plane + "}"),
       "test.json: effects.contacts.stiffness: expected a non-negative number, got -1"},
      {with(R"({"stiffness": 1, "friction": -0.5, )" + point + ", " + plane + "}"),
       "test.json: effects.contacts.friction: expected a non-negative number, got -0.5"},
      {with(R"({"stiffness": 1, "stiction": 1, )" + point + ", " + plane + "}"),
       "test.json: effects.contacts.stiction: unknown key (expected one of: all_links, creep_speed, damping, friction, "
       "planes, points, spheres, stiffness)"},
  };
  for (const Case& c : cases) EXPECT_EQ(scene_error(c.json), c.message) << c.json;
}

// The shipped contact scenes load, declare contacts and step (serial, 2 instances,
// 50 steps) without a failure.
TEST(SimContactsScene, ShippedContactScenesLoadAndStep) {
  for (const char* name : {"rope_drape", "curtain_drape", "hyq_stand"}) {
    Scene s = sim::load_scene(std::string(SCANDYN_SOURCE_DIR) + "/scenes/" + name + ".json");
    EXPECT_NE(s.effects & sim::kContacts, 0u) << name;
    EXPECT_TRUE(s.backend_auto) << name;
    s.instances = 2;
    Simulator<double> sim(s, BackendKind::Serial);
    for (int k = 0; k < 50; ++k) sim.step();
    EXPECT_TRUE(sim.status().ok()) << name << ": " << sim::failure_message(sim.status());
  }
}

// ---- the law -------------------------------------------------------------------------

// One pair: f_n = k d + c d_dot (clamped at zero), friction -mu f_n v_t / max(|v_t|, v_s).
TEST(SimContactsLaw, PairForceIsTheStatedLaw) {
  const sim::ContactLaw<double> law{1000, 10, 0.5, 1e-3};
  const Vec3<double> n{0, 0, 1};
  for (const Vec3<double> pv : {Vec3<double>{0, 0, -0.2}, Vec3<double>{0.3, -0.4, 0.1}, Vec3<double>{2e-4, 0, 0},
                                Vec3<double>{0, 0, 0.5}}) {
    const double d = 0.01, d_dot = -pv.z;
    Vec3<double> f = Vec3<double>::zero();
    double gain = 0;
    const double fn = sim::contact_pair_force(law, n, d, pv, 0.0, f, gain);
    const double expect = std::max(0.0, 1000 * d + 10 * d_dot);
    EXPECT_DOUBLE_EQ(fn, expect);
    EXPECT_DOUBLE_EQ(f.z, expect);
    const double vt = std::hypot(pv.x, pv.y);
    const double ft = std::hypot(f.x, f.y);
    if (expect > 0) {
      EXPECT_NEAR(ft, 0.5 * expect * vt / std::max(vt, 1e-3), 1e-12);
      EXPECT_LE(ft, 0.5 * fn * (1 + 1e-15));  // inside the cone
      if (vt > 0) {
        EXPECT_LT(f.x * pv.x + f.y * pv.y, 0);  // opposing the slip
      }
    } else {
      EXPECT_EQ(ft, 0.0);  // never pulls, no friction without a normal force
    }
  }
}

// ---- the point mass ------------------------------------------------------------------

// At rest on the plane: d = m g / k for every integrator (m: the 1 kg ball and the
// two 1 mg carriages, which all move along z), the reading's force m g up; the
// implicit step at dt = 1 ms with k = 1e5 (penetration 0.1 mm), euler and rk4 at
// dt = 0.1 ms.
TEST(SimContactsPointMass, RestsAtMgOverK) {
  const double m = 1 + 2e-6;
  for (const char* integrator : {"euler", "rk4", "implicit"}) {
    const bool implicit = std::string(integrator) == "implicit";
    const double k = 1e5, c = 2 * std::sqrt(k * m);  // critically damped
    const Scene scene = scene_from(ball_scene(integrator, implicit ? 1e-3 : 1e-4,
                                              R"("stiffness": 1e5, "damping": )" + std::to_string(c) +
                                                  R"(, "friction": 0.8)",
                                              R"({"q": [0.1, 0, 0], "qd": [-0.5, 0, 0]})"));
    Simulator<double> sim(scene);
    const int steps = implicit ? 2000 : 20000;  // 2 s
    for (int s = 0; s < steps; ++s) sim.step();
    ASSERT_TRUE(sim.status().ok()) << integrator;
    const double depth = 0.1 - state0(sim).q[0];
    EXPECT_NEAR(depth, m * kG / k, 1e-9 * m * kG / k + 1e-15) << integrator;
    const auto r = readings(sim);
    EXPECT_EQ(r[0].in_contact, 1);
    EXPECT_NEAR(r[0].force.z, m * kG, 1e-9) << integrator;
    EXPECT_NEAR(r[0].depth, m * kG / k, 1e-12) << integrator;
  }
}

// A box on its four bottom corners (points (+-0.1, +-0.1, -0.1) of the ball's
// body: a box that translates without turning; the turning box needs the floating
// base) dropped flat comes to rest at d = m g / (4 k) and stays there: no drift
// between 10^4 and 2 10^4 steps. Implicit at dt = 1 ms, k = 1e5, in double and
// float (float: the depth to 1e-4 of itself, the drift below 1e-7 m).
template <class S>
void box_on_four_corners() {
  const double m = 1 + 2e-6, k = 1e5;
  std::string points;
  for (const char* c : {"[0.1, 0.1, -0.1]", "[0.1, -0.1, -0.1]", "[-0.1, 0.1, -0.1]", "[-0.1, -0.1, -0.1]"})
    points += std::string(points.empty() ? "" : ", ") + R"({"link": "ball", "position": )" + c + "}";
  const Scene scene = scene_from(R"({"model": "point_mass.urdf", "dt": 1e-3, "integrator": "implicit",
      "effects": {"gravity": true, "contacts": {"planes": [{"normal": [0, 0, 1]}], "points": [)" + points + R"(],
                  "stiffness": 1e5, "damping": 300, "friction": 0.8}},
      "initial": {"q": [0.15, 0, 0], "qd": [0, 0.2, 0.1]}})");
  Simulator<S> sim(scene);
  for (int s = 0; s < 10000; ++s) sim.step();
  const double z1 = state0(sim).q[0];
  for (int s = 0; s < 10000; ++s) sim.step();
  ASSERT_TRUE(sim.status().ok());
  const double z2 = state0(sim).q[0];
  const double expect = m * kG / (4 * k);
  const bool fl = sizeof(S) == 4;
  EXPECT_NEAR(0.1 - z2, expect, (fl ? 1e-4 : 1e-9) * expect);
  EXPECT_LE(std::abs(z2 - z1), fl ? 1e-7 : 1e-12);
  for (const auto& r : readings(sim)) EXPECT_NEAR(double(r.force.z), m * kG / 4, (fl ? 1e-4 : 1e-9) * m * kG);
}
TEST(SimContactsPointMass, BoxOnFourCornersRestsAtMgOver4kDouble) { box_on_four_corners<double>(); }
TEST(SimContactsPointMass, BoxOnFourCornersRestsAtMgOver4kFloat) { box_on_four_corners<float>(); }

// The bounce: from a drop height h0 the ball lands at v0 = sqrt(2 g h0); while it
// touches, m d'' = -k d - c d' + m g exactly (d: penetration); it leaves when the
// clamped force k d + c d' reaches zero, at depth d1 moving up at u1, and rises to
// 0.1 - d1 + u1^2 / (2 g). The linear ODE's solution is closed-form; the instant the
// force vanishes is found by bisection on it. rk4 at dt = 10 us; within 0.2%.
TEST(SimContactsPointMass, BouncesToTheHeightTheDampingPredicts) {
  const double m = 1 + 2e-6, k = 1e5, c = 40, h0 = 0.5;
  const double w0 = std::sqrt(k / m), zeta = c / (2 * std::sqrt(k * m)), wd = w0 * std::sqrt(1 - zeta * zeta);
  const double ds = m * kG / k, v0 = std::sqrt(2 * kG * h0);
  // d(t) = ds + e^{-zeta w0 t} (A cos wd t + B sin wd t), d(0) = 0, d'(0) = v0
  const double A = -ds, B = (v0 + zeta * w0 * A) / wd;
  auto d = [&](double t) { return ds + std::exp(-zeta * w0 * t) * (A * std::cos(wd * t) + B * std::sin(wd * t)); };
  auto dd = [&](double t) {
    return std::exp(-zeta * w0 * t) * ((B * wd - zeta * w0 * A) * std::cos(wd * t) - (A * wd + zeta * w0 * B) * std::sin(wd * t));
  };
  auto force = [&](double t) { return k * d(t) + c * dd(t); };
  double lo = 0.5 * M_PI / wd, hi = M_PI / wd;  // the force is positive at the deepest point, negative at d = 0
  ASSERT_GT(force(lo), 0);
  ASSERT_LT(force(hi), 0);
  for (int it = 0; it < 200; ++it) (force(0.5 * (lo + hi)) > 0 ? lo : hi) = 0.5 * (lo + hi);
  const double d1 = d(lo), u1 = -dd(lo);
  const double apex = 0.1 - d1 + u1 * u1 / (2 * kG);
  ASSERT_GT(u1, 0.5 * v0);
  ASSERT_LT(u1, v0);

  const Scene scene = scene_from(ball_scene("rk4", 1e-5, R"("stiffness": 1e5, "damping": 40)",
                                            R"({"q": [0.6, 0, 0]})"));
  Simulator<double> sim(scene);
  double top = 0;
  bool landed = false;
  for (int s = 0; s < 100000; ++s) {  // 1 s: lands at 0.32 s, apex near 0.58 s
    sim.step();
    const State st = state0(sim);
    landed = landed || st.q[0] < 0.1;
    if (landed && st.q[0] > 0.1) top = std::max(top, st.q[0]);
  }
  ASSERT_TRUE(sim.status().ok());
  EXPECT_NEAR(top - 0.1, apex - 0.1, 2e-3 * (apex - 0.1)) << "apex " << top << " predicted " << apex;
}

// Sliding on the plane at v0 = 1 m/s: Coulomb friction decelerates at mu g (the
// normal force carries the 1 kg + 2 mg on z, friction brakes the 1 kg on x), so it
// stops after v0^2 / (2 mu g) (within 2%; the regularisation below v_s = 1 mm/s
// shortens the last 1e-6 m). Euler at dt = 0.1 ms (the friction's velocity gain mu
// f_n / v_s needs dt < 2 m v_s / (mu f_n) = 0.4 ms explicitly).
TEST(SimContactsPointMass, SlidingStopsAfterV0SquaredOver2MuG) {
  const double m = 1 + 2e-6, k = 1e4, mu = 0.5, v0 = 1;
  const double z = 0.1 - m * kG / k;  // resting depth
  const Scene scene = scene_from(ball_scene("euler", 1e-4, R"("stiffness": 1e4, "damping": 200, "friction": 0.5)",
                                            "{\"q\": [" + std::to_string(z) + ", 0, 0], \"qd\": [0, 0, 1]}"));
  Simulator<double> sim(scene);
  for (int s = 0; s < 5000; ++s) sim.step();  // 0.5 s; it stops at 0.2 s
  ASSERT_TRUE(sim.status().ok());
  const State st = state0(sim);
  const double expect = v0 * v0 / (2 * mu * kG * m);
  EXPECT_NEAR(st.q[2], expect, 0.02 * expect);
  EXPECT_LT(std::abs(st.qd[2]), 1e-3);  // at rest (creeping below v_s at most)
}

// A plane tilted by theta about y (normal (-sin, 0, cos)): with tan(theta) < mu the
// ball sticks (it creeps below v_s = 1 mm/s, the stated tolerance: at v_s tan / mu);
// with tan(theta) > mu it slides with a = g (sin - mu cos) along the slope.
TEST(SimContactsPointMass, TiltedPlaneSticksBelowAtanMuAndSlidesAbove) {
  const double m = 1 + 2e-6, k = 1e4, mu = 0.5;
  for (const double theta : {0.3, 0.6}) {  // tan 0.3 = 0.31 < 0.5 < tan 0.6 = 0.68
    const double s = std::sin(theta), c = std::cos(theta);
    // start at rest at the resting depth along the normal: centre at (0.1 - d) n
    const double r = 0.1 - m * kG * c / k;
    const std::string normal = "[" + std::to_string(-s) + ", 0, " + std::to_string(c) + "]";
    const Scene scene = scene_from(ball_scene("euler", 1e-4, R"("stiffness": 1e4, "damping": 200, "friction": 0.5)",
                                              "{\"q\": [" + std::to_string(r * c) + ", 0, " + std::to_string(-r * s) + "]}",
                                              normal));
    ASSERT_NEAR(std::hypot(scene.contacts.planes[0].normal.x, scene.contacts.planes[0].normal.z), 1.0, 1e-6);
    Simulator<double> sim(scene);
    const double T = 0.5;
    for (int k2 = 0; k2 < 5000; ++k2) sim.step();
    ASSERT_TRUE(sim.status().ok());
    const State st = state0(sim);
    const double v_along = st.qd[2] * c + st.qd[0] * s;  // along (cos, 0, sin): up the slope
    if (std::tan(theta) < mu) {
      EXPECT_LE(std::abs(v_along), 1e-3 * std::tan(theta) / mu * 1.01) << theta;
      EXPECT_LE(std::abs(st.q[2] + r * s) + std::abs(st.q[0] - r * c), 1e-3 * T) << theta;
    } else {
      const double a = kG * (s - mu * c);  // down the slope
      EXPECT_NEAR(-v_along, a * T, 0.01 * a * T) << theta;
    }
  }
}

// ---- a hinged rod on a plane ------------------------------------------------------------

// rope:1 (a 1 cm, 10 g rod hinged at the origin about x) turned horizontal (q =
// pi/2: along +y), its tip (0, 0, -0.01 in the link frame) on the plane z = 0: the
// moments about the hinge balance when k d L cos(phi) = m g (L/2) cos(phi), so the
// tip rests at d = m g / (2 k) whatever the angle. Every integrator; implicit at dt
// = 2 ms, beyond explicit Euler's limit for this contact (the tip's effective mass
// m / 3 with k = 1e5: dt < 2 sqrt(m / 3k) = 0.37 ms).
TEST(SimContactsRod, TipRestsAtTheDepthOfItsMomentBalance) {
  const double m = 0.01, k = 1e5;
  for (const char* integrator : {"euler", "rk4", "implicit"}) {
    const bool implicit = std::string(integrator) == "implicit";
    const Scene scene = scene_from(std::string(R"({"model": "rope:1", "dt": )") + (implicit ? "2e-3" : "1e-4") +
                                   R"(, "integrator": ")" + integrator + R"(", "effects": {"gravity": true,
        "contacts": {"planes": [{"normal": [0, 0, 1]}], "points": [{"link": "link_0", "position": [0, 0, -0.01]}],
                     "stiffness": 1e5, "damping": 2, "friction": 0.5}},
        "initial": {"q": 1.5707963267948966}})");
    Simulator<double> sim(scene);
    const int steps = implicit ? 2000 : 40000;  // 4 s
    for (int s = 0; s < steps; ++s) sim.step();
    ASSERT_TRUE(sim.status().ok()) << integrator;
    const auto r = readings(sim);
    EXPECT_EQ(r[0].in_contact, 1) << integrator;
    EXPECT_NEAR(r[0].depth, m * kG / (2 * k), 1e-6 * m * kG / (2 * k)) << integrator;
    const double L = 0.01, d = r[0].depth;
    EXPECT_NEAR(state0(sim).q[0], M_PI / 2 - std::asin(d / L), 1e-9) << integrator;  // the tip dips below z = 0
  }
}

// ---- rope:200 draped over a sphere ----------------------------------------------------

// rope:200 (2 m) starts horizontal along +y from its fixed end and falls onto a
// sphere of radius 0.3 centred at (0, 1, -0.35), every link origin a contact point
// (k = 1e4, mu = 1, joint damping 3e-3): it wraps over the sphere, both ends hang
// and it comes to rest. Checked in double (euler, implicit) and float (implicit)
// over 4 s at dt = 0.1 ms: the mechanical energy (with the contacts' springs,
// sampled every 100 steps) never rises by more than 1e-3 of what the fall released
// (measured: 0 for euler, 7e-4 for implicit), the kinetic energy at the end is
// below 5% of it (measured 1.7-3%: the hanging ends still swing slowly), the
// deepest penetration stays below 2 mm (measured 0.8-1.2 mm; the static depth of
// one link is m g / k = 10 um) and more than 20 points lie on the sphere.
template <class S>
void drape_rope(const std::string& integrator) {
  std::string q0 = "[1.5707963267948966";  // the first joint turns the rope horizontal
  for (int i = 1; i < 200; ++i) q0 += ", 0";
  const Scene scene = scene_from(R"({"model": "rope:200", "dt": 1e-4, "integrator": ")" + integrator + R"(",
      "effects": {"gravity": true, "damping": 3e-3,
        "contacts": {"spheres": [{"center": [0, 1, -0.35], "radius": 0.3}], "all_links": {"radius": 0.002},
                     "stiffness": 1e4, "damping": 5, "friction": 1, "creep_speed": 0.01}},
      "initial": {"q": )" + q0 + "]}}");
  Simulator<S> sim(scene);
  const double e0 = sim.energy()[0];
  double prev = e0, rise = 0, deepest = 0;
  int touching = 0;
  for (int s = 1; s <= 40000; ++s) {  // 4 s
    sim.step();
    if (s % 100 == 0) {
      const double e = sim.energy()[0];
      ASSERT_TRUE(std::isfinite(e)) << s;
      rise = std::max(rise, e - prev);
      prev = e;
      touching = 0;
      for (const auto& r : readings(sim)) deepest = std::max(deepest, double(r.depth)), touching += r.in_contact;
    }
  }
  ASSERT_TRUE(sim.status().ok());
  const double released = e0 - prev;
  EXPECT_GT(released, 1.0);                      // it fell
  EXPECT_LE(rise, 1e-3 * released);             // energy never rises beyond the step's fluctuation
  EXPECT_LT(deepest, 2e-3);
  EXPECT_GT(touching, 20);                       // it lies on the sphere
  // coming to rest: the kinetic energy is a small part of what the fall released
  const State st = state0(sim);
  const std::vector<double> zero(st.q.size(), 0.0);
  const double kinetic = sim::mechanical_energy(scene.model, 0, nullptr, st.q.data(), st.qd.data());
  std::printf("%s %s: rise %g released %g deepest %g kinetic %g touching %d\n", sizeof(S) == 4 ? "float" : "double",
              integrator.c_str(), rise, released, deepest, kinetic, touching);
  EXPECT_LT(kinetic, 0.05 * released);
}
TEST(SimContactsRope, Rope200DrapesOverASphereDouble) {
  drape_rope<double>("euler");
  drape_rope<double>("implicit");
}
TEST(SimContactsRope, Rope200DrapesOverASphereFloat) {
  drape_rope<float>("implicit");
}

// ---- backends ----------------------------------------------------------------------------

// OpenMP steps every instance exactly as serial (the same per-instance code):
// bitwise equal states and readings, 8 instances with random starts, every integrator.
TEST(SimContactsBackends, OpenMPEqualsSerial) {
  for (const char* integrator : {"euler", "rk4", "implicit"}) {
    const Scene scene = scene_from(std::string(R"({"model": "chain:6", "dt": 1e-3, "integrator": ")") + integrator +
                                   R"(", "instances": 8, "effects": {"gravity": true, "damping": 0.01,
        "contacts": {"planes": [{"normal": [0, 0, 1], "offset": -0.3}], "spheres": [{"center": [0.1, 0, 0.6], "radius": 0.15}],
                     "all_links": {"radius": 0.01}, "points": [{"link": "link_5", "position": [0.1, 0, 0.2], "radius": 0.02}],
                     "stiffness": 1e4, "damping": 20, "friction": 0.7}},
        "initial": {"random": {"seed": 3, "q": 1.5, "qd": 1}}})");
    Simulator<double> serial(scene, BackendKind::Serial);
    Simulator<double> openmp(scene, BackendKind::OpenMP);
    int touching = 0;  // touching point-steps
    for (int s = 0; s < 100; ++s) {
      serial.step(), openmp.step();
      for (const auto& r : readings(serial)) touching += r.in_contact;
    }
    const std::size_t n = static_cast<std::size_t>(serial.nv() * serial.batch());
    std::vector<double> q1(n), qd1(n), q2(n), qd2(n);
    serial.read_state(q1.data(), qd1.data());
    openmp.read_state(q2.data(), qd2.data());
    EXPECT_EQ(q1, q2) << integrator;
    EXPECT_EQ(qd1, qd2) << integrator;
    const auto r1 = readings(serial), r2 = readings(openmp);
    for (std::size_t k = 0; k < r1.size(); ++k) {
      EXPECT_EQ(r1[k].force.x, r2[k].force.x);
      EXPECT_EQ(r1[k].force.z, r2[k].force.z);
      EXPECT_EQ(r1[k].in_contact, r2[k].in_contact);
    }
    EXPECT_GT(touching, 0) << integrator;  // the scene does touch
  }
}

// Without the key, no readings; the scene without contacts steps as before.
TEST(SimContactsBackends, NoContactsNoReadings) {
  const Scene scene = scene_from(R"({"model": "chain:3", "dt": 1e-3, "effects": {"gravity": true}})");
  Simulator<double> sim(scene);
  EXPECT_EQ(sim.contact_forces(), nullptr);
  EXPECT_EQ(sim.contact_count(), 0);
}

// ---- with prescribed joints and closed loops ------------------------------------------

// The contact pass's two ways to the points' poses and twists (ContactSet::walk_paths,
// chosen by contact_walks_paths): a walk from each point's body to the root, and
// every body's pose and twist into per-body scratch (contact_kinematics /
// contact_kinematics_at). The same wrenches, implicit armature and readings, double,
// within 1e-12 of the largest entry (the products associate differently): random
// trees of revolute and prismatic joints with arbitrary axes, and random trees on a
// free root with ball joints, 12 points on random bodies against a plane and a
// sphere placed so that some touch and some do not, with friction and the implicit
// look-ahead.
template <bool kMultiDof>
void path_walks_equal_per_body_pass(const Model& m, unsigned seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(-1, 1);
  const Index nb = m.nbodies(), nv = m.nv();
  const std::vector<double> q = test::random_q(m, rng, -1.5, 1.5);
  const std::vector<double> qd = test::random_vector(rng, static_cast<int>(nv), -1, 1);
  std::vector<sim::ContactPoint<double>> points;
  for (int k = 0; k < 12; ++k)
    points.push_back({static_cast<Index>(rng() % static_cast<unsigned>(nb)), Vec3<double>{0.2 * u(rng), 0.2 * u(rng), 0.2 * u(rng)}, 0.01});
  // where the points are (the per-body kinematics), to place the obstacles among them
  std::vector<Transform<double>> X(static_cast<std::size_t>(nb));
  std::vector<Motion<double>> v(static_cast<std::size_t>(nb));
  if constexpr (kMultiDof) sim::contact_kinematics_at(m.bodies.data(), nb, q.data(), qd.data(), X.data(), v.data());
  else sim::contact_kinematics(m.bodies.data(), nb, q.data(), qd.data(), 1, X.data(), v.data());
  std::vector<double> heights;
  for (const auto& cp : points) heights.push_back((mul_transpose(X[cp.body].E, cp.position) + X[cp.body].r).z);
  std::sort(heights.begin(), heights.end());
  const auto& c0 = points[0];
  const sim::ContactPlane<double> plane{{0, 0, 1}, heights[heights.size() / 2]};  // half the points below it
  const sim::ContactSphere<double> sphere{mul_transpose(X[c0.body].E, c0.position) + X[c0.body].r + Vec3<double>{0.05, 0, 0}, 0.3};
  sim::ContactSet<double> cs;
  cs.points = points.data(), cs.npoints = static_cast<Index>(points.size());
  cs.planes = &plane, cs.nplanes = 1, cs.spheres = &sphere, cs.nspheres = 1;
  cs.law = {1e4, 50, 0.7, 1e-3};
  cs.obstacles = sim::kPlanes | sim::kSpheres;
  struct Out {
    std::vector<Force<double>> f;
    std::vector<double> arm;
    std::vector<ContactReading<double>> r;
  };
  auto run = [&](bool walk) {
    cs.walk_paths = walk;
    Out o{std::vector<Force<double>>(static_cast<std::size_t>(nb), Force<double>::zero()),
          std::vector<double>(static_cast<std::size_t>(nv), 0.0), std::vector<ContactReading<double>>(points.size())};
    std::vector<Transform<double>> Xs(static_cast<std::size_t>(nb));
    std::vector<Motion<double>> vs(static_cast<std::size_t>(nb));
    sim::contact_pass<sim::kPlanes | sim::kSpheres, kMultiDof>(cs, m.bodies.data(), nb, q.data(), qd.data(), 1, 1e-3,
                                                               Xs.data(), vs.data(), o.f.data(), o.arm.data(), o.r.data());
    return o;
  };
  const Out a = run(false), b = run(true);
  int touching = 0;
  double scale = 0;
  for (const auto& r : a.r)
    touching += r.in_contact, scale = std::max({scale, std::abs(r.force.x), std::abs(r.force.y), std::abs(r.force.z)});
  ASSERT_GT(touching, 0);
  ASSERT_LT(touching, static_cast<int>(points.size()));
  for (std::size_t k = 0; k < points.size(); ++k) {
    EXPECT_EQ(a.r[k].in_contact, b.r[k].in_contact) << "point " << k;
    EXPECT_NEAR(a.r[k].depth, b.r[k].depth, 1e-12) << "point " << k;
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(a.r[k].force[c], b.r[k].force[c], 1e-12 * scale) << "point " << k;
  }
  double fscale = 0, ascale = 0;
  for (const auto& f : a.f)
    for (int c = 0; c < 6; ++c) fscale = std::max(fscale, std::abs(f[c]));
  for (double x : a.arm) ascale = std::max(ascale, std::abs(x));
  ASSERT_GT(ascale, 0);
  for (Index i = 0; i < nb; ++i)
    for (int c = 0; c < 6; ++c) EXPECT_NEAR(a.f[i][c], b.f[i][c], 1e-12 * fscale) << "body " << i << " entry " << c;
  for (Index j = 0; j < nv; ++j) EXPECT_NEAR(a.arm[j], b.arm[j], 1e-12 * ascale) << "DoF " << j;
  // the walks' generalized forces (qforce) are J^T of the body wrenches: bias_forces
  // without and with the wrenches differ by exactly that
  cs.walk_paths = true;
  std::vector<double> Q(static_cast<std::size_t>(nv), 0.0), arm(static_cast<std::size_t>(nv), 0.0);
  std::vector<ContactReading<double>> r(points.size());
  sim::contact_pass<sim::kPlanes | sim::kSpheres, kMultiDof>(cs, m.bodies.data(), nb, q.data(), qd.data(), 1, 1e-3,
                                                             static_cast<Transform<double>*>(nullptr),
                                                             static_cast<Motion<double>*>(nullptr),
                                                             static_cast<Force<double>*>(nullptr), arm.data(), r.data(),
                                                             Q.data());
  Data data(m);
  std::vector<double> h0(static_cast<std::size_t>(nv)), hf(static_cast<std::size_t>(nv));
  bias_forces(m, data, q.data(), qd.data(), h0.data());
  bias_forces(m, data, q.data(), qd.data(), hf.data(), a.f.data());
  double qscale = 0;
  for (Index j = 0; j < nv; ++j) qscale = std::max(qscale, std::abs(h0[j] - hf[j]));
  ASSERT_GT(qscale, 0);
  for (Index j = 0; j < nv; ++j) EXPECT_NEAR(Q[j], h0[j] - hf[j], 1e-12 * qscale) << "DoF " << j;
}

TEST(SimContactsPass, PathWalksEqualThePerBodyPassOnRandomTrees) {
  for (unsigned seed : {1u, 2u, 3u}) {
    SCOPED_TRACE(seed);
    path_walks_equal_per_body_pass<false>(test::random_model(9, seed), seed);
    path_walks_equal_per_body_pass<true>(test::random_floating_model(9, seed), seed);
  }
}

// contact_walks_paths: a few points (a robot's feet) walk, all-link points on a chain do not.
TEST(SimContactsPass, WalksForFewPointsOnly) {
  const Model hyq = test::load_robot("hyq.urdf");
  std::vector<sim::ContactPoint<double>> feet;
  for (Index i = 0; i < hyq.nbodies(); ++i)
    if (hyq.bodies[i].parent >= 0 && hyq.bodies[hyq.bodies[i].parent].parent >= 0) feet.push_back({i, {}, 0});
  EXPECT_TRUE(sim::contact_walks_paths(hyq.bodies.data(), hyq.nbodies(), feet.data(), static_cast<Index>(feet.size())));
  const Model rope = test::random_chain(50, 4);
  std::vector<sim::ContactPoint<double>> all;
  for (Index i = 0; i < rope.nbodies(); ++i) all.push_back({i, {}, 0});
  EXPECT_FALSE(sim::contact_walks_paths(rope.bodies.data(), rope.nbodies(), all.data(), static_cast<Index>(all.size())));
}

// Prescribed x (the point mass's DoF 2 on a sine, peak speed 0.2 * 2 pi = 1.26 m/s)
// while the ball rests on the plane: the hybrid step sees the contacts at the driven
// state. z rests at m g / k exactly as undriven (the friction is horizontal), y
// stays 0 (no sideways slip), x is on its trajectory, and the reading's friction is
// mu f_n against the slip (|v_x| > v_s: the Coulomb limit exactly). Every integrator.
TEST(SimContactsPrescribed, DrivenSlidingBallRestsAtMgOverKWithCoulombFriction) {
  const double m = 1 + 2e-6, k = 1e5, mu = 0.8, c = 2 * std::sqrt(k * m);
  for (const char* integrator : {"euler", "rk4", "implicit"}) {
    SCOPED_TRACE(integrator);
    const bool implicit = std::string(integrator) == "implicit";
    const double dt = implicit ? 1e-3 : 1e-4;
    std::string json = ball_scene(integrator, dt, R"("stiffness": 1e5, "damping": )" + std::to_string(c) +
                                                      R"(, "friction": 0.8)",
                                  R"({"q": [0.1, 0, 0], "qd": [-0.5, 0, 0]})");
    json.pop_back();
    json += R"(, "prescribed": {"joints": ["c_x"], "trajectory": [{"sine": {"amplitude": 0.2, "frequency": 1}}]}})";
    Simulator<double> sim(scene_from(json));
    const int steps = static_cast<int>(std::lround(2.1 / dt));  // 2.1 s: x at 0.2 sin(4.2 pi), moving at 0.39 m/s
    for (int s = 0; s < steps; ++s) sim.step();
    ASSERT_TRUE(sim.status().ok());
    const State st = state0(sim);
    const double t = sim.time(), w = 2 * M_PI;
    EXPECT_NEAR(st.q[2], 0.2 * std::sin(w * t), 1e-12);
    EXPECT_NEAR(st.qd[2], 0.2 * w * std::cos(w * t), 1e-12);
    EXPECT_EQ(st.q[1], 0.0);
    EXPECT_EQ(st.qd[1], 0.0);
    EXPECT_NEAR(0.1 - st.q[0], m * kG / k, 1e-6 * m * kG / k);
    const auto r = readings(sim);
    ASSERT_EQ(r[0].in_contact, 1);
    EXPECT_NEAR(r[0].force.z, m * kG, 1e-6 * m * kG);
    // the readings are the step's first forward dynamics': the slip at the step's start
    const double vx = 0.2 * w * std::cos(w * (t - dt));
    ASSERT_GT(std::abs(vx), 100 * 1e-3);
    EXPECT_NEAR(r[0].force.x, -mu * r[0].force.z * (vx > 0 ? 1 : -1), 1e-9 * m * kG);
    EXPECT_EQ(r[0].force.y, 0.0);
  }
}

// The fourbar (a closed loop, no gravity) pushed by a constant torque on its crank
// against a plane set 5 mm ahead of a point on its coupler, joint damping, no
// friction: it comes to rest on the plane with the loop closed (1e-11 m), and at
// rest the virtual work balances: for every velocity the loop admits (qd with J qd
// = 0), tau . qd + f . v_p = 0 (f the reading's force, v_p the point's velocity
// along qd by central differences of its position). euler and rk4; implicit with
// loops is refused, naming the loops.
TEST(SimContactsLoops, FourbarRestsOnAPlaneWithTheVirtualWorkBalanced) {
  const Scene base = scene_from(R"({"model": "fourbar", "dt": 1e-4})");
  const Model& model = base.model;
  const Index n = model.nv();
  const Index coupler = static_cast<Index>(
      std::find(model.link_names.begin(), model.link_names.end(), "coupler") - model.link_names.begin());
  ASSERT_LT(coupler, n);
  const Vec3<double> point{0.2, 0, 0};  // the coupler's middle
  auto position = [&](const std::vector<double>& q) {
    std::vector<Transform<double>> X(static_cast<std::size_t>(n));
    std::vector<Motion<double>> v(static_cast<std::size_t>(n));
    const std::vector<double> zero(static_cast<std::size_t>(n), 0.0);
    sim::contact_kinematics(model.bodies.data(), n, q.data(), zero.data(), 1, X.data(), v.data());
    return mul_transpose(X[coupler].E, point) + X[coupler].r;
  };
  // a velocity the loop admits, its crank rate positive, at q
  auto admissible = [&](std::vector<double> q) {
    std::vector<double> qd(static_cast<std::size_t>(n), 0.0);
    qd[0] = 1;
    project_to_loops(model, base.loops, q.data(), qd.data());
    if (qd[0] < 0)
      for (double& x : qd) x = -x;
    return qd;
  };
  auto point_velocity = [&](const std::vector<double>& q, const std::vector<double>& qd) {
    const double h = 1e-6;
    std::vector<double> qp = q, qm = q;
    for (Index i = 0; i < n; ++i) qp[i] += h * qd[i], qm[i] -= h * qd[i];
    return (1 / (2 * h)) * (position(qp) - position(qm));
  };
  const std::vector<double> q0(static_cast<std::size_t>(n), 0.0);  // closed (docs/models.md)
  const Vec3<double> p0 = position(q0), v0 = point_velocity(q0, admissible(q0));
  const Vec3<double> normal = (-1 / std::sqrt(dot(v0, v0))) * v0;  // facing the point, against its motion
  const double offset = dot(normal, p0) - 0.005;
  char plane[256];
  std::snprintf(plane, sizeof plane, R"({"normal": [%.17g, %.17g, %.17g], "offset": %.17g})", normal.x, normal.y,
                normal.z, offset);
  const double k = 1e4, tau_a = 0.05;
  for (const char* integrator : {"euler", "rk4", "implicit"}) {
    SCOPED_TRACE(integrator);
    const std::string json = std::string(R"({"model": "fourbar", "dt": 1e-4, "integrator": ")") + integrator +
                             R"(", "effects": {"damping": 0.05, "contacts": {"planes": [)" + plane +
                             R"(], "points": [{"link": "coupler", "position": [0.2, 0, 0]}], "stiffness": 1e4,
                             "damping": 20, "friction": 0}}})";
    if (std::string(integrator) == "implicit") {
      try {
        Simulator<double> sim(scene_from(json), BackendKind::Serial);
        ADD_FAILURE() << "implicit with loops was accepted";
      } catch (const std::exception& e) {
        EXPECT_NE(std::string(e.what()).find("closed loops step with euler or rk4, not implicit"), std::string::npos)
            << e.what();
      }
      continue;
    }
    Simulator<double> sim(scene_from(json), BackendKind::Serial);
    std::vector<double> tau(static_cast<std::size_t>(n), 0.0);
    tau[0] = tau_a;
    const BatchView<const double> tv = BatchView<const double>::aos(tau.data(), n, 1);
    std::vector<double> q(static_cast<std::size_t>(n)), qd(static_cast<std::size_t>(n));
    double worst_closure = 0;
    for (int s = 0; s < 30000; ++s) {  // 3 s
      sim.step(tv);
      if (s % 100 == 99) {
        sim.read_state(q.data(), qd.data());
        worst_closure = std::max(worst_closure, loop_violation(model, base.loops, q.data(), qd.data()));
      }
    }
    ASSERT_TRUE(sim.status().ok()) << sim::failure_message(sim.status());
    sim.read_state(q.data(), qd.data());
    EXPECT_LE(worst_closure, 1e-11);
    for (double x : qd) EXPECT_LT(std::abs(x), 1e-9);  // at rest
    const auto r = readings(sim);
    ASSERT_EQ(r[0].in_contact, 1);
    const Vec3<double> f = r[0].force;
    EXPECT_NEAR(dot(f, normal), k * r[0].depth, 1e-9 * k * r[0].depth);  // the normal law at rest
    EXPECT_NEAR(std::sqrt(dot(f, f)), std::abs(dot(f, normal)), 1e-12);   // no friction
    const std::vector<double> u = admissible(q);
    const double power_tau = tau_a * u[0], power_f = dot(f, point_velocity(q, u));
    EXPECT_NEAR(power_tau + power_f, 0.0, 1e-6 * std::abs(power_tau));
  }
}

}  // namespace
}  // namespace scandyn
