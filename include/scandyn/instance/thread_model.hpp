// scandyn/instance/thread_model.hpp: the model as the thread-per-instance kernels read it.
//
// ThreadModelParams<S, C>: a model of at most C bodies (DoF) with, for each body, the
// flags that say how it exchanges values with its parent in a per-thread traversal
// (scandyn/instance/traversal.hpp): through registers (parent = previous body, or
// the base) or through a branch stack or slot (kStacked, kOpensSlot, the slot
// number). The kernels take it as a __grid_constant__ parameter; the instance
// functions (rnea_instance, crba_instance, fd_jsi_instance, aba_instance) read it.
// ThreadModel<S>: the host object that builds it for the smallest capacity that
// holds a model (8, 16, 32 or 64).
#pragma once

#include <string>
#include <type_traits>
#include <variant>
#include "scandyn/build_config.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/joint_frames.hpp"
#include "scandyn/model/model.hpp"

#if SCANDYN_HAS_CUDA
namespace scandyn {
namespace cuda {

// Largest model (DoF) the thread-per-instance kernels take: kMaxThreadDofs (scandyn/engine.hpp).

// How body i exchanges quantities with its parent; precomputed on the host so that
// the kernel keeps the common case (parent = body i - 1, or the base) in registers
// and touches per-thread memory only at branch points of the tree.
enum ThreadBodyFlag : int {
  kParentIsBase = 1,  // parent is the fixed base (-1)
  kParentIsPrev = 2,  // parent is body i - 1
  kStacked = 4,       // a child other than body i + 1 (a branch child) reads v_i, a_i and
                      // adds to f_i: body i is a branch point of the tree
  kOpensSlot = 8,     // body i is the highest-numbered branch child of its parent: the
                      // first of them to reach the parent going leaves to root
  kTurned = 16,       // (z-axis models) body i's frame is its user frame turned by
                      // frame_Q[i]: body wrenches given by the user are turned on reading
};

// Bits kSlotShift.. of a kStacked body's flags: its branch slot, a small number
// shared by branch points whose children do not interleave. Branch point p's slot
// is in use from p to its highest-numbered branch child h(p) (root to leaves) or
// from h(p) back to p (leaves to root); the host gives two branch points the same
// slot only when one's range ends where or before the other's starts, so that a
// kernel holding one value per slot (aba_instance: velocities, articulated
// inertias) needs as many slots as branch points whose ranges overlap
// (ThreadModel::branch_slots()), not one per body.
inline constexpr int kSlotShift = 8;
SCANDYN_HD constexpr int branch_slot(int flags) { return flags >> kSlotShift; }

// The model as the kernels read it, for capacity C (nv <= C): the kernel parameter
// (__grid_constant__: it stays in the constant bank, read without copies). Bd: the
// body type, Body<S> (the user's frames, any joint axis) or ZJointBody<S> (every
// frame turned so that its joint axis is +z, scandyn/model/joint_frames.hpp: the
// step functions then test no axis).
template <class S, int C, class Bd = Body<S>>
struct ThreadModelParams {
  static constexpr int capacity = C;
  static constexpr bool z_axes = !std::is_same_v<Bd, Body<S>>;
  Bd body[C];                      // (nv) bodies in DoF order; entries past nv unused
  int flags[C];                    // (nv) ThreadBodyFlag bits of each body
  unsigned long long ancestors[C]; // (nv) bit j of ancestors[i]: body j is a proper ancestor
                                   // of body i (the sparsity of row i of M; forward dynamics)
  Motion<S> a0;                    // base acceleration: gravity entered as -g (world frame; with a
                                   // floating base, the acceleration of the world the base moves in)
  Index nv;                        // number of bodies in body[] (their DoF), <= C
  Mat3<S> frame_Q[z_axes ? C : 1]; // (nv, z-axis models) Q_i: body i's user-frame
                                   // coordinates -> its z-axis frame's (kTurned bodies)
  // (last, so that the fields above keep their places in the fixed-base kernels)
  int floating;                    // 1: the model's body 0 is a floating base (a free joint to the
                                   // world), held apart in `base`: body[] are the model's bodies
                                   // 1.. (parents shifted by one; the base's children are
                                   // kParentIsBase) and every instance vector starts with the
                                   // base's entries (q: 7, qd/qdd/tau: 6, fext: 1 wrench); 0: fixed
  Body<S> base;                    // (floating) the base: its free joint and rigid inertia
};

// Body i's external wrench fext[i], given in body i's user frame, in the frame the
// kernels work in (turned by Q_i for a kTurned body of a z-axis model).
template <class S, int C, class Bd>
SCANDYN_HD Force<S> external_wrench(const ThreadModelParams<S, C, Bd>& model, Index i, const Force<S>* fext) {
  if constexpr (ThreadModelParams<S, C, Bd>::z_axes) {
    if (model.flags[i] & kTurned) {
      const Mat3<S>& Q = model.frame_Q[i];
      return {Q * fext[i].n, Q * fext[i].f};
    }
  }
  return fext[i];
}

// The inverse: a wrench on body i in the kernels' frame, in body i's user frame.
template <class S, int C, class Bd>
SCANDYN_HD Force<S> user_wrench(const ThreadModelParams<S, C, Bd>& model, Index i, const Force<S>& f) {
  if constexpr (ThreadModelParams<S, C, Bd>::z_axes) {
    if (model.flags[i] & kTurned) {
      const Mat3<S>& Q = model.frame_Q[i];
      return {mul_transpose(Q, f.n), mul_transpose(Q, f.f)};
    }
  }
  return f;
}

// ---- the floating base -------------------------------------------------------
// With model.floating, an instance's vectors hold the base's entries first: the
// kernels' body i (body i + 1 of the model) has its q at 7 + i, its qd, qdd, tau at
// 6 + i and its wrench at 1 + i. These are the offsets (0 for a fixed base).
template <class S, int C, class Bd>
SCANDYN_HD Index q_offset(const ThreadModelParams<S, C, Bd>& model) {
  return model.floating ? 7 : 0;
}
template <class S, int C, class Bd>
SCANDYN_HD Index v_offset(const ThreadModelParams<S, C, Bd>& model) {
  return model.floating ? 6 : 0;
}
// The model's DoF (the length of qd) and bodies (the length of fext).
template <class S, int C, class Bd>
SCANDYN_HD Index model_nv(const ThreadModelParams<S, C, Bd>& model) {
  return model.nv + v_offset(model);
}
template <class S, int C, class Bd>
SCANDYN_HD Index model_nbodies(const ThreadModelParams<S, C, Bd>& model) {
  return model.nv + model.floating;
}

// One model prepared for the kernels: the parameter block of the smallest capacity
// that holds it. Host memory only; built once, then copied into each launch. With
// Bd = ZJointBody<S> (ZThreadModel) the bodies are z_axis_model's, their joints
// revolute or prismatic only.
template <class S, class Bd = Body<S>>
class ThreadModel {
 public:
  using Params = std::variant<ThreadModelParams<S, 8, Bd>, ThreadModelParams<S, 16, Bd>,
                              ThreadModelParams<S, 32, Bd>, ThreadModelParams<S, 64, Bd>>;

  // Throws BackendError when the model has more than kMaxThreadDofs bodies beside a
  // floating base, a multi-DoF joint other than a floating base (a spherical joint),
  // or (z-axis) a joint that is neither revolute nor prismatic.
  explicit ThreadModel(const ModelTpl<S>& model);

  Index nv() const { return nv_; }  // the model's DoF (a floating base's 6 included)
  Index nq() const { return nq_; }  // the model's position entries (nv + 1 with a floating base)
  bool floating() const { return floating_; }
  Index capacity() const { return capacity_; }  // 8, 16, 32 or 64
  const Params& params() const { return params_; }
  // Branch slots the model needs (see kSlotShift): 0 when every body's parent is the
  // previous body or the base (a chain, or chains hanging from the base)
  Index branch_slots() const { return branch_slots_; }

 private:
  Index nv_ = 0;
  Index nq_ = 0;
  bool floating_ = false;
  Index capacity_ = 0;
  Index branch_slots_ = 0;
  Params params_;
};

// Which kernels are compiled for floating-base models (kFloating): those of z-axis
// models only, what the engines run (each kernel once more per capacity and
// precision costs minutes of nvcc).
template <class S, class Bd>
inline constexpr bool kFloatingKernels = !std::is_same_v<Bd, Body<S>>;
// The capacities whose floating-base kernels a build compiles: all, or with
// SCANDYN_SIM_EFFECT_SETS=0 (the reduced kernel set of builds without a GPU,
// scripts/test.sh) one: kReducedFloatingCapacity, 16 (hyq: 12 joints past its base),
// or 8 where SCANDYN_CUDA_ALL_CAPACITIES is OFF too (below); ThreadModel's engines
// refuse the others there, naming the option.
#if !defined(SCANDYN_SIM_EFFECT_SETS)
#define SCANDYN_SIM_EFFECT_SETS 1
#endif
inline constexpr int kReducedFloatingCapacity = SCANDYN_CUDA_ALL_CAPACITIES ? 16 : 8;
template <int C>
inline constexpr bool kFloatingCapacity = SCANDYN_SIM_EFFECT_SETS || C == kReducedFloatingCapacity;

// Throws BackendError for a floating-base model of a capacity this build leaves out
// (kFloatingCapacity); the engines call it on their thread model. name: the model's.
template <class S, class Bd>
void require_floating_capacity(const ThreadModel<S, Bd>& tm, const std::string& name) {
  if (!tm.floating() || SCANDYN_SIM_EFFECT_SETS || tm.capacity() == kReducedFloatingCapacity) return;
  throw BackendError("backend 'cuda': model '" + name + "' has " + std::to_string(tm.nv() - 6) +
                     " joints past its floating base; this build compiles the floating-base kernels for " +
                     (kReducedFloatingCapacity == 16 ? "9 to 16" : "up to 7") +
                     " of them only (SCANDYN_SIM_EFFECT_SETS=OFF, the reduced kernel set of builds without a GPU)");
}

// The capacities whose kernels a build compiles (one kernel per capacity, precision
// and variant: what makes nvcc slow): all, or with SCANDYN_CUDA_ALL_CAPACITIES 0
// (scandyn/build_config.hpp; CMake option SCANDYN_CUDA_ALL_CAPACITIES=OFF, what
// scripts/test.sh configures on machines without a GPU, where CUDA code is compiled
// but never run) capacity 8 only: models of up to 8 bodies (7 joints past a floating
// base). The launches go through visit_compiled_capacity, which refuses the others.
constexpr bool compiled_capacity(Index capacity) { return SCANDYN_CUDA_ALL_CAPACITIES || capacity == 8; }
template <int C>
inline constexpr bool kCompiledCapacity = compiled_capacity(C);

// The refusal of a capacity this build leaves out: BackendError naming the option.
// what: the computation ("the rollout derivatives"); name: the model's, or empty.
[[noreturn]] inline void throw_capacity_not_compiled(Index capacity, const std::string& what,
                                                     const std::string& name) {
  throw BackendError("backend 'cuda': " + (name.empty() ? std::string("the model") : "model '" + name + "'") +
                     " needs the capacity-" + std::to_string(capacity) + " kernels of " + what +
                     "; this build compiles the thread-per-instance kernels for up to 8 bodies only "
                     "(SCANDYN_CUDA_ALL_CAPACITIES=OFF, the reduced kernel set of builds without a GPU)");
}

// Throws that BackendError when `capacity` (8, 16, 32 or 64) is one this build leaves
// out (kCompiledCapacity); the engines call it at construction, where the model's
// name is known.
inline void require_compiled_capacity(Index capacity, const std::string& what, const std::string& name) {
  if (!compiled_capacity(capacity)) throw_capacity_not_compiled(capacity, what, name);
}

// std::visit(f, params) over a per-capacity variant (ThreadModel::Params and the
// like: alternatives with a static `capacity`), f instantiated for the capacities
// this build compiles only; a model of another capacity throws (host code, before
// any launch).
template <class V, class F>
void visit_compiled_capacity(const V& params, F&& f) {
  std::visit(
      [&](const auto& p) {
        constexpr int C = std::decay_t<decltype(p)>::capacity;
        if constexpr (kCompiledCapacity<C>) f(p);
        else throw_capacity_not_compiled(C, "this computation", "");
      },
      params);
}

// Is `model` run by the kernels' floating-base instantiation (kFloating)?
template <class S, class Bd>
bool floating_kernels(const ThreadModel<S, Bd>& model) {
  return kFloatingKernels<S, Bd> && model.floating();
}

// The thread-per-instance model with every joint axis on its frame's z axis: what the
// inverse dynamics, mass matrix, forward dynamics and fused simulator step kernels
// run on (results in the user's frames: joint-space quantities do not change, and
// body wrenches are turned on reading, external_wrench).
template <class S>
using ZThreadModel = ThreadModel<S, ZJointBody<S>>;

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
