// The forward-dynamics check on the command line (--fd-check, --fd-check-tol,
// --fallback double; docs/cli.md): the silent case, float jsi on chain:64,
// now an error naming the row and the estimate, or fixed by a fallback; the check off
// and a loose threshold give the unchecked numbers; bad flags are usage errors.
#include <cmath>
#include <random>

#include "cli/cli_test_util.hpp"

namespace scandyn::test::cli {
namespace {

using CliFdCheck = CliDirTest;

// n random states of an nv-DoF model in eval's columns q_, qd_, tau_ (uniform [-1, 1]).
std::string states_csv(int nv, int rows, unsigned seed) {
  std::mt19937_64 g(seed);
  std::uniform_real_distribution<double> U(-1, 1);
  std::string s;
  for (const char* f : {"q", "qd", "tau"})
    for (int i = 0; i < nv; ++i) s += (s.empty() ? "" : ",") + std::string(f) + "_" + std::to_string(i);
  s += "\n";
  char b[32];
  for (int r = 0; r < rows; ++r) {
    for (int k = 0; k < 3 * nv; ++k) {
      std::snprintf(b, sizeof b, "%s%.9g", k ? "," : "", U(g));
      s += b;
    }
    s += "\n";
  }
  return s;
}

TEST_F(CliFdCheck, FloatJsiOnChain64IsFlaggedOrFixed) {
  write_text(path("c64.csv"), states_csv(64, 8, 3));
  const std::string base = "eval --model chain:64 --states c64.csv --algo fd --fd jsi --precision float";
  // the check is eval's default: exit 1, nothing written, the row and the estimate named
  const Result r = run(base + " --out o.csv");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("c64.csv: row 1 (line 2): forward dynamics failed: forward dynamics check: estimated error "
                       "of qdd "),
            std::string::npos)
      << r.err;
  EXPECT_NE(r.err.find("above the threshold 0.0001"), std::string::npos) << r.err;
  EXPECT_FALSE(fs::exists(path("o.csv")));
  // --fd-check off and a threshold above the error: the unchecked result, the same numbers
  ASSERT_EQ(run(base + " --out off.csv --fd-check off").code, 0);
  const Result loose = run(base + " --out loose.csv --fd-check-tol 10");
  ASSERT_EQ(loose.code, 0) << loose.err;
  EXPECT_EQ(read_text(path("off.csv")), read_text(path("loose.csv")));
  // --fallback double: every row recomputed, one warning counting them
  const Result fb = run(base + " --out fb.csv --fallback double");
  ASSERT_EQ(fb.code, 0) << fb.err;
  EXPECT_EQ(fb.err,
            "scandyn: warning: the forward-dynamics check flagged 8 of 8 rows (estimated error of qdd above "
            "--fd-check-tol); they were computed again by the fallback (--fallback) and passed\n");
  // and its numbers are the double aba's to float rounding
  ASSERT_EQ(run("eval --model chain:64 --states c64.csv --algo fd --fd aba --out ref.csv").code, 0);
  const std::string a = read_text(path("fb.csv")), b = read_text(path("ref.csv"));
  std::istringstream fa(a), fbr(b);
  std::string la, lb;
  std::getline(fa, la), std::getline(fbr, lb);
  EXPECT_EQ(la, lb);  // header
  double worst = 0;
  while (std::getline(fa, la) && std::getline(fbr, lb)) {
    std::istringstream ca(la), cb(lb);
    std::string x, y;
    double scale = 1, err = 0;
    while (std::getline(ca, x, ',') && std::getline(cb, y, ',')) {
      err = std::max(err, std::abs(std::stod(x) - std::stod(y)));
      scale = std::max(scale, std::abs(std::stod(y)));
    }
    worst = std::max(worst, err / scale);
  }
  EXPECT_LT(worst, 1e-6);
}

TEST_F(CliFdCheck, BenchMarksTheCheckAndWarns) {
  const Result r = run("bench --model chain:64 --algo fd --fd jsi --precision float --instances 4 --min-time 0 "
                       "--fd-check on");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.out.find("fd,jsi+check,serial,float,chain:64,64,4,"), std::string::npos) << r.out;
  EXPECT_NE(r.err.find("scandyn: warning: bench: instance 0: forward dynamics check: "), std::string::npos) << r.err;
  const Result off = run("bench --model chain:64 --algo fd --fd jsi --precision float --instances 4 --min-time 0");
  EXPECT_NE(off.out.find("fd,jsi,serial,float,chain:64,64,4,"), std::string::npos) << off.out;  // auto: off here
  EXPECT_EQ(off.err, "");
}

TEST_F(CliFdCheck, BadFlagsAreUsageErrors) {
  write_text(path("s.csv"), states_csv(5, 1, 1));
  const std::string base = "eval --model rope:5 --states s.csv --out o.csv --algo fd";
  for (const char* bad : {" --fd-check maybe", " --fd-check-tol 0", " --fd-check-tol -1", " --fd-check-tol x",
                          " --fallback double", " --fallback double --precision float --fd-check off",
                          " --fallback aba,triple"}) {
    const Result r = run(base + bad);
    EXPECT_EQ(r.code, 2) << bad << ": " << r.err;
  }
  EXPECT_EQ(run(base + " --fallback double --precision float").code, 0);
}

}  // namespace
}  // namespace scandyn::test::cli
