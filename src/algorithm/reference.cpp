// Serial reference algorithms: loops over bodies in DoF order calling the shared
// step functions of scandyn/algorithm/steps.hpp.
#include "reference_impl.hpp"

namespace scandyn {

SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)

}  // namespace scandyn
