// scandyn/cuda/second_derivatives.hpp: the second-order derivatives of inverse
// dynamics of a batch on a CUDA device, one thread per instance (models of 1-DoF
// joints, up to kMaxThreadDofs DoF).
//
// Layers, as for the other CUDA engines:
//   rnea_second_derivatives_analytic_instance()
//                               __host__ __device__ (scandyn/instance/
//                               second_derivatives_analytic.hpp): one instance, the
//                               serial function's analytical second-order recursion
//                               (Singh, Russell & Wensing, RA-L 2022);
//   id_second_derivatives_kernel
//                               one thread per instance (kernels/second_derivatives.cu);
//   launch_id_second_derivatives()
//                               host wrapper: device pointers, a stream, the launch's
//                               cudaError_t, never synchronises;
// and the engine CudaIdSecondDerivatives on top: compute() on HOST views (copies in,
// launches, copies out, synchronises), compute_async() on DEVICE views and a stream.
// Output layout: scandyn/engine.hpp (IdSecondDerivativesOut: nv^3 entries per
// instance and tensor; soa, the instance innermost, is the fast layout on the device).
//
// Memory: the model is the kernel's parameter (SecondOrderModelParams: made once on
// the host, read from the constant bank by every thread). Per thread, in local
// memory: C DerivativeBody<S> (72 scalars each), C the capacity (8, 16, 32 or 64, the
// smallest >= nv): 72 C scalars, e.g. 4.6 KB in double for iiwa and 9.2 KB for hyq
// (C = 8, 16), 36.9 KB at C = 64 (the dual-number passes this kernel ran before took
// 156 C scalars, 80 KB at C = 64).
#pragma once

#include <memory>
#include <string>
#include <variant>

#include "scandyn/build_config.hpp"
#include "scandyn/engine.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

#include "scandyn/instance/second_derivatives_analytic.hpp"

namespace scandyn {
namespace cuda {

namespace detail {
class StagingBuffer;  // kernels/staging.hpp
}  // namespace detail

// Threads per block of the second-derivative kernel.
inline constexpr int kSecondDerivativesBlock = 64;

// The model as id_second_derivatives_kernel reads it, for capacity C (nv <= C): the
// kernel parameter (__grid_constant__: it stays in the constant bank).
template <class S, int C>
struct SecondOrderModelParams {
  static constexpr int capacity = C;
  Body<S> body[C];        // (nv) the bodies in DoF order; entries past nv unused
  Motion<S> a0;           // base acceleration: gravity entered as -g (world frame)
  Index nv;               // number of bodies in body[] (their DoF), <= C
};

// One model prepared for the kernel: the parameter block of the smallest capacity
// that holds it. Host memory only; built once, then copied into each launch.
template <class S>
class SecondOrderThreadModel {
 public:
  using Params = std::variant<SecondOrderModelParams<S, 8>, SecondOrderModelParams<S, 16>, SecondOrderModelParams<S, 32>,
                              SecondOrderModelParams<S, 64>>;
  // Throws BackendError for a model of more than kMaxThreadDofs DoF or with a
  // multi-DoF joint.
  explicit SecondOrderThreadModel(const ModelTpl<S>& model);
  Index nv() const { return nv_; }
  Index capacity() const { return capacity_; }  // 8, 16, 32 or 64
  const Params& params() const { return params_; }

 private:
  Index nv_ = 0;
  Index capacity_ = 0;
  Params params_;
};

// out = the second derivatives of the B = in.q.batch instances; DEVICE pointers, any
// strides (out.dM_dq.data null: not written). cudaErrorInvalidValue for batch sizes
// that disagree or a null pointer with B > 0; else the launch's error.
template <class S>
cudaError_t launch_id_second_derivatives(const SecondOrderThreadModel<S>& model, const IdBatchIn<S>& in,
                                         const IdSecondDerivativesOut<S>& out, cudaStream_t stream);

template <class S>
class CudaIdSecondDerivatives final : public IdSecondDerivatives<S> {
 public:
  // Throws BackendError for a model beyond kMaxThreadDofs, no usable device, or
  // staging buffers (q, qd, qdd, fext and four nv^3 tensors per instance, for
  // max_batch instances) that do not fit.
  CudaIdSecondDerivatives(const ModelTpl<S>& model, const BackendOptions& options);
  ~CudaIdSecondDerivatives() override;
  void compute(const IdBatchIn<S>& in, const IdSecondDerivativesOut<S>& out) override;
  cudaError_t compute_async(const IdBatchIn<S>& in, const IdSecondDerivativesOut<S>& out, cudaStream_t stream);
  std::string strategy() const override { return "thread"; }
  BackendKind backend() const override { return BackendKind::Cuda; }

 private:
  Index nv_ = 0, max_batch_ = 0;
  std::unique_ptr<SecondOrderThreadModel<S>> model_;
  std::unique_ptr<detail::StagingBuffer> staging_;
};

// The factory's CUDA branch (scandyn/engine.hpp: make_id_second_derivatives).
template <class S>
std::unique_ptr<IdSecondDerivatives<S>> make_cuda_id_second_derivatives(const ModelTpl<S>& model,
                                                                        const BackendOptions& options);

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
