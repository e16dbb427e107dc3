// src/sim/iterative_loops.cpp: the simulator's iterative loop solver
// (scandyn/sim/iterative_loops.hpp): conjugate gradients over the tree passes of
// scandyn/algorithm/loop_iterative.hpp.
#include "scandyn/sim/iterative_loops.hpp"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>

#include "scandyn/algorithm/loops.hpp"

namespace scandyn::sim {

namespace {
using Clock = std::chrono::steady_clock;
// iterative_loop_totals' sums (seconds in nanoseconds)
std::atomic<long> g_fd_solves{0}, g_fd_iterations{0}, g_proj_solves{0}, g_proj_iterations{0}, g_applies{0},
    g_apply_ns{0}, g_fd_ns{0}, g_proj_ns{0};
long ns(double seconds) { return static_cast<long>(seconds * 1e9); }

double seconds_since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }
double dot(const double* a, const double* b, Index m) {
  double s = 0;
  for (Index k = 0; k < m; ++k) s += a[k] * b[k];
  return s;
}
double norm(const double* a, Index m) { return std::sqrt(dot(a, a, m)); }
std::string sci(double x) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.3g", x);
  return buf;
}
}  // namespace

IterativeLoopSolver::IterativeLoopSolver(const Model& model, const LoopSet& loops, const IterativeLoopOptions& options)
    : model_(model), loops_(loops), rows_(loop_rows_of<double>(loops)), options_(options) {
  if (model_.multi_dof())
    throw LoopError("iterative loop solver: the model has multi-DoF joints (closed loops take 1-DoF joints)");
  if (!(options_.tolerance > 0) || options_.max_iterations < 1)
    throw LoopError("iterative loop solver: the tolerance must be positive and max_iterations at least 1");
  n_ = model_.nv(), m_ = loops_.rows();
  const std::size_t n = static_cast<std::size_t>(n_), m = static_cast<std::size_t>(m_);
  Xup_.resize(n), X0_.resize(n), U_.resize(n), f_.resize(n), pA_.resize(n);
  D_.resize(n), u_.resize(n), qdd0_.resize(n), tmp_n_.resize(n), xbest_.resize(n), dx_.resize(n), px_.resize(n);
  v_.resize(n), c_.resize(n), a_.resize(n), acc_.resize(n), IA_.resize(n);
  trial_X0_.resize(n), trial_v_.resize(n), trial_a_.resize(n);  // project's trial points (no allocation per call)
  Omega_.resize(n);  // the preconditioner's and the projection's damping scale
  lambda_.assign(m, 0.0);
  b_.resize(m), gamma_.resize(m), r_.resize(m), z_.resize(m), p_.resize(m), Ap_.resize(m), best_.resize(m);
  tmp_m_.resize(m);
  blocks_.assign(rows_.size() * 36, 0.0), block_inv_.assign(rows_.size() * 36, 0.0);
  if (neighbour_blocks(options_.preconditioner)) build_pattern();
  // L_J at q = 0: the unit tree's diagonal blocks
  std::vector<double> q0(n, 0.0);
  loop_body_motion(model_.bodies.data(), n_, q0.data(), static_cast<const double*>(nullptr), X0_.data(), v_.data(),
                   a_.data());
  loop_joint_transforms(model_.bodies.data(), n_, q0.data(), Xup_.data());
  build_preconditioner(nullptr, nullptr, LoopPreconditioner::BlockJacobi);
  double big = 0;
  for (std::size_t k = 0; k < rows_.size(); ++k) {
    const int d = rows_[k].rows();
    for (int i = 0; i < d; ++i) big = std::max(big, blocks_[36 * k + i * d + i]);
  }
  jscale_ = big > 0 ? std::sqrt(big) : 1.0;
}

bool IterativeLoopSolver::neighbour_blocks(LoopPreconditioner p) {
  return p == LoopPreconditioner::SymmetricGaussSeidel || p == LoopPreconditioner::Ssor ||
         p == LoopPreconditioner::BlockTridiagonal || p == LoopPreconditioner::BlockDilu;
}

// The neighbour blocks' pattern (it does not depend on q): every two loops with a link
// on one body, or on a child and its parent; the pairs in rows by the later loop.
void IterativeLoopSolver::build_pattern() {
  const Index nl = static_cast<Index>(rows_.size());
  // the loop sides on each body
  std::vector<Index> start(static_cast<std::size_t>(n_) + 1, 0);
  for (const LoopRow<double>& l : rows_)
    for (Index b : {l.body_a, l.body_b})
      if (b >= 0) ++start[static_cast<std::size_t>(b) + 1];
  for (Index i = 0; i < n_; ++i) start[i + 1] += start[i];
  std::vector<Index> side_loop(static_cast<std::size_t>(start[n_])), fill(start.begin(), start.end() - 1);
  std::vector<int> side_of(side_loop.size());
  for (Index k = 0; k < nl; ++k)
    for (int side = 0; side < 2; ++side) {
      const Index b = side == 0 ? rows_[k].body_a : rows_[k].body_b;
      if (b < 0) continue;
      side_loop[fill[b]] = k, side_of[fill[b]] = side, ++fill[b];
    }
  terms_.clear();
  auto add = [&](Index k1, int s1, Index k2, int s2, int rel12) {
    // rel12: 0 one body, 1 k1's body the child of k2's, 2 k2's the child of k1's
    if (k1 == k2) return;  // (a loop's own cross term through a common ancestor: left out, as on the diagonal)
    if (k1 > k2) terms_.push_back({0, k1, k2, s1, s2, rel12});
    else terms_.push_back({0, k2, k1, s2, s1, rel12 == 0 ? 0 : 3 - rel12});
  };
  for (Index b = 0; b < n_; ++b) {
    for (Index e = start[b]; e < start[b + 1]; ++e) {
      for (Index f = e + 1; f < start[b + 1]; ++f) add(side_loop[e], side_of[e], side_loop[f], side_of[f], 0);
      const Index p = model_.bodies[static_cast<std::size_t>(b)].parent;
      if (p < 0) continue;
      for (Index f = start[p]; f < start[p + 1]; ++f) add(side_loop[e], side_of[e], side_loop[f], side_of[f], 1);
    }
  }
  std::sort(terms_.begin(), terms_.end(), [](const PairTerm& a, const PairTerm& b) {
    return a.hi != b.hi ? a.hi < b.hi : a.lo < b.lo;
  });
  pair_start_.assign(static_cast<std::size_t>(nl) + 1, 0);
  pair_lo_.clear(), pair_off_.clear(), pair_line_.clear();
  std::size_t off = 0;
  for (std::size_t t = 0; t < terms_.size(); ++t) {
    PairTerm& term = terms_[t];
    const bool fresh = t == 0 || term.hi != terms_[t - 1].hi || term.lo != terms_[t - 1].lo;
    if (fresh) {
      pair_lo_.push_back(term.lo), pair_off_.push_back(off), pair_line_.push_back(0);
      ++pair_start_[static_cast<std::size_t>(term.hi) + 1];
      off += static_cast<std::size_t>(rows_[term.hi].rows() * rows_[term.lo].rows());
    }
    term.pair = static_cast<Index>(pair_lo_.size()) - 1;
  }
  for (Index k = 0; k < nl; ++k) pair_start_[k + 1] += pair_start_[k];
  // line neighbours: both links of each of the two loops take part (bits: hi's sides 1, 2; lo's 4, 8)
  std::vector<unsigned char> cover(pair_lo_.size(), 0);
  for (const PairTerm& t : terms_) cover[static_cast<std::size_t>(t.pair)] |= static_cast<unsigned char>((1 << t.s_hi) | (4 << t.s_lo));
  for (std::size_t p = 0; p < cover.size(); ++p) pair_line_[p] = cover[p] == 15;
  pair_vals_.assign(off, 0.0);
  loop_row_.assign(static_cast<std::size_t>(nl) + 1, 0);
  for (Index k = 0; k < nl; ++k) loop_row_[k + 1] = loop_row_[k] + rows_[k].rows();
  pre_acc_.assign(static_cast<std::size_t>(m_), 0.0);
  all_points_ = std::all_of(rows_.begin(), rows_.end(), [](const LoopRow<double>& l) { return !l.weld; });
}

// Raw diagonal blocks of J Omega J^T (U null: the unit tree's) at the current X0_, Xup_,
// and (neighbour_blocks(kind)) the neighbour blocks.
void IterativeLoopSolver::build_preconditioner(const Force<double>* U, const double* D, LoopPreconditioner kind) {
  loop_response_blocks(model_.bodies.data(), n_, Xup_.data(), U, D, Omega_.data());
  for (std::size_t k = 0; k < rows_.size(); ++k) loop_schur_block(rows_[k], X0_.data(), Omega_.data(), &blocks_[36 * k]);
  if (!neighbour_blocks(kind)) return;
  std::fill(pair_vals_.begin(), pair_vals_.end(), 0.0);
  for (const PairTerm& t : terms_) {
    const LoopRow<double>& hi = rows_[t.hi];
    const LoopRow<double>& lo = rows_[t.lo];
    const Index bh = t.s_hi == 0 ? hi.body_a : hi.body_b, bl = t.s_lo == 0 ? lo.body_a : lo.body_b;
    Mat6<double> O;
    if (t.rel == 0) {
      O = Omega_[bh];
    } else {
      const Index c = t.rel == 1 ? bh : bl, p = t.rel == 1 ? bl : bh;
      O = loop_child_response(model_.bodies[c], Xup_[c], U ? &U[c] : nullptr, U ? D[c] : 1.0, Omega_[p]);
      if (t.rel == 2) O = transpose(O);
    }
    loop_pair_block(hi, t.s_hi, lo, t.s_lo, X0_.data(), O, &pair_vals_[pair_off_[t.pair]]);
  }
  if (kind == LoopPreconditioner::Ssor)  // L -> omega L
    for (double& e : pair_vals_) e *= options_.relaxation;
}

void IterativeLoopSolver::apply_preconditioner(const double* r, double* z) const {
  if (weights_ == LoopPreconditioner::None) {
    std::copy(r, r + m_, z);
    return;
  }
  auto block = [&](std::size_t k, const double* in, double* out) {  // out = Dt_k^-1 in
    const int d = rows_[k].rows();
    const double* B = &block_inv_[36 * k];
    for (int i = 0; i < d; ++i) {
      double s = 0;
      for (int j = 0; j < d; ++j) s += B[i * d + j] * in[j];
      out[i] = s;
    }
  };
  if (!neighbour_blocks(weights_)) {
    Index row = 0;
    for (std::size_t k = 0; k < rows_.size(); ++k) {
      block(k, r + row, z + row);
      row += rows_[k].rows();
    }
    return;
  }
  // W r = (Dt + L)^-T Dt (Dt + L)^-1 r: forward y_k = Dt_k^-1 (r_k - sum_{l < k} A_kl y_l),
  // backward z_k = y_k - Dt_k^-1 sum_{l > k} A_kl z_l (the sums scattered by A_lk^T)
  const bool line_only = weights_ == LoopPreconditioner::BlockTridiagonal;
  const Index nl = static_cast<Index>(rows_.size());
  double t[6], y[6];
  if (all_points_ && !line_only) {  // the same sweeps with 3 x 3 blocks (the cloths': unrolled)
    for (Index k = 0; k < nl; ++k) {
      const Index row = 3 * k;
      double t0 = r[row], t1 = r[row + 1], t2 = r[row + 2];
      for (Index p = pair_start_[k]; p < pair_start_[k + 1]; ++p) {
        const double* A = &pair_vals_[9 * static_cast<std::size_t>(p)];
        const double* yl = z + 3 * pair_lo_[p];
        t0 -= A[0] * yl[0] + A[1] * yl[1] + A[2] * yl[2];
        t1 -= A[3] * yl[0] + A[4] * yl[1] + A[5] * yl[2];
        t2 -= A[6] * yl[0] + A[7] * yl[1] + A[8] * yl[2];
      }
      const double* B = &block_inv_[36 * static_cast<std::size_t>(k)];
      z[row] = B[0] * t0 + B[1] * t1 + B[2] * t2;
      z[row + 1] = B[3] * t0 + B[4] * t1 + B[5] * t2;
      z[row + 2] = B[6] * t0 + B[7] * t1 + B[8] * t2;
    }
    double* acc = pre_acc_.data();
    std::fill(acc, acc + m_, 0.0);
    for (Index k = nl - 1; k >= 0; --k) {
      const Index row = 3 * k;
      const double* B = &block_inv_[36 * static_cast<std::size_t>(k)];
      const double a0 = acc[row], a1 = acc[row + 1], a2 = acc[row + 2];
      const double z0 = z[row] - (B[0] * a0 + B[1] * a1 + B[2] * a2);
      const double z1 = z[row + 1] - (B[3] * a0 + B[4] * a1 + B[5] * a2);
      const double z2 = z[row + 2] - (B[6] * a0 + B[7] * a1 + B[8] * a2);
      z[row] = z0, z[row + 1] = z1, z[row + 2] = z2;
      for (Index p = pair_start_[k]; p < pair_start_[k + 1]; ++p) {
        const double* A = &pair_vals_[9 * static_cast<std::size_t>(p)];
        double* al = acc + 3 * pair_lo_[p];
        al[0] += A[0] * z0 + A[3] * z1 + A[6] * z2;
        al[1] += A[1] * z0 + A[4] * z1 + A[7] * z2;
        al[2] += A[2] * z0 + A[5] * z1 + A[8] * z2;
      }
    }
    return;
  }
  for (Index k = 0; k < nl; ++k) {
    const int d = rows_[k].rows();
    const Index row = loop_row_[k];
    for (int i = 0; i < d; ++i) t[i] = r[row + i];
    for (Index p = pair_start_[k]; p < pair_start_[k + 1]; ++p) {
      if (line_only && !pair_line_[p]) continue;
      const Index l = pair_lo_[p];
      const int dl = rows_[l].rows();
      const double* A = &pair_vals_[pair_off_[p]];
      const double* yl = z + loop_row_[l];
      for (int i = 0; i < d; ++i)
        for (int j = 0; j < dl; ++j) t[i] -= A[i * dl + j] * yl[j];
    }
    block(static_cast<std::size_t>(k), t, z + row);
  }
  double* acc = pre_acc_.data();
  std::fill(acc, acc + m_, 0.0);
  for (Index k = nl - 1; k >= 0; --k) {
    const int d = rows_[k].rows();
    const Index row = loop_row_[k];
    block(static_cast<std::size_t>(k), acc + row, y);
    for (int i = 0; i < d; ++i) z[row + i] -= y[i];
    for (Index p = pair_start_[k]; p < pair_start_[k + 1]; ++p) {
      if (line_only && !pair_line_[p]) continue;
      const Index l = pair_lo_[p];
      const int dl = rows_[l].rows();
      const double* A = &pair_vals_[pair_off_[p]];
      double* al = acc + loop_row_[l];
      for (int i = 0; i < d; ++i)
        for (int j = 0; j < dl; ++j) al[j] += A[i * dl + j] * z[row + i];
    }
  }
}

// The weights W: the blocks' inverses with their eigenvalues floored (kLoopBlockFloor);
// BlockDilu and BlockTridiagonal: the incomplete factorisation's Dt_k, in the loops' order.
void IterativeLoopSolver::invert_blocks(LoopPreconditioner kind) {
  const bool dilu = kind == LoopPreconditioner::BlockDilu || kind == LoopPreconditioner::BlockTridiagonal;
  const bool line_only = kind == LoopPreconditioner::BlockTridiagonal;
  for (std::size_t k = 0; k < rows_.size(); ++k) {
    const int d = rows_[k].rows();
    double* Dk = &block_inv_[36 * k];
    std::copy(&blocks_[36 * k], &blocks_[36 * k] + d * d, Dk);
    if (!dilu) {
      symmetric_pseudo_inverse(Dk, d, kLoopBlockFloor);
      continue;
    }
    // Dt_k = A_kk - sum_{l < k} A_kl Dt_l^-1 A_kl^T
    for (Index p = pair_start_[k]; p < pair_start_[k + 1]; ++p) {
      if (line_only && !pair_line_[p]) continue;
      const Index l = pair_lo_[p];
      const int dl = rows_[l].rows();
      const double* A = &pair_vals_[pair_off_[p]];
      const double* Bl = &block_inv_[36 * static_cast<std::size_t>(l)];
      double AB[36];  // A_kl Dt_l^-1 (d x dl)
      for (int i = 0; i < d; ++i)
        for (int j = 0; j < dl; ++j) {
          double s = 0;
          for (int e = 0; e < dl; ++e) s += A[i * dl + e] * Bl[e * dl + j];
          AB[i * dl + j] = s;
        }
      for (int i = 0; i < d; ++i)
        for (int j = 0; j < d; ++j) {
          double s = 0;
          for (int e = 0; e < dl; ++e) s += AB[i * dl + e] * A[j * dl + e];
          Dk[i * d + j] -= s;
        }
    }
    for (int i = 0; i < d; ++i)  // (symmetric up to rounding)
      for (int j = i + 1; j < d; ++j) Dk[i * d + j] = Dk[j * d + i] = 0.5 * (Dk[i * d + j] + Dk[j * d + i]);
    // the floor relative to A_kk's largest eigenvalue; a Dt_k weaker than A_kk in more
    // directions (the incomplete factorisation broke down): A_kk
    double V[36], lam_a[6], lam_d[6];
    symmetric_eigen(&blocks_[36 * k], d, V, lam_a);
    symmetric_eigen(Dk, d, V, lam_d);
    double big = 0;
    for (int i = 0; i < d; ++i) big = std::max(big, lam_a[i]);
    int weak_a = 0, weak_d = 0;
    for (int i = 0; i < d; ++i) weak_a += lam_a[i] <= kLoopBlockFloor * big, weak_d += lam_d[i] <= kLoopBlockFloor * big;
    if (weak_d > weak_a) {
      std::copy(&blocks_[36 * k], &blocks_[36 * k] + d * d, Dk);
      ++stats_.dilu_fallbacks;
    }
    symmetric_pseudo_inverse(Dk, d, kLoopBlockFloor, big);
  }
  weights_ = kind;
}

// The M^-1 J^T of row values w, and J of it: s = M^-1 J^T w (n, in tmp_n_) and
// Js (m) from the tree's response at zero velocity (loop_tree_response, U_ and D_).
void IterativeLoopSolver::schur_response(const double* w, double* Js) {
  const auto t0 = Clock::now();
  const Index nl = static_cast<Index>(rows_.size());
  loop_point_wrenches(rows_.data(), nl, n_, X0_.data(), w, f_.data());
  loop_tree_response(model_.bodies.data(), n_, Xup_.data(), U_.data(), D_.data(), f_.data(), pA_.data(), tmp_n_.data(),
                     acc_.data());
  loop_rows_apply(rows_.data(), nl, X0_.data(), acc_.data(), Js);
  ++stats_.applies;
  stats_.apply_seconds += seconds_since(t0);
}

// lambda_ from b_: conjugate gradients on the normal equations of J x = b in the metric
// of M (x = M^-1 J^T lambda, the constraint accelerations' change), weighted by W
// (CGLS: min ||J x - b||_W, x of least M-norm; the iterates' lambda directions are
// those of preconditioned CG on A lambda = b, and the iteration counts alike, but the
// residual ||b - J x||_W decreases monotonically, also when rounding leaves part of b
// outside A's range, where CG on A diverges). Per iteration one response
// (schur_response): J^T, M^-1 and J as O(n) passes. From the previous lambda (warm
// start). Converged: ||b - A lambda||_2 <= target; or, b partly outside the range, the
// normal residual ||J^T W (b - A lambda)||_{M^-1} at most tolerance times its first value
// and the true ||b - A lambda|| within 10 % (+ target) of the recurrence's.
bool IterativeLoopSolver::fd_solve(double target, int& it, double& rnorm) {
  const Index m = m_, n = n_;
  double* res = r_.data();  // b - J x
  double* w = z_.data();    // W res
  double* pl = p_.data();   // the direction in lambda
  double* Jp = Ap_.data();  // J px = A pl
  double* Js = best_.data();
  double* WJp = tmp_m_.data();
  double* x = dx_.data();   // M^-1 J^T lambda (n)
  double* px = px_.data();  // the direction in x (n)
  const double* s = tmp_n_.data();  // schur_response's M^-1 J^T w
  it = 0;
  bool any = false;
  for (double e : lambda_) any = any || e != 0;
  if (any) {
    schur_response(lambda_.data(), Js);
    std::copy(s, s + n, x);
    for (Index k = 0; k < m; ++k) res[k] = b_[k] - Js[k];
  } else {
    std::fill(x, x + n, 0.0);
    std::copy(b_.begin(), b_.end(), res);
  }
  rnorm = norm(res, m);
  if (rnorm <= target) return true;
  apply_preconditioner(res, w);
  schur_response(w, Js);
  double gamma = dot(w, Js, m);
  const double gamma0 = gamma;
  std::copy(w, w + m, pl);
  std::copy(s, s + n, px);
  std::copy(Js, Js + m, Jp);
  bool least_squares = false;
  LeastSquaresStop stop;
  while (it < options_.max_iterations && gamma > 0) {
    apply_preconditioner(Jp, WJp);
    const double delta = dot(Jp, WJp, m);
    if (!(delta > 0) || !std::isfinite(delta)) break;
    const double alpha = gamma / delta;
    for (Index k = 0; k < m; ++k) lambda_[k] += alpha * pl[k], res[k] -= alpha * Jp[k];
    for (Index i = 0; i < n; ++i) x[i] += alpha * px[i];
    for (Index k = 0; k < m; ++k) w[k] -= alpha * WJp[k];  // W res by its recurrence (W is linear)
    ++it;
    rnorm = norm(res, m);
    if (!std::isfinite(rnorm)) return false;
    if (rnorm <= target) break;
    schur_response(w, Js);
    const double gamma1 = dot(w, Js, m);
    if (stop.least_squares(rnorm, std::sqrt(gamma1 / gamma0))) {
      least_squares = true;
      break;
    }
    const double beta = gamma1 / gamma;
    gamma = gamma1;
    for (Index k = 0; k < m; ++k) pl[k] = w[k] + beta * pl[k], Jp[k] = Js[k] + beta * Jp[k];
    for (Index i = 0; i < n; ++i) px[i] = s[i] + beta * px[i];
  }
  // the true residual b - J x (the recurrence's may drift): converged when it meets
  // the target, or, least squares, when it is the recurrence's (the part of b outside
  // the range, which no x removes). x, not M^-1 J^T lambda: lambda may drift along
  // J^T's null space (without effect on x) where b is partly outside the range.
  const double recurrence = rnorm;
  loop_joint_motion(model_.bodies.data(), n, Xup_.data(), x, acc_.data());
  loop_rows_apply(rows_.data(), static_cast<Index>(rows_.size()), X0_.data(), acc_.data(), Js);
  for (Index k = 0; k < m; ++k) res[k] = b_[k] - Js[k];
  rnorm = norm(res, m);
  return rnorm <= target || (least_squares && rnorm <= 1.1 * recurrence + target);
}

void IterativeLoopSolver::add_to_totals(const IterativeLoopStats& before) const {
  g_fd_solves += stats_.fd_solves - before.fd_solves;
  g_fd_iterations += stats_.fd_iterations - before.fd_iterations;
  g_proj_solves += stats_.proj_solves - before.proj_solves;
  g_proj_iterations += stats_.proj_iterations - before.proj_iterations;
  g_applies += stats_.applies - before.applies;
  g_apply_ns += ns(stats_.apply_seconds - before.apply_seconds);
  g_fd_ns += ns(stats_.fd_seconds - before.fd_seconds);
  g_proj_ns += ns(stats_.proj_seconds - before.proj_seconds);
}

IterativeLoopStats iterative_loop_totals() {
  IterativeLoopStats t;
  t.fd_solves = g_fd_solves, t.fd_iterations = g_fd_iterations, t.proj_solves = g_proj_solves;
  t.proj_iterations = g_proj_iterations, t.applies = g_applies;
  t.apply_seconds = 1e-9 * double(g_apply_ns), t.fd_seconds = 1e-9 * double(g_fd_ns);
  t.proj_seconds = 1e-9 * double(g_proj_ns);
  return t;
}

void reset_iterative_loop_totals() {
  g_fd_solves = 0, g_fd_iterations = 0, g_proj_solves = 0, g_proj_iterations = 0, g_applies = 0, g_apply_ns = 0;
  g_fd_ns = 0, g_proj_ns = 0;
}

void IterativeLoopSolver::forward_dynamics(const double* q, const double* qd, const double* tau, double* qdd,
                                           double* lambda) {
  const IterativeLoopStats before = stats_;
  struct Add {
    const IterativeLoopSolver& s;
    const IterativeLoopStats& before;
    ~Add() { s.add_to_totals(before); }
  } add{*this, before};
  const auto t0 = Clock::now();
  const Body<double>* bodies = model_.bodies.data();
  const Index n = n_, m = m_, nl = static_cast<Index>(rows_.size());
  // X0, and gamma = Jdot qd (body motion with qdd = 0, no gravity)
  loop_body_motion(bodies, n, q, qd, X0_.data(), v_.data(), a_.data());
  loop_rows(bodies, n, rows_.data(), nl, X0_.data(), v_.data(), a_.data(), static_cast<double*>(nullptr),
            static_cast<double*>(nullptr), gamma_.data());
  // the tree: qdd0 and the articulated inertias' U, D
  const Index failed = loop_aba_factor(bodies, n, model_.gravity, q, qd, tau, Xup_.data(), U_.data(), D_.data(),
                                       qdd0_.data(), v_.data(), c_.data(), a_.data(), IA_.data(), pA_.data(), u_.data());
  if (failed >= 0)
    throw LoopError("iterative loop solver: the articulated-body pivot of DoF " + std::to_string(failed) +
                    " is not positive and finite");
  // b = -gamma - J qdd0
  loop_joint_motion(bodies, n, Xup_.data(), qdd0_.data(), acc_.data());
  loop_rows_apply(rows_.data(), nl, X0_.data(), acc_.data(), tmp_m_.data());
  for (Index k = 0; k < m; ++k) b_[k] = -gamma_[k] - tmp_m_[k];
  // the size of the constraint accelerations, ||gamma|| + ||J qdd0||, and the floor
  // kIterativeLoopFloor L_J ||qdd0|| (L_J: sqrt of the largest diagonal entry of J J^T at
  // q = 0, a length), which keeps the target above rounding and above the part of b a
  // state's loop violation puts outside J's range, where gamma and J qdd0 cancel
  const double scale = norm(gamma_.data(), m) + norm(tmp_m_.data(), m);
  const double floor = kIterativeLoopFloor * jscale_ * norm(qdd0_.data(), n);
  if (!options_.warm_start) std::fill(lambda_.begin(), lambda_.end(), 0.0);
  for (double e : lambda_)
    if (!std::isfinite(e)) {
      std::fill(lambda_.begin(), lambda_.end(), 0.0);
      break;
    }
  const double target = options_.tolerance * scale + floor;
  if (m > 0) {
    if (options_.preconditioner != LoopPreconditioner::None) {
      build_preconditioner(U_.data(), D_.data(), options_.preconditioner);
      invert_blocks(options_.preconditioner);
    }
    int it = 0;
    double residual = 0;
    const bool ok = fd_solve(target, it, residual);
    residual /= scale > 0 ? scale : 1.0;
    ++stats_.fd_solves;
    stats_.fd_iterations += it;
    stats_.last_iterations = it;
    stats_.last_residual = residual;
    if (!ok) {
      std::fill(lambda_.begin(), lambda_.end(), 0.0);  // no warm start from a failed solve
      stats_.fd_seconds += seconds_since(t0);
      throw LoopSolveNotConverged("iterative loop solver: conjugate gradients on J M^-1 J^T did not converge (relative residual " +
                      sci(residual) + " after " + std::to_string(it) + " iterations, at most " +
                      std::to_string(options_.max_iterations) + "; tolerance " + sci(options_.tolerance) + ")");
    }
  }
  // qdd = qdd0 + M^-1 J^T lambda (fd_solve's x)
  if (m == 0) std::fill(dx_.begin(), dx_.end(), 0.0);
  for (Index i = 0; i < n; ++i) {
    qdd[i] = qdd0_[i] + dx_[i];
    if (!std::isfinite(qdd[i])) {
      std::fill(lambda_.begin(), lambda_.end(), 0.0);
      stats_.fd_seconds += seconds_since(t0);
      throw LoopSolveNotConverged("iterative loop solver: qdd of DoF " + std::to_string(i) + " is not finite");
    }
  }
  if (lambda) std::copy(lambda_.begin(), lambda_.end(), lambda);
  stats_.fd_seconds += seconds_since(t0);
}

// The projection's step x = argmin ||J x - r||_W^2 + mu ||x||^2 = J^T (J J^T + mu W^-1)^-1 r
// at its linearisation, by conjugate gradients on the normal equations
// (J^T W J + mu I) x = J^T W r from x = 0 (CGLS: each iteration one J p and one J^T W q;
// min-norm, and a least-squares solution also when r is not in J's range, as a
// projection's residual partly is at rounding level). W: the SSOR or block-Jacobi weights
// of J J^T (this is CG on J J^T + mu W^-1 with that preconditioner, in the rows' terms;
// W times the residual by its recurrence), or 1 without a preconditioner. mu is at least
// kLoopRankTolerance (of the damping scale). Converged (mu = 0 asked), judged on the TRUE
// residual r - J x at the end (the recurrence's and the normal residual's only decide
// when to stop): ||r - J x||_2 <= tolerance ||r||_2 + floor; or, where the rounds stopped
// at the damped normal residual ||J^T W (r - J x) - mu x||_2 <= tolerance times its first
// value (the residual no longer halving), ||r - J x||_2 <= allowance + floor (the part of
// r the rank floor mu leaves: the caller's sqrt(kLoopRankTolerance) L_J ||v||_2 for r = J
// v). A recurrence's residual at the target that the true one is not (drift): another
// round from the true residual. mu > 0 asked: the damped problem solved (its normal
// residual), the residual is what it is.
void IterativeLoopSolver::unit_solve(const double* r, double mu_in, double floor, double allowance, double* x,
                                     bool& converged) {
  const Index n = n_, m = m_, nl = static_cast<Index>(rows_.size());
  // every solve damped by at least kLoopRankTolerance of the scale: J's directions of
  // singular value below 1e-5 (relative) stay out of the step, as the dense solve's
  // rank threshold keeps them out (a right-hand side at rounding level would otherwise
  // be "solved" along them by steps of any length)
  const double mu = std::max(mu_in, kLoopRankTolerance * unit_scale_);
  const Body<double>* bodies = model_.bodies.data();
  double* res = r_.data();  // r - J x (rows)
  double* wq = z_.data();   // W times a row vector
  double* q = Ap_.data();   // J p (rows)
  std::vector<double>& s = tmp_n_;
  std::vector<double>& p = qdd0_;  // (free during a projection)
  std::copy(r, r + m, res);
  std::fill(x, x + n, 0.0);
  double* wres = tmp_m_.data();  // W res, by its recurrence within a round (W is linear)
  auto jt = [&](const double* wrows, double* out) {  // out (n) = J^T wrows
    loop_point_wrenches(rows_.data(), nl, n, X0_.data(), wrows, f_.data());
    loop_joint_forces(bodies, n, Xup_.data(), f_.data(), pA_.data(), out);
  };
  auto jv = [&](const double* v, double* out) {  // out (m) = J v
    loop_joint_motion(bodies, n, Xup_.data(), v, acc_.data());
    loop_rows_apply(rows_.data(), nl, X0_.data(), acc_.data(), out);
  };
  const auto t0 = Clock::now();
  const double r0 = norm(res, m);
  const double target = options_.tolerance * r0 + floor;
  double rn = r0, sn = 0, s0 = 0;
  int it = 0;
  converged = rn <= target;
  // the iterate of least residual: a right-hand side at rounding level (a step's drift
  // closed to it) may not decrease further
  double best = r0;
  std::vector<double>& xbest = xbest_;
  std::fill(xbest.begin(), xbest.end(), 0.0);
  // rounds: CGLS to its damped normal residual, then (mu = 0 asked) again from the true
  // residual r - J x while that is above the target and the last round halved it
  bool damped = false;  // stopped at the damped normal residual (mu = 0 asked)
  for (int round = 0; round < 4 && !converged && it < options_.max_iterations; ++round) {
    const double round_start = rn;
    if (round > 0) {  // the true residual at x
      jv(x, q);
      for (Index k = 0; k < m; ++k) res[k] = r[k] - q[k];
      rn = norm(res, m);
      if (mu_in == 0 && rn <= target) {
        converged = true;
        break;
      }
    }
    apply_preconditioner(res, wres);
    jt(wres, s.data());
    for (Index i = 0; i < n; ++i) s[i] -= mu * x[i];
    sn = norm(s.data(), n);
    if (round == 0) s0 = sn;  // (every round's normal residual relative to the first's)
    double gamma = sn * sn;
    std::copy(s.begin(), s.end(), p.begin());
    bool normal = sn <= options_.tolerance * s0;
    while (!normal && it < options_.max_iterations && gamma > 0) {
      jv(p.data(), q);
      apply_preconditioner(q, wq);
      const double delta = dot(q, wq, m) + mu * dot(p.data(), p.data(), n);
      if (!(delta > 0) || !std::isfinite(delta)) break;
      const double alpha = gamma / delta;
      for (Index i = 0; i < n; ++i) x[i] += alpha * p[i];
      for (Index k = 0; k < m; ++k) res[k] -= alpha * q[k], wres[k] -= alpha * wq[k];
      ++it;
      rn = norm(res, m);
      if (!std::isfinite(rn)) break;
      if (rn < best) best = rn, std::copy(x, x + n, xbest.begin());
      if (mu_in == 0 && rn <= target) {
        converged = true;
        break;
      }
      jt(wres, s.data());
      for (Index i = 0; i < n; ++i) s[i] -= mu * x[i];
      const double gamma1 = dot(s.data(), s.data(), n);
      sn = std::sqrt(gamma1);
      // the damped normal equations' residual (r - J x need not vanish)
      if (sn <= options_.tolerance * s0) {
        normal = true;
        break;
      }
      const double beta = gamma1 / gamma;
      gamma = gamma1;
      for (Index i = 0; i < n; ++i) p[i] = s[i] + beta * p[i];
    }
    if (converged) {
      // the recurrence's residual at the target: the true one too, else (drift) the next
      // round from it
      jv(x, q);
      double t = 0;
      for (Index k = 0; k < m; ++k) t += (r[k] - q[k]) * (r[k] - q[k]);
      if (std::sqrt(t) <= target) break;
      converged = false;
      continue;
    }
    if (!normal) break;  // the cap, or a breakdown: not converged
    if (mu_in != 0 || !(rn <= 0.5 * round_start)) {
      converged = true;  // the damped problem solved (its residual is what remains)
      damped = mu_in == 0;
      break;
    }
  }
  if (mu_in == 0 && !(rn <= best)) {
    std::copy(xbest.begin(), xbest.end(), x);
    rn = best;
    converged = converged || rn <= target;
  }
  for (Index i = 0; i < n; ++i)
    if (!std::isfinite(x[i])) {
      std::fill(x, x + n, 0.0);
      converged = false;
      break;
    }
  last_r0_ = r0, last_target_ = target, last_allowance_ = allowance + floor;
  if (mu_in == 0) {
    // the acceptance, on the true residual r - J x (never the recurrence's or the damped
    // normal residual alone: where J J^T's small singular values leave r - J x far above
    // a normal residual at its tolerance, that would be a wrong projection)
    jv(x, q);
    double t = 0;
    for (Index k = 0; k < m; ++k) t += (r[k] - q[k]) * (r[k] - q[k]);
    rn = std::sqrt(t);
    const bool within = rn <= target || (damped && rn <= allowance + floor);
    converged = std::isfinite(rn) && within && (converged || rn <= target);
  }
  stats_.applies += it;
  stats_.apply_seconds += seconds_since(t0);
  ++stats_.proj_solves;
  stats_.proj_iterations += it;
  stats_.last_iterations = it;
  stats_.last_residual = r0 > 0 ? rn / r0 : 0;
  last_residual_abs_ = rn;
}

double IterativeLoopSolver::project(double* q, double* qd, double tol, int iterations, LoopProjectionInfo* info) {
  const IterativeLoopStats before = stats_;
  struct Add {
    const IterativeLoopSolver& s;
    const IterativeLoopStats& before;
    ~Add() { s.add_to_totals(before); }
  } add{*this, before};
  const auto t0 = Clock::now();
  const Body<double>* bodies = model_.bodies.data();
  const Index n = n_, m = m_, nl = static_cast<Index>(rows_.size());
  struct Ops {
    IterativeLoopSolver& s;
    bool last_converged = true;
    bool residual(const double* x, double* phi) {  // (the trial points' poses in the solver's scratch)
      loop_body_motion(s.model_.bodies.data(), s.n_, x, static_cast<const double*>(nullptr), s.trial_X0_.data(),
                       s.trial_v_.data(), s.trial_a_.data());
      loop_rows(s.model_.bodies.data(), s.n_, s.rows_.data(), static_cast<Index>(s.rows_.size()), s.trial_X0_.data(),
                s.trial_v_.data(), s.trial_a_.data(), phi, static_cast<double*>(nullptr), static_cast<double*>(nullptr));
      for (Index k = 0; k < s.m_; ++k)
        if (!std::isfinite(phi[k])) return false;
      return true;
    }
    void factorize(const double* x) {
      loop_body_motion(s.model_.bodies.data(), s.n_, x, static_cast<const double*>(nullptr), s.X0_.data(),
                       s.v_.data(), s.a_.data());
      loop_joint_transforms(s.model_.bodies.data(), s.n_, x, s.Xup_.data());
      // the unit tree's blocks: also the damping's scale; the weights: None, Ssor, or
      // block Jacobi for the others (their neighbour-block weights of J J^T are
      // ill-conditioned: docs/loops.md, "Preconditioner")
      const LoopPreconditioner p = s.options_.preconditioner;
      const LoopPreconditioner kind =
          p == LoopPreconditioner::None || p == LoopPreconditioner::Ssor ? p : LoopPreconditioner::BlockJacobi;
      s.build_preconditioner(nullptr, nullptr, kind);
      double big = 0;
      for (std::size_t k = 0; k < s.rows_.size(); ++k) {
        const int d = s.rows_[k].rows();
        for (int i = 0; i < d; ++i) big = std::max(big, s.blocks_[36 * k + i * d + i]);
      }
      // Levenberg-Marquardt's damping scale, the size of J J^T in the weights' units: 1
      // with weights (block Jacobi: W^1/2 J J^T W^1/2 has unit diagonal blocks; SSOR's
      // are of that size), else the largest diagonal entry of J J^T
      s.unit_scale_ = s.options_.preconditioner != LoopPreconditioner::None ? 1.0 : big > 0 ? big : 1.0;
      if (kind != LoopPreconditioner::None) s.invert_blocks(kind);
    }
    double floor = 0, allowance = 0;  // the solves' absolute tolerances (below)
    void solve(const double* r, double mu, double* x) {
      s.unit_solve(r, mu, floor, allowance, x, last_converged);
      if (!last_converged && mu == 0) ++s.stats_.proj_unconverged;
    }
    void apply(const double* v_in, double* out) {
      loop_joint_motion(s.model_.bodies.data(), s.n_, s.Xup_.data(), v_in, s.acc_.data());
      loop_rows_apply(s.rows_.data(), static_cast<Index>(s.rows_.size()), s.X0_.data(), s.acc_.data(), out);
    }
    double damping_scale() const { return s.unit_scale_; }
  } ops{*this};
  (void)bodies, (void)nl;
  LoopProjectionInfo out;
  // the floor of the solves' residual r - J x for r = J v (v: q for the position steps,
  // qd for the velocities): kIterativeLoopFloor L_J max(||q||_2, ||qd||_2), the
  // residual a dense projection leaves
  ops.floor = kIterativeLoopFloor * jscale_ * std::max(norm(q, n), norm(qd, n));
  // and the part of J qd the rank floor mu = kLoopRankTolerance leaves (J qd along J's
  // directions of singular value below sqrt(kLoopRankTolerance) L_J, which the damping
  // keeps out of the step as the dense solve's rank threshold does): the velocity
  // projection's allowance where it stops at the damped normal residual
  ops.allowance = std::sqrt(kLoopRankTolerance) * jscale_ * norm(qd, n);
  const double phi = project_onto_loops(ops, n, m, q, qd, tol, iterations, &out);
  if (info) *info = out;
  stats_.proj_seconds += seconds_since(t0);
  // the last solve was the velocity projection's (J qd = 0): it must have converged, on
  // its true residual ||J qd'||_2 (unit_solve's acceptance)
  if (m > 0 && !ops.last_converged)
    throw LoopSolveNotConverged(
        "iterative loop solver: the velocity projection did not converge: ||J qd||_2 " + sci(last_residual_abs_) +
        " after it (" + sci(last_r0_) + " before; relative residual " + sci(stats_.last_residual) + ") after " +
        std::to_string(stats_.last_iterations) + " iterations (at most " + std::to_string(options_.max_iterations) +
        "); accepted: at most " + sci(last_target_) + " (tolerance " + sci(options_.tolerance) +
        " of ||J qd||_2 before + 1e-12 L_J max(||q||_2, ||qd||_2)), or " + sci(last_allowance_) +
        " where it stopped at the damped normal residual (1e-5 L_J ||qd||_2 + the same floor)");
  return phi;
}

std::unique_ptr<LoopSolver> make_iterative_loop_solver(const Model& model, const LoopSet& loops) {
  return std::make_unique<IterativeLoopSolver>(model, loops);
}

namespace {
template <LoopPreconditioner P>
std::unique_ptr<LoopSolver> make_preconditioned(const Model& model, const LoopSet& loops) {
  IterativeLoopOptions options;
  options.preconditioner = P;
  return std::make_unique<IterativeLoopSolver>(model, loops, options);
}
}  // namespace

LoopSolverFactory iterative_loop_solver_factory(LoopPreconditioner p) {
  switch (p) {
    case LoopPreconditioner::None: return &make_preconditioned<LoopPreconditioner::None>;
    case LoopPreconditioner::BlockJacobi: return &make_preconditioned<LoopPreconditioner::BlockJacobi>;
    case LoopPreconditioner::SymmetricGaussSeidel: return &make_preconditioned<LoopPreconditioner::SymmetricGaussSeidel>;
    case LoopPreconditioner::Ssor: return &make_preconditioned<LoopPreconditioner::Ssor>;
    case LoopPreconditioner::BlockTridiagonal: return &make_preconditioned<LoopPreconditioner::BlockTridiagonal>;
    case LoopPreconditioner::BlockDilu: return &make_preconditioned<LoopPreconditioner::BlockDilu>;
  }
  return &make_iterative_loop_solver;
}

}  // namespace scandyn::sim
