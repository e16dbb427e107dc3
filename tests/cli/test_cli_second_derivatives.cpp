// `scandyn eval --algo d2id` and `scandyn bench --algo d2id`: the columns (names,
// order, every value) against the library's serial rnea_second_derivatives, and the
// errors (a missing input column, a model with a multi-DoF joint, a strategy).
#include <gtest/gtest.h>

#include <sstream>
#include <string>
#include <vector>

#include "cli/cli_test_util.hpp"
#include "scandyn/algorithm/second_derivatives.hpp"
#include "scandyn/io/csv.hpp"
#include "test_util.hpp"

namespace scandyn::test::cli {
namespace {

using SecondDerivativesCli = CliDirTest;

TEST_F(SecondDerivativesCli, EvalWritesTheThreeTensorsOfTheSerialFunction) {
  const Model model = load_robot("iiwa.urdf");
  const Index n = model.nv();
  std::ostringstream csv;
  csv.precision(17);
  for (const char* f : {"q_", "qd_", "qdd_"})
    for (Index i = 0; i < n; ++i) csv << (csv.tellp() ? "," : "") << f << i;
  csv << "\n";
  const double row[3] = {0.3, -0.7, 1.1};
  for (int f = 0; f < 3; ++f)
    for (Index i = 0; i < n; ++i) csv << (f + i ? "," : "") << row[f] * (i + 1) / n;
  csv << "\n";
  write_text(path("in.csv"), csv.str());
  const Result r =
      run("eval --model " + quote(model_path("iiwa.urdf")) + " --states in.csv --out out.csv --algo d2id");
  ASSERT_EQ(r.code, 0) << r.err;
  io::CsvReader out(path("out.csv").string());
  const std::vector<std::string>& cols = out.columns();
  const std::size_t n3 = static_cast<std::size_t>(n) * n * n;
  ASSERT_EQ(cols.size(), 3 * n3);
  EXPECT_EQ(cols[0], "d2tau_dq2_0_0_0");
  EXPECT_EQ(cols[1], "d2tau_dq2_0_0_1");       // k fastest
  EXPECT_EQ(cols[n], "d2tau_dq2_0_1_0");
  EXPECT_EQ(cols[n3 + n * n], "d2tau_dqd2_1_0_0");
  EXPECT_EQ(cols[3 * n3 - 1], "d2tau_dqdqd_6_6_6");
  std::vector<double> values;
  ASSERT_TRUE(out.next_row(values));
  // the library on the same inputs
  std::vector<double> in[3];
  for (int f = 0; f < 3; ++f)
    for (Index i = 0; i < n; ++i) in[f].push_back(row[f] * (i + 1) / n);
  SecondDerivativeData<double> sd(model);
  std::vector<double> ref(3 * n3);
  rnea_second_derivatives(model, sd, in[0].data(), in[1].data(), in[2].data(), static_cast<const Force<double>*>(nullptr),
                          ref.data(), ref.data() + n3, ref.data() + 2 * n3);
  for (std::size_t k = 0; k < ref.size(); ++k) EXPECT_EQ(values[k], ref[k]) << cols[k];  // %.17g round-trips
}

TEST_F(SecondDerivativesCli, BenchRowAndErrors) {
  write_text(path("in.csv"), "q_0,q_1,qd_0,qd_1\n0,0,0,0\n");
  Result r = run("eval --model chain:2 --states in.csv --out out.csv --algo d2id");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("missing column qdd_0 (needed by --algo d2id)"), std::string::npos) << r.err;
  r = run("bench --model chain:3 --algo d2id --instances 4 --min-time 0 --floating-base");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("multi-DoF joint"), std::string::npos) << r.err;
  EXPECT_EQ(files(), std::vector<std::string>{"in.csv"});
  r = run("bench --model chain:3 --algo d2id --instances 4 --min-time 0");
  EXPECT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.out.rfind("d2id,rnea_second_derivatives,serial,double,chain:3,3,4,", 0), 0u) << r.out;
  r = run("bench --model chain:3 --algo d2id --instances 5 --min-time 0 --backend openmp --precision float");
  EXPECT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.out.rfind("d2id,rnea_second_derivatives,openmp,float,chain:3,3,5,", 0), 0u) << r.out;
}

}  // namespace
}  // namespace scandyn::test::cli
