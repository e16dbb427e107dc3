// scandyn/batch.hpp: the batch types every engine reads and writes.
//
// A batch holds B instances of one model. Per-DoF arrays are plain strided buffers:
// entry (DoF i, instance b) lives at data[i * dof_stride + b * batch_stride].
// scandyn's native layout is structure-of-arrays with the instance innermost,
// q[i * B + b] (BatchView::soa); an array of per-instance rows, q[b * nv + i], is
// BatchView::aos (what NumPy / PyTorch call a (B, nv) C-contiguous array). Any
// other strides work too, so callers pass their own memory without copies.
#pragma once

#include <cstddef>
#include <string>

#include "scandyn/model/model.hpp"

namespace scandyn {

template <class T>
struct BatchView {
  T* data = nullptr;
  Index batch = 0;                 // number of instances B
  std::ptrdiff_t dof_stride = 0;   // elements between DoF i and i + 1 of one instance
  std::ptrdiff_t batch_stride = 0; // elements between instance b and b + 1

  SCANDYN_HD T& at(Index dof, Index b) const { return data[dof * dof_stride + b * batch_stride]; }
  static BatchView soa(T* data, Index nv, Index B) { (void)nv; return {data, B, B, 1}; }
  static BatchView aos(T* data, Index nv, Index B) { return {data, B, 1, nv}; }
};

// Inverse dynamics' inputs: tau = ID(q, qd, qdd, fext).
template <class S>
struct IdBatchIn {
  BatchView<const S> q, qd, qdd;      // (nq x B) joint positions, (nv x B) velocities, accelerations
  const Force<S>* fext = nullptr;     // optional (B x nbodies) body wrenches, fext[b * nbodies + i], body frames
};

// Forward dynamics' inputs: qdd = FD(q, qd, tau, fext).
template <class S>
struct FdBatchIn {
  BatchView<const S> q, qd, tau;      // (nq x B) joint positions, (nv x B) velocities, forces
  const Force<S>* fext = nullptr;     // optional (B x nbodies) body wrenches, fext[b * nbodies + i], body frames
};

// Bias forces' inputs: h = RNEA(q, qd, 0, fext).
template <class S>
struct BiasBatchIn {
  BatchView<const S> q, qd;           // (nq x B) joint positions, (nv x B) velocities
  const Force<S>* fext = nullptr;     // optional (B x nbodies) body wrenches, fext[b * nbodies + i], body frames
};

// Hybrid dynamics' inputs: each DoF has its acceleration or its force given (the
// engine's prescribed mask, HybridDynamics).
template <class S>
struct HybridBatchIn {
  BatchView<const S> q, qd;           // (nv x B) joint positions, velocities
  BatchView<const S> qdd;             // (nv x B) accelerations: read at prescribed DoFs only
  BatchView<const S> tau;             // (nv x B) forces: read at the other DoFs only
  const Force<S>* fext = nullptr;     // optional (B x nv) body wrenches, fext[b * nv + i], body frames
};

// Forward-dynamics methods. Auto resolves by backend and shape (choose_fd_method).
enum class FdMethod {
  Auto,
  Aba,       // articulated-body algorithm
  Jsi,       // joint-space inertia: CRBA + tree-sparse L^T L (dense cuSOLVER beyond 64 DoF on cuda)
  Parallel,  // the parallel chain forward dynamics: scans over links (unbranched chains from the base)
  Hybrid,    // articulated inertias on the host, the other passes as device scans (chains, cuda only)
};

// What failed in one instance of a batch; the pivot named in messages.
enum class Failure {
  None,
  ArticulatedPivot,  // an articulated inertia pivot D_i = S_i^T IA_i S_i (aba, parallel, hybrid)
  MassMatrixPivot,   // a diagonal entry of the mass matrix's L^T L (jsi)
  BothPivots,        // jsi failed, and the aba it fell back to failed too (the DoF is the aba's)
  NonFinite,         // a simulator step left a state entry (q or qd at the DoF) that is not finite
  ResidualTooLarge,  // forward dynamics' run-time check (BackendOptions::fd_check): the estimated
                     // error of qdd, from the residual ID(q, qd, qdd) - tau, is above the threshold
                     // (the DoF is that of the largest correction); qdd holds the flagged result
  NotConverged,      // the variational integrator's Newton iteration did not converge (iteration cap,
                     // a zero or non-finite pivot of its Jacobian's LU, a non-finite residual); the DoF
                     // is that of the largest last correction; the instance kept its state
  LoopNotClosed,     // a simulator step with closed loops whose projection onto them left the state
                     // more than the tolerance off them (max |phi|, |J qd|: BatchStatus::estimate,
                     // threshold; infinite: its factorisation failed), or failed; first_dof
                     // holds the worst loop's index; the instance kept its state
};

// The outcome of one batched call (or, for the simulator, of its steps since the
// last clear). Instances that fail have their outputs left unwritten, never NaN.
struct BatchStatus {
  Index failed = 0;            // failed instances (simulator: failed instance-steps)
  Index first_instance = -1;   // the lowest failing instance, -1 when none
  Index first_dof = -1;        // the DoF at which its computation stopped
  Failure failure = Failure::None;  // what failed in first_instance
  Index fell_back = 0;         // instances whose jsi failed and that aba computed instead
                               // (FdOptions::fallback_aba); not counted in `failed`
  Index retried = 0;           // instances the run-time check flagged whose retry (fallback_aba,
                               // fallback_double) passed it; not counted in `failed`
  double estimate = 0;         // ResidualTooLarge: first_instance's estimated error of qdd;
                               // LoopNotClosed: its loop violation after the projection
  double threshold = 0;        // ResidualTooLarge, LoopNotClosed: the threshold it exceeded
  const int* failed_dof = nullptr;  // (B) per instance: -1, or the DoF that failed; host memory
                                    // owned by the engine, valid until its next call; null when
                                    // the engine does not keep them (the simulator)

  bool ok() const { return failed == 0; }
  // Records instance b failing at dof (keeps the lowest instance as the first).
  void record(Index b, Index dof, Failure what) {
    ++failed;
    if (first_instance < 0 || b < first_instance) {
      first_instance = b;
      first_dof = dof;
      failure = what;
    }
  }
  // Adds another status's counts (e.g. the next step's); keeps the lowest instance.
  void merge(const BatchStatus& other);
  // "" when ok(); else what failed in the first instance, e.g.
  //   "articulated inertia pivot at DoF 6 is not positive"
  //   "mass matrix pivot at DoF 6 is not positive"
  //   "mass matrix pivot not positive, and by the aba fallback the articulated inertia pivot at DoF 6 is not positive"
  //   "the state at DoF 6 is not finite after the step"
  //   "forward dynamics check: estimated error of qdd 2.1e-01 above the threshold 1e-04 (largest at DoF 6)"
  //   "the variational step's Newton iteration did not converge (largest correction at DoF 6)"
  //   "the projection onto the closed loops left loop 4 violated by 2.3e-03 (max |phi| m, |J qd| m/s;
  //    tolerance 1e-06)"
  std::string reason() const;
  // "" when ok(); else "instance 3: " + reason(), followed by
  // " (and 41 more instances)" when others failed too.
  std::string message() const;
};

// The status of a batch from its per-instance failed DoFs (B entries in host memory,
// failed_dof[b] >= 0: instance b failed at that DoF), each failure of kind `what`;
// the status keeps failed_dof as its per-instance array.
BatchStatus summarize_failures(const int* failed_dof, Index B, Failure what, Index fell_back = 0);

// The status of a batch of derivative steps (the CUDA step Jacobian and rollouts):
// failed_dof[b] = -1 (ok), >= 0 (the ABA's pivot failed at that DoF:
// Failure::ArticulatedPivot) or -2 - i (row i of a result is not finite:
// Failure::NonFinite); the codes -2 - i are rewritten to i in place, so that the
// status's per-instance array names the row.
BatchStatus summarize_step_failures(int* failed_dof, Index B);

// The same with forward dynamics' run-time check: an instance b that failed with
// estimate[b] not at most threshold (above it, or NaN) failed the check
// (Failure::ResidualTooLarge), any other failed one failed a pivot (`pivot`).
BatchStatus summarize_checked(const int* failed_dof, const double* estimate, Index B, Failure pivot,
                              double threshold, Index fell_back, Index retried);

// The pivot a method's failure names: jsi's mass matrix, every other method's articulated inertia.
inline Failure pivot_failure(FdMethod method) {
  return method == FdMethod::Jsi ? Failure::MassMatrixPivot : Failure::ArticulatedPivot;
}

}  // namespace scandyn
