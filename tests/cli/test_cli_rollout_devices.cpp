// `scandyn rollout --devices` and `scandyn bench --algo step --devices` (docs/cli.md):
// every bad use is one error line, exit 2, no output left behind; --backend other
// than cuda drops a scene's devices. With a CUDA device: the rollout on devices 0,0
// (two shards on one GPU), torques from --tau included, writes the same file as on
// the current device.
#include <gtest/gtest.h>

#include <string>
#include <vector>

#include "cli_test_util.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/io/npy.hpp"

namespace {

using namespace scandyn::test::cli;
using namespace scandyn;

class RolloutDevices : public CliDirTest {};

std::string scene(const std::string& backend, const std::string& devices = "") {
  return R"({"model": "rope:4", "dt": 1e-4, "instances": 9, "backend": ")" + backend + "\", " +
         (devices.empty() ? "" : "\"devices\": " + devices + ", ") +
         R"("effects": {"gravity": true, "damping": 1e-6,
      "contacts": {"planes": [{"normal": [0, 0, 1], "offset": -0.025}], "all_links": {"radius": 0.002}, "stiffness": 10}},
    "initial": {"q": 0.2, "random": {"seed": 5, "q": 0.5, "qd": 1}}})";
}

TEST_F(RolloutDevices, BadUsesAreUsageErrors) {
  write_text(path("s.json"), scene("serial"));
  struct Case {
    std::string args, message;
  };
  std::vector<Case> cases = {
      {"--devices 0,1", "--devices applies only to --backend cuda (backend 'serial')"},
      {"--devices 0 --backend openmp", "--devices applies only to --backend cuda (backend 'openmp')"},
      {"--devices x", "--devices: devices 'x': 'x' is not a device ordinal"},
      {"--devices 0,,1", "--devices: devices '0,,1': '' is not a device ordinal"},
  };
  if (!backend_unusable(BackendKind::Cuda).empty())
    cases.push_back({"--devices all", "--devices: devices 'all': no usable CUDA device"});
  for (const Case& c : cases) {
    for (const char* cmd : {"rollout --steps 2 --out t.csv", "bench --algo step --min-time 0"}) {
      const Result r = run(std::string(cmd) + " --scene s.json " + c.args);
      EXPECT_EQ(r.code, 2) << cmd << " " << c.args << ": " << r.err;
      EXPECT_NE(r.err.find(c.message), std::string::npos) << cmd << " " << c.args << ": " << r.err;
      EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
    }
  }
  EXPECT_EQ(files(), std::vector<std::string>{"s.json"});  // no output left behind
}

TEST_F(RolloutDevices, ABackendOtherThanCudaDropsTheScenesDevices) {
  write_text(path("c.json"), scene("cuda", "[0, 1]"));
  write_text(path("s.json"), scene("serial"));
  ASSERT_EQ(run("rollout --scene c.json --backend serial --steps 3 --out c.csv").code, 0);
  ASSERT_EQ(run("rollout --scene s.json --steps 3 --out s.csv").code, 0);
  EXPECT_EQ(read_text(path("c.csv")), read_text(path("s.csv")));
}

TEST_F(RolloutDevices, TwoShardsOnOneDeviceWriteTheSameTrajectory) {
  if (const std::string why = backend_unusable(BackendKind::Cuda); !why.empty())
    GTEST_SKIP() << "backend cuda: " << why;
  write_text(path("s.json"), scene("cuda"));
  // (B, nv) torques, constant per instance
  std::vector<double> tau(9 * 4);
  for (std::size_t k = 0; k < tau.size(); ++k) tau[k] = 1e-5 * (double(k % 7) - 3);
  write_text(path("tau.npy"), io::npy_header("<f8", {9, 4}) +
                                  std::string(reinterpret_cast<const char*>(tau.data()), tau.size() * sizeof(double)));
  const std::string common = "rollout --scene s.json --steps 40 --every 10 --contacts --tau tau.npy";
  const Result one = run(common + " --out one.npy");
  ASSERT_EQ(one.code, 0) << one.err;
  const Result two = run(common + " --out two.npy --devices 0,0");
  ASSERT_EQ(two.code, 0) << two.err;
  EXPECT_EQ(read_text(path("one.npy")), read_text(path("two.npy")));
  const Result bench = run("bench --algo step --scene s.json --min-time 0 --devices 0,0");
  ASSERT_EQ(bench.code, 0) << bench.err;
  EXPECT_NE(bench.out.find("step,fused-aba-x2:"), std::string::npos) << bench.out;
}

}  // namespace
