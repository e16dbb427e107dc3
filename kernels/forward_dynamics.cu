// kernels/forward_dynamics.cu: batched forward dynamics by the joint-space inertia or
// the articulated-body algorithm, one thread per instance.
//
// The layers of scandyn/cuda/forward_dynamics.hpp: fd_jsi_instance / aba_instance
// (the header) -> fd_instances_kernel -> launch_fd_jsi_instances /
// launch_aba_instances -> CudaForwardDynamics (host staging for compute(): the
// pinned chunked pipeline of kernels/host_pipeline.hpp for the thread strategies,
// or the pageable copies of kernels/staging.hpp; the plain launch for
// compute_async()).
#include <cuda_runtime.h>

#include <algorithm>
#include <string>
#include <type_traits>

#include "scandyn/cuda/device.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/cuda/fd_check.hpp"
#include "host_pipeline.hpp"
#include "staging.hpp"

namespace scandyn {
namespace cuda {

using detail::check;
using detail::copy;
using detail::plan;
using detail::Staging;

// ---- kernel and launch ---------------------------------------------------------

// fd_instances_kernel's algorithm argument: the joint-space inertia, or the ABA with
// aba_instance's kSlots branch slots (0: chains; kAbaRegisterSlots; C: any tree).
inline constexpr int kJsiKernel = -1;

// The kernels' compile-time choices for capacity C, precision S and algorithm kAlgo
// (kJsiKernel or the ABA's kSlots); ptxas, sm_90, CUDA 13, block 128:
//   JSI: measured on the H100 (bench_cuda_fd, iiwa, 10^7 instances): fastest in
//        float unrolled at capacity 8 and held to 128 registers (4 resident blocks;
//        4.4 ms against 5.6 ms with 167), in double with the loops rolled (8.8 ms
//        against 9.6 ms unrolled and spilling at 255 registers).
//   ABA: float rolled and held to 128 registers (4 resident blocks), chains, slots
//        and trees alike: measured on the H100 (10^7 instances) iiwa 3.3 ms against
//        5.2 unrolled in 168 registers and 7.7 in 255; atlas with its register slot
//        22.8 ms against 25.2 in 152 registers (88 B of spill stores at 128 cost
//        less than the lost block). Double rolled, up to 255 registers (226 for
//        chains, 240 for trees; unrolled it spills and takes 12.0 ms against 7.5 on
//        iiwa). Sin and cos as the inverse dynamics (kThreadTrig: the SFU in float).
template <class S, int C, int kAlgo>
struct FdKernelChoice {
  static constexpr bool kAba = kAlgo != kJsiKernel;
  static constexpr bool kUnrolled = sizeof(S) == 4 && C <= 8 && !kAba;
  static constexpr int kMinBlocks = sizeof(S) == 8 ? 1 : 4;
};

// One thread per instance b < B: the forward dynamics of instance b, by the
// joint-space inertia (kAlgo == kJsiKernel) or the ABA with kAlgo branch slots.
// kFloating (ABA only): the model has a floating base (aba_instance's kFloating).
template <class S, int C, int kAlgo, class Bd, bool kFloating = false>
__global__ void __launch_bounds__(kFdInstancesBlock, FdKernelChoice<S, C, kAlgo>::kMinBlocks)
    fd_instances_kernel(const __grid_constant__ ThreadModelParams<S, C, Bd> model, const FdBatchIn<S> batch_in,
                        const BatchView<S> qdd_out, int* const failed_dof_out) {
  using Choice = FdKernelChoice<S, C, kAlgo>;
  static_assert(Choice::kAba || !kFloating, "fd_instances_kernel: the JSI kernels take a fixed base");
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= batch_in.q.batch) return;
  const Force<S>* fext = batch_in.fext ? batch_in.fext + b * (kFloating ? model_nbodies(model) : model.nv) : nullptr;
  const DofColumn<const S> q = instance_column(batch_in.q, b), qd = instance_column(batch_in.qd, b),
                           tau = instance_column(batch_in.tau, b);
  if constexpr (Choice::kAba)
    failed_dof_out[b] = aba_instance<S, C, false, Choice::kUnrolled, kThreadTrig<S>, kAlgo, false, Bd, kFloating>(
        model, q, qd, tau, fext, instance_column(qdd_out, b));
  else
    failed_dof_out[b] =
        fd_jsi_instance<S, C, false, Choice::kUnrolled>(model, q, qd, tau, fext, instance_column(qdd_out, b));
}

namespace {

// The checks and the launch of launch_fd_jsi_instances and launch_aba_instances.
template <bool kAba, class S, class Bd>
cudaError_t launch_fd_instances(const ThreadModel<S, Bd>& model, const FdBatchIn<S>& batch_in, const BatchView<S>& qdd_out,
                                int* failed_dof_out, cudaStream_t stream) {
  const Index B = batch_in.q.batch;
  if (B < 0 || batch_in.qd.batch != B || batch_in.tau.batch != B || qdd_out.batch != B) return cudaErrorInvalidValue;
  if (B == 0) return cudaSuccess;
  if (!failed_dof_out) return cudaErrorInvalidValue;
  if (model.nv() > 0 && (!batch_in.q.data || !batch_in.qd.data || !batch_in.tau.data || !qdd_out.data))
    return cudaErrorInvalidValue;
  const unsigned blocks = static_cast<unsigned>((static_cast<long long>(B) + kFdInstancesBlock - 1) / kFdInstancesBlock);
  auto launch = [&](const auto& params, auto algo) {
    constexpr int C = std::decay_t<decltype(params)>::capacity;
    if constexpr (kAba && kFloatingKernels<S, Bd> && kFloatingCapacity<C>) {
      if (model.floating()) {
        fd_instances_kernel<S, C, decltype(algo)::value, Bd, true>
            <<<blocks, kFdInstancesBlock, 0, stream>>>(params, batch_in, qdd_out, failed_dof_out);
        return;
      }
    }
    fd_instances_kernel<S, C, decltype(algo)::value, Bd>
        <<<blocks, kFdInstancesBlock, 0, stream>>>(params, batch_in, qdd_out, failed_dof_out);
  };
  if constexpr (kAba) {
    visit_aba_kernel(model, launch);
  } else {
    if (model.floating()) return cudaErrorNotSupported;  // (the engine refuses it first)
    visit_compiled_capacity(model.params(),
                            [&](const auto& params) { launch(params, std::integral_constant<int, kJsiKernel>{}); });
  }
  return cudaGetLastError();
}

}  // namespace

template <class S, class Bd>
cudaError_t launch_fd_jsi_instances(const ThreadModel<S, Bd>& model, const FdBatchIn<S>& batch_in,
                                    const BatchView<S>& qdd_out, int* failed_dof_out, cudaStream_t stream) {
  return launch_fd_instances<false>(model, batch_in, qdd_out, failed_dof_out, stream);
}

template <class S, class Bd>
cudaError_t launch_aba_instances(const ThreadModel<S, Bd>& model, const FdBatchIn<S>& batch_in,
                                 const BatchView<S>& qdd_out, int* failed_dof_out, cudaStream_t stream) {
  return launch_fd_instances<true>(model, batch_in, qdd_out, failed_dof_out, stream);
}

// ---- the engine -------------------------------------------------------------------

template <class S>
CudaForwardDynamics<S>::CudaForwardDynamics(const ModelTpl<S>& model, BackendOptions options, FdMethod method)
    : CudaForwardDynamics(model, (options.fd_method = method, options)) {}

template <class S>
CudaForwardDynamics<S>::CudaForwardDynamics(const ModelTpl<S>& model, const BackendOptions& options)
    : nv_(model.nv()), nq_(model.nq()), nb_(model.nbodies()), max_batch_(options.max_batch) {
  FdMethod algorithm = options.fd_method;
  if (options.strategy != IdStrategy::Auto && options.strategy != IdStrategy::Recursion)
    throw BackendError(std::string("backend 'cuda': strategy '") + to_string(options.strategy) +
                       "' is not available for forward dynamics (use auto or recursion)");
  if (algorithm == FdMethod::Auto) algorithm = choose_fd_method(BackendKind::Cuda, model, 1, 1);
  algorithm_ = algorithm;
  aba_ = algorithm == FdMethod::Aba;
  const bool chain = algorithm == FdMethod::Parallel || algorithm == FdMethod::Hybrid;
  // the thread kernels' bodies: past a floating base (which they hold apart). The ABA
  // of models they do not take (spherical joints; a floating base with more bodies
  // past it; 1-DoF joints beyond kMaxThreadDofs) runs the general path, one thread per
  // instance, O(nv) each.
  const Index thread_bodies = model.floating_base() ? nb_ - 1 : nv_;
  const bool general = aba_ && (takes_general_path(model) || thread_bodies > kMaxThreadDofs);
  if (model.multi_dof() && !chain && algorithm != FdMethod::Aba)
    throw BackendError(std::string("backend 'cuda': model '") + model.name +
                       "' has multi-DoF joints (a floating base or spherical joints), which forward dynamics by " +
                       to_string(algorithm) + " does not take on this backend (use aba, or parallel for a free rope)");
  // q, qd, tau, qdd (nq scalars each, detail::stage_inputs), fext (6 nq) and a failed DoF for
  // max_batch instances
  staging_ = std::make_unique<detail::StagingBuffer>(
      max_batch_, nv_, sizeof(S) == 4 ? "float" : "double", "q, qd, tau, qdd, fext and a failed DoF",
      10 * static_cast<std::size_t>(nq_) * sizeof(S) + sizeof(int));
  device_ = staging_->device();
  if (chain) {
    chain_ = std::make_unique<ChainFdPlan<S>>(model, max_batch_);
    // the hybrid's host part on the options' threads (0: openmp_threads())
    if (algorithm == FdMethod::Hybrid) chain_->set_host_threads(options.threads);
  } else if (general)  // a thread per instance (or a warp over the levels: general_aba_from_env)
    general_ = std::make_unique<GeneralPlan<S>>(model, max_batch_, 0, 0, 0, general_interleave_from_env(),
                                                general_aba_from_env());
  else if (thread_bodies <= kMaxThreadDofs)
    thread_ = std::make_unique<ZThreadModel<S>>(model), require_floating_capacity(*thread_, model.name);
  else dense_ = std::make_unique<DenseJsiPlan<S>>(model, max_batch_);
  bytes_ = staging_->bytes() + (dense_ ? dense_->device_bytes() : 0) + (chain_ ? chain_->device_bytes() : 0) +
           (general_ ? general_->device_bytes() : 0);
  failed_host_.resize(static_cast<std::size_t>(max_batch_));
  // the pinned host path: the thread kernels, one per instance, take a chunk as a sub-batch
  if (thread_ && detail::host_staging_from_env() == host_staging::Mode::Pinned) {
    pipeline_ = std::make_unique<detail::HostPipeline>();
  }
  if (options.fallback_aba) set_fallback_aba(true);
  BackendOptions cuda_options = options;  // the Auto rule of the cuda backend, however the engine was made
  cuda_options.backend = BackendKind::Cuda;
  check_ = std::make_unique<FdBatchCheck<S>>(model, cuda_options, algorithm, openmp_threads());
  if (check_->on()) {
    const std::size_t B = static_cast<std::size_t>(std::max<Index>(max_batch_, 1));
    estimate_host_.assign(B, -1.0);
    before_.assign(B, -1);
    check_rows_.assign(4 * static_cast<std::size_t>(nv_), S(0));
    if (thread_ && !model.multi_dof()) {  // (a floating base: checked on the host, settle_batch)
      device_check_ = std::make_unique<DeviceFdCheck<S>>(model);
      check(cudaMalloc(reinterpret_cast<void**>(&check_estimates_), B * sizeof(double)),
            "allocating the forward-dynamics check's estimates");
      bytes_ += B * sizeof(double);
    }
  }
}

template <class S>
CudaForwardDynamics<S>::~CudaForwardDynamics() {
  if (check_estimates_) cudaFree(check_estimates_);
}

template <class S>
std::size_t CudaForwardDynamics<S>::host_ring_bytes() const {
  return pipeline_ ? pipeline_->ring_bytes() : 0;
}

template <class S>
int CudaForwardDynamics<S>::host_ring_allocations() const {
  return pipeline_ ? pipeline_->allocations() : 0;
}

template <class S>
cudaError_t CudaForwardDynamics<S>::compute_async(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed_dof,
                                                  cudaStream_t stream) {
  if (chain_) return algorithm_ == FdMethod::Hybrid ? cudaErrorNotSupported : chain_->launch(in, qdd, failed_dof, stream);
  if (dense_) return dense_->launch(in, qdd, failed_dof, stream);
  if (general_) return general_->launch_aba(in, qdd, failed_dof, stream);
  const cudaError_t e = aba_ ? launch_aba_instances(*thread_, in, qdd, failed_dof, stream)
                             : launch_fd_jsi_instances(*thread_, in, qdd, failed_dof, stream);
  if (e != cudaSuccess || !device_check_) return e;
  if (in.q.batch > max_batch_) return cudaErrorInvalidValue;  // the estimates hold max_batch
  return device_check_->launch(in, BatchView<const S>{qdd.data, qdd.batch, qdd.dof_stride, qdd.batch_stride},
                               check_->threshold(), failed_dof, check_estimates_, stream);
}

template <class S>
BatchStatus CudaForwardDynamics<S>::compute(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed_dof) {
  check_batch(in, qdd, max_batch_);
  const Index B = in.q.batch;
  const Index nv = nv_;
  int* const failed = failed_dof ? failed_dof : failed_host_.data();
  BatchStatus status;
  status.failed_dof = failed;
  if (B == 0) return status;
  if (nv == 0) {  // nothing to factorise
    for (Index b = 0; b < B; ++b) failed[b] = -1;
    return status;
  }
  // staging buffers: nq x max_batch scalars each, then the wrenches, then the failed DoFs
  const std::size_t cap = static_cast<std::size_t>(nq_) * max_batch_;
  const cudaStream_t stream = staging_->stream();
  S* const buffer = static_cast<S*>(staging_->data());
  S* const dqdd = buffer + 3 * cap;
  int* const dfailed = reinterpret_cast<int*>(reinterpret_cast<Force<S>*>(buffer + 4 * cap) + cap);

  // (both paths: a qdd view whose entries overlap is refused here)
  const Staging sqdd = plan(qdd, nv, cap, true, "qdd");
  if (pipeline_) {
    compute_pinned(in, qdd, failed);
    status = summarize_failures(failed, B, pivot_failure(algorithm_));
  } else {
    // copy in, in whatever layout keeps the copies few
    const detail::StagedInputs<S> d = detail::stage_inputs<S>({in.q, in.qd, in.tau}, {"q", "qd", "tau"}, in.fext,
                                                              {nq_, nv, nv}, nb_, cap, buffer, stream);
    // run
    const FdBatchIn<S> din{d.in[0], d.in[1], d.in[2], d.fext};
    if (chain_ && algorithm_ == FdMethod::Hybrid)
      check(chain_->launch_hybrid(in.q, din, sqdd.device_view(dqdd, B), dfailed, stream,
                                  record_timeline_ ? &timeline_ : nullptr),
            "running the hybrid forward dynamics");
    else
      check(compute_async(din, sqdd.device_view(dqdd, B), dfailed, stream), "launching the forward dynamics");
    // which instances failed, before qdd comes back over their entries
    check(cudaMemcpyAsync(failed, dfailed, static_cast<std::size_t>(B) * sizeof(int), cudaMemcpyDeviceToHost, stream),
          "copying the failed DoFs to the host");
    if (device_check_)
      check(cudaMemcpyAsync(estimate_host_.data(), check_estimates_, static_cast<std::size_t>(B) * sizeof(double),
                            cudaMemcpyDeviceToHost, stream),
            "copying the forward-dynamics check's estimates to the host");
    check(cudaStreamSynchronize(stream), "running the forward dynamics");
    status = summarize_failures(failed, B, pivot_failure(algorithm_));
    // a failed pivot leaves qdd unwritten on the device; an instance the device check
    // flagged (estimate not -1) has its result there
    const auto pivot_failed = [&](Index b) { return failed[b] >= 0 && (!device_check_ || estimate_host_[b] == -1.0); };
    // keep the failed instances' qdd entries (the device holds nothing for them)
    if (status.failed > 0) {
      const std::size_t need = static_cast<std::size_t>(status.failed) * nv;
      if (kept_.size() < need) kept_.resize(need);
      std::size_t k = 0;
      for (Index b = 0; b < B; ++b)
        if (pivot_failed(b))
          for (Index i = 0; i < nv; ++i) kept_[k++] = qdd.at(i, b);
    }
    // copy out: qdd's entries only
    check(copy(sqdd, qdd, nv, dqdd, cudaMemcpyDeviceToHost, stream), "copying qdd to the host");
    check(cudaStreamSynchronize(stream), "copying qdd to the host");
    if (status.failed > 0) {
      std::size_t k = 0;
      for (Index b = 0; b < B; ++b)
        if (pivot_failed(b))
          for (Index i = 0; i < nv; ++i) qdd.at(i, b) = kept_[k++];
    }
  }
  if (!check_->on()) {
    if (fallback_aba_ && status.failed > 0) return compute_failed_by_aba(in, qdd, failed, status.failed);
    return status;
  }
  std::copy_n(failed, B, before_.begin());
  if (!device_check_) std::fill_n(estimate_host_.begin(), B, -1.0);
  // the aba fallback takes the device's flagged instances with the failed pivots
  const bool fell = fallback_aba_ && status.failed > 0;
  if (fell) compute_failed_by_aba(in, qdd, failed, status.failed);
  return settle_checked(in, qdd, failed, fell);
}

// The pinned path (host_pipeline.hpp): per chunk, q, qd, tau packed in the layout
// their host views suggest (host_staging::choose_layout), fext verbatim; back: qdd,
// the failed DoFs and the device check's estimates. Fills failed (B) and
// estimate_host_ (with the device check), and qdd's entries of every instance
// except those whose pivot failed (their entries kept, as the pageable path does).
template <class S>
void CudaForwardDynamics<S>::compute_pinned(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed) {
  namespace hs = host_staging;
  const Index B = in.q.batch, nv = nv_;
  const detail::PackedBatchInputs<S, FdBatchIn<S>> inputs(in, nq_, nv, nb_);
  const hs::Layout lqdd = hs::choose_layout(qdd, nv, true);
  const bool estimates = device_check_ != nullptr;
  const auto layout = [&](Index n) {
    const std::size_t un = static_cast<std::size_t>(n);
    detail::SlotLayout L;
    inputs.add_to(L, n);                                 // arrays 0-3
    L.add(hs::packed_entries(lqdd, nv, n) * sizeof(S));  // 4: qdd
    L.add(un * sizeof(int));                             // 5: failed DoFs
    L.add(estimates ? un * sizeof(double) : 0);          // 6: the check's estimates
    return L;
  };
  const std::size_t per_instance = inputs.bytes_per_instance() + static_cast<std::size_t>(nv) * sizeof(S) +
                                   sizeof(int) + (estimates ? sizeof(double) : 0);
  const auto pack = [&](const detail::HostChunk& c) { inputs.pack(c); };
  const auto launch = [&](const detail::HostChunk& c, cudaStream_t stream) {
    const Index n = c.range.count;
    const FdBatchIn<S> din = inputs.device_batch(c);
    const BatchView<S> dqdd = hs::packed_view(c.device_array<S>(4), lqdd, nv, n);
    int* const dfailed = c.device_array<int>(5);
    cudaError_t e = aba_ ? launch_aba_instances(*thread_, din, dqdd, dfailed, stream)
                         : launch_fd_jsi_instances(*thread_, din, dqdd, dfailed, stream);
    if (e != cudaSuccess || !estimates) return e;
    double* const dest = c.device_array<double>(6);
    e = device_check_->launch(din, BatchView<const S>{dqdd.data, dqdd.batch, dqdd.dof_stride, dqdd.batch_stride},
                              check_->threshold(), dfailed, dest, stream);
    if (e != cudaSuccess) return e;
    // device_estimates(): the batch's, as the pageable path leaves them
    return cudaMemcpyAsync(check_estimates_ + c.range.begin, dest, static_cast<std::size_t>(n) * sizeof(double),
                           cudaMemcpyDeviceToDevice, stream);
  };
  const auto unpack = [&](const detail::HostChunk& c) {
    const Index b0 = c.range.begin, n = c.range.count;
    std::copy_n(c.host_array<const int>(5), n, failed + b0);
    if (estimates) std::copy_n(c.host_array<const double>(6), n, estimate_host_.data() + b0);
    // a failed pivot leaves qdd unwritten on the device (an instance the device check
    // flagged, estimate not -1, has its result there): keep those entries
    const auto pivot_failed = [&](Index b) { return failed[b] >= 0 && (!estimates || estimate_host_[b] == -1.0); };
    std::size_t k = 0;
    for (Index b = b0; b < b0 + n; ++b)
      if (pivot_failed(b)) {
        if (kept_.size() < k + static_cast<std::size_t>(nv)) kept_.resize(k + static_cast<std::size_t>(nv));
        for (Index i = 0; i < nv; ++i) kept_[k++] = qdd.at(i, b);
      }
    hs::unpack(c.host_array<const S>(4), lqdd, qdd, nv, c.range, 0);
    if (k == 0) return;
    k = 0;
    for (Index b = b0; b < b0 + n; ++b)
      if (pivot_failed(b))
        for (Index i = 0; i < nv; ++i) qdd.at(i, b) = kept_[k++];
  };
  pipeline_->run(B, per_instance, max_batch_, layout, pack, launch, unpack,
                 "launching the forward dynamics", "running the forward dynamics");
}

template <class S>
BatchStatus CudaForwardDynamics<S>::settle_checked(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed,
                                                   bool fell_back_ran) {
  const Index B = in.q.batch, n = nv_;
  const double threshold = check_->threshold();
  Index fell_back = 0, retried = 0;
  if (!device_check_) {
    // jsi_dense, parallel, hybrid: every instance checked on the host
    retried = check_->settle_batch(in, qdd, failed, estimate_host_.data());
  } else {
    for (Index b = 0; b < B; ++b) {
      const bool flagged = before_[b] >= 0 && !(estimate_host_[b] <= threshold) && estimate_host_[b] != -1.0;
      const bool pivot = before_[b] >= 0 && !flagged;
      if (failed[b] >= 0 && !(flagged && !fell_back_ran)) {  // a pivot that stayed failed
        estimate_host_[b] = -1;
        continue;
      }
      if (!flagged && !pivot) continue;  // passed on the device
      // flagged (or computed by the aba fallback): checked and retried on the host
      S* row = check_rows_.data();
      for (Index i = 0; i < n; ++i) {
        row[i] = in.q.at(i, b);
        row[n + i] = in.qd.at(i, b);
        row[2 * n + i] = in.tau.at(i, b);
        row[3 * n + i] = qdd.at(i, b);
      }
      const auto o = check_->settle(0, row, row + n, row + 2 * n,
                                    in.fext ? in.fext + static_cast<std::size_t>(b) * n : nullptr, row + 3 * n,
                                    aba_ || fell_back_ran);
      if (o.changed)
        for (Index i = 0; i < n; ++i) qdd.at(i, b) = row[3 * n + i];
      failed[b] = o.failed_dof;
      estimate_host_[b] = o.estimate;
      if (pivot && o.failed_dof < 0) ++fell_back;
      if (flagged && o.failed_dof < 0) ++retried;
    }
  }
  return summarize_checked(failed, estimate_host_.data(), B,
                           fallback_aba_ ? Failure::BothPivots : pivot_failure(algorithm_), threshold, fell_back,
                           retried);
}

template <class S>
void CudaForwardDynamics<S>::set_fallback_aba(bool on) {
  if (on && !(thread_ && !aba_))
    throw BackendError("backend 'cuda': the fallback to the ABA needs the thread-per-instance joint-space inertia "
                       "(jsi_thread, up to " + std::to_string(kMaxThreadDofs) + " DoF); this engine runs " + strategy());
  fallback_aba_ = on;
}

template <class S>
BatchStatus CudaForwardDynamics<S>::compute_failed_by_aba(const FdBatchIn<S>& in, const BatchView<S>& qdd,
                                                            int* failed, Index count) {
  const Index B = in.q.batch, nv = nv_, F = count;
  const std::size_t n = static_cast<std::size_t>(nv), f = static_cast<std::size_t>(F);
  std::vector<Index> which;  // (F) the failed instances
  which.reserve(f);
  for (Index b = 0; b < B; ++b)
    if (failed[b] >= 0) which.push_back(b);
  // gathered on the host: q, qd, tau (nv x F each, entry (i, k) at i * F + k), fext (F x nv)
  std::vector<S> host(3 * n * f);
  std::vector<Force<S>> wrenches(in.fext ? n * f : 0);
  for (std::size_t k = 0; k < f; ++k) {
    const Index b = which[k];
    for (Index i = 0; i < nv; ++i) {
      const std::size_t e = static_cast<std::size_t>(i) * f + k;
      host[e] = in.q.at(i, b);
      host[n * f + e] = in.qd.at(i, b);
      host[2 * n * f + e] = in.tau.at(i, b);
    }
    if (in.fext) std::copy_n(in.fext + static_cast<std::size_t>(b) * n, n, wrenches.begin() + k * n);
  }
  // through the staging buffers as compute() uses them (F <= max_batch)
  const std::size_t cap = n * static_cast<std::size_t>(max_batch_);
  const cudaStream_t stream = staging_->stream();
  S* const buffer = static_cast<S*>(staging_->data());
  S* const dqdd = buffer + 3 * cap;
  int* const dfailed = reinterpret_cast<int*>(reinterpret_cast<Force<S>*>(buffer + 4 * cap) + cap);
  using V = BatchView<const S>;
  const detail::StagedInputs<S> d = detail::stage_inputs<S>(
      {V::soa(host.data(), nv, F), V::soa(host.data() + n * f, nv, F), V::soa(host.data() + 2 * n * f, nv, F)},
      {"q", "qd", "tau"}, in.fext ? wrenches.data() : nullptr, nv, cap, buffer, stream);
  check(launch_aba_instances(*thread_, FdBatchIn<S>{d.in[0], d.in[1], d.in[2], d.fext}, BatchView<S>::soa(dqdd, nv, F),
                             dfailed, stream),
        "launching the ABA for the instances whose JSI failed");
  std::vector<S> aba_qdd(n * f);  // nv x F, as the inputs
  std::vector<int> aba_failed(f);
  check(cudaMemcpyAsync(aba_qdd.data(), dqdd, n * f * sizeof(S), cudaMemcpyDeviceToHost, stream),
        "copying the fallback's qdd to the host");
  check(cudaMemcpyAsync(aba_failed.data(), dfailed, f * sizeof(int), cudaMemcpyDeviceToHost, stream),
        "copying the fallback's failed DoFs to the host");
  check(cudaStreamSynchronize(stream), "running the ABA for the instances whose JSI failed");
  for (std::size_t k = 0; k < f; ++k) {
    const Index b = which[k];
    failed[b] = aba_failed[k];
    if (aba_failed[k] < 0)
      for (Index i = 0; i < nv; ++i) qdd.at(i, b) = aba_qdd[static_cast<std::size_t>(i) * f + k];
  }
  BatchStatus status = summarize_failures(failed, B, Failure::BothPivots);
  status.fell_back = F - status.failed;
  return status;
}

#define SCANDYN_INSTANTIATE(S)                                                                             \
  template class CudaForwardDynamics<S>;                                                                   \
  template cudaError_t launch_fd_jsi_instances(const ThreadModel<S>&, const FdBatchIn<S>&, const BatchView<S>&, \
                                               int*, cudaStream_t);                             \
  template cudaError_t launch_aba_instances(const ThreadModel<S>&, const FdBatchIn<S>&, const BatchView<S>&, \
                                            int*, cudaStream_t);                                           \
  template cudaError_t launch_fd_jsi_instances(const ZThreadModel<S>&, const FdBatchIn<S>&, const BatchView<S>&, \
                                               int*, cudaStream_t);                                        \
  template cudaError_t launch_aba_instances(const ZThreadModel<S>&, const FdBatchIn<S>&, const BatchView<S>&, \
                                            int*, cudaStream_t);
SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)
#undef SCANDYN_INSTANTIATE

}  // namespace cuda
}  // namespace scandyn
