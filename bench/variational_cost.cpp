// bench/variational_cost.cpp: the variational integrator (scandyn/sim/variational.hpp)
// against euler (semi-implicit) and rk4 steps of the same scene: the cost per step
// and the long-run energy error. CPU, one instance, double, serial (one thread).
//
// Usage:
//   variational_cost cost [min_seconds] [MODEL DT]...
//       CSV on stdout: model,nv,dt,integrator,step_us,newton_iterations,over_euler,failed_steps
//       (newton_iterations: mean updates per step over the first 100 steps: Newton
//       up to 64 DoFs, the chord iteration beyond, scandyn/sim/variational.hpp);
//       the rows: the MODEL DT pairs given, by default rope:2 1e-3, iiwa.urdf 1e-3,
//       rope:1000 1e-5
//   variational_cost energy MODEL DT STEPS EVERY [integrators...]
//       CSV on stdout: model,integrator,dt,step,t,rel_err,swing_err with
//       rel_err = |E - E0| / |E0| and swing_err = |E - E0| / (E0 - E_rest), every
//       EVERY steps (MODEL: rope:2, iiwa.urdf, rope:1000, ...; gravity only, the
//       start of the tests: rope:2 from (1, 0.5) rad at rest, iiwa from a bent pose
//       with joint speeds, other models from seed 2's random q of 0.05 rad).
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

#include "plain_bench_util.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"
#include "scandyn/sim/variational.hpp"

using namespace scandyn;

namespace {

std::string initial_of(const std::string& model) {
  if (model == "rope:2") return "\"initial\": {\"q\": [1.0, 0.5], \"qd\": [0, 0]}";
  if (model == "iiwa.urdf")
    return "\"initial\": {\"q\": [0.3, 0.8, -0.2, -1.0, 0.4, 0.6, 0.1], \"qd\": [0.5, -0.3, 0.4, 0.2, -0.6, 0.3, 0.8]}";
  return "\"initial\": {\"random\": {\"seed\": 2, \"q\": 0.05}}";
}

sim::Scene scene_of(const std::string& model, const std::string& integrator, double dt) {
  char b[64];
  std::snprintf(b, sizeof b, "%.17g", dt);
  return sim::parse_scene("{\"model\": \"" + model + "\", \"integrator\": \"" + integrator + "\", \"dt\": " + b +
                              ", \"effects\": {\"gravity\": true}, " + initial_of(model) + "}",
                          "bench.json", bench::models_dir());
}

struct Row {
  const char* model;
  double dt;
};

int cost(double min_time, std::vector<Row> rows) {
  if (rows.empty()) rows = {Row{"rope:2", 1e-3}, Row{"iiwa.urdf", 1e-3}, Row{"rope:1000", 1e-5}};
  std::printf("model,nv,dt,integrator,step_us,newton_iterations,over_euler,failed_steps\n");
  for (const Row& r : rows) {
    double euler = 0;
    for (const char* integrator : {"euler", "rk4", "variational"}) {
      const sim::Scene scene = scene_of(r.model, integrator, r.dt);
      sim::Simulator<double> one(scene, BackendKind::Serial);
      // steps from the scene's start, the state reset every 100 steps
      int k = 0;
      const double t = bench::best_seconds_per_call(min_time, [&] {
        if (k++ % 100 == 0) one.reset_all();
        one.step();
        return std::size_t(1);
      });
      double iterations = 0;
      int failed = 0;
      if (std::strcmp(integrator, "variational") == 0) {  // the Newton iterations of the first steps
        sim::VariationalWork<double> w(scene.model);
        std::vector<double> q = scene.initial.q, qd = scene.initial.qd, tau(scene.nv(), 0.0);
        if (scene.initial.random) {
          std::vector<double> qq(scene.nq()), qdd(scene.nv());
          one.reset_all();
          one.read_state(qq.data(), qdd.data());
          q = qq, qd = qdd;
        }
        const int n = 100;
        for (int s = 0; s < n; ++s) {
          const sim::VariationalResult res = sim::variational_step<sim::kGravity>(
              scene.model, w, r.dt, scene.joints.data(), q.data(), qd.data(), tau.data(),
              static_cast<const Force<double>*>(nullptr));
          iterations += res.iterations;
          failed += res.failed_dof >= 0;
        }
        iterations /= n;
      }
      if (std::strcmp(integrator, "euler") == 0) euler = t;
      const Index simulator_failed = one.status().failed;  // the timed steps' failures
      std::printf("%s,%lld,%g,%s,%.4g,%.3g,%.3g,%lld\n", r.model, static_cast<long long>(scene.nv()), r.dt, integrator,
                  t * 1e6, iterations, t / euler, static_cast<long long>(simulator_failed + failed));
      std::fflush(stdout);
    }
  }
  return 0;
}

int energy(const std::string& model, double dt, long long steps, long long every, std::vector<std::string> integrators) {
  if (integrators.empty()) integrators = {"euler", "rk4", "variational"};
  std::printf("model,integrator,dt,step,t,rel_err,swing_err\n");
  for (const std::string& integrator : integrators) {
    const sim::Scene scene = scene_of(model, integrator, dt);
    sim::Simulator<double> sim(scene, BackendKind::Serial);
    const std::vector<double> zero(scene.nv(), 0.0);
    const double rest =
        sim::mechanical_energy(scene.model, scene.effects, scene.joints.data(), zero.data(), zero.data());
    const double e0 = sim.energy()[0];
    const auto t0 = std::chrono::steady_clock::now();
    for (long long s = 1; s <= steps; ++s) {
      sim.step();
      if (s % every != 0) continue;
      const double e = sim.energy()[0];
      std::printf("%s,%s,%g,%lld,%.6g,%.4g,%.4g\n", model.c_str(), integrator.c_str(), dt, s, double(s) * dt,
                  std::abs(e - e0) / std::abs(e0), std::abs(e - e0) / std::abs(e0 - rest));
      std::fflush(stdout);  // a long run's rows as they come
    }
    const double el = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    std::fprintf(stderr, "%s %s: %lld steps in %.3g s; %s\n", model.c_str(), integrator.c_str(), steps, el,
                 sim.status().ok() ? "ok" : sim::failure_message(sim.status()).c_str());
    std::fflush(stdout);
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  const std::string mode = argc > 1 ? argv[1] : "cost";
  if (mode == "cost" && argc % 2 == 1) {
    std::vector<Row> rows;
    for (int k = 3; k + 1 < argc; k += 2) rows.push_back(Row{argv[k], std::atof(argv[k + 1])});
    return cost(argc > 2 ? std::atof(argv[2]) : 0.3, rows);
  }
  if (mode == "cost" && argc == 2) return cost(0.3, {});
  if (mode == "energy" && argc >= 6) {
    std::vector<std::string> integrators(argv + 6, argv + argc);
    return energy(argv[2], std::atof(argv[3]), std::atoll(argv[4]), std::atoll(argv[5]), integrators);
  }
  std::fprintf(stderr,
               "usage: variational_cost cost [min_seconds] [MODEL DT]... | energy MODEL DT STEPS EVERY "
               "[integrators...]\n");
  return 2;
}
