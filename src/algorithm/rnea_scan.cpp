// Inverse dynamics as scans over links: local-frame affine form and world-frame form.
#include "scandyn/algorithm/rnea_scan.hpp"

#include <stdexcept>

#include "scandyn/scan/omp_scan.hpp"

namespace scandyn {

template <class S>
ScanWorkspace<S>::ScanWorkspace(const ModelTpl<S>& model, int threads_) : threads(threads_ < 1 ? 1 : threads_) {
  if (model.multi_dof())
    throw std::invalid_argument("rnea_scan: model '" + model.name + "' has multi-DoF joints; the scans take "
                                "revolute and prismatic joints only");
  const Index n = model.nv();
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

template <class S>
void rnea_scan_local(const ModelTpl<S>& m, ScanWorkspace<S>& ws, const S* q, const S* qd, const S* qdd,
                     S* tau, const Force<S>* fext) {
  const Index n = m.nv();
  const Motion<S> a0 = base_acceleration(m.gravity);
  // velocities: x_i = Xup_i x_parent + S qd
#pragma omp for schedule(static)
  for (Index i = 0; i < n; ++i) {
    ws.Xup[i] = joint_transform(m.bodies[i], q[i]);
    ws.fwd[i] = id_velocity_element(m.bodies[i], ws.Xup[i], qd[i]);
  }
  tree_prefix_scan(ws.plan, ws.fwd.data(), ws.carry_fwd.data(), ComposeMotionAffine{}, KnownMotionAffine{});
  // accelerations: x_i = Xup_i x_parent + S qdd + v x S qd, the base moving with -g
#pragma omp for schedule(static)
  for (Index i = 0; i < n; ++i) {
    const Body<S>& b = m.bodies[i];
    ws.v[i] = ws.fwd[i].b;
    const MotionAffine<S> e = id_acceleration_element(b, ws.Xup[i], ws.v[i], qd[i], qdd ? qdd[i] : S(0));
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
  // tau_i = S^T F_i with F_i = Xup_i^{-T} B_i
#pragma omp for schedule(static)
  for (Index i = 0; i < n; ++i) tau[i] = joint_project(m.bodies[i], ws.Xup[i].apply(ws.bwd[i].B));
}

template <class S>
void rnea_scan_world(const ModelTpl<S>& m, ScanWorkspace<S>& ws, const S* q, const S* qd, const S* qdd,
                     S* tau, const Force<S>* fext) {
  const Index n = m.nv();
  const Motion<S> a0 = base_acceleration(m.gravity);
  // poses P_i = Xup_i P_parent (world -> body)
#pragma omp for schedule(static)
  for (Index i = 0; i < n; ++i) ws.P[i] = joint_transform(m.bodies[i], q[i]);
  tree_prefix_scan(ws.plan, ws.P.data(), ws.carry_pose.data(), ComposePose{}, ComposePose{});
  // world joint twists; velocities are their root-path sums
#pragma omp for schedule(static)
  for (Index i = 0; i < n; ++i) {
    ws.sw[i] = ws.P[i].apply_inverse(joint_motion(m.bodies[i], S(1)));
    ws.Vw[i] = qd[i] * ws.sw[i];
  }
  tree_prefix_scan(ws.plan, ws.Vw.data(), ws.carry_motion.data(), Plus{}, Plus{});
  // accelerations: root-path sums of sw qdd + V x sw qd, plus the base's -g
#pragma omp for schedule(static)
  for (Index i = 0; i < n; ++i) {
    Motion<S> c = (qdd ? qdd[i] : S(0)) * ws.sw[i] + cross(ws.Vw[i], qd[i] * ws.sw[i]);
    if (m.bodies[i].parent < 0) c += a0;
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
  for (Index i = 0; i < n; ++i) tau[i] = dot(ws.sw[i], ws.Fw[i]);
}

}  // namespace

template <class S>
void rnea_scan(const ModelTpl<S>& model, ScanWorkspace<S>& ws, ScanForm form, const S* q, const S* qd,
               const S* qdd, S* tau, const Force<S>* fext) {
  auto run = [&] {
    if (form == ScanForm::Local) rnea_scan_local(model, ws, q, qd, qdd, tau, fext);
    else rnea_scan_world(model, ws, q, qd, qdd, tau, fext);
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
