// The serial reference algorithms' general path (multi-DoF joints) for float and
// double: reference_general_impl.hpp.
#include "reference_general_impl.hpp"

namespace scandyn {

SCANDYN_INSTANTIATE_GENERAL(float)
SCANDYN_INSTANTIATE_GENERAL(double)

}  // namespace scandyn
