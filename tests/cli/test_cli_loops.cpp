// `scandyn eval` and `scandyn bench` on models with closed loops and `scandyn info --print-loops`
// (docs/loops.md): the columns, the result against the library's constrained
// dynamics to the printed digits, a generator's loops equal to its printed loop file,
// and the errors (exit code, one message, no output file).
#include <gtest/gtest.h>
#include <stdlib.h>
#include <sys/wait.h>

#include <cmath>
#include <filesystem>
#include <random>
#include <sstream>

#include "cli_test_util.hpp"
#include "scandyn/algorithm/loops.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

namespace {

using namespace scandyn;
using scandyn::test::cli::CliDirTest;
using scandyn::test::cli::read_text;
using scandyn::test::cli::write_text;

class CliLoops : public CliDirTest {};

std::vector<double> last_row(const std::string& text) {
  std::istringstream in(text);
  std::string line, last;
  while (std::getline(in, line)) last = line;
  std::vector<double> r;
  std::istringstream ls(last);
  for (std::string f; std::getline(ls, f, ',');) r.push_back(std::stod(f));
  return r;
}

TEST_F(CliLoops, FivebarForwardAndInverseDynamics) {
  const Model m = load_model("fivebar");
  const LoopSet loops = generator_loops("fivebar", m);
  std::vector<double> q{0.05, -0.1, 0.02, 0.0}, qd{0.3, -0.2, 0.1, 0.4};
  project_to_loops(m, loops, q.data(), qd.data());
  const std::vector<double> tau{0.5, 0, -0.5, 0};
  std::ostringstream csv;
  csv.precision(17);
  csv << "q_0,q_1,q_2,q_3,qd_0,qd_1,qd_2,qd_3,tau_0,tau_1,tau_2,tau_3\n";
  for (double x : q) csv << x << ",";
  for (double x : qd) csv << x << ",";
  csv << "0.5,0,-0.5,0\n";
  write_text(path("s.csv"), csv.str());
  auto r = run("eval --model fivebar --states s.csv --out o.csv");
  ASSERT_EQ(r.code, 0) << r.err;
  const std::string text = read_text(path("o.csv"));
  EXPECT_EQ(text.rfind("qdd_fd_0,qdd_fd_1,qdd_fd_2,qdd_fd_3,lambda_0,lambda_1,lambda_2\n", 0), 0u);
  std::vector<double> qdd(4), lam(3);
  constrained_forward_dynamics(m, loops, q.data(), qd.data(), tau.data(), qdd.data(), lam.data());
  const auto row = last_row(text);
  ASSERT_EQ(row.size(), 7u);
  for (int i = 0; i < 4; ++i) EXPECT_EQ(row[i], qdd[i]);
  for (int k = 0; k < 3; ++k) EXPECT_EQ(row[4 + k], lam[k]);
  // the same loops from the printed loop file, on the plain tree (the generator carries them)
  r = run("info --model fivebar --print-loops");
  ASSERT_EQ(r.code, 0) << r.err;
  write_text(path("l.json"), r.out);
  // inverse dynamics of that motion with the proximal joints actuated: the torques back
  std::ostringstream csv2;
  csv2.precision(17);
  csv2 << "q_0,q_1,q_2,q_3,qd_0,qd_1,qd_2,qd_3,qdd_0,qdd_1,qdd_2,qdd_3\n";
  for (double x : q) csv2 << x << ",";
  for (double x : qd) csv2 << x << ",";
  csv2 << qdd[0] << "," << qdd[1] << "," << qdd[2] << "," << qdd[3] << "\n";
  write_text(path("s2.csv"), csv2.str());
  r = run("eval --model fivebar --states s2.csv --out o2.csv --algo id --actuated joint_l0,joint_r0");
  ASSERT_EQ(r.code, 0) << r.err;
  const auto row2 = last_row(read_text(path("o2.csv")));
  for (int i = 0; i < 4; ++i) EXPECT_NEAR(row2[i], tau[i], 1e-9);
}

// --loop-solver iterative --backend cuda (double, float) against the serial iterative
// solver on cloth:4:4 at q = 0, qd = 0 (closed) with torques tau_i = sin(1 + i): qdd to
// 1e-7 of max |qdd| in double (both stop at the relative residual 1e-10), 1e-3 in float.
// Skipped, with the reason, without a device or in a build without CUDA.
TEST_F(CliLoops, CudaIterativeEqualsSerialIterative) {
  const int n = 16;
  std::ostringstream csv;
  for (const char* f : {"q_", "qd_", "tau_"})
    for (int i = 0; i < n; ++i) csv << (f[0] == 'q' && f[1] == '_' && i == 0 ? "" : ",") << f << i;
  csv << "\n";
  csv.precision(17);
  for (int j = 0; j < 3 * n; ++j) csv << (j ? "," : "") << (j < 2 * n ? 0.0 : std::sin(1.0 + (j - 2 * n)));
  csv << "\n";
  write_text(path("c.csv"), csv.str());
  auto r = run("eval --model cloth:4:4 --states c.csv --out ref.csv --loop-solver iterative");
  ASSERT_EQ(r.code, 0) << r.err;
  const auto ref = last_row(read_text(path("ref.csv")));
  double big = 0;
  for (int i = 0; i < n; ++i) big = std::max(big, std::fabs(ref[i]));
  for (const char* precision : {"double", "float"}) {
    SCOPED_TRACE(precision);
    r = run(std::string("eval --model cloth:4:4 --states c.csv --out gpu.csv --loop-solver iterative --backend cuda "
                        "--precision ") + precision);
    if (r.code != 0 && (r.err.find("no usable CUDA device") != std::string::npos ||
                        r.err.find("built without CUDA") != std::string::npos))
      GTEST_SKIP() << r.err;
    ASSERT_EQ(r.code, 0) << r.err;
    const auto row = last_row(read_text(path("gpu.csv")));
    ASSERT_EQ(row.size(), ref.size());
    const double bound = std::string(precision) == "double" ? 1e-7 : 1e-3;
    for (int i = 0; i < n; ++i) EXPECT_NEAR(row[i], ref[i], bound * big) << "qdd_fd_" << i;
  }
}

TEST_F(CliLoops, Errors) {
  write_text(path("s.csv"), "q_0,q_1,q_2,q_3,qd_0,qd_1,qd_2,qd_3,tau_0,tau_1,tau_2,tau_3\n0.2,0,0,0,0,0,0,0,0,0,0,0\n");
  write_text(path("bad.json"), R"({"loops": [{"type": "point", "link_a": "x", "point_a": [0,0,0], "link_b": "left_distal", "point_b": [0,0,0]}]})");
  struct Case {
    std::string args, message;
    int code;
  } cases[] = {
      {"--model fivebar", "row 1 (line 2): the state violates loop 0 (left_distal - right_distal) by", 1},
      {"--model chain:4 --loops bad.json", "bad.json: loops[0].link_a: unknown link 'x'", 1},
      {"--model fivebar --backend openmp", "a model with loops runs on the serial backend in double", 2},
      {"--model fivebar --backend cuda", "--backend cuda with loops: forward dynamics (--algo fd) by --loop-solver iterative only", 2},
      {"--model fivebar --backend cuda --loop-solver iterative --precision half", "--precision half: expected double or float", 2},
      {"--model fivebar --algo id", "--algo id with loops needs --actuated LIST", 2},
      {"--model fivebar --algo mass", "with loops, eval computes fd", 2},
      {"--model chain:4 --actuated 0", "--actuated applies only to models with loops", 2},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.args);
    const auto res = run("eval --states s.csv --out o.csv " + c.args);
    EXPECT_EQ(res.code, c.code);
    EXPECT_NE(res.err.find(c.message), std::string::npos) << res.err;
    EXPECT_FALSE(std::filesystem::exists(path("o.csv")));
  }
}

// `scandyn bench` on a model with loops: one row of the bench CSV (fd-loops, the
// engine's strategy, 10 fields) whose max_rel_err (the engine against the Eigen
// reference) is at rounding level; the flags that do not apply are usage errors.
TEST_F(CliLoops, Bench) {
  auto r = run("bench --model fivebar --algo fd --instances 300 --min-time 0.01");
  ASSERT_EQ(r.code, 0) << r.err;
  std::istringstream in(r.out);
  std::string line, last;
  while (std::getline(in, line))
    if (!line.empty()) last = line;
  EXPECT_EQ(last.rfind("fd-loops,dense,serial,double,fivebar,4,300,", 0), 0u) << last;
  const double err = std::stod(last.substr(last.rfind(',') + 1));
  EXPECT_LE(err, 1e-12);
  for (const char* bad : {"--algo id", "--algo fd --prescribed 0", "--algo fd --fd aba"}) {
    SCOPED_TRACE(bad);
    r = run(std::string("bench --model fivebar --instances 10 ") + bad);
    EXPECT_EQ(r.code, 2) << r.err;
  }
}

// eval's forward dynamics through --loop-solver iterative (matrix-free conjugate
// gradients, scandyn/sim/iterative_loops.hpp) against dense (the Eigen reference,
// the default below 200 DoF) on cloth:5:5 (75 DoF, 120 loop rows) from three random
// closed states: qdd within 1e-8 of max(1, max |qdd|) (the solve's relative residual
// is 1e-10; measured ~1e-12), both satisfying the loops' J qdd + gamma = 0 through
// lambda (lambda itself is not unique: the grid's rows are redundant); and the
// option's errors (exit 2, nothing written).
TEST_F(CliLoops, EvalIterativeSolverEqualsDense) {
  const std::string spec = "cloth:5:5";
  const Model m = load_model(spec);
  const LoopSet loops = generator_loops(spec, m);
  const Index n = m.nv();
  std::ostringstream csv;
  csv.precision(17);
  for (const char* f : {"q_", "qd_", "tau_"})
    for (Index i = 0; i < n; ++i) csv << (f == std::string("q_") && i == 0 ? "" : ",") << f << i;
  csv << "\n";
  std::mt19937_64 g(5);
  for (int row = 0; row < 3; ++row) {
    std::vector<double> q = test::random_vector(g, n, -0.3, 0.3), qd = test::random_vector(g, n, -1, 1);
    ASSERT_LE(project_to_loops(m, loops, q.data(), qd.data()), 1e-12);
    const std::vector<double> tau = test::random_vector(g, n, -1e-3, 1e-3);
    for (const std::vector<double>* v : std::initializer_list<const std::vector<double>*>{&q, &qd, &tau})
      for (Index i = 0; i < n; ++i) csv << (v == &q && i == 0 ? "" : ",") << (*v)[i];
    csv << "\n";
  }
  write_text(path("s.csv"), csv.str());
  auto dense = run("eval --model " + spec + " --states s.csv --out dense.csv --loop-solver dense");
  ASSERT_EQ(dense.code, 0) << dense.err;
  auto iterative = run("eval --model " + spec + " --states s.csv --out it.csv --loop-solver iterative");
  ASSERT_EQ(iterative.code, 0) << iterative.err;
  auto rows = [](const std::string& text) {
    std::vector<std::vector<double>> out;
    std::istringstream in(text);
    std::string line;
    std::getline(in, line);  // the header
    while (std::getline(in, line)) {
      std::vector<double> r;
      std::istringstream ls(line);
      for (std::string f; std::getline(ls, f, ',');) r.push_back(std::stod(f));
      out.push_back(r);
    }
    return out;
  };
  const auto a = rows(read_text(path("dense.csv"))), b = rows(read_text(path("it.csv")));
  ASSERT_EQ(a.size(), 3u);
  ASSERT_EQ(b.size(), 3u);
  for (std::size_t r = 0; r < 3; ++r) {
    double scale = 1, diff = 0;
    for (Index i = 0; i < n; ++i) scale = std::max(scale, std::abs(a[r][i]));
    for (Index i = 0; i < n; ++i) diff = std::max(diff, std::abs(a[r][i] - b[r][i]));
    EXPECT_LE(diff, 1e-8 * scale) << "row " << r;
  }
  struct Case {
    std::string args, message;
  } cases[] = {
      {"--loop-solver cholesky", "--loop-solver cholesky: expected dense, sparse, iterative or auto"},
      {"--algo id --actuated 0 --loop-solver iterative", "inverse dynamics with loops (--algo id) solves densely"},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.args);
    const auto res = run("eval --model " + spec + " --states s.csv --out o.csv " + c.args);
    EXPECT_EQ(res.code, 2);
    EXPECT_NE(res.err.find(c.message), std::string::npos) << res.err;
    EXPECT_FALSE(std::filesystem::exists(path("o.csv")));
  }
}

}  // namespace
