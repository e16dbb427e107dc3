// kernels/sim_fused_double_rk4.cu: the fused simulator step kernels in double with the
// rk4 integrator, every capacity and compiled effect set (kernels/sim_fused.cuh).
#define SCANDYN_SIM_FUSED_DEFINE
#include "sim_fused.cuh"

namespace scandyn {
namespace sim {
namespace detail {
SCANDYN_SIM_FUSED_INSTANTIATE(double, Integrator::Rk4)
}  // namespace detail
}  // namespace sim
}  // namespace scandyn
