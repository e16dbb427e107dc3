// scandyn/algorithm/point_kinematics.hpp: per-body kinematics of body-fixed points and
// frames in the base (world) frame: what loop closures need (scandyn/algorithm/loops.hpp).
// SCANDYN_HD step functions on the body quantities of the shared recursions (Xup and
// the body velocities and accelerations of rnea_forward_step), so that every backend
// can call them.
//
// Conventions: X0_i (Transform, E and r) is body i <- base: r is body i's origin in
// base coordinates and E rotates base coordinates into body coordinates, so a
// body-fixed point p (body coordinates) is at r + E^T p in the base frame.
#pragma once

#include "scandyn/algorithm/steps.hpp"

namespace scandyn {

// Forward step of the body poses: X0_i = Xup_i X0_parent (X0_parent: identity for the base).
template <class S>
SCANDYN_HD Transform<S> world_transform_step(const Transform<S>& Xup, const Transform<S>* X0_parent) {
  return X0_parent ? Xup * *X0_parent : Xup;
}

// A body-fixed point p (body coordinates) in base coordinates.
template <class S>
SCANDYN_HD Vec3<S> point_position(const Transform<S>& X0, const Vec3<S>& p) {
  return X0.r + mul_transpose(X0.E, p);
}

// A body vector (body coordinates) in base coordinates.
template <class S>
SCANDYN_HD Vec3<S> to_world(const Transform<S>& X0, const Vec3<S>& w) {
  return mul_transpose(X0.E, w);
}

// The velocity (base coordinates) of body-fixed point p of a body moving with
// spatial velocity v (body frame): E^T (v_O + w x p).
template <class S>
SCANDYN_HD Vec3<S> point_velocity(const Transform<S>& X0, const Motion<S>& v, const Vec3<S>& p) {
  return to_world(X0, v.v + cross(v.w, p));
}

// The classical acceleration (base coordinates) of body-fixed point p of a body with
// spatial velocity v and spatial acceleration a (body frame):
// E^T (a_O + wdot x p + w x (v_O + w x p)). With a from a pass with qdd = 0 and no
// gravity, it is the point's Jdot qd.
template <class S>
SCANDYN_HD Vec3<S> point_acceleration(const Transform<S>& X0, const Motion<S>& v, const Motion<S>& a,
                                      const Vec3<S>& p) {
  return to_world(X0, a.v + cross(a.w, p) + cross(v.w, v.v + cross(v.w, p)));
}

// Joint j's column of a point's Jacobian: the base-frame angular velocity w and the
// velocity of the point at base position p_world for a unit rate of joint j, whose
// body has pose X0_j: revolute, w = E^T axis and v = w x (p - origin); prismatic,
// w = 0 and v = E^T axis.
template <class S>
SCANDYN_HD void joint_point_column(const Body<S>& b, const Transform<S>& X0, const Vec3<S>& p_world, Vec3<S>& w,
                                   Vec3<S>& v) {
  const Vec3<S> axis = to_world(X0, b.axis);
  if (b.type == JointType::Revolute) {
    w = axis;
    v = cross(axis, p_world - X0.r);
  } else {
    w = Vec3<S>::zero();
    v = axis;
  }
}

}  // namespace scandyn
