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
//
// The runs' composites (RigidComposite: C + T^T Ia T) are what a free link's element
// and a chunk boundary inside a run need (S_p: link p and the prescribed run after
// it): a chunk whose last link e has a prescribed child takes S_{e+1}, and its walks
// compose the rest locally. S_{e+1} comes from a backward scan of the links'
// composites (pass 0, beside the velocities; O(n) work for any mask) or, when every
// run is short (HybridRunScan, hybrid_scans_runs: the longest at most kScanRunChunks
// chunks), from a walk to the run's end per chunk (no extra scan). Before the scan a
// boundary inside a run of R links walked to its end, O(R^2 / chunk) in all, and the
// free link before a long run made one chunk walk all of it.
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

// ---- the prescribed runs as composite rigid bodies ----------------------------

// A run of links that moves as one rigid body for the articulated inertia (a link and
// the prescribed links after it), as Featherstone's composite rigid body (RBDA 6.2,
// the composite inertia I^c of CRBA) and a congruence map on the inertia the run's
// last link receives from its child:
//   f(Ia) = C + T^T Ia T.
// Link k alone: C = I_k, T = Xup_{k+1} (k's frame to k + 1's). Composition, a's links
// before b's: (a o b)(Ia) = a(b(Ia)), C = C_a + T_a^T C_b T_a, T = T_b T_a. A closed
// element's last link has no child or a free child (the run ends there): a closed a
// ignores what lies after it, a o b = a, so the composite of the elements from link p
// to the chain's end is S_p, the composite of p and the prescribed run after it (up
// to the next free link), whatever follows; associative, so scanned backward (a
// suffix scan) in chunks as the other passes' elements (Value: the composite itself,
// start(): the identity, open).
template <class S>
struct RigidComposite {
  Inertia<S> C;         // the run's composite rigid-body inertia, in its first link's frame
  Transform<S> T;       // its first link's frame to the frame of the link after it (product of Xup)
  Index next = -1;      // closed: the free link after the run, -1 when the chain ends (T unused)
  bool closed = false;  // the run ends at its last link: later elements do not enter

  using Scalar = S;
  using Value = RigidComposite;
  SCANDYN_HD Value apply(const Value& after) const { return compose(*this, after); }
  // (a o b): a's links, then b's
  SCANDYN_HD static RigidComposite compose(const RigidComposite& a, const RigidComposite& b) {
    if (a.closed) return a;
    return {a.C + b.C.transform_transpose(a.T), b.T * a.T, b.next, b.closed};
  }
  SCANDYN_HD static Value start() { return {Inertia<S>::zero(), Transform<S>::identity(), -1, false}; }
};

// The hybrid's run composites, in pass 1's scalar whatever the precision (as the dual
// maps): a run's product of Xup over 10^3 links accumulates its rounding. Float is
// ill-conditioned where free links carry a long run (tests/prescribed_masks.hpp,
// long_run_masks); there, over 48 float cases (rope:2000, runs 100..1899 and 500..1999,
// seeds 12..19, chunks 3, 8, 64), the largest error was 2.5e-1 with float composites,
// 4.7e-2 with these, 9.5e-2 with the walks before the run scan (medians 2e-3 to 3e-3).
template <class S>
using HybridRun = RigidComposite<DualScalar>;

// Whether link g's element is closed (no child, or a free child): from the mask alone.
template <class S>
SCANDYN_HD bool hybrid_composite_closed(const ChainHybridData<S>& d, Index g) {
  return !d.has_child(g) || !d.given(g + 1);
}

// Link g's element: C = I_g, T = Xup_{g+1}; closed unless g has a prescribed child.
template <class S>
SCANDYN_HD HybridRun<S> hybrid_composite_element(const ChainHybridData<S>& d, Index g) {
  const bool child = d.has_child(g);
  const bool closed = hybrid_composite_closed(d, g);
  using T = typename HybridRun<S>::Scalar;
  return {d.body_of(g).I.template cast<T>(), child ? d.Xup(g + 1).template cast<T>() : Transform<T>::identity(),
          child && closed ? g + 1 : -1, closed};
}

// The composite of links g..last's elements and `after` (what follows last), leaf to
// root: each link's element composed onto the composite of the links after it,
// C = I_k + Xup_{k+1}^T C Xup_{k+1}, T = T Xup_{k+1}, as the serial recursion sums a
// composite inertia (each congruence by one link's Xup, not by the run's product).
template <class S>
SCANDYN_HD HybridRun<S> hybrid_composite_fold(const ChainHybridData<S>& d, Index g, Index last, HybridRun<S> after) {
  for (Index k = last; k >= g; --k) after = HybridRun<S>::compose(hybrid_composite_element(d, k), after);
  return after;
}

// The composite of links s..e's elements (the run scan's chunk aggregate): S_s as a map
// of what follows e; the links after the first closed element do not enter.
template <class S>
SCANDYN_HD HybridRun<S> hybrid_composite_aggregate(const ChainHybridData<S>& d, Index s, Index e) {
  Index last = s;
  while (last < e && !hybrid_composite_closed(d, last)) ++last;
  return hybrid_composite_fold(d, s, last, HybridRun<S>::start());
}

// S_{e+1} by a walk, O(run): the composite of link e + 1 and its prescribed run where
// e + 1 is a prescribed child of e (what pass 0's and pass 1's walks read), else start().
template <class S>
SCANDYN_HD HybridRun<S> hybrid_composite_after(const ChainHybridData<S>& d, Index e) {
  if (!d.has_child(e) || !d.given(e + 1)) return HybridRun<S>::start();
  Index last = e + 1;
  while (!hybrid_composite_closed(d, last)) ++last;
  return hybrid_composite_fold(d, e + 1, last, HybridRun<S>::start());
}

// Pass 1's element of free link g from run = S_g, its composite with the prescribed run
// after it: the dual Riccati map of one rigid body (its composite inertia at the
// current q, inverted per instance; alone, link g's own inverse Phi) whose child is
// run.next through run.T.
template <class S>
SCANDYN_HD HybridDual<DualScalar> hybrid_dual_element(const ChainHybridData<S>& d, Index g, const HybridRun<S>& run,
                                                      bool alone) {
  const InverseInertia<DualScalar> Phi =
      alone ? d.Phi_of(g) : InverseInertia<DualScalar>::from(run.C.template cast<DualScalar>());
  const Body<S>& b = d.body_of(g);
  const bool next = run.next >= 0;
  return {dual_element(b, Phi, next, next ? d.body_of(run.next) : b, run.T.template cast<S>()), false};
}

// Whether the drivers scan the prescribed runs' composites (On: O(1) per chunk
// boundary and free link, an extra backward scan of RigidComposite) or each chunk
// walks its boundary's run (Off: hybrid_composite_after, O(run) per chunk boundary
// inside a run, O(run^2 / chunk) in all); Auto: On when the mask's longest run of
// prescribed DoFs exceeds kScanRunChunks chunks (hybrid_scans_runs).
enum class HybridRunScan { Auto, On, Off };
inline constexpr Index kScanRunChunks = 2;

// The longest run of consecutive prescribed DoFs in a mask.
inline Index longest_prescribed_run(const std::vector<unsigned char>& prescribed) {
  Index best = 0, run = 0;
  for (unsigned char p : prescribed) {
    run = p ? run + 1 : 0;
    best = run > best ? run : best;
  }
  return best;
}

// Whether a driver with chunks of `chunk` links scans the runs of this mask.
inline bool hybrid_scans_runs(const std::vector<unsigned char>& prescribed, Index chunk, HybridRunScan mode) {
  if (mode != HybridRunScan::Auto) return mode == HybridRunScan::On;
  return longest_prescribed_run(prescribed) > kScanRunChunks * chunk;
}

// Pass 0's walk from v_{s-1}: stores v; returns pass 1's aggregate of the chunk: its
// free links' HybridDual elements, each from its S_g, the fold of its run's links in the
// chunk (hybrid_composite_fold) onto after = S_{e+1} where the run continues past e.
// Each link enters one fold: O(chunk). The chunk's prescribed links before its first
// free link (or at an instance's start) belong to no free link's run here. after: the
// run scan's carry when scanned; otherwise walked here (hybrid_composite_after) and
// stored, for pass 1's hybrid_inertia_carry.
template <class S>
SCANDYN_HD HybridDual<DualScalar> hybrid_velocity_walk(const ChainHybridData<S>& d, Index s, Index e,
                                                       const Vec6<S>& v_in, HybridRun<S>& after, bool scanned) {
  if (!scanned) after = hybrid_composite_after(d, e);
  velocity_walk<false>(d, s, e, v_in);
  HybridDual<DualScalar> agg;
  Index g = s;  // the next free link
  while (g <= e && d.given(g)) ++g;
  while (g <= e) {
    Index last = g;  // the last link of g's run in this chunk
    while (last < e && !hybrid_composite_closed(d, last)) ++last;
    const bool past = !hybrid_composite_closed(d, last);  // the run continues past e
    const HybridRun<S> run = hybrid_composite_fold(d, g, last, past ? after : HybridRun<S>::start());
    // alone: g's element is closed, S_g = (I_g, Xup_{g+1})
    agg = HybridDual<DualScalar>::compose(agg, hybrid_dual_element(d, g, run, hybrid_composite_closed(d, g)));
    g = last + 1;
    while (g <= e && d.given(g)) ++g;
  }
  return agg;
}

// The articulated inertia link e + 1 passes to link e (its frame): a free e + 1's
// projected inertia from its carried dual Y; a prescribed e + 1 rigid with its run,
// IA = C + T^T Ia_j T from after = S_{e+1} (j = after.next, whose dual the carried Y is:
// prescribed links' HybridDual elements are the identity; C alone when the chain ends).
template <class S>
SCANDYN_HD ABInertia<S> hybrid_inertia_carry(const ChainHybridData<S>& d, Index e, const Mat5<DualScalar>& Y,
                                             const HybridRun<S>& after) {
  if (!d.has_child(e) || !d.given(e + 1)) return chunk_inertia_carry(d, e, Y);
  using T = typename HybridRun<S>::Scalar;
  ABInertia<T> IA = ABInertia<T>::from(after.C);
  if (after.next >= 0) IA += articulated_from_dual_in<T>(d.body_of(after.next), Y).transform_transpose(after.T);
  return IA.template cast<S>();
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
      el = free_acceleration_element(b, d.has_parent(g), X, d.a0, d.c(g), U, Dinv, u);
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
  // the links per chunk from the size and the threads; runs: whether to scan the
  // prescribed runs' composites (Auto: by the mask, hybrid_scans_runs). Throws
  // BackendError for a model that is not chains from the base or a mask of another size.
  ChainHybridDynamics(const ModelTpl<S>& model, const std::vector<unsigned char>& prescribed, Index max_batch,
                      int threads = 0, Index chunk = 0, HybridRunScan runs = HybridRunScan::Auto);

  // qdd_out and tau_out (nv x B, full vectors; the given entries copied through) for
  // in.q.batch instances, gravity included. Returns the number of instances whose
  // articulated pivot (of a free DoF) was not positive and finite (their outputs
  // unwritten); failed, when not null, receives B entries: -1 or the first failed link.
  Index compute(const HybridBatchIn<S>& in, const BatchView<S>& qdd_out, const BatchView<S>& tau_out,
                int* failed = nullptr);

  Index nv() const { return n_; }
  int threads() const { return threads_; }
  Index chunk() const { return chunk_; }            // links per chunk
  bool scans_runs() const { return scan_runs_; }     // the runs' composites scanned (else walked)

 private:
  Index n_ = 0, max_batch_ = 0, chunk_ = 0;
  int threads_ = 1;
  bool scan_runs_ = false;
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
  // the runs' composites: per level aggregates and carries (S_{e+1} of each chunk at
  // level 0; above it only when scanned)
  ChainLevels<HybridRun<S>> run_;
};

}  // namespace scandyn
