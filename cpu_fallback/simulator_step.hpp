// cpu_fallback/simulator_step.hpp: the simulator's serial and OpenMP step, the CPU
// backends behind scandyn::sim::Simulator (scandyn/sim/simulator.hpp; its front
// end, the setup from a scene, resets and energy, is src/sim/simulator.cpp).
//
//   per instance   step_instance over the reference aba for every instance, through
//                  the CPU engines' instance loop (for_instance_blocks):
//                  "serial-aba", "openmp-aba";
//   per forward    a few long chains on openmp: the effects of every DoF into tau,
//   dynamics       the forward-dynamics engine (make_forward_dynamics, FdMethod::
//                  Parallel: scans across links on all threads) on the whole batch,
//                  the integration of every DoF: "openmp-engine-parallel", as the
//                  CUDA backend's engine path beyond 64 DoF (kernels/simulator_step.cu).
// A failed instance-step is recorded as the engines record a failed instance (a
// per-instance failed-DoF array summarised by summarize_failures) and added to
// the simulator's BatchStatus (sim::add_step_failures).
#pragma once

#include <memory>

#include "scandyn/sim/simulator.hpp"

namespace scandyn {
namespace cpu {

// True when the simulator steps setup on `backend` with `threads` OpenMP threads
// per forward dynamics through the parallel chain forward dynamics: openmp, a
// model choose_fd_method(OpenMP, model, batch, threads) runs by FdMethod::Parallel
// (unbranched chains from the base of >= 4096 links with at least
// kChainFdThreadsPerInstance threads per instance, scandyn/engine.hpp; with fewer,
// the threads stepping whole instances with the serial ABA are faster, one thread
// per instance at most), and euler or rk4 (the chain forward dynamics takes no
// armature: implicit steps per instance), without contacts (their pass runs per
// instance).
template <class S>
bool steps_per_forward_dynamics(const sim::SimSetup<S>& setup, BackendKind backend, int threads);

// The step of setup on backend Serial or OpenMP (threads: setup.threads, 0 for
// openmp_threads()). Throws BackendError for openmp in a build without it.
template <class S>
std::unique_ptr<sim::detail::SimBackend<S>> make_simulator_step(const sim::SimSetup<S>& setup, BackendKind backend);

}  // namespace cpu
}  // namespace scandyn
