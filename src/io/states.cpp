// src/io/states.cpp: the states files' columns (scandyn/io/states.hpp).
#include "scandyn/io/states.hpp"

#include <cmath>
#include <cstdio>

#include "scandyn/io/csv.hpp"
#include "scandyn/io/limits.hpp"

namespace scandyn::io {

const char* algo_name(Algo algo) {
  switch (algo) {
    case Algo::Id: return "id";
    case Algo::Fd: return "fd";
    case Algo::Mass: return "mass";
    case Algo::Bias: return "bias";
    case Algo::DId: return "did";
    case Algo::DFd: return "dfd";
    case Algo::D2Id: return "d2id";
  }
  return "?";
}

bool parse_algo(const std::string& name, Algo& algo) {
  for (Algo a : {Algo::Id, Algo::Fd, Algo::Mass, Algo::Bias, Algo::DId, Algo::DFd, Algo::D2Id}) {
    if (name == algo_name(a)) {
      algo = a;
      return true;
    }
  }
  return false;
}

std::string algo_list(AlgoSet algos, const char* sep) {
  std::string out;
  for (Algo a : {Algo::Id, Algo::Fd, Algo::Mass, Algo::Bias, Algo::DId, Algo::DFd, Algo::D2Id}) {
    if (!(algos & algo_bit(a))) continue;
    if (!out.empty()) out += sep;
    out += algo_name(a);
  }
  return out;
}

std::size_t output_width(Algo algo, Index nv) {
  const std::size_t n = static_cast<std::size_t>(nv);
  if (algo == Algo::D2Id) return 3 * n * n * n;
  if (algo == Algo::DId || algo == Algo::DFd) return 3 * n * n;
  return algo == Algo::Mass ? n * n : n;
}

std::vector<std::string> output_columns(Algo algo, Index nv) {
  std::vector<std::string> names;
  names.reserve(output_width(algo, nv));
  auto matrix = [&](const char* prefix) {
    for (Index i = 0; i < nv; ++i)
      for (Index j = 0; j < nv; ++j) names.push_back(prefix + std::to_string(i) + "_" + std::to_string(j));
  };
  if (algo == Algo::Mass) {
    matrix("M_");
    return names;
  }
  if (algo == Algo::D2Id) {
    for (const char* p : {"d2tau_dq2_", "d2tau_dqd2_", "d2tau_dqdqd_"})
      for (Index i = 0; i < nv; ++i)
        for (Index j = 0; j < nv; ++j)
          for (Index k = 0; k < nv; ++k)
            names.push_back(p + std::to_string(i) + "_" + std::to_string(j) + "_" + std::to_string(k));
    return names;
  }
  if (algo == Algo::DId || algo == Algo::DFd) {
    const bool id = algo == Algo::DId;
    for (const char* p : id ? std::array<const char*, 3>{"dtau_dq_", "dtau_dqd_", "dtau_dqdd_"}
                            : std::array<const char*, 3>{"dqdd_dq_", "dqdd_dqd_", "dqdd_dtau_"})
      matrix(p);
    return names;
  }
  const char* prefix = algo == Algo::Id ? "tau_id_" : algo == Algo::Fd ? "qdd_fd_" : "h_";
  for (Index i = 0; i < nv; ++i) names.push_back(prefix + std::to_string(i));
  return names;
}

const char* family_prefix(Family f) {
  switch (f) {
    case Family::Q: return "q_";
    case Family::Qd: return "qd_";
    case Family::Qdd: return "qdd_";
    case Family::Tau: return "tau_";
  }
  return "?";
}

std::vector<Family> algo_inputs(Algo algo) {
  switch (algo) {
    case Algo::Id: return {Family::Q, Family::Qd, Family::Qdd};
    case Algo::Fd: return {Family::Q, Family::Qd, Family::Tau};
    case Algo::Mass: return {Family::Q};
    case Algo::Bias: return {Family::Q, Family::Qd};
    case Algo::DId:
    case Algo::D2Id: return {Family::Q, Family::Qd, Family::Qdd};
    case Algo::DFd: return {Family::Q, Family::Qd, Family::Tau};
  }
  return {};
}

bool StateColumns::any(Family f) const {
  for (int c : of(f))
    if (c >= 0) return true;
  return false;
}

Index StateColumns::first_missing(Family f) const {
  const std::vector<int>& c = of(f);
  for (std::size_t i = 0; i < c.size(); ++i)
    if (c[i] < 0) return static_cast<Index>(i);
  return -1;
}

bool StateColumns::supports(Algo algo) const {
  for (Family f : algo_inputs(algo))
    if (!complete(f)) return false;
  return true;
}

namespace {

// Parses the decimal index after a family prefix: digits only, no leading zero
// (so each entry has exactly one spelling). Returns -1 if malformed or huge.
long parse_index(const std::string& digits) {
  if (digits.empty() || digits.size() > 9) return -1;
  if (digits.size() > 1 && digits[0] == '0') return -1;
  long v = 0;
  for (char ch : digits) {
    if (ch < '0' || ch > '9') return -1;
    v = 10 * v + (ch - '0');
  }
  return v;
}

// For a model with nq != nv, what a missing column of family f may mean: a file
// written for the model without its floating base (or with nv positions).
std::string size_hint(const StateColumns& cols, Family f) {
  if (cols.nq == cols.nv) return "";
  return std::string("; the model has nq = ") + std::to_string(cols.nq) + " positions (q_0..q_" +
         std::to_string(cols.nq - 1) + ": a quaternion takes 4) and nv = " + std::to_string(cols.nv) +
         " velocities (" + family_prefix(f == Family::Q ? Family::Qd : f) + "0..." +
         std::to_string(cols.nv - 1) + ")";
}

}  // namespace

void normalize_quaternions(const StateColumns& cols, const std::vector<Index>& offsets, double* row,
                           const std::string& where) {
  const std::vector<int>& c = cols.of(Family::Q);
  for (Index k : offsets) {
    double* x[4];
    for (int j = 0; j < 4; ++j) x[j] = row + c[static_cast<std::size_t>(k + j)];
    const double n = std::sqrt(*x[0] * *x[0] + *x[1] * *x[1] + *x[2] * *x[2] + *x[3] * *x[3]);
    if (!(std::fabs(n - 1) <= kQuaternionNormTol)) {
      char buf[64];
      std::snprintf(buf, sizeof buf, "%.9g", n);
      throw CsvError(where + ": columns q_" + std::to_string(k) + "..q_" + std::to_string(k + 3) +
                     ": the quaternion (x, y, z, w) has norm " + buf + ", not 1 (within a relative " +
                     "1e-6 it is normalised)");
    }
    for (int j = 0; j < 4; ++j) *x[j] /= n;
  }
}

StateColumns map_state_columns(const std::vector<std::string>& names, Index nv,
                               const std::string& source) {
  return map_state_columns(names, nv, nv, source);
}

StateColumns map_state_columns(const std::vector<std::string>& names, Index nq, Index nv,
                               const std::string& source) {
  StateColumns cols;
  cols.nv = nv;
  cols.nq = nq;
  for (auto& c : cols.column) c.assign(static_cast<std::size_t>(nv), -1);
  cols.column[static_cast<int>(Family::Q)].assign(static_cast<std::size_t>(nq), -1);
  for (std::size_t k = 0; k < names.size(); ++k) {
    const std::string& name = names[k];
    // the prefixes are prefix-free ("q_" does not start "qd_"): at most one matches
    int family = -1;
    std::size_t plen = 0;
    for (int f = 0; f < kFamilies && family < 0; ++f) {
      const std::string p = family_prefix(static_cast<Family>(f));
      if (name.compare(0, p.size(), p) == 0) {
        family = f;
        plen = p.size();
      }
    }
    const long i = family < 0 ? -1 : parse_index(name.substr(plen));
    if (i < 0)
      throw CsvError(source + ": unknown column '" + printable(name.substr(0, 100)) +
                      "' (expected q_<i>, qd_<i>, qdd_<i> or tau_<i>)");
    const Index n = family == static_cast<int>(Family::Q) ? nq : nv;
    if (i >= n)
      throw CsvError(source + ": column " + name + ": index " + std::to_string(i) +
                     " out of range (the model has " +
                     (nq == nv ? std::to_string(nv) + " DoF"
                               : "nq = " + std::to_string(nq) + " positions q_<i> and nv = " + std::to_string(nv) +
                                     " velocities qd_<i>, qdd_<i>, tau_<i>") +
                     ")");
    cols.column[family][static_cast<std::size_t>(i)] = static_cast<int>(k);
  }
  return cols;
}

void check_state_columns(const StateColumns& cols, const std::vector<Algo>& algos,
                         const std::string& source) {
  for (Algo a : algos) {
    for (Family f : algo_inputs(a)) {
      const Index i = cols.first_missing(f);
      if (i >= 0)
        throw CsvError(source + ": missing column " + family_prefix(f) + std::to_string(i) +
                       " (needed by --algo " + algo_name(a) + ")" + size_hint(cols, f));
    }
  }
  for (int f = 0; f < kFamilies; ++f) {
    const Family fam = static_cast<Family>(f);
    const Index i = cols.first_missing(fam);
    if (i >= 0 && cols.any(fam))
      throw CsvError(source + ": missing column " + family_prefix(fam) + std::to_string(i) +
                     " (other " + family_prefix(fam) + "<i> columns are present)" + size_hint(cols, fam));
  }
}

}  // namespace scandyn::io
