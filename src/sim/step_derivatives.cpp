// src/sim/step_derivatives.cpp: what the derivatives of the simulator's step cover
// (scandyn/sim/step_derivatives.hpp); the engines are in
// cpu_fallback/step_derivatives.cpp.
#include "scandyn/sim/step_derivatives.hpp"

namespace scandyn {
namespace sim {

template <class S>
void require_differentiable_step(const SimSetup<S>& setup, const char* what, BackendKind backend) {
  const std::string name(what);
  if (setup.integrator == Integrator::Variational)
    throw BackendError(name + " do not cover the variational integrator (an implicit step solved by Newton)");
  if (setup.effects & kContacts)
    throw BackendError(name + " do not cover the contacts effect (its force switches with the contact set)");
  if (!setup.prescribed.empty()) throw BackendError(name + " do not cover prescribed joint motion");
  if (!setup.loops.empty()) throw BackendError(name + " do not cover closed loops");
  if (setup.model.multi_dof() && backend == BackendKind::Cuda)
    throw BackendError(name + " on backend 'cuda': model '" + setup.model.name + "' has the multi-DoF joint '" +
                       first_multi_dof_joint(setup.model) + "' (" +
                       (setup.model.floating_base() ? "the floating base" : "a spherical joint") +
                       "), and the CUDA step-derivative kernels take revolute and prismatic joints only; use backend "
                       "serial or openmp");
}

template void require_differentiable_step(const SimSetup<float>&, const char*, BackendKind);
template void require_differentiable_step(const SimSetup<double>&, const char*, BackendKind);

}  // namespace sim
}  // namespace scandyn
