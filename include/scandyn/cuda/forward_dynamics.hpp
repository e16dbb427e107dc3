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
//                              kernels (this header under nvcc) and on the host;
//   fd_instances_kernel    one thread per instance (kernels/fd_instances.cu);
//   launch_fd_jsi_instances()  host wrapper: device pointers, a stream, returns the
//                              cudaError_t of the launch, never synchronises.
// and the engine CudaForwardDynamics on top:
//     compute()        HOST pointers: copies in, launches, copies out, synchronises;
//                      returns an FdBatchStatus.
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
#pragma once

#include <cstddef>
#include <memory>
#include <string>
#include <vector>

#include "scandyn/backend.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/cuda/fd_dense.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

namespace scandyn {
namespace cuda {

// Threads per block of fd_instances_kernel.
inline constexpr int kFdInstancesBlock = 128;

// What compute() reports about the factorisations of one batch.
struct FdBatchStatus {
  Index failed = 0;           // instances whose mass matrix had a pivot that is not positive and finite
  Index first_instance = -1;  // the lowest such instance, -1 when none
  Index first_dof = -1;       // the DoF at which its factorisation stopped
  bool ok() const { return failed == 0; }
  // "" when ok(); else one line, e.g.
  //   "instance 3: mass matrix pivot at DoF 6 is not positive"
  // followed by " (and 41 more instances)" when others failed too.
  std::string message() const {
    if (ok()) return "";
    std::string s = "instance " + std::to_string(first_instance) + ": mass matrix pivot at DoF " +
                    std::to_string(first_dof) + " is not positive";
    if (failed > 1)
      s += " (and " + std::to_string(failed - 1) + " more instance" + (failed > 2 ? "s" : "") + ")";
    return s;
  }
};

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

// The same by the articulated-body algorithm (aba_instance, fd_instances_kernel with kAba),
// with the same arguments, checks and return values; failed_dof_out[b] is -1 or the
// DoF whose articulated pivot D failed (qdd of that instance unwritten).
template <class S>
cudaError_t launch_aba_instances(const ThreadModel<S>& model, const FdBatchIn<S>& batch_in,
                                 const BatchView<S>& qdd_out, int* failed_dof_out, cudaStream_t stream);

// Which algorithm CudaForwardDynamics runs.
enum class FdAlgorithm {
  Auto,  // Jsi. Measured on the H100 (bench_cuda_fd, 10^7 instances): ABA is faster
         // from about 30 DoF (atlas: 28.8 ms against 48.0 ms float, 57 against
         // 95 ms double), slower at 7-12 (iiwa float 9.8 against 4.5 ms: the ABA
         // kernel spills at 128 registers); a choice by size is the next step
  Jsi,   // joint-space inertia: jsi_thread up to kMaxThreadDofs DoF, jsi_dense beyond
  Aba,   // articulated-body algorithm, one thread per instance ("aba_thread"), up to
         // kMaxThreadDofs DoF (beyond: BackendError, no kernel yet)
};

// The batched forward-dynamics engine on one CUDA device (the device current at
// construction).
template <class S>
class CudaForwardDynamics {
 public:
  // Prepares the model and allocates the device buffers compute() stages through:
  // q, qd, tau, qdd and fext for options.max_batch instances plus one int each,
  // (10 * nv * sizeof(S) + sizeof(int)) * max_batch bytes (compute_async needs none
  // of them); beyond kMaxThreadDofs DoF also DenseJsiPlan's buffers (the mass
  // matrices: nv^2 scalars per instance). options.strategy must be Auto or
  // Recursion. Throws BackendError when there is no usable device, or the buffers
  // do not fit in device memory (the message gives the bytes needed and the bytes
  // free). algorithm: FdAlgorithm::Aba selects the articulated-body algorithm
  // (strategy "aba_thread"), for models of up to kMaxThreadDofs DoF (beyond: a
  // BackendError); Auto and Jsi the joint-space inertia. The staging and the
  // compute() / compute_async() contracts are the same for both.
  CudaForwardDynamics(const ModelTpl<S>& model, const BackendOptions& options,
                      FdAlgorithm algorithm = FdAlgorithm::Auto);
  ~CudaForwardDynamics();
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
  FdBatchStatus compute(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed_dof = nullptr);

  // DEVICE pointers, any strides, on `stream` (failed_dof: B ints on the device).
  // Asynchronous: returns after queuing the kernels, with no hidden
  // synchronisation, copy or allocation.
  //   jsi_thread: launch_fd_jsi_instances with this engine's model; not limited by
  //               max_batch; safe from several host threads on different streams;
  //   aba_thread: launch_aba_instances, likewise;
  //   jsi_dense:  DenseJsiPlan::launch; B <= max_batch (else cudaErrorInvalidValue);
  //               the engine's scratch, so one stream at a time.
  cudaError_t compute_async(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed_dof,
                            cudaStream_t stream);

  // "jsi_thread" (one thread per instance, up to kMaxThreadDofs DoF), "jsi_dense"
  // (CRBA per block, cuSOLVER's batched Cholesky: DenseJsiPlan, beyond) or
  // "aba_thread" (FdAlgorithm::Aba: ABA, one thread per instance)
  std::string strategy() const { return aba_ ? "aba_thread" : dense_ ? "jsi_dense" : "jsi_thread"; }
  // Jsi or Aba: the algorithm the engine runs (Auto resolved)
  FdAlgorithm algorithm() const { return aba_ ? FdAlgorithm::Aba : FdAlgorithm::Jsi; }
  std::string backend() const { return "cuda"; }

  const ThreadModel<S>* thread_model() const { return thread_.get(); }  // null for jsi_dense
  Index nv() const { return nv_; }
  Index max_batch() const { return max_batch_; }
  int device() const { return device_; }
  std::size_t device_bytes() const { return bytes_; }  // held by the staging buffers

 private:
  Index nv_ = 0;
  bool aba_ = false;
  std::unique_ptr<ThreadModel<S>> thread_;
  std::unique_ptr<DenseJsiPlan<S>> dense_;
  Index max_batch_ = 0;
  int device_ = 0;
  std::size_t bytes_ = 0;
  // compute()'s stream and its one allocation: q, qd, tau, qdd (nv x max_batch each),
  // fext, failed DoFs
  std::unique_ptr<detail::StagingBuffer> staging_;
  std::vector<int> failed_host_;  // (max_batch) when the caller passes no failed_dof
  std::vector<S> kept_;           // qdd entries of failed instances, restored after the copy back
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

}  // namespace fd_detail

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
// F_k of its subtree to its parent. Then the L^T L factorisation of the packed lower
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
  constexpr int kRegs = kUnrolled ? C : 1;  // register copies of q, qd when unrolled
  constexpr int kXup = kKeepXup ? C : 1;
  const Index n = model.nv;
  S q_r[kRegs], qd_r[kRegs];
  S x[C];                   // (nv) tau - h, then the solution qdd
  S M[C * (C + 1) / 2];     // M(k, j) at tri(k, j) for j = k and j an ancestor of k; then L
  Transform<S> Xup[kXup];   // (nv) parent -> body transforms (kKeepXup)
  Force<S> w[C];            // (nv) body i's net force f_i until its backward step, then the
                            // force F_i of column i of M, carried towards the root
  Motion<S> sv[C], sa[C];   // stack: v, a of kStacked bodies
  Force<S> sf[C];           // stack: f of kStacked bodies plus their children other than the next
  Inertia<S> sI[C];         // stack: the same for composite inertias

  // load: all of one instance's inputs in flight before the first use
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = 0; i < C; ++i) {
    if (i < n) {
      if constexpr (kUnrolled) {
        q_r[kUnrolled ? i : 0] = q[i];
        qd_r[kUnrolled ? i : 0] = qd[i];
      }
      x[i] = tau[i];
    }
  }

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
    if constexpr (kKeepXup) Xup[kKeepXup ? i : 0] = X;
    const RneaForward<S> o = rnea_forward_step(b, X, vp, ap, kUnrolled ? qd_r[kUnrolled ? i : 0] : qd[i], S(0));
    w[i] = fext ? o.f - fext[i] : o.f;
    if (fl & kStacked) sv[i] = o.v, sa[i] = o.a, sf[i] = w[i], sI[i] = b.I;
    v_prev = o.v;
    a_prev = o.a;
  }

  // backward: bias forces, composite inertias and the columns of M. Body i's force
  // and composite inertia go to its parent, the next body's through registers
  // (fcarry, Icarry), others' through the stack; a parent receives its children in
  // descending order, as in the reference.
  Force<S> fcarry = Force<S>::zero();      // Xup^T f of body i + 1, when its parent is body i
  Inertia<S> Icarry = Inertia<S>::zero();  // its composite inertia in body i's frame
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = C - 1; i >= 0; --i) {
    if (i >= n) continue;
    const Body<S>& b = model.body[i];
    const int fl = model.flags[i];
    Force<S> fi = (fl & kStacked) ? sf[i] : w[i];
    Inertia<S> Ic = (fl & kStacked) ? sI[i] : b.I;
    if (i + 1 < n && (model.flags[i + 1 < C ? i + 1 : i] & kParentIsPrev)) {
      fi += fcarry;
      Ic += Icarry;
    }
    x[i] -= joint_project(b, fi);  // tau_i - h_i
    // the columns of i's descendants have reached its frame: M(k, i) = S_i^T F_k
    fd_detail::for_descendants<kUnrolled>(model, i, [&](Index k) { M[tri(k, i)] = joint_project(b, w[k]); });
    w[i] = crba_column_force(b, Ic);
    M[tri(i, i)] = joint_project(b, w[i]);
    if (armature) M[tri(i, i)] += armature[i];
    if (fl & kParentIsBase) continue;
    Transform<S> X;
    if constexpr (kKeepXup) X = Xup[kKeepXup ? i : 0];
    else X = joint_transform<kTrig>(b, kUnrolled ? q_r[kUnrolled ? i : 0] : q[i]);
    const Force<S> up = X.apply_transpose(fi);
    const Inertia<S> Iup = crba_composite_step(X, Ic);
    if (fl & kParentIsPrev) fcarry = up, Icarry = Iup;
    else sf[b.parent] += up, sI[b.parent] += Iup;
    w[i] = crba_column_step(X, w[i]);
    fd_detail::for_descendants<kUnrolled>(model, i, [&](Index k) { w[k] = crba_column_step(X, w[k]); });
  }

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

// Forward dynamics of one instance by the articulated-body algorithm (ABA,
// Featherstone (2008) 7.3): the three passes of the serial scandyn::aba
// (src/algorithm/reference.cpp) over the same step functions (steps.hpp), in its
// order: pass 1 (velocities, c = v x S qd, bias forces pA = v x* I v - fext), pass 2
// from the last body to the first (aba_joint_terms, the pivot check, then
// aba_backward_to_parent into the parent's articulated inertia and bias force),
// pass 3 from the first to the last (aba_acceleration_step). gravity included;
// fext: nv body wrenches or null. Returns -1, or the DoF whose articulated pivot
// D_i = S_i^T IA_i S_i was not positive and finite (the DoF the serial aba reports),
// in which case qdd is not written (pass 2 completes before pass 3 writes anything).
//
// A parent receives its children in descending order, as in the reference: body
// i + 1 (kParentIsPrev) is the last of them, and hands its articulated inertia and
// bias force over in registers (IAcarry, pcarry), added after the others; every
// other child adds into its parent's slot of the stack arrays sIA / pA (the parent is
// then kStacked, and its sIA slot starts as its rigid inertia in pass 1). A body's
// v (pass 1) and a (pass 3) reach its children in registers (body i + 1) or through
// the stack array sm (kStacked bodies; pass 1's v there is dead once pass 1 ends).
//
// Also a host function (under nvcc), so the tests check its logic without a device.
//
// State (per thread): c, U, pA (C each, 6 scalars), D, u (C), the stack arrays
// sIA (C articulated inertias, 21 scalars; only kStacked bodies' slots are used) and
// sm (C motions). With kUnrolled every loop runs over compile-time indices so that
// the per-body arrays can live in registers; otherwise they are per-thread (local)
// memory. kKeepXup keeps each body's transform from pass 1 for passes 2 and 3;
// otherwise joint_transform is evaluated again in each (fewer registers, more
// arithmetic).
template <class S, int C, bool kKeepXup = false, bool kUnrolled = (C <= 8), Trig kTrig = Trig::Library>
__host__ __device__ __forceinline__ Index aba_instance(const ThreadModelParams<S, C>& model, DofColumn<const S> q,
                                                       DofColumn<const S> qd, DofColumn<const S> tau,
                                                       const Force<S>* fext, DofColumn<S> qdd) {
  constexpr int kRegs = kUnrolled ? C : 1;  // register copies of q when unrolled
  constexpr int kXup = kKeepXup ? C : 1;
  const Index n = model.nv;
  S q_r[kRegs] = {};
  Transform<S> Xup[kXup];  // (nv) parent -> body transforms (kKeepXup)
  Motion<S> c[C];          // (nv) v_i x S_i qd_i
  Force<S> pA[C];          // (nv) bias force; non-chain children add theirs here
  Force<S> U[C];           // (nv) IA_i S_i
  S D[C], u[C];            // (nv) S_i^T U_i, tau_i - S_i^T pA_i
  ABInertia<S> sIA[C];     // stack: articulated inertias of kStacked bodies
  Motion<S> sm[C];         // stack: v (pass 1), then a (pass 3), of kStacked bodies

  auto q_at = [&](Index i) -> S {
    if constexpr (kUnrolled) return q_r[kUnrolled ? i : 0];
    else return q[i];
  };
  auto xup = [&](Index i, const Body<S>& b) -> Transform<S> {
    if constexpr (kKeepXup) return Xup[kKeepXup ? i : 0];
    else return joint_transform<kTrig>(b, q_at(i));
  };

  // load q: all of it in flight before the first use (unrolled)
  if constexpr (kUnrolled) {
#pragma unroll
    for (Index i = 0; i < C; ++i)
      if (i < n) q_r[kUnrolled ? i : 0] = q[i];
  }

  // pass 1: kinematics and bias forces, root to leaves
  Motion<S> v_prev = Motion<S>::zero();  // body i - 1's v
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = 0; i < C; ++i) {
    if (i >= n) continue;  // (not break: a loop of C trips unrolls, indices stay constant)
    const Body<S>& b = model.body[i];
    const int fl = model.flags[i];
    Motion<S> vp = Motion<S>::zero();
    if (fl & kParentIsPrev) vp = v_prev;
    else if (!(fl & kParentIsBase)) vp = sm[b.parent];
    const Transform<S> X = joint_transform<kTrig>(b, q_at(i));
    if constexpr (kKeepXup) Xup[kKeepXup ? i : 0] = X;
    const AbaForward<S> o = aba_forward_step(b, X, vp, qd[i]);
    c[i] = o.c;
    pA[i] = fext ? o.pA - fext[i] : o.pA;
    if (fl & kStacked) sm[i] = o.v, sIA[i] = ABInertia<S>::from(b.I);
    v_prev = o.v;
  }

  // pass 2: articulated inertias and bias forces, leaves to root
  ABInertia<S> IAcarry{};  // body i + 1's contribution Xup^T Ia Xup, when its parent is body i
  Force<S> pcarry = Force<S>::zero();
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = C - 1; i >= 0; --i) {
    if (i >= n) continue;
    const Body<S>& b = model.body[i];
    const int fl = model.flags[i];
    ABInertia<S> IA = (fl & kStacked) ? sIA[i] : ABInertia<S>::from(b.I);
    Force<S> p = pA[i];
    if (i + 1 < n && (model.flags[i + 1 < C ? i + 1 : i] & kParentIsPrev)) {
      IA += IAcarry;
      p += pcarry;
    }
    Force<S> Ui;
    S Di, ui;
    aba_joint_terms(b, IA, p, tau[i], Ui, Di, ui);
    if (!pivot_ok(Di)) return i;
    U[i] = Ui, D[i] = Di, u[i] = ui;
    if (fl & kParentIsBase) continue;
    const Transform<S> X = xup(i, b);
    if (fl & kParentIsPrev) {
      // the parent's slots start from zero: 0 + x == x, the same sums as the reference's
      IAcarry = ABInertia<S>{};
      pcarry = Force<S>::zero();
      aba_backward_to_parent(X, IA, p, c[i], Ui, Di, ui, IAcarry, pcarry);
    } else {
      aba_backward_to_parent(X, IA, p, c[i], Ui, Di, ui, sIA[b.parent], pA[b.parent]);
    }
  }

  // pass 3: accelerations, root to leaves
  const Motion<S> a0 = model.a0;
  Motion<S> a_prev = a0;  // body i - 1's a
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = 0; i < C; ++i) {
    if (i >= n) continue;
    const Body<S>& b = model.body[i];
    const int fl = model.flags[i];
    Motion<S> ap = a0;
    if (fl & kParentIsPrev) ap = a_prev;
    else if (!(fl & kParentIsBase)) ap = sm[b.parent];
    Motion<S> a;
    qdd[i] = aba_acceleration_step(b, xup(i, b), ap, c[i], U[i], D[i], u[i], a);
    if (fl & kStacked) sm[i] = a;
    a_prev = a;
  }
  return -1;
}
#endif  // __CUDACC__

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
