// The CUDA driver of the chain forward dynamics (scandyn/cuda/chain_fd.hpp): the
// walks and scans of scandyn/algorithm/chain_fd.hpp, one thread per chunk.
#include <cuda_runtime.h>

#include <algorithm>
#include <chrono>
#include <climits>
#include <cstring>
#include <string>
#include <utility>
#include <vector>

#include "scandyn/cuda/chain_fd.hpp"
#include "chain_scan.cuh"
#include "staging.hpp"

namespace scandyn {
namespace cuda {

using detail::check;

namespace {

template <class S, bool kB>
__global__ void velocity_aggregate_kernel(const ChainFdData<S, kB> d, ChunkRange r, Index chunks, Affine6<S>* agg) {
  const Index c = static_cast<Index>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (c < chunks) agg[c] = velocity_aggregate(d, r.first(c), r.last(c));
}

template <bool kDual, class S, bool kB>
__global__ void velocity_walk_kernel(const ChainFdData<S, kB> d, ChunkRange r, Index chunks, const Vec6<S>* carry,
                                     DualRiccati<DualScalar>* dual) {
  const Index c = static_cast<Index>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (c >= chunks) return;
  const DualRiccati<DualScalar> agg = velocity_walk<kDual>(d, r.first(c), r.last(c), carry[c]);
  if constexpr (kDual) dual[c] = agg;
}

// Pass 1's walks of chunks [c0, c1): from the dual carries (parallel) or the host's
// articulated inertias (hybrid).
template <class S, bool kB>
__global__ void inertia_walk_kernel(const ChainFdData<S, kB> d, ChunkRange r, Index c0, Index c1, const Mat5<DualScalar>* dual_carry,
                                    const ABInertia<S>* Ia_carry, Affine6<S>* agg) {
  const Index c = c0 + static_cast<Index>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (c >= c1) return;
  const Index e = r.last(c);
  const ABInertia<S> Ia = dual_carry ? chunk_inertia_carry(d, e, dual_carry[c]) : Ia_carry[c];
  agg[c] = inertia_walk(d, r.first(c), e, Ia);
}

template <class S, bool kB>
__global__ void acceleration_walk_kernel(const ChainFdData<S, kB> d, ChunkRange r, Index chunks, const Vec6<S>* carry) {
  const Index c = static_cast<Index>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (c < chunks) acceleration_walk(d, r.first(c), r.last(c), carry[c]);
}

}  // namespace

template <class S>
ChainFdPlan<S>::ChainFdPlan(const ModelTpl<S>& model, Index max_batch, Index chunk, Index fan_in, bool directional)
    : n_(model.nbodies()),
      max_batch_(std::max<Index>(max_batch, 1)),
      chunk_(chunk > 0 ? chunk : kDefaultChunk),
      fan_in_(fan_in > 1 ? fan_in : kDefaultFanIn) {
  host_ = ChainBodies<S>::from(model, max_batch_);
  floating_ = model.floating_base();
  if (directional && floating_)
    throw BackendError("backend 'cuda': the parallel chain JVP / VJP of forward dynamics takes chains of 1-DoF joints "
                       "from a fixed base; body 0 (joint '" + model.joint_names[0] + "') is a floating base (a free rope)");
  a0_ = base_acceleration(model.gravity);
  const std::size_t links = static_cast<std::size_t>(n_) * max_batch_;
  level_size_ = level_sizes(static_cast<Index>(links), chunk_, fan_in_);
  const std::size_t chunks = static_cast<std::size_t>(level_size_[0]);
  // one allocation: tables, per-link scratch, per-level aggregates and carries
  DeviceLayout m;
  const ChainTablesLayout<S> tables(m, host_, links);
  const std::size_t o_Ia = m.take(chunks * sizeof(ABInertia<S>));
  // a floating base's IA_0, acceleration and qdd per instance
  const std::size_t nbase = floating_ ? static_cast<std::size_t>(max_batch_) : 0;
  const std::size_t o_IAb = m.take(nbase * sizeof(ABInertia<S>)), o_ab = m.take(nbase * sizeof(Motion<S>)),
                    o_qddb = m.take(nbase * sizeof(Vec6<S>));
  // the directional scratch
  const std::size_t nd = directional ? links : 0;
  const std::size_t o_a = m.take(nd * sizeof(Motion<S>)), o_F = m.take(nd * sizeof(Force<S>)),
                    o_dv = m.take(nd * sizeof(Motion<S>)), o_df = m.take(nd * sizeof(Force<S>)),
                    o_x = m.take(nd * sizeof(S)), o_IA = m.take(nd * sizeof(ABInertia<S>));
  const LevelsLayout<Affine6<S>> aff(m, level_size_);
  const LevelsLayout<DualRiccati<DualScalar>> dual(m, level_size_);
  bytes_ = m.bytes;
  memory_ = allocate_chain(m, tables, host_,
                           "backend 'cuda': the chain forward dynamics of " + std::to_string(n_) + " links x " +
                               std::to_string(max_batch_) + " instances");
  chain_ = tables.pointers(memory_);
  Ia_carry_ = at_offset<ABInertia<S>>(memory_, o_Ia);
  if (floating_) {
    IA_base_ = at_offset<ABInertia<S>>(memory_, o_IAb);
    a_base_ = at_offset<Motion<S>>(memory_, o_ab);
    qdd_base_ = at_offset<Vec6<S>>(memory_, o_qddb);
  }
  if (directional) {
    a_ = at_offset<Motion<S>>(memory_, o_a);
    F_ = at_offset<Force<S>>(memory_, o_F);
    dv_ = at_offset<Motion<S>>(memory_, o_dv);
    df_ = at_offset<Force<S>>(memory_, o_df);
    x_ = at_offset<S>(memory_, o_x);
    IA_ = at_offset<ABInertia<S>>(memory_, o_IA);
  }
  aff.pointers(memory_, aff_, aff_carry_);
  dual.pointers(memory_, dual_, dual_carry_);
  check(cudaMallocHost(&Ia_pinned_, chunks * sizeof(ABInertia<S>)), "allocating pinned memory");
  set_host_threads(0);
}

template <class S>
void ChainFdPlan<S>::set_host_threads(int threads) {
  carries_ = std::make_unique<ChainInertiaCarries<S>>(threads);
  // 4, then 2 per walk group: at most groups per range x (threads + 1) ranges
  const std::size_t want = 4 + 2 * static_cast<std::size_t>(carries_->groups()) * (carries_->threads() + 1);
  while (events_.size() < want) {
    cudaEvent_t e = nullptr;
    check(cudaEventCreate(&e), "cudaEventCreate");
    events_.push_back(e);
  }
}

template <class S>
int ChainFdPlan<S>::host_threads() const {
  return carries_->threads();
}

template <class S>
ChainFdPlan<S>::~ChainFdPlan() {
  for (auto& e : events_) cudaEventDestroy(e);
  if (Ia_pinned_) cudaFreeHost(Ia_pinned_);
  if (memory_) cudaFree(memory_);
}

template <class S>
template <bool kB>
ChainFdData<S, kB> ChainFdPlan<S>::data(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed) const {
  ChainFdData<S, kB> d;
  d.n = n_;
  d.bind(in, qdd);
  chain_.bind(d);
  d.a0 = a0_;
  d.a = a_;  // null unless directional
  d.failed = failed;
  if (floating_) d.bind_base(IA_base_, a_base_, qdd_base_);
  return d;
}

template <class S>
template <bool kB>
cudaError_t ChainFdPlan<S>::velocities(const ChainFdData<S, kB>& d, bool dual, cudaStream_t stream) {
  const std::vector<Index> size = level_sizes(d.count(), chunk_, fan_in_);
  const ChunkRange r{chunk_, d.count()};
  const Index chunks = size[0];
  velocity_aggregate_kernel<<<blocks(chunks), kBlock, 0, stream>>>(d, r, chunks, aff_[0]);
  cudaError_t err = scan_levels(size, aff_.data(), aff_carry_.data(), fan_in_, true, stream);
  if (err != cudaSuccess) return err;
  if (dual) velocity_walk_kernel<true><<<blocks(chunks), kBlock, 0, stream>>>(d, r, chunks, aff_carry_[0], dual_[0]);
  else velocity_walk_kernel<false><<<blocks(chunks), kBlock, 0, stream>>>(d, r, chunks, aff_carry_[0],
                                                                        static_cast<DualRiccati<DualScalar>*>(nullptr));
  return cudaGetLastError();
}

template <class S>
template <bool kB>
cudaError_t ChainFdPlan<S>::finish(const ChainFdData<S, kB>& d, cudaStream_t stream) {
  const std::vector<Index> size = level_sizes(d.count(), chunk_, fan_in_);
  const ChunkRange r{chunk_, d.count()};
  const Index chunks = size[0];
  cudaError_t err = scan_levels(size, aff_.data(), aff_carry_.data(), fan_in_, false, stream);
  if (err != cudaSuccess) return err;
  chunk_walk_kernel<&bias_walk<S, kB>><<<blocks(chunks), kBlock, 0, stream>>>(d, r, chunks, aff_carry_[0], aff_[0]);
  err = scan_levels(size, aff_.data(), aff_carry_.data(), fan_in_, true, stream);
  if (err != cudaSuccess) return err;
  acceleration_walk_kernel<<<blocks(chunks), kBlock, 0, stream>>>(d, r, chunks, aff_carry_[0]);
  return cudaGetLastError();
}

template <class S>
cudaError_t ChainFdPlan<S>::launch(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed, cudaStream_t stream) {
  const Index B = in.q.batch;
  if (B > max_batch_ || B < 0) return cudaErrorInvalidValue;
  if (B == 0) return cudaSuccess;
  const cudaError_t err = cudaMemsetAsync(failed, 0xff, static_cast<std::size_t>(B) * sizeof(int), stream);  // -1
  if (err != cudaSuccess) return err;
  return floating_ ? passes(data<true>(in, qdd, failed), stream) : passes(data<false>(in, qdd, failed), stream);
}

template <class S>
template <bool kB>
cudaError_t ChainFdPlan<S>::passes(const ChainFdData<S, kB>& d, cudaStream_t stream) {
  cudaError_t err = cudaSuccess;
  const std::vector<Index> size = level_sizes(d.count(), chunk_, fan_in_);
  const ChunkRange r{chunk_, d.count()};
  const Index chunks = size[0];
  if ((err = velocities(d, true, stream)) != cudaSuccess) return err;
  if ((err = scan_levels(size, dual_.data(), dual_carry_.data(), fan_in_, false, stream)) != cudaSuccess) return err;
  inertia_walk_kernel<<<blocks(chunks), kBlock, 0, stream>>>(d, r, Index(0), chunks, dual_carry_[0],
                                                             static_cast<const ABInertia<S>*>(nullptr), aff_[0]);
  return finish(d, stream);
}

namespace {

// launch_hybrid's queue: called on the calling thread by ChainInertiaCarries::compute
// as chunks' carries are written; copies them to the device and queues their walks
// (events before and after the kernel when timed).
template <class S>
struct HybridQueue {
  ChainFdData<S> d;
  ChunkRange r;
  cudaStream_t stream;
  const ABInertia<S>* pinned;
  ABInertia<S>* carry;
  Affine6<S>* agg;
  const cudaEvent_t* events;  // 2 per group, or null
  std::size_t capacity;       // groups the events hold
  std::vector<std::pair<Index, Index>>* groups;  // (c_lo, c_hi) per group, in queue order
  cudaError_t err = cudaSuccess;

  static void ready(void* self, Index c_lo, Index c_hi) {
    HybridQueue& q = *static_cast<HybridQueue*>(self);
    if (q.err != cudaSuccess) return;
    const std::size_t k = q.groups->size();
    const bool timed = q.events && k < q.capacity;
    const std::size_t bytes = static_cast<std::size_t>(c_hi - c_lo) * sizeof(ABInertia<S>);
    if ((q.err = cudaMemcpyAsync(q.carry + c_lo, q.pinned + c_lo, bytes, cudaMemcpyHostToDevice, q.stream)) !=
        cudaSuccess)
      return;
    if (timed && (q.err = cudaEventRecord(q.events[2 * k], q.stream)) != cudaSuccess) return;
    inertia_walk_kernel<<<blocks(c_hi - c_lo), kBlock, 0, q.stream>>>(
        q.d, q.r, c_lo, c_hi, static_cast<const Mat5<DualScalar>*>(nullptr), q.carry, q.agg);
    if ((q.err = cudaGetLastError()) != cudaSuccess) return;
    if (timed && (q.err = cudaEventRecord(q.events[2 * k + 1], q.stream)) != cudaSuccess) return;
    q.groups->emplace_back(c_lo, c_hi);
  }
};

}  // namespace

template <class S>
cudaError_t ChainFdPlan<S>::launch_hybrid(const BatchView<const S>& q_host, const FdBatchIn<S>& in,
                                          const BatchView<S>& qdd, int* failed, cudaStream_t stream,
                                          std::vector<ChainTimelineEvent>* timeline) {
  using clock = std::chrono::steady_clock;
  const auto t0 = clock::now();
  const Index B = in.q.batch;
  if (B > max_batch_ || B < 0 || q_host.batch != B) return cudaErrorInvalidValue;
  if (floating_) return cudaErrorNotSupported;  // the host recursion takes 1-DoF joints (the engine refuses hybrid)
  if (B == 0) return cudaSuccess;
  cudaError_t err = cudaMemsetAsync(failed, 0xff, static_cast<std::size_t>(B) * sizeof(int), stream);
  if (err != cudaSuccess) return err;
  const bool timed = timeline != nullptr;
  cudaEvent_t start = events_[0], after_velocities = events_[1], before_finish = events_[2], end = events_[3];
  if (timed && (err = cudaEventRecord(start, stream)) != cudaSuccess) return err;
  const ChainFdData<S> d = data<false>(in, qdd, failed);
  const Index count = d.count();
  const ChunkRange r{chunk_, count};
  // the device: velocities (no dual aggregates) while the host starts
  if ((err = velocities(d, false, stream)) != cudaSuccess) return err;
  if (timed && (err = cudaEventRecord(after_velocities, stream)) != cudaSuccess) return err;
  // the host: the articulated inertias at the chunk boundaries (ChainInertiaCarries on
  // host_threads() threads) from q_host; each group's walks queued as soon as its
  // carries are written
  ChainFdData<S> h;  // the chain on the host: its constants and q_host
  h.n = n_;
  h.batch = B;
  h.q = q_host;
  h.body = host_.body.data();
  h.Phi = host_.Phi.data();
  h.body_class = host_.body_class.data();
  std::vector<std::pair<Index, Index>> groups;
  groups.reserve((events_.size() - 4) / 2);
  HybridQueue<S> queue{d, r, stream, Ia_pinned_, Ia_carry_, aff_[0], timed ? events_.data() + 4 : nullptr,
                       (events_.size() - 4) / 2, &groups};
  carries_->compute(h, chunk_, Ia_pinned_, &HybridQueue<S>::ready, &queue, timed ? &t0 : nullptr);
  if (queue.err != cudaSuccess) return queue.err;
  if (timed && (err = cudaEventRecord(before_finish, stream)) != cudaSuccess) return err;
  if ((err = finish(d, stream)) != cudaSuccess) return err;
  if (timed && (err = cudaEventRecord(end, stream)) != cudaSuccess) return err;
  if (timed) {
    if ((err = cudaEventSynchronize(end)) != cudaSuccess) return err;
    auto gpu_ms = [&](cudaEvent_t e) {
      float ms = 0;
      cudaEventElapsedTime(&ms, start, e);
      return double(ms);
    };
    std::vector<ChainTimelineEvent> tl;
    tl.push_back({"gpu velocities", 0.0, gpu_ms(after_velocities)});
    for (const ChainCarryInterval& iv : carries_->intervals()) {
      if (iv.start_ms < 0) continue;
      const char* what = iv.kind == ChainCarryInterval::Walk ? "cpu walk"
                         : iv.kind == ChainCarryInterval::Reduce ? "cpu reduce" : "cpu combine";
      tl.push_back({what, iv.start_ms, iv.end_ms, iv.thread, iv.c_lo, iv.c_hi});
    }
    const std::size_t timed_groups = std::min(groups.size(), queue.capacity);
    for (std::size_t k = 0; k < timed_groups; ++k)
      tl.push_back({"gpu walk", gpu_ms(events_[4 + 2 * k]), gpu_ms(events_[4 + 2 * k + 1]), -1, groups[k].first,
                    groups[k].second});
    tl.push_back({"gpu finish", gpu_ms(before_finish), gpu_ms(end)});
    *timeline = std::move(tl);
  }
  return cudaGetLastError();
}

template class ChainFdPlan<float>;
template class ChainFdPlan<double>;
// used by launch_jvp / launch_vjp (kernels/chain_directional.cu)
template cudaError_t ChainFdPlan<float>::passes<false>(const ChainFdData<float, false>&, cudaStream_t);
template cudaError_t ChainFdPlan<double>::passes<false>(const ChainFdData<double, false>&, cudaStream_t);
template cudaError_t ChainFdPlan<float>::finish<false>(const ChainFdData<float, false>&, cudaStream_t);
template cudaError_t ChainFdPlan<double>::finish<false>(const ChainFdData<double, false>&, cudaStream_t);
template ChainFdData<float, false> ChainFdPlan<float>::data<false>(const FdBatchIn<float>&, const BatchView<float>&,
                                                                   int*) const;
template ChainFdData<double, false> ChainFdPlan<double>::data<false>(const FdBatchIn<double>&,
                                                                     const BatchView<double>&, int*) const;

}  // namespace cuda
}  // namespace scandyn
