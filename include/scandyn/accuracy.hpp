// scandyn/accuracy.hpp: the one definition of "relative error" used by tests,
// benchmarks and `scandyn bench`.
#pragma once

#include <cmath>
#include <cstddef>
#include <limits>

namespace scandyn {

// max_i |x_i - ref_i| / max(1, max_i |ref_i|): the error relative to the
// reference's scale (absolute for values below 1). NaN when any x_i or ref_i is
// NaN, so an output left unwritten (NaN-filled) always fails a comparison.
template <class A, class B>
double rel_err(const A* x, const B* ref, std::size_t n) {
  double scale = 1.0, err = 0.0;
  for (std::size_t i = 0; i < n; ++i) {
    const double e = std::fabs(double(x[i]) - double(ref[i]));
    if (std::isnan(e)) return std::numeric_limits<double>::quiet_NaN();
    err = std::fmax(err, e);
    scale = std::fmax(scale, std::fabs(double(ref[i])));
  }
  return err / scale;
}

}  // namespace scandyn
