// Tests of the `scandyn` command (docs/cli.md): each runs the built executable in a
// fresh temporary directory and checks its files, exit code and messages against
// the library called directly.
#include <gtest/gtest.h>
#include <stdlib.h>
#include <sys/wait.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <random>
#include <sstream>
#include <string>

#include <vector>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sim/simulator.hpp"
#include "cli_test_util.hpp"
#include "test_util.hpp"

namespace {

namespace fs = std::filesystem;
using namespace scandyn::test::cli;
using scandyn::Model;

// ---- helpers ------------------------------------------------------------------

// Why `--backend cuda` cannot run here ("" when it can): the command's message
// after "scandyn: ", as docs/cli.md gives it.
std::string cuda_backend_error() {
#if SCANDYN_HAS_CUDA
  const auto count = scandyn::cuda::device_count();
  if (!count) return "backend 'cuda': " + count.error;
  if (count.value == 0) return "backend 'cuda': no usable CUDA device: the CUDA runtime reports 0 devices";
  return "";
#else
  return "backend 'cuda' is not available in this build";
#endif
}

std::vector<std::string> split(const std::string& s, char sep) {
  std::vector<std::string> parts;
  std::size_t start = 0;
  for (;;) {
    const std::size_t k = s.find(sep, start);
    parts.push_back(s.substr(start, k == std::string::npos ? std::string::npos : k - start));
    if (k == std::string::npos) return parts;
    start = k + 1;
  }
}

std::vector<std::string> lines(const std::string& text) {
  std::vector<std::string> out = split(text, '\n');
  if (!out.empty() && out.back().empty()) out.pop_back();
  return out;
}

std::string fmt17(double x) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.17g", x);
  return buf;
}

// A parsed numeric CSV file (as eval writes it).
struct Table {
  std::vector<std::string> names;
  std::vector<std::vector<double>> rows;

  // Values of columns prefix0 .. prefix(n-1) in row r.
  std::vector<double> get(std::size_t r, const std::string& prefix, int n) const {
    std::vector<double> v;
    for (int i = 0; i < n; ++i) {
      const auto it = std::find(names.begin(), names.end(), prefix + std::to_string(i));
      if (it == names.end()) {
        ADD_FAILURE() << "no column " << prefix << i;
        return v;
      }
      v.push_back(rows.at(r).at(static_cast<std::size_t>(it - names.begin())));
    }
    return v;
  }
};

Table parse_csv(const std::string& text) {
  Table t;
  const std::vector<std::string> ls = lines(text);
  if (ls.empty()) return t;
  t.names = split(ls[0], ',');
  for (std::size_t k = 1; k < ls.size(); ++k) {
    std::vector<double> row;
    for (const std::string& f : split(ls[k], ',')) row.push_back(std::strtod(f.c_str(), nullptr));
    EXPECT_EQ(row.size(), t.names.size()) << "line " << k + 1;
    t.rows.push_back(row);
  }
  return t;
}

// Every value of got within tol * max(1, max |row|) of want's, row by row, same
// columns and rows.
void expect_tables_near(const Table& got, const Table& want, double tol) {
  ASSERT_EQ(got.names, want.names);
  ASSERT_EQ(got.rows.size(), want.rows.size());
  for (std::size_t r = 0; r < want.rows.size(); ++r) {
    double scale = 1;
    for (double x : want.rows[r]) scale = std::max(scale, std::fabs(x));
    for (std::size_t c = 0; c < want.rows[r].size(); ++c)
      EXPECT_NEAR(got.rows[r][c], want.rows[r][c], tol * scale) << "row " << r << " column " << want.names[c];
  }
}

// Random states: [row][dof] for each family, uniform in [-1, 1].
struct States {
  int nv = 0;
  std::vector<std::vector<double>> q, qd, qdd, tau;

  States(int nv_, int rows, unsigned seed) : nv(nv_) {
    std::mt19937_64 rng(seed);
    for (auto* fam : {&q, &qd, &qdd, &tau})
      for (int r = 0; r < rows; ++r) fam->push_back(scandyn::test::random_vector(rng, nv, -1, 1));
  }
  const std::vector<std::vector<double>>& family(const std::string& name) const {
    return name == "q" ? q : name == "qd" ? qd : name == "qdd" ? qdd : tau;
  }
  std::size_t rows() const { return q.size(); }

  // CSV text with the given families, columns in family-major order, or shuffled.
  std::string csv(const std::vector<std::string>& families, unsigned shuffle_seed = 0) const {
    std::vector<std::pair<std::string, int>> cols;
    for (const std::string& f : families)
      for (int i = 0; i < nv; ++i) cols.emplace_back(f, i);
    if (shuffle_seed) {
      std::mt19937 rng(shuffle_seed);
      std::shuffle(cols.begin(), cols.end(), rng);
    }
    std::string text;
    for (std::size_t c = 0; c < cols.size(); ++c)
      text += (c ? "," : "") + cols[c].first + "_" + std::to_string(cols[c].second);
    text += "\n";
    for (std::size_t r = 0; r < rows(); ++r) {
      for (std::size_t c = 0; c < cols.size(); ++c)
        text += (c ? "," : "") +
                fmt17(family(cols[c].first)[r][static_cast<std::size_t>(cols[c].second)]);
      text += "\n";
    }
    return text;
  }
};

// Each test in a fresh directory (cli_test_util.hpp).
using Cli = CliDirTest;

// The info table's DoF rows: [index, joint, type, parent, child, axis...].
std::vector<std::vector<std::string>> info_dofs(const std::string& out) {
  std::vector<std::vector<std::string>> rows;
  bool in_table = false;
  for (const std::string& l : lines(out)) {
    std::istringstream ss(l);
    std::vector<std::string> words;
    for (std::string w; ss >> w;) words.push_back(w);
    if (!words.empty() && words[0] == "index") {
      in_table = true;
      continue;
    }
    if (in_table && words.empty()) break;  // the frames table follows after a blank line
    if (in_table) rows.push_back(words);
  }
  return rows;
}

// ---- info ---------------------------------------------------------------------

TEST_F(Cli, InfoChainListsDofsInOrderWithParents) {
  const Model model = scandyn::load_model("chain:3");
  const Result r = run("info --model chain:3");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(r.err.empty());
  EXPECT_NE(r.out.find("nv       3"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("gravity  0 0 -9.81"), std::string::npos) << r.out;
  const auto dofs = info_dofs(r.out);
  ASSERT_EQ(dofs.size(), 3u) << r.out;
  for (int i = 0; i < 3; ++i) {
    ASSERT_GE(dofs[i].size(), 8u);
    EXPECT_EQ(dofs[i][0], std::to_string(i));
    EXPECT_EQ(dofs[i][1], model.joint_names[i]);
    EXPECT_EQ(dofs[i][2], "revolute");
    EXPECT_EQ(dofs[i][3], std::to_string(i - 1));  // a chain: each body hangs from the previous
    EXPECT_EQ(dofs[i][4], model.link_names[i]);
  }
}

TEST_F(Cli, InfoReportsCudaDevicesOrWhyNone) {
  const Result r = run("info --model chain:2");
  ASSERT_EQ(r.code, 0) << r.err;
  std::vector<std::string> expected;  // the cuda rows, as the library describes the devices
  const auto count = scandyn::cuda::device_count();
  if (!count) expected.push_back(count.error);
  else if (count.value == 0) expected.push_back("no usable CUDA device: the CUDA runtime reports 0 devices");
  for (int d = 0; count && d < count.value; ++d) {
    const auto info = scandyn::cuda::device_info(d);
    expected.push_back(info ? scandyn::cuda::describe(info.value) : info.error);
  }
  std::vector<std::string> rows;  // the summary's cuda rows, before the blank line
  for (const std::string& l : lines(r.out)) {
    if (l.empty()) break;
    if (l.rfind("cuda ", 0) == 0) rows.push_back(l.substr(l.find_first_not_of(' ', 4)));
  }
  EXPECT_EQ(rows, expected) << r.out;
  EXPECT_EQ(info_dofs(r.out).size(), 2u) << r.out;
}

TEST_F(Cli, InfoIiwaListsSevenJoints) {
  const Result r = run("info --model " + quote(scandyn::test::model_path("iiwa.urdf")));
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.out.find("iiwa14"), std::string::npos) << r.out;
  const auto dofs = info_dofs(r.out);
  ASSERT_EQ(dofs.size(), 7u) << r.out;
  for (int i = 0; i < 7; ++i) {
    EXPECT_EQ(dofs[i][0], std::to_string(i));
    EXPECT_EQ(dofs[i][1], "iiwa_joint_" + std::to_string(i + 1));
    EXPECT_EQ(dofs[i][2], "revolute");
    EXPECT_EQ(dofs[i][3], std::to_string(i - 1));
  }
}

TEST_F(Cli, NonPhysicalInertiaIsRefusedUnlessAllowed) {
  // GRiD's atlas.urdf: utorso, l_foot, r_foot not positive definite, l_lglut breaks
  // the triangle inequality
  const std::string atlas = quote(scandyn::test::model_path("atlas.urdf"));
  const Result strict = run("info --model " + atlas);
  EXPECT_EQ(strict.code, 1);
  EXPECT_NE(strict.err.find("atlas.urdf"), std::string::npos) << strict.err;
  EXPECT_NE(strict.err.find("--allow-nonphysical-inertia"), std::string::npos) << strict.err;
  EXPECT_EQ(std::count(strict.err.begin(), strict.err.end(), '\n'), 1) << strict.err;
  const Result lenient = run("info --model " + atlas + " --allow-nonphysical-inertia");
  ASSERT_EQ(lenient.code, 0) << lenient.err;
  EXPECT_EQ(info_dofs(lenient.out).size(), 30u);
  EXPECT_NE(lenient.err.find("warning"), std::string::npos);
  EXPECT_NE(lenient.err.find("l_foot"), std::string::npos);
  EXPECT_NE(run("info --model " + atlas + " --allow-nonphysical-inertia=1").code, 0);
}

// ---- eval against the library -------------------------------------------------

class EvalModel : public Cli, public ::testing::WithParamInterface<const char*> {
 protected:
  std::string spec() const {
    const std::string p = GetParam();
    return p == "iiwa" ? scandyn::test::model_path("iiwa.urdf") : p;
  }
};

TEST_P(EvalModel, AllAlgorithmsMatchTheReference) {
  const Model model = scandyn::load_model(spec());
  const int n = model.nv();
  scandyn::DataTpl<double> data(model);
  const States s(n, 6, 11);
  write_text(path("states.csv"), s.csv({"q", "qd", "qdd", "tau"}));
  const Result r = run("eval --model " + quote(spec()) +
                       " --states states.csv --out out.csv --algo bias,mass,fd,id");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(r.err.empty()) << r.err;
  const Table t = parse_csv(read_text(path("out.csv")));
  ASSERT_EQ(t.rows.size(), s.rows());

  // columns: tau_id, qdd_fd, M (row-major), h, whatever the --algo order
  std::vector<std::string> expected;
  for (int i = 0; i < n; ++i) expected.push_back("tau_id_" + std::to_string(i));
  for (int i = 0; i < n; ++i) expected.push_back("qdd_fd_" + std::to_string(i));
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j)
      expected.push_back("M_" + std::to_string(i) + "_" + std::to_string(j));
  for (int i = 0; i < n; ++i) expected.push_back("h_" + std::to_string(i));
  ASSERT_EQ(t.names, expected);

  for (std::size_t row = 0; row < s.rows(); ++row) {
    SCOPED_TRACE("row " + std::to_string(row + 1));
    const double* q = s.q[row].data();
    const double* qd = s.qd[row].data();
    std::vector<double> ref(n), zero(n, 0.0), M(n * n);

    // id: 17 digits read back exactly
    scandyn::rnea(model, data, q, qd, s.qdd[row].data(), ref.data());
    EXPECT_EQ(t.get(row, "tau_id_", n), ref);

    // fd: ID(FD(tau)) = tau
    const std::vector<double> qdd_fd = t.get(row, "qdd_fd_", n);
    scandyn::rnea(model, data, q, qd, qdd_fd.data(), ref.data());
    EXPECT_LT(scandyn::test::max_rel_err(ref, s.tau[row]), 1e-9);

    // mass: CRBA exactly, symmetric
    scandyn::crba(model, data, q, M.data());
    for (int i = 0; i < n; ++i) {
      const std::vector<double> Mi = t.get(row, "M_" + std::to_string(i) + "_", n);
      for (int j = 0; j < n; ++j) EXPECT_EQ(Mi[j], M[i * n + j]) << "M_" << i << "_" << j;
      for (int j = 0; j < i; ++j)
        EXPECT_EQ(Mi[j], t.get(row, "M_" + std::to_string(j) + "_", n)[i])
            << "symmetry " << i << "," << j;
    }

    // bias: RNEA with qdd = 0
    const std::vector<double> h = t.get(row, "h_", n);
    scandyn::rnea(model, data, q, qd, zero.data(), ref.data());
    EXPECT_LE(scandyn::test::max_rel_err(h, ref), 1e-15);
    scandyn::bias_forces(model, data, q, qd, ref.data());
    EXPECT_EQ(h, ref);
  }
}

TEST_P(EvalModel, FloatPrecisionIsCloseToDouble) {
  const Model model = scandyn::load_model(spec());
  const States s(model.nv(), 4, 12);
  write_text(path("states.csv"), s.csv({"q", "qd", "qdd", "tau"}));
  const std::string base =
      "eval --model " + quote(spec()) + " --states states.csv --algo id,fd,mass,bias";
  const Result rd = run(base + " --out double.csv");
  const Result rf = run(base + " --out float.csv --precision float");
  ASSERT_EQ(rd.code, 0) << rd.err;
  ASSERT_EQ(rf.code, 0) << rf.err;
  const Table td = parse_csv(read_text(path("double.csv")));
  const Table tf = parse_csv(read_text(path("float.csv")));
  ASSERT_EQ(td.names, tf.names);
  ASSERT_EQ(td.rows.size(), tf.rows.size());
  bool differs = false;
  for (std::size_t row = 0; row < td.rows.size(); ++row) {
    EXPECT_LT(scandyn::test::max_rel_err(tf.rows[row], td.rows[row]), 1e-4) << "row " << row + 1;
    differs = differs || tf.rows[row] != td.rows[row];
    // each value is a float widened to double
    for (double v : tf.rows[row]) EXPECT_EQ(v, static_cast<double>(static_cast<float>(v)));
  }
  EXPECT_TRUE(differs) << "float output identical to double: was it computed in float?";
}

INSTANTIATE_TEST_SUITE_P(
    Models, EvalModel, ::testing::Values("chain:4", "iiwa"),
    [](const ::testing::TestParamInfo<const char*>& info) {
      return std::string(info.param).substr(0, std::string(info.param).find(':'));
    });

TEST_F(Cli, EvalOutputDoesNotDependOnInputColumnOrder) {
  const States s(4, 5, 13);
  write_text(path("a.csv"), s.csv({"q", "qd", "qdd", "tau"}));
  write_text(path("b.csv"), s.csv({"tau", "qdd", "qd", "q"}, 7));
  ASSERT_NE(read_text(path("a.csv")), read_text(path("b.csv")));
  const std::string args = " --model chain:4 --algo id,fd,mass,bias";
  ASSERT_EQ(run("eval --states a.csv --out a_out.csv" + args).code, 0);
  ASSERT_EQ(run("eval --states b.csv --out b_out.csv" + args).code, 0);
  const std::string a = read_text(path("a_out.csv"));
  EXPECT_FALSE(a.empty());
  EXPECT_EQ(a, read_text(path("b_out.csv")));
}

TEST_F(Cli, EvalBackendsAndStrategiesAgree) {
  // OpenMP splits instances over threads running the same recursion: identical
  // bytes (--simd off: the SIMD groups differ from the scalar remainder at rounding
  // where the build contracts to FMA, -march=native). The scan forms reassociate the
  // sums: equal to rounding.
  const States s(7, 40, 21);
  write_text(path("in.csv"), s.csv({"q", "qd", "qdd", "tau"}));
  const std::string model = " --model " + quote(scandyn::test::model_path("iiwa.urdf"));
  const std::string io = " --states in.csv --algo id,fd,mass,bias --simd off";
  ASSERT_EQ(run("eval --out serial.csv" + model + io).code, 0);
  const Result omp = run("eval --out omp.csv --backend openmp --threads 2" + model + io);
#if SCANDYN_HAS_OPENMP
  ASSERT_EQ(omp.code, 0) << omp.err;
  EXPECT_EQ(read_text(path("serial.csv")), read_text(path("omp.csv")));
#else
  EXPECT_EQ(omp.err, "scandyn: backend 'openmp' is not available in this build\n");
#endif
  const Table ref = parse_csv(read_text(path("serial.csv")));
  for (const char* strategy : {"scan-local", "scan-world"}) {
    const std::string out = std::string(strategy) + ".csv";
    const Result r = run("eval --out " + out + " --algo id --states in.csv --strategy " + strategy + model);
    ASSERT_EQ(r.code, 0) << r.err;
    const Table t = parse_csv(read_text(path(out)));
    ASSERT_EQ(t.rows.size(), ref.rows.size());
    for (std::size_t k = 0; k < t.rows.size(); ++k)
      EXPECT_LT(scandyn::test::max_rel_err(t.get(k, "tau_id_", 7), ref.get(k, "tau_id_", 7)), 1e-13) << strategy;
  }
}

TEST_F(Cli, EvalDefaultAlgorithmsFollowTheColumnsPresent) {
  const States s(3, 2, 14);
  struct Case {
    std::vector<std::string> families;
    std::vector<std::string> first_columns;  // of each output block, in order
  };
  const std::vector<Case> cases = {
      {{"q", "qd", "qdd", "tau"}, {"tau_id_0", "qdd_fd_0", "h_0"}},
      {{"q", "qd", "qdd"}, {"tau_id_0", "h_0"}},
      {{"q", "qd", "tau"}, {"qdd_fd_0", "h_0"}},
      {{"qd", "q"}, {"h_0"}},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(::testing::PrintToString(c.families));
    write_text(path("states.csv"), s.csv(c.families));
    const Result r = run("eval --model chain:3 --states states.csv --out out.csv");
    ASSERT_EQ(r.code, 0) << r.err;
    const Table t = parse_csv(read_text(path("out.csv")));
    ASSERT_EQ(t.names.size(), 3 * c.first_columns.size());
    for (std::size_t k = 0; k < c.first_columns.size(); ++k)
      EXPECT_EQ(t.names[3 * k], c.first_columns[k]);
    EXPECT_EQ(t.rows.size(), 2u);
  }
  // mass only on request
  write_text(path("states.csv"), s.csv({"q"}));
  fs::remove(path("out.csv"));
  const Result r = run("eval --model chain:3 --states states.csv --out out.csv");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("no algorithm"), std::string::npos) << r.err;
  EXPECT_FALSE(fs::exists(path("out.csv")));
  ASSERT_EQ(run("eval --model chain:3 --states states.csv --out out.csv --algo mass").code, 0);
  EXPECT_EQ(parse_csv(read_text(path("out.csv"))).names.size(), 9u);
}

// fk and jac: their columns after the dynamics', the flags they need and the error
// for an unknown frame (values are the engine tests' and check_pinocchio.py's).
TEST_F(Cli, EvalFkJacColumnsFlagsAndErrors) {
  const States s(3, 2, 15);
  write_text(path("states.csv"), s.csv({"q"}));
  Result r = run("eval --model chain:3 --states states.csv --out out.csv --algo jac,mass,fk --frames link_2,base");
  ASSERT_EQ(r.code, 0) << r.err;
  Table t = parse_csv(read_text(path("out.csv")));
  ASSERT_EQ(t.names.size(), 9u + 2 * 7 + 2 * 6 * 3);
  EXPECT_EQ(t.names[8], "M_2_2");
  EXPECT_EQ(t.names[9], "fk_link_2_px");
  EXPECT_EQ(t.names[15], "fk_link_2_qw");
  EXPECT_EQ(t.names[16], "fk_base_px");
  EXPECT_EQ(t.names[23], "J_link_2_0_0");
  EXPECT_EQ(t.names.back(), "J_base_5_2");
  ASSERT_EQ(t.rows.size(), 2u);
  for (int j = 41; j < 59; ++j) EXPECT_EQ(t.rows[0][j], 0.0) << t.names[j];  // the base does not move
  // default: every frame (4 links); --reference local
  ASSERT_EQ(run("eval --model chain:3 --states states.csv --out out.csv --algo fk,jac --reference local").code, 0);
  EXPECT_EQ(parse_csv(read_text(path("out.csv"))).names.size(), 4u * 7 + 4 * 18);
  // flags without their algorithms, a bad reference, an unknown frame: nothing written
  fs::remove(path("out.csv"));
  r = run("eval --model chain:3 --states states.csv --out out.csv --algo mass --frames base");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("--frames needs fk or jac"), std::string::npos) << r.err;
  r = run("eval --model chain:3 --states states.csv --out out.csv --algo jac --reference body");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("'body'"), std::string::npos) << r.err;
  r = run("eval --model chain:3 --states states.csv --out out.csv --algo fk --frames link_0,tool");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("no frame 'tool'"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("link_2"), std::string::npos) << r.err;
  EXPECT_FALSE(fs::exists(path("out.csv")));
  // q is needed
  write_text(path("states.csv"), s.csv({"qd"}));
  r = run("eval --model chain:3 --states states.csv --out out.csv --algo fk");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.err.find("q_0"), std::string::npos) << r.err;
}

TEST_F(Cli, EvalAcceptsCrlfSpacesAndMissingFinalNewline) {
  const States s(3, 3, 15);
  const std::string clean = s.csv({"q", "qd", "qdd"});
  write_text(path("clean.csv"), clean);
  // CRLF, spaces and tabs around fields, a '+' sign, no final newline
  std::string messy;
  for (char c : clean)
    messy += c == ',' ? std::string(" ,\t ") : c == '\n' ? std::string(" \r\n") : std::string(1, c);
  messy.resize(messy.size() - 2);
  messy.insert(messy.find('\n') + 1, "+");
  write_text(path("messy.csv"), messy);
  write_text(path("trailing.csv"), clean + "\n\r\n  \n");
  ASSERT_EQ(run("eval --model chain:3 --states clean.csv --out clean_out.csv").code, 0);
  const std::string expected = read_text(path("clean_out.csv"));
  for (const char* name : {"messy", "trailing"}) {
    const Result r =
        run(std::string("eval --model chain:3 --states ") + name + ".csv --out out.csv");
    ASSERT_EQ(r.code, 0) << name << ": " << r.err;
    EXPECT_EQ(read_text(path("out.csv")), expected) << name;
  }
}

TEST_F(Cli, EvalHeaderOnlyGivesHeaderOnly) {
  write_text(path("states.csv"), "q_0,q_1,q_2,qd_0,qd_1,qd_2\n");
  const Result r = run("eval --model chain:3 --states states.csv --out out.csv");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(read_text(path("out.csv")), "h_0,h_1,h_2\n");
}

// ---- eval errors --------------------------------------------------------------

struct BadCase {
  const char* name;
  const char* states;  // contents of states.csv; nullptr: no such file
  std::string args;    // the command line after "scandyn"
  int code;
  std::vector<std::string> expect;  // substrings of the message
};

const std::string kEval = "eval --model chain:3 --states states.csv --out out.csv ";

const char* const kHeader = "q_0,q_1,q_2,qd_0,qd_1,qd_2,qdd_0,qdd_1,qdd_2\n";

std::string good_states(const std::string& row2 = "0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9",
                        const std::string& row3 = "1,2,3,4,5,6,7,8,9") {
  return std::string(kHeader) + "0,0,0,0,0,0,0,0,0\n" + row2 + "\n" + row3 + "\n";
}

TEST_F(Cli, EvalRejectsBadInputWithOneLineAndNoOutput) {
  const std::string wrong_count = good_states("0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8");
  const std::string too_many = good_states("0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0");
  const std::string nan = good_states("0,0,0,0,0,0,0,0,0", "1,2,3,4,5,nan,7,8,9");
  const std::string nan_upper = good_states("0,0,0,0,0,0,0,0,0", "1,2,3,4,5,NaN,7,8,9");
  const std::string inf = good_states("0,inf,0,0,0,0,0,0,0");
  const std::string minus_inf = good_states("0,-Infinity,0,0,0,0,0,0,0");
  const std::string overflow = good_states("0,1e400,0,0,0,0,0,0,0");
  const std::string word = good_states("0,abc,0,0,0,0,0,0,0");
  const std::string trailing_junk = good_states("0,1.5x,0,0,0,0,0,0,0");
  const std::string empty_field = good_states("0,,0,0,0,0,0,0,0");
  const std::string blank_line = std::string(kHeader) + "0,0,0,0,0,0,0,0,0\n\n1,2,3,4,5,6,7,8,9\n";
  // clang-format off
  const std::vector<BadCase> cases = {
      {"missing file", nullptr, kEval, 1, {"states.csv: cannot open"}},
      {"empty file", "", kEval, 1, {"states.csv: empty file"}},
      {"blank file", " \n\r\n", kEval, 1, {"states.csv: empty file"}},
      {"unknown column", "q_0,q_1,q_2,foo\n", kEval, 1, {"states.csv", "unknown column 'foo'"}},
      {"leading zero", "q_0,q_1,q_02\n", kEval, 1, {"states.csv", "unknown column 'q_02'"}},
      {"duplicate column", "q_0,q_1,q_2,q_1\n", kEval, 1, {"states.csv", "duplicate column q_1"}},
      {"index >= nv", "q_0,q_1,q_2,qd_3\n", kEval, 1, {"states.csv", "qd_3", "out of range"}},
      {"empty column name", "q_0,,q_2\n", kEval, 1, {"states.csv", "column 2 has an empty name"}},
      {"too few fields", wrong_count.c_str(), kEval, 1, {"states.csv: row 2 (line 3): expected 9 fields, found 8"}},
      {"too many fields", too_many.c_str(), kEval, 1, {"states.csv: row 2 (line 3): expected 9 fields, found 10"}},
      {"blank line", blank_line.c_str(), kEval, 1, {"states.csv: row 2 (line 3): empty line"}},
      {"nan", nan.c_str(), kEval, 1, {"states.csv: row 3 (line 4), column qd_2: NaN"}},
      {"NaN", nan_upper.c_str(), kEval, 1, {"states.csv: row 3 (line 4), column qd_2: NaN"}},
      {"inf", inf.c_str(), kEval, 1, {"states.csv: row 2 (line 3), column q_1: Inf"}},
      {"-inf", minus_inf.c_str(), kEval, 1, {"states.csv: row 2 (line 3), column q_1: -Inf"}},
      {"overflow", overflow.c_str(), kEval, 1, {"states.csv: row 2 (line 3), column q_1: Inf"}},
      {"not a number", word.c_str(), kEval, 1, {"states.csv: row 2 (line 3), column q_1: not a number: 'abc'"}},
      {"junk after number", trailing_junk.c_str(), kEval, 1, {"row 2 (line 3), column q_1: not a number: '1.5x'"}},
      {"empty field", empty_field.c_str(), kEval, 1, {"states.csv: row 2 (line 3), column q_1: empty field"}},
      {"id needs qdd", "q_0,q_1,q_2,qd_0,qd_1,qd_2,qdd_0,qdd_2\n", kEval + "--algo id", 1, {"states.csv: missing column qdd_1 (needed by --algo id)"}},
      {"fd needs tau", kHeader, kEval + "--algo fd", 1, {"states.csv: missing column tau_0 (needed by --algo fd)"}},
      {"partial family", "q_0,q_1,q_2,qd_0,qd_1,qd_2,tau_1\n", kEval + "--algo bias", 1, {"states.csv: missing column tau_0 (other tau_<i> columns are present)"}},
      {"no default algo", "q_0,q_1,q_2\n", kEval, 1, {"states.csv: no algorithm"}},
      {"unknown algo", kHeader, kEval + "--algo id,foo", 2, {"unknown --algo value 'foo'"}},
      {"empty algo item", kHeader, kEval + "--algo id,", 2, {"unknown --algo value ''"}},
      {"unknown backend", kHeader, kEval + "--backend gpu", 2, {"--backend: unknown backend 'gpu' (expected serial, openmp or cuda)"}},
      {"unknown strategy", kHeader, kEval + "--strategy fastest", 2, {"--strategy: unknown strategy 'fastest'"}},
      {"bad threads", kHeader, kEval + "--threads 0", 2, {"--threads must be an integer"}},
      {"unknown precision", kHeader, kEval + "--precision half", 2, {"--precision: unknown precision 'half' (expected double or float)"}},
      {"unknown flag", kHeader, kEval + "--fast", 2, {"unknown flag '--fast'"}},
      {"repeated flag", kHeader, kEval + "--algo id --algo fd", 2, {"'--algo' given more than once"}},
      {"missing model file", kHeader, "eval --model nope.urdf --states states.csv --out out.csv", 1, {"nope.urdf"}},
      {"malformed generator", kHeader, "eval --model chain:x --states states.csv --out out.csv", 1, {"chain:x"}},
      {"output directory missing", kHeader, "eval --model chain:3 --states states.csv --out nodir/out.csv", 1, {"nodir/out.csv: cannot create file"}},
      {"missing --out", kHeader, "eval --model chain:3 --states states.csv", 2, {"'eval' needs --out"}},
      {"stray argument", kHeader, kEval + "extra", 2, {"unexpected argument 'extra'"}},
  };
  // clang-format on
  for (const BadCase& c : cases) {
    for (bool existing : {false, true}) {
      SCOPED_TRACE(std::string(c.name) + (existing ? ", existing output" : ", no output"));
      fs::remove(path("states.csv"));
      fs::remove(path("out.csv"));
      if (c.states) write_text(path("states.csv"), c.states);
      if (existing) write_text(path("out.csv"), "sentinel\n");
      const std::vector<std::string> before = files();
      const Result r = run(c.args);
      EXPECT_EQ(r.code, c.code);
      ASSERT_FALSE(r.err.empty());
      EXPECT_EQ(r.err.rfind("scandyn: ", 0), 0u) << r.err;
      EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
      EXPECT_EQ(r.err.back(), '\n');
      for (const std::string& e : c.expect) EXPECT_NE(r.err.find(e), std::string::npos) << r.err;
      EXPECT_TRUE(r.out.empty()) << r.out;
      EXPECT_EQ(files(), before) << "no file created or removed (temporary files included)";
      if (existing) {
        EXPECT_EQ(read_text(path("out.csv")), "sentinel\n");
      }
    }
  }
}

// A body of 1e300 kg on a prismatic joint: when it slides 1e5 m out, the articulated
// inertia about the first (revolute) joint, 1e300 * (1e5)^2, overflows and its pivot
// is not finite (so does the mass matrix's M(0, 0), the joint-space inertia's pivot
// at DoF 0). Row 1 (at the origin) is fine, row 2 fails.
std::string heavy_urdf() {
  const std::string inertial =
      "<inertial><origin xyz=\"0 0 0\"/><mass value=\"1e300\"/>"
      "<inertia ixx=\"1\" iyy=\"1\" izz=\"1\" ixy=\"0\" ixz=\"0\" iyz=\"0\"/></inertial>";
  const std::string limit = "<limit lower=\"-1\" upper=\"1\" effort=\"1\" velocity=\"1\"/>";
  return "<robot name=\"heavy\"><link name=\"base\"/>"
         "<link name=\"a\">" +
         inertial + "</link><link name=\"b\">" + inertial +
         "</link>"
         "<joint name=\"j1\" type=\"revolute\"><parent link=\"base\"/><child link=\"a\"/>"
         "<axis xyz=\"0 0 1\"/>" +
         limit +
         "</joint>"
         "<joint name=\"j2\" type=\"prismatic\"><parent link=\"a\"/><child link=\"b\"/>"
         "<axis xyz=\"1 0 0\"/>" +
         limit + "</joint></robot>\n";
}
const char* const kHeavyStates = "q_0,q_1,qd_0,qd_1,tau_0,tau_1\n0,0,0,0,0,0\n0,1e5,0,0,0,0\n";
// row 2 of kHeavyStates with --fd jsi --fallback aba: the JSI fails, then the ABA
const char* const kHeavyFallbackError =
    "scandyn: heavy.csv: row 2 (line 3): forward dynamics failed: mass matrix pivot not positive, and by "
    "the aba fallback the articulated inertia pivot at DoF 0 is not positive\n";

TEST_F(Cli, EvalReportsTheRowWhoseForwardDynamicsFails) {
  write_text(path("heavy.urdf"), heavy_urdf());
  write_text(path("states.csv"), kHeavyStates);
  write_text(path("out.csv"), "sentinel\n");
  const Result r = run("eval --model heavy.urdf --states states.csv --out out.csv --algo fd");
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.err,
            "scandyn: states.csv: row 2 (line 3): forward dynamics failed: articulated inertia "
            "pivot at DoF 0 is not positive\n");
  EXPECT_EQ(read_text(path("out.csv")), "sentinel\n");
  // the first row alone is fine
  write_text(path("states.csv"), "q_0,q_1,qd_0,qd_1,tau_0,tau_1\n0,0,0,0,0,0\n");
  const Result ok = run("eval --model heavy.urdf --states states.csv --out out.csv --algo fd");
  EXPECT_EQ(ok.code, 0) << ok.err;
  EXPECT_EQ(read_text(path("out.csv")), "qdd_fd_0,qdd_fd_1\n0,0\n");
}

// ---- usage --------------------------------------------------------------------

TEST_F(Cli, HelpAndUsageErrors) {
  for (const char* args : {"--help", "info --help", "eval --help", "bench --help"}) {
    const Result r = run(args);
    EXPECT_EQ(r.code, 0) << args;
    EXPECT_EQ(r.out.rfind("usage: scandyn", 0), 0u) << args << ": " << r.out;
    EXPECT_TRUE(r.err.empty()) << args;
  }
  for (const char* args :
       {"", "frobnicate", "info", "info --model", "info --model chain:3 --states x.csv",
        "bench --model chain:3 --algo id", "bench --model chain:3 --algo id --instances 0",
        "bench --model chain:3 --algo id --instances 2.5",
        "bench --model chain:3 --algo step --instances 1",
        "bench --model chain:3 --algo id --fd jsi --instances 1",
        "bench --model chain:3 --algo fd --fd lu --instances 1",
        "bench --model chain:3 --algo id --instances 1 --min-time -1",
        "bench --model chain:3 --algo fd --instances 1 --strategy scan-local"}) {
    const Result r = run(args);
    EXPECT_EQ(r.code, 2) << args;
    EXPECT_EQ(r.err.rfind("scandyn: ", 0), 0u) << args << ": " << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << args << ": " << r.err;
    EXPECT_TRUE(r.out.empty()) << args;
  }
}

TEST_F(Cli, UnavailableBackendMessageIsExact) {
#if !SCANDYN_HAS_OPENMP
  const Result omp = run("bench --model chain:2 --algo id --instances 1 --backend openmp");
  EXPECT_EQ(omp.code, 2);
  EXPECT_EQ(omp.err, "scandyn: backend 'openmp' is not available in this build\n");
#endif
  const std::string why = cuda_backend_error();
  if (why.empty()) GTEST_SKIP() << "a CUDA device is usable: the cuda backend is available";
  const Result r = run("bench --model chain:2 --algo id --instances 1 --backend cuda");
  EXPECT_EQ(r.code, 2);
  EXPECT_EQ(r.err, "scandyn: " + why + "\n");
}

// ---- bench --------------------------------------------------------------------

std::vector<std::string> bench_row(const Result& r) {
  EXPECT_EQ(r.code, 0) << r.err;
  const std::vector<std::string> ls = lines(r.out);
  EXPECT_EQ(ls.size(), 1u) << r.out;  // stdout is not a terminal: no header
  return ls.empty() ? std::vector<std::string>() : split(ls[0], ',');
}

// One row of `bench --model iiwa.urdf --instances 3000 --backend cuda`: its columns, a
// rate that agrees with the time, and an error within max_err (nan fails).
void expect_cuda_iiwa_row(const std::string& line, const std::string& algo, const std::string& strategy,
                          const std::string& precision, double max_err) {
  const std::vector<std::string> row = split(line, ',');
  ASSERT_EQ(row.size(), 10u) << line;
  EXPECT_EQ(row[0], algo);
  EXPECT_EQ(row[1], strategy);
  EXPECT_EQ(row[2], "cuda");
  EXPECT_EQ(row[3], precision);
  EXPECT_EQ(row[4], "iiwa");
  EXPECT_EQ(row[5], "7");
  EXPECT_EQ(row[6], "3000");
  EXPECT_GT(std::stod(row[7]), 0);
  EXPECT_NEAR(std::stod(row[8]) * std::stod(row[7]), 3000.0, 3000.0 * 1e-5);  // both printed to 6 significant digits
  EXPECT_LE(std::stod(row[9]), max_err);
}

TEST_F(Cli, BenchPrintsOneRow) {
  const std::string base = "bench --model chain:5 --instances 7 --min-time 0.01";
  const std::vector<std::string> id = bench_row(run(base + " --algo id"));
  ASSERT_EQ(id.size(), 10u);
  // the strategy without the SIMD path's suffix (-simd<W>, when --simd auto takes it)
  const auto base_strategy = [](const std::string& st) { return st.substr(0, st.find("-simd")); };
  EXPECT_EQ(id[0], "id");
  EXPECT_EQ(base_strategy(id[1]), "recursion");
  EXPECT_EQ(id[2], "serial");
  EXPECT_EQ(id[3], "double");
  EXPECT_EQ(id[4], "chain:5");
  EXPECT_EQ(id[5], "5");
  EXPECT_EQ(id[6], "7");
  EXPECT_GT(std::stod(id[7]), 0);
  EXPECT_GT(std::stod(id[8]), 0);
  EXPECT_NEAR(std::stod(id[8]) * std::stod(id[7]), 7.0, 1e-3);  // instances / seconds_per_call
  EXPECT_EQ(id[9], "0");

  const std::vector<std::string> f = bench_row(run(base + " --algo id --precision float"));
  ASSERT_EQ(f.size(), 10u);
  EXPECT_EQ(f[3], "float");
  EXPECT_GT(std::stod(f[9]), 0);  // really computed in float
  EXPECT_LT(std::stod(f[9]), 1e-3);

  const std::vector<std::string> jsi = bench_row(run(base + " --algo fd --fd jsi"));
  ASSERT_EQ(jsi.size(), 10u);
  EXPECT_EQ(jsi[0], "fd");
  EXPECT_EQ(jsi[1], "jsi");
  EXPECT_LT(std::stod(jsi[9]), 1e-10);

  for (const char* algo : {"fd", "mass", "bias"}) {
    const std::vector<std::string> row = bench_row(run(base + " --algo " + algo));
    ASSERT_EQ(row.size(), 10u) << algo;
    const std::string scalar = std::string(algo) == "fd" ? "aba" : std::string(algo) == "mass" ? "crba" : "recursion";
    EXPECT_EQ(base_strategy(row[1]), scalar);
    EXPECT_EQ(row[9], "0") << algo;
    // --simd off: the scalar recursion; on: W instances per register (2 <= W <= 16 in every
    // build) for a batch that fills a group (37); none for fewer instances than W (1)
    const std::string batch = "bench --model chain:5 --instances 37 --min-time 0.01 --algo " + std::string(algo);
    EXPECT_EQ(bench_row(run(batch + " --simd off"))[1], scalar);
    EXPECT_EQ(bench_row(run(batch + " --simd on"))[1].rfind(scalar + "-simd", 0), 0u);
    const std::string one = "bench --model chain:5 --instances 1 --min-time 0.01 --algo " + std::string(algo);
    EXPECT_EQ(bench_row(run(one + " --simd on"))[1], scalar);
  }
}

// bench --algo fk / jac: one row on the CPU, the serial engine its own reference;
// --frames and --reference only with them.
TEST_F(Cli, BenchKinematicsPrintsOneRow) {
  const std::string base = "bench --model chain:5 --instances 9 --min-time 0.01";
  for (const char* algo : {"fk", "jac"}) {
    const std::vector<std::string> r = bench_row(run(base + " --algo " + algo + " --frames link_4,base"));
    ASSERT_EQ(r.size(), 10u) << algo;
    EXPECT_EQ(r[0], algo);
    EXPECT_EQ(r[1], "recursion");
    EXPECT_EQ(r[5], "5");
    EXPECT_EQ(r[6], "9");
    EXPECT_EQ(r[9], "0");
    const std::vector<std::string> f = bench_row(run(base + " --algo " + algo + " --precision float"));
    ASSERT_EQ(f.size(), 10u);
    EXPECT_GT(std::stod(f[9]), 0);
    EXPECT_LT(std::stod(f[9]), 1e-5);
  }
  const Result r = run(base + " --algo id --frames base");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("--frames applies only to --algo fk or jac"), std::string::npos) << r.err;
  EXPECT_EQ(run(base + " --algo fk --frames tool").code, 1);
}

TEST_F(Cli, BenchAppendsToCsvFile) {
  const std::string header =
      "algo,strategy,backend,precision,model,links,instances,seconds_per_call,evals_per_second,max_"
      "rel_err";
  const std::string args = "bench --model " + quote(scandyn::test::model_path("iiwa.urdf")) +
                           " --algo bias --instances 3 --min-time 0.001 --csv results.csv";
  const Result a = run(args);
  const Result b = run(args + " --precision float");
  ASSERT_EQ(a.code, 0) << a.err;
  ASSERT_EQ(b.code, 0) << b.err;
  const std::vector<std::string> ls = lines(read_text(path("results.csv")));
  ASSERT_EQ(ls.size(), 3u);
  EXPECT_EQ(ls[0], header);
  EXPECT_EQ(ls[1] + "\n", a.out);
  EXPECT_EQ(ls[2] + "\n", b.out);
  EXPECT_EQ(split(ls[1], ',')[4], "iiwa");
  EXPECT_EQ(split(ls[1], ',')[5], "7");

  // an existing file with another header is not appended to
  write_text(path("other.csv"), "a,b\n1,2\n");
  const Result c =
      run("bench --model chain:2 --algo id --instances 1 --min-time 0 --csv other.csv");
  EXPECT_EQ(c.code, 1);
  EXPECT_NE(c.err.find("other.csv: existing header does not match"), std::string::npos) << c.err;
  EXPECT_EQ(read_text(path("other.csv")), "a,b\n1,2\n");
}

// ---- --backend cuda ------------------------------------------------------------

// Without a usable device (or without CUDA in the build) every use of the backend is
// one line, exit 2, and leaves no file behind: neither eval's output (an existing
// one untouched) nor bench's --csv file.
TEST_F(Cli, CudaBackendWithoutDeviceFailsCleanly) {
  const std::string why = cuda_backend_error();
  if (why.empty()) GTEST_SKIP() << "a CUDA device is usable: the cuda backend runs here";
  write_text(path("states.csv"), good_states());
  for (const std::string& args :
       {kEval + "--backend cuda", kEval + "--backend cuda --algo id", kEval + "--backend cuda --algo bias --precision float",
        std::string("bench --model chain:3 --algo id --instances 100 --backend cuda --csv results.csv"),
        std::string("bench --model chain:3 --algo bias --instances 1 --backend cuda --precision float --csv results.csv"),
        kEval + "--backend cuda --algo fd",
        std::string("bench --model chain:3 --algo fd --instances 1 --backend cuda --csv results.csv"),
        std::string("bench --model chain:3 --algo fd --fd jsi --instances 1 --backend cuda --precision float"),
        std::string("bench --model chain:3 --algo fd --fd jsi --fallback aba --instances 1 --backend cuda"),
        kEval + "--backend cuda --algo fd --fd jsi --fallback aba",
        kEval + "--backend cuda --algo mass", kEval + "--backend cuda --algo bias,mass,id",
        std::string("bench --model chain:3 --algo mass --instances 1 --backend cuda --precision float --csv results.csv"),
        std::string("bench --model rope:70 --algo mass --instances 2 --backend cuda")}) {
    for (bool existing : {false, true}) {
      SCOPED_TRACE(args + (existing ? ", existing output" : ", no output"));
      fs::remove(path("out.csv"));
      if (existing) write_text(path("out.csv"), "sentinel\n");
      const std::vector<std::string> before = files();
      const Result r = run(args);
      EXPECT_EQ(r.code, 2);
      EXPECT_EQ(r.err, "scandyn: " + why + "\n");
      EXPECT_TRUE(r.out.empty()) << r.out;
      EXPECT_EQ(files(), before) << "no file created or removed (temporary files included)";
      if (existing) {
        EXPECT_EQ(read_text(path("out.csv")), "sentinel\n");
      }
    }
  }
}

// The tests below need a device: they skip, with the reason, without one.
#define SKIP_WITHOUT_CUDA_BACKEND()                                          \
  do {                                                                       \
    const std::string why_ = cuda_backend_error();                           \
    if (!why_.empty()) GTEST_SKIP() << "no CUDA backend here: " << why_;     \
  } while (0)

class EvalCuda : public Cli, public ::testing::WithParamInterface<const char*> {
 protected:
  std::string spec() const {
    const std::string p = GetParam();
    return p == "iiwa" || p == "hyq" ? scandyn::test::model_path(p + ".urdf") : p;
  }
  // Runs the eval command `base` (without --out) on the serial and the cuda backend:
  // both succeed, cuda with nothing on stderr. Their outputs, serial first.
  void eval_serial_and_cuda(const std::string& base, Table& serial, Table& cuda) const {
    const Result rs = run(base + " --out serial.csv");
    const Result rc = run(base + " --out cuda.csv --backend cuda");
    ASSERT_EQ(rs.code, 0) << rs.err;
    ASSERT_EQ(rc.code, 0) << rc.err;
    EXPECT_TRUE(rc.err.empty()) << rc.err;
    serial = parse_csv(read_text(path("serial.csv")));
    cuda = parse_csv(read_text(path("cuda.csv")));
  }
};

// fk and jac on cuda (the kinematics engine's staged compute(), both outputs
// interleaved into the same rows after the mass matrix's) give the serial CSV up to
// rounding: 1e-10 in double, 1e-4 in float; quaternions up to sign (q and -q).
TEST_P(EvalCuda, KinematicsMatchSerial) {
  SKIP_WITHOUT_CUDA_BACKEND();
  const Model model = scandyn::load_model(spec());
  if (model.nv() > 64) GTEST_SKIP() << "the CUDA kinematics engine takes up to 64 DoF";
  const States s(model.nv(), 5000, 32);
  write_text(path("states.csv"), s.csv({"q"}));
  for (const char* precision : {"double", "float"}) {
    SCOPED_TRACE(precision);
    const std::string base = "eval --model " + quote(spec()) + " --states states.csv --algo fk,mass,jac --precision " +
                             precision + " --reference local";
    Table ts, tc;
    ASSERT_NO_FATAL_FAILURE(eval_serial_and_cuda(base, ts, tc));
    ASSERT_EQ(tc.names, ts.names);
    ASSERT_EQ(tc.rows.size(), s.rows());
    const double tol = std::string(precision) == "float" ? 1e-4 : 1e-10;
    for (std::size_t row = 0; row < s.rows(); ++row) {
      std::vector<double>& c = tc.rows[row];
      const std::vector<double>& r = ts.rows[row];
      for (std::size_t j = 0; j + 3 < tc.names.size(); ++j) {  // qx, qy, qz, qw of each frame
        const std::string& n = tc.names[j];
        if (n.size() < 3 || n.compare(n.size() - 3, 3, "_qx") != 0) continue;
        if (c[j] * r[j] + c[j + 1] * r[j + 1] + c[j + 2] * r[j + 2] + c[j + 3] * r[j + 3] < 0)
          for (int e = 0; e < 4; ++e) c[j + e] = -c[j + e];
      }
      ASSERT_LE(scandyn::test::max_rel_err(c, r), tol) << "row " << row + 1;
    }
  }
}

// eval --backend cuda gives the serial backend's CSV up to rounding: the same
// header, one row per input row (5000 rows: two chunks), every value within 1e-10
// (double) or 1e-4 (float, against the serial float output) relative to
// max(1, max |row|) per output block, and in float each value a float.
TEST_P(EvalCuda, MatchesSerial) {
  SKIP_WITHOUT_CUDA_BACKEND();
  const Model model = scandyn::load_model(spec());
  const int n = model.nv();
  const States s(n, 5000, 31);
  write_text(path("states.csv"), s.csv({"q", "qd", "qdd", "tau"}));
  for (const char* precision : {"double", "float"}) {
    SCOPED_TRACE(precision);
    const bool is_float = std::string(precision) == "float";
    const std::string base = "eval --model " + quote(spec()) +
                             " --states states.csv --algo bias,id --precision " + precision;
    Table ts, tc;
    ASSERT_NO_FATAL_FAILURE(eval_serial_and_cuda(base, ts, tc));
    ASSERT_EQ(tc.names, ts.names);
    ASSERT_EQ(tc.rows.size(), s.rows());
    ASSERT_EQ(ts.rows.size(), s.rows());
    const double tol = is_float ? 1e-4 : 1e-10;
    double worst = 0;
    for (std::size_t row = 0; row < s.rows(); ++row) {
      for (const char* prefix : {"tau_id_", "h_"}) {
        const double e = scandyn::test::max_rel_err(tc.get(row, prefix, n), ts.get(row, prefix, n));
        if (!(e <= worst)) worst = e;
        ASSERT_LE(e, tol) << "row " << row + 1 << ", " << prefix;
      }
      if (is_float) {
        for (double v : tc.rows[row]) ASSERT_EQ(v, static_cast<double>(static_cast<float>(v)));
      }
    }
    EXPECT_FALSE(std::isnan(worst));
  }
}

// (the command line's chunks, columns and formatting; every model's engine against
// serial is tests/engine/test_engines.cpp's)
INSTANTIATE_TEST_SUITE_P(
    Models, EvalCuda, ::testing::Values("iiwa"),
    [](const ::testing::TestParamInfo<const char*>& info) {
      return std::string(info.param).substr(0, std::string(info.param).find(':'));
    });

// eval --algo fd --backend cuda (the joint-space inertia, one GPU thread per
// instance) against the serial backend's (ABA, in double): every value within 1e-9
// (double) or 1e-3 (float) relative to max(1, max |row|), 5000 rows (two chunks).
class EvalCudaFd : public EvalCuda {};

TEST_P(EvalCudaFd, MatchesSerial) {
  SKIP_WITHOUT_CUDA_BACKEND();
  const Model model = scandyn::load_model(spec());
  const int n = model.nv();
  const States s(n, 5000, 34);
  write_text(path("states.csv"), s.csv({"q", "qd", "tau"}));
  const std::string base = "eval --model " + quote(spec()) + " --states states.csv --algo fd";
  const Result rs = run(base + " --out serial.csv");
  ASSERT_EQ(rs.code, 0) << rs.err;
  const Table ts = parse_csv(read_text(path("serial.csv")));
  ASSERT_EQ(ts.rows.size(), s.rows());
  for (const char* precision : {"double", "float"}) {
    SCOPED_TRACE(precision);
    const bool is_float = std::string(precision) == "float";
    const Result rc = run(base + " --out cuda.csv --backend cuda --precision " + precision);
    ASSERT_EQ(rc.code, 0) << rc.err;
    EXPECT_TRUE(rc.err.empty()) << rc.err;
    const Table tc = parse_csv(read_text(path("cuda.csv")));
    ASSERT_EQ(tc.names, ts.names);
    ASSERT_EQ(tc.rows.size(), s.rows());
    const double tol = is_float ? 1e-3 : 1e-9;
    double worst = 0;
    for (std::size_t row = 0; row < s.rows(); ++row) {
      const double e = scandyn::test::max_rel_err(tc.get(row, "qdd_fd_", n), ts.get(row, "qdd_fd_", n));
      if (!(e <= worst)) worst = e;
      ASSERT_LE(e, tol) << "row " << row + 1;
    }
    EXPECT_FALSE(std::isnan(worst));
  }
}

INSTANTIATE_TEST_SUITE_P(Models, EvalCudaFd, ::testing::Values("iiwa"),
                         [](const ::testing::TestParamInfo<const char*>& info) { return std::string(info.param); });

// eval --algo mass --backend cuda (the CRBA: a GPU thread per row up to 64 DoF, a
// thread block per row beyond) against the serial backend's crba: the same header
// (M_<i>_<j>, row-major), every value within 1e-12 (double) or 1e-5 (float, against
// the serial float output) relative to max(1, max |row|), and in float each value a
// float. 5000 rows for the robots (two chunks), fewer for the long models (their
// chunks hold fewer rows: nv^2 values each).
class EvalCudaMass : public EvalCuda {};

TEST_P(EvalCudaMass, MatchesSerial) {
  SKIP_WITHOUT_CUDA_BACKEND();
  const Model model = scandyn::load_model(spec());
  const int n = model.nv();
  const States s(n, n <= 64 ? 5000 : 300, 35);
  write_text(path("states.csv"), s.csv({"q"}));
  for (const char* precision : {"double", "float"}) {
    SCOPED_TRACE(precision);
    const bool is_float = std::string(precision) == "float";
    const std::string base = "eval --model " + quote(spec()) + " --states states.csv --algo mass --precision " + precision;
    Table ts, tc;
    ASSERT_NO_FATAL_FAILURE(eval_serial_and_cuda(base, ts, tc));
    ASSERT_EQ(tc.names.size(), static_cast<std::size_t>(n * n));
    EXPECT_EQ(tc.names.front(), "M_0_0");
    EXPECT_EQ(tc.names[1], n > 1 ? "M_0_1" : "M_0_0");
    EXPECT_EQ(tc.rows.size(), s.rows());
    expect_tables_near(tc, ts, is_float ? 1e-5 : 1e-12);
    if (is_float) {
      for (const auto& row : tc.rows)
        for (double v : row) ASSERT_EQ(v, static_cast<double>(static_cast<float>(v)));
    }
  }
}

INSTANTIATE_TEST_SUITE_P(
    Models, EvalCudaMass, ::testing::Values("iiwa", "rope:65"),  // rope:65: chunks of nv^2 values
    [](const ::testing::TestParamInfo<const char*>& info) {
      std::string name = info.param;
      std::replace(name.begin(), name.end(), ':', '_');
      return name;
    });

// A failed factorisation on the device: the row and the joint-space inertia's pivot,
// as on the CPU backends, and no output.
TEST_F(Cli, EvalCudaReportsTheRowWhoseForwardDynamicsFails) {
  SKIP_WITHOUT_CUDA_BACKEND();
  write_text(path("heavy.urdf"), heavy_urdf());
  write_text(path("states.csv"), kHeavyStates);
  write_text(path("out.csv"), "sentinel\n");
  const Result r = run("eval --model heavy.urdf --states states.csv --out out.csv --algo fd --fd jsi --backend cuda");
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.err,
            "scandyn: states.csv: row 2 (line 3): forward dynamics failed: mass matrix "
            "pivot at DoF 0 is not positive\n");
  EXPECT_EQ(read_text(path("out.csv")), "sentinel\n");
}

// --fd jsi --fallback aba on the device: where nothing fails, the JSI's output and
// no warning; bench times it with the host copies only (jsi_thread+aba-host: the
// fallback must see which instances failed, which a device-resident row cannot);
// beyond 64 DoF (jsi_dense) it is refused. Which instances fall back, and that they
// get the ABA's qdd, is CudaStabilityJsiFallback's test.
TEST_F(Cli, CudaJsiFallbackToAba) {
  SKIP_WITHOUT_CUDA_BACKEND();
  write_text(path("states.csv"), States(10, 20, 33).csv({"q", "qd", "tau"}));
  const std::string base = "eval --model rope:10 --states states.csv --algo fd --fd jsi --backend cuda";
  ASSERT_EQ(run(base + " --out jsi.csv").code, 0);
  const Result r = run(base + " --out fallback.csv --fallback aba");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.err, "");
  EXPECT_EQ(read_text(path("fallback.csv")), read_text(path("jsi.csv")));

  const Result b = run("bench --model rope:10 --algo fd --fd jsi --fallback aba --backend cuda --instances 4 --min-time 0");
  ASSERT_EQ(b.code, 0) << b.err;
  const std::vector<std::string> row = bench_row(b);
  ASSERT_EQ(row.size(), 10u) << b.out;
  EXPECT_EQ(row[1], "jsi_thread+aba-host");

  // an instance that fails the ABA too: as on the CPU backends
  write_text(path("heavy.urdf"), heavy_urdf());
  write_text(path("heavy.csv"), kHeavyStates);
  const Result h = run("eval --model heavy.urdf --states heavy.csv --out heavy_out.csv --algo fd --fd jsi "
                       "--fallback aba --backend cuda");
  EXPECT_EQ(h.code, 1);
  EXPECT_EQ(h.err, kHeavyFallbackError);

  const Result big = run("bench --model rope:100 --algo fd --fd jsi --fallback aba --backend cuda --instances 1");
  EXPECT_EQ(big.code, 2);
  EXPECT_NE(big.err.find("needs the thread-per-instance joint-space inertia"), std::string::npos) << big.err;
}

TEST_F(Cli, EvalCudaDefaultsAndLimits) {
  SKIP_WITHOUT_CUDA_BACKEND();
  const States s(3, 10, 32);
  // without --algo: id and bias from q, qd, qdd, as on the serial backend
  write_text(path("states.csv"), s.csv({"q", "qd", "qdd"}));
  ASSERT_EQ(run("eval --model chain:3 --states states.csv --out serial.csv").code, 0);
  const Result r = run("eval --model chain:3 --states states.csv --out cuda.csv --backend cuda");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(parse_csv(read_text(path("cuda.csv"))).names, parse_csv(read_text(path("serial.csv"))).names);
  // ... and tau columns select fd too
  write_text(path("states.csv"), s.csv({"q", "qd", "qdd", "tau"}));
  ASSERT_EQ(run("eval --model chain:3 --states states.csv --out serial.csv").code, 0);
  const Result d = run("eval --model chain:3 --states states.csv --out cuda.csv --backend cuda");
  ASSERT_EQ(d.code, 0) << d.err;
  const Table dc = parse_csv(read_text(path("cuda.csv"))), ds = parse_csv(read_text(path("serial.csv")));
  EXPECT_EQ(dc.names, ds.names);
  EXPECT_NE(std::find(dc.names.begin(), dc.names.end(), "qdd_fd_0"), dc.names.end());
  EXPECT_EQ(dc.rows.size(), ds.rows.size());
  // beyond the thread-per-instance kernels' 64 DoF: the link scans, same numbers
  write_text(path("rope.csv"), States(65, 2, 33).csv({"q", "qd", "qdd"}));
  ASSERT_EQ(run("eval --model rope:65 --states rope.csv --out rope_serial.csv --algo id").code, 0);
  const Result big = run("eval --model rope:65 --states rope.csv --out rope_cuda.csv --backend cuda --algo id");
  ASSERT_EQ(big.code, 0) << big.err;
  expect_tables_near(parse_csv(read_text(path("rope_cuda.csv"))), parse_csv(read_text(path("rope_serial.csv"))), 1e-10);
  // ... unless the thread strategy is asked for; scan-world is not on this backend
  const Result rec = run("eval --model rope:65 --states rope.csv --out out.csv --backend cuda --algo id "
                         "--strategy recursion");
  EXPECT_EQ(rec.code, 2);
  EXPECT_NE(rec.err.find("scandyn: backend 'cuda': model 'rope:65' has 65 DoF"), std::string::npos) << rec.err;
  EXPECT_NE(rec.err.find("at most 64"), std::string::npos) << rec.err;
  // fd beyond 64 DoF (auto: the general path's ABA, aba_general), the serial ABA's numbers
  write_text(path("rope.csv"), States(65, 2, 33).csv({"q", "qd", "qdd", "tau"}));
  ASSERT_EQ(run("eval --model rope:65 --states rope.csv --out fd_serial.csv --algo fd").code, 0);
  const Result fd = run("eval --model rope:65 --states rope.csv --out fd_cuda.csv --backend cuda --algo fd");
  ASSERT_EQ(fd.code, 0) << fd.err;
  // double against the serial ABA on a 65-link rope (also what --fd jsi's tolerance would be)
  expect_tables_near(parse_csv(read_text(path("fd_cuda.csv"))), parse_csv(read_text(path("fd_serial.csv"))), 1e-6);
  const Result bench_fd = run("bench --model rope:65 --algo fd --fd jsi --instances 3 --backend cuda");
  EXPECT_EQ(bench_fd.code, 0) << bench_fd.err;
  EXPECT_NE(bench_fd.out.find("fd,jsi_dense-host,cuda"), std::string::npos) << bench_fd.out;
  // auto: a chain of 65-128 links goes to the general path's ABA, a longer one to the
  // link scans (choose_fd_method)
  const Result bench_auto = run("bench --model rope:65 --algo fd --instances 3 --backend cuda");
  EXPECT_EQ(bench_auto.code, 0) << bench_auto.err;
  EXPECT_NE(bench_auto.out.find("fd,aba_general-host,cuda"), std::string::npos) << bench_auto.out;
  const Result bench_long = run("bench --model rope:129 --algo fd --instances 3 --backend cuda");
  EXPECT_EQ(bench_long.code, 0) << bench_long.err;
  EXPECT_NE(bench_long.out.find("fd,parallel-host,cuda"), std::string::npos) << bench_long.out;
  for (const char* method : {"parallel", "hybrid"}) {
    const Result r = run(std::string("eval --model rope:65 --states rope.csv --out fd_") + method +
                         ".csv --backend cuda --algo fd --fd " + method);
    ASSERT_EQ(r.code, 0) << r.err;
    expect_tables_near(parse_csv(read_text(path(std::string("fd_") + method + ".csv"))),
                       parse_csv(read_text(path("fd_serial.csv"))), 1e-9);
  }
  const Result aba65 = run("bench --model rope:65 --algo fd --fd aba --instances 3 --backend cuda");
  EXPECT_EQ(aba65.code, 0) << aba65.err;
  EXPECT_NE(aba65.out.find("fd,aba_general-host,cuda"), std::string::npos) << aba65.out;
  const Result scan = run("eval --model chain:3 --states states.csv --out out.csv --backend cuda --algo id "
                          "--strategy scan-world");
  EXPECT_EQ(scan.code, 2);
  EXPECT_NE(scan.err.find("strategy 'scan-world' is not available on this backend"), std::string::npos) << scan.err;
  EXPECT_EQ(std::count(scan.err.begin(), scan.err.end(), '\n'), 1);
  EXPECT_FALSE(fs::exists(path("out.csv")));
}

// bench --backend cuda: two rows, the device-resident batch (thread; crba_thread
// for mass) and the host-staged call (thread-host; crba_thread-host), both with
// their measured error.
TEST_F(Cli, BenchCudaKinematicsPrintsResidentAndHostRows) {
  SKIP_WITHOUT_CUDA_BACKEND();
  const std::string iiwa = quote(scandyn::test::model_path("iiwa.urdf"));
  for (const char* algo : {"fk", "jac"})
    for (const char* precision : {"double", "float"}) {
      SCOPED_TRACE(std::string(algo) + " " + precision);
      const Result r = run("bench --model " + iiwa + " --algo " + algo + " --instances 3000 --min-time 0.02" +
                           " --backend cuda --precision " + precision);
      ASSERT_EQ(r.code, 0) << r.err;
      const std::vector<std::string> ls = lines(r.out);
      ASSERT_EQ(ls.size(), 2u) << r.out;
      for (std::size_t k = 0; k < 2; ++k)
        expect_cuda_iiwa_row(ls[k], algo, k == 0 ? "thread" : "thread-host", precision,
                             std::string(precision) == "float" ? 1e-4 : 1e-10);
    }
}

TEST_F(Cli, BenchCudaPrintsResidentAndHostRows) {
  SKIP_WITHOUT_CUDA_BACKEND();
  const std::string iiwa = quote(scandyn::test::model_path("iiwa.urdf"));
  for (const char* algo : {"id", "bias", "mass"}) {
    const std::string engine = std::string(algo) == "mass" ? "crba_thread" : "thread";
    for (const char* precision : {"double", "float"}) {
      SCOPED_TRACE(std::string(algo) + " " + precision);
      const Result r = run("bench --model " + iiwa + " --algo " + algo + " --instances 3000 --min-time 0.02" +
                           " --backend cuda --csv results.csv --precision " + precision);
      ASSERT_EQ(r.code, 0) << r.err;
      EXPECT_TRUE(r.err.empty()) << r.err;
      const std::vector<std::string> ls = lines(r.out);
      ASSERT_EQ(ls.size(), 2u) << r.out;
      for (std::size_t k = 0; k < 2; ++k) {
        expect_cuda_iiwa_row(ls[k], algo, k == 0 ? engine : engine + "-host", precision,
                             std::string(precision) == "float" ? 1e-4 : 1e-10);
      }
    }
  }
  const std::vector<std::string> csv = lines(read_text(path("results.csv")));
  ASSERT_EQ(csv.size(), 13u);  // header and 6 x 2 rows
  EXPECT_EQ(csv[0].rfind("algo,strategy,backend", 0), 0u);
  // a batch of one, and a single timed pass
  const Result one = run("bench --model chain:2 --algo id --instances 1 --min-time 0 --backend cuda");
  ASSERT_EQ(one.code, 0) << one.err;
  EXPECT_EQ(lines(one.out).size(), 2u);
  // the mass matrix beyond 64 DoF: a thread block per instance, both rows, double
  const Result big = run("bench --model rope:70 --algo mass --instances 5 --min-time 0 --backend cuda");
  ASSERT_EQ(big.code, 0) << big.err;
  const std::vector<std::string> ls = lines(big.out);
  ASSERT_EQ(ls.size(), 2u) << big.out;
  for (std::size_t k = 0; k < 2; ++k) {
    const std::vector<std::string> row = split(ls[k], ',');
    ASSERT_EQ(row.size(), 10u) << ls[k];
    EXPECT_EQ(row[1], k == 0 ? "crba_block" : "crba_block-host");
    EXPECT_EQ(row[5], "70");
    EXPECT_LE(std::stod(row[9]), 1e-12);  // nan fails
  }
}

// bench --algo fd --backend cuda: two rows, the device-resident batch (the engine's
// strategy: aba_thread without --fd, jsi_thread with --fd jsi, parallel with --fd
// parallel) and the host-staged call (the same with -host), each with its error
// against the serial ABA; --fd hybrid (articulated inertias on the host) has the
// host row only.
TEST_F(Cli, BenchCudaFdPrintsResidentAndHostRows) {
  SKIP_WITHOUT_CUDA_BACKEND();
  const std::string iiwa = quote(scandyn::test::model_path("iiwa.urdf"));
  std::size_t printed = 0;
  for (const char* fd : {"", "jsi", "parallel", "hybrid"}) {
    const std::string method = fd;
    const std::string engine = method.empty() ? "aba_thread" : method == "jsi" ? "jsi_thread" : method;
    const bool hybrid = method == "hybrid";
    for (const char* precision : {"double", "float"}) {
      SCOPED_TRACE(method + " " + precision);
      const Result r = run("bench --model " + iiwa + " --algo fd" + (method.empty() ? "" : " --fd " + method) +
                           " --instances 3000 --min-time 0.02 --backend cuda --csv results.csv --precision " +
                           precision);
      ASSERT_EQ(r.code, 0) << r.err;
      EXPECT_TRUE(r.err.empty()) << r.err;
      const std::vector<std::string> ls = lines(r.out);
      ASSERT_EQ(ls.size(), hybrid ? 1u : 2u) << r.out;
      printed += ls.size();
      for (std::size_t k = 0; k < ls.size(); ++k) {
        expect_cuda_iiwa_row(ls[k], "fd", k + 1 == ls.size() ? engine + "-host" : engine,  // auto: ABA
                             precision, std::string(precision) == "float" ? 1e-3 : 1e-9);
      }
    }
  }
  ASSERT_EQ(lines(read_text(path("results.csv"))).size(), 1 + printed);  // header and every row
}

// A forward dynamics that fails in bench --backend cuda is reported as on the serial
// backend (the host row's report): the instance and the pivot of the method, exit 1,
// no row printed and no --csv file, also from the device-resident batch, which runs
// first. heavy.urdf in float: the 1e300 kg links' inertias are inf, every pivot fails.
TEST_F(Cli, BenchCudaFdReportsFailuresLikeTheHostRow) {
  SKIP_WITHOUT_CUDA_BACKEND();
  write_text(path("heavy.urdf"), heavy_urdf());
  for (const char* fd : {"jsi", "aba"}) {
    SCOPED_TRACE(fd);
    const std::string args =
        std::string("bench --model heavy.urdf --algo fd --fd ") + fd + " --instances 50 --precision float --min-time 0";
    const Result serial = run(args);
    ASSERT_EQ(serial.code, 1) << serial.err;
    EXPECT_NE(serial.err.find("bench: instance 0: forward dynamics failed: "), std::string::npos) << serial.err;
    const Result r = run(args + " --backend cuda --csv results.csv");
    EXPECT_EQ(r.code, 1);
    EXPECT_EQ(r.err, serial.err);
    EXPECT_TRUE(r.out.empty()) << r.out;
    EXPECT_FALSE(fs::exists(path("results.csv")));
  }
}

// ---- rollout and bench --algo step (docs/cli.md) --------------------------------------

const char* const kChainScene = R"({"model": "chain:3", "dt": 0.001, "instances": 2, "integrator": "rk4",
  "effects": {"gravity": true, "damping": 0.1}, "initial": {"random": {"seed": 4, "q": 0.3, "qd": 0.2}}})";

// The rollout's numbers equal the Simulator's, step by step.
TEST_F(Cli, RolloutCsvMatchesTheSimulator) {
  write_text(path("s.json"), kChainScene);
  const Result r = run("rollout --scene s.json --steps 7 --every 3 --out traj.csv");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.err, "");  // no progress bar: stderr is not a terminal
  const std::vector<std::string> rows = lines(read_text(path("traj.csv")));
  ASSERT_EQ(rows.size(), 1u + 4 * 2);  // steps 0, 3, 6, 7; two instances each
  EXPECT_EQ(rows[0], "step,time,instance,q_0,q_1,q_2,qd_0,qd_1,qd_2");
  scandyn::sim::Simulator<double> sim(scandyn::sim::load_scene(path("s.json").string()));
  int step = 0;
  for (int rec : {0, 3, 6, 7}) {
    while (step < rec) sim.step(), ++step;
    for (int b = 0; b < 2; ++b) {
      const std::vector<std::string> f = split(rows[1 + (rec == 0 ? 0 : rec == 3 ? 1 : rec == 6 ? 2 : 3) * 2 + b], ',');
      ASSERT_EQ(f.size(), 9u);
      EXPECT_EQ(std::stoi(f[0]), rec);
      EXPECT_DOUBLE_EQ(std::stod(f[1]), rec * 0.001);
      EXPECT_EQ(std::stoi(f[2]), b);
      for (int i = 0; i < 3; ++i) {
        EXPECT_EQ(std::stod(f[3 + i]), sim.q().at(i, b));  // 17 digits: the same double
        EXPECT_EQ(std::stod(f[6 + i]), sim.qd().at(i, b));
      }
    }
  }
}

// --contacts: four columns per contact point after qd, the Simulator's readings of
// the step that ended at the record (zeros at step 0); on a scene without contacts
// it is a usage error (exit 2).
TEST_F(Cli, RolloutContactsWritesTheContactForces) {
  write_text(path("c.json"), R"({"model": "chain:3", "dt": 0.001, "instances": 2, "integrator": "euler",
    "effects": {"gravity": true, "contacts": {"planes": [{"normal": [0, 0, 1], "offset": 0.25}],
      "all_links": {"radius": 0.01}, "stiffness": 1e4, "damping": 10, "friction": 0.5}},
    "initial": {"random": {"seed": 4, "q": 0.3, "qd": 0.2}}})");
  const Result r = run("rollout --scene c.json --steps 3 --out traj.csv --contacts");
  ASSERT_EQ(r.code, 0) << r.err;
  const std::vector<std::string> rows = lines(read_text(path("traj.csv")));
  ASSERT_EQ(rows.size(), 1u + 4 * 2);
  EXPECT_EQ(rows[0], "step,time,instance,q_0,q_1,q_2,qd_0,qd_1,qd_2,cf_0_x,cf_0_y,cf_0_z,contact_0,cf_1_x,cf_1_y,"
                     "cf_1_z,contact_1,cf_2_x,cf_2_y,cf_2_z,contact_2");
  scandyn::sim::Simulator<double> sim(scandyn::sim::load_scene(path("c.json").string()));
  for (int step = 0; step <= 3; ++step) {
    if (step > 0) sim.step();
    std::vector<scandyn::sim::ContactReading<double>> c(2 * 3);
    sim.read_contact_forces(c.data());
    for (int b = 0; b < 2; ++b) {
      const std::vector<std::string> f = split(rows[1 + step * 2 + b], ',');
      ASSERT_EQ(f.size(), 21u);
      for (int k = 0; k < 3; ++k) {
        const auto& x = c[static_cast<std::size_t>(b * 3 + k)];
        EXPECT_EQ(std::stod(f[9 + 4 * k]), x.force.x);
        EXPECT_EQ(std::stod(f[11 + 4 * k]), x.force.z);
        EXPECT_EQ(std::stoi(f[12 + 4 * k]), x.in_contact);
      }
    }
  }
  EXPECT_EQ(split(rows[3], ',')[12], "1");  // step 1: the first link's origin is below the plane, pushed
  write_text(path("s.json"), kChainScene);
  const Result none = run("rollout --scene s.json --steps 3 --out t2.csv --contacts");
  EXPECT_EQ(none.code, 2);
  EXPECT_NE(none.err.find("--contacts: the scene s.json declares no effects.contacts"), std::string::npos) << none.err;
}

// The .npy file: the version 1.0 header numpy writes (checked byte by byte here, as
// the machine running the tests may have no numpy), then the array.
TEST_F(Cli, RolloutNpyHasTheDocumentedHeaderAndData) {
  write_text(path("s.json"), kChainScene);
  ASSERT_EQ(run("rollout --scene s.json --steps 4 --every 2 --out traj.npy").code, 0);
  ASSERT_EQ(run("rollout --scene s.json --steps 4 --every 2 --out traj.csv").code, 0);
  const std::string npy = read_text(path("traj.npy"));
  ASSERT_GT(npy.size(), 10u);
  EXPECT_EQ(npy.substr(0, 8), std::string("\x93NUMPY\x01\x00", 8));
  const std::size_t hlen = static_cast<unsigned char>(npy[8]) | (static_cast<unsigned char>(npy[9]) << 8);
  EXPECT_EQ((10 + hlen) % 64, 0u);
  const std::string header = npy.substr(10, hlen);
  EXPECT_EQ(header.substr(0, header.find(" }") + 2), "{'descr': '<f8', 'fortran_order': False, 'shape': (3, 2, 7), }");
  EXPECT_EQ(header.back(), '\n');
  ASSERT_EQ(npy.size(), 10 + hlen + 3 * 2 * 7 * sizeof(double));
  std::vector<double> data(3 * 2 * 7);
  std::memcpy(data.data(), npy.data() + 10 + hlen, data.size() * sizeof(double));
  const std::vector<std::string> rows = lines(read_text(path("traj.csv")));
  ASSERT_EQ(rows.size(), 1u + 6);
  for (int r = 0; r < 6; ++r) {  // record r / 2, instance r % 2
    const std::vector<std::string> f = split(rows[1 + r], ',');
    for (int k = 0; k < 7; ++k) EXPECT_EQ(data[r * 7 + k], std::stod(f[1 + (k == 0 ? 0 : k + 1)])) << r << " " << k;
  }
}

// A trajectory of more than 2 GiB is announced before the first step (here the
// simulator is then refused for its memory: 10^9 instances of chain:64); a small
// one is not.
TEST_F(Cli, RolloutAnnouncesALargeOutput) {
  write_text(path("s.json"), R"({"model":"chain:64","dt":0.001,"instances":1000000000,"backend":"serial"})");
  const Result r = run("rollout --scene s.json --steps 1 --out -");  // (stdout: no disk check)
  EXPECT_EQ(r.code, 1) << r.err;
  EXPECT_EQ(r.err.rfind("scandyn: -: the trajectory of 2 records x 1000000000 instances x 129 values takes about ", 0),
            0u)
      << r.err;
  EXPECT_NE(r.err.find(" TiB (--every records fewer steps)\nscandyn: a simulator of 1000000000 instances"),
            std::string::npos)
      << r.err;
  write_text(path("small.json"), R"({"model":"chain:2","dt":0.001,"instances":3})");
  const Result small = run("rollout --scene small.json --steps 2 --out t.npy --backend serial");
  EXPECT_EQ(small.code, 0) << small.err;
  EXPECT_EQ(small.err.find("takes about"), std::string::npos) << small.err;
}

TEST_F(Cli, RolloutErrorsWriteNothing) {
  write_text(path("bad.json"), R"({"model": "chain:3", "dt": -1})");
  Result r = run("rollout --scene bad.json --steps 3 --out t.csv");
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.err, "scandyn: bad.json: dt: expected a positive number, got -1\n");
  r = run("rollout --scene missing.json --steps 3 --out t.csv");
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.err, "scandyn: missing.json: cannot open file: No such file or directory\n");
  write_text(path("s.json"), kChainScene);
  r = run("rollout --scene s.json --steps 3 --out t.txt");
  EXPECT_EQ(r.code, 2);
  r = run("rollout --scene s.json --steps -3 --out t.csv");
  EXPECT_EQ(r.code, 2);
  r = run("rollout --scene s.json --steps 3 --out t.csv --backend tpu");
  EXPECT_EQ(r.code, 2);
  if (!cuda_backend_error().empty()) {
    r = run("rollout --scene s.json --steps 3 --out t.csv --backend cuda");
    EXPECT_EQ(r.code, 2);
    EXPECT_NE(r.err.find("backend 'cuda'"), std::string::npos) << r.err;
  }
  // a forward dynamics that fails (here: the state overflows to inf, then NaN, and
  // the mass matrix's pivot is no longer finite) is exit 1 and no file
  write_text(path("nan.json"), R"({"model": "chain:3", "dt": 0.001, "initial": {"q": [0, 1e308, 0], "qd": [1e308, 1e308, 1e308]}})");
  r = run("rollout --scene nan.json --steps 50 --out t.csv");
  EXPECT_EQ(r.code, 1) << r.err;
  EXPECT_NE(r.err.find("nan.json: step "), std::string::npos) << r.err;
  std::vector<std::string> f = files();
  f.erase(std::remove_if(f.begin(), f.end(), [](const std::string& n) { return n.find(".json") != std::string::npos; }),
          f.end());
  EXPECT_TRUE(f.empty()) << f[0];
}

// A scene's "backend": "auto" is said in one line on stderr by rollout and bench
// --algo step (cuda where a device is usable, else openmp); --backend overrides it,
// silently.
TEST_F(Cli, RolloutAndBenchStepSayTheAutoBackend) {
  std::string json = kChainScene;
  json.insert(1, R"("backend": "auto", )");
  write_text(path("auto.json"), json);
  const scandyn::sim::Scene scene = scandyn::sim::load_scene(path("auto.json").string());
  ASSERT_TRUE(scene.backend_auto);
  const std::string said = "scandyn: " + scandyn::sim::backend_choice(scene) + "\n";
  EXPECT_EQ(said.rfind(std::string("scandyn: scene backend auto: ") + to_string(scene.backend), 0), 0u) << said;
#if !SCANDYN_HAS_CUDA && SCANDYN_HAS_OPENMP
  EXPECT_EQ(said, "scandyn: scene backend auto: openmp (cuda: backend 'cuda' is not available in this build)\n");
#endif
  Result r = run("rollout --scene auto.json --steps 3 --out traj.csv");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.err, said);
  r = run("rollout --scene auto.json --steps 3 --out traj.csv --backend serial");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.err, "");
  r = run("bench --algo step --scene auto.json --min-time 0.01");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.err, said);
  const std::vector<std::string> row = bench_row(r);
  ASSERT_EQ(row.size(), 10u);
  EXPECT_EQ(row[2], to_string(scene.backend));
  r = run("bench --algo step --scene auto.json --min-time 0.01 --backend serial");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.err, "");
  EXPECT_EQ(bench_row(r)[2], "serial");
}

TEST_F(Cli, BenchStepPrintsOneRow) {
  write_text(path("s.json"), kChainScene);
  const std::vector<std::string> row = bench_row(run("bench --algo step --scene s.json --instances 5 --min-time 0.01"));
  ASSERT_EQ(row.size(), 10u);
  EXPECT_EQ(row[0], "step");
  EXPECT_EQ(row[1], "serial-aba:rk4:gravity+damping");
  EXPECT_EQ(row[2], "serial");
  EXPECT_EQ(row[3], "double");
  EXPECT_EQ(row[4], "chain:3");
  EXPECT_EQ(row[5], "3");
  EXPECT_EQ(row[6], "5");
  EXPECT_NEAR(std::stod(row[8]) * std::stod(row[7]), 5.0, 1e-3);
  EXPECT_EQ(row[9], "0");  // the serial double simulator is the reference
  const std::vector<std::string> f =
      bench_row(run("bench --algo step --scene s.json --instances 5 --min-time 0.01 --precision float --backend openmp"));
  ASSERT_EQ(f.size(), 10u);
  EXPECT_EQ(f[3], "float");
  EXPECT_GT(std::stod(f[9]), 0);
  EXPECT_LT(std::stod(f[9]), 1e-4);
  EXPECT_EQ(run("bench --algo step --model chain:3 --scene s.json").code, 2);
  EXPECT_EQ(run("bench --algo id --model chain:3 --instances 2 --scene s.json").code, 2);
}

}  // namespace

namespace {

// --fd on the CPU backends: parallel (link scans) agrees with aba on a rope; hybrid
// is cuda's only; parallel refuses a tree naming the body; auto picks aba here.
TEST_F(Cli, FdMethodsOnTheCpu) {
  write_text(path("rope.csv"), States(300, 3, 5).csv({"q", "qd", "tau"}));
  ASSERT_EQ(run("eval --model rope:300 --states rope.csv --out aba.csv --algo fd --fd aba").code, 0);
  for (const char* backend : {"serial", "openmp"}) {
    SCOPED_TRACE(backend);
    const Result r = run(std::string("eval --model rope:300 --states rope.csv --out par.csv --algo fd --fd parallel "
                                     "--backend ") + backend);
    ASSERT_EQ(r.code, 0) << r.err;
    expect_tables_near(parse_csv(read_text(path("par.csv"))), parse_csv(read_text(path("aba.csv"))), 1e-10);
    const Result h = run(std::string("eval --model rope:300 --states rope.csv --out h.csv --algo fd --fd hybrid "
                                     "--backend ") + backend);
    EXPECT_EQ(h.code, 2);
    EXPECT_NE(h.err.find("--fd hybrid: hybrid runs on the cuda backend only"), std::string::npos) << h.err;
    EXPECT_FALSE(fs::exists(path("h.csv")));
  }
  const Result tree = run("bench --model tree:20:3 --algo fd --fd parallel --instances 2");
  EXPECT_EQ(tree.code, 2);
  EXPECT_NE(tree.err.find("needs unbranched chains hanging from the base"), std::string::npos) << tree.err;
  const Result bad = run("bench --model rope:5 --algo fd --fd fast --instances 2");
  EXPECT_EQ(bad.code, 2);
  EXPECT_NE(bad.err.find("--fd: unknown forward-dynamics method 'fast' (expected auto, aba, jsi, hybrid or parallel)"), std::string::npos)
      << bad.err;
  const std::vector<std::string> row = bench_row(run("bench --model rope:300 --algo fd --fd parallel --instances 2 "
                                                     "--min-time 0.01"));
  ASSERT_EQ(row.size(), 10u);
  EXPECT_EQ(row[1], "parallel");
  EXPECT_LT(std::stod(row[9]), 1e-10);
}

// --fd jsi --fallback aba: float JSI fails its factorisation on rope:1000 (the
// mass matrix is not numerically positive definite in float); with the fallback
// every row is computed by aba (the same numbers as --fd aba) and one warning
// line counts them.
TEST_F(Cli, JsiFallbackToAbaOnTheCpu) {
  write_text(path("rope.csv"), States(1000, 2, 11).csv({"q", "qd", "tau"}));
  const std::string base = "eval --model rope:1000 --states rope.csv --algo fd --precision float";
  const Result fail = run(base + " --out jsi.csv --fd jsi");
  EXPECT_EQ(fail.code, 1);
  EXPECT_NE(fail.err.find("forward dynamics failed: mass matrix pivot at DoF"), std::string::npos) << fail.err;
  ASSERT_EQ(run(base + " --out aba.csv --fd aba").code, 0);
  for (const char* backend : {"serial", "openmp"}) {
    SCOPED_TRACE(backend);
    const Result r = run(base + " --out jsi.csv --fd jsi --fallback aba --backend " + backend);
    ASSERT_EQ(r.code, 0) << r.err;
    EXPECT_EQ(r.err,
              "scandyn: warning: forward dynamics by jsi failed on 2 of 2 rows (mass matrix pivot not positive); "
              "they were computed by aba (--fallback aba)\n");
    EXPECT_EQ(read_text(path("jsi.csv")), read_text(path("aba.csv")));
  }
  // where JSI succeeds nothing falls back and nothing is printed
  write_text(path("short.csv"), States(10, 2, 11).csv({"q", "qd", "tau"}));
  const Result ok = run("eval --model rope:10 --states short.csv --out s.csv --algo fd --fd jsi --fallback aba");
  EXPECT_EQ(ok.code, 0);
  EXPECT_EQ(ok.err, "");

  const Result bench = run("bench --model rope:1000 --algo fd --fd jsi --fallback aba --precision float "
                           "--instances 1 --min-time 0");
  const std::vector<std::string> row = bench_row(bench);
  ASSERT_EQ(row.size(), 10u);
  EXPECT_EQ(row[1], "jsi+aba+check");  // bench checks jsi from 200 DoF (--fd-check auto)
  EXPECT_LT(std::stod(row[9]), 1e-5);  // float aba
  EXPECT_NE(bench.err.find("failed on 1 of 1 instances"), std::string::npos) << bench.err;

  // an instance that fails the ABA too stays an error, and the message says both failed
  write_text(path("heavy.urdf"), heavy_urdf());
  write_text(path("heavy.csv"), kHeavyStates);
  for (const char* backend : {"serial", "openmp"}) {
    const Result r = run(std::string("eval --model heavy.urdf --states heavy.csv --out heavy_out.csv --algo fd --fd jsi "
                                     "--fallback aba --backend ") + backend);
    EXPECT_EQ(r.code, 1) << backend;
    EXPECT_EQ(r.err, kHeavyFallbackError) << backend;
    EXPECT_FALSE(fs::exists(path("heavy_out.csv"))) << backend;
  }

  for (const char* args : {"bench --model rope:5 --algo fd --fd aba --fallback aba --instances 1",
                           "bench --model rope:5 --algo fd --fallback aba --instances 1",
                           "bench --model rope:5 --algo fd --fd jsi --fallback none --instances 1"}) {
    const Result r = run(args);
    EXPECT_EQ(r.code, 2) << args;
  }
}

}  // namespace
