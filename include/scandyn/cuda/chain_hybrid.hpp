// scandyn/cuda/chain_hybrid.hpp: hybrid dynamics (Featherstone 2008, 9.2: some DoFs'
// accelerations given, the others' forces) of long unbranched chains (hanging from the
// base) on a CUDA device, by the chunked scans of the parallel chain forward dynamics.
//
// The device twin of ChainHybridDynamics (scandyn/algorithm/chain_hybrid.hpp): the same
// walks (hybrid_velocity_walk, hybrid_inertia_carry + hybrid_inertia_walk,
// hybrid_bias_walk, hybrid_acceleration_walk; SCANDYN_HD, called by the host driver
// too) and the same scan elements (Affine6 for passes 0, 2, 3; HybridDual, the dual
// Riccati map of a free link with the run of prescribed links after it as one rigid
// body, for pass 1; RigidComposite, the runs' composite rigid bodies, scanned backward
// beside pass 0 unless set_scan_runs(false)), one thread per chunk of `chunk` links,
// chunk aggregates scanned in levels of fan_in by the launch plumbing of the chain
// forward dynamics (kernels/chain_scan.cuh). Kernels per call: the velocity (and run)
// aggregates, then per pass (four, five with the run scan) the level folds, one thread
// for the top level, the level carries and the pass's walk: 1 + 4 (2 L) with L levels
// (L = 4 for rope:10^5, chunk = fan_in = 8), 2 L more with the run scan.
//
// Two layers:
//   ChainHybridPlan::launch()       DEVICE pointers and a stream: no allocation, no
//                                   synchronisation;
//   make_cuda_chain_hybrid_dynamics the engine API's HybridDynamics (strategy
//                                   "parallel"; make_hybrid_dynamics with
//                                   BackendKind::Cuda picks it for unbranched chains
//                                   beyond kMaxThreadDofs DoF, or fd_method Parallel):
//                                   host views copied in, launched on the engine's
//                                   stream, copied out (compute waits); its
//                                   compute_async takes device views.
#pragma once

#include <memory>
#include <vector>

#include "scandyn/algorithm/chain_hybrid.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/cuda/hybrid_dynamics.hpp"
#include "scandyn/engine.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

namespace scandyn {
namespace cuda {

template <class S>
class ChainHybridPlan {
 public:
  static constexpr Index kDefaultChunk = 8;  // links per thread at level 0
  static constexpr Index kDefaultFanIn = 8;  // aggregates per thread at the levels above

  // Copies the model's distinct bodies to the device and allocates the scratch for
  // max_batch instances (per link: v, U, w, D, u; per level: Affine6, HybridDual and
  // RigidComposite aggregates and carries). chunk: links per thread (0: kDefaultChunk); fan_in:
  // aggregates per thread above (0: kDefaultFanIn). Throws BackendError for a model
  // with a multi-DoF joint (a floating base, a spherical joint), a model that is not
  // unbranched chains from the base (naming the body), a batch whose links do not fit
  // in 2^30, device memory that does not suffice, or a CUDA error.
  ChainHybridPlan(const ModelTpl<S>& model, Index max_batch, Index chunk = 0, Index fan_in = 0);
  ~ChainHybridPlan();
  ChainHybridPlan(const ChainHybridPlan&) = delete;
  ChainHybridPlan& operator=(const ChainHybridPlan&) = delete;

  // qdd and tau (nv x B, full vectors: the given entries copied through) of the B =
  // in.q.batch <= max_batch instances, gravity included; prescribed: nv DEVICE bytes
  // (nonzero: that DoF's acceleration in.qdd is given, else its force in.tau), read by
  // the kernels (it may change between calls). Every pointer is a DEVICE pointer, any
  // strides; on `stream`, no synchronisation. failed: B device ints, -1 or the first
  // DoF whose articulated pivot (of a free DoF) was not positive and finite (that
  // instance's qdd and tau unwritten). Returns cudaErrorInvalidValue for B > max_batch,
  // views whose batch differs from q's, or a null pointer with B > 0, else the first
  // launch error.
  cudaError_t launch(const HybridBatchIn<S>& in, const unsigned char* prescribed, const BatchView<S>& qdd,
                     const BatchView<S>& tau, int* failed, cudaStream_t stream);

  // Whether launch() scans the prescribed runs' composites (true, the default: O(n)
  // work and one walk per chunk of bounded length for any mask) or each chunk's thread
  // walks the run at its boundary to its end (false: no extra scan, for masks whose
  // runs are short; O(run^2 / chunk) on long ones). The engine sets it from its mask
  // (hybrid_scans_runs).
  void set_scan_runs(bool scan) { scan_runs_ = scan; }
  bool scans_runs() const { return scan_runs_; }

  Index links() const { return n_; }  // DoF (bodies) per instance
  Index max_batch() const { return max_batch_; }
  Index chunk() const { return chunk_; }
  Index fan_in() const { return fan_in_; }
  std::size_t device_bytes() const { return bytes_; }

 private:
  Index n_ = 0, max_batch_ = 0, chunk_ = 0, fan_in_ = 0;
  Motion<S> a0_;
  std::size_t bytes_ = 0;
  void* memory_ = nullptr;  // one device allocation for everything below
  bool scan_runs_ = true;   // launch() scans the runs' composites (else each chunk walks its boundary's run)
  ChainScratch<S> chain_;   // the chain's tables and (n max_batch) per-link scratch
  std::vector<Affine6<S>*> aff_;  // per level
  std::vector<Vec6<S>*> aff_carry_;
  std::vector<HybridDual<DualScalar>*> dual_;
  std::vector<Mat5<DualScalar>*> dual_carry_;
  std::vector<HybridRun<S>*> run_;        // the runs' composites: aggregates (scanned only)
  std::vector<HybridRun<S>*> run_carry_;  // and carries; level 0: S_{e+1} per chunk (always)
};

// The engine API's hybrid dynamics of unbranched chains on cuda (strategy "parallel"):
// a ChainHybridPlan with the prescribed mask on the device and staging for host views.
// compute(): HOST views, any strides (copied in, launched on the engine's stream, copied
// out; waits); outputs of failed instances untouched. Throws BackendError as the plan,
// for a mask of another size, without a usable device, and for a CUDA error.
template <class S>
class CudaChainHybridDynamics final : public CudaHybridEngine<S> {
 public:
  CudaChainHybridDynamics(const ModelTpl<S>& model, const std::vector<unsigned char>& prescribed,
                          const BackendOptions& options);
  ~CudaChainHybridDynamics() override;
  CudaChainHybridDynamics(const CudaChainHybridDynamics&) = delete;
  CudaChainHybridDynamics& operator=(const CudaChainHybridDynamics&) = delete;

  BatchStatus compute(const HybridBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& tau) override;
  // DEVICE views on `stream` (failed_dof: B device ints): the plan's launch with the
  // engine's mask.
  cudaError_t compute_async(const HybridBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& tau,
                            int* failed_dof, cudaStream_t stream) override {
    return plan_->launch(in, mask_, qdd, tau, failed_dof, stream);
  }

  const std::vector<unsigned char>& prescribed() const override { return prescribed_; }
  std::string strategy() const override { return "parallel"; }
  const ChainHybridPlan<S>& plan() const { return *plan_; }
  int device() const override { return device_; }

 private:
  int device_ = 0;
  Index n_ = 0, max_batch_ = 0;
  std::vector<unsigned char> prescribed_;
  std::unique_ptr<ChainHybridPlan<S>> plan_;
  cudaStream_t stream_ = nullptr;
  void* buffer_ = nullptr;  // device: q, qd, qdd in, tau in, qdd out, tau out (n x max_batch
                            // each, SoA), fext (n max_batch), failed (max_batch), the mask (n)
  S* array_[6] = {};
  Force<S>* fext_ = nullptr;
  int* failed_ = nullptr;
  unsigned char* mask_ = nullptr;
  std::vector<S> host_;           // host staging of the six arrays
  std::vector<int> failed_host_;  // (max_batch)
};

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
