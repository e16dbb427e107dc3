// scandyn/cuda/constrained_dynamics.hpp: forward dynamics of trees closed by loops on a
// CUDA device, one thread per instance (strategy "dense_thread"), for small loop
// systems: models of up to kLoopMaxDofs DoF with up to kLoopMaxRows constraint rows
// (a five-bar: 4 DoF, 3 rows; a four-bar: 3 DoF, 3 rows). Per thread: M by
// crba_instance, h by rnea_instance (qdd = 0), the loops' rows and the dense
// rank-revealing solve of scandyn/algorithm/loop_solver.hpp (the routines the CPU
// engines run), all in thread-local storage sized at compile time (capacities 8 / 16
// DoF, 6 / 12 rows). The engine (make_constrained_forward_dynamics with
// BackendKind::Cuda):
//   compute(), residual()   HOST views: copies in, launches, copies out, synchronises;
//   compute_async(), residual_async()   DEVICE views and your stream: one launch.
// A larger system is refused (BackendError: use the serial or openmp backend).
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "scandyn/algorithm/loop_solver.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/instance/thread_model.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

namespace scandyn {
namespace cuda {

namespace detail {
class StagingBuffer;  // kernels/staging.hpp
}

inline constexpr Index kLoopMaxDofs = 16;  // DoF of the largest model the thread kernel takes
inline constexpr Index kLoopMaxRows = 12;  // constraint rows of the largest loop set

template <class S>
class CudaConstrainedForwardDynamics final : public ConstrainedForwardDynamics<S> {
 public:
  // Copies the loops to the device and prepares compute()'s staging buffers. Throws
  // BackendError without a usable device, for a model beyond kLoopMaxDofs DoF or loops
  // beyond kLoopMaxRows rows, or when the buffers do not fit.
  CudaConstrainedForwardDynamics(const ModelTpl<S>& model, const LoopSet& loops, const BackendOptions& options);
  ~CudaConstrainedForwardDynamics() override;
  CudaConstrainedForwardDynamics(const CudaConstrainedForwardDynamics&) = delete;
  CudaConstrainedForwardDynamics& operator=(const CudaConstrainedForwardDynamics&) = delete;

  BatchStatus compute(const FdBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& lambda) override;
  void residual(const BatchView<const S>& q, const BatchView<const S>& qd, const BatchView<S>& phi,
                const BatchView<S>& velocity) override;
  // DEVICE views on `stream` (failed_dof: B ints on the device, -1 or the row of M's
  // Cholesky that failed; that instance's outputs unwritten). Returns
  // cudaErrorInvalidValue for batch sizes that disagree or exceed max_batch, else the
  // launch's error. No copy, no allocation, no synchronisation.
  cudaError_t compute_async(const FdBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& lambda,
                            int* failed_dof, cudaStream_t stream);
  cudaError_t residual_async(const BatchView<const S>& q, const BatchView<const S>& qd, const BatchView<S>& phi,
                             const BatchView<S>& velocity, cudaStream_t stream);

  Index rows() const override { return m_; }
  std::string strategy() const override { return "dense_thread"; }
  BackendKind backend() const override { return BackendKind::Cuda; }
  int device() const { return device_; }

 private:
  int device_ = 0;
  Index nv_ = 0, m_ = 0, nloops_ = 0, max_batch_ = 0;
  std::unique_ptr<ThreadModel<S>> thread_;
  LoopRow<S>* loops_ = nullptr;  // (loops) device copy
  std::unique_ptr<detail::StagingBuffer> staging_;
  std::vector<int> failed_host_;  // (max_batch)
};

template <class S>
std::unique_ptr<ConstrainedForwardDynamics<S>> make_constrained_forward_dynamics(const ModelTpl<S>& model,
                                                                                 const LoopSet& loops,
                                                                                 const BackendOptions& options);

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
