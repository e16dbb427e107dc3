// scandyn/sim/contacts.hpp: the contact effect: spheres fixed on links against
// fixed world planes and spheres, a compliant normal law and regularised Coulomb
// friction. One SCANDYN_HD routine, shared by the serial and OpenMP step
// (cpu_fallback/simulator_step.cpp) and the CUDA steps (kernels/sim_fused.cuh,
// kernels/simulator_step.cu).
//
// Geometry. A contact point is a sphere of radius rho >= 0 whose centre c is fixed
// in body i's frame. "World" is the frame of the model's fixed base, or for a
// floating base the frame its pose (q's first 7 entries) is given in
// (contact_kinematics_at). With X_i (body
// i <- world, (E, r)) and v_i (body i's twist in its frame, [w; v] of its origin),
// the centre is at p = E^T c + r and moves with p_dot = E^T (v + w x c).
// Obstacles:
//   plane  {x : n . x = o}, unit normal n pointing out of the solid side:
//          penetration d = o + rho - n . p, contact normal n;
//   sphere centre s, radius R: d = R + rho - |p - s|, contact normal (p - s) / |p - s|.
// A pair touches when d > 0; its penetration rate is d_dot = -n . p_dot.
//
// Normal law (a clamped linear spring-damper, Kelvin-Voigt, never pulling):
//   f_n = max(0, k (d + h d_dot) + c d_dot)          (d > 0; zero otherwise)
// k = "stiffness" (N/m), c = "damping" (N s/m), h the implicit integrator's look-ahead
// (dt for implicit, 0 for euler and rk4; see below). The contact ends when the
// force reaches zero (k d + c d_dot = 0), slightly before d = 0 on the way out.
// Closed forms the tests use: a point of mass m resting on a plane sinks to
// d = m g / k; a body of mass m landing with speed v0 leaves when k d + c d_dot = 0
// on the solution of m d'' = -k d - c d' + m g (d(0) = 0, d'(0) = v0), which the
// tests solve exactly and compare the bounce height with.
//
// Friction (regularised Coulomb, viscous below a creep speed):
//   f_t = -mu f_n v_t / max(|v_t|, v_s)
// v_t = p_dot - (n . p_dot) n the sliding velocity, mu = "friction", v_s =
// "creep_speed" (m/s, default 1e-3). |f_t| <= mu f_n always (inside the Coulomb
// cone); sliding faster than v_s feels exactly mu f_n; a load that static friction
// would hold (tangential load F < mu f_n) creeps at |v_t| = v_s F / (mu f_n) < v_s:
// v_s is the stated creep tolerance.
//
// The force on each point, f = f_n n + f_t summed over the obstacles, enters the
// dynamics as the body wrench of body i in its frame about its origin,
// [c x E f; E f], added to the external wrenches (fext) every forward dynamics
// takes, so every engine and backend gets it.
//
// The implicit integrator (sim/integrators.hpp) treats the contacts' stiffness and
// damping linearised, as the joints': the normal force looks h = dt ahead, and
// each touching pair adds to the joint-space armature the diagonal of its
// linearised stiffness and damping J^T W J, W = wn n n^T + wt (I - n n^T), wn =
// dt c + dt^2 k, wt = dt mu f_n / max(|v_t|, v_s) (J: the point's 3 x nv Jacobian,
// columns J_j for the joints j on its path to the base): armature_j += wn (n .
// J_j)^2 + wt (|J_j|^2 - (n . J_j)^2). Exact when one joint moves the point (a
// hinged rod) or the joints move it along orthogonal directions (a point on
// prismatic x, y, z); otherwise the diagonal of a coupled matrix, whose stable dt
// is measured (docs/scenes.md, "Contacts"). The rest state is exact: the armature
// multiplies qdd only. Cost: one walk to the base per touching pair. (A diagonal
// dominating the whole matrix, Gershgorin's a_j sum_l |a_l|, would make a frozen
// contact set unconditionally stable, but it puts so much inertia on the joints
// near a rope's base that its changes from step to step pump energy into a
// whipping rope; with the exact diagonal the drape scenes stay stable, see
// docs/scenes.md for where it is not.)
#pragma once

#include <type_traits>

#include "scandyn/algorithm/steps.hpp"
#include "scandyn/config.hpp"
#include "scandyn/spatial.hpp"

namespace scandyn {
namespace sim {

// A contact point: a sphere fixed on a body.
template <class S>
struct ContactPoint {
  Index body;         // the body (DoF index) it is fixed on
  Vec3<S> position;   // its centre in the body's frame (m)
  S radius;           // >= 0 (m)
};

// A fixed world plane {x : normal . x = offset}; normal unit, out of the solid.
template <class S>
struct ContactPlane {
  Vec3<S> normal;
  S offset;  // (m)
};

// A fixed world sphere.
template <class S>
struct ContactSphere {
  Vec3<S> center;  // (m)
  S radius;        // > 0 (m)
};

// The contact law's coefficients (see the header comment).
template <class S>
struct ContactLaw {
  S stiffness;    // k >= 0 (N/m)
  S damping;      // c >= 0 (N s/m)
  S friction;     // mu >= 0
  S creep_speed;  // v_s > 0 (m/s)
};

// Which obstacles a scene declares: the contact loop is specialised on them.
enum ContactObstacles : unsigned { kPlanes = 1u, kSpheres = 2u };

// Everything the contact pass reads (pointers into the backend's memory).
template <class S>
struct ContactSet {
  const ContactPoint<S>* points = nullptr;    // (P)
  Index npoints = 0;
  const ContactPlane<S>* planes = nullptr;    // (nplanes)
  Index nplanes = 0;
  const ContactSphere<S>* spheres = nullptr;  // (nspheres)
  Index nspheres = 0;
  ContactLaw<S> law{};
  unsigned obstacles = 0;                     // ContactObstacles bits of the non-empty lists
  bool walk_paths = false;                    // contact_walks_paths: each point's pose by a walk
                                              // to the root, no per-body scratch
};

// One point's contact after a step (the state the step started from; rk4: its
// first stage): the per-instance output Simulator::contact_forces() exposes.
template <class S>
struct ContactReading {
  Vec3<S> force;    // total contact force on the point, world frame (N)
  S depth;          // largest penetration over the obstacles (m), 0 when apart
  int in_contact;   // 1 when some obstacle pushes on it (f_n > 0), else 0
};

// The force of one obstacle on one point (normal n, penetration d > 0, rate d_dot,
// centre velocity pv), look-ahead h. Returns f_n (>= 0); adds f_n n + f_t to f;
// gain gets the friction's velocity gain mu f_n / max(|v_t|, v_s).
template <class S>
SCANDYN_HD S contact_pair_force(const ContactLaw<S>& law, const Vec3<S>& n, S d, const Vec3<S>& pv, S h,
                                Vec3<S>& f, S& gain) {
  const S d_dot = -dot(n, pv);
  S fn = law.stiffness * (d + h * d_dot) + law.damping * d_dot;
  if (!(fn > S(0))) return S(0);
  const Vec3<S> vt = pv - dot(n, pv) * n;
  const S speed = ScalarMath<S>::sqrt(dot(vt, vt));
  gain = law.friction * fn / (speed > law.creep_speed ? speed : law.creep_speed);
  f += fn * n;
  f -= gain * vt;
  return fn;
}

// The forces of every obstacle on one point with centre p moving at pv (world
// frame). Returns the total force; reading (when not null) gets it with the depth
// and the flag; touched(n, wn, wt) is called for each pair that pushes, with the
// implicit weights of the header comment: wn = h c + h^2 k along the normal n, wt
// = h mu f_n / max(|v_t|, v_s) across it (zero when h is).
template <unsigned kObstacles, class S, class Touched>
SCANDYN_HD Vec3<S> contact_point_force(const ContactSet<S>& cs, const Vec3<S>& p, const Vec3<S>& pv, S rho, S h,
                                       ContactReading<S>* reading, Touched&& touched) {
  const ContactLaw<S>& law = cs.law;
  Vec3<S> f = Vec3<S>::zero();
  S depth = S(0);
  bool touching = false;
  const S wn = h * law.damping + h * h * law.stiffness;
  auto pair = [&](const Vec3<S>& n, S d) {
    if (!(d > S(0))) return;
    depth = d > depth ? d : depth;
    S gain = S(0);
    if (contact_pair_force(law, n, d, pv, h, f, gain) > S(0)) {
      touching = true;
      touched(n, wn, h * gain);
    }
  };
  if constexpr ((kObstacles & kPlanes) != 0) {
    for (Index k = 0; k < cs.nplanes; ++k) {
      const ContactPlane<S>& pl = cs.planes[k];
      pair(pl.normal, pl.offset + rho - dot(pl.normal, p));
    }
  }
  if constexpr ((kObstacles & kSpheres) != 0) {
    for (Index k = 0; k < cs.nspheres; ++k) {
      const ContactSphere<S>& sp = cs.spheres[k];
      const Vec3<S> e = p - sp.center;
      const S dist = ScalarMath<S>::sqrt(dot(e, e));
      if (!(dist > S(0))) continue;  // the centre at the obstacle's centre: no normal
      pair(S(1) / dist * e, sp.radius + rho - dist);
    }
  }
  if (reading) *reading = {f, depth, touching ? 1 : 0};
  return f;
}

// Column k of a point's Jacobian for body b's joint (the point's velocity per unit
// rate of the joint's DoF k) in any frame F: turn(e) takes a direction of body b's
// frame to F, lever is the point minus b's origin (F). A 1-DoF joint (k = 0) moves
// about or along its axis; a ball joint's and the free joint's k < 3 rotate about
// the body's axes through its origin, the free joint's k >= 3 translate along them.
template <class S, class Bd, class Turn>
SCANDYN_HD Vec3<S> contact_column(const Bd& b, int k, Turn&& turn, const Vec3<S>& lever) {
  if (b.type == JointType::Revolute) return cross(turn(joint_axis(b)), lever);
  if (b.type == JointType::Prismatic) return turn(joint_axis(b));
  const Vec3<S> axis = turn(Vec3<S>{S(k % 3 == 0), S(k % 3 == 1), S(k % 3 == 2)});
  return k < 3 ? cross(axis, lever) : axis;
}

// The model as the contact pass walks it, at one instance's (q, qd): a "path" gives
// body j's parent (-1 at the root; parents before children), its Xup (parent ->
// body j), its joint's motion S_j qd_j, and its joint's DoFs with their Jacobian
// columns (for_each_column(j, turn, lever, f): f(DoF, column) for each, as
// contact_column). ContactBodyPath: an array of bodies, q[j * stride] and
// qd[j * stride] for 1-DoF joints, or (kMultiDof; Body<S> only, stride 1) the
// entries at each body's idx_q / idx_v. The floating-base thread kernels walk their
// own model the same way (kernels/sim_fused.cuh).
template <bool kMultiDof, class S, class Bd>
struct ContactBodyPath {
  const Bd* bodies;
  const S* q;
  const S* qd;
  long long stride;
  SCANDYN_HD Index parent(Index j) const { return bodies[j].parent; }
  SCANDYN_HD Transform<S> xup(Index j) const {
    if constexpr (kMultiDof) return joint_transform_at(bodies[j], q + bodies[j].idx_q);
    else return joint_transform(bodies[j], q[j * stride]);
  }
  SCANDYN_HD Motion<S> motion(Index j) const {
    if constexpr (kMultiDof) return joint_motion_at(bodies[j], qd + bodies[j].idx_v);
    else return add_joint_motion(bodies[j], Motion<S>::zero(), qd[j * stride]);
  }
  template <class Turn, class F>
  SCANDYN_HD void for_each_column(Index j, Turn&& turn, const Vec3<S>& lever, F&& f) const {
    if constexpr (kMultiDof) {
      for (int c = 0; c < joint_nv(bodies[j].type); ++c) f(bodies[j].idx_v + c, contact_column(bodies[j], c, turn, lever));
    } else {
      f(j, contact_column(bodies[j], 0, turn, lever));
    }
  }
};

// f(std::integral_constant<unsigned, K>{}) with K the obstacles cs declares (planes
// only, spheres only, both: the contact loop's specialisations, one switch); false,
// without calling f, when it declares none.
template <class S, class F>
SCANDYN_HD bool with_obstacles(const ContactSet<S>& cs, F&& f) {
  switch (cs.obstacles) {
    case kPlanes: f(std::integral_constant<unsigned, kPlanes>{}); return true;
    case kSpheres: f(std::integral_constant<unsigned, kSpheres>{}); return true;
    case kPlanes | kSpheres: f(std::integral_constant<unsigned, kPlanes | kSpheres>{}); return true;
    default: return false;
  }
}

// One point's centre p and its velocity pv (world frame) from its body's pose Xi
// (body <- world) and twist vi (body frame).
template <class S>
SCANDYN_HD void contact_point_motion(const ContactPoint<S>& cp, const Transform<S>& Xi, const Motion<S>& vi, Vec3<S>& p,
                                     Vec3<S>& pv) {
  p = mul_transpose(Xi.E, cp.position) + Xi.r;
  pv = mul_transpose(Xi.E, vi.v + cross(vi.w, cp.position));
}

// The wrench of a force fb (body frame) on the point cp, added to its body's wrench f.
template <class S>
SCANDYN_HD void add_point_wrench(const ContactPoint<S>& cp, const Vec3<S>& fb, Force<S>& f) {
  f.n += cross(cp.position, fb);
  f.f += fb;
}

// The contact wrench of point cp at its body's pose and twist (explicit: no
// look-ahead, no implicit diagonal) with the obstacles chosen at run time, added to
// f (the body's wrench, its frame); reading (or null) gets the point's contact.
template <class S>
SCANDYN_HD void add_contact_point_wrench(const ContactSet<S>& cs, const ContactPoint<S>& cp, const Transform<S>& Xi,
                                         const Motion<S>& vi, ContactReading<S>* reading, Force<S>& f) {
  Vec3<S> p, pv;
  contact_point_motion(cp, Xi, vi, p, pv);
  auto none = [](const Vec3<S>&, S, S) {};
  Vec3<S> fw = Vec3<S>::zero();
  if (!with_obstacles(cs, [&](auto k) {
        fw = contact_point_force<decltype(k)::value>(cs, p, pv, cp.radius, S(0), reading, none);
      })) {
    if (reading) *reading = {Vec3<S>::zero(), S(0), 0};  // no obstacles: the point touches nothing
    return;
  }
  add_point_wrench(cp, Xi.E * fw, f);
}

// The world pose and twist of bodies 0..n-1 of a path (the contact pass's per-body
// kinematics): X[i] body i <- world, v[i] body i's twist in its frame.
template <class S, class Path>
SCANDYN_HD void contact_path_poses(const Path& path, Index n, Transform<S>* X, Motion<S>* v) {
  for (Index i = 0; i < n; ++i) {
    const Index p = path.parent(i);
    const Transform<S> Xup = path.xup(i);
    X[i] = p < 0 ? Xup : Xup * X[p];
    v[i] = p < 0 ? path.motion(i) : Xup.apply(v[p]) + path.motion(i);
  }
}

// contact_path_poses over bodies with q and qd at q[j * stride].
template <class S, class Bd>
SCANDYN_HD void contact_kinematics(const Bd* bodies, Index n, const S* q, const S* qd, long long stride,
                                   Transform<S>* X, Motion<S>* v) {
  contact_path_poses(ContactBodyPath<false, S, Bd>{bodies, q, qd, stride}, n, X, v);
}

// contact_kinematics for a model with multi-DoF joints (a floating base, ball
// joints): q (nq) and qd (nv) contiguous, bodies[0..nb) with idx_q / idx_v set.
// The floating base's joint places body 0 in the world from q's first 7 entries
// (position, quaternion), so X is body <- world for every body.
template <class S>
SCANDYN_HD void contact_kinematics_at(const Body<S>* bodies, Index nb, const S* q, const S* qd, Transform<S>* X,
                                      Motion<S>* v) {
  contact_path_poses(ContactBodyPath<true, S, Body<S>>{bodies, q, qd, 1}, nb, X, v);
}

// The column of a world point p for a 1-DoF joint j (world frame), X = body j <- world.
template <class S, class Bd>
SCANDYN_HD Vec3<S> contact_jacobian_column(const Bd& b, const Transform<S>& X, const Vec3<S>& p) {
  return contact_column(b, 0, [&](const Vec3<S>& e) { return mul_transpose(X.E, e); }, p - X.r);
}

// Column k of a world point p for body b's joint of any type (world frame).
template <class S>
SCANDYN_HD Vec3<S> contact_jacobian_column_at(const Body<S>& b, const Transform<S>& X, const Vec3<S>& p, int k) {
  return contact_column(b, k, [&](const Vec3<S>& e) { return mul_transpose(X.E, e); }, p - X.r);
}

// Body i's pose X (body i <- world) and twist v (its frame) by one walk from i to
// the root, with no per-body scratch: X = Xup_i Xup_p(i) ... and v = sum over the
// path of X_{i <- j} S_j qd_j (the same quantities as contact_path_poses, products
// associated from the leaf).
template <class S, class Path>
SCANDYN_HD void contact_path_kinematics(const Path& path, Index i, Transform<S>& X, Motion<S>& v) {
  X = path.xup(i);
  v = path.motion(i);
  for (Index j = path.parent(i); j >= 0; j = path.parent(j)) {
    v += X.apply(path.motion(j));
    X = X * path.xup(j);
  }
}

// Should the contact pass walk each point's path to the root (contact_path_kinematics)
// rather than compute every body's pose and twist into per-body scratch? Yes when the
// walks visit at most twice as many bodies as there are (a few points, as on a robot's
// feet): the walks are arithmetic in registers, where the scratch is per-thread memory
// on the GPU. All-link points on a chain (ropes) visit n^2 / 2 bodies: the per-body pass.
template <class S, class Bd>
bool contact_walks_paths(const Bd* bodies, Index nb, const ContactPoint<S>* points, Index npoints) {
  long long visits = 0;
  for (Index k = 0; k < npoints; ++k)
    for (Index j = points[k].body; j >= 0 && visits <= 2LL * nb; j = bodies[j].parent) ++visits;
  return visits <= 2LL * nb;
}

// The contact pass of one instance over a path (see ContactBodyPath) of n bodies:
// adds every point's contact wrench to fext (n body wrenches, the path's body
// frames, in which the points' positions are); with armature (the path's DoFs, or
// null) adds the implicit bound; readings (P, or null) get the points' forces.
// X, v: n entries of scratch, not touched when cs.walk_paths (each point's body by
// contact_path_kinematics instead). h: the look-ahead (dt for implicit, else 0).
// qforce (the path's DoFs, or null): with cs.walk_paths, the contacts go there as
// generalized forces instead, sum over points of J(p)^T f (the columns of the
// point's walk; the same joint-space dynamics as the body wrenches), and fext is
// not touched (it may be null): no per-body array at all.
template <unsigned kObstacles, class S, class Path>
SCANDYN_HD void contact_pass_on(const Path& path, const ContactSet<S>& cs, Index n, S h, Transform<S>* X,
                                Motion<S>* v, Force<S>* fext, S* armature, ContactReading<S>* readings,
                                S* qforce = nullptr) {
  if (!cs.walk_paths) contact_path_poses(path, n, X, v);
  // f(col, dof) for every joint column on the path from body i to the root, in body
  // i's frame (Xi: body i <- world), the point at c (body i's frame)
  auto walk_columns = [&](Index i, const Vec3<S>& c, auto&& f) {
    Transform<S> T = Transform<S>::identity();  // (i <- j)
    for (Index j = i; j >= 0; j = path.parent(j)) {
      path.for_each_column(j, [&](const Vec3<S>& e) { return T.E * e; }, c + T.E * T.r, f);  // lever: c minus j's origin
      if (path.parent(j) >= 0) T = T * path.xup(j);
    }
  };
  for (Index k = 0; k < cs.npoints; ++k) {
    const ContactPoint<S>& cp = cs.points[k];
    const Index i = cp.body;
    Transform<S> Xi;
    Motion<S> vi;
    if (cs.walk_paths) contact_path_kinematics(path, i, Xi, vi);
    else Xi = X[i], vi = v[i];
    Vec3<S> p, pv;
    contact_point_motion(cp, Xi, vi, p, pv);
    // implicit: the diagonal of the pair's J^T W J on the joints of the point's path to the base
    auto touched = [&](const Vec3<S>& nrm, S wn, S wt) {
      if (!armature) return;
      auto add = [&](const Vec3<S>& nj) {
        return [&, nj](Index dof, const Vec3<S>& col) {
          const S a = dot(nj, col);
          armature[dof] += wn * a * a + wt * (dot(col, col) - a * a);
        };
      };
      if (cs.walk_paths) {
        walk_columns(i, cp.position, add(Xi.E * nrm));
        return;
      }
      for (Index j = i; j >= 0; j = path.parent(j))
        path.for_each_column(j, [&](const Vec3<S>& e) { return mul_transpose(X[j].E, e); }, p - X[j].r, add(nrm));
    };
    const Vec3<S> f = contact_point_force<kObstacles>(cs, p, pv, cp.radius, h, readings ? readings + k : nullptr, touched);
    const Vec3<S> fb = Xi.E * f;
    if (qforce && cs.walk_paths) {
      if (fb.x != S(0) || fb.y != S(0) || fb.z != S(0))
        walk_columns(i, cp.position, [&](Index dof, const Vec3<S>& col) { qforce[dof] += dot(col, fb); });
      continue;
    }
    add_point_wrench(cp, fb, fext[i]);
  }
}

// contact_pass_on over bodies (Body<S>, the user's frames, or ZJointBody<S>, z-axis
// frames, scandyn/model/joint_frames.hpp; the points' positions and fext in the same
// frames), q and qd at q[j * stride]; kMultiDof: a model with multi-DoF joints
// (Body<S> only; n bodies, q with nq and qd and armature with nv entries, stride 1).
template <unsigned kObstacles, bool kMultiDof = false, class S, class Bd>
SCANDYN_HD void contact_pass(const ContactSet<S>& cs, const Bd* bodies, Index n, const S* q, const S* qd,
                             long long stride, S h, Transform<S>* X, Motion<S>* v, Force<S>* fext, S* armature,
                             ContactReading<S>* readings, S* qforce = nullptr) {
  contact_pass_on<kObstacles>(ContactBodyPath<kMultiDof, S, Bd>{bodies, q, qd, stride}, cs, n, h, X, v, fext, armature,
                              readings, qforce);
}

// contact_pass_on with the specialisation of cs.obstacles chosen at run time (one
// switch per pass: planes only, spheres only, both).
template <class S, class Path>
SCANDYN_HD void contact_pass_on_any(const Path& path, const ContactSet<S>& cs, Index n, S h, Transform<S>* X,
                                    Motion<S>* v, Force<S>* fext, S* armature, ContactReading<S>* readings,
                                    S* qforce = nullptr) {
  if (!with_obstacles(cs, [&](auto k) {
        contact_pass_on<decltype(k)::value>(path, cs, n, h, X, v, fext, armature, readings, qforce);
      }))  // no obstacles: the points touch nothing
    for (Index k = 0; readings && k < cs.npoints; ++k) readings[k] = {Vec3<S>::zero(), S(0), 0};
}

// contact_pass (over bodies) with the obstacles chosen at run time.
template <bool kMultiDof = false, class S, class Bd>
SCANDYN_HD void contact_pass_any(const ContactSet<S>& cs, const Bd* bodies, Index n, const S* q, const S* qd,
                                 long long stride, S h, Transform<S>* X, Motion<S>* v, Force<S>* fext, S* armature,
                                 ContactReading<S>* readings) {
  contact_pass_on_any(ContactBodyPath<kMultiDof, S, Bd>{bodies, q, qd, stride}, cs, n, h, X, v, fext, armature,
                      readings);
}

// One forward dynamics' wrenches and implicit armature with the contacts in: the
// contact pass at (q, qd) over copies of fext (nb wrenches, null: none) into f and
// of arm (nv, null for explicit integrators) into arm_out, which gets the
// contacts' diagonal (h = dt when arm is given); fext and arm then point at the
// copies. X, v: nb scratch. readings written, then nulled (an rk4 step reports its
// first stage's contacts). The caller skips it for a scene without contact points.
template <bool kMultiDof, class S, class Bd>
SCANDYN_HD void add_contact_wrenches(const ContactSet<S>& cs, const Bd* bodies, Index nb, Index nv, S dt, const S* q,
                                     const S* qd, const Force<S>*& fext, const S*& arm, Transform<S>* X, Motion<S>* v,
                                     Force<S>* f, S* arm_out, ContactReading<S>*& readings) {
  for (Index i = 0; i < nb; ++i) f[i] = fext ? fext[i] : Force<S>::zero();
  if (arm)
    for (Index i = 0; i < nv; ++i) arm_out[i] = arm[i];
  contact_pass_any<kMultiDof>(cs, bodies, nb, q, qd, 1, arm ? dt : S(0), X, v, f, arm ? arm_out : nullptr, readings);
  readings = nullptr;
  fext = f;
  if (arm) arm = arm_out;
}

// The elastic energy of the contacts at the world positions of the points: sum
// over touching pairs of 1/2 k d^2 (a diagnostic; the clamp and the damping make
// the law dissipative, never a source).
template <class S>
SCANDYN_HD S contact_energy_at(const ContactSet<S>& cs, const Vec3<S>& p, S rho) {
  S e = S(0);
  for (Index k = 0; k < cs.nplanes; ++k) {
    const S d = cs.planes[k].offset + rho - dot(cs.planes[k].normal, p);
    if (d > S(0)) e += S(0.5) * cs.law.stiffness * d * d;
  }
  for (Index k = 0; k < cs.nspheres; ++k) {
    const Vec3<S> x = p - cs.spheres[k].center;
    const S d = cs.spheres[k].radius + rho - ScalarMath<S>::sqrt(dot(x, x));
    if (d > S(0)) e += S(0.5) * cs.law.stiffness * d * d;
  }
  return e;
}

}  // namespace sim
}  // namespace scandyn
