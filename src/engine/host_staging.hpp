// src/engine/host_staging.hpp (internal): the host side of the CUDA engines' pinned
// staging pipeline (kernels/host_pipeline.hpp), kept free of CUDA so that it is
// compiled with OpenMP (src/engine/host_staging.cpp) and tested without a device
// (tests/engine/test_host_staging.cpp):
//   Mode, parse_mode()          SCANDYN_HOST_STAGING: pageable | pinned;
//   chunk_instances()           instances per chunk (kChunkBytes, or
//                               SCANDYN_HOST_CHUNK_INSTANCES);
//   chunk_count(), chunk_range() the partition of a batch into chunks;
//   Layout, choose_layout(), packed_view(), pack(), unpack(), copy_bytes()
//                               one chunk of a host view gathered into (or scattered
//                               from) a dense block, on OpenMP threads.
// Not installed: it is no part of the public API.
#pragma once

#include <cstddef>

#include "scandyn/batch.hpp"

namespace scandyn {
namespace host_staging {

// How compute() of a CUDA engine moves host views (SCANDYN_HOST_STAGING):
//   Pageable  the copies straight from and to the user's (pageable) memory, the
//             whole batch at once (kernels/staging.hpp: plan(), copy());
//   Pinned    the chunked pipeline through the engine's pinned ring
//             (kernels/host_pipeline.hpp), where the engine's strategy has it.
enum class Mode { Pageable, Pinned };

// The mode named by `value` (the environment's SCANDYN_HOST_STAGING): null or empty:
// Pinned. Throws std::invalid_argument for any other name than pageable or pinned.
Mode parse_mode(const char* value);
const char* to_string(Mode mode);

// Default chunk: the instances whose packed inputs and outputs come to about 16 MiB
// (iiwa, float: ~150k instances). Measured on an H200 (iiwa id from host buffers,
// float, 10^6 instances, `scandyn bench`, bench/results/host-staging-h200.csv):
// chunks of 8192 instances 15.0 ms (no better than the pageable path's 14.5), 37449
// (4 MiB) 4.03 ms, 131072 2.31 ms, 262144 2.17 ms: per chunk a fixed cost (events,
// the OpenMP team's start) that small chunks repeat. 16 MiB keeps a 10^6 batch in ~7
// chunks, so packing, DMA and kernels still overlap, and the ring (3 slots) at ~48 MiB
// of pinned and of device memory. SCANDYN_HOST_CHUNK_INSTANCES overrides it.
inline constexpr std::size_t kChunkBytes = std::size_t(16) << 20;

// Instances per chunk: `value` (SCANDYN_HOST_CHUNK_INSTANCES) when given (a positive
// integer, else std::invalid_argument), else kChunkBytes / bytes_per_instance, at least 1.
Index chunk_instances(std::size_t bytes_per_instance, const char* value);

// Instances [begin, begin + count) of a batch.
struct Range {
  Index begin = 0;
  Index count = 0;
};

// Chunks of `chunk` instances covering `batch` (the last one shorter).
inline Index chunk_count(Index batch, Index chunk) { return batch <= 0 ? 0 : (batch + chunk - 1) / chunk; }
// Chunk k of the partition.
inline Range chunk_range(Index batch, Index chunk, Index k) {
  const Index begin = k * chunk;
  const Index rest = batch - begin;
  return {begin, rest < chunk ? rest : chunk};
}

// The layout of one chunk of n instances of a w-wide view in a packed block:
//   InstanceMajor  entry (i, k) at k * w + i (the host view's instances are far
//                  apart: AoS, and AoS-dense views pack with one memcpy);
//   DofMajor       entry (i, k) at i * n + k (the host view's DoFs are far apart:
//                  SoA, one memcpy per DoF for SoA-dense views);
//   Broadcast      an input with batch stride 0 (one instance for all): its w
//                  entries once, the packed view's batch stride 0.
enum class Layout { InstanceMajor, DofMajor, Broadcast };

// The layout for view v (w x B); outputs are never Broadcast (plan() has refused a
// zero stride).
template <class T>
Layout choose_layout(const BatchView<T>& v, Index w, bool output) {
  const std::ptrdiff_t ds = w > 1 ? v.dof_stride : 0, bs = v.batch > 1 ? v.batch_stride : 0;
  if (v.batch <= 1) return Layout::InstanceMajor;  // (one instance: both layouts are the same)
  if (!output && bs == 0) return Layout::Broadcast;
  const std::ptrdiff_t ads = ds < 0 ? -ds : ds, abs_bs = bs < 0 ? -bs : bs;
  return ads > abs_bs ? Layout::DofMajor : Layout::InstanceMajor;
}

// Entries of the packed block for a chunk of n instances.
inline std::size_t packed_entries(Layout layout, Index w, Index n) {
  return static_cast<std::size_t>(w) * static_cast<std::size_t>(layout == Layout::Broadcast ? 1 : n);
}

// The view of a packed block (n instances) at p.
template <class T>
BatchView<T> packed_view(T* p, Layout layout, Index w, Index n) {
  switch (layout) {
    case Layout::DofMajor: return {p, n, n, 1};
    case Layout::Broadcast: return {p, n, 1, 0};
    case Layout::InstanceMajor: break;
  }
  return {p, n, 1, w};
}

// Gathers instances r of v (w x B) into dst (packed_entries(layout, w, r.count)
// entries), on up to `threads` OpenMP threads (0: openmp_threads()); small blocks
// on one.
template <class T>
void pack(const BatchView<const T>& v, Index w, Range r, Layout layout, T* dst, int threads);

// Scatters a packed block (layout not Broadcast) into instances r of v, writing v's
// entries only.
template <class T>
void unpack(const T* src, Layout layout, const BatchView<T>& v, Index w, Range r, int threads);

// memcpy on up to `threads` OpenMP threads.
void copy_bytes(void* dst, const void* src, std::size_t bytes, int threads);

}  // namespace host_staging
}  // namespace scandyn
