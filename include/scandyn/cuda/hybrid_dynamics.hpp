// scandyn/cuda/hybrid_dynamics.hpp: batched hybrid dynamics (Featherstone 2008, 9.2) on
// a CUDA device, one thread per instance (strategy "aba_thread"), for models of up to
// kMaxThreadDofs DoF.
//
// The layers of the forward dynamics (scandyn/cuda/forward_dynamics.hpp):
//   hybrid_instance()          __host__ __device__ (scandyn/instance/hybrid_instance.hpp):
//                              aba_instance's passes with the prescribed joints' steps;
//   hybrid_instances_kernel    one thread per instance (kernels/hybrid_dynamics.cu),
//                              the ABA kernel variant choose_aba_kernel picks;
//   launch_hybrid_instances()  host wrapper: device pointers, a stream, returns the
//                              cudaError_t of the launch, never synchronises;
// and the engine CudaHybridDynamics (make_hybrid_dynamics with BackendKind::Cuda):
//   compute()        HOST pointers: copies in, launches, copies out, synchronises;
//   compute_async()  DEVICE pointers and your stream: one launch, nothing else.
// The prescribed set is a 64-bit mask, a kernel argument. An instance whose
// articulated pivot (of a DoF whose force is given) is not positive and finite has
// its failed DoF reported and its outputs left unwritten.
//
// Not here: models beyond kMaxThreadDofs DoF (BackendError): make_hybrid_dynamics
// takes the parallel chain hybrid dynamics (scandyn/cuda/chain_hybrid.hpp) for
// unbranched chains from the base and refuses other shapes (choose_hybrid_method).
#pragma once

#include <memory>
#include <string>
#include <vector>

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

// The 64-bit mask of a prescribed vector (bit i: prescribed[i] != 0); nv <= 64.
unsigned long long prescribed_bits(const std::vector<unsigned char>& prescribed);

// qdd_out and tau_out (nv x B) = hybrid dynamics of the B = batch_in.q.batch
// instances with the DoFs of `prescribed` (bit i: DoF i) given their acceleration:
// one launch on `stream`. Writes failed_dof_out[b] for every b < B (-1, or the DoF
// whose articulated pivot failed; that instance's outputs unwritten). DEVICE pointers,
// any strides; nothing copied, allocated or synchronised. Returns
// cudaErrorInvalidValue for batch sizes that disagree or a null pointer with B > 0,
// else the launch's error.
template <class S>
cudaError_t launch_hybrid_instances(const ThreadModel<S>& model, unsigned long long prescribed,
                                    const HybridBatchIn<S>& batch_in, const BatchView<S>& qdd_out,
                                    const BatchView<S>& tau_out, int* failed_dof_out, cudaStream_t stream);

// What every CUDA hybrid-dynamics engine offers beside HybridDynamics: the launch on
// DEVICE views and the caller's stream, and its device. Implemented by
// CudaHybridDynamics (one thread per instance, below) and CudaChainHybridDynamics
// (the parallel chain hybrid, scandyn/cuda/chain_hybrid.hpp), so that a caller holding
// device arrays (the Python package) reaches whichever make_hybrid_dynamics chose.
template <class S>
class CudaHybridEngine : public HybridDynamics<S> {
 public:
  // qdd and tau (nv x B) of the B = in.q.batch instances on `stream`; failed_dof: B
  // device ints (-1, or the DoF whose articulated pivot failed; that instance's outputs
  // unwritten). Nothing copied or synchronised.
  virtual cudaError_t compute_async(const HybridBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& tau,
                                    int* failed_dof, cudaStream_t stream) = 0;
  virtual int device() const = 0;  // the CUDA device the engine was made on
  BackendKind backend() const override { return BackendKind::Cuda; }
};

template <class S>
class CudaHybridDynamics final : public CudaHybridEngine<S> {
 public:
  // Prepares the model and the staging buffers of compute(): q, qd, qdd, tau in, qdd
  // and tau out, fext and a failed DoF per instance, (12 nv sizeof(S) + sizeof(int))
  // max_batch bytes. Throws BackendError without a usable device, for models beyond
  // kMaxThreadDofs DoF, or when the buffers do not fit.
  CudaHybridDynamics(const ModelTpl<S>& model, const std::vector<unsigned char>& prescribed,
                     const BackendOptions& options);
  ~CudaHybridDynamics() override;
  CudaHybridDynamics(const CudaHybridDynamics&) = delete;
  CudaHybridDynamics& operator=(const CudaHybridDynamics&) = delete;

  // HOST pointers, any strides (outputs' entries must not overlap). Writes only the
  // outputs' entries, not those of failed instances. Throws BackendError for B >
  // max_batch, sizes that disagree, or a CUDA error.
  BatchStatus compute(const HybridBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& tau) override;
  // DEVICE pointers on `stream` (failed_dof: B ints on the device): launch_hybrid_instances.
  cudaError_t compute_async(const HybridBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& tau,
                            int* failed_dof, cudaStream_t stream) override;

  const std::vector<unsigned char>& prescribed() const override { return prescribed_; }
  std::string strategy() const override { return "aba_thread"; }
  const ThreadModel<S>& thread_model() const { return *thread_; }
  int device() const override { return device_; }

 private:
  int device_ = 0;
  Index nv_ = 0;
  Index max_batch_ = 0;
  std::vector<unsigned char> prescribed_;  // (nv)
  unsigned long long bits_ = 0;            // prescribed_ as a mask
  std::unique_ptr<ThreadModel<S>> thread_;
  std::unique_ptr<detail::StagingBuffer> staging_;
  std::vector<int> failed_host_;  // (max_batch)
  std::vector<S> kept_;           // outputs of failed instances, restored after the copy back
};

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
