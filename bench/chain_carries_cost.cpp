// bench/chain_carries_cost.cpp: the host part of the hybrid forward dynamics
// (cuda::ChainFdPlan::launch_hybrid): the articulated inertias at the chunk
// boundaries of rope:N, one instance, chunks of 8 links (the CUDA plan's), by
// ChainInertiaCarries (scandyn/algorithm/chain_fd.hpp) on 1 thread (the serial
// recursion the hybrid ran before, inertia_carry_walk) and on T threads, next to the
// two costs its schedule is made of: the reduction of every link to pass 1's dual
// Riccati aggregate (dual_aggregate, one thread) and one application of an aggregate
// (the combine's step).
//
// Usage: chain_carries_cost [--rounds R] [--threads T1,T2,...] [--models rope:N,...]
//                           [--estimate T,...]
//   defaults: 7 rounds, threads 2, rope:100000 and rope:1000000, estimate 16.
// Every round runs every configuration once (interleaved); the row keeps the fastest
// and the median of the rounds. CSV on stdout, after '#' lines naming the program,
// the machine (CPU model, cores, load average) and the command.
//
// Columns: model, precision, config, threads, links, ms_fastest, ms_median,
// ns_per_link (fastest / links), note.
//   config serial     ChainInertiaCarries with 1 thread
//   config reduce     dual_aggregate over every link, 1 thread
//   config apply      one DualRiccati::apply (ms_* in ms per application)
//   config threads    ChainInertiaCarries with T threads (note: threads used, and the
//                     last round's phases: tip walk, reduction, combine, walks, in ms)
//   config reduce-par T threads at once, each dual_aggregate over its own N / T links
//                     (links = N / T: ns_per_link is one thread's cost per link; against
//                     the reduce row, how the reduction scales on this machine)
//                     (in a FlushDenormalsScope, as ChainInertiaCarries reduces; the
//                     reduce row too)
//   config reduce-par-subnormal  the same without it (subnormals computed: on Intel
//                     x86 each costs a microcode assist)
//   config walk-par   the same for inertia_carry_walk over C / T chunks each
//   config estimate   NOT MEASURED: (1 + r) N / (T + r) t_walk + (T - 1) t_apply with
//                     r = reduce / serial per link measured here, t_walk the serial
//                     row's ns per link, t_apply the apply row's; for a thread count
//                     this machine lacks (the GPU machine's host: 16 cores). note
//                     gives the same model at the measured thread counts next to the
//                     measurement (its overhead).
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <memory>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include "scandyn/algorithm/chain_fd.hpp"
#include "scandyn/flush_denormals.hpp"
#include "scandyn/model/load.hpp"
#include "plain_bench_util.hpp"

#if defined(_OPENMP)
#include <omp.h>
#endif

using namespace scandyn;

namespace {

using bench::first_line_with;
using bench::ms_of;
using Clock = std::chrono::steady_clock;

Index this_thread() {
#if defined(_OPENMP)
  return omp_get_thread_num();
#else
  return 0;
#endif
}

struct Row {
  std::string model, precision, config;
  int threads = 1;
  Index links = 0;
  std::vector<double> ms;
  std::string note;
  double fastest() const { return bench::fastest_of(ms); }
  double median() const { return bench::median_of(ms); }
};

template <class S>
struct Rope {
  ChainBodies<S> bodies;
  std::vector<S> q;
  ChainFdData<S> d;
  explicit Rope(const Model& m) {
    const ModelTpl<S> ms = m.cast<S>();
    const Index n = ms.nbodies();
    bodies = ChainBodies<S>::from(ms, 1);
    std::mt19937_64 rng(42);
    std::uniform_real_distribution<double> u(-1, 1);
    q.resize(static_cast<std::size_t>(n));
    for (auto& x : q) x = static_cast<S>(u(rng));
    d.n = n;
    d.batch = 1;
    d.q = BatchView<const S>::soa(q.data(), n, 1);
    d.body = bodies.body.data();
    d.Phi = bodies.Phi.data();
    d.body_class = bodies.body_class.data();
  }
};

template <class S>
void measure(const Model& m, int rounds, const std::vector<int>& threads, std::vector<Row>& rows) {
  const char* prec = sizeof(S) == 4 ? "float" : "double";
  const Rope<S> rope(m);
  const ChainFdData<S>& d = rope.d;
  const Index N = d.count(), chunk = 8, C = (N + chunk - 1) / chunk;
  std::vector<ABInertia<S>> out(static_cast<std::size_t>(C));
  ChainInertiaCarries<S> serial(1);
  std::vector<std::unique_ptr<ChainInertiaCarries<S>>> par;
  for (int t : threads) par.push_back(std::make_unique<ChainInertiaCarries<S>>(t));
  const std::size_t base = rows.size();
  rows.push_back({m.source, prec, "serial", 1, N, {}, ""});
  rows.push_back({m.source, prec, "reduce", 1, N, {}, ""});
  rows.push_back({m.source, prec, "apply", 1, N, {}, ""});
  for (int t : threads) rows.push_back({m.source, prec, "threads", t, N, {}, ""});
  // the machine's scaling of the two kernels the schedule is made of: t threads each on
  // its own 1/t of the links at once (links = N / t, so ns_per_link is a thread's)
  const std::size_t scaling = rows.size();
  for (int t : threads) {
    rows.push_back({m.source, prec, "reduce-par", t, N / t, {}, "t threads, each dual_aggregate over its own N / t links"});
    rows.push_back({m.source, prec, "reduce-par-subnormal", t, N / t, {},
                    "the same without FlushDenormalsScope (subnormals computed)"});
    rows.push_back({m.source, prec, "walk-par", t, N / t, {}, "t threads, each inertia_carry_walk over its own C / t chunks"});
  }
  // an aggregate to apply: the first 64 links'
  const DualRiccati<DualScalar> agg = dual_aggregate(d, 0, std::min<Index>(N, 64) - 1);
  Mat5<DualScalar> Y = dual_aggregate(d, std::min<Index>(N, 64), std::min<Index>(N, 128) - 1).apply(Mat5<DualScalar>::identity());
  volatile double sink = 0;
  for (int r = 0; r < rounds; ++r) {
    rows[base + 0].ms.push_back(ms_of([&] { serial.compute(d, chunk, out.data()); }));
    rows[base + 1].ms.push_back(ms_of([&] {
      const FlushDenormalsScope flush;  // as ChainInertiaCarries reduces
      sink = sink + dual_aggregate(d, 0, N - 1).Q.m[0];
    }));
    const int reps = 10000;
    rows[base + 2].ms.push_back(ms_of([&] {
                                  Mat5<DualScalar> y = Y;
                                  for (int k = 0; k < reps; ++k) y = agg.apply(y);
                                  sink = sink + y.m[0];
                                }) /
                                reps);
    for (std::size_t k = 0; k < threads.size(); ++k) {
      const int t = threads[k];
      std::vector<double> sinks(static_cast<std::size_t>(t), 0.0);
      // t threads at once, each reducing its 1/t of the links, subnormals flushed or not
      const auto reduce_par = [&](bool flush) {
        return ms_of([&] {
#pragma omp parallel num_threads(t)
          {
            const Index j = this_thread();
            std::optional<FlushDenormalsScope> scope;
            if (flush) scope.emplace();
            if (j < t) sinks[static_cast<std::size_t>(j)] += dual_aggregate(d, j * N / t, (j + 1) * N / t - 1).Q.m[0];
          }
        });
      };
      rows[scaling + 3 * k].ms.push_back(reduce_par(true));
      rows[scaling + 3 * k + 2].ms.push_back(ms_of([&] {
#pragma omp parallel num_threads(t)
        {
          const Index j = this_thread();
          if (j < t) {
            ABInertia<S> Ia{}, IA_first{};
            Transform<S> X = Transform<S>::identity();
            inertia_carry_walk(d, chunk, j * C / t, (j + 1) * C / t, out.data(), Ia, X, IA_first);
          }
        }
      }));
      rows[scaling + 3 * k + 1].ms.push_back(reduce_par(false));
      for (double x : sinks) sink = sink + x;
    }
    for (std::size_t k = 0; k < threads.size(); ++k) {
      ChainInertiaCarries<S>& c = *par[k];
      const auto origin = Clock::now();
      rows[base + 3 + k].ms.push_back(ms_of([&] { c.compute(d, chunk, out.data(), nullptr, nullptr, &origin); }));
      // the last round's phases
      double tip = 0, reduce = 0, combine_end = 0, end = 0;
      for (const auto& iv : c.intervals()) {
        if (iv.start_ms < 0) continue;
        end = std::max(end, iv.end_ms);
        if (iv.kind == ChainCarryInterval::Reduce) reduce = std::max(reduce, iv.end_ms);
        if (iv.kind == ChainCarryInterval::Combine) combine_end = iv.end_ms;
        if (iv.kind == ChainCarryInterval::Walk && iv.c_hi == C) tip = std::max(tip, iv.end_ms);
      }
      char note[200];
      std::snprintf(note, sizeof note, "used %d; phases (ms from start): tip walk group 0 ends %.2f, reductions end %.2f, "
                    "combine ends %.2f, walks end %.2f", c.threads_used(), tip, reduce, combine_end, end);
      rows[base + 3 + k].note = note;
    }
  }
}

void print_row(const Row& r) {
  std::printf("%s,%s,%s,%d,%d,%.4f,%.4f,%.2f,\"%s\"\n", r.model.c_str(), r.precision.c_str(), r.config.c_str(), r.threads,
              r.links, r.fastest(), r.median(), r.fastest() * 1e6 / r.links, r.note.c_str());
}

}  // namespace

int main(int argc, char** argv) {
  int rounds = 7;
  std::vector<int> threads{2}, estimate{16};
  std::vector<std::string> models{"rope:100000", "rope:1000000"};
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "chain_carries_cost: %s needs a value\n", a.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--rounds") rounds = std::max(1, std::atoi(next().c_str()));
    else if (a == "--threads" || a == "--estimate") {
      std::vector<int>& v = a == "--threads" ? threads : estimate;
      v.clear();
      for (const auto& s : bench::split_list(next())) v.push_back(std::max(1, std::atoi(s.c_str())));
    } else if (a == "--models") models = bench::split_list(next());
    else {
      std::fprintf(stderr, "usage: chain_carries_cost [--rounds R] [--threads T,...] [--models rope:N,...] [--estimate T,...]\n");
      return 2;
    }
  }
  std::string cmd = argv[0];
  for (int i = 1; i < argc; ++i) cmd += std::string(" ") + argv[i];
  std::printf("# chain_carries_cost: ChainInertiaCarries (the hybrid's host pass 1), chunks of 8 links, one instance\n");
  std::printf("# machine: %s, %s, openmp_threads() %d\n", first_line_with("/proc/cpuinfo", "model name").c_str(),
              first_line_with("/proc/cpuinfo", "cpu cores").c_str(), openmp_threads());
  std::ifstream load("/proc/loadavg");
  std::string la;
  std::getline(load, la);
  std::printf("# load average at start: %s\n", la.c_str());
  std::printf("# command: %s\n", cmd.c_str());
  std::printf("model,precision,config,threads,links,ms_fastest,ms_median,ns_per_link,note\n");
  for (const auto& spec : models) {
    const Model m = make_generated(spec);
    for (int p = 0; p < 2; ++p) {
      std::vector<Row> rows;
      if (p == 0) measure<double>(m, rounds, threads, rows);
      else measure<float>(m, rounds, threads, rows);
      for (const auto& r : rows) print_row(r);
      // the model of the schedule from the single-thread costs
      const double tw = rows[0].fastest() / rows[0].links, r = rows[1].fastest() / rows[0].fastest(),
                   ta = rows[2].fastest();
      auto model_ms = [&](int T) { return (1 + r) * rows[0].links / (T + r) * tw + (T - 1) * ta; };
      std::string check;
      for (std::size_t k = 3; k < rows.size(); ++k) {
        if (rows[k].config != "threads") continue;
        char b[120];
        std::snprintf(b, sizeof b, "%sT=%d model %.3f ms vs measured %.3f ms", check.empty() ? "" : "; ", rows[k].threads,
                      model_ms(rows[k].threads), rows[k].fastest());
        check += b;
      }
      for (int T : estimate) {
        char b[400];
        std::snprintf(b, sizeof b, "ESTIMATE, not measured: (1 + r) N / (T + r) t_walk + (T - 1) t_apply, r = %.2f, "
                      "t_walk = %.2f ns, t_apply = %.2f us; %s", r, tw * 1e6, ta * 1e3, check.c_str());
        Row e{rows[0].model, rows[0].precision, "estimate", T, rows[0].links, {model_ms(T)}, b};
        print_row(e);
      }
    }
  }
  return 0;
}
