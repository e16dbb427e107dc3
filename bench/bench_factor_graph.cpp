// bench/bench_factor_graph.cpp: the factor-graph seed's Tables I and II (inverse and
// forward dynamics time per elimination ordering) next to scandyn's RNEA, ABA and
// CRBA + Cholesky, same machine, same run; and the same for loop systems (a planar
// five-bar, a cloth grid). Writes CSV to stdout (docs/factor-graph.md).
//
// Times are the minimum over --reps repetitions of the mean of --inner calls (the
// machine may be shared: minima are the stable statistic). Factor-graph rows time
// assemble + numeric factorisation + solve (one refinement step) for a symbolic
// analysis done once; nnz_L and flops are CHOLMOD's symbolic counts.
//
// Usage: bench_factor_graph [--reps 30] [--inner 200] [--cloth K:N ...] [--models DIR]
//                           [--patterns FILE] [--small] [--gpu] [--accuracy [--states S]]
// --accuracy: the loop systems' forward dynamics against the dense reference
// constrained_forward_dynamics (docs/loops.md) at S (default 3) random closed states
// of fivebar, fourbar and the cloth grids (default 4:4, 10:10, 30:30): q in
// [-0.2, 0.2] and qd in [-1, 1] projected onto the loops, tau in [-1, 1] N m
// (1e-3 for the cloths' 10 g links); CHOLMOD's nested dissection, kLoopBeta,
// kLoopRefine. CSV: model,links,loop_rows,states,fg_us,dense_us,max_qdd_rel_err
// (max over the states of max |qdd - qdd_ref| / max |qdd_ref|),max_residual (SI).
// --gpu: only the cloth grids (default 10:10, 30:30, 50:50, 100:100), one forward
// dynamics with loops each, solved by CHOLMOD on the host and by cuSOLVER's sparse
// Cholesky on the GPU (GpuSparseCholesky) under the same elimination order
// (CHOLMOD's nested dissection), with the symbolic analysis, the numeric
// factorisation and the solve (3 refinement steps) timed separately; CSV columns
// as below plus solver, analysis_us, device_mb and qdd_vs_cholmod.
// Instruction counts (the machine may be loaded; counts are not):
//   valgrind --tool=callgrind --collect-atstart=no --callgrind-out-file=/tmp/fg_cg.%p
//     build-cpu/bench_factor_graph --small --reps 1 --inner 50 > /dev/null
//   scripts/factor_graph_callgrind.py /tmp/fg_cg.*
// --patterns writes the pattern of L (row, col in elimination positions) of every
// system with at most 2000 unknowns (the robots, the five-bar) for the fill figures
// (scripts/factor_graph_figures.py).
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <functional>
#include <random>
#include <string>
#include <vector>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/factor_graph/dynamics_graph.hpp"
#include "scandyn/factor_graph/gpu_sparse_cholesky.hpp"
#include "scandyn/factor_graph/normal_equations.hpp"
#include "scandyn/factor_graph/sparse_cholesky.hpp"
#include "scandyn/model/load.hpp"

#if __has_include(<valgrind/callgrind.h>)
#include <valgrind/callgrind.h>
#else  // without valgrind's headers: never under callgrind
#define RUNNING_ON_VALGRIND 0
#define CALLGRIND_TOGGLE_COLLECT
#define CALLGRIND_DUMP_STATS_AT(label) (void)(label)
#endif

using namespace scandyn;
using namespace scandyn::factor_graph;

namespace {

using LoopClosure = factor_graph::LoopClosure;  // the graph's loops, not the loop files' (scandyn::LoopClosure)

int g_reps = 30, g_inner = 200;
std::FILE* g_patterns = nullptr;  // --patterns FILE: the factor L of selected systems
// Loop systems: kLoopBeta, kLoopRefine (scandyn/factor_graph/normal_equations.hpp).

// Under valgrind --tool=callgrind --collect-atstart=no, each measurement instead
// runs f `inner` times with collection on and dumps the counts with the label
// "<label> x<inner>" (scripts/factor_graph_callgrind.py divides them); returns 0.
double time_us(const std::string& label, const std::function<void()>& f, int inner) {
  if (RUNNING_ON_VALGRIND) {
    CALLGRIND_TOGGLE_COLLECT;
    for (int k = 0; k < inner; ++k) f();
    CALLGRIND_TOGGLE_COLLECT;
    const std::string dump = label + " x" + std::to_string(inner);
    CALLGRIND_DUMP_STATS_AT(dump.c_str());
    return 0;
  }
  double best = 1e300;
  for (int r = 0; r < g_reps; ++r) {
    const auto t0 = std::chrono::steady_clock::now();
    for (int k = 0; k < inner; ++k) f();
    const auto t1 = std::chrono::steady_clock::now();
    best = std::min(best, std::chrono::duration<double, std::micro>(t1 - t0).count() / inner);
  }
  return best;
}

double max_diff(const std::vector<double>& a, const std::vector<double>& b) {
  double m = 0;
  for (std::size_t k = 0; k < a.size(); ++k) m = std::max(m, std::abs(a[k] - b[k]));
  return m;
}

// max |b - A x| of the graph's system, each equation in SI (the system is stored in
// the model's units: DynamicsGraph::equation_unit)
double residual_norm(const DynamicsGraph& g, const std::vector<double>& x) {
  std::vector<double> r(g.b().size());
  residual(g.At(), g.b(), x.data(), r.data());
  double m = 0;
  for (std::size_t e = 0; e < r.size(); ++e) m = std::max(m, std::abs(r[e]) * g.equation_unit()[e]);
  return m;
}

// top_body: the body whose unknown is eliminated last (the top separator of a
// nested dissection), -1 for a loop multiplier or a row without elimination.
void row(const std::string& model, const char* problem, const std::string& method, double us,
         double factor_us, double solve_us, const EliminationStats* s, double err, Index top_body = -1) {
  std::printf("%s,%s,%s,%.3f,%.3f,%.3f,%.0f,%.0f,%.0f,%d,%d,%.3g\n", model.c_str(), problem, method.c_str(), us,
              factor_us, solve_us, s ? s->nnz_A : 0.0, s ? s->nnz_L : 0.0, s ? s->flops : 0.0,
              s ? s->etree_height : 0, top_body, err);
  std::fflush(stdout);
}

// One factor-graph row per ordering: total (assemble + factor + solve), factor, solve.
void graph_rows(const std::string& name, const char* problem, DynamicsGraph& g, const double* q,
                const double* qd, const double* qdd_in, const double* tau_in, double beta,
                const std::vector<double>* ref, bool want_tau, int inner, bool with_cr, int refine = 1) {
  const Index nv = g.model().nv();
  struct O { Ordering o; std::string label; std::vector<Index> perm; };
  std::vector<O> orders = {{Ordering::Given, "fg-tree", g.tree_order()}, {Ordering::AMD, "fg-amd", {}},
                           {Ordering::COLAMD, "fg-colamd", {}}, {Ordering::METIS, "fg-metis-nd", {}},
                           {Ordering::NESDIS, "fg-cholmod-nd", {}}};
  // The tree order puts the loop multipliers last: one dense block of all of them.
  if (g.unknowns() - 14 * nv > 3000) orders.erase(orders.begin());
  if (with_cr) orders.push_back({Ordering::Given, "fg-cyclic-reduction", g.cyclic_reduction_order()});
  for (const O& o : orders) {
    g.assemble(q, qd, qdd_in, tau_in);
    SparseCholesky chol(g.At(), o.o, o.perm, beta);
    std::vector<double> x;
    chol.factorize(g.At());
    chol.solve(g.At(), g.b(), x, refine);
    double err = 0;
    if (ref) {
      std::vector<double> out(static_cast<std::size_t>(nv));
      g.extract(x.data(), want_tau ? nullptr : out.data(), want_tau ? out.data() : nullptr, nullptr);
      err = max_diff(out, *ref);
    } else {
      err = residual_norm(g, x);
    }
    const std::string label = name + "," + problem + "," + o.label;
    const double total = time_us(label + ",total", [&] {
      g.assemble(q, qd, qdd_in, tau_in);
      chol.factorize(g.At());
      chol.solve(g.At(), g.b(), x, refine);
    }, inner);
    const double fac = time_us(label + ",factor", [&] { chol.factorize(g.At()); }, inner);
    const double sol = time_us(label + ",solve", [&] { chol.solve(g.At(), g.b(), x, refine); }, inner);
    const Index last = chol.elimination_order().back();
    row(name, problem, o.label, total, fac, sol, &chol.stats(), err, last < 14 * nv ? last / 14 : -1);
    if (g_patterns && g.unknowns() <= 2000)
      for (const auto& [r, c] : chol.factor_pattern())
        std::fprintf(g_patterns, "%s,%s,%s,%d,%d\n", name.c_str(), problem, o.label.c_str(), r, c);
  }
}

// Planar five-bar: two 2-link chains from the base (at x = 0 and x = 1), all joints
// about z, links 1 m, the tips joined by a point loop; closed at q = (pi/2, -pi/6,
// pi/2, pi/6) (a rhombus).
Model five_bar() {
  RawTree t;
  t.name = t.source = "five-bar";
  auto link = [&](const std::string& n) {
    RawLink l; l.name = n; l.has_inertial = true; l.mass = 1.0; l.com_xyz = {0.5, 0, 0};
    l.inertia = {0.001, 1.0 / 12, 1.0 / 12, 0, 0, 0}; t.links.push_back(l);
  };
  RawLink base; base.name = "base"; t.links.push_back(base);
  for (const char* n : {"a1", "a2", "b1", "b2"}) link(n);
  auto joint = [&](const std::string& n, const std::string& p, const std::string& c, Vec3<double> xyz) {
    RawJoint j; j.name = n; j.type = RawJointType::Continuous; j.type_name = "continuous"; j.parent = p;
    j.child = c; j.xyz = xyz; j.axis = {0, 0, 1}; t.joints.push_back(j);
  };
  joint("ja1", "base", "a1", {0, 0, 0});
  joint("ja2", "a1", "a2", {1, 0, 0});
  joint("jb1", "base", "b1", {1, 0, 0});
  joint("jb2", "b1", "b2", {1, 0, 0});
  return build_model(t);
}

void tree_tables(const std::string& path) {
  const Model model = load_urdf(path);
  const Index nv = model.nv();
  Data data(model);
  std::mt19937_64 rng(560);
  std::uniform_real_distribution<double> u(-1, 1);
  std::vector<double> q(nv), qd(nv), qdd(nv), tau(nv), out(nv), M(nv * nv);
  for (Index i = 0; i < nv; ++i) { q[i] = 3 * u(rng); qd[i] = u(rng); qdd[i] = 2 * u(rng); }
  // Table I: inverse dynamics
  rnea(model, data, q.data(), qd.data(), qdd.data(), tau.data());
  const std::vector<double> tau_ref = tau;
  const double t_rnea = time_us(model.name + ",id,rnea,total", [&] { rnea(model, data, q.data(), qd.data(), qdd.data(), out.data()); }, g_inner * 10);
  row(model.name, "id", "rnea", t_rnea, 0, 0, nullptr, max_diff(out, tau_ref));
  DynamicsGraph gid(model, {}, std::vector<char>(nv, 1));
  graph_rows(model.name, "id", gid, q.data(), qd.data(), qdd.data(), nullptr, 0.0, &tau_ref, true, g_inner, false);
  // Table II: forward dynamics
  aba(model, data, q.data(), qd.data(), tau.data(), out.data());
  const std::vector<double> qdd_ref = out;
  const double t_aba = time_us(model.name + ",fd,aba,total", [&] { aba(model, data, q.data(), qd.data(), tau.data(), out.data()); }, g_inner * 10);
  row(model.name, "fd", "aba", t_aba, 0, 0, nullptr, max_diff(out, qdd_ref));
  row(model.name, "fd", "crba", time_us(model.name + ",fd,crba,total", [&] { crba(model, data, q.data(), M.data()); }, g_inner * 10), 0, 0, nullptr, 0);
  const double t_jsi = time_us(model.name + ",fd,crba+ltl (fd_jsi),total", [&] { fd_jsi(model, data, q.data(), qd.data(), tau.data(), out.data()); }, g_inner * 10);
  row(model.name, "fd", "crba+ltl (fd_jsi)", t_jsi, 0, 0, nullptr, max_diff(out, qdd_ref));
  DynamicsGraph gfd(model, {}, {});
  graph_rows(model.name, "fd", gfd, q.data(), qd.data(), nullptr, tau.data(), 0.0, &qdd_ref, false, g_inner,
             model.nv() > 0 && [&] { for (Index i = 0; i < nv; ++i) if (model.parent(i) != i - 1) return false; return true; }());
}

void loop_tables(const std::string& name, const Model& model, const std::vector<LoopClosure>& loops,
                 const std::vector<double>& q, double tau_scale, int inner) {
  const Index nv = model.nv();
  std::vector<double> qd(nv, 0.0), tau(nv, 0.0);
  for (Index i = 0; i < nv; ++i) tau[i] = tau_scale * std::sin(1.0 + i);
  DynamicsGraph g(model, loops, {});
  graph_rows(name, "fd-loops", g, q.data(), qd.data(), nullptr, tau.data(), kLoopBeta, nullptr, false, inner, false,
             kLoopRefine);
  Data data(model, nv <= 2000);
  std::vector<double> out(nv);
  row(name, "fd-tree-only", "aba", time_us(name + ",fd-tree-only,aba,total", [&] { aba(model, data, q.data(), qd.data(), tau.data(), out.data()); }, inner), 0, 0, nullptr, 0);
}

#if SCANDYN_HAS_FACTOR_GRAPH_GPU
// The GPU's sparse Cholesky next to CHOLMOD on one loop system (forward dynamics at
// q = 0, qd = 0, tau_i = 1e-5 sin(1 + i)), both under CHOLMOD's nested-dissection
// order: the symbolic analysis once (timed once), then per repetition assemble,
// factorise and solve (kLoopRefine refinement steps) timed separately; minima over
// the repetitions, time_us = the minimum of their sums.
void gpu_rows(const std::string& name, const Model& model, const std::vector<LoopClosure>& loops, int reps) {
  const Index nv = model.nv();
  const std::vector<double> q(static_cast<std::size_t>(nv), 0.0), qd(q);
  std::vector<double> tau(static_cast<std::size_t>(nv));
  for (Index i = 0; i < nv; ++i) tau[i] = 1e-5 * std::sin(1.0 + i);
  DynamicsGraph g(model, loops, {});
  g.assemble(q.data(), qd.data(), nullptr, tau.data());
  using clock = std::chrono::steady_clock;
  auto us = [](clock::time_point a, clock::time_point b) { return std::chrono::duration<double, std::micro>(b - a).count(); };
  struct Times { double total = 1e300, assemble = 1e300, factor = 1e300, solve = 1e300; };
  // reps x {assemble, factorize, solve} of one solver
  auto measure = [&](auto& solver, std::vector<double>& x) {
    Times t;
    for (int r = 0; r < reps; ++r) {
      const auto t0 = clock::now();
      g.assemble(q.data(), qd.data(), nullptr, tau.data());
      const auto t1 = clock::now();
      solver.factorize(g.At());
      const auto t2 = clock::now();
      solver.solve(g.At(), g.b(), x, kLoopRefine);
      const auto t3 = clock::now();
      t.assemble = std::min(t.assemble, us(t0, t1));
      t.factor = std::min(t.factor, us(t1, t2));
      t.solve = std::min(t.solve, us(t2, t3));
      t.total = std::min(t.total, us(t0, t3));
    }
    return t;
  };
  auto qdd_of = [&](const std::vector<double>& x) {
    std::vector<double> qdd(static_cast<std::size_t>(nv));
    g.extract(x.data(), qdd.data(), nullptr, nullptr);
    return qdd;
  };
  auto print = [&](const char* solver, const Times& t, double analysis, const EliminationStats& s, double device_mb,
                   double err, double vs, Index last) {
    std::printf("%s,fd-loops,fg-cholmod-nd,%s,%.3f,%.3f,%.3f,%.3f,%.0f,%.0f,%.0f,%d,%d,%.3g,%.3f,%.3g\n", name.c_str(),
                solver, t.total, analysis, t.factor, t.solve, s.nnz_A, s.nnz_L, s.flops, s.etree_height,
                last < 14 * nv ? last / 14 : -1, err, device_mb, vs);
    std::fflush(stdout);
  };
  const auto a0 = clock::now();
  SparseCholesky chol(g.At(), Ordering::NESDIS, {}, kLoopBeta);
  const double chol_analysis = us(a0, clock::now());
  std::vector<double> x_chol, x_gpu;
  const Times tc = measure(chol, x_chol);
  const std::vector<double> qdd_chol = qdd_of(x_chol);
  const Index last = chol.elimination_order().back();
  print("cholmod", tc, chol_analysis, chol.stats(), 0.0, residual_norm(g, x_chol), 0.0, last);
  const auto a1 = clock::now();
  GpuSparseCholesky gpu(g.At(), chol.elimination_order(), kLoopBeta);
  const double gpu_analysis = us(a1, clock::now());
  const Times tg = measure(gpu, x_gpu);
  const std::vector<double> qdd_gpu = qdd_of(x_gpu);
  double scale = 0;
  for (double v : qdd_chol) scale = std::max(scale, std::abs(v));
  const double device_mb = static_cast<double>(gpu.stats().internal_bytes + gpu.stats().workspace_bytes +
                                               (sizeof(double) + sizeof(int)) * gpu.stats().nnz_B) / 1e6;
  print("cusolver-sp", tg, gpu_analysis, chol.stats(), device_mb, residual_norm(g, x_gpu),
        max_diff(qdd_gpu, qdd_chol) / std::max(scale, 1e-300), last);
}
#endif

// The factor graph's loop forward dynamics against the dense reference at `states`
// random closed states (see --accuracy above); times: the minimum over the states of
// one call each (factor graph: assemble + factorise + solve, analysis done once).
void accuracy_rows(const std::string& spec, int states) {
  const Model model = make_generated(spec);
  const LoopSet loops = generator_loops(spec, model);
  const Index nv = model.nv(), m = loops.rows();
  const double tau_scale = spec.rfind("cloth", 0) == 0 ? 1e-3 : 1.0;
  DynamicsGraph g(model, graph_loops(loops), {});
  SparseCholesky chol(g.At(), Ordering::NESDIS, {}, kLoopBeta);
  std::mt19937_64 rng(21);
  std::uniform_real_distribution<double> u(-1, 1);
  using clock = std::chrono::steady_clock;
  auto us = [](clock::time_point a, clock::time_point b) { return std::chrono::duration<double, std::micro>(b - a).count(); };
  double fg_us = 1e300, dense_us = 1e300, worst = 0, worst_res = 0;
  std::vector<double> q(nv), qd(nv), tau(nv), qdd(nv), qdd_ref(nv), lambda_ref(m), x;
  for (int s = 0; s < states; ++s) {
    for (double r = 1; r > 1e-12;) {  // a closed state (redraw when the projection fails)
      for (Index i = 0; i < nv; ++i) { q[i] = 0.2 * u(rng); qd[i] = u(rng); }
      r = project_to_loops(model, loops, q.data(), qd.data());
    }
    for (Index i = 0; i < nv; ++i) tau[i] = tau_scale * u(rng);
    const auto t0 = clock::now();
    constrained_forward_dynamics(model, loops, q.data(), qd.data(), tau.data(), qdd_ref.data(), lambda_ref.data());
    const auto t1 = clock::now();
    g.assemble(q.data(), qd.data(), nullptr, tau.data());
    chol.factorize(g.At());
    chol.solve(g.At(), g.b(), x, kLoopRefine);
    const auto t2 = clock::now();
    g.extract(x.data(), qdd.data(), nullptr, nullptr);
    dense_us = std::min(dense_us, us(t0, t1));
    fg_us = std::min(fg_us, us(t1, t2));
    double scale = 0;
    for (double v : qdd_ref) scale = std::max(scale, std::abs(v));
    worst = std::max(worst, max_diff(qdd, qdd_ref) / scale);
    worst_res = std::max(worst_res, residual_norm(g, x));
  }
  std::printf("%s,%d,%d,%d,%.1f,%.1f,%.3g,%.3g\n", spec.c_str(), nv, m, states, fg_us, dense_us, worst, worst_res);
  std::fflush(stdout);
}

// Chains: nested dissection against block cyclic reduction (the parallel chain
// FD's scan, scandyn/algorithm/chain_fd.hpp). Symbolic counts only.
void chain_orderings(long long n) {
  const Model model = make_generated("chain:" + std::to_string(n));
  DynamicsGraph g(model, {}, {});
  const std::string name = "chain:" + std::to_string(n);
  struct O { Ordering o; const char* label; std::vector<Index> perm; };
  const O orders[] = {{Ordering::Given, "fg-tree", g.tree_order()},
                      {Ordering::Given, "fg-cyclic-reduction", g.cyclic_reduction_order()},
                      {Ordering::METIS, "fg-metis-nd", {}}, {Ordering::NESDIS, "fg-cholmod-nd", {}},
                      {Ordering::AMD, "fg-amd", {}}};
  for (const O& o : orders) {
    SparseCholesky chol(g.At(), o.o, o.perm, 0.0, true);
    const Index last = chol.elimination_order().back();
    row(name, "fd-symbolic", o.label, 0, 0, 0, &chol.stats(), 0, last / 14);
    if (g_patterns && g.unknowns() <= 2000) {
      const std::vector<double> zero(static_cast<std::size_t>(n), 0.0);
      g.assemble(zero.data(), zero.data(), nullptr, zero.data());
      chol.factorize(g.At());
      for (const auto& [r, c] : chol.factor_pattern())
        std::fprintf(g_patterns, "%s,fd-symbolic,%s,%d,%d\n", name.c_str(), o.label, r, c);
    }
  }
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<std::string> cloths = {"10:10", "30:30", "50:50"};
  std::string models_dir = SCANDYN_DEFAULT_MODELS_DIR;
  bool custom_cloth = false, small_only = false, gpu = false, accuracy = false;
  int states = 3;
  for (int k = 1; k < argc; ++k) {
    const std::string a = argv[k];
    if (a == "--reps" && k + 1 < argc) g_reps = std::atoi(argv[++k]);
    else if (a == "--inner" && k + 1 < argc) g_inner = std::atoi(argv[++k]);
    else if (a == "--models" && k + 1 < argc) models_dir = argv[++k];
    else if (a == "--small") small_only = true;  // robots and five-bar only (callgrind)
    else if (a == "--gpu") gpu = true;
    else if (a == "--accuracy") accuracy = true;
    else if (a == "--states" && k + 1 < argc) states = std::atoi(argv[++k]);
    else if (a == "--patterns" && k + 1 < argc) {
      g_patterns = std::fopen(argv[++k], "w");
      if (!g_patterns) { std::fprintf(stderr, "bench_factor_graph: cannot write '%s'\n", argv[k]); return 1; }
      std::fprintf(g_patterns, "model,problem,method,row,col\n");
    }
    else if (a == "--cloth" && k + 1 < argc) { if (!custom_cloth) cloths.clear(); custom_cloth = true; cloths.push_back(argv[++k]); }
    else { std::fprintf(stderr, "bench_factor_graph: unknown argument '%s'\n", a.c_str()); return 2; }
  }
  if (accuracy) {
    if (!custom_cloth) cloths = {"4:4", "10:10", "30:30"};
    std::printf("model,links,loop_rows,states,fg_us,dense_us,max_qdd_rel_err,max_residual\n");
    for (const std::string& spec : {std::string("fivebar"), std::string("fourbar")}) accuracy_rows(spec, states);
    for (const std::string& kn : cloths) accuracy_rows("cloth:" + kn, states);
    return 0;
  }
  if (gpu) {
#if SCANDYN_HAS_FACTOR_GRAPH_GPU
    if (!custom_cloth) cloths = {"10:10", "30:30", "50:50", "100:100"};
    std::printf("model,problem,method,solver,time_us,analysis_us,factor_us,solve_us,nnz_A,nnz_L,flops,etree_height,"
                "top_body,max_err,device_mb,qdd_vs_cholmod\n");
    try {
      {  // CUDA context and cuSOLVER's libraries loaded before the first timed analysis
        const Model m = make_generated("cloth:2:2");
        DynamicsGraph g(m, graph_loops(generator_loops("cloth:2:2", m)), {});
        GpuSparseCholesky warm(g.At(), {}, kLoopBeta);
      }
      for (const std::string& kn : cloths) {
        const Model m = make_generated("cloth:" + kn);
        const int reps = m.nv() >= 10000 ? 1 : m.nv() >= 900 ? std::min(g_reps, 3) : g_reps;
        gpu_rows("cloth:" + kn, m, graph_loops(generator_loops("cloth:" + kn, m)), reps);
      }
    } catch (const std::exception& e) {
      std::fprintf(stderr, "bench_factor_graph: %s\n", e.what());
      return 1;
    }
    return 0;
#else
    std::fprintf(stderr, "bench_factor_graph: --gpu needs a build with CUDA and cuSOLVER (SCANDYN_CUDA=ON)\n");
    return 2;
#endif
  }
  std::printf("model,problem,method,time_us,factor_us,solve_us,nnz_A,nnz_L,flops,etree_height,top_body,max_err\n");
  tree_tables(models_dir + "/puma560.urdf");
  tree_tables(models_dir + "/iiwa.urdf");
  if (!small_only)
    for (long long n : {15LL, 63LL, 255LL, 1023LL, 4095LL}) chain_orderings(n);
  {  // five-bar
    const Model m = five_bar();
    factor_graph::LoopClosure L; L.body_a = 1; L.point_a = {1, 0, 0}; L.body_b = 3; L.point_b = {1, 0, 0};
    const double pi = 3.14159265358979323846;
    loop_tables("five-bar", m, {L}, {pi / 2, -pi / 6, pi / 2, pi / 6}, 1.0, g_inner);
  }
  if (small_only) cloths.clear();
  for (const std::string& kn : cloths) {  // cloth grid: curtain:K:N + point loops between neighbouring ropes
    const Model m = make_generated("cloth:" + kn);
    const std::vector<factor_graph::LoopClosure> loops = graph_loops(generator_loops("cloth:" + kn, m));
    const int reps = g_reps;
    if (m.nv() >= 900) g_reps = std::min(g_reps, 3);  // seconds per solve: a few repetitions
    loop_tables("cloth:" + kn, m, loops, std::vector<double>(m.nv(), 0.0), 1e-5, std::max(1, g_inner / m.nv()));
    g_reps = reps;
  }
  if (g_patterns) std::fclose(g_patterns);
  return 0;
}
