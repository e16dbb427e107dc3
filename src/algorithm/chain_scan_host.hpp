// The host (OpenMP) scans of the chain drivers (src/algorithm/chain_fd.cpp,
// src/algorithm/chain_directional.cpp, src/algorithm/chain_hybrid.cpp, whose element
// types are the hybrid's own): a pass's chunk aggregates scanned in levels
// (scandyn/algorithm/chain_fd.hpp: fold_range, carry_range), the binding of a
// driver's scratch, and the chain forward dynamics' four passes over a ChainFdData. Private to the library's sources.
#pragma once

#include <algorithm>
#include <vector>

#include "scandyn/algorithm/chain_fd.hpp"

namespace scandyn {
namespace chain_host {

// Points d (a ChainFdData, or the hybrid's ChainHybridData) at the chain's constants
// (bodies, the base acceleration a0) and at a driver's per-link scratch (n B each):
// pass 0's v, pass 1's U, D, w, pass 2's u; failed (B instances).
template <class Data, class S>
void bind_chain(Data& d, const ChainBodies<S>& bodies, const Motion<S>& a0, std::vector<Motion<S>>& v,
                std::vector<Force<S>>& U, std::vector<S>& D, std::vector<Force<S>>& w, std::vector<S>& u,
                std::vector<int>& failed) {
  ChainScratch<S>{bodies.body.data(), bodies.Phi.data(), bodies.body_class.data(), v.data(), U.data(), w.data(),
                  D.data(), u.data()}
      .bind(d);
  d.a0 = a0;
  d.failed = failed.data();
}

// f(c, s, e) for every chunk c of ck's level 0 over count links (links s..e: ck.chunk
// each, the last chunk's up to count - 1), on T threads, static schedule.
template <class F>
void for_chunks(const ChainChunking& ck, Index count, int T, F&& f) {
  const Index chunks = ck.chunks(), L = ck.chunk;
#pragma omp parallel for num_threads(T) schedule(static)
  for (Index c = 0; c < chunks; ++c) f(c, c * L, std::min(count, (c + 1) * L) - 1);
}

// The aggregates above level 0 and the carries of every level, for one pass whose
// level-0 aggregates are in agg[0]; E::start() enters the whole sequence.
template <class E>
void scan_levels(const ChainChunking& ck, std::vector<std::vector<E>>& agg,
                 std::vector<std::vector<typename E::Value>>& carry, bool forward, int threads) {
  const Index levels = static_cast<Index>(ck.level_size.size());
  for (Index k = 0; k + 1 < levels; ++k) {
    const Index m = ck.level_size[k + 1], size = ck.level_size[k], f = ck.fan_in;
    const E* lower = agg[k].data();
    E* upper = agg[k + 1].data();
#pragma omp parallel for num_threads(threads) schedule(static) if (m > 1)
    for (Index j = 0; j < m; ++j) upper[j] = fold_range(lower, j * f, std::min(size, (j + 1) * f), forward);
  }
  carry_range(agg[levels - 1].data(), carry[levels - 1].data(), 0, ck.level_size[levels - 1], forward, E::start());
  for (Index k = levels - 2; k >= 0; --k) {
    const Index m = ck.level_size[k + 1], size = ck.level_size[k], f = ck.fan_in;
    const E* lower = agg[k].data();
    auto* lc = carry[k].data();
    const auto* uc = carry[k + 1].data();
#pragma omp parallel for num_threads(threads) schedule(static) if (m > 1)
    for (Index j = 0; j < m; ++j) carry_range(lower, lc, j * f, std::min(size, (j + 1) * f), forward, uc[j]);
  }
}

// Passes 2 and 3 from pass 2's level-0 aggregates in aff.agg[0] (pass 1's walks
// done): also M^-1 x of the chain at rest (scandyn/algorithm/chain_directional.hpp).
template <class S, bool kB>
void finish_passes(const ChainFdData<S, kB>& d, const ChainChunking& ck, ChainLevels<Affine6<S>>& aff, int T) {
  auto& agg = aff.agg[0];
  auto& carry = aff.carry[0];
  scan_levels(ck, aff.agg, aff.carry, false, T);
  for_chunks(ck, d.count(), T, [&](Index c, Index s, Index e) { agg[c] = bias_walk(d, s, e, carry[c]); });
  scan_levels(ck, aff.agg, aff.carry, true, T);
  for_chunks(ck, d.count(), T, [&](Index c, Index s, Index e) { acceleration_walk(d, s, e, carry[c]); });
}

// qdd = FD(d) by the four passes (velocities, articulated inertias, bias forces,
// accelerations) over chunks of ck.chunk links, T threads; aff and dual hold the
// scans' levels (sized for at least ck). d.failed must hold -1 for every instance.
template <class S, bool kB>
void fd_passes(const ChainFdData<S, kB>& d, const ChainChunking& ck, ChainLevels<Affine6<S>>& aff,
               ChainLevels<DualRiccati<DualScalar>>& dual, int T) {
  // pass 0: velocities (and pass 1's aggregates)
  for_chunks(ck, d.count(), T, [&](Index c, Index s, Index e) { aff.agg[0][c] = velocity_aggregate(d, s, e); });
  scan_levels(ck, aff.agg, aff.carry, true, T);
  for_chunks(ck, d.count(), T,
             [&](Index c, Index s, Index e) { dual.agg[0][c] = velocity_walk(d, s, e, aff.carry[0][c]); });
  // pass 1: articulated inertias (and pass 2's aggregates)
  scan_levels(ck, dual.agg, dual.carry, false, T);
  for_chunks(ck, d.count(), T, [&](Index c, Index s, Index e) {
    aff.agg[0][c] = inertia_walk(d, s, e, chunk_inertia_carry(d, e, dual.carry[0][c]));
  });
  // passes 2 and 3: bias forces (and pass 3's aggregates), accelerations
  finish_passes(d, ck, aff, T);
}

}  // namespace chain_host
}  // namespace scandyn
