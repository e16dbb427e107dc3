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

// ---- the tangent space of one joint (Runge-Kutta on the manifold) ----------
// A stage of a Runge-Kutta step sits at q ⊕ theta for a tangent offset theta
// (joint_nv entries per joint, the coordinates of joint_integrate with h = 1). The
// offset moves with theta' = joint_tangent_slope(theta, v) when the joint's rate is
// v (Munthe-Kaas's method: the ODE for theta is one on a vector space, so the
// classical Runge-Kutta weights combine the stages' slopes there):
//   revolute, prismatic  theta' = v
//   spherical            theta' = Jr^-1(theta) w       (quat = quat0 (x) Exp(theta),
//                                                        w in the child frame)
//   free                 theta_w' = Jr^-1(theta_w) w,  theta_v' = Exp(theta_w) v
//                        (p = p0 + R0 theta_v, so p' = R v = R0 Exp(theta_w) v)
// with Jr^-1 the inverse of SO(3)'s right Jacobian:
//   Jr^-1(t) w = w + 1/2 t x w + (1 / |t|^2 - (1 + cos|t|) / (2 |t| sin|t|)) t x (t x w).

// Jr^-1(t) w (a series in |t|^2 near zero: the coefficient 1/12 + |t|^2 / 720).
template <class S>
SCANDYN_HD Vec3<S> so3_right_jacobian_inverse(const Vec3<S>& t, const Vec3<S>& w) {
  const S t2 = dot(t, t);
  S c;
  if (t2 < S(1e-4)) {
    c = S(1) / S(12) + t2 / S(720) + t2 * t2 / S(30240);
  } else {
    const S a = ScalarMath<S>::sqrt(t2);
    c = S(1) / t2 - (S(1) + ScalarMath<S>::cos(a)) / (S(2) * a * ScalarMath<S>::sin(a));
  }
  const Vec3<S> txw = cross(t, w);
  return w + S(0.5) * txw + c * cross(t, txw);
}

// Exp(t) v: v rotated by the rotation vector t (Rodrigues; series near zero).
template <class S>
SCANDYN_HD Vec3<S> so3_exp_apply(const Vec3<S>& t, const Vec3<S>& v) {
  const S t2 = dot(t, t);
  S s, c;  // sin|t| / |t|, (1 - cos|t|) / |t|^2
  if (t2 < S(1e-4)) {
    s = S(1) - t2 / S(6) + t2 * t2 / S(120);
    c = S(0.5) - t2 / S(24) + t2 * t2 / S(720);
  } else {
    const S a = ScalarMath<S>::sqrt(t2);
    s = ScalarMath<S>::sin(a) / a;
    c = (S(1) - ScalarMath<S>::cos(a)) / t2;
  }
  const Vec3<S> txv = cross(t, v);
  return v + s * txv + c * cross(t, txv);
}

// One joint's theta' at the tangent offset theta (its rates v): joint_nv entries
// written to out (out may not alias theta or v).
template <class S>
SCANDYN_HD void joint_tangent_slope(const Body<S>& b, const S* theta, const S* v, S* out) {
  if (b.type == JointType::Revolute || b.type == JointType::Prismatic) {
    out[0] = v[0];
    return;
  }
  const Vec3<S> t{theta[0], theta[1], theta[2]};
  const Vec3<S> w = so3_right_jacobian_inverse(t, Vec3<S>{v[0], v[1], v[2]});
  out[0] = w.x, out[1] = w.y, out[2] = w.z;
  if (b.type == JointType::Free) {
    const Vec3<S> u = so3_exp_apply(t, Vec3<S>{v[3], v[4], v[5]});
    out[3] = u.x, out[4] = u.y, out[5] = u.z;
  }
}

// ---- the whole configuration over a body array (device-callable) ------------
// The same as integrate_configuration / configuration_derivative /
// normalize_configuration below, over bodies[0..nb) whose idx_q / idx_v are set
// (any model: the CUDA simulator step calls these per thread).

// q ⊕ v h (q: nq, v: nv), in place.
template <class S>
SCANDYN_HD void integrate_bodies(const Body<S>* bodies, Index nb, S* q, const S* v, S h) {
  for (Index i = 0; i < nb; ++i) joint_integrate(bodies[i], q + bodies[i].idx_q, v + bodies[i].idx_v, h);
}

// Renormalises every quaternion of q (nq) in place.
template <class S>
SCANDYN_HD void normalize_bodies(const Body<S>* bodies, Index nb, S* q) {
  for (Index i = 0; i < nb; ++i) {
    if (bodies[i].type == JointType::Spherical) quat_normalize(q + bodies[i].idx_q);
    else if (bodies[i].type == JointType::Free) quat_normalize(q + bodies[i].idx_q + 3);
  }
}

// The neutral configuration (nq): identity quaternions, every other entry zero.
template <class S>
SCANDYN_HD void neutral_bodies(const Body<S>* bodies, Index nb, S* q) {
  for (Index i = 0; i < nb; ++i) {
    const Body<S>& b = bodies[i];
    for (int k = 0; k < joint_nq(b.type); ++k) q[b.idx_q + k] = S(0);
    if (b.type == JointType::Spherical) q[b.idx_q + 3] = S(1);
    else if (b.type == JointType::Free) q[b.idx_q + 6] = S(1);
  }
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
