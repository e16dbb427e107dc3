// scandyn/instance/traversal.hpp: walks of the tree inside one thread, shared by the instance functions
// (rnea_instance, crba_instance / fd_jsi_instance, aba_instance).
#pragma once

#include <type_traits>

#include "scandyn/build_config.hpp"
#include "scandyn/instance/thread_model.hpp"

#if SCANDYN_HAS_CUDA
namespace scandyn {
namespace cuda {

#if defined(__CUDACC__)
namespace fd_detail {

// Is body j a proper ancestor of body k?
template <class S, int C, class Bd = Body<S>>
__host__ __device__ __forceinline__ bool is_ancestor(const ThreadModelParams<S, C, Bd>& m, Index j, Index k) {
  return (m.ancestors[k] >> j) & 1ull;
}

// Calls f(j) for every proper ancestor j of body k, nearest first (the order of the
// reference's for_path). Unrolled: a loop of compile-time indices (once k is one)
// over the ancestor bits, so that arrays indexed by j stay in registers; otherwise
// the walk up the parents.
template <bool kUnrolled, class S, int C, class F, class Bd = Body<S>>
__host__ __device__ __forceinline__ void for_ancestors(const ThreadModelParams<S, C, Bd>& m, Index k, F&& f) {
  if constexpr (kUnrolled) {
#pragma unroll
    for (Index j = C - 2; j >= 0; --j)
      if (j < k && is_ancestor(m, j, k)) f(j);
  } else {
    for (Index j = m.body[k].parent; j >= 0; j = m.body[j].parent) f(j);
  }
}

// Calls f(k) for every proper descendant k of body i (any order; ascending here).
template <bool kUnrolled, class S, int C, class F, class Bd = Body<S>>
__host__ __device__ __forceinline__ void for_descendants(const ThreadModelParams<S, C, Bd>& m, Index i, F&& f) {
#pragma unroll(kUnrolled ? C : 1)
  for (Index k = 1; k < C; ++k)
    if (k > i && k < m.nv && is_ancestor(m, i, k)) f(k);
}

}  // namespace fd_detail

// ---- the per-thread tree traversal ---------------------------------------------
// One thread walks one instance's tree, bodies in DoF order (parent[i] < i). Body
// i's parent is the base (kParentIsBase), the previous body (kParentIsPrev) or a
// branch point further back, whose values wait in memory the caller owns (a stack
// entry per body, or a branch slot: see kSlotShift). The two passes below keep the
// common case in registers, as rnea_instance, jsi_passes and aba_instance all need
// it: going root to leaves, each body's values reach the next body in a register;
// going leaves to root, each body's contribution reaches its parent in a register
// (the carry) when the parent is the previous body. Only branch points go through
// memory, by the caller's functors. n is model.nv as the caller read it (one read
// of the kernel parameter for all passes). With kUnrolled every loop runs over C
// compile-time indices (bodies past nv skipped, not a break), so that the caller's
// per-body arrays indexed by i can live in registers.

// A body's velocity and acceleration, what the RNEA's forward pass (and the ABA's
// pass 3) hands a body's children.
template <class S>
struct BodyKinematics {
  Motion<S> v;
  Motion<S> a;
};

// Root to leaves: for each body i < nv in order,
//   x_i = step(i, flags_i, x_parent)
// where x_parent is `base` for a body on the base, x_{i-1} (a register) when the
// parent is body i - 1, else branch_parent(i), the caller's read of body i's
// parent's value (which step stored when it visited that kStacked body). T: what a
// body hands its children (a Motion, or BodyKinematics).
template <bool kUnrolled, class S, int C, class T, class BranchParent, class Step, class Bd = Body<S>>
__host__ __device__ __forceinline__ void forward_pass(const ThreadModelParams<S, C, Bd>& model, Index n, const T& base,
                                                      BranchParent&& branch_parent, Step&& step) {
  T prev = base;  // body i - 1's value
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = 0; i < C; ++i) {
    if (i >= n) continue;  // (not break: a loop of C trips unrolls, indices stay constant)
    const int fl = model.flags[i];
    T parent = base;
    if (fl & kParentIsPrev) parent = prev;
    else if (!(fl & kParentIsBase)) parent = branch_parent(i);
    prev = step(i, fl, parent);
  }
}

// How backward_pass ended: through every body (complete), or stopped at body `at`
// by step. (A flag, not just `at` >= 0: the caller's early return then branches on
// a constant per exit, and the compiler keeps the stopped exit apart from the code
// that follows a complete pass, as a hand-written loop's `return i` does; with the
// index alone aba_instance's double tree kernel took 242 registers against 240.)
struct PassEnd {
  bool complete;
  Index at;  // the body at which step returned false (when not complete)
};

// Leaves to root: for each body i from the last,
//   t = own(i, flags_i)              its own value (or its stack entry / slot, into
//                                    which its branch children have gone already)
//   t += carry                       body i + 1's contribution, when its parent is i
//   step(i, flags_i, t)              the body's own work; false stops the pass
//   up = lift(i, t)                  unless on the base: the contribution to the
//                                    parent, in the parent's frame, then either
//   carry = up                       (the parent is body i - 1), or
//   to_branch_parent(i, flags_i, up) (the caller adds it to the parent's memory).
// A parent thus receives its children in descending order, as in the serial
// reference: branch children (higher-numbered) first, body i + 1 last. T needs
// += and value-initialises to zero (the carry before any body sets it). Returns
// whether the pass went through every body, else the body at which step returned
// false (PassEnd).
//
// lift may instead take a third argument, hand_off, and call hand_off(up) itself,
// once: its work after that (which needs what it computed for up, a transform)
// then runs after the hand-off, as in a hand-written loop, in registers that up no
// longer holds (jsi_passes moves its columns on so; work ahead of the hand-off
// costs registers).
//
// to_base (optional): with a floating base (ThreadModelParams::floating), a body on
// the base is lifted too and to_base(i, up) called once lift has returned (so after
// any work lift does past its hand-off): the base's children in descending order,
// as the reference adds them. Without it (NoBase), a body on the base hands nothing on.
struct NoBase {};
// f as backward_pass' to_base when kFloating, else NoBase (no lift for bodies on the base).
template <bool kFloating, class F>
__host__ __device__ __forceinline__ auto base_hook(F&& f) {
  if constexpr (kFloating) return f;
  else return NoBase{};
}
template <bool kUnrolled, class S, int C, class T, class Own, class Step, class Lift, class ToBranchParent,
          class Bd = Body<S>, class ToBase = NoBase>
__host__ __device__ __forceinline__ PassEnd backward_pass(const ThreadModelParams<S, C, Bd>& model, Index n, Own&& own,
                                                          Step&& step, Lift&& lift,
                                                          ToBranchParent&& to_branch_parent,
                                                          ToBase to_base = {}) {
  T carry{};  // body i + 1's contribution, when its parent is body i
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = C - 1; i >= 0; --i) {
    if (i >= n) continue;
    const int fl = model.flags[i];
    T t = own(i, fl);
    if (i + 1 < n && (model.flags[i + 1 < C ? i + 1 : i] & kParentIsPrev)) t += carry;
    if (!step(i, fl, t)) return PassEnd{false, i};
    if (fl & kParentIsBase) {
      if constexpr (!std::is_same_v<ToBase, NoBase>) {
        if constexpr (std::is_invocable_v<Lift&, Index, const T&>) {
          to_base(i, lift(i, t));
        } else {
          T up{};
          lift(i, t, [&](const T& u) { up = u; });
          to_base(i, up);
        }
      }
      continue;
    }
    auto hand_off = [&](const T& up) {
      if (fl & kParentIsPrev) carry = up;
      else to_branch_parent(i, fl, up);
    };
    if constexpr (std::is_invocable_v<Lift&, Index, const T&>) hand_off(lift(i, t));
    else lift(i, t, hand_off);
  }
  return PassEnd{true, -1};
}
#endif  // __CUDACC__

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
