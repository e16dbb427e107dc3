// scandyn rollout with quaternion positions (a floating base, ball joints): nq q
// columns in the CSV and the .npy record, equal to the Simulator's state; a scene's
// non-unit initial quaternion and an nv-long initial.q are data errors naming the
// entries, nothing written.
#include <string>
#include <vector>

#include "cli/cli_test_util.hpp"
#include "scandyn/sim/simulator.hpp"

using namespace scandyn::test::cli;

namespace {

std::vector<std::string> split(const std::string& s, char c) {
  std::vector<std::string> out(1);
  for (char x : s) {
    if (x == c) out.emplace_back();
    else out.back().push_back(x);
  }
  return out;
}
std::vector<std::string> lines(const std::string& s) {
  std::vector<std::string> out = split(s, '\n');
  if (!out.empty() && out.back().empty()) out.pop_back();
  return out;
}

class CliRolloutFloating : public CliDirTest {};

// chain:2 with a free base: nv = 7, nq = 8
const char* const kFreeChain = R"({"model": "chain:2", "base": "floating", "dt": 0.001, "instances": 2,
  "integrator": "rk4", "effects": {"gravity": true, "damping": 0.1},
  "initial": {"q": [0, 0, 1, 0, 0, 0, 1, 0.2], "random": {"seed": 4, "q": 0.3, "qd": 0.2}}})";

TEST_F(CliRolloutFloating, CsvAndNpyHaveNqPositionColumns) {
  write_text(path("s.json"), kFreeChain);
  const Result r = run("rollout --scene s.json --steps 5 --every 5 --out traj.csv");
  ASSERT_EQ(r.code, 0) << r.err;
  const std::vector<std::string> rows = lines(read_text(path("traj.csv")));
  ASSERT_EQ(rows.size(), 1u + 2 * 2);
  EXPECT_EQ(rows[0], "step,time,instance,q_0,q_1,q_2,q_3,q_4,q_5,q_6,q_7,qd_0,qd_1,qd_2,qd_3,qd_4,qd_5,qd_6");
  scandyn::sim::Simulator<double> sim(scandyn::sim::load_scene(path("s.json").string()));
  ASSERT_EQ(sim.nq(), 8);
  for (int s = 0; s < 5; ++s) sim.step();
  for (int b = 0; b < 2; ++b) {
    const std::vector<std::string> f = split(rows[3 + b], ',');
    ASSERT_EQ(f.size(), 3u + 8 + 7);
    for (int i = 0; i < 8; ++i) EXPECT_EQ(std::stod(f[3 + i]), sim.q().at(i, b)) << "q_" << i;
    for (int i = 0; i < 7; ++i) EXPECT_EQ(std::stod(f[11 + i]), sim.qd().at(i, b)) << "qd_" << i;
  }
  ASSERT_EQ(run("rollout --scene s.json --steps 5 --every 5 --out traj.npy").code, 0);
  const std::string npy = read_text(path("traj.npy"));
  const std::size_t hlen = static_cast<unsigned char>(npy[8]) | (static_cast<unsigned char>(npy[9]) << 8);
  const std::string header = npy.substr(10, hlen);
  EXPECT_EQ(header.substr(0, header.find(" }") + 2), "{'descr': '<f8', 'fortran_order': False, 'shape': (2, 2, 16), }");
  EXPECT_EQ(npy.size(), 10 + hlen + 2 * 2 * 16 * sizeof(double));
}

TEST_F(CliRolloutFloating, BadInitialPositionsAreDataErrorsNamingTheEntries) {
  write_text(path("q.json"), R"({"model": "rope:2", "base": "floating", "dt": 0.001,
    "initial": {"q": [0, 0, 1, 0, 0, 0.1, 1, 0.2]}})");
  Result r = run("rollout --scene q.json --steps 3 --out t.csv");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("q.json: initial.q[3..6]: the quaternion (x, y, z, w) of joint 'root_joint' has norm 1.00499"),
            std::string::npos)
      << r.err;
  write_text(path("n.json"), R"({"model": "rope:2", "base": "floating", "dt": 0.001,
    "initial": {"q": [0, 0, 1, 0, 0, 0, 1]}})");
  r = run("rollout --scene n.json --steps 3 --out t.csv");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("n.json: initial.q: expected 8 entries (nq"), std::string::npos) << r.err;
  EXPECT_FALSE(std::filesystem::exists(path("t.csv")));
}

}  // namespace
