// src/factor_graph/sparse_constrained_dynamics.cpp: the simulator's sparse loop path
// (scandyn/factor_graph/sparse_constrained_dynamics.hpp).
#include "scandyn/factor_graph/sparse_constrained_dynamics.hpp"

#if SCANDYN_HAS_CHOLMOD
#include <algorithm>
#include <chrono>
#include <cmath>
#include <stdexcept>

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
         Ordering ordering, bool on_gpu)
      : graph(model, graph_loops(loops), {}, std::move(armature), &units), chol(graph.At(), ordering, {}, kLoopBeta) {
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
        std::vector<double>(static_cast<std::size_t>(model_.nv()), u.mass * u.length * u.length), u, ordering_, gpu_);
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

double SparseConstrainedDynamics::project(double* q, double* qd, double tol, int iterations) {
  const Index n = model_.nv(), m = loops_.rows();
  if (m == 0) return 0;
  const Index nl = static_cast<Index>(rows_.size());
  auto residual = [&] {  // phi at q
    loop_body_motion(model_.bodies.data(), n, q, static_cast<const double*>(nullptr), X0_.data(), v_.data(),
                     a_.data());
    loop_rows(model_.bodies.data(), n, rows_.data(), nl, X0_.data(), v_.data(), a_.data(), phi_.data(),
              static_cast<double*>(nullptr), static_cast<double*>(nullptr));
    double worst = 0;
    for (double p : phi_) worst = std::max(worst, std::fabs(p));
    return worst;
  };
  for (int it = 0; it < iterations; ++it) {
    if (residual() <= tol) break;
    for (Index k = 0; k < m; ++k) r_[k] = -phi_[k];
    solve_projection(q, r_.data(), dx_.data(), true);  // Gauss-Newton: dq = -J^+ phi
    for (Index i = 0; i < n; ++i) q[i] += dx_[i];
  }
  const double worst = residual();
  // J qd: the loop rows' classical acceleration term with the bodies' velocities as
  // accelerations and no velocity (point_acceleration(X, 0, v, p) = v.v + v.w x p)
  loop_body_motion(model_.bodies.data(), n, q, qd, X0_.data(), v_.data(), a_.data());
  loop_rows(model_.bodies.data(), n, rows_.data(), nl, X0_.data(), zero_.data(), v_.data(),
            static_cast<double*>(nullptr), static_cast<double*>(nullptr), r_.data());
  for (Index k = 0; k < m; ++k) r_[k] = -r_[k];
  std::vector<double> dqd(static_cast<std::size_t>(n));
  solve_projection(q, r_.data(), dqd.data(), true);  // dqd = -J^+ J qd, J at the final q
  for (Index i = 0; i < n; ++i) qd[i] += dqd[i];
  return worst;
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
