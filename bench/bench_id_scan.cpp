// Inverse dynamics through the batched engines: what accuracy costs in time.
//
// Two families, both through make_inverse_dynamics (scandyn/engine.hpp):
//  * ropes, one instance, rope:N for N = 10 .. 10^6: the serial recursion, the
//    local-frame scan and the world-frame scan (one thread each), and the OpenMP
//    scans across links; float and double, with max_rel_err against the double
//    recursion on the same inputs;
//  * trees, one instance: curtain:100:100, curtain:1000:1000 (wide) and
//    tree:100000:1 (random, deep segment tree), recursion vs scans;
//  * iiwa batches, B = 1, 10^3, 10^6 (10^5 with --quick): serial vs OpenMP threads
//    over instances.
// Benchmark names follow scripts/bench_results.py: id_<strategy>/<precision>/<model>/<backend>.
//
// Flags (before Google Benchmark's): --quick (ropes to 10^4, one curtain, iiwa to 10^5),
// --max-rope=N, --models-dir=DIR (default $SCANDYN_MODELS_DIR or the shipped models/).
#include <benchmark/benchmark.h>

#include <cmath>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "scandyn/accuracy.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/model/load.hpp"

#ifdef _OPENMP
#include <omp.h>
#endif

using namespace scandyn;

namespace {

// q, qd, qdd for B instances, nv x B structure of arrays, uniform in [-1, 1]
struct Inputs {
  std::vector<double> q, qd, qdd;
  Inputs(Index nv, Index B) {
    std::mt19937_64 g(7);
    std::uniform_real_distribution<double> u(-1, 1);
    for (auto* v : {&q, &qd, &qdd}) {
      v->resize(static_cast<std::size_t>(nv) * B);
      for (auto& x : *v) x = u(g);
    }
  }
};

// max over instances of max|tau - ref| / max(1, max|ref|), ref = double recursion;
// checked on at most 64 instances.
template <class S>
double max_rel_err(const Model& md, const Inputs& in, const std::vector<S>& tau, Index B) {
  const Index nv = md.nv();
  Data d(md, false);
  std::vector<double> q(nv), qd(nv), qdd(nv), ref(nv), ours(nv);
  double worst = 0;
  const Index step = B > 64 ? B / 64 : 1;
  for (Index b = 0; b < B; b += step) {
    for (Index i = 0; i < nv; ++i) {
      const std::size_t k = static_cast<std::size_t>(i) * B + b;
      q[i] = double(S(in.q[k]));
      qd[i] = double(S(in.qd[k]));
      qdd[i] = double(S(in.qdd[k]));
    }
    rnea(md, d, q.data(), qd.data(), qdd.data(), ref.data());
    for (Index i = 0; i < nv; ++i) ours[i] = double(tau[static_cast<std::size_t>(i) * B + b]);
    const double e = rel_err(ours.data(), ref.data(), ref.size());
    if (std::isnan(e)) return e;
    worst = std::fmax(worst, e);
  }
  return worst;
}

template <class S>
void bench(benchmark::State& state, const Model* md, BackendKind backend, IdStrategy strategy, Index B) {
  const ModelTpl<S> m = md->cast<S>();
  const Index nv = m.nv();
  const Inputs in(nv, B);
  const std::vector<S> q(in.q.begin(), in.q.end()), qd(in.qd.begin(), in.qd.end()), qdd(in.qdd.begin(), in.qdd.end());
  std::vector<S> tau(q.size(), std::numeric_limits<S>::quiet_NaN());
  BackendOptions o;
  o.backend = backend;
  o.strategy = strategy;
  o.max_batch = B;
  auto engine = make_inverse_dynamics<S>(m, o);
  const IdBatchIn<S> batch{BatchView<const S>::soa(q.data(), nv, B), BatchView<const S>::soa(qd.data(), nv, B),
                           BatchView<const S>::soa(qdd.data(), nv, B)};
  const BatchView<S> out = BatchView<S>::soa(tau.data(), nv, B);
  for (auto _ : state) {
    engine->compute(batch, out);
    benchmark::ClobberMemory();
  }
  state.counters["links"] = nv;
  state.counters["instances"] = B;
  state.counters["max_rel_err"] = max_rel_err<S>(*md, in, tau, B);
#ifdef _OPENMP
  state.counters["threads"] = backend == BackendKind::OpenMP ? omp_get_max_threads() : 1;
#endif
  state.SetLabel(engine->strategy());
}

std::vector<std::unique_ptr<Model>> g_models;  // outlive the registered benchmarks

const Model* keep(Model m) {
  g_models.push_back(std::make_unique<Model>(std::move(m)));
  return g_models.back().get();
}

void add(const std::string& model_label, const Model* m, BackendKind backend, IdStrategy s, Index B,
         double min_time) {
  const std::string strat = s == IdStrategy::Recursion ? "recursion" : s == IdStrategy::ScanLocal ? "scan-local" : "scan-world";
  for (int prec = 0; prec < 2; ++prec) {
    const std::string name = "id_" + strat + (prec ? "/float/" : "/double/") + model_label + "/" + to_string(backend);
    auto* b = prec ? benchmark::RegisterBenchmark(name.c_str(), [=](benchmark::State& st) { bench<float>(st, m, backend, s, B); })
                   : benchmark::RegisterBenchmark(name.c_str(), [=](benchmark::State& st) { bench<double>(st, m, backend, s, B); });
    b->UseRealTime()->Unit(benchmark::kMicrosecond)->MinTime(min_time);
  }
}

}  // namespace

int main(int argc, char** argv) {
  bool quick = false;
  long max_rope = 1000000;
  const std::vector<std::string> dirs = model_search_dirs();  // $SCANDYN_MODELS_DIR, the shipped models
  std::string models_dir = dirs.empty() ? "models" : dirs.front();
  std::vector<char*> rest;
  for (int i = 0; i < argc; ++i) {
    if (std::strcmp(argv[i], "--quick") == 0) quick = true;
    else if (std::strncmp(argv[i], "--max-rope=", 11) == 0) max_rope = std::atol(argv[i] + 11);
    else if (std::strncmp(argv[i], "--models-dir=", 13) == 0) models_dir = argv[i] + 13;
    else rest.push_back(argv[i]);
  }
  if (quick) max_rope = std::min(max_rope, 10000L);
  const bool omp = SCANDYN_HAS_OPENMP;

  for (long n = 10; n <= max_rope; n *= 10) {
    const std::string label = "rope:" + std::to_string(n);
    const Model* m = keep(load_model(label));
    const double t = n >= 100000 ? 0.5 : 0.2;
    for (IdStrategy s : {IdStrategy::Recursion, IdStrategy::ScanLocal, IdStrategy::ScanWorld})
      add(label, m, BackendKind::Serial, s, 1, t);
    if (omp)
      for (IdStrategy s : {IdStrategy::ScanLocal, IdStrategy::ScanWorld}) add(label, m, BackendKind::OpenMP, s, 1, t);
  }
  // trees: wide (curtains: many independent segments) and random (short segments,
  // many levels of the segment tree)
  for (const char* spec : {"curtain:100:100", "curtain:1000:1000", "tree:100000:1"}) {
    if (quick && std::string(spec) != "curtain:100:100") continue;
    const Model* m = keep(load_model(spec));
    add(spec, m, BackendKind::Serial, IdStrategy::Recursion, 1, 0.3);
    add(spec, m, BackendKind::Serial, IdStrategy::ScanLocal, 1, 0.3);
    if (omp)
      for (IdStrategy s : {IdStrategy::ScanLocal, IdStrategy::ScanWorld}) add(spec, m, BackendKind::OpenMP, s, 1, 0.3);
  }
  try {
    const Model* iiwa = keep(load_urdf(models_dir + "/iiwa.urdf"));
    for (Index B : {Index(1), Index(1000), Index(quick ? 100000 : 1000000)}) {
      add("iiwa", iiwa, BackendKind::Serial, IdStrategy::Recursion, B, 0.3);
      if (omp) add("iiwa", iiwa, BackendKind::OpenMP, IdStrategy::Recursion, B, 0.3);
    }
  } catch (const ModelError& e) {
    std::fprintf(stderr, "bench_id_scan: skipping iiwa: %s\n", e.what());
  }
  int rargc = static_cast<int>(rest.size());
  benchmark::Initialize(&rargc, rest.data());
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
