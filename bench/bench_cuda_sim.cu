// The simulator's step on the GPU (scandyn/sim/simulator.hpp, kernels/simulator_step.cu):
// the state resident on the device, one fused kernel per step (aba_instance +
// effects + integration, one thread per instance), or beyond 64 DoF the engine path.
//
// Rows (names as scripts/bench_results.py reads them: algo step, strategy
// <engine>:<integrator>:<effects>):
//   step_fused-aba:euler:gravity+damping/float/iiwa/cuda, B = 10^6 and 10^7: the RL
//       target row (iiwa, gravity + damping, float, semi-implicit Euler);
//   the same in double, and hyq (16-DoF kernels) in float;
//   step_fused-aba:<integrator>:<gravity|all-zero>/float/iiwa/cuda, B = 10^6: the
//       effects table: only gravity declared against every effect declared with
//       zero coefficients (same trajectory, the all-effects instantiation), per
//       integrator (implicit with only gravity runs as euler: nothing to treat
//       implicitly);
//   step_engine-parallel:euler:gravity/<precision>/rope:<n>/cuda: the path beyond
//       64 DoF for chains (effects kernel, CudaForwardDynamics' parallel chain
//       forward dynamics, integration kernel): rope:128 x 10^3 instances, the
//       hanging ropes rope:10^4 and rope:10^6 (one instance; the rope:10^6 step
//       target row);
//   step_engine-parallel:euler:gravity/<precision>/curtain:100:100/cuda: 100 ropes of
//       100 links from one base (chains from the base: the parallel chain forward
//       dynamics too);
//   step_engine-jsi_dense:euler:gravity/<precision>/tree:128:4/cuda, B = 10^3: the
//       same path for trees (the dense JSI);
//   the cost of contacts (sim_bench_util.hpp's contacts_json), each next to the same
//   scene without them: step_fused-aba:<euler|implicit>:gravity+damping[+contacts]/
//       float/<iiwa|hyq>/cuda, B = 10^6 (a plane, a point at every link origin: the
//       contacts kernel); step_engine-parallel:euler:gravity[+contacts]/float/
//       rope:10000/cuda, one rope on a plane and a sphere (the engine path's contact
//       kernel: one thread walks the rope).
// Each row checks that the simulator runs the engine its name says (else it is
// skipped with the strategy it got).
// Timing: CUDA events around `iterations` steps queued on the simulator's stream
// (manual time), so a row is the device's throughput with launch overhead, no
// host copies. Counters: links, instances, max_rel_err (q and qd after 10 steps
// against the double serial simulator on the first 64 instances), GBps (q, qd, tau
// read and q, qd written per step).
//
// Flags (before Google Benchmark's): --max-instances=N (default 10^7).
#include <benchmark/benchmark.h>
#include <cuda_runtime.h>

#include <cstdio>
#include <cstring>
#include <memory>
#include <string>

#include "scandyn/cuda/device.hpp"
#include "sim_bench_util.hpp"

namespace {

using namespace scandyn;

long long g_max_instances = 10000000;

template <class S>
void BM_CudaStep(benchmark::State& st, std::string engine, std::string model, std::string effects,
                 std::string integrator, long long instances, double dt) {
  if (instances > g_max_instances) {
    st.SkipWithError("beyond --max-instances");
    return;
  }
  const char* precision = sizeof(S) == 4 ? "float" : "double";
  std::unique_ptr<sim::Simulator<S>> s;
  double err = 0;
  try {
    const sim::Scene scene = bench::make_scene(model, effects, integrator, precision, "cuda", instances, dt);
    s = std::make_unique<sim::Simulator<S>>(scene);
    if (s->strategy() != engine) {  // Simulator::strategy(): the engine only
      st.SkipWithError(("the simulator runs " + s->strategy() + ", not " + engine).c_str());
      return;
    }
    err = bench::max_rel_err_after(*s, scene, 10, static_cast<Index>(std::min<long long>(instances, 64)));
  } catch (const std::exception& e) {
    st.SkipWithError(e.what());
    return;
  }
  const cudaStream_t stream = static_cast<cudaStream_t>(s->stream());
  cudaEvent_t start, stop;
  cudaEventCreate(&start);
  cudaEventCreate(&stop);
  s->step();
  s->synchronize();
  for (auto _ : st) {
    cudaEventRecord(start, stream);
    s->step();
    cudaEventRecord(stop, stream);
    cudaEventSynchronize(stop);
    float ms = 0;
    cudaEventElapsedTime(&ms, start, stop);
    st.SetIterationTime(ms * 1e-3);
  }
  cudaEventDestroy(start);
  cudaEventDestroy(stop);
  if (!s->status().ok()) st.SkipWithError(sim::failure_message(s->status()).c_str());
  st.counters["links"] = s->nv();
  st.counters["instances"] = static_cast<double>(instances);
  st.counters["max_rel_err"] = err;
  st.counters["GBps"] = benchmark::Counter(5.0 * s->nv() * sizeof(S) * static_cast<double>(instances) / 1e9,
                                           benchmark::Counter::kIsIterationInvariantRate);
}

template <class S>
void add(const std::string& strategy, const std::string& model, const std::string& effects, const std::string& integ,
         long long B, double dt = 1e-3) {
  const std::string name = "step_" + strategy + ":" + integ + ":" + effects + "/" + (sizeof(S) == 4 ? "float" : "double") +
                           "/" + model + "/cuda";
  benchmark::RegisterBenchmark(name.c_str(), BM_CudaStep<S>, strategy, model, effects, integ, B, dt)
      ->UseManualTime()
      ->Unit(benchmark::kMillisecond);
}

}  // namespace

int main(int argc, char** argv) {
  for (int k = 1; k < argc; ++k)
    if (std::strncmp(argv[k], "--max-instances=", 16) == 0) {
      g_max_instances = std::atoll(argv[k] + 16);
      for (int j = k; j + 1 < argc; ++j) argv[j] = argv[j + 1];
      --argc, --k;
    }
  const auto count = cuda::device_count();
  if (!count || count.value == 0) {
    std::fprintf(stderr, "bench_cuda_sim: no usable CUDA device: %s\n", count ? "0 devices" : count.error.c_str());
    return 0;
  }
  for (long long B : {1000000LL, 10000000LL}) {
    add<float>("fused-aba", "iiwa", "gravity+damping", "euler", B);
    add<double>("fused-aba", "iiwa", "gravity+damping", "euler", B);
  }
  add<float>("fused-aba", "hyq", "gravity+damping", "euler", 1000000LL);
  for (const char* integ : {"euler", "rk4", "implicit"})
    for (const char* effects : {"gravity", "all-zero"}) add<float>("fused-aba", "iiwa", effects, integ, 1000000LL);
  for (const char* model : {"iiwa", "hyq"})
    for (const char* integ : {"euler", "implicit"})
      for (const char* effects : {"gravity+damping", "gravity+damping+contacts"})
        add<float>("fused-aba", model, effects, integ, 1000000LL);
  for (const char* effects : {"gravity", "gravity+contacts"})
    add<float>("engine-parallel", "rope:10000", effects, "euler", 1LL, 1e-6);
  // The explicit step's dt limit on the bench's random initial state (0.3 rad,
  // 0.1 rad/s per joint): rope:128 at dt 1e-3 or 1e-4 gains energy until qd passes
  // 200 rad/s within 0.3 s and the forward dynamics meets non-finite pivots
  // (reported as a row error; the openmp ABA rollout grows the same way), at 2e-5 it
  // stays near 50 rad/s over 3000 steps. The ropes of 1 cm links use the dt of
  // scenes/rope_1e6.json.
  add<float>("engine-parallel", "rope:128", "gravity", "euler", 1000LL, 2e-5);
  add<double>("engine-parallel", "rope:128", "gravity", "euler", 1000LL, 2e-5);
  for (const char* rope : {"rope:10000", "rope:1000000"}) {
    add<float>("engine-parallel", rope, "gravity", "euler", 1LL, 1e-6);
    add<double>("engine-parallel", rope, "gravity", "euler", 1LL, 1e-6);
  }
  add<float>("engine-parallel", "curtain:100:100", "gravity", "euler", 1LL, 2e-5);  // as scenes/curtain.json
  add<double>("engine-parallel", "curtain:100:100", "gravity", "euler", 1LL, 2e-5);
  add<float>("engine-jsi_dense", "tree:128:4", "gravity", "euler", 1000LL);
  add<double>("engine-jsi_dense", "tree:128:4", "gravity", "euler", 1000LL);
  benchmark::Initialize(&argc, argv);
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
