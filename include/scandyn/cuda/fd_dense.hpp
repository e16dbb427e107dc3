// scandyn/cuda/fd_dense.hpp: batched forward dynamics by the joint-space inertia
// for models beyond the thread-per-instance kernels (more than 64 DoF).
//
// qdd = M^{-1} (tau - h) per instance, with
//   h     the bias forces, RNEA(q, qd, 0) - sum J^T fext, by the link scans
//         (IdScanPlan, scandyn/cuda/id_scan.hpp);
//   M     CRBA, one thread block per instance: joint transforms in parallel over
//         bodies, the composite inertias leaves to root (one thread: the serial
//         order of the reference), then one thread per column carrying Ic_i S_i to
//         the root (crba_* steps of scandyn/algorithm/steps.hpp, as crba());
//   solve cuSOLVER's batched dense Cholesky, potrfBatched + potrsBatched.
// The factorisation is dense (n^3 / 3 per instance, against the tree-sparse L^T L
// of the thread kernels and of fd_jsi), so this is for models of tens to a few
// hundred DoF; on chains JSI's conditioning grows quickly with length (float loses
// all digits by about 30 links: docs/benchmarks.md), where ABA is the method.
//
// A leading minor of M that is not positive definite (cuSOLVER's info), or a
// solution that is not finite, is reported per instance in failed_dof: the DoF
// (the minor's order - 1, or the first non-finite entry); that instance's qdd is
// left unwritten. Every pointer given to launch() is a DEVICE pointer; nothing is
// allocated or synchronised per call; one plan serves one stream at a time.
#pragma once

#include <cstddef>
#include <memory>

#include "scandyn/algorithm/steps.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/build_config.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

#include "scandyn/cuda/id_scan.hpp"

namespace scandyn {
namespace cuda {

template <class S>
class DenseJsiPlan {
 public:
  // Copies the model to the device and allocates everything for max_batch
  // instances. Throws BackendError when the memory does not suffice (naming the
  // bytes), when cuSOLVER cannot be initialised, or when scandyn was built without
  // cuSOLVER.
  DenseJsiPlan(const ModelTpl<S>& model, Index max_batch);
  ~DenseJsiPlan();
  DenseJsiPlan(const DenseJsiPlan&) = delete;
  DenseJsiPlan& operator=(const DenseJsiPlan&) = delete;

  // qdd (nv x B) and failed_dof (B ints: -1 or the DoF) for B = in.q.batch <=
  // max_batch instances, on `stream`. Returns cudaErrorInvalidValue for disagreeing
  // batch sizes, B > max_batch or null pointers, else the first launch error.
  cudaError_t launch(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed_dof, cudaStream_t stream);

  Index nv() const { return nv_; }
  Index max_batch() const { return max_batch_; }
  std::size_t device_bytes() const;  // this plan's own memory and its bias plan's

  // Device bytes a plan for this model and batch size would hold.
  static std::size_t bytes_needed(const ModelTpl<S>& model, Index max_batch);

 private:
  struct Impl;
  Index nv_ = 0;
  Index max_batch_ = 0;
  std::unique_ptr<Impl> impl_;
};

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
