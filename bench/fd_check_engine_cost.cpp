// bench/fd_check_engine_cost.cpp: what the run-time check (BackendOptions::fd_check)
// costs each forward-dynamics engine, through the engine API.
//
// Per backend x method x precision x model x batch: seconds per compute() with the
// check off and on (the same engine options otherwise, the same random states:
// q in [-pi, pi] for the robots, [-1, 1] for chains and ropes; qd, tau in [-1, 1];
// seed 42), best of 3 runs of at least --min-time seconds each, and the overhead
// on / off - 1. Where the check flags instances (float jsi on long chains) the "on"
// time includes nothing more: no fallback is set. The CSV's `flagged` column counts
// the instances the check flagged in one call. A plain timing loop.
//
//   fd_check_engine_cost [--min-time 0.2] [--backend serial,openmp,cuda] [--out FILE.csv]
// Models: iiwa, hyq, atlas ($SCANDYN_MODELS_DIR, default the shipped models/),
// chain:64, rope:100, rope:1000, rope:10000 (aba, parallel), rope:100000 (parallel).
// On cuda compute() is timed: host buffers, the copies to and from the device
// included (the device-resident cost of the kernel is bench_cuda_fd_check's).
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "plain_bench_util.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"

using namespace scandyn;

namespace {

using bench::models_dir;

struct Case {
  std::string label, spec;
  double q_range;
  Index batch;
  std::vector<FdMethod> methods;
};

template <class S>
void run(FILE* out, BackendKind backend, const Case& c, const Model& md, double min_time) {
  const ModelTpl<S> m = md.cast<S>();
  const Index n = m.nv(), B = c.batch;
  std::mt19937_64 g(42);
  std::uniform_real_distribution<double> U(-1, 1);
  const std::size_t size = static_cast<std::size_t>(n * B);
  std::vector<S> q(size), qd(size), tau(size), qdd(size);
  for (std::size_t k = 0; k < size; ++k) {
    q[k] = S(c.q_range * U(g));
    qd[k] = S(U(g));
    tau[k] = S(U(g));
  }
  using V = BatchView<const S>;
  const FdBatchIn<S> in{V::soa(q.data(), n, B), V::soa(qd.data(), n, B), V::soa(tau.data(), n, B)};
  const BatchView<S> out_view = BatchView<S>::soa(qdd.data(), n, B);
  for (FdMethod method : c.methods) {
    BackendOptions o;
    o.backend = backend;
    o.fd_method = method;
    o.max_batch = B;
    double t[2] = {0, 0};
    Index flagged = 0;
    std::string strategy;
    bool skip = false;
    for (int on = 0; on < 2 && !skip; ++on) {
      o.fd_check = on ? FdCheckMode::On : FdCheckMode::Off;
      std::unique_ptr<ForwardDynamics<S>> fd;
      try {
        fd = make_forward_dynamics<S>(m, o);
      } catch (const BackendError& e) {  // a method this backend or model cannot take
        std::fprintf(stderr, "  %s %s %s: skipped (%s)\n", to_string(backend), to_string(method), c.label.c_str(),
                     e.what());
        skip = true;
        break;
      }
      if (on) strategy = fd->strategy();
      const BatchStatus st = fd->compute(in, out_view);
      if (on) flagged = st.failed;
      t[on] = bench::best_seconds_per_call(min_time, [&] {
        fd->compute(in, out_view);
        return std::size_t(1);
      });
    }
    if (skip) continue;
    std::fprintf(out, "%s,%s,%s,%s,%s,%lld,%lld,%.4g,%.4g,%.3f,%lld\n", to_string(backend), to_string(method),
                 strategy.c_str(), sizeof(S) == 4 ? "float" : "double", c.label.c_str(), static_cast<long long>(n),
                 static_cast<long long>(B), t[0], t[1], t[1] / t[0] - 1, static_cast<long long>(flagged));
    std::fflush(out);
  }
}

}  // namespace

int main(int argc, char** argv) {
  double min_time = 0.2;
  std::string out_path, backends = "serial,openmp";
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--min-time") && i + 1 < argc) min_time = std::atof(argv[++i]);
    else if (!std::strcmp(argv[i], "--out") && i + 1 < argc) out_path = argv[++i];
    else if (!std::strcmp(argv[i], "--backend") && i + 1 < argc) backends = argv[++i];
    else {
      std::fprintf(stderr, "usage: fd_check_engine_cost [--min-time S] [--backend LIST] [--out FILE.csv]\n");
      return 2;
    }
  }
  FILE* out = out_path.empty() ? stdout : std::fopen(out_path.c_str(), "w");
  if (!out) {
    std::fprintf(stderr, "fd_check_engine_cost: cannot write %s\n", out_path.c_str());
    return 1;
  }
  std::fprintf(out, "backend,method,strategy,precision,model,links,instances,off_s,on_s,overhead,flagged\n");
  BuildOptions robot;
  robot.require_physical_inertia = false;  // GRiD's atlas.urdf (docs/models.md)
  const double pi = 3.141592653589793;
  using F = FdMethod;
  for (std::size_t at = 0; at <= backends.size();) {
    const std::size_t end = std::min(backends.find(',', at), backends.size());
    const BackendKind backend = parse_backend(backends.substr(at, end - at));
    at = end + 1;
    const std::string why = backend_unusable(backend);
    if (!why.empty()) {
      std::fprintf(stderr, "fd_check_engine_cost: %s: %s\n", to_string(backend), why.c_str());
      continue;
    }
    const bool cuda = backend == BackendKind::Cuda;
    const Index robots = cuda ? 65536 : 256;
    std::vector<Case> cases = {
        {"iiwa", models_dir() + "/iiwa.urdf", pi, robots, {F::Aba, F::Jsi}},
        {"hyq", models_dir() + "/hyq.urdf", pi, robots, {F::Aba, F::Jsi}},
        {"atlas", models_dir() + "/atlas.urdf", pi, robots, {F::Aba, F::Jsi}},
        {"chain:64", "chain:64", 1, cuda ? 16384 : 64, {F::Aba, F::Jsi}},
        {"rope:100", "rope:100", 1, cuda ? 64 : 16, {F::Jsi, F::Parallel}},
        {"rope:1000", "rope:1000", 1, cuda ? 4 : 4, {F::Jsi, F::Parallel}},
        {"rope:10000", "rope:10000", 1, 1, {F::Parallel}},
        {"rope:100000", "rope:100000", 1, 1, {F::Parallel}},
    };
    if (!cuda) {
      cases[4].methods.insert(cases[4].methods.begin(), F::Aba);
      cases[5].methods.insert(cases[5].methods.begin(), F::Aba);
      cases[6].methods.insert(cases[6].methods.begin(), F::Aba);
    }
    for (const Case& c : cases) {
      const Model md = load_model(c.spec, robot);
      const auto t0 = std::chrono::steady_clock::now();
      run<float>(out, backend, c, md, min_time);
      run<double>(out, backend, c, md, min_time);
      std::fprintf(stderr, "  %s %s: %.1f s\n", to_string(backend), c.label.c_str(),
                   std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
    }
  }
  if (out != stdout) std::fclose(out);
  return 0;
}
