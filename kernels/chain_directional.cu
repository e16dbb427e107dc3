// The CUDA driver of the chain forward dynamics' JVP and VJP
// (ChainFdPlan::launch_jvp / launch_vjp, scandyn/cuda/chain_fd.hpp): the walks of
// scandyn/algorithm/chain_directional.hpp, one thread per chunk, the level scans of
// chain_scan.cuh, after the plan's own forward-dynamics passes (kernels/chain_fd.cu).
#include <cuda_runtime.h>

#include <vector>

#include "chain_scan.cuh"
#include "scandyn/cuda/chain_fd.hpp"

namespace scandyn {
namespace cuda {

namespace {

#define SCANDYN_CHUNK_INDEX                                                  \
  const Index c = static_cast<Index>(blockIdx.x) * blockDim.x + threadIdx.x; \
  if (c >= chunks) return;                                                   \
  const Index s = r.first(c), e = r.last(c)

// ---- JVP ----
template <class S>
__global__ void jvp_first_kernel(const ChainDirectionalData<S> d, ChunkRange r, Index chunks, Affine6<S>* F_agg,
                                 Affine6<S>* dv_agg) {
  SCANDYN_CHUNK_INDEX;
  F_agg[c] = subtree_force_aggregate(d.fd, s, e);
  dv_agg[c] = jvp_velocity_aggregate(d, s, e);
}

template <class S>
__global__ void jvp_velocity_kernel(const ChainDirectionalData<S> d, ChunkRange r, Index chunks, const Vec6<S>* F_carry,
                                    const Vec6<S>* dv_carry, Affine6<S>* da_agg) {
  SCANDYN_CHUNK_INDEX;
  subtree_force_walk(d, s, e, F_carry[c]);
  da_agg[c] = jvp_velocity_walk(d, s, e, dv_carry[c]);
}

template <class S>
__global__ void jvp_acceleration_kernel(const ChainDirectionalData<S> d, ChunkRange r, Index chunks,
                                        const Vec6<S>* carry, Affine6<S>* agg) {
  SCANDYN_CHUNK_INDEX;
  agg[c] = jvp_acceleration_walk(d, s, e, carry[c]);
}

template <class S>
__global__ void jvp_force_kernel(const ChainDirectionalData<S> d, ChunkRange r, Index chunks, const Vec6<S>* carry,
                                 Affine6<S>* agg) {
  SCANDYN_CHUNK_INDEX;
  agg[c] = jvp_force_walk(d, s, e, carry[c]);
}

// ---- VJP ----
template <class S>
__global__ void vjp_first_kernel(const ChainDirectionalData<S> d, ChunkRange r, Index chunks, Affine6<S>* F_agg,
                                 Affine6<S>* z_agg) {
  SCANDYN_CHUNK_INDEX;
  vjp_first_aggregates(d, s, e, F_agg[c], z_agg[c]);
}

// F's walk and the rest solve's pass 2 (u = M^-1 w).
template <class S>
__global__ void vjp_bias_kernel(const ChainDirectionalData<S> d, ChunkRange r, Index chunks, const Vec6<S>* F_carry,
                                const Vec6<S>* z_carry, Affine6<S>* agg) {
  SCANDYN_CHUNK_INDEX;
  subtree_force_walk(d, s, e, F_carry[c]);
  agg[c] = bias_walk(d.rest, s, e, z_carry[c]);
}

// The rest solve's pass 3 (u in x, Fbar in dv), then RA, gtau and RV's aggregate.
template <class S>
__global__ void vjp_solve_kernel(const ChainDirectionalData<S> d, ChunkRange r, Index chunks, const Vec6<S>* carry,
                                 Affine6<S>* agg) {
  SCANDYN_CHUNK_INDEX;
  acceleration_walk(d.rest, s, e, carry[c]);
  agg[c] = vjp_adjoint_walk(d, s, e, carry[c]);
}

template <class S>
__global__ void vjp_rv_kernel(const ChainDirectionalData<S> d, ChunkRange r, Index chunks, const Vec6<S>* carry) {
  SCANDYN_CHUNK_INDEX;
  vjp_rv_walk(d, s, e, carry[c]);
}

#undef SCANDYN_CHUNK_INDEX

}  // namespace

template <class S>
ChainDirectionalData<S> ChainFdPlan<S>::directional_data(const FdBatchIn<S>& in, const BatchView<S>& qdd,
                                                         int* failed) const {
  ChainDirectionalData<S> d;
  d.fd = data<false>(in, qdd, failed);
  // the chain at rest: v, w, fext, a null, no gravity; tau and qdd set by the caller
  d.rest = d.fd;
  d.rest.v = nullptr;
  d.rest.w = nullptr;
  d.rest.fext = nullptr;
  d.rest.a = nullptr;
  d.rest.a0 = Motion<S>::zero();
  d.F = F_;
  d.dv = dv_;
  d.df = df_;
  d.x = x_;
  return d;
}

template <class S>
cudaError_t ChainFdPlan<S>::launch_jvp(const FdBatchIn<S>& in, const BatchView<const S>& dq,
                                       const BatchView<const S>& dqd, const BatchView<const S>& dtau,
                                       const BatchView<S>& qdd, const BatchView<S>& dqdd, int* failed,
                                       cudaStream_t stream) {
  const Index B = in.q.batch;
  if (!directional()) return cudaErrorNotSupported;
  if (B > max_batch_ || B < 0 || dq.batch != B || dqd.batch != B || dtau.batch != B || dqdd.batch != B)
    return cudaErrorInvalidValue;
  if (B == 0) return cudaSuccess;
  cudaError_t err = cudaMemsetAsync(failed, 0xff, static_cast<std::size_t>(B) * sizeof(int), stream);  // -1
  if (err != cudaSuccess) return err;
  ChainDirectionalData<S> d = directional_data(in, qdd, failed);
  d.dq = dq;
  d.dqd = dqd;
  d.dtau = dtau;
  d.rest.tau = BatchView<const S>::aos(x_, n_, B);
  d.rest.qdd = dqdd;
  if ((err = passes(d.fd, stream)) != cudaSuccess) return err;  // v, U, D, a; qdd
  const std::vector<Index> size = level_sizes(d.count(), chunk_, fan_in_);
  const ChunkRange r{chunk_, d.count()};
  const Index chunks = size[0];
  const unsigned nb = blocks(chunks);
  // F (backward) and dv (forward)
  jvp_first_kernel<<<nb, kBlock, 0, stream>>>(d, r, chunks, aff2_[0], aff_[0]);
  if ((err = scan_levels(size, aff2_.data(), aff2_carry_.data(), fan_in_, false, stream)) != cudaSuccess) return err;
  if ((err = scan_levels(size, aff_.data(), aff_carry_.data(), fan_in_, true, stream)) != cudaSuccess) return err;
  jvp_velocity_kernel<<<nb, kBlock, 0, stream>>>(d, r, chunks, aff2_carry_[0], aff_carry_[0], aff_[0]);
  // da (forward), df
  if ((err = scan_levels(size, aff_.data(), aff_carry_.data(), fan_in_, true, stream)) != cudaSuccess) return err;
  jvp_acceleration_kernel<<<nb, kBlock, 0, stream>>>(d, r, chunks, aff_carry_[0], aff_[0]);
  // dF (backward), dtau - r
  if ((err = scan_levels(size, aff_.data(), aff_carry_.data(), fan_in_, false, stream)) != cudaSuccess) return err;
  jvp_force_kernel<<<nb, kBlock, 0, stream>>>(d, r, chunks, aff_carry_[0], aff_[0]);
  if ((err = cudaGetLastError()) != cudaSuccess) return err;
  // dqdd = M^-1 (dtau - r): passes 2 and 3 at rest
  return finish(d.rest, stream);
}

template <class S>
cudaError_t ChainFdPlan<S>::launch_vjp(const FdBatchIn<S>& in, const BatchView<const S>& w, const BatchView<S>& qdd,
                                       const BatchView<S>& gq, const BatchView<S>& gqd, const BatchView<S>& gtau,
                                       int* failed, cudaStream_t stream) {
  const Index B = in.q.batch;
  if (!directional()) return cudaErrorNotSupported;
  if (B > max_batch_ || B < 0 || w.batch != B || gq.batch != B || gqd.batch != B || gtau.batch != B)
    return cudaErrorInvalidValue;
  if (B == 0) return cudaSuccess;
  cudaError_t err = cudaMemsetAsync(failed, 0xff, static_cast<std::size_t>(B) * sizeof(int), stream);  // -1
  if (err != cudaSuccess) return err;
  ChainDirectionalData<S> d = directional_data(in, qdd, failed);
  d.gq = gq;
  d.gqd = gqd;
  d.gtau = gtau;
  d.rest.tau = w;
  d.rest.qdd = BatchView<S>::aos(x_, n_, B);  // u
  d.rest.a = dv_;                              // Fbar
  d.rest.pA_out = df_;                         // pA of the rest problem
  d.fd.IA_out = IA_;                           // pass 1's IA
  if ((err = passes(d.fd, stream)) != cudaSuccess) return err;  // v, U, D, a; qdd
  const std::vector<Index> size = level_sizes(d.count(), chunk_, fan_in_);
  const ChunkRange r{chunk_, d.count()};
  const Index chunks = size[0];
  const unsigned nb = blocks(chunks);
  // F and the rest solve's pass 2 (both backward)
  vjp_first_kernel<<<nb, kBlock, 0, stream>>>(d, r, chunks, aff2_[0], aff_[0]);
  if ((err = scan_levels(size, aff2_.data(), aff2_carry_.data(), fan_in_, false, stream)) != cudaSuccess) return err;
  if ((err = scan_levels(size, aff_.data(), aff_carry_.data(), fan_in_, false, stream)) != cudaSuccess) return err;
  vjp_bias_kernel<<<nb, kBlock, 0, stream>>>(d, r, chunks, aff2_carry_[0], aff_carry_[0], aff_[0]);
  // the rest solve's pass 3 (u = M^-1 w in x, Fbar in dv); RA, gtau, RV's aggregates
  if ((err = scan_levels(size, aff_.data(), aff_carry_.data(), fan_in_, true, stream)) != cudaSuccess) return err;
  vjp_solve_kernel<<<nb, kBlock, 0, stream>>>(d, r, chunks, aff_carry_[0], aff_[0]);
  // RV (backward); gq, gqd
  if ((err = scan_levels(size, aff_.data(), aff_carry_.data(), fan_in_, false, stream)) != cudaSuccess) return err;
  vjp_rv_kernel<<<nb, kBlock, 0, stream>>>(d, r, chunks, aff_carry_[0]);
  return cudaGetLastError();
}

#define SCANDYN_INSTANTIATE_CHAIN_DIRECTIONAL(S)                                                                   \
  template ChainDirectionalData<S> ChainFdPlan<S>::directional_data(const FdBatchIn<S>&, const BatchView<S>&, int*) \
      const;                                                                                                        \
  template cudaError_t ChainFdPlan<S>::launch_jvp(const FdBatchIn<S>&, const BatchView<const S>&,                  \
                                                  const BatchView<const S>&, const BatchView<const S>&,             \
                                                  const BatchView<S>&, const BatchView<S>&, int*, cudaStream_t);    \
  template cudaError_t ChainFdPlan<S>::launch_vjp(const FdBatchIn<S>&, const BatchView<const S>&,                  \
                                                  const BatchView<S>&, const BatchView<S>&, const BatchView<S>&,    \
                                                  const BatchView<S>&, int*, cudaStream_t);
SCANDYN_INSTANTIATE_CHAIN_DIRECTIONAL(float)
SCANDYN_INSTANTIATE_CHAIN_DIRECTIONAL(double)
#undef SCANDYN_INSTANTIATE_CHAIN_DIRECTIONAL

}  // namespace cuda
}  // namespace scandyn
