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

#include <variant>
#include "scandyn/build_config.hpp"
#include "scandyn/engine.hpp"
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

// The model as the kernels read it, for capacity C (nv <= C): the kernel parameter.
template <class S, int C>
struct ThreadModelParams {
  static constexpr int capacity = C;
  Body<S> body[C];                 // (nv) bodies in DoF order; entries past nv unused
  int flags[C];                    // (nv) ThreadBodyFlag bits of each body
  unsigned long long ancestors[C]; // (nv) bit j of ancestors[i]: body j is a proper ancestor
                                   // of body i (the sparsity of row i of M; forward dynamics)
  Motion<S> a0;                    // base acceleration: gravity entered as -g
  Index nv;                        // number of bodies (DoF), <= C
};

// One model prepared for the kernels: the parameter block of the smallest capacity
// that holds it. Host memory only; built once, then copied into each launch.
template <class S>
class ThreadModel {
 public:
  using Params = std::variant<ThreadModelParams<S, 8>, ThreadModelParams<S, 16>,
                              ThreadModelParams<S, 32>, ThreadModelParams<S, 64>>;

  // Throws BackendError when model.nv() > kMaxThreadDofs.
  explicit ThreadModel(const ModelTpl<S>& model);

  Index nv() const { return nv_; }
  Index capacity() const { return capacity_; }  // 8, 16, 32 or 64
  const Params& params() const { return params_; }
  // Branch slots the model needs (see kSlotShift): 0 when every body's parent is the
  // previous body or the base (a chain, or chains hanging from the base)
  Index branch_slots() const { return branch_slots_; }

 private:
  Index nv_ = 0;
  Index capacity_ = 0;
  Index branch_slots_ = 0;
  Params params_;
};

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
