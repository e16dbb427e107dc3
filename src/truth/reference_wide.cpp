// The serial reference algorithms in long double and __float128: the
// high-precision truth (library scandyn_truth; scandyn/truth/truth.hpp).
#include "scandyn/truth/float128.hpp"  // ScalarMath<float128> before any instantiation

#include "../algorithm/reference_general_impl.hpp"
#include "../algorithm/reference_impl.hpp"

namespace scandyn {

SCANDYN_INSTANTIATE(long double)
SCANDYN_INSTANTIATE(float128)
SCANDYN_INSTANTIATE_GENERAL(long double)
SCANDYN_INSTANTIATE_GENERAL(float128)

}  // namespace scandyn
