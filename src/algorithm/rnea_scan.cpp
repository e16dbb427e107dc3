// Inverse dynamics as scans over links: local-frame affine form and world-frame form.
#include "scandyn/algorithm/rnea_scan.hpp"

#include <stdexcept>

#include "scandyn/scan/omp_scan.hpp"

namespace scandyn {

template <class S>
ScanWorkspace<S>::ScanWorkspace(const ModelTpl<S>& model, int threads_) : threads(threads_ < 1 ? 1 : threads_) {
  // per body (nbodies; = nv for 1-DoF joints): a floating base and spherical joints
  // are one scan element each
  const Index n = model.nbodies();
  std::vector<Index> parent(static_cast<std::size_t>(n));
  for (Index i = 0; i < n; ++i) parent[i] = model.bodies[i].parent;
  plan = make_tree_scan_plan(parent, default_max_piece(n, threads));
  const std::size_t un = static_cast<std::size_t>(n), np = plan.pieces.size();
  Xup.resize(un);
  v.resize(un);
  fwd.resize(un);
  bwd.resize(un);
  P.resize(un);
  sw.resize(un);
  Vw.resize(un);
  Aw.resize(un);
  Fw.resize(un);
  carry_fwd.resize(np);
  carry_bwd.resize(np);
  carry_pose.resize(np);
  carry_motion.resize(np);
  carry_force.resize(np);
}

namespace {

// value of a node whose parent's prefix is final: only the offset is needed
struct KnownMotionAffine {
  template <class S>
  MotionAffine<S> operator()(const MotionAffine<S>& parent, const MotionAffine<S>& e) const {
    return {e.X, apply(e, parent.b)};
  }
};
// value of a node whose child-side suffix is final
struct KnownForceAffine {
  template <class S>
  ForceAffine<S> operator()(const ForceAffine<S>& o, const ForceAffine<S>& d) const {
    return {o.Y, o.B + o.Y.apply_transpose(d.B)};
  }
};
// a branch child's delivered force joins its parent's element: B += Y^T (child B)
struct FoldForceAffine {
  template <class S>
  void operator()(ForceAffine<S>& p, const ForceAffine<S>& c) const {
    p.B += p.Y.apply_transpose(c.B);
  }
};
struct FoldPlus {
  template <class T>
  void operator()(T& p, const T& c) const {
    p += c;
  }
};

// Body i's Xup: a model of 1-DoF joints indexes q by the body, the general path
// (kGeneral: multi-DoF joints) at Body::idx_q.
template <bool kGeneral, class S>
Transform<S> scan_joint_transform(const Body<S>& b, Index i, const S* q) {
  if (kGeneral && joint_nv(b.type) > 1) return joint_transform_at(b, q + b.idx_q);
  return joint_transform(b, q[kGeneral ? b.idx_q : i]);
}

template <bool kGeneral, class S>
void rnea_scan_local(const ModelTpl<S>& m, ScanWorkspace<S>& ws, const S* q, const S* qd, const S* qdd,
                     S* tau, const Force<S>* fext) {
  const Index n = m.nbodies();
  const Motion<S> a0 = base_acceleration(m.gravity);
  // velocities: x_i = Xup_i x_parent + S qd (a floating base: its twist, the root's offset)
#pragma omp for schedule(static)
  for (Index i = 0; i < n; ++i) {
    const Body<S>& b = m.bodies[i];
    ws.Xup[i] = scan_joint_transform<kGeneral>(b, i, q);
    if constexpr (kGeneral) ws.fwd[i] = id_velocity_element_at(b, ws.Xup[i], qd + b.idx_v);
    else ws.fwd[i] = id_velocity_element(b, ws.Xup[i], qd[i]);
  }
  tree_prefix_scan(ws.plan, ws.fwd.data(), ws.carry_fwd.data(), ComposeMotionAffine{}, KnownMotionAffine{});
  // accelerations: x_i = Xup_i x_parent + S qdd + v x S qd, the base moving with -g
#pragma omp for schedule(static)
  for (Index i = 0; i < n; ++i) {
    const Body<S>& b = m.bodies[i];
    ws.v[i] = ws.fwd[i].b;
    MotionAffine<S> e;
    if constexpr (kGeneral)
      e = id_acceleration_element_at(b, ws.Xup[i], ws.v[i], qd + b.idx_v, qdd ? qdd + b.idx_v : nullptr);
    else e = id_acceleration_element(b, ws.Xup[i], ws.v[i], qd[i], qdd ? qdd[i] : S(0));
    ws.fwd[i] = b.parent < 0 ? fold_parent(e, a0) : e;
  }
  tree_prefix_scan(ws.plan, ws.fwd.data(), ws.carry_fwd.data(), ComposeMotionAffine{}, KnownMotionAffine{});
  // wrenches: B_i = Xup_i^T (f_i + sum over children)
#pragma omp for schedule(static)
  for (Index i = 0; i < n; ++i) {
    const Force<S> f = body_force(m.bodies[i], ws.v[i], ws.fwd[i].b, fext ? fext + i : nullptr);
    ws.bwd[i] = {ws.Xup[i], ws.Xup[i].apply_transpose(f)};
  }
  tree_suffix_scan(ws.plan, ws.bwd.data(), ws.carry_bwd.data(), ComposeForceAffine{}, KnownForceAffine{},
                   FoldForceAffine{});
  // tau_i = S^T F_i with F_i = Xup_i^{-T} B_i (a floating base: its wrench, tau's first 6)
#pragma omp for schedule(static)
  for (Index i = 0; i < n; ++i) {
    const Body<S>& b = m.bodies[i];
    const Force<S> F = ws.Xup[i].apply(ws.bwd[i].B);
    if constexpr (kGeneral) joint_project_at(b, F, tau + b.idx_v);
    else tau[i] = joint_project(b, F);
  }
}

template <bool kGeneral, class S>
void rnea_scan_world(const ModelTpl<S>& m, ScanWorkspace<S>& ws, const S* q, const S* qd, const S* qdd,
                     S* tau, const Force<S>* fext) {
  const Index n = m.nbodies();
  const Motion<S> a0 = base_acceleration(m.gravity);
  // poses P_i = Xup_i P_parent (world -> body; a floating base's pose is the root's)
#pragma omp for schedule(static)
  for (Index i = 0; i < n; ++i) ws.P[i] = scan_joint_transform<kGeneral>(m.bodies[i], i, q);
  tree_prefix_scan(ws.plan, ws.P.data(), ws.carry_pose.data(), ComposePose{}, ComposePose{});
  // world joint twists: sw the unit twist of a 1-DoF joint, S qd of a multi-DoF one;
  // velocities are the root-path sums of the joints' twists
#pragma omp for schedule(static)
  for (Index i = 0; i < n; ++i) {
    const Body<S>& b = m.bodies[i];
    const Index iv = kGeneral ? b.idx_v : i;
    if (kGeneral && joint_nv(b.type) > 1) {
      ws.sw[i] = ws.P[i].apply_inverse(joint_motion_at(b, qd + iv));
      ws.Vw[i] = ws.sw[i];
    } else {
      ws.sw[i] = ws.P[i].apply_inverse(joint_motion(b, S(1)));
      ws.Vw[i] = qd[iv] * ws.sw[i];
    }
  }
  tree_prefix_scan(ws.plan, ws.Vw.data(), ws.carry_motion.data(), Plus{}, Plus{});
  // accelerations: root-path sums of S qdd + V x S qd (world), plus the base's -g
#pragma omp for schedule(static)
  for (Index i = 0; i < n; ++i) {
    const Body<S>& b = m.bodies[i];
    const Index iv = kGeneral ? b.idx_v : i;
    Motion<S> c;
    if (kGeneral && joint_nv(b.type) > 1) {
      c = cross(ws.Vw[i], ws.sw[i]);
      if (qdd) c += ws.P[i].apply_inverse(joint_motion_at(b, qdd + iv));
    } else {
      c = (qdd ? qdd[iv] : S(0)) * ws.sw[i] + cross(ws.Vw[i], qd[iv] * ws.sw[i]);
    }
    if (b.parent < 0) c += a0;
    ws.Aw[i] = c;
  }
  tree_prefix_scan(ws.plan, ws.Aw.data(), ws.carry_motion.data(), Plus{}, Plus{});
  // body wrenches, computed in body frames and moved to the world frame
#pragma omp for schedule(static)
  for (Index i = 0; i < n; ++i) {
    const Transform<S>& P = ws.P[i];
    const Force<S> f = body_force(m.bodies[i], P.apply(ws.Vw[i]), P.apply(ws.Aw[i]), fext ? fext + i : nullptr);
    ws.Fw[i] = P.apply_transpose(f);
  }
  tree_suffix_scan(ws.plan, ws.Fw.data(), ws.carry_force.data(), Plus{}, Plus{}, FoldPlus{});
#pragma omp for schedule(static)
  for (Index i = 0; i < n; ++i) {
    const Body<S>& b = m.bodies[i];
    if (kGeneral && joint_nv(b.type) > 1) joint_project_at(b, ws.P[i].apply(ws.Fw[i]), tau + b.idx_v);  // body frame
    else tau[kGeneral ? b.idx_v : i] = dot(ws.sw[i], ws.Fw[i]);
  }
}

}  // namespace

template <class S>
void rnea_scan(const ModelTpl<S>& model, ScanWorkspace<S>& ws, ScanForm form, const S* q, const S* qd,
               const S* qdd, S* tau, const Force<S>* fext) {
  auto run = [&] {
    if (model.multi_dof()) {
      if (form == ScanForm::Local) rnea_scan_local<true>(model, ws, q, qd, qdd, tau, fext);
      else rnea_scan_world<true>(model, ws, q, qd, qdd, tau, fext);
    } else if (form == ScanForm::Local) {
      rnea_scan_local<false>(model, ws, q, qd, qdd, tau, fext);
    } else {
      rnea_scan_world<false>(model, ws, q, qd, qdd, tau, fext);
    }
  };
  if (ws.threads == 1) {
    run();  // the worksharing constructs run serially outside a parallel region
    return;
  }
#pragma omp parallel num_threads(ws.threads)
  run();
}

template struct ScanWorkspace<float>;
template struct ScanWorkspace<double>;
template void rnea_scan(const ModelTpl<float>&, ScanWorkspace<float>&, ScanForm, const float*, const float*,
                        const float*, float*, const Force<float>*);
template void rnea_scan(const ModelTpl<double>&, ScanWorkspace<double>&, ScanForm, const double*, const double*,
                        const double*, double*, const Force<double>*);

}  // namespace scandyn
