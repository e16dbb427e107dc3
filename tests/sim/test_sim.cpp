// Tests of scandyn/sim: scene files, effects, integrators, the Simulator on the CPU
// backends. Truths: conservation of energy (symplectic Euler), the damped
// oscillator's stability bounds, a dense solve of (M + diag(a)) qdd = tau - h for
// the armature, bitwise agreement of declared-zero and absent effects, serial vs
// OpenMP.
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <cmath>
#include <fstream>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"
#include "scene_util.hpp"
#include "test_util.hpp"
#include "../cpu_fallback/simulator_step.hpp"

namespace scandyn {
namespace {

using sim::Integrator;
using sim::Scene;
using sim::SceneError;
using sim::Simulator;

using test::scene_error;
using test::scene_from;


// ---- scene files -----------------------------------------------------------------

TEST(SimScene, ParsesEveryKey) {
  const Scene s = scene_from(R"({
    "model": "chain:3", "dt": 0.002, "integrator": "implicit", "precision": "float",
    "backend": "openmp", "threads": 2, "instances": 5,
    "effects": {"gravity": [0, 0, -1.5], "damping": [0.1, 0.2, 0.3],
                "springs": {"stiffness": 4, "rest": [0, 0.5, 0]},
                "limits": {"stiffness": 100, "damping": 1, "lower": -1, "upper": [1, null, 2]},
                "external": {"wrenches": [{"link": "link_1", "wrench": [0, 0, 1, 2, 0, 0]}], "per_step": true}},
    "initial": {"q": [0.1, 0.2, 0.3], "qd": 0.5, "random": {"seed": 7, "q": 0.01}}
  })");
  EXPECT_EQ(s.nv(), 3);
  EXPECT_EQ(s.effects, sim::kAllEffects & ~sim::kContacts);
  EXPECT_EQ(s.model.gravity.z, -1.5);
  EXPECT_EQ(s.integrator, Integrator::Implicit);
  EXPECT_EQ(s.dt, 0.002);
  EXPECT_EQ(s.precision, Precision::Float);
  EXPECT_EQ(s.backend, BackendKind::OpenMP);
  EXPECT_EQ(s.threads, 2);
  EXPECT_EQ(s.instances, 5);
  EXPECT_EQ(s.joints[1].damping, 0.2);
  EXPECT_EQ(s.joints[2].stiffness, 4);
  EXPECT_EQ(s.joints[1].rest, 0.5);
  EXPECT_EQ(s.joints[0].lower, -1);
  EXPECT_EQ(s.joints[1].upper, HUGE_VAL);
  EXPECT_EQ(s.joints[2].upper, 2);
  ASSERT_EQ(s.wrenches.size(), 1u);
  EXPECT_EQ(s.wrenches[0].body, 1);
  EXPECT_EQ(s.wrenches[0].wrench.f.x, 2);
  EXPECT_TRUE(s.wrenches_per_step);
  EXPECT_EQ(s.initial.qd[2], 0.5);
  EXPECT_TRUE(s.initial.random);
  EXPECT_EQ(s.initial.seed, 7u);
  EXPECT_EQ(s.initial.q_spread[0], 0.01);
  EXPECT_EQ(s.initial.qd_spread[0], 0.0);
}

TEST(SimScene, DefaultsAndNoEffects) {
  const Scene s = scene_from(R"({"model": "rope:4", "dt": 0.001})");
  EXPECT_EQ(s.effects, 0u);
  EXPECT_EQ(s.model.gravity.z, 0.0);  // gravity absent: zero base acceleration
  EXPECT_EQ(s.integrator, Integrator::Euler);
  EXPECT_EQ(s.backend, BackendKind::Serial);
  EXPECT_EQ(s.instances, 1);
  EXPECT_FALSE(s.initial.random);
  const Scene g = scene_from(R"({"model": "rope:4", "dt": 0.001, "effects": {"gravity": true}})");
  EXPECT_EQ(g.model.gravity.z, -9.81);
}

TEST(SimScene, LimitsDefaultToTheUrdf) {
  const std::string urdf = test::models_dir() + "/iiwa.urdf";
  if (!std::ifstream(urdf)) GTEST_SKIP() << urdf << " not found (set SCANDYN_MODELS_DIR)";
  const Model m = load_urdf(urdf);
  const Scene s = scene_from(R"({"model": ")" + urdf + R"(", "dt": 0.001, "effects": {"limits": {"stiffness": 10}}})");
  for (Index i = 0; i < m.nv(); ++i) {
    EXPECT_EQ(s.joints[i].lower, m.q_lower[i]);
    EXPECT_EQ(s.joints[i].upper, m.q_upper[i]);
    EXPECT_LT(m.q_lower[i], m.q_upper[i]);  // iiwa's joints all have <limit>
    EXPECT_TRUE(std::isfinite(m.q_lower[i]));
  }
}

TEST(SimScene, ErrorsNameTheFileAndTheKey) {
  const std::string head = R"({"model": "chain:3", "dt": 0.001, )";
  struct Case {
    std::string json, message;
  };
  const Case cases[] = {
      {R"({"model": "chain:3", "dt": 0.001, "effects": {"damping": -1}})",
       "test.json: effects.damping: expected a non-negative number or an array of 3 non-negative numbers, got -1"},
      {head + R"("effects": {"damping": [1, 2]}})", "test.json: effects.damping: expected 3 entries (one per DoF), got 2"},
      {head + R"("effects": {"damping": [1, -2, 0]}})", "test.json: effects.damping[1]: expected a non-negative number, got -2"},
      {head + R"("bogus": 1})", "test.json: bogus: unknown key (expected one of: "},
      {head + R"("effects": {"friction": 1}})", "test.json: effects.friction: unknown key"},
      {head + R"("effects": {"springs": {"stiffness": 1, "rest": 0, "x": 0}}})", "test.json: effects.springs.x: unknown key"},
      {head + R"("effects": {"springs": {"rest": 0}}})", "test.json: effects.springs.stiffness: missing"},
      {head + R"("integrator": "verlet"})", R"(test.json: integrator: expected "euler", "rk4", "implicit" or "variational", got "verlet")"},
      {R"({"model": "chain:3", "dt": 0})", "test.json: dt: expected a positive number, got 0"},
      {R"({"model": "chain:3"})", "test.json: dt: missing"},
      {R"({"dt": 0.1})", "test.json: model: missing"},
      {R"({"model": "rope:0", "dt": 0.1})", "test.json: model: rope:0: N must be >= 1"},
      {R"({"model": "nowhere.urdf", "dt": 0.1})", "test.json: model: 'nowhere.urdf' not found"},
      {head + R"("precision": "half"})", "test.json: precision: expected \"double\" or \"float\", got \"half\""},
      {head + R"("base": "free"})", "test.json: base: expected \"fixed\" or \"floating\", got \"free\""},
      {head + R"("backend": "tpu"})", "test.json: backend: expected"},
      {head + R"("instances": 0})", "test.json: instances: expected an integer from 1 to 1000000000, got 0"},
      {head + R"("instances": 2.5})", "test.json: instances: expected an integer"},
      {head + R"("effects": {"gravity": "down"}})", "test.json: effects.gravity: expected true, false or [gx, gy, gz]"},
      {head + R"("effects": {"limits": {"stiffness": 1, "lower": 1, "upper": 0}}})",
       "test.json: effects.limits: DoF 0 (joint 'joint_0'): lower limit 1 is above upper limit 0"},
      {head + R"("effects": {"external": {"wrenches": [{"link": "nope", "wrench": [0,0,0,0,0,0]}]}}})",
       "test.json: effects.external.wrenches[0].link: no moving link named 'nope'"},
      {head + R"("effects": {"external": {"wrenches": [{"link": "link_0", "wrench": [0,0,0]}]}}})",
       "test.json: effects.external.wrenches[0].wrench: expected [nx, ny, nz, fx, fy, fz]"},
      {head + R"("initial": {"random": {"q": 0.1}}})", "test.json: initial.random.seed: missing"},
      {head + R"("initial": {"random": {"seed": -3}}})", "test.json: initial.random.seed: expected a non-negative integer, got -3"},
      {head + R"("initial": {"q": [1, 2, "x"]}})", "test.json: initial.q: expected a number or an array of 3 numbers"},
      {R"({"model": "chain:3", "dt": 0.001,)", "test.json: not valid JSON: "},
      {R"([1, 2])", "test.json: expected an object, got [1,2]"},
  };
  for (const Case& c : cases) {
    const std::string got = scene_error(c.json);
    EXPECT_EQ(got.compare(0, c.message.size(), c.message), 0) << "scene: " << c.json << "\n got: " << got
                                                               << "\nwant: " << c.message;
  }
}

// "backend": "auto" is cuda where a device is usable, else openmp (serial in a
// build without OpenMP), resolved when the scene is read and said in one line.
TEST(SimScene, BackendAutoPicksCudaWhenUsableElseOpenMP) {
  const Scene s = scene_from(R"({"model": "chain:3", "dt": 0.001, "backend": "auto"})");
  EXPECT_TRUE(s.backend_auto);
  const std::string cuda = backend_unusable(BackendKind::Cuda);
  const std::string openmp = backend_unusable(BackendKind::OpenMP);
  const BackendKind expected = cuda.empty()     ? BackendKind::Cuda
                               : openmp.empty() ? BackendKind::OpenMP
                                                : BackendKind::Serial;
  EXPECT_EQ(s.backend, expected);
  EXPECT_EQ(sim::auto_backend(), expected);
  if (cuda.empty()) {
    EXPECT_EQ(s.backend_note, "");
    EXPECT_EQ(sim::backend_choice(s), "scene backend auto: cuda");
  } else {
    EXPECT_EQ(s.backend_note.rfind("cuda: " + cuda, 0), 0u) << s.backend_note;
    EXPECT_EQ(sim::backend_choice(s), std::string("scene backend auto: ") + to_string(expected) + " (" + s.backend_note + ")");
  }
#if !SCANDYN_HAS_CUDA && SCANDYN_HAS_OPENMP
  // this build (no CUDA): openmp
  EXPECT_EQ(s.backend, BackendKind::OpenMP);
  EXPECT_EQ(sim::backend_choice(s), "scene backend auto: openmp (cuda: backend 'cuda' is not available in this build)");
#endif
  // the scene runs there
  Simulator<double> sim(s);
  sim.step();
  EXPECT_TRUE(sim.status().ok());
  // a named backend is no choice: nothing to say
  const Scene named = scene_from(R"({"model": "chain:3", "dt": 0.001, "backend": "serial"})");
  EXPECT_FALSE(named.backend_auto);
  EXPECT_EQ(sim::backend_choice(named), "");
}

// Every shipped scene (scenes/*.json) is valid: parsed with its model, generators
// made (rope:10^6 included: about 1 s), robots found through SCANDYN_MODELS_DIR or
// the shipped models/; each says "backend": "auto", so it runs on a machine without a
// GPU (here: openmp when CUDA is not built).
TEST(SimScene, ShippedScenesLoad) {
  int count = 0;
  for (const char* name : {"iiwa_rl", "hyq_rl", "rope_1e4", "rope_1e6", "curtain"}) {
    const std::string path = std::string(SCANDYN_SOURCE_DIR) + "/scenes/" + name + ".json";
    const Scene s = sim::load_scene(path);
    EXPECT_GT(s.nv(), 0) << path;
    EXPECT_NE(s.effects & sim::kGravity, 0u) << path;
    EXPECT_TRUE(s.backend_auto) << path;
    EXPECT_EQ(s.backend, sim::auto_backend()) << path;
#if !SCANDYN_HAS_CUDA && SCANDYN_HAS_OPENMP
    EXPECT_EQ(s.backend, BackendKind::OpenMP) << path;
#endif
    ++count;
  }
  EXPECT_EQ(count, 5);
}

TEST(SimScene, MissingFile) {
  try {
    sim::load_scene("/nonexistent/scene.json");
    FAIL() << "no error";
  } catch (const SceneError& e) {
    EXPECT_STREQ(e.what(), "/nonexistent/scene.json: cannot open file: No such file or directory");
  }
}

// ---- armature: one source, checked against a dense solve ----------------------------

TEST(SimArmature, AbaAndJsiSolveTheShiftedMassMatrix) {
  const Model model = make_generated("tree:12:3");
  const Index n = model.nv();
  Data data(model);
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> u(-1, 1);
  std::vector<double> q(n), qd(n), tau(n), arm(n), qdd_aba(n), qdd_jsi(n), h(n), M(n * n);
  for (Index i = 0; i < n; ++i) q[i] = u(rng), qd[i] = u(rng), tau[i] = u(rng), arm[i] = 0.5 + u(rng) * 0.4;
  ASSERT_TRUE(aba(model, data, q.data(), qd.data(), tau.data(), qdd_aba.data(), static_cast<const Force<double>*>(nullptr), arm.data()).ok());
  ASSERT_TRUE(fd_jsi(model, data, q.data(), qd.data(), tau.data(), qdd_jsi.data(), static_cast<const Force<double>*>(nullptr), arm.data()).ok());
  crba(model, data, q.data(), M.data());
  bias_forces(model, data, q.data(), qd.data(), h.data());
  Eigen::MatrixXd A = Eigen::Map<Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>>(M.data(), n, n);
  Eigen::VectorXd rhs(n);
  for (Index i = 0; i < n; ++i) A(i, i) += arm[i], rhs[i] = tau[i] - h[i];
  const Eigen::VectorXd x = A.ldlt().solve(rhs);
  for (Index i = 0; i < n; ++i) {
    EXPECT_NEAR(qdd_aba[i], x[i], 1e-10 * (1 + std::abs(x[i])));
    EXPECT_NEAR(qdd_jsi[i], x[i], 1e-10 * (1 + std::abs(x[i])));
  }
  // a null armature is exactly the call without one
  std::vector<double> a1(n), a2(n);
  aba(model, data, q.data(), qd.data(), tau.data(), a1.data());
  aba(model, data, q.data(), qd.data(), tau.data(), a2.data(), static_cast<const Force<double>*>(nullptr), static_cast<const double*>(nullptr));
  EXPECT_EQ(a1, a2);
}

// ---- energy -------------------------------------------------------------------------

// An undamped rope:1000 in double with semi-implicit Euler: the relative energy
// drift max_t |E(t) - E(0)| / |E(0)| (potential measured from the base, the rope
// hanging below it) stays <= 1e-4 over 10^4 steps of 2e-5 s (measured: 1.1e-5).
// As that normalisation includes the rope's large potential energy, the test also
// bounds the error relative to the swinging energy E(0) - E_rest (E_rest: hanging
// still) by 2e-3 (measured: 7.3e-4; it scales as dt^1.5: 2.5e-4 at 1e-5, 6.7e-3
// at 5e-5). 10^4 ABA steps of 1000 links: about 2 s on one core.
TEST(SimEnergy, UndampedRope1000SymplecticEulerDriftBelow1e4Over1e4Steps) {
  const Scene scene = scene_from(R"({"model": "rope:1000", "dt": 2e-5, "integrator": "euler",
      "effects": {"gravity": true}, "initial": {"random": {"seed": 1, "q": 0.02}}})");
  Simulator<double> sim(scene);
  const std::vector<double> zero(scene.nv(), 0.0);
  const double rest = sim::mechanical_energy(scene.model, scene.effects, scene.joints.data(), zero.data(), zero.data());
  const double e0 = sim.energy()[0];
  ASSERT_GT(e0 - rest, 1.0);  // it swings: 7.5 J above rest
  double drift = 0, swing = 0;
  for (int s = 0; s < 10000; ++s) {
    sim.step();
    if (s % 50 == 49) {
      const double e = sim.energy()[0];
      drift = std::max(drift, std::abs(e - e0) / std::abs(e0));
      swing = std::max(swing, std::abs(e - e0) / (e0 - rest));
    }
  }
  ASSERT_TRUE(sim.status().ok());
  EXPECT_LE(drift, 1e-4);
  EXPECT_LE(swing, 2e-3);
}

// Energy of a scene, instance 0, for the rest of the energy tests.
double energy0(Simulator<double>& sim) { return sim.energy()[0]; }

// Damped scenes lose energy at every step (springs' energy included): chain:4 with
// gravity, damping and springs, every integrator.
TEST(SimEnergy, DampedScenesLoseEnergyMonotonically) {
  for (const char* integrator : {"euler", "rk4", "implicit"}) {
    const Scene scene = scene_from(std::string(R"({"model": "chain:4", "dt": 1e-3, "integrator": ")") + integrator +
                                   R"(", "effects": {"gravity": true, "damping": 0.5, "springs": {"stiffness": 2}},
        "initial": {"q": [0.6, -0.4, 0.8, 0.3], "qd": [1, 0, -1, 0.5]}})");
    Simulator<double> sim(scene);
    double prev = energy0(sim);
    const double first = prev;
    int rises = 0;
    for (int s = 0; s < 3000; ++s) {
      sim.step();
      const double e = energy0(sim);
      rises += e > prev;
      prev = e;
    }
    EXPECT_EQ(rises, 0) << integrator;
    EXPECT_LT(prev, first - 0.5 * (first - prev) - 1e-3) << integrator;  // and it does lose energy
  }
}

// Stiff damping: one joint with dt d / m = 4 > 2. Explicit (semi-implicit) Euler
// multiplies the velocity by |1 - dt d / m| = 3 per step and diverges; the implicit
// treatment by 1 / (1 + dt d / m) and stays bounded. Likewise stiff springs
// (dt^2 k / m = 8 > 4: outside symplectic Euler's stability interval). Bounded
// means: the mechanical energy (kinetic + the spring's) never exceeds its start.
TEST(SimIntegrators, ImplicitStaysBoundedWhereExplicitEulerDiverges) {
  // chain:1, no gravity: a rod spinning about its own axis z, M = Izz = 1e-3 kg m^2
  const double m = make_generated("chain:1").bodies[0].I.I.zz;
  const double dt = 1e-3;
  for (const char* effects : {R"("damping": 4)", R"("springs": {"stiffness": 8000}, "damping": 0)"}) {
    const bool springs = std::string(effects).find("springs") != std::string::npos;
    for (const char* integrator : {"euler", "implicit"}) {
      const Scene scene = scene_from(std::string(R"({"model": "chain:1", "dt": 0.001, "integrator": ")") + integrator +
                                     R"(", "effects": {)" + effects + R"(}, "initial": {"q": 0.1, "qd": 1}})");
      ASSERT_NEAR(scene.joints[0].damping * dt / m + scene.joints[0].stiffness * dt * dt / m, springs ? 8.0 : 4.0, 1e-9);
      Simulator<double> sim(scene);
      const double e0 = sim.energy()[0];
      double worst = 0;
      for (int s = 0; s < 200; ++s) {
        sim.step();
        const double e = sim.energy()[0];
        worst = std::isfinite(e) ? std::max(worst, e / e0) : HUGE_VAL;
      }
      if (std::string(integrator) == "euler") EXPECT_GT(worst, 1e6) << effects << ": explicit Euler did not diverge";
      else EXPECT_LE(worst, 1 + 1e-12) << effects << ": the implicit step gained energy";
    }
  }
}

// ---- effects: compile-time instantiations ---------------------------------------------

// The trajectory of instance b, all of q then all of qd per step.
template <class S>
std::vector<S> rollout(const Scene& scene, int steps, BackendKind backend) {
  Simulator<S> sim(scene, backend);
  std::vector<S> out;
  for (int s = 0; s < steps; ++s) {
    sim.step();
    std::vector<S> q(sim.nv() * sim.batch()), qd(q.size());
    sim.read_state(q.data(), qd.data());
    out.insert(out.end(), q.begin(), q.end());
    out.insert(out.end(), qd.begin(), qd.end());
  }
  EXPECT_TRUE(sim.status().ok());
  return out;
}

// An effect declared with zero coefficients gives the same trajectory as the effect
// absent, bit for bit, for every integrator: the instantiation with the effect adds
// exact zeros.
TEST(SimEffects, ZeroCoefficientsEqualAbsentEffects) {
  const std::string base = R"("model": "chain:5", "dt": 1e-3, "instances": 3,
      "initial": {"random": {"seed": 3, "q": 0.5, "qd": 0.5}})";
  for (const char* integrator : {"euler", "rk4", "implicit"}) {
    const std::string in = std::string(R"("integrator": ")") + integrator + "\", ";
    const Scene only = scene_from("{" + in + base + R"(, "effects": {"gravity": true}})");
    const Scene all = scene_from("{" + in + base + R"(, "effects": {"gravity": true, "damping": 0,
        "springs": {"stiffness": 0, "rest": 0.3}, "limits": {"stiffness": 0, "damping": 0, "lower": -0.1, "upper": 0.1},
        "external": {"wrenches": [{"link": "link_2", "wrench": [0, 0, 0, 0, 0, 0]}]}}})");
    EXPECT_EQ(all.effects, sim::kAllEffects & ~sim::kContacts);
    EXPECT_EQ(rollout<double>(only, 50, BackendKind::Serial), rollout<double>(all, 50, BackendKind::Serial)) << integrator;
    EXPECT_EQ(rollout<float>(only, 50, BackendKind::Serial), rollout<float>(all, 50, BackendKind::Serial)) << integrator;
  }
}

// Each effect, declared with non-zero coefficients, changes the trajectory, against
// a closed form where there is one: a prismatic-free rod about z (chain:1, Izz
// = m) under a spring and damper is the damped oscillator m qdd = -k q - d qd.
TEST(SimEffects, DampedOscillatorMatchesTheClosedForm) {
  const double m = make_generated("chain:1").bodies[0].I.I.zz;
  const double k = 0.1, d = 2e-3, q0 = 0.2;  // underdamped: d^2 < 4 k m
  const Scene scene = scene_from(R"({"model": "chain:1", "dt": 1e-4, "integrator": "rk4",
      "effects": {"damping": 2e-3, "springs": {"stiffness": 0.1}}, "initial": {"q": 0.2}})");
  Simulator<double> sim(scene);
  const double wd = std::sqrt(k / m - d * d / (4 * m * m)), z = d / (2 * m);
  for (int s = 1; s <= 5000; ++s) {
    sim.step();
    if (s % 500 != 0) continue;
    const double t = s * 1e-4;
    const double exact = q0 * std::exp(-z * t) * (std::cos(wd * t) + z / wd * std::sin(wd * t));
    EXPECT_NEAR(sim.q().at(0, 0), exact, 1e-9) << "t = " << t;
  }
}

// A joint limit pushes back: chain:1 spinning at 1 rad/s into a limit at 0.1 rad
// stops and returns; the penalty spring's overshoot is about qd sqrt(m / kl).
TEST(SimEffects, LimitsPushBack) {
  const Scene scene = scene_from(R"({"model": "chain:1", "dt": 1e-4, "integrator": "euler",
      "effects": {"limits": {"stiffness": 10, "lower": -0.1, "upper": 0.1}}, "initial": {"qd": 1}})");
  const double m = scene.model.bodies[0].I.I.zz;
  Simulator<double> sim(scene);
  double top = 0, slowest = 1;
  for (int s = 0; s < 1500; ++s) {  // 0.15 s: into the upper limit (at 0.1 s) and back out
    sim.step();
    top = std::max(top, sim.q().at(0, 0));
    slowest = std::min(slowest, sim.qd().at(0, 0));
  }
  EXPECT_NEAR(top, 0.1 + std::sqrt(m / 10), 2e-3);
  EXPECT_NEAR(slowest, -1, 1e-2);  // bounced back elastically (no limit damping)
  EXPECT_LT(sim.q().at(0, 0), 0.1);
}

// External wrenches: a constant force on a rope's last link equals, through the
// forward dynamics, the torque J^T f; checked against the reference aba with fext.
TEST(SimEffects, ExternalWrenchesReachTheForwardDynamics) {
  const Scene scene = scene_from(R"({"model": "rope:3", "dt": 1e-3,
      "effects": {"external": {"wrenches": [{"link": "link_2", "wrench": [0, 0, 0, 1, 0, 0]}], "per_step": true}}})");
  Simulator<double> sim(scene);
  ASSERT_NE(sim.wrenches(), nullptr);
  sim.wrenches()[2].f.y = 0.5;  // per step: the caller's change is used
  sim.step();
  Data data(scene.model);
  std::vector<Force<double>> f(3, Force<double>::zero());
  f[2].f = {1, 0.5, 0};
  const std::vector<double> q(3, 0.0), qd(3, 0.0), tau(3, 0.0);
  std::vector<double> qdd(3);
  ASSERT_TRUE(aba(scene.model, data, q.data(), qd.data(), tau.data(), qdd.data(), f.data()).ok());
  for (Index i = 0; i < 3; ++i) {
    EXPECT_NEAR(sim.qd().at(i, 0), 1e-3 * qdd[i], 1e-15);
    EXPECT_NE(qdd[i], 0.0);
  }
}

// ---- the simulator -------------------------------------------------------------------

TEST(Simulator, SerialAndOpenMPAgreeFor100Steps) {
#if !SCANDYN_HAS_OPENMP
  GTEST_SKIP() << "built without OpenMP";
#endif
  for (const char* integrator : {"euler", "rk4", "implicit"}) {
    const Scene scene = scene_from(std::string(R"({"model": "tree:9:2", "dt": 1e-3, "integrator": ")") + integrator +
                                   R"(", "instances": 37, "threads": 2, "effects": {"gravity": true, "damping": 0.1,
        "springs": {"stiffness": 1}, "limits": {"stiffness": 50, "lower": -0.5, "upper": 0.5}},
        "initial": {"random": {"seed": 9, "q": 0.4, "qd": 1}}})");
    // same code, same order of operations per instance: equal bit for bit
    EXPECT_EQ(rollout<double>(scene, 100, BackendKind::Serial), rollout<double>(scene, 100, BackendKind::OpenMP));
  }
}

// A forward dynamics that fails is recorded as the engines record a failed
// instance: the simulator's BatchStatus counts failed instance-steps and names the
// lowest failing instance, the DoF where its ABA stopped and the pivot; the
// instance keeps its state for that step; serial and openmp agree.
TEST(Simulator, FailuresAreRecordedAsTheEnginesRecordThem) {
  const Scene scene = scene_from(R"({"model": "chain:3", "dt": 1e-3, "instances": 5, "threads": 2,
      "effects": {"gravity": true}, "initial": {"random": {"seed": 1, "q": 0.3}}})");
  // the DoF at which the reference aba stops for instance 3's state
  Simulator<double> probe(scene, BackendKind::Serial);
  std::vector<double> q(3), qd(3, 0.0), tau(3, 0.0), qdd(3);
  for (Index i = 0; i < 3; ++i) q[i] = probe.q().at(i, 3);
  q[1] = HUGE_VAL;
  Data data(scene.model);
  const Status ref = aba(scene.model, data, q.data(), qd.data(), tau.data(), qdd.data());
  ASSERT_FALSE(ref.ok());
  for (BackendKind backend : {BackendKind::Serial, BackendKind::OpenMP}) {
#if !SCANDYN_HAS_OPENMP
    if (backend == BackendKind::OpenMP) continue;
#endif
    Simulator<double> sim(scene, backend);
    sim.q().at(1, 3) = HUGE_VAL;
    const double q03 = sim.q().at(0, 3);
    sim.step();
    sim.step();
    const BatchStatus st = sim.status();
    EXPECT_EQ(st.failed, 2) << to_string(backend);  // instance 3 in both steps
    EXPECT_EQ(st.first_instance, 3);
    EXPECT_EQ(st.first_dof, ref.failed_dof);
    EXPECT_EQ(st.failure, Failure::ArticulatedPivot);
    EXPECT_EQ(st.failed_dof, nullptr);
    EXPECT_EQ(sim.q().at(0, 3), q03);  // kept its state
    EXPECT_EQ(sim.qd().at(0, 3), 0.0);
    EXPECT_GT(std::abs(sim.qd().at(0, 2)) + std::abs(sim.qd().at(1, 2)) + std::abs(sim.qd().at(2, 2)), 0.0);  // the others stepped
    EXPECT_EQ(sim::failure_message(st), "forward dynamics failed in 2 instance-steps, first in instance 3: "
                                        "articulated inertia pivot at DoF " + std::to_string(ref.failed_dof) +
                                        " is not positive; those instances kept their state for those steps");
    sim.clear_status();
    EXPECT_TRUE(sim.status().ok());
    EXPECT_EQ(sim::failure_message(sim.status()), "");
  }
}

// A step that leaves the state non-finite (damping 1e300 on a joint moving at 1e300
// rad/s: the explicit step overflows) is recorded per instance with the first
// such DoF, and the state is kept as computed; a finite instance beside it is not.
TEST(SimStatus, NonFiniteStateIsRecorded) {
  Scene scene = scene_from(R"({"model": "chain:1", "dt": 0.001, "instances": 2,
                               "effects": {"damping": 1e300}, "initial": {"qd": 0}})");
  for (BackendKind backend : {BackendKind::Serial, BackendKind::OpenMP}) {
#if !SCANDYN_HAS_OPENMP
    if (backend == BackendKind::OpenMP) continue;
#endif
    Simulator<double> sim(scene, backend);
    sim.qd().at(0, 1) = 1e300;
    sim.step();
    sim.step();
    const BatchStatus st = sim.status();
    EXPECT_GE(st.failed, 1) << to_string(backend);
    EXPECT_EQ(st.first_instance, 1);
    EXPECT_EQ(st.first_dof, 0);
    EXPECT_EQ(st.failure, Failure::NonFinite);
    EXPECT_FALSE(std::isfinite(sim.qd().at(0, 1)));  // kept as computed
    EXPECT_TRUE(std::isfinite(sim.qd().at(0, 0)));
    EXPECT_EQ(sim::failure_message(st).rfind("the state became non-finite in ", 0), 0u) << sim::failure_message(st);
    EXPECT_NE(sim::failure_message(st).find("first in instance 1: the state at DoF 0 is not finite after the step"),
              std::string::npos);
  }
}

// The status's count saturates instead of overflowing; the lowest instance is kept.
TEST(Simulator, StepFailuresAddUpAndSaturate) {
  BatchStatus total;
  BatchStatus step;
  step.record(7, 2, Failure::ArticulatedPivot);
  step.record(9, 1, Failure::ArticulatedPivot);
  sim::add_step_failures(total, step);
  BatchStatus lower;
  lower.record(4, 0, Failure::MassMatrixPivot);
  sim::add_step_failures(total, lower);
  EXPECT_EQ(total.failed, 3);
  EXPECT_EQ(total.first_instance, 4);
  EXPECT_EQ(total.first_dof, 0);
  EXPECT_EQ(total.failure, Failure::MassMatrixPivot);
  BatchStatus many;
  many.record(5, 1, Failure::ArticulatedPivot);
  many.failed = std::numeric_limits<Index>::max() - 1;
  sim::add_step_failures(total, many);
  EXPECT_EQ(total.failed, std::numeric_limits<Index>::max());
  EXPECT_EQ(total.first_instance, 4);
}

// ---- one long chain on openmp: the parallel chain forward dynamics ---------------------

// When the openmp step goes through the forward-dynamics engine: a chain from the
// base that choose_fd_method(OpenMP) runs by the parallel method (>= 4096 links),
// at least kChainFdThreadsPerInstance threads per instance, euler or rk4.
TEST(SimOpenMPChain, StepsPerForwardDynamicsOnlyWithEnoughThreadsPerInstance) {
  constexpr int kT = kChainFdThreadsPerInstance;
  sim::SimSetup<double> s;
  s.model = make_generated("rope:4096");
  s.batch = 1;
  s.integrator = Integrator::Euler;
  EXPECT_TRUE(cpu::steps_per_forward_dynamics(s, BackendKind::OpenMP, kT));
  EXPECT_FALSE(cpu::steps_per_forward_dynamics(s, BackendKind::OpenMP, kT - 1));
  EXPECT_FALSE(cpu::steps_per_forward_dynamics(s, BackendKind::Serial, kT));
  s.integrator = Integrator::Rk4;
  EXPECT_TRUE(cpu::steps_per_forward_dynamics(s, BackendKind::OpenMP, kT));
  s.integrator = Integrator::Implicit;  // the chain forward dynamics takes no armature
  EXPECT_FALSE(cpu::steps_per_forward_dynamics(s, BackendKind::OpenMP, 4 * kT));
  s.integrator = Integrator::Euler;
  s.batch = 2;
  EXPECT_FALSE(cpu::steps_per_forward_dynamics(s, BackendKind::OpenMP, 2 * kT - 1));
  EXPECT_TRUE(cpu::steps_per_forward_dynamics(s, BackendKind::OpenMP, 2 * kT));
  s.batch = 1;
  s.model = make_generated("rope:4095");  // below choose_fd_method's threshold
  EXPECT_FALSE(cpu::steps_per_forward_dynamics(s, BackendKind::OpenMP, 4 * kT));
  s.model = make_generated("tree:5000:1");  // branched
  EXPECT_FALSE(cpu::steps_per_forward_dynamics(s, BackendKind::OpenMP, 4 * kT));
  s.model = make_generated("curtain:2:3000");  // chains hanging from the base
  EXPECT_TRUE(cpu::steps_per_forward_dynamics(s, BackendKind::OpenMP, kT));
  // the engine path steps none of contacts, prescribed motion and closed loops
  s.effects = sim::kContacts;
  EXPECT_FALSE(cpu::steps_per_forward_dynamics(s, BackendKind::OpenMP, kT));
  s.effects = 0;
  s.prescribed.dofs = {0};
  EXPECT_FALSE(cpu::steps_per_forward_dynamics(s, BackendKind::OpenMP, kT));
  s.prescribed.dofs.clear();
  s.loops.loops.resize(1);
  ASSERT_FALSE(s.loops.empty());
  EXPECT_FALSE(cpu::steps_per_forward_dynamics(s, BackendKind::OpenMP, kT));
}

// max_i |x_i - ref_i| / max_i |ref_i| over q, and over qd, of all instances.
double relative_state_error(Simulator<double>& s, Simulator<double>& ref) {
  const std::size_t n = static_cast<std::size_t>(s.nv() * s.batch());
  std::vector<double> q(n), qd(n), rq(n), rqd(n);
  s.read_state(q.data(), qd.data());
  ref.read_state(rq.data(), rqd.data());
  double eq = 0, eqd = 0, sq = 0, sqd = 0;
  for (std::size_t k = 0; k < n; ++k) {
    eq = std::max(eq, std::abs(q[k] - rq[k]));
    eqd = std::max(eqd, std::abs(qd[k] - rqd[k]));
    sq = std::max(sq, std::abs(rq[k]));
    sqd = std::max(sqd, std::abs(rqd[k]));
  }
  return std::max(eq / sq, eqd / sqd);
}

// rope:5000 on openmp with 16 threads per instance steps through the parallel chain
// forward dynamics ("openmp-engine-parallel") and follows the serial ABA step: the
// same integrator formulas around a forward dynamics equal to rounding. Measured
// (double, the larger of max |dq| / max |q| and max |dqd| / max |qd|) for these
// scenes after 1, 3, 10 and 99 steps: euler 2.4e-13, 9.0e-14, 1.0e-13, 2.3e-13;
// rk4 7.5e-14, 4.1e-14, 4.4e-14, 1.2e-13; two instances as euler (with gravity and
// damping alone: at most 1.6e-12 over 100 steps). Bound: 1e-10. Two instances
// (with 32 threads) and external wrenches, constant (expanded per instance for the
// engine) and per step, go through the same path.
TEST(SimOpenMPChain, LongChainStepsThroughTheParallelChainForwardDynamics) {
#if !SCANDYN_HAS_OPENMP
  GTEST_SKIP() << "built without OpenMP";
#endif
  const int kT = kChainFdThreadsPerInstance;
  struct Case {
    const char* integrator;
    int instances;
    const char* external;
  };
  const Case cases[] = {{"euler", 1, ""},
                        {"rk4", 1, R"(, "external": {"wrenches": [{"link": "link_0100", "wrench": [0, 0, 0.01, 0, 0.5, 0]}], "per_step": true})"},
                        {"euler", 2, R"(, "external": {"wrenches": [{"link": "link_4999", "wrench": [0, 0, 0, 0.2, 0, 0]}]})"}};
  for (const Case& c : cases) {
    const Scene scene = scene_from(std::string(R"({"model": "rope:5000", "dt": 1e-5, "integrator": ")") + c.integrator +
                                   R"(", "instances": )" + std::to_string(c.instances) + R"(, "threads": )" +
                                   std::to_string(kT * c.instances) + R"(, "effects": {"gravity": true, "damping": 1e-6,
        "springs": {"stiffness": 1e-4}, "limits": {"stiffness": 10, "lower": -0.005, "upper": 0.005})" + c.external +
                                   R"(}, "initial": {"random": {"seed": 3, "q": 0.01, "qd": 0.1}}})");
    Simulator<double> engine(scene, BackendKind::OpenMP);
    Simulator<double> serial(scene, BackendKind::Serial);
    EXPECT_EQ(engine.strategy(), "openmp-engine-parallel") << c.integrator;
    EXPECT_EQ(serial.strategy(), "serial-aba");
    for (int s = 0; s < 3; ++s) {
      if (engine.wrenches()) engine.wrenches()[100].f.z += 0.1, serial.wrenches()[100].f.z += 0.1;
      engine.step();
      serial.step();
    }
    ASSERT_TRUE(engine.status().ok()) << sim::failure_message(engine.status());
    ASSERT_TRUE(serial.status().ok());
    EXPECT_LE(relative_state_error(engine, serial), 1e-10) << c.integrator << " B = " << c.instances;
    EXPECT_GT(std::abs(engine.qd().at(10, c.instances - 1)), 0.0);  // it moved
  }
  // implicit steps per instance (the chain forward dynamics takes no armature)
  const Scene implicit = scene_from(std::string(R"({"model": "rope:4096", "dt": 1e-5, "integrator": "implicit",
      "threads": )") + std::to_string(kT) + R"(, "effects": {"damping": 1e-6}})");
  EXPECT_EQ(Simulator<double>(implicit, BackendKind::OpenMP).strategy(), "openmp-aba");
  // fewer threads per instance: whole instances per thread
  const Scene few = scene_from(R"({"model": "rope:4096", "dt": 1e-5, "threads": 2, "effects": {"gravity": true}})");
  EXPECT_EQ(Simulator<double>(few, BackendKind::OpenMP).strategy(), "openmp-aba");
}

// A failed forward dynamics on the engine path: the instance keeps its state for
// the step and the status names it, as on the per-instance path.
TEST(SimOpenMPChain, EnginePathFailuresLeaveTheStateAlone) {
#if !SCANDYN_HAS_OPENMP
  GTEST_SKIP() << "built without OpenMP";
#endif
  const int kT = kChainFdThreadsPerInstance;
  for (const char* integrator : {"euler", "rk4"}) {
    const Scene scene = scene_from(std::string(R"({"model": "rope:4096", "dt": 1e-5, "integrator": ")") + integrator +
                                   R"(", "instances": 2, "threads": )" + std::to_string(2 * kT) +
                                   R"(, "effects": {"gravity": true}, "initial": {"q": 0.01}})");
    Simulator<double> sim(scene, BackendKind::OpenMP);
    ASSERT_EQ(sim.strategy(), "openmp-engine-parallel");
    sim.q().at(10, 1) = HUGE_VAL;  // instance 1's articulated inertias above link 10 are not finite
    sim.step();
    const BatchStatus st = sim.status();
    EXPECT_EQ(st.failed, 1) << integrator;
    EXPECT_EQ(st.first_instance, 1);
    EXPECT_GE(st.first_dof, 0);
    EXPECT_LT(st.first_dof, 10);
    EXPECT_EQ(st.failure, Failure::ArticulatedPivot);
    EXPECT_EQ(sim.q().at(10, 1), HUGE_VAL);  // instance 1 kept its state
    EXPECT_EQ(sim.qd().at(4095, 1), 0.0);
    EXPECT_EQ(sim.q().at(4095, 1), 0.01);
    EXPECT_NE(sim.qd().at(4095, 0), 0.0);  // instance 0 stepped
  }
}

TEST(Simulator, ResetRestoresAndRedraws) {
  const Scene scene = scene_from(R"({"model": "chain:2", "dt": 1e-3, "instances": 4,
      "effects": {"gravity": true}, "initial": {"q": [0.1, 0.2], "random": {"seed": 5, "q": 0.05, "qd": [0, 0.1]}}})");
  Simulator<double> sim(scene);
  // the initial draws are within the spreads and differ between instances
  for (Index b = 0; b < 4; ++b) {
    EXPECT_LE(std::abs(sim.q().at(0, b) - 0.1), 0.05);
    EXPECT_LE(std::abs(sim.q().at(1, b) - 0.2), 0.05);
    EXPECT_EQ(std::abs(sim.qd().at(0, b)), 0.0);
    EXPECT_LE(std::abs(sim.qd().at(1, b)), 0.1);
  }
  EXPECT_NE(sim.q().at(0, 0), sim.q().at(0, 1));
  const double q10 = sim.q().at(0, 1);
  for (int s = 0; s < 10; ++s) sim.step();
  const double q2 = sim.q().at(0, 2);
  sim.reset({1});
  EXPECT_LE(std::abs(sim.q().at(0, 1) - 0.1), 0.05);
  EXPECT_NE(sim.q().at(0, 1), q10);  // drawn again, not replayed
  EXPECT_EQ(sim.q().at(0, 2), q2);   // the others untouched
  EXPECT_THROW(sim.reset({4}), std::out_of_range);
  // the same seed replays the same first draws
  Simulator<double> again(scene);
  EXPECT_EQ(again.q().at(0, 1), q10);
}

TEST(Simulator, StateIsWrittenInPlaceAndTorquesAreUsed) {
  const Scene scene = scene_from(R"({"model": "chain:2", "dt": 1e-3, "instances": 2})");
  Simulator<double> sim(scene);
  sim.q().at(1, 1) = 0.3;  // a write through the view is the state
  std::vector<double> tau{0, 0, 0, 0.01};  // (nv x B): DoF 1 of instance 1
  sim.step(BatchView<const double>::soa(tau.data(), 2, 2));
  EXPECT_EQ(sim.q().at(1, 0), 0.0);
  EXPECT_NE(sim.qd().at(1, 1), 0.0);
  EXPECT_EQ(sim.qd().at(0, 0), 0.0);
  // reference: one semi-implicit Euler step with the serial ABA
  Data data(scene.model);
  const double q[2] = {0, 0.3}, qd[2] = {0, 0}, t[2] = {0, 0.01};
  double qdd[2];
  ASSERT_TRUE(aba(scene.model, data, q, qd, t, qdd).ok());
  EXPECT_EQ(sim.qd().at(0, 1), 1e-3 * qdd[0]);
  EXPECT_EQ(sim.qd().at(1, 1), 1e-3 * qdd[1]);
  EXPECT_EQ(sim.q().at(1, 1), 0.3 + 1e-3 * (1e-3 * qdd[1]));
  EXPECT_DOUBLE_EQ(sim.time(), 1e-3);
}

// ---- long rollouts (the stability suite's) ------------------------------------------

// 10^5 steps (10 s) of an undamped rope:100 in double with semi-implicit Euler:
// symplectic, so the energy error oscillates instead of drifting. Bounded relative
// to the swinging energy E(0) - E_rest; the second half of the run must not be
// worse than the first by more than a factor of 2 (no secular drift).
TEST(SimLongRollout, UndampedRope100For1e5StepsKeepsItsEnergy) {
  const Scene scene = scene_from(R"({"model": "rope:100", "dt": 1e-4, "integrator": "euler",
      "effects": {"gravity": true}, "initial": {"random": {"seed": 2, "q": 0.05}}})");
  Simulator<double> sim(scene);
  const std::vector<double> zero(scene.nv(), 0.0);
  const double rest = sim::mechanical_energy(scene.model, scene.effects, scene.joints.data(), zero.data(), zero.data());
  const double e0 = sim.energy()[0];
  ASSERT_GT(e0 - rest, 0.0);
  double first = 0, second = 0;
  for (int s = 0; s < 100000; ++s) {
    sim.step();
    if (s % 100 == 99) {
      const double err = std::abs(sim.energy()[0] - e0) / (e0 - rest);
      ASSERT_TRUE(std::isfinite(err)) << "step " << s;
      (s < 50000 ? first : second) = std::max(s < 50000 ? first : second, err);
    }
  }
  ASSERT_TRUE(sim.status().ok());
  // measured: 1.6e-2 in the first half, 1.2e-2 in the second
  EXPECT_LE(std::max(first, second), 5e-2);
  EXPECT_LE(second, 2 * first + 1e-12);
}

// A stiff spring scene with the implicit integrator over 10^5 steps: joint springs
// of 10^4 N m/rad on chain:6 at dt = 1e-2 (explicit Euler diverges there within a
// few steps, see ImplicitStaysBoundedWhereExplicitEulerDiverges); without gravity
// the implicit step only removes energy, so it never exceeds its start.
TEST(SimLongRollout, StiffSpringsImplicitFor1e5Steps) {
  const Scene scene = scene_from(R"({"model": "chain:6", "dt": 1e-2, "integrator": "implicit",
      "effects": {"springs": {"stiffness": 1e4, "rest": 0.1}, "damping": 0.01},
      "initial": {"random": {"seed": 4, "q": 0.5, "qd": 1.0}}})");
  Simulator<double> sim(scene);
  const double e0 = sim.energy()[0];
  double worst = 0;
  for (int s = 0; s < 100000; ++s) {
    sim.step();
    if (s % 100 == 99) worst = std::max(worst, sim.energy()[0] / e0);
  }
  ASSERT_TRUE(sim.status().ok());
  EXPECT_TRUE(std::isfinite(worst));
  EXPECT_LE(worst, 1 + 1e-12);
}

}  // namespace
}  // namespace scandyn

