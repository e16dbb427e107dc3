// The simulator's step on the CPU backends (scandyn/sim/simulator.hpp).
//
// Rows (names as scripts/bench_results.py reads them: algo step, strategy
// <engine>:<integrator>:<effects>):
//   step_<serial|openmp>-aba:euler:gravity+damping/<precision>/iiwa/<backend>
//       the RL row, B = 10^3 .. 10^5 instances;
//   step_openmp-aba:<integrator>:<gravity|all-zero>/float/iiwa/openmp, B = 10^4:
//       the effects table: only gravity declared against every effect declared with
//       zero coefficients (the same trajectory), per integrator (the name gives the
//       integrator asked for: implicit with gravity alone runs as euler);
//   step_serial-aba:euler:gravity/double/rope:N/serial, one rope of 10^3 .. 10^6
//       links;
//   the cost of contacts (sim_bench_util.hpp's contacts_json: a point at every link
//   origin, a plane for robots, a plane and a sphere for ropes), each next to the
//   same scene without them:
//   step_openmp-aba:<integrator>:gravity+damping[+contacts]/float/iiwa/openmp, B = 10^4,
//   step_serial-aba:<integrator>:gravity[+contacts]/double/rope:10000/serial, one rope
//       (euler, and implicit: the contacts' diagonal on the armature).
//   the floating base (scene files, on the configuration manifold):
//   step_<serial|openmp>-aba:implicit:<effects>/float/hyq_floating/<backend>, B = 10^4
//       (scenes/hyq_floating.json: gravity, damping, limits, four foot contacts), and
//       atlas_floating.json the same; step_serial-aba:rk4:none/double/
//       rope_free_1000|ballrope_1000/serial, one free rope tumbling;
// One iteration = one step of all B instances; evals_per_second = instance-steps/s.
// Counters: links, instances, max_rel_err (q and qd after 10 steps against the
// double serial simulator, first 64 instances).
#include <benchmark/benchmark.h>

#include <memory>
#include <string>

#include "sim_bench_util.hpp"

namespace {

using namespace scandyn;

// Times the steps of the simulator made by make() (a scene and its Simulator<S>),
// after its error against the double serial simulator over 10 steps (max_rel_err);
// links counts the model's bodies.
template <class S, class Make>
void time_steps(benchmark::State& st, long long instances, Make&& make) {
  std::unique_ptr<sim::Simulator<S>> s;
  double err = 0;
  try {
    const sim::Scene scene = make();
    s = std::make_unique<sim::Simulator<S>>(scene, scene.backend);
    err = bench::max_rel_err_after(*s, scene, 10, static_cast<Index>(std::min<long long>(instances, 64)));
  } catch (const std::exception& e) {
    st.SkipWithError(e.what());
    return;
  }
  for (auto _ : st) s->step();
  if (!s->status().ok()) st.SkipWithError(sim::failure_message(s->status()).c_str());
  st.counters["links"] = static_cast<double>(s->setup().model.nbodies());
  st.counters["instances"] = static_cast<double>(instances);
  st.counters["max_rel_err"] = err;
  st.counters["instance_steps_per_second"] =
      benchmark::Counter(static_cast<double>(instances), benchmark::Counter::kIsIterationInvariantRate);
}

template <class S>
void BM_Step(benchmark::State& st, std::string model, std::string effects, std::string integrator, const char* backend,
             long long instances, double dt) {
  const char* precision = sizeof(S) == 4 ? "float" : "double";
  time_steps<S>(st, instances, [&] { return bench::make_scene(model, effects, integrator, precision, backend, instances, dt); });
}

// A shipped scene (scenes/NAME.json) with its instances and backend replaced.
template <class S>
void BM_SceneStep(benchmark::State& st, std::string name, const char* backend, long long instances) {
  time_steps<S>(st, instances, [&] {
    sim::Scene scene = sim::load_scene(std::string(SCANDYN_SOURCE_DIR) + "/scenes/" + name + ".json");
    scene.instances = static_cast<Index>(instances);
    scene.backend = std::string(backend) == "openmp" ? BackendKind::OpenMP : BackendKind::Serial;
    return scene;
  });
}

void register_all() {
  for (const char* backend : {"serial", "openmp"})
    for (long long B : {1000LL, 10000LL, 100000LL}) {
      const std::string tail = std::string("/iiwa/") + backend;
      benchmark::RegisterBenchmark((std::string("step_") + backend + "-aba:euler:gravity+damping/float" + tail).c_str(),
                                   BM_Step<float>, "iiwa", "gravity+damping", "euler", backend, B, 1e-3)
          ->Unit(benchmark::kMillisecond)->UseRealTime();
      benchmark::RegisterBenchmark((std::string("step_") + backend + "-aba:euler:gravity+damping/double" + tail).c_str(),
                                   BM_Step<double>, "iiwa", "gravity+damping", "euler", backend, B, 1e-3)
          ->Unit(benchmark::kMillisecond)->UseRealTime();
    }
  for (const char* integrator : {"euler", "rk4", "implicit"})
    for (const char* effects : {"gravity", "all-zero"})
      benchmark::RegisterBenchmark(
          (std::string("step_openmp-aba:") + integrator + ":" + effects + "/float/iiwa/openmp").c_str(),
          BM_Step<float>, "iiwa", effects, integrator, "openmp", 10000LL, 1e-3)
          ->Unit(benchmark::kMillisecond)->UseRealTime();
  for (const char* integrator : {"euler", "implicit"})
    for (const char* effects : {"gravity+damping", "gravity+damping+contacts"})
      benchmark::RegisterBenchmark(
          (std::string("step_openmp-aba:") + integrator + ":" + effects + "/float/iiwa/openmp").c_str(),
          BM_Step<float>, "iiwa", effects, integrator, "openmp", 10000LL, 1e-3)
          ->Unit(benchmark::kMillisecond)->UseRealTime();
  for (const char* integrator : {"euler", "implicit"})
    for (const char* effects : {"gravity", "gravity+contacts"})
      benchmark::RegisterBenchmark(
          (std::string("step_serial-aba:") + integrator + ":" + effects + "/double/rope:10000/serial").c_str(),
          BM_Step<double>, "rope:10000", effects, integrator, "serial", 1LL, 1e-5)
          ->Unit(benchmark::kMillisecond)->UseRealTime()->MinTime(0.2);
  for (const char* backend : {"serial", "openmp"}) {
    benchmark::RegisterBenchmark(
        (std::string("step_") + backend + "-aba:implicit:gravity+damping+limits+contacts/float/hyq_floating/" + backend).c_str(),
        BM_SceneStep<float>, "hyq_floating", backend, 10000LL)
        ->Unit(benchmark::kMillisecond)->UseRealTime();
    benchmark::RegisterBenchmark(
        (std::string("step_") + backend + "-aba:implicit:gravity+damping+contacts/float/atlas_floating/" + backend).c_str(),
        BM_SceneStep<float>, "atlas_floating", backend, 10000LL)
        ->Unit(benchmark::kMillisecond)->UseRealTime();
  }
  for (const char* name : {"rope_free_1000", "ballrope_1000"})
    benchmark::RegisterBenchmark((std::string("step_serial-aba:rk4:none/double/") + name + "/serial").c_str(),
                                 BM_SceneStep<double>, name, "serial", 1LL)
        ->Unit(benchmark::kMillisecond)->UseRealTime()->MinTime(0.2);
  for (long long n : {1000LL, 10000LL, 100000LL, 1000000LL})
    benchmark::RegisterBenchmark(("step_serial-aba:euler:gravity/double/rope:" + std::to_string(n) + "/serial").c_str(),
                                 BM_Step<double>, "rope:" + std::to_string(n), "gravity", "euler", "serial", 1LL, 1e-5)
        ->Unit(benchmark::kMillisecond)->UseRealTime()->MinTime(0.2);
}

}  // namespace

int main(int argc, char** argv) {
  register_all();
  benchmark::Initialize(&argc, argv);
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
