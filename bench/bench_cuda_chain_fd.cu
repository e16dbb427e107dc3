// Forward dynamics of ropes (rope:N, one instance unless stated) on the GPU by the
// chain scans (parallel, hybrid) and by the joint-space inertia, against the serial
// ABA on this machine's CPU.
//
// Rows (names as scripts/bench_results.py reads them):
//   fd_parallel/<precision>/rope:N/cuda       CudaForwardDynamics, FdMethod::Parallel,
//                                             compute_async on device buffers (events
//                                             around the launch), N = 10 .. 10^6;
//   fd_parallel-host/<precision>/rope:N/cuda  compute() from host buffers (copies in
//                                             and out included), as the hybrid is;
//   fd_hybrid/<precision>/rope:N/cuda         FdMethod::Hybrid through compute():
//                                             the articulated inertias on this host
//                                             (ChainInertiaCarries on all threads,
//                                             openmp_threads()), the other passes on
//                                             the device;
//   fd_hybrid-t1/<precision>/rope:N/cuda      the same with one host thread (the serial
//                                             recursion), N >= 10^5;
//   fd_jsi/<precision>/rope:N/cuda            FdMethod::Jsi (jsi_thread to 64 links,
//                                             then CRBA + cuSOLVER's Cholesky), compute_async,
//                                             N = 10 .. 4000 (M is N^2 scalars);
//   fd_aba/<precision>/rope:N/serial          the serial reference aba on this host;
//   fd_parallel/<precision>/rope:1000/cuda    with instances = 10 .. 1000 (batches of ropes);
//   fd_parallel-c<L>f<F>/float/rope:N/cuda    ChainFdPlan with L links per chunk and fan-in F
//                                             (the engine's default: c8f8), N = 10^4, 10^6;
//   fd_parallel-graph/float/rope:N/cuda       the default plan's launch captured in a CUDA
//                                             graph and replayed;
//   fd_parallel-plan/<precision>/rope:N[-floating]/cuda
//                                             the default ChainFdPlan's launch on device
//                                             buffers, the fixed rope and the free one
//                                             (--floating-base: a floating base, then N - 1
//                                             links) side by side, N = 10^4 .. 10^6.
// max_rel_err: every qdd entry against the double serial aba on the same
// (precision-rounded) inputs: q uniform in [-1, 1] rad, qd and tau in [-1, 1] (a free
// rope's base quaternion normalised).
// Counters: links, instances, max_rel_err, failed (instances reported failed).
//
// Before the rows: the device, and the hybrid's timeline for rope:10^6 in float and
// double as lines "timeline,<precision>,<lane>,<event>,<c_lo>,<c_hi>,<start ms>,<end ms>":
// busy intervals, the host threads' walks, reductions and combine (lanes cpu<thread>)
// and the device's velocities, walks of each group of chunks (CUDA events right before
// and after the kernel) and passes 2-3 (lane gpu). scripts/gpu_check.sh keeps them as
// hybrid-timeline-rope1e6.csv; scripts/chain_fd_report.py --timeline draws them.
//
// Flags (before Google Benchmark's): --max-links=N (default 10^6).
#include <benchmark/benchmark.h>
#include <cuda_runtime.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <map>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "cuda_bench_util.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/model/load.hpp"

using namespace scandyn;
using namespace scandyn::bench;

namespace {

// Inputs of one configuration in double (the reference's) and the reference qdd.
struct Inputs {
  std::vector<double> q, qd, tau, ref;  // SoA: q (nq x B), the others (nv x B)
};

std::map<std::string, std::shared_ptr<Inputs>> g_inputs;  // by "<precision>/<spec>/<B>"

template <class S>
std::shared_ptr<Inputs> inputs(const Model& m, Index B) {
  const std::string key = std::string(sizeof(S) == 4 ? "f/" : "d/") + m.source +
                          (m.floating_base() ? "-floating/" : "/") + std::to_string(B);
  auto& slot = g_inputs[key];
  if (slot) return slot;
  slot = std::make_shared<Inputs>();
  const Index n = m.nv(), nq = m.nq();
  std::mt19937_64 rng(42);
  std::uniform_real_distribution<double> u(-1, 1);
  for (auto* v : {&slot->q, &slot->qd, &slot->tau}) {
    v->resize(static_cast<std::size_t>(v == &slot->q ? nq : n) * B);
    for (auto& x : *v) x = double(S(u(rng)));
  }
  if (m.floating_base())  // the base's quaternion, rows 3..6: unit in precision S
    for (Index b = 0; b < B; ++b) {
      double nrm = 0;
      for (Index k = 3; k < 7; ++k) nrm += slot->q[k * B + b] * slot->q[k * B + b];
      for (Index k = 3; k < 7; ++k) slot->q[k * B + b] = double(S(slot->q[k * B + b] / std::sqrt(nrm)));
    }
  slot->ref.resize(slot->qd.size());
  Data data(m, false);
  std::vector<double> qi(nq), qdi(n), ti(n), qddi(n);
  for (Index b = 0; b < B; ++b) {
    for (Index i = 0; i < nq; ++i) qi[i] = slot->q[i * B + b];
    for (Index i = 0; i < n; ++i) qdi[i] = slot->qd[i * B + b], ti[i] = slot->tau[i * B + b];
    aba(m, data, qi.data(), qdi.data(), ti.data(), qddi.data());
    for (Index i = 0; i < n; ++i) slot->ref[i * B + b] = qddi[i];
  }
  return slot;
}

template <class S>
double error_of(const std::vector<S>& qdd, const Inputs& in) {
  std::vector<double> d(qdd.begin(), qdd.end());
  return rel_err(d.data(), in.ref.data(), d.size());
}

template <class S>
void set(benchmark::State& st, Index n, Index B, double err, Index failed) {
  st.counters["links"] = n;
  st.counters["instances"] = B;
  st.counters["max_rel_err"] = err;
  st.counters["failed"] = failed;
}

// One configuration's inputs on the device (q, qd, tau, then qdd; SoA: q nq x B, the
// others n x B, each given count = nq B entries) and B failed links; freed on scope exit.
template <class S>
struct DeviceInputs {
  S* p = nullptr;
  int* failed = nullptr;
  Index n = 0, B = 0;
  std::size_t count = 0;
  FdBatchIn<S> in{};
  BatchView<S> qdd{};

  bool upload(benchmark::State& st, const Inputs& h, Index n_, Index B_) {
    n = n_, B = B_, count = h.q.size();
    if (!cuda_ok(st, cudaMalloc(&p, 4 * count * sizeof(S)), "cudaMalloc") ||
        !cuda_ok(st, cudaMalloc(&failed, B * sizeof(int)), "cudaMalloc"))
      return false;
    const std::vector<double>* src[3] = {&h.q, &h.qd, &h.tau};
    for (int a = 0; a < 3; ++a) {
      const std::vector<S> v(src[a]->begin(), src[a]->end());
      cudaMemcpy(p + a * count, v.data(), v.size() * sizeof(S), cudaMemcpyHostToDevice);
    }
    using V = BatchView<const S>;
    in = {V::soa(p, static_cast<Index>(count) / B, B), V::soa(p + count, n, B), V::soa(p + 2 * count, n, B), nullptr};
    qdd = BatchView<S>::soa(p + 3 * count, n, B);
    return true;
  }
  // qdd back on the host, and how many instances reported a failed pivot
  std::vector<S> result(Index& bad) const {
    std::vector<S> out(static_cast<std::size_t>(n) * B);
    std::vector<int> f(static_cast<std::size_t>(B));
    cudaMemcpy(out.data(), p + 3 * count, out.size() * sizeof(S), cudaMemcpyDeviceToHost);
    cudaMemcpy(f.data(), failed, B * sizeof(int), cudaMemcpyDeviceToHost);
    bad = 0;
    for (int x : f) bad += x >= 0;
    return out;
  }
  ~DeviceInputs() {
    if (p) cudaFree(p);
    if (failed) cudaFree(failed);
  }
};

// The engine for B instances of m by algo, or null (the row skipped with the reason).
template <class S>
std::unique_ptr<cuda::CudaForwardDynamics<S>> make_engine(benchmark::State& st, const Model* m, Index B,
                                                          FdMethod algo, int threads = 0) {
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  o.threads = threads;  // the hybrid's host threads (0: openmp_threads())
  try {
    return std::make_unique<cuda::CudaForwardDynamics<S>>(m->cast<S>(), o, algo);
  } catch (const std::exception& e) {
    st.SkipWithError(e.what());
    return nullptr;
  }
}

// Device rows: compute_async on device buffers.
template <class S>
void run_device(benchmark::State& st, const Model* m, Index B, FdMethod algo) {
  const Index n = m->nv();
  const auto in = inputs<S>(*m, B);
  const auto fd = make_engine<S>(st, m, B, algo);
  if (!fd) return;
  DeviceInputs<S> dev;
  if (!dev.upload(st, *in, n, B)) return;
  time_launches(st, [&] { return fd->compute_async(dev.in, dev.qdd, dev.failed, nullptr); });
  Index bad = 0;
  const std::vector<S> qdd = dev.result(bad);
  set<S>(st, n, B, error_of(qdd, *in), bad);
}

// Host rows: compute() from host buffers (the hybrid needs q on the host).
template <class S>
void run_host(benchmark::State& st, const Model* m, Index B, FdMethod algo, int threads = 0) {
  const Index n = m->nv();
  const auto in = inputs<S>(*m, B);
  const auto fd = make_engine<S>(st, m, B, algo, threads);
  if (!fd) return;
  const std::vector<S> q(in->q.begin(), in->q.end()), qd(in->qd.begin(), in->qd.end()), tau(in->tau.begin(), in->tau.end());
  std::vector<S> qdd(q.size());
  using V = BatchView<const S>;
  const FdBatchIn<S> hin{V::soa(q.data(), n, B), V::soa(qd.data(), n, B), V::soa(tau.data(), n, B), nullptr};
  BatchStatus status;
  for (auto _ : st) status = fd->compute(hin, BatchView<S>::soa(qdd.data(), n, B));
  set<S>(st, n, B, error_of(qdd, *in), status.failed);
}

template <class S>
void run_serial_aba(benchmark::State& st, const Model* m) {
  const Index n = m->nv();
  const auto in = inputs<S>(*m, 1);
  const ModelTpl<S> ms = m->cast<S>();
  DataTpl<S> data(ms, false);
  const std::vector<S> q(in->q.begin(), in->q.end()), qd(in->qd.begin(), in->qd.end()), tau(in->tau.begin(), in->tau.end());
  std::vector<S> qdd(q.size());
  for (auto _ : st) {
    aba(ms, data, q.data(), qd.data(), tau.data(), qdd.data());
    benchmark::DoNotOptimize(qdd.data());
  }
  set<S>(st, n, 1, error_of(qdd, *in), 0);
}

// Variant rows: the plan with other chunk lengths and fan-ins, and the default plan's
// launch captured once in a CUDA graph and replayed (kernel launch costs).
template <class S>
void run_plan(benchmark::State& st, const Model* m, Index chunk, Index fan_in, bool graph) {
  const Index n = m->nv(), B = 1;
  const auto in = inputs<S>(*m, B);
  std::unique_ptr<cuda::ChainFdPlan<S>> plan;
  try {
    plan = std::make_unique<cuda::ChainFdPlan<S>>(m->cast<S>(), B, chunk, fan_in);
  } catch (const std::exception& e) {
    st.SkipWithError(e.what());
    return;
  }
  DeviceInputs<S> dev;
  if (!dev.upload(st, *in, n, B)) return;
  const FdBatchIn<S> din = dev.in;
  const BatchView<S> dqdd = dev.qdd;
  int* const failed = dev.failed;
  cudaStream_t stream = nullptr;
  cudaGraphExec_t exec = nullptr;
  cudaStreamCreateWithFlags(&stream, cudaStreamNonBlocking);
  if (graph) {
    cudaGraph_t g = nullptr;
    cudaStreamBeginCapture(stream, cudaStreamCaptureModeThreadLocal);
    plan->launch(din, dqdd, failed, stream);
    if (!cuda_ok(st, cudaStreamEndCapture(stream, &g), "graph capture") ||
        !cuda_ok(st, cudaGraphInstantiate(&exec, g, 0), "graph instantiate"))
      return;
    cudaGraphDestroy(g);
  }
  time_launches(st, [&] { return graph ? cudaGraphLaunch(exec, nullptr) : plan->launch(din, dqdd, failed, nullptr); });
  Index bad = 0;
  const std::vector<S> qdd = dev.result(bad);
  set<S>(st, n, B, error_of(qdd, *in), bad);
  if (exec) cudaGraphExecDestroy(exec);
  cudaStreamDestroy(stream);
}

std::vector<std::unique_ptr<Model>> g_models;

// The hybrid's busy intervals on rope:n, one instance, the host part on all threads:
// "timeline,<precision>,<lane>,<event>,<c_lo>,<c_hi>,<start_ms>,<end_ms>" (lane: gpu, or
// cpu<thread>), for the last of three calls.
template <class S>
void print_hybrid_timeline(Index n) {
  const Model m = make_generated("rope:" + std::to_string(n));
  const auto in = inputs<S>(m, 1);
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  cuda::CudaForwardDynamics<S> fd(m.cast<S>(), o, FdMethod::Hybrid);
  fd.record_timeline(true);
  const std::vector<S> q(in->q.begin(), in->q.end()), qd(in->qd.begin(), in->qd.end()), tau(in->tau.begin(), in->tau.end());
  std::vector<S> qdd(q.size());
  using V = BatchView<const S>;
  const FdBatchIn<S> hin{V::soa(q.data(), n, 1), V::soa(qd.data(), n, 1), V::soa(tau.data(), n, 1), nullptr};
  for (int r = 0; r < 3; ++r) fd.compute(hin, BatchView<S>::soa(qdd.data(), n, 1));  // warm, then the last one
  const char* prec = sizeof(S) == 4 ? "float" : "double";
  std::printf("timeline,precision,lane,event,c_lo,c_hi,start_ms,end_ms  (hybrid, %s, rope:%d, one instance, "
              "%d host threads)\n", prec, n, openmp_threads());
  for (const auto& e : fd.timeline()) {
    const std::string lane = e.thread < 0 ? "gpu" : "cpu" + std::to_string(e.thread);
    std::printf("timeline,%s,%s,%s,%d,%d,%.4f,%.4f\n", prec, lane.c_str(), e.what.c_str(), e.c_lo, e.c_hi, e.start_ms,
                e.end_ms);
  }
}

}  // namespace

int main(int argc, char** argv) {
  long max_links = 1000000;
  std::vector<char*> rest;
  for (int i = 0; i < argc; ++i) {
    if (std::strncmp(argv[i], "--max-links=", 12) == 0) max_links = std::atol(argv[i] + 12);
    else rest.push_back(argv[i]);
  }
  const auto count = cuda::device_count();
  if (!count || count.value == 0) {
    std::fprintf(stderr, "bench_cuda_chain_fd: %s; nothing to run\n",
                 count ? "no CUDA device: the CUDA runtime reports 0 devices" : count.error.c_str());
    return 0;
  }
  print_device_and_roofline("bench_cuda_chain_fd");
  print_hybrid_timeline<float>(static_cast<Index>(std::min<long>(max_links, 1000000)));
  print_hybrid_timeline<double>(static_cast<Index>(std::min<long>(max_links, 1000000)));

  for (long N = 10; N <= max_links; N *= 10) {
    g_models.push_back(std::make_unique<Model>(make_generated("rope:" + std::to_string(N))));
    const Model* m = g_models.back().get();
    for (int prec = 0; prec < 2; ++prec) {
      const bool fl = prec == 1;
      const std::string tail = std::string(fl ? "float/" : "double/") + m->source;
      auto reg = [&](const std::string& name, auto fn) {
        benchmark::RegisterBenchmark(name.c_str(), fn)->UseManualTime()->Unit(benchmark::kMicrosecond);
      };
      auto regh = [&](const std::string& name, auto fn) {
        benchmark::RegisterBenchmark(name.c_str(), fn)->UseRealTime()->Unit(benchmark::kMicrosecond);
      };
      if (fl) {
        reg("fd_parallel/" + tail + "/cuda", [m](benchmark::State& st) { run_device<float>(st, m, 1, FdMethod::Parallel); });
        regh("fd_parallel-host/" + tail + "/cuda", [m](benchmark::State& st) { run_host<float>(st, m, 1, FdMethod::Parallel); });
        regh("fd_hybrid/" + tail + "/cuda", [m](benchmark::State& st) { run_host<float>(st, m, 1, FdMethod::Hybrid); });
        if (N >= 100000)
          regh("fd_hybrid-t1/" + tail + "/cuda",
               [m](benchmark::State& st) { run_host<float>(st, m, 1, FdMethod::Hybrid, 1); });
        if (N <= 4000)
          reg("fd_jsi/" + tail + "/cuda", [m](benchmark::State& st) { run_device<float>(st, m, 1, FdMethod::Jsi); });
        regh("fd_aba/" + tail + "/serial", [m](benchmark::State& st) { run_serial_aba<float>(st, m); });
      } else {
        reg("fd_parallel/" + tail + "/cuda", [m](benchmark::State& st) { run_device<double>(st, m, 1, FdMethod::Parallel); });
        regh("fd_parallel-host/" + tail + "/cuda", [m](benchmark::State& st) { run_host<double>(st, m, 1, FdMethod::Parallel); });
        regh("fd_hybrid/" + tail + "/cuda", [m](benchmark::State& st) { run_host<double>(st, m, 1, FdMethod::Hybrid); });
        if (N >= 100000)
          regh("fd_hybrid-t1/" + tail + "/cuda",
               [m](benchmark::State& st) { run_host<double>(st, m, 1, FdMethod::Hybrid, 1); });
        if (N <= 4000)
          reg("fd_jsi/" + tail + "/cuda", [m](benchmark::State& st) { run_device<double>(st, m, 1, FdMethod::Jsi); });
        regh("fd_aba/" + tail + "/serial", [m](benchmark::State& st) { run_serial_aba<double>(st, m); });
      }
    }
  }
  // variants: chunk length and fan-in, and a CUDA graph of the default plan
  std::vector<const Model*> variant_models;  // rope:10^4 and the longest
  if (g_models.size() > 3) variant_models.push_back(g_models[3].get());
  if (g_models.size() > 4) variant_models.push_back(g_models.back().get());
  for (const Model* m : variant_models) {
    const std::string tail = std::string("/float/") + m->source + "/cuda";
    for (auto [c, f] : std::vector<std::pair<int, int>>{{4, 4}, {4, 8}, {8, 4}, {16, 4}, {16, 8}, {32, 8}, {8, 16}})
      benchmark::RegisterBenchmark(("fd_parallel-c" + std::to_string(c) + "f" + std::to_string(f) + tail).c_str(),
                                   [m, c = c, f = f](benchmark::State& st) { run_plan<float>(st, m, c, f, false); })
          ->UseManualTime()
          ->Unit(benchmark::kMicrosecond);
    benchmark::RegisterBenchmark(("fd_parallel-graph" + tail).c_str(),
                                 [m](benchmark::State& st) { run_plan<float>(st, m, 0, 0, true); })
        ->UseManualTime()
        ->Unit(benchmark::kMicrosecond);
  }
  // the free rope against the fixed one on the same plan (issue: within 1.2x)
  for (long N = 10000; N <= max_links; N *= 10) {
    for (bool floating : {false, true}) {
      BuildOptions o;
      o.floating_base = floating;
      g_models.push_back(std::make_unique<Model>(make_generated("rope:" + std::to_string(N), o)));
      const Model* m = g_models.back().get();
      const std::string label = m->source + (floating ? "-floating" : "");
      benchmark::RegisterBenchmark(("fd_parallel-plan/float/" + label + "/cuda").c_str(),
                                   [m](benchmark::State& st) { run_plan<float>(st, m, 0, 0, false); })
          ->UseManualTime()
          ->Unit(benchmark::kMicrosecond);
      benchmark::RegisterBenchmark(("fd_parallel-plan/double/" + label + "/cuda").c_str(),
                                   [m](benchmark::State& st) { run_plan<double>(st, m, 0, 0, false); })
          ->UseManualTime()
          ->Unit(benchmark::kMicrosecond);
    }
  }
  // batches of rope:1000
  g_models.push_back(std::make_unique<Model>(make_generated("rope:1000")));
  const Model* r1000 = g_models.back().get();
  for (long B : {10L, 100L, 1000L}) {
    benchmark::RegisterBenchmark(("fd_parallel/float/rope:1000/cuda/B" + std::to_string(B)).c_str(),
                                 [r1000, B](benchmark::State& st) { run_device<float>(st, r1000, B, FdMethod::Parallel); })
        ->UseManualTime()
        ->Unit(benchmark::kMicrosecond);
  }
  int rargc = static_cast<int>(rest.size());
  benchmark::Initialize(&rargc, rest.data());
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
