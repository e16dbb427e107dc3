// scandyn/algorithm/steps.hpp: per-body step functions of RNEA, CRBA and ABA.
//
// These are the one source of truth for the recursions: the serial reference,
// the OpenMP backend and the CUDA kernels all call them. Each takes the body's
// constants, the parent's quantities and the joint variables, and returns the
// body's quantities (Featherstone, Rigid Body Dynamics Algorithms, ch. 5-7).
#pragma once

#include <cmath>

#include "scandyn/model/joint_frames.hpp"
#include "scandyn/model/model.hpp"

namespace scandyn {

// R(axis, q)^T Etree for a revolute joint. An axis along +-x, +-y or +-z (the common
// case, decided per call from the stored axis) touches two rows of Etree only.
template <class S>
SCANDYN_HD Mat3<S> rotate_rows(const Vec3<S>& axis, S s, S c, const Mat3<S>& E) {
  // rows i, j of R^T E = [c s; -s c] applied to rows i, j of E, with (i, j, sign) by axis
  auto mix = [&](int i, int j, S sn) {
    Mat3<S> o = E;
    for (int k = 0; k < 3; ++k) {
      o.m[3 * i + k] = c * E.m[3 * i + k] + sn * E.m[3 * j + k];
      o.m[3 * j + k] = c * E.m[3 * j + k] - sn * E.m[3 * i + k];
    }
    return o;
  };
  if (axis.x == S(0) && axis.y == S(0)) return mix(0, 1, axis.z * s);
  if (axis.y == S(0) && axis.z == S(0)) return mix(1, 2, axis.x * s);
  if (axis.x == S(0) && axis.z == S(0)) return mix(2, 0, axis.y * s);
  return mul_transpose(axis_angle(axis, s, c), E);
}

// How joint angles become sin q and cos q (joint_sincos).
enum class Trig {
  Exact,     // correctly rounded in float too (the default)
  Library,   // the platform's sin/cos (on the device: CUDA's sinf/cosf, 2 ulp)
  Hardware,  // device float: reduction to [-pi, pi] and the SFU's __sincosf
             // (absolute error <= 2^-21.4); elsewhere as Library
};

// sin q and cos q of a revolute joint. Trig::Exact rounds correctly in float as
// well: CUDA's sinf/cosf are within 2 ulp, but their error has a bias (the mean of
// s^2 + c^2 - 1 is about 8e-9, 0.1 ulp), and a chain multiplies one joint rotation
// per link, so the bias grows linearly with the length: float ropes of 10^5 links
// drifted by 10^-3 from the double reference. A scaling of (s, c) cannot remove a
// bias below half an ulp (the scaled value rounds back to the same float), so on
// the device a float angle is evaluated in double and rounded once, like glibc's
// sinf/cosf on the host. The thread-per-instance kernels (at most 64 links, where
// that drift stays below 1e-6) use the cheaper kinds.
template <Trig kTrig = Trig::Exact, class S>
SCANDYN_HD void joint_sincos(S q, S& s, S& c) {
#if defined(__CUDA_ARCH__)
  if constexpr (sizeof(S) < sizeof(double) && kTrig == Trig::Exact) {
    double sd, cd;
    ::sincos(double(q), &sd, &cd);
    s = S(sd);
    c = S(cd);
    return;
  } else if constexpr (sizeof(S) < sizeof(double) && kTrig == Trig::Hardware) {
    const float k = rintf(q * 0.159154943f);                            // turns
    const float r = fmaf(-k, -1.74845553e-7f, fmaf(-k, 6.28318548f, q));  // q - 2 pi k, 2 pi in two parts
    __sincosf(r, &s, &c);
    return;
  }
#endif
  s = ScalarMath<S>::sin(q);
  c = ScalarMath<S>::cos(q);
}

// Xup = XJ(q) Xtree: parent frame -> body frame at joint position q (kTrig: see
// joint_sincos).
template <Trig kTrig = Trig::Exact, class S>
SCANDYN_HD Transform<S> joint_transform(const Body<S>& b, S q) {
  if (b.type == JointType::Revolute) {
    // XJ = rot(R(axis, q)^T): E = R^T Etree, r = rtree
    S s, c;
    joint_sincos<kTrig>(q, s, c);
    return {rotate_rows(b.axis, s, c, b.Xtree.E), b.Xtree.r};
  }
  // XJ = xlt(axis q): E = Etree, r = rtree + Etree^T axis q
  return {b.Xtree.E, b.Xtree.r + mul_transpose(b.Xtree.E, q * b.axis)};
}

// S s: the joint's motion for a joint rate s.
template <class S>
SCANDYN_HD Motion<S> joint_motion(const Body<S>& b, S s) {
  if (b.type == JointType::Revolute) return {s * b.axis, Vec3<S>::zero()};
  return {Vec3<S>::zero(), s * b.axis};
}

// v + S s, without arithmetic on the zero half of S.
template <class S>
SCANDYN_HD Motion<S> add_joint_motion(const Body<S>& b, Motion<S> v, S s) {
  if (b.type == JointType::Revolute) v.w += s * b.axis;
  else v.v += s * b.axis;
  return v;
}

// v x (S s), without arithmetic on the zero half of S.
template <class S>
SCANDYN_HD Motion<S> cross_joint_motion(const Body<S>& b, const Motion<S>& v, S s) {
  const Vec3<S> sa = s * b.axis;
  if (b.type == JointType::Revolute) return {cross(v.w, sa), cross(v.v, sa)};
  return {Vec3<S>::zero(), cross(v.w, sa)};
}

// S^T f: the joint component of a force.
template <class S>
SCANDYN_HD S joint_project(const Body<S>& b, const Force<S>& f) {
  return dot(b.axis, b.type == JointType::Revolute ? f.n : f.f);
}

// I S: an inertia's (rigid or articulated) column along the joint's unit motion (the
// ABA's U = IA S, the CRBA's column force Ic S).
template <class In, class S>
SCANDYN_HD Force<S> inertia_joint_column(const In& I, const Body<S>& b) {
  return I * joint_motion(b, S(1));
}

// ---- joints about / along the body frame's z axis (ZJointBody) ----------------
// The same primitives for a model re-expressed by z_axis_model
// (scandyn/model/joint_frames.hpp): S = e_z in the angular (revolute) or linear
// (prismatic) half, known at compile time, so that no step tests an axis; revolute
// and prismatic differ by selects only. The composite steps below take either body.

// Xup = XJ(q) Xtree: a revolute joint turns rows 0 and 1 of Etree by (c, s) (R_z(q)^T
// Etree); a prismatic one moves the origin along row 2 of Etree (Etree^T e_z q). Both
// are evaluated for either type with the other's motion zero: s = 0, c = 1 and a zero
// displacement leave E and r exactly as they are.
template <Trig kTrig = Trig::Exact, class S>
SCANDYN_HD Transform<S> joint_transform(const ZJointBody<S>& b, S q) {
  const bool rev = b.type == JointType::Revolute;
  S s, c;
  joint_sincos<kTrig>(rev ? q : S(0), s, c);
  const S d = rev ? S(0) : q;  // prismatic displacement
  const Mat3<S>& E = b.Xtree.E;
  Transform<S> X;
  for (int k = 0; k < 3; ++k) {
    X.E.m[k] = c * E.m[k] + s * E.m[3 + k];
    X.E.m[3 + k] = c * E.m[3 + k] - s * E.m[k];
    X.E.m[6 + k] = E.m[6 + k];
  }
  X.r = Vec3<S>{b.Xtree.r.x + d * E.m[6], b.Xtree.r.y + d * E.m[7], b.Xtree.r.z + d * E.m[8]};
  return X;
}

// S s.
template <class S>
SCANDYN_HD Motion<S> joint_motion(const ZJointBody<S>& b, S s) {
  const bool rev = b.type == JointType::Revolute;
  return {Vec3<S>{S(0), S(0), rev ? s : S(0)}, Vec3<S>{S(0), S(0), rev ? S(0) : s}};
}

// v + S s.
template <class S>
SCANDYN_HD Motion<S> add_joint_motion(const ZJointBody<S>& b, Motion<S> v, S s) {
  const bool rev = b.type == JointType::Revolute;
  v.w.z += rev ? s : S(0);
  v.v.z += rev ? S(0) : s;
  return v;
}

// v x (S s): a x (0, 0, s) = (a.y s, -a.x s, 0) for a = w, v (revolute) or 0, w (prismatic).
template <class S>
SCANDYN_HD Motion<S> cross_joint_motion(const ZJointBody<S>& b, const Motion<S>& v, S s) {
  const bool rev = b.type == JointType::Revolute;
  const Vec3<S>& lin = rev ? v.v : v.w;
  const S ws = rev ? s : S(0);
  return {Vec3<S>{v.w.y * ws, -v.w.x * ws, S(0)}, Vec3<S>{lin.y * s, -lin.x * s, S(0)}};
}

// S^T f.
template <class S>
SCANDYN_HD S joint_project(const ZJointBody<S>& b, const Force<S>& f) {
  return b.type == JointType::Revolute ? f.n.z : f.f.z;
}

// I S and IA S: an inertia's (rigid or articulated) column along the joint's unit
// motion: the force I e_z picks from I without a multiplication (and without the
// products with S's zeros, which IEEE arithmetic keeps: 0 * x is not folded).
template <class S>
SCANDYN_HD Force<S> inertia_joint_column(const Inertia<S>& I, const ZJointBody<S>& b) {
  const bool rev = b.type == JointType::Revolute;
  // revolute: {Ibar e_z, -h x e_z}; prismatic: {h x e_z, m e_z}  (h x e_z = (h.y, -h.x, 0))
  return {Vec3<S>{rev ? I.I.xz : I.h.y, rev ? I.I.yz : -I.h.x, rev ? I.I.zz : S(0)},
          Vec3<S>{rev ? -I.h.y : S(0), rev ? I.h.x : S(0), rev ? S(0) : I.m}};
}
template <class S>
SCANDYN_HD Force<S> inertia_joint_column(const ABInertia<S>& I, const ZJointBody<S>& b) {
  const bool rev = b.type == JointType::Revolute;
  // revolute: {Iww e_z, Iwv^T e_z} (row 2 of Iwv); prismatic: {Iwv e_z (column 2), Ivv e_z}
  const Mat3<S>& H = I.Iwv;
  return {Vec3<S>{rev ? I.Iww.xz : H.m[2], rev ? I.Iww.yz : H.m[5], rev ? I.Iww.zz : H.m[8]},
          Vec3<S>{rev ? H.m[6] : I.Ivv.xz, rev ? H.m[7] : I.Ivv.yz, rev ? H.m[8] : I.Ivv.zz}};
}

// The joint's unit axis in its body frame: the stored one, or +z.
template <class S>
SCANDYN_HD Vec3<S> joint_axis(const Body<S>& b) {
  return b.axis;
}
template <class S>
SCANDYN_HD Vec3<S> joint_axis(const ZJointBody<S>&) {
  return {S(0), S(0), S(1)};
}

// The base's spatial acceleration: gravity entered as a base acceleration -g.
template <class S>
SCANDYN_HD Motion<S> base_acceleration(const Vec3<S>& gravity) {
  return {Vec3<S>::zero(), -gravity};
}

// A pivot of a factorisation (ABA's D_i = S_i^T IA_i S_i, a diagonal entry of the
// L^T L factorisation of M) is usable when it is positive and finite: false for
// zero, negative values, NaN and +inf.
template <class S>
SCANDYN_HD bool pivot_ok(S d) {
  return d > S(0) && ScalarMath<S>::isfinite(d);
}

// ---- RNEA -------------------------------------------------------------------

// The net force on a body moving with velocity v and acceleration a (body frame,
// Featherstone (2008) 5.3):
//   f = I a + v x* I v - fext
// fext: the external wrench on the body, or null for none. The RNEA's forward step,
// the scans over links (CPU and CUDA) and the per-instance functions all take their
// body forces from here.
template <class S, class Bd>
SCANDYN_HD Force<S> body_force(const Bd& b, const Motion<S>& v, const Motion<S>& a,
                               const Force<S>* fext = nullptr) {
  const Force<S> f = b.I * a + cross(v, b.I * v);
  return fext ? f - *fext : f;
}

// Forward step: body velocity v, acceleration a and net body force f
//   v = Xup v_parent + S qd
//   a = Xup a_parent + S qdd + v x (S qd)
//   f = I a + v x* I v - fext
template <class S>
struct RneaForward {
  Motion<S> v;  // body velocity, body frame
  Motion<S> a;  // body acceleration (gravity included), body frame
  Force<S> f;   // force the parent transmits across the joint, before children
};

template <class S, class Bd>
SCANDYN_HD RneaForward<S> rnea_forward_step(const Bd& b, const Transform<S>& Xup,
                                            const Motion<S>& v_parent, const Motion<S>& a_parent,
                                            S qd, S qdd) {
  RneaForward<S> o;
  o.v = add_joint_motion(b, Xup.apply(v_parent), qd);
  o.a = add_joint_motion(b, Xup.apply(a_parent), qdd) + cross_joint_motion(b, o.v, qd);
  o.f = body_force(b, o.v, o.a);
  return o;
}

// ---- CRBA -------------------------------------------------------------------

// Composite step, leaves to root: body i's composite inertia Ic (its own plus its
// subtree's) expressed in its parent's frame, Xup^T Ic Xup; the caller adds it to
// the parent's: Ic_parent += crba_composite_step(Xup, Ic), children in descending
// order.
template <class S>
SCANDYN_HD Inertia<S> crba_composite_step(const Transform<S>& Xup, const Inertia<S>& Ic) {
  return Ic.transform_transpose(Xup);
}

// Column i of M starts from the force F = Ic_i S_i (M_ii = S_i^T F) ...
template <class S, class Bd>
SCANDYN_HD Force<S> crba_column_force(const Bd& b, const Inertia<S>& Ic) {
  return inertia_joint_column(Ic, b);
}

// ... and is carried to the root one joint at a time: F = Xup_j^T F moves it from
// body j's frame to its parent p's, where M_ip = M_pi = S_p^T F.
template <class S>
SCANDYN_HD Force<S> crba_column_step(const Transform<S>& Xup, const Force<S>& F) {
  return Xup.apply_transpose(F);
}

// ---- ABA --------------------------------------------------------------------

// Pass 1 step: velocity, velocity-product acceleration c and bias force pA.
template <class S>
struct AbaForward {
  Motion<S> v;  // body velocity
  Motion<S> c;  // v x (S qd)
  Force<S> pA;  // bias force v x* I v (external force subtracted by the caller)
};

// The velocity-product acceleration c = v x (S qd) of a body moving with v.
template <class S, class Bd>
SCANDYN_HD Motion<S> aba_velocity_product(const Bd& b, const Motion<S>& v, S qd) {
  return cross_joint_motion(b, v, qd);
}

// The bias force v x* I v of a body moving with v (pA before external forces).
template <class S, class Bd>
SCANDYN_HD Force<S> aba_bias_force(const Bd& b, const Motion<S>& v) {
  return cross(v, b.I * v);
}

template <class S, class Bd>
SCANDYN_HD AbaForward<S> aba_forward_step(const Bd& b, const Transform<S>& Xup,
                                          const Motion<S>& v_parent, S qd) {
  AbaForward<S> o;
  o.v = add_joint_motion(b, Xup.apply(v_parent), qd);
  o.c = aba_velocity_product(b, o.v, qd);
  o.pA = aba_bias_force(b, o.v);
  return o;
}

// Pass 2 step: with the body's articulated inertia IA and bias force pA complete,
// computes U = IA S, D = S^T U (+ armature), u = tau - S^T pA and the contributions
//   Ia = IA - U U^T / D,  pa = pA + Ia c + U u / D
// that the parent receives as Xup^T Ia Xup and Xup^T pa.
//
// armature: a joint-space inertia added to the joint's own diagonal entry of M (a
// rotor's reflected inertia, or the simulator's dt d + dt^2 k of implicit damping
// and springs, scandyn/sim/integrators.hpp): M + diag(armature) is the mass matrix
// of the same tree with a massless rotor of that inertia on each joint, and in the
// ABA it enters only D (Featherstone 2008, 7.3 / exercise 7.3). 0 adds nothing
// (D + 0 == D exactly).
template <class S, class Bd>
SCANDYN_HD void aba_joint_terms(const Bd& b, const ABInertia<S>& IA, const Force<S>& pA,
                                S tau, Force<S>& U, S& D, S& u, S armature = S(0)) {
  U = inertia_joint_column(IA, b);
  D = joint_project(b, U) + armature;
  u = tau - joint_project(b, pA);
}

template <class S>
SCANDYN_HD void aba_backward_to_parent(const Transform<S>& Xup, const ABInertia<S>& IA,
                                       const Force<S>& pA, const Motion<S>& c, const Force<S>& U,
                                       S D, S u, ABInertia<S>& IA_parent, Force<S>& pA_parent) {
  const S Dinv = S(1) / D;
  const ABInertia<S> Ia = IA.minus_outer(U, Dinv);
  const Force<S> pa = pA + Ia * c + (u * Dinv) * U;
  IA_parent += Ia.transform_transpose(Xup);
  pA_parent += Xup.apply_transpose(pa);
}

// Pass 3 step: a' = Xup a_parent + c, qdd = (u - U^T a') / D, a = a' + S qdd.
template <class S, class Bd>
SCANDYN_HD S aba_acceleration_step(const Bd& b, const Transform<S>& Xup,
                                   const Motion<S>& a_parent, const Motion<S>& c,
                                   const Force<S>& U, S D, S u, Motion<S>& a) {
  const Motion<S> ap = Xup.apply(a_parent) + c;
  const S qdd = (u - dot(ap, U)) / D;
  a = add_joint_motion(b, ap, qdd);
  return qdd;
}

// ---- hybrid dynamics (Featherstone 2008, 9.2) ---------------------------------
//
// The articulated-body hybrid dynamics: each DoF has either its force tau_i given
// (its acceleration unknown: the ABA's steps above) or its acceleration qdd_i given
// (prescribed motion, its force unknown: the steps below). A prescribed joint is
// rigid for the articulated-body recursion: the parent receives the body's whole
// articulated inertia, and its bias force moved by the known joint acceleration.
// Pass 2 computes U = IA S and u = -S^T pA for it with aba_joint_terms(tau = 0) (no
// pivot: D is not divided by); pass 3 gives its force from them.

// Pass 2 step of a prescribed joint: Ia = IA, pa = pA + IA (c + S qdd), which the
// parent receives as Xup^T Ia Xup and Xup^T pa.
template <class S, class Bd>
SCANDYN_HD void hybrid_prescribed_to_parent(const Bd& b, const Transform<S>& Xup, const ABInertia<S>& IA,
                                            const Force<S>& pA, const Motion<S>& c, S qdd,
                                            ABInertia<S>& IA_parent, Force<S>& pA_parent) {
  const Force<S> pa = pA + IA * add_joint_motion(b, c, qdd);
  IA_parent += IA.transform_transpose(Xup);
  pA_parent += Xup.apply_transpose(pa);
}

// Pass 3 step of a prescribed joint: a = Xup a_parent + c + S qdd, and the joint
// force tau = S^T (IA a + pA) = U^T a - u (U = IA S, u = -S^T pA from pass 2), the
// force the articulated body beyond the joint needs to move with a.
template <class S, class Bd>
SCANDYN_HD S hybrid_prescribed_acceleration_step(const Bd& b, const Transform<S>& Xup,
                                                 const Motion<S>& a_parent, const Motion<S>& c,
                                                 const Force<S>& U, S u, S qdd, Motion<S>& a) {
  a = add_joint_motion(b, Xup.apply(a_parent) + c, qdd);
  return dot(a, U) - u;
}

// ---- joints of any type (spherical and free included) -----------------------
// The general path of every algorithm, for models with multi-DoF joints
// (ModelTpl::multi_dof()): q and qd point at the body's own entries (b.idx_q,
// b.idx_v); a 1-DoF joint goes through the functions above, unchanged. Motion
// subspaces: revolute / prismatic the axis; spherical S = [I3; 0]; free S = I6, both
// in the body frame (Featherstone 2008, table 4.1; a free joint's qd is the body's
// own twist and its S is constant in the body frame, so v x (S qd) = 0 at the root).

// Largest number of DoFs of one joint.
inline constexpr int kMaxJointDofs = 6;

// Xup = XJ(q) Xtree at the joint's positions q (b.idx_q's entries).
template <Trig kTrig = Trig::Exact, class S>
SCANDYN_HD Transform<S> joint_transform_at(const Body<S>& b, const S* q) {
  if (b.type == JointType::Spherical)  // XJ = rot(R^T): E = R^T Etree, r = rtree
    return {mul_transpose(quat_to_matrix(q), b.Xtree.E), b.Xtree.r};
  if (b.type == JointType::Free)  // XJ: pose (R, p) of the body in its parent
    return Transform<S>::from_pose(quat_to_matrix(q + 3), Vec3<S>{q[0], q[1], q[2]}) * b.Xtree;
  return joint_transform<kTrig>(b, q[0]);
}

// Column k of S (k < joint_nv(b.type)).
template <class S>
SCANDYN_HD Motion<S> joint_column(const Body<S>& b, int k) {
  if (b.type == JointType::Revolute || b.type == JointType::Prismatic) return joint_motion(b, S(1));
  return {Vec3<S>{S(k == 0), S(k == 1), S(k == 2)}, Vec3<S>{S(k == 3), S(k == 4), S(k == 5)}};
}

// S qd for the joint's rates qd (b.idx_v's entries).
template <class S>
SCANDYN_HD Motion<S> joint_motion_at(const Body<S>& b, const S* qd) {
  if (b.type == JointType::Spherical) return {Vec3<S>{qd[0], qd[1], qd[2]}, Vec3<S>::zero()};
  if (b.type == JointType::Free) return {Vec3<S>{qd[0], qd[1], qd[2]}, Vec3<S>{qd[3], qd[4], qd[5]}};
  return joint_motion(b, qd[0]);
}

// S^T f, written to out (joint_nv(b.type) entries).
template <class S>
SCANDYN_HD void joint_project_at(const Body<S>& b, const Force<S>& f, S* out) {
  if (b.type == JointType::Revolute || b.type == JointType::Prismatic) {
    out[0] = joint_project(b, f);
    return;
  }
  out[0] = f.n.x, out[1] = f.n.y, out[2] = f.n.z;
  if (b.type == JointType::Free) out[3] = f.f.x, out[4] = f.f.y, out[5] = f.f.z;
}

// Entry k of S^T f (k < joint_nv(b.type)): joint_project_at's out[k].
template <class S>
SCANDYN_HD S joint_project_entry(const Body<S>& b, const Force<S>& f, int k) {
  if (b.type == JointType::Revolute || b.type == JointType::Prismatic) return joint_project(b, f);
  switch (k) {
    case 0: return f.n.x;
    case 1: return f.n.y;
    case 2: return f.n.z;
    case 3: return f.f.x;
    case 4: return f.f.y;
    default: return f.f.z;
  }
}

// RNEA forward step at any joint (qdd null: zero accelerations).
template <class S>
SCANDYN_HD RneaForward<S> rnea_forward_step_at(const Body<S>& b, const Transform<S>& Xup,
                                               const Motion<S>& v_parent, const Motion<S>& a_parent,
                                               const S* qd, const S* qdd) {
  if (b.type == JointType::Revolute || b.type == JointType::Prismatic)
    return rnea_forward_step(b, Xup, v_parent, a_parent, qd[0], qdd ? qdd[0] : S(0));
  RneaForward<S> o;
  const Motion<S> vJ = joint_motion_at(b, qd);
  o.v = Xup.apply(v_parent) + vJ;
  o.a = Xup.apply(a_parent) + cross(o.v, vJ);
  if (qdd) o.a = o.a + joint_motion_at(b, qdd);
  o.f = body_force(b, o.v, o.a);
  return o;
}

// ABA pass 1 at any joint.
template <class S>
SCANDYN_HD AbaForward<S> aba_forward_step_at(const Body<S>& b, const Transform<S>& Xup,
                                             const Motion<S>& v_parent, const S* qd) {
  if (b.type == JointType::Revolute || b.type == JointType::Prismatic)
    return aba_forward_step(b, Xup, v_parent, qd[0]);
  AbaForward<S> o;
  const Motion<S> vJ = joint_motion_at(b, qd);
  o.v = Xup.apply(v_parent) + vJ;
  o.c = cross(o.v, vJ);
  o.pA = aba_bias_force(b, o.v);
  return o;
}

// ABA pass 2 at a joint of nj = joint_nv(b.type) DoFs (Featherstone 2008, 7.3):
// U = IA S, D = S^T U + diag(armature), u = tau - S^T pA, with D factored as L L^T
// and carried as Y = U L^-T (nj forces) and w = L^-1 u, so that U D^-1 U^T = Y Y^T and
// U D^-1 u = Y w. L is written row k at L[k * kMaxJointDofs] (lower triangle).
// Returns the first k whose pivot is not positive and finite, or -1. For nj = 1 this
// is not the 1-DoF path's arithmetic (aba_joint_terms), which 1-DoF joints keep.
//
// (D's entries and S^T pA are read one at a time, joint_project_entry, not from an
// array that joint_project_at fills: in the floating-base ABA kernel for chains,
// nvcc (CUDA 13, sm_90) read that array's linear entries wrongly, the pivot at DoF
// 3 failing for every state.)
// kNj: the joint's DoFs when known at compile time (6: the floating base in the
// thread kernels, whose loops then run over constant indices), else 0.
template <int kNj = 0, class S>
SCANDYN_HD int aba_joint_terms_at(const Body<S>& b, const ABInertia<S>& IA, const Force<S>& pA,
                                  const S* tau, Force<S>* Y, S* L, S* w, const S* armature) {
  const int nj = kNj > 0 ? kNj : joint_nv(b.type);
  for (int k = 0; k < nj; ++k) Y[k] = IA * joint_column(b, k);  // U
  for (int k = 0; k < nj; ++k) {
    const Force<S> Uk = Y[k];  // column k of D: S^T U_k
    // Cholesky row by row: L_kl for l < k from D_kl, then the pivot
    for (int l = 0; l < k; ++l) {
      S x = joint_project_entry(b, Uk, l);
      for (int m = 0; m < l; ++m) x -= L[k * kMaxJointDofs + m] * L[l * kMaxJointDofs + m];
      L[k * kMaxJointDofs + l] = x / L[l * kMaxJointDofs + l];
    }
    S d = joint_project_entry(b, Uk, k) + (armature ? armature[k] : S(0));
    for (int m = 0; m < k; ++m) d -= L[k * kMaxJointDofs + m] * L[k * kMaxJointDofs + m];
    if (!pivot_ok(d)) return k;
    L[k * kMaxJointDofs + k] = ScalarMath<S>::sqrt(d);
  }
  // Y = U L^-T (forward substitution over columns), w = L^-1 (tau - S^T pA)
  for (int k = 0; k < nj; ++k) {
    Force<S> y = Y[k];
    S x = tau[k] - joint_project_entry(b, pA, k);
    for (int l = 0; l < k; ++l) {
      const S Lkl = L[k * kMaxJointDofs + l];
      y = y - Lkl * Y[l];
      x -= Lkl * w[l];
    }
    const S inv = S(1) / L[k * kMaxJointDofs + k];
    Y[k] = inv * y;
    w[k] = inv * x;
  }
  return -1;
}

// ABA pass 2, the parent's share at a joint of nj DoFs:
//   Ia = IA - Y Y^T,  pa = pA + Ia c + Y w,  IA_parent += Xup^T Ia Xup,  pA_parent += Xup^T pa.
template <class S>
SCANDYN_HD void aba_backward_to_parent_at(int nj, const Transform<S>& Xup, const ABInertia<S>& IA,
                                          const Force<S>& pA, const Motion<S>& c, const Force<S>* Y,
                                          const S* w, ABInertia<S>& IA_parent, Force<S>& pA_parent) {
  ABInertia<S> Ia = IA;
  for (int k = 0; k < nj; ++k) Ia = Ia.minus_outer(Y[k], S(1));
  Force<S> pa = pA + Ia * c;
  for (int k = 0; k < nj; ++k) pa = pa + w[k] * Y[k];
  IA_parent += Ia.transform_transpose(Xup);
  pA_parent += Xup.apply_transpose(pa);
}

// ABA pass 3 at a joint of nj DoFs: a' = Xup a_parent + c, qdd = L^-T (w - Y^T a'),
// a = a' + S qdd.
// (kNj as for aba_joint_terms_at.)
template <int kNj = 0, class S>
SCANDYN_HD void aba_acceleration_step_at(const Body<S>& b, const Transform<S>& Xup,
                                         const Motion<S>& a_parent, const Motion<S>& c,
                                         const Force<S>* Y, const S* L, const S* w, S* qdd,
                                         Motion<S>& a) {
  const int nj = kNj > 0 ? kNj : joint_nv(b.type);
  const Motion<S> ap = Xup.apply(a_parent) + c;
  for (int k = nj - 1; k >= 0; --k) {
    S x = w[k] - dot(ap, Y[k]);
    for (int l = k + 1; l < nj; ++l) x -= L[l * kMaxJointDofs + k] * qdd[l];
    qdd[k] = x / L[k * kMaxJointDofs + k];
  }
  a = ap + joint_motion_at(b, qdd);
}

}  // namespace scandyn
