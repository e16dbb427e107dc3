// bench/fd_residual_cost.cpp: what the forward-dynamics check costs against the
// forward dynamics it checks (serial reference, one state per call, one thread).
//
// Per model and precision: seconds per call of aba, fd_jsi, the residual alone
// (one rnea: ID(q, qd, qdd) - tau) and fd_check (residual + M^-1 r) in double (the
// recommended check, also for float results) and in the result's own precision.
// Each time is the best of 3 runs of at least --min-time seconds over 64 random
// states (uniform in [-1, 1], seed 42) cycled. A plain timing loop, no Google
// Benchmark.
//
//   fd_residual_cost [--min-time 0.2] [--out docs/accuracy/fd_check_cost.csv]
// Models: iiwa, hyq, atlas ($SCANDYN_MODELS_DIR, default the shipped models/), rope:100, rope:1000.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "plain_bench_util.hpp"
#include "scandyn/algorithm/fd_check.hpp"
#include "scandyn/model/load.hpp"

using namespace scandyn;

namespace {

constexpr int kStates = 64;
volatile double g_sink = 0;  // keeps results alive

using bench::models_dir;

// Best of 3 runs of seconds per call of f(k), k cycling over the states.
template <class F>
double time_per_call(double min_time, F&& f) {
  return bench::best_seconds_per_call(min_time, [&] {
    for (int k = 0; k < kStates; ++k) f(k);
    return std::size_t(kStates);
  });
}

template <class S>
void run(FILE* out, const std::string& label, const Model& md, double min_time) {
  const int n = md.nv();
  const ModelTpl<S> ms = md.cast<S>();
  const bool jsi = n <= 1000;
  DataTpl<S> ds(ms, jsi);
  Data dd(md, false);
  DataTpl<S> dcheck(ms, false);
  std::mt19937_64 g(42);
  std::uniform_real_distribution<double> U(-1, 1);
  std::vector<S> q(kStates * n), qd(kStates * n), tau(kStates * n), qdd(kStates * n), id(n);
  for (auto* v : {&q, &qd, &tau})
    for (S& x : *v) x = S(U(g));
  for (int k = 0; k < kStates; ++k)
    aba(ms, ds, &q[k * n], &qd[k * n], &tau[k * n], &qdd[k * n]);
  std::vector<S> tmp(n);
  const double t_aba = time_per_call(min_time, [&](int k) {
    aba(ms, ds, &q[k * n], &qd[k * n], &tau[k * n], tmp.data());
    g_sink = g_sink + double(tmp[0]);
  });
  const double t_jsi = jsi ? time_per_call(min_time, [&](int k) {
    fd_jsi(ms, ds, &q[k * n], &qd[k * n], &tau[k * n], tmp.data());
    g_sink = g_sink + double(tmp[0]);
  }) : 0.0;
  const double t_res = time_per_call(min_time, [&](int k) {
    rnea(ms, ds, &q[k * n], &qd[k * n], &qdd[k * n], id.data());
    S r = S(0);
    for (int i = 0; i < n; ++i) r = std::max(r, ScalarMath<S>::abs(id[i] - tau[k * n + i]));
    g_sink = g_sink + double(r);
  });
  const double t_check_d = time_per_call(min_time, [&](int k) {
    g_sink = g_sink + fd_check(md, dd, &q[k * n], &qd[k * n], &tau[k * n], &qdd[k * n]).error_estimate;
  });
  const double t_check_s = time_per_call(min_time, [&](int k) {
    g_sink = g_sink + double(fd_check(ms, dcheck, &q[k * n], &qd[k * n], &tau[k * n], &qdd[k * n]).error_estimate);
  });
  const char* p = sizeof(S) == sizeof(float) ? "float" : "double";
  std::fprintf(out, "%s,%d,%s,%.4g,%.4g,%.4g,%.4g,%.4g,%.3f,%.3f,%.3f,%.3f\n", label.c_str(), n, p, t_aba, t_jsi, t_res,
               t_check_d, t_check_s, t_res / t_aba, t_check_d / t_aba, t_check_s / t_aba,
               jsi ? t_check_d / t_jsi : 0.0);
  std::fflush(out);
}

}  // namespace

int main(int argc, char** argv) {
  double min_time = 0.2;
  std::string out_path;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--min-time") && i + 1 < argc) min_time = std::atof(argv[++i]);
    else if (!std::strcmp(argv[i], "--out") && i + 1 < argc) out_path = argv[++i];
    else {
      std::fprintf(stderr, "usage: fd_residual_cost [--min-time SECONDS] [--out FILE.csv]\n");
      return 2;
    }
  }
  FILE* out = out_path.empty() ? stdout : std::fopen(out_path.c_str(), "w");
  if (!out) {
    std::fprintf(stderr, "fd_residual_cost: cannot write %s\n", out_path.c_str());
    return 1;
  }
  std::fprintf(out,
               "model,links,precision,aba_s,jsi_s,residual_s,check_double_s,check_same_s,residual_over_aba,"
               "check_double_over_aba,check_same_over_aba,check_double_over_jsi\n");
  BuildOptions robot;
  robot.require_physical_inertia = false;  // GRiD's atlas.urdf
  const std::vector<std::pair<std::string, std::string>> models = {
      {"iiwa", models_dir() + "/iiwa.urdf"}, {"hyq", models_dir() + "/hyq.urdf"},
      {"atlas", models_dir() + "/atlas.urdf"}, {"rope:100", "rope:100"}, {"rope:1000", "rope:1000"}};
  for (const auto& [label, spec] : models) {
    const Model m = load_model(spec, robot);
    run<float>(out, label, m, min_time);
    run<double>(out, label, m, min_time);
  }
  if (out != stdout) std::fclose(out);
  return 0;
}
