// scandyn/scan/elements.hpp: scan elements and associative operators of inverse
// dynamics as two scans (host + device).
//
// Forward (root -> leaves) along each root path, local frames:
//   x_i = Xup_i x_parent + b_i             (velocities: b = S qd; accelerations:
//                                            b = S qdd + v x S qd, gravity at the root)
// is the affine map (Xup_i, b_i). Composing a node after its ancestor's prefix,
//   (X2, b2) o (X1, b1) = (X2 X1, X2 b1 + b2),
// is associative, so the root-path prefix is a scan; its offset part is x_i.
//
// Backward (leaves -> root), local frames: the map that takes the force G already
// accumulated in body i's frame from below and returns body i's joint force moved
// into its parent's frame, Phi_i(G) = Xup_i^T (f_i + G), is affine: G -> B + Y^T G.
// Composition (outer node o, inner node d below it):
//   (Y_o, B_o) o (Y_d, B_d) = (Y_d Y_o, B_o + Y_o^T B_d).
//
// World-frame form: a scan of poses P_i = Xup_i P_parent (world -> body), after
// which world-frame twists, accelerations and subtree wrenches are plain sums.
#pragma once

#include "scandyn/algorithm/steps.hpp"
#include "scandyn/spatial.hpp"

namespace scandyn {

// Affine map on motion vectors, x -> X x + b.
template <class S>
struct MotionAffine {
  Transform<S> X;  // parent -> this node, or root -> node for a prefix
  Motion<S> b;     // offset; for a root-path prefix: the node's value
};

// ancestor-prefix `acc` followed by node element `e`
template <class S>
SCANDYN_HD MotionAffine<S> compose(const MotionAffine<S>& acc, const MotionAffine<S>& e) {
  return {e.X * acc.X, e.X.apply(acc.b) + e.b};
}
// only the value, when the full prefix is not needed downstream
template <class S>
SCANDYN_HD Motion<S> apply(const MotionAffine<S>& e, const Motion<S>& x_parent) {
  return e.X.apply(x_parent) + e.b;
}

// Affine map on force vectors, G -> B + Y^T G (Y: this node's Xup; B in parent frame).
template <class S>
struct ForceAffine {
  Transform<S> Y;  // Xup of the outermost node of the composed run
  Force<S> B;      // force delivered to the parent of that node, parent frame
};

// outer node (closer to the root) `o` after the inner run `d` below it
template <class S>
SCANDYN_HD ForceAffine<S> compose(const ForceAffine<S>& o, const ForceAffine<S>& d) {
  return {d.Y * o.Y, o.B + o.Y.apply_transpose(d.B)};
}

// ---- inverse dynamics' forward elements, one body at a time -------------------
// The local-frame elements of body i, built here for the CPU scans
// (src/algorithm/rnea_scan.cpp) and the CUDA scans (kernels/id_scan.cu) alike.

// Velocities, v_i = Xup_i v_parent + S_i qd_i: the element (Xup_i, S_i qd_i).
template <class S>
SCANDYN_HD MotionAffine<S> id_velocity_element(const Body<S>& b, const Transform<S>& Xup, S qd) {
  return {Xup, joint_motion(b, qd)};
}

// Accelerations, a_i = Xup_i a_parent + S_i qdd_i + v_i x S_i qd_i (v_i from the
// velocity scan): the element (Xup_i, S_i qdd_i + v_i x S_i qd_i).
template <class S>
SCANDYN_HD MotionAffine<S> id_acceleration_element(const Body<S>& b, const Transform<S>& Xup, const Motion<S>& v,
                                                   S qd, S qdd) {
  return {Xup, add_joint_motion(b, cross_joint_motion(b, v, qd), qdd)};
}

// The same elements at a joint of any type (spherical, free; 1-DoF joints through
// the functions above), with the joint's rates qd, qdd at b.idx_v's entries (qdd
// null: zero). A free joint is the root: its parent's velocity is zero, so its
// velocity element's offset S qd is the base twist, and v x S qd = 0 in its
// acceleration element, whose parent value is the base acceleration -g (folded in
// with fold_parent): the floating base enters the prefix scans as their first
// element, its pose in Xup.
template <class S>
SCANDYN_HD MotionAffine<S> id_velocity_element_at(const Body<S>& b, const Transform<S>& Xup, const S* qd) {
  return {Xup, joint_motion_at(b, qd)};
}
template <class S>
SCANDYN_HD MotionAffine<S> id_acceleration_element_at(const Body<S>& b, const Transform<S>& Xup, const Motion<S>& v,
                                                      const S* qd, const S* qdd) {
  if (b.type == JointType::Revolute || b.type == JointType::Prismatic)
    return id_acceleration_element(b, Xup, v, qd[0], qdd ? qdd[0] : S(0));
  const Motion<S> c = cross(v, joint_motion_at(b, qd));
  return {Xup, qdd ? c + joint_motion_at(b, qdd) : c};
}

// A transform that maps every vector to zero.
template <class S>
SCANDYN_HD Transform<S> zero_transform() {
  return {Mat3<S>::zero(), Vec3<S>::zero()};
}

// Element e of a body whose parent's value x_parent is already final (the base's
// acceleration -g, or a CUDA segment head's parent in an earlier level), folded into
// the offset: (0, X x_parent + b), a map that ignores whatever precedes it.
template <class S>
SCANDYN_HD MotionAffine<S> fold_parent(const MotionAffine<S>& e, const Motion<S>& x_parent) {
  return {zero_transform<S>(), e.X.apply(x_parent) + e.b};
}

// The backward (force) elements differ by form: the CPU scans deliver each body's
// force to its parent, (Xup_i, Xup_i^T f_i); the CUDA scans keep it in the body's
// frame, (Xup_{i+1}, f_i + branch children). Both take f_i from body_force
// (scandyn/algorithm/steps.hpp).

// Operators as function objects, for the generic scan drivers (host and device).
struct ComposeMotionAffine {
  template <class S>
  SCANDYN_HD MotionAffine<S> operator()(const MotionAffine<S>& acc, const MotionAffine<S>& e) const {
    return compose(acc, e);
  }
};
struct ComposeForceAffine {
  template <class S>
  SCANDYN_HD ForceAffine<S> operator()(const ForceAffine<S>& o, const ForceAffine<S>& d) const {
    return compose(o, d);
  }
};
// Pose prefix: P_node = Xup_node P_ancestor.
struct ComposePose {
  template <class S>
  SCANDYN_HD Transform<S> operator()(const Transform<S>& acc, const Transform<S>& e) const {
    return e * acc;
  }
};
// Plain sums (world-frame twists, accelerations, wrenches).
struct Plus {
  template <class T>
  SCANDYN_HD T operator()(const T& a, const T& b) const {
    return a + b;
  }
};

}  // namespace scandyn
