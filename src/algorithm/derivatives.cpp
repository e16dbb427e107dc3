// src/algorithm/derivatives.cpp: the serial reference derivatives
// (scandyn/algorithm/derivatives.hpp) for float and double.
#include "scandyn/algorithm/derivatives.hpp"
#include "scandyn/algorithm/directional_derivatives.hpp"

namespace scandyn {

template <class S>
void rnea_derivatives(const ModelTpl<S>& model, DerivativeDataTpl<S>& data, const S* q, const S* qd,
                      const S* qdd, const Force<S>* fext, MatrixRef<S> dtau_dq, MatrixRef<S> dtau_dqd,
                      MatrixRef<S> M, S* tau) {
  const Motion<S> a0 = base_acceleration(model.gravity);
  if (tau)
    rnea_derivatives_instance(model.bodies.data(), model.nv(), a0, q, qd, qdd, fext, data.work.data(), dtau_dq,
                              dtau_dqd, M, tau);
  else
    rnea_derivatives_instance(model.bodies.data(), model.nv(), a0, q, qd, qdd, fext, data.work.data(), dtau_dq,
                              dtau_dqd, M, nullptr);
}

template <class S>
Status aba_derivatives(const ModelTpl<S>& model, DerivativeDataTpl<S>& data, const S* q, const S* qd,
                       const S* tau, const Force<S>* fext, S* qdd, MatrixRef<S> dqdd_dq, MatrixRef<S> dqdd_dqd,
                       MatrixRef<S> dqdd_dtau, const S* armature) {
  const Status st = aba(model, data.aba, q, qd, tau, qdd, fext, armature);
  if (!st.ok()) return st;
  const Index failed = fd_derivatives_instance(model.bodies.data(), model.nv(), base_acceleration(model.gravity), q,
                                               qd, static_cast<const S*>(qdd), fext, data.work.data(), dqdd_dq,
                                               dqdd_dqd, dqdd_dtau, armature);
  return Status{failed};
}

template <class S>
void rnea_jvp(const ModelTpl<S>& model, RneaJvpData<S>& data, const S* q, const S* qd, const S* qdd,
              const Force<S>* fext, const S* dq, const S* dqd, const S* dqdd, S* dtau, S* tau) {
  const Index n = model.nv();
  DataTpl<S>& d = data.rnea;
  const Motion<S> a0 = base_acceleration(model.gravity);
  // forward: the RNEA's values and their tangents
  for (Index i = 0; i < n; ++i) {
    const Body<S>& b = model.bodies[i];
    const Index p = b.parent;
    d.Xup[i] = joint_transform(b, q[i]);
    const Motion<S> vp = p < 0 ? Motion<S>::zero() : d.v[p], ap = p < 0 ? a0 : d.a[p];
    const Motion<S> dvp = p < 0 ? Motion<S>::zero() : data.t[p].v, dap = p < 0 ? Motion<S>::zero() : data.t[p].a;
    const RneaForward<S> o = rnea_forward_step(b, d.Xup[i], vp, ap, qd[i], qdd[i]);
    d.v[i] = o.v;
    d.a[i] = o.a;
    d.f[i] = fext ? o.f - fext[i] : o.f;
    data.t[i] = rnea_tangent_forward_step(b, d.Xup[i], vp, ap, dvp, dap, o, qd[i], dq[i], dqd[i], dqdd[i]);
  }
  // backward: subtree forces and their tangents
  for (Index i = n - 1; i >= 0; --i) {
    const Body<S>& b = model.bodies[i];
    dtau[i] = joint_project(b, data.t[i].f);
    if (tau) tau[i] = joint_project(b, d.f[i]);
    if (b.parent < 0) continue;
    const Transform<S>& X = d.Xup[i];
    data.t[b.parent].f += X.apply_transpose(data.t[i].f + dq[i] * cross(joint_motion(b, S(1)), d.f[i]));
    d.f[b.parent] += X.apply_transpose(d.f[i]);
  }
}

template <class S>
void rnea_vjp(const ModelTpl<S>& model, RneaJvpData<S>& data, const S* q, const S* qd, const S* qdd,
              const Force<S>* fext, const S* w, S* gq, S* gqd, S* gqdd) {
  const Index n = model.nv();
  DataTpl<S>& d = data.rnea;
  rnea(model, d, q, qd, qdd, gqdd, fext);  // Xup, v, a and the subtree forces F (tau unused)
  const Motion<S> a0 = base_acceleration(model.gravity);
  // root to leaves: Fbar, and the body force's own adjoints
  for (Index i = 0; i < n; ++i) {
    const Body<S>& b = model.bodies[i];
    const Motion<S> s = joint_motion(b, S(1));
    RneaAdjoint<S>& r = data.adj[i];
    const Motion<S> from_parent = b.parent < 0 ? Motion<S>::zero() : d.Xup[i].apply(data.adj[b.parent].F);
    r.F = w[i] * s + from_parent;
    gq[i] = dot(from_parent, cross(s, d.f[i]));
    r.a = b.I * r.F;
    r.v = -(cross(r.F, b.I * d.v[i]) + b.I * cross(d.v[i], r.F));
  }
  // leaves to root: the acceleration and velocity adjoints, to the parents
  for (Index i = n - 1; i >= 0; --i) {
    const Body<S>& b = model.bodies[i];
    const Index p = b.parent;
    const Transform<S>& X = d.Xup[i];
    const Motion<S> s = joint_motion(b, S(1));
    RneaAdjoint<S>& r = data.adj[i];
    const Motion<S> Xa = X.apply(p < 0 ? a0 : d.a[p]), Xv = X.apply(p < 0 ? Motion<S>::zero() : d.v[p]);
    gqdd[i] = dot(s, r.a);
    gqd[i] = dot(cross(d.v[i], s), r.a);
    r.v += qd[i] * cross(s, r.a);
    gq[i] -= dot(cross(s, Xa), r.a) + dot(cross(s, Xv), r.v);
    gqd[i] += dot(s, r.v);
    if (p >= 0) {
      data.adj[p].a += X.apply_transpose(r.a);
      data.adj[p].v += X.apply_transpose(r.v);
    }
  }
}

template <class S>
AbaJvpData<S>::AbaJvpData(const ModelTpl<S>& model)
    : id(model), at_rest(model), aba(model, /*mass_matrix=*/false), zero(model.nv(), S(0)), r0(model.nv()),
      r1(model.nv()) {
  at_rest.gravity = Vec3<S>::zero();
}

template <class S>
Status aba_jvp(const ModelTpl<S>& model, AbaJvpData<S>& data, const S* q, const S* qd, const S* tau,
               const Force<S>* fext, const S* dq, const S* dqd, const S* dtau, S* dqdd, S* qdd, const S* armature) {
  const Status st = aba(model, data.aba, q, qd, tau, qdd, fext, armature);
  if (!st.ok()) return st;
  // r0 = dtau/dq dq + dtau/dqd dqd (the JVP of ID with dqdd = 0), then dtau - r0
  rnea_jvp(model, data.id, q, qd, static_cast<const S*>(qdd), fext, dq, dqd, data.zero.data(), data.r0.data());
  const Index n = model.nv();
  for (Index i = 0; i < n; ++i) data.r0[i] = dtau[i] - data.r0[i];
  return aba(data.at_rest, data.aba, q, data.zero.data(), data.r0.data(), dqdd, static_cast<const Force<S>*>(nullptr), armature);
}

template <class S>
Status aba_vjp(const ModelTpl<S>& model, AbaJvpData<S>& data, const S* q, const S* qd, const S* tau,
               const Force<S>* fext, const S* w, S* gq, S* gqd, S* gtau, S* qdd, const S* armature) {
  Status st = aba(model, data.aba, q, qd, tau, qdd, fext, armature);
  if (!st.ok()) return st;
  st = aba(data.at_rest, data.aba, q, data.zero.data(), w, gtau, static_cast<const Force<S>*>(nullptr), armature);  // u = M^-1 w
  if (!st.ok()) return st;
  rnea_vjp(model, data.id, q, qd, static_cast<const S*>(qdd), fext, static_cast<const S*>(gtau), gq, gqd,
           data.r1.data());
  const Index n = model.nv();
  for (Index i = 0; i < n; ++i) gq[i] = -gq[i], gqd[i] = -gqd[i];
  return st;
}

#define SCANDYN_INSTANTIATE_DERIVATIVES(S)                                                                     \
  template void rnea_derivatives(const ModelTpl<S>&, DerivativeDataTpl<S>&, const S*, const S*, const S*,     \
                                 const Force<S>*, MatrixRef<S>, MatrixRef<S>, MatrixRef<S>, S*);               \
  template Status aba_derivatives(const ModelTpl<S>&, DerivativeDataTpl<S>&, const S*, const S*, const S*,    \
                                  const Force<S>*, S*, MatrixRef<S>, MatrixRef<S>, MatrixRef<S>, const S*);     \
  template void rnea_jvp(const ModelTpl<S>&, RneaJvpData<S>&, const S*, const S*, const S*, const Force<S>*,    \
                         const S*, const S*, const S*, S*, S*);                                        \
  template void rnea_vjp(const ModelTpl<S>&, RneaJvpData<S>&, const S*, const S*, const S*, const Force<S>*,    \
                         const S*, S*, S*, S*);                                                        \
  template struct AbaJvpData<S>;                                                                               \
  template Status aba_jvp(const ModelTpl<S>&, AbaJvpData<S>&, const S*, const S*, const S*, const Force<S>*,    \
                          const S*, const S*, const S*, S*, S*, const S*);                                     \
  template Status aba_vjp(const ModelTpl<S>&, AbaJvpData<S>&, const S*, const S*, const S*, const Force<S>*,    \
                          const S*, S*, S*, S*, S*, const S*);
SCANDYN_INSTANTIATE_DERIVATIVES(float)
SCANDYN_INSTANTIATE_DERIVATIVES(double)
#undef SCANDYN_INSTANTIATE_DERIVATIVES

}  // namespace scandyn
