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
// Usage: step_derivatives_cost [floating] [min_seconds]   (CSV on stdout; floating:
// hyq, tree:30:4 and ballrope:20 on a floating base instead of the 1-DoF models)
//
// step_derivatives_cost cuda [min_seconds] [B ...] (builds with CUDA): the CUDA
// rollout adjoint (scandyn/cuda/rollout_derivatives.hpp) on device memory, iiwa
// (gravity, damping 0.01, dt 1e-3) euler and rk4, T = 100 steps, float and double,
// B instances (default 10^4 and 10^5). Columns: model, integrator, precision,
// instances, steps, checkpoint_interval, rollout_ns (the rollout alone) and vjp_ns
// (the whole adjoint: forward checkpoints, recomputation, reverse) in nanoseconds
// per instance-step, vjp_over_rollout, store_bytes_per_instance (the checkpoint
// store), gpu (the device's name). Each time: one call to warm up, then calls until
// min_seconds (default 0.3), the mean.
//
// step_derivatives_cost cuda-jacobian [min_seconds] [B ...] (builds with CUDA): the
// CUDA step Jacobian (cuda::CudaStepDerivatives, scandyn/cuda/step_derivatives.hpp,
// compute_async on device views: the six nv x nv blocks d(q', qd')/d(q, qd, tau) of
// every instance, soa with the instance innermost, the new state not written) on
// device memory, iiwa (gravity, damping 0.01, dt 1e-3) euler, rk4 and implicit,
// float and double, B instances (default 10^4 and 10^5). Columns: model, integrator,
// precision, instances, nv, jacobian_ns_per_instance (one compute_async over the
// batch, per instance), step_ns_per_instance_step (the plain step of the same scene
// on the same device: a device-resident rollout of 10 steps,
// cuda::CudaRolloutDerivatives::rollout_async, per instance and step),
// jacobian_over_step, output_bytes_per_instance (6 nv^2 scalars written),
// failed (instances the engine's failed_dof marks after the timed calls: 0 expected),
// gpu (the device's name). Each time: one call to warm up, then calls until
// min_seconds (default 0.3), the mean.
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "plain_bench_util.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"
#include "scandyn/sim/step_derivatives.hpp"
#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

#include "scandyn/cuda/rollout_derivatives.hpp"
#include "scandyn/cuda/step_derivatives.hpp"
#endif

using namespace scandyn;

namespace {

sim::Scene scene_of(const std::string& model, const std::string& integrator, double dt, Index B,
                    bool floating = false) {
  char dt_text[32];  // (std::to_string prints 1e-7 as 0.000000)
  std::snprintf(dt_text, sizeof dt_text, "%.17g", dt);
  sim::Scene s = sim::parse_scene("{\"model\": \"" + model + "\", \"integrator\": \"" + integrator +
                                      "\", \"dt\": " + dt_text +
                                      (floating ? ", \"base\": \"floating\"" : "") +
                                      ", \"effects\": {\"gravity\": true, \"damping\": 0.01}}",
                                  "bench.json", bench::models_dir());
  s.instances = B;
  return s;
}

}  // namespace

#if SCANDYN_HAS_CUDA
namespace {

void cuda_check(cudaError_t e, const char* what) { bench::exit_on_cuda_error("step_derivatives_cost", e, what); }

// The cuda modes' command line, step_derivatives_cost <mode> [min_seconds] [B ...]:
// min_time (default 0.3 s), the batches (default 10^4 and 10^5), and device 0.
struct CudaModeArgs {
  double min_time = 0.3;
  std::vector<Index> batches;
  cudaDeviceProp prop{};
};

CudaModeArgs cuda_mode_args(int argc, char** argv) {
  CudaModeArgs a;
  a.min_time = argc > 2 ? std::atof(argv[2]) : 0.3;
  for (int k = 3; k < argc; ++k) a.batches.push_back(static_cast<Index>(std::atol(argv[k])));
  if (a.batches.empty()) a.batches = {10000, 100000};
  cuda_check(cudaGetDeviceProperties(&a.prop, 0), "cudaGetDeviceProperties");
  return a;
}

// Seconds per call of f (launches on `stream`): one call to warm up, then calls
// until min_time, the mean.
template <class F>
double device_seconds(double min_time, cudaStream_t stream, F&& f) {
  using Clock = std::chrono::steady_clock;
  f();
  cuda_check(cudaStreamSynchronize(stream), "the warm-up call");
  int calls = 0;
  const auto t0 = Clock::now();
  double el = 0;
  do {
    f();
    cuda_check(cudaStreamSynchronize(stream), "a timed call");
    ++calls;
    el = std::chrono::duration<double>(Clock::now() - t0).count();
  } while (el < min_time);
  return el / calls;
}

template <class S>
void cuda_rollout_rows(const char* integrator, Index B, double min_time, const char* gpu) {
  const Index T = 100;
  const sim::Scene scene = scene_of("iiwa.urdf", integrator, 1e-3, 1);
  const Index n = scene.nv();
  sim::Simulator<S> one(scene, BackendKind::Serial);
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  cuda::CudaRolloutDerivatives<S> engine(one.setup(), o);
  // device arrays, (T, nv, B) with the instance innermost: tau, gq, gqd, gtau; the
  // states q0, qd0, gq0, gqd0; the rollout's q, qd
  const std::size_t state = static_cast<std::size_t>(n) * B, seq = state * T;
  std::vector<S> host(state + seq);
  std::mt19937_64 rng(1);
  std::uniform_real_distribution<double> u(-0.3, 0.3);
  for (S& x : host) x = S(u(rng));
  S* d = nullptr;
  cuda_check(cudaMalloc(reinterpret_cast<void**>(&d), (4 * state + 6 * seq) * sizeof(S)), "allocating the arrays");
  S *q0 = d, *qd0 = q0 + state, *gq0 = qd0 + state, *gqd0 = gq0 + state, *tau = gqd0 + state, *gq = tau + seq,
    *gqd = gq + seq, *gtau = gqd + seq, *q = gtau + seq, *qd = q + seq;
  for (S* x : {q0, qd0}) cuda_check(cudaMemcpy(x, host.data(), state * sizeof(S), cudaMemcpyHostToDevice), "copying");
  for (S* x : {tau, gq, gqd})
    cuda_check(cudaMemcpy(x, host.data() + state, seq * sizeof(S), cudaMemcpyHostToDevice), "copying");
  using CV = BatchView<const S>;
  auto cseq = [&](S* x) { return sim::StepSequence<const S>{CV::soa(x, n, B), static_cast<std::ptrdiff_t>(state), T}; };
  auto oseq = [&](S* x) {
    return sim::StepSequence<S>{BatchView<S>::soa(x, n, B), static_cast<std::ptrdiff_t>(state), T};
  };
  const cudaStream_t stream = engine.stream();
  const double rollout = device_seconds(min_time, stream, [&] {
    cuda_check(engine.rollout_async(CV::soa(q0, n, B), CV::soa(qd0, n, B), cseq(tau), oseq(q), oseq(qd), nullptr,
                                    stream),
               "rollout_async");
  });
  const double vjp = device_seconds(min_time, stream, [&] {
    cuda_check(engine.vjp_async(CV::soa(q0, n, B), CV::soa(qd0, n, B), cseq(tau), cseq(gq), cseq(gqd),
                                BatchView<S>::soa(gq0, n, B), BatchView<S>::soa(gqd0, n, B), oseq(gtau), nullptr,
                                stream),
               "vjp_async");
  });
  cuda_check(cudaFree(d), "freeing the arrays");
  const double per = 1e9 / (double(B) * T);
  std::printf("iiwa.urdf,%s,%s,%d,%d,%d,%.3f,%.3f,%.2f,%zu,%s\n", integrator, sizeof(S) == 4 ? "float" : "double",
              int(B), int(T), int(engine.checkpoint_interval(T)), rollout * per, vjp * per, vjp / rollout,
              engine.store_bytes(T, B) / static_cast<std::size_t>(B), gpu);
  std::fflush(stdout);
}

int cuda_main(int argc, char** argv) {
  const CudaModeArgs a = cuda_mode_args(argc, argv);
  std::printf("model,integrator,precision,instances,steps,checkpoint_interval,rollout_ns_per_instance_step,"
              "vjp_ns_per_instance_step,vjp_over_rollout,store_bytes_per_instance,gpu\n");
  for (Index B : a.batches)
    for (const char* integrator : {"euler", "rk4"}) {
      cuda_rollout_rows<float>(integrator, B, a.min_time, a.prop.name);
      cuda_rollout_rows<double>(integrator, B, a.min_time, a.prop.name);
    }
  return 0;
}

// One row of `cuda-jacobian`: the step Jacobian of B iiwa instances on device views,
// next to the device-resident plain step (a rollout of 10 steps).
template <class S>
void cuda_jacobian_rows(const char* integrator, Index B, double min_time, const char* gpu) {
  const sim::Scene scene = scene_of("iiwa.urdf", integrator, 1e-3, 1);
  const Index n = scene.nv();
  sim::Simulator<S> one(scene, BackendKind::Serial);
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  cuda::CudaStepDerivatives<S> engine(one.setup(), o);
  const Index T = 10;  // steps of the plain-step rollout
  cuda::CudaRolloutDerivatives<S> roll(one.setup(), o);
  // device arrays: q, qd, tau (nv x B), the six blocks (nv^2 x B each), and for the
  // rollout tau, q, qd (T, nv, B); the instance innermost everywhere
  const std::size_t state = static_cast<std::size_t>(n) * B, block = state * n, seq = state * T;
  std::vector<S> host(state);
  std::mt19937_64 rng(1);
  std::uniform_real_distribution<double> u(-0.3, 0.3);
  S* d = nullptr;
  cuda_check(cudaMalloc(reinterpret_cast<void**>(&d), (3 * state + 6 * block + 3 * seq) * sizeof(S)),
             "allocating the arrays");
  S *q = d, *qd = q + state, *tau = qd + state, *blocks = tau + state, *rtau = blocks + 6 * block, *rq = rtau + seq,
    *rqd = rq + seq;
  for (S* x : {q, qd, tau}) {
    for (S& v : host) v = S(u(rng));
    cuda_check(cudaMemcpy(x, host.data(), state * sizeof(S), cudaMemcpyHostToDevice), "copying the inputs");
  }
  for (Index t = 0; t < T; ++t)
    cuda_check(cudaMemcpy(rtau + t * state, tau, state * sizeof(S), cudaMemcpyDeviceToDevice), "copying tau");
  int* failed = nullptr;
  cuda_check(cudaMalloc(reinterpret_cast<void**>(&failed), static_cast<std::size_t>(B) * sizeof(int)),
             "allocating failed_dof");
  cudaStream_t stream = nullptr;
  cuda_check(cudaStreamCreate(&stream), "cudaStreamCreate");
  using CV = BatchView<const S>;
  auto bv = [&](int k) { return BatchView<S>::soa(blocks + k * block, n * n, B); };
  const FdBatchIn<S> in{CV::soa(q, n, B), CV::soa(qd, n, B), CV::soa(tau, n, B)};
  const sim::StepDerivativesOut<S> out{bv(0), bv(1), bv(2), bv(3), bv(4), bv(5), {}, {}};
  const double jac = device_seconds(min_time, stream, [&] {
    cuda_check(engine.compute_async(in, out, failed, stream), "compute_async");
  });
  std::vector<int> fh(static_cast<std::size_t>(B));
  cuda_check(cudaMemcpy(fh.data(), failed, fh.size() * sizeof(int), cudaMemcpyDeviceToHost), "copying failed_dof");
  long long nfailed = 0;
  for (int f : fh) nfailed += f != -1;
  const double step = device_seconds(min_time, stream, [&] {
    cuda_check(roll.rollout_async(CV::soa(q, n, B), CV::soa(qd, n, B),
                                  sim::StepSequence<const S>{CV::soa(rtau, n, B), static_cast<std::ptrdiff_t>(state), T},
                                  sim::StepSequence<S>{BatchView<S>::soa(rq, n, B), static_cast<std::ptrdiff_t>(state), T},
                                  sim::StepSequence<S>{BatchView<S>::soa(rqd, n, B), static_cast<std::ptrdiff_t>(state), T},
                                  nullptr, stream),
               "rollout_async");
  });
  cuda_check(cudaStreamDestroy(stream), "cudaStreamDestroy");
  cuda_check(cudaFree(failed), "freeing failed_dof");
  cuda_check(cudaFree(d), "freeing the arrays");
  const double jac_ns = jac * 1e9 / double(B), step_ns = step * 1e9 / (double(B) * T);
  std::printf("iiwa.urdf,%s,%s,%d,%d,%.3f,%.3f,%.2f,%zu,%lld,%s\n", integrator, sizeof(S) == 4 ? "float" : "double",
              int(B), int(n), jac_ns, step_ns, jac_ns / step_ns, 6 * static_cast<std::size_t>(n) * n * sizeof(S),
              nfailed, gpu);
  std::fflush(stdout);
}

int cuda_jacobian_main(int argc, char** argv) {
  const CudaModeArgs a = cuda_mode_args(argc, argv);
  std::printf("model,integrator,precision,instances,nv,jacobian_ns_per_instance,step_ns_per_instance_step,"
              "jacobian_over_step,output_bytes_per_instance,failed,gpu\n");
  for (Index B : a.batches)
    for (const char* integrator : {"euler", "rk4", "implicit"}) {
      cuda_jacobian_rows<float>(integrator, B, a.min_time, a.prop.name);
      cuda_jacobian_rows<double>(integrator, B, a.min_time, a.prop.name);
    }
  return 0;
}

}  // namespace
#endif

int main(int argc, char** argv) {
  if (argc > 1 && std::strcmp(argv[1], "cuda-jacobian") == 0) {
#if SCANDYN_HAS_CUDA
    return cuda_jacobian_main(argc, argv);
#else
    std::fprintf(stderr, "step_derivatives_cost cuda-jacobian: this build has no CUDA backend\n");
    return 2;
#endif
  }
  if (argc > 1 && std::strcmp(argv[1], "cuda") == 0) {
#if SCANDYN_HAS_CUDA
    return cuda_main(argc, argv);
#else
    std::fprintf(stderr, "step_derivatives_cost cuda: this build has no CUDA backend\n");
    return 2;
#endif
  }
  // step_derivatives_cost floating [min_seconds]: the same columns on models with a
  // floating base (multi-DoF joints: step_jacobian_at_instance; the rollouts' JVP and
  // VJP as products with the dense Jacobian per step)
  const bool floating = argc > 1 && std::strcmp(argv[1], "floating") == 0;
  if (floating) --argc, ++argv;
  const double min_time = argc > 1 ? std::atof(argv[1]) : 0.3;
  std::printf("model,integrator,nv,step_us,jacobian_us,central_us,jacobian_over_step,central_over_jacobian,"
              "rollout_vjp_us_per_step,rollout_jvp_us_per_step\n");
  struct Row {
    const char* model;
    double dt;
  };
  const std::vector<Row> rows =
      floating ? std::vector<Row>{Row{"hyq.urdf", 1e-3}, Row{"tree:30:4", 1e-4}, Row{"ballrope:20", 1e-7}}
               : std::vector<Row>{Row{"iiwa.urdf", 1e-3}, Row{"hyq.urdf", 1e-3}, Row{"tree:30:4", 1e-4},
                                  Row{"rope:20", 1e-5}, Row{"rope:100", 1e-6}};
  for (const Row& r : rows) {
    for (const char* integrator : {"euler", "rk4"}) {
      const sim::Scene scene = scene_of(r.model, integrator, r.dt, 1, floating);
      const Index n = scene.nv(), nq = scene.nq();
      sim::Simulator<double> one(scene, BackendKind::Serial);
      std::mt19937_64 rng(1);
      std::uniform_real_distribution<double> u(-0.3, 0.3);
      std::vector<double> q(nq, 0.0), qd(n), tau(n, 0.0), v(n);
      // q: the neutral configuration moved by a random tangent (q = v on 1-DoF models)
      neutral_bodies(scene.model.bodies.data(), scene.model.nbodies(), q.data());
      for (Index i = 0; i < n; ++i) v[i] = u(rng), qd[i] = u(rng);
      integrate_configuration(scene.model, q.data(), v.data(), 1.0);
      using V = BatchView<const double>;
      // a plain step: the same state each time
      const double step = bench::best_seconds_per_call(min_time, [&] {
        for (Index i = 0; i < nq; ++i) one.q().at(i, 0) = q[i];
        for (Index i = 0; i < n; ++i) one.qd().at(i, 0) = qd[i];
        one.step(V::soa(tau.data(), n, 1));
        return std::size_t(1);
      });
      // the dense Jacobian
      BackendOptions o;
      auto engine = sim::make_step_derivatives(one.setup(), o);
      std::vector<std::vector<double>> blocks(6, std::vector<double>(static_cast<std::size_t>(n) * n));
      auto bv = [&](int k) { return BatchView<double>::aos(blocks[k].data(), n * n, 1); };
      const sim::StepDerivativesOut<double> out{bv(0), bv(1), bv(2), bv(3), bv(4), bv(5), {}, {}};
      const FdBatchIn<double> in{V::aos(q.data(), nq, 1), V::aos(qd.data(), n, 1), V::aos(tau.data(), n, 1)};
      const double jac = bench::best_seconds_per_call(min_time, [&] {
        engine->compute(in, out);
        return std::size_t(1);
      });
      // central differences: 6 nv perturbed steps
      sim::Simulator<double> many(scene_of(r.model, integrator, r.dt, 6 * n, floating), BackendKind::Serial);
      const double central = bench::best_seconds_per_call(min_time, [&] {
        for (Index b = 0; b < 6 * n; ++b) {
          for (Index i = 0; i < nq; ++i) many.q().at(i, b) = q[i];
          for (Index i = 0; i < n; ++i) many.qd().at(i, b) = qd[i];
        }
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
      // every timed call must succeed (a failed instance stops early: its time would mislead)
      auto require_ok = [&](const BatchStatus& st, const char* what) {
        if (st.ok()) return;
        std::fprintf(stderr, "step_derivatives_cost: %s of %s %s failed: %s\n", what, r.model, integrator,
                     sim::failure_message(st).c_str());
        std::exit(1);
      };
      require_ok(engine->compute(in, out), "the Jacobian");
      const double vjp = bench::best_seconds_per_call(min_time, [&] {
        require_ok(rd.vjp(in.q, in.qd, seq(taus), seq(g), seq(g), BatchView<double>::aos(g0.data(), n, 1),
               BatchView<double>::aos(gd0.data(), n, 1), out_seq(gt)), "the rollout adjoint");
        return std::size_t(T);
      });
      const double jvp = bench::best_seconds_per_call(min_time, [&] {
        require_ok(rd.jvp(in.q, in.qd, seq(taus), in.qd, in.qd, seq(g), out_seq(dq), out_seq(dqd)), "the rollout JVP");
        return std::size_t(T);
      });
      std::printf("%s,%s,%d,%.3f,%.3f,%.3f,%.2f,%.2f,%.3f,%.3f\n", r.model, integrator, int(n), step * 1e6, jac * 1e6,
                  central * 1e6, jac / step, central / jac, vjp * 1e6, jvp * 1e6);
      std::fflush(stdout);
    }
  }
  return 0;
}
