// kernels/mass_matrix.cu: the batched mass matrix by the CRBA, one thread per
// instance up to kMaxThreadDofs DoF (its entries written by each thread, or staged
// by warps through shared memory for per-instance row-major outputs), one thread
// block per instance beyond.
//
// The layers of scandyn/cuda/mass_matrix.hpp: crba_instance (forward_dynamics.hpp)
// -> mass_matrix_instance (the header) -> crba_instances_kernel ->
// launch_crba_instances -> CudaMassMatrix (host staging through kernels/staging.hpp
// for compute(), the plain launch for compute_async()); beyond 64 DoF
// detail::CrbaBlocks (kernels/crba_block.hpp, defined in kernels/fd_dense.cu).
#include <cuda_runtime.h>

#include <string>
#include <type_traits>

#include "crba_block.hpp"
#include "scandyn/cuda/mass_matrix.hpp"
#include "staging.hpp"

namespace scandyn {
namespace cuda {

using detail::check;
using detail::copy;
using detail::plan;
using detail::Staging;

// ---- kernel and launch ---------------------------------------------------------

// The kernel's compile-time choices for capacity C and precision S, those of the
// JSI forward dynamics' kernel (FdKernelChoice in forward_dynamics.cu, measured there):
// float at capacity 8 unrolled, so that the packed M (36 scalars), the column
// forces and q stay in registers, held to 128 registers (4 resident blocks);
// double, and capacities 16..64, rolled, M and the forces in per-thread local
// memory. ptxas (sm_90, CUDA 13, block 128): float capacity 8 127 registers,
// 16..64 64; double 118 (240 unrolled at capacity 8); no spills; the stack frame
// holds the branch points' composite inertias and sin/cos's slow-path scratch
// (352 B at float capacity 8), and when rolled M and the column forces (24.9 KB
// per thread at double capacity 64). Not timed on a device yet (bench --algo
// mass --backend cuda prints both rows).
template <class S, int C>
struct MassKernelChoice {
  static constexpr bool kUnrolled = sizeof(S) == 4 && C <= 8;
  static constexpr int kMinBlocks = sizeof(S) == 8 ? 1 : 4;
};

// Warp-staged output (kStaged): a warp's 32 instances put their entries, kMassTileEntries
// at a time, into a shared tile (entry e of lane r at tile[e][r], rows padded to 33 so that
// neither the lanes' writes nor the reads below meet in a bank), then the warp stores the
// tile instance by instance: consecutive lanes write consecutive entries of one instance.
// With each instance's matrix contiguous (a (B, nv, nv) C-contiguous array, BatchView::aos)
// a store instruction covers 32 consecutive scalars instead of 32 lines nv^2 scalars apart.
// Tile: 4 warps x 32 x 33 scalars per block (16.9 KB float, 33.8 KB double).
constexpr int kWarpSize = 32;
constexpr int kMassTileEntries = 32;
constexpr int kMassTileRow = kWarpSize + 1;

// Stores a warp's staged entries first .. first + count - 1 of its instances b0 ..
// b0 + lanes - 1 (lanes <= 32): all of the warp's threads call it together.
template <class S>
__device__ __noinline__ void store_mass_tile(const S* tile, const BatchView<S> M_out, long long b0, int lanes,
                                             Index first, int count) {
  __syncwarp();
  const int lane = static_cast<int>(threadIdx.x) % kWarpSize;
  for (int k = lane; k < lanes * count; k += kWarpSize) {
    const int r = k / count, e = k - r * count;
    M_out.data[(b0 + r) * M_out.batch_stride + (first + e) * M_out.dof_stride] = tile[e * kMassTileRow + r];
  }
  __syncwarp();
}

// One thread per instance b < B: M(q) of instance b, all nv^2 entries, written by
// each thread (kStaged false: coalesced when instances are innermost, BatchView::soa)
// or staged by warps (kStaged true: coalesced when each instance's entries are).
// kFloating: the model has a floating base (crba_instance's kFloating).
template <class S, int C, bool kStaged, class Bd, bool kFloating = false>
__global__ void __launch_bounds__(kMassInstancesBlock, MassKernelChoice<S, C>::kMinBlocks)
    crba_instances_kernel(const __grid_constant__ ThreadModelParams<S, C, Bd> model, const BatchView<const S> q,
                          const BatchView<S> M_out) {
  constexpr bool kUnrolled = MassKernelChoice<S, C>::kUnrolled;
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if constexpr (!kStaged) {
    if (b >= q.batch) return;
    mass_matrix_instance<S, C, kUnrolled, Trig::Library, Bd, kFloating>(model, instance_column(q, b),
                                                                         instance_column(M_out, b));
  } else {
    static_assert(kMassInstancesBlock % kWarpSize == 0, "whole warps per block");
    __shared__ S tiles[kMassInstancesBlock / kWarpSize][kMassTileEntries * kMassTileRow];
    const int lane = static_cast<int>(threadIdx.x) % kWarpSize;
    const long long b0 = b - lane;  // the warp's first instance
    if (b0 >= q.batch) return;      // the whole warp (a uniform exit)
    const int lanes = static_cast<int>(q.batch - b0 < kWarpSize ? q.batch - b0 : kWarpSize);
    S* const tile = tiles[threadIdx.x / kWarpSize];
    // lanes past the batch compute the warp's last instance again (and store nothing),
    // so that every thread takes part in the tile's stores
    S M[C * (C + 1) / 2];
    FloatingMassRows<S, C, kFloating> base;
    crba_instance<S, C, kUnrolled, Trig::Library, Bd, kFloating>(
        model, instance_column(q, b0 + (lane < lanes ? lane : lanes - 1)), M, nullptr, &base);
    for_each_mass_entry<S, C, kUnrolled>(
        model, M,
        [&](Index e, S v) {
          const int slot = static_cast<int>(e % kMassTileEntries);
          tile[slot * kMassTileRow + lane] = v;
          if (slot == kMassTileEntries - 1) store_mass_tile(tile, M_out, b0, lanes, e - slot, kMassTileEntries);
        },
        &base);
    const Index n = kFloating ? model_nv(model) : model.nv;  // the matrix's order
    const Index entries = n * n;
    if (const int rest = static_cast<int>(entries % kMassTileEntries))
      store_mass_tile(tile, M_out, b0, lanes, entries - rest, rest);
  }
}

// The staged kernel when each instance's entries lie closer together than
// consecutive instances do (|dof_stride| < |batch_stride|: (B, nv, nv) arrays).
template <class S>
bool stage_mass_entries(const BatchView<S>& M_out) {
  const auto mag = [](std::ptrdiff_t s) { return s < 0 ? -s : s; };
  return M_out.batch > 1 && mag(M_out.dof_stride) < mag(M_out.batch_stride);
}

template <class S, class Bd>
cudaError_t launch_crba_instances(const ThreadModel<S, Bd>& model, const BatchView<const S>& q, const BatchView<S>& M_out,
                                  cudaStream_t stream) {
  const Index B = q.batch;
  if (B < 0 || M_out.batch != B) return cudaErrorInvalidValue;
  if (B == 0 || model.nv() == 0) return cudaSuccess;
  if (!q.data || !M_out.data) return cudaErrorInvalidValue;
  const unsigned blocks =
      static_cast<unsigned>((static_cast<long long>(B) + kMassInstancesBlock - 1) / kMassInstancesBlock);
  const bool staged = stage_mass_entries(M_out);
  visit_compiled_capacity(model.params(), [&](const auto& params) {
    using P = std::decay_t<decltype(params)>;
    constexpr bool kF = kFloatingKernels<S, Bd> && kFloatingCapacity<P::capacity>;
    if (floating_kernels(model)) {
      if constexpr (!kF) return;  // (refused by ThreadModel in this build)
      if (staged)
        crba_instances_kernel<S, P::capacity, true, Bd, kF>
            <<<blocks, kMassInstancesBlock, 0, stream>>>(params, q, M_out);
      else
        crba_instances_kernel<S, P::capacity, false, Bd, kF>
            <<<blocks, kMassInstancesBlock, 0, stream>>>(params, q, M_out);
    } else if (staged) {
      crba_instances_kernel<S, P::capacity, true, Bd><<<blocks, kMassInstancesBlock, 0, stream>>>(params, q, M_out);
    } else {
      crba_instances_kernel<S, P::capacity, false, Bd><<<blocks, kMassInstancesBlock, 0, stream>>>(params, q, M_out);
    }
  });
  return cudaGetLastError();
}

// ---- the engine -------------------------------------------------------------------

template <class S>
CudaMassMatrix<S>::CudaMassMatrix(const ModelTpl<S>& model, const BackendOptions& options)
    : nv_(model.nv()), nq_(model.nq()), nb_(model.nbodies()), max_batch_(options.max_batch) {
  if (options.strategy != IdStrategy::Auto && options.strategy != IdStrategy::Recursion)
    throw BackendError(std::string("backend 'cuda': strategy '") + to_string(options.strategy) +
                       "' is not available for the mass matrix (use auto or recursion)");
  // the thread kernels' bodies: past a floating base (which they hold apart). Models
  // they do not take (spherical joints; a floating base with more bodies past it)
  // run the general path.
  const Index thread_bodies = model.floating_base() ? nb_ - 1 : nv_;
  const bool general = takes_general_path(model);
  if (max_batch_ < 0) throw BackendError("backend 'cuda': max_batch " + std::to_string(max_batch_) + " is negative");
  const std::size_t n = static_cast<std::size_t>(nv_);
  // q (nq scalars) and M (nv^2) for max_batch instances
  staging_ = std::make_unique<detail::StagingBuffer>(max_batch_, nv_, sizeof(S) == 4 ? "float" : "double", "q and M",
                                                     (static_cast<std::size_t>(nq_) + n * n) * sizeof(S));
  device_ = staging_->device();
  if (general) general_ = std::make_unique<GeneralPlan<S>>(model, max_batch_);
  else if (thread_bodies > kMaxThreadDofs) blocks_ = std::make_unique<detail::CrbaBlocks<S>>(model, max_batch_);
  else thread_ = std::make_unique<ZThreadModel<S>>(model), require_floating_capacity(*thread_, model.name);
  bytes_ = staging_->bytes() + (blocks_ ? blocks_->device_bytes() : 0) + (general_ ? general_->device_bytes() : 0);
}

template <class S>
CudaMassMatrix<S>::~CudaMassMatrix() = default;

template <class S>
cudaError_t CudaMassMatrix<S>::compute_async(const BatchView<const S>& q, const BatchView<S>& M, cudaStream_t stream) {
  if (general_) return general_->launch_crba(q, M, stream);
  return blocks_ ? blocks_->launch(q, M, stream) : launch_crba_instances(*thread_, q, M, stream);
}

template <class S>
void CudaMassMatrix<S>::compute(const BatchView<const S>& q, const BatchView<S>& M) {
  const Index B = q.batch;
  if (M.batch != B)
    throw BackendError("batch sizes disagree: q " + std::to_string(B) + ", M " + std::to_string(M.batch));
  if (B < 0) throw BackendError("negative batch size " + std::to_string(B));
  if (B > max_batch_)
    throw BackendError("batch of " + std::to_string(B) + " instances exceeds the engine's max_batch " +
                       std::to_string(max_batch_));
  if (B > 0 && (!q.data || !M.data))
    throw BackendError("null data pointer in a batch of " + std::to_string(B) + " instances");
  const Index nv = nv_;
  if (B == 0 || nv == 0) return;
  // staging buffer: q (nq x max_batch), then M (nv^2 x max_batch)
  const std::size_t qcap = static_cast<std::size_t>(nq_) * max_batch_;
  const std::size_t mcap = static_cast<std::size_t>(nv) * nv * max_batch_;
  const Index entries = nv * nv;  // M's entries per instance
  S* const dq = static_cast<S*>(staging_->data());
  S* const dM = dq + qcap;
  const cudaStream_t stream = staging_->stream();

  // copy in, in whatever layout keeps the copies few
  const Staging sM = plan(M, entries, mcap, true, "M");
  const Staging sq = plan(q, nq_, qcap, false);
  check(copy(sq, q, nq_, dq, cudaMemcpyHostToDevice, stream), "copying q to the device");
  // run
  check(compute_async(sq.device_view<const S>(dq, B), sM.device_view(dM, B), stream),
        general_ ? "launching crba_general_kernel"
        : blocks_ ? "launching the CRBA (a block per instance)" : "launching crba_instances_kernel");
  // copy out: M's entries only
  check(copy(sM, M, entries, dM, cudaMemcpyDeviceToHost, stream), "copying M to the host");
  check(cudaStreamSynchronize(stream), general_ ? "running crba_general_kernel"
                                       : blocks_ ? "running the CRBA (a block per instance)" : "running crba_instances_kernel");
}

#define SCANDYN_INSTANTIATE(S)         \
  template class CudaMassMatrix<S>;   \
  template cudaError_t launch_crba_instances(const ThreadModel<S>&, const BatchView<const S>&, const BatchView<S>&, \
                                             cudaStream_t);                                                       \
  template cudaError_t launch_crba_instances(const ZThreadModel<S>&, const BatchView<const S>&, const BatchView<S>&, \
                                             cudaStream_t);
SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)
#undef SCANDYN_INSTANTIATE

}  // namespace cuda
}  // namespace scandyn
