// The CUDA driver of the parallel chain hybrid dynamics (scandyn/cuda/chain_hybrid.hpp):
// the walks of scandyn/algorithm/chain_hybrid.hpp (the host driver's, SCANDYN_HD), one
// thread per chunk, and the level scans of chain_scan.cuh (the chain forward
// dynamics' launch plumbing), in the order of ChainHybridDynamics::compute
// (src/algorithm/chain_hybrid.cpp).
#include <cuda_runtime.h>

#include <algorithm>
#include <string>
#include <vector>

#include "chain_scan.cuh"
#include "scandyn/cuda/chain_hybrid.hpp"
#include "staging.hpp"

namespace scandyn {
namespace cuda {

using detail::check;

namespace {

#define SCANDYN_CHUNK_INDEX                                                  \
  const Index c = static_cast<Index>(blockIdx.x) * blockDim.x + threadIdx.x; \
  if (c >= chunks) return;                                                   \
  const Index s = r.first(c), e = r.last(c)

// pass 0's aggregates (velocity_aggregate reads no mask: the chain FD's)
template <class S>
__global__ void hybrid_velocity_aggregate_kernel(const ChainHybridData<S> d, ChunkRange r, Index chunks,
                                                 Affine6<S>* agg) {
  SCANDYN_CHUNK_INDEX;
  agg[c] = velocity_aggregate<S, false>(d, s, e);
}

// pass 0's walks: v, and pass 1's aggregates (HybridDual)
template <class S>
__global__ void hybrid_velocity_walk_kernel(const ChainHybridData<S> d, ChunkRange r, Index chunks,
                                            const Vec6<S>* carry, HybridDual<DualScalar>* dual) {
  SCANDYN_CHUNK_INDEX;
  dual[c] = hybrid_velocity_walk(d, s, e, carry[c]);
}

// pass 1's walks from the carried dual (prescribed joints rigid): U, D, w; pass 2's aggregates
template <class S>
__global__ void hybrid_inertia_walk_kernel(const ChainHybridData<S> d, ChunkRange r, Index chunks,
                                           const Mat5<DualScalar>* dual_carry, Affine6<S>* agg) {
  SCANDYN_CHUNK_INDEX;
  agg[c] = hybrid_inertia_walk(d, s, e, hybrid_inertia_carry(d, e, dual_carry[c]));
}

// pass 2's walks: u; pass 3's aggregates
template <class S>
__global__ void hybrid_bias_walk_kernel(const ChainHybridData<S> d, ChunkRange r, Index chunks, const Vec6<S>* carry,
                                        Affine6<S>* agg) {
  SCANDYN_CHUNK_INDEX;
  agg[c] = hybrid_bias_walk(d, s, e, carry[c]);
}

// pass 3's walks: qdd and tau
template <class S>
__global__ void hybrid_acceleration_walk_kernel(const ChainHybridData<S> d, ChunkRange r, Index chunks,
                                                const Vec6<S>* carry) {
  SCANDYN_CHUNK_INDEX;
  hybrid_acceleration_walk(d, s, e, carry[c]);
}

#undef SCANDYN_CHUNK_INDEX

}  // namespace

template <class S>
ChainHybridPlan<S>::ChainHybridPlan(const ModelTpl<S>& model, Index max_batch, Index chunk, Index fan_in)
    : n_(model.nbodies()),
      max_batch_(std::max<Index>(max_batch, 1)),
      chunk_(chunk > 0 ? chunk : kDefaultChunk),
      fan_in_(fan_in > 1 ? fan_in : kDefaultFanIn) {
  require_one_dof_joints(model, "backend 'cuda': the parallel chain hybrid dynamics");
  const ChainBodies<S> host = ChainBodies<S>::from(model, max_batch_);
  a0_ = base_acceleration(model.gravity);
  const std::size_t links = static_cast<std::size_t>(n_) * max_batch_;
  const std::vector<Index> level_size = level_sizes(static_cast<Index>(links), chunk_, fan_in_);
  const std::size_t classes = host.body.size();
  std::size_t off = 0;
  auto take = [&](std::size_t bytes) {
    const std::size_t at = off;
    off += aligned(bytes);
    return at;
  };
  const std::size_t o_body = take(classes * sizeof(Body<S>)), o_phi = take(classes * sizeof(InverseInertia<DualScalar>)),
                    o_class = take(static_cast<std::size_t>(n_) * sizeof(int)), o_v = take(links * sizeof(Motion<S>)),
                    o_U = take(links * sizeof(Force<S>)), o_w = take(links * sizeof(Force<S>)),
                    o_D = take(links * sizeof(S)), o_u = take(links * sizeof(S));
  std::vector<std::size_t> o_aff, o_affc, o_dual, o_dualc;
  for (Index size : level_size) {
    o_aff.push_back(take(size * sizeof(Affine6<S>)));
    o_affc.push_back(take(size * sizeof(Vec6<S>)));
    o_dual.push_back(take(size * sizeof(HybridDual<DualScalar>)));
    o_dualc.push_back(take(size * sizeof(Mat5<DualScalar>)));
  }
  bytes_ = off;
  memory_ = detail::device_malloc(bytes_, [&](std::size_t free_bytes, std::size_t) {
    return "backend 'cuda': the parallel chain hybrid dynamics of " + std::to_string(n_) + " links x " +
           std::to_string(max_batch_) + " instances needs " + std::to_string(bytes_) + " bytes of device memory; " +
           std::to_string(free_bytes) + " are free";
  });
  char* base = static_cast<char*>(memory_);
  body_ = reinterpret_cast<const Body<S>*>(base + o_body);
  Phi_ = reinterpret_cast<const InverseInertia<DualScalar>*>(base + o_phi);
  body_class_ = reinterpret_cast<const int*>(base + o_class);
  v_ = reinterpret_cast<Motion<S>*>(base + o_v);
  U_ = reinterpret_cast<Force<S>*>(base + o_U);
  w_ = reinterpret_cast<Force<S>*>(base + o_w);
  D_ = reinterpret_cast<S*>(base + o_D);
  u_ = reinterpret_cast<S*>(base + o_u);
  for (std::size_t k = 0; k < level_size.size(); ++k) {
    aff_.push_back(reinterpret_cast<Affine6<S>*>(base + o_aff[k]));
    aff_carry_.push_back(reinterpret_cast<Vec6<S>*>(base + o_affc[k]));
    dual_.push_back(reinterpret_cast<HybridDual<DualScalar>*>(base + o_dual[k]));
    dual_carry_.push_back(reinterpret_cast<Mat5<DualScalar>*>(base + o_dualc[k]));
  }
  try {
    check(cudaMemcpy(base + o_body, host.body.data(), classes * sizeof(Body<S>), cudaMemcpyHostToDevice),
          "copying the chain's bodies");
    check(cudaMemcpy(base + o_phi, host.Phi.data(), classes * sizeof(InverseInertia<DualScalar>),
                     cudaMemcpyHostToDevice),
          "copying the chain's inverse inertias");
    check(cudaMemcpy(base + o_class, host.body_class.data(), static_cast<std::size_t>(n_) * sizeof(int),
                     cudaMemcpyHostToDevice),
          "copying the chain's body classes");
  } catch (...) {
    cudaFree(memory_);
    memory_ = nullptr;
    throw;
  }
}

template <class S>
ChainHybridPlan<S>::~ChainHybridPlan() {
  if (memory_) cudaFree(memory_);
}

template <class S>
cudaError_t ChainHybridPlan<S>::launch(const HybridBatchIn<S>& in, const unsigned char* prescribed,
                                       const BatchView<S>& qdd, const BatchView<S>& tau, int* failed,
                                       cudaStream_t stream) {
  const Index B = in.q.batch;
  if (B > max_batch_ || B < 0 || in.qd.batch != B || in.qdd.batch != B || in.tau.batch != B || qdd.batch != B ||
      tau.batch != B)
    return cudaErrorInvalidValue;
  if (B == 0) return cudaSuccess;
  if (!prescribed || !failed || !in.q.data || !in.qd.data || !in.qdd.data || !in.tau.data || !qdd.data || !tau.data)
    return cudaErrorInvalidValue;
  cudaError_t err = cudaMemsetAsync(failed, 0xff, static_cast<std::size_t>(B) * sizeof(int), stream);  // -1
  if (err != cudaSuccess) return err;
  // the chain on the device (as ChainHybridDynamics::compute binds it on the host)
  ChainHybridData<S> d;
  d.n = n_;
  d.batch = B;
  d.body = body_;
  d.Phi = Phi_;
  d.body_class = body_class_;
  d.a0 = a0_;
  d.v = v_;
  d.U = U_;
  d.D = D_;
  d.w = w_;
  d.u = u_;
  d.failed = failed;
  d.q = in.q;
  d.qd = in.qd;
  d.tau = in.tau;
  d.fext = in.fext;
  d.qdd = qdd;
  d.prescribed = prescribed;
  d.qdd_in = in.qdd;
  d.tau_out = tau;

  const std::vector<Index> size = level_sizes(d.count(), chunk_, fan_in_);
  const ChunkRange r{chunk_, d.count()};
  const Index chunks = size[0];
  const unsigned g = blocks(chunks);
  // pass 0: velocities (and pass 1's aggregates)
  hybrid_velocity_aggregate_kernel<<<g, kBlock, 0, stream>>>(d, r, chunks, aff_[0]);
  if ((err = scan_levels(size, aff_.data(), aff_carry_.data(), fan_in_, true, stream)) != cudaSuccess) return err;
  hybrid_velocity_walk_kernel<<<g, kBlock, 0, stream>>>(d, r, chunks, aff_carry_[0], dual_[0]);
  // pass 1: articulated inertias, prescribed joints rigid (and pass 2's aggregates)
  if ((err = scan_levels(size, dual_.data(), dual_carry_.data(), fan_in_, false, stream)) != cudaSuccess) return err;
  hybrid_inertia_walk_kernel<<<g, kBlock, 0, stream>>>(d, r, chunks, dual_carry_[0], aff_[0]);
  // pass 2: bias forces, prescribed accelerations included (and pass 3's aggregates)
  if ((err = scan_levels(size, aff_.data(), aff_carry_.data(), fan_in_, false, stream)) != cudaSuccess) return err;
  hybrid_bias_walk_kernel<<<g, kBlock, 0, stream>>>(d, r, chunks, aff_carry_[0], aff_[0]);
  // pass 3: accelerations and the prescribed joints' forces
  if ((err = scan_levels(size, aff_.data(), aff_carry_.data(), fan_in_, true, stream)) != cudaSuccess) return err;
  hybrid_acceleration_walk_kernel<<<g, kBlock, 0, stream>>>(d, r, chunks, aff_carry_[0]);
  return cudaGetLastError();
}

// ---- the engine ----------------------------------------------------------------

template <class S>
CudaChainHybridDynamics<S>::CudaChainHybridDynamics(const ModelTpl<S>& model,
                                                    const std::vector<unsigned char>& prescribed,
                                                    const BackendOptions& o)
    : n_(model.nv()), max_batch_(std::max<Index>(o.max_batch, 1)), prescribed_(prescribed) {
  if (static_cast<Index>(prescribed.size()) != n_)
    throw BackendError("backend 'cuda': the parallel chain hybrid dynamics: the prescribed mask has " +
                       std::to_string(prescribed.size()) + " entries for a model of " + std::to_string(n_) + " DoF");
  if (const std::string why = backend_unusable(BackendKind::Cuda); !why.empty())
    throw BackendError("backend 'cuda': " + why);
  check(cudaGetDevice(&device_), "cudaGetDevice");
  plan_ = std::make_unique<ChainHybridPlan<S>>(model, max_batch_);
  const std::size_t N = static_cast<std::size_t>(n_) * max_batch_;
  const std::size_t bytes = 6 * N * sizeof(S) + N * sizeof(Force<S>) + max_batch_ * sizeof(int) + N;
  check(cudaStreamCreateWithFlags(&stream_, cudaStreamNonBlocking), "cudaStreamCreateWithFlags");
  try {
    buffer_ = detail::device_malloc(bytes, [&](std::size_t free_bytes, std::size_t) {
      return "backend 'cuda': the parallel chain hybrid dynamics' staging of " + std::to_string(n_) + " DoF x " +
             std::to_string(max_batch_) + " instances needs " + std::to_string(bytes) + " bytes of device memory; " +
             std::to_string(free_bytes) + " are free";
    });
  } catch (...) {
    cudaStreamDestroy(stream_);
    throw;
  }
  S* p = static_cast<S*>(buffer_);
  for (int k = 0; k < 6; ++k) array_[k] = p + k * N;
  fext_ = reinterpret_cast<Force<S>*>(p + 6 * N);  // Force<S> is 6 S: aligned as S
  failed_ = reinterpret_cast<int*>(fext_ + N);
  mask_ = reinterpret_cast<unsigned char*>(failed_ + max_batch_);
  check(cudaMemcpy(mask_, prescribed_.data(), static_cast<std::size_t>(n_), cudaMemcpyHostToDevice), "copying the prescribed mask");
  host_.resize(6 * N);
  failed_host_.resize(static_cast<std::size_t>(max_batch_));
}

template <class S>
CudaChainHybridDynamics<S>::~CudaChainHybridDynamics() {
  if (buffer_) cudaFree(buffer_);
  if (stream_) cudaStreamDestroy(stream_);
}

template <class S>
BatchStatus CudaChainHybridDynamics<S>::compute(const HybridBatchIn<S>& in, const BatchView<S>& qdd,
                                                const BatchView<S>& tau) {
  check_batch(in, qdd, tau, max_batch_);
  const Index B = in.q.batch;
  if (B == 0) return {};
  const std::size_t NB = static_cast<std::size_t>(n_) * B;
  // inputs: q, qd, qdd in, tau in, SoA (n x B)
  const BatchView<const S>* src[4] = {&in.q, &in.qd, &in.qdd, &in.tau};
  for (int a = 0; a < 4; ++a) {
    S* h = host_.data() + a * NB;
    for (Index i = 0; i < n_; ++i)
      for (Index b = 0; b < B; ++b) h[i * B + b] = src[a]->at(i, b);
    check(cudaMemcpyAsync(array_[a], h, NB * sizeof(S), cudaMemcpyHostToDevice, stream_), "copying the inputs");
  }
  if (in.fext)
    check(cudaMemcpyAsync(fext_, in.fext, NB * sizeof(Force<S>), cudaMemcpyHostToDevice, stream_), "copying fext");
  auto soa = [&](int k) { return BatchView<const S>::soa(array_[k], n_, B); };
  const HybridBatchIn<S> din{soa(0), soa(1), soa(2), soa(3), in.fext ? fext_ : nullptr};
  check(compute_async(din, BatchView<S>::soa(array_[4], n_, B), BatchView<S>::soa(array_[5], n_, B), failed_, stream_),
        "launching the parallel chain hybrid dynamics");
  for (int k = 4; k < 6; ++k)
    check(cudaMemcpyAsync(host_.data() + k * NB, array_[k], NB * sizeof(S), cudaMemcpyDeviceToHost, stream_),
          "copying the outputs");
  check(cudaMemcpyAsync(failed_host_.data(), failed_, B * sizeof(int), cudaMemcpyDeviceToHost, stream_),
        "copying the failures");
  check(cudaStreamSynchronize(stream_), "running the parallel chain hybrid dynamics");
  const S* hq = host_.data() + 4 * NB;
  const S* ht = host_.data() + 5 * NB;
  for (Index b = 0; b < B; ++b)
    if (failed_host_[b] < 0)
      for (Index i = 0; i < n_; ++i) qdd.at(i, b) = hq[i * B + b], tau.at(i, b) = ht[i * B + b];
  return summarize_failures(failed_host_.data(), B, Failure::ArticulatedPivot);
}

template class ChainHybridPlan<float>;
template class ChainHybridPlan<double>;
template class CudaChainHybridDynamics<float>;
template class CudaChainHybridDynamics<double>;

}  // namespace cuda
}  // namespace scandyn
