// kernels/kinematics.cu: batched frame poses and frame Jacobians, one thread per
// instance (1-DoF models of up to kMaxThreadDofs DoF; models with multi-DoF joints
// through GeneralPlan, kernels/general_dynamics.cu).
//
// The layers of scandyn/cuda/kinematics.hpp: kinematics_instance
// (scandyn/instance/kinematics_instance.hpp, the CPU engines' routine) ->
// kinematics_instances_kernel -> launch_kinematics_instances -> CudaKinematics (host
// staging through kernels/staging.hpp for compute(), the plain launch for
// compute_async()).
#include <cuda_runtime.h>

#include <string>
#include <type_traits>

#include "scandyn/cuda/inverse_dynamics.hpp"
#include "scandyn/cuda/kinematics.hpp"
#include "scandyn/instance/dof_column.hpp"
#include "scandyn/instance/kinematics_instance.hpp"
#include "staging.hpp"

namespace scandyn {
namespace cuda {

using detail::check;
using detail::copy;
using detail::plan;
using detail::Staging;

// ---- kernel and launch ---------------------------------------------------------

// One thread per instance b < B. The body placements (C transforms) live in
// per-thread local memory; sin and cos as the other thread-per-instance kernels
// (kThreadTrig: the SFU in float).
template <class S, int C>
__global__ void __launch_bounds__(kKinematicsInstancesBlock)
    kinematics_instances_kernel(const __grid_constant__ ThreadModelParams<S, C> model,
                                const FramePlacement<S>* __restrict__ frames, Index F, PoseFormat format,
                                FrameReference reference, const BatchView<const S> q, const BatchView<S> poses,
                                const BatchView<S> J) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= q.batch) return;
  Transform<S> X0[C];
  const Strided<S> pb{poses.data ? poses.data + b * poses.batch_stride : nullptr, poses.dof_stride};
  const Strided<S> Jb{J.data ? J.data + b * J.batch_stride : nullptr, J.dof_stride};
  kinematics_instance<kThreadTrig<S>>(model.body, model.nv, frames, F, format, reference, instance_column(q, b), X0,
                                      pb, Jb);
}

template <class S>
cudaError_t launch_kinematics_instances(const ThreadModel<S>& model, const FramePlacement<S>* frames, Index F,
                                        PoseFormat format, FrameReference reference, const BatchView<const S>& q,
                                        const BatchView<S>& poses, const BatchView<S>& J, cudaStream_t stream) {
  const Index B = q.batch;
  if (B < 0 || (poses.data && poses.batch != B) || (J.data && J.batch != B)) return cudaErrorInvalidValue;
  if (B == 0 || F == 0 || (!poses.data && !J.data)) return cudaSuccess;
  if (!q.data && model.nv() > 0) return cudaErrorInvalidValue;
  if (!frames) return cudaErrorInvalidValue;
  const unsigned blocks = static_cast<unsigned>((static_cast<long long>(B) + kKinematicsInstancesBlock - 1) /
                                                kKinematicsInstancesBlock);
  visit_compiled_capacity(model.params(), [&](const auto& params) {
    using P = std::decay_t<decltype(params)>;
    kinematics_instances_kernel<S, P::capacity>
        <<<blocks, kKinematicsInstancesBlock, 0, stream>>>(params, frames, F, format, reference, q, poses, J);
  });
  return cudaGetLastError();
}

// ---- the engine -------------------------------------------------------------------

template <class S>
CudaKinematics<S>::CudaKinematics(const ModelTpl<S>& model, const BackendOptions& options,
                                  const KinematicsOptions& kinematics)
    : nv_(model.nv()), nq_(model.nq()), max_batch_(options.max_batch), options_(kinematics) {
  check_kinematics_options(model, kinematics);
  if (options.strategy != IdStrategy::Auto && options.strategy != IdStrategy::Recursion)
    throw BackendError(std::string("backend 'cuda': strategy '") + to_string(options.strategy) +
                       "' is not available for kinematics (use auto or recursion)");
  if (model.multi_dof()) general_ = std::make_unique<GeneralPlan<S>>(model, max_batch_);
  else thread_ = std::make_unique<ThreadModel<S>>(model);  // throws beyond kMaxThreadDofs
  const std::size_t n = static_cast<std::size_t>(nv_), F = kinematics.frames.size();
  const std::size_t pw = static_cast<std::size_t>(pose_width(kinematics.pose));
  staging_ = std::make_unique<detail::StagingBuffer>(max_batch_, nv_, sizeof(S) == 4 ? "float" : "double",
                                                     "q, poses and J",
                                                     (static_cast<std::size_t>(nq_) + F * (pw + 6 * n)) * sizeof(S));
  if (F > 0) {
    std::vector<FramePlacement<S>> host;
    for (Index f : kinematics.frames) host.push_back(model.frames[static_cast<std::size_t>(f)]);
    frames_ = static_cast<FramePlacement<S>*>(detail::device_malloc(F * sizeof(FramePlacement<S>), [&](std::size_t free_bytes, std::size_t) {
      return "backend 'cuda': " + std::to_string(F) + " frames need " + std::to_string(F * sizeof(FramePlacement<S>)) +
             " bytes of device memory; " + std::to_string(free_bytes) + " are free";
    }));
    check(cudaMemcpy(frames_, host.data(), F * sizeof(FramePlacement<S>), cudaMemcpyHostToDevice),
          "copying the frames to the device");
  }
}

template <class S>
CudaKinematics<S>::~CudaKinematics() {
  if (frames_) cudaFree(frames_);
}

template <class S>
int CudaKinematics<S>::device() const {
  return staging_->device();
}

template <class S>
cudaError_t CudaKinematics<S>::compute_async(const BatchView<const S>& q, const BatchView<S>& poses,
                                             const BatchView<S>& J, cudaStream_t stream) {
  const Index F = static_cast<Index>(options_.frames.size());
  if (general_) return general_->launch_kinematics(frames_, F, options_.pose, options_.reference, q, poses, J, stream);
  return launch_kinematics_instances(*thread_, frames_, F, options_.pose, options_.reference, q, poses, J, stream);
}

template <class S>
void CudaKinematics<S>::compute(const BatchView<const S>& q, const BatchView<S>& poses, const BatchView<S>& J) {
  check_batch(q, poses, J, max_batch_);
  const Index B = q.batch, nv = nv_, nq = nq_, F = static_cast<Index>(options_.frames.size());
  if (B == 0 || F == 0 || (!poses.data && !J.data)) return;
  // staging buffer: q (nq x max_batch), poses (F pw x max_batch), then J (F 6 nv x max_batch)
  const Index pw = pose_width(options_.pose);
  const std::size_t qcap = static_cast<std::size_t>(nq) * max_batch_;
  const std::size_t pcap = static_cast<std::size_t>(F * pw) * max_batch_;
  const std::size_t jcap = static_cast<std::size_t>(F * 6 * nv) * max_batch_;
  S* const dq = static_cast<S*>(staging_->data());
  S* const dp = dq + qcap;
  S* const dJ = dp + pcap;
  const cudaStream_t stream = staging_->stream();

  const Staging sq = plan(q, nq, qcap, false);
  BatchView<S> dposes{}, dJv{};
  Staging sp, sJ;
  if (poses.data) sp = plan(poses, F * pw, pcap, true, "poses"), dposes = sp.device_view(dp, B);
  if (J.data) sJ = plan(J, F * 6 * nv, jcap, true, "J"), dJv = sJ.device_view(dJ, B);
  if (nq > 0) check(copy(sq, q, nq, dq, cudaMemcpyHostToDevice, stream), "copying q to the device");
  check(compute_async(sq.device_view<const S>(dq, B), dposes, dJv, stream),
        general_ ? "launching kinematics_general_kernel" : "launching kinematics_instances_kernel");
  if (poses.data) check(copy(sp, poses, F * pw, dp, cudaMemcpyDeviceToHost, stream), "copying the poses to the host");
  if (J.data) check(copy(sJ, J, F * 6 * nv, dJ, cudaMemcpyDeviceToHost, stream), "copying J to the host");
  check(cudaStreamSynchronize(stream), general_ ? "running kinematics_general_kernel" : "running kinematics_instances_kernel");
}

#define SCANDYN_INSTANTIATE(S)                                                                                    \
  template class CudaKinematics<S>;                                                                               \
  template cudaError_t launch_kinematics_instances(const ThreadModel<S>&, const FramePlacement<S>*, Index,        \
                                                   PoseFormat, FrameReference, const BatchView<const S>&,         \
                                                   const BatchView<S>&, const BatchView<S>&, cudaStream_t);
SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)
#undef SCANDYN_INSTANTIATE

}  // namespace cuda
}  // namespace scandyn
