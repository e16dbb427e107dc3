// scandyn/cuda/inverse_dynamics.hpp: batched inverse dynamics on a CUDA device,
// one thread per instance (strategy "thread").
//
// Three layers, as in GRiD and CUB:
//   rnea_instance()        __host__ __device__: the RNEA of one instance, the serial
//                          reference's loops over the same SCANDYN_HD step functions
//                          (joint_transform, rnea_forward_step, joint_project,
//                          Transform::apply_transpose), state in per-thread arrays;
//                          callable from your own kernels
//                          (scandyn/instance/rnea_instance.hpp, under nvcc; the
//                          model it reads: scandyn/instance/thread_model.hpp);
//   id_instances_kernel    one thread per instance (kernels/inverse_dynamics.cu);
//   launch_id_instances()  host wrapper: device pointers, a stream, returns the
//                          cudaError_t of the launch, never synchronises.
// and the engine of scandyn/engine.hpp on top:
//   CudaInverseDynamics<S> make_inverse_dynamics() with BackendKind::Cuda gives one.
//     compute()        HOST pointers: copies in, launches, copies out, synchronises
//                      (the convenience path of the command line); throws BackendError.
//     compute_async()  DEVICE pointers and your stream: one launch, no copy, no
//                      synchronisation, no allocation; returns the cudaError_t.
//
// Layout: any BatchView strides work, on the host and on the device. The fast one
// is structure of arrays with the instance innermost, q[i * B + b]
// (BatchView::soa): a warp's 32 threads then read 32 consecutive scalars of each
// DoF. fext, when given, is (B x nv) wrenches, fext[b * nv + i], as in IdBatchIn.
//
// Joint frames. The engine's kernels run on the z-axis model (ZThreadModel,
// scandyn/model/joint_frames.hpp): every joint frame turned so that its axis is +z,
// so that a joint transform is one rotation about z with no axis test; tau is the
// same, and fext, given in the user's body frames, is turned on reading.
//
// Model constants. The kernels read the model from the constant bank through the
// kernel parameter (ThreadModelParams, at most 17.2 KB with the z-axis frames'
// rotations: sm_70+ with CUDA >= 12.1 take parameters of up to 32 KB). It is built once per engine on the host and
// travels with each launch; the kernel then reads every body constant at a
// compile-time address as an operand of the arithmetic (no load instruction), and
// two engines on two streams cannot overwrite each other's model, as they could in
// one process-wide __constant__ symbol.
//
// Capacity. Per-thread state is sized at compile time: kernels exist for models of
// up to 8, 16, 32 and 64 DoF; the smallest that fits is used. A model with more
// than kMaxThreadDofs DoF gets a BackendError (it wants the scans across links).
#pragma once

#include <cstddef>
#include <memory>
#include <string>
#include <variant>

#include "scandyn/algorithm/steps.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/cuda/id_scan.hpp"
#include "scandyn/instance/dof_column.hpp"
#include "scandyn/instance/rnea_instance.hpp"
#include "scandyn/instance/thread_model.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

namespace scandyn {
namespace cuda {

namespace detail {
class StagingBuffer;  // kernels/staging.hpp: an engine's stream and device buffer
class HostPipeline;   // kernels/host_pipeline.hpp: the pinned ring and chunked pipeline
}  // namespace detail

// Largest model (DoF) the thread-per-instance kernels take: kMaxThreadDofs (scandyn/engine.hpp).

// How id_instances_kernel turns joint angles into sin and cos: in float the SFU's
// __sincosf after a reduction to [-pi, pi] (Trig::Hardware; on iiwa on the H100,
// 9.2e9 instead of 6.9e9 evaluations/s, max relative error 1.9e-6 instead of 4e-7
// against the double reference: bench_cuda_id's id_thread-libtrig rows), in double
// the library's sin/cos.
template <class S>
inline constexpr Trig kThreadTrig = sizeof(S) == 4 ? Trig::Hardware : Trig::Library;

// Threads per block of id_instances_kernel.
inline constexpr int kIdInstancesBlock = 128;

// tau_out (nv x B) = RNEA(q, qd, qdd) - sum J^T fext for the B = batch_in.q.batch
// instances, gravity included: one launch of id_instances_kernel on `stream`.
// Every pointer is a DEVICE pointer (views with any strides); nothing is copied,
// allocated or synchronised. Returns cudaErrorInvalidValue for views whose batch
// sizes disagree or a null pointer with B > 0, else the launch's error (kernel
// faults surface later, at your synchronisation). B = 0 launches nothing. model: the
// user's frames (ThreadModel) or z-axis frames (ZThreadModel, the engine's), either
// giving the same tau.
template <class S, class Bd>
cudaError_t launch_id_instances(const ThreadModel<S, Bd>& model, const IdBatchIn<S>& batch_in,
                                const BatchView<S>& tau_out, cudaStream_t stream);

// The batched engine on one CUDA device (the device current at construction),
// with two strategies (BackendOptions::strategy):
//   recursion   ("thread") one thread per instance, launch_id_instances: models of
//               up to kMaxThreadDofs DoF;
//   scan-local  device-wide scans across links, IdScanPlan (scandyn/cuda/id_scan.hpp):
//               any model, for few instances of long chains and the middle shapes;
//   auto        recursion up to kMaxThreadDofs DoF, else scan-local (choose_id_strategy).
// scan-world is not offered on this backend.
template <class S>
class CudaInverseDynamics final : public InverseDynamics<S> {
 public:
  // Prepares the model and allocates the device buffers compute() stages through:
  // q, qd, qdd, tau and fext for options.max_batch instances, 10 * nv * max_batch
  // scalars (compute_async needs none of them), plus the scan strategy's scratch.
  // Throws BackendError when there is no usable device, the strategy cannot take
  // the model (recursion beyond kMaxThreadDofs DoF, scan-world), or the buffers do
  // not fit in device memory (the message gives the bytes needed and the bytes free).
  CudaInverseDynamics(const ModelTpl<S>& model, const BackendOptions& options);
  ~CudaInverseDynamics() override;
  CudaInverseDynamics(const CudaInverseDynamics&) = delete;
  CudaInverseDynamics& operator=(const CudaInverseDynamics&) = delete;

  // HOST pointers, any strides. Copies the inputs to the device, runs the kernels,
  // copies tau back (writing only tau's entries: gaps between strided entries keep
  // their contents) and waits for all of it. Throws BackendError for B > max_batch,
  // views whose batch sizes disagree, a tau view whose entries overlap, or any CUDA
  // error (the engine stays usable). How the host views travel
  // (SCANDYN_HOST_STAGING, read at construction; host_staging()):
  //   pinned    (the default, strategy thread) in chunks through a pinned ring the
  //             engine allocates at the first call and reuses: host threads pack
  //             chunk k + 1 while chunk k is copied and computed
  //             (kernels/host_pipeline.hpp; SCANDYN_HOST_CHUNK_INSTANCES sets the
  //             chunk); same kernel, same results bit for bit;
  //   pageable  the whole batch copied straight from and to the user's memory on
  //             the engine's own stream (and strategy scan-local always).
  void compute(const IdBatchIn<S>& in, const BatchView<S>& tau) override;

  // DEVICE pointers, any strides, on `stream`. Asynchronous: returns after queuing
  // the kernels, with no hidden synchronisation, copy or allocation.
  //   thread: launch_id_instances with this engine's model; not limited by
  //           max_batch; safe from several host threads on different streams.
  //   scan:   IdScanPlan::launch; B <= max_batch (else cudaErrorInvalidValue); uses
  //           the engine's scratch, so one stream at a time.
  cudaError_t compute_async(const IdBatchIn<S>& in, const BatchView<S>& tau, cudaStream_t stream);

  std::string strategy() const override { return scan_ ? "scan-local" : "thread"; }
  BackendKind backend() const override { return BackendKind::Cuda; }

  const ZThreadModel<S>* thread_model() const { return thread_.get(); }  // null for the scan strategy
  const IdScanPlan<S>* scan_plan() const { return scan_.get(); }        // null for the thread strategy
  Index nv() const { return nv_; }
  Index max_batch() const { return max_batch_; }
  int device() const { return device_; }
  std::size_t device_bytes() const { return bytes_; }  // staging buffers and scan scratch
  // compute()'s host path: "pinned" or "pageable" (above)
  std::string host_staging() const { return pipeline_ ? "pinned" : "pageable"; }
  // the pinned path's ring: bytes of pinned memory held (as many of device memory,
  // beyond device_bytes()) and times it was allocated; 0 before the first call
  std::size_t host_ring_bytes() const;
  int host_ring_allocations() const;

 private:
  Index nv_ = 0;
  Index nq_ = 0;  // entries of q (nv + 1 with a floating base)
  Index nb_ = 0;  // bodies (entries of fext)
  std::unique_ptr<ZThreadModel<S>> thread_;
  std::unique_ptr<detail::HostPipeline> pipeline_;  // the pinned path (null: pageable)
  void compute_pinned(const IdBatchIn<S>& in, const BatchView<S>& tau);
  std::unique_ptr<IdScanPlan<S>> scan_;
  Index max_batch_ = 0;
  int device_ = 0;
  std::size_t bytes_ = 0;
  // compute()'s stream and its one allocation: q, qd, qdd, tau (nv x max_batch each), fext
  std::unique_ptr<detail::StagingBuffer> staging_;
};

// The bias forces h = RNEA(q, qd, 0, fext): the inverse-dynamics engine above (its
// strategies, buffers and contracts) with qdd a zero read by every entry.
template <class S>
class CudaBiasForces final : public BiasForces<S> {
 public:
  CudaBiasForces(const ModelTpl<S>& model, const BackendOptions& options);
  ~CudaBiasForces() override;
  CudaBiasForces(const CudaBiasForces&) = delete;
  CudaBiasForces& operator=(const CudaBiasForces&) = delete;

  // HOST pointers, as CudaInverseDynamics::compute.
  void compute(const BiasBatchIn<S>& in, const BatchView<S>& h) override;
  // DEVICE pointers on `stream`, as CudaInverseDynamics::compute_async.
  cudaError_t compute_async(const BiasBatchIn<S>& in, const BatchView<S>& h, cudaStream_t stream);

  std::string strategy() const override { return id_.strategy(); }
  BackendKind backend() const override { return BackendKind::Cuda; }
  const CudaInverseDynamics<S>& inverse_dynamics() const { return id_; }
  std::size_t device_bytes() const { return id_.device_bytes() + sizeof(S); }

 private:
  CudaInverseDynamics<S> id_;
  S zero_host_ = S(0);
  S* zero_device_ = nullptr;  // one zero in device memory: compute_async's qdd
};


}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
