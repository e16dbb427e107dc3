// scandyn/instance/rnea_instance.hpp: the RNEA of one instance in one thread (inverse dynamics).
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
// The passes' functors read per-thread arrays (the branch stack, the register copies
// of the inputs) that are written before they are read, but after the functors are
// created; nvcc's front end sees the capture as a read of an unset variable (#549).
#pragma nv_diagnostic push
#pragma nv_diag_suppress 549
// The RNEA of one instance: tau = RNEA(q, qd, qdd) - sum J^T fext, gravity included,
// the loops of scandyn::rnea (src/algorithm/reference.cpp) over the same step
// functions and in the same order of summation. fext: nv body wrenches or null.
//
// Also a host function (under nvcc), so the tests check its logic without a device.
//
// State: with kUnrolled (the default for capacities 8 and 16 in float, 8 in
// double) the loops are unrolled, so the per-body arrays are indexed at compile
// time and live in registers; otherwise the forces live in per-thread (local)
// memory and q, qd, qdd are read where they are used (double with 16 bodies
// unrolled needs more than 255 registers). A body whose parent is body i - 1 or
// the base takes v, a from registers and hands its force back in a register; only
// tree branch points (kStacked) go through the stack arrays. kKeepXup keeps each
// body's transform from the forward pass for the backward pass; otherwise
// joint_transform is evaluated again there (fewer registers, more arithmetic).
// kTrig: how joint angles become sin and cos (Trig::Library, CUDA's sinf/cosf, by
// default: at most 64 links, so their slight bias stays below 1e-6; see joint_sincos).
//
// kFloating: for models with a floating base (model.floating, which must be set):
// the base is the root of the walk, its velocity and acceleration the forward pass's
// start (rnea_forward_step_at of the reference's general path, gravity included),
// and the wrenches of its children gather into its own (backward_pass' to_base), of
// which tau's first six entries are the projection (joint_project_at). Without it
// model.floating must be 0.
template <class S, int C, bool kKeepXup = false, bool kUnrolled = (C * sizeof(S) <= 64), Trig kTrig = Trig::Library,
          class Bd = Body<S>, bool kFloating = false>
__host__ __device__ __forceinline__ void rnea_instance(const ThreadModelParams<S, C, Bd>& model,
                                                       DofColumn<const S> q, DofColumn<const S> qd,
                                                       DofColumn<const S> qdd, const Force<S>* fext,
                                                       DofColumn<S> tau) {
  constexpr int kRegs = kUnrolled ? C : 1;  // register copies of the inputs when unrolled
  constexpr int kXup = kKeepXup ? C : 1;
  const Index n = model.nv;
  S q_r[kRegs], qd_r[kRegs], qdd_r[kRegs];  // (nv) joint variables, loaded up front
  Transform<S> Xup[kXup];                   // (nv) parent -> body transforms (kKeepXup)
  Force<S> f[C];                            // (nv) net body forces from the forward pass
  Motion<S> sv[C], sa[C];                   // stack: v, a of kStacked bodies
  Force<S> sf[C];                           // stack: f of kStacked bodies plus their
                                            // children other than the next body
  BodyKinematics<S> root{Motion<S>::zero(), model.a0};  // what the base hands its children
  Force<S> f0;                              // (kFloating) the base's net force, then its wrench
  DofColumn<S> tau0 = tau;                  // (kFloating) the base's entries of tau
  if constexpr (kFloating) {
    S qb[7], qdb[6], qddb[6];
    for (int k = 0; k < 7; ++k) qb[k] = q[k];
    for (int k = 0; k < 6; ++k) qdb[k] = qd[k], qddb[k] = qdd[k];
    const RneaForward<S> o =
        rnea_forward_step_at(model.base, joint_transform_at(model.base, qb), Motion<S>::zero(), model.a0, qdb, qddb);
    root = {o.v, o.a};
    f0 = fext ? o.f - fext[0] : o.f;
    q = column_from(q, 7), qd = column_from(qd, 6), qdd = column_from(qdd, 6), tau = column_from(tau, 6);
    if (fext) ++fext;
  }

  // load: all of one instance's inputs in flight before the first use
  if constexpr (kUnrolled) {
#pragma unroll
    for (Index i = 0; i < C; ++i) {
      if (i < n) {
        q_r[i] = q[i];
        qd_r[i] = qd[i];
        qdd_r[i] = qdd[i];
      }
    }
  }
  // forward: kinematics and body forces
  forward_pass<kUnrolled>(
      model, n, root,
      [&](Index i) { return BodyKinematics<S>{sv[model.body[i].parent], sa[model.body[i].parent]}; },
      [&](Index i, int fl, const BodyKinematics<S>& p) {
        const auto& b = model.body[i];
        const S qi = kUnrolled ? q_r[kUnrolled ? i : 0] : q[i];
        const Transform<S> X = joint_transform<kTrig>(b, qi);
        if constexpr (kKeepXup) Xup[kKeepXup ? i : 0] = X;
        const S qdi = kUnrolled ? qd_r[kUnrolled ? i : 0] : qd[i];
        const S qddi = kUnrolled ? qdd_r[kUnrolled ? i : 0] : qdd[i];
        const RneaForward<S> o = rnea_forward_step(b, X, p.v, p.a, qdi, qddi);
        f[i] = fext ? o.f - external_wrench(model, i, fext) : o.f;
        if (fl & kStacked) sv[i] = o.v, sa[i] = o.a, sf[i] = f[i];
        return BodyKinematics<S>{o.v, o.a};
      });
  // backward: joint torques; each body's force goes to its parent, the next body's
  // through the carry, others' through the stack (sf, which starts as the branch
  // point's own force)
  backward_pass<kUnrolled, S, C, Force<S>>(
      model, n, [&](Index i, int fl) { return (fl & kStacked) ? sf[i] : f[i]; },
      [&](Index i, int, const Force<S>& fi) {
        tau[i] = joint_project(model.body[i], fi);
        return true;
      },
      [&](Index i, const Force<S>& fi) {
        const auto& b = model.body[i];
        Transform<S> X;
        if constexpr (kKeepXup) X = Xup[kKeepXup ? i : 0];
        else X = joint_transform<kTrig>(b, kUnrolled ? q_r[kUnrolled ? i : 0] : q[i]);
        return X.apply_transpose(fi);
      },
      [&](Index i, int, const Force<S>& up) { sf[model.body[i].parent] += up; },
      base_hook<kFloating>([&](Index, const Force<S>& up) { f0 += up; }));
  if constexpr (kFloating) {
    S out[6];
    joint_project_at(model.base, f0, out);
    for (int k = 0; k < 6; ++k) tau0[k] = out[k];
  }
}
#pragma nv_diagnostic pop
#endif  // __CUDACC__

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
