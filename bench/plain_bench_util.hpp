// bench/plain_bench_util.hpp: what the plain timing programs (no Google Benchmark:
// fd_residual_cost, fd_residual_study, fd_check_engine_cost, step_derivatives_cost,
// directional_derivatives_cost, ...) share.
#pragma once

#include <algorithm>
#include <chrono>
#include <cstddef>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "scandyn/build_config.hpp"
#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>
#endif

namespace scandyn::bench {

// Directory of the shipped robots: $SCANDYN_MODELS_DIR, else the build-time default.
inline std::string models_dir() {
  const char* env = std::getenv("SCANDYN_MODELS_DIR");
  return env && *env ? std::string(env) : std::string(SCANDYN_DEFAULT_MODELS_DIR);
}

// Milliseconds one call of f takes.
template <class F>
double ms_of(F&& f) {
  using Clock = std::chrono::steady_clock;
  const auto t0 = Clock::now();
  f();
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

// A comma-separated command-line list ("1,2", "rope:5000,rope:20000").
inline std::vector<std::string> split_list(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream ss(s);
  std::string item;
  while (std::getline(ss, item, ',')) out.push_back(item);
  return out;
}

// The first line of a text file that starts with key ("" when none): the machine's
// lines of /proc/cpuinfo ("model name", "cpu cores") in a program's '#' header.
inline std::string first_line_with(const char* path, const char* key) {
  std::ifstream in(path);
  std::string line;
  while (std::getline(in, line))
    if (line.rfind(key, 0) == 0) return line;
  return "";
}

// The fastest and the median of one configuration's times over rounds (not empty).
inline double fastest_of(const std::vector<double>& t) { return *std::min_element(t.begin(), t.end()); }
inline double median_of(std::vector<double> t) {
  std::sort(t.begin(), t.end());
  return t[t.size() / 2];
}

// Best of 3 runs of seconds per call: each run repeats batch() (which makes some
// calls and returns how many) until min_time seconds have passed.
template <class F>
double best_seconds_per_call(double min_time, F&& batch) {
  using Clock = std::chrono::steady_clock;
  double best = 1e300;
  for (int rep = 0; rep < 3; ++rep) {
    std::size_t calls = 0;
    const auto t0 = Clock::now();
    double el = 0;
    do {
      calls += batch();
      el = std::chrono::duration<double>(Clock::now() - t0).count();
    } while (el < min_time);
    best = std::min(best, el / double(calls));
  }
  return best;
}

#if SCANDYN_HAS_CUDA
// The plain programs' `cuda` modes: unless e is cudaSuccess, prints
// "<program> cuda: <what>: <CUDA's message>" and exits with status 1.
inline void exit_on_cuda_error(const char* program, cudaError_t e, const char* what) {
  if (e != cudaSuccess) {
    std::fprintf(stderr, "%s cuda: %s: %s\n", program, what, cudaGetErrorString(e));
    std::exit(1);
  }
}
#endif

}  // namespace scandyn::bench
