// Shared helpers for the test programs: model paths, random states, tolerances.
#pragma once

#include <cmath>
#include <cstdlib>
#include <random>
#include <string>
#include <type_traits>
#include <vector>

namespace scandyn::test {

// Directory holding iiwa.urdf, hyq.urdf, atlas.urdf: $SCANDYN_MODELS_DIR, else the
// build-time default (../shared/models next to the source tree).
inline std::string models_dir() {
  const char* env = std::getenv("SCANDYN_MODELS_DIR");
  return env && *env ? std::string(env) : std::string(SCANDYN_DEFAULT_MODELS_DIR);
}
inline std::string model_path(const std::string& file) { return models_dir() + "/" + file; }

// The scandyn executable built alongside the tests.
inline std::string cli_path() { return SCANDYN_CLI_PATH; }

// Tolerance by precision: Tol<S>(for_double, for_float).
template <class S>
constexpr S Tol(double for_double, double for_float) {
  return std::is_same<S, float>::value ? S(for_float) : S(for_double);
}

// Uniform random vector in [lo, hi].
inline std::vector<double> random_vector(std::mt19937_64& rng, int n, double lo, double hi) {
  std::uniform_real_distribution<double> d(lo, hi);
  std::vector<double> v(static_cast<std::size_t>(n));
  for (auto& x : v) x = d(rng);
  return v;
}

template <class T>
std::vector<T> cast_vector(const std::vector<double>& v) {
  return std::vector<T>(v.begin(), v.end());
}

// max_i |a_i - b_i| / max(1, max_i |b_i|): relative to the reference's scale; NaN if any
// entry of a is NaN (so untouched NaN-filled outputs fail).
template <class A, class B>
double max_rel_err(const std::vector<A>& a, const std::vector<B>& b) {
  double scale = 1.0, err = 0.0;
  for (std::size_t i = 0; i < b.size(); ++i) scale = std::fmax(scale, std::fabs(double(b[i])));
  for (std::size_t i = 0; i < b.size(); ++i) {
    const double e = std::fabs(double(a[i]) - double(b[i]));
    if (!(e <= err)) err = e;  // NaN propagates
  }
  return err / scale;
}

}  // namespace scandyn::test
