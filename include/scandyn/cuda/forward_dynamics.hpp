// scandyn/cuda/forward_dynamics.hpp: batched forward dynamics on a CUDA device by
// the joint-space inertia (JSI) method, one thread per instance (strategy
// "jsi_thread").
//
// For each instance, qdd = M(q)^{-1} (tau - h(q, qd)) with
//   M  from the CRBA (composite inertias, each column carried to the root),
//   h  = RNEA(q, qd, 0) - sum J^T fext (gravity included),
//   M = L^T L, the tree-sparse factorisation of Featherstone (2008) 6.5, no fill-in,
// the formulas and the order of operations of scandyn::fd_jsi
// (src/algorithm/reference.cpp) over the same step functions (steps.hpp).
//
// Three layers, as for inverse dynamics (scandyn/cuda/inverse_dynamics.hpp):
//   fd_jsi_instance()          __host__ __device__: one instance, state in per-thread
//                              arrays sized at compile time; callable from your own
//                              kernels (scandyn/instance/crba_instance.hpp, under
//                              nvcc) and on the host. Its
//                              mass matrix is crba_instance()'s (the CRBA alone, also
//                              behind scandyn/cuda/mass_matrix.hpp): one function,
//                              fd_detail::jsi_passes, computes both;
//   fd_instances_kernel    one thread per instance (kernels/forward_dynamics.cu);
//   launch_fd_jsi_instances()  host wrapper: device pointers, a stream, returns the
//                              cudaError_t of the launch, never synchronises.
// and the engine CudaForwardDynamics on top:
//     compute()        HOST pointers: copies in, launches, copies out, synchronises;
//                      returns an BatchStatus.
//     compute_async()  DEVICE pointers and your stream: one launch, no copy, no
//                      synchronisation, no allocation; returns the cudaError_t.
//
// A factorisation that fails is reported, never turned into NaN. When a pivot of
// L^T L (a diagonal entry of M as the factorisation reaches it, DoFs from the last
// to the first) is not positive and finite, the instance's failed DoF is that DoF
// and its qdd entries are LEFT UNWRITTEN (they keep what the caller's buffer held,
// on the device and, through compute(), on the host); otherwise its failed DoF is
// -1. A non-finite position of a joint that is not a root makes M non-finite, so it
// is reported the same way; as in the serial fd_jsi, non-finite qd, tau, fext or
// root joint positions (M does not depend on them) with a sound M give non-finite
// qdd.
//
// Layout, model constants and capacities are those of the inverse dynamics:
// BatchView strides of any kind (q[i * B + b], BatchView::soa, is the fast one),
// fext as (B x nv) wrenches, the model as a __grid_constant__ kernel parameter
// (ThreadModelParams), kernels for models of up to 8, 16, 32 and 64 DoF.
//
// Resources (ptxas, sm_90, CUDA 13, block 128; bench_cuda_fd prints them on the
// device): capacity 8 is unrolled, in registers: float 167 registers, no spills,
// double 255 registers with 148 B of spill stores; its 928 B (float) stack frame is
// the branch stack and sin/cos's slow-path scratch, untouched for a chain such as
// iiwa. Capacities 16..64 keep M and the forces in local memory: 72 (float) / 128
// (double) registers, 2.8 KB (16 DoF float) to 34.6 KB (64 DoF double) per thread.
//
// The same by the articulated-body algorithm (FdMethod::Aba, strategy
// "aba_thread"): aba_instance (scandyn/instance/aba_instance.hpp), launch_aba_instances, one kernel per model shape
// (choose_aba_kernel). Resources (ptxas as above): float chains (iiwa) unrolled in
// 168 registers, other float kernels rolled in 128 (chains, trees) or 152 (one
// branch slot in registers: atlas), double rolled in 226 (chains) or 240 (trees);
// no spills except 8 B in the unrolled float chain; per thread, 32 B (float) of
// local memory per body for the rolled kernels' per-body state, plus the slots of
// the tree kernels (only branch points touch them).
//
// The run-time check (BackendOptions::fd_check; Auto is off on cuda): the thread
// engines (aba_thread, jsi_thread) check on the device (DeviceFdCheck,
// scandyn/cuda/fd_check.hpp: one more launch after the forward dynamics, in
// compute() and compute_async() alike, marking flagged instances in failed_dof;
// its estimates hold max_batch instances, so with the check on compute_async()
// takes at most max_batch: cudaErrorInvalidValue beyond, device_estimates() reads them);
// compute() then retries the flagged ones on the host (FdBatchCheck: aba on the
// device for jsi_thread with fallback_aba, the double aba on the host with
// fallback_double) and reports them as Failure::ResidualTooLarge. jsi_dense,
// parallel and hybrid are checked on the host after the copy back (compute() only;
// their compute_async() is unchecked).
#pragma once

#include <cstddef>
#include <memory>
#include <string>
#include <vector>

#include "scandyn/engine.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/algorithm/fd_check_batch.hpp"
#include "scandyn/cuda/chain_fd.hpp"
#include "scandyn/cuda/fd_check.hpp"
#include "scandyn/cuda/fd_dense.hpp"
#include "scandyn/cuda/general_dynamics.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"
#include "scandyn/instance/aba_instance.hpp"
#include "scandyn/instance/crba_instance.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

namespace scandyn {
namespace cuda {

// Threads per block of fd_instances_kernel.
inline constexpr int kFdInstancesBlock = 128;

// Which method CudaForwardDynamics runs (BackendOptions::fd_method):
//   Auto      choose_fd_method: Aba up to kMaxThreadDofs DoF; beyond, Aba
//             ("aba_general") for chains of up to 128 DoF and for trees, Parallel for
//             longer unbranched chains from the base;
//   Jsi       joint-space inertia: jsi_thread up to kMaxThreadDofs DoF, jsi_dense beyond;
//   Aba       articulated-body algorithm, one thread per instance: "aba_thread" up to
//             kMaxThreadDofs DoF, "aba_general" (GeneralPlan, O(nv) per instance)
//             beyond and for multi-DoF joints;
//   Parallel  unbranched chains from the base, any length: the articulated-body algorithm
//             as scans over links, every pass on the device (ChainFdPlan::launch);
//   Hybrid    the same shapes: articulated inertias on the host, the other passes as
//             device scans (ChainFdPlan::launch_hybrid); compute() only. The host part
//             runs on BackendOptions::threads host threads (0: openmp_threads()).

// qdd_out (nv x B) = FD(q, qd, tau, fext) for the B = batch_in.q.batch instances,
// gravity included: one launch of fd_instances_kernel on `stream`. Writes
// failed_dof_out[b] for every b < B: -1, or the DoF whose pivot failed (qdd of that
// instance unwritten). Every pointer is a DEVICE pointer (views with any strides;
// failed_dof_out dense, B entries); nothing is copied, allocated or synchronised.
// Returns cudaErrorInvalidValue for views whose batch sizes disagree or a null
// pointer (failed_dof_out included) with B > 0, else the launch's error (kernel
// faults surface later, at your synchronisation). B = 0 launches nothing.
template <class S, class Bd>
cudaError_t launch_fd_jsi_instances(const ThreadModel<S, Bd>& model, const FdBatchIn<S>& batch_in,
                                    const BatchView<S>& qdd_out, int* failed_dof_out, cudaStream_t stream);

// The same by the articulated-body algorithm (aba_instance in fd_instances_kernel,
// the variant choose_aba_kernel picks), with the same arguments, checks and return
// values; failed_dof_out[b] is -1 or the DoF whose articulated pivot D failed (qdd
// of that instance unwritten).
template <class S, class Bd>
cudaError_t launch_aba_instances(const ThreadModel<S, Bd>& model, const FdBatchIn<S>& batch_in,
                                 const BatchView<S>& qdd_out, int* failed_dof_out, cudaStream_t stream);

// The batched forward-dynamics engine on one CUDA device (the device current at
// construction).
template <class S>
class CudaForwardDynamics final : public ForwardDynamics<S> {
 public:
  // Prepares the model and allocates the device buffers compute() stages through:
  // q, qd, tau, qdd and fext for options.max_batch instances plus one int each,
  // (10 * nv * sizeof(S) + sizeof(int)) * max_batch bytes (compute_async needs none
  // of them); beyond kMaxThreadDofs DoF also DenseJsiPlan's buffers (the mass
  // matrices: nv^2 scalars per instance). options.strategy must be Auto or
  // Recursion. Throws BackendError when there is no usable device, or the buffers
  // do not fit in device memory (the message gives the bytes needed and the bytes
  // free). algorithm: FdMethod::Aba selects the articulated-body algorithm
  // (strategy "aba_thread" up to kMaxThreadDofs DoF, "aba_general" beyond); Auto
  // and Jsi the joint-space inertia. The staging and the
  // compute() / compute_async() contracts are the same for both.
  // options.fallback_aba: set_fallback_aba(true).
  CudaForwardDynamics(const ModelTpl<S>& model, const BackendOptions& options);
  // The same with options.fd_method = method.
  CudaForwardDynamics(const ModelTpl<S>& model, BackendOptions options, FdMethod method);
  ~CudaForwardDynamics() override;
  CudaForwardDynamics(const CudaForwardDynamics&) = delete;
  CudaForwardDynamics& operator=(const CudaForwardDynamics&) = delete;

  // HOST pointers, any strides. Copies the inputs to the device, runs the kernel,
  // copies qdd back and waits for all of it on the engine's own stream. Writes only
  // qdd's entries (gaps between strided entries keep their contents), and not those
  // of instances whose factorisation failed. Returns which failed (status.message()
  // names the first); failed_dof, when not null, receives B entries on the host:
  // -1 or the failed DoF of each instance. Throws BackendError for B > max_batch,
  // views whose batch sizes disagree, a qdd view whose entries overlap, or any CUDA
  // error; a failed factorisation is not an exception. Allocates nothing, except
  // the first time more instances fail than ever before (to keep their qdd), and
  // the pinned ring. The host path (SCANDYN_HOST_STAGING, read at construction) is
  // CudaInverseDynamics::compute's: pinned, in chunks through the engine's pinned
  // ring (kernels/host_pipeline.hpp), for jsi_thread and aba_thread (by default);
  // pageable, the whole batch straight from the user's memory, for the others.
  BatchStatus compute(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed_dof);
  // The same; the status's failed_dof is the engine's own host array.
  BatchStatus compute(const FdBatchIn<S>& in, const BatchView<S>& qdd) override {
    return compute(in, qdd, nullptr);
  }

  // DEVICE pointers, any strides, on `stream` (failed_dof: B ints on the device).
  // Asynchronous: returns after queuing the kernels, with no hidden
  // synchronisation, copy or allocation.
  //   jsi_thread: launch_fd_jsi_instances with this engine's model; not limited by
  //               max_batch; safe from several host threads on different streams;
  //   aba_thread: launch_aba_instances, likewise;
  //   jsi_dense:  DenseJsiPlan::launch; B <= max_batch (else cudaErrorInvalidValue);
  //               the engine's scratch, so one stream at a time;
  //   parallel:   ChainFdPlan::launch, likewise;
  //   hybrid:     not here (its host recursion needs q in host memory):
  //               cudaErrorNotSupported; compute() runs it.
  cudaError_t compute_async(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed_dof,
                            cudaStream_t stream);

  // With on, compute() computes the instances whose JSI factorisation failed again by
  // the ABA (one launch of the ABA kernel over just those instances, gathered on the
  // host and staged through the same buffers): their qdd is the ABA's, their
  // failed_dof -1, and the returned status counts them in fell_back (an instance whose
  // ABA pivot fails too stays failed, Failure::BothPivots). compute_async() is not
  // affected: it cannot see which instances failed without waiting for them. Only
  // the thread-per-instance JSI (strategy "jsi_thread", up to kMaxThreadDofs DoF) has
  // it; any other engine throws BackendError for on.
  void set_fallback_aba(bool on);
  bool fallback_aba() const { return fallback_aba_; }

  // "jsi_thread" (one thread per instance, up to kMaxThreadDofs DoF), "jsi_dense"
  // (CRBA per block, cuSOLVER's batched Cholesky: DenseJsiPlan, beyond) or
  // "aba_thread" (FdMethod::Aba: ABA, one thread per instance), "aba_general"
  // (FdMethod::Aba of joints of any type: spherical, a floating base or 1-DoF joints
  // beyond the thread kernels; GeneralPlan, one thread per instance)
  // "parallel" and "hybrid" (ChainFdPlan) likewise.
  // With set_fallback_aba: "jsi_thread+aba".
  // With the check on: "+check" appended.
  std::string strategy() const override {
    const std::string check = check_ && check_->on() ? "+check" : "";
    if (chain_) return (algorithm_ == FdMethod::Hybrid ? "hybrid" : "parallel") + check;
    if (fallback_aba_) return "jsi_thread+aba" + check;
    return (general_ ? "aba_general" : aba_ ? "aba_thread" : dense_ ? "jsi_dense" : "jsi_thread") + check;
  }
  // the check's estimates of the last compute() / compute_async() on the device
  // (thread engines with the check on; B doubles, device memory), else null
  const double* device_estimates() const { return device_check_ ? check_estimates_ : nullptr; }
  // the method the engine runs (Auto resolved)
  FdMethod method() const override { return algorithm_; }
  // the hybrid's timeline of its last compute() when record_timeline(true) was set
  void record_timeline(bool on) { record_timeline_ = on; }
  const std::vector<ChainTimelineEvent>& timeline() const { return timeline_; }
  BackendKind backend() const override { return BackendKind::Cuda; }

  const ZThreadModel<S>* thread_model() const { return thread_.get(); }  // null for jsi_dense, aba_general
  Index nv() const { return nv_; }
  Index max_batch() const { return max_batch_; }
  int device() const { return device_; }
  std::size_t device_bytes() const { return bytes_; }  // held by the staging buffers
  // compute()'s host path, "pinned" or "pageable", and the pinned ring's bytes and
  // allocations, as CudaInverseDynamics's
  std::string host_staging() const { return pipeline_ ? "pinned" : "pageable"; }
  std::size_t host_ring_bytes() const;
  int host_ring_allocations() const;

 private:
  Index nv_ = 0;
  Index nq_ = 0;  // entries of q (nv + 1 with a floating base)
  Index nb_ = 0;  // bodies (entries of fext)
  bool aba_ = false;
  FdMethod algorithm_ = FdMethod::Jsi;
  std::unique_ptr<ZThreadModel<S>> thread_;
  std::unique_ptr<DenseJsiPlan<S>> dense_;
  std::unique_ptr<ChainFdPlan<S>> chain_;
  std::unique_ptr<GeneralPlan<S>> general_;
  bool record_timeline_ = false;
  std::vector<ChainTimelineEvent> timeline_;
  Index max_batch_ = 0;
  int device_ = 0;
  std::size_t bytes_ = 0;
  // compute()'s stream and its one allocation: q, qd, tau, qdd (nv x max_batch each),
  // fext, failed DoFs
  std::unique_ptr<detail::StagingBuffer> staging_;
  std::vector<int> failed_host_;  // (max_batch) when the caller passes no failed_dof
  std::vector<S> kept_;           // qdd entries of failed instances, restored after the copy back
  std::unique_ptr<detail::HostPipeline> pipeline_;  // the pinned path (null: pageable)
  // compute()'s pinned path up to the failed DoFs and the device check's estimates
  void compute_pinned(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed);
  bool fallback_aba_ = false;     // set_fallback_aba
  // compute()'s second pass for set_fallback_aba: the failed instances by the ABA
  BatchStatus compute_failed_by_aba(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed,
                                      Index count);
  // the run-time check: its host side (always made; on() or not), the device kernel
  // (thread engines) and its device estimates (max_batch doubles)
  std::unique_ptr<FdBatchCheck<S>> check_;
  std::unique_ptr<DeviceFdCheck<S>> device_check_;
  double* check_estimates_ = nullptr;
  std::vector<double> estimate_host_;  // (max_batch) estimates, -1: not flagged by the device
  std::vector<int> before_;            // (max_batch) failed DoFs before the aba fallback
  std::vector<S> check_rows_;          // (4 nv) one instance's q, qd, tau, qdd for a host retry
  // compute()'s last step with the check on: retries and the status
  BatchStatus settle_checked(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed, bool fell_back_ran);
};


}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
