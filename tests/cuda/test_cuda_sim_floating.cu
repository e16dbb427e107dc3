// The simulator's CUDA step with a floating base (sim_fused_floating_kernel:
// step_instance_at on the configuration manifold over aba_instance's floating-base
// kernel, the contact pass in the user's frames) against the serial simulator:
// rollouts of hyq on a floating base standing on a ground plane (gravity, damping,
// limits, contacts), a free random chain and a free rope tumbling in zero gravity
// with an external wrench, every integrator, float and double; resets of quaternion
// states. Tolerances relative to the largest |q|, |qd|: double 1e-9 (the same steps,
// FMA contraction apart; contacts 1e-7 over 50 steps, their stiff law amplifying
// rounding), float 1e-3 (2e-3 with contacts: the SFU's sin/cos and float rounding
// over the steps). The general step (ball joints, a free rope of 70 links) and atlas
// (the capacity-32 kernel) likewise.
#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <string>
#include <vector>

#include "cuda_test_util.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"

namespace scandyn {
namespace {

using sim::Integrator;
using sim::Scene;
using sim::Simulator;

Scene scene_from(const std::string& json) { return sim::parse_scene(json, "test.json"); }

// hyq on a floating base over a ground plane, its feet as contact points (as scenes/hyq_floating.json)
std::string hyq_scene(const std::string& integrator, int B) {
  return R"({"model": "hyq.urdf", "base": "floating", "dt": 1e-3, "integrator": ")" + integrator +
         R"(", "instances": )" + std::to_string(B) + R"(,
    "effects": {"gravity": true, "damping": 1.0, "limits": {"stiffness": 2000, "damping": 20},
      "contacts": {"planes": [{"normal": [0, 0, 1], "offset": 0.0}],
        "points": [{"link": "lf_lowerleg", "position": [0.33, 0, 0], "radius": 0.02},
                   {"link": "lh_lowerleg", "position": [0.33, 0, 0], "radius": 0.02},
                   {"link": "rf_lowerleg", "position": [0.33, 0, 0], "radius": 0.02},
                   {"link": "rh_lowerleg", "position": [0.33, 0, 0], "radius": 0.02}],
        "stiffness": 200000.0, "damping": 2000.0, "friction": 0.8}},
    "initial": {"q": [0, 0, 0.62, 0, 0, 0, 1, 0, 0.6, -1.2, 0, -0.6, 1.2, 0, 0.6, -1.2, 0, -0.6, 1.2],
      "random": {"seed": 2, "q": [0, 0, 0, 0, 0, 0, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1],
                 "qd": [0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1]}}})";
}

// a free chain in zero gravity, spinning, with a small wrench on its base and light joint
// damping and springs (rope:12's links are light and short: a 0.1 N force on its base, or
// damping 0.02, drives explicit euler at dt 1e-3 to overflow within 100 steps on every backend)
std::string free_scene(const std::string& model, const std::string& integrator, int B) {
  const std::string base_link = load_model(model).link_names[0];
  return R"({"model": ")" + model + R"(", "base": "floating", "dt": 1e-3, "integrator": ")" + integrator +
         R"(", "instances": )" + std::to_string(B) + R"(,
    "effects": {"damping": 1e-4, "springs": {"stiffness": 0.01},
      "external": {"wrenches": [{"link": ")" + base_link + R"(", "wrench": [2e-4, 0, 1e-4, 0, 1e-3, 0]}]}},
    "initial": {"random": {"seed": 5, "q": 0.3, "qd": 0.8}}})";
}

// max over entries of |x - ref| / max(1, max |ref|): q (nq rows) and qd (nv rows) of every instance
template <class S>
double state_error(Simulator<S>& s, Simulator<double>& ref) {
  const std::size_t nq = static_cast<std::size_t>(s.nq()) * s.batch(), nv = static_cast<std::size_t>(s.nv()) * s.batch();
  std::vector<S> q(nq), qd(nv);
  std::vector<double> rq(nq), rqd(nv);
  s.read_state(q.data(), qd.data());
  ref.read_state(rq.data(), rqd.data());
  double scale = 1, worst = 0;
  for (double x : rq) scale = std::max(scale, std::abs(x));
  for (double x : rqd) scale = std::max(scale, std::abs(x));
  for (std::size_t k = 0; k < nq; ++k) worst = std::max(worst, std::abs(double(q[k]) - rq[k]));
  for (std::size_t k = 0; k < nv; ++k) worst = std::max(worst, std::abs(double(qd[k]) - rqd[k]));
  for (std::size_t k = 0; k < nq; ++k)
    if (!std::isfinite(double(q[k]))) return INFINITY;
  return worst / scale;
}

template <class S>
double rollout_error(const Scene& scene, int steps, const std::string& strategy = "fused-aba") {
  Simulator<S> gpu(scene, BackendKind::Cuda);
  Simulator<double> cpu(scene, BackendKind::Serial);
  EXPECT_EQ(gpu.strategy(), strategy);
  for (int s = 0; s < steps; ++s) gpu.step(), cpu.step();
  EXPECT_TRUE(gpu.status().ok()) << sim::failure_message(gpu.status());
  EXPECT_TRUE(cpu.status().ok()) << sim::failure_message(cpu.status());
  return state_error(gpu, cpu);
}

class CudaSimFloating : public ::testing::Test {
 protected:
  void SetUp() override {
    const std::string why = test::no_device_reason();
    if (!why.empty()) GTEST_SKIP() << "no usable CUDA device: " << why;
  }
};

TEST_F(CudaSimFloating, RolloutsMatchSerial) {
  for (const char* integrator : {"euler", "rk4", "implicit"}) {
    SCOPED_TRACE(integrator);
    const Scene hyq = scene_from(hyq_scene(integrator, 64));
    EXPECT_LE(rollout_error<double>(hyq, 50), 1e-7) << "hyq";
    EXPECT_LE(rollout_error<float>(hyq, 50), 2e-3) << "hyq";
    for (const char* model : {"rope:12", "chain:10"}) {  // capacity 16 (what every build compiles)
      const Scene free = scene_from(free_scene(model, integrator, 40));
      EXPECT_LE(rollout_error<double>(free, 100), 1e-9) << model;
      EXPECT_LE(rollout_error<float>(free, 100), 1e-3) << model;
    }
  }
}

// atlas on a floating base standing on its feet (scenes/atlas_floating.json: gravity,
// damping, eight contact points on a ground plane): the fused kernel of capacity 32
// (builds with SCANDYN_SIM_EFFECT_SETS; others refuse the model by name).
TEST_F(CudaSimFloating, AtlasRolloutsMatchSerial) {
  Scene atlas = sim::load_scene(std::string(SCANDYN_SOURCE_DIR) + "/scenes/atlas_floating.json");
  atlas.instances = 32;
  try {
    Simulator<float> probe(atlas, BackendKind::Cuda);
  } catch (const BackendError& e) {
    GTEST_SKIP() << "this build leaves out the capacity-32 floating-base kernels: " << e.what();
  }
  // the scene's implicit integrator; rk4 in double (explicit euler is unstable under
  // the feet's stiff contacts at dt 1e-3, and float rk4 rollouts of them part after
  // a few steps on any two backends: the contacts amplify rounding)
  EXPECT_LE(rollout_error<double>(atlas, 50), 1e-7);
  EXPECT_LE(rollout_error<float>(atlas, 50), 2e-3);
  atlas.integrator = Integrator::Rk4;
  EXPECT_LE(rollout_error<double>(atlas, 50), 1e-7);
}

// A ball-joint rope (ballrope:8, spherical joints) hanging under gravity with its
// lower links on a plane (every link a contact sphere), and a free rope of 70 links
// (more bodies past the base than the fused kernels hold): the general step
// (sim_general_kernel: step_instance_at over aba_general, one thread per instance).
// (dt 1e-4: the rope's 1 cm links have inertias ~3e-7 kg m^2)
std::string ballrope_scene(const std::string& integrator, int B) {
  return R"({"model": "ballrope:8", "dt": 1e-4, "integrator": ")" + integrator + R"(", "instances": )" +
         std::to_string(B) + R"(,
    "effects": {"gravity": true, "damping": 1e-4,
      "contacts": {"planes": [{"normal": [0, 0, 1], "offset": -0.075}], "all_links": {"radius": 0.01},
                   "stiffness": 1000.0, "damping": 1.0, "friction": 0.5}},
    "initial": {"random": {"seed": 3, "q": 0.3, "qd": 0.5}}})";
}

TEST_F(CudaSimFloating, GeneralStepMatchesSerial) {
  for (const char* integrator : {"euler", "rk4", "implicit"}) {
    SCOPED_TRACE(integrator);
    const Scene ball = scene_from(ballrope_scene(integrator, 48));
    EXPECT_LE(rollout_error<double>(ball, 100, "general-aba"), 1e-7) << "ballrope:8";
    // float: the rope's M is ill-conditioned (1 cm links, inertias ~3e-7 kg m^2), so a
    // float rollout parts from double by up to a few % over these 100 steps on any
    // backend (measured 6e-2 euler, 9e-3 rk4, < 2e-3 implicit): the float general step
    // is checked to run without failures here and to the tolerance on rope:70 below
    EXPECT_TRUE(std::isfinite(rollout_error<float>(ball, 100, "general-aba"))) << "ballrope:8";
    const Scene free = scene_from(free_scene("rope:70", integrator, 24));
    EXPECT_LE(rollout_error<double>(free, 50, "general-aba"), 1e-9) << "rope:70";
    EXPECT_LE(rollout_error<float>(free, 50, "general-aba"), 1e-3) << "rope:70";
  }
  // contact readings: the same forces as the serial step's
  const Scene ball = scene_from(ballrope_scene("rk4", 8));
  Simulator<double> gpu(ball, BackendKind::Cuda), cpu(ball, BackendKind::Serial);
  for (int s = 0; s < 20; ++s) gpu.step(), cpu.step();
  const std::size_t P = static_cast<std::size_t>(ball.instances) * 8;  // B x 8 links
  std::vector<sim::ContactReading<double>> g(P), c(P);
  gpu.read_contact_forces(g.data());
  cpu.read_contact_forces(c.data());
  double scale = 1e-3, worst = 0;
  for (std::size_t k = 0; k < c.size(); ++k) scale = std::max(scale, std::abs(double(c[k].force.z)));
  for (std::size_t k = 0; k < c.size(); ++k) {
    worst = std::max(worst, std::abs(double(g[k].force.z - c[k].force.z)));
    EXPECT_EQ(g[k].in_contact, c[k].in_contact) << k;
  }
  EXPECT_LE(worst / scale, 1e-6);
}

// Resets write the scene's initial quaternion states on the device as on the host.
TEST_F(CudaSimFloating, ResetsMatchSerial) {
  const Scene scene = scene_from(free_scene("rope:12", "rk4", 16));
  Simulator<double> gpu(scene, BackendKind::Cuda), cpu(scene, BackendKind::Serial);
  for (int s = 0; s < 20; ++s) gpu.step(), cpu.step();
  const std::vector<Index> which = {0, 3, 15};
  gpu.reset(which);
  cpu.reset(which);
  for (int s = 0; s < 10; ++s) gpu.step(), cpu.step();
  EXPECT_LE(state_error(gpu, cpu), 1e-9);
}

}  // namespace
}  // namespace scandyn
