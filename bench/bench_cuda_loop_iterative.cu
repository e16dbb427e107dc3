// One closed-loop forward dynamics of cloth:K:N on the GPU (cuda::CudaIterativeLoopSolver,
// scandyn/cuda/loop_iterative.hpp: CGLS with block Jacobi, a thread per rope and per
// loop) next to the CPU iterative solver (sim::IterativeLoopSolver, block Jacobi, one
// core) on the same grid and state. A plain program (no Google Benchmark).
//
//   bench_cuda_loop_iterative [--grids 30:30,100:100,300:300,1000:1000] [--cpu-max-links L]
//                             [--float] [--max-iterations K] [--torque A] [--csv FILE]
//
// State (bench_loop_step's --start x): q = 0.1 and qd = 0.5 on every x-axis joint (even
// j of each rope), 0 on the others (the ropes alike: closed), torques tau_i = A sin(1 + i)
// (A = --torque, default 1e-4: the cloth deforms, so the constraint forces do not vanish).
// Every solve cold (lambda = 0), tolerance 1e-10 (float: 1e-5). The CPU solves grids of
// at most --cpu-max-links links (default 10^5: up to cloth:300:300, ~10-20 s there).
// The GPU solvers are made and warmed up (the kernels' first launch, JIT from PTX) on
// cloth:4:4 before the timed rows; each timed row is one forward_dynamics call (host
// copies of q, qd, tau in and qdd out included); setup_s: the solver's construction.
//
// Columns: grid, links, rows, solver, iterations, seconds, setup_s, closure
// (||J qdd + gamma||_2 by the host's passes), closure_rel (closure / (||gamma|| + ||J qdd0||)),
// qdd_diff (max |qdd - qdd_cpu| / max |qdd_cpu|; against the CPU row where it ran, else
// against the GPU double row for float, else -), status (ok, or the error).
//
// --sim-steps K (whole simulator steps; the forward-dynamics rows above are then not run):
// per grid, K rk4 steps (dt --dt, default 2e-4 s) of sim::Simulator<double> (serial
// backend, gravity, the state above as the scene's initial state, the torques above) with
// "loop_solver": "iterative-cuda" (block Jacobi: the GPU solver's forward dynamics and
// projection) next to "iterative" with "loop_preconditioner": "block-jacobi" (the CPU's,
// one core) on grids of at most --step-cpu-max-links links (default 2 10^4: up to
// cloth:100:100, whose CPU steps take seconds each). Columns: grid, links, solver,
// steps, s_per_step (the steps' wall time / K, after one untimed step), setup_s (the
// simulator's construction and the first step), violation (max(|phi|, |J qd|) after
// the last step), failures (failed instance-steps), fd_iterations and proj_iterations
// per step (the GPU solver's own counters are not reachable through the simulator: the
// CPU rows' from iterative_loop_totals, the GPU rows' -), status.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include "scandyn/algorithm/loop_iterative.hpp"
#include "scandyn/algorithm/loops.hpp"
#include "scandyn/cuda/loop_iterative.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/io/csv.hpp"
#include "scandyn/sim/iterative_loops.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"

using namespace scandyn;
using Clock = std::chrono::steady_clock;

namespace {

double seconds_since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

double rel_diff(const std::vector<double>& a, const std::vector<double>& ref) {
  double d = 0, r = 0;
  for (std::size_t i = 0; i < a.size(); ++i) d = std::max(d, std::fabs(a[i] - ref[i])), r = std::max(r, std::fabs(ref[i]));
  return d / (r > 0 ? r : 1);
}

std::vector<std::string> split(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream ss(s);
  std::string item;
  while (std::getline(ss, item, ','))
    if (!item.empty()) out.push_back(item);
  return out;
}

struct Row {
  std::string grid, solver, status = "ok";
  long long links = 0, rows = 0;
  int iterations = 0;
  double seconds = 0, setup = 0, closure = NAN, closure_rel = NAN, diff = NAN;
};

FILE* g_csv = nullptr;
// the row's closure ||J qdd + gamma|| and its ratio to ||gamma|| + ||J qdd0||, by the
// host's passes
void set_closure(Row& r, const Model& model, const LoopSet& loops, const std::vector<double>& q,
                 const std::vector<double>& qd, const std::vector<double>& tau, const std::vector<double>& qdd) {
  const LoopAccelerationClosure c = loop_acceleration_closure(model, loops, q.data(), qd.data(), tau.data(), qdd.data());
  r.closure = c.residual, r.closure_rel = c.residual / (c.gamma + c.jqdd0);
}

void print(const Row& r) {
  char diff[32] = "-";
  if (std::isfinite(r.diff)) std::snprintf(diff, sizeof diff, "%.3g", r.diff);
  std::string status = r.status;
  std::replace(status.begin(), status.end(), ',', ';');
  char line[1024];
  std::snprintf(line, sizeof line, "%s,%lld,%lld,%s,%d,%.4g,%.3g,%.3g,%.3g,%s,%s\n", r.grid.c_str(), r.links, r.rows,
                r.solver.c_str(), r.iterations, r.seconds, r.setup, r.closure, r.closure_rel, diff, status.c_str());
  std::fputs(line, stdout);
  std::fflush(stdout);
  if (g_csv) std::fputs(line, g_csv), std::fflush(g_csv);
}

template <class S>
Row run_gpu(const std::string& spec, const Model& model, const LoopSet& loops, const std::vector<double>& q,
            const std::vector<double>& qd, const std::vector<double>& tau, int max_iterations, std::vector<double>& qdd) {
  Row r;
  r.grid = spec, r.links = model.nv(), r.rows = loops.rows();
  r.solver = sizeof(S) == sizeof(float) ? "cuda-float" : "cuda-double";
  cuda::CudaIterativeLoopOptions o;
  o.warm_start = false;
  o.max_iterations = max_iterations;
  qdd.assign(model.nv(), NAN);
  try {
    auto t0 = Clock::now();
    cuda::CudaIterativeLoopSolver<S> gpu(model, loops, o);
    r.setup = seconds_since(t0);
    t0 = Clock::now();
    try {
      gpu.forward_dynamics(q.data(), qd.data(), tau.data(), qdd.data(), nullptr);
    } catch (const LoopError& e) {
      r.status = std::string("error: ") + e.what();
    }
    r.seconds = seconds_since(t0);
    r.iterations = gpu.stats().last_iterations;
  } catch (const std::exception& e) {
    r.status = std::string("error: ") + e.what();
  }
  return r;
}

// --sim-steps: K simulator steps of cloth:<g> with the loop solver `solver`
// cloth:<g> (g = "K:N") and the state of the header: q = 0.1, qd = 0.5 on the x-axis
// joints (even j of each rope), 0 on the others; tau_i = torque sin(1 + i)
struct Grid {
  std::string spec;
  Model model;
  LoopSet loops;
  Index n = 0;
  std::vector<double> q, qd, tau;
  Grid(const std::string& g, double torque)
      : spec("cloth:" + g), model(load_model(spec)), loops(generator_loops(spec, model)), n(model.nv()) {
    const Index N = std::atoi(g.c_str() + g.rfind(':') + 1);
    q.resize(n), qd.resize(n), tau.resize(n);
    for (Index i = 0; i < n; ++i) {
      const bool x_axis = (i % N) % 2 == 0;
      q[i] = x_axis ? 0.1 : 0.0, qd[i] = x_axis ? 0.5 : 0.0, tau[i] = torque * std::sin(1.0 + double(i));
    }
  }
};

void run_steps(const std::string& spec, const Model& model, const LoopSet& loops, const std::vector<double>& q,
               const std::vector<double>& qd, const std::vector<double>& tau, const std::string& solver, int steps,
               double dt) {
  const Index n = model.nv();
  std::string status = "ok", violation = "-", failures = "-", fd_it = "-", proj_it = "-";
  double per_step = NAN, setup = NAN;
  try {
    const std::string json = std::string(R"({"model": ")") + spec +
                             R"(", "effects": {"gravity": true}, "integrator": "rk4", "loop_solver": ")" + solver +
                             R"(", "loop_preconditioner": "block-jacobi", "dt": )" + std::to_string(dt) +
                             R"(, "initial": {"q": )" + io::number_array(q.data(), q.size()) + R"(, "qd": )" +
                             io::number_array(qd.data(), qd.size()) + "}}";
    auto t0 = Clock::now();
    sim::Simulator<double> s(sim::parse_scene(json, "bench.json"), BackendKind::Serial);
    const BatchView<const double> u = BatchView<const double>::soa(tau.data(), n, 1);
    s.step(u);  // (the first: the loop solver's construction, the kernels' first launch)
    setup = seconds_since(t0);
    sim::reset_iterative_loop_totals();
    t0 = Clock::now();
    for (int k = 0; k < steps; ++k) s.step(u);
    per_step = seconds_since(t0) / steps;
    if (solver == "iterative") {
      const sim::IterativeLoopStats t = sim::iterative_loop_totals();
      fd_it = std::to_string(t.fd_iterations / steps), proj_it = std::to_string(t.proj_iterations / steps);
    }
    const BatchStatus st = s.status();
    failures = std::to_string(st.failed);
    if (!st.ok()) status = "error: " + sim::failure_message(st);
    std::vector<double> qe(n), qde(n);
    s.read_state(qe.data(), qde.data());
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.3g", loop_violation(model, loops, qe.data(), qde.data()));
    violation = buf;
  } catch (const std::exception& e) {
    status = std::string("error: ") + e.what();
  }
  std::replace(status.begin(), status.end(), ',', ';');
  char line[2048];
  std::snprintf(line, sizeof line, "%s,%lld,%s,%d,%.4g,%.3g,%s,%s,%s,%s,%s\n", spec.c_str(), (long long)n,
                solver.c_str(), steps, per_step, setup, violation.c_str(), failures.c_str(), fd_it.c_str(),
                proj_it.c_str(), status.c_str());
  std::fputs(line, stdout);
  std::fflush(stdout);
  if (g_csv) std::fputs(line, g_csv), std::fflush(g_csv);
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<std::string> grids = {"30:30", "100:100", "300:300", "1000:1000"};
  long long cpu_max_links = 100000;
  bool with_float = false;
  int max_iterations = sim::kIterativeLoopMaxIterations;
  double torque = 1e-4;
  int sim_steps = 0;
  double dt = 2e-4;
  long long step_cpu_max_links = 20000;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--grids" && i + 1 < argc) grids = split(argv[++i]);
    else if (a == "--cpu-max-links" && i + 1 < argc) cpu_max_links = std::atoll(argv[++i]);
    else if (a == "--float") with_float = true;
    else if (a == "--max-iterations" && i + 1 < argc) max_iterations = std::atoi(argv[++i]);
    else if (a == "--torque" && i + 1 < argc) torque = std::atof(argv[++i]);
    else if (a == "--csv" && i + 1 < argc) g_csv = std::fopen(argv[++i], "w");
    else if (a == "--sim-steps" && i + 1 < argc) sim_steps = std::atoi(argv[++i]);
    else if (a == "--dt" && i + 1 < argc) dt = std::atof(argv[++i]);
    else if (a == "--step-cpu-max-links" && i + 1 < argc) step_cpu_max_links = std::atoll(argv[++i]);
    else {
      std::fprintf(stderr,
                   "usage: bench_cuda_loop_iterative [--grids 30:30,100:100,...] [--cpu-max-links L] [--float] "
                   "[--max-iterations K] [--torque A] [--csv FILE] [--sim-steps K [--dt DT] [--step-cpu-max-links L]]\n");
      return 2;
    }
  }
  // warm-up: every kernel of both precisions launched once
  {
    const Model model = load_model("cloth:4:4");
    const LoopSet loops = generator_loops("cloth:4:4", model);
    std::vector<double> z(model.nv(), 0.0), t(model.nv(), 1e-4), out;
    try {
      run_gpu<double>("cloth:4:4", model, loops, z, z, t, 100, out);
      run_gpu<float>("cloth:4:4", model, loops, z, z, t, 100, out);
    } catch (const std::exception& e) {
      std::fprintf(stderr, "warm-up: %s\n", e.what());
    }
  }
  if (sim_steps > 0) {
    const char* h = "grid,links,solver,steps,s_per_step,setup_s,violation,failures,fd_iterations,proj_iterations,status\n";
    std::fputs(h, stdout);
    if (g_csv) std::fputs(h, g_csv);
    for (const std::string& g : grids) {
      const Grid c(g, torque);
      if (c.n <= step_cpu_max_links) run_steps(c.spec, c.model, c.loops, c.q, c.qd, c.tau, "iterative", sim_steps, dt);
      run_steps(c.spec, c.model, c.loops, c.q, c.qd, c.tau, "iterative-cuda", sim_steps, dt);
    }
    if (g_csv) std::fclose(g_csv);
    return 0;
  }
  const char* header = "grid,links,rows,solver,iterations,seconds,setup_s,closure,closure_rel,qdd_diff,status\n";
  std::fputs(header, stdout);
  if (g_csv) std::fputs(header, g_csv);
  for (const std::string& g : grids) {
    const Grid c(g, torque);
    const std::string& spec = c.spec;
    const Model& model = c.model;
    const LoopSet& loops = c.loops;
    const Index n = c.n;
    const std::vector<double>&q = c.q, &qd = c.qd, &tau = c.tau;
    std::vector<double> qdd_cpu, qdd_gpu, qdd_f;
    if (n <= cpu_max_links) {
      Row r;
      r.grid = spec, r.links = n, r.rows = loops.rows(), r.solver = "cpu-iterative";
      sim::IterativeLoopOptions o;
      o.preconditioner = sim::LoopPreconditioner::BlockJacobi;
      o.warm_start = false;
      o.max_iterations = max_iterations;
      auto t0 = Clock::now();
      sim::IterativeLoopSolver cpu(model, loops, o);
      r.setup = seconds_since(t0);
      qdd_cpu.assign(n, NAN);
      t0 = Clock::now();
      try {
        cpu.forward_dynamics(q.data(), qd.data(), tau.data(), qdd_cpu.data(), nullptr);
      } catch (const LoopError& e) {
        r.status = std::string("error: ") + e.what();
        qdd_cpu.clear();
      }
      r.seconds = seconds_since(t0);
      r.iterations = cpu.stats().last_iterations;
      if (!qdd_cpu.empty()) set_closure(r, model, loops, q, qd, tau, qdd_cpu);
      print(r);
    }
    Row r = run_gpu<double>(spec, model, loops, q, qd, tau, max_iterations, qdd_gpu);
    if (r.status == "ok") {
      set_closure(r, model, loops, q, qd, tau, qdd_gpu);
      if (!qdd_cpu.empty()) r.diff = rel_diff(qdd_gpu, qdd_cpu);
    }
    print(r);
    if (with_float) {
      Row f = run_gpu<float>(spec, model, loops, q, qd, tau, max_iterations, qdd_f);
      if (f.status == "ok") {
        set_closure(f, model, loops, q, qd, tau, qdd_f);
        if (!qdd_cpu.empty()) f.diff = rel_diff(qdd_f, qdd_cpu);
        else if (r.status == "ok") f.diff = rel_diff(qdd_f, qdd_gpu);
      }
      print(f);
    }
  }
  if (g_csv) std::fclose(g_csv);
  return 0;
}
