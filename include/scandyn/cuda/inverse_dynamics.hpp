// scandyn/cuda/inverse_dynamics.hpp: batched inverse dynamics on a CUDA device,
// one thread per instance (strategy "thread").
//
// Three layers, as in GRiD and CUB:
//   rnea_instance()        __host__ __device__: the RNEA of one instance, the serial
//                          reference's loops over the same SCANDYN_HD step functions
//                          (joint_transform, rnea_forward_step, joint_project,
//                          Transform::apply_transpose), state in per-thread arrays;
//                          callable from your own kernels (this header under nvcc);
//   id_instances_kernel    one thread per instance (kernels/id_instances.cu);
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
// Model constants. The kernels read the model from the constant bank through the
// kernel parameter (ThreadModelParams, at most 14.1 KB: sm_70+ with CUDA >= 12.1
// take parameters of up to 32 KB). It is built once per engine on the host and
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

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

namespace scandyn {
namespace cuda {

namespace detail {
class StagingBuffer;  // kernels/staging.hpp: an engine's stream and device buffer
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

// How body i exchanges quantities with its parent; precomputed on the host so that
// the kernel keeps the common case (parent = body i - 1, or the base) in registers
// and touches per-thread memory only at branch points of the tree.
enum ThreadBodyFlag : int {
  kParentIsBase = 1,  // parent is the fixed base (-1)
  kParentIsPrev = 2,  // parent is body i - 1
  kStacked = 4,       // a child other than body i + 1 (a branch child) reads v_i, a_i and
                      // adds to f_i: body i is a branch point of the tree
  kOpensSlot = 8,     // body i is the highest-numbered branch child of its parent: the
                      // first of them to reach the parent going leaves to root
};

// Bits kSlotShift.. of a kStacked body's flags: its branch slot, a small number
// shared by branch points whose children do not interleave. Branch point p's slot
// is in use from p to its highest-numbered branch child h(p) (root to leaves) or
// from h(p) back to p (leaves to root); the host gives two branch points the same
// slot only when one's range ends where or before the other's starts, so that a
// kernel holding one value per slot (aba_instance: velocities, articulated
// inertias) needs as many slots as branch points whose ranges overlap
// (ThreadModel::branch_slots()), not one per body.
inline constexpr int kSlotShift = 8;
SCANDYN_HD constexpr int branch_slot(int flags) { return flags >> kSlotShift; }

// The model as the kernels read it, for capacity C (nv <= C): the kernel parameter.
template <class S, int C>
struct ThreadModelParams {
  static constexpr int capacity = C;
  Body<S> body[C];                 // (nv) bodies in DoF order; entries past nv unused
  int flags[C];                    // (nv) ThreadBodyFlag bits of each body
  unsigned long long ancestors[C]; // (nv) bit j of ancestors[i]: body j is a proper ancestor
                                   // of body i (the sparsity of row i of M; forward dynamics)
  Motion<S> a0;                    // base acceleration: gravity entered as -g
  Index nv;                        // number of bodies (DoF), <= C
};

// One model prepared for the kernels: the parameter block of the smallest capacity
// that holds it. Host memory only; built once, then copied into each launch.
template <class S>
class ThreadModel {
 public:
  using Params = std::variant<ThreadModelParams<S, 8>, ThreadModelParams<S, 16>,
                              ThreadModelParams<S, 32>, ThreadModelParams<S, 64>>;

  // Throws BackendError when model.nv() > kMaxThreadDofs.
  explicit ThreadModel(const ModelTpl<S>& model);

  Index nv() const { return nv_; }
  Index capacity() const { return capacity_; }  // 8, 16, 32 or 64
  const Params& params() const { return params_; }
  // Branch slots the model needs (see kSlotShift): 0 when every body's parent is the
  // previous body or the base (a chain, or chains hanging from the base)
  Index branch_slots() const { return branch_slots_; }

 private:
  Index nv_ = 0;
  Index capacity_ = 0;
  Index branch_slots_ = 0;
  Params params_;
};

// tau_out (nv x B) = RNEA(q, qd, qdd) - sum J^T fext for the B = batch_in.q.batch
// instances, gravity included: one launch of id_instances_kernel on `stream`.
// Every pointer is a DEVICE pointer (views with any strides); nothing is copied,
// allocated or synchronised. Returns cudaErrorInvalidValue for views whose batch
// sizes disagree or a null pointer with B > 0, else the launch's error (kernel
// faults surface later, at your synchronisation). B = 0 launches nothing.
template <class S>
cudaError_t launch_id_instances(const ThreadModel<S>& model, const IdBatchIn<S>& batch_in,
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
  // their contents) and waits for all of it on the engine's own stream. Throws
  // BackendError for B > max_batch, views whose batch sizes disagree, a tau view
  // whose entries overlap, or any CUDA error.
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

  const ThreadModel<S>* thread_model() const { return thread_.get(); }  // null for the scan strategy
  const IdScanPlan<S>* scan_plan() const { return scan_.get(); }        // null for the thread strategy
  Index nv() const { return nv_; }
  Index max_batch() const { return max_batch_; }
  int device() const { return device_; }
  std::size_t device_bytes() const { return bytes_; }  // staging buffers and scan scratch

 private:
  Index nv_ = 0;
  std::unique_ptr<ThreadModel<S>> thread_;
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


#if defined(__CUDACC__)
// ---- device API --------------------------------------------------------------

// One instance's entries of a strided batch array: DoF i at data[i * stride].
template <class T>
struct DofColumn {
  T* data;
  std::ptrdiff_t stride;
  __host__ __device__ __forceinline__ T& operator[](Index i) const { return data[i * stride]; }
};

// Instance b's entries of a batch view.
template <class T>
__host__ __device__ __forceinline__ DofColumn<T> instance_column(const BatchView<T>& v, long long b) {
  return {v.data + b * v.batch_stride, v.dof_stride};
}

// The RNEA of one instance: tau = RNEA(q, qd, qdd) - sum J^T fext, gravity included,
// the loops of scandyn::rnea (src/algorithm/reference.cpp) over the same step
// functions and in the same order of summation. fext: nv body wrenches or null.
//
// Also a host function (under nvcc), so the tests check its logic without a device.
//
// State: with kUnrolled (the default for capacities 8 and 16 in float, 8 in
// double) the loops are unrolled, so the per-body arrays are indexed at compile
// time and live in registers; otherwise the forces live in per-thread (local)
// memory and q, qd, qdd are read where they are used (double with 16 bodies
// unrolled needs more than 255 registers). A body whose parent is body i - 1 or
// the base takes v, a from registers and hands its force back in a register; only
// tree branch points (kStacked) go through the stack arrays. kKeepXup keeps each
// body's transform from the forward pass for the backward pass; otherwise
// joint_transform is evaluated again there (fewer registers, more arithmetic).
// kTrig: how joint angles become sin and cos (Trig::Library, CUDA's sinf/cosf, by
// default: at most 64 links, so their slight bias stays below 1e-6; see joint_sincos).
template <class S, int C, bool kKeepXup = false, bool kUnrolled = (C * sizeof(S) <= 64), Trig kTrig = Trig::Library>
__host__ __device__ __forceinline__ void rnea_instance(const ThreadModelParams<S, C>& model,
                                                       DofColumn<const S> q, DofColumn<const S> qd,
                                                       DofColumn<const S> qdd, const Force<S>* fext,
                                                       DofColumn<S> tau) {
  constexpr int kRegs = kUnrolled ? C : 1;  // register copies of the inputs when unrolled
  constexpr int kXup = kKeepXup ? C : 1;
  const Index n = model.nv;
  S q_r[kRegs], qd_r[kRegs], qdd_r[kRegs];  // (nv) joint variables, loaded up front
  Transform<S> Xup[kXup];                   // (nv) parent -> body transforms (kKeepXup)
  Force<S> f[C];                            // (nv) net body forces from the forward pass
  Motion<S> sv[C], sa[C];                   // stack: v, a of kStacked bodies
  Force<S> sf[C];                           // stack: f of kStacked bodies plus their
                                            // children other than the next body

  // load: all of one instance's inputs in flight before the first use
  if constexpr (kUnrolled) {
#pragma unroll
    for (Index i = 0; i < C; ++i) {
      if (i < n) {
        q_r[i] = q[i];
        qd_r[i] = qd[i];
        qdd_r[i] = qdd[i];
      }
    }
  }
  // forward: kinematics and body forces
  const Motion<S> a0 = model.a0;
  Motion<S> v_prev = Motion<S>::zero(), a_prev = a0;  // body i - 1's v and a
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = 0; i < C; ++i) {
    if (i >= n) continue;  // (not break: a loop of C trips unrolls, indices stay constant)
    const Body<S>& b = model.body[i];
    const int fl = model.flags[i];
    Motion<S> vp = Motion<S>::zero(), ap = a0;
    if (fl & kParentIsPrev) vp = v_prev, ap = a_prev;
    else if (!(fl & kParentIsBase)) vp = sv[b.parent], ap = sa[b.parent];
    const S qi = kUnrolled ? q_r[kUnrolled ? i : 0] : q[i];
    const Transform<S> X = joint_transform<kTrig>(b, qi);
    if constexpr (kKeepXup) Xup[kKeepXup ? i : 0] = X;
    const S qdi = kUnrolled ? qd_r[kUnrolled ? i : 0] : qd[i];
    const S qddi = kUnrolled ? qdd_r[kUnrolled ? i : 0] : qdd[i];
    const RneaForward<S> o = rnea_forward_step(b, X, vp, ap, qdi, qddi);
    f[i] = fext ? o.f - fext[i] : o.f;
    if (fl & kStacked) sv[i] = o.v, sa[i] = o.a, sf[i] = f[i];
    v_prev = o.v;
    a_prev = o.a;
  }
  // backward: joint torques; each body's force goes to its parent, the next body's
  // through a register (`carry`), others' through the stack. A parent receives its
  // children in descending order, as in the reference.
  Force<S> carry = Force<S>::zero();  // from body i + 1, when its parent is body i
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = C - 1; i >= 0; --i) {
    if (i >= n) continue;
    const Body<S>& b = model.body[i];
    const int fl = model.flags[i];
    Force<S> fi = (fl & kStacked) ? sf[i] : f[i];
    if (i + 1 < n && (model.flags[i + 1 < C ? i + 1 : i] & kParentIsPrev)) fi += carry;
    tau[i] = joint_project(b, fi);
    if (fl & kParentIsBase) continue;
    Transform<S> X;
    if constexpr (kKeepXup) X = Xup[kKeepXup ? i : 0];
    else X = joint_transform<kTrig>(b, kUnrolled ? q_r[kUnrolled ? i : 0] : q[i]);
    const Force<S> up = X.apply_transpose(fi);
    if (fl & kParentIsPrev) carry = up;
    else sf[b.parent] += up;
  }
}
#endif  // __CUDACC__

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
