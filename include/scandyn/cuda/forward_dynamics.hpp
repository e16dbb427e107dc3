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
//                              kernels (this header under nvcc) and on the host. Its
//                              mass matrix is crba_instance()'s (the CRBA alone, also
//                              behind scandyn/cuda/mass_matrix.hpp): one function,
//                              fd_detail::jsi_passes, computes both;
//   fd_instances_kernel    one thread per instance (kernels/fd_instances.cu);
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
// "aba_thread"): aba_instance, launch_aba_instances, one kernel per model shape
// (choose_aba_kernel). Resources (ptxas as above): float chains (iiwa) unrolled in
// 168 registers, other float kernels rolled in 128 (chains, trees) or 152 (one
// branch slot in registers: atlas), double rolled in 226 (chains) or 240 (trees);
// no spills except 8 B in the unrolled float chain; per thread, 32 B (float) of
// local memory per body for the rolled kernels' per-body state, plus the slots of
// the tree kernels (only branch points touch them).
#pragma once

#include <cstddef>
#include <memory>
#include <string>
#include <vector>

#include "scandyn/engine.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/cuda/chain_fd.hpp"
#include "scandyn/cuda/fd_dense.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

namespace scandyn {
namespace cuda {

// Threads per block of fd_instances_kernel.
inline constexpr int kFdInstancesBlock = 128;

// Which method CudaForwardDynamics runs (BackendOptions::fd_method):
//   Auto      choose_fd_method: Aba up to kMaxThreadDofs DoF; beyond, Parallel for
//             unbranched chains from the base, else Jsi;
//   Jsi       joint-space inertia: jsi_thread up to kMaxThreadDofs DoF, jsi_dense beyond;
//   Aba       articulated-body algorithm, one thread per instance ("aba_thread"), up to
//             kMaxThreadDofs DoF (beyond: BackendError);
//   Parallel  unbranched chains from the base, any length: the articulated-body algorithm
//             as scans over links, every pass on the device (ChainFdPlan::launch);
//   Hybrid    the same shapes: articulated inertias on the host, the other passes as
//             device scans (ChainFdPlan::launch_hybrid); compute() only.

// qdd_out (nv x B) = FD(q, qd, tau, fext) for the B = batch_in.q.batch instances,
// gravity included: one launch of fd_instances_kernel on `stream`. Writes
// failed_dof_out[b] for every b < B: -1, or the DoF whose pivot failed (qdd of that
// instance unwritten). Every pointer is a DEVICE pointer (views with any strides;
// failed_dof_out dense, B entries); nothing is copied, allocated or synchronised.
// Returns cudaErrorInvalidValue for views whose batch sizes disagree or a null
// pointer (failed_dof_out included) with B > 0, else the launch's error (kernel
// faults surface later, at your synchronisation). B = 0 launches nothing.
template <class S>
cudaError_t launch_fd_jsi_instances(const ThreadModel<S>& model, const FdBatchIn<S>& batch_in,
                                    const BatchView<S>& qdd_out, int* failed_dof_out, cudaStream_t stream);

// The same by the articulated-body algorithm (aba_instance in fd_instances_kernel,
// the variant choose_aba_kernel picks), with the same arguments, checks and return
// values; failed_dof_out[b] is -1 or the DoF whose articulated pivot D failed (qdd
// of that instance unwritten).
template <class S>
cudaError_t launch_aba_instances(const ThreadModel<S>& model, const FdBatchIn<S>& batch_in,
                                 const BatchView<S>& qdd_out, int* failed_dof_out, cudaStream_t stream);

// Branch slots that the ABA kernel for branched models keeps in registers
// (aba_instance's kSlots; atlas needs 1). Each costs 39 scalars of pass state: in
// float, 1 fits without spilling (152 registers at capacity 32), 2 spill.
inline constexpr Index kAbaRegisterSlots = 1;

// The ABA kernels (aba_instance's kSlots, from the model's shape), as
// launch_aba_instances picks them.
enum class AbaKernel {
  Chains,    // "chain": no branch children (ThreadModel::branch_slots() == 0: a chain,
             // or chains hanging from the base such as hyq's legs); no slots at all
  Branches,  // "slots": float, at most kAbaRegisterSlots branch slots, in registers
  Tree,      // "tree": any model; a slot per branch point in per-thread local memory
             // (double's pick for branched models: 240 registers, no spills, where
             // register slots spill at 255)
};


inline const char* to_string(AbaKernel k) {
  return k == AbaKernel::Chains ? "chain" : k == AbaKernel::Branches ? "slots" : "tree";
}

// The ABA kernel launch_aba_instances runs for `model` in precision S.
template <class S>
AbaKernel choose_aba_kernel(const ThreadModel<S>& model) {
  if (model.branch_slots() == 0) return AbaKernel::Chains;
  if (sizeof(S) == 4 && model.branch_slots() <= kAbaRegisterSlots) return AbaKernel::Branches;
  return AbaKernel::Tree;
}

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
  // (strategy "aba_thread"), for models of up to kMaxThreadDofs DoF (beyond: a
  // BackendError); Auto and Jsi the joint-space inertia. The staging and the
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
  // the first time more instances fail than ever before (to keep their qdd).
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
  // "aba_thread" (FdMethod::Aba: ABA, one thread per instance)
  // "parallel" and "hybrid" (ChainFdPlan) likewise.
  // With set_fallback_aba: "jsi_thread+aba".
  std::string strategy() const override {
    if (chain_) return algorithm_ == FdMethod::Hybrid ? "hybrid" : "parallel";
    if (fallback_aba_) return "jsi_thread+aba";
    return aba_ ? "aba_thread" : dense_ ? "jsi_dense" : "jsi_thread";
  }
  // the method the engine runs (Auto resolved)
  FdMethod method() const override { return algorithm_; }
  // the hybrid's timeline of its last compute() when record_timeline(true) was set
  void record_timeline(bool on) { record_timeline_ = on; }
  const std::vector<ChainTimelineEvent>& timeline() const { return timeline_; }
  BackendKind backend() const override { return BackendKind::Cuda; }

  const ThreadModel<S>* thread_model() const { return thread_.get(); }  // null for jsi_dense
  Index nv() const { return nv_; }
  Index max_batch() const { return max_batch_; }
  int device() const { return device_; }
  std::size_t device_bytes() const { return bytes_; }  // held by the staging buffers

 private:
  Index nv_ = 0;
  bool aba_ = false;
  FdMethod algorithm_ = FdMethod::Jsi;
  std::unique_ptr<ThreadModel<S>> thread_;
  std::unique_ptr<DenseJsiPlan<S>> dense_;
  std::unique_ptr<ChainFdPlan<S>> chain_;
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
  bool fallback_aba_ = false;     // set_fallback_aba
  // compute()'s second pass for set_fallback_aba: the failed instances by the ABA
  BatchStatus compute_failed_by_aba(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed,
                                      Index count);
};

#if defined(__CUDACC__)
// ---- device API --------------------------------------------------------------

namespace fd_detail {

// Index of M(k, j), j <= k, in a packed lower triangle.
__host__ __device__ constexpr int tri(int k, int j) { return k * (k + 1) / 2 + j; }

// Is body j a proper ancestor of body k?
template <class S, int C>
__host__ __device__ __forceinline__ bool is_ancestor(const ThreadModelParams<S, C>& m, Index j, Index k) {
  return (m.ancestors[k] >> j) & 1ull;
}

// Calls f(j) for every proper ancestor j of body k, nearest first (the order of the
// reference's for_path). Unrolled: a loop of compile-time indices (once k is one)
// over the ancestor bits, so that arrays indexed by j stay in registers; otherwise
// the walk up the parents.
template <bool kUnrolled, class S, int C, class F>
__host__ __device__ __forceinline__ void for_ancestors(const ThreadModelParams<S, C>& m, Index k, F&& f) {
  if constexpr (kUnrolled) {
#pragma unroll
    for (Index j = C - 2; j >= 0; --j)
      if (j < k && is_ancestor(m, j, k)) f(j);
  } else {
    for (Index j = m.body[k].parent; j >= 0; j = m.body[j].parent) f(j);
  }
}

// Calls f(k) for every proper descendant k of body i (any order; ascending here).
template <bool kUnrolled, class S, int C, class F>
__host__ __device__ __forceinline__ void for_descendants(const ThreadModelParams<S, C>& m, Index i, F&& f) {
#pragma unroll(kUnrolled ? C : 1)
  for (Index k = 1; k < C; ++k)
    if (k > i && k < m.nv && is_ancestor(m, i, k)) f(k);
}

// The CRBA of one instance (kBias = false: crba_instance) or the CRBA and the bias
// forces in the same passes (kBias = true: fd_jsi_instance), so that the CRBA's
// formulas and order exist once for both.
//
// With kBias, a forward pass (transforms, velocities, accelerations and body forces
// of the RNEA with qdd = 0). Then one backward pass that, for each body i from the
// last, completes its composite inertia Ic_i, the entries M(k, i) of the columns k
// of its descendants (their forces F_k reach body i's frame there) and its own
// column's force F_i = Ic_i S_i (with kBias also its force f_i: h_i = S_i^T f_i),
// then carries Ic_i, every F_k of its subtree (and f_i) to its parent. A parent
// receives its children in descending order, as in the reference: body i + 1's
// through registers (Icarry, fcarry), others' through the stack. Each entry is
// computed by the reference's formulas (crba, rnea) in the reference's order of
// summation.
//
// Out: M(k, j) at tri(k, j) for j = k and j an ancestor of k (the tree's nonzeros;
// other entries of the triangle are not written), armature[i] (optional, nv
// scalars) added to M(i, i); with kBias x = tau - h (nv), else x is not touched.
//
// State (per thread): the column forces (C, one slot per body: with kBias body i's
// force until its backward step, then column i's), a stack of composite inertias
// (and with kBias v, a, f) for the bodies at which the tree branches (kStacked), as
// in rnea_instance. kUnrolled, kKeepXup (kBias only: without a forward pass the
// backward pass evaluates each transform once anyway) and kTrig as for
// fd_jsi_instance.
template <bool kBias, class S, int C, bool kKeepXup, bool kUnrolled, Trig kTrig>
__host__ __device__ __forceinline__ void jsi_passes(const ThreadModelParams<S, C>& model, DofColumn<const S> q,
                                                    DofColumn<const S> qd, DofColumn<const S> tau,
                                                    const Force<S>* fext, const S* armature, S (&x)[C],
                                                    S (&M)[C * (C + 1) / 2]) {
  constexpr int kRegs = kUnrolled ? C : 1;  // register copies of q, qd when unrolled
  constexpr bool kKeep = kBias && kKeepXup;
  constexpr int kXup = kKeep ? C : 1;
  constexpr int kStack = kBias ? C : 1;     // extent of the bias forces' stack arrays
  const Index n = model.nv;
  S q_r[kRegs], qd_r[kRegs];
  Transform<S> Xup[kXup];       // (nv) parent -> body transforms (kKeepXup)
  Force<S> w[C];                // (nv) body i's net force f_i until its backward step (kBias), then
                                // the force F_i of column i of M, carried towards the root
  Motion<S> sv[kStack], sa[kStack];  // stack: v, a of kStacked bodies (kBias)
  Force<S> sf[kStack];          // stack: f of kStacked bodies plus their children other than the
                                // next (kBias)
  Inertia<S> sI[C];             // stack: the same for composite inertias

  // load: all of one instance's inputs in flight before the first use
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = 0; i < C; ++i) {
    if (i < n) {
      if constexpr (kUnrolled) {
        q_r[kUnrolled ? i : 0] = q[i];
        if constexpr (kBias) qd_r[kUnrolled ? i : 0] = qd[i];
      }
      if constexpr (kBias) x[i] = tau[i];
    }
  }

  if constexpr (kBias) {
    // forward: kinematics and the bias forces' body forces (RNEA with qdd = 0)
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
      const Transform<S> X = joint_transform<kTrig>(b, kUnrolled ? q_r[kUnrolled ? i : 0] : q[i]);
      if constexpr (kKeep) Xup[kKeep ? i : 0] = X;
      const RneaForward<S> o = rnea_forward_step(b, X, vp, ap, kUnrolled ? qd_r[kUnrolled ? i : 0] : qd[i], S(0));
      w[i] = fext ? o.f - fext[i] : o.f;
      if (fl & kStacked) sv[i] = o.v, sa[i] = o.a, sf[i] = w[i], sI[i] = b.I;
      v_prev = o.v;
      a_prev = o.a;
    }
  } else {
    // a branch point's composite inertia starts as its rigid inertia (the forward
    // pass does this when there is one)
#pragma unroll(kUnrolled ? C : 1)
    for (Index i = 0; i < C; ++i)
      if (i < n && (model.flags[i] & kStacked)) sI[i] = model.body[i].I;
  }

  // backward: composite inertias, the columns of M (and the bias forces)
  Force<S> fcarry = Force<S>::zero();      // Xup^T f of body i + 1, when its parent is body i (kBias)
  Inertia<S> Icarry = Inertia<S>::zero();  // its composite inertia in body i's frame
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = C - 1; i >= 0; --i) {
    if (i >= n) continue;
    const Body<S>& b = model.body[i];
    const int fl = model.flags[i];
    Force<S> fi = Force<S>::zero();
    if constexpr (kBias) fi = (fl & kStacked) ? sf[i] : w[i];
    Inertia<S> Ic = (fl & kStacked) ? sI[i] : b.I;
    if (i + 1 < n && (model.flags[i + 1 < C ? i + 1 : i] & kParentIsPrev)) {
      if constexpr (kBias) fi += fcarry;
      Ic += Icarry;
    }
    if constexpr (kBias) x[i] -= joint_project(b, fi);  // tau_i - h_i
    // the columns of i's descendants have reached its frame: M(k, i) = S_i^T F_k
    for_descendants<kUnrolled>(model, i, [&](Index k) { M[tri(k, i)] = joint_project(b, w[k]); });
    w[i] = crba_column_force(b, Ic);
    M[tri(i, i)] = joint_project(b, w[i]);
    if (armature) M[tri(i, i)] += armature[i];
    if (fl & kParentIsBase) continue;
    Transform<S> X;
    if constexpr (kKeep) X = Xup[kKeep ? i : 0];
    else X = joint_transform<kTrig>(b, kUnrolled ? q_r[kUnrolled ? i : 0] : q[i]);
    Force<S> up = Force<S>::zero();
    if constexpr (kBias) up = X.apply_transpose(fi);
    const Inertia<S> Iup = crba_composite_step(X, Ic);
    if (fl & kParentIsPrev) {
      if constexpr (kBias) fcarry = up;
      Icarry = Iup;
    } else {
      if constexpr (kBias) sf[b.parent] += up;
      sI[b.parent] += Iup;
    }
    w[i] = crba_column_step(X, w[i]);
    for_descendants<kUnrolled>(model, i, [&](Index k) { w[k] = crba_column_step(X, w[k]); });
  }
}

}  // namespace fd_detail

// The joint-space inertia matrix M(q) of one instance by the composite-rigid-body
// algorithm (CRBA, Featherstone (2008) 6.2): composite inertias Ic_i from the leaves
// to the root, then each column's force F_i = Ic_i S_i carried to the root,
// M(i, j) = S_j^T F_i along the way; the formulas and the order of summation of the
// serial scandyn::crba (src/algorithm/reference.cpp), over the same step functions
// (crba_composite_step, crba_column_force, crba_column_step; on the host bit-identical
// to it). The same code computes fd_jsi_instance's mass matrix (fd_detail::jsi_passes).
//
// Out: M as a packed lower triangle, M(k, j) (j <= k) at fd_detail::tri(k, j) =
// k (k + 1) / 2 + j, written for j = k and for j an ancestor of k; the entries of
// pairs of which neither body is an ancestor of the other are zero in M and are NOT
// written (mass_matrix_instance, scandyn/cuda/mass_matrix.hpp, writes the full
// matrix). armature (optional, nv scalars) is added to the diagonal.
//
// Also a host function (under nvcc), so the tests check it without a device.
// kUnrolled (default for capacity 8): every loop over compile-time indices, so that
// M (C (C + 1) / 2 scalars), the column forces and the inputs can stay in
// registers; otherwise per-thread (local) memory and walks up the parents. kTrig:
// how joint angles become sin and cos (see joint_sincos).
template <class S, int C, bool kUnrolled = (C <= 8), Trig kTrig = Trig::Library>
__host__ __device__ __forceinline__ void crba_instance(const ThreadModelParams<S, C>& model, DofColumn<const S> q,
                                                      S (&M)[C * (C + 1) / 2], const S* armature = nullptr) {
  S unused[C];  // the bias forces' tau - h, which the CRBA alone does not compute (never touched)
  fd_detail::jsi_passes<false, S, C, false, kUnrolled, kTrig>(model, q, DofColumn<const S>{nullptr, 0},
                                                              DofColumn<const S>{nullptr, 0}, nullptr, armature,
                                                              unused, M);
}

// Forward dynamics of one instance by the joint-space inertia:
//   qdd = M(q)^{-1} (tau - h(q, qd, fext)),
// gravity included; fext: nv body wrenches or null. Returns -1, or the DoF whose
// pivot was not positive and finite, in which case qdd is not written.
//
// One forward pass (transforms, velocities, accelerations and body forces of the
// RNEA with qdd = 0) and one backward pass that, for each body i from the last,
// completes its force (h_i = S_i^T f_i), its composite inertia Ic_i, the entries
// M(k, i) of the columns k of its descendants (their forces F_k reach body i's frame
// there) and its own column's force F_i = Ic_i S_i, then carries f_i, Ic_i and every
// F_k of its subtree to its parent: crba_instance's passes with the bias forces
// riding along (fd_detail::jsi_passes). Then the L^T L factorisation of the packed lower
// triangle of M, with the pivot check, and the two triangular solves. Each entry is
// computed by the reference's formulas in the reference's order of summation.
//
// Also a host function (under nvcc), so the tests check its logic without a device.
//
// State (per thread): M as a packed lower triangle of C (C + 1) / 2 scalars, tau - h
// and the solution (C), the forces f_i / F_i (C, one slot per body: body i's force
// until its backward step, then column i's), and a stack for the bodies at which
// the tree branches (kStacked), as in rnea_instance. With kUnrolled (the default for
// capacity 8) every loop runs over compile-time indices so that all of it but the
// branch stack lives in registers, and the tree's sparsity is tested per entry from
// ThreadModelParams::ancestors (C^3 / 6 tests in the factorisation); otherwise the
// arrays live in per-thread (local) memory and the ancestor loops walk the parents,
// touching only the entries a tree has. (Capacity 16 unrolled needs more than 255
// registers in float too: M alone is 136 scalars.) kKeepXup keeps each body's
// transform from the forward pass for the backward pass; otherwise joint_transform
// is evaluated again there (fewer registers, more arithmetic).
//
// armature (optional, nv scalars, any memory the thread can read): joint-space
// inertias added to M's diagonal before the factorisation, as in the serial fd_jsi
// (scandyn/sim's implicit damping and springs); null adds nothing.
template <class S, int C, bool kKeepXup = false, bool kUnrolled = (C <= 8), Trig kTrig = Trig::Library>
__host__ __device__ __forceinline__ Index fd_jsi_instance(const ThreadModelParams<S, C>& model,
                                                          DofColumn<const S> q, DofColumn<const S> qd,
                                                          DofColumn<const S> tau, const Force<S>* fext,
                                                          DofColumn<S> qdd, const S* armature = nullptr) {
  using fd_detail::tri;
  using std::sqrt;
  const Index n = model.nv;
  S x[C];                // (nv) tau - h, then the solution qdd
  S M[C * (C + 1) / 2];  // M(k, j) at tri(k, j) for j = k and j an ancestor of k; then L

  // CRBA and bias forces: one forward and one backward pass
  fd_detail::jsi_passes<true, S, C, kKeepXup, kUnrolled, kTrig>(model, q, qd, tau, fext, armature, x, M);

  // M = L^T L in place (ltl_factor), from the last DoF to the first
#pragma unroll(kUnrolled ? C : 1)
  for (Index k = C - 1; k >= 0; --k) {
    if (k >= n) continue;
    const S d = M[tri(k, k)];
    if (!pivot_ok(d)) return k;
    const S Lkk = sqrt(d);
    M[tri(k, k)] = Lkk;
    const S inv = S(1) / Lkk;
    fd_detail::for_ancestors<kUnrolled>(model, k, [&](Index i) { M[tri(k, i)] *= inv; });
    fd_detail::for_ancestors<kUnrolled>(model, k, [&](Index i) {
      const S Lki = M[tri(k, i)];
      M[tri(i, i)] -= Lki * M[tri(k, i)];
      fd_detail::for_ancestors<kUnrolled>(model, i, [&](Index j) { M[tri(i, j)] -= Lki * M[tri(k, j)]; });
    });
  }

  // L^T y = tau - h, then L qdd = y (ltl_solve)
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = C - 1; i >= 0; --i) {
    if (i >= n) continue;
    x[i] /= M[tri(i, i)];
    const S xi = x[i];
    fd_detail::for_ancestors<kUnrolled>(model, i, [&](Index j) { x[j] -= M[tri(i, j)] * xi; });
  }
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = 0; i < C; ++i) {
    if (i >= n) continue;
    S acc = x[i];
    fd_detail::for_ancestors<kUnrolled>(model, i, [&](Index j) { acc -= M[tri(i, j)] * x[j]; });
    x[i] = acc / M[tri(i, i)];
    qdd[i] = x[i];
  }
  return -1;
}

namespace fd_detail {

// Body i's state between the passes of aba_instance, one storage for two uses (8
// scalars): its velocity v_i = [x; y] from pass 1 until pass 2 reaches body i, then
// U_i = IA_i S_i = [x; y], D_i and u_i for pass 3.
template <class S>
struct AbaBodyState {
  Vec3<S> x, y;  // v_i (angular; linear), then U_i (moment; force)
  S D, u;        // D_i = S_i^T U_i, u_i = tau_i - S_i^T pA_i (from pass 2)
  __host__ __device__ __forceinline__ Motion<S> v() const { return {x, y}; }
  __host__ __device__ __forceinline__ Force<S> U() const { return {x, y}; }
  __host__ __device__ __forceinline__ void set_v(const Motion<S>& v) { x = v.w, y = v.v; }
  __host__ __device__ __forceinline__ void set_terms(const Force<S>& U, S Dv, S uv) {
    x = U.n, y = U.f, D = Dv, u = uv;
  }
};

// Slot s (a run-time value) of K branch slots. With K < C a loop of compile-time
// indices selects it, so that the slots can stay in registers (K selects per
// scalar); with K == C the slot indexes the array (per-thread local memory).
template <int K, int C, class T>
__host__ __device__ __forceinline__ T slot_get(const T (&slots)[K], int s) {
  if constexpr (K < C) {
    T r = slots[0];
#pragma unroll
    for (int k = 1; k < K; ++k)
      if (k == s) r = slots[k];
    return r;
  } else {
    return slots[s];
  }
}

// f(slots[s]) for a run-time slot s, as slot_get.
template <int K, int C, class T, class F>
__host__ __device__ __forceinline__ void slot_update(T (&slots)[K], int s, F&& f) {
  if constexpr (K < C) {
#pragma unroll
    for (int k = 0; k < K; ++k)
      if (k == s) f(slots[k]);
  } else {
    f(slots[s]);
  }
}

}  // namespace fd_detail

// Forward dynamics of one instance by the articulated-body algorithm (ABA,
// Featherstone (2008) 7.3): the three passes of the serial scandyn::aba
// (src/algorithm/reference.cpp) over the same step functions (steps.hpp), with the
// same sums in the same order: pass 1 (velocities), pass 2 from the last body to
// the first (c = v x S qd and pA = v x* I v - fext, aba_joint_terms, the pivot
// check, aba_backward_to_parent into the parent's articulated inertia and bias
// force), pass 3 from the first to the last (aba_acceleration_step). Gravity
// included; fext: nv body wrenches or null. Returns -1, or the DoF whose articulated
// pivot D_i = S_i^T IA_i S_i was not positive and finite (the DoF the serial aba
// reports), in which case qdd is not written (pass 2 completes before pass 3 writes
// anything).
//
// What stays live between the passes is kept small, so that a chain's state fits
// in registers: pass 1 keeps only each body's velocity v_i; pass 2 computes c_i and
// pA_i from it when it reaches body i (the serial aba's values: the same functions
// of the same v_i) and keeps U_i, D_i, u_i in v_i's place (AbaBodyState, 8 scalars
// per body); pass 3 evaluates v_i and c_i again from the parent's velocity, next to
// the acceleration (one more transform of a motion per body).
//
// A parent receives its children in descending order, as in the reference. Body
// i + 1 (kParentIsPrev) is the last of them and hands its articulated inertia and
// bias force over in registers (IAcarry, pcarry), added after the others. Every
// other child (a branch child) adds into its parent's branch slot (kSlotShift): the
// highest-numbered one (kOpensSlot) starts the slot from the parent's rigid inertia
// and bias force, the rest add to it, and the parent reads it back. The slot also
// carries the branch point's v (pass 1) and v, a (pass 3) to its branch children.
// kSlots is how many slots there are:
//   0           no branch children: every body's parent is the previous body or the
//               base (ThreadModel::branch_slots() == 0, e.g. a chain, or chains
//               hanging from the base); no slot code at all;
//   1 .. C - 1  slots selected by loops of compile-time indices, so that they can
//               stay in registers; only for models with branch_slots() <= kSlots
//               (others would get wrong results; choose_aba_kernel respects it);
//   C           (the default) slots indexed at run time (per-thread local memory);
//               any model.
//
// armature (optional, nv scalars, any memory the thread can read): joint-space
// inertias added to the pivots D_i, i.e. to M's diagonal (the serial aba's
// armature; the simulator's implicit damping and springs); null: none.
//
// Also a host function (under nvcc), so the tests check its logic without a device.
//
// State (per thread): AbaBodyState (C x 8 scalars), q and qd (C each, when
// unrolled), the slots (kSlots x (v, a, an articulated inertia of 21 scalars and a
// bias force: 39 scalars)). With kUnrolled every loop runs over compile-time indices so that the
// per-body state can live in registers; otherwise it is per-thread (local) memory.
// kKeepXup keeps each body's transform from pass 1 for passes 2 and 3; otherwise
// joint_transform is evaluated again in each (fewer registers, more arithmetic).
// kTrig: how joint angles become sin and cos (see joint_sincos).
template <class S, int C, bool kKeepXup = false, bool kUnrolled = (C <= 8), Trig kTrig = Trig::Library,
          int kSlots = C>
__host__ __device__ __forceinline__ Index aba_instance(const ThreadModelParams<S, C>& model, DofColumn<const S> q,
                                                       DofColumn<const S> qd, DofColumn<const S> tau,
                                                       const Force<S>* fext, DofColumn<S> qdd,
                                                       const S* armature = nullptr) {
  static_assert(kSlots >= 0 && kSlots <= C, "aba_instance: kSlots is 0 (chains), below C (registers) or C");
  using fd_detail::slot_get;
  using fd_detail::slot_update;
  constexpr bool kBranches = kSlots > 0;     // are there branch children at all
  constexpr int kRegs = kUnrolled ? C : 1;   // register copies of q, qd when unrolled
  constexpr int kXup = kKeepXup ? C : 1;
  constexpr int K = kSlots > 0 ? kSlots : 1;  // extent of the slot arrays
  const Index n = model.nv;
  S q_r[kRegs] = {}, qd_r[kRegs] = {};
  Transform<S> Xup[kXup] = {};         // (nv) parent -> body transforms (kKeepXup)
  fd_detail::AbaBodyState<S> st[C];    // (nv) v_i, then U_i, D_i, u_i
  Motion<S> sv[K], sa[K];              // (slots) a branch point's v (passes 1 and 3) and a (pass 3)
  ABInertia<S> sIA[K];                 // (slots) a branch point's articulated inertia (pass 2) ...
  Force<S> spA[K];                     // ... and bias force

  auto q_at = [&](Index i) -> S {
    if constexpr (kUnrolled) return q_r[kUnrolled ? i : 0];
    else return q[i];
  };
  auto qd_at = [&](Index i) -> S {
    if constexpr (kUnrolled) return qd_r[kUnrolled ? i : 0];
    else return qd[i];
  };
  auto xup = [&](Index i, const Body<S>& b) -> Transform<S> {
    if constexpr (kKeepXup) return Xup[kKeepXup ? i : 0];
    else return joint_transform<kTrig>(b, q_at(i));
  };
  auto slot_of = [&](Index j) -> int { return branch_slot(model.flags[j]); };
  // v_p of a body p < i while pass 2 is at body i (its state still holds v_p)
  auto velocity_of = [&](Index p, Index i) -> Motion<S> {
    if constexpr (kUnrolled) {
      Motion<S> r = st[0].v();
#pragma unroll
      for (Index j = 1; j < C; ++j)
        if (j < i && j == p) r = st[j].v();
      return r;
    } else {
      return st[p].v();
    }
  };

  // load q, qd: all of them in flight before the first use (unrolled)
  if constexpr (kUnrolled) {
#pragma unroll
    for (Index i = 0; i < C; ++i) {
      if (i < n) {
        q_r[kUnrolled ? i : 0] = q[i];
        qd_r[kUnrolled ? i : 0] = qd[i];
      }
    }
  }

  // pass 1: velocities, root to leaves
  Motion<S> v_prev = Motion<S>::zero();  // body i - 1's v
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = 0; i < C; ++i) {
    if (i >= n) continue;  // (not break: a loop of C trips unrolls, indices stay constant)
    const Body<S>& b = model.body[i];
    const int fl = model.flags[i];
    Motion<S> vp = Motion<S>::zero();
    if (fl & kParentIsPrev) vp = v_prev;
    else if (kBranches && !(fl & kParentIsBase)) vp = slot_get<K, C>(sv, slot_of(b.parent));
    const Transform<S> X = joint_transform<kTrig>(b, q_at(i));
    if constexpr (kKeepXup) Xup[kKeepXup ? i : 0] = X;
    const Motion<S> v = aba_forward_step(b, X, vp, qd_at(i)).v;
    st[i].set_v(v);
    if (kBranches && (fl & kStacked)) slot_update<K, C>(sv, slot_of(i), [&](Motion<S>& s) { s = v; });
    v_prev = v;
  }
  if constexpr (kBranches && kSlots < C) {
    // pass 1's slot values are dead (pass 3 writes its own before reading them);
    // saying so frees their registers during pass 2
#pragma unroll
    for (int k = 0; k < K; ++k) sv[k] = Motion<S>::zero();
  }

  // pass 2: articulated inertias and bias forces, leaves to root
  ABInertia<S> IAcarry{};  // body i + 1's contribution Xup^T Ia Xup, when its parent is body i
  Force<S> pcarry = Force<S>::zero();
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = C - 1; i >= 0; --i) {
    if (i >= n) continue;
    const Body<S>& b = model.body[i];
    const int fl = model.flags[i];
    const Motion<S> v = st[i].v();
    // IA_i and pA_i: from the branch slot (rigid inertia, bias force and the branch
    // children), or the rigid inertia and bias force; then body i + 1's
    ABInertia<S> IA;
    Force<S> p;
    if (kBranches && (fl & kStacked)) {
      IA = slot_get<K, C>(sIA, slot_of(i));
      p = slot_get<K, C>(spA, slot_of(i));
    } else {
      IA = ABInertia<S>::from(b.I);
      p = aba_bias_force(b, v);
      if (fext) p = p - fext[i];
    }
    if (i + 1 < n && (model.flags[i + 1 < C ? i + 1 : i] & kParentIsPrev)) {
      IA += IAcarry;
      p += pcarry;
    }
    Force<S> Ui;
    S Di, ui;
    aba_joint_terms(b, IA, p, tau[i], Ui, Di, ui, armature ? armature[i] : S(0));
    if (!pivot_ok(Di)) return i;
    st[i].set_terms(Ui, Di, ui);
    if (fl & kParentIsBase) continue;
    // the contribution to the parent, from zero (0 + x == x: the parent's sums are
    // the reference's)
    ABInertia<S> IAc{};
    Force<S> pc = Force<S>::zero();
    aba_backward_to_parent(xup(i, b), IA, p, aba_velocity_product(b, v, qd_at(i)), Ui, Di, ui, IAc, pc);
    if (fl & kParentIsPrev) {
      IAcarry = IAc;
      pcarry = pc;
    } else if constexpr (kBranches) {
      const Index par = b.parent;
      if (fl & kOpensSlot) {
        // the first branch child to arrive: the parent's rigid inertia and bias force first
        const Body<S>& bp = model.body[par];
        Force<S> pA = aba_bias_force(bp, velocity_of(par, i));
        if (fext) pA = pA - fext[par];
        const ABInertia<S> IAp = ABInertia<S>::from(bp.I) + IAc;
        pA += pc;
        slot_update<K, C>(sIA, slot_of(par), [&](ABInertia<S>& s) { s = IAp; });
        slot_update<K, C>(spA, slot_of(par), [&](Force<S>& s) { s = pA; });
      } else {
        slot_update<K, C>(sIA, slot_of(par), [&](ABInertia<S>& s) { s += IAc; });
        slot_update<K, C>(spA, slot_of(par), [&](Force<S>& s) { s += pc; });
      }
    }
  }

  // pass 3: accelerations, root to leaves
  const Motion<S> a0 = model.a0;
  Motion<S> a_prev = a0;  // body i - 1's a (and v_prev its v)
  v_prev = Motion<S>::zero();
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = 0; i < C; ++i) {
    if (i >= n) continue;
    const Body<S>& b = model.body[i];
    const int fl = model.flags[i];
    Motion<S> vp = Motion<S>::zero(), ap = a0;
    if (fl & kParentIsPrev) {
      vp = v_prev;
      ap = a_prev;
    } else if (kBranches && !(fl & kParentIsBase)) {
      vp = slot_get<K, C>(sv, slot_of(b.parent));
      ap = slot_get<K, C>(sa, slot_of(b.parent));
    }
    const Transform<S> X = xup(i, b);
    const AbaForward<S> o = aba_forward_step(b, X, vp, qd_at(i));
    Motion<S> a;
    qdd[i] = aba_acceleration_step(b, X, ap, o.c, st[i].U(), st[i].D, st[i].u, a);
    if (kBranches && (fl & kStacked)) {
      slot_update<K, C>(sv, slot_of(i), [&](Motion<S>& s) { s = o.v; });
      slot_update<K, C>(sa, slot_of(i), [&](Motion<S>& s) { s = a; });
    }
    v_prev = o.v;
    a_prev = a;
  }
  return -1;
}
#endif  // __CUDACC__

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
