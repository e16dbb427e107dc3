// scandyn/model/model.hpp: the immutable kinematic-tree model.
//
// A model is a tree of moving bodies, one joint each: revolute or prismatic (1 DoF),
// spherical (3 DoF, a unit quaternion in q) or free (6 DoF, the floating base: body
// 0 only, q = [position; quaternion], qd = the base twist in the base frame).
// Bodies are numbered in DoF order: depth-first preorder from the URDF root,
// siblings ordered by joint name, so parent[i] < i. Links attached through fixed
// joints are merged into the body they hang from (their inertia is added and their
// child joints re-rooted); the root link and everything fixed to it are the base.
#pragma once

#include <string>
#include <vector>

#include "scandyn/spatial.hpp"

namespace scandyn {

enum class JointType : int {
  Revolute = 0,   // rotation about axis (URDF revolute or continuous)
  Prismatic = 1,  // translation along axis
  Spherical = 2,  // ball joint: q = unit quaternion (x, y, z, w) rotating child-frame vectors
                  // into the parent frame; qd = relative angular velocity in the child frame;
                  // motion subspace S = [I3; 0]
  Free = 3,       // floating base (body 0, parent -1): q = [p (world); quaternion (x, y, z, w)
                  // rotating base-frame vectors into the world]; qd = the base twist in the base
                  // frame [w; v]; motion subspace S = I6
};

// Entries of q and of qd (= DoFs) a joint of this type has.
SCANDYN_HD constexpr int joint_nq(JointType t) {
  return t == JointType::Free ? 7 : t == JointType::Spherical ? 4 : 1;
}
SCANDYN_HD constexpr int joint_nv(JointType t) {
  return t == JointType::Free ? 6 : t == JointType::Spherical ? 3 : 1;
}

// Per-body constants: everything the per-link step functions read.
template <class S>
struct Body {
  Index parent;        // parent body, -1 for the fixed base; parent < this body's index
  JointType type;      // joint between parent and this body
  Vec3<S> axis;        // unit joint axis, in this body's frame
  Transform<S> Xtree;  // parent body frame -> this body's frame at q = 0 (joint origin)
  Inertia<S> I;        // spatial inertia in this body's frame, merged fixed links included
  // First entry of this body's joint in q and in qd (qdd, tau). Read only for models
  // with multi-DoF joints (ModelTpl::multi_dof()); in a model of 1-DoF joints both
  // equal the body's index (the builder sets them; hand-made 1-DoF models may not).
  Index idx_q = 0;
  Index idx_v = 0;

  template <class T>
  Body<T> cast() const {
    return {parent, type, axis.template cast<T>(), Xtree.template cast<T>(), I.template cast<T>(),
            idx_q, idx_v};
  }
};

// A frame: a URDF link as a placement on the body that carries it. Every link has
// one: the link of a moving joint sits at its body's origin (X the identity); a link
// attached by fixed joints was merged into the body it hangs from, and X places it
// there; the root link and the links fixed to it are on the base (body -1, X its
// placement in the base frame, which is the world frame).
template <class S>
struct FramePlacement {
  Index body;       // body carrying the frame, -1 for the fixed base
  Transform<S> X;   // frame_X_body: body frame -> frame (E: body axes -> frame axes,
                    // r: the frame's origin in body coordinates)

  template <class T>
  SCANDYN_HD FramePlacement<T> cast() const { return {body, X.template cast<T>()}; }
};

template <class S>
struct ModelTpl {
  using Scalar = S;

  std::string name;                      // robot name (URDF) or generator spec
  std::string source;                    // file path or generator spec it was loaded from
  std::string root_link;                 // URDF root link (the fixed base)
  std::vector<Body<S>> bodies;           // (nbodies) bodies in DoF order
  std::vector<std::string> joint_names;  // (nbodies) joint of each body ("root_joint": the free joint)
  std::vector<std::string> link_names;   // (nbodies) URDF child link of each joint (the root link)
  std::vector<S> q_lower;                // (nbodies) joint position limits from the URDF <limit>
  std::vector<S> q_upper;                // (nbodies) (rad or m); -inf / +inf where there is none
                                         // (continuous joints, generators); used by the
                                         // simulator's joint-limit effect only
  Vec3<S> gravity{S(0), S(0), S(-9.81)};  // gravitational acceleration in the world frame
                                          // (the fixed base's frame) (m/s^2)
  Index extra_q = 0;  // sum over bodies of joint_nq - 1: 0 for a model of 1-DoF joints
  Index extra_v = 0;  // sum over bodies of joint_nv - 1: 0 for a model of 1-DoF joints
  std::vector<FramePlacement<S>> frames;  // (links) every URDF link, in the order the builder
                                          // visits them: the root link first, then depth-first
                                          // preorder (the link of body i comes after body i's
                                          // parent's); scandyn/model/frames.hpp finds them by name
  std::vector<std::string> frame_names;   // (links) the link name of each frame

  // Number of degrees of freedom (entries of qd, qdd, tau; = nbodies() for 1-DoF joints).
  Index nv() const { return static_cast<Index>(bodies.size()) + extra_v; }
  // Entries of q (= nv() unless a joint holds a quaternion).
  Index nq() const { return static_cast<Index>(bodies.size()) + extra_q; }
  // Number of moving bodies.
  Index nbodies() const { return static_cast<Index>(bodies.size()); }
  // True when some joint has more than one DoF (spherical, free): the algorithms'
  // general path, which reads Body::idx_q / idx_v.
  bool multi_dof() const { return extra_v != 0; }
  // True when body 0 is a free joint (the floating base).
  bool floating_base() const { return !bodies.empty() && bodies[0].type == JointType::Free; }
  // True when every joint has one DoF, or a floating base has 1-DoF joints past it
  // (what the CUDA thread-per-instance kernels take; spherical joints do not).
  bool one_dof_past_base() const { return extra_v == 0 || (floating_base() && extra_v == 5); }
  Index parent(Index i) const { return bodies[i].parent; }

  template <class T>
  ModelTpl<T> cast() const {
    ModelTpl<T> m;
    m.name = name;
    m.source = source;
    m.root_link = root_link;
    m.bodies.reserve(bodies.size());
    for (const auto& b : bodies) m.bodies.push_back(b.template cast<T>());
    m.joint_names = joint_names;
    m.link_names = link_names;
    m.q_lower.assign(q_lower.begin(), q_lower.end());
    m.q_upper.assign(q_upper.begin(), q_upper.end());
    m.gravity = gravity.template cast<T>();
    m.extra_q = extra_q;
    m.extra_v = extra_v;
    m.frames.reserve(frames.size());
    for (const auto& f : frames) m.frames.push_back(f.template cast<T>());
    m.frame_names = frame_names;
    return m;
  }
};

using Model = ModelTpl<double>;

// Sets every body's idx_q / idx_v (running sums of joint_nq / joint_nv in body order)
// and the model's extra_q / extra_v: what the builder does, for models made by hand.
template <class S>
void set_joint_offsets(ModelTpl<S>& m) {
  Index iq = 0, iv = 0;
  for (Body<S>& b : m.bodies) {
    b.idx_q = iq;
    b.idx_v = iv;
    iq += joint_nq(b.type);
    iv += joint_nv(b.type);
  }
  m.extra_q = iq - m.nbodies();
  m.extra_v = iv - m.nbodies();
}

// Name of the first joint with more than one DoF (the free joint is "root_joint"),
// for the errors of what takes 1-DoF joints only; "" in a model of 1-DoF joints.
template <class S>
std::string first_multi_dof_joint(const ModelTpl<S>& m) {
  for (std::size_t i = 0; i < m.bodies.size(); ++i)
    if (joint_nv(m.bodies[i].type) > 1) return i < m.joint_names.size() ? m.joint_names[i] : std::to_string(i);
  return "";
}

}  // namespace scandyn
