// scandyn/instance/crba_instance.hpp: the CRBA of one instance in one thread (the mass matrix), and the
// joint-space inertia forward dynamics built on the same passes (fd_jsi_instance).
#pragma once

#include "scandyn/algorithm/steps.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/instance/dof_column.hpp"
#include "scandyn/instance/thread_model.hpp"
#include "scandyn/instance/traversal.hpp"

#if SCANDYN_HAS_CUDA
namespace scandyn {
namespace cuda {

#if defined(__CUDACC__)
// A floating base's rows of one instance's M (kFloating; one scalar each otherwise):
// block[r * 6 + c] = M(r, c) and coupling[k * 6 + r] = M(r, 6 + k) = M(6 + k, r) for
// the base's DoFs r, c < 6 and the kernels' body k (ThreadModelParams::floating).
template <class S, int C, bool kFloating>
struct FloatingMassRows {
  S block[36];
  S coupling[6 * C];
};
template <class S, int C>
struct FloatingMassRows<S, C, false> {};

namespace fd_detail {

// Index of M(k, j), j <= k, in a packed lower triangle.
__host__ __device__ constexpr int tri(int k, int j) { return k * (k + 1) / 2 + j; }

// What body i hands its parent in jsi_passes' backward pass, in the parent's frame:
// its force Xup^T f_i (kBias; else zero, unused) and composite inertia Xup^T Ic_i Xup.
template <class S>
struct JsiCarry {
  Force<S> f;
  Inertia<S> I;
};
template <class S>
__host__ __device__ __forceinline__ JsiCarry<S>& operator+=(JsiCarry<S>& a, const JsiCarry<S>& b) {
  a.f += b.f;
  a.I += b.I;
  return a;
}

// The CRBA of one instance (kBias = false: crba_instance) or the CRBA and the bias
// forces in the same passes (kBias = true: fd_jsi_instance), so that the CRBA's
// formulas and order exist once for both.
//
// With kBias, a forward pass (transforms, velocities, accelerations and body forces
// of the RNEA with qdd = 0). Then one backward pass that, for each body i from the
// last, completes its composite inertia Ic_i, the entries M(k, i) of the columns k
// of its descendants (their forces F_k reach body i's frame there) and its own
// column's force F_i = Ic_i S_i (with kBias also its force f_i: h_i = S_i^T f_i),
// then carries Ic_i, every F_k of its subtree (and f_i) to its parent. A parent
// receives its children in descending order, as in the reference: body i + 1's
// through registers (backward_pass' carry), others' through the stack. Each entry is
// computed by the reference's formulas (crba, rnea) in the reference's order of
// summation.
//
// Out: M(k, j) at tri(k, j) for j = k and j an ancestor of k (the tree's nonzeros;
// other entries of the triangle are not written), armature[i] (optional, nv
// scalars) added to M(i, i); with kBias x = tau - h (nv), else x is not touched.
//
// State (per thread): the column forces (C, one slot per body: with kBias body i's
// force until its backward step, then column i's), a stack of composite inertias
// (and with kBias v, a, f) for the bodies at which the tree branches (kStacked), as
// in rnea_instance. kUnrolled, kKeepXup (kBias only: without a forward pass the
// backward pass evaluates each transform once anyway) and kTrig as for
// fd_jsi_instance.
// (The passes' functors read per-thread arrays written before they are read but after
// the functors are created: nvcc's #549, as in rnea_instance.)
//
// kFloating (CRBA only, kBias false): the model has a floating base (model.floating):
// q starts with the base's 7 entries, and the base's rows of M go to `base`
// (FloatingMassRows): its children's composite inertias gather into its own
// (backward_pass' to_base), and every column's force, once in the base's frame,
// gives the column's base entries, as in the reference's general path (crba_at).
#pragma nv_diagnostic push
#pragma nv_diag_suppress 549
template <bool kBias, class S, int C, bool kKeepXup, bool kUnrolled, Trig kTrig, class Bd = Body<S>,
          bool kFloating = false>
__host__ __device__ __forceinline__ void jsi_passes(const ThreadModelParams<S, C, Bd>& model, DofColumn<const S> q,
                                                    DofColumn<const S> qd, DofColumn<const S> tau,
                                                    const Force<S>* fext, const S* armature, S (&x)[C],
                                                    S (&M)[C * (C + 1) / 2],
                                                    FloatingMassRows<S, C, kFloating>* base = nullptr) {
  static_assert(!(kBias && kFloating), "jsi_passes: the joint-space inertia forward dynamics take a fixed base");
  Inertia<S> Ic0;  // (kFloating) the base's composite inertia
  if constexpr (kFloating) {
    Ic0 = model.base.I;
    q = column_from(q, 7);
  }
  constexpr int kRegs = kUnrolled ? C : 1;  // register copies of q, qd when unrolled
  constexpr bool kKeep = kBias && kKeepXup;
  constexpr int kXup = kKeep ? C : 1;
  constexpr int kStack = kBias ? C : 1;     // extent of the bias forces' stack arrays
  const Index n = model.nv;
  S q_r[kRegs], qd_r[kRegs];
  Transform<S> Xup[kXup];       // (nv) parent -> body transforms (kKeepXup)
  Force<S> w[C];                // (nv) body i's net force f_i until its backward step (kBias), then
                                // the force F_i of column i of M, carried towards the root
  Motion<S> sv[kStack], sa[kStack];  // stack: v, a of kStacked bodies (kBias)
  Force<S> sf[kStack];          // stack: f of kStacked bodies plus their children other than the
                                // next (kBias)
  Inertia<S> sI[C];             // stack: the same for composite inertias

  // load: all of one instance's inputs in flight before the first use
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = 0; i < C; ++i) {
    if (i < n) {
      if constexpr (kUnrolled) {
        q_r[kUnrolled ? i : 0] = q[i];
        if constexpr (kBias) qd_r[kUnrolled ? i : 0] = qd[i];
      }
      if constexpr (kBias) x[i] = tau[i];
    }
  }

  if constexpr (kBias) {
    // forward: kinematics and the bias forces' body forces (RNEA with qdd = 0)
    forward_pass<kUnrolled>(
        model, n, BodyKinematics<S>{Motion<S>::zero(), model.a0},
        [&](Index i) { return BodyKinematics<S>{sv[model.body[i].parent], sa[model.body[i].parent]}; },
        [&](Index i, int fl, const BodyKinematics<S>& p) {
          const auto& b = model.body[i];
          const Transform<S> X = joint_transform<kTrig>(b, kUnrolled ? q_r[kUnrolled ? i : 0] : q[i]);
          if constexpr (kKeep) Xup[kKeep ? i : 0] = X;
          const RneaForward<S> o =
              rnea_forward_step(b, X, p.v, p.a, kUnrolled ? qd_r[kUnrolled ? i : 0] : qd[i], S(0));
          w[i] = fext ? o.f - external_wrench(model, i, fext) : o.f;
          if (fl & kStacked) sv[i] = o.v, sa[i] = o.a, sf[i] = w[i], sI[i] = b.I;
          return BodyKinematics<S>{o.v, o.a};
        });
  } else {
    // a branch point's composite inertia starts as its rigid inertia (the forward
    // pass does this when there is one)
#pragma unroll(kUnrolled ? C : 1)
    for (Index i = 0; i < C; ++i)
      if (i < n && (model.flags[i] & kStacked)) sI[i] = model.body[i].I;
  }

  // backward: composite inertias, the columns of M (and the bias forces); body i
  // hands its parent Xup^T f_i (kBias) and Xup^T Ic_i Xup (JsiCarry)
  backward_pass<kUnrolled, S, C, JsiCarry<S>>(
      model, n,
      [&](Index i, int fl) {
        JsiCarry<S> t{Force<S>::zero(), (fl & kStacked) ? sI[i] : model.body[i].I};
        if constexpr (kBias) t.f = (fl & kStacked) ? sf[i] : w[i];
        return t;
      },
      [&](Index i, int, const JsiCarry<S>& t) {
        const auto& b = model.body[i];
        if constexpr (kBias) x[i] -= joint_project(b, t.f);  // tau_i - h_i
        // the columns of i's descendants have reached its frame: M(k, i) = S_i^T F_k
        for_descendants<kUnrolled>(model, i, [&](Index k) { M[tri(k, i)] = joint_project(b, w[k]); });
        w[i] = crba_column_force(b, t.I);
        M[tri(i, i)] = joint_project(b, w[i]);
        if (armature) M[tri(i, i)] += armature[i];
        return true;
      },
      [&](Index i, const JsiCarry<S>& t, auto&& hand_off) {
        Transform<S> X;
        if constexpr (kKeep) X = Xup[kKeep ? i : 0];
        else X = joint_transform<kTrig>(model.body[i], kUnrolled ? q_r[kUnrolled ? i : 0] : q[i]);
        JsiCarry<S> up{Force<S>::zero(), Inertia<S>::zero()};
        if constexpr (kBias) up.f = X.apply_transpose(t.f);
        up.I = crba_composite_step(X, t.I);
        hand_off(up);
        // then the columns of body i's subtree move on to its parent's frame
        w[i] = crba_column_step(X, w[i]);
        for_descendants<kUnrolled>(model, i, [&](Index k) { w[k] = crba_column_step(X, w[k]); });
      },
      [&](Index i, int, const JsiCarry<S>& up) {
        const Index p = model.body[i].parent;
        if constexpr (kBias) sf[p] += up.f;
        sI[p] += up.I;
      },
      base_hook<kFloating>([&](Index i, const JsiCarry<S>& up) {
        // body i's subtree's columns have reached the base's frame: their base entries
        if constexpr (kFloating) {
          Ic0 += up.I;
          const auto put = [&](Index k) { joint_project_at(model.base, w[k], &base->coupling[k * 6]); };
          put(i);
          for_descendants<kUnrolled>(model, i, put);
        }
      }));
  if constexpr (kFloating) {
    // the base's own block: its composite inertia's columns
    for (int c = 0; c < 6; ++c) {
      S col[6];
      joint_project_at(model.base, Ic0 * joint_column(model.base, c), col);
      for (int r = 0; r < 6; ++r) base->block[r * 6 + c] = col[r];
    }
  }
}
#pragma nv_diagnostic pop

}  // namespace fd_detail

// The joint-space inertia matrix M(q) of one instance by the composite-rigid-body
// algorithm (CRBA, Featherstone (2008) 6.2): composite inertias Ic_i from the leaves
// to the root, then each column's force F_i = Ic_i S_i carried to the root,
// M(i, j) = S_j^T F_i along the way; the formulas and the order of summation of the
// serial scandyn::crba (src/algorithm/reference.cpp), over the same step functions
// (crba_composite_step, crba_column_force, crba_column_step; on the host bit-identical
// to it). The same code computes fd_jsi_instance's mass matrix (fd_detail::jsi_passes).
//
// Out: M as a packed lower triangle, M(k, j) (j <= k) at fd_detail::tri(k, j) =
// k (k + 1) / 2 + j, written for j = k and for j an ancestor of k; the entries of
// pairs of which neither body is an ancestor of the other are zero in M and are NOT
// written (mass_matrix_instance, below, writes the full
// matrix). armature (optional, nv scalars) is added to the diagonal.
//
// Also a host function (under nvcc), so the tests check it without a device.
// kUnrolled (default for capacity 8): every loop over compile-time indices, so that
// M (C (C + 1) / 2 scalars), the column forces and the inputs can stay in
// registers; otherwise per-thread (local) memory and walks up the parents. kTrig:
// how joint angles become sin and cos (see joint_sincos).
//
// kFloating: the model has a floating base (model.floating): q starts with its 7
// entries, M holds the kernels' bodies' DoFs (the model's 6..), the base's rows go to
// *base (FloatingMassRows), and armature's entries are the kernels' bodies'.
template <class S, int C, bool kUnrolled = (C <= 8), Trig kTrig = Trig::Library, class Bd = Body<S>,
          bool kFloating = false>
__host__ __device__ __forceinline__ void crba_instance(const ThreadModelParams<S, C, Bd>& model, DofColumn<const S> q,
                                                      S (&M)[C * (C + 1) / 2], const S* armature = nullptr,
                                                      FloatingMassRows<S, C, kFloating>* base = nullptr) {
  S unused[C];  // the bias forces' tau - h, which the CRBA alone does not compute (never touched)
  fd_detail::jsi_passes<false, S, C, false, kUnrolled, kTrig, Bd, kFloating>(
      model, q, DofColumn<const S>{nullptr, 0}, DofColumn<const S>{nullptr, 0}, nullptr, armature, unused, M, base);
}

// Forward dynamics of one instance by the joint-space inertia:
//   qdd = M(q)^{-1} (tau - h(q, qd, fext)),
// gravity included; fext: nv body wrenches or null. Returns -1, or the DoF whose
// pivot was not positive and finite, in which case qdd is not written.
//
// One forward pass (transforms, velocities, accelerations and body forces of the
// RNEA with qdd = 0) and one backward pass that, for each body i from the last,
// completes its force (h_i = S_i^T f_i), its composite inertia Ic_i, the entries
// M(k, i) of the columns k of its descendants (their forces F_k reach body i's frame
// there) and its own column's force F_i = Ic_i S_i, then carries f_i, Ic_i and every
// F_k of its subtree to its parent: crba_instance's passes with the bias forces
// riding along (fd_detail::jsi_passes). Then the L^T L factorisation of the packed lower
// triangle of M, with the pivot check, and the two triangular solves. Each entry is
// computed by the reference's formulas in the reference's order of summation.
//
// Also a host function (under nvcc), so the tests check its logic without a device.
//
// State (per thread): M as a packed lower triangle of C (C + 1) / 2 scalars, tau - h
// and the solution (C), the forces f_i / F_i (C, one slot per body: body i's force
// until its backward step, then column i's), and a stack for the bodies at which
// the tree branches (kStacked), as in rnea_instance. With kUnrolled (the default for
// capacity 8) every loop runs over compile-time indices so that all of it but the
// branch stack lives in registers, and the tree's sparsity is tested per entry from
// ThreadModelParams::ancestors (C^3 / 6 tests in the factorisation); otherwise the
// arrays live in per-thread (local) memory and the ancestor loops walk the parents,
// touching only the entries a tree has. (Capacity 16 unrolled needs more than 255
// registers in float too: M alone is 136 scalars.) kKeepXup keeps each body's
// transform from the forward pass for the backward pass; otherwise joint_transform
// is evaluated again there (fewer registers, more arithmetic).
//
// armature (optional, nv scalars, any memory the thread can read): joint-space
// inertias added to M's diagonal before the factorisation, as in the serial fd_jsi
// (scandyn/sim's implicit damping and springs); null adds nothing.
template <class S, int C, bool kKeepXup = false, bool kUnrolled = (C <= 8), Trig kTrig = Trig::Library, class Bd = Body<S>>
__host__ __device__ __forceinline__ Index fd_jsi_instance(const ThreadModelParams<S, C, Bd>& model,
                                                          DofColumn<const S> q, DofColumn<const S> qd,
                                                          DofColumn<const S> tau, const Force<S>* fext,
                                                          DofColumn<S> qdd, const S* armature = nullptr) {
  using fd_detail::tri;
  using std::sqrt;
  const Index n = model.nv;
  S x[C];                // (nv) tau - h, then the solution qdd
  S M[C * (C + 1) / 2];  // M(k, j) at tri(k, j) for j = k and j an ancestor of k; then L

  // CRBA and bias forces: one forward and one backward pass
  fd_detail::jsi_passes<true, S, C, kKeepXup, kUnrolled, kTrig>(model, q, qd, tau, fext, armature, x, M);

  // M = L^T L in place (ltl_factor), from the last DoF to the first
#pragma unroll(kUnrolled ? C : 1)
  for (Index k = C - 1; k >= 0; --k) {
    if (k >= n) continue;
    const S d = M[tri(k, k)];
    if (!pivot_ok(d)) return k;
    const S Lkk = sqrt(d);
    M[tri(k, k)] = Lkk;
    const S inv = S(1) / Lkk;
    fd_detail::for_ancestors<kUnrolled>(model, k, [&](Index i) { M[tri(k, i)] *= inv; });
    fd_detail::for_ancestors<kUnrolled>(model, k, [&](Index i) {
      const S Lki = M[tri(k, i)];
      M[tri(i, i)] -= Lki * M[tri(k, i)];
      fd_detail::for_ancestors<kUnrolled>(model, i, [&](Index j) { M[tri(i, j)] -= Lki * M[tri(k, j)]; });
    });
  }

  // L^T y = tau - h, then L qdd = y (ltl_solve)
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = C - 1; i >= 0; --i) {
    if (i >= n) continue;
    x[i] /= M[tri(i, i)];
    const S xi = x[i];
    fd_detail::for_ancestors<kUnrolled>(model, i, [&](Index j) { x[j] -= M[tri(i, j)] * xi; });
  }
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = 0; i < C; ++i) {
    if (i >= n) continue;
    S acc = x[i];
    fd_detail::for_ancestors<kUnrolled>(model, i, [&](Index j) { acc -= M[tri(i, j)] * x[j]; });
    x[i] = acc / M[tri(i, i)];
    qdd[i] = x[i];
  }
  return -1;
}

// Every entry of one instance's full nv x nv matrix from crba_instance's packed
// triangle M, in row-major order: put(i * nv + j, M(i, j)) for i, j < nv (both
// triangles; zero where neither body is an ancestor of the other). The order and
// the indices are the same on every thread of a model (a warp may stage the
// entries together: kernels/mass_matrix.cu). kUnrolled as for crba_instance.
//
// kFloating: the full matrix of a floating-base model (model_nv(model) square, the
// base's rows first) from M and the base's rows (FloatingMassRows), still row by row.
template <class S, int C, bool kUnrolled = (C <= 8), class Put, class Bd = Body<S>, bool kFloating = false>
__host__ __device__ __forceinline__ void for_each_mass_entry(const ThreadModelParams<S, C, Bd>& model,
                                                            const S (&M)[C * (C + 1) / 2], Put&& put,
                                                            const FloatingMassRows<S, C, kFloating>* base = nullptr) {
  using fd_detail::tri;
  const Index n = model.nv;
  constexpr Index o = kFloating ? 6 : 0;  // the base's DoFs come first
  const Index N = n + o;                    // the row length
  if constexpr (kFloating) {
    for (Index r = 0; r < 6; ++r) {
      for (Index c = 0; c < 6; ++c) put(r * N + c, base->block[r * 6 + c]);
#pragma unroll(kUnrolled ? C : 1)
      for (Index k = 0; k < C; ++k)
        if (k < n) put(r * N + 6 + k, base->coupling[k * 6 + r]);
    }
  }
#pragma unroll(kUnrolled ? C : 1)
  for (Index i = 0; i < C; ++i) {
    if (i >= n) continue;
    if constexpr (kFloating)
      for (Index c = 0; c < 6; ++c) put((o + i) * N + c, base->coupling[i * 6 + c]);
#pragma unroll(kUnrolled ? C : 1)
    for (Index j = 0; j < C; ++j) {
      if (j >= n) continue;
      const Index hi = i > j ? i : j, lo = i > j ? j : i;
      // a nonzero entry pairs a body with itself or one of its ancestors
      put((o + i) * N + o + j, hi == lo || fd_detail::is_ancestor(model, lo, hi) ? M[tri(hi, lo)] : S(0));
    }
  }
}

// M(q) of one instance, the full nv x nv matrix: M_out[i * nv + j] = M(i, j) for
// every i, j < nv (row-major; both triangles; zero where neither body is an
// ancestor of the other). crba_instance into per-thread storage (C (C + 1) / 2
// scalars: registers when unrolled, else local memory), then nv^2 stores, row by
// row (for_each_mass_entry). Also a host function (under nvcc): the tests check it
// against scandyn::crba without a device. kUnrolled and kTrig as for crba_instance.
// kFloating as for crba_instance: the full model_nv(model)^2 matrix.
template <class S, int C, bool kUnrolled = (C <= 8), Trig kTrig = Trig::Library, class Bd = Body<S>,
          bool kFloating = false>
__host__ __device__ __forceinline__ void mass_matrix_instance(const ThreadModelParams<S, C, Bd>& model,
                                                              DofColumn<const S> q, DofColumn<S> M_out) {
  S M[C * (C + 1) / 2];  // M(k, j) at tri(k, j), j = k or an ancestor of k
  FloatingMassRows<S, C, kFloating> base;
  crba_instance<S, C, kUnrolled, kTrig, Bd, kFloating>(model, q, M, nullptr, &base);
  for_each_mass_entry<S, C, kUnrolled>(model, M, [&](Index e, S v) { M_out[e] = v; }, &base);
}
#endif  // __CUDACC__

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
