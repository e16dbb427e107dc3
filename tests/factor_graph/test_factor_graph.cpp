// The dynamics factor graph (scandyn/factor_graph/*): its sparse system, solved by
// CHOLMOD under every ordering, reproduces the serial RNEA (all qdd given), ABA (all
// tau given) and the hybrid dynamics (tau = RNEA(q, qd, qdd) on every row, the given
// entries unchanged) on random trees and the shipped robots; loop closures hold at
// the acceleration level; for a chain, the cyclic-reduction order and nested
// dissection both have a logarithmic elimination tree where the tree order's is linear.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>

#include <Eigen/Dense>

#include "loop_cases.hpp"
#include "scandyn/algorithm/loops.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/factor_graph/dynamics_graph.hpp"
#include "scandyn/factor_graph/normal_equations.hpp"
#include "scandyn/factor_graph/sparse_cholesky.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

using test::max_abs;
using test::max_diff;

using factor_graph::DynamicsGraph;
using factor_graph::LoopClosure;

std::vector<Model> test_models() {
  std::vector<Model> models;
  for (const char* f : {"iiwa.urdf", "hyq.urdf", "atlas.urdf", "puma560.urdf"}) models.push_back(test::load_robot(f));
  for (const char* spec : {"tree:12:1", "tree:30:7", "chain:20", "tree:5:3"}) models.push_back(make_generated(spec));
  return models;
}

TEST(FactorGraph, SystemIsSquareWithFourteenUnknownsPerBody) {
  const Model model = make_generated("tree:9:2");
  DynamicsGraph g(model, {}, {});
  EXPECT_EQ(g.unknowns(), 14 * model.nv());
  EXPECT_EQ(g.At().cols, g.At().rows);
  const std::vector<Index> order = g.tree_order();
  std::vector<Index> sorted = order;
  std::sort(sorted.begin(), sorted.end());
  for (Index k = 0; k < g.unknowns(); ++k) ASSERT_EQ(sorted[k], k);
}

TEST(FactorGraph, RejectsBadLoops) {
  const Model model = make_generated("chain:4");
  LoopClosure self;
  self.body_a = self.body_b = 2;
  EXPECT_THROW(DynamicsGraph(model, {self}, {}), std::invalid_argument);
  LoopClosure outside;
  outside.body_a = 7;
  EXPECT_THROW(DynamicsGraph(model, {outside}, {}), std::invalid_argument);
}

// The explicit normal matrix (what the GPU's solver factors): B = P (D A^T A D +
// beta I) P^T under a random elimination order equals the dense product formed
// from A entry by entry (1e-14 of its largest entry; double), is exactly symmetric,
// has the diagonal and ascending columns in every row (a tree and a loop system);
// its dense Cholesky through NormalEquations::solve reproduces ABA on iiwa (1e-12
// relative, double).
TEST(FactorGraph, NormalMatrixIsTheScaledNormalEquations) {
  using factor_graph::NormalEquations;
  using factor_graph::NormalMatrix;
  std::mt19937_64 rng(25);
  auto shuffled = [&](Index n) {
    std::vector<Index> order(static_cast<std::size_t>(n));
    for (Index k = 0; k < n; ++k) order[k] = k;
    std::shuffle(order.begin(), order.end(), rng);
    return order;
  };
  // B as a dense matrix
  auto dense = [](const NormalMatrix& B) {
    Eigen::MatrixXd Bd = Eigen::MatrixXd::Zero(B.n(), B.n());
    for (Index k = 0; k < B.n(); ++k)
      for (Index p = B.row_ptr()[k]; p < B.row_ptr()[k + 1]; ++p) Bd(k, B.col_idx()[p]) = B.val()[p];
    return Bd;
  };
  const Model curtain = make_generated("curtain:2:4");
  LoopClosure point;
  point.body_a = 3; point.point_a = {0.01, 0, -0.01};
  point.body_b = 7; point.point_b = {-0.01, 0, -0.01};
  for (const std::vector<LoopClosure>& loops : {std::vector<LoopClosure>{}, std::vector<LoopClosure>{point}}) {
    const int nv = curtain.nv();
    DynamicsGraph g(curtain, loops, {});
    const auto q = test::random_vector(rng, nv, -1, 1), qd = test::random_vector(rng, nv, -1, 1),
               tau = test::random_vector(rng, nv, -1e-3, 1e-3);
    g.assemble(q.data(), qd.data(), nullptr, tau.data());
    const factor_graph::SparseMatrix& At = g.At();
    const Index n = At.rows;
    const std::vector<Index> order = shuffled(n);
    // dense A (equations x unknowns), its column norms, the normal matrix
    Eigen::MatrixXd A = Eigen::MatrixXd::Zero(At.cols, n);
    for (Index e = 0; e < At.cols; ++e)
      for (Index t = At.col_ptr[e]; t < At.col_ptr[e + 1]; ++t) A(e, At.row_idx[t]) = At.val[t];
    const double beta = 1e-3;
    const Eigen::VectorXd d = A.colwise().norm().cwiseInverse().transpose();
    const Eigen::MatrixXd N = d.asDiagonal() * (A.transpose() * A) * d.asDiagonal() +
                              beta * Eigen::MatrixXd::Identity(n, n);
    NormalEquations ne;
    ne.equilibrate(At);
    NormalMatrix B(At, order);
    B.assemble(At, ne.scaled(), beta);
    ASSERT_EQ(B.n(), n);
    for (Index k = 0; k < n; ++k) {
      bool diagonal = false;
      for (Index p = B.row_ptr()[k]; p < B.row_ptr()[k + 1]; ++p) {
        if (p > B.row_ptr()[k]) {
          ASSERT_LT(B.col_idx()[p - 1], B.col_idx()[p]) << "row " << k;
        }
        diagonal |= B.col_idx()[p] == k;
      }
      EXPECT_TRUE(diagonal) << "row " << k;
    }
    const Eigen::MatrixXd Bd = dense(B);
    EXPECT_EQ((Bd - Bd.transpose()).cwiseAbs().maxCoeff(), 0.0);
    double err = 0;
    for (Index k = 0; k < n; ++k)
      for (Index l = 0; l < n; ++l) err = std::max(err, std::abs(Bd(k, l) - N(order[k], order[l])));
    EXPECT_LE(err, 1e-14 * N.cwiseAbs().maxCoeff()) << loops.size() << " loops";
  }
  {  // a tree: B is definite with beta = 0; the refined solve through it gives ABA's qdd
    const Model model = test::load_robot("iiwa.urdf");
    const int nv = model.nv();
    DynamicsGraph g(model, {}, {});
    const auto q = test::random_vector(rng, nv, -3, 3), qd = test::random_vector(rng, nv, -2, 2),
               tau = test::random_vector(rng, nv, -10, 10);
    g.assemble(q.data(), qd.data(), nullptr, tau.data());
    const Index n = g.unknowns();
    const std::vector<Index> order = shuffled(n);
    NormalEquations ne;
    ne.equilibrate(g.At());
    NormalMatrix B(g.At(), order);
    B.assemble(g.At(), ne.scaled(), 0.0);
    const Eigen::LLT<Eigen::MatrixXd> llt(dense(B));
    ASSERT_EQ(llt.info(), Eigen::Success);
    std::vector<double> x, qdd(static_cast<std::size_t>(nv)), qdd_fg(static_cast<std::size_t>(nv));
    ne.solve(g.At(), g.b(), x, 2, [&](const double* rhs, double* y) {
      Eigen::VectorXd z(n);
      for (Index k = 0; k < n; ++k) z[k] = rhs[order[k]];
      z = llt.solve(z);
      for (Index k = 0; k < n; ++k) y[order[k]] = z[k];
    });
    g.extract(x.data(), qdd_fg.data(), nullptr, nullptr);
    Data data(model);
    ASSERT_TRUE(aba(model, data, q.data(), qd.data(), tau.data(), qdd.data()).ok());
    EXPECT_LE(max_diff(qdd_fg, qdd), 1e-12 * (1 + max_abs(qdd)));
  }
  // an order that is not a permutation of the unknowns
  DynamicsGraph g(curtain, {}, {});
  std::vector<Index> bad(static_cast<std::size_t>(g.unknowns()), 0);
  EXPECT_THROW(NormalMatrix(g.At(), bad), std::invalid_argument);
  EXPECT_THROW(NormalMatrix(g.At(), std::vector<Index>{0, 1}), std::invalid_argument);
}

#if SCANDYN_HAS_CHOLMOD
using factor_graph::Ordering;
using factor_graph::SparseCholesky;

constexpr Ordering kOrderings[] = {Ordering::Given, Ordering::AMD, Ordering::COLAMD, Ordering::METIS,
                                   Ordering::NESDIS};

// Solves g's system under ordering o (Given: the tree order).
std::vector<double> solve(const DynamicsGraph& g, Ordering o) {
  SparseCholesky chol(g.At(), o, o == Ordering::Given ? g.tree_order() : std::vector<Index>{});
  chol.factorize(g.At());
  std::vector<double> x;
  chol.solve(g.At(), g.b(), x, 2);
  return x;
}

// Inverse dynamics: every ordering gives RNEA's tau to 1e-12 (relative to the torques' size).
TEST(FactorGraph, InverseDynamicsEqualsRneaUnderEveryOrdering) {
  std::mt19937_64 rng(21);
  for (const Model& model : test_models()) {
    const int nv = model.nv();
    Data data(model);
    DynamicsGraph g(model, {}, std::vector<char>(static_cast<std::size_t>(nv), 1));
    for (int trial = 0; trial < 3; ++trial) {
      const auto q = test::random_vector(rng, nv, -3, 3), qd = test::random_vector(rng, nv, -2, 2),
                 qdd = test::random_vector(rng, nv, -5, 5);
      std::vector<double> tau(static_cast<std::size_t>(nv));
      rnea(model, data, q.data(), qd.data(), qdd.data(), tau.data());
      g.assemble(q.data(), qd.data(), qdd.data(), nullptr);
      for (Ordering o : kOrderings) {
        std::vector<double> tau_fg(static_cast<std::size_t>(nv)), qdd_fg(static_cast<std::size_t>(nv));
        g.extract(solve(g, o).data(), qdd_fg.data(), tau_fg.data(), nullptr);
        EXPECT_LE(max_diff(tau_fg, tau), 1e-12 * (1 + max_abs(tau)))
            << model.name << " " << factor_graph::ordering_name(o);
        EXPECT_LE(max_diff(qdd_fg, qdd), 1e-12 * (1 + max_abs(qdd))) << model.name;
      }
    }
  }
}

// Forward dynamics: every ordering gives ABA's qdd to 1e-12 (relative).
TEST(FactorGraph, ForwardDynamicsEqualsAbaUnderEveryOrdering) {
  std::mt19937_64 rng(22);
  for (const Model& model : test_models()) {
    const int nv = model.nv();
    Data data(model);
    DynamicsGraph g(model, {}, {});
    for (int trial = 0; trial < 3; ++trial) {
      const auto q = test::random_vector(rng, nv, -3, 3), qd = test::random_vector(rng, nv, -2, 2),
                 tau = test::random_vector(rng, nv, -10, 10);
      std::vector<double> qdd(static_cast<std::size_t>(nv));
      ASSERT_TRUE(aba(model, data, q.data(), qd.data(), tau.data(), qdd.data()).ok());
      g.assemble(q.data(), qd.data(), nullptr, tau.data());
      for (Ordering o : kOrderings) {
        std::vector<double> qdd_fg(static_cast<std::size_t>(nv));
        g.extract(solve(g, o).data(), qdd_fg.data(), nullptr, nullptr);
        EXPECT_LE(max_diff(qdd_fg, qdd), 1e-12 * (1 + max_abs(qdd)))
            << model.name << " " << factor_graph::ordering_name(o);
      }
    }
  }
}

// Hybrid dynamics: a random half of the DoFs prescribed; the solution satisfies
// tau = RNEA(q, qd, qdd) on every row and keeps the given entries.
TEST(FactorGraph, HybridDynamicsSatisfiesRnea) {
  std::mt19937_64 rng(23);
  for (const Model& model : test_models()) {
    const int nv = model.nv();
    Data data(model);
    std::vector<char> known(static_cast<std::size_t>(nv));
    for (auto& k : known) k = static_cast<char>(rng() % 2);
    DynamicsGraph g(model, {}, known);
    const auto q = test::random_vector(rng, nv, -3, 3), qd = test::random_vector(rng, nv, -2, 2),
               qdd_in = test::random_vector(rng, nv, -5, 5), tau_in = test::random_vector(rng, nv, -10, 10);
    g.assemble(q.data(), qd.data(), qdd_in.data(), tau_in.data());
    for (Ordering o : kOrderings) {
      std::vector<double> qdd(static_cast<std::size_t>(nv)), tau(static_cast<std::size_t>(nv)),
          tau_rnea(static_cast<std::size_t>(nv));
      g.extract(solve(g, o).data(), qdd.data(), tau.data(), nullptr);
      rnea(model, data, q.data(), qd.data(), qdd.data(), tau_rnea.data());
      EXPECT_LE(max_diff(tau, tau_rnea), 1e-11 * (1 + max_abs(tau_rnea))) << model.name;
      for (int i = 0; i < nv; ++i) {
        if (known[i]) EXPECT_NEAR(qdd[i], qdd_in[i], 1e-12 * (1 + std::abs(qdd_in[i])));
        else EXPECT_NEAR(tau[i], tau_in[i], 1e-12 * (1 + std::abs(tau_in[i])));
      }
    }
  }
}

// For a chain, block cyclic reduction's order and nested dissection give an
// elimination tree of logarithmic height; the tree (ABA) order's is linear.
TEST(FactorGraph, ChainNestedDissectionIsCyclicReduction) {
  const Model model = make_generated("chain:255");
  DynamicsGraph g(model, {}, {});
  SparseCholesky tree(g.At(), Ordering::Given, g.tree_order(), 0.0, true);
  SparseCholesky cr(g.At(), Ordering::Given, g.cyclic_reduction_order(), 0.0, true);
  SparseCholesky nd(g.At(), Ordering::METIS, {}, 0.0, true);
  EXPECT_GE(tree.stats().etree_height, 255 * 4);
  EXPECT_LE(cr.stats().etree_height, 14 * 8 + 14 * 8);  // O(log n) blocks of bounded size
  EXPECT_LE(nd.stats().etree_height, 14 * 8 + 14 * 8);
  // both eliminate the middle body last (the top separator / the last reduction level)
  EXPECT_EQ(cr.elimination_order().back() / 14, 127);
  EXPECT_EQ(nd.elimination_order().back() / 14, 127);
  // and both still solve the system
  const std::vector<double> q(255, 0.3), qd(255, -0.2), tau(255, 1.0);
  g.assemble(q.data(), qd.data(), nullptr, tau.data());
  Data data(model);
  std::vector<double> qdd(255), qdd_cr(255);
  ASSERT_TRUE(aba(model, data, q.data(), qd.data(), tau.data(), qdd.data()).ok());
  cr.factorize(g.At());
  std::vector<double> x;
  cr.solve(g.At(), g.b(), x, 2);
  g.extract(x.data(), qdd_cr.data(), nullptr, nullptr);
  EXPECT_LE(max_diff(qdd_cr, qdd), 1e-10 * (1 + max_abs(qdd)));
}

// ---- loops: against finite-difference kinematics and the joint-space equations ----

// World pose of body j at q: rotation R (body axes -> world) and origin r.
void world_pose(const Model& model, const std::vector<double>& q, Index j, Mat3<double>& R, Vec3<double>& r) {
  Transform<double> X0 = Transform<double>::identity();
  std::vector<Transform<double>> X(static_cast<std::size_t>(model.nv()));
  for (Index i = 0; i <= j; ++i) {
    const Transform<double> Xup = joint_transform(model.bodies[i], q[i]);
    X[i] = model.parent(i) < 0 ? Xup : Xup * X[model.parent(i)];
  }
  X0 = X[j];
  R = transpose(X0.E);
  r = X0.r;
}

// The loop's constraint function c(q) in world axes: for a point loop the point of
// side a minus the point of side b; a weld adds the relative rotation, read by
// finite differences as an angular velocity. Returns c's velocity J(q) qd and its
// acceleration-level drift Jdot qd by central differences along q + t qd.
Eigen::VectorXd loop_velocity(const Model& model, const LoopClosure& L, const std::vector<double>& q,
                              const std::vector<double>& qd, double t) {
  const double h = 1e-5;
  auto at = [&](double s, Index j, const Vec3<double>& p, Mat3<double>& R) {
    std::vector<double> qs(q);
    for (std::size_t k = 0; k < qs.size(); ++k) qs[k] += (t + s) * qd[k];
    Vec3<double> r;
    if (j < 0) { R = Mat3<double>::identity(); return p; }
    world_pose(model, qs, j, R, r);
    return r + R * p;
  };
  Eigen::VectorXd out(L.dim());
  const int lin = L.type == LoopClosure::Type::Weld ? 3 : 0;
  Mat3<double> Rap, Ram, Rbp, Rbm, Ra0, Rb0;
  const Vec3<double> dp = (1.0 / (2 * h)) * ((at(h, L.body_a, L.point_a, Rap) - at(-h, L.body_a, L.point_a, Ram)) -
                                              (at(h, L.body_b, L.point_b, Rbp) - at(-h, L.body_b, L.point_b, Rbm)));
  for (int k = 0; k < 3; ++k) out[lin + k] = dp[k];
  if (lin) {  // omega: skew part of dR/dt R^T
    at(0, L.body_a, L.point_a, Ra0);
    at(0, L.body_b, L.point_b, Rb0);
    auto omega = [&](const Mat3<double>& Rp, const Mat3<double>& Rm, const Mat3<double>& R0) -> Eigen::Vector3d {
      Eigen::Matrix3d P, M, Z;
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) { P(i, j) = Rp(i, j); M(i, j) = Rm(i, j); Z(i, j) = R0(i, j); }
      const Eigen::Matrix3d W = (P - M) / (2 * h) * Z.transpose();
      return Eigen::Vector3d(W(2, 1) - W(1, 2), W(0, 2) - W(2, 0), W(1, 0) - W(0, 1)) / 2;
    };
    const Eigen::Vector3d w = omega(Rap, Ram, Ra0) - omega(Rbp, Rbm, Rb0);
    for (int k = 0; k < 3; ++k) out[k] = w[k];
  }
  return out;
}

// A random tree with one point loop and one weld loop between bodies of different
// branches: at a state whose velocity satisfies the loops, the factor graph's
// forward dynamics satisfies J qdd + Jdot qd = 0 (finite differences of the world
// poses) and M qdd + h = tau + J^T lambda (CRBA, bias forces), under every ordering.
TEST(FactorGraph, LoopForwardDynamicsSatisfiesConstraintsAndEquationsOfMotion) {
  // two ropes of 8 links (axes x, y, x, ...: spatial motion), bodies 0-7 and 8-15
  const Model model = make_generated("curtain:2:8");
  const int nv = model.nv();
  std::mt19937_64 rng(24);
  LoopClosure point, weld;
  point.body_a = 7; point.point_a = {0.01, -0.005, -0.01};
  point.body_b = 15; point.point_b = {-0.01, 0.003, -0.008};
  weld.type = LoopClosure::Type::Weld;
  weld.body_a = 5; weld.point_a = {0.01, 0.0, -0.005};
  weld.body_b = 12; weld.point_b = {-0.01, 0.002, -0.01};
  const std::vector<LoopClosure> loops = {point, weld};
  const auto q = test::random_vector(rng, nv, -2, 2);
  auto qd = test::random_vector(rng, nv, -1, 1);
  const double tau_scale = 1e-3;  // 10 g links, 1 cm long
  const auto tau = test::random_vector(rng, nv, -tau_scale, tau_scale);
  // J by finite differences, column by column; qd projected onto its null space.
  const int m = 9;
  Eigen::MatrixXd J(m, nv);
  for (int k = 0; k < nv; ++k) {
    std::vector<double> e(static_cast<std::size_t>(nv), 0.0);
    e[k] = 1;
    J.col(k) << loop_velocity(model, point, q, e, 0), loop_velocity(model, weld, q, e, 0);
  }
  Eigen::VectorXd v = Eigen::Map<Eigen::VectorXd>(qd.data(), nv);
  v -= J.transpose() * (J * J.transpose()).ldlt().solve(J * v);
  for (int k = 0; k < nv; ++k) qd[k] = v[k];
  ASSERT_EQ(Eigen::FullPivLU<Eigen::MatrixXd>(J).rank(), m);  // the loops leave 7 DoFs free
  // Jdot qd: the constraint velocity's derivative along the motion
  const double ht = 1e-4;
  Eigen::VectorXd Jdqd(m);
  Jdqd << (loop_velocity(model, point, q, qd, ht) - loop_velocity(model, point, q, qd, -ht)) / (2 * ht),
      (loop_velocity(model, weld, q, qd, ht) - loop_velocity(model, weld, q, qd, -ht)) / (2 * ht);
  Data data(model);
  std::vector<double> Mrow(static_cast<std::size_t>(nv * nv)), h(static_cast<std::size_t>(nv));
  crba(model, data, q.data(), Mrow.data());
  bias_forces(model, data, q.data(), qd.data(), h.data());
  const Eigen::MatrixXd M = Eigen::Map<Eigen::Matrix<double, -1, -1, Eigen::RowMajor>>(Mrow.data(), nv, nv);
  DynamicsGraph g(model, loops, {});
  g.assemble(q.data(), qd.data(), nullptr, tau.data());
  for (Ordering o : kOrderings) {
    std::vector<double> qdd(static_cast<std::size_t>(nv)), lambda(9);
    g.extract(solve(g, o).data(), qdd.data(), nullptr, lambda.data());
    const Eigen::VectorXd a = Eigen::Map<Eigen::VectorXd>(qdd.data(), nv);
    const Eigen::VectorXd c = J * a + Jdqd;
    // scale of the terms: |J| |qdd| + |Jdot qd| (finite differences: ~1e-8 relative)
    const double c_scale = (J.cwiseAbs() * a.cwiseAbs()).maxCoeff() + Jdqd.cwiseAbs().maxCoeff();
    EXPECT_LE(c.cwiseAbs().maxCoeff(), 1e-6 * c_scale) << factor_graph::ordering_name(o);
    // lambda: [point force (3); weld moment (3); weld force (3)] -> J rows [point; weld ang; weld lin]
    const Eigen::VectorXd lam = Eigen::Map<Eigen::VectorXd>(lambda.data(), 9);
    const Eigen::VectorXd eom = M * a + Eigen::Map<Eigen::VectorXd>(h.data(), nv) -
                                Eigen::Map<const Eigen::VectorXd>(tau.data(), nv) - J.transpose() * lam;
    const double eom_scale = (M.cwiseAbs() * a.cwiseAbs()).maxCoeff() + (J.transpose().cwiseAbs() * lam.cwiseAbs()).maxCoeff() +
                             tau_scale + Eigen::Map<Eigen::VectorXd>(h.data(), nv).cwiseAbs().maxCoeff();
    EXPECT_LE(eom.cwiseAbs().maxCoeff(), 1e-6 * eom_scale) << factor_graph::ordering_name(o);
    EXPECT_GT((J * a).cwiseAbs().maxCoeff(), 1e-3 * Jdqd.cwiseAbs().maxCoeff());  // the drift is not trivially zero
  }
}

// The generators' loop systems (fivebar, fourbar: 1 kg-scale links; cloth:4:4,
// cloth:10:10: 10 g links of 1 cm, redundant point loops) at 3 random closed states
// each (tests/loop_cases.hpp), solved as bench_factor_graph solves them (CHOLMOD's
// nested dissection, beta = kLoopBeta, kLoopRefine refinement steps), against the
// dense reference constrained_forward_dynamics (Eigen, rank-revealing):
// max |qdd - qdd_ref| <= 1e-8 max |qdd_ref|, and the joint-space equations of motion
// M qdd + h - tau - J^T lambda (M from crba, h from bias_forces, J from
// loop_kinematics; lambda the factor graph's) to 1e-8 of their terms' scale
// (max_i sum_j |M_ij qdd_j| + |h_i| + |tau_i| + sum_r |J_ri lambda_r|), double.
TEST(FactorGraph, LoopForwardDynamicsEqualsTheDenseReference) {
  std::mt19937_64 rng(26);
  for (const test::LoopCase& c : test::loop_cases({"fivebar", "fourbar", "cloth:4:4", "cloth:10:10"})) {
    const Index nv = c.model.nv(), m = c.loops.rows();
    const double tau_scale = c.spec.rfind("cloth", 0) == 0 ? 1e-3 : 1.0;  // 10 g links, 1 cm long
    DynamicsGraph g(c.model, factor_graph::graph_loops(c.loops), {});
    SparseCholesky chol(g.At(), Ordering::NESDIS, {}, factor_graph::kLoopBeta);
    Data data(c.model);
    for (int trial = 0; trial < 3; ++trial) {
      SCOPED_TRACE(c.spec + " state " + std::to_string(trial));
      std::vector<double> q, qd;
      ASSERT_LE(test::closed_state(c, rng, q, qd), 1e-12);
      const auto tau = test::random_vector(rng, nv, -tau_scale, tau_scale);
      std::vector<double> qdd_ref(static_cast<std::size_t>(nv)), lambda_ref(static_cast<std::size_t>(m));
      constrained_forward_dynamics(c.model, c.loops, q.data(), qd.data(), tau.data(), qdd_ref.data(),
                                   lambda_ref.data());
      g.assemble(q.data(), qd.data(), nullptr, tau.data());
      chol.factorize(g.At());
      std::vector<double> x, qdd(static_cast<std::size_t>(nv)), lambda(static_cast<std::size_t>(m));
      chol.solve(g.At(), g.b(), x, factor_graph::kLoopRefine);
      g.extract(x.data(), qdd.data(), nullptr, lambda.data());
      EXPECT_LE(max_diff(qdd, qdd_ref), 1e-8 * max_abs(qdd_ref)) << "qdd against constrained_forward_dynamics";
      // M qdd + h - tau - J^T lambda
      std::vector<double> M(static_cast<std::size_t>(nv * nv)), h(static_cast<std::size_t>(nv)),
          J(static_cast<std::size_t>(m * nv));
      crba(c.model, data, q.data(), M.data());
      bias_forces(c.model, data, q.data(), qd.data(), h.data());
      loop_kinematics(c.model, c.loops, q.data(), qd.data(), nullptr, J.data(), nullptr);
      double worst = 0, scale = 0;
      for (Index i = 0; i < nv; ++i) {
        double e = h[i] - tau[i], terms = std::abs(h[i]) + std::abs(tau[i]);
        for (Index j = 0; j < nv; ++j) {
          e += M[i * nv + j] * qdd[j];
          terms += std::abs(M[i * nv + j] * qdd[j]);
        }
        for (Index r = 0; r < m; ++r) {
          e -= J[r * nv + i] * lambda[r];
          terms += std::abs(J[r * nv + i] * lambda[r]);
        }
        worst = std::max(worst, std::abs(e));
        scale = std::max(scale, terms);
      }
      EXPECT_LE(worst, 1e-8 * scale) << "M qdd + h - tau - J^T lambda";
    }
  }
}
#else
TEST(FactorGraph, SolversNeedCholmod) {
  GTEST_SKIP() << "built without SuiteSparse CHOLMOD (apt-get install libsuitesparse-dev libmetis-dev)";
}
#endif

}  // namespace
}  // namespace scandyn
