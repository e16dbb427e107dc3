// `scandyn eval --algo did,dfd` and `scandyn bench --algo did|dfd`: the columns
// (names, order, every value) against the library's serial derivatives, and the
// errors (a missing input column, a forward-dynamics method other than aba).
#include <gtest/gtest.h>

#include <sstream>
#include <string>
#include <vector>

#include "cli/cli_test_util.hpp"
#include "scandyn/algorithm/derivatives.hpp"
#include "scandyn/io/csv.hpp"
#include "test_util.hpp"

namespace scandyn::test::cli {
namespace {

using DerivativesCli = CliDirTest;

TEST_F(DerivativesCli, EvalWritesEveryBlockOfTheSerialDerivatives) {
  const Model model = load_robot("iiwa.urdf");
  const Index n = model.nv();
  std::ostringstream csv;
  csv.precision(17);
  for (const char* f : {"q_", "qd_", "qdd_", "tau_"})
    for (Index i = 0; i < n; ++i) csv << (csv.tellp() ? "," : "") << f << i;
  csv << "\n";
  const double row[4] = {0.3, -0.7, 1.1, 2.5};
  for (int f = 0; f < 4; ++f)
    for (Index i = 0; i < n; ++i) csv << (f + i ? "," : "") << row[f] * (i + 1) / n;
  csv << "\n";
  write_text(path("in.csv"), csv.str());
  const Result r = run("eval --model " + quote(model_path("iiwa.urdf")) +
                       " --states in.csv --out out.csv --algo dfd,did");
  ASSERT_EQ(r.code, 0) << r.err;
  io::CsvReader out(path("out.csv").string());
  const std::vector<std::string>& cols = out.columns();
  ASSERT_EQ(cols.size(), static_cast<std::size_t>(6 * n * n));
  EXPECT_EQ(cols[0], "dtau_dq_0_0");
  EXPECT_EQ(cols[n * n + 1], "dtau_dqd_0_1");
  EXPECT_EQ(cols[2 * n * n + n], "dtau_dqdd_1_0");
  EXPECT_EQ(cols[3 * n * n], "dqdd_dq_0_0");
  EXPECT_EQ(cols[6 * n * n - 1], "dqdd_dtau_6_6");
  std::vector<double> values;
  ASSERT_TRUE(out.next_row(values));
  // the library on the same inputs
  std::vector<double> in[4];
  for (int f = 0; f < 4; ++f)
    for (Index i = 0; i < n; ++i) in[f].push_back(row[f] * (i + 1) / n);
  const Force<double>* const kNoWrenches = nullptr;
  DerivativeDataTpl<double> dd(model);
  const std::size_t nn = static_cast<std::size_t>(n) * n;
  std::vector<double> ref(6 * nn), qdd(n);
  rnea_derivatives(model, dd, in[0].data(), in[1].data(), in[2].data(), kNoWrenches, {ref.data(), n, 1},
                   {ref.data() + nn, n, 1}, {ref.data() + 2 * nn, n, 1});
  ASSERT_TRUE(aba_derivatives(model, dd, in[0].data(), in[1].data(), in[3].data(), kNoWrenches, qdd.data(),
                              {ref.data() + 3 * nn, n, 1}, {ref.data() + 4 * nn, n, 1}, {ref.data() + 5 * nn, n, 1})
                  .ok());
  for (std::size_t k = 0; k < ref.size(); ++k) EXPECT_EQ(values[k], ref[k]) << cols[k];  // %.17g round-trips
}

TEST_F(DerivativesCli, Errors) {
  write_text(path("in.csv"), "q_0,q_1,qd_0,qd_1\n0,0,0,0\n");
  Result r = run("eval --model chain:2 --states in.csv --out out.csv --algo did");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("missing column qdd_0 (needed by --algo did)"), std::string::npos) << r.err;
  write_text(path("in.csv"), "q_0,q_1,qd_0,qd_1,tau_0,tau_1\n0,0,0,0,1,1\n");
  r = run("eval --model chain:2 --states in.csv --out out.csv --algo dfd --fd jsi");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("not available for the forward-dynamics derivatives"), std::string::npos) << r.err;
  EXPECT_EQ(files(), std::vector<std::string>{"in.csv"});
  r = run("bench --model chain:3 --algo dfd --instances 4 --min-time 0");
  EXPECT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.out.rfind("dfd,aba_derivatives,serial,double,chain:3,3,4,", 0), 0u) << r.out;
}

}  // namespace
}  // namespace scandyn::test::cli
