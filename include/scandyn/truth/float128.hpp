// scandyn/truth/float128.hpp: __float128 (IEEE binary128, GCC's libquadmath) as a
// scalar of the reference algorithms: ScalarMath<__float128> and decimal I/O.
//
// Host only, for the high-precision truth (library scandyn_truth: tests and the
// accuracy tools). binary128 has a 113-bit significand: epsilon = 2^-112 = 1.9e-34,
// about 10^15 times finer than double's. Its arithmetic is done in software
// (libquadmath / libgcc), some 20-100x slower than double.
#pragma once

#if defined(__CUDACC__)
#error "scandyn/truth/float128.hpp is host-only (the truth is not built for the device)"
#endif
#if !defined(__SIZEOF_FLOAT128__)
#error "this compiler has no __float128 (build with SCANDYN_TRUTH=OFF)"
#endif

#include <quadmath.h>

#include <string>

#include "scandyn/spatial/scalar.hpp"

namespace scandyn {

using float128 = __float128;

template <>
struct ScalarMath<float128> {
  static float128 sqrt(float128 x) { return ::sqrtq(x); }
  static float128 sin(float128 x) { return ::sinq(x); }
  static float128 cos(float128 x) { return ::cosq(x); }
  static float128 abs(float128 x) { return ::fabsq(x); }
  static bool isfinite(float128 x) { return ::finiteq(x) != 0; }
  // 2^-112 (FLT128_EPSILON, without the Q literal suffix that strict C++ lacks)
  static constexpr float128 epsilon() {
    return float128(1) / (float128(1ull << 56) * float128(1ull << 56));
  }
};

// x in decimal with `digits` significant digits (36 round-trips any binary128).
inline std::string to_string(float128 x, int digits = 36) {
  char buf[64];
  ::quadmath_snprintf(buf, sizeof buf, "%.*Qg", digits, x);
  return buf;
}

// The binary128 nearest to the decimal text (exact for every value written by
// to_string); end, when given, receives the first character not parsed.
inline float128 parse_float128(const char* text, char** end = nullptr) { return ::strtoflt128(text, end); }

}  // namespace scandyn
