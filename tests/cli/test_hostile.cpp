// Hostile and careless input: each test reproduces one hostile case (huge or deep
// models and scenes, non-regular and oversized files, non-finite rollouts, memory and
// thread-count refusals, signals mid-write, symlinked or '-' outputs) against the
// built `scandyn` (or the library) and checks the documented outcome: one clear error
// line, the exit code, nothing half-written, no debris.
#include <gtest/gtest.h>
#include <fcntl.h>
#include <signal.h>
#include <stdlib.h>
#include <sys/stat.h>
#include <sys/types.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/io/limits.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sim/scene.hpp"
#include "cli_test_util.hpp"
#include "test_util.hpp"

namespace {

namespace fs = std::filesystem;
using namespace scandyn::test::cli;
using namespace scandyn;

bool contains(const std::string& s, const std::string& needle) { return s.find(needle) != std::string::npos; }

// One-link URDF with the given <axis xyz> and <inertial> body.
std::string one_link_urdf(const std::string& axis, const std::string& inertial =
                                                       "<mass value=\"1\"/><inertia ixx=\"1\" iyy=\"1\" izz=\"1\" "
                                                       "ixy=\"0\" ixz=\"0\" iyz=\"0\"/>") {
  return "<robot name=\"r\"><link name=\"base\"/><link name=\"l1\"><inertial>" + inertial +
         "</inertial></link><joint name=\"j1\" type=\"revolute\"><parent link=\"base\"/><child link=\"l1\"/>"
         "<origin xyz=\"0 0 0.5\"/><axis xyz=\"" + axis +
         "\"/><limit lower=\"-1\" upper=\"1\" effort=\"1\" velocity=\"1\"/></joint></robot>";
}

class Hostile : public CliDirTest {
 protected:
  bool has_temporary() const {
    for (const std::string& n : files())
      if (contains(n, ".tmp.")) return true;
    return false;
  }

  // Starts scandyn with args (split on spaces) in the test directory; stdout and
  // stderr to .stdout / .stderr.
  pid_t spawn(const std::vector<std::string>& args) const {
    const pid_t pid = ::fork();
    if (pid == 0) {
      if (::chdir(dir_.c_str()) != 0) ::_exit(127);
      const int out = ::open(".stdout", O_WRONLY | O_CREAT | O_TRUNC, 0644);
      const int err = ::open(".stderr", O_WRONLY | O_CREAT | O_TRUNC, 0644);
      ::dup2(out, 1);
      ::dup2(err, 2);
      std::vector<char*> argv;
      const std::string exe = test::cli_path();
      argv.push_back(const_cast<char*>(exe.c_str()));
      for (const std::string& a : args) argv.push_back(const_cast<char*>(a.c_str()));
      argv.push_back(nullptr);
      ::execv(exe.c_str(), argv.data());
      ::_exit(127);
    }
    return pid;
  }
  // Waits (up to 60 s) until a temporary file exists in the directory.
  bool wait_for_temporary() const {
    for (int k = 0; k < 6000; ++k) {
      if (has_temporary()) return true;
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    return false;
  }
  static int wait_exit(pid_t pid) {
    int status = 0;
    ::waitpid(pid, &status, 0);
    return WIFEXITED(status) ? WEXITSTATUS(status) : 1000 + (WIFSIGNALED(status) ? WTERMSIG(status) : 0);
  }
};

// ---- wrong physics: a huge axis -------------------------------------------------

TEST(HostileModel, HugeAxisIsNormalisedWithoutOverflow) {
  // |axis|^2 overflows for 1e155 (and 1e308 1e308 0); the scaled norm does not
  const Model a = build_model(parse_urdf(one_link_urdf("1e155 0 0"), "a.urdf"));
  EXPECT_DOUBLE_EQ(a.bodies[0].axis.x, 1.0);
  EXPECT_EQ(a.bodies[0].axis.y, 0.0);
  const Model b = build_model(parse_urdf(one_link_urdf("1e308 1e308 0"), "b.urdf"));
  EXPECT_NEAR(b.bodies[0].axis.x, std::sqrt(0.5), 1e-15);
  EXPECT_NEAR(b.bodies[0].axis.y, std::sqrt(0.5), 1e-15);
  // the same dynamics as the unit axis
  const Model ref = build_model(parse_urdf(one_link_urdf("1 0 0"), "ref.urdf"));
  Data da(a), dr(ref);
  double Ma = 0, Mr = 0;
  const double q = 0.3;
  crba(a, da, &q, &Ma);
  crba(ref, dr, &q, &Mr);
  EXPECT_GT(Ma, 0);
  EXPECT_DOUBLE_EQ(Ma, Mr);
}

TEST_F(Hostile, HugeAxisGivesTheUnitAxisDynamicsOnTheCommandLine) {
  for (const char* axis : {"1e155 0 0", "1e308 1e308 0"}) {
    write_text(path("r.urdf"), one_link_urdf(axis));
    write_text(path("s.csv"), "q_0,qd_0,qdd_0\n0.3,0.5,0.7\n");
    const Result r = run("eval --model r.urdf --states s.csv --out o.csv --algo id,mass,bias");
    ASSERT_EQ(r.code, 0) << r.err;
    const std::string out = read_text(path("o.csv"));
    const std::string row = out.substr(out.find('\n') + 1);
    const double tau = std::stod(row), M = std::stod(row.substr(row.find(',') + 1));
    EXPECT_GT(M, 0.1) << axis << ": " << out;
    EXPECT_NE(tau, 0) << axis << ": " << out;
  }
}

TEST(HostileModel, OverflowInADerivedQuantityIsAnError) {
  // each number finite, m c^2 (the inertia about the link origin) is not
  const std::string huge = "<origin xyz=\"1e200 0 0\"/><mass value=\"1e200\"/><inertia ixx=\"1\" iyy=\"1\" "
                           "izz=\"1\" ixy=\"0\" ixz=\"0\" iyz=\"0\"/>";
  try {
    build_model(parse_urdf(one_link_urdf("0 0 1", huge), "h.urdf"));
    FAIL() << "no ModelError";
  } catch (const ModelError& e) {
    EXPECT_TRUE(contains(e.what(), "h.urdf: joint 'j1': the spatial inertia")) << e.what();
    EXPECT_TRUE(contains(e.what(), "overflows")) << e.what();
  }
}

// ---- nesting depth and file kinds -------------------------------------------------

TEST(HostileModel, DeepXmlIsRefusedBeforeParsing) {
  std::string xml = "<robot name=\"r\">";
  for (int k = 0; k < 50000; ++k) xml += "<a>";
  for (int k = 0; k < 50000; ++k) xml += "</a>";
  xml += "</robot>";
  const auto t0 = std::chrono::steady_clock::now();
  try {
    parse_urdf(xml, "deep.urdf");
    FAIL() << "no ModelError";
  } catch (const ModelError& e) {
    EXPECT_STREQ(e.what(), "deep.urdf: XML elements nested deeper than 64 levels (a URDF needs 4)");
  }
  EXPECT_LT(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count(), 2.0);
}

TEST(HostileModel, XmlDepthSkipsCommentsCdataAndDeclarations) {
  EXPECT_EQ(xml_depth("<a><b/><c x='>'><d></d></c></a>", 64), 3);
  EXPECT_EQ(xml_depth("<?xml version=\"1.0\"?><!DOCTYPE r [<!ENTITY e \"<x><y>\">]><r><!-- <a><b><c> --><![CDATA[<p><q>]]></r>", 64), 1);
  EXPECT_EQ(xml_depth("<a><a><a><a>", 2), 3);  // stops past the limit
}

TEST_F(Hostile, DeepUrdfFileIsOneClearError) {
  std::string xml = "<robot name=\"r\">";
  for (int k = 0; k < 50000; ++k) xml += "<link>";
  write_text(path("deep.urdf"), xml);
  const Result r = run("info --model deep.urdf");
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.err, "scandyn: deep.urdf: XML elements nested deeper than 64 levels (a URDF needs 4)\n");
}

TEST_F(Hostile, DeeplyNestedSceneValuesAreOneClearError) {
  const std::string deep = std::string(100000, '[') + std::string(100000, ']');
  for (const std::string& text : {"{\"model\": " + deep + ", \"dt\": 0.1}", "{\"model\": \"chain:1\", \"dt\": " + deep + "}",
                                  deep}) {
    write_text(path("s.json"), text);
    const Result r = run("rollout --scene s.json --steps 1 --out t.csv");
    EXPECT_EQ(r.code, 1) << r.err;
    EXPECT_TRUE(contains(r.err, "scandyn: s.json: ")) << r.err;
    EXPECT_TRUE(contains(r.err, "nested deeper than 64 levels of arrays and objects")) << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
    EXPECT_TRUE(files() == std::vector<std::string>{"s.json"});
  }
}

TEST_F(Hostile, OnlyRegularFilesAreRead) {
  ASSERT_EQ(::mkfifo(path("fifo").c_str(), 0644), 0);
  Result r = run("info --model ./fifo", "timeout 20");
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.err, "scandyn: ./fifo: not a regular file (a FIFO); a URDF file must be a regular file\n");
  r = run("info --model /dev/zero", "timeout 20");
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.err, "scandyn: /dev/zero: not a regular file (a character device); a URDF file must be a regular file\n");
  fs::create_directory(path("dir"));
  r = run("rollout --scene dir --steps 1 --out t.csv");
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.err, "scandyn: dir: not a regular file (a directory); a scene file must be a regular file\n");
  r = run("eval --model chain:1 --states fifo --out o.csv", "timeout 20");
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.err, "scandyn: fifo: not a regular file (a FIFO); a CSV file must be a regular file\n");
}

TEST(HostileFiles, SizeLimitIsStatedBeforeReading) {
  const fs::path p = fs::temp_directory_path() / ("scandyn_big_" + std::to_string(::getpid()) + ".json");
  write_text(p, std::string(100, ' '));
  try {
    read_regular_file(p.string(), 50, "scene file");
    ADD_FAILURE() << "no InputError";
  } catch (const InputError& e) {
    EXPECT_EQ(std::string(e.what()), p.string() + ": the file has 100 bytes; a scene file may have at most 50 (50 B)");
  }
  EXPECT_EQ(read_regular_file(p.string(), 100, "scene file").size(), 100u);
  fs::remove(p);
}

// ---- numbers nobody can use ----------------------------------------------------

TEST_F(Hostile, NonFiniteRolloutStopsWithTheStepAndInstance) {
  write_text(path("s.json"),
             R"({"model":"chain:1","effects":{"damping":1e300},"dt":0.001,"initial":{"qd":1e300}})");
  for (const char* out : {"t.csv", "t.npy"}) {
    const Result r = run(std::string("rollout --scene s.json --steps 10 --out ") + out);
    EXPECT_EQ(r.code, 1);
    EXPECT_EQ(r.err,
              "scandyn: s.json: step 1: the state is not finite in 1 of 1 instances, first instance 0 (q_0 = -inf) "
              "(the simulation overflowed: smaller dt, coefficients or initial state)\n");
    EXPECT_TRUE(files() == std::vector<std::string>{"s.json"});
  }
  const Result b = run("bench --algo step --scene s.json --min-time 0");
  EXPECT_EQ(b.code, 1);
  EXPECT_EQ(b.out, "");
  // (the simulator's own status: a step left the state non-finite)
  EXPECT_TRUE(contains(b.err, "scandyn: s.json: the state became non-finite in ")) << b.err;
  EXPECT_TRUE(contains(b.err, "first in instance 0: the state at DoF 0 is not finite after the step")) << b.err;
}

TEST_F(Hostile, UnclearMessagesNameTheFileKeyAndLine) {
  write_text(path("s.json"), "{\"model\": \"chain:1\",\n \"dt\": 1e999}");
  Result r = run("rollout --scene s.json --steps 1 --out t.csv");
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.err, "scandyn: s.json: dt: line 2, column 8: number 1e999 is out of range (a double holds at most +-1.8e308)\n");
  write_text(path("n.json"), R"({"model": "chain:1\u0000.urdf", "dt": 0.1})");
  r = run("rollout --scene n.json --steps 1 --out t.csv");
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.err, "scandyn: n.json: model: 'chain:1\\x00.urdf' contains a NUL character\n");
  write_text(path("cr.csv"), "q_0,qd_0\r0.1,0.2\r0.3,0.4\r");
  r = run("eval --model chain:1 --states cr.csv --out o.csv");
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.err, "scandyn: cr.csv: line 1: a carriage return (CR) not followed by LF; lines must end in LF or CRLF "
                   "(CR-only line ends are not read)\n");
  write_text(path("q.csv"), "q_0,q_1\n0.1,0.2\n");
  r = run("eval --model chain:2 --states q.csv --out o.csv");
  EXPECT_EQ(r.code, 1);
  EXPECT_TRUE(contains(r.err, "scandyn: q.csv: no algorithm has all its input columns: id lacks column qd_0, fd lacks "
                              "column qd_0, bias lacks column qd_0")) << r.err;
  EXPECT_TRUE(files() == (std::vector<std::string>{"cr.csv", "n.json", "q.csv", "s.json"}));
}

// ---- resources -------------------------------------------------------------------

TEST_F(Hostile, MemoryRefusalsNameWhatIsAskedNeededAndFree) {
  const std::uint64_t avail = host_memory_available();
  ASSERT_GT(avail, 0u);
  auto expect_refusal = [&](const Result& r, const std::string& start) {
    EXPECT_EQ(r.code, 1) << r.err;
    // (the last line: a rollout may first announce its large output)
    EXPECT_TRUE(r.err.rfind("scandyn: " + start, 0) == 0 || contains(r.err, "\nscandyn: " + start)) << r.err;
    EXPECT_TRUE(contains(r.err, " of host memory; ")) << r.err;
    EXPECT_TRUE(contains(r.err, " available\n")) << r.err;
  };
  expect_refusal(run("bench --model chain:7 --algo id --instances 1000000000"),
                 "bench --algo id on chain:7 (7 DoF), 1000000000 instances in double needs about 417 GiB");
  // (sizes beyond any host's memory: the GPU machine has 128 GiB)
  expect_refusal(run("bench --model rope:300000 --algo fd --fd jsi --instances 1"),
                 "bench --algo fd --fd jsi on rope:300000 (300000 DoF), 1 instances in double needs about");
  std::string header, row;
  for (int i = 0; i < 100000; ++i) header += (i ? ",q_" : "q_") + std::to_string(i), row += i ? ",0" : "0";
  write_text(path("q.csv"), header + "\n" + row + "\n");
  expect_refusal(run("eval --model rope:100000 --states q.csv --out o.csv --algo mass"),
                 "eval --algo mass on rope:100000 (100000 DoF, 1e+10 output columns per row) needs about");
  write_text(path("s.json"), R"({"model":"chain:64","dt":0.001,"instances":1000000000,"backend":"serial"})");
  expect_refusal(run("rollout --scene s.json --steps 1 --out -"),  // (stdout: no disk check first)
                 "a simulator of 1000000000 instances of chain:64 (64 DoF, double) needs about");
  expect_refusal(run("bench --algo step --scene s.json"),
                 "a simulator of 1000000000 instances of chain:64 (64 DoF, double) needs about");
  // the trajectory is checked against the free disk before anything is made
  write_text(path("s.json"), R"({"model":"chain:1","dt":0.001,"instances":1000000,"backend":"serial"})");
  const Result r = run("rollout --scene s.json --steps 1000000000 --out t.npy");
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.err.rfind("scandyn: the trajectory of 1000000001 records x 1000000 instances x 3 values needs about ", 0), 0u)
      << r.err;
  EXPECT_TRUE(contains(r.err, " of disk space for t.npy; ")) << r.err;
  EXPECT_TRUE(files() == (std::vector<std::string>{"q.csv", "s.json"}));
}

TEST_F(Hostile, HugeOmpNumThreadsIsRefused) {
  const Result r = run("bench --model chain:3 --algo id --instances 10 --backend openmp --min-time 0",
                       "OMP_NUM_THREADS=100000");
  EXPECT_EQ(r.code, 2);
  EXPECT_EQ(r.err, "scandyn: OMP_NUM_THREADS=100000: at most 4096 threads (the limit of --threads); unset it or lower it\n");
  EXPECT_EQ(run("bench --model chain:3 --algo id --instances 10 --min-time 0", "OMP_NUM_THREADS=4,2").code, 0);
}

// ---- signals ------------------------------------------------------------------

// An interrupted rollout publishes the records written so far as a valid .npy
// (shape fixed up) and exits 128 + signal; no temporary file is left.
TEST_F(Hostile, SignalDuringRolloutLeavesAValidPrefix) {
  write_text(path("s.json"), R"({"model":"chain:20","dt":0.001,"instances":50})");
  for (const int sig : {SIGINT, SIGTERM, SIGHUP}) {
    fs::remove(path("t.npy"));
    const pid_t pid = spawn({"rollout", "--scene", "s.json", "--steps", "100000000", "--every", "100", "--out", "t.npy"});
    ASSERT_TRUE(wait_for_temporary());
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    ::kill(pid, sig);
    EXPECT_EQ(wait_exit(pid), 128 + sig);
    EXPECT_FALSE(has_temporary());
    const std::string npy = read_text(path("t.npy"));
    ASSERT_GT(npy.size(), 10u);
    const std::size_t hlen = static_cast<unsigned char>(npy[8]) | (static_cast<unsigned char>(npy[9]) << 8);
    EXPECT_EQ((10 + hlen) % 64, 0u);
    const std::string header = npy.substr(10, hlen);
    const std::size_t k = header.find("'shape': (");
    ASSERT_NE(k, std::string::npos) << header;
    const long long records = std::stoll(header.substr(k + 10));
    EXPECT_GE(records, 1);
    EXPECT_TRUE(contains(header, "(" + std::to_string(records) + ", 50, 41), }")) << header;
    EXPECT_EQ(npy.size(), 10 + hlen + static_cast<std::size_t>(records) * 50 * 41 * 8);
    const std::string err = read_text(path(".stderr"));
    EXPECT_TRUE(contains(err, "interrupted by signal " + std::to_string(sig))) << err;
    EXPECT_TRUE(contains(err, "t.npy holds the " + std::to_string(records) + " records written so far")) << err;
  }
}

// An interrupted eval leaves nothing: the temporary file is removed, an existing
// output is untouched.
TEST_F(Hostile, SignalDuringEvalRemovesTheTemporaryFile) {
  std::string csv;
  for (int i = 0; i < 2000; ++i) csv += std::string(i ? "," : "") + "q_" + std::to_string(i) + ",qd_" + std::to_string(i) + ",tau_" + std::to_string(i);
  csv += "\n";
  std::string row;
  for (int i = 0; i < 6000; ++i) row += i ? ",0.1" : "0.1";
  for (int r = 0; r < 400; ++r) csv += row + "\n";
  write_text(path("s.csv"), csv);
  for (const int sig : {SIGINT, SIGTERM, SIGHUP}) {
    write_text(path("o.csv"), "old\n");
    const pid_t pid = spawn({"eval", "--model", "rope:2000", "--states", "s.csv", "--out", "o.csv", "--algo", "fd", "--fd", "jsi"});
    ASSERT_TRUE(wait_for_temporary());
    ::kill(pid, sig);
    EXPECT_EQ(wait_exit(pid), 128 + sig);
    EXPECT_FALSE(has_temporary());
    EXPECT_EQ(read_text(path("o.csv")), "old\n");
  }
}

// ---- output destinations ------------------------------------------------------------

TEST_F(Hostile, OutputThroughASymlinkWritesTheTargetAndKeepsTheMode) {
  write_text(path("s.csv"), "q_0,qd_0,qdd_0\n0.1,0.2,0.3\n");
  fs::create_directory(path("real"));
  write_text(path("real/o.csv"), "old\n");
  ASSERT_EQ(::chmod(path("real/o.csv").c_str(), 0600), 0);
  fs::create_symlink("real/o.csv", path("link.csv"));
  Result r = run("eval --model chain:1 --states s.csv --out link.csv");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(fs::is_symlink(path("link.csv")));
  EXPECT_EQ(read_text(path("real/o.csv")).rfind("tau_id_0,h_0\n", 0), 0u) << read_text(path("real/o.csv"));
  struct stat st {};
  ASSERT_EQ(::stat(path("real/o.csv").c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 0777, 0600u);
  // a dangling link is refused, nothing created
  fs::create_symlink("nowhere/x.csv", path("dangling.csv"));
  r = run("eval --model chain:1 --states s.csv --out dangling.csv");
  EXPECT_EQ(r.code, 1);
  EXPECT_TRUE(contains(r.err, "scandyn: dangling.csv: a symbolic link whose target cannot be resolved")) << r.err;
  EXPECT_FALSE(fs::exists(path("nowhere")));
}

TEST_F(Hostile, OutDashWritesToStdout) {
  write_text(path("s.csv"), "q_0,qd_0,qdd_0\n0.1,0.2,0.3\n");
  Result r = run("eval --model chain:1 --states s.csv --out -");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.out.rfind("tau_id_0,h_0\n", 0), 0u) << r.out;
  write_text(path("c.json"), R"({"model":"chain:2","dt":0.01})");
  r = run("rollout --scene c.json --steps 2 --out -");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.out.rfind("step,time,instance,q_0,q_1,qd_0,qd_1\n", 0), 0u) << r.out;
  EXPECT_EQ(std::count(r.out.begin(), r.out.end(), '\n'), 4);
  EXPECT_FALSE(fs::exists(path("-")));
  r = run("eval --model chain:1 --states s.csv --out /dev/null");
  EXPECT_EQ(r.code, 0) << r.err;
}

TEST_F(Hostile, HelpWinsOverABadFlag) {
  const Result r = run("bench --help --bogus");
  EXPECT_EQ(r.code, 0);
  EXPECT_EQ(r.out.rfind("usage: scandyn bench", 0), 0u);
  EXPECT_EQ(run("eval --bogus -h").code, 0);
}

}  // namespace
