// scandyn/cuda/general_dynamics.hpp: the general path on the GPU, for models with
// joints of any type (spherical joints; a floating base with more bodies past it
// than the thread kernels hold): forward dynamics by the ABA, the mass matrix by
// the CRBA, frame poses and Jacobians, one thread per instance.
//
// Each thread runs the serial reference's general path itself
// (scandyn/instance/general_instance.hpp: aba_general, crba_general;
// scandyn/instance/kinematics_instance.hpp: kinematics_instance_at) over a device
// copy of the model's bodies, its scratch (GeneralWorkOf's arrays and the
// instance's q, qd, tau, result) in one device buffer shared by `slots` threads,
// each thread taking instances t, t + slots, ... so that the buffer stays within a
// budget (512 MiB) whatever the batch. The scratch is interleaved across the
// threads (GeneralInterleave, scandyn/instance/interleaved.hpp): element i of
// thread t's array next to element i of thread t + 1's, so that a warp's loads and
// stores coalesce. The 1-DoF thread kernels (fixed frames folded into the z-axis,
// state in registers) were ~30x faster per DoF when this scratch was per instance
// (docs/benchmarks.md); this path is for what they do not take, and for ABA
// beyond their 64 DoFs (FdMethod::Aba on a model of 1-DoF joints past
// kMaxThreadDofs). Every pointer given to a launch is a DEVICE pointer; nothing is
// allocated or synchronised per call; one plan serves one stream at a time.
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

// How a plan lays its threads' scratch out (scandyn/instance/interleaved.hpp):
//   Instance: each thread's arrays contiguous (element i of thread t at
//             base + t n + i; a warp's loads 32 slices apart: the layout before issue 22)
//   Structs:  whole elements interleaved (element i of thread t at base + i slots + t)
//   Scalars:  every scalar interleaved (scalar k of element i of thread t at
//             base + (i N + k) slots + t, N the element's scalars)
// The q, qd, tau and result scalars follow the same rule (Structs and Scalars:
// interleaved). kGeneralInterleave is the default; the environment variable
// SCANDYN_GENERAL_INTERLEAVE (instance, structs, scalars) overrides it when a plan is
// made, for A/B measurements (the results are the same: one routine, its arithmetic
// unchanged).
enum class GeneralInterleave { Instance, Structs, Scalars };
inline constexpr GeneralInterleave kGeneralInterleave = GeneralInterleave::Scalars;
const char* interleave_name(GeneralInterleave i);
// kGeneralInterleave, or SCANDYN_GENERAL_INTERLEAVE's value (BackendError for another).
GeneralInterleave general_interleave_from_env();

// How a plan's launch_aba runs an instance:
//   Thread  one thread per instance (aba_general), the scratch laid out as the
//           plan's GeneralInterleave says: the default;
//   Levels  one warp per instance: the lanes take a tree level's bodies, level
//           after level (the per-body steps of aba_general, general_instance.hpp,
//           in the serial order: the same result), the scratch of an instance
//           contiguous (GeneralInterleave::Instance).
// Measured on the H200 (bench/results/general-path-levels-h200.csv, fd, float):
// Levels takes 1.2-2.3x Thread's time on tree:1000:1 and tree:300:7 at 10^4 and
// 10^5 instances, float and double (a warp's lanes load different bodies' structs,
// 32 separate segments, where Thread's interleaved scratch coalesces), so Thread is
// the default; SCANDYN_GENERAL_ABA=levels selects Levels when a plan is made (A/B
// measurements, batches too small to fill the GPU with threads).
enum class GeneralAba { Thread, Levels };
const char* general_aba_name(GeneralAba a);
// Thread, or SCANDYN_GENERAL_ABA's value (thread, levels; BackendError for another).
GeneralAba general_aba_from_env();

// A tree's level schedule (device arrays; Levels plans).
struct LevelSchedule {
  const int* order = nullptr;        // (nb) bodies by depth (roots first), increasing index within a level
  const int* level_begin = nullptr;  // (levels + 1) offsets of each level in order
  const int* child_begin = nullptr;  // (nb + 1) CSR offsets of each body's children in child
  const int* child = nullptr;        // children of each body in decreasing index (the order in
                                     // which the serial ABA adds their shares to the parent)
  Index levels = 0;
};

// Where the scratch's arrays lie in the plan's buffer: byte offsets of each area
// (GeneralWorkOf's arrays, then `scalars` scalars per thread: the instance's inputs
// and outputs, then `extra` bytes per thread for the caller, contiguous per thread),
// every area aligned to 16 bytes. make() fills bytes, the bytes of one thread's share
// (each area's share rounded up to 16 bytes: slots * bytes bounds the buffer);
// place() the offsets for a number of slots.
template <class S>
struct GeneralLayout {
  std::size_t Xup, v, a, c, f, Ic, IA, U, D, u, L, scalars, extra, bytes, end;
  Index nb, nv, nscalars;
  std::size_t extra_bytes;  // per thread, a multiple of 16

  static GeneralLayout make(Index nb, Index nv, Index scalars, std::size_t extra_bytes);
  void place(long long slots);
};

// What a general kernel reads of the model and its scratch (a kernel parameter).
template <class S>
struct GeneralArgs {
  const Body<S>* bodies;  // (nb) device copy of the model's bodies
  Index nb, nv, nq;
  Motion<S> a0;            // base_acceleration(gravity)
  GeneralLayout<S> layout;
  char* work;              // the scratch (layout.end bytes)
  long long slots;         // threads launched; thread t takes instances t, t + slots, ...
  GeneralInterleave interleave;

  // Thread t's array of n elements T at byte offset off: contiguous (Instance) or
  // interleaved a whole T at a time.
  template <class T>
  SCANDYN_HD StridedArray<T> strided(std::size_t off, Index n, long long t) const {
    T* const base = reinterpret_cast<T*>(work + off);
    if (interleave == GeneralInterleave::Instance) return {base + t * n, 1};
    return {base + t, slots};
  }
  // Thread t's GeneralWorkOf: of StridedArrays (Instance, Structs) ...
  SCANDYN_HD GeneralWorkOf<S, StridedArray> work_strided(long long t) const {
    const GeneralLayout<S>& l = layout;
    const Index nb_ = nb, nv_ = nv;
    return {strided<Transform<S>>(l.Xup, nb_, t), strided<Motion<S>>(l.v, nb_, t),   strided<Motion<S>>(l.a, nb_, t),
            strided<Motion<S>>(l.c, nb_, t),      strided<Force<S>>(l.f, nb_, t),    strided<Inertia<S>>(l.Ic, nb_, t),
            strided<ABInertia<S>>(l.IA, nb_, t),  strided<Force<S>>(l.U, nv_, t),    strided<S>(l.D, nv_, t),
            strided<S>(l.u, nv_, t),              strided<S>(l.L, kMaxJointDofs * nv_, t)};
  }
  // ... or with every scalar interleaved (Scalars).
  SCANDYN_HD GeneralWorkOf<S, ScalarInterleavedArray> work_scalars(long long t) const {
    const GeneralLayout<S>& l = layout;
    auto at = [&](std::size_t off) { return reinterpret_cast<S*>(work + off) + t; };
    return {{at(l.Xup), slots}, {at(l.v), slots}, {at(l.a), slots},  {at(l.c), slots},
            {at(l.f), slots},   {at(l.Ic), slots}, {at(l.IA), slots}, {at(l.U), slots},
            {at(l.D), slots},   {at(l.u), slots},  {at(l.L), slots}};
  }
  // Thread t's scalars (layout.nscalars of them).
  SCANDYN_HD StridedArray<S> scalar_area(long long t) const { return strided<S>(layout.scalars, layout.nscalars, t); }
  // Thread t's extra bytes (contiguous).
  SCANDYN_HD char* extra_area(long long t) const {
    return work + layout.extra + t * static_cast<long long>(layout.extra_bytes);
  }
  // the blocks of kGeneralBlock threads a launch for B instances takes: min(slots, B) threads
  unsigned blocks(Index B) const {
    const long long threads = slots < B ? slots : static_cast<long long>(B);
    return static_cast<unsigned>((threads + kGeneralBlock - 1) / kGeneralBlock);
  }
};

template <class S>
class GeneralPlan {
 public:
  // The device memory a plan's scratch takes at most by default (fewer slots
  // beyond): an eighth of the free device memory, within [kMinBudgetBytes,
  // kMaxBudgetBytes]. A tree of 1000 bodies takes ~330 KB of scratch per instance in
  // float, so 512 MiB held 1600 instances at a time.
  static constexpr std::size_t kMinBudgetBytes = std::size_t(512) << 20;
  static constexpr std::size_t kMaxBudgetBytes = std::size_t(4) << 30;

  // Copies the bodies to the device and allocates the scratch of
  // min(max_batch, budget_bytes / slice) slices (at least one; budget_bytes 0: the
  // default above); extra_bytes per slice for the caller
  // (GeneralArgs::layout.extra_area), extra_scalars more scalars. Throws
  // BackendError when the device memory does not suffice. The scratch's layout:
  // interleave (kGeneralInterleave unless SCANDYN_GENERAL_INTERLEAVE says otherwise:
  // general_interleave_from_env()); aba Levels lays it out per instance
  // (GeneralInterleave::Instance) whatever interleave says, and a slice is then a
  // warp's.
  GeneralPlan(const ModelTpl<S>& model, Index max_batch, std::size_t extra_bytes = 0, Index extra_scalars = 0,
              std::size_t budget_bytes = 0, GeneralInterleave interleave = general_interleave_from_env(),
              GeneralAba aba = GeneralAba::Thread);
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
  GeneralAba aba() const { return aba_; }

 private:
  GeneralArgs<S> args_{};
  GeneralAba aba_ = GeneralAba::Thread;
  LevelSchedule levels_{};  // Levels: the schedule (in memory_)
  void* memory_ = nullptr;
  std::size_t bytes_ = 0;
};

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
