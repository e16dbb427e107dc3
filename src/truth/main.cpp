// src/truth/main.cpp: `scandyn-truth`, the high-precision truth of a states file
// and the error of a result against it (scripts/accuracy_report calls it).
//
//   scandyn-truth states --model M --rows R --out IN.csv [--seed 42]
//   scandyn-truth eval   --model M --states IN.csv --out TRUTH.csv [--algo id,fd,mass,bias]
//                        [--precision float128|longdouble]
//   scandyn-truth error  --truth TRUTH.csv --result OUT.csv [--result-precision double|longdouble|float128]
//   scandyn-truth check  --model M --states IN.csv --result OUT.csv [--precision float|double]
//                        [--threshold X] [--truth TRUTH.csv]
//   (states, eval and check also take --allow-nonphysical-inertia, and --floating-base:
//   the model on a free joint at its root, as `scandyn --floating-base`)
//
// Models with a floating base or spherical joints: q has nq columns q_0..q_{nq-1}
// (each quaternion x, y, z, w; scandyn/model/model.hpp), the other families nv.
//
// states: R random states drawn as `scandyn bench --instances R` draws them
//   (std::mt19937_64(seed), uniform in [-1, 1]; q, then qd, then the third family,
//   each R x nv in that order), written with columns q_<i>, qd_<i>, qdd_<i>, tau_<i>
//   (qdd and tau both the third family, as bench uses it for id and for fd), 17
//   significant digits (every double exactly). Row 0 of --rows 1 is the state of
//   `scandyn bench --instances 1`.
// eval: `scandyn eval`'s columns (tau_id_<i>, qdd_fd_<i>, M_<i>_<j>, h_<i>) computed
//   by the serial reference in binary128 (36 significant digits) or long double
//   (21 digits), forward dynamics by ABA; the model converted from double exactly.
// error: for each output family present in both files, `family,rows,max_rel_err`:
//   the largest over rows of max_i |x_i - t_i| / max(1, max_i |t_i|), the
//   differences taken in binary128. The result's values are read as doubles (what
//   `scandyn eval` writes, 17 digits, exactly) unless --result-precision says wider.
// check: the forward-dynamics check (scandyn/algorithm/fd_check.hpp) of the
//   result's qdd_fd columns, in double, on the inputs the engine saw (q, qd, tau
//   rounded to --precision, the result's): one line
//   `rows,flagged,threshold,max_error_estimate,max_relative_residual`, flagged =
//   rows whose error_estimate exceeds --threshold (default fd_check_threshold of
//   the precision: float 1e-4, double 1e-10). With --truth TRUTH.csv (eval's output on
//   the same states) also each row's true error (as `error` measures it): the line
//   gains `budget,bad,caught,false_positives,missed,max_error`, bad = rows whose error
//   exceeds the precision's budget (float 1e-4, double 1e-10), caught = bad and
//   flagged, false_positives = flagged and not bad, missed = bad and not flagged.
//   Models with multi-DoF joints are checked as the engines check them
//   (FdBatchCheck: the residual's scale without joint loads).
//
// Exit status: 0 success, 1 bad data (file, model, failed computation), 2 bad command line.
#include <algorithm>
#include <cmath>
#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <map>
#include <memory>
#include <random>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "scandyn/algorithm/fd_check.hpp"
#include "scandyn/algorithm/fd_check_batch.hpp"
#include "scandyn/io/states.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/truth/truth.hpp"

using namespace scandyn;

namespace {

struct UsageError : std::runtime_error {
  using std::runtime_error::runtime_error;
};
struct DataError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

const char* kUsage =
    "usage: scandyn-truth states --model M --rows R --out IN.csv [--seed 42]\n"
    "       scandyn-truth eval --model M --states IN.csv --out TRUTH.csv [--algo id,fd,mass,bias]\n"
    "                          [--precision float128|longdouble]\n"
    "       scandyn-truth error --truth TRUTH.csv --result OUT.csv\n"
    "                          [--result-precision double|longdouble|float128]\n"
    "       scandyn-truth check --model M --states IN.csv --result OUT.csv [--precision float|double]\n"
    "                          [--threshold X] [--truth TRUTH.csv]\n"
    "       (states, eval and check also take --allow-nonphysical-inertia and --floating-base)\n";

// --name value pairs after the subcommand; flags without a value: --allow-nonphysical-inertia,
// --floating-base.
struct Args {
  std::map<std::string, std::string> values;
  bool has(const std::string& k) const { return values.count(k) != 0; }
  const std::string& required(const std::string& k) const {
    auto it = values.find(k);
    if (it == values.end()) throw UsageError("missing --" + k);
    return it->second;
  }
  std::string get(const std::string& k, const std::string& d) const { return has(k) ? values.at(k) : d; }
};

Args parse_args(int argc, char** argv, const std::vector<std::string>& known) {
  Args a;
  for (int i = 2; i < argc; ++i) {
    std::string k = argv[i];
    if (k.rfind("--", 0) != 0) throw UsageError("unexpected argument '" + k + "'");
    k = k.substr(2);
    if (std::find(known.begin(), known.end(), k) == known.end()) throw UsageError("unknown flag --" + k);
    if (k == "allow-nonphysical-inertia" || k == "floating-base") {
      a.values[k] = "1";
      continue;
    }
    if (i + 1 >= argc) throw UsageError("--" + k + " needs a value");
    a.values[k] = argv[++i];
  }
  return a;
}

Model load(const Args& a) {
  BuildOptions o;
  o.require_physical_inertia = !a.has("allow-nonphysical-inertia");
  o.floating_base = a.has("floating-base");
  try {
    return load_model(a.required("model"), o);
  } catch (const std::exception& e) {
    throw DataError(e.what());
  }
}

// ---- CSV ---------------------------------------------------------------------

struct Csv {
  std::string path;
  std::vector<std::string> names;
  std::map<std::string, int> index;            // name -> column
  std::vector<std::vector<std::string>> rows;  // fields as text
  int column(const std::string& name) const {
    auto it = index.find(name);
    return it == index.end() ? -1 : it->second;
  }
};

std::vector<std::string> split(const std::string& line) {
  std::vector<std::string> out;
  std::string cur;
  std::istringstream s(line);
  while (std::getline(s, cur, ',')) out.push_back(cur);
  if (!line.empty() && line.back() == ',') out.emplace_back();
  return out;
}

Csv read_csv(const std::string& path) {
  std::ifstream f(path);
  if (!f) throw DataError(path + ": cannot open");
  Csv c;
  c.path = path;
  std::string line;
  if (!std::getline(f, line)) throw DataError(path + ": empty file");
  if (!line.empty() && line.back() == '\r') line.pop_back();
  c.names = split(line);
  for (std::size_t k = 0; k < c.names.size(); ++k) c.index.emplace(c.names[k], static_cast<int>(k));
  while (std::getline(f, line)) {
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line.empty()) continue;
    c.rows.push_back(split(line));
    if (c.rows.back().size() != c.names.size())
      throw DataError(path + ": row " + std::to_string(c.rows.size() - 1) + ": expected " +
                      std::to_string(c.names.size()) + " fields, found " + std::to_string(c.rows.back().size()));
  }
  return c;
}

double parse_double(const std::string& s, const std::string& where) {
  char* end = nullptr;
  errno = 0;
  const double v = std::strtod(s.c_str(), &end);
  if (s.empty() || *end != '\0') throw DataError(where + ": not a number: '" + s + "'");
  return v;
}

template <class T>
T parse_wide(const std::string& s, const std::string& where, const std::string& precision) {
  char* end = nullptr;
  T v;
  if (precision == "double") v = T(std::strtod(s.c_str(), &end));
  else if (precision == "longdouble") v = T(std::strtold(s.c_str(), &end));
  else v = T(parse_float128(s.c_str(), &end));
  if (s.empty() || *end != '\0') throw DataError(where + ": not a number: '" + s + "'");
  return v;
}

std::string fmt17(double x) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.17g", x);
  return buf;
}
std::string fmt(float128 x) { return to_string(x, 36); }
std::string fmt(long double x) {
  char buf[48];
  std::snprintf(buf, sizeof buf, "%.21Lg", x);
  return buf;
}

// ---- states ------------------------------------------------------------------

int run_states(const Args& a) {
  const Model model = load(a);
  const std::size_t nv = static_cast<std::size_t>(model.nv()), nq = static_cast<std::size_t>(model.nq());
  const long rows = std::strtol(a.required("rows").c_str(), nullptr, 10);
  if (rows < 1) throw UsageError("--rows must be a positive integer");
  const unsigned long long seed = std::strtoull(a.get("seed", "42").c_str(), nullptr, 10);
  // scandyn bench's RandomStates: one stream, q (R x nq) then qd then the third family
  // (R x nv each), then each quaternion of q divided by its norm
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> uniform(-1.0, 1.0);
  const std::size_t R = static_cast<std::size_t>(rows);
  std::vector<double> q(R * nq), qd(R * nv), third(R * nv);
  for (std::vector<double>* v : {&q, &qd, &third})
    for (double& x : *v) x = uniform(rng);
  for (std::size_t b = 0; b < R; ++b)
    for (Index k : io::quaternion_offsets(model)) {
      double* x = q.data() + b * nq + static_cast<std::size_t>(k);
      const double n = std::sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2] + x[3] * x[3]);
      for (int j = 0; j < 4; ++j) x[j] /= n;
    }
  const std::string& out = a.required("out");
  std::ofstream f(out);
  if (!f) throw DataError(out + ": cannot write");
  std::string line;
  for (const char* fam : {"q_", "qd_", "qdd_", "tau_"})
    for (std::size_t i = 0; i < (fam[1] == '_' ? nq : nv); ++i)
      line += (line.empty() ? "" : ",") + std::string(fam) + std::to_string(i);
  f << line << "\n";
  for (std::size_t b = 0; b < R; ++b) {
    line.clear();
    for (std::size_t i = 0; i < nq; ++i) line += (line.empty() ? "" : ",") + fmt17(q[b * nq + i]);
    for (const std::vector<double>* v : {&qd, &third, &third})
      for (std::size_t i = 0; i < nv; ++i) line += "," + fmt17((*v)[b * nv + i]);
    f << line << "\n";
  }
  if (!f) throw DataError(out + ": write failed");
  return 0;
}

// ---- eval --------------------------------------------------------------------

// Columns of one family (prefix) in a file: index i < n at cols[i], -1 if absent.
std::vector<int> family_columns(const Csv& c, const std::string& prefix, std::size_t n) {
  std::vector<int> cols(n);
  for (std::size_t i = 0; i < n; ++i) cols[i] = c.column(prefix + std::to_string(i));
  return cols;
}
bool complete(const std::vector<int>& cols) {
  return std::all_of(cols.begin(), cols.end(), [](int k) { return k >= 0; });
}

// The input rows of a states file as `scandyn eval` reads them: columns matched by
// name (io::map_state_columns: q_<i> for i < nq, the others < nv), every field a
// number, the quaternions of q checked and normalised in double
// (io::normalize_quaternions: a norm off by more than 1e-6 is an error naming the row
// and columns).
struct StateRows {
  const Csv& csv;
  io::StateColumns cols;
  std::vector<Index> quaternions;  // offsets in q of the model's quaternions
  std::vector<double> row;         // the current row's fields

  StateRows(const Csv& c, const Model& model)
      : csv(c), cols(io::map_state_columns(c.names, model.nq(), model.nv(), c.path)),
        quaternions(io::quaternion_offsets(model)), row(c.names.size()) {}
  const std::vector<int>& of(io::Family f) const { return cols.of(f); }
  std::string where(std::size_t r) const { return csv.path + ": row " + std::to_string(r); }
  // Parses row r (normalising q's quaternions when q is complete).
  void read(std::size_t r) {
    for (std::size_t k = 0; k < row.size(); ++k) row[k] = parse_double(csv.rows[r][k], where(r));
    if (!quaternions.empty() && cols.complete(io::Family::Q))
      io::normalize_quaternions(cols, quaternions, row.data(), where(r));
  }
  void gather(io::Family f, std::vector<double>& dst) const { io::gather_family(cols, f, row.data(), dst.data()); }
};

template <class T>
int run_eval_in(const Args& a, const Model& model) {
  using io::Family;
  const std::size_t nv = static_cast<std::size_t>(model.nv()), nq = static_cast<std::size_t>(model.nq());
  const Csv in = read_csv(a.required("states"));
  StateRows rows(in, model);
  const auto &cq = rows.of(Family::Q), &cqd = rows.of(Family::Qd), &cqdd = rows.of(Family::Qdd),
             &ctau = rows.of(Family::Tau);
  // algorithms: --algo, else each whose inputs are complete
  std::vector<std::string> algos;
  if (a.has("algo")) {
    std::istringstream s(a.required("algo"));
    std::string item;
    while (std::getline(s, item, ','))
      if (item != "id" && item != "fd" && item != "mass" && item != "bias")
        throw UsageError("unknown --algo value '" + item + "' (expected id, fd, mass, bias)");
    for (const char* k : {"id", "fd", "mass", "bias"})
      if (("," + a.required("algo") + ",").find(std::string(",") + k + ",") != std::string::npos) algos.push_back(k);
  } else {
    if (complete(cq) && complete(cqd) && complete(cqdd)) algos.push_back("id");
    if (complete(cq) && complete(cqd) && complete(ctau)) algos.push_back("fd");
    if (complete(cq) && complete(cqd)) algos.push_back("bias");
  }
  auto need = [&](const std::vector<int>& cols, const char* fam, const std::string& algo) {
    if (!complete(cols))
      throw DataError(in.path + ": missing column " + fam +
                      std::to_string(std::find(cols.begin(), cols.end(), -1) - cols.begin()) + " (needed by " +
                      algo + ")");
  };
  std::vector<std::string> names;
  const bool mass = std::find(algos.begin(), algos.end(), "mass") != algos.end();
  for (const std::string& al : algos) {
    need(cq, "q_", al);
    if (al != "mass") need(cqd, "qd_", al);
    if (al == "id") need(cqdd, "qdd_", al);
    if (al == "fd") need(ctau, "tau_", al);
    if (al == "mass") {
      for (std::size_t i = 0; i < nv; ++i)
        for (std::size_t j = 0; j < nv; ++j) names.push_back("M_" + std::to_string(i) + "_" + std::to_string(j));
      continue;
    }
    const char* prefix = al == "id" ? "tau_id_" : al == "fd" ? "qdd_fd_" : "h_";
    for (std::size_t i = 0; i < nv; ++i) names.push_back(prefix + std::to_string(i));
  }
  truth::Truth<T> t(model, mass);
  std::vector<double> q(nq), qd(nv), x(nv);
  std::vector<T> out(mass ? nv * nv : nv);
  const std::string& out_path = a.required("out");
  const std::string tmp = out_path + ".tmp";
  {
    std::ofstream f(tmp);
    if (!f) throw DataError(out_path + ": cannot write");
    std::string line;
    for (const std::string& n : names) line += (line.empty() ? "" : ",") + n;
    f << line << "\n";
    for (std::size_t r = 0; r < in.rows.size(); ++r) {
      rows.read(r);
      line.clear();
      for (const std::string& al : algos) {
        rows.gather(Family::Q, q);
        std::size_t width = nv;
        if (al == "id") {
          rows.gather(Family::Qd, qd);
          rows.gather(Family::Qdd, x);
          t.id(q.data(), qd.data(), x.data(), out.data());
        } else if (al == "fd") {
          rows.gather(Family::Qd, qd);
          rows.gather(Family::Tau, x);
          const Status st = t.fd(q.data(), qd.data(), x.data(), out.data());
          if (!st.ok())
            throw DataError(rows.where(r) + ": forward dynamics failed: articulated inertia pivot at DoF " +
                            std::to_string(st.failed_dof) + " is not positive");
        } else if (al == "bias") {
          rows.gather(Family::Qd, qd);
          t.bias(q.data(), qd.data(), out.data());
        } else {
          t.mass(q.data(), out.data());
          width = nv * nv;
        }
        for (std::size_t k = 0; k < width; ++k) line += (line.empty() ? "" : ",") + fmt(out[k]);
      }
      f << line << "\n";
    }
    if (!f) throw DataError(out_path + ": write failed");
  }
  if (std::rename(tmp.c_str(), out_path.c_str()) != 0) throw DataError(out_path + ": cannot write");
  return 0;
}

int run_eval(const Args& a) {
  const std::string precision = a.get("precision", "float128");
  if (precision != "float128" && precision != "longdouble")
    throw UsageError("unknown --precision value '" + precision + "' (expected float128 or longdouble)");
  const Model model = load(a);
  return precision == "float128" ? run_eval_in<float128>(a, model) : run_eval_in<long double>(a, model);
}

// ---- error -------------------------------------------------------------------

int run_error(const Args& a) {
  const std::string rp = a.get("result-precision", "double");
  if (rp != "double" && rp != "longdouble" && rp != "float128")
    throw UsageError("unknown --result-precision value '" + rp + "' (expected double, longdouble or float128)");
  const Csv truth = read_csv(a.required("truth"));
  const Csv result = read_csv(a.required("result"));
  if (truth.rows.size() != result.rows.size())
    throw DataError(result.path + ": " + std::to_string(result.rows.size()) + " rows, the truth has " +
                    std::to_string(truth.rows.size()));
  // families by column-name prefix, in the truth's order
  struct Fam {
    std::string name;
    std::vector<int> t, r;  // columns in truth and result
  };
  std::vector<Fam> fams;
  for (const char* prefix : {"tau_id_", "qdd_fd_", "M_", "h_"}) {
    Fam f{std::string(prefix).substr(0, std::strlen(prefix) - 1), {}, {}};
    for (std::size_t k = 0; k < truth.names.size(); ++k)
      if (truth.names[k].rfind(prefix, 0) == 0) {
        const int rk = result.column(truth.names[k]);
        if (rk < 0) {
          f.t.clear();
          break;
        }
        f.t.push_back(static_cast<int>(k));
        f.r.push_back(rk);
      }
    if (!f.t.empty()) fams.push_back(f);
  }
  if (fams.empty()) throw DataError(result.path + ": no output family in common with " + truth.path);
  std::printf("family,rows,max_rel_err\n");
  for (const Fam& f : fams) {
    double worst = 0;
    std::vector<float128> x(f.t.size()), ref(f.t.size());
    for (std::size_t row = 0; row < truth.rows.size() && !std::isnan(worst); ++row) {
      const std::string where = "row " + std::to_string(row);
      for (std::size_t k = 0; k < f.t.size(); ++k) {
        ref[k] = parse_wide<float128>(truth.rows[row][static_cast<std::size_t>(f.t[k])], truth.path + ": " + where,
                                      "float128");
        x[k] = parse_wide<float128>(result.rows[row][static_cast<std::size_t>(f.r[k])], result.path + ": " + where,
                                    rp);
      }
      const double e = truth::rel_err(x.data(), ref.data(), x.size());
      worst = std::isnan(e) ? e : std::max(worst, e);
    }
    std::printf("%s,%zu,%.6g\n", f.name.c_str(), truth.rows.size(), worst);
  }
  return 0;
}

// ---- check -------------------------------------------------------------------

int run_check(const Args& a) {
  const std::string precision = a.get("precision", "double");
  if (precision != "float" && precision != "double")
    throw UsageError("unknown --precision value '" + precision + "' (expected float or double)");
  const bool is_float = precision == "float";
  double threshold = is_float ? fd_check_threshold<float>() : fd_check_threshold<double>();
  if (a.has("threshold")) {
    char* end = nullptr;
    threshold = std::strtod(a.required("threshold").c_str(), &end);
    if (*end != '\0' || !(threshold > 0)) throw UsageError("--threshold must be a positive number");
  }
  const Model model = load(a);
  const std::size_t nv = static_cast<std::size_t>(model.nv()), nq = static_cast<std::size_t>(model.nq());
  const Csv in = read_csv(a.required("states"));
  const Csv result = read_csv(a.required("result"));
  if (in.rows.size() != result.rows.size())
    throw DataError(result.path + ": " + std::to_string(result.rows.size()) + " rows, the states have " +
                    std::to_string(in.rows.size()));
  StateRows rows(in, model);
  for (io::Family fam : {io::Family::Q, io::Family::Qd, io::Family::Tau})
    if (!complete(rows.of(fam))) throw DataError(in.path + ": needs the columns q_<i>, qd_<i>, tau_<i>");
  const auto cqdd = family_columns(result, "qdd_fd_", nv);
  if (!complete(cqdd)) throw DataError(result.path + ": needs the columns qdd_fd_<i>");
  // --truth: each row's true error too (the result against the truth's qdd_fd, as
  // `error` measures it), bad = above the precision's budget
  const double budget = is_float ? fd_check_threshold<float>() : fd_check_threshold<double>();
  Csv truth_csv;
  std::vector<int> ctruth;
  if (a.has("truth")) {
    truth_csv = read_csv(a.required("truth"));
    ctruth = family_columns(truth_csv, "qdd_fd_", nv);
    if (!complete(ctruth)) throw DataError(truth_csv.path + ": needs the columns qdd_fd_<i>");
    if (truth_csv.rows.size() != in.rows.size())
      throw DataError(truth_csv.path + ": " + std::to_string(truth_csv.rows.size()) + " rows, the states have " +
                      std::to_string(in.rows.size()));
  }
  std::size_t bad = 0, caught = 0, false_positives = 0;
  double worst_err = 0;
  std::vector<float128> xq(nv), tq(nv);
  // 1-DoF models: fd_check itself (with the joint loads in the residual's scale);
  // multi-DoF models: the engines' check (FdBatchCheck: the general RNEA's residual,
  // M^-1 r by the general ABA at rest), on the double model either way
  Data data(model, false);
  BackendOptions options;
  options.fd_check = FdCheckMode::On;
  options.fd_check_tol_double = threshold;
  std::unique_ptr<FdBatchCheck<double>> batch_check;
  if (model.multi_dof()) batch_check = std::make_unique<FdBatchCheck<double>>(model, options, FdMethod::Aba, 1);
  std::vector<double> q(nq), qd(nv), tau(nv), qdd(nv), id(nv);
  std::size_t flagged = 0;
  double worst_est = 0, worst_res = 0;
  for (std::size_t r = 0; r < in.rows.size(); ++r) {
    rows.read(r);
    rows.gather(io::Family::Q, q);
    rows.gather(io::Family::Qd, qd);
    rows.gather(io::Family::Tau, tau);
    if (is_float)  // what a float engine was given
      for (std::vector<double>* v : {&q, &qd, &tau})
        for (double& x : *v) x = double(float(x));
    for (std::size_t i = 0; i < nv; ++i)
      qdd[i] = parse_double(result.rows[r][static_cast<std::size_t>(cqdd[i])], result.path + ": row " + std::to_string(r));
    double estimate = 0, relative_residual = 0;
    if (batch_check) {
      estimate = batch_check->settle(0, q.data(), qd.data(), tau.data(), nullptr, qdd.data(), true).estimate;
      // the residual's relative size, as FdBatchCheck measures it (no joint loads)
      rnea(model, data, q.data(), qd.data(), qdd.data(), id.data());
      FdCheckNorms<double> norms;
      for (std::size_t i = 0; i < nv; ++i) fd_check_residual(norms, id[i], tau[i], 0.0);
      relative_residual = fd_relative_residual(norms);
    } else {
      const FdCheck<double> c = fd_check(model, data, q.data(), qd.data(), tau.data(), qdd.data());
      estimate = c.error_estimate;
      relative_residual = c.relative_residual;
    }
    const bool flag = !(estimate <= threshold);
    flagged += flag;
    if (!ctruth.empty()) {
      const std::string where = truth_csv.path + ": row " + std::to_string(r);
      for (std::size_t i = 0; i < nv; ++i) {
        xq[i] = float128(qdd[i]);
        tq[i] = parse_wide<float128>(truth_csv.rows[r][static_cast<std::size_t>(ctruth[i])], where, "float128");
      }
      const double e = truth::rel_err(xq.data(), tq.data(), nv);
      const bool is_bad = !(e <= budget);
      bad += is_bad;
      caught += is_bad && flag;
      false_positives += flag && !is_bad;
      worst_err = std::isnan(e) ? e : std::max(worst_err, e);
    }
    worst_est = std::isnan(estimate) ? estimate : std::max(worst_est, estimate);
    worst_res = std::max(worst_res, relative_residual);
  }
  if (ctruth.empty()) {
    std::printf("rows,flagged,threshold,max_error_estimate,max_relative_residual\n%zu,%zu,%.3g,%.6g,%.6g\n",
                in.rows.size(), flagged, threshold, worst_est, worst_res);
  } else {
    std::printf("rows,flagged,threshold,max_error_estimate,max_relative_residual,budget,bad,caught,false_positives,"
                "missed,max_error\n%zu,%zu,%.3g,%.6g,%.6g,%.3g,%zu,%zu,%zu,%zu,%.6g\n",
                in.rows.size(), flagged, threshold, worst_est, worst_res, budget, bad, caught, false_positives,
                bad - caught, worst_err);
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    if (argc < 2 || !std::strcmp(argv[1], "--help") || !std::strcmp(argv[1], "-h")) {
      std::fputs(kUsage, argc < 2 ? stderr : stdout);
      return argc < 2 ? 2 : 0;
    }
    const std::string cmd = argv[1];
    if (cmd == "states") return run_states(parse_args(argc, argv, {"model", "rows", "out", "seed", "allow-nonphysical-inertia", "floating-base"}));
    if (cmd == "eval")
      return run_eval(parse_args(argc, argv, {"model", "states", "out", "algo", "precision", "allow-nonphysical-inertia", "floating-base"}));
    if (cmd == "check")
      return run_check(parse_args(argc, argv, {"model", "states", "result", "precision", "threshold",
                                               "truth", "allow-nonphysical-inertia", "floating-base"}));
    if (cmd == "error") return run_error(parse_args(argc, argv, {"truth", "result", "result-precision"}));
    throw UsageError("unknown command '" + cmd + "'");
  } catch (const UsageError& e) {
    std::fprintf(stderr, "scandyn-truth: %s\n%s", e.what(), kUsage);
    return 2;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "scandyn-truth: %s\n", e.what());
    return 1;
  }
}
