// scandyn/model/model.hpp: the immutable kinematic-tree model.
//
// A model is a fixed-base tree of nv moving bodies, one single-DoF joint each.
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
};

// Per-body constants: everything the per-link step functions read.
template <class S>
struct Body {
  Index parent;        // parent body, -1 for the fixed base; parent < this body's index
  JointType type;      // joint between parent and this body
  Vec3<S> axis;        // unit joint axis, in this body's frame
  Transform<S> Xtree;  // parent body frame -> this body's frame at q = 0 (joint origin)
  Inertia<S> I;        // spatial inertia in this body's frame, merged fixed links included

  template <class T>
  Body<T> cast() const {
    return {parent, type, axis.template cast<T>(), Xtree.template cast<T>(), I.template cast<T>()};
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
  std::vector<Body<S>> bodies;           // (nv) bodies in DoF order
  std::vector<std::string> joint_names;  // (nv) joint of each body
  std::vector<std::string> link_names;   // (nv) URDF child link of each joint
  std::vector<S> q_lower;                // (nv) joint position limits from the URDF <limit>
  std::vector<S> q_upper;                // (nv) (rad or m); -inf / +inf where there is none
                                         // (continuous joints, generators); used by the
                                         // simulator's joint-limit effect only
  Vec3<S> gravity{S(0), S(0), S(-9.81)};  // gravitational acceleration in the base frame (m/s^2)
  std::vector<FramePlacement<S>> frames;  // (links) every URDF link, in the order the builder
                                          // visits them: the root link first, then depth-first
                                          // preorder (the link of body i comes after body i's
                                          // parent's); scandyn/model/frames.hpp finds them by name
  std::vector<std::string> frame_names;   // (links) the link name of each frame

  // Number of degrees of freedom (= moving bodies).
  Index nv() const { return static_cast<Index>(bodies.size()); }
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
    m.frames.reserve(frames.size());
    for (const auto& f : frames) m.frames.push_back(f.template cast<T>());
    m.frame_names = frame_names;
    return m;
  }
};

using Model = ModelTpl<double>;

}  // namespace scandyn
