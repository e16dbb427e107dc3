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

namespace scandyn {
namespace cuda {

using detail::check;

namespace {

// pass 0's aggregates: velocities (velocity_aggregate reads no mask: the chain FD's)
// and, when run_agg is not null, the runs' composites (RigidComposite)
template <class S>
__global__ void hybrid_aggregate_kernel(const ChainHybridData<S> d, ChunkRange r, Index chunks, Affine6<S>* agg,
                                        HybridRun<S>* run_agg) {
  SCANDYN_CHUNK_INDEX;
  agg[c] = velocity_aggregate<S, false>(d, s, e);
  if (run_agg) run_agg[c] = hybrid_composite_aggregate(d, s, e);
}

// pass 0's walks: v, and pass 1's aggregates (HybridDual); run_after: S_{e+1} per
// chunk, the run scan's carries (scanned) or walked and written here
template <class S>
__global__ void hybrid_velocity_walk_kernel(const ChainHybridData<S> d, ChunkRange r, Index chunks,
                                            const Vec6<S>* carry, HybridRun<S>* run_after, bool scanned,
                                            HybridDual<DualScalar>* dual) {
  SCANDYN_CHUNK_INDEX;
  dual[c] = hybrid_velocity_walk(d, s, e, carry[c], run_after[c], scanned);
}

// pass 1's walks from the carried dual and S_{e+1} (prescribed joints rigid): U, D, w;
// pass 2's aggregates
template <class S>
__global__ void hybrid_inertia_walk_kernel(const ChainHybridData<S> d, ChunkRange r, Index chunks,
                                           const Mat5<DualScalar>* dual_carry, const HybridRun<S>* run_after,
                                           Affine6<S>* agg) {
  SCANDYN_CHUNK_INDEX;
  agg[c] = hybrid_inertia_walk(d, s, e, hybrid_inertia_carry(d, e, dual_carry[c], run_after[c]));
}

// pass 3's walks: qdd and tau
template <class S>
__global__ void hybrid_acceleration_walk_kernel(const ChainHybridData<S> d, ChunkRange r, Index chunks,
                                                const Vec6<S>* carry) {
  SCANDYN_CHUNK_INDEX;
  hybrid_acceleration_walk(d, s, e, carry[c]);
}

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
  DeviceLayout m;
  const ChainTablesLayout<S> tables(m, host, links);
  const LevelsLayout<Affine6<S>> aff(m, level_size);
  const LevelsLayout<HybridDual<DualScalar>> dual(m, level_size);
  const LevelsLayout<HybridRun<S>> run(m, level_size);
  bytes_ = m.bytes;
  memory_ = allocate_chain(m, tables, host,
                           "backend 'cuda': the parallel chain hybrid dynamics of " + std::to_string(n_) + " links x " +
                               std::to_string(max_batch_) + " instances");
  chain_ = tables.pointers(memory_);
  aff.pointers(memory_, aff_, aff_carry_);
  dual.pointers(memory_, dual_, dual_carry_);
  run.pointers(memory_, run_, run_carry_);
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
  chain_.bind(d);
  d.a0 = a0_;
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
  // pass 0: velocities and the runs' composites S_{e+1} at the chunk boundaries
  // (scanned, or walked by each chunk's thread); pass 1's aggregates
  hybrid_aggregate_kernel<<<g, kBlock, 0, stream>>>(d, r, chunks, aff_[0], scan_runs_ ? run_[0] : nullptr);
  if ((err = scan_levels(size, aff_.data(), aff_carry_.data(), fan_in_, true, stream)) != cudaSuccess) return err;
  if (scan_runs_ && (err = scan_levels(size, run_.data(), run_carry_.data(), fan_in_, false, stream)) != cudaSuccess)
    return err;
  hybrid_velocity_walk_kernel<<<g, kBlock, 0, stream>>>(d, r, chunks, aff_carry_[0], run_carry_[0], scan_runs_,
                                                        dual_[0]);
  // pass 1: articulated inertias, prescribed joints rigid (and pass 2's aggregates)
  if ((err = scan_levels(size, dual_.data(), dual_carry_.data(), fan_in_, false, stream)) != cudaSuccess) return err;
  hybrid_inertia_walk_kernel<<<g, kBlock, 0, stream>>>(d, r, chunks, dual_carry_[0], run_carry_[0], aff_[0]);
  // pass 2: bias forces, prescribed accelerations included (and pass 3's aggregates)
  if ((err = scan_levels(size, aff_.data(), aff_carry_.data(), fan_in_, false, stream)) != cudaSuccess) return err;
  chunk_walk_kernel<&hybrid_bias_walk<S>><<<g, kBlock, 0, stream>>>(d, r, chunks, aff_carry_[0], aff_[0]);
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
  plan_->set_scan_runs(hybrid_scans_runs(prescribed_, plan_->chunk(), HybridRunScan::Auto));
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
