// scandyn/spatial/scalar.hpp: the scalar functions the spatial algebra and the
// algorithms call (sqrt, sin, cos, abs, isfinite, epsilon).
//
// Every such call goes through ScalarMath<S>, so that one set of algorithms runs in
// any scalar type. The primary template is <cmath> and <limits> for float, double
// and long double: for float and double it makes exactly the calls the code made
// before (std::sqrt(float) is sqrtf, on the host and, through CUDA's overloads, on
// the device), so their results are unchanged bit for bit. A scalar that <cmath>
// does not know specialises it: __float128 in scandyn/truth/float128.hpp (host
// only, used by the high-precision truth). For such a type an unqualified
// std:: call does not compile (the conversions to float, double and long double
// are ambiguous), so no wide value is silently rounded to double.
#pragma once

#include <cmath>
#include <limits>

#include "scandyn/config.hpp"

namespace scandyn {

template <class S>
struct ScalarMath {
  SCANDYN_HD static S sqrt(S x) { return std::sqrt(x); }
  SCANDYN_HD static S sin(S x) { return std::sin(x); }
  SCANDYN_HD static S cos(S x) { return std::cos(x); }
  SCANDYN_HD static S abs(S x) { return std::fabs(x); }
  SCANDYN_HD static bool isfinite(S x) { return std::isfinite(x); }
  // the distance from 1 to the next representable value
  SCANDYN_HD static constexpr S epsilon() { return std::numeric_limits<S>::epsilon(); }
};

// True for a SIMD pack of scalars (scandyn/spatial/pack.hpp), one lane per instance:
// code over a pack must not branch on data values, so the algorithms' paths that do
// (the multi-DoF joints' general path) are compiled for plain scalars only.
template <class S>
inline constexpr bool kIsPack = false;

}  // namespace scandyn
