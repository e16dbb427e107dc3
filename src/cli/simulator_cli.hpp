// src/cli/simulator_cli.hpp: the simulator as the command line's subcommands make
// it (scandyn rollout, scandyn bench --algo step).
#pragma once

#include <cstdio>
#include <memory>

#include "cli.hpp"
#include "scandyn/io/limits.hpp"
#include "scandyn/sharded.hpp"
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

// The devices a scene's simulator shards across on `backend`: --devices when given
// (all, current, 0,1: scandyn/sharded.hpp's parse_devices), else the scene's "devices",
// none when --backend chose a backend other than cuda. A bad value, or a device list
// on another backend, is a usage error.
inline void scene_devices(sim::Scene& scene, BackendKind backend, const Args& args) {
  if (!args.has("devices")) {
    if (args.has("backend") && backend != BackendKind::Cuda) scene.devices.clear();
    return;
  }
  try {
    scene.devices = parse_devices(args.required("devices"));
  } catch (const BackendError& e) {
    throw UsageError(std::string("--devices: ") + e.what());
  }
  if (!scene.devices.empty() && backend != BackendKind::Cuda)
    throw UsageError("--devices applies only to --backend cuda (backend '" + std::string(to_string(backend)) + "')");
}

// Host memory of a simulator of the scene on backend, in precision S: the state
// (on the CPU backends), the rows and indices reset_all() writes, the per-step
// wrenches, the per-thread workspaces.
template <class S>
double simulator_host_bytes(const sim::Scene& scene, BackendKind backend) {
  const double B = static_cast<double>(scene.instances), n = static_cast<double>(scene.nv()), s = sizeof(S);
  const double nq = static_cast<double>(scene.nq());  // q's rows (> nv with quaternions)
  double bytes = B * (nq + n) * s + B * 8;  // reset rows, instance indices
  if (backend != BackendKind::Cuda) {
    bytes += B * (nq + n) * s;                                          // q, qd
    if (scene.wrenches_per_step) bytes += B * n * s * 6;                // per-step wrenches
    bytes += workspace_bytes(static_cast<std::size_t>(scene.nv()), backend_threads(backend, scene.threads), false, sizeof(S));
  }
  return bytes;
}

// A Simulator<S> of `scene` on `backend`; what the backend refuses (no device, a
// model too large for its kernels, implicit beyond 64 DoF on cuda, ...) becomes
// the command line's usage error (exit 2) with the backend's message.
// extra_host_bytes: what the caller allocates besides (e.g. rollout's copies of the state).
template <class S>
std::unique_ptr<sim::Simulator<S>> make_simulator(const sim::Scene& scene, BackendKind backend,
                                                  double extra_host_bytes = 0) {
  require_host_memory("a simulator of " + std::to_string(scene.instances) + " instances of " +
                          printable(scene.model_spec) + " (" + std::to_string(scene.nv()) + " DoF, " +
                          (sizeof(S) == 4 ? "float" : "double") + ")",
                      simulator_host_bytes<S>(scene, backend) + extra_host_bytes);
  try {
    return std::make_unique<sim::Simulator<S>>(scene, backend);
  } catch (const BackendError& e) {
    throw UsageError(e.what(), false);
  }
}

}  // namespace scandyn::cli
