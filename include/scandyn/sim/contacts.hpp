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

// The world pose and twist of every body (the contact pass's kinematics):
// X[i] body i <- world, v[i] body i's twist in its frame. q and qd at q[j * stride].
template <class S, class Bd>
SCANDYN_HD void contact_kinematics(const Bd* bodies, Index n, const S* q, const S* qd, long long stride,
                                   Transform<S>* X, Motion<S>* v) {
  for (Index i = 0; i < n; ++i) {
    const Bd& b = bodies[i];
    const Transform<S> Xup = joint_transform(b, q[i * stride]);
    X[i] = b.parent < 0 ? Xup : Xup * X[b.parent];
    v[i] = add_joint_motion(b, b.parent < 0 ? Motion<S>::zero() : Xup.apply(v[b.parent]), qd[i * stride]);
  }
}

// contact_kinematics for a model with multi-DoF joints (a floating base, ball
// joints): q (nq) and qd (nv) contiguous, bodies[0..nb) with idx_q / idx_v set.
// The floating base's joint places body 0 in the world from q's first 7 entries
// (position, quaternion), so X is body <- world for every body.
template <class S>
SCANDYN_HD void contact_kinematics_at(const Body<S>* bodies, Index nb, const S* q, const S* qd, Transform<S>* X,
                                      Motion<S>* v) {
  for (Index i = 0; i < nb; ++i) {
    const Body<S>& b = bodies[i];
    const Transform<S> Xup = joint_transform_at(b, q + b.idx_q);
    X[i] = b.parent < 0 ? Xup : Xup * X[b.parent];
    const Motion<S> vJ = joint_motion_at(b, qd + b.idx_v);
    v[i] = b.parent < 0 ? vJ : Xup.apply(v[b.parent]) + vJ;
  }
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

// Body j's Xup and S_j qd_j in the contact pass: q[j * stride], qd[j * stride] for
// 1-DoF bodies, or (kMultiDof) the entries at the body's idx_q / idx_v.
template <bool kMultiDof, class S, class Bd>
SCANDYN_HD Transform<S> contact_joint_transform(const Bd& b, Index j, const S* q, long long stride) {
  if constexpr (kMultiDof) return joint_transform_at(b, q + b.idx_q);
  else return joint_transform(b, q[j * stride]);
}
template <bool kMultiDof, class S, class Bd>
SCANDYN_HD Motion<S> contact_joint_motion(const Bd& b, Index j, const S* qd, long long stride) {
  if constexpr (kMultiDof) return joint_motion_at(b, qd + b.idx_v);
  else return add_joint_motion(b, Motion<S>::zero(), qd[j * stride]);
}

// Body i's pose X (body i <- world) and twist v (its frame) by one walk from i to
// the root, with no per-body scratch: X = Xup_i Xup_p(i) ... and v = sum over the
// path of X_{i <- j} S_j qd_j (the same quantities as contact_kinematics, products
// associated from the leaf).
template <bool kMultiDof, class S, class Bd>
SCANDYN_HD void contact_path_kinematics(const Bd* bodies, Index i, const S* q, const S* qd, long long stride,
                                        Transform<S>& X, Motion<S>& v) {
  X = contact_joint_transform<kMultiDof>(bodies[i], i, q, stride);
  v = contact_joint_motion<kMultiDof>(bodies[i], i, qd, stride);
  for (Index j = bodies[i].parent; j >= 0; j = bodies[j].parent) {
    v += X.apply(contact_joint_motion<kMultiDof>(bodies[j], j, qd, stride));
    X = X * contact_joint_transform<kMultiDof>(bodies[j], j, q, stride);
  }
}

// Should the contact pass walk each point's path to the root (contact_path_kinematics)
// rather than compute every body's pose and twist into per-body scratch? Yes when the
// walks visit at most twice as many bodies as there are (a few points, as on a robot's
// feet): the walks are arithmetic in registers, where the scratch is per-thread memory
// on the GPU (its traffic made the floating hyq's step 2.3x slower with four feet).
// All-link points on a chain (ropes) visit n^2 / 2 bodies: the per-body pass.
template <class S, class Bd>
bool contact_walks_paths(const Bd* bodies, Index nb, const ContactPoint<S>* points, Index npoints) {
  long long visits = 0;
  for (Index k = 0; k < npoints; ++k)
    for (Index j = points[k].body; j >= 0 && visits <= 2LL * nb; j = bodies[j].parent) ++visits;
  return visits <= 2LL * nb;
}

// The contact pass of one instance at (q, qd) (q[j * stride]): adds every point's
// contact wrench to fext (n body wrenches, body frames); with armature (n, or
// null) adds the implicit bound; readings (P, or null) get the points' forces.
// X, v: n entries of scratch, not touched when cs.walk_paths (each point's body by
// contact_path_kinematics instead). h: the look-ahead (dt for implicit, else 0).
// bodies: Body<S> (the user's frames) or ZJointBody<S> (z-axis frames,
// scandyn/model/joint_frames.hpp); the points' positions and fext are in the same frames.
// kMultiDof: a model with multi-DoF joints (joint_transform_at; Body<S> only; n
// bodies, q with nq and qd and armature with nv entries, stride 1).
template <unsigned kObstacles, bool kMultiDof = false, class S, class Bd>
SCANDYN_HD void contact_pass(const ContactSet<S>& cs, const Bd* bodies, Index n, const S* q, const S* qd,
                             long long stride, S h, Transform<S>* X, Motion<S>* v, Force<S>* fext, S* armature,
                             ContactReading<S>* readings) {
  if (!cs.walk_paths) {
    if constexpr (kMultiDof) {
      (void)stride;
      contact_kinematics_at(bodies, n, q, qd, X, v);
    } else {
      contact_kinematics(bodies, n, q, qd, stride, X, v);
    }
  }
  for (Index k = 0; k < cs.npoints; ++k) {
    const ContactPoint<S>& cp = cs.points[k];
    const Index i = cp.body;
    Transform<S> Xi;
    Motion<S> vi;
    if (cs.walk_paths) contact_path_kinematics<kMultiDof>(bodies, i, q, qd, stride, Xi, vi);
    else Xi = X[i], vi = v[i];
    const Vec3<S> p = mul_transpose(Xi.E, cp.position) + Xi.r;
    const Vec3<S> pv = mul_transpose(Xi.E, vi.v + cross(vi.w, cp.position));
    // implicit: the diagonal of the pair's J^T W J on the joints of the point's path to the base
    auto add = [&](Index j, const Vec3<S>& nrm, S wn, S wt, auto&& column) {
      if constexpr (kMultiDof) {
        for (int c = 0; c < joint_nv(bodies[j].type); ++c) {
          const Vec3<S> col = column(c);
          const S a = dot(nrm, col);
          armature[bodies[j].idx_v + c] += wn * a * a + wt * (dot(col, col) - a * a);
        }
      } else {
        const Vec3<S> col = column(0);
        const S a = dot(nrm, col);
        armature[j] += wn * a * a + wt * (dot(col, col) - a * a);
      }
    };
    auto touched = [&](const Vec3<S>& nrm, S wn, S wt) {
      if (!armature) return;
      if (cs.walk_paths) {
        // in body i's frame: T = (i <- j) along the path, the point at cp.position
        const Vec3<S> ni = Xi.E * nrm;
        Transform<S> T = Transform<S>::identity();
        for (Index j = i; j >= 0; j = bodies[j].parent) {
          const Vec3<S> lever = cp.position + T.E * T.r;  // the point minus body j's origin
          add(j, ni, wn, wt, [&](int c) {
            return contact_column(bodies[j], c, [&](const Vec3<S>& e) { return T.E * e; }, lever);
          });
          T = T * contact_joint_transform<kMultiDof>(bodies[j], j, q, stride);
        }
        return;
      }
      for (Index j = i; j >= 0; j = bodies[j].parent)
        add(j, nrm, wn, wt, [&](int c) {
          return contact_column(bodies[j], c, [&](const Vec3<S>& e) { return mul_transpose(X[j].E, e); }, p - X[j].r);
        });
    };
    const Vec3<S> f = contact_point_force<kObstacles>(cs, p, pv, cp.radius, h, readings ? readings + k : nullptr, touched);
    const Vec3<S> fb = Xi.E * f;
    fext[i].n += cross(cp.position, fb);
    fext[i].f += fb;
  }
}

// contact_pass with the specialisation of cs.obstacles chosen at run time (one
// switch per pass: planes only, spheres only, both).
template <bool kMultiDof = false, class S, class Bd>
SCANDYN_HD void contact_pass_any(const ContactSet<S>& cs, const Bd* bodies, Index n, const S* q, const S* qd,
                                 long long stride, S h, Transform<S>* X, Motion<S>* v, Force<S>* fext, S* armature,
                                 ContactReading<S>* readings) {
  switch (cs.obstacles) {
    case kPlanes: contact_pass<kPlanes, kMultiDof>(cs, bodies, n, q, qd, stride, h, X, v, fext, armature, readings); break;
    case kSpheres: contact_pass<kSpheres, kMultiDof>(cs, bodies, n, q, qd, stride, h, X, v, fext, armature, readings); break;
    case kPlanes | kSpheres:
      contact_pass<kPlanes | kSpheres, kMultiDof>(cs, bodies, n, q, qd, stride, h, X, v, fext, armature, readings);
      break;
    default:  // no obstacles: the points touch nothing
      for (Index k = 0; readings && k < cs.npoints; ++k) readings[k] = {Vec3<S>::zero(), S(0), 0};
      break;
  }
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
