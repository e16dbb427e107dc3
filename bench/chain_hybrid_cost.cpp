// bench/chain_hybrid_cost.cpp: the parallel chain hybrid dynamics on the host
// (ChainHybridDynamics, scandyn/algorithm/chain_hybrid.hpp) on rope:N, one instance,
// per prescribed pattern and thread count, next to the serial hybrid_dynamics (the
// recursion, one thread). What it is for: the cost of long prescribed runs (before the
// rigid-composite scan each chunk boundary inside a run walked to the run's end), and
// of the run scan where runs are short.
//
// Usage: chain_hybrid_cost [--rounds R] [--threads T1,T2,...] [--models rope:N,...]
//                          [--masks all,none,run,sparse,random30] [--precision double|float|both]
//                          [--runs auto,on,off]
//   defaults: 5 rounds, threads 1,2, rope:5000 and rope:20000, every mask, double, runs auto.
// Every round runs every configuration once (interleaved); the row keeps the fastest
// and the median of the rounds. CSV on stdout, after '#' lines naming the program,
// the machine (CPU model, cores, load average) and the command.
//
// Masks (nonzero: the DoF's acceleration is given):
//   all       every DoF prescribed (inverse dynamics through the hybrid)
//   none      no DoF prescribed (forward dynamics through the hybrid)
//   run       one run, DoFs N/20 .. N - N/20 - 1 (90% of the rope)
//   sparse    every 100th DoF (the common case: few prescribed DoFs, runs of one)
//   random30  each DoF with probability 0.3 (short runs)
//
// Runs (HybridRunScan): auto, the runs' composites scanned when the longest run exceeds
// kScanRunChunks chunks (hybrid_scans_runs); on, always scanned; off, walked per chunk
// boundary (O(run^2 / chunk) on long runs).
//
// Columns: model, mask, precision, config, threads, chunk, links, longest_run,
// ms_fastest, ms_median, ns_per_link (fastest / links), note.
//   config chain-auto, chain-on, chain-off
//                     ChainHybridDynamics with `threads` threads (chunk: its default)
//                     and that run scan (note: scanned or walked)
//   config serial     the serial hybrid_dynamics (the reference recursion), 1 thread
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "scandyn/algorithm/chain_hybrid.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/model/load.hpp"
#include "plain_bench_util.hpp"

using namespace scandyn;

namespace {

using bench::first_line_with;
using bench::ms_of;

std::vector<unsigned char> make_mask(const std::string& name, Index n) {
  std::vector<unsigned char> m(static_cast<std::size_t>(n), 0);
  if (name == "all") std::fill(m.begin(), m.end(), 1);
  else if (name == "none") {
  } else if (name == "run") {
    for (Index i = n / 20; i < n - n / 20; ++i) m[i] = 1;
  } else if (name == "sparse") {
    for (Index i = 0; i < n; i += 100) m[i] = 1;
  } else if (name == "random30") {
    std::mt19937_64 g(7);
    std::bernoulli_distribution coin(0.3);
    for (auto& x : m) x = coin(g);
  } else {
    std::fprintf(stderr, "chain_hybrid_cost: unknown mask '%s' (all, none, run, sparse, random30)\n", name.c_str());
    std::exit(2);
  }
  return m;
}

struct Row {
  std::string model, mask, precision, config;
  int threads = 1;
  Index chunk = 0, links = 0, run = 0;
  std::vector<double> ms;
  std::string note;
  double fastest() const { return bench::fastest_of(ms); }
  double median() const { return bench::median_of(ms); }
};

HybridRunScan parse_runs(const std::string& r) {
  if (r == "auto") return HybridRunScan::Auto;
  if (r == "on") return HybridRunScan::On;
  if (r == "off") return HybridRunScan::Off;
  std::fprintf(stderr, "chain_hybrid_cost: unknown --runs '%s' (auto, on, off)\n", r.c_str());
  std::exit(2);
}

template <class S>
void measure(const Model& model, const std::string& mask_name, int rounds, const std::vector<int>& threads,
             const std::vector<std::string>& runs, std::vector<Row>& rows) {
  const char* prec = sizeof(S) == 4 ? "float" : "double";
  const ModelTpl<S> m = model.cast<S>();
  const Index n = m.nv();
  const std::vector<unsigned char> mask = make_mask(mask_name, n);
  std::mt19937_64 rng(42);
  std::uniform_real_distribution<double> u(-1, 1);
  std::vector<S> q(n), qd(n), a(n), t(n), qdd(n), tau(n);
  for (Index i = 0; i < n; ++i) q[i] = S(u(rng)), qd[i] = S(u(rng)), a[i] = S(u(rng)), t[i] = S(u(rng));
  using V = BatchView<const S>;
  const HybridBatchIn<S> in{V::soa(q.data(), n, 1), V::soa(qd.data(), n, 1), V::soa(a.data(), n, 1),
                            V::soa(t.data(), n, 1), nullptr};
  std::vector<std::unique_ptr<ChainHybridDynamics<S>>> engines;
  const std::size_t base = rows.size();
  const Index run = longest_prescribed_run(mask);
  for (const std::string& r : runs)
    for (int th : threads) {
      engines.push_back(std::make_unique<ChainHybridDynamics<S>>(m, mask, 1, th, 0, parse_runs(r)));
      const ChainHybridDynamics<S>& e = *engines.back();
      rows.push_back({model.source, mask_name, prec, "chain-" + r, th, e.chunk(), n, run, {},
                      e.scans_runs() ? "runs scanned" : "runs walked"});
    }
  rows.push_back({model.source, mask_name, prec, "serial", 1, 0, n, run, {}, "hybrid_dynamics"});
  DataTpl<S> data(m, false);
  for (int r = 0; r < rounds; ++r) {
    for (std::size_t k = 0; k < engines.size(); ++k) {
      ChainHybridDynamics<S>& e = *engines[k];
      rows[base + k].ms.push_back(ms_of([&] {
        if (e.compute(in, BatchView<S>::soa(qdd.data(), n, 1), BatchView<S>::soa(tau.data(), n, 1)) != 0) {
          std::fprintf(stderr, "chain_hybrid_cost: a pivot failed\n");
          std::exit(1);
        }
      }));
    }
    rows[base + engines.size()].ms.push_back(ms_of([&] {
      const Status st =
          hybrid_dynamics(m, data, q.data(), qd.data(), mask.data(), a.data(), t.data(), qdd.data(), tau.data());
      if (!st.ok()) {
        std::fprintf(stderr, "chain_hybrid_cost: the serial hybrid failed\n");
        std::exit(1);
      }
    }));
  }
}

void print_row(const Row& r) {
  std::printf("%s,%s,%s,%s,%d,%d,%d,%d,%.4f,%.4f,%.2f,\"%s\"\n", r.model.c_str(), r.mask.c_str(), r.precision.c_str(),
              r.config.c_str(), r.threads, r.chunk, r.links, r.run, r.fastest(), r.median(),
              r.fastest() * 1e6 / r.links, r.note.c_str());
}

}  // namespace

int main(int argc, char** argv) {
  int rounds = 5;
  std::vector<int> threads{1, 2};
  std::vector<std::string> models{"rope:5000", "rope:20000"}, masks{"all", "none", "run", "sparse", "random30"};
  std::string precision = "double";
  std::vector<std::string> runs{"auto"};
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "chain_hybrid_cost: %s needs a value\n", a.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--rounds") rounds = std::max(1, std::atoi(next().c_str()));
    else if (a == "--threads") {
      threads.clear();
      for (const auto& s : bench::split_list(next())) threads.push_back(std::max(1, std::atoi(s.c_str())));
    } else if (a == "--models") models = bench::split_list(next());
    else if (a == "--masks") masks = bench::split_list(next());
    else if (a == "--precision") precision = next();
    else if (a == "--runs") runs = bench::split_list(next());
    else {
      std::fprintf(stderr,
                   "usage: chain_hybrid_cost [--rounds R] [--threads T,...] [--models rope:N,...] "
                   "[--masks all,none,run,sparse,random30] [--precision double|float|both] [--runs auto,on,off]\n");
      return 2;
    }
  }
  std::string cmd = argv[0];
  for (int i = 1; i < argc; ++i) cmd += std::string(" ") + argv[i];
  std::printf("# chain_hybrid_cost: ChainHybridDynamics (the parallel chain hybrid, host) and the serial "
              "hybrid_dynamics, one instance\n");
  const char* wait = std::getenv("OMP_WAIT_POLICY");
  std::printf("# machine: %s, %s, openmp_threads() %d, OMP_WAIT_POLICY %s\n",
              first_line_with("/proc/cpuinfo", "model name").c_str(),
              first_line_with("/proc/cpuinfo", "cpu cores").c_str(), openmp_threads(), wait ? wait : "(unset)");
  std::ifstream load("/proc/loadavg");
  std::string la;
  std::getline(load, la);
  std::printf("# load average at start: %s\n", la.c_str());
  std::printf("# command: %s\n", cmd.c_str());
  std::printf("model,mask,precision,config,threads,chunk,links,longest_run,ms_fastest,ms_median,ns_per_link,note\n");
  for (const auto& spec : models) {
    const Model m = make_generated(spec);
    for (const auto& mask : masks)
      for (int p = 0; p < 2; ++p) {
        if ((p == 0 && precision == "float") || (p == 1 && precision == "double")) continue;
        std::vector<Row> rows;
        if (p == 0) measure<double>(m, mask, rounds, threads, runs, rows);
        else measure<float>(m, mask, rounds, threads, runs, rows);
        for (const auto& r : rows) print_row(r);
        std::fflush(stdout);
      }
  }
  return 0;
}
