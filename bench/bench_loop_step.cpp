// bench/bench_loop_step.cpp: seconds per simulator step of a cloth grid with its loop
// closures, on the sparse loop path (the factor graph's
// system and CHOLMOD, scandyn/factor_graph/sparse_constrained_dynamics.hpp) and,
// with --dense, the dense one (constrained_forward_dynamics, project_to_loops).
//
//   bench_loop_step [--cloth K:N]... [--steps S] [--dense] [--gpu] [--dt DT] [--analyse-only]
//
// One CSV row per grid and solver on stdout: the scene is the cloth with gravity,
// rk4, dt, initial q = 0.1, qd = 0.5 (closed: the ropes move alike), serial backend.
//   first_step_s  the simulator's first step (the sparse solver's symbolic analyses
//                 included: each thread's workspace makes its solver then)
//   step_s        the mean of the following steps
//   closure       after the last step: max(|phi|, |J qd|) (max_phi, max_jqd apart;
//                 m and m/s); failed_steps: the simulator's failed instance-steps
//                 (Failure::LoopNotClosed: a projection left the state off its loops)
//   reset_*       the reset's projection of q = 0.1, qd = 0.5 onto the loops
//                 (Levenberg-Marquardt, sim::kResetLinearisations, tolerance 1e-13) on
//                 a solver of its own: seconds, linearisations, trials, factorisations
//                 (sparse), max |phi| after; the simulator starts from its result
// and, sparse, from a solver of its own running one rk4 step's solves (4 forward
// dynamics, one projection) at the initial state: the symbolic analyses' time, the
// numeric factorisations' (per factorisation), the solves', and each system's
// unknowns, nnz(L) and flops (CHOLMOD's nested dissection).
// --analyse-only: the symbolic analyses and their statistics alone (no steps).
// --iterative: the iterative path instead (scene "loop_solver": "iterative",
// scandyn/sim/iterative_loops.hpp), its own CSV (header below), from the closed start
// of --start x (also taken by the sparse path with --start x): q = 0.1 and qd = 0.5 on
// every x-axis joint (even i of each rope), 0 on the others (rotations about the rod's
// axis keep the loops closed: phi = 0, J qd = 0); without --start x the start of the
// rows above.
// Columns: the simulator's steps (first, mean after it), CG iterations per forward
// dynamics solve and per projection solve during the steps (warm-started), seconds per
// application of J M^-1 J^T (one J^T, M^-1, J pass), and on a solver of its own at
// the start state: one cold forward dynamics solve (lambda = 0) and the velocity
// projection, each with the block-Jacobi preconditioner and with none (iterations,
// seconds). --max-seconds S: skip the steps of a grid whose cold solve took more
// than S seconds (the solves are still reported). --quick: the cold solves with the
// preconditioner only, and no velocity projection (their columns -1 ... 0).
// --max-iterations K: the cold solves' iteration cap (default the solver's,
// sim::kIterativeLoopMaxIterations): a grid too large to converge in the time at hand
// reports its residual after K iterations (cold_fd_iterations -1) and the time per
// application. --torque A (iterative): the joint
// torques tau_i = A sin(1 + i) (N m) at every step and in the cold solve (else 0): with
// --start x the cloth then deforms (with tau = 0 its ropes swing alike, where the
// constraint forces vanish and a warm-started solve needs no iteration).
// --preconditioner P[,P...] (iterative): the preconditioners to run (each grid's rows in
// the order given, one row each, interleaved grid by grid; default block-jacobi; the
// names of sim::loop_preconditioner_name), the steps through the scene's
// "loop_preconditioner"; the cold solves' and velocity projection's "none" columns are
// computed once per grid and repeated in its rows.
// --gpu: the sparse path's factorisations and solves by cuSOLVER on the GPU
// (GpuSparseCholesky under CHOLMOD's order; the serial simulator backend steps, the
// CUDA one refuses loops); its analysis column includes cuSOLVER's.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

#include "scandyn/algorithm/loop_solver.hpp"
#include "scandyn/factor_graph/sparse_constrained_dynamics.hpp"
#include "scandyn/io/csv.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sim/iterative_loops.hpp"
#include "scandyn/sim/simulator.hpp"

using namespace scandyn;

namespace {
double now() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}
// loop_violation's max over |phi| and |J qd| without its dense J: J qd is the loop
// rows' classical acceleration with the bodies' velocities as accelerations.
double sparse_violation(const Model& model, const LoopSet& loops, const double* q, const double* qd,
                        double* max_phi = nullptr, double* max_jqd = nullptr) {
  const Index n = model.nv(), m = loops.rows();
  const std::vector<LoopRow<double>> rows = loop_rows_of<double>(loops);
  std::vector<Transform<double>> X0(n);
  std::vector<Motion<double>> v(n), a(n), zero(n, Motion<double>::zero());
  std::vector<double> phi(m), jqd(m);
  loop_body_motion(model.bodies.data(), n, q, qd, X0.data(), v.data(), a.data());
  loop_rows(model.bodies.data(), n, rows.data(), static_cast<Index>(rows.size()), X0.data(), zero.data(), v.data(),
            phi.data(), static_cast<double*>(nullptr), jqd.data());
  double wp = 0, wv = 0;
  for (Index k = 0; k < m; ++k) wp = std::max(wp, std::fabs(phi[k])), wv = std::max(wv, std::fabs(jqd[k]));
  if (max_phi) *max_phi = wp;
  if (max_jqd) *max_jqd = wv;
  return std::max(wp, wv);
}

// --start x: q = 0.1 and qd = 0.5 on the x-axis joints (even i of each rope of N links),
// 0 on the others: every rope turns about the rod's axis alike, closed in q and qd.
void closed_start_state(const std::string& spec, std::vector<double>& q, std::vector<double>& qd) {
  const std::size_t colon = spec.rfind(':');
  const Index N = std::atol(spec.c_str() + colon + 1);
  for (std::size_t i = 0; i < q.size(); ++i) {
    const bool x_axis = (static_cast<Index>(i) % N) % 2 == 0;
    q[i] = x_axis ? 0.1 : 0.0;
    qd[i] = x_axis ? 0.5 : 0.0;
  }
}

int iterative_main(const std::vector<std::string>& grids, int steps, double dt, bool closed_start, double max_seconds,
                   double torque, bool quick, int max_iterations, const std::vector<std::string>& pres) {
  std::printf("grid,links,loop_rows,solver,steps,first_step_s,step_s,closure,max_phi,max_jqd,fd_iterations_per_solve,"
              "proj_iterations_per_solve,apply_s,fd_s_per_solve,proj_s_per_solve,reset_s,reset_linearisations,reset_max_phi,"
              "cold_fd_iterations,cold_fd_s,cold_fd_iterations_none,cold_fd_s_none,vel_proj_iterations,vel_proj_s,"
              "vel_proj_iterations_none,vel_proj_s_none,failed_steps\n");
  std::fflush(stdout);
  for (const std::string& g : grids) {
    bool none_done = false;
    int none_cold_it = -1, none_vel_it = -1;
    double none_cold_s = 0, none_vel_s = 0;
    for (const std::string& pre_name : pres) {
      const sim::LoopPreconditioner pre_kind = sim::parse_loop_preconditioner(pre_name);
      const std::string spec = "cloth:" + g;
      const std::string head = R"({"model": ")" + spec + R"(", "effects": {"gravity": true}, "integrator": "rk4", "dt": )" +
                               std::to_string(dt) + R"(, "loop_solver": "iterative", "loop_preconditioner": ")" +
                               pre_name + R"(", "initial": )";
      const sim::Scene raw = sim::parse_scene(head + R"({"q": 0.1, "qd": 0.5}})", "bench.json");
      const Index n = raw.model.nv(), m = raw.loops.rows();
      std::vector<double> q0(n, 0.1), qd0(n, 0.5);
      if (closed_start) closed_start_state(spec, q0, qd0);
      // the reset's projection on a solver of its own (the simulator then starts from its result)
      LoopProjectionInfo reset;
      double t0 = now();
      try {
        sim::IterativeLoopOptions ro;
        ro.preconditioner = pre_kind;
        sim::IterativeLoopSolver rs(raw.model, raw.loops, ro);
        rs.project(q0.data(), qd0.data(), 1e-13, sim::kResetLinearisations, &reset);
      } catch (const LoopError& e) {
        std::fprintf(stderr, "%s: the reset projection failed: %s\n", spec.c_str(), e.what());
        continue;
      }
      const double reset_s = now() - t0;
      std::fprintf(stderr, "%s iterative: reset projection %.2f s, %d linearisations, max |phi| %.3g, max |J qd| %.3g\n",
                   spec.c_str(), reset_s, reset.linearisations, reset.phi, reset.jqd);
      // cold solves at the start, with and without the preconditioner
      int cold_it[2] = {0, 0}, vel_it[2] = {0, 0};
      double cold_s[2] = {0, 0}, vel_s[2] = {0, 0};
      std::vector<double> tau(n, 0.0), qdd(n);
      for (Index i = 0; i < n; ++i) tau[i] = torque * std::sin(1.0 + double(i));
      for (int pre = 0; pre < (quick ? 1 : 2); ++pre) {
        if (pre == 1 && none_done) {
          cold_it[1] = none_cold_it, cold_s[1] = none_cold_s, vel_it[1] = none_vel_it, vel_s[1] = none_vel_s;
          break;
        }
        sim::IterativeLoopOptions opt;
        opt.preconditioner = pre == 0 ? pre_kind : sim::LoopPreconditioner::None;
        opt.max_iterations = max_iterations;
        sim::IterativeLoopSolver s(raw.model, raw.loops, opt);
        t0 = now();
        try {
          s.forward_dynamics(q0.data(), qd0.data(), tau.data(), qdd.data(), nullptr);
          cold_it[pre] = s.stats().last_iterations;
        } catch (const LoopError& e) {
          std::fprintf(stderr, "%s: %s\n", spec.c_str(), e.what());
          cold_it[pre] = -1;
        }
        cold_s[pre] = now() - t0;
        std::fprintf(stderr, "%s %s: cold forward dynamics %d iterations, %.3g s (%ld applications, %.3g s each; relative residual %.3g; %ld incomplete-factorisation fallbacks)\n",
                     spec.c_str(), pre == 0 ? pre_name.c_str() : "none", cold_it[pre], cold_s[pre], s.stats().applies,
                     s.stats().applies ? s.stats().apply_seconds / double(s.stats().applies) : 0.0, s.stats().last_residual,
                     s.stats().dilu_fallbacks);
        if (quick) {
          cold_it[1] = vel_it[0] = vel_it[1] = -1;
          break;
        }
        // the velocity projection of qd + a disturbance (one CGLS solve at a closed q)
        std::vector<double> q = q0, qd = qd0;
        for (Index i = 0; i < n; ++i) qd[i] += 0.1 * std::sin(2.0 + double(i));
        s.reset_stats();
        t0 = now();
        try {
          s.project(q.data(), qd.data(), 1e-12, 0);
          vel_it[pre] = s.stats().last_iterations;
        } catch (const LoopError& e) {
          std::fprintf(stderr, "%s: %s\n", spec.c_str(), e.what());
          vel_it[pre] = -1;
        }
        vel_s[pre] = now() - t0;
        std::fprintf(stderr, "%s %s: cold forward dynamics %d iterations %.3g s, velocity projection %d iterations %.3g s (relative residual %.3g)\n",
                     spec.c_str(), pre == 0 ? pre_name.c_str() : "none", cold_it[pre], cold_s[pre], vel_it[pre], vel_s[pre],
                     s.stats().last_residual);
        if (pre == 1) {
          none_done = true;
          none_cold_it = cold_it[1], none_cold_s = cold_s[1], none_vel_it = vel_it[1], none_vel_s = vel_s[1];
        }
      }
      auto array = [](const std::vector<double>& x) { return io::number_array(x.data(), x.size()); };
      double first = 0, mean = 0, closure = 0, closure_phi = 0, closure_jqd = 0, apply_s = 0, fd_per = 0, proj_per = 0,
             fd_s = 0, proj_s = 0;
      long long failed_steps = 0;
      int ran = 0;
      if (cold_s[0] <= max_seconds) {
        const sim::Scene scene = sim::parse_scene(head + R"({"q": )" + array(q0) + R"(, "qd": )" + array(qd0) + "}}", "bench.json");
        sim::Simulator<double> s(scene, BackendKind::Serial);
        sim::reset_iterative_loop_totals();
        const BatchView<const double> tv = BatchView<const double>::soa(tau.data(), n, 1);
        t0 = now();
        s.step(tv);
        first = now() - t0;
        t0 = now();
        for (int k = 1; k < steps; ++k) s.step(tv);
        mean = steps > 1 ? (now() - t0) / (steps - 1) : 0;
        ran = steps;
        const sim::IterativeLoopStats t = sim::iterative_loop_totals();
        std::fprintf(stderr, "%s: steps: %ld forward dynamics solves (%ld iterations), %ld projection solves (%ld iterations), %ld applications (%.3g s)\n",
                     spec.c_str(), t.fd_solves, t.fd_iterations, t.proj_solves, t.proj_iterations, t.applies, t.apply_seconds);
        fd_per = t.fd_solves ? double(t.fd_iterations) / double(t.fd_solves) : 0;
        proj_per = t.proj_solves ? double(t.proj_iterations) / double(t.proj_solves) : 0;
        apply_s = t.applies ? t.apply_seconds / double(t.applies) : 0;
        fd_s = t.fd_solves ? t.fd_seconds / double(t.fd_solves) : 0;
        proj_s = t.proj_solves ? t.proj_seconds / double(steps) : 0;  // per projection (one per step)
        std::vector<double> q(n), qd(n);
        s.read_state(q.data(), qd.data());
        failed_steps = static_cast<long long>(s.status().failed);
        if (!s.status().ok()) std::fprintf(stderr, "%s: %s\n", spec.c_str(), sim::failure_message(s.status()).c_str());
        closure = sparse_violation(scene.model, scene.loops, q.data(), qd.data(), &closure_phi, &closure_jqd);
      }
      std::printf("%s,%lld,%lld,iterative-cgls-%s%s,%d,%.4g,%.4g,%.3g,%.3g,%.3g,%.4g,%.4g,%.4g,%.4g,%.4g,%.4g,%d,%.3g,%d,%.4g,%d,%.4g,"
                  "%d,%.4g,%d,%.4g,%lld\n",
                  spec.c_str(), (long long)n, (long long)m, pre_name.c_str(), torque != 0 ? "-torque" : "", ran, first, mean, closure, closure_phi, closure_jqd, fd_per,
                  proj_per, apply_s, fd_s, proj_s, reset_s, reset.linearisations, reset.phi, cold_it[0], cold_s[0],
                  cold_it[1], cold_s[1], vel_it[0], vel_s[0], vel_it[1], vel_s[1], failed_steps);
      std::fflush(stdout);
    }
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<std::string> grids;
  int steps = 3;
  bool dense = false, analyse_only = false, gpu = false, iterative = false, closed_start = false;
  double dt = 1e-4, max_seconds = 1e30, torque = 0;
  bool quick = false;
  int max_iterations = sim::kIterativeLoopMaxIterations;
  std::vector<std::string> pres;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--cloth" && i + 1 < argc) grids.push_back(argv[++i]);
    else if (a == "--steps" && i + 1 < argc) steps = std::atoi(argv[++i]);
    else if (a == "--dt" && i + 1 < argc) dt = std::atof(argv[++i]);
    else if (a == "--dense") dense = true;
    else if (a == "--gpu") gpu = true;
    else if (a == "--analyse-only") analyse_only = true;
    else if (a == "--iterative") iterative = true;
    else if (a == "--start" && i + 1 < argc && std::string(argv[i + 1]) == "x") closed_start = true, ++i;
    else if (a == "--max-seconds" && i + 1 < argc) max_seconds = std::atof(argv[++i]);
    else if (a == "--torque" && i + 1 < argc) torque = std::atof(argv[++i]);
    else if (a == "--quick") quick = true;
    else if (a == "--preconditioner" && i + 1 < argc) {
      std::string list = argv[++i];
      for (std::size_t at = 0; at <= list.size();) {
        const std::size_t comma = std::min(list.find(',', at), list.size());
        pres.push_back(list.substr(at, comma - at));
        at = comma + 1;
      }
    }
    else if (a == "--max-iterations" && i + 1 < argc) max_iterations = std::atoi(argv[++i]);
    else {
      std::fprintf(stderr, "usage: bench_loop_step [--cloth K:N]... [--steps S] [--dt DT] [--dense] [--gpu] [--analyse-only] "
                           "[--iterative] [--start x] [--max-seconds S] [--torque A] [--quick] [--max-iterations K] "
                           "[--preconditioner P[,P...]]\n");
      return 2;
    }
  }
  if (grids.empty()) grids = {"10:10", "30:30"};
  if (pres.empty()) pres = {"block-jacobi"};
  for (const std::string& p : pres) {
    try {
      (void)sim::parse_loop_preconditioner(p);
    } catch (const LoopError& e) {
      std::fprintf(stderr, "bench_loop_step: %s\n", e.what());
      return 2;
    }
  }
  if (iterative) return iterative_main(grids, steps, dt, closed_start, max_seconds, torque, quick, max_iterations, pres);
  factor_graph::register_sparse_loop_solver(gpu);
  std::printf("grid,links,loop_rows,solver,steps,first_step_s,step_s,closure,max_phi,max_jqd,analysis_fd_s,analysis_proj_s,"
              "factorize_s,solve_s,factorizations_per_step,unknowns_fd,nnz_L_fd,flops_fd,nnz_L_proj,flops_proj,reset_s,"
              "reset_linearisations,reset_trials,reset_factorizations,reset_max_phi,failed_steps\n");
  std::fflush(stdout);
  for (const std::string& g : grids) {
    const std::string spec = "cloth:" + g;
    for (int pass = 0; pass < (dense ? 2 : 1); ++pass) {
      const bool sparse = pass == 0;
      const std::string head = R"({"model": ")" + spec + R"(", "effects": {"gravity": true}, "integrator": "rk4", "dt": )" +
                               std::to_string(dt) + R"(, "loop_solver": ")" + (sparse ? "sparse" : "dense") +
                               R"(", "initial": )";
      const sim::Scene raw = sim::parse_scene(head + R"({"q": 0.1, "qd": 0.5}})", "bench.json");
      const Index n = raw.model.nv(), m = raw.loops.rows();
      // the reset's projection of q = 0.1, qd = 0.5 onto the loops (the simulator's:
      // Levenberg-Marquardt, kResetLinearisations, tolerance 1e-13) on a solver of its
      // own, timed; the simulator then starts from its result (its own reset finds it
      // closed: no position step)
      std::vector<double> q0(n, 0.1), qd0(n, 0.5);
      if (closed_start) closed_start_state(spec, q0, qd0);
      LoopProjectionInfo reset;
      double reset_s = 0;
      long reset_factorizations = 0;
      if (!analyse_only) {
        const double t0 = now();
        if (sparse) {
          factor_graph::SparseConstrainedDynamics rs(raw.model, raw.loops, factor_graph::Ordering::NESDIS, gpu);
          rs.project(q0.data(), qd0.data(), 1e-13, sim::kResetLinearisations, &reset);
          reset_factorizations = rs.timing().factorizations;
        } else {
          project_to_loops(raw.model, raw.loops, q0.data(), qd0.data(), 1e-13, sim::kResetLinearisations, &reset);
        }
        reset_s = now() - t0;
        std::fprintf(stderr, "%s %s: reset projection %.1f s, %d linearisations, %d trials, max |phi| %.3g, max |J qd| %.3g\n",
                     spec.c_str(), sparse ? "sparse" : "dense", reset_s, reset.linearisations, reset.trials, reset.phi,
                     reset.jqd);
      }
      auto array = [](const std::vector<double>& x) { return io::number_array(x.data(), x.size()); };
      const sim::Scene scene =
          analyse_only ? raw : sim::parse_scene(head + R"({"q": )" + array(q0) + R"(, "qd": )" + array(qd0) + "}}", "bench.json");
      // the sparse solver's analyses and one rk4 step's solves, on a solver of its own
      double an_fd = 0, an_proj = 0, fac = 0, sol = 0, per_step = 0;
      factor_graph::EliminationStats sfd, sproj;
      Index unknowns = 0;
      if (sparse) {
        factor_graph::SparseConstrainedDynamics sc(scene.model, scene.loops, factor_graph::Ordering::NESDIS, gpu);
        sfd = sc.forward_dynamics_stats();
        an_fd = sc.timing().analysis;
        sproj = sc.projection_stats();
        an_proj = sc.timing().analysis - an_fd;
        unknowns = sc.forward_dynamics_unknowns();
        if (!analyse_only) {
          std::vector<double> q = q0, qd = qd0, tau(n, 0.0), qdd(n), lambda(m);
          sc.reset_timing();
          for (int s = 0; s < 4; ++s) sc.forward_dynamics(q.data(), qd.data(), tau.data(), qdd.data(), lambda.data());
          for (Index i = 0; i < n; ++i) q[i] += 1e-6 * qd[i];  // off the loops a little: one Gauss-Newton step
          sc.project(q.data(), qd.data(), 1e-12, 10);
          const auto& t = sc.timing();
          per_step = double(t.factorizations);
          fac = t.factorize / double(t.factorizations);
          sol = t.solve / double(t.solves);
        }
      }
      double first = 0, mean = 0, closure = 0, closure_phi = 0, closure_jqd = 0;
      long long failed_steps = 0;
      if (!analyse_only) {
        sim::Simulator<double> s(scene, BackendKind::Serial);
        double t0 = now();
        s.step();
        first = now() - t0;
        t0 = now();
        for (int k = 1; k < steps; ++k) s.step();
        mean = steps > 1 ? (now() - t0) / (steps - 1) : 0;
        std::vector<double> q(n), qd(n);
        s.read_state(q.data(), qd.data());
        failed_steps = static_cast<long long>(s.status().failed);
        if (!s.status().ok()) std::fprintf(stderr, "%s: %s\n", spec.c_str(), sim::failure_message(s.status()).c_str());
        // max |phi| and |J qd| (sparse: without the dense J of loop_violation)
        closure = sparse_violation(scene.model, scene.loops, q.data(), qd.data(), &closure_phi, &closure_jqd);
      }
      std::printf("%s,%lld,%lld,%s,%d,%.4g,%.4g,%.3g,%.3g,%.3g,%.4g,%.4g,%.4g,%.4g,%.0f,%lld,%.6g,%.6g,%.6g,%.6g,%.4g,%d,%d,%ld,%.3g,%lld\n", spec.c_str(),
                  (long long)n, (long long)m, sparse ? (gpu ? "sparse-cusolver-nesdis" : "sparse-cholmod-nesdis") : "dense", analyse_only ? 0 : steps,
                  first, mean, closure, closure_phi, closure_jqd, an_fd, an_proj, fac, sol, per_step, (long long)unknowns, sfd.nnz_L, sfd.flops,
                  sproj.nnz_L, sproj.flops, reset_s, reset.linearisations, reset.trials, reset_factorizations, reset.phi,
                  failed_steps);
      std::fflush(stdout);
    }
  }
  return 0;
}
