// scandyn/algorithm/configuration.hpp: the configuration manifold of a model with
// quaternion joints: q (nq entries) moved by a velocity qd (nv entries).
//
// Per joint (scandyn/model/model.hpp for the conventions):
//   revolute, prismatic  q += v dt
//   spherical            quat = quat (x) exp(w dt / 2)        (w in the child frame)
//   free                 p += R(quat) v dt, quat = quat (x) exp(w dt / 2)
//                        (v, w in the base frame: the base's translation and
//                        rotation over the step, each at its start orientation)
// and the time derivative of q for a velocity qd (the embedding's ODE, what a
// Runge-Kutta method on q integrates):
//   spherical / free     quat' = 1/2 quat (x) (w, 0),  free p' = R(quat) v.
// The integrators of the simulator use these for models with multi-DoF joints
// (ModelTpl::multi_dof()); for 1-DoF models q ⊕ v dt is q + v dt.
#pragma once

#include "scandyn/algorithm/steps.hpp"

namespace scandyn {

// exp(w h / 2) as a unit quaternion (x, y, z, w): the rotation by the angle |w| h
// about w. A series near zero angle (no division by |w|).
template <class S>
SCANDYN_HD void quat_exp(const Vec3<S>& w, S h, S* out) {
  const Vec3<S> a = h * w;  // rotation vector
  const S t2 = dot(a, a);   // angle^2
  S s, c;                   // sin(angle / 2) / angle, cos(angle / 2)
  if (t2 < S(1e-8)) {
    s = S(0.5) - t2 / S(48);
    c = S(1) - t2 / S(8);
  } else {
    const S t = ScalarMath<S>::sqrt(t2);
    s = ScalarMath<S>::sin(S(0.5) * t) / t;
    c = ScalarMath<S>::cos(S(0.5) * t);
  }
  out[0] = s * a.x, out[1] = s * a.y, out[2] = s * a.z, out[3] = c;
}

// Divides the quaternion p[0..3] by its norm.
template <class S>
SCANDYN_HD void quat_normalize(S* p) {
  const S n = ScalarMath<S>::sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2] + p[3] * p[3]);
  const S inv = S(1) / n;
  for (int k = 0; k < 4; ++k) p[k] *= inv;
}

// One joint's q ⊕ v h, in place: q at the joint's positions (b.idx_q), v at its
// rates (b.idx_v). The quaternions come out unit (renormalised).
template <class S>
SCANDYN_HD void joint_integrate(const Body<S>& b, S* q, const S* v, S h) {
  if (b.type == JointType::Revolute || b.type == JointType::Prismatic) {
    q[0] += h * v[0];
    return;
  }
  S* quat = b.type == JointType::Free ? q + 3 : q;
  if (b.type == JointType::Free) {
    const Vec3<S> dp = quat_to_matrix(quat) * Vec3<S>{v[3], v[4], v[5]};
    q[0] += h * dp.x, q[1] += h * dp.y, q[2] += h * dp.z;
  }
  S e[4], r[4];
  quat_exp(Vec3<S>{v[0], v[1], v[2]}, h, e);
  quat_multiply(quat, e, r);
  quat_normalize(r);
  for (int k = 0; k < 4; ++k) quat[k] = r[k];
}

// One joint's dq/dt for the rates v (writes joint_nq(b.type) entries at qdot).
template <class S>
SCANDYN_HD void joint_q_derivative(const Body<S>& b, const S* q, const S* v, S* qdot) {
  if (b.type == JointType::Revolute || b.type == JointType::Prismatic) {
    qdot[0] = v[0];
    return;
  }
  const S* quat = b.type == JointType::Free ? q + 3 : q;
  S* dquat = b.type == JointType::Free ? qdot + 3 : qdot;
  if (b.type == JointType::Free) {
    const Vec3<S> dp = quat_to_matrix(quat) * Vec3<S>{v[3], v[4], v[5]};
    qdot[0] = dp.x, qdot[1] = dp.y, qdot[2] = dp.z;
  }
  const S half_w[4] = {S(0.5) * v[0], S(0.5) * v[1], S(0.5) * v[2], S(0)};
  quat_multiply(quat, half_w, dquat);
}

// q ⊕ v h for the whole model (q: nq, v: nv), in place.
template <class S>
void integrate_configuration(const ModelTpl<S>& model, S* q, const S* v, S h) {
  if (!model.multi_dof()) {  // idx_q = idx_v = i (and unset in hand-made 1-DoF models)
    for (Index i = 0; i < model.nv(); ++i) q[i] += h * v[i];
    return;
  }
  for (const Body<S>& b : model.bodies) joint_integrate(b, q + b.idx_q, v + b.idx_v, h);
}

// dq/dt (nq) for the rates v (nv) at q (nq).
template <class S>
void configuration_derivative(const ModelTpl<S>& model, const S* q, const S* v, S* qdot) {
  if (!model.multi_dof()) {
    for (Index i = 0; i < model.nv(); ++i) qdot[i] = v[i];
    return;
  }
  for (const Body<S>& b : model.bodies) joint_q_derivative(b, q + b.idx_q, v + b.idx_v, qdot + b.idx_q);
}

// Renormalises every quaternion of q (nq) in place.
template <class S>
void normalize_configuration(const ModelTpl<S>& model, S* q) {
  if (!model.multi_dof()) return;
  for (const Body<S>& b : model.bodies) {
    if (b.type == JointType::Spherical) quat_normalize(q + b.idx_q);
    else if (b.type == JointType::Free) quat_normalize(q + b.idx_q + 3);
  }
}

}  // namespace scandyn
