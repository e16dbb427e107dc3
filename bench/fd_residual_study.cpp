// bench/fd_residual_study.cpp: how well the forward-dynamics check
// (scandyn/algorithm/fd_check.hpp) separates bad results from clean ones.
//
// For each case (model x method x precision) it draws random states, computes qdd
// with the serial reference (aba or fd_jsi in float or double), measures the true
// error against the binary128 truth (ABA in __float128; error = scandyn::rel_err's
// max_i |qdd_i - t_i| / max(1, max_i |t_i|), differences in binary128), and runs
// fd_check in double on the inputs the method saw. A row is bad when its true error
// exceeds the accuracy report's budget (float 1e-4, double 1e-10); flagged when
// error_estimate exceeds fd_check_threshold. It counts, per case: states, pivots
// reported (not silent, not checked), bad rows, flagged rows, catches (bad and
// flagged), false positives (flagged, not bad), misses (bad, not flagged), with the
// ranges of the true error, the estimate and the relative residual on clean and on
// bad rows. Also the estimate computed in the result's own precision (est_same),
// to show why the check runs in double, and the ratio estimate / true error over
// the rows whose true error is above 10 epsilon of their precision (below that
// the truth's comparison is rounding noise).
//
// States cycle through four kinds (k mod 4): 0 q, qd, tau uniform in [-1, 1] (q in
// [-pi, pi] for the robots): `scandyn bench`'s distribution; 1 the same with tau = 0
// (free motion); 2 qd = 0 and tau = 0 (released from rest under gravity); 3 qd in
// [-3, 3], tau in [-10, 10]. Each state is rounded to float first, so float and
// double methods solve the same problem as the truth.
//
//   fd_residual_study [--quick] [--out docs/accuracy/fd_check.csv]
// (--quick: 1/20 of the states, for a smoke run.) Models from $SCANDYN_MODELS_DIR
// (default the shipped models/).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "plain_bench_util.hpp"
#include "scandyn/algorithm/fd_check.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/truth/truth.hpp"

using namespace scandyn;

namespace {

using bench::models_dir;

double budget(bool is_float) { return is_float ? 1e-4 : 1e-10; }

// Range of a quantity over a set of rows.
struct Range {
  double lo = std::numeric_limits<double>::infinity(), hi = 0;
  int count = 0;
  void add(double x) {
    lo = std::min(lo, x);
    hi = std::isnan(x) ? x : std::max(hi, x);
    ++count;
  }
  std::string str() const {
    if (!count) return "";
    char b[64];
    std::snprintf(b, sizeof b, "%.2g..%.2g", lo, hi);
    return b;
  }
};

struct Tally {
  std::string model, method, precision;
  int states = 0, reported = 0, bad = 0, flagged = 0, caught = 0, false_pos = 0, missed = 0;
  Range err_clean, err_bad, est_clean, est_bad, est_same_clean, est_same_bad, rres_clean, rres_bad;
  Range ratio;  // estimate / true error, rows whose true error is above 10 eps of the precision
};

// One method x precision on a model.
struct Variant {
  bool jsi, is_float;
  Tally t;
};

template <class S>
Status solve(bool jsi, const ModelTpl<S>& m, DataTpl<S>& d, const std::vector<S>& q, const std::vector<S>& qd,
             const std::vector<S>& tau, std::vector<S>& qdd) {
  return jsi ? fd_jsi(m, d, q.data(), qd.data(), tau.data(), qdd.data())
             : aba(m, d, q.data(), qd.data(), tau.data(), qdd.data());
}

// Runs one model: `states` states, the variants given (methods x precisions).
void run_model(const std::string& label, const Model& md, int states, double q_range, bool with_jsi,
               std::vector<Tally>& out) {
  const int n = md.nv();
  const ModelTpl<float> mf = md.cast<float>();
  DataTpl<float> df(mf, with_jsi);
  Data dd(md, with_jsi);
  Data dcheck(md, false);
  DataTpl<float> dcheck_f(mf, false);
  truth::Truth<float128> truth(md, false);
  std::vector<Variant> vs;
  for (bool jsi : {false, true}) {
    if (jsi && !with_jsi) continue;
    for (bool is_float : {true, false}) {
      Variant v{jsi, is_float, Tally{}};
      v.t.model = label;
      v.t.method = jsi ? "jsi" : "aba";
      v.t.precision = is_float ? "float" : "double";
      vs.push_back(v);
    }
  }
  std::mt19937_64 g(1234 + static_cast<unsigned>(n));
  std::uniform_real_distribution<double> U(-1, 1);
  std::vector<double> q(n), qd(n), tau(n), qdd_d(n);
  std::vector<float> qf(n), qdf(n), tauf(n), qdd_f(n);
  std::vector<float128> t(n);
  for (int k = 0; k < states; ++k) {
    const int kind = k % 4;
    for (int i = 0; i < n; ++i) {
      qf[i] = float(q_range * U(g));
      qdf[i] = kind == 2 ? 0.f : float((kind == 3 ? 3.0 : 1.0) * U(g));
      tauf[i] = kind == 1 || kind == 2 ? 0.f : float((kind == 3 ? 10.0 : 1.0) * U(g));
      q[i] = qf[i];
      qd[i] = qdf[i];
      tau[i] = tauf[i];
    }
    if (!truth.fd(q.data(), qd.data(), tau.data(), t.data()).ok()) {
      std::fprintf(stderr, "fd_residual_study: %s: the truth's pivot failed at state %d\n", label.c_str(), k);
      std::exit(1);
    }
    for (Variant& v : vs) {
      Tally& T = v.t;
      ++T.states;
      double err, est, est_same, rres;
      if (v.is_float) {
        if (!solve(v.jsi, mf, df, qf, qdf, tauf, qdd_f).ok()) {
          ++T.reported;
          continue;
        }
        err = truth::rel_err(qdd_f.data(), t.data(), n);
        const FdCheck<double> c = fd_check(md, dcheck, qf.data(), qdf.data(), tauf.data(), qdd_f.data());
        est = c.error_estimate;
        rres = c.relative_residual;
        est_same = fd_check(mf, dcheck_f, qf.data(), qdf.data(), tauf.data(), qdd_f.data()).error_estimate;
      } else {
        if (!solve(v.jsi, md, dd, q, qd, tau, qdd_d).ok()) {
          ++T.reported;
          continue;
        }
        err = truth::rel_err(qdd_d.data(), t.data(), n);
        const FdCheck<double> c = fd_check(md, dcheck, q.data(), qd.data(), tau.data(), qdd_d.data());
        est = est_same = c.error_estimate;
        rres = c.relative_residual;
      }
      const bool bad = !(err <= budget(v.is_float));
      const bool flagged = !(est <= (v.is_float ? fd_check_threshold<float>() : fd_check_threshold<double>()));
      T.bad += bad;
      T.flagged += flagged;
      T.caught += bad && flagged;
      T.false_pos += flagged && !bad;
      T.missed += bad && !flagged;
      (bad ? T.err_bad : T.err_clean).add(err);
      (bad ? T.est_bad : T.est_clean).add(est);
      (bad ? T.est_same_bad : T.est_same_clean).add(est_same);
      (bad ? T.rres_bad : T.rres_clean).add(rres);
      if (err > 10 * (v.is_float ? 1.2e-7 : 2.2e-16)) T.ratio.add(est / err);
    }
  }
  for (Variant& v : vs) out.push_back(v.t);
}

}  // namespace

int main(int argc, char** argv) {
  bool quick = false;
  std::string out_path;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--quick")) quick = true;
    else if (!std::strcmp(argv[i], "--out") && i + 1 < argc) out_path = argv[++i];
    else {
      std::fprintf(stderr, "usage: fd_residual_study [--quick] [--out FILE.csv]\n");
      return 2;
    }
  }
  const int div = quick ? 20 : 1;
  BuildOptions robot;
  robot.require_physical_inertia = false;  // GRiD's atlas.urdf (docs/models.md)
  const double pi = 3.141592653589793;
  struct Case {
    std::string label, spec;
    int states;
    double q_range;
    bool jsi;
  };
  const std::vector<Case> cases = {
      {"iiwa", models_dir() + "/iiwa.urdf", 10000, pi, true},
      {"hyq", models_dir() + "/hyq.urdf", 10000, pi, true},
      {"atlas", models_dir() + "/atlas.urdf", 10000, pi, true},
      {"rope:10", "rope:10", 2500, 1, true},
      {"rope:30", "rope:30", 2500, 1, true},
      {"rope:100", "rope:100", 2500, 1, true},
      {"rope:300", "rope:300", 2500, 1, true},
      {"chain:64", "chain:64", 2000, 1, true},
      {"tree:100:7", "tree:100:7", 1000, 1, true},
      {"rope:1000", "rope:1000", 100, 1, false},
      {"rope:10000", "rope:10000", 20, 1, false},
      {"rope:100000", "rope:100000", 4, 1, false},
  };
  std::vector<Tally> all;
  for (const Case& c : cases) {
    const auto t0 = std::chrono::steady_clock::now();
    const Model m = load_model(c.spec, robot);
    run_model(c.label, m, std::max(c.states / div, 4), c.q_range, c.jsi, all);
    std::fprintf(stderr, "  %s: %.1f s\n", c.label.c_str(),
                 std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  }
  FILE* f = out_path.empty() ? stdout : std::fopen(out_path.c_str(), "w");
  if (!f) {
    std::fprintf(stderr, "fd_residual_study: cannot write %s\n", out_path.c_str());
    return 1;
  }
  std::fprintf(f,
               "model,method,precision,states,reported,bad,flagged,caught,false_positives,missed,"
               "error_clean,error_bad,estimate_clean,estimate_bad,estimate_same_precision_clean,"
               "estimate_same_precision_bad,relative_residual_clean,relative_residual_bad,estimate_over_error\n");
  for (const Tally& T : all)
    std::fprintf(f, "%s,%s,%s,%d,%d,%d,%d,%d,%d,%d,%s,%s,%s,%s,%s,%s,%s,%s,%s\n", T.model.c_str(), T.method.c_str(),
                 T.precision.c_str(), T.states, T.reported, T.bad, T.flagged, T.caught, T.false_pos, T.missed,
                 T.err_clean.str().c_str(), T.err_bad.str().c_str(), T.est_clean.str().c_str(),
                 T.est_bad.str().c_str(), T.est_same_clean.str().c_str(), T.est_same_bad.str().c_str(),
                 T.rres_clean.str().c_str(), T.rres_bad.str().c_str(), T.ratio.str().c_str());
  if (f != stdout) std::fclose(f);
  return 0;
}
