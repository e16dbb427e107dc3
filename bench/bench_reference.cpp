// Serial reference algorithms, one call on one state: RNEA, CRBA, ABA and
// CRBA + Cholesky forward dynamics, double and float, on the robots and rope:1000.
//
// Each benchmark cycles through 64 random states and reports the counters
// scripts/bench_results.py turns into bench/results rows: links, instances and
// max_rel_err (float against the double reference of the same algorithm; JSI
// forward dynamics against double ABA).
//
// Models: $SCANDYN_MODELS_DIR (default: the shipped models/) for the URDFs, or the list
// given with --models=a.urdf,rope:1000 (before the Google Benchmark flags).
#include <benchmark/benchmark.h>

#include <cmath>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <iostream>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "scandyn/accuracy.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/model/load.hpp"

using namespace scandyn;

namespace {

constexpr int kStates = 64;

struct States {
  int n = 0;
  std::vector<double> q, qd, x;  // (kStates x n): positions, velocities, qdd or tau
};

States random_states(int n) {
  States s;
  s.n = n;
  std::mt19937_64 g(42);
  std::uniform_real_distribution<double> d(-1, 1);
  for (auto* v : {&s.q, &s.qd, &s.x}) {
    v->resize(static_cast<std::size_t>(kStates) * n);
    for (auto& e : *v) e = d(g);
  }
  return s;
}

enum class Algo { Id, Mass, Aba, Jsi };
const char* algo_name(Algo a) {
  switch (a) {
    case Algo::Id: return "id_recursion";
    case Algo::Mass: return "mass_crba";
    case Algo::Aba: return "fd_aba";
    case Algo::Jsi: return "fd_jsi";
  }
  return "?";
}

// Runs algorithm a on state k; out has n (or n*n for mass) entries.
template <class S>
void run(Algo a, const ModelTpl<S>& m, DataTpl<S>& d, const S* q, const S* qd, const S* x, S* out) {
  switch (a) {
    case Algo::Id: rnea(m, d, q, qd, x, out); break;
    case Algo::Mass: crba(m, d, q, out); break;
    case Algo::Aba: aba(m, d, q, qd, x, out); break;
    case Algo::Jsi: fd_jsi(m, d, q, qd, x, out); break;
  }
}

// max over states of max|x - ref| / max(1, max|ref|), against the double reference
// (ABA for both forward-dynamics variants).
template <class S>
double max_rel_err(Algo a, const Model& md, const ModelTpl<S>& m, const States& st) {
  const int n = st.n;
  const std::size_t len = a == Algo::Mass ? std::size_t(n) * n : std::size_t(n);
  Data dd(md);
  DataTpl<S> d(m);
  std::vector<double> ref(len);
  std::vector<S> out(len);
  const Algo ref_algo = a == Algo::Jsi ? Algo::Aba : a;
  double worst = 0;
  for (int k = 0; k < kStates; ++k) {
    const std::size_t o = std::size_t(k) * n;
    run<double>(ref_algo, md, dd, &st.q[o], &st.qd[o], &st.x[o], ref.data());
    std::vector<S> q(&st.q[o], &st.q[o] + n), qd(&st.qd[o], &st.qd[o] + n), x(&st.x[o], &st.x[o] + n);
    run<S>(a, m, d, q.data(), qd.data(), x.data(), out.data());
    const double e = rel_err(out.data(), ref.data(), len);
    if (std::isnan(e)) return e;
    worst = std::fmax(worst, e);
  }
  return worst;
}

template <class S>
void bench(benchmark::State& state, const Model& md, Algo a) {
  const ModelTpl<S> m = md.cast<S>();
  DataTpl<S> d(m);
  const int n = m.nv();
  const States st = random_states(n);
  const std::vector<S> q(st.q.begin(), st.q.end()), qd(st.qd.begin(), st.qd.end()),
      x(st.x.begin(), st.x.end());
  std::vector<S> out(a == Algo::Mass ? std::size_t(n) * n : std::size_t(n));
  int k = 0;
  for (auto _ : state) {
    const std::size_t o = std::size_t(k) * n;
    run<S>(a, m, d, &q[o], &qd[o], &x[o], out.data());
    benchmark::DoNotOptimize(out.data());
    benchmark::ClobberMemory();
    k = (k + 1) % kStates;
  }
  state.counters["links"] = n;
  state.counters["instances"] = 1;
  state.counters["max_rel_err"] = max_rel_err<S>(a, md, m, st);
}

// $SCANDYN_MODELS_DIR, else the shipped models (scandyn::model_search_dirs)
std::string default_models_dir() {
  const std::vector<std::string> dirs = scandyn::model_search_dirs();
  return dirs.empty() ? "models" : dirs.front();
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<std::string> specs;
  std::vector<char*> rest;
  for (int i = 0; i < argc; ++i) {
    if (std::strncmp(argv[i], "--models=", 9) == 0) {
      std::string list = argv[i] + 9;
      for (std::size_t p = 0; p <= list.size();) {
        const std::size_t c = std::min(list.find(',', p), list.size());
        specs.push_back(list.substr(p, c - p));
        p = c + 1;
      }
    } else {
      rest.push_back(argv[i]);
    }
  }
  if (specs.empty()) {
    const std::string dir = default_models_dir();
    specs = {dir + "/iiwa.urdf", dir + "/hyq.urdf", dir + "/atlas.urdf", "rope:1000"};
  }
  static std::vector<Model> models;  // outlive the registered benchmarks
  models.reserve(specs.size());
  try {
    // the public benchmark models as they are: GRiD's atlas.urdf has non-physical inertias
    BuildOptions lenient;
    lenient.require_physical_inertia = false;
    for (const auto& s : specs) models.push_back(load_model(s, lenient));
  } catch (const ModelError& e) {
    std::cerr << "bench_reference: " << e.what() << "\n";
    return 1;
  }
  for (std::size_t i = 0; i < models.size(); ++i) {
    std::string label = specs[i];
    const std::size_t slash = label.find_last_of('/');
    if (slash != std::string::npos) label = label.substr(slash + 1);
    if (label.size() > 5 && label.compare(label.size() - 5, 5, ".urdf") == 0) label.resize(label.size() - 5);
    const Model& md = models[i];
    for (Algo a : {Algo::Id, Algo::Mass, Algo::Aba, Algo::Jsi}) {
      benchmark::RegisterBenchmark((std::string(algo_name(a)) + "/double/" + label).c_str(),
                                   [&md, a](benchmark::State& s) { bench<double>(s, md, a); });
      benchmark::RegisterBenchmark((std::string(algo_name(a)) + "/float/" + label).c_str(),
                                   [&md, a](benchmark::State& s) { bench<float>(s, md, a); });
    }
  }
  int rargc = static_cast<int>(rest.size());
  benchmark::Initialize(&rargc, rest.data());
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
