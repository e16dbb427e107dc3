// scandyn/model/joint_frames.hpp: the model re-expressed so that every 1-DoF joint's axis is
// its body frame's z axis.
//
// A revolute or prismatic joint's transform XJ(q) is a rotation about, or a translation
// along, its axis in the body frame. Body i's frame can be turned by any constant
// rotation Q_i (its "z-axis frame": coordinates x' = Q_i x) without changing the
// joint-space dynamics: with Q_i axis_i = e_z,
//   Xtree'_i = rot(Q_i) Xtree_i rot(Q_parent)^-1,   I'_i = rot(Q_i)^-* I_i rot(Q_i)^-1,
//   XJ'(q) = rot(Q_i) XJ(q) rot(Q_i)^-1 = XJ(e_z, q),
// so tau, qdd, M and h are unchanged, and every per-body quantity is its user-frame
// value seen through rot(Q_i): v'_i = rot(Q_i) v_i, f'_i = rot(Q_i)^-* f_i (a pure
// rotation maps forces as motions: both halves rotate by Q_i), points p' = Q_i p.
// Then every joint transform is one rotation about (or translation along) z with no
// per-body axis test: ZJointBody and its step functions (scandyn/algorithm/steps.hpp),
// which the thread-per-instance CUDA kernels use. The CPU reference keeps the user's
// frames; this is the device model's view (scandyn/instance/thread_model.hpp).
//
// Q_i is the identity for a joint whose axis is +z already, and a signed permutation
// for +-x, +-y, -z (both exact in any precision); spherical and free joints keep their
// frames (Q = identity).
#pragma once

#include <cmath>
#include <stdexcept>
#include <string>
#include <vector>

#include "scandyn/model/model.hpp"

namespace scandyn {

// A body of a 1-DoF joint whose axis is its frame's +z axis (a model after
// z_axis_model): everything the z-axis step functions read.
template <class S>
struct ZJointBody {
  Index parent;        // parent body, -1 for the fixed base; parent < this body's index
  JointType type;      // Revolute (about z) or Prismatic (along z)
  Transform<S> Xtree;  // parent's z-axis frame -> this body's z-axis frame at q = 0
  Inertia<S> I;        // spatial inertia in this body's z-axis frame
};

// Q with Q axis = e_z (rows: the z-axis frame's x, y, z axes in the body's coordinates):
// the identity for axis = +z, a signed permutation for +-x, +-y, -z. axis: unit.
template <class S>
Mat3<S> z_axis_rotation(const Vec3<S>& axis) {
  const S zero(0), one(1);
  if (axis.x == zero && axis.y == zero && axis.z == one) return Mat3<S>::identity();
  // helper: the coordinate axis least aligned with `axis` (x on ties); u = helper x axis,
  // w = axis x u, so that u x w = axis: the rows u, w, axis are a right-handed basis
  const S ax = std::fabs(axis.x), ay = std::fabs(axis.y), az = std::fabs(axis.z);
  Vec3<S> h = Vec3<S>::zero();
  if (ax <= ay && ax <= az) h.x = one;
  else if (ay <= az) h.y = one;
  else h.z = one;
  Vec3<S> u = cross(h, axis);
  u = (one / std::sqrt(dot(u, u))) * u;
  const Vec3<S> w = cross(axis, u);
  Mat3<S> Q;
  const Vec3<S> rows[3] = {u, w, axis};
  for (int i = 0; i < 3; ++i) Q.m[3 * i] = rows[i].x, Q.m[3 * i + 1] = rows[i].y, Q.m[3 * i + 2] = rows[i].z;
  return Q;
}

// A model with every 1-DoF joint's frame turned so that its axis is +z, and the
// rotations that map each body's user-frame quantities into it.
template <class S>
struct ZAxisModel {
  ModelTpl<S> model;             // the re-expressed model (same joint-space dynamics)
  std::vector<Mat3<S>> frame_Q;  // (nbodies) Q_i: body i's user-frame coordinates ->
                                 // its z-axis frame's (identity where unchanged)
  std::vector<bool> turned;      // (nbodies) Q_i is not the identity

  // A body wrench given in body i's user frame, in its z-axis frame.
  Force<S> to_z_frame(Index i, const Force<S>& f) const {
    return turned[i] ? Force<S>{frame_Q[i] * f.n, frame_Q[i] * f.f} : f;
  }
  // A point fixed on body i, given in its user frame, in its z-axis frame.
  Vec3<S> to_z_frame(Index i, const Vec3<S>& p) const { return turned[i] ? frame_Q[i] * p : p; }
  // A body twist / acceleration, both ways.
  Motion<S> to_z_frame(Index i, const Motion<S>& v) const {
    return turned[i] ? Motion<S>{frame_Q[i] * v.w, frame_Q[i] * v.v} : v;
  }
  Motion<S> to_user_frame(Index i, const Motion<S>& v) const {
    return turned[i] ? Motion<S>{mul_transpose(frame_Q[i], v.w), mul_transpose(frame_Q[i], v.v)} : v;
  }
};

// The model with every revolute / prismatic axis re-expressed as its body frame's +z
// (see the header comment). Frames attached to bodies (model.frames) are re-placed so
// that they stay where they were. A float model is re-expressed in double and rounded
// once (the turned transforms and inertias then carry one rounding, not a float
// product's). Throws std::invalid_argument naming the joint when an axis is not a
// unit vector (|axis| off 1 by more than 1e-5).
template <class S>
ZAxisModel<S> z_axis_model(const ModelTpl<S>& model) {
  if constexpr (sizeof(S) < sizeof(double)) {
    const ZAxisModel<double> wide = z_axis_model(model.template cast<double>());
    ZAxisModel<S> out{wide.model.template cast<S>(), {}, wide.turned};
    for (const Mat3<double>& Q : wide.frame_Q) out.frame_Q.push_back(Q.template cast<S>());
    return out;
  }
  ZAxisModel<S> out;
  out.model = model;
  const Index n = model.nbodies();
  out.frame_Q.assign(n, Mat3<S>::identity());
  out.turned.assign(n, false);
  for (Index i = 0; i < n; ++i) {
    const Body<S>& b = model.bodies[i];
    if (b.type != JointType::Revolute && b.type != JointType::Prismatic) continue;
    const double len = std::sqrt(double(dot(b.axis, b.axis)));
    if (!(std::fabs(len - 1.0) <= 1e-5))
      throw std::invalid_argument("model '" + model.name + "': joint '" +
                                  (i < Index(model.joint_names.size()) ? model.joint_names[i] : std::to_string(i)) +
                                  "' has an axis of length " + std::to_string(len) + " (a unit vector is needed)");
    out.frame_Q[i] = z_axis_rotation(b.axis);
    out.turned[i] = !(b.axis.x == S(0) && b.axis.y == S(0) && b.axis.z == S(1));
  }
  auto rot = [&](Index i) { return Transform<S>{out.frame_Q[i], Vec3<S>::zero()}; };
  for (Index i = 0; i < n; ++i) {
    Body<S>& b = out.model.bodies[i];
    const Index p = b.parent;
    if (p >= 0 && out.turned[p]) b.Xtree = b.Xtree * rot(p).inverse();  // from the parent's z-axis frame
    if (!out.turned[i]) continue;
    b.Xtree = rot(i) * b.Xtree;
    b.I = b.I.transform_transpose(rot(i).inverse());
    b.axis = Vec3<S>{S(0), S(0), S(1)};
  }
  for (FramePlacement<S>& f : out.model.frames)  // frame_X_body' = frame_X_body rot(Q)^-1
    if (f.body >= 0 && out.turned[f.body]) f.X = f.X * rot(f.body).inverse();
  return out;
}

// The z-axis body of a re-expressed model's body (type Revolute or Prismatic, axis +z).
template <class S>
ZJointBody<S> z_joint_body(const Body<S>& b) {
  return {b.parent, b.type, b.Xtree, b.I};
}

}  // namespace scandyn
