// scandyn/cuda/general_dynamics.hpp: the general path on the GPU, for models with
// joints of any type (spherical joints; a floating base with more bodies past it
// than the thread kernels hold): forward dynamics by the ABA, the mass matrix by
// the CRBA, frame poses and Jacobians, one thread per instance.
//
// Each thread runs the serial reference's general path itself
// (scandyn/instance/general_instance.hpp: aba_general, crba_general;
// scandyn/instance/kinematics_instance.hpp: kinematics_instance_at) over a device
// copy of the model's bodies, its scratch (GeneralWork and the instance's q, qd,
// tau, result) a slice of one device buffer: `slots` slices, each thread taking
// instances t, t + slots, ... so that the buffer stays within a budget (512 MiB)
// whatever the batch. The 1-DoF thread kernels (fixed frames folded into the
// z-axis, state in registers) are ~30x faster per DoF (docs/benchmarks.md: the
// scratch here is per instance, a warp's loads uncoalesced); this path is for what
// they do not take. Every pointer given to a launch is a DEVICE pointer; nothing is allocated
// or synchronised per call; one plan serves one stream at a time.
#pragma once

#include <cstddef>

#include "scandyn/build_config.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/instance/general_instance.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

namespace scandyn {
namespace cuda {

// Does the model go to the general path? What the thread-per-instance kernels do not
// take: spherical joints, or a floating base with more than kMaxThreadDofs bodies past
// it. (The forward dynamics, mass matrix and simulator engines decide by it; kinematics,
// whose thread kernel takes no multi-DoF joint, sends every multi_dof() model.)
template <class S>
bool takes_general_path(const ModelTpl<S>& model) {
  return !model.one_dof_past_base() || (model.floating_base() && model.nbodies() - 1 > kMaxThreadDofs);
}

// Threads per block of the general kernels.
inline constexpr int kGeneralBlock = 64;

// Where one instance's scratch lies in its slice (byte offsets; every array aligned
// to 16 bytes): GeneralWork's arrays, then `scalars` scalars (the instance's inputs
// and outputs), then `extra` bytes for the caller.
template <class S>
struct GeneralLayout {
  std::size_t Xup, v, a, c, f, Ic, IA, U, D, u, L, scalars, extra, bytes;

  static GeneralLayout make(Index nb, Index nv, Index scalars, std::size_t extra_bytes);
  SCANDYN_HD GeneralWork<S> work(char* slice) const {
    return {reinterpret_cast<Transform<S>*>(slice + Xup), reinterpret_cast<Motion<S>*>(slice + v),
            reinterpret_cast<Motion<S>*>(slice + a),      reinterpret_cast<Motion<S>*>(slice + c),
            reinterpret_cast<Force<S>*>(slice + f),       reinterpret_cast<Inertia<S>*>(slice + Ic),
            reinterpret_cast<ABInertia<S>*>(slice + IA),  reinterpret_cast<Force<S>*>(slice + U),
            reinterpret_cast<S*>(slice + D),              reinterpret_cast<S*>(slice + u),
            reinterpret_cast<S*>(slice + L)};
  }
  SCANDYN_HD S* scalar_area(char* slice) const { return reinterpret_cast<S*>(slice + scalars); }
  SCANDYN_HD char* extra_area(char* slice) const { return slice + extra; }
};

// What a general kernel reads of the model and its scratch (a kernel parameter).
template <class S>
struct GeneralArgs {
  const Body<S>* bodies;  // (nb) device copy of the model's bodies
  Index nb, nv, nq;
  Motion<S> a0;            // base_acceleration(gravity)
  GeneralLayout<S> layout;
  char* work;              // (slots x layout.bytes)
  long long slots;         // threads launched; thread t takes instances t, t + slots, ...

  SCANDYN_HD char* slice(long long t) const { return work + t * static_cast<long long>(layout.bytes); }
  // the blocks of kGeneralBlock threads a launch for B instances takes: min(slots, B) threads
  unsigned blocks(Index B) const {
    const long long threads = slots < B ? slots : static_cast<long long>(B);
    return static_cast<unsigned>((threads + kGeneralBlock - 1) / kGeneralBlock);
  }
};

template <class S>
class GeneralPlan {
 public:
  // The most device memory a plan's scratch takes by default (fewer slots beyond).
  static constexpr std::size_t kBudgetBytes = std::size_t(512) << 20;

  // Copies the bodies to the device and allocates the scratch of
  // min(max_batch, budget_bytes / slice) slices (at least one); extra_bytes per
  // slice for the caller (GeneralArgs::layout.extra_area), extra_scalars more
  // scalars. Throws BackendError when the device memory does not suffice.
  GeneralPlan(const ModelTpl<S>& model, Index max_batch, std::size_t extra_bytes = 0, Index extra_scalars = 0,
              std::size_t budget_bytes = kBudgetBytes);
  ~GeneralPlan();
  GeneralPlan(const GeneralPlan&) = delete;
  GeneralPlan& operator=(const GeneralPlan&) = delete;

  // qdd (nv x B) and failed_dof (B ints: -1 or the DoF whose pivot failed; that
  // instance's qdd unwritten) for B = in.q.batch instances.
  cudaError_t launch_aba(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed_dof, cudaStream_t stream) const;
  // M (nv nv x B: entry r nv + c of each instance) for B = q.batch instances.
  cudaError_t launch_crba(const BatchView<const S>& q, const BatchView<S>& M, cudaStream_t stream) const;
  // The poses (F pose_width entries per instance, or none: poses.data null) and
  // Jacobians (F 6 nv) of the F frames (device FramePlacements).
  cudaError_t launch_kinematics(const FramePlacement<S>* frames, Index F, PoseFormat format, FrameReference reference,
                                const BatchView<const S>& q, const BatchView<S>& poses, const BatchView<S>& J,
                                cudaStream_t stream) const;

  const GeneralArgs<S>& args() const { return args_; }
  std::size_t device_bytes() const { return bytes_; }

 private:
  GeneralArgs<S> args_{};
  void* memory_ = nullptr;
  std::size_t bytes_ = 0;
};

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
