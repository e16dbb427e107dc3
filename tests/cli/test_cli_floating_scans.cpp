// The command line's free rope on the link scans and the parallel chain forward
// dynamics: `scandyn bench --floating-base` rows whose max_rel_err (against the
// double serial reference on the same states) stays at rounding, and the refusals
// of the chain for a ball rope and of hybrid. The values themselves are checked by
// tests/scan/test_scan_floating.cpp and tests/algorithm/test_chain_fd_floating.cpp.
#include <gtest/gtest.h>

#include <sstream>
#include <string>
#include <vector>

#include "cli_test_util.hpp"
#include "scandyn/engine.hpp"

using namespace scandyn::test::cli;

namespace {

class CliFloatingScans : public CliDirTest {
 protected:
  // the last field (max_rel_err) of the bench row that starts with `prefix`; -1 if none
  static double row_error(const std::string& out, const std::string& prefix) {
    std::istringstream lines(out);
    for (std::string line; std::getline(lines, line);)
      if (line.rfind(prefix, 0) == 0) return std::stod(line.substr(line.rfind(',') + 1));
    return -1;
  }
};

}  // namespace

TEST_F(CliFloatingScans, BenchRowsOfAFreeRopeAreExact) {
  const std::string backend = scandyn::backend_unusable(scandyn::BackendKind::OpenMP).empty() ? "openmp" : "serial";
  const std::string common = " --model rope:3000 --floating-base --instances 2 --min-time 0 --threads 2 --backend " + backend;
  Result r = run("bench --algo fd --fd parallel" + common);
  ASSERT_EQ(r.code, 0) << r.err;
  double e = row_error(r.out, "fd,parallel," + backend + ",double,rope:3000-floating,3005,2,");
  EXPECT_GE(e, 0) << r.out;
  EXPECT_LT(e, 1e-9) << r.out;
  for (const char* s : {"scan-local", "scan-world"}) {
    r = run(std::string("bench --algo id --strategy ") + s + common);
    ASSERT_EQ(r.code, 0) << r.err;
    e = row_error(r.out, std::string("id,") + s + "," + backend + ",double,rope:3000-floating,3005,2,");
    EXPECT_GE(e, 0) << r.out;
    EXPECT_LT(e, 1e-10) << s << ": " << r.out;
  }
}

TEST_F(CliFloatingScans, ChainRefusalsNameWhatIsNotTaken) {
  Result r = run("bench --model ballrope:100 --floating-base --algo fd --fd parallel --instances 1 --min-time 0");
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.err.find("spherical joint"), std::string::npos) << r.err;
  r = run("bench --model rope:100 --floating-base --algo fd --fd hybrid --instances 1 --min-time 0");
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.err.find("hybrid"), std::string::npos) << r.err;
}
