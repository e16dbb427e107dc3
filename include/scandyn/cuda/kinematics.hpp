// scandyn/cuda/kinematics.hpp: frame poses and frame Jacobians of a batch on a CUDA
// device, one thread per instance.
//
// Layers, as for the dynamics engines:
//   kinematics_instance()       SCANDYN_HD (scandyn/instance/kinematics_instance.hpp):
//                               one instance, the same routine the CPU engines run;
//   kinematics_instances_kernel one thread per instance, the bodies in the kernel
//                               parameter (ThreadModelParams), the selected frames in
//                               device memory, the body placements in per-thread memory
//                               (kernels/kinematics.cu);
//   launch_kinematics_instances host wrapper: device pointers, a stream, returns the
//                               cudaError_t of the launch, never synchronises.
// and the engine CudaKinematics on top:
//     compute()        HOST pointers: copies q in, launches, copies poses and J out,
//                      synchronises;
//     compute_async()  DEVICE pointers and your stream: one launch, no copy, no
//                      synchronisation, no allocation; returns the cudaError_t.
//
// Models of 1-DoF joints of up to kMaxThreadDofs DoF (strategy "thread"); models
// with multi-DoF joints (a floating base, spherical joints) of any size run the
// general path, kinematics_instance_at per thread over GeneralPlan (strategy
// "general", scandyn/cuda/general_dynamics.hpp). Accuracy: the CPU engines'
// formulas in the same order; on the device FMA contraction and sin/cos as the other
// thread-per-instance kernels (kThreadTrig: the library's in double, the SFU's in
// float) make the difference.
#pragma once

#include <cstddef>
#include <memory>
#include <string>

#include "scandyn/build_config.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/cuda/general_dynamics.hpp"
#include "scandyn/instance/thread_model.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

namespace scandyn {
namespace cuda {

namespace detail {
class StagingBuffer;
}  // namespace detail

// Threads per block of kinematics_instances_kernel.
inline constexpr int kKinematicsInstancesBlock = 128;

// poses / J (entries per instance as Kinematics::compute; either's data may be
// null: not computed) for the q.batch instances, with `frames` (F placements in
// DEVICE memory): one launch on `stream`. Every pointer is a DEVICE pointer;
// nothing is copied, allocated or synchronised. cudaErrorInvalidValue when batch
// sizes disagree or a pointer is null with B > 0.
template <class S>
cudaError_t launch_kinematics_instances(const ThreadModel<S>& model, const FramePlacement<S>* frames, Index F,
                                        PoseFormat format, FrameReference reference, const BatchView<const S>& q,
                                        const BatchView<S>& poses, const BatchView<S>& J, cudaStream_t stream);

// The batched kinematics engine on one CUDA device (the device current at construction).
template <class S>
class CudaKinematics final : public Kinematics<S> {
 public:
  // Prepares the model and the frames (device memory) and the staging buffer for
  // options.max_batch instances: q, poses and J, (nq + F (16 + 6 nv)) * sizeof(S)
  // bytes per instance. Throws BackendError for a 1-DoF model beyond kMaxThreadDofs DoF, for a frame
  // index outside model.frames, without a usable device, or when the buffers do not
  // fit in device memory.
  CudaKinematics(const ModelTpl<S>& model, const BackendOptions& options, const KinematicsOptions& kinematics);
  ~CudaKinematics() override;
  CudaKinematics(const CudaKinematics&) = delete;
  CudaKinematics& operator=(const CudaKinematics&) = delete;

  // HOST pointers, any strides (Kinematics::compute).
  void compute(const BatchView<const S>& q, const BatchView<S>& poses, const BatchView<S>& J) override;
  // DEVICE pointers, any strides, on `stream`; not limited by max_batch.
  cudaError_t compute_async(const BatchView<const S>& q, const BatchView<S>& poses, const BatchView<S>& J,
                            cudaStream_t stream);

  const KinematicsOptions& options() const override { return options_; }
  std::string strategy() const override { return general_ ? "general" : "thread"; }
  BackendKind backend() const override { return BackendKind::Cuda; }
  Index max_batch() const { return max_batch_; }
  // The CUDA device the engine was made on (its frames and buffers live there).
  int device() const;

 private:
  Index nv_ = 0;
  Index nq_ = 0;  // entries of q (nv + 1 per quaternion joint)
  Index max_batch_ = 0;
  KinematicsOptions options_;
  std::unique_ptr<ThreadModel<S>> thread_;   // 1-DoF models
  std::unique_ptr<GeneralPlan<S>> general_;  // models with multi-DoF joints
  FramePlacement<S>* frames_ = nullptr;  // (F) the selected frames, device memory
  // compute()'s stream and its one allocation: q (nq x max_batch), poses, then J
  std::unique_ptr<detail::StagingBuffer> staging_;
};

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
