// Tests of the simulator's CUDA backend (kernels/simulator_step.cu, kernels/sim_fused.cuh).
//
// Host part (runs in CI without a GPU): the fused kernel's per-thread composition,
// step_instance over fused_forward_dynamics (aba_instance) with capacity-sized
// arrays, executed on the host, against the serial Simulator (step_instance over
// the reference aba).
// Device part (skipped with the reason when no device is usable): CUDA rollouts of
// 100 steps against the serial backend, for the fused kernels (capacities 8, 16, 64;
// every integrator; the float capacity-8 per-set kernels and the all-effects
// kernels) and the engine path beyond 64 DoF; resets and in-place state on the
// device; failures reported.
#include <gtest/gtest.h>

#include <cmath>
#include <string>
#include <vector>

#include "cuda_test_util.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sim/simulator.hpp"
#include "../kernels/sim_fused.cuh"

namespace scandyn {
namespace {

using sim::Integrator;
using sim::Scene;
using sim::Simulator;

Scene scene_from(const std::string& json) { return sim::parse_scene(json, "test.json"); }

std::string scene_json(const std::string& model, const std::string& integrator, const std::string& effects, int B) {
  return R"({"model": ")" + model + R"(", "dt": 1e-3, "integrator": ")" + integrator + R"(", "instances": )" +
         std::to_string(B) + R"(, "effects": )" + effects + R"(, "initial": {"random": {"seed": 11, "q": 0.4, "qd": 0.5}}})";
}

const char* const kAllEffects = R"({"gravity": true, "damping": 0.05, "springs": {"stiffness": 0.5, "rest": 0.1},
    "limits": {"stiffness": 200, "damping": 1, "lower": -0.3, "upper": 0.3},
    "external": {"wrenches": [{"link": "link_1", "wrench": [0.01, 0, 0, 0, 0.2, 0]}]}})";

// max over entries of |x - ref| / max(1, max |ref|), the state of all instances
template <class S>
double state_error(Simulator<S>& s, Simulator<double>& ref) {
  const std::size_t n = static_cast<std::size_t>(s.nv()) * s.batch();
  std::vector<S> q(n), qd(n);
  std::vector<double> rq(n), rqd(n);
  s.read_state(q.data(), qd.data());
  ref.read_state(rq.data(), rqd.data());
  double scale = 1, worst = 0;
  for (std::size_t k = 0; k < n; ++k) scale = std::max({scale, std::abs(rq[k]), std::abs(rqd[k])});
  for (std::size_t k = 0; k < n; ++k) {
    const double e = std::max(std::abs(double(q[k]) - rq[k]), std::abs(double(qd[k]) - rqd[k]));
    if (std::isnan(e)) return e;
    worst = std::max(worst, e);
  }
  return worst / scale;
}

// ---- host: the fused kernel's composition ------------------------------------------------

// One step of one instance as sim_fused_kernel runs it, on the host.
template <unsigned E, Integrator I, int kSlots, class S, int C, class Bd>
Index fused_step_on_host(const cuda::ThreadModelParams<S, C, Bd>& model, const sim::SimSetup<S>& setup, S* q, S* qd,
                         const S* tau) {
  S tw[C], qdd[C], qs[C], qds[C], aq[C], aqd[C];
  const Force<S>* fext = (E & sim::kExternal) ? setup.wrenches.data() : nullptr;
  auto fd = [&](const S* qa, const S* qda, const S* t, const S* arm, S* out) -> Index {
    return sim::detail::fused_forward_dynamics<S, C, kSlots>(model, fext, qa, qda, t, arm, out);
  };
  const sim::StepScratch<S> w{tw, qdd, qs, qds, aq, aqd};
  return sim::step_instance<E, I, C>(setup.model.nv(), setup.dt, setup.coef.data(),
                                     setup.armature.empty() ? nullptr : setup.armature.data(), q, qd, tau, w, fd);
}

// kSlots: 0 (the chain kernels; models without branch children) or 8 (any model).
// Bd: the user's frames (Body) or the z-axis frames the fused kernels run on.
template <Integrator I, int kSlots, class Bd = Body<double>>
void check_host_composition(const std::string& model, const std::string& integrator) {
  constexpr unsigned E = sim::kAllEffects & ~sim::kContacts;
  const Scene scene = scene_from(scene_json(model, integrator, kAllEffects, 1));
  Simulator<double> ref(scene, BackendKind::Serial);
  const sim::SimSetup<double>& setup = ref.setup();
  const Index n = setup.model.nv();
  const cuda::ThreadModel<double, Bd> tm(setup.model);
  ASSERT_TRUE(kSlots == 8 || tm.branch_slots() == 0) << model;
  const auto& params = std::get<cuda::ThreadModelParams<double, 8, Bd>>(tm.params());
  double q[8], qd[8], tau[8] = {};
  for (Index i = 0; i < n; ++i) q[i] = ref.q().at(i, 0), qd[i] = ref.qd().at(i, 0);
  for (int s = 0; s < 100; ++s) {
    ASSERT_EQ((fused_step_on_host<E, I, kSlots>(params, setup, q, qd, tau)), -1);
    ref.step();
  }
  for (Index i = 0; i < n; ++i) {  // the same ABA steps in the same order: rounding (contraction) apart
    EXPECT_NEAR(q[i], ref.q().at(i, 0), 1e-11) << model << " " << integrator << " DoF " << i;
    EXPECT_NEAR(qd[i], ref.qd().at(i, 0), 1e-10) << model << " " << integrator << " DoF " << i;
  }
}

TEST(CudaSimHost, FusedCompositionMatchesTheSerialSimulator) {
  check_host_composition<Integrator::Euler, 0>("chain:6", "euler");
  check_host_composition<Integrator::Rk4, 0>("chain:6", "rk4");
  check_host_composition<Integrator::Implicit, 0>("chain:6", "implicit");
  check_host_composition<Integrator::Euler, 8>("tree:8:3", "euler");
  check_host_composition<Integrator::Rk4, 8>("tree:8:3", "rk4");
  check_host_composition<Integrator::Implicit, 8>("tree:8:3", "implicit");
  // the z-axis frames of the fused kernels (tree:8:3: every joint frame turned)
  check_host_composition<Integrator::Euler, 0, ZJointBody<double>>("chain:6", "euler");
  check_host_composition<Integrator::Implicit, 0, ZJointBody<double>>("chain:6", "implicit");
  check_host_composition<Integrator::Euler, 8, ZJointBody<double>>("tree:8:3", "euler");
  check_host_composition<Integrator::Rk4, 8, ZJointBody<double>>("tree:8:3", "rk4");
  check_host_composition<Integrator::Implicit, 8, ZJointBody<double>>("tree:8:3", "implicit");
}

// ---- device ---------------------------------------------------------------------------------

class CudaSim : public ::testing::Test {
 protected:
  void SetUp() override {
    const std::string why = test::no_device_reason();
    if (!why.empty()) GTEST_SKIP() << "no usable CUDA device: " << why;
  }
};

template <class S>
double rollout_error(const Scene& scene, int steps) {
  Simulator<S> gpu(scene, BackendKind::Cuda);
  Simulator<double> cpu(scene, BackendKind::Serial);
  for (int s = 0; s < steps; ++s) gpu.step(), cpu.step();
  EXPECT_TRUE(gpu.status().ok()) << sim::failure_message(gpu.status());
  return state_error(gpu, cpu);
}

// Rollouts of 100 steps agree with the serial double backend: within 1e-9 (double:
// the same ABA, FMA contraction apart; beyond 64 DoF the engine's forward
// dynamics) and 1e-3 (float: 100 steps of float rounding, the SFU's sin/cos in the
// fused kernels), relative to the largest |q|, |qd|. (With the joint-space inertia
// in the fused kernel, chain:40 in float was 5e-2 off: the reason it runs the ABA.)
TEST_F(CudaSim, RolloutsMatchSerialFor100Steps) {
  for (const char* model : {"chain:7", "tree:12:3", "chain:40"})
    for (const char* integrator : {"euler", "rk4", "implicit"})
      for (const char* effects_in : {R"({"gravity": true, "damping": 0.05})", kAllEffects}) {
        // the wrench on the model's first moving link (generated names are zero-padded)
        std::string effects = effects_in;
        const std::size_t at = effects.find("link_1");
        if (at != std::string::npos) effects.replace(at, 6, make_generated(model).link_names[0]);
        const Scene scene = scene_from(scene_json(model, integrator, effects, 300));
        EXPECT_LE(rollout_error<double>(scene, 100), 1e-9) << model << " " << integrator << " " << effects;
        EXPECT_LE(rollout_error<float>(scene, 100), 1e-3) << model << " " << integrator << " " << effects;
      }
}

// Every compiled effect set of the float capacity-8 kernels (16 per integrator).
TEST_F(CudaSim, EveryEffectSetOfTheFloatKernels) {
  const char* parts[] = {R"("damping": 0.05)", R"("springs": {"stiffness": 0.5})",
                         R"("limits": {"stiffness": 200, "lower": -0.3, "upper": 0.3})",
                         R"("external": {"wrenches": [{"link": "link_1", "wrench": [0, 0, 0, 0, 0.2, 0]}]})"};
  for (unsigned set = 0; set < 16; ++set)
    for (const char* integrator : {"euler", "rk4", "implicit"}) {
      std::string effects = R"({"gravity": true)";
      for (int k = 0; k < 4; ++k)
        if (set & (1u << k)) effects += std::string(", ") + parts[k];
      effects += "}";
      const Scene scene = scene_from(scene_json("chain:5", integrator, effects, 65));
      EXPECT_LE(rollout_error<float>(scene, 100), 1e-3) << integrator << " " << effects;
    }
}

// Beyond 64 DoF: the engine path (euler, rk4); implicit is refused there.
TEST_F(CudaSim, EnginePathBeyond64Dof) {
  for (const char* integrator : {"euler", "rk4"}) {
    const Scene scene = scene_from(scene_json("rope:70", integrator, R"({"gravity": true, "damping": 1e-5})", 3));
    EXPECT_LE(rollout_error<double>(scene, 100), 1e-9) << integrator;
  }
  const Scene implicit = scene_from(scene_json("rope:70", "implicit", R"({"damping": 1e-5})", 1));
  EXPECT_THROW(Simulator<double>(implicit, BackendKind::Cuda), BackendError);
}

// The state is device memory, written in place; resets reach the device; torques
// are a device view.
TEST_F(CudaSim, DeviceStateResetsAndTorques) {
  const Scene scene = scene_from(scene_json("chain:3", "euler", R"({"gravity": true})", 4));
  Simulator<double> gpu(scene, BackendKind::Cuda);
  Simulator<double> cpu(scene, BackendKind::Serial);
  ASSERT_TRUE(gpu.on_device());
  cudaPointerAttributes attr;
  ASSERT_EQ(cudaPointerGetAttributes(&attr, gpu.q().data), cudaSuccess);
  EXPECT_EQ(attr.type, cudaMemoryTypeDevice);
  std::vector<double> tau(3 * 4, 0.0);
  tau[2 * 4 + 3] = 0.05;  // DoF 2 of instance 3
  test::DeviceArray<double> dtau;
  ASSERT_EQ(dtau.alloc(tau.size()), cudaSuccess);
  ASSERT_EQ(cudaMemcpy(dtau.ptr, tau.data(), tau.size() * sizeof(double), cudaMemcpyHostToDevice), cudaSuccess);
  for (int s = 0; s < 20; ++s) {
    gpu.step(BatchView<const double>::soa(dtau.ptr, 3, 4));
    cpu.step(BatchView<const double>::soa(tau.data(), 3, 4));
  }
  EXPECT_LE(state_error(gpu, cpu), 1e-10);
  gpu.reset({1, 3});
  cpu.reset({1, 3});
  EXPECT_LE(state_error(gpu, cpu), 1e-10);  // reset instances: the same draws, copied; others as before
  const double one = 0.25;
  ASSERT_EQ(cudaMemcpy(&gpu.q().at(0, 2), &one, sizeof one, cudaMemcpyHostToDevice), cudaSuccess);
  cpu.q().at(0, 2) = one;
  gpu.step(), cpu.step();
  EXPECT_LE(state_error(gpu, cpu), 1e-10);
}

// A failed instance-step is recorded as on the CPU (a BatchStatus: count, lowest
// instance, the DoF where its ABA stopped, the pivot) and leaves the state alone,
// in the fused kernel and on the engine path (euler and rk4).
TEST_F(CudaSim, FailuresAreReportedAndLeaveTheStateAlone) {
  const double inf = HUGE_VAL;
  for (const char* model : {"chain:3", "rope:70"})
    for (const char* integrator : {"euler", "rk4"}) {
      const Scene scene = scene_from(std::string(R"({"model": ")") + model + R"(", "dt": 1e-3, "instances": 5,
          "integrator": ")" + integrator + R"(", "effects": {"gravity": true}, "initial": {"q": 0.2}})");
      const Index n = scene.nv();
      Simulator<double> gpu(scene, BackendKind::Cuda);
      Simulator<double> cpu(scene, BackendKind::Serial);
      ASSERT_EQ(cudaMemcpy(&gpu.q().at(1, 3), &inf, sizeof inf, cudaMemcpyHostToDevice), cudaSuccess);
      ASSERT_EQ(cudaMemcpy(&gpu.q().at(1, 4), &inf, sizeof inf, cudaMemcpyHostToDevice), cudaSuccess);
      cpu.q().at(1, 3) = inf;
      cpu.q().at(1, 4) = inf;
      gpu.step(), cpu.step();
      gpu.step(), cpu.step();
      const BatchStatus st = gpu.status();
      const BatchStatus ref = cpu.status();
      EXPECT_EQ(st.failed, 4) << model << " " << integrator;  // instances 3 and 4, two steps
      EXPECT_EQ(st.first_instance, 3);
      EXPECT_EQ(st.failure, Failure::ArticulatedPivot);  // the fused ABA, the engine's parallel chain FD
      if (n <= cuda::kMaxThreadDofs) EXPECT_EQ(st.first_dof, ref.first_dof);  // the same ABA
      else EXPECT_LE(st.first_dof, 1);  // the chain FD names the lowest failed link
      EXPECT_EQ(ref.failed, 4);
      std::vector<double> q(n * 5), qd(n * 5);
      gpu.read_state(q.data(), qd.data());
      EXPECT_EQ(q[1 * 5 + 3], inf);
      EXPECT_EQ(qd[0 * 5 + 3], 0.0);  // instance 3 kept its state: at rest
      EXPECT_NE(qd[(n - 1) * 5 + 2], 0.0);  // instance 2 stepped
      EXPECT_NE(sim::failure_message(st).find("4 instance-steps, first in instance 3: articulated inertia pivot"),
                std::string::npos) << sim::failure_message(st);
      gpu.clear_status();
      EXPECT_TRUE(gpu.status().ok());
    }
}

// A step that leaves an instance's state non-finite (damping 1e300 on a joint moving
// at 1e300 rad/s, euler) is recorded as on the CPU: Failure::NonFinite, the instance
// and a DoF, the state kept as computed; on the fused kernel and the engine path.
TEST_F(CudaSim, NonFiniteStateIsRecorded) {
  const double huge = 1e300;
  for (const char* model : {"chain:3", "rope:70"})
    for (const char* integrator : {"euler", "rk4"}) {
      const Scene scene = scene_from(std::string(R"({"model": ")") + model + R"(", "dt": 1e-3, "instances": 3,
          "integrator": ")" + integrator + R"(", "effects": {"damping": 1e300}})");
      const Index n = scene.nv();
      Simulator<double> gpu(scene, BackendKind::Cuda);
      Simulator<double> cpu(scene, BackendKind::Serial);
      ASSERT_EQ(cudaMemcpy(&gpu.qd().at(0, 1), &huge, sizeof huge, cudaMemcpyHostToDevice), cudaSuccess);
      cpu.qd().at(0, 1) = huge;
      gpu.step(), cpu.step();
      const BatchStatus st = gpu.status(), ref = cpu.status();
      // euler's update overflows (NonFinite); rk4's stages overflow first and its
      // forward dynamics fails there (a pivot: the state is kept), as on the CPU
      EXPECT_NE(ref.failure, Failure::None) << model << " " << integrator;
      EXPECT_EQ(st.failure, ref.failure) << model << " " << integrator;
      EXPECT_EQ(st.failed, ref.failed);
      EXPECT_EQ(st.first_instance, 1);
      EXPECT_GE(st.first_dof, 0);
      EXPECT_LT(st.first_dof, n);
      std::vector<double> q(n * 3), qd(n * 3);
      gpu.read_state(q.data(), qd.data());
      for (Index i = 0; i < n; ++i) EXPECT_TRUE(std::isfinite(qd[i * 3 + 0]) && std::isfinite(q[i * 3 + 2]));
      if (ref.failure == Failure::NonFinite) {
        EXPECT_FALSE(std::isfinite(qd[0 * 3 + 1]));  // kept as computed
        EXPECT_EQ(sim::failure_message(st).rfind("the state became non-finite in ", 0), 0u) << sim::failure_message(st);
      }
    }
}

}  // namespace
}  // namespace scandyn
