// The command line with --floating-base: info's nq / nv / base, eval's q_0..q_{nq-1}
// columns (quaternions normalised within 1e-6, a data error beyond, naming the row
// and the columns), the nq / nv column mismatch, a root link that is the world
// frame, bench's floating rows, the first-order derivatives on backend cuda (bench
// rows; eval's dfd against serial's). The values themselves are checked against
// Pinocchio's free flyer by scripts/check_pinocchio.py (ctest pinocchio_crosscheck).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <string>
#include <vector>

#include "cli/cli_test_util.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/io/states.hpp"
#include "scandyn/model/load.hpp"

using namespace scandyn::test::cli;
using scandyn::Index;

namespace {

class CliFloating : public CliDirTest {
 protected:
  // A states file for a model of nq positions and nv DoFs: `rows` rows of q, qd and
  // tau, q's quaternion at q_3..q_6 scaled by `quat_scale` (1: unit).
  void write_states(const std::string& name, Index nq, Index nv, int rows, double quat_scale,
                    std::vector<std::vector<double>>* q_rows = nullptr) {
    std::mt19937_64 g(3);
    std::uniform_real_distribution<double> u(-1, 1);
    std::string text;
    for (Index i = 0; i < nq; ++i) text += (i ? "," : "") + std::string("q_") + std::to_string(i);
    for (Index i = 0; i < nv; ++i) text += ",qd_" + std::to_string(i);
    for (Index i = 0; i < nv; ++i) text += ",tau_" + std::to_string(i);
    text += "\n";
    for (int r = 0; r < rows; ++r) {
      std::vector<double> q(nq);
      for (double& x : q) x = u(g);
      const double n = std::sqrt(q[3] * q[3] + q[4] * q[4] + q[5] * q[5] + q[6] * q[6]);
      for (int k = 3; k < 7; ++k) q[k] *= quat_scale / n;
      if (q_rows) q_rows->push_back(q);
      char buf[40];
      for (Index i = 0; i < nq; ++i) {
        std::snprintf(buf, sizeof buf, "%s%.17g", i ? "," : "", q[i]);
        text += buf;
      }
      for (Index i = 0; i < 2 * nv; ++i) {
        std::snprintf(buf, sizeof buf, ",%.17g", u(g));
        text += buf;
      }
      text += "\n";
    }
    write_text(path(name), text);
  }
};

}  // namespace

TEST_F(CliFloating, InfoPrintsNqNvAndTheBase) {
  Result r = run("info --model hyq --floating-base");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.out.find("nv       18"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("nq       19"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("base     floating"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("root_joint"), std::string::npos) << r.out;
  r = run("info --model hyq");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.out.find("nq       12"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("base     fixed"), std::string::npos) << r.out;
  r = run("info --model ballrope:3");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.out.find("spherical"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("nq       12"), std::string::npos) << r.out;
}

// Within 1e-6 the quaternion is normalised: the result equals the unit one's.
TEST_F(CliFloating, EvalNormalisesNearlyUnitQuaternions) {
  const scandyn::Model m = scandyn::load_model("hyq", [] {
    scandyn::BuildOptions o;
    o.floating_base = true;
    return o;
  }());
  write_states("unit.csv", m.nq(), m.nv(), 3, 1.0);
  write_states("near.csv", m.nq(), m.nv(), 3, 1.0 + 5e-7);
  Result r = run("eval --model hyq --floating-base --states unit.csv --out a.csv --algo fd,id,mass,bias --precision double");
  ASSERT_EQ(r.code, 1) << "the file has no qdd columns: id cannot run";
  r = run("eval --model hyq --floating-base --states unit.csv --out a.csv --algo fd,mass,bias");
  ASSERT_EQ(r.code, 0) << r.err;
  r = run("eval --model hyq --floating-base --states near.csv --out b.csv --algo fd,mass,bias");
  ASSERT_EQ(r.code, 0) << r.err;
  const std::string a = read_text(path("a.csv")), b = read_text(path("b.csv"));
  EXPECT_NE(a.find("qdd_fd_17"), std::string::npos);
  EXPECT_NE(a.find("M_17_17"), std::string::npos);
  EXPECT_EQ(a.find("qdd_fd_18"), std::string::npos);
  // normalising x (1 + 5e-7) gives x up to an ulp or so: results agree to ~1e-15
  std::istringstream sa(a), sb(b);
  std::string la, lb;
  std::getline(sa, la), std::getline(sb, lb);
  ASSERT_EQ(la, lb);
  while (std::getline(sa, la) && std::getline(sb, lb)) {
    std::istringstream ca(la), cb(lb);
    std::string x, y;
    while (std::getline(ca, x, ',') && std::getline(cb, y, ','))
      EXPECT_NEAR(std::stod(x), std::stod(y), 1e-12 * std::max(1.0, std::fabs(std::stod(y))));
  }
}

TEST_F(CliFloating, BadQuaternionIsADataErrorNamingRowAndColumns) {
  write_states("bad.csv", 19, 18, 4, 1.0 + 2e-6);
  const Result r = run("eval --model hyq --floating-base --states bad.csv --out o.csv --algo fd");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("row 1"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("q_3..q_6"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("quaternion"), std::string::npos) << r.err;
  EXPECT_FALSE(std::filesystem::exists(path("o.csv")));
  EXPECT_EQ(files(), std::vector<std::string>{"bad.csv"}) << "nothing half-written";
}

TEST_F(CliFloating, ColumnCountMismatchIsNamed) {
  // a fixed-base file (nq = nv = 12) for the floating model (nq = 19, nv = 18)
  write_states("fixed.csv", 12, 12, 2, 1.0);
  Result r = run("eval --model hyq --floating-base --states fixed.csv --out o.csv --algo fd");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("missing column q_12"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("nq = 19"), std::string::npos) << r.err;
  // a floating file for the fixed model
  write_states("floating.csv", 19, 18, 2, 1.0);
  r = run("eval --model hyq --states floating.csv --out o.csv --algo fd");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("out of range"), std::string::npos) << r.err;
  EXPECT_FALSE(std::filesystem::exists(path("o.csv")));
}

TEST_F(CliFloating, WorldRootIsRefused) {
  write_text(path("bolted.urdf"),
             "<robot name=\"bolted\"><link name=\"world\"/>"
             "<link name=\"base\"><inertial><mass value=\"1\"/><inertia ixx=\"0.1\" ixy=\"0\" ixz=\"0\" iyy=\"0.1\" "
             "iyz=\"0\" izz=\"0.1\"/></inertial></link>"
             "<joint name=\"bolt\" type=\"fixed\"><parent link=\"world\"/><child link=\"base\"/></joint></robot>");
  Result r = run("info --model bolted.urdf --floating-base");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("link 'world'"), std::string::npos) << r.err;
  r = run("info --model bolted.urdf");
  EXPECT_EQ(r.code, 0) << r.err;
}

TEST_F(CliFloating, BenchRowsNameTheFloatingModel) {
  const Result r = run("bench --model hyq --floating-base --algo fd --instances 8 --min-time 0");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.out.find("fd,aba,serial,double,hyq-floating,18,8,"), std::string::npos) << r.out;
  // cuda: the floating-base thread kernels where a device is usable, else an error saying why
  const Result c = run("bench --model hyq --floating-base --algo fd --instances 8 --min-time 0 --backend cuda");
  if (scandyn::backend_unusable(scandyn::BackendKind::Cuda).empty()) {
    ASSERT_EQ(c.code, 0) << c.err;
    EXPECT_NE(c.out.find("fd,aba_thread,cuda,double,hyq-floating,18,8,"), std::string::npos) << c.out;
  } else {
    EXPECT_NE(c.code, 0);
    EXPECT_NE(c.err.find("cuda"), std::string::npos) << c.err;
  }
}

// fk and jac take the floating base (values: ctest pinocchio_crosscheck); the
// forward-dynamics check is on by default (float too); what takes 1-DoF joints only
// says so, naming the feature and the joint, and writes nothing.
TEST_F(CliFloating, KinematicsCheckAndRefusals) {
  write_states("s.csv", 19, 18, 3, 1.0);
  Result r = run("eval --model hyq --floating-base --states s.csv --out k.csv --algo fd,fk,jac --precision float");
  ASSERT_EQ(r.code, 0) << r.err;
  const std::string k = read_text(path("k.csv"));
  EXPECT_NE(k.find("J_base_link_0_5_17"), std::string::npos);
  EXPECT_EQ(k.find("J_base_link_0_5_18"), std::string::npos);
  r = run("eval --model hyq --floating-base --states s.csv --out h.csv --algo hybrid --prescribed 0");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("--algo hybrid"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("root_joint"), std::string::npos) << r.err;
  EXPECT_FALSE(std::filesystem::exists(path("h.csv")));
  // the first-order derivatives take the floating base: nv x nv blocks (18 DoF; values:
  // tests/algorithm/test_derivatives_multi_dof.cpp, ctest pinocchio_crosscheck)
  r = run("eval --model hyq --floating-base --states s.csv --out e.csv --algo dfd");
  ASSERT_EQ(r.code, 0) << r.err;
  const std::string e = read_text(path("e.csv"));
  EXPECT_NE(e.find("dqdd_dq_17_17"), std::string::npos);
  EXPECT_NE(e.find("dqdd_dtau_17_17"), std::string::npos);
  EXPECT_EQ(e.find("dqdd_dq_18_"), std::string::npos);
  EXPECT_EQ(e.find("nan"), std::string::npos);
}

namespace {

// The numbers of a CSV file after its header, row by row.
std::vector<double> csv_numbers(const std::string& text) {
  std::vector<double> v;
  const std::size_t body = text.find('\n');
  std::string cell;
  for (std::size_t i = body == std::string::npos ? text.size() : body + 1; i <= text.size(); ++i) {
    if (i == text.size() || text[i] == ',' || text[i] == '\n') {
      if (!cell.empty()) v.push_back(std::strtod(cell.c_str(), nullptr));
      cell.clear();
    } else {
      cell += text[i];
    }
  }
  return v;
}

}  // namespace

// The first-order derivatives on backend cuda take the floating base (the general
// derivative kernels, strategy "general"): bench rows, and eval's dfd equal to
// serial's within 1e-9 of the largest entry. Without a usable device the error says
// why; a build without SCANDYN_CUDA_ALL_CAPACITIES (capacity 8 only) refuses hyq's 18
// DoF naming the option.
TEST_F(CliFloating, DerivativesOnCuda) {
  const bool device = scandyn::backend_unusable(scandyn::BackendKind::Cuda).empty();
  for (const char* algo : {"did", "dfd"}) {
    const Result c = run(std::string("bench --model hyq --floating-base --algo ") + algo +
                         " --instances 8 --min-time 0 --backend cuda");
    if (!device) {
      EXPECT_NE(c.code, 0);
      EXPECT_NE(c.err.find("cuda"), std::string::npos) << c.err;
    } else if (!SCANDYN_CUDA_ALL_CAPACITIES) {
      EXPECT_NE(c.code, 0);
      EXPECT_NE(c.err.find("SCANDYN_CUDA_ALL_CAPACITIES"), std::string::npos) << c.err;
    } else {
      ASSERT_EQ(c.code, 0) << c.err;
      EXPECT_NE(c.out.find(std::string(algo) + ",general,cuda,double,hyq-floating,18,8,"), std::string::npos) << c.out;
    }
  }
  if (!device || !SCANDYN_CUDA_ALL_CAPACITIES) return;
  write_states("s.csv", 19, 18, 5, 1.0);
  Result r = run("eval --model hyq --floating-base --states s.csv --out serial.csv --algo dfd");
  ASSERT_EQ(r.code, 0) << r.err;
  r = run("eval --model hyq --floating-base --states s.csv --out cuda.csv --algo dfd --backend cuda");
  ASSERT_EQ(r.code, 0) << r.err;
  const std::vector<double> a = csv_numbers(read_text(path("cuda.csv"))), b = csv_numbers(read_text(path("serial.csv")));
  ASSERT_EQ(a.size(), b.size());
  ASSERT_EQ(a.size(), std::size_t(5) * 3 * 18 * 18);
  double scale = 1, err = 0;
  for (std::size_t k = 0; k < a.size(); ++k) {
    scale = std::max(scale, std::fabs(b[k]));
    err = std::max(err, std::fabs(a[k] - b[k]));
  }
  EXPECT_LT(err / scale, 1e-9);
}
