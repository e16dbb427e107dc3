// scandyn/scan/omp_scan.hpp: root-path prefix and subtree suffix scans over a
// TreeScanPlan on CPU threads.
//
// The drivers use orphaned OpenMP worksharing (omp for / omp single): called
// inside a `#pragma omp parallel` region they split the work among its threads;
// called outside one (or built without OpenMP) they run serially with the same
// results. Every thread of the region must call them.
//
// Two operators per scan:
//   op(a, b)     the full associative composition (used for piece-local scans)
//   known(a, b)  the same result's value part when one side is already final;
//                it may skip work op does (e.g. the transform product), and is
//                used wherever the incoming value is known.
#pragma once

#include "scandyn/scan/tree_plan.hpp"

#ifdef _OPENMP
#include <omp.h>
#endif

namespace scandyn {

namespace detail {
// Pieces handed out per grab: about eight grabs per thread in a level, so a level
// of 50,000 two-node segments is not scheduled one piece at a time.
inline Index piece_chunk(Index pieces) {
#ifdef _OPENMP
  const Index threads = omp_get_num_threads();
#else
  const Index threads = 1;
#endif
  const Index c = pieces / (8 * threads);
  return c > 1 ? c : 1;
}
}  // namespace detail

// Root-path prefix: on return x[i] = e_root o ... o e_parent o e_i (the value of
// node i), for all i, given elements e_i in x. Roots keep their element.
// carry: scratch of plan.pieces.size() entries.
template <class T, class Op, class Known>
void tree_prefix_scan(const TreeScanPlan& plan, T* x, T* carry, Op op, Known known) {
  for (Index l = 0; l < plan.num_levels(); ++l) {
    const Index kb = plan.level_begin[l], ke = plan.level_begin[l + 1];
    const Index chunk = detail::piece_chunk(ke - kb);
#pragma omp for schedule(dynamic, chunk)
    for (Index k = kb; k < ke; ++k) {
      const TreeScanPlan::Piece& pc = plan.pieces[k];
      if (pc.first) {
        const Index pn = plan.seg_parent_node[pc.segment];
        if (pn >= 0) x[pc.begin] = known(x[pn], x[pc.begin]);
        for (Index i = pc.begin + 1; i < pc.end; ++i) x[i] = known(x[i - 1], x[i]);
      } else {
        for (Index i = pc.begin + 1; i < pc.end; ++i) x[i] = op(x[i - 1], x[i]);
      }
    }
    if (!plan.has_split_segments) continue;
#pragma omp single
    for (Index k = kb; k < ke; ++k) {
      const TreeScanPlan::Piece& pc = plan.pieces[k];
      if (pc.first) continue;
      const T& last = x[plan.pieces[k - 1].end - 1];
      carry[k] = plan.pieces[k - 1].first ? last : known(carry[k - 1], last);
    }
#pragma omp for schedule(dynamic, 1)
    for (Index k = kb; k < ke; ++k) {
      const TreeScanPlan::Piece& pc = plan.pieces[k];
      if (pc.first) continue;
      for (Index i = pc.begin; i < pc.end; ++i) x[i] = known(carry[k], x[i]);
    }
  }
}

// Subtree suffix: processes levels leaves-first; before a node's run is scanned,
// fold(x[p], x[c]) adds each branch child c's final value into its parent p's
// element; along a run, x[i] = op(x[i], x[i + 1]). On return x[i] is node i's
// value including its whole subtree.
template <class T, class Op, class Known, class Fold>
void tree_suffix_scan(const TreeScanPlan& plan, T* x, T* carry, Op op, Known known, Fold fold) {
  for (Index l = plan.num_levels() - 1; l >= 0; --l) {
    const Index kb = plan.level_begin[l], ke = plan.level_begin[l + 1];
    const Index chunk = detail::piece_chunk(ke - kb);
#pragma omp for schedule(dynamic, chunk)
    for (Index k = kb; k < ke; ++k) {
      const TreeScanPlan::Piece& pc = plan.pieces[k];
      const Index s = pc.segment;
      for (Index c = plan.child_segs_begin[s]; c < plan.child_segs_begin[s + 1]; ++c) {
        const Index cs = plan.child_segs[c];
        const Index p = plan.seg_parent_node[cs];
        if (p >= pc.begin && p < pc.end) fold(x[p], x[plan.seg_begin[cs]]);
      }
      if (pc.last) {
        for (Index i = pc.end - 2; i >= pc.begin; --i) x[i] = known(x[i], x[i + 1]);
      } else {
        for (Index i = pc.end - 2; i >= pc.begin; --i) x[i] = op(x[i], x[i + 1]);
      }
    }
    if (!plan.has_split_segments) continue;
#pragma omp single
    for (Index k = ke - 1; k >= kb; --k) {
      const TreeScanPlan::Piece& pc = plan.pieces[k];
      if (pc.last) continue;
      const T& next_first = x[plan.pieces[k + 1].begin];
      carry[k] = plan.pieces[k + 1].last ? next_first : known(next_first, carry[k + 1]);
    }
#pragma omp for schedule(dynamic, 1)
    for (Index k = kb; k < ke; ++k) {
      const TreeScanPlan::Piece& pc = plan.pieces[k];
      if (pc.last) continue;
      for (Index i = pc.begin; i < pc.end; ++i) x[i] = known(x[i], carry[k]);
    }
  }
}

// Inclusive scan of a plain array (a one-segment plan) with the same machinery:
// the CPU counterpart of a device-wide scan, for tests and chains.
template <class T, class Op>
void chain_inclusive_scan(const TreeScanPlan& chain_plan, T* x, T* carry, Op op) {
  tree_prefix_scan(chain_plan, x, carry, op, op);
}

}  // namespace scandyn
