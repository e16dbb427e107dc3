// scandyn/algorithm/chain_fd.hpp: forward dynamics of unbranched chains as
// associative scans over the links, with O(log n) span.
//
// The articulated-body algorithm (Featherstone, RBDA ch. 7) on a chain is four
// recursions; each is written here as the application of a per-link map, and the
// maps compose associatively, so a chain of n links is cut into chunks, each chunk's
// maps are composed into one aggregate, the aggregates are scanned (recursively, in
// chunks again) and every chunk then walks its links with the serial ABA step
// functions from the value at its boundary. Every link's result is therefore
// computed by the serial recursion; the scans only supply the chunk boundary values.
//
//   pass 0, root to leaf:  v_i = Xup_i v_{i-1} + S_i qd_i                 (Affine6)
//   pass 1, leaf to root:  the articulated inertias, carried in the dual
//                          (constraint-space) form Y_i = T_i^T IA_i^{-1} T_i (DualRiccati)
//   pass 2, leaf to root:  z_i = pA_i + Ia_i c_i + U_i u_i / D_i, the force body i
//                          passes to its parent (the seed's z scan)       (Affine6)
//   pass 3, root to leaf:  a_i = Xup_i a_{i-1} + c_i + S_i qdd_i          (Affine6)
//
// Pass 1 is the Riccati recursion of ABA,
//   IA_i = I_i + Xup_{i+1}^T Ia_{i+1} Xup_{i+1},  Ia = IA - U U^T / D,  U = IA S,  D = S^T U.
// Its projection Ia is singular (Ia S = 0), so the recursion is not a composition of
// well-defined Möbius maps in IA; in the constraint space it is. With T_i (6x5) a
// basis of the forces a joint transmits without doing work (S_i^T T_i = 0),
//   Ia_i = T_i (T_i^T IA_i^{-1} T_i)^{-1} T_i^T = T_i Y_i^{-1} T_i^T,
// and with Phi_i = I_i^{-1} and B_{i+1} = Xup_{i+1}^T T_{i+1} (Woodbury),
//   Y_i = Q_i - C_i (Y_{i+1} + R_i)^{-1} C_i^T,
//   [Q_i C_i; C_i^T R_i] = [T_i B_{i+1}]^T Phi_i [T_i B_{i+1}].
// Maps of the form Y -> Q - C (Y + R)^{-1} C^T are closed under composition:
//   (a o b)(Y): W = Q_b + R_a,  Q = Q_a - C_a W^{-1} C_a^T,  C = C_a W^{-1} C_b,
//               R = R_b - C_b^T W^{-1} C_b,
// which is one step of block cyclic reduction on the chain's constraint-force
// system; W is the relative mobility across a joint, symmetric positive definite,
// so every composition solves a well-conditioned 5x5 SPD system (no pivoting).
//
// Several instances of the chain are one sequence of links g = b * n + i. A link
// with no parent (i = 0) or no child (i = n - 1) has an element that ignores its
// input (M = 0, or C = 0), so scans run across instance boundaries unchanged.
//
// A free rope (the floating base, body 0's free joint, then 1-DoF links, each the
// previous one's child) is one chain whose first link has no parent either: its
// velocity element is the constant base twist, and its element of pass 1 and 2 is
// never read (nothing lies above the base). Pass 1's scan delivers the projected
// articulated inertia of link 1 to the base, whose 6x6 articulated inertia
// IA_0 = I_0 + Xup_1^T Ia_1 Xup_1 the walk of pass 1 keeps (per instance); pass 2's
// walk, with z_1, solves the base's acceleration from it (the steps of the serial
// ABA's general path, aba_joint_terms_at and aba_acceleration_step_at: a Cholesky
// factor of IA_0), and that acceleration is pass 3's constant first element.
// Spherical joints are not offered (their 3-DoF joints break the 5-dimensional
// constraint space of the dual Riccati maps).
//
// The same holds inside an instance whose model is several unbranched chains
// hanging from the base (every body's parent the previous body or the base, bodies
// numbered chain by chain: a curtain of ropes, a hand's fingers on a fixed palm):
// the chains are independent (the base absorbs their forces), so each chain's first
// link has no parent and each chain's last link no child, exactly as at an
// instance boundary.
#pragma once

#include <atomic>
#include <chrono>
#include <cmath>
#include <memory>
#include <vector>

#include "scandyn/algorithm/steps.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/spatial/small_matrix.hpp"

namespace scandyn {

template <class S>
using Mat5 = SmallMat<S, 5, 5>;

// ---- scan elements ----------------------------------------------------------

// x -> M x + b on 6-vectors (motions or forces). A constant map (an instance's
// first link forward, its last backward) ignores its input exactly: composing with
// it never multiplies by the other side, so a NaN in one instance stays there.
template <class S>
struct Affine6 {
  Mat6<S> M;              // (6x6) linear part (zero and unused when constant)
  Vec6<S> b;              // (6) offset
  bool constant = false;  // x -> b

  using Value = Vec6<S>;
  SCANDYN_HD static Affine6 make_constant(const Vec6<S>& b) { return {Mat6<S>::zero(), b, true}; }
  SCANDYN_HD Value apply(const Value& x) const { return constant ? b : M * x + b; }
  // (outer o inner)(x) = outer(inner(x))
  SCANDYN_HD static Affine6 compose(const Affine6& outer, const Affine6& inner) {
    if (outer.constant) return outer;
    if (inner.constant) return make_constant(outer.M * inner.b + outer.b);
    return {outer.M * inner.M, outer.M * inner.b + outer.b, false};
  }
  SCANDYN_HD static Value start() { return Vec6<S>::zero(); }
};

// Y -> Q - C (Y + R)^{-1} C^T on symmetric positive definite 5x5 Y; a leaf's map
// (constant: C = R = 0) is Y -> Q, and composing with it stays exact as above.
template <class S>
struct DualRiccati {
  Mat5<S> Q;              // (5x5) symmetric
  Mat5<S> C;              // (5x5)
  Mat5<S> R;              // (5x5) symmetric
  bool constant = false;  // Y -> Q

  using Value = Mat5<S>;
  SCANDYN_HD Value apply(const Value& Y) const {
    if (constant) return Q;
    Mat5<S> L = Y + R;
    Mat5<S> Z = transpose(C);  // (Y + R)^{-1} C^T
    if (!cholesky(L)) return nan_value();
    cholesky_solve(L, Z);
    return symmetrize(Q - C * Z);
  }
  SCANDYN_HD static DualRiccati compose(const DualRiccati& a, const DualRiccati& b) {
    if (a.constant) return a;
    Mat5<S> W = b.Q + a.R;
    Mat5<S> Za = transpose(a.C);  // W^{-1} C_a^T
    if (!cholesky(W)) return {nan_value(), nan_value(), nan_value(), b.constant};
    cholesky_solve(W, Za);
    const Mat5<S> Q = symmetrize(a.Q - a.C * Za);
    if (b.constant) return {Q, Mat5<S>::zero(), Mat5<S>::zero(), true};
    Mat5<S> Zb = b.C;  // W^{-1} C_b
    cholesky_solve(W, Zb);
    return {Q, transpose(Za) * b.C, symmetrize(b.R - mul_transpose(b.C, Zb)), false};
  }
  SCANDYN_HD static Value start() { return Mat5<S>::identity(); }  // absorbed by every leaf
  SCANDYN_HD static Value nan_value() {
    Mat5<S> o;
    for (int k = 0; k < 25; ++k) o.m[k] = S(NAN);
    return o;
  }
};

// ---- per-link constants -----------------------------------------------------

// Phi = I^{-1} of a rigid body, stored through its centre of mass c (10 scalars):
//   I^{-1} [n; f] = [w; c x w + f / m],  w = Ic^{-1} (n - c x f),
// Ic the rotational inertia about the centre of mass.
template <class S>
struct InverseInertia {
  Sym3<S> Ic_inv;  // (3x3) inverse rotational inertia about the centre of mass
  Vec3<S> c;       // centre of mass in the body frame
  S m_inv;         // 1 / mass

  // A body without positive mass and positive definite Ic gives non-finite entries.
  // (SCANDYN_HD: the hybrid chain's pass 1 inverts composite inertias per instance on
  // the device too, scandyn/algorithm/chain_hybrid.hpp.)
  SCANDYN_HD static InverseInertia from(const Inertia<S>& I) {
    InverseInertia o;
    o.m_inv = S(1) / I.m;
    o.c = o.m_inv * I.h;
    // Ic = Ibar - m (|c|^2 1 - c c^T)
    Sym3<S> Ic = I.I + sym_outer(o.c, I.m);
    const S cc = I.m * dot(o.c, o.c);
    Ic.xx -= cc; Ic.yy -= cc; Ic.zz -= cc;
    // inverse by cofactors
    const S a = Ic.xx, b = Ic.yy, c = Ic.zz, d = Ic.xy, e = Ic.xz, f = Ic.yz;
    const S A = b * c - f * f, B = e * f - d * c, C = d * f - b * e;
    const S det = a * A + d * B + e * C;
    const S r = S(1) / det;
    o.Ic_inv = {r * A, r * (a * c - e * e), r * (a * b - d * d), r * B, r * C, r * (d * e - a * f)};
    return o;
  }

  template <class T>
  SCANDYN_HD InverseInertia<T> cast() const {
    return {Ic_inv.template cast<T>(), c.template cast<T>(), T(m_inv)};
  }

  SCANDYN_HD Motion<S> operator*(const Force<S>& f) const {
    const Vec3<S> w = Ic_inv * (f.n - cross(c, f.f));
    return {w, cross(c, w) + m_inv * f.f};
  }
};

// Column k (0..4) of T: a basis of the forces a joint transmits without working on
// its motion S (S^T T = 0), orthonormal. Revolute about a: the moments
// perpendicular to a (e1, e2) and every linear force; prismatic along a: every
// moment and the linear forces perpendicular to a.
template <class S>
SCANDYN_HD void perpendicular_basis(const Vec3<S>& a, Vec3<S>& e1, Vec3<S>& e2) {
  using std::fabs;
  using std::sqrt;
  const Vec3<S> t = fabs(a.x) < S(0.6) ? Vec3<S>{S(1), S(0), S(0)}
                                       : (fabs(a.y) < S(0.6) ? Vec3<S>{S(0), S(1), S(0)} : Vec3<S>{S(0), S(0), S(1)});
  Vec3<S> p = cross(a, t);
  p = (S(1) / sqrt(dot(p, p))) * p;
  e1 = p;
  e2 = cross(a, p);
}

template <class T, class S>
SCANDYN_HD Force<T> constraint_force_in(const Body<S>& b, int k) {
  Vec3<T> e1, e2;
  perpendicular_basis(b.axis.template cast<T>(), e1, e2);
  const Vec3<T> z = Vec3<T>::zero();
  const Vec3<T> unit[3] = {{T(1), T(0), T(0)}, {T(0), T(1), T(0)}, {T(0), T(0), T(1)}};
  if (b.type == JointType::Revolute) {
    if (k == 0) return {e1, z};
    if (k == 1) return {e2, z};
    return {z, unit[k - 2]};
  }
  if (k < 3) return {unit[k], z};
  return {z, k == 3 ? e1 : e2};
}
template <class S>
SCANDYN_HD Force<S> constraint_force(const Body<S>& b, int k) {
  return constraint_force_in<S>(b, k);
}

// The scalar of pass 1's dual Riccati maps, whatever the precision of the rest:
// Y = T^T IA^{-1} T mixes the mobilities of neighbouring links, whose ratio is the
// inverse of their mass ratio, and Y^{-1} recovers Ia from it. In float that loses
// the lighter side once neighbouring masses differ by 10^5 or more (a wrong qdd
// without any failed pivot); in double it holds (mass ratios of 10^6 within 1e-8).
using DualScalar = double;

// Ia = T K T^T: the articulated inertia passed across a joint, from K = Y^{-1}
// (computed in K's scalar T).
template <class T, class S>
SCANDYN_HD ABInertia<T> constraint_congruence(const Body<S>& b, const Mat5<T>& K) {
  SmallMat<T, 6, 5> Tb;
  for (int k = 0; k < 5; ++k) {
    const Vec6<T> t = to_vec6(constraint_force_in<T>(b, k));
    for (int r = 0; r < 6; ++r) Tb(r, k) = t.m[r];
  }
  return to_abinertia(Tb * K * transpose(Tb));
}

// The articulated inertia Ia = T Y^{-1} T^T that a body passes to its parent, from
// its dual Y (NaN when Y is not positive definite), in the scalar T (pass 1's; the
// hybrid's prescribed runs take it in it), or rounded to the body's scalar.
template <class T, class S>
SCANDYN_HD ABInertia<T> articulated_from_dual_in(const Body<S>& b, const Mat5<DualScalar>& Y) {
  using D = DualScalar;
  Mat5<D> L = Y;
  Mat5<D> K = Mat5<D>::identity();
  if (!cholesky(L)) K = DualRiccati<D>::nan_value();
  else cholesky_solve(L, K);
  return constraint_congruence(b, symmetrize(K)).template cast<T>();
}
template <class S>
SCANDYN_HD ABInertia<S> articulated_from_dual(const Body<S>& b, const Mat5<DualScalar>& Y) {
  return articulated_from_dual_in<S>(b, Y);
}

// Pass 1's element of link i: Y_{i+1} -> Y_i. Xup_next is link i + 1's transform;
// has_child false gives the leaf element (C = R = 0, Y_i = T_i^T Phi_i T_i).
template <class S>
SCANDYN_HD DualRiccati<DualScalar> dual_element(const Body<S>& b, const InverseInertia<DualScalar>& Phi, bool has_child,
                                                const Body<S>& next, const Transform<S>& Xup_next_s) {
  using D = DualScalar;
  const Transform<D> Xup_next = Xup_next_s.template cast<D>();
  Force<D> G[10];       // [T_i, B_{i+1}] as forces in body i's frame
  Motion<D> PhiG[10];   // Phi_i G
  const int cols = has_child ? 10 : 5;
  for (int k = 0; k < 5; ++k) G[k] = constraint_force_in<D>(b, k);
  if (has_child)
    for (int k = 0; k < 5; ++k) G[5 + k] = Xup_next.apply_transpose(constraint_force_in<D>(next, k));
  for (int k = 0; k < cols; ++k) PhiG[k] = Phi * G[k];
  DualRiccati<D> e{Mat5<D>::zero(), Mat5<D>::zero(), Mat5<D>::zero(), !has_child};
  for (int r = 0; r < 5; ++r)
    for (int c = 0; c < 5; ++c) {
      e.Q(r, c) = dot(PhiG[c], G[r]);
      if (has_child) {
        e.C(r, c) = dot(PhiG[5 + c], G[r]);
        e.R(r, c) = dot(PhiG[5 + c], G[5 + r]);
      }
    }
  e.Q = symmetrize(e.Q);
  e.R = symmetrize(e.R);
  return e;
}

// ---- the chain and its per-link scratch -------------------------------------

// B instances of an n-link model of unbranched chains from the base (every body's
// parent the previous one or the base) and the per-link scratch of the passes; link
// g = b * n + i is body i of instance b. Pointers are host or device memory, as the
// driver needs. kBase: link 0 of every instance is a floating base (a free rope); the
// drivers instantiate the walks for it separately, so that a fixed chain's walks
// carry no code (and no registers) of the base's.
template <class S, bool kBase = false>
struct ChainFdData {
  Index n = 0;                              // links per instance (nbodies)
  Index batch = 0;                          // instances B
  Index dq = 0, dv = 0;                     // a floating base's extra entries of q (6) and qd (5):
                                            // link i > 0 at q row i + dq, qd / tau / qdd row i + dv
  const Body<S>* body = nullptr;            // (table) distinct bodies; parent: -1 (the base) or
                                            // kChainPrevious (the previous link), see ChainBodies
  const InverseInertia<DualScalar>* Phi = nullptr;  // (table) their inverse inertias (pass 1's scalar)
  const int* body_class = nullptr;          // (n) table entry of body i
  Motion<S> a0;                             // base acceleration (-gravity)
  BatchView<const S> q, qd, tau;            // (n x B) inputs
  const Force<S>* fext = nullptr;           // optional (B x n) body wrenches
  BatchView<S> qdd;                         // (n x B) output
  Motion<S>* v = nullptr;                   // (B n) body velocities (pass 0)
  Force<S>* U = nullptr;                    // (B n) IA S (pass 1)
  S* D = nullptr;                           // (B n) S^T IA S (pass 1)
  Force<S>* w = nullptr;                    // (B n) Ia c (pass 1)
  S* u = nullptr;                           // (B n) tau - S^T pA (pass 2)
  Motion<S>* a = nullptr;                   // optional (B n): body accelerations, gravity included (pass 3)
  ABInertia<S>* IA_out = nullptr;           // optional (B n): articulated inertias IA, children's included (pass 1)
  Force<S>* pA_out = nullptr;               // optional (B n): articulated bias forces pA, children's included (pass 2)
  int* failed = nullptr;                    // (B) -1, or the first DoF whose pivot D failed
  // a floating base (link 0 a free joint), per instance:
  ABInertia<S>* IA_base = nullptr;          // (B) the base's articulated inertia IA_0 (pass 1)
  Motion<S>* a_base = nullptr;              // (B) its acceleration, gravity included (pass 2)
  Vec6<S>* qdd_base = nullptr;              // (B) its qdd_0..5 (pass 2)

  // the drivers' setup: a batch's views (batch = in.q.batch), and a floating base's
  // rows and per-instance scratch (each B entries)
  void bind(const FdBatchIn<S>& in, const BatchView<S>& qdd_out) {
    batch = in.q.batch;
    q = in.q;
    qd = in.qd;
    tau = in.tau;
    fext = in.fext;
    qdd = qdd_out;
  }
  void bind_base(ABInertia<S>* IA, Motion<S>* a, Vec6<S>* qdd_b) {
    dq = 6;
    dv = 5;
    IA_base = IA;
    a_base = a;
    qdd_base = qdd_b;
  }

  SCANDYN_HD Index count() const { return n * batch; }
  SCANDYN_HD Index link(Index g) const { return g % n; }
  SCANDYN_HD Index instance(Index g) const { return g / n; }
  SCANDYN_HD bool has_parent(Index g) const { return body_of(g).parent != -1; }  // (body 0's is -1)
  SCANDYN_HD bool has_child(Index g) const { return g % n != n - 1 && body_of(g + 1).parent != -1; }
  SCANDYN_HD const Body<S>& body_of(Index g) const { return body[body_class[g % n]]; }
  SCANDYN_HD const InverseInertia<DualScalar>& Phi_of(Index g) const { return Phi[body_class[g % n]]; }
  // rows of link i (> 0 for a floating base) in q and in qd, tau, qdd
  SCANDYN_HD Index q_row(Index i) const { return kBase && i > 0 ? i + dq : i; }
  SCANDYN_HD Index v_row(Index i) const { return kBase && i > 0 ? i + dv : i; }
  SCANDYN_HD bool is_base(Index g) const { return kBase && g % n == 0; }
  SCANDYN_HD S q_of(Index g) const { return q.at(q_row(g % n), g / n); }
  SCANDYN_HD S qd_of(Index g) const { return qd.at(v_row(g % n), g / n); }
  SCANDYN_HD S tau_of(Index g) const { return tau.at(v_row(g % n), g / n); }
  SCANDYN_HD Transform<S> Xup(Index g) const {
    if (is_base(g)) {  // the base's pose, q_0..q_6
      S qb[7];
      for (int k = 0; k < 7; ++k) qb[k] = q.at(k, g / n);
      return joint_transform_at(body_of(g), qb);
    }
    return joint_transform(body_of(g), q_of(g));
  }
  // S qd of link g: a floating base's twist, qd_0..qd_5
  SCANDYN_HD Motion<S> joint_velocity(Index g) const {
    if (is_base(g)) {
      S v[6];
      for (int k = 0; k < 6; ++k) v[k] = qd.at(k, g / n);
      return joint_motion_at(body_of(g), v);
    }
    return joint_motion(body_of(g), qd_of(g));
  }
  // bias force v x* I v - fext of link g (pass 0's velocities complete; v null:
  // the chain at rest, v = 0)
  SCANDYN_HD Force<S> pA(Index g) const {
    const Body<S>& b = body_of(g);
    const Force<S> p = v ? cross(v[g], b.I * v[g]) : Force<S>::zero();
    return fext ? p - fext[g] : p;
  }
  // v x S qd (0 at a floating base, whose velocity is its S qd, and at rest)
  SCANDYN_HD Motion<S> c(Index g) const {
    return is_base(g) || !v ? Motion<S>::zero() : cross_joint_motion(body_of(g), v[g], qd_of(g));
  }
  // Ia c of link g (pass 1; w null: the chain at rest, c = 0)
  SCANDYN_HD Force<S> w_of(Index g) const { return w ? w[g] : Force<S>::zero(); }
};

// Records that the articulated pivot of link g's joint DoF k failed: failed[instance]
// becomes the smallest such DoF (-1: none), safely from concurrent threads.
template <class S, bool kB>
SCANDYN_HD void record_failure(const ChainFdData<S, kB>& d, Index g, int k = 0) {
  int* slot = d.failed + g / d.n;
  const int dof = static_cast<int>(d.v_row(g % d.n)) + k;
#if defined(__CUDA_ARCH__)
  int cur = *slot;
  while (cur < 0 || dof < cur) {
    const int seen = atomicCAS(slot, cur, dof);
    if (seen == cur) break;
    cur = seen;
  }
#else
  int cur = __atomic_load_n(slot, __ATOMIC_RELAXED);
  while ((cur < 0 || dof < cur) &&
         !__atomic_compare_exchange_n(slot, &cur, dof, false, __ATOMIC_RELAXED, __ATOMIC_RELAXED)) {
  }
#endif
}

// ---- chunk walks: links s..e (inclusive, s <= e), shared by every driver ------

// Pass 1's element of link g (not a floating base): Y_g as a map of Y_{g+1}.
// Xnext is link g + 1's transform, read only when link g has a child.
template <class S, bool kB>
SCANDYN_HD DualRiccati<DualScalar> link_dual_element(const ChainFdData<S, kB>& d, Index g, const Transform<S>& Xnext) {
  const Body<S>& b = d.body_of(g);
  const bool child = d.has_child(g);
  return dual_element(b, d.Phi_of(g), child, child ? d.body_of(g + 1) : b, Xnext);
}

// Pass 0's aggregate of links s..e: v_e as a map of v_{s-1}.
template <class S, bool kB>
SCANDYN_HD Affine6<S> velocity_aggregate(const ChainFdData<S, kB>& d, Index s, Index e) {
  Affine6<S> agg{Mat6<S>::identity(), Vec6<S>::zero(), false};
  for (Index g = s; g <= e; ++g) {
    const Vec6<S> Sqd = to_vec6(d.joint_velocity(g));
    const Affine6<S> el = d.has_parent(g) ? Affine6<S>{to_mat6(d.Xup(g)), Sqd} : Affine6<S>::make_constant(Sqd);
    agg = Affine6<S>::compose(el, agg);
  }
  return agg;
}

// Pass 0's walk from v_{s-1}: stores v; returns pass 1's aggregate of the chunk,
// Y_s as a map of Y_{e+1} (kDual; otherwise nothing, for the hybrid).
template <bool kDual = true, class S, bool kB>
SCANDYN_HD DualRiccati<DualScalar> velocity_walk(const ChainFdData<S, kB>& d, Index s, Index e, const Vec6<S>& v_in) {
  Motion<S> v_parent = to_motion(v_in);
  Transform<S> X = d.Xup(s);
  DualRiccati<DualScalar> agg{};
  for (Index g = s; g <= e; ++g) {
    const Body<S>& b = d.body_of(g);
    // a floating base moves with its twist (c = 0); other links by the ABA step
    const Motion<S> v = d.is_base(g) ? d.joint_velocity(g)
                                     : aba_forward_step(b, X, d.has_parent(g) ? v_parent : Motion<S>::zero(),
                                                        d.qd_of(g)).v;
    d.v[g] = v;
    v_parent = v;
    const bool more = g + 1 < d.count();
    const Transform<S> Xnext = more ? d.Xup(g + 1) : X;  // the next link's (the next instance's first)
    if constexpr (kDual) {
      // a floating base: the dual of a joint that transmits every force has no
      // coordinates, and no link reads the base's (a constant map, as at a leaf)
      const DualRiccati<DualScalar> el =
          d.is_base(g) ? DualRiccati<DualScalar>{Mat5<DualScalar>::identity(), Mat5<DualScalar>::zero(),
                                                 Mat5<DualScalar>::zero(), true}
                       : link_dual_element(d, g, Xnext);
      agg = g == s ? el : DualRiccati<DualScalar>::compose(agg, el);
    }
    X = Xnext;
  }
  return agg;
}

// Pass 2's element of a link (not a floating base) with U, 1 / D, its bias force pA,
// w = Ia c and its tau: z_g as a map of z_{g+1} (child: link g + 1, whose transform
// is Xnext, is its child; otherwise constant),
//   z_g = N (pA + Xnext^T z_{g+1}) + w + U tau / D,  N = 1 - U S^T / D.
// The chain at rest (M^-1 x, scandyn/algorithm/chain_directional.hpp) has pA = w = 0.
template <class S>
SCANDYN_HD Affine6<S> bias_element(const Body<S>& b, bool child, const Transform<S>& Xnext, const Force<S>& U, S Dinv,
                                   const Force<S>& pA, const Force<S>& w, S tau) {
  Affine6<S> el = Affine6<S>::make_constant(Vec6<S>::zero());
  if (child) {
    const Mat6<S> XT = transpose(to_mat6(Xnext));
    el.constant = false;
    el.M = XT;
    const Vec6<S> Uv = to_vec6(U);
    for (int c = 0; c < 6; ++c) {
      Vec6<S> col;
      for (int r = 0; r < 6; ++r) col.m[r] = XT(r, c);
      const S st = joint_project(b, to_force(col)) * Dinv;
      for (int r = 0; r < 6; ++r) el.M(r, c) -= Uv.m[r] * st;
    }
  }
  const S sp = joint_project(b, pA);
  el.b = to_vec6(pA - (sp * Dinv) * U + w + (tau * Dinv) * U);
  return el;
}

// Pass 1's step of link g with a free 1-DoF joint, from its articulated inertia IA
// (children's included) and articulated bias force pA: U = IA S, D = S^T U (a failed
// pivot recorded, D = NaN), the projected inertia Ia = IA - U U^T / D (6x6, into
// Ia_out) and w = Ia c; stores U, D, w; returns pass 2's element of the link
// (bias_element with its tau). Shared by inertia_walk and the hybrid's walk
// (scandyn/algorithm/chain_hybrid.hpp).
template <class S, bool kB>
SCANDYN_HD Affine6<S> free_joint_step(const ChainFdData<S, kB>& d, Index g, const Body<S>& b, bool child,
                                      const Transform<S>& Xnext, const ABInertia<S>& IA, const Force<S>& pA,
                                      ABInertia<S>& Ia_out) {
  Force<S> U;
  S D, u_unused;
  aba_joint_terms(b, IA, pA, S(0), U, D, u_unused);
  if (!pivot_ok(D)) {
    record_failure(d, g);
    D = S(NAN);
  }
  const S Dinv = S(1) / D;
  const ABInertia<S> Ia = IA.minus_outer(U, Dinv);
  const Force<S> w = Ia * d.c(g);
  d.U[g] = U;
  d.D[g] = D;
  d.w[g] = w;
  Ia_out = Ia;
  return bias_element(b, child, Xnext, U, Dinv, pA, w, d.tau_of(g));
}

// Pass 1's walk from Ia_in, the projected articulated inertia of link e + 1 (its
// frame; ignored when link e has no child): the ABA articulated-inertia recursion
// over e..s with the step functions; stores U, D, w = Ia c and records a failed
// pivot; returns pass 2's aggregate of the chunk, z_s as a map of z_{e+1}.
template <class S, bool kB>
SCANDYN_HD Affine6<S> inertia_walk(const ChainFdData<S, kB>& d, Index s, Index e, const ABInertia<S>& Ia_in) {
  ABInertia<S> Ia_next = Ia_in;  // Ia of link g + 1, its frame
  Transform<S> Xnext = d.has_child(e) ? d.Xup(e + 1) : Transform<S>::identity();
  Affine6<S> agg{Mat6<S>::identity(), Vec6<S>::zero(), false};
  for (Index g = e; g >= s; --g) {
    const Body<S>& b = d.body_of(g);
    const bool child = d.has_child(g);
    ABInertia<S> IA = ABInertia<S>::from(b.I);
    if (child) IA += Ia_next.transform_transpose(Xnext);
    if (d.is_base(g)) {
      // the floating base: IA_0 for pass 2's walk; its z (nothing above) is never read
      d.IA_base[g / d.n] = IA;
      agg = Affine6<S>::compose(Affine6<S>::make_constant(Vec6<S>::zero()), agg);
      continue;  // the link before it (another instance's last) does not read Ia_next, Xnext, z_next
    }
    if (d.IA_out) d.IA_out[g] = IA;
    agg = Affine6<S>::compose(free_joint_step(d, g, b, child, Xnext, IA, d.pA(g), Ia_next), agg);
    Xnext = d.Xup(g);
  }
  return agg;
}

// Pass 2's step at a floating base g with its bias force pA (z_1 included): the
// base's acceleration and qdd from IA_0 = D (L L^T), as aba_at does it; stores them
// (a_base, qdd_base) and returns the acceleration (NaN, and the failure recorded,
// when IA_0 is not positive definite).
template <class S, bool kB>
SCANDYN_HD Motion<S> base_acceleration_walk(const ChainFdData<S, kB>& d, Index g, const Force<S>& pA) {
  const Body<S>& b = d.body_of(g);
  const Index inst = g / d.n;
  S tau[6], L[kMaxJointDofs * kMaxJointDofs], w[6], qdd[6];
  Force<S> Y[6];
  for (int k = 0; k < 6; ++k) tau[k] = d.tau.at(k, inst);
  Motion<S> a;
  const int k = aba_joint_terms_at(b, d.IA_base[inst], pA, tau, Y, L, w, static_cast<const S*>(nullptr));
  if (k >= 0) {
    record_failure(d, g, k);
    a = {Vec3<S>{S(NAN), S(NAN), S(NAN)}, Vec3<S>{S(NAN), S(NAN), S(NAN)}};
    for (int j = 0; j < 6; ++j) qdd[j] = S(NAN);
  } else {
    aba_acceleration_step_at(b, d.Xup(g), d.a0, Motion<S>::zero(), Y, L, w, qdd, a);
  }
  d.a_base[inst] = a;
  for (int j = 0; j < 6; ++j) d.qdd_base[inst].m[j] = qdd[j];
  return a;
}

// Pass 3's element of a link with a free 1-DoF joint (ABA's acceleration step as a
// map): a_g as a map of a_{g-1} from its transform X = Xup_g, c = v x S qd, U, 1 / D
// and u = tau - S^T pA,
//   a_g = N^T (X a_{g-1} + c) + S u / D,  N^T = 1 - S U^T / D,
// constant (from the base acceleration a0) at a chain's first link (no parent).
// Shared by bias_walk and the hybrid's walk (scandyn/algorithm/chain_hybrid.hpp).
template <class S>
SCANDYN_HD Affine6<S> free_acceleration_element(const Body<S>& b, bool has_parent, const Transform<S>& X,
                                                const Motion<S>& a0, const Motion<S>& c, const Force<S>& U, S Dinv,
                                                S u) {
  const Vec6<S> Uv = to_vec6(U);
  const Vec6<S> Sv = to_vec6(joint_motion(b, S(1)));
  auto project = [&](Vec6<S> x) {  // N^T x
    S t = S(0);
    for (int r = 0; r < 6; ++r) t += Uv.m[r] * x.m[r];
    t *= Dinv;
    for (int r = 0; r < 6; ++r) x.m[r] -= Sv.m[r] * t;
    return x;
  };
  const Vec6<S> Su = to_vec6(joint_motion(b, u * Dinv));
  if (!has_parent) return Affine6<S>::make_constant(project(to_vec6(X.apply(a0) + c)) + Su);
  Affine6<S> el;
  const Mat6<S> XM = to_mat6(X);
  for (int k = 0; k < 6; ++k) {
    Vec6<S> col;
    for (int r = 0; r < 6; ++r) col.m[r] = XM(r, k);
    col = project(col);
    for (int r = 0; r < 6; ++r) el.M(r, k) = col.m[r];
  }
  el.b = project(to_vec6(c)) + Su;
  el.constant = false;
  return el;
}

// Pass 2's walk from z_{e+1}: stores u = tau - S^T pA; returns pass 3's aggregate of
// the chunk, a_e as a map of a_{s-1}.
template <class S, bool kB>
SCANDYN_HD Affine6<S> bias_walk(const ChainFdData<S, kB>& d, Index s, Index e, const Vec6<S>& z_in) {
  Force<S> z_next = to_force(z_in);
  Transform<S> Xnext = d.has_child(e) ? d.Xup(e + 1) : Transform<S>::identity();
  Affine6<S> agg{Mat6<S>::identity(), Vec6<S>::zero(), false};
  for (Index g = e; g >= s; --g) {
    const Body<S>& b = d.body_of(g);
    Force<S> pA = d.pA(g);
    if (d.has_child(g)) pA += Xnext.apply_transpose(z_next);
    if (d.is_base(g)) {
      // the floating base: a_0 = IA_0^{-1} (tau_0 - pA_0), by the serial ABA's steps,
      // pass 3's constant first element
      agg = Affine6<S>::compose(agg, Affine6<S>::make_constant(to_vec6(base_acceleration_walk(d, g, pA))));
      continue;  // the link before it (another instance's last) reads neither Xnext nor z_next
    }
    if (d.pA_out) d.pA_out[g] = pA;
    const S D = d.D[g], Dinv = S(1) / D;
    const Force<S> U = d.U[g];
    const S u = d.tau_of(g) - joint_project(b, pA);
    d.u[g] = u;
    z_next = pA + d.w_of(g) + (u * Dinv) * U;
    const Transform<S> X = d.Xup(g);
    agg = Affine6<S>::compose(agg, free_acceleration_element(b, d.has_parent(g), X, d.a0, d.c(g), U, Dinv, u));
    Xnext = X;
  }
  return agg;
}

// Pass 3's walk from a_{s-1}: qdd by aba_acceleration_step.
template <class S, bool kB>
SCANDYN_HD void acceleration_walk(const ChainFdData<S, kB>& d, Index s, Index e, const Vec6<S>& a_in) {
  Motion<S> a_parent = to_motion(a_in);
  for (Index g = s; g <= e; ++g) {
    const Body<S>& b = d.body_of(g);
    Motion<S> a;
    if (d.is_base(g)) {  // pass 2's walk solved it
      const Index inst = g / d.n;
      if (d.failed[inst] < 0)
        for (int k = 0; k < 6; ++k) d.qdd.at(k, inst) = d.qdd_base[inst].m[k];
      a_parent = d.a_base[inst];
      continue;
    }
    const S qdd = aba_acceleration_step(b, d.Xup(g), d.has_parent(g) ? a_parent : d.a0, d.c(g), d.U[g], d.D[g],
                                        d.u[g], a);
    if (d.failed[g / d.n] < 0) d.qdd.at(d.v_row(g % d.n), g / d.n) = qdd;  // a failed instance's qdd stays unwritten
    if (d.a) d.a[g] = a;
    a_parent = a;
  }
}

// ---- scans of chunk aggregates, shared by every driver -------------------------
//
// A pass runs `forward` (values flow from link 0 to the last: the carry of element
// k is the value after elements 0..k-1) or backward (the carry of element k is the
// value after elements k+1..); an aggregate of elements a..b is the map from the
// value entering the range to the value leaving it.

// The aggregate of elements [a, b).
template <class E>
SCANDYN_HD E fold_range(const E* el, Index a, Index b, bool forward) {
  E agg = el[a];
  for (Index k = a + 1; k < b; ++k) agg = forward ? E::compose(el[k], agg) : E::compose(agg, el[k]);
  return agg;
}

// carry[k] for k in [a, b) from the value `in` entering the range.
template <class E>
SCANDYN_HD void carry_range(const E* el, typename E::Value* carry, Index a, Index b, bool forward,
                            typename E::Value in) {
  if (forward) {
    for (Index k = a; k < b; ++k) {
      carry[k] = in;
      in = el[k].apply(in);
    }
  } else {
    for (Index k = b - 1; k >= a; --k) {
      carry[k] = in;
      in = el[k].apply(in);
    }
  }
}

// The carried dual Y of link e + 1 as the articulated inertia the walk of pass 1
// starts from (link e + 1 exists: e is not an instance's last link).
template <class S, bool kB>
SCANDYN_HD ABInertia<S> chunk_inertia_carry(const ChainFdData<S, kB>& d, Index e, const Mat5<DualScalar>& Y) {
  return d.has_child(e) ? articulated_from_dual(d.body_of(e + 1), Y) : ABInertia<S>{};
}

// ---- the hybrid's host pass 1 (ChainInertiaCarries below) --------------------

// Pass 1's aggregate of links s..e (no floating base): Y_s as a map of Y_{e+1}, the
// composition of link_dual_element over the links (what velocity_walk returns,
// without the velocities).
template <class S, bool kB>
SCANDYN_HD DualRiccati<DualScalar> dual_aggregate(const ChainFdData<S, kB>& d, Index s, Index e) {
  DualRiccati<DualScalar> agg{};
  Transform<S> Xnext = d.Xup(s + 1 < d.count() ? s + 1 : s);
  for (Index g = s; g <= e; ++g) {
    const DualRiccati<DualScalar> el = link_dual_element(d, g, Xnext);
    agg = g == s ? el : DualRiccati<DualScalar>::compose(agg, el);
    if (g + 2 < d.count()) Xnext = d.Xup(g + 2);
  }
  return agg;
}

// The dual Y = T^T IA^{-1} T of a link with joint body b from its articulated inertia
// IA (children's included, not projected), in pass 1's scalar; NaN when IA is not
// positive definite. articulated_from_dual(b, Y) is then Ia = IA - U U^T / D.
template <class S>
SCANDYN_HD Mat5<DualScalar> dual_from_articulated(const Body<S>& b, const ABInertia<S>& IA) {
  using D = DualScalar;
  Mat6<D> L = to_mat6(IA.template cast<D>());
  SmallMat<D, 6, 5> Z;  // IA^{-1} T
  for (int k = 0; k < 5; ++k) {
    const Vec6<D> t = to_vec6(constraint_force_in<D>(b, k));
    for (int r = 0; r < 6; ++r) Z(r, k) = t.m[r];
  }
  const SmallMat<D, 6, 5> T = Z;
  if (!cholesky(L)) return DualRiccati<D>::nan_value();
  cholesky_solve(L, Z);
  return symmetrize(mul_transpose(T, Z));
}

// One step of the articulated-inertia recursion at link g (ABA pass 2's Riccati
// part): IA = I_g + Xnext^T Ia_next Xnext (Ia_next, Xnext: link g + 1's projected
// inertia and transform, read only when g has a child), U = IA S, D = S^T U,
// returns Ia = IA - U U^T / D, NaN when the pivot D is not positive and finite (the
// walk of pass 1 reports it). IA_out receives IA.
template <class S, bool kB>
SCANDYN_HD ABInertia<S> inertia_carry_step(const ChainFdData<S, kB>& d, Index g, const ABInertia<S>& Ia_next,
                                           const Transform<S>& Xnext, ABInertia<S>& IA_out) {
  const Body<S>& b = d.body_of(g);
  ABInertia<S> IA = ABInertia<S>::from(b.I);
  if (d.has_child(g)) IA += Ia_next.transform_transpose(Xnext);
  Force<S> U;
  S D, u;
  aba_joint_terms(b, IA, Force<S>::zero(), S(0), U, D, u);
  if (!pivot_ok(D)) D = S(NAN);
  IA_out = IA;
  return IA.minus_outer(U, S(1) / D);
}

// The serial recursion over chunks [c_lo, c_hi) of `chunk` links, from the last
// link of chunk c_hi - 1 down to the first of chunk c_lo: Ia_out[c] = Ia of link
// last(c) + 1 (its frame) on entering chunk c. Ia_next and Xnext carry link g + 1's
// Ia and transform in and out (link last(c_hi - 1) + 1's on entry); IA_first
// receives the articulated inertia of the group's first link.
template <class S, bool kB>
SCANDYN_HD void inertia_carry_walk(const ChainFdData<S, kB>& d, Index chunk, Index c_lo, Index c_hi,
                                   ABInertia<S>* Ia_out, ABInertia<S>& Ia_next, Transform<S>& Xnext,
                                   ABInertia<S>& IA_first) {
  const Index count = d.count();
  for (Index c = c_hi - 1; c >= c_lo; --c) {
    Ia_out[c] = Ia_next;  // unused when link last(c) has no child
    const Index last = (c + 1) * chunk < count ? (c + 1) * chunk - 1 : count - 1;
    for (Index g = last; g >= c * chunk; --g) {
      Ia_next = inertia_carry_step(d, g, Ia_next, Xnext, IA_first);
      Xnext = d.Xup(g);
    }
  }
}

}  // namespace scandyn

namespace scandyn {

// ---- the CPU engine ------------------------------------------------------------

// How the links of a batch are cut: chunks of `chunk` links walked by one thread
// each, their aggregates scanned in levels of `fan_in` until one level has at most
// `fan_in` entries (scanned serially).
struct ChainChunking {
  Index links = 0;               // n * B
  Index chunk = 0;               // links per chunk (level 0)
  Index fan_in = 0;              // aggregates per chunk at the levels above
  std::vector<Index> level_size; // entries per level; level 0: chunks of links

  ChainChunking() = default;
  ChainChunking(Index links, Index chunk, Index fan_in);
  Index chunks() const { return level_size.empty() ? 0 : level_size[0]; }
};

// Per-level aggregates and carries of one scan over a ChainChunking's levels (the
// host drivers' scratch).
template <class E>
struct ChainLevels {
  std::vector<std::vector<E>> agg;                    // (levels) x (level size)
  std::vector<std::vector<typename E::Value>> carry;  // the same
  void resize(const ChainChunking& ck) {
    agg.clear();
    carry.clear();
    for (Index size : ck.level_size) {
      agg.emplace_back(static_cast<std::size_t>(size));
      carry.emplace_back(static_cast<std::size_t>(size));
    }
  }
};

// The chain forward dynamics' requirement on a model: unbranched chains hanging
// from the base, bodies numbered chain by chain, i.e. every body's parent is the
// previous body or the base. Returns the first body that breaks it, or -1 (also
// -1 for a model without bodies).
template <class S>
Index first_branching_body(const ModelTpl<S>& model) {
  for (Index i = 0; i < model.nbodies(); ++i)
    if (model.parent(i) != i - 1 && model.parent(i) != -1) return i;
  return -1;
}

// The chain forward dynamics' joints: revolute and prismatic, and a floating base
// (a free joint at body 0: a free rope). Returns the first body whose joint it does
// not take (a spherical joint), or -1.
template <class S>
Index first_unsupported_chain_joint(const ModelTpl<S>& model) {
  for (Index i = 0; i < model.nbodies(); ++i) {
    const JointType t = model.bodies[i].type;
    if (t == JointType::Spherical || (t == JointType::Free && i != 0)) return i;
  }
  return -1;
}

// Throws BackendError unless the model has bodies, first_branching_body is -1 and
// first_unsupported_chain_joint is -1, naming the body (and joint) that breaks it.
template <class S>
void require_chain(const ModelTpl<S>& model, const char* what);

// The parent a ChainBodies entry records for a link whose parent is the previous
// link (-1: the base).
inline constexpr Index kChainPrevious = 0;

// A chain's constants as every driver keeps them: its distinct bodies (equal bodies
// share one entry, whatever their rows in q and qd: a generated rope's links are
// three, the first and then axes y and x in turn), their inverse inertias in pass
// 1's scalar, and each body's entry.
template <class S>
struct ChainBodies {
  std::vector<Body<S>> body;                   // (classes) distinct bodies; parent -1 (a chain's
                                               // first link: the base) or kChainPrevious
  std::vector<InverseInertia<DualScalar>> Phi;  // (classes) their inverse inertias
  std::vector<int> body_class;                 // (n) entry of body i

  // does body i have a child (the next body, in the same chain)?
  bool has_child(Index i) const {
    return i + 1 < static_cast<Index>(body_class.size()) && body[body_class[i + 1]].parent != -1;
  }

  // Throws BackendError unless the model is chains from the base (require_chain) and
  // n x max_batch links fit in 2^30.
  static ChainBodies from(const ModelTpl<S>& model, Index max_batch);
};

// Where a driver keeps a chain's tables (ChainBodies' arrays) and the four passes'
// per-link scratch, as it points a ChainFdData (or the hybrid's ChainHybridData) at
// them: host vectors' data (chain_host::bind_chain) or device pointers into a CUDA
// plan's allocation (kernels/chain_scan.cuh, ChainTablesLayout).
template <class S>
struct ChainScratch {
  const Body<S>* body = nullptr;                    // (classes) distinct bodies
  const InverseInertia<DualScalar>* Phi = nullptr;  // (classes) their inverse inertias
  const int* body_class = nullptr;                  // (n) entry of body i
  Motion<S>* v = nullptr;                           // (links) pass 0's velocities
  Force<S>* U = nullptr;                            // (links) pass 1's IA S
  Force<S>* w = nullptr;                            // (links) pass 1's Ia c
  S* D = nullptr;                                   // (links) pass 1's S^T IA S
  S* u = nullptr;                                   // (links) pass 2's tau - S^T pA

  template <class Data>
  void bind(Data& d) const {
    d.body = body;
    d.Phi = Phi;
    d.body_class = body_class;
    d.v = v;
    d.U = U;
    d.w = w;
    d.D = D;
    d.u = u;
  }
};

// Forward dynamics of B instances of unbranched chains from the base by the chunked scans above
// ("parallel"), on the host with OpenMP threads (1: serial). Agrees with the serial
// aba to rounding (see tests/algorithm/test_chain_fd.cpp for the measured errors). Owns all
// scratch for max_batch instances; compute() allocates nothing.
template <class S>
class ChainForwardDynamics {
 public:
  // chunk 0 picks the links per chunk from the size and the threads.
  ChainForwardDynamics(const ModelTpl<S>& model, Index max_batch, int threads = 0, Index chunk = 0);

  // qdd = FD(q, qd, tau, fext) for in.q.batch instances, gravity included. Returns
  // the number of instances whose articulated pivot D = S^T IA S was not positive
  // and finite (their qdd is left unwritten); failed, when not null, receives B
  // entries: -1 or the first failed DoF of each instance (the link, for 1-DoF joints).
  Index compute(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed = nullptr);

  Index links() const { return n_; }
  Index max_batch() const { return max_batch_; }
  int threads() const { return threads_; }
  Index chunk() const { return chunk_; }

 private:
  Index n_ = 0, max_batch_ = 0, chunk_ = 0;  // n_: links (bodies) per instance
  int threads_ = 1;
  bool floating_ = false;                    // link 0 is a floating base
  std::vector<ABInertia<S>> IA_base_;        // (max_batch) a floating base's IA_0
  std::vector<Motion<S>> a_base_;            // (max_batch) its acceleration
  std::vector<Vec6<S>> qdd_base_;            // (max_batch) its qdd
  Motion<S> a0_;
  ChainBodies<S> bodies_;
  std::vector<Motion<S>> v_;
  std::vector<Force<S>> U_, w_;
  std::vector<S> D_, u_;
  std::vector<int> failed_;
  // per level: aggregates and carries of the three Affine6 passes and the dual pass
  ChainLevels<Affine6<S>> aff_;
  ChainLevels<DualRiccati<DualScalar>> dual_;
};

// ---- the hybrid's host pass 1 --------------------------------------------------

// One interval of a host thread's work in ChainInertiaCarries::compute, in ms from
// the caller's origin (the hybrid's timeline).
struct ChainCarryInterval {
  enum Kind : int { Walk = 0, Reduce = 1, Combine = 2 };
  int thread = 0;                   // OpenMP thread number (0: the calling thread)
  Kind kind = Walk;                 // the recursion over the chunks, their dual aggregate, the combine
  Index c_lo = 0, c_hi = 0;         // chunks [c_lo, c_hi) (Combine: the whole call's)
  double start_ms = 0, end_ms = 0;  // -1 / -1: not run in this call
};

// ChainInertiaCarries::compute's report to its caller: chunks [c_lo, c_hi)'s carries
// are written. Called on the calling thread, each chunk once, ranges in no fixed order.
using ChainCarryReady = void (*)(void* context, Index c_lo, Index c_hi);

// The articulated inertias at the chunk boundaries of a chain (the carries of pass 1,
// what the hybrid forward dynamics computes on the host, cuda::ChainFdPlan::launch_hybrid)
// with `threads` host threads. One thread runs the serial recursion (inertia_carry_walk)
// from the last link to the first. With T >= 2 the chunks are cut into T + 1 ranges
// from the root: range 0, ranges 1..T-1 and the tip range T.
//   phase A  thread T-1 walks the tip range from its leaf by the serial recursion and
//            turns the articulated inertia of its first link into the dual Y
//            (dual_from_articulated); threads 0..T-2 each reduce a range 1..T-1 to its
//            pass-1 aggregate, the composed dual Riccati map (dual_aggregate: the
//            aggregate the parallel chain FD scans);
//   combine  the last thread to finish phase A applies the aggregates from the tip down:
//            the dual carry of every range (T - 1 DualRiccati applications);
//   phase C  threads 0..T-2 walk ranges 1..T-1 and thread T-1 range 0, each from its
//            carry (chunk_inertia_carry of the dual; range T-1 takes the tip walk's Ia
//            itself) by the serial recursion, writing every chunk's carry.
// A reduction costs about reduce_cost times the walk per link, so the tip range (walked,
// never reduced) gets reduce_cost times the links of each other range and every thread
// is busy for about (1 + reduce_cost) L of the N = (T + reduce_cost) L links. Range 0 is
// never reduced (no range lies below it). Walks run in `groups` groups per range, each
// reported through `ready` as soon as it is written (the calling thread polls the
// others between its own groups and pieces of its reduction).
// With 1 thread the carries are those of the serial recursion; with more, ranges T and
// T-1 are too (their carries come from the tip's walk), the others start from carries
// through the dual maps (equal to rounding). A pivot that is not positive and finite
// makes the carries below it in that instance NaN (inertia_carry_step), and the walks of
// pass 1 report it; instances never mix (an instance's last link's dual map is constant).
template <class S>
class ChainInertiaCarries {
 public:
  // Reduction / walk cost per link, one thread of a 2-core AMD EPYC: 5.3-5.5 in
  // double, 7.1-7.3 in float (the reduction runs in double either way) on rope:10^5
  // and 10^6 (bench/chain_carries_cost.cpp, bench/results/chain_carries-cpu-amd-epyc-2c-shared.csv).
  static constexpr double kReduceCost = sizeof(S) == 4 ? 7.0 : 5.5;
  // Fewest chunks per range; with fewer chunks the threads drop until it holds.
  static constexpr Index kMinChunksPerRange = 8;

  // threads: host threads (0: openmp_threads()); groups: walk groups per range (0: 64
  // for one thread, else max(2, 64 / (threads + 1))); reduce_cost: see above.
  explicit ChainInertiaCarries(int threads = 0, Index groups = 0, double reduce_cost = kReduceCost);

  // Ia_out[c] for every chunk c of `chunk` links of d's d.count() links (d: n, batch,
  // the bodies, Phi, body_class and q; a fixed base): the projected articulated
  // inertia Ia of link last(c) + 1 in its frame (unused, and unspecified, when link
  // last(c) has no child). ready(context, c_lo, c_hi), when not null, as chunks are
  // written. With origin not null, intervals() receives each thread's work in ms
  // from *origin.
  void compute(const ChainFdData<S>& d, Index chunk, ABInertia<S>* Ia_out, ChainCarryReady ready = nullptr,
               void* context = nullptr, const std::chrono::steady_clock::time_point* origin = nullptr);

  int threads() const { return threads_; }
  Index groups() const { return groups_; }  // walk groups per range
  // the threads the last compute() ran (fewer for short chains) and its ranges' first chunks
  int threads_used() const { return used_; }
  const std::vector<Index>& range_starts() const { return bound_; }
  const std::vector<ChainCarryInterval>& intervals() const { return intervals_; }

 private:
  int threads_ = 1, used_ = 1;
  Index groups_ = 0;
  double reduce_cost_ = kReduceCost;
  std::vector<Index> bound_;                       // (T + 2) range k: chunks [bound_[k], bound_[k + 1])
  std::vector<DualRiccati<DualScalar>> agg_;       // (T + 1) ranges' aggregates
  std::vector<Mat5<DualScalar>> carry_;            // (T + 1) ranges' dual carries
  ABInertia<S> tip_Ia_{};                          // Ia the tip's walk passes to range T - 1
  std::unique_ptr<std::atomic<Index>[]> done_;     // (T + 1) groups walked per range
  std::vector<Index> reported_;                    // (T + 1) groups reported per range
  std::atomic<int> arrived_{0};                    // phase A finished (threads)
  std::atomic<bool> combined_{false};
  std::vector<ChainCarryInterval> intervals_;      // (T + 1) groups + T reduce + combine
};

}  // namespace scandyn
