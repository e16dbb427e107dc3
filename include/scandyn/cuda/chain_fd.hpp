// scandyn/cuda/chain_fd.hpp: forward dynamics of long unbranched chains (hanging from the base) on a CUDA
// device, by the chunked scans of scandyn/algorithm/chain_fd.hpp.
//
// Two variants share the kernels:
//   parallel  every pass on the device: the articulated-inertia recursion as a scan
//             of constraint-space Riccati maps (DualRiccati), O(log n) span;
//   hybrid    the seed's split: the articulated inertias at the chunk boundaries
//             are computed on the host (ChainInertiaCarries, scandyn/algorithm/
//             chain_fd.hpp: the serial recursion on one thread; on T threads, ranges
//             of the chain walked by it from carries that pass 1's dual aggregates
//             supply), in groups of chunks; each group's boundary inertias go to the
//             device through pinned memory as soon as they are known and that
//             group's pass-1 walks start while the host works on the others. The
//             other passes (velocities, the z and acceleration scans) run on the
//             device.
//
// Kernels (one thread per chunk of `chunk` links, chunk aggregates scanned in levels
// of kFanIn): velocity aggregate, then per pass the level folds, one thread for the
// top level, the level carries, and the pass's walk. Every pointer given to launch()
// is a DEVICE pointer; the plan owns its scratch (per link: v, U, w, D, u; per
// level: aggregates and carries), allocates nothing per call and does not
// synchronise (launch_hybrid waits for the host recursion only).
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "scandyn/algorithm/chain_directional.hpp"
#include "scandyn/algorithm/chain_fd.hpp"
#include "scandyn/build_config.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

namespace scandyn {
namespace cuda {

// One busy interval of the hybrid's timeline, in milliseconds: host intervals from
// the start of the call (host clock), device intervals from the call's first event
// on the stream (CUDA events recorded right before and after the work).
struct ChainTimelineEvent {
  std::string what;  // host: "cpu walk" (the recursion over chunks [c_lo, c_hi)), "cpu reduce"
                     // (their dual aggregate), "cpu combine"; device: "gpu velocities",
                     // "gpu walk" (pass 1's walks of chunks [c_lo, c_hi), one kernel),
                     // "gpu finish" (passes 2 and 3)
  double start_ms = 0, end_ms = 0;
  int thread = -1;           // the host thread (OpenMP number) of a cpu interval; -1: the device
  Index c_lo = 0, c_hi = 0;  // the chunks (walks, reductions)
};

template <class S>
class ChainFdPlan {
 public:
  static constexpr Index kDefaultChunk = 8;  // links per thread at level 0
  static constexpr Index kDefaultFanIn = 8;  // aggregates per thread at the levels above

  // Copies the model's distinct bodies to the device and allocates the scratch for
  // max_batch instances. chunk: links per thread (0: kDefaultChunk); fan_in:
  // aggregates per thread above (0: kDefaultFanIn). Throws BackendError for a
  // model that is not unbranched chains from the base (naming the body), a batch whose links do
  // not fit in 2^30, device memory that does not suffice, or a CUDA error.
  // directional: also the scratch of launch_jvp / launch_vjp (per link: a, F, dv, df,
  // x, IA); a floating base is then a BackendError.
  ChainFdPlan(const ModelTpl<S>& model, Index max_batch, Index chunk = 0, Index fan_in = 0, bool directional = false);
  ~ChainFdPlan();
  ChainFdPlan(const ChainFdPlan&) = delete;
  ChainFdPlan& operator=(const ChainFdPlan&) = delete;

  // parallel: qdd (nv x B) = FD(q, qd, tau, fext) for B = in.q.batch <= max_batch
  // (device views, any strides), on `stream`, no synchronisation. failed: B device
  // ints, -1 or the first DoF whose articulated pivot failed (qdd of that instance
  // unwritten). Returns cudaErrorInvalidValue for B > max_batch, else the first
  // launch error.
  cudaError_t launch(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed, cudaStream_t stream);

  // A free rope (a floating base, then 1-DoF links): q has nq = n + 6 rows, qd, tau
  // and qdd nv = n + 5; the base's 6x6 articulated inertia is solved on the device
  // (scandyn/algorithm/chain_fd.hpp). Spherical joints: BackendError naming the joint.

  // hybrid: the same result, with the articulated inertias computed on the host
  // from q_host (the same positions as in.q, in host memory) on host_threads()
  // threads. Returns after the host's work and the queuing of every kernel (not
  // after the kernels). When timeline is not null it receives the host's and the
  // device's busy intervals of the call (events before and after each group's
  // walks), and the call then waits for the device at the end. A free rope:
  // cudaErrorNotSupported.
  cudaError_t launch_hybrid(const BatchView<const S>& q_host, const FdBatchIn<S>& in, const BatchView<S>& qdd,
                            int* failed, cudaStream_t stream, std::vector<ChainTimelineEvent>* timeline = nullptr);

  // The JVP and VJP of forward dynamics (scandyn/algorithm/chain_directional.hpp:
  // the FD's passes 0-3, then 5 (JVP) or 6 (VJP) Affine6 scans; pass 1 is not rerun
  // for M^-1). A plan constructed with directional = true, fixed base; device views
  // (n x B, any strides), `stream`, no synchronisation; failed as launch(), every
  // output of a failed instance unwritten. Returns cudaErrorInvalidValue for
  // B > max_batch or a batch mismatch, cudaErrorNotSupported without the
  // directional scratch, else the first launch error.
  // Kernels beyond launch(): JVP 5 walks and 5 scans, VJP 4 walks and 3 scans.
  //   launch_jvp: qdd = FD(in), dqdd = (dqdd/dq) dq + (dqdd/dqd) dqd + M^-1 dtau
  //   launch_vjp: qdd = FD(in), gq = (dqdd/dq)^T w, gqd = (dqdd/dqd)^T w, gtau = M^-1 w
  cudaError_t launch_jvp(const FdBatchIn<S>& in, const BatchView<const S>& dq, const BatchView<const S>& dqd,
                         const BatchView<const S>& dtau, const BatchView<S>& qdd, const BatchView<S>& dqdd, int* failed,
                         cudaStream_t stream);
  cudaError_t launch_vjp(const FdBatchIn<S>& in, const BatchView<const S>& w, const BatchView<S>& qdd,
                         const BatchView<S>& gq, const BatchView<S>& gqd, const BatchView<S>& gtau, int* failed,
                         cudaStream_t stream);
  bool directional() const { return F_ != nullptr; }

  // the hybrid's host threads (0: openmp_threads(), the default)
  void set_host_threads(int threads);
  int host_threads() const;

  Index links() const { return n_; }  // bodies per instance (nv, or nv - 5 for a free rope)
  Index max_batch() const { return max_batch_; }
  Index chunk() const { return chunk_; }
  Index fan_in() const { return fan_in_; }
  std::size_t device_bytes() const { return bytes_; }

 private:
  // kB: a free rope's walks (ChainFdData's kBase)
  template <bool kB>
  ChainFdData<S, kB> data(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed) const;
  template <bool kB>
  cudaError_t passes(const ChainFdData<S, kB>& d, cudaStream_t stream);  // launch()'s passes 0 to 3
  template <bool kB>
  cudaError_t velocities(const ChainFdData<S, kB>& d, bool dual, cudaStream_t stream);
  template <bool kB>
  cudaError_t finish(const ChainFdData<S, kB>& d, cudaStream_t stream);  // passes 2 and 3
  ChainDirectionalData<S> directional_data(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed) const;

  Index n_ = 0, max_batch_ = 0, chunk_ = 0, fan_in_ = 0;  // n_: links (bodies) per instance
  bool floating_ = false;                   // link 0 is a floating base (a free rope)
  Motion<S> a0_;
  ChainBodies<S> host_;                     // the chain's constants (hybrid's host recursion)
  std::size_t bytes_ = 0;
  void* memory_ = nullptr;                  // one device allocation for everything below
  ChainScratch<S> chain_;                   // the chain's tables and (n max_batch) per-link scratch
  // directional scratch (null unless constructed with directional): (n max_batch) each
  Motion<S>* a_ = nullptr;                  // body accelerations (pass 3)
  Force<S>* F_ = nullptr;                   // subtree forces
  Motion<S>* dv_ = nullptr;                 // JVP dv / VJP Fbar
  Force<S>* df_ = nullptr;                  // JVP df / VJP RA
  S* x_ = nullptr;                          // JVP dtau - r / VJP u, gq's first term
  ABInertia<S>* IA_ = nullptr;              // VJP: pass 1's articulated inertias IA
  std::vector<Index> level_size_;           // for max_batch; a call uses its own sizes
  std::vector<Affine6<S>*> aff_;            // per level
  std::vector<Vec6<S>*> aff_carry_;
  std::vector<DualRiccati<DualScalar>*> dual_;
  std::vector<Mat5<DualScalar>*> dual_carry_;
  ABInertia<S>* IA_base_ = nullptr;         // (max_batch) a floating base's IA_0 (pass 1), or null
  Motion<S>* a_base_ = nullptr;             // (max_batch) its acceleration (pass 2)
  Vec6<S>* qdd_base_ = nullptr;             // (max_batch) its qdd (pass 2)
  ABInertia<S>* Ia_carry_ = nullptr;        // (chunks) hybrid: Ia of each chunk's link e + 1
  ABInertia<S>* Ia_pinned_ = nullptr;       // (chunks) host pinned staging of the same
  std::unique_ptr<ChainInertiaCarries<S>> carries_;  // the hybrid's host part and its threads
  std::vector<cudaEvent_t> events_;         // hybrid timeline: 4, then 2 per walk group
};

// The engine API's directional derivatives of forward dynamics on cuda
// (make_fd_directional_derivatives, scandyn/engine.hpp): a directional ChainFdPlan
// behind host views (copied in, launched on the engine's stream, copied out; the
// call waits for them). Unbranched chains from a fixed base only (BackendError
// otherwise, naming the body); strategy "parallel".
template <class S>
std::unique_ptr<FdDirectionalDerivatives<S>> make_cuda_fd_directional_derivatives(const ModelTpl<S>& model,
                                                                                  const BackendOptions& options);

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
