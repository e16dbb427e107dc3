// scandyn/algorithm/chain_hybrid.hpp: hybrid dynamics (Featherstone 2008, 9.2: some
// DoFs' accelerations given, the others' forces) of unbranched chains by the chunked
// scans of the parallel chain forward dynamics (scandyn/algorithm/chain_fd.hpp), on the
// host with OpenMP threads (ChainHybridDynamics, below) and on a CUDA device
// (cuda::ChainHybridPlan, scandyn/cuda/chain_hybrid.hpp: the same walks, SCANDYN_HD,
// one thread per chunk).
//
// A prescribed joint is rigid for the articulated inertia: it passes its whole
// articulated inertia IA to its parent (no projection), and its known acceleration
// enters the bias: z_i = pA_i + IA_i (c_i + S_i qdd_i) + Xup_{i+1}^T z_{i+1}, a_i =
// Xup_i a_{i-1} + c_i + S_i qdd_i, tau_i = S_i^T (IA_i a_i + pA_i + ...) (the steps
// hybrid_prescribed_* of steps.hpp). Passes 0, 2 and 3 keep their Affine6 scans with
// these elements. Pass 1 scans the dual Riccati maps of the free links only: a free
// link i with a run of prescribed links after it (up to the next free link j, or the
// chain's end) is, for the inertia, one rigid body with the run (its composite
// inertia at the current q, inverted per instance), whose child is j through the
// product of the run's transforms; a prescribed link's element is the identity
// (HybridDual), so the value carried across it is the dual Y of the next free link.
// Every link's result is then computed by the serial recursion's steps from its
// chunk's boundary values, as in the forward dynamics.
#pragma once

#include <vector>

#include "scandyn/algorithm/chain_fd.hpp"

namespace scandyn {

// A pass-1 element of the hybrid chain: a dual Riccati map, or the identity (a
// prescribed link: the value passes through).
template <class S>
struct HybridDual {
  DualRiccati<S> map;
  bool identity = true;

  using Value = Mat5<S>;
  SCANDYN_HD Value apply(const Value& Y) const { return identity ? Y : map.apply(Y); }
  // (a o b)(Y) = a(b(Y))
  SCANDYN_HD static HybridDual compose(const HybridDual& a, const HybridDual& b) {
    if (a.identity) return b;
    if (b.identity) return a;
    return {DualRiccati<S>::compose(a.map, b.map), false};
  }
  SCANDYN_HD static Value start() { return DualRiccati<S>::start(); }
};

// The chain, its per-link scratch (ChainFdData: v, U, D, w, u) and the hybrid's inputs
// and outputs (host or device pointers, as the driver needs). For a prescribed link,
// U = IA S, D unused, w = IA c and u = -S^T pA (pA with its children's forces), so
// that tau = U^T a - u.
template <class S>
struct ChainHybridData : ChainFdData<S> {
  const unsigned char* prescribed = nullptr;  // (n) nonzero: the DoF's acceleration is given
  BatchView<const S> qdd_in;                  // (n x B) read at prescribed DoFs
  BatchView<S> tau_out;                       // (n x B) written at every DoF

  SCANDYN_HD bool given(Index g) const { return prescribed[g % this->n] != 0; }
  SCANDYN_HD S qdd_given(Index g) const { return qdd_in.at(g % this->n, g / this->n); }
};

// The composite rigid body of free link g and the run of prescribed links after it
// (in g's frame), and the transform from g's frame to the next free link's (the run's
// product of Xup); next: that link, -1 when the run reaches the chain's end.
template <class S>
SCANDYN_HD Inertia<S> hybrid_run_inertia(const ChainHybridData<S>& d, Index g, Transform<S>& X_next, Index& next) {
  Index end = g;  // the run's last link
  while (d.has_child(end) && d.given(end + 1)) ++end;
  next = d.has_child(end) ? end + 1 : -1;
  Inertia<S> Ic = d.body_of(end).I;
  for (Index k = end; k > g; --k) {  // composite inertia, leaf to root
    Inertia<S> parent = d.body_of(k - 1).I;
    parent += crba_composite_step(d.Xup(k), Ic);
    Ic = parent;
  }
  X_next = Transform<S>::identity();
  if (next >= 0)
    for (Index k = g + 1; k <= next; ++k) X_next = d.Xup(k) * X_next;
  return Ic;
}

// Pass 1's element of link g.
template <class S>
SCANDYN_HD HybridDual<DualScalar> hybrid_dual_element(const ChainHybridData<S>& d, Index g) {
  if (d.given(g)) return {};
  Transform<S> X;
  Index next;
  const Inertia<S> I = hybrid_run_inertia(d, g, X, next);
  const InverseInertia<DualScalar> Phi = InverseInertia<DualScalar>::from(I.template cast<DualScalar>());
  const Body<S>& b = d.body_of(g);
  return {dual_element(b, Phi, next >= 0, next >= 0 ? d.body_of(next) : b, X), false};
}

// Pass 0's walk from v_{s-1}: stores v; returns pass 1's aggregate of the chunk.
template <class S>
SCANDYN_HD HybridDual<DualScalar> hybrid_velocity_walk(const ChainHybridData<S>& d, Index s, Index e, const Vec6<S>& v_in) {
  velocity_walk<false>(d, s, e, v_in);
  HybridDual<DualScalar> agg;
  for (Index g = s; g <= e; ++g) agg = HybridDual<DualScalar>::compose(agg, hybrid_dual_element(d, g));
  return agg;
}

// The articulated inertia link e + 1 passes to link e (its frame), from the carried Y
// of the first free link at or after e + 1: that link's projected inertia, then the
// prescribed links before it rigid (IA = I + Xup^T Ia Xup).
template <class S>
SCANDYN_HD ABInertia<S> hybrid_inertia_carry(const ChainHybridData<S>& d, Index e, const Mat5<DualScalar>& Y) {
  if (!d.has_child(e)) return ABInertia<S>{};
  Index j = e + 1;
  while (d.given(j) && d.has_child(j)) ++j;
  ABInertia<S> Ia = d.given(j) ? ABInertia<S>::from(d.body_of(j).I) : articulated_from_dual(d.body_of(j), Y);
  for (Index k = j - 1; k > e; --k) {
    ABInertia<S> IA = ABInertia<S>::from(d.body_of(k).I);
    IA += Ia.transform_transpose(d.Xup(k + 1));
    Ia = IA;
  }
  return Ia;
}

// Pass 1's walk from Ia_in (link e + 1's, its frame): the articulated inertias of links
// e..s (prescribed links rigid); stores U, D, w and records a failed pivot of a free
// link; returns pass 2's aggregate, z_s as a map of z_{e+1}.
template <class S>
SCANDYN_HD Affine6<S> hybrid_inertia_walk(const ChainHybridData<S>& d, Index s, Index e, const ABInertia<S>& Ia_in) {
  ABInertia<S> Ia_next = Ia_in;
  Transform<S> Xnext = d.has_child(e) ? d.Xup(e + 1) : Transform<S>::identity();
  Affine6<S> agg{Mat6<S>::identity(), Vec6<S>::zero(), false};
  for (Index g = e; g >= s; --g) {
    const Body<S>& b = d.body_of(g);
    const bool child = d.has_child(g);
    ABInertia<S> IA = ABInertia<S>::from(b.I);
    if (child) IA += Ia_next.transform_transpose(Xnext);
    const Force<S> pA = d.pA(g);
    Affine6<S> el = Affine6<S>::make_constant(Vec6<S>::zero());
    if (d.given(g)) {
      // z_g = pA + Xnext^T z_{g+1} + IA (c + S qdd)
      const Force<S> U = IA * joint_motion(b, S(1));
      const Force<S> w = IA * d.c(g);
      d.U[g] = U;
      d.D[g] = S(1);
      d.w[g] = w;
      if (child) el = {transpose(to_mat6(Xnext)), Vec6<S>::zero(), false};
      el.b = to_vec6(pA + w + d.qdd_given(g) * U);
      Ia_next = IA;
    } else {
      // U = IA S, D = S^T U, Ia = IA - U U^T / D, w = Ia c;
      // z_g = N (pA + Xnext^T z_{g+1}) + w + U tau / D,  N = 1 - U S^T / D
      el = free_joint_step(d, g, b, child, Xnext, IA, pA, Ia_next);
    }
    agg = Affine6<S>::compose(el, agg);
    Xnext = d.Xup(g);
  }
  return agg;
}

// Pass 2's walk from z_{e+1}: stores u (free: tau - S^T pA; prescribed: -S^T pA);
// returns pass 3's aggregate, a_e as a map of a_{s-1}.
template <class S>
SCANDYN_HD Affine6<S> hybrid_bias_walk(const ChainHybridData<S>& d, Index s, Index e, const Vec6<S>& z_in) {
  Force<S> z_next = to_force(z_in);
  Transform<S> Xnext = d.has_child(e) ? d.Xup(e + 1) : Transform<S>::identity();
  Affine6<S> agg{Mat6<S>::identity(), Vec6<S>::zero(), false};
  for (Index g = e; g >= s; --g) {
    const Body<S>& b = d.body_of(g);
    Force<S> pA = d.pA(g);
    if (d.has_child(g)) pA += Xnext.apply_transpose(z_next);
    const Force<S> U = d.U[g];
    const Transform<S> X = d.Xup(g);
    Affine6<S> el;
    if (d.given(g)) {
      const S qdd = d.qdd_given(g);
      d.u[g] = -joint_project(b, pA);
      z_next = pA + d.w[g] + qdd * U;
      // a_g = Xup a_{g-1} + c + S qdd
      const Vec6<S> cS = to_vec6(add_joint_motion(b, d.c(g), qdd));
      if (d.has_parent(g)) el = {to_mat6(X), cS, false};
      else el = Affine6<S>::make_constant(to_vec6(X.apply(d.a0)) + cS);
    } else {
      const S D = d.D[g], Dinv = S(1) / D;
      const S u = d.tau_of(g) - joint_project(b, pA);
      d.u[g] = u;
      z_next = pA + d.w[g] + (u * Dinv) * U;
      // a_g = N^T (Xup a_{g-1} + c) + S u / D,  N^T = 1 - S U^T / D
      const Vec6<S> Uv = to_vec6(U);
      const Vec6<S> Sv = to_vec6(joint_motion(b, S(1)));
      auto project = [&](Vec6<S> x) {
        S t = S(0);
        for (int r = 0; r < 6; ++r) t += Uv.m[r] * x.m[r];
        t *= Dinv;
        for (int r = 0; r < 6; ++r) x.m[r] -= Sv.m[r] * t;
        return x;
      };
      const Vec6<S> Su = to_vec6(joint_motion(b, u * Dinv));
      if (d.has_parent(g)) {
        const Mat6<S> XM = to_mat6(X);
        for (int c = 0; c < 6; ++c) {
          Vec6<S> col;
          for (int r = 0; r < 6; ++r) col.m[r] = XM(r, c);
          col = project(col);
          for (int r = 0; r < 6; ++r) el.M(r, c) = col.m[r];
        }
        el.b = project(to_vec6(d.c(g))) + Su;
        el.constant = false;
      } else {
        el = Affine6<S>::make_constant(project(to_vec6(X.apply(d.a0) + d.c(g))) + Su);
      }
    }
    agg = Affine6<S>::compose(agg, el);
    Xnext = X;
  }
  return agg;
}

// Pass 3's walk from a_{s-1}: qdd and tau of links s..e (a failed instance's unwritten).
template <class S>
SCANDYN_HD void hybrid_acceleration_walk(const ChainHybridData<S>& d, Index s, Index e, const Vec6<S>& a_in) {
  Motion<S> a_parent = to_motion(a_in);
  for (Index g = s; g <= e; ++g) {
    const Body<S>& b = d.body_of(g);
    const Motion<S> ap = d.has_parent(g) ? a_parent : d.a0;
    Motion<S> a;
    S qdd, tau;
    if (d.given(g)) {
      qdd = d.qdd_given(g);
      tau = hybrid_prescribed_acceleration_step(b, d.Xup(g), ap, d.c(g), d.U[g], d.u[g], qdd, a);
    } else {
      qdd = aba_acceleration_step(b, d.Xup(g), ap, d.c(g), d.U[g], d.D[g], d.u[g], a);
      tau = d.tau_of(g);
    }
    if (d.failed[g / d.n] < 0) {
      d.qdd.at(g % d.n, g / d.n) = qdd;
      d.tau_out.at(g % d.n, g / d.n) = tau;
    }
    a_parent = a;
  }
}

// Hybrid dynamics of B instances of unbranched chains from the base by the chunked
// scans, on the host with OpenMP threads (1: serial). Agrees with the serial
// hybrid_dynamics to rounding (tests/algorithm/test_chain_hybrid.cpp). Owns all scratch
// for max_batch instances; compute() allocates nothing.
template <class S>
class ChainHybridDynamics {
 public:
  // prescribed: nv entries (nonzero: the DoF's acceleration is given). chunk 0 picks
  // the links per chunk from the size and the threads. Throws BackendError for a model
  // that is not chains from the base or a mask of another size.
  ChainHybridDynamics(const ModelTpl<S>& model, const std::vector<unsigned char>& prescribed, Index max_batch,
                      int threads = 0, Index chunk = 0);

  // qdd_out and tau_out (nv x B, full vectors; the given entries copied through) for
  // in.q.batch instances, gravity included. Returns the number of instances whose
  // articulated pivot (of a free DoF) was not positive and finite (their outputs
  // unwritten); failed, when not null, receives B entries: -1 or the first failed link.
  Index compute(const HybridBatchIn<S>& in, const BatchView<S>& qdd_out, const BatchView<S>& tau_out,
                int* failed = nullptr);

  Index nv() const { return n_; }
  int threads() const { return threads_; }

 private:
  Index n_ = 0, max_batch_ = 0, chunk_ = 0;
  int threads_ = 1;
  Motion<S> a0_;
  std::vector<unsigned char> prescribed_;
  ChainBodies<S> bodies_;
  std::vector<Motion<S>> v_;
  std::vector<Force<S>> U_, w_;
  std::vector<S> D_, u_;
  std::vector<int> failed_;
  std::vector<std::vector<Affine6<S>>> aff_;
  std::vector<std::vector<Vec6<S>>> aff_carry_;
  std::vector<std::vector<HybridDual<DualScalar>>> dual_;
  std::vector<std::vector<Mat5<DualScalar>>> dual_carry_;
};

}  // namespace scandyn
