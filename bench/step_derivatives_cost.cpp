// bench/step_derivatives_cost.cpp: the CPU cost of the simulator step's derivatives
// (scandyn/sim/step_derivatives.hpp), one instance, double, serial (one thread), next
// to a plain step of the same scene and to the central differences that the dense
// Jacobian replaces. Columns (microseconds per instance):
//   step        one step (Simulator, serial-aba)
//   jacobian    the dense Jacobian d(q', qd')/d(q, qd, tau) (make_step_derivatives)
//   central     central differences of the step: 2 * 3 nv steps (one step of a
//               simulator of 6 nv instances)
//   rollout_vjp per step of a rollout's adjoint (T = 100, checkpoints every sqrt(T)),
//               forward checkpoints and recomputation included
//   rollout_jvp per step of the forward-mode product along one direction
// Usage: step_derivatives_cost [min_seconds]   (CSV on stdout)
#include <cstdio>
#include <cstdlib>
#include <random>
#include <string>
#include <vector>

#include "plain_bench_util.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"
#include "scandyn/sim/step_derivatives.hpp"

using namespace scandyn;

namespace {

sim::Scene scene_of(const std::string& model, const std::string& integrator, double dt, Index B) {
  sim::Scene s = sim::parse_scene("{\"model\": \"" + model + "\", \"integrator\": \"" + integrator +
                                      "\", \"dt\": " + std::to_string(dt) +
                                      ", \"effects\": {\"gravity\": true, \"damping\": 0.01}}",
                                  "bench.json", bench::models_dir());
  s.instances = B;
  return s;
}

}  // namespace

int main(int argc, char** argv) {
  const double min_time = argc > 1 ? std::atof(argv[1]) : 0.3;
  std::printf("model,integrator,nv,step_us,jacobian_us,central_us,jacobian_over_step,central_over_jacobian,"
              "rollout_vjp_us_per_step,rollout_jvp_us_per_step\n");
  struct Row {
    const char* model;
    double dt;
  };
  for (const Row& r : {Row{"iiwa.urdf", 1e-3}, Row{"hyq.urdf", 1e-3}, Row{"tree:30:4", 1e-4}, Row{"rope:20", 1e-5},
                       Row{"rope:100", 1e-6}}) {
    for (const char* integrator : {"euler", "rk4"}) {
      const sim::Scene scene = scene_of(r.model, integrator, r.dt, 1);
      const Index n = scene.nv();
      sim::Simulator<double> one(scene, BackendKind::Serial);
      std::mt19937_64 rng(1);
      std::uniform_real_distribution<double> u(-0.3, 0.3);
      std::vector<double> q(n), qd(n), tau(n, 0.0);
      for (Index i = 0; i < n; ++i) q[i] = u(rng), qd[i] = u(rng);
      using V = BatchView<const double>;
      // a plain step: the same state each time
      const double step = bench::best_seconds_per_call(min_time, [&] {
        for (Index i = 0; i < n; ++i) one.q().at(i, 0) = q[i], one.qd().at(i, 0) = qd[i];
        one.step(V::soa(tau.data(), n, 1));
        return std::size_t(1);
      });
      // the dense Jacobian
      BackendOptions o;
      auto engine = sim::make_step_derivatives(one.setup(), o);
      std::vector<std::vector<double>> blocks(6, std::vector<double>(static_cast<std::size_t>(n) * n));
      auto bv = [&](int k) { return BatchView<double>::aos(blocks[k].data(), n * n, 1); };
      const sim::StepDerivativesOut<double> out{bv(0), bv(1), bv(2), bv(3), bv(4), bv(5), {}, {}};
      const FdBatchIn<double> in{V::aos(q.data(), n, 1), V::aos(qd.data(), n, 1), V::aos(tau.data(), n, 1)};
      const double jac = bench::best_seconds_per_call(min_time, [&] {
        engine->compute(in, out);
        return std::size_t(1);
      });
      // central differences: 6 nv perturbed steps
      sim::Simulator<double> many(scene_of(r.model, integrator, r.dt, 6 * n), BackendKind::Serial);
      const double central = bench::best_seconds_per_call(min_time, [&] {
        for (Index b = 0; b < 6 * n; ++b)
          for (Index i = 0; i < n; ++i) many.q().at(i, b) = q[i], many.qd().at(i, b) = qd[i];
        many.step();
        return std::size_t(1);
      });
      // rollouts of T steps
      const Index T = 100;
      sim::RolloutDerivatives<double> rd(one.setup(), o);
      std::vector<double> taus(static_cast<std::size_t>(T) * n, 0.0), g(taus.size(), 1e-3), gt(taus.size()),
          dq(taus.size()), dqd(taus.size()), g0(n), gd0(n);
      auto seq = [&](std::vector<double>& v) {
        return sim::StepSequence<const double>{V::aos(v.data(), n, 1), n, T};
      };
      auto out_seq = [&](std::vector<double>& v) {
        return sim::StepSequence<double>{BatchView<double>::aos(v.data(), n, 1), n, T};
      };
      const double vjp = bench::best_seconds_per_call(min_time, [&] {
        rd.vjp(in.q, in.qd, seq(taus), seq(g), seq(g), BatchView<double>::aos(g0.data(), n, 1),
               BatchView<double>::aos(gd0.data(), n, 1), out_seq(gt));
        return std::size_t(T);
      });
      const double jvp = bench::best_seconds_per_call(min_time, [&] {
        rd.jvp(in.q, in.qd, seq(taus), in.q, in.qd, seq(g), out_seq(dq), out_seq(dqd));
        return std::size_t(T);
      });
      std::printf("%s,%s,%d,%.3f,%.3f,%.3f,%.2f,%.2f,%.3f,%.3f\n", r.model, integrator, int(n), step * 1e6, jac * 1e6,
                  central * 1e6, jac / step, central / jac, vjp * 1e6, jvp * 1e6);
      std::fflush(stdout);
    }
  }
  return 0;
}
