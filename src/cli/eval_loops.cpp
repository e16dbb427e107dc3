// src/cli/eval_loops.cpp: `scandyn eval` on a model with closed loops (--loops FILE, or
// a generator that carries loops: fivebar, fourbar, cloth:K:N): forward dynamics
// (qdd_fd_<i>, lambda_<k>) and, with --actuated LIST, inverse dynamics (tau_id_<i>,
// lambda_<k>) of the constrained system (scandyn/algorithm/loops.hpp), serial double.
// Forward dynamics through --loop-solver: dense (constrained_forward_dynamics), sparse
// (the registered CHOLMOD solver, scandyn/sim/sparse_loops.hpp) or iterative
// (scandyn/sim/iterative_loops.hpp): the simulator's loop solvers, one per call; with
// --backend cuda (and --loop-solver iterative), the iterative solver on the GPU
// (scandyn/cuda/loop_iterative.hpp: chains from the base, block Jacobi; --precision
// double or float), one solver for every row (warm-started from the previous row).
#include <cmath>
#include <cstdio>
#include <memory>

#include "hybrid.hpp"
#include "engines.hpp"
#include "scandyn/algorithm/loops.hpp"
#include "scandyn/io/csv.hpp"
#include "scandyn/io/limits.hpp"
#include "scandyn/io/states.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/cuda/loop_iterative.hpp"
#include "scandyn/sim/iterative_loops.hpp"
#include "scandyn/sim/sparse_loops.hpp"

namespace scandyn::cli {

LoopSet load_cli_loops(const Args& args, const Model& model) {
  LoopSet loops = generator_loops(args.required("model"), model);
  if (args.has("loops")) {
    try {
      for (const LoopClosure& l : load_loops(args.required("loops"), model).loops) loops.loops.push_back(l);
    } catch (const LoopError& e) {
      throw DataError(e.what());
    }
  }
  return loops;
}

namespace {

// --loop-solver of eval's forward dynamics: null for the dense solve, else the
// simulator's solver factory (the same choice as a scene's "loop_solver").
sim::LoopSolverFactory eval_loop_solver(const Args& args, const std::string& algo, Index nv) {
  const std::string name = args.get("loop-solver", "auto");
  if (name != "auto" && name != "dense" && name != "sparse" && name != "iterative")
    throw UsageError("--loop-solver " + name + ": expected dense, sparse, iterative or auto");
  if (algo == "id") {
    if (name != "auto" && name != "dense")
      throw UsageError("--loop-solver " + name + ": inverse dynamics with loops (--algo id) solves densely");
    return nullptr;
  }
  if (name == "dense") return nullptr;
  if (name == "sparse") {
    if (!sim::sparse_loop_solver())
      throw UsageError("--loop-solver sparse: this scandyn was built without SuiteSparse CHOLMOD (`scandyn info` "
                       "lists its loop solvers); use iterative or dense");
    return sim::sparse_loop_solver();
  }
  if (name == "iterative" || nv >= sim::kSparseLoopDofs)
    return name == "auto" && sim::sparse_loop_solver() ? sim::sparse_loop_solver() : &sim::make_iterative_loop_solver;
  return nullptr;
}

}  // namespace

int run_eval_loops(const Args& args) {
  const std::string& states_path = args.required("states");
  const std::string& out_path = args.required("out");
  const std::string algo = args.get("algo", args.has("actuated") ? "id" : "fd");
  if (algo != "fd" && algo != "id")
    throw UsageError("--algo " + algo + ": with loops, eval computes fd (constrained forward dynamics) or id "
                     "(with --actuated LIST)");
  if (algo == "id" && !args.has("actuated"))
    throw UsageError("--algo id with loops needs --actuated LIST (the DoFs with actuators)");
  if (algo == "fd" && args.has("actuated")) throw UsageError("--actuated applies only to --algo id");
  for (const char* f : {"fd", "fallback", "strategy", "prescribed"})
    if (args.has(f)) throw UsageError(std::string("--") + f + " does not apply to a model with loops");
  // --backend cuda: the CUDA iterative solver (scandyn/cuda/loop_iterative.hpp), double
  // or float; every other combination runs on the serial backend in double
  const std::string backend = args.get("backend", "serial"), precision = args.get("precision", "double");
  const bool cuda_backend = backend == "cuda";
  if (cuda_backend) {
    if (algo != "fd" || args.get("loop-solver", "auto") != "iterative")
      throw UsageError("--backend cuda with loops: forward dynamics (--algo fd) by --loop-solver iterative only "
                       "(the CUDA iterative loop solver)");
    if (precision != "double" && precision != "float")
      throw UsageError("--precision " + precision + ": expected double or float");
#if !SCANDYN_HAS_CUDA
    throw UsageError("--backend cuda: this scandyn was built without CUDA");
#endif
  } else if (backend != "serial" || precision != "double") {
    throw UsageError("a model with loops runs on the serial backend in double (the dense loop solver), or with "
                     "--loop-solver iterative --backend cuda (double or float)");
  }
  const Model model = load_cli_model(args);
  const LoopSet loops = load_cli_loops(args, model);
  const Index n = model.nv(), m = loops.rows();
  std::vector<unsigned char> actuated;
  if (args.has("actuated")) actuated = parse_prescribed(args.required("actuated"), model, "actuated");

  sim::LoopSolverFactory factory = eval_loop_solver(args, algo, n);  // (usage errors before the files)
#if SCANDYN_HAS_CUDA
  if (cuda_backend)
    factory = precision == "float" ? &cuda::make_cuda_iterative_loop_solver_float : &cuda::make_cuda_iterative_loop_solver;
#endif

  CsvReader in(states_path);
  const StateColumns cols = map_state_columns(in.columns(), n, states_path);
  const Family given = algo == "fd" ? Family::Tau : Family::Qdd;
  for (Family f : {Family::Q, Family::Qd, given}) {
    const Index i = cols.first_missing(f);
    if (i >= 0)
      throw CsvError(states_path + ": missing column " + family_prefix(f) + std::to_string(i) + " (needed by --algo " +
                     algo + " with loops)");
  }
  std::unique_ptr<sim::LoopSolver> solver;
  if (factory) {
    try {
      solver = factory(model, loops);
    } catch (const LoopError& e) {
      throw DataError(printable(model.source) + ": " + e.what());
    }
  } else {
    require_host_memory("eval with loops on " + printable(model.source) + " (the dense solve; --loop-solver)",
                        8.0 * double(n) * double(n + m) * 4 + 1e6);
  }
  CsvWriter out(out_path);
  std::vector<std::string> names;
  for (Index i = 0; i < n; ++i) names.push_back((algo == "fd" ? "qdd_fd_" : "tau_id_") + std::to_string(i));
  for (Index k = 0; k < m; ++k) names.push_back("lambda_" + std::to_string(k));
  out.write_header(names);
  std::vector<double> row, q(n), qd(n), u(n), res(n + m);
  while (in.next_row(row)) {
    gather_family(cols, Family::Q, row.data(), q.data());
    gather_family(cols, Family::Qd, row.data(), qd.data());
    gather_family(cols, given, row.data(), u.data());
    Index loop = -1;
    const double v = loop_violation(model, loops, q.data(), qd.data(), &loop);
    if (!(v <= kLoopStateTolerance))
      throw DataError(in.where() + ": the state violates loop " + std::to_string(loop) + " (" +
                      loops.loops[loop].link_a + " - " + loops.loops[loop].link_b + ") by " + std::to_string(v) +
                      " (tolerance " + std::to_string(kLoopStateTolerance) + " m, rad, m/s, rad/s)");
    if (solver) {
      try {
        solver->forward_dynamics(q.data(), qd.data(), u.data(), res.data(), res.data() + n);
      } catch (const LoopError& e) {
        throw DataError(in.where() + ": " + e.what());
      }
    } else if (algo == "fd") {
      constrained_forward_dynamics(model, loops, q.data(), qd.data(), u.data(), res.data(), res.data() + n);
    } else {
      constrained_inverse_dynamics(model, loops, q.data(), qd.data(), u.data(), actuated.data(), res.data(),
                                   res.data() + n);
    }
    for (std::size_t j = 0; j < res.size(); ++j)
      if (!std::isfinite(res[j])) throw DataError(in.where() + ": result " + names[j] + " is not finite");
    out.write_row(res.data(), res.size());
  }
  out.commit();
  return kExitOk;
}

}  // namespace scandyn::cli
