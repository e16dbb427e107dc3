// scandyn/instance/aba_instance.hpp: the articulated-body algorithm of one instance in one thread
// (forward dynamics), and the choice among its kernels (choose_aba_kernel).
#pragma once

#include "scandyn/algorithm/steps.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/instance/dof_column.hpp"
#include "scandyn/instance/thread_model.hpp"
#include "scandyn/instance/traversal.hpp"

#include <type_traits>
#include <variant>

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
template <class S, class Bd>
AbaKernel choose_aba_kernel(const ThreadModel<S, Bd>& model) {
  if (model.branch_slots() == 0) return AbaKernel::Chains;
  if (sizeof(S) == 4 && model.branch_slots() <= kAbaRegisterSlots) return AbaKernel::Branches;
  return AbaKernel::Tree;
}

// Calls launch(params, std::integral_constant<int, kSlots>{}) with the model's
// parameter block and the ABA kernel variant choose_aba_kernel picks (kSlots: 0 for
// chains, kAbaRegisterSlots for float's register slots, the capacity for any tree):
// the one dispatch of the ABA's kernels (forward and hybrid dynamics).
template <class S, class Bd, class F>
void visit_aba_kernel(const ThreadModel<S, Bd>& model, F&& launch) {
  const AbaKernel kernel = choose_aba_kernel(model);
  visit_compiled_capacity(model.params(), [&](const auto& params) {
    constexpr int C = std::decay_t<decltype(params)>::capacity;
    using std::integral_constant;
    if (kernel == AbaKernel::Chains)
      launch(params, integral_constant<int, 0>{});
    else if constexpr (sizeof(S) == 4) {  // (Branches is float's only)
      if (kernel == AbaKernel::Branches)
        launch(params, integral_constant<int, int(kAbaRegisterSlots)>{});
      else
        launch(params, integral_constant<int, C>{});
    } else {
      launch(params, integral_constant<int, C>{});
    }
  });
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

// What body i hands its parent in aba_instance's pass 2, in the parent's frame:
// Xup^T Ia_i Xup and Xup^T pa_i.
template <class S>
struct AbaCarry {
  ABInertia<S> IA;
  Force<S> pA;
};
template <class S>
__host__ __device__ __forceinline__ AbaCarry<S>& operator+=(AbaCarry<S>& a, const AbaCarry<S>& b) {
  a.IA += b.IA;
  a.pA += b.pA;
  return a;
}

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

// The hybrid dynamics' extra arguments of aba_instance (kHybrid): which DoFs have
// their acceleration given, those accelerations, and where the forces go.
template <class S>
struct HybridColumns {
  unsigned long long prescribed = 0;  // bit i: DoF i's acceleration is given (qdd_in[i])
  DofColumn<const S> qdd_in{};        // (nv) given accelerations, read at prescribed DoFs only
  DofColumn<S> tau_out{};             // (nv) every DoF's force (the given ones copied through)
};

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
// bias force over in registers (backward_pass' carry), added after the others. Every
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
//
// kHybrid: the hybrid dynamics of the serial scandyn::hybrid_dynamics (Featherstone
// 2008, 9.2) instead, with the same steps in the same order: the DoFs whose bit is
// set in hd.prescribed take their acceleration from hd.qdd_in (tau not read there)
// and get their force in hd.tau_out (hybrid_prescribed_to_parent in pass 2,
// hybrid_prescribed_acceleration_step in pass 3, U_i and u_i of pass 2 in their
// AbaBodyState); the others are the ABA's, their tau copied to hd.tau_out. Returns
// -1 or the failed DoF as above (nothing written). Without kHybrid, hd is not read.
// Models of up to 64 DoF (one bit per DoF).
//
// kFloating: for models with a floating base (model.floating, which must be set; not
// with kHybrid): the base is the root of the walk, with the reference general path's
// steps at its free joint (aba_forward_step_at, aba_joint_terms_at: the 6 x 6
// articulated inertia factored, aba_acceleration_step_at, gravity included): its
// velocity starts pass 1, its children's articulated inertias and bias forces
// gather into its own in pass 2 (backward_pass' to_base), and its acceleration
// starts pass 3. The returned DoF counts the base's six (0..5 the base's).
template <class S, int C, bool kKeepXup = false, bool kUnrolled = (C <= 8), Trig kTrig = Trig::Library,
          int kSlots = C, bool kHybrid = false, class Bd = Body<S>, bool kFloating = false>
__host__ __device__ __forceinline__ Index aba_instance(const ThreadModelParams<S, C, Bd>& model, DofColumn<const S> q,
                                                       DofColumn<const S> qd, DofColumn<const S> tau,
                                                       const Force<S>* fext, DofColumn<S> qdd,
                                                       const S* armature = nullptr,
                                                       HybridColumns<S> hd = {}) {
  static_assert(kSlots >= 0 && kSlots <= C, "aba_instance: kSlots is 0 (chains), below C (registers) or C");
  static_assert(!kHybrid || C <= 64, "aba_instance: the hybrid's prescribed mask has 64 bits");
  static_assert(!(kHybrid && kFloating), "aba_instance: the hybrid dynamics take a fixed base");
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
  auto xup = [&](Index i, const auto& b) -> Transform<S> {
    if constexpr (kKeepXup) return Xup[kKeepXup ? i : 0];
    else return joint_transform<kTrig>(b, q_at(i));
  };
  auto slot_of = [&](Index j) -> int { return branch_slot(model.flags[j]); };
  // kHybrid: DoF i's acceleration is given
  auto given = [&](Index i) -> bool {
    if constexpr (kHybrid) return (hd.prescribed >> i) & 1ull;
    else return false;
  };
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

  // the floating base (kFloating): its articulated inertia and bias force (pass 2
  // adds its children); then the columns past its entries. Its positions and rates
  // are read again in pass 3 rather than held through pass 2 (registers), and its
  // velocity-product term is zero (the root's v x S qd with v = S qd), as pass 3 takes it.
  fd_detail::AbaCarry<S> base_t{};
  const DofColumn<const S> q0 = q, qd0 = qd, tau0 = tau;
  const DofColumn<S> qdd0 = qdd;
  const S* armature0 = armature;
  // the base's q and qd entries (pass 1 and pass 3)
  auto base_q = [&](S (&qb)[7]) {
    for (int k = 0; k < 7; ++k) qb[k] = q0[k];
  };
  auto base_velocity = [&]() -> Motion<S> {
    return {Vec3<S>{qd0[0], qd0[1], qd0[2]}, Vec3<S>{qd0[3], qd0[4], qd0[5]}};
  };
  Motion<S> v0 = Motion<S>::zero();
  if constexpr (kFloating) {
    S qb[7], qdb[6];
    base_q(qb);
    for (int k = 0; k < 6; ++k) qdb[k] = qd[k];
    const AbaForward<S> o = aba_forward_step_at(model.base, joint_transform_at(model.base, qb), Motion<S>::zero(), qdb);
    v0 = o.v;
    base_t.IA = ABInertia<S>::from(model.base.I);
    base_t.pA = fext ? o.pA - fext[0] : o.pA;
    q = column_from(q, 7), qd = column_from(qd, 6), tau = column_from(tau, 6), qdd = column_from(qdd, 6);
    if (armature) armature += 6;
    if (fext) ++fext;
  }

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
  forward_pass<kUnrolled>(
      model, n, v0,
      [&](Index i) -> Motion<S> {
        if constexpr (kBranches) return slot_get<K, C>(sv, slot_of(model.body[i].parent));
        else return Motion<S>::zero();
      },
      [&](Index i, int fl, const Motion<S>& vp) {
        const auto& b = model.body[i];
        const Transform<S> X = joint_transform<kTrig>(b, q_at(i));
        if constexpr (kKeepXup) Xup[kKeepXup ? i : 0] = X;
        const Motion<S> v = aba_forward_step(b, X, vp, qd_at(i)).v;
        st[i].set_v(v);
        if (kBranches && (fl & kStacked)) slot_update<K, C>(sv, slot_of(i), [&](Motion<S>& s) { s = v; });
        return v;
      });
  if constexpr (kBranches && kSlots < C) {
    // pass 1's slot values are dead (pass 3 writes its own before reading them);
    // saying so frees their registers during pass 2
#pragma unroll
    for (int k = 0; k < K; ++k) sv[k] = Motion<S>::zero();
  }

  // pass 2: articulated inertias and bias forces, leaves to root. Body i hands its
  // parent Xup^T Ia Xup and Xup^T pa (AbaCarry): body i + 1 through the carry, added
  // after the others; every other child (a branch child) into its parent's branch
  // slot, which the highest-numbered one (kOpensSlot) starts from the parent's rigid
  // inertia and bias force.
  Motion<S> v;  // body i's v_i, read before its state becomes U_i, D_i, u_i
  Force<S> Ui;  // body i's U_i, D_i, u_i, for its contribution to the parent
  S Di, ui;
  using fd_detail::AbaCarry;
  const PassEnd pass2 = backward_pass<kUnrolled, S, C, AbaCarry<S>>(
      model, n,
      [&](Index i, int fl) {
        // IA_i and pA_i: from the branch slot (rigid inertia, bias force and the
        // branch children), or the rigid inertia and bias force
        const auto& b = model.body[i];
        v = st[i].v();
        AbaCarry<S> t;
        if (kBranches && (fl & kStacked)) {
          t.IA = slot_get<K, C>(sIA, slot_of(i));
          t.pA = slot_get<K, C>(spA, slot_of(i));
        } else {
          t.IA = ABInertia<S>::from(b.I);
          t.pA = aba_bias_force(b, v);
          if (fext) t.pA = t.pA - external_wrench(model, i, fext);
        }
        return t;
      },
      [&](Index i, int, const AbaCarry<S>& t) {
        if (given(i)) {
          aba_joint_terms(model.body[i], t.IA, t.pA, S(0), Ui, Di, ui);
          st[i].set_terms(Ui, Di, ui);
          return true;
        }
        aba_joint_terms(model.body[i], t.IA, t.pA, tau[i], Ui, Di, ui, armature ? armature[i] : S(0));
        if (!pivot_ok(Di)) return false;
        st[i].set_terms(Ui, Di, ui);
        return true;
      },
      [&](Index i, const AbaCarry<S>& t) {
        // the contribution to the parent, from zero (0 + x == x: the parent's sums are
        // the reference's)
        const auto& b = model.body[i];
        AbaCarry<S> up{ABInertia<S>{}, Force<S>::zero()};
        if (given(i)) {
          hybrid_prescribed_to_parent(b, xup(i, b), t.IA, t.pA, aba_velocity_product(b, v, qd_at(i)), hd.qdd_in[i],
                                      up.IA, up.pA);
          return up;
        }
        aba_backward_to_parent(xup(i, b), t.IA, t.pA, aba_velocity_product(b, v, qd_at(i)), Ui, Di, ui, up.IA, up.pA);
        return up;
      },
      [&](Index i, int fl, const AbaCarry<S>& up) {
        if constexpr (kBranches) {
          const Index par = model.body[i].parent;
          if (fl & kOpensSlot) {
            // the first branch child to arrive: the parent's rigid inertia and bias force first
            const auto& bp = model.body[par];
            Force<S> pA = aba_bias_force(bp, velocity_of(par, i));
            if (fext) pA = pA - external_wrench(model, par, fext);
            const ABInertia<S> IAp = ABInertia<S>::from(bp.I) + up.IA;
            pA += up.pA;
            slot_update<K, C>(sIA, slot_of(par), [&](ABInertia<S>& s) { s = IAp; });
            slot_update<K, C>(spA, slot_of(par), [&](Force<S>& s) { s = pA; });
          } else {
            slot_update<K, C>(sIA, slot_of(par), [&](ABInertia<S>& s) { s += up.IA; });
            slot_update<K, C>(spA, slot_of(par), [&](Force<S>& s) { s += up.pA; });
          }
        }
      },
      base_hook<kFloating>([&](Index, const AbaCarry<S>& up) { base_t += up; }));
  if (!pass2.complete) return pass2.at + (kFloating ? Index(6) : Index(0));  // (the base's DoFs first)

  // the floating base: its joint terms (the 6 x 6 articulated inertia factored) and
  // its acceleration, which starts pass 3
  BodyKinematics<S> root{Motion<S>::zero(), model.a0};
  if constexpr (kFloating) {
    S qb[7], taub[6], w[6], L[kMaxJointDofs * kMaxJointDofs], qddb[6];
    Force<S> Y[6];
    for (int k = 0; k < 6; ++k) taub[k] = tau0[k];
    const int failed = aba_joint_terms_at<6>(model.base, base_t.IA, base_t.pA, taub, Y, L, w, armature0);
    if (failed >= 0) return failed;
    Motion<S> a;
    base_q(qb);
    aba_acceleration_step_at<6>(model.base, joint_transform_at(model.base, qb), model.a0, Motion<S>::zero(), Y, L, w,
                                qddb, a);
    for (int k = 0; k < 6; ++k) qdd0[k] = qddb[k];
    root = {base_velocity(), a};
  }

  // pass 3: accelerations, root to leaves
  forward_pass<kUnrolled>(
      model, n, root,
      [&](Index i) -> BodyKinematics<S> {
        if constexpr (kBranches) {
          const int s = slot_of(model.body[i].parent);
          return {slot_get<K, C>(sv, s), slot_get<K, C>(sa, s)};
        } else {
          return {Motion<S>::zero(), model.a0};
        }
      },
      [&](Index i, int fl, const BodyKinematics<S>& p) {
        const auto& b = model.body[i];
        const Transform<S> X = xup(i, b);
        const AbaForward<S> o = aba_forward_step(b, X, p.v, qd_at(i));
        Motion<S> a;
        if (given(i)) {
          const S qddi = hd.qdd_in[i];
          hd.tau_out[i] = hybrid_prescribed_acceleration_step(b, X, p.a, o.c, st[i].U(), st[i].u, qddi, a);
          qdd[i] = qddi;
        } else {
          qdd[i] = aba_acceleration_step(b, X, p.a, o.c, st[i].U(), st[i].D, st[i].u, a);
          if constexpr (kHybrid) hd.tau_out[i] = tau[i];
        }
        if (kBranches && (fl & kStacked)) {
          slot_update<K, C>(sv, slot_of(i), [&](Motion<S>& s) { s = o.v; });
          slot_update<K, C>(sa, slot_of(i), [&](Motion<S>& s) { s = a; });
        }
        return BodyKinematics<S>{o.v, a};
      });
  return -1;
}
#endif  // __CUDACC__

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
