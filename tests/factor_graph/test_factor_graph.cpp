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

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/factor_graph/dynamics_graph.hpp"
#include "scandyn/factor_graph/sparse_cholesky.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

using factor_graph::DynamicsGraph;
using factor_graph::LoopClosure;

double max_abs(const std::vector<double>& x) {
  double m = 0;
  for (double v : x) m = std::max(m, std::abs(v));
  return m;
}

double max_diff(const std::vector<double>& x, const std::vector<double>& y) {
  double m = 0;
  for (std::size_t k = 0; k < x.size(); ++k) m = std::max(m, std::abs(x[k] - y[k]));
  return m;
}

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
#else
TEST(FactorGraph, SolversNeedCholmod) {
  GTEST_SKIP() << "built without SuiteSparse CHOLMOD (apt-get install libsuitesparse-dev libmetis-dev)";
}
#endif

}  // namespace
}  // namespace scandyn
