// `scandyn-truth` (src/truth/main.cpp) on models with multi-DoF joints: states with
// nq position columns (quaternions unit), the binary128 truth of them, the error of
// `scandyn eval`'s double and float results against it and the run-time check of the
// forward dynamics; bad quaternions and missing columns as data errors.
//
// Tolerances: double results within 1e-13 of the truth (measured ~3e-16 on floating
// hyq, ~1e-15 on ballrope:10), float within 1e-4 (the report's float budget; measured
// ~1e-6), the check flagging none of these clean results.
#include <cstdio>
#include <map>

#include "cli_test_util.hpp"

namespace scandyn::test::cli {
namespace {

class CliTruth : public CliDirTest {
 protected:
  void SetUp() override {
#ifndef SCANDYN_TRUTH_CLI_PATH
    GTEST_SKIP() << "scandyn-truth is not built (SCANDYN_TRUTH off: no __float128 / libquadmath)";
#else
    CliDirTest::SetUp();
#endif
  }
  // Runs `scandyn-truth args` in the test directory.
  Result truth(const std::string& args) const {
#ifdef SCANDYN_TRUTH_CLI_PATH
    return run_program(SCANDYN_TRUTH_CLI_PATH, args);
#else
    (void)args;
    return {};
#endif
  }
  // `scandyn-truth error`'s lines family -> max_rel_err.
  static std::map<std::string, double> errors(const std::string& out) {
    std::map<std::string, double> e;
    std::istringstream s(out);
    std::string line;
    std::getline(s, line);  // header
    while (std::getline(s, line)) {
      const auto a = line.find(','), b = line.rfind(',');
      e[line.substr(0, a)] = std::stod(line.substr(b + 1));
    }
    return e;
  }
  // `scandyn-truth check`'s flagged count.
  static int flagged(const std::string& out) {
    const std::string row = out.substr(out.find('\n') + 1);
    return std::stoi(row.substr(row.find(',') + 1));
  }

  // states -> truth -> scandyn eval in double and float -> error and check.
  void round_trip(const std::string& model) {
    ASSERT_EQ(truth("states --model " + model + " --rows 4 --out s.csv").code, 0);
    Result r = truth("eval --model " + model + " --states s.csv --out t.csv --algo id,fd,mass,bias");
    ASSERT_EQ(r.code, 0) << r.err;
    for (const char* precision : {"double", "float"}) {
      SCOPED_TRACE(precision);
      const double tol = std::string(precision) == "double" ? 1e-13 : 1e-4;
      r = run("eval --model " + model + " --states s.csv --out d.csv --algo id,fd,mass,bias --precision " +
              precision);
      ASSERT_EQ(r.code, 0) << r.err;
      r = truth("error --truth t.csv --result d.csv");
      ASSERT_EQ(r.code, 0) << r.err;
      const auto e = errors(r.out);
      ASSERT_EQ(e.size(), 4u) << r.out;
      for (const auto& [family, err] : e) EXPECT_LE(err, tol) << family;
      r = truth("check --model " + model + " --states s.csv --result d.csv --precision " + precision);
      ASSERT_EQ(r.code, 0) << r.err;
      EXPECT_EQ(flagged(r.out), 0) << r.out;
      // with the truth: no row over the budget, none flagged
      r = truth("check --model " + model + " --states s.csv --result d.csv --truth t.csv --precision " + precision);
      ASSERT_EQ(r.code, 0) << r.err;
      EXPECT_NE(r.out.find("bad,caught,false_positives,missed"), std::string::npos) << r.out;
      EXPECT_NE(r.out.find(",0,0,0,0,"), std::string::npos) << r.out;
    }
  }
};

TEST_F(CliTruth, StatesOfAFloatingBaseHaveNqPositionColumns) {
  ASSERT_EQ(truth("states --model hyq --floating-base --rows 3 --out s.csv").code, 0);
  std::istringstream s(read_text(path("s.csv")));
  std::string header, row;
  std::getline(s, header);
  EXPECT_EQ(header.rfind("q_0,", 0), 0u);
  EXPECT_NE(header.find(",q_18,qd_0,"), std::string::npos) << header;  // nq = 19
  EXPECT_NE(header.find(",qd_17,qdd_0,"), std::string::npos) << header;  // nv = 18
  EXPECT_EQ(header.find("q_19"), std::string::npos);
  // each row's base quaternion (q_3..q_6) is unit
  while (std::getline(s, row)) {
    std::vector<double> v;
    std::istringstream f(row);
    std::string x;
    while (std::getline(f, x, ',')) v.push_back(std::stod(x));
    ASSERT_EQ(v.size(), 19u + 3 * 18u);
    EXPECT_NEAR(v[3] * v[3] + v[4] * v[4] + v[5] * v[5] + v[6] * v[6], 1.0, 4e-16);
  }
}

TEST_F(CliTruth, FloatingHyqAgainstEval) { round_trip("hyq --floating-base"); }
TEST_F(CliTruth, BallRopeAgainstEval) { round_trip("ballrope:10"); }
TEST_F(CliTruth, FreeRopeAgainstEval) { round_trip("rope:12 --floating-base"); }

// A double result made wrong in one row (qdd_fd_0 + 1e-3) is bad against the truth
// and caught by the check; the other rows are clean and not flagged.
TEST_F(CliTruth, CheckWithTheTruthCountsCatches) {
  const std::string model = "hyq --floating-base";
  ASSERT_EQ(truth("states --model " + model + " --rows 3 --out s.csv").code, 0);
  ASSERT_EQ(truth("eval --model " + model + " --states s.csv --out t.csv --algo fd").code, 0);
  ASSERT_EQ(run("eval --model " + model + " --states s.csv --out d.csv --algo fd").code, 0);
  std::istringstream s(read_text(path("d.csv")));
  std::string text, line;
  for (int k = 0; std::getline(s, line); ++k) {
    if (k == 2) {  // row 1
      const auto c = line.find(',');
      char buf[40];
      std::snprintf(buf, sizeof buf, "%.17g", std::stod(line.substr(0, c)) + 1e-3);
      line = buf + line.substr(c);
    }
    text += line + "\n";
  }
  write_text(path("d.csv"), text);
  const Result r = truth("check --model " + model + " --states s.csv --result d.csv --truth t.csv");
  ASSERT_EQ(r.code, 0) << r.err;
  // rows,flagged,...,bad,caught,false_positives,missed,max_error
  EXPECT_EQ(flagged(r.out), 1) << r.out;
  EXPECT_NE(r.out.find(",1,1,0,0,"), std::string::npos) << r.out;
}

TEST_F(CliTruth, BadQuaternionIsADataErrorNamingRowAndColumns) {
  ASSERT_EQ(truth("states --model hyq --floating-base --rows 2 --out s.csv").code, 0);
  // row 1's q_6 (the base quaternion's w) scaled: norm off by far more than 1e-6
  std::istringstream s(read_text(path("s.csv")));
  std::string header, r0, r1;
  std::getline(s, header);
  std::getline(s, r0);
  std::getline(s, r1);
  std::vector<std::string> f;
  std::istringstream rs(r1);
  for (std::string x; std::getline(rs, x, ',');) f.push_back(x);
  f[6] = std::to_string(2 * std::stod(f[6]) + 0.5);
  std::string bad;
  for (const std::string& x : f) bad += (bad.empty() ? "" : ",") + x;
  write_text(path("bad.csv"), header + "\n" + r0 + "\n" + bad + "\n");
  const Result r = truth("eval --model hyq --floating-base --states bad.csv --out t.csv");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("row 1"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("q_3..q_6"), std::string::npos) << r.err;
  EXPECT_FALSE(fs::exists(path("t.csv")));
}

TEST_F(CliTruth, StatesOfTheFixedModelAreRefusedForTheFloatingOne) {
  // a fixed-base hyq states file has q_0..q_11 only: for the floating model (nq 19)
  // q_12..q_18 are missing
  ASSERT_EQ(truth("states --model hyq --rows 2 --out s.csv").code, 0);
  const Result r = truth("eval --model hyq --floating-base --states s.csv --out t.csv --algo id");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("q_"), std::string::npos) << r.err;
  EXPECT_FALSE(fs::exists(path("t.csv")));
}

}  // namespace
}  // namespace scandyn::test::cli
