// Forward dynamics of closed loops (ConstrainedForwardDynamics) on the GPU, one thread
// per instance, against the OpenMP engine on this host: the five-bar and the
// four-bar, batches of 10^3 .. 10^6 instances.
//
// Rows (names as scripts/bench_results.py reads them):
//   loop_fd/<precision>/<model>/cuda/B<B>     compute_async on device buffers (events
//                                             around the launch);
//   loop_fd-host/<precision>/<model>/cuda/B<B> compute() from host buffers (copies in
//                                             and out included);
//   loop_fd/<precision>/<model>/openmp/B<B>   the OpenMP engine (every host thread).
// Inputs: K = 1024 random closed states (q near 0 moved onto the loops by
// project_to_loops, qd in J's null space, tau in [-1, 1]), instance b taking state
// b mod K, structure-of-arrays. max_rel_err: qdd and lambda of every K-th instance
// against the Eigen reference constrained_forward_dynamics (double) on the same
// (precision-rounded) inputs. Counters: dofs, rows, instances, max_rel_err, failed.
//
// Flags (before Google Benchmark's): --max-instances=N (default 10^6).
#include <benchmark/benchmark.h>
#include <cuda_runtime.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "cuda_bench_util.hpp"
#include "scandyn/algorithm/loops.hpp"
#include "scandyn/cuda/constrained_dynamics.hpp"
#include "scandyn/model/load.hpp"

using namespace scandyn;
using namespace scandyn::bench;

namespace {

constexpr Index kStates = 1024;

// K closed states of a model (instance-major, double) and their reference qdd, lambda.
struct States {
  Model model;
  LoopSet loops;
  std::vector<double> q, qd, tau;  // (K x nv)
  explicit States(const std::string& spec) : model(load_model(spec)), loops(generator_loops(spec, model)) {
    const Index n = model.nv();
    std::mt19937_64 rng(7);
    std::uniform_real_distribution<double> u(-1, 1);
    for (Index k = 0; k < kStates; ++k) {
      std::vector<double> qk(n), qdk(n);
      double r = 1;
      while (r > 1e-12) {
        for (Index i = 0; i < n; ++i) qk[i] = 0.2 * u(rng), qdk[i] = u(rng);
        r = project_to_loops(model, loops, qk.data(), qdk.data());
      }
      q.insert(q.end(), qk.begin(), qk.end());
      qd.insert(qd.end(), qdk.begin(), qdk.end());
      for (Index i = 0; i < n; ++i) tau.push_back(u(rng));
    }
  }
};

// The B-instance batch of precision S, structure-of-arrays (nv x B): q, qd, tau.
template <class S>
std::vector<S> tiled(const std::vector<double>& x, Index n, Index B) {
  std::vector<S> out(static_cast<std::size_t>(n) * B);
  for (Index b = 0; b < B; ++b)
    for (Index i = 0; i < n; ++i) out[static_cast<std::size_t>(i) * B + b] = S(x[(b % kStates) * n + i]);
  return out;
}

// max rel_err of [qdd, lambda] of instances 0 .. K-1 (soa, nv x B and m x B) against the
// reference on the S-rounded inputs.
template <class S>
double error_of(const States& s, Index B, const std::vector<S>& qdd, const std::vector<S>& lam) {
  const Index n = s.model.nv(), m = s.loops.rows();
  double worst = 0;
  std::vector<double> qi(n), qdi(n), ti(n), ref(n + m), ours(n + m);
  for (Index b = 0; b < std::min(B, kStates); ++b) {
    for (Index i = 0; i < n; ++i)
      qi[i] = double(S(s.q[b * n + i])), qdi[i] = double(S(s.qd[b * n + i])), ti[i] = double(S(s.tau[b * n + i]));
    constrained_forward_dynamics(s.model, s.loops, qi.data(), qdi.data(), ti.data(), ref.data(), ref.data() + n);
    for (Index i = 0; i < n; ++i) ours[i] = double(qdd[static_cast<std::size_t>(i) * B + b]);
    for (Index k = 0; k < m; ++k) ours[n + k] = double(lam[static_cast<std::size_t>(k) * B + b]);
    const double e = rel_err(ours.data(), ref.data(), ref.size());
    if (std::isnan(e)) return e;
    worst = std::fmax(worst, e);
  }
  return worst;
}

void set(benchmark::State& st, const States& s, Index B, double err, Index failed) {
  st.counters["dofs"] = s.model.nv();
  st.counters["rows"] = s.loops.rows();
  st.counters["instances"] = B;
  st.counters["max_rel_err"] = err;
  st.counters["failed"] = failed;
}

template <class S>
void bench_device(benchmark::State& st, const States& s, Index B, bool host) {
  const Index n = s.model.nv(), m = s.loops.rows();
  const ModelTpl<S> ms = s.model.cast<S>();
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  std::unique_ptr<ConstrainedForwardDynamics<S>> e;
  try {
    e = make_constrained_forward_dynamics<S>(ms, s.loops, o);
  } catch (const BackendError& err) {
    st.SkipWithError(err.what());
    return;
  }
  auto* ce = dynamic_cast<cuda::CudaConstrainedForwardDynamics<S>*>(e.get());
  const std::vector<S> q = tiled<S>(s.q, n, B), qd = tiled<S>(s.qd, n, B), tau = tiled<S>(s.tau, n, B);
  std::vector<S> qdd(static_cast<std::size_t>(n) * B), lam(static_cast<std::size_t>(m) * B);
  using V = BatchView<const S>;
  Index failed = 0;
  if (host) {
    const FdBatchIn<S> in{V::soa(q.data(), n, B), V::soa(qd.data(), n, B), V::soa(tau.data(), n, B), nullptr};
    for (auto _ : st) failed = e->compute(in, BatchView<S>::soa(qdd.data(), n, B), BatchView<S>::soa(lam.data(), m, B)).failed;
  } else {
    const std::size_t cn = q.size(), cm = lam.size();
    S* d = nullptr;
    int* df = nullptr;
    if (!cuda_ok(st, cudaMalloc(&d, (4 * cn + cm) * sizeof(S)), "cudaMalloc") ||
        !cuda_ok(st, cudaMalloc(&df, B * sizeof(int)), "cudaMalloc"))
      return;
    cudaMemcpy(d, q.data(), cn * sizeof(S), cudaMemcpyHostToDevice);
    cudaMemcpy(d + cn, qd.data(), cn * sizeof(S), cudaMemcpyHostToDevice);
    cudaMemcpy(d + 2 * cn, tau.data(), cn * sizeof(S), cudaMemcpyHostToDevice);
    const FdBatchIn<S> in{V::soa(d, n, B), V::soa(d + cn, n, B), V::soa(d + 2 * cn, n, B), nullptr};
    const BatchView<S> qv = BatchView<S>::soa(d + 3 * cn, n, B), lv = BatchView<S>::soa(d + 4 * cn, m, B);
    time_launches(st, [&] { return ce->compute_async(in, qv, lv, df, nullptr); });
    cudaMemcpy(qdd.data(), d + 3 * cn, cn * sizeof(S), cudaMemcpyDeviceToHost);
    cudaMemcpy(lam.data(), d + 4 * cn, cm * sizeof(S), cudaMemcpyDeviceToHost);
    std::vector<int> f(static_cast<std::size_t>(B));
    cudaMemcpy(f.data(), df, B * sizeof(int), cudaMemcpyDeviceToHost);
    for (int x : f) failed += x >= 0;
    cudaFree(d);
    cudaFree(df);
  }
  set(st, s, B, error_of<S>(s, B, qdd, lam), failed);
}

template <class S>
void bench_openmp(benchmark::State& st, const States& s, Index B) {
  const Index n = s.model.nv(), m = s.loops.rows();
  const ModelTpl<S> ms = s.model.cast<S>();
  BackendOptions o;
  o.backend = BackendKind::OpenMP;
  o.max_batch = B;
  auto e = make_constrained_forward_dynamics<S>(ms, s.loops, o);
  const std::vector<S> q = tiled<S>(s.q, n, B), qd = tiled<S>(s.qd, n, B), tau = tiled<S>(s.tau, n, B);
  std::vector<S> qdd(static_cast<std::size_t>(n) * B), lam(static_cast<std::size_t>(m) * B);
  using V = BatchView<const S>;
  const FdBatchIn<S> in{V::soa(q.data(), n, B), V::soa(qd.data(), n, B), V::soa(tau.data(), n, B), nullptr};
  Index failed = 0;
  for (auto _ : st) failed = e->compute(in, BatchView<S>::soa(qdd.data(), n, B), BatchView<S>::soa(lam.data(), m, B)).failed;
  set(st, s, B, error_of<S>(s, B, qdd, lam), failed);
}

}  // namespace

int main(int argc, char** argv) {
  Index max_instances = 1000000;
  std::vector<char*> rest{argv[0]};
  for (int i = 1; i < argc; ++i) {
    if (std::strncmp(argv[i], "--max-instances=", 16) == 0) max_instances = std::atol(argv[i] + 16);
    else rest.push_back(argv[i]);
  }
  print_device_and_roofline("bench_cuda_loops");
  static std::vector<std::unique_ptr<States>> models;
  for (const char* spec : {"fivebar", "fourbar"}) models.push_back(std::make_unique<States>(spec));
  for (const auto& sp : models) {
    const States& s = *sp;
    for (Index B = 1000; B <= max_instances; B *= 10) {
      for (int prec = 0; prec < 2; ++prec) {
        const std::string p = prec == 0 ? "float" : "double";
        const std::string tail = "/" + p + "/" + s.model.source + "/";
        const std::string b = "/B" + std::to_string(B);
        auto reg = [&](const std::string& name, auto fn, bool manual) {
          auto* r = benchmark::RegisterBenchmark(name.c_str(), fn);
          (manual ? r->UseManualTime() : r->UseRealTime())->Unit(benchmark::kMicrosecond);
        };
        if (prec == 0) {
          reg("loop_fd" + tail + "cuda" + b, [&s, B](benchmark::State& st) { bench_device<float>(st, s, B, false); }, true);
          reg("loop_fd-host" + tail + "cuda" + b, [&s, B](benchmark::State& st) { bench_device<float>(st, s, B, true); }, false);
          reg("loop_fd" + tail + "openmp" + b, [&s, B](benchmark::State& st) { bench_openmp<float>(st, s, B); }, false);
        } else {
          reg("loop_fd" + tail + "cuda" + b, [&s, B](benchmark::State& st) { bench_device<double>(st, s, B, false); }, true);
          reg("loop_fd-host" + tail + "cuda" + b, [&s, B](benchmark::State& st) { bench_device<double>(st, s, B, true); }, false);
          reg("loop_fd" + tail + "openmp" + b, [&s, B](benchmark::State& st) { bench_openmp<double>(st, s, B); }, false);
        }
      }
    }
  }
  int rargc = static_cast<int>(rest.size());
  benchmark::Initialize(&rargc, rest.data());
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
