// Tests of the contact effect on the simulator's CUDA backend (kernels/sim_fused.cuh,
// kernels/simulator_step.cu).
//
// Host part (runs in CI without a GPU): the fused kernel's composition with
// contacts, step_instance over fused_contact_forward_dynamics (the contact pass,
// then aba_instance) with capacity-sized arrays, on the host, against the serial
// Simulator, every integrator.
// Device part (skipped with the reason when no device is usable): rollouts of 200
// steps against the serial backend, states and contact readings, for the fused
// kernel (a chain and a tree touching a plane and a sphere, the point mass on a
// plane; every integrator) and the engine path beyond 64 DoF (rope:70 on a plane
// and a sphere; euler and rk4).
#include <gtest/gtest.h>

#include <cmath>
#include <string>
#include <type_traits>
#include <vector>

#include "cuda_test_util.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sim/simulator.hpp"
#include "../kernels/sim_fused.cuh"

namespace scandyn {
namespace {

using sim::Integrator;
using sim::Scene;
using sim::Simulator;

Scene scene_from(const std::string& json) { return sim::parse_scene(json, "test.json", SCANDYN_SOURCE_DIR "/models"); }

// A scene of model with contacts on every link origin (radius 0.01) and a point on
// its second link, against a plane and a sphere (obstacles: their JSON), starting
// from random states. The defaults suit chain:N and tree:N (standing along +z);
// ropes hang along -z.
//
// The rollout comparisons need scenes that the explicit integrators integrate
// stably: an unstable (or chattering) rollout amplifies the backends' rounding
// differences (FMA contraction on the device) without bound, and no tolerance then
// separates a wrong kernel from a right one. The regularised friction acts below the
// creep speed v_s as a viscous damper of gain mu f_n / v_s: with friction 0.7 and
// v_s = 1e-3 (the default) it is ~10^4 N s/m, far beyond euler's and rk4's stable
// dt at 1e-3 (on the serial backend alone, a 1e-15 change of the initial state
// moved chain:6 and tree:12:3 by 4e-2 after 200 steps). The law here (friction 0.3,
// v_s = 1 m/s) keeps that amplification near 10^2 (1e-12 -> 1e-10) for every
// integrator. Ropes (0.01 kg links, joint inertia ~1e-6 kg m^2) need the smaller
// joint damping, softer contacts and dt of rope_scene.
std::string contact_scene(const std::string& model, const std::string& integrator, int B,
                          const std::string& obstacles = R"("planes": [{"normal": [0, 0, 1], "offset": -0.3}],
                   "spheres": [{"center": [0.1, 0, 0.6], "radius": 0.15}])", double spread = 1.5,
                          const std::string& law = R"("stiffness": 1e4, "damping": 20, "friction": 0.3, "creep_speed": 1)",
                          const std::string& dt = "1e-3", const std::string& joint_damping = "0.01") {
  return R"({"model": ")" + model + R"(", "dt": )" + dt + R"(, "integrator": ")" + integrator + R"(", "instances": )" +
         std::to_string(B) + R"(, "effects": {"gravity": true, "damping": )" + joint_damping + R"(,
      "contacts": {)" + obstacles + R"(, "all_links": {"radius": 0.01},
                   "points": [{"link": ")" + make_generated(model).link_names[1] + R"(", "position": [0.1, 0, 0.2], "radius": 0.02}],
                   )" + law + R"(}},
      "initial": {"random": {"seed": 5, "q": )" + std::to_string(spread) + R"(, "qd": 1}}})";
}

// rope:N (N > 64: the engine path) touching a plane and a sphere. With the joint
// damping 0.01 of contact_scene, dt = 1e-3 is unstable for euler even without
// contacts (d dt / I ~ 10); this scene (joint damping 1e-5, k = 300 N/m, c = 0.1 N
// s/m, dt = 1e-4) integrates stably with euler and rk4 on the serial backend
// (a 1e-12 change of the initial state moves it by < 1e-10 in 200 steps), and
// its initial curl puts ~10 points on the obstacles.
std::string rope_scene(const std::string& model, const std::string& integrator, int B) {
  return contact_scene(model, integrator, B, R"("planes": [{"normal": [0, 0, 1], "offset": -0.3}],
        "spheres": [{"center": [0.05, 0, -0.15], "radius": 0.1}])", 0.2,
                       R"("stiffness": 300, "damping": 0.1, "friction": 0.3, "creep_speed": 1)", "1e-4", "1e-5");
}

// The point mass dropped on the plane while sliding.
std::string ball_scene(const std::string& integrator, int B) {
  return R"({"model": "point_mass.urdf", "dt": 1e-4, "integrator": ")" + integrator + R"(", "instances": )" +
         std::to_string(B) + R"(, "effects": {"gravity": true, "contacts": {"planes": [{"normal": [0, 0, 1]}],
      "points": [{"link": "ball", "radius": 0.1}], "stiffness": 1e4, "damping": 50, "friction": 0.5}},
      "initial": {"q": [0.12, 0, 0], "qd": [0, 0.3, 1], "random": {"seed": 2, "q": 0.01, "qd": 0.5}}})";
}

// ---- host: the fused kernel's composition ------------------------------------------------

// Bd: the bodies of the thread-per-instance model, the user's frames (Body) or the
// z-axis frames the fused kernels run on (ZJointBody: the contact points turned
// into them as kernels/simulator_step.cu does).
template <Integrator I, class Bd = Body<double>>
void check_host_composition(const std::string& model, const std::string& integrator) {
  // the plane z = 0.25 passes between the first link's origin (held at the base by
  // its joint about z: always pushed) and the second's
  const Scene scene = scene_from(contact_scene(model, integrator, 1, R"("planes": [{"normal": [0, 0, 1], "offset": 0.25}],
      "spheres": [{"center": [0.1, 0, 0.6], "radius": 0.15}])"));
  Simulator<double> ref(scene, BackendKind::Serial);
  const sim::SimSetup<double>& setup = ref.setup();
  const Index n = setup.model.nv();
  const cuda::ThreadModel<double, Bd> tm(setup.model);
  const auto& params = std::get<cuda::ThreadModelParams<double, 8, Bd>>(tm.params());
  sim::ContactSet<double> cs = setup.contact_set();
  std::vector<sim::ContactPoint<double>> points = setup.contact_points;
  if constexpr (!std::is_same_v<Bd, Body<double>>) {
    const ZAxisModel<double> zm = z_axis_model(setup.model);
    for (sim::ContactPoint<double>& cp : points) cp.position = zm.to_z_frame(cp.body, cp.position);
    cs.points = points.data();
  }
  constexpr unsigned E = sim::detail::kContactKernelSet;
  const std::vector<Force<double>> zero(static_cast<std::size_t>(n), Force<double>::zero());
  double q[8], qd[8], tau[8] = {}, tw[8], qdd[8], qs[8], qds[8], aq[8], aqd[8];
  std::vector<sim::JointCoefficients<double>> coef = setup.coef;
  sim::detail::FusedContactScratch<double, 8> cw;
  std::vector<sim::ContactReading<double>> readings(static_cast<std::size_t>(setup.contact_count()));
  for (Index i = 0; i < n; ++i) q[i] = ref.q().at(i, 0), qd[i] = ref.qd().at(i, 0);
  int touching = 0;
  for (int s = 0; s < 200; ++s) {
    sim::ContactReading<double>* r = readings.data();
    auto fd = [&](const double* qa, const double* qda, const double* t, const double* arm, double* out) -> Index {
      return sim::detail::fused_contact_forward_dynamics<double, 8, 8>(params, setup.dt, cs, zero.data(), cw, r, qa,
                                                                      qda, t, arm, out);
    };
    const sim::StepScratch<double> w{tw, qdd, qs, qds, aq, aqd};
    ASSERT_EQ((sim::step_instance<E, I, 8>(n, setup.dt, coef.data(),
                                          setup.armature.empty() ? nullptr : setup.armature.data(), q, qd, tau, w, fd)),
              -1);
    ref.step();
    for (const auto& x : readings) touching += x.in_contact;
  }
  EXPECT_GT(touching, 0) << model << " " << integrator;
  std::vector<sim::ContactReading<double>> expect(readings.size());
  ref.read_contact_forces(expect.data());
  for (std::size_t k = 0; k < readings.size(); ++k) {
    EXPECT_NEAR(readings[k].force.z, expect[k].force.z, 1e-8 * (1 + std::abs(expect[k].force.z))) << model << " " << k;
    EXPECT_EQ(readings[k].in_contact, expect[k].in_contact) << model << " " << k;
  }
  for (Index i = 0; i < n; ++i) {  // the same steps in the same order: rounding (contraction) apart
    EXPECT_NEAR(q[i], ref.q().at(i, 0), 1e-9) << model << " " << integrator << " DoF " << i;
    EXPECT_NEAR(qd[i], ref.qd().at(i, 0), 1e-8) << model << " " << integrator << " DoF " << i;
  }
}

TEST(CudaContactsHost, FusedCompositionMatchesTheSerialSimulator) {
  check_host_composition<Integrator::Euler>("chain:6", "euler");
  check_host_composition<Integrator::Rk4>("chain:6", "rk4");
  check_host_composition<Integrator::Implicit>("chain:6", "implicit");
  check_host_composition<Integrator::Euler>("tree:8:3", "euler");
  check_host_composition<Integrator::Implicit>("tree:8:3", "implicit");
  // the z-axis frames of the fused kernels (tree:8:3: every axis slanted, all turned)
  check_host_composition<Integrator::Euler, ZJointBody<double>>("chain:6", "euler");
  check_host_composition<Integrator::Euler, ZJointBody<double>>("tree:8:3", "euler");
  check_host_composition<Integrator::Rk4, ZJointBody<double>>("tree:8:3", "rk4");
  check_host_composition<Integrator::Implicit, ZJointBody<double>>("tree:8:3", "implicit");
}

// ---- device ---------------------------------------------------------------------------------

class CudaContacts : public ::testing::Test {
 protected:
  void SetUp() override {
    const std::string why = test::no_device_reason();
    if (!why.empty()) GTEST_SKIP() << "no usable CUDA device: " << why;
  }
};

// max relative state error and max contact-force error (relative to the largest
// force) of a CUDA rollout against the serial double one, after `steps` steps
template <class S>
std::pair<double, double> rollout_error(const Scene& scene, int steps) {
  Simulator<S> gpu(scene, BackendKind::Cuda);
  Simulator<double> cpu(scene, BackendKind::Serial);
  for (int s = 0; s < steps; ++s) gpu.step(), cpu.step();
  EXPECT_TRUE(cpu.status().ok()) << "the serial reference: " << sim::failure_message(cpu.status());
  EXPECT_TRUE(gpu.status().ok()) << sim::failure_message(gpu.status());
  const std::size_t n = static_cast<std::size_t>(gpu.nv()) * gpu.batch();
  std::vector<S> q(n), qd(n);
  std::vector<double> rq(n), rqd(n);
  gpu.read_state(q.data(), qd.data());
  cpu.read_state(rq.data(), rqd.data());
  double scale = 1, worst = 0;
  for (std::size_t k = 0; k < n; ++k) scale = std::max({scale, std::abs(rq[k]), std::abs(rqd[k])});
  for (std::size_t k = 0; k < n; ++k)
    worst = std::max({worst, std::abs(double(q[k]) - rq[k]), std::abs(double(qd[k]) - rqd[k])});
  const std::size_t P = static_cast<std::size_t>(gpu.batch() * gpu.contact_count());
  std::vector<sim::ContactReading<S>> r(P);
  std::vector<sim::ContactReading<double>> rr(P);
  gpu.read_contact_forces(r.data());
  cpu.read_contact_forces(rr.data());
  double fscale = 1, ferr = 0;
  int touching = 0;
  for (std::size_t k = 0; k < P; ++k) {
    fscale = std::max(fscale, std::abs(rr[k].force.z));
    ferr = std::max({ferr, std::abs(double(r[k].force.x) - rr[k].force.x), std::abs(double(r[k].force.z) - rr[k].force.z)});
    touching += rr[k].in_contact;
  }
  EXPECT_GT(touching, 0);
  return {worst / scale, ferr / fscale};
}

// The fused kernel (up to 64 DoF): within 1e-8 in double (the same steps, FMA
// contraction apart; contacts switch on and off, which amplifies rounding less
// than the 200 steps' dynamics), 2e-2 in float (float rounding through stiff
// contacts), states and forces.
TEST_F(CudaContacts, FusedRolloutsMatchSerial) {
  for (const char* integrator : {"euler", "rk4", "implicit"}) {
    for (const char* model : {"chain:6", "tree:12:3"}) {
      const Scene scene = scene_from(contact_scene(model, integrator, 300));
      const auto d = rollout_error<double>(scene, 200);
      EXPECT_LE(d.first, 1e-8) << model << " " << integrator;
      EXPECT_LE(d.second, 1e-8) << model << " " << integrator;
      const auto f = rollout_error<float>(scene, 200);
      EXPECT_LE(f.first, 2e-2) << model << " " << integrator;
    }
    const auto b = rollout_error<double>(scene_from(ball_scene(integrator, 257)), 2000);
    EXPECT_LE(b.first, 1e-9) << integrator;
    EXPECT_LE(b.second, 1e-9) << integrator;
  }
}

// Beyond 64 DoF: the engine path with the contact kernel (euler, rk4).
TEST_F(CudaContacts, EnginePathBeyond64Dof) {
  for (const char* integrator : {"euler", "rk4"}) {
    const Scene scene = scene_from(rope_scene("rope:70", integrator, 3));
    const auto d = rollout_error<double>(scene, 200);
    EXPECT_LE(d.first, 1e-8) << integrator;
    EXPECT_LE(d.second, 1e-8) << integrator;
  }
}

}  // namespace
}  // namespace scandyn
