// The CUDA chain drivers' shared launch plumbing (kernels/chain_fd.cu,
// kernels/chain_directional.cu): one thread per chunk of links, and a pass's chunk
// aggregates scanned in levels of fan_in (scandyn/algorithm/chain_fd.hpp: fold_range,
// carry_range): the level folds, one thread for the top level, the level carries.
#pragma once

#include <cuda_runtime.h>

#include <vector>

#include "scandyn/algorithm/chain_fd.hpp"

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

}  // namespace
}  // namespace cuda
}  // namespace scandyn
