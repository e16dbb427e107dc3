// src/cli/simulator_cli.hpp: the simulator as the command line's subcommands make
// it (scandyn rollout, scandyn bench --algo step).
#pragma once

#include <memory>

#include "cli.hpp"
#include "scandyn/sim/simulator.hpp"

namespace scandyn::cli {

// A Simulator<S> of `scene` on `backend`; what the backend refuses (no device, a
// model too large for its kernels, implicit beyond 64 DoF on cuda, ...) becomes
// the command line's usage error (exit 2) with the backend's message.
template <class S>
std::unique_ptr<sim::Simulator<S>> make_simulator(const sim::Scene& scene, BackendKind backend) {
  try {
    return std::make_unique<sim::Simulator<S>>(scene, backend);
  } catch (const BackendError& e) {
    throw UsageError(e.what(), false);
  }
}

}  // namespace scandyn::cli
