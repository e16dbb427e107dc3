// src/algorithm/loops.cpp: loop-closure kinematics and the constrained dynamics
// (scandyn/algorithm/loops.hpp): the loops' rows by the per-instance routines of
// loop_solver.hpp (shared with the loop engines), the tree's recursions for M and h
// (crba, bias_forces), and dense rank-revealing solves (Eigen): the reference the
// engines' own solve (constrained_fd_solve) is tested against.
#include "scandyn/algorithm/loops.hpp"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>

#include "scandyn/algorithm/loop_iterative.hpp"
#include "scandyn/algorithm/loop_projection.hpp"
#include "scandyn/algorithm/loop_solver.hpp"
#include "scandyn/algorithm/reference.hpp"

namespace scandyn {

using MatX = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
using VecX = Eigen::VectorXd;

Index LoopSet::rows() const {
  Index m = 0;
  for (const LoopClosure& l : loops) m += l.rows();
  return m;
}

void loop_kinematics(const Model& model, const LoopSet& loops, const double* q, const double* qd, double* phi,
                     double* J, double* gamma) {
  const Index n = model.nv();
  std::vector<Transform<double>> X0(n);  // (nv) body <- base
  std::vector<Motion<double>> v(n), a(n);  // (nv) body frames, qdd = 0 and no gravity
  loop_body_motion(model.bodies.data(), n, q, qd, X0.data(), v.data(), a.data());
  const std::vector<LoopRow<double>> rows = loop_rows_of<double>(loops);
  loop_rows(model.bodies.data(), n, rows.data(), static_cast<Index>(rows.size()), X0.data(), v.data(), a.data(), phi,
            J, gamma);
}

double loop_violation(const Model& model, const LoopSet& loops, const double* q, const double* qd, Index* loop) {
  // phi from the loops' rows; J qd as the points' relative velocities (and a weld's
  // relative angular velocity) by loop_rows_apply over the bodies' velocities, without
  // forming J: O(nv + m), as large grids need
  const Index n = model.nv(), m = loops.rows();
  std::vector<Transform<double>> X0(n);
  std::vector<Motion<double>> v(n), a(n);
  loop_body_motion(model.bodies.data(), n, q, qd, X0.data(), v.data(), a.data());
  const std::vector<LoopRow<double>> rows = loop_rows_of<double>(loops);
  const Index nl = static_cast<Index>(rows.size());
  std::vector<double> phi(m), jqd(m);
  loop_rows(model.bodies.data(), n, rows.data(), nl, X0.data(), v.data(), a.data(), phi.data(),
            static_cast<double*>(nullptr), static_cast<double*>(nullptr));
  loop_rows_apply(rows.data(), nl, X0.data(), v.data(), jqd.data());
  double worst = 0;
  Index row = 0, where = -1;
  for (Index k = 0; k < nl; ++k) {
    for (Index r = row; r < row + rows[k].rows(); ++r) {
      const double e = std::max(std::fabs(phi[r]), std::fabs(jqd[r]));
      if (where < 0 || e > worst || std::isnan(e)) worst = e, where = k;
    }
    row += rows[k].rows();
  }
  if (loop) *loop = where;
  return worst;
}

LoopAccelerationClosure loop_acceleration_closure(const Model& model, const LoopSet& loops, const double* q,
                                                  const double* qd, const double* tau, const double* qdd) {
  const Index n = model.nv(), m = loops.rows();
  const std::vector<LoopRow<double>> rows = loop_rows_of<double>(loops);
  const Index nl = static_cast<Index>(rows.size());
  const Body<double>* bodies = model.bodies.data();
  std::vector<Transform<double>> X0(n), Xup(n);
  std::vector<Motion<double>> v(n), a(n), acc(n), c(n);
  std::vector<Force<double>> U(n), pA(n);
  std::vector<ABInertia<double>> IA(n);
  std::vector<double> gamma(m), jq(m), D(n), u(n), qdd0(n);
  loop_body_motion(bodies, n, q, qd, X0.data(), v.data(), a.data());
  loop_rows(bodies, n, rows.data(), nl, X0.data(), v.data(), a.data(), static_cast<double*>(nullptr),
            static_cast<double*>(nullptr), gamma.data());
  loop_aba_factor(bodies, n, model.gravity, q, qd, tau, Xup.data(), U.data(), D.data(), qdd0.data(), v.data(),
                  c.data(), a.data(), IA.data(), pA.data(), u.data());
  const auto norm = [](const std::vector<double>& x) {
    double s = 0;
    for (double e : x) s += e * e;
    return std::sqrt(s);
  };
  LoopAccelerationClosure out;
  loop_joint_motion(bodies, n, Xup.data(), qdd0.data(), acc.data());
  loop_rows_apply(rows.data(), nl, X0.data(), acc.data(), jq.data());
  out.jqdd0 = norm(jq), out.gamma = norm(gamma), out.qdd0 = norm(qdd0);
  loop_joint_motion(bodies, n, Xup.data(), qdd, acc.data());
  loop_rows_apply(rows.data(), nl, X0.data(), acc.data(), jq.data());
  for (Index k = 0; k < m; ++k) jq[k] += gamma[k];
  out.residual = norm(jq);
  return out;
}

bool generator_has_loops(const std::string& spec) {
  return spec == "fivebar" || spec == "fourbar" || spec.rfind("cloth:", 0) == 0;
}

namespace {

// min-norm least-squares solver of A x = b with the loops' rank threshold
Eigen::CompleteOrthogonalDecomposition<Eigen::MatrixXd> rank_revealing(const Eigen::MatrixXd& A) {
  Eigen::CompleteOrthogonalDecomposition<Eigen::MatrixXd> cod;
  cod.setThreshold(kLoopRankTolerance);
  cod.compute(A);
  return cod;
}

}  // namespace

LoopSolveInfo constrained_forward_dynamics(const Model& model, const LoopSet& loops, const double* q, const double* qd,
                                           const double* tau, double* qdd, double* lambda,
                                           const Force<double>* fext) {
  const Index n = model.nv(), m = loops.rows();
  Data data(model);
  MatX M(n, n);
  VecX h(n);
  crba(model, data, q, M.data());
  bias_forces(model, data, q, qd, h.data(), fext);
  const Eigen::LLT<Eigen::MatrixXd> llt(M);
  if (llt.info() != Eigen::Success) throw LoopError("constrained forward dynamics: the mass matrix is not positive definite");
  const VecX qdd0 = llt.solve(Eigen::Map<const VecX>(tau, n) - h);
  LoopSolveInfo info;
  if (m == 0) {
    Eigen::Map<VecX>(qdd, n) = qdd0;
    return info;
  }
  MatX J(m, n);
  VecX gamma(m);
  loop_kinematics(model, loops, q, qd, nullptr, J.data(), gamma.data());
  const Eigen::MatrixXd MinvJt = llt.solve(J.transpose());
  const Eigen::MatrixXd A = J * MinvJt;
  const auto cod = rank_revealing(A);
  VecX lam = cod.solve(VecX(-gamma - J * qdd0));
  VecX x = qdd0 + MinvJt * lam;
  // one step of iterative refinement on J qdd + gamma = 0 (ill-conditioned A: cloth grids)
  const VecX dlam = cod.solve(VecX(-(J * x + gamma)));
  lam += dlam;
  x += MinvJt * dlam;
  Eigen::Map<VecX>(qdd, n) = x;
  Eigen::Map<VecX>(lambda, m) = lam;
  info.rank = cod.rank();
  info.residual = (J * x + gamma).cwiseAbs().maxCoeff();
  return info;
}

LoopSolveInfo constrained_inverse_dynamics(const Model& model, const LoopSet& loops, const double* q, const double* qd,
                                           const double* qdd, const unsigned char* actuated, double* tau,
                                           double* lambda, const Force<double>* fext) {
  const Index n = model.nv(), m = loops.rows();
  Data data(model, false);
  VecX b(n);
  rnea(model, data, q, qd, qdd, b.data(), fext);  // M qdd + h
  MatX J(m, n);
  loop_kinematics(model, loops, q, qd, nullptr, J.data(), nullptr);
  std::vector<Index> act, un;
  for (Index i = 0; i < n; ++i) (actuated[i] ? act : un).push_back(i);
  // J^T's rows at the unactuated DoFs (JU, |U| x m) and at the actuated ones (JA)
  Eigen::MatrixXd JU(un.size(), m), JA(act.size(), m);
  VecX bU(un.size()), bA(act.size());
  for (std::size_t k = 0; k < un.size(); ++k) JU.row(k) = J.col(un[k]).transpose(), bU[k] = b[un[k]];
  for (std::size_t k = 0; k < act.size(); ++k) JA.row(k) = J.col(act[k]).transpose(), bA[k] = b[act[k]];
  // lambda = lambda_p + N z: JU lambda = bU, N spans JU's null space
  VecX lp = VecX::Zero(m);
  Eigen::MatrixXd N = Eigen::MatrixXd::Identity(m, m);
  LoopSolveInfo info;
  if (!un.empty() && m > 0) {
    Eigen::JacobiSVD<Eigen::MatrixXd> svd(JU, Eigen::ComputeThinU | Eigen::ComputeFullV);
    svd.setThreshold(kLoopRankTolerance);
    lp = svd.solve(bU);
    const Index r = svd.rank();
    N = svd.matrixV().rightCols(m - r);
    info.rank = r;
  }
  // tau_A = bA - JA lambda, of minimum norm over z
  VecX lam = lp;
  if (N.cols() > 0 && !act.empty()) {
    const auto cod = rank_revealing(JA * N);
    lam = lp + N * cod.solve(VecX(bA - JA * lp));
  }
  const VecX tA = bA - JA * lam;
  Eigen::Map<VecX> t(tau, n);
  t.setZero();
  for (std::size_t k = 0; k < act.size(); ++k) t[act[k]] = tA[k];
  if (m > 0) Eigen::Map<VecX>(lambda, m) = lam;
  info.residual = (t + J.transpose() * lam - b).cwiseAbs().maxCoeff();
  return info;
}

double project_to_loops(const Model& model, const LoopSet& loops, double* q, double* qd, double tol, int iterations,
                        LoopProjectionInfo* info) {
  const Index n = model.nv(), m = loops.rows();
  // Levenberg-Marquardt of loop_projection.hpp over the dense J: Gauss-Newton's
  // minimum-norm steps by its complete orthogonal decomposition, damped ones by its
  // SVD (computed at the first damped step of a linearisation), x = V diag(s / (s^2 +
  // mu)) U^T r over the singular values above the rank threshold
  struct Dense {
    const Model& model;
    const LoopSet& loops;
    MatX J;
    Eigen::CompleteOrthogonalDecomposition<Eigen::MatrixXd> cod;
    Eigen::BDCSVD<Eigen::MatrixXd> svd;
    bool have_svd = false;
    bool residual(const double* x, double* phi) {
      loop_kinematics(model, loops, x, nullptr, phi, nullptr, nullptr);
      for (Index k = 0; k < J.rows(); ++k)
        if (!std::isfinite(phi[k])) return false;
      return true;
    }
    void factorize(const double* x) {
      loop_kinematics(model, loops, x, nullptr, nullptr, J.data(), nullptr);
      cod = rank_revealing(J);
      have_svd = false;
    }
    void solve(const double* r, double mu, double* x) {
      const Eigen::Map<const VecX> rv(r, J.rows());
      if (mu == 0) {
        Eigen::Map<VecX>(x, J.cols()) = cod.solve(rv);
        return;
      }
      if (!have_svd) svd.compute(J, Eigen::ComputeThinU | Eigen::ComputeThinV), have_svd = true;
      const VecX& sv = svd.singularValues();
      VecX c = svd.matrixU().transpose() * rv;
      for (Index k = 0; k < sv.size(); ++k)
        c[k] = sv[k] > kLoopRankTolerance * sv[0] ? c[k] * sv[k] / (sv[k] * sv[k] + mu) : 0.0;
      Eigen::Map<VecX>(x, J.cols()) = svd.matrixV() * c;
    }
    void apply(const double* v, double* out) { Eigen::Map<VecX>(out, J.rows()) = J * Eigen::Map<const VecX>(v, J.cols()); }
    double damping_scale() const { return J.rowwise().squaredNorm().maxCoeff(); }
  } ops{model, loops, MatX(m, n), {}, {}, false};
  return project_onto_loops(ops, n, m, q, qd, tol, iterations, info);
}

}  // namespace scandyn
