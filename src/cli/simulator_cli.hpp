// src/cli/simulator_cli.hpp: the simulator as the command line's subcommands make
// it (scandyn rollout, scandyn bench --algo step).
#pragma once

#include <cstdio>
#include <memory>

#include "cli.hpp"
#include "scandyn/sim/simulator.hpp"

namespace scandyn::cli {

// The backend a scene runs on: --backend when given, else the scene's; a scene's
// "auto" is said on stderr in one line, e.g. "scandyn: scene backend auto: openmp
// (cuda: no usable CUDA device: ...)".
inline BackendKind scene_backend(const sim::Scene& scene, const Args& args) {
  if (args.has("backend")) {
    try {
      return parse_backend(args.required("backend"));
    } catch (const BackendError& e) {
      throw UsageError(e.what());
    }
  }
  if (scene.backend_auto) std::fprintf(stderr, "scandyn: %s\n", sim::backend_choice(scene).c_str());
  return scene.backend;
}

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
