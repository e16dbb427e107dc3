// src/cli/resources.hpp: memory and disk estimates checked before the large
// allocations and outputs of the subcommands (docs/cli.md, "Limits"). Each estimate
// counts the dominant terms (per-instance and per-row buffers, nv x nv workspaces,
// column names) from the model size, the algorithm, the precision and the thread
// count; the refusal (ResourceError, exit 1) names what was asked, the bytes it
// needs and the bytes available. Device memory is checked by the CUDA engines
// themselves when they allocate (kernels/staging.hpp, device_malloc).
#pragma once

#include <cstddef>
#include <string>

#include "engines.hpp"

namespace scandyn::cli {

// Free bytes on the file system that would hold path (its directory), 0 if unknown.
double disk_space_available(const std::string& path);

// Throws ResourceError when bytes exceed the free space where path would be written
// (nothing is checked for "-" or a FIFO/device, or when the space is unknown).
void require_disk_space(const std::string& path, const std::string& what, double bytes);

// Host bytes of `threads` evaluator workspaces for the model (DataTpl, and the nv x nv
// mass matrix when jsi is true), in scalars of `scalar` bytes.
double workspace_bytes(std::size_t nv, int threads, bool jsi, std::size_t scalar);

// The OpenMP threads an evaluator will use (--threads, else OMP's maximum).
int planned_threads(BackendKind backend, int threads_flag);

}  // namespace scandyn::cli
