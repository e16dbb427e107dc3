// scandyn/instance/aba_instance.hpp: the articulated-body algorithm of one instance in one thread
// (forward dynamics), and the choice among its kernels (choose_aba_kernel).
#pragma once

#include "scandyn/algorithm/steps.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/instance/dof_column.hpp"
#include "scandyn/instance/thread_model.hpp"
#include "scandyn/instance/traversal.hpp"

#if SCANDYN_HAS_CUDA
namespace scandyn {
namespace cuda {

// Branch slots that the ABA kernel for branched models keeps in registers
// (aba_instance's kSlots; atlas needs 1). Each costs 39 scalars of pass state: in
// float, 1 fits without spilling (152 registers at capacity 32), 2 spill.
inline constexpr Index kAbaRegisterSlots = 1;

// The ABA kernels (aba_instance's kSlots, from the model's shape), as
// launch_aba_instances picks them.
enum class AbaKernel {
  Chains,    // "chain": no branch children (ThreadModel::branch_slots() == 0: a chain,
             // or chains hanging from the base such as hyq's legs); no slots at all
  Branches,  // "slots": float, at most kAbaRegisterSlots branch slots, in registers
  Tree,      // "tree": any model; a slot per branch point in per-thread local memory
             // (double's pick for branched models: 240 registers, no spills, where
             // register slots spill at 255)
};


inline const char* to_string(AbaKernel k) {
  return k == AbaKernel::Chains ? "chain" : k == AbaKernel::Branches ? "slots" : "tree";
}

// The ABA kernel launch_aba_instances runs for `model` in precision S.
template <class S>
AbaKernel choose_aba_kernel(const ThreadModel<S>& model) {
  if (model.branch_slots() == 0) return AbaKernel::Chains;
  if (sizeof(S) == 4 && model.branch_slots() <= kAbaRegisterSlots) return AbaKernel::Branches;
  return AbaKernel::Tree;
}

#if defined(__CUDACC__)
namespace fd_detail {

// Body i's state between the passes of aba_instance, one storage for two uses (8
// scalars): its velocity v_i = [x; y] from pass 1 until pass 2 reaches body i, then
// U_i = IA_i S_i = [x; y], D_i and u_i for pass 3.
template <class S>
struct AbaBodyState {
  Vec3<S> x, y;  // v_i (angular; linear), then U_i (moment; force)
  S D, u;        // D_i = S_i^T U_i, u_i = tau_i - S_i^T pA_i (from pass 2)
  __host__ __device__ __forceinline__ Motion<S> v() const { return {x, y}; }
  __host__ __device__ __forceinline__ Force<S> U() const { return {x, y}; }
  __host__ __device__ __forceinline__ void set_v(const Motion<S>& v) { x = v.w, y = v.v; }
  __host__ __device__ __forceinline__ void set_terms(const Force<S>& U, S Dv, S uv) {
    x = U.n, y = U.f, D = Dv, u = uv;
  }
};

// Slot s (a run-time value) of K branch slots. With K < C a loop of compile-time
// indices selects it, so that the slots can stay in registers (K selects per
// scalar); with K == C the slot indexes the array (per-thread local memory).
template <int K, int C, class T>
__host__ __device__ __forceinline__ T slot_get(const T (&slots)[K], int s) {
  if constexpr (K < C) {
    T r = slots[0];
#pragma unroll
    for (int k = 1; k < K; ++k)
      if (k == s) r = slots[k];
    return r;
  } else {
    return slots[s];
  }
}

// f(slots[s]) for a run-time slot s, as slot_get.
template <int K, int C, class T, class F>
__host__ __device__ __forceinline__ void slot_update(T (&slots)[K], int s, F&& f) {
  if constexpr (K < C) {
#pragma unroll
    for (int k = 0; k < K; ++k)
      if (k == s) f(slots[k]);
  } else {
    f(slots[s]);
  }
}

}  // namespace fd_detail

// Forward dynamics of one instance by the articulated-body algorithm (ABA,
// Featherstone (2008) 7.3): the three passes of the serial scandyn::aba
// (src/algorithm/reference.cpp) over the same step functions (steps.hpp), with the
// same sums in the same order: pass 1 (velocities), pass 2 from the last body to
// the first (c = v x S qd and pA = v x* I v - fext, aba_joint_terms, the pivot
// check, aba_backward_to_parent into the parent's articulated inertia and bias
// force), pass 3 from the first to the last (aba_acceleration_step). Gravity
// included; fext: nv body wrenches or null. Returns -1, or the DoF whose articulated
// pivot D_i = S_i^T IA_i S_i was not positive and finite (the DoF the serial aba
// reports), in which case qdd is not written (pass 2 completes before pass 3 writes
// anything).
//
// What stays live between the passes is kept small, so that a chain's state fits
// in registers: pass 1 keeps only each body's velocity v_i; pass 2 computes c_i and
// pA_i from it when it reaches body i (the serial aba's values: the same functions
// of the same v_i) and keeps U_i, D_i, u_i in v_i's place (AbaBodyState, 8 scalars
// per body); pass 3 evaluates v_i and c_i again from the parent's velocity, next to
// the acceleration (one more transform of a motion per body).
//
// A parent receives its children in descending order, as in the reference. Body
// i + 1 (kParentIsPrev) is the last of them and hands its articulated inertia and
// bias force over in registers (IAcarry, pcarry), added after the others. Every
// other child (a branch child) adds into its parent's branch slot (kSlotShift): the
// highest-numbered one (kOpensSlot) starts the slot from the parent's rigid inertia
// and bias force, the rest add to it, and the parent reads it back. The slot also
// carries the branch point's v (pass 1) and v, a (pass 3) to its branch children.
// kSlots is how many slots there are:
//   0           no branch children: every body's parent is the previous body or the
//               base (ThreadModel::branch_slots() == 0, e.g. a chain, or chains
//               hanging from the base); no slot code at all;
//   1 .. C - 1  slots selected by loops of compile-time indices, so that they can
//               stay in registers; only for models with branch_slots() <= kSlots
//               (others would get wrong results; choose_aba_kernel respects it);
//   C           (the default) slots indexed at run time (per-thread local memory);
//               any model.
//
// armature (optional, nv scalars, any memory the thread can read): joint-space
// inertias added to the pivots D_i, i.e. to M's diagonal (the serial aba's
// armature; the simulator's implicit damping and springs); null: none.
//
// Also a host function (under nvcc), so the tests check its logic without a device.
//
// State (per thread): AbaBodyState (C x 8 scalars), q and qd (C each, when
// unrolled), the slots (kSlots x (v, a, an articulated inertia of 21 scalars and a
// bias force: 39 scalars)). With kUnrolled every loop runs over compile-time indices so that the
// per-body state can live in registers; otherwise it is per-thread (local) memory.
// kKeepXup keeps each body's transform from pass 1 for passes 2 and 3; otherwise
// joint_transform is evaluated again in each (fewer registers, more arithmetic).
// kTrig: how joint angles become sin and cos (see joint_sincos).
template <class S, int C, bool kKeepXup = false, bool kUnrolled = (C <= 8), Trig kTrig = Trig::Library,
          int kSlots = C>
__host__ __device__ __forceinline__ Index aba_instance(const ThreadModelParams<S, C>& model, DofColumn<const S> q,
                                                       DofColumn<const S> qd, DofColumn<const S> tau,
                                                       const Force<S>* fext, DofColumn<S> qdd,
                                                       const S* armature = nullptr) {
  static_assert(kSlots >= 0 && kSlots <= C, "aba_instance: kSlots is 0 (chains), below C (registers) or C");
  using fd_detail::slot_get;
  using fd_detail::slot_update;
  constexpr bool kBranches = kSlots > 0;     // are there branch children at all
  constexpr int kRegs = kUnrolled ? C : 1;   // register copies of q, qd when unrolled
  constexpr int kXup = kKeepXup ? C : 1;
  constexpr int K = kSlots > 0 ? kSlots : 1;  // extent of the slot arrays
  const Index n = model.nv;
  S q_r[kRegs] = {}, qd_r[kRegs] = {};
  Transform<S> Xup[kXup] = {};         // (nv) parent -> body transforms (kKeepXup)
  fd_detail::AbaBodyState<S> st[C];    // (nv) v_i, then U_i, D_i, u_i
  Motion<S> sv[K], sa[K];              // (slots) a branch point's v (passes 1 and 3) and a (pass 3)
  ABInertia<S> sIA[K];                 // (slots) a branch point's articulated inertia (pass 2) ...
  Force<S> spA[K];                     // ... and bias force

  auto q_at = [&](Index i) -> S {
    if constexpr (kUnrolled) return q_r[kUnrolled ? i : 0];
    else return q[i];
  };
  auto qd_at = [&](Index i) -> S {
    if constexpr (kUnrolled) return qd_r[kUnrolled ? i : 0];
    else return qd[i];
  };
  auto xup = [&](Index i, const Body<S>& b) -> Transform<S> {
    if constexpr (kKeepXup) return Xup[kKeepXup ? i : 0];
    else return joint_transform<kTrig>(b, q_at(i));
  };
  auto slot_of = [&](Index j) -> int { return branch_slot(model.flags[j]); };
  // v_p of a body p < i while pass 2 is at body i (its state still holds v_p)
  auto velocity_of = [&](Index p, Index i) -> Motion<S> {
    if constexpr (kUnrolled) {
      Motion<S> r = st[0].v();
#pragma unroll
      for (Index j = 1; j < C; ++j)
        if (j < i && j == p) r = st[j].v();
      return r;
    } else {
      return st[p].v();
    }
  };

  // load q, qd: all of them in flight before the first use (unrolled)
  if constexpr (kUnrolled) {
#pragma unroll
    for (Index i = 0; i < C; ++i) {
      if (i < n) {
        q_r[kUnrolled ? i : 0] = q[i];
        qd_r[kUnrolled ? i : 0] = qd[i];
      }
    }
  }

  // pass 1: velocities, root to leaves
  Motion<S> v_prev = Motion<S>::zero();  // body i - 1's v
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = 0; i < C; ++i) {
    if (i >= n) continue;  // (not break: a loop of C trips unrolls, indices stay constant)
    const Body<S>& b = model.body[i];
    const int fl = model.flags[i];
    Motion<S> vp = Motion<S>::zero();
    if (fl & kParentIsPrev) vp = v_prev;
    else if (kBranches && !(fl & kParentIsBase)) vp = slot_get<K, C>(sv, slot_of(b.parent));
    const Transform<S> X = joint_transform<kTrig>(b, q_at(i));
    if constexpr (kKeepXup) Xup[kKeepXup ? i : 0] = X;
    const Motion<S> v = aba_forward_step(b, X, vp, qd_at(i)).v;
    st[i].set_v(v);
    if (kBranches && (fl & kStacked)) slot_update<K, C>(sv, slot_of(i), [&](Motion<S>& s) { s = v; });
    v_prev = v;
  }
  if constexpr (kBranches && kSlots < C) {
    // pass 1's slot values are dead (pass 3 writes its own before reading them);
    // saying so frees their registers during pass 2
#pragma unroll
    for (int k = 0; k < K; ++k) sv[k] = Motion<S>::zero();
  }

  // pass 2: articulated inertias and bias forces, leaves to root
  ABInertia<S> IAcarry{};  // body i + 1's contribution Xup^T Ia Xup, when its parent is body i
  Force<S> pcarry = Force<S>::zero();
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = C - 1; i >= 0; --i) {
    if (i >= n) continue;
    const Body<S>& b = model.body[i];
    const int fl = model.flags[i];
    const Motion<S> v = st[i].v();
    // IA_i and pA_i: from the branch slot (rigid inertia, bias force and the branch
    // children), or the rigid inertia and bias force; then body i + 1's
    ABInertia<S> IA;
    Force<S> p;
    if (kBranches && (fl & kStacked)) {
      IA = slot_get<K, C>(sIA, slot_of(i));
      p = slot_get<K, C>(spA, slot_of(i));
    } else {
      IA = ABInertia<S>::from(b.I);
      p = aba_bias_force(b, v);
      if (fext) p = p - fext[i];
    }
    if (i + 1 < n && (model.flags[i + 1 < C ? i + 1 : i] & kParentIsPrev)) {
      IA += IAcarry;
      p += pcarry;
    }
    Force<S> Ui;
    S Di, ui;
    aba_joint_terms(b, IA, p, tau[i], Ui, Di, ui, armature ? armature[i] : S(0));
    if (!pivot_ok(Di)) return i;
    st[i].set_terms(Ui, Di, ui);
    if (fl & kParentIsBase) continue;
    // the contribution to the parent, from zero (0 + x == x: the parent's sums are
    // the reference's)
    ABInertia<S> IAc{};
    Force<S> pc = Force<S>::zero();
    aba_backward_to_parent(xup(i, b), IA, p, aba_velocity_product(b, v, qd_at(i)), Ui, Di, ui, IAc, pc);
    if (fl & kParentIsPrev) {
      IAcarry = IAc;
      pcarry = pc;
    } else if constexpr (kBranches) {
      const Index par = b.parent;
      if (fl & kOpensSlot) {
        // the first branch child to arrive: the parent's rigid inertia and bias force first
        const Body<S>& bp = model.body[par];
        Force<S> pA = aba_bias_force(bp, velocity_of(par, i));
        if (fext) pA = pA - fext[par];
        const ABInertia<S> IAp = ABInertia<S>::from(bp.I) + IAc;
        pA += pc;
        slot_update<K, C>(sIA, slot_of(par), [&](ABInertia<S>& s) { s = IAp; });
        slot_update<K, C>(spA, slot_of(par), [&](Force<S>& s) { s = pA; });
      } else {
        slot_update<K, C>(sIA, slot_of(par), [&](ABInertia<S>& s) { s += IAc; });
        slot_update<K, C>(spA, slot_of(par), [&](Force<S>& s) { s += pc; });
      }
    }
  }

  // pass 3: accelerations, root to leaves
  const Motion<S> a0 = model.a0;
  Motion<S> a_prev = a0;  // body i - 1's a (and v_prev its v)
  v_prev = Motion<S>::zero();
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = 0; i < C; ++i) {
    if (i >= n) continue;
    const Body<S>& b = model.body[i];
    const int fl = model.flags[i];
    Motion<S> vp = Motion<S>::zero(), ap = a0;
    if (fl & kParentIsPrev) {
      vp = v_prev;
      ap = a_prev;
    } else if (kBranches && !(fl & kParentIsBase)) {
      vp = slot_get<K, C>(sv, slot_of(b.parent));
      ap = slot_get<K, C>(sa, slot_of(b.parent));
    }
    const Transform<S> X = xup(i, b);
    const AbaForward<S> o = aba_forward_step(b, X, vp, qd_at(i));
    Motion<S> a;
    qdd[i] = aba_acceleration_step(b, X, ap, o.c, st[i].U(), st[i].D, st[i].u, a);
    if (kBranches && (fl & kStacked)) {
      slot_update<K, C>(sv, slot_of(i), [&](Motion<S>& s) { s = o.v; });
      slot_update<K, C>(sa, slot_of(i), [&](Motion<S>& s) { s = a; });
    }
    v_prev = o.v;
    a_prev = a;
  }
  return -1;
}
#endif  // __CUDACC__

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
