// src/factor_graph/sparse_constrained_dynamics.cpp: the simulator's sparse loop path
// (scandyn/factor_graph/sparse_constrained_dynamics.hpp).
#include "scandyn/factor_graph/sparse_constrained_dynamics.hpp"

#if SCANDYN_HAS_CHOLMOD
#include <algorithm>
#include <chrono>
#include <cmath>
#include <stdexcept>

#include "scandyn/algorithm/loop_projection.hpp"
#include "scandyn/algorithm/loop_solver.hpp"
#include "scandyn/factor_graph/gpu_sparse_cholesky.hpp"
#include "scandyn/factor_graph/normal_equations.hpp"

namespace scandyn::factor_graph {

namespace {
double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}
}  // namespace

// One system: its graph and its factor (symbolic analysis at construction): CHOLMOD's,
// or with gpu cuSOLVER's under CHOLMOD's elimination order (CHOLMOD then only orders).
struct SparseConstrainedDynamics::System {
  DynamicsGraph graph;
  SparseCholesky chol;
#if SCANDYN_HAS_FACTOR_GRAPH_GPU
  std::unique_ptr<GpuSparseCholesky> gpu;
#endif
  System(const Model& model, const LoopSet& loops, std::vector<double> armature, const ModelUnits& units,
         Ordering ordering, bool on_gpu, bool compliance = false)
      : graph(model, graph_loops(loops), {}, std::move(armature), &units, compliance), chol(graph.At(), ordering, {}, kLoopBeta) {
#if SCANDYN_HAS_FACTOR_GRAPH_GPU
    if (on_gpu) gpu = std::make_unique<GpuSparseCholesky>(graph.At(), chol.elimination_order(), kLoopBeta);
#else
    if (on_gpu) throw std::runtime_error("sparse loop solver: built without the factor graph's GPU solver (cuSOLVER)");
#endif
  }
  void factorize() {
#if SCANDYN_HAS_FACTOR_GRAPH_GPU
    if (gpu) return gpu->factorize(graph.At());
#endif
    chol.factorize(graph.At());
  }
  void solve(const std::vector<double>& b, std::vector<double>& x, int refine = kLoopRefine) {
#if SCANDYN_HAS_FACTOR_GRAPH_GPU
    if (gpu) return gpu->solve(graph.At(), b, x, refine);
#endif
    chol.solve(graph.At(), b, x, refine);
  }
};

SparseConstrainedDynamics::SparseConstrainedDynamics(const Model& model, const LoopSet& loops, Ordering ordering,
                                                     bool gpu)
    : model_(model), kinematic_model_(model), loops_(loops), rows_(loop_rows_of<double>(loops)), ordering_(ordering),
      gpu_(gpu) {
  // the projection's tree: the same joints, no inertia, no gravity (its joint-space
  // inertia is the unit armature alone)
  for (Body<double>& b : kinematic_model_.bodies) b.I = Inertia<double>::zero();
  kinematic_model_.gravity = Vec3<double>::zero();
  const Index n = model_.nv(), m = loops_.rows();
  X0_.resize(static_cast<std::size_t>(n));
  X0_lin_.resize(static_cast<std::size_t>(n));
  v_.resize(static_cast<std::size_t>(n));
  a_.resize(static_cast<std::size_t>(n));
  zero_.assign(static_cast<std::size_t>(n), Motion<double>::zero());
  phi_.resize(static_cast<std::size_t>(m));
  r_.resize(static_cast<std::size_t>(m));
  dx_.resize(static_cast<std::size_t>(n));
}

SparseConstrainedDynamics::~SparseConstrainedDynamics() = default;

SparseConstrainedDynamics::System& SparseConstrainedDynamics::fd() {
  if (!fd_) {
    const auto t0 = std::chrono::steady_clock::now();
    fd_ = std::make_unique<System>(model_, loops_, std::vector<double>{}, model_units(model_), ordering_, gpu_);
    timing_.analysis += seconds_since(t0);
  }
  return *fd_;
}

SparseConstrainedDynamics::System& SparseConstrainedDynamics::projection() {
  if (!projection_) {
    const auto t0 = std::chrono::steady_clock::now();
    // in the model's units (the massless tree has none of its own: its lengths are
    // the model's), with the armature one unit of joint inertia, M L^2, on every joint:
    // any constant gives the same minimum-norm step, and this one is O(1) there
    const ModelUnits u = model_units(model_);
    projection_ = std::make_unique<System>(
        kinematic_model_, loops_,
        std::vector<double>(static_cast<std::size_t>(model_.nv()), u.mass * u.length * u.length), u, ordering_, gpu_,
        true);  // with the loop rows' compliance: the damped steps
    timing_.analysis += seconds_since(t0);
  }
  return *projection_;
}

const EliminationStats& SparseConstrainedDynamics::forward_dynamics_stats() { return fd().chol.stats(); }
const EliminationStats& SparseConstrainedDynamics::projection_stats() { return projection().chol.stats(); }
Index SparseConstrainedDynamics::forward_dynamics_unknowns() const { return fd_ ? fd_->graph.unknowns() : 0; }

void SparseConstrainedDynamics::forward_dynamics(const double* q, const double* qd, const double* tau, double* qdd,
                                                 double* lambda) {
  System& s = fd();
  const auto t0 = std::chrono::steady_clock::now();
  s.graph.assemble(q, qd, nullptr, tau);
  timing_.assemble += seconds_since(t0);
  factorize_timed(s, "sparse constrained forward dynamics");
  solve_timed(s, s.graph.b());
  s.graph.extract(x_.data(), qdd, nullptr, lambda);
}

void SparseConstrainedDynamics::factorize_timed(System& s, const char* what) {
  const auto t0 = std::chrono::steady_clock::now();
  try {
    s.factorize();
  } catch (const std::runtime_error& e) {
    throw LoopError(std::string(what) + ": " + e.what());
  }
  timing_.factorize += seconds_since(t0);
  ++timing_.factorizations;
}

void SparseConstrainedDynamics::solve_timed(System& s, const std::vector<double>& b) {
  const auto t0 = std::chrono::steady_clock::now();
  s.solve(b, x_);
  timing_.solve += seconds_since(t0);
  ++timing_.solves;
}

void SparseConstrainedDynamics::solve_projection(const double* q, const double* r, double* x, bool factor) {
  System& s = projection();
  DynamicsGraph& g = s.graph;
  if (factor) {
    const auto t0 = std::chrono::steady_clock::now();
    std::fill(dx_.begin(), dx_.end(), 0.0);
    g.assemble(q, dx_.data(), nullptr, dx_.data());  // qd = 0, tau = 0: A at q
    timing_.assemble += seconds_since(t0);
    factorize_timed(s, "sparse loop projection");
  }
  // b: zero but the loop rows (no gravity, qd = 0, tau = 0), r in the model's units
  b_.assign(g.b().size(), 0.0);
  const std::vector<double>& unit = g.equation_unit();
  Index row = 0;
  for (std::size_t k = 0; k < loops_.loops.size(); ++k) {
    const Index e0 = g.var_lambda(k);  // loop k's equations have its multipliers' indices
    for (Index t = 0; t < loops_.loops[k].rows(); ++t, ++row)
      b_[static_cast<std::size_t>(e0 + t)] = r[row] / unit[static_cast<std::size_t>(e0 + t)];
  }
  solve_timed(s, b_);
  g.extract(x_.data(), x, nullptr, nullptr);
}

void SparseConstrainedDynamics::min_norm_step(const double* q, const double* r, double mu, double* x, bool factor) {
  if (mu != factored_mu_) factor = true;
  if (factor) projection().graph.set_loop_compliance(mu), factored_mu_ = mu;
  solve_projection(q, r, x, factor);
}

double SparseConstrainedDynamics::project(double* q, double* qd, double tol, int iterations,
                                          LoopProjectionInfo* info) {
  const Index n = model_.nv(), m = loops_.rows();
  const Index nl = static_cast<Index>(rows_.size());
  // Levenberg-Marquardt of loop_projection.hpp: phi from the loop rows' routines, the
  // minimum-norm solves through the projection system, J v and J^T r by the loops'
  // paths at the factorised q (X0_lin_)
  struct Sparse {
    SparseConstrainedDynamics& s;
    Index n, nl;
    std::vector<double> q_lin;
    bool pending = false;
    bool residual(const double* x, double* phi) {
      loop_body_motion(s.model_.bodies.data(), n, x, static_cast<const double*>(nullptr), s.X0_.data(), s.v_.data(),
                       s.a_.data());
      loop_rows(s.model_.bodies.data(), n, s.rows_.data(), nl, s.X0_.data(), s.v_.data(), s.a_.data(), phi,
                static_cast<double*>(nullptr), static_cast<double*>(nullptr));
      for (Index k = 0; k < s.loops_.rows(); ++k)
        if (!std::isfinite(phi[k])) return false;
      return true;
    }
    void factorize(const double* x) {
      q_lin.assign(x, x + n);
      loop_body_motion(s.model_.bodies.data(), n, x, static_cast<const double*>(nullptr), s.X0_lin_.data(),
                       s.v_.data(), s.a_.data());
      pending = true;  // assembled and factorised at x by the next solve
    }
    void solve(const double* r, double mu, double* x) {
      s.min_norm_step(q_lin.data(), r, mu, x, pending);
      pending = false;
    }
    void apply(const double* v, double* out) {
      loop_jacobian_apply(s.model_.bodies.data(), s.rows_.data(), nl, s.X0_lin_.data(), v, out);
    }
    double damping_scale() const { return 1.0; }  // J J^T in the model's units: O(1)
  } ops{*this, n, nl, {}, true};
  return project_onto_loops(ops, n, m, q, qd, tol, iterations, info);
}

std::unique_ptr<sim::LoopSolver> make_sparse_loop_solver(const Model& model, const LoopSet& loops) {
  return std::make_unique<SparseConstrainedDynamics>(model, loops);
}
std::unique_ptr<sim::LoopSolver> make_gpu_sparse_loop_solver(const Model& model, const LoopSet& loops) {
  return std::make_unique<SparseConstrainedDynamics>(model, loops, Ordering::NESDIS, true);
}

void register_sparse_loop_solver(bool gpu) {
#if !SCANDYN_HAS_FACTOR_GRAPH_GPU
  if (gpu) throw std::runtime_error("sparse loop solver: built without the factor graph's GPU solver (cuSOLVER)");
#endif
  sim::set_sparse_loop_solver(gpu ? &make_gpu_sparse_loop_solver : &make_sparse_loop_solver);
}

}  // namespace scandyn::factor_graph
#endif
