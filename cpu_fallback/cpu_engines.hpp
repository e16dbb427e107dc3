// cpu_fallback/cpu_engines.hpp: the serial and OpenMP engines behind the factories
// of scandyn/engine.hpp (make_inverse_dynamics, ... with BackendKind::Serial or
// OpenMP). One source per algorithm, named above each factory below; the engines run
// their instances through instance_loop.hpp.
#pragma once

#include <memory>

#include "scandyn/engine.hpp"

namespace scandyn {
namespace cpu {

// inverse_dynamics.cpp (with the bias forces)
template <class S>
std::unique_ptr<InverseDynamics<S>> make_inverse_dynamics(const ModelTpl<S>& model, const BackendOptions& options);
template <class S>
std::unique_ptr<BiasForces<S>> make_bias_forces(const ModelTpl<S>& model, const BackendOptions& options);
// mass_matrix.cpp
template <class S>
std::unique_ptr<MassMatrix<S>> make_mass_matrix(const ModelTpl<S>& model, const BackendOptions& options);
// forward_dynamics.cpp
template <class S>
std::unique_ptr<ForwardDynamics<S>> make_forward_dynamics(const ModelTpl<S>& model, const BackendOptions& options);
// derivatives.cpp
template <class S>
std::unique_ptr<IdDerivatives<S>> make_id_derivatives(const ModelTpl<S>& model, const BackendOptions& options);
template <class S>
std::unique_ptr<FdDerivatives<S>> make_fd_derivatives(const ModelTpl<S>& model, const BackendOptions& options);
// fd_directional.cpp (chain: the chunked scans of ChainFdDirectional, else aba_jvp per instance)
template <class S>
std::unique_ptr<FdDirectionalDerivatives<S>> make_fd_directional_derivatives(const ModelTpl<S>& model,
                                                                             const BackendOptions& options, bool chain);
// second_derivatives.cpp
template <class S>
std::unique_ptr<IdSecondDerivatives<S>> make_id_second_derivatives(const ModelTpl<S>& model,
                                                                   const BackendOptions& options);
// kinematics.cpp
template <class S>
std::unique_ptr<Kinematics<S>> make_kinematics(const ModelTpl<S>& model, const BackendOptions& options,
                                               const KinematicsOptions& kinematics);
// hybrid_dynamics.cpp (long chains on openmp: ChainHybridDynamics)
template <class S>
std::unique_ptr<HybridDynamics<S>> make_hybrid_dynamics(const ModelTpl<S>& model,
                                                        const std::vector<unsigned char>& prescribed,
                                                        const BackendOptions& options);
// constrained_dynamics.cpp
template <class S>
std::unique_ptr<ConstrainedForwardDynamics<S>> make_constrained_forward_dynamics(const ModelTpl<S>& model,
                                                                                 const LoopSet& loops,
                                                                                 const BackendOptions& options);

}  // namespace cpu
}  // namespace scandyn
