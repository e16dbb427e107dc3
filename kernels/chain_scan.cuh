// The CUDA chain drivers' shared launch plumbing (kernels/chain_fd.cu,
// kernels/chain_directional.cu, kernels/chain_hybrid.cu): one thread per chunk of
// links, a pass's chunk aggregates scanned in levels of fan_in
// (scandyn/algorithm/chain_fd.hpp: fold_range, carry_range): the level folds, one
// thread for the top level, the level carries; and a plan's one device allocation
// (the chain's tables and per-link scratch first).
#pragma once

#include <cuda_runtime.h>

#include <string>
#include <vector>

#include "scandyn/algorithm/chain_fd.hpp"
#include "staging.hpp"

// The first lines of a kernel with one thread per chunk (ChunkRange r, Index chunks in
// scope): chunk c and its links s..e; threads past the last chunk return.
#define SCANDYN_CHUNK_INDEX                                                  \
  const Index c = static_cast<Index>(blockIdx.x) * blockDim.x + threadIdx.x; \
  if (c >= chunks) return;                                                   \
  const Index s = r.first(c), e = r.last(c)

namespace scandyn {
namespace cuda {
namespace {

constexpr int kBlock = 128;

inline unsigned blocks(Index threads) { return static_cast<unsigned>((threads + kBlock - 1) / kBlock); }

// Links s..e of chunk c.
struct ChunkRange {
  Index chunk, count;
  __host__ __device__ Index first(Index c) const { return c * chunk; }
  __host__ __device__ Index last(Index c) const { return min(count, (c + 1) * chunk) - 1; }
};

// One thread per chunk: out[c] = kWalk(d, s, e, carry[c]), a pass's walks from their
// carries returning the next pass's aggregates (kWalk: the address of a SCANDYN_HD
// walk, e.g. &bias_walk<S, false>).
template <auto kWalk, class Data, class In, class Out>
__global__ void chunk_walk_kernel(const Data d, ChunkRange r, Index chunks, const In* carry, Out* out) {
  SCANDYN_CHUNK_INDEX;
  out[c] = kWalk(d, s, e, carry[c]);
}

// ---- scans of aggregates in levels --------------------------------------------

template <class E>
__global__ void fold_kernel(const E* lower, Index size, E* upper, Index m, Index fan_in, bool forward) {
  const Index j = static_cast<Index>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (j < m) upper[j] = fold_range(lower, j * fan_in, min(size, (j + 1) * fan_in), forward);
}

template <class E>
__global__ void top_kernel(const E* agg, typename E::Value* carry, Index size, bool forward) {
  if (blockIdx.x == 0 && threadIdx.x == 0) carry_range(agg, carry, 0, size, forward, E::start());
}

template <class E>
__global__ void carry_kernel(const E* lower, typename E::Value* lower_carry, Index size,
                             const typename E::Value* upper_carry, Index m, Index fan_in, bool forward) {
  const Index j = static_cast<Index>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (j < m) carry_range(lower, lower_carry, j * fan_in, min(size, (j + 1) * fan_in), forward, upper_carry[j]);
}

// The carries of level 0 from its aggregates agg[0] (sizes: this call's levels).
template <class E>
cudaError_t scan_levels(const std::vector<Index>& size, E* const* agg, typename E::Value* const* carry, Index fan_in,
                        bool forward, cudaStream_t stream) {
  const Index levels = static_cast<Index>(size.size());
  for (Index k = 0; k + 1 < levels; ++k)
    fold_kernel<<<blocks(size[k + 1]), kBlock, 0, stream>>>(agg[k], size[k], agg[k + 1], size[k + 1], fan_in, forward);
  top_kernel<<<1, 1, 0, stream>>>(agg[levels - 1], carry[levels - 1], size[levels - 1], forward);
  for (Index k = levels - 2; k >= 0; --k)
    carry_kernel<<<blocks(size[k + 1]), kBlock, 0, stream>>>(agg[k], carry[k], size[k], carry[k + 1], size[k + 1],
                                                               fan_in, forward);
  return cudaGetLastError();
}

inline std::vector<Index> level_sizes(Index links, Index chunk, Index fan_in) {
  return ChainChunking(links, chunk, fan_in).level_size;
}

constexpr std::size_t kAlign = 256;
inline std::size_t aligned(std::size_t x) { return (x + kAlign - 1) / kAlign * kAlign; }

// ---- a plan's one device allocation ----------------------------------------------

// A plan's device memory laid out before it is allocated: take(bytes) gives each
// piece's byte offset (pieces aligned to kAlign), bytes the total so far.
struct DeviceLayout {
  std::size_t bytes = 0;
  std::size_t take(std::size_t n) {
    const std::size_t at = bytes;
    bytes += aligned(n);
    return at;
  }
};

template <class T>
T* at_offset(void* base, std::size_t offset) {
  return reinterpret_cast<T*>(static_cast<char*>(base) + offset);
}

// The pieces every chain plan lays out first: the chain's tables (ChainBodies: its
// distinct bodies, their inverse inertias, each body's entry) and the four passes'
// per-link scratch (v, U, w, D, u) for `links` links.
template <class S>
struct ChainTablesLayout {
  std::size_t classes = 0, n = 0;                         // table entries, bodies per instance
  std::size_t body = 0, Phi = 0, body_class = 0;          // byte offsets of the tables
  std::size_t v = 0, U = 0, w = 0, D = 0, u = 0;          // and of the per-link scratch

  ChainTablesLayout(DeviceLayout& m, const ChainBodies<S>& host, std::size_t links)
      : classes(host.body.size()), n(host.body_class.size()) {
    body = m.take(classes * sizeof(Body<S>));
    Phi = m.take(classes * sizeof(InverseInertia<DualScalar>));
    body_class = m.take(n * sizeof(int));
    v = m.take(links * sizeof(Motion<S>));
    U = m.take(links * sizeof(Force<S>));
    w = m.take(links * sizeof(Force<S>));
    D = m.take(links * sizeof(S));
    u = m.take(links * sizeof(S));
  }
  ChainScratch<S> pointers(void* base) const {
    return {at_offset<const Body<S>>(base, body), at_offset<const InverseInertia<DualScalar>>(base, Phi),
            at_offset<const int>(base, body_class), at_offset<Motion<S>>(base, v), at_offset<Force<S>>(base, U),
            at_offset<Force<S>>(base, w), at_offset<S>(base, D), at_offset<S>(base, u)};
  }
};

// A scan's per-level aggregates (E) and carries (E::Value) laid out for level sizes
// `size` (a plan's max_batch); pointers() then gives each level's arrays.
template <class E>
struct LevelsLayout {
  std::vector<std::size_t> agg, carry;  // byte offsets per level
  LevelsLayout(DeviceLayout& m, const std::vector<Index>& size) {
    for (Index n : size) {
      agg.push_back(m.take(static_cast<std::size_t>(n) * sizeof(E)));
      carry.push_back(m.take(static_cast<std::size_t>(n) * sizeof(typename E::Value)));
    }
  }
  void pointers(void* base, std::vector<E*>& agg_out, std::vector<typename E::Value*>& carry_out) const {
    for (std::size_t k = 0; k < agg.size(); ++k) {
      agg_out.push_back(at_offset<E>(base, agg[k]));
      carry_out.push_back(at_offset<typename E::Value>(base, carry[k]));
    }
  }
};

// Allocates the layout's bytes (`what`: who needs them, for the message when they do
// not fit, detail::device_malloc) and copies the chain's tables into it; frees it
// again and rethrows when a copy fails. Returns the allocation.
template <class S>
void* allocate_chain(const DeviceLayout& m, const ChainTablesLayout<S>& t, const ChainBodies<S>& host,
                     const std::string& what) {
  void* base = detail::device_malloc(m.bytes, [&](std::size_t free_bytes, std::size_t) {
    return what + " needs " + std::to_string(m.bytes) + " bytes of device memory; " + std::to_string(free_bytes) +
           " are free";
  });
  try {
    detail::check(cudaMemcpy(at_offset<char>(base, t.body), host.body.data(), t.classes * sizeof(Body<S>),
                             cudaMemcpyHostToDevice),
                  "copying the chain's bodies");
    detail::check(cudaMemcpy(at_offset<char>(base, t.Phi), host.Phi.data(),
                             t.classes * sizeof(InverseInertia<DualScalar>), cudaMemcpyHostToDevice),
                  "copying the chain's inverse inertias");
    detail::check(cudaMemcpy(at_offset<char>(base, t.body_class), host.body_class.data(), t.n * sizeof(int),
                             cudaMemcpyHostToDevice),
                  "copying the chain's body classes");
  } catch (...) {
    cudaFree(base);
    throw;
  }
  return base;
}

}  // namespace
}  // namespace cuda
}  // namespace scandyn
