// `scandyn rollout --tau FILE.npy` (docs/cli.md): the torques reach the simulator
// (a gravity-compensating torque holds the arm still; the trajectory equals the
// Simulator stepped with the same torques, bit for bit), the three shapes agree, and
// every malformed file is one error line, exit 1, with no output file left behind.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <string>
#include <vector>

#include "cli_test_util.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/io/npy.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"

namespace {

using namespace scandyn::test::cli;
using namespace scandyn;

class RolloutTau : public CliDirTest {};

// A .npy file: `dict` the header dictionary as written, `data` the raw bytes.
std::string npy_bytes(const std::string& dict, const std::string& data, int major = 1) {
  std::string d = dict;
  const std::size_t prefix = major == 1 ? 10 : 12;
  d.append((64 - (prefix + d.size() + 1) % 64) % 64, ' ');
  d += '\n';
  std::string h = "\x93NUMPY";
  h += static_cast<char>(major);
  h += '\0';
  const std::uint32_t len = static_cast<std::uint32_t>(d.size());
  h += static_cast<char>(len & 0xff);
  h += static_cast<char>((len >> 8) & 0xff);
  if (major != 1) h += static_cast<char>((len >> 16) & 0xff), h += static_cast<char>(len >> 24);
  return h + d + data;
}

template <class T>
std::string raw(const std::vector<T>& v) {
  return std::string(reinterpret_cast<const char*>(v.data()), v.size() * sizeof(T));
}

// A C-order float64 (or float32) .npy of `shape` holding v.
template <class T>
std::string npy_of(const std::vector<long long>& shape, const std::vector<T>& v) {
  std::string h = io::npy_header(sizeof(T) == 4 ? "<f4" : "<f8", shape);
  return h + raw(v);
}

std::vector<double> read_npy_doubles(const std::string& bytes, std::size_t count) {
  const std::size_t hlen = static_cast<unsigned char>(bytes[8]) | (static_cast<unsigned char>(bytes[9]) << 8);
  std::vector<double> v(count);
  EXPECT_EQ(bytes.size(), 10 + hlen + count * sizeof(double));
  std::memcpy(v.data(), bytes.data() + 10 + hlen, count * sizeof(double));
  return v;
}

// chain:3 hanging under gravity from a fixed, non-trivial state, 2 instances, euler
const char* const kScene = R"({"model": "chain:3", "dt": 0.001, "instances": 2, "integrator": "euler",
  "effects": {"gravity": true}, "initial": {"q": [0.7, -0.4, 0.9]}, "backend": "serial"})";
constexpr int kNv = 3, kB = 2, kSteps = 40;

// Gravity compensation: tau = g(q0) (the RNEA's bias forces at rest, an algorithm the
// simulator's ABA does not use) gives qdd = 0, so the arm stays where it starts;
// without it the arm falls.
TEST_F(RolloutTau, GravityCompensatingTorqueHoldsTheArm) {
  write_text(path("s.json"), kScene);
  const Model m = load_model("chain:3");
  Data data(m);
  const std::vector<double> q0 = {0.7, -0.4, 0.9}, zero(kNv, 0.0);
  std::vector<double> g(kNv);
  bias_forces(m, data, q0.data(), zero.data(), g.data());
  write_text(path("g.npy"), npy_of<double>({kNv}, g));
  Result r = run("rollout --scene s.json --steps 40 --out held.npy --tau g.npy");
  ASSERT_EQ(r.code, 0) << r.err;
  r = run("rollout --scene s.json --steps 40 --out fell.npy");
  ASSERT_EQ(r.code, 0) << r.err;
  const std::size_t width = 1 + 2 * kNv, count = (kSteps + 1) * kB * width;
  const std::vector<double> held = read_npy_doubles(read_text(path("held.npy")), count);
  const std::vector<double> fell = read_npy_doubles(read_text(path("fell.npy")), count);
  double held_dev = 0, fell_dev = 0;
  const std::size_t last = kSteps * kB * width;
  for (int b = 0; b < kB; ++b)
    for (int i = 0; i < kNv; ++i) {
      held_dev = std::max({held_dev, std::abs(held[last + b * width + 1 + i] - q0[i]),
                           std::abs(held[last + b * width + 1 + kNv + i])});
      fell_dev = std::max(fell_dev, std::abs(fell[last + b * width + 1 + kNv + i]));
    }
  EXPECT_LT(held_dev, 1e-11) << "the compensated arm moved";
  EXPECT_GT(fell_dev, 1e-2) << "without torques the arm should fall";
}

// Per-step torques: the rollout equals the Simulator stepped with the same torques.
TEST_F(RolloutTau, PerStepTorquesEqualTheSimulatorsSteps) {
  write_text(path("s.json"), kScene);
  std::vector<double> tau(kSteps * kB * kNv);
  for (std::size_t k = 0; k < tau.size(); ++k) tau[k] = std::sin(0.37 * double(k)) * 3.0;
  write_text(path("tau.npy"), npy_of<double>({kSteps, kB, kNv}, tau));
  const Result r = run("rollout --scene s.json --steps 40 --every 40 --out t.npy --tau tau.npy");
  ASSERT_EQ(r.code, 0) << r.err;
  const std::size_t width = 1 + 2 * kNv;
  const std::vector<double> t = read_npy_doubles(read_text(path("t.npy")), 2 * kB * width);
  sim::Simulator<double> s(sim::load_scene(path("s.json").string()));
  for (int step = 0; step < kSteps; ++step)
    s.step(BatchView<const double>::aos(tau.data() + std::size_t(step) * kB * kNv, kNv, kB));
  for (int b = 0; b < kB; ++b)
    for (int i = 0; i < kNv; ++i) {
      EXPECT_EQ(t[(kB + b) * width + 1 + i], s.q().at(i, b)) << b << " " << i;
      EXPECT_EQ(t[(kB + b) * width + 1 + kNv + i], s.qd().at(i, b)) << b << " " << i;
    }
}

// On cuda (where a device is usable) the torques are copied to the device step by step
// on the simulator's stream: the trajectory equals the serial one's within double
// rounding (the device's FMA and sin/cos), per-step and broadcast torques alike.
TEST_F(RolloutTau, CudaRolloutTakesTheTorques) {
  const std::string why = backend_unusable(BackendKind::Cuda);
  if (!why.empty()) GTEST_SKIP() << "no CUDA backend here: " << why;
  write_text(path("s.json"), kScene);
  std::vector<double> tau(kSteps * kB * kNv);
  for (std::size_t k = 0; k < tau.size(); ++k) tau[k] = std::cos(0.21 * double(k)) * 2.0;
  write_text(path("tau.npy"), npy_of<double>({kSteps, kB, kNv}, tau));
  write_text(path("row.npy"), npy_of<double>({kNv}, std::vector<double>{0.5, -1.0, 0.25}));
  const std::size_t count = (kSteps + 1) * kB * (1 + 2 * kNv);
  for (const char* f : {"tau", "row"}) {
    for (const char* backend : {"serial", "cuda"}) {
      const Result r = run(std::string("rollout --scene s.json --steps 40 --backend ") + backend + " --out " + f + "." +
                           backend + ".npy --tau " + f + ".npy");
      ASSERT_EQ(r.code, 0) << f << " " << backend << ": " << r.err;
    }
    const std::vector<double> serial = read_npy_doubles(read_text(path(std::string(f) + ".serial.npy")), count);
    const std::vector<double> cuda = read_npy_doubles(read_text(path(std::string(f) + ".cuda.npy")), count);
    double err = 0, zero_err = 0;
    for (std::size_t k = 0; k < count; ++k) err = std::max(err, std::abs(serial[k] - cuda[k]));
    EXPECT_LT(err, 1e-10) << f;
    // and the torques mattered: the zero-torque rollout differs
    const Result z = run(std::string("rollout --scene s.json --steps 40 --backend cuda --out zero.npy"));
    ASSERT_EQ(z.code, 0) << z.err;
    const std::vector<double> zero = read_npy_doubles(read_text(path("zero.npy")), count);
    for (std::size_t k = 0; k < count; ++k) zero_err = std::max(zero_err, std::abs(zero[k] - cuda[k]));
    EXPECT_GT(zero_err, 1e-4) << f;
  }
}

// (nv,), (B, nv) and (N, B, nv) holding the same torques give the same trajectory,
// in float64 and float32 files alike (values exact in both).
TEST_F(RolloutTau, TheThreeShapesAgree) {
  write_text(path("s.json"), kScene);
  const std::vector<double> row = {1.5, -2.25, 0.75};
  std::vector<double> inst, steps;
  for (int b = 0; b < kB; ++b) inst.insert(inst.end(), row.begin(), row.end());
  for (int s = 0; s < kSteps; ++s) steps.insert(steps.end(), inst.begin(), inst.end());
  write_text(path("row.npy"), npy_of<double>({kNv}, row));
  write_text(path("inst.npy"), npy_of<float>({kB, kNv}, std::vector<float>(inst.begin(), inst.end())));
  write_text(path("steps.npy"), npy_of<double>({kSteps, kB, kNv}, steps));
  for (const char* f : {"row", "inst", "steps"})
    ASSERT_EQ(run(std::string("rollout --scene s.json --steps 40 --out ") + f + ".out.npy --tau " + f + ".npy").code,
              0)
        << f;
  EXPECT_EQ(read_text(path("row.out.npy")), read_text(path("inst.out.npy")));
  EXPECT_EQ(read_text(path("row.out.npy")), read_text(path("steps.out.npy")));
}

// Every malformed torque file: exit 1, one line naming --tau, the file and what is
// wrong, and no trajectory written.
TEST_F(RolloutTau, MalformedFilesAreOneClearError) {
  write_text(path("s.json"), kScene);
  const std::vector<double> ok6(kB * kNv, 0.0);
  struct Case {
    const char* name;
    std::string bytes;
    const char* says;
  };
  std::string be = npy_bytes("{'descr': '>f8', 'fortran_order': False, 'shape': (3,), }", raw(std::vector<double>(3)));
  std::vector<double> nan_steps(kSteps * kB * kNv, 0.0);
  nan_steps[(7 * kB + 1) * kNv + 2] = std::nan("");
  const std::vector<Case> cases = {
      {"nv.npy", npy_of<double>({4}, std::vector<double>(4)), "the last dimension is not the model's nv = 3"},
      {"inst.npy", npy_of<double>({3, kNv}, std::vector<double>(9)), "not the scene's 2 instances"},
      {"steps.npy", npy_of<double>({7, kB, kNv}, std::vector<double>(7 * kB * kNv)),
       "torques for 7 steps, the rollout takes 40"},
      {"rank.npy", npy_of<double>({1, 1, kB, kNv}, ok6), "not 1, 2 or 3 dimensions"},
      {"int.npy", npy_bytes("{'descr': '<i8', 'fortran_order': False, 'shape': (3,), }", raw(std::vector<double>(3))),
       "dtype '<i8' is not supported"},
      {"big.npy", be, "dtype '>f8' is not supported"},
      {"fortran.npy", npy_bytes("{'descr': '<f8', 'fortran_order': True, 'shape': (2, 3), }", raw(ok6)),
       "Fortran order"},
      {"short.npy", npy_of<double>({kB, kNv}, ok6).substr(0, npy_of<double>({kB, kNv}, ok6).size() - 8),
       "truncated: a float64 array of shape (2, 3) needs 48 bytes of data, the file holds 40"},
      {"long.npy", npy_of<double>({kB, kNv}, ok6) + "xyz", "3 bytes after the data"},
      {"text.npy", "q_0,q_1\n1,2\n", "not a .npy file"},
      {"version.npy", std::string("\x93NUMPY\x09\x00", 8) + std::string(60, ' '), "version 9.0 is not supported"},
      {"header.npy", npy_bytes("{'descr': '<f8', 'shape': (3,), }", raw(std::vector<double>(3))),
       "lacks one of 'descr', 'fortran_order', 'shape'"},
      {"garbled.npy", npy_bytes("{'descr': '<f8', 'fortran_order': Maybe, 'shape': (3,), }", raw(std::vector<double>(3))),
       "fortran_order is neither True nor False"},
      {"hdrlen.npy", std::string("\x93NUMPY\x01\x00\xff\xff", 10) + "{'descr'", "truncated .npy header"},
      {"nan.npy", npy_of<double>({kSteps, kB, kNv}, nan_steps),
       "tau[7, 1, 2] (step 8, instance 1, DoF 2) is nan; torques must be finite"},
  };
  for (const Case& c : cases) {
    write_text(path(c.name), c.bytes);
    const Result r = run(std::string("rollout --scene s.json --steps 40 --out t.npy --tau ") + c.name);
    EXPECT_EQ(r.code, 1) << c.name << ": " << r.err;
    EXPECT_EQ(r.err.rfind(std::string("scandyn: --tau ") + c.name + ": ", 0), 0u) << r.err;
    EXPECT_NE(r.err.find(c.says), std::string::npos) << c.name << ": " << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
    EXPECT_FALSE(fs::exists(path("t.npy"))) << c.name << " left a trajectory";
  }
  // a version 2.0 header is read like 1.0
  write_text(path("v2.npy"), npy_bytes("{'descr': '<f8', 'fortran_order': False, 'shape': (3,), }",
                                       raw(std::vector<double>{0.5, 0.5, 0.5}), 2));
  EXPECT_EQ(run("rollout --scene s.json --steps 2 --out v2.out.npy --tau v2.npy").code, 0);
  Result r = run("rollout --scene s.json --steps 2 --out t.npy --tau missing.npy");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("missing.npy: cannot open"), std::string::npos) << r.err;
  fs::create_directory(path("dir.npy"));
  r = run("rollout --scene s.json --steps 2 --out t.npy --tau dir.npy");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("dir.npy: not a regular file"), std::string::npos) << r.err;
  r = run("rollout --scene s.json --steps 2 --out t.npy --tau=");
  EXPECT_EQ(r.code, 2) << r.err;
}

}  // namespace

// --tau and --contacts together: the torques push chain:3 onto a plane, the record
// holds the state and the four contact columns per point, all equal to the
// Simulator stepped with the same torques and read after the last step.
TEST_F(RolloutTau, TorquesWithContactsEqualTheSimulator) {
  write_text(path("c.json"), R"({"model": "chain:3", "dt": 0.001, "instances": 2, "integrator": "euler",
    "effects": {"gravity": true, "contacts": {"planes": [{"normal": [0, 0, 1], "offset": 0.25}],
      "all_links": {"radius": 0.01}, "stiffness": 1e4, "damping": 10, "friction": 0.5}},
    "initial": {"q": [0.7, -0.4, 0.9]}, "backend": "serial"})");
  std::vector<double> tau(kSteps * kB * kNv);
  for (std::size_t k = 0; k < tau.size(); ++k) tau[k] = std::sin(0.37 * double(k)) * 3.0;
  write_text(path("tau.npy"), npy_of<double>({kSteps, kB, kNv}, tau));
  const Result r = run("rollout --scene c.json --steps 40 --every 40 --out t.npy --tau tau.npy --contacts");
  ASSERT_EQ(r.code, 0) << r.err;
  const std::size_t points = 3, width = 1 + 2 * kNv + 4 * points;
  const std::vector<double> t = read_npy_doubles(read_text(path("t.npy")), 2 * kB * width);
  sim::Simulator<double> s(sim::load_scene(path("c.json").string()));
  for (int step = 0; step < kSteps; ++step)
    s.step(BatchView<const double>::aos(tau.data() + std::size_t(step) * kB * kNv, kNv, kB));
  std::vector<sim::ContactReading<double>> c(kB * points);
  s.read_contact_forces(c.data());
  int touching = 0;
  for (int b = 0; b < kB; ++b) {
    const double* row = t.data() + (kB + b) * width;
    for (int i = 0; i < kNv; ++i) {
      EXPECT_EQ(row[1 + i], s.q().at(i, b)) << b << " " << i;
      EXPECT_EQ(row[1 + kNv + i], s.qd().at(i, b)) << b << " " << i;
    }
    for (std::size_t k = 0; k < points; ++k) {
      const auto& x = c[b * points + k];
      const double* f = row + 1 + 2 * kNv + 4 * k;
      EXPECT_EQ(f[0], x.force.x);
      EXPECT_EQ(f[1], x.force.y);
      EXPECT_EQ(f[2], x.force.z);
      EXPECT_EQ(f[3], double(x.in_contact));
      touching += x.in_contact;
    }
  }
  EXPECT_GT(touching, 0);  // the scene does touch the plane
}
