// The shape sweep: inverse dynamics on the GPU against the OpenMP backend on the
// same machine's CPU cores, from many instances of a small robot to a few ropes of
// 10^6 links, links x instances ~ 10^7 (and single long ropes, links x 1).
//
// Rows (names as scripts/bench_results.py reads them):
//   id_<strategy>/<precision>/<model>/cuda     CudaInverseDynamics::compute_async on
//                                              device buffers (soa), CUDA events around
//                                              the call; strategy as the engine chose it
//                                              (thread or scan-local);
//   id_<strategy>/<precision>/<model>/openmp   the OpenMP engine (all cores, its own
//                                              auto choice: recursion or scan-local) on
//                                              host buffers with the same inputs.
//   fd_jsi_thread/<precision>/<model>/cuda    forward dynamics by the joint-space
//                                              inertia, CudaForwardDynamics::compute_async
//                                              (models of up to 64 DoF);
//   fd_jsi/<precision>/<model>/cpu-threads    the serial fd_jsi on every host thread
//                                              (std::thread, instances split evenly):
//                                              the library has no batched CPU forward-
//                                              dynamics engine, this is what one would
//                                              write with it.
// JSI forward dynamics stops at 64 DoF here: beyond that there is no GPU kernel for
// it, and on chains its cost grows as n^3 and its float accuracy is gone by about 30
// links (docs/accuracy-id-scan.md, bench_cuda_fd).
// Counters: links, instances, max_rel_err against the double serial reference (a
// few instances), and for the cuda rows GBps (inputs and outputs per second).
// scripts/sweep_table.py pairs the rows into the speed-up table of docs/benchmarks.md.
//
// Flags (before Google Benchmark's): --models-dir=DIR (default $SCANDYN_MODELS_DIR or
// ../shared/models), --elements=N (links x instances per shape, default 10^7),
// --no-openmp (GPU rows only).
#include <benchmark/benchmark.h>
#include <cuda_runtime.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <string>
#include <vector>

#include "cuda_bench_util.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"
#include "scandyn/model/load.hpp"

#include <thread>


using namespace scandyn;
using namespace scandyn::bench;

namespace {

// Instances whose error is checked: every instance's reference is a serial RNEA.
Index samples_for(Index nv) { return nv >= 100000 ? 1 : nv >= 1000 ? 4 : 64; }

template <class S>
void bench_cuda(benchmark::State& st, const Model* md, Index B) {
  const ModelTpl<S> m = md->cast<S>();
  const Index nv = m.nv();
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;  // the scan strategy sizes its scratch by it; no host staging is used here
  const auto engine = make_or_skip<cuda::CudaInverseDynamics<S>>(st, m, o);
  if (!engine) return;
  time_device_id<S>(st, *md, B, samples_for(nv), [&](const IdBatchIn<S>& in, const BatchView<S>& tau) {
    return engine->compute_async(in, tau, nullptr);
  });
  st.SetLabel(engine->strategy());
}

template <class S>
void bench_openmp(benchmark::State& st, const Model* md, Index B) {
  st.SetLabel(time_host_id<S>(st, *md, B, BackendKind::OpenMP, S(0), samples_for(md->nv())));
}


// id_scan-local-runs<N>: the link scans with about N threads per pass (IdScanPlan's
// target_runs), one rope instance: what the default (2^16) costs.
template <class S>
void bench_scan_runs(benchmark::State& st, const Model* md, unsigned target_runs) {
  const ModelTpl<S> m = md->cast<S>();
  const auto plan = make_or_skip<cuda::IdScanPlan<S>>(st, m, 1, target_runs);
  if (!plan) return;
  time_device_id<S>(st, *md, 1, 1, [&](const IdBatchIn<S>& in, const BatchView<S>& tau) {
    return plan->launch(in, tau, nullptr);
  });
}

// ---- forward dynamics by the joint-space inertia --------------------------------------

// max rel_err of qdd (soa, host or device) against the double serial fd_jsi on the
// same (S-rounded) inputs, over up to 16 instances; inputs: arrays 0, 1, 2 = q, qd, tau;
// an instance whose error is NaN is left out
template <class S>
double fd_error(const Model& md, Index B, const S* qdd, bool on_device) {
  return fd_max_rel_err<S>(md, B, qdd, on_device, false, 16, SampleFailures{false, true});
}

template <class S>
void bench_fd_cuda(benchmark::State& st, const Model* md, Index B) {
  const ModelTpl<S> m = md->cast<S>();
  const Index nv = m.nv();
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 0;  // device path only
  const auto engine = make_or_skip<cuda::CudaForwardDynamics<S>>(st, m, o);
  if (!engine) return;
  DeviceBatch<S> buf;  // q, qd, tau (array 2), qdd (array 3)
  int* failed = nullptr;
  if (!cuda_ok(st, buf.alloc(nv, B), "allocating and filling the batch") ||
      !cuda_ok(st, cudaMalloc(reinterpret_cast<void**>(&failed), std::size_t(B) * sizeof(int)), "cudaMalloc"))
    return;
  const IdBatchIn<S> id = buf.in(nv, B);
  const FdBatchIn<S> in{id.q, id.qd, id.qdd};
  const BatchView<S> qdd = buf.tau(nv, B);
  const double seconds = time_launches(st, [&] { return engine->compute_async(in, qdd, failed, nullptr); });
  set_counters(st, nv, B, fd_error<S>(*md, B, qdd.data, true), seconds, sizeof(S));
  cudaFree(failed);
}

template <class S>
void bench_fd_cpu(benchmark::State& st, const Model* md, Index B) {
  const ModelTpl<S> m = md->cast<S>();
  const Index nv = m.nv();
  const std::size_t n = static_cast<std::size_t>(nv) * B;
  const HostInputs<S> x(n);
  const std::vector<S>& q = x.q, &qd = x.qd, &tau = x.u;
  std::vector<S> qdd(n, S(0));
  const int threads = std::max(1u, std::thread::hardware_concurrency());
  std::vector<DataTpl<S>> data;
  for (int t = 0; t < threads; ++t) data.emplace_back(m, true);
  auto run = [&] {
    std::vector<std::thread> pool;
    for (int t = 0; t < threads; ++t)
      pool.emplace_back([&, t] {
        std::vector<S> qi(nv), qdi(nv), ti(nv), out(nv);
        for (Index b = Index(std::int64_t(B) * t / threads); b < Index(std::int64_t(B) * (t + 1) / threads); ++b) {
          for (Index i = 0; i < nv; ++i) {
            const std::size_t k = static_cast<std::size_t>(i) * B + b;
            qi[i] = q[k], qdi[i] = qd[k], ti[i] = tau[k];
          }
          fd_jsi(m, data[t], qi.data(), qdi.data(), ti.data(), out.data());
          for (Index i = 0; i < nv; ++i) qdd[static_cast<std::size_t>(i) * B + b] = out[i];
        }
      });
    for (auto& th : pool) th.join();
  };
  run();  // warm-up
  for (auto _ : st) {
    run();
    benchmark::ClobberMemory();
  }
  st.counters["links"] = nv;
  st.counters["instances"] = B;
  st.counters["max_rel_err"] = fd_error<S>(*md, B, qdd.data(), false);
}

std::vector<std::unique_ptr<Model>> g_models;

}  // namespace

int main(int argc, char** argv) {
  const char* env = std::getenv("SCANDYN_MODELS_DIR");
  std::string models_dir = env && *env ? env : "../shared/models";
  double elements = 1e7;
  bool openmp = true;
  std::vector<char*> rest;
  for (int i = 0; i < argc; ++i) {
    if (std::strncmp(argv[i], "--models-dir=", 13) == 0) models_dir = argv[i] + 13;
    else if (std::strncmp(argv[i], "--elements=", 11) == 0) elements = std::atof(argv[i] + 11);
    else if (std::strcmp(argv[i], "--no-openmp") == 0) openmp = false;
    else rest.push_back(argv[i]);
  }
  if (!have_device("bench_cuda_sweep")) return 0;
  const auto info = cuda::device_info(0);
  const int threads = openmp_threads();
  std::printf("bench_cuda_sweep: device %s; OpenMP rows on %d threads\n",
              info ? cuda::describe(info.value).c_str() : info.error.c_str(), threads);

  // (model, instances): links x instances ~ elements, then single long ropes
  std::vector<std::pair<std::string, double>> shapes;
  for (const char* s : {"iiwa.urdf", "atlas.urdf", "chain:64", "rope:100", "rope:1000", "rope:10000", "rope:100000",
                        "rope:1000000"})
    shapes.emplace_back(s, 0.0);
  for (const char* s : {"rope:1000", "rope:10000", "rope:100000", "rope:1000000"}) shapes.emplace_back(s, 1.0);
  for (const auto& [spec, fixed_b] : shapes) {
    BuildOptions bo;
    bo.require_physical_inertia = false;  // GRiD's atlas.urdf
    try {
      const bool urdf = spec.size() > 5 && spec.compare(spec.size() - 5, 5, ".urdf") == 0;
      g_models.push_back(std::make_unique<Model>(urdf ? load_urdf(models_dir + "/" + spec, bo) : load_model(spec)));
    } catch (const ModelError& e) {
      std::fprintf(stderr, "bench_cuda_sweep: skipping %s: %s\n", spec.c_str(), e.what());
      continue;
    }
    const Model* md = g_models.back().get();
    const Index nv = md->nv();
    const Index B = fixed_b > 0 ? static_cast<Index>(fixed_b)
                                : static_cast<Index>(std::max(1.0, std::round(elements / double(nv))));
    const std::string label = spec.size() > 5 && spec.compare(spec.size() - 5, 5, ".urdf") == 0
                                  ? spec.substr(0, spec.size() - 5)
                                  : spec;
    for (int prec = 0; prec < 2; ++prec) {
      const std::string p = prec ? "float/" : "double/";
      const IdStrategy gs = choose_id_strategy(BackendKind::Cuda, nv, B, 1);
      const std::string gname =
          std::string("id_") + (gs == IdStrategy::ScanLocal ? "scan-local/" : "thread/") + p + label + "/cuda";
      auto* g = prec ? benchmark::RegisterBenchmark(gname.c_str(), [=](benchmark::State& st) { bench_cuda<float>(st, md, B); })
                     : benchmark::RegisterBenchmark(gname.c_str(), [=](benchmark::State& st) { bench_cuda<double>(st, md, B); });
      g->UseManualTime()->Unit(benchmark::kMicrosecond)->MinTime(0.1);
      if (!openmp) continue;
      const IdStrategy cs = choose_id_strategy(BackendKind::OpenMP, nv, B, threads);
      const std::string cname =
          std::string("id_") + (cs == IdStrategy::ScanLocal ? "scan-local/" : "recursion/") + p + label + "/openmp";
      auto* c = prec ? benchmark::RegisterBenchmark(cname.c_str(), [=](benchmark::State& st) { bench_openmp<float>(st, md, B); })
                     : benchmark::RegisterBenchmark(cname.c_str(), [=](benchmark::State& st) { bench_openmp<double>(st, md, B); });
      c->UseRealTime()->Unit(benchmark::kMicrosecond)->MinTime(0.2);
    }
    if (fixed_b > 0 && nv >= 1000000) {
      for (unsigned runs : {1u << 14, 1u << 15, 1u << 17, 1u << 18}) {
        const std::string name = "id_scan-local-runs" + std::to_string(runs) + "/float/" + label + "/cuda";
        benchmark::RegisterBenchmark(name.c_str(), [=](benchmark::State& st) { bench_scan_runs<float>(st, md, runs); })
            ->UseManualTime()->Unit(benchmark::kMicrosecond)->MinTime(0.1);
      }
    }
    if (fixed_b > 0 || nv > cuda::kMaxThreadDofs) continue;
    for (int prec = 0; prec < 2; ++prec) {
      const std::string p = prec ? "float/" : "double/";
      const std::string gname = "fd_jsi_thread/" + p + label + "/cuda";
      auto* g = prec ? benchmark::RegisterBenchmark(gname.c_str(), [=](benchmark::State& st) { bench_fd_cuda<float>(st, md, B); })
                     : benchmark::RegisterBenchmark(gname.c_str(), [=](benchmark::State& st) { bench_fd_cuda<double>(st, md, B); });
      g->UseManualTime()->Unit(benchmark::kMicrosecond)->MinTime(0.1);
      if (!openmp) continue;
      const std::string cname = "fd_jsi/" + p + label + "/cpu-threads";
      auto* c = prec ? benchmark::RegisterBenchmark(cname.c_str(), [=](benchmark::State& st) { bench_fd_cpu<float>(st, md, B); })
                     : benchmark::RegisterBenchmark(cname.c_str(), [=](benchmark::State& st) { bench_fd_cpu<double>(st, md, B); });
      c->UseRealTime()->Unit(benchmark::kMicrosecond)->MinTime(0.2);
    }
  }
  return run_benchmarks(rest);
}
