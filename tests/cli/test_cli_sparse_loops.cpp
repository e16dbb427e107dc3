// `scandyn rollout` of a cloth grid with "loop_solver": "sparse" (the factor graph's
// CHOLMOD solver, which the command registers at startup when built with CHOLMOD:
// CMakeLists.txt, src/cli/main.cpp; docs/loops.md "The simulator's sparse loop
// path") against the same scene with "loop_solver": "dense" (the Eigen dense
// solve): the final state within 1e-12 (q) and 1e-11 (qd) relative to
// max(1, max |x|) (tests/factor_graph/test_sparse_loop_step.cpp measures the two
// equal to ~1e-13 per step), the loops closed, and `scandyn info`'s "loops" row. A
// build without CHOLMOD checks the "sparse" scene's error instead and skips the
// comparison, saying why.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <sstream>

#include "cli_test_util.hpp"
#include "scandyn/algorithm/loops.hpp"
#include "scandyn/io/csv.hpp"
#include "scandyn/model/load.hpp"

#ifndef SCANDYN_CLI_SPARSE_LOOPS  // tests/CMakeLists.txt: 1 when the command has the sparse solver
#define SCANDYN_CLI_SPARSE_LOOPS 0
#endif

namespace {

using namespace scandyn;
using scandyn::test::cli::CliDirTest;
using scandyn::test::cli::read_text;
using scandyn::test::cli::write_text;

class CliSparseLoops : public CliDirTest {};

constexpr const char* kModel = "cloth:6:6";
constexpr int kSteps = 40;

std::string json_array(const std::vector<double>& x) { return io::number_array(x.data(), x.size()); }

// The scene: the cloth under gravity from a closed state (projected here by the
// library's dense projection, so both solvers start from the same point), rk4.
std::string scene(const std::string& solver, const std::vector<double>& q0, const std::vector<double>& qd0) {
  return std::string(R"({"model": ")") + kModel + R"(", "backend": "serial", "effects": {"gravity": true},
    "integrator": "rk4", "dt": 2e-4, "loop_solver": ")" + solver + R"(",
    "initial": {"q": )" + json_array(q0) + R"(, "qd": )" + json_array(qd0) + "}}";
}

// The last CSV row's q and qd (one instance: the final step's state).
void last_state(const std::string& text, Index nv, std::vector<double>& q, std::vector<double>& qd) {
  std::istringstream in(text);
  std::string line, last;
  while (std::getline(in, line))
    if (!line.empty()) last = line;
  std::vector<double> row;
  std::istringstream ls(last);
  for (std::string f; std::getline(ls, f, ',');) row.push_back(std::stod(f));
  ASSERT_EQ(row.size(), static_cast<std::size_t>(3 + 2 * nv)) << last;
  EXPECT_EQ(row[0], kSteps);
  q.assign(row.begin() + 3, row.begin() + 3 + nv);
  qd.assign(row.begin() + 3 + nv, row.end());
}

double max_abs(const std::vector<double>& x) {
  double m = 0;
  for (double v : x) m = std::max(m, std::abs(v));
  return m;
}
double max_diff(const std::vector<double>& a, const std::vector<double>& b) {
  double m = 0;
  for (std::size_t i = 0; i < a.size(); ++i) m = std::max(m, std::abs(a[i] - b[i]));
  return m;
}

TEST_F(CliSparseLoops, InfoSaysWhetherTheSparseSolverIsThere) {
  const auto r = run("info --model fivebar");
  ASSERT_EQ(r.code, 0) << r.err;
  const std::string row = SCANDYN_CLI_SPARSE_LOOPS
                              ? "loops    dense, iterative, sparse (CHOLMOD)"
                              : "loops    dense, iterative (no sparse loop solver: built without SuiteSparse CHOLMOD)";
  EXPECT_NE(r.out.find("\n" + row + "\n"), std::string::npos) << r.out;
}

TEST_F(CliSparseLoops, ClothRolloutSparseEqualsDense) {
  const Model model = load_model(kModel);
  const LoopSet loops = generator_loops(kModel, model);
  const Index nv = model.nv();
  ASSERT_GT(loops.rows(), 0);
  std::vector<double> q0(nv), qd0(nv);
  for (Index i = 0; i < nv; ++i) q0[i] = 0.1 + 0.05 * std::sin(1.0 + i), qd0[i] = 0.5 * std::cos(2.0 + i);
  ASSERT_LE(project_to_loops(model, loops, q0.data(), qd0.data()), 1e-12);
  write_text(path("sparse.json"), scene("sparse", q0, qd0));
  write_text(path("dense.json"), scene("dense", q0, qd0));
  const std::string steps = " --steps " + std::to_string(kSteps) + " --every " + std::to_string(kSteps);
  const auto sparse = run("rollout --scene sparse.json --out sparse.csv" + steps);
  if (!SCANDYN_CLI_SPARSE_LOOPS) {
    // the simulator's error as a usage error (exit 2, docs/cli.md), nothing written
    EXPECT_EQ(sparse.code, 2);
    EXPECT_NE(sparse.err.find("no sparse loop solver"), std::string::npos) << sparse.err;
    EXPECT_FALSE(std::filesystem::exists(path("sparse.csv")));
    GTEST_SKIP() << "scandyn was built without SuiteSparse CHOLMOD: no sparse loop solver (the error checked)";
  }
  ASSERT_EQ(sparse.code, 0) << sparse.err;
  const auto dense = run("rollout --scene dense.json --out dense.csv" + steps);
  ASSERT_EQ(dense.code, 0) << dense.err;
  std::vector<double> q, qd, q_ref, qd_ref;
  last_state(read_text(path("sparse.csv")), nv, q, qd);
  last_state(read_text(path("dense.csv")), nv, q_ref, qd_ref);
  ASSERT_EQ(q.size(), static_cast<std::size_t>(nv));
  EXPECT_GT(max_diff(q_ref, q0), 1e-4) << "the cloth moved";
  EXPECT_LE(max_diff(q, q_ref), 1e-12 * std::max(1.0, max_abs(q_ref))) << "q";
  EXPECT_LE(max_diff(qd, qd_ref), 1e-11 * std::max(1.0, max_abs(qd_ref))) << "qd";
  EXPECT_LE(loop_violation(model, loops, q.data(), qd.data()), 1e-10) << "the sparse run's loops closed";
}

// eval's forward dynamics with --loop-solver sparse (CHOLMOD) against dense on
// cloth:6:6 from a closed state: qdd within 1e-9 of max(1, max |qdd|) (the solve of
// docs/factor-graph.md that equals the dense reference; the simulator's test measures
// ~1e-13); without CHOLMOD, the option's usage error (exit 2, nothing written).
TEST_F(CliSparseLoops, EvalSparseSolverEqualsDense) {
  const Model model = load_model(kModel);
  const LoopSet loops = generator_loops(kModel, model);
  const Index nv = model.nv();
  std::vector<double> q(nv), qd(nv), tau(nv);
  for (Index i = 0; i < nv; ++i)
    q[i] = 0.1 + 0.05 * std::sin(1.0 + i), qd[i] = 0.5 * std::cos(2.0 + i), tau[i] = 1e-3 * std::sin(3.0 * i);
  ASSERT_LE(project_to_loops(model, loops, q.data(), qd.data()), 1e-12);
  std::string header, row;
  for (const char* f : {"q_", "qd_", "tau_"})
    for (Index i = 0; i < nv; ++i) header += (header.empty() ? "" : ",") + std::string(f) + std::to_string(i);
  for (const std::vector<double>* v : std::initializer_list<const std::vector<double>*>{&q, &qd, &tau})
    for (Index i = 0; i < nv; ++i) {
      char buf[32];
      std::snprintf(buf, sizeof buf, "%.17g", (*v)[i]);
      row += (row.empty() ? "" : ",") + std::string(buf);
    }
  write_text(path("s.csv"), header + "\n" + row + "\n");
  const std::string base = std::string("eval --model ") + kModel + " --states s.csv ";
  const auto sparse = run(base + "--out sparse.csv --loop-solver sparse");
  if (!SCANDYN_CLI_SPARSE_LOOPS) {
    EXPECT_EQ(sparse.code, 2);
    EXPECT_NE(sparse.err.find("--loop-solver sparse: this scandyn was built without SuiteSparse CHOLMOD"),
              std::string::npos) << sparse.err;
    EXPECT_FALSE(std::filesystem::exists(path("sparse.csv")));
    GTEST_SKIP() << "scandyn was built without SuiteSparse CHOLMOD: no sparse loop solver (the error checked)";
  }
  ASSERT_EQ(sparse.code, 0) << sparse.err;
  const auto dense = run(base + "--out dense.csv --loop-solver dense");
  ASSERT_EQ(dense.code, 0) << dense.err;
  auto first_values = [nv](const std::string& text) {
    std::istringstream in(text);
    std::string line;
    std::getline(in, line);
    std::getline(in, line);
    std::vector<double> r;
    std::istringstream ls(line);
    for (std::string f; std::getline(ls, f, ',') && static_cast<Index>(r.size()) < nv;) r.push_back(std::stod(f));
    return r;
  };
  const std::vector<double> a = first_values(read_text(path("sparse.csv"))), b = first_values(read_text(path("dense.csv")));
  ASSERT_EQ(a.size(), static_cast<std::size_t>(nv));
  EXPECT_LE(max_diff(a, b), 1e-9 * std::max(1.0, max_abs(b)));
}

}  // namespace
