// `scandyn eval --algo hybrid` and `scandyn bench --algo hybrid` (docs/cli.md): the
// columns read and written, the prescribed list by indices and joint names, the
// result against the library's hybrid_dynamics to the 17 printed digits, and the
// errors (exit code, one message, no output file).
#include <gtest/gtest.h>
#include <stdlib.h>
#include <sys/wait.h>

#include <algorithm>
#include <filesystem>
#include <sstream>

#include "cli_test_util.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

namespace {

using namespace scandyn;
using scandyn::test::cli::CliDirTest;
using scandyn::test::cli::read_text;
using scandyn::test::cli::write_text;

class CliHybrid : public CliDirTest {};

// The header and rows of a CSV text.
std::vector<std::vector<double>> csv_rows(const std::string& text, std::string& header) {
  std::istringstream in(text);
  std::getline(in, header);
  std::vector<std::vector<double>> rows;
  for (std::string line; std::getline(in, line);) {
    std::vector<double> r;
    std::istringstream ls(line);
    for (std::string f; std::getline(ls, f, ',');) r.push_back(std::stod(f));
    rows.push_back(r);
  }
  return rows;
}

// iiwa states with q, qd, qdd of DoFs 1 and 4, tau of the others (columns shuffled).
TEST_F(CliHybrid, EvalMatchesLibraryByIndicesAndNames) {
  const Model m = load_model("iiwa");
  const Index n = m.nv();
  const std::vector<unsigned char> mask{0, 1, 0, 0, 1, 0, 0};
  std::mt19937_64 g(3);
  std::string text = "tau_0,qdd_4,";
  for (Index i = 0; i < n; ++i) text += "q_" + std::to_string(i) + ",qd_" + std::to_string(i) + ",";
  text += "qdd_1,tau_2,tau_3,tau_5,tau_6\n";
  std::vector<std::vector<double>> q, qd, qdd, tau;
  for (int r = 0; r < 5; ++r) {
    q.push_back(test::random_vector(g, n, -3, 3));
    qd.push_back(test::random_vector(g, n, -2, 2));
    qdd.push_back(test::random_vector(g, n, -2, 2));
    tau.push_back(test::random_vector(g, n, -5, 5));
    std::ostringstream row;
    row.precision(17);
    row << tau[r][0] << "," << qdd[r][4] << ",";
    for (Index i = 0; i < n; ++i) row << q[r][i] << "," << qd[r][i] << ",";
    row << qdd[r][1] << "," << tau[r][2] << "," << tau[r][3] << "," << tau[r][5] << "," << tau[r][6] << "\n";
    text += row.str();
  }
  write_text(path("s.csv"), text);
  for (const std::string list : {"1,4", "iiwa_joint_2,iiwa_joint_5", "4,iiwa_joint_2"}) {
    SCOPED_TRACE(list);
    const auto res = run("eval --model iiwa --states s.csv --out o.csv --algo hybrid --prescribed " + list);
    ASSERT_EQ(res.code, 0) << res.err;
    std::string header;
    const auto rows = csv_rows(read_text(path("o.csv")), header);
    EXPECT_EQ(header.rfind("qdd_hd_0,qdd_hd_1,", 0), 0u);
    EXPECT_NE(header.find(",tau_hd_0,"), std::string::npos);
    ASSERT_EQ(rows.size(), 5u);
    Data d(m, false);
    for (int r = 0; r < 5; ++r) {
      std::vector<double> eq(n), et(n);
      ASSERT_TRUE(hybrid_dynamics(m, d, q[r].data(), qd[r].data(), mask.data(), qdd[r].data(), tau[r].data(),
                                  eq.data(), et.data())
                      .ok());
      for (Index i = 0; i < n; ++i) {
        EXPECT_EQ(rows[r][i], eq[i]) << "row " << r << " qdd_hd_" << i;
        EXPECT_EQ(rows[r][n + i], et[i]) << "row " << r << " tau_hd_" << i;
      }
    }
  }
}

TEST_F(CliHybrid, Errors) {
  write_text(path("s.csv"), "q_0,q_1,qd_0,qd_1,qdd_0,tau_1\n0.1,0.2,0,0,1,2\n");
  struct Case {
    std::string args, message;
    int code;
  } cases[] = {
      {"--prescribed 2", "--prescribed: DoF 2 is out of range", 2},
      {"--prescribed 0,nope", "--prescribed: 'nope' is neither a DoF index nor a joint", 2},
      {"--prescribed 0,0", "--prescribed: DoF 0 is listed twice", 2},
      {"--prescribed 0,", "--prescribed: empty item", 2},
      {"", "--algo hybrid needs --prescribed", 2},
      {"--prescribed 1", "s.csv: missing column tau_0 (needed by --algo hybrid: DoF 0 is not prescribed)", 1},
      {"--prescribed 0 --fd aba", "--fd does not apply to --algo hybrid", 2},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.args);
    const auto res = run("eval --model chain:2 --states s.csv --out o.csv --algo hybrid " + c.args);
    EXPECT_EQ(res.code, c.code);
    EXPECT_NE(res.err.find(c.message), std::string::npos) << res.err;
    EXPECT_FALSE(std::filesystem::exists(path("o.csv")));
  }
  const auto res = run("eval --model chain:2 --states s.csv --out o.csv --algo id --prescribed 0");
  EXPECT_EQ(res.code, 2);
  EXPECT_NE(res.err.find("--prescribed applies only to --algo hybrid"), std::string::npos) << res.err;
}

TEST_F(CliHybrid, BenchPrintsOneRow) {
  const auto res = run("bench --model chain:5 --algo hybrid --prescribed 0,2 --instances 8 --min-time 0 --precision float");
  ASSERT_EQ(res.code, 0) << res.err;
  EXPECT_EQ(res.out.rfind("hybrid,recursion,serial,float,chain:5,5,8,", 0), 0u) << res.out;
  double err = 1;
  ASSERT_TRUE(std::sscanf(res.out.substr(res.out.rfind(',') + 1).c_str(), "%lf", &err) == 1);
  EXPECT_LT(err, 1e-4);
  EXPECT_GT(err, 0);  // float is measured against the double reference
}

}  // namespace
