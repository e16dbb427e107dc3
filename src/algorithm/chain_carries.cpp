// The hybrid's host pass 1 (scandyn/algorithm/chain_fd.hpp, ChainInertiaCarries): the
// articulated inertias at the chunk boundaries of a chain with OpenMP threads, by the
// serial recursion (inertia_carry_walk) from carries that the pass-1 aggregates of the
// parallel chain FD (dual_aggregate) supply.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <thread>

#include "scandyn/algorithm/chain_fd.hpp"
#include "scandyn/flush_denormals.hpp"

#if defined(_OPENMP)
#include <omp.h>
#endif

namespace scandyn {

namespace {

using Clock = std::chrono::steady_clock;

double ms_since(const Clock::time_point* origin) {
  return origin ? std::chrono::duration<double, std::milli>(Clock::now() - *origin).count() : 0.0;
}

// Group i of a range [lo, hi) walked in groups of `step` chunks from the top.
struct Group {
  Index lo, hi;
};
Group group_of(Index lo, Index hi, Index step, Index i) { return {std::max(lo, hi - (i + 1) * step), hi - i * step}; }
Index groups_in(Index lo, Index hi, Index step) { return hi > lo ? (hi - lo + step - 1) / step : 0; }

int this_thread_number() {
#if defined(_OPENMP)
  return omp_get_thread_num();
#else
  return 0;
#endif
}
int team_size() {
#if defined(_OPENMP)
  return omp_get_num_threads();
#else
  return 1;
#endif
}

}  // namespace

template <class S>
ChainInertiaCarries<S>::ChainInertiaCarries(int threads, Index groups, double reduce_cost)
    : threads_(threads > 0 ? threads : openmp_threads()), reduce_cost_(std::max(reduce_cost, 0.0)) {
#if !defined(_OPENMP)
  threads_ = 1;
#endif
  groups_ = groups > 0 ? groups : (threads_ == 1 ? Index(64) : std::max<Index>(2, 64 / (threads_ + 1)));
  const std::size_t ranges = static_cast<std::size_t>(threads_) + 1;
  bound_.assign(ranges + 1, 0);
  agg_.resize(ranges);
  carry_.resize(ranges);
  done_.reset(new std::atomic<Index>[ranges]);
  reported_.assign(ranges, 0);
  intervals_.resize(ranges * static_cast<std::size_t>(groups_) + static_cast<std::size_t>(threads_) + 1);
}

template <class S>
void ChainInertiaCarries<S>::compute(const ChainFdData<S>& d, Index chunk, ABInertia<S>* Ia_out, ChainCarryReady ready,
                                     void* context, const Clock::time_point* origin) {
  const Index count = d.count();
  for (auto& iv : intervals_) iv = {0, ChainCarryInterval::Walk, 0, 0, -1.0, -1.0};
  if (count <= 0) return;
  chunk = std::max<Index>(chunk, 1);
  const Index C = (count + chunk - 1) / chunk;  // chunks
  const Index G = groups_;

  // the threads this chain keeps busy: ranges of at least kMinChunksPerRange chunks
  int T = threads_;
  while (T >= 2 && static_cast<double>(C) < (T + reduce_cost_) * kMinChunksPerRange) --T;
  if (T < 2) T = 1;
  used_ = T;

  // ranges from the root: 0 and 1..T-1 of L chunks each, the tip T of reduce_cost L
  // (one range, all chunks, with one thread)
  const std::size_t R = static_cast<std::size_t>(T) + 1;  // ranges (T = 1: range 0 only, range 1 empty)
  if (T == 1) {
    bound_[0] = 0;
    bound_[1] = C;
    bound_[2] = C;
  } else {
    const double L = static_cast<double>(C) / (T + reduce_cost_);
    for (int k = 0; k <= T; ++k) bound_[k] = std::min<Index>(C - 1, static_cast<Index>(std::llround(k * L)));
    bound_[R] = C;
  }
  for (std::size_t k = 0; k < R; ++k) {
    done_[k].store(0, std::memory_order_relaxed);
    reported_[k] = 0;
  }
  arrived_.store(0, std::memory_order_relaxed);
  combined_.store(false, std::memory_order_relaxed);

  auto step_of = [&](std::size_t k) {
    const Index size = bound_[k + 1] - bound_[k];
    return std::max<Index>(1, (size + G - 1) / G);
  };
  auto slot = [&](std::size_t k, Index i) -> ChainCarryInterval& {
    return intervals_[k * static_cast<std::size_t>(G) + static_cast<std::size_t>(i)];
  };
  // the calling thread: report every group walked since the last poll, a range's
  // consecutive groups as one interval
  auto poll = [&]() {
    if (!ready) return;
    for (std::size_t k = 0; k < R; ++k) {
      const Index done = done_[k].load(std::memory_order_acquire);
      if (done == reported_[k]) continue;
      const Index step = step_of(k);
      const Index hi = group_of(bound_[k], bound_[k + 1], step, reported_[k]).hi;
      const Index lo = group_of(bound_[k], bound_[k + 1], step, done - 1).lo;
      ready(context, lo, hi);
      reported_[k] = done;
    }
  };
  // walk range k from Ia_next / Xnext (link bound_[k + 1]'s), group by group
  auto walk = [&](std::size_t k, int thread, ABInertia<S> Ia_next, Transform<S> Xnext, ABInertia<S>& IA_first) {
    const Index step = step_of(k);
    const Index n = groups_in(bound_[k], bound_[k + 1], step);
    for (Index i = 0; i < n; ++i) {
      const Group grp = group_of(bound_[k], bound_[k + 1], step, i);
      ChainCarryInterval& iv = slot(k, i);
      iv.thread = thread;
      iv.kind = ChainCarryInterval::Walk;
      iv.c_lo = grp.lo;
      iv.c_hi = grp.hi;
      if (origin) iv.start_ms = ms_since(origin);
      inertia_carry_walk(d, chunk, grp.lo, grp.hi, Ia_out, Ia_next, Xnext, IA_first);
      if (origin) iv.end_ms = ms_since(origin);
      done_[k].store(i + 1, std::memory_order_release);
      if (thread == 0) poll();
    }
    return Ia_next;
  };

  if (T == 1) {  // the serial recursion, from the leaf
    ABInertia<S> IA_first{};
    walk(0, 0, ABInertia<S>{}, Transform<S>::identity(), IA_first);
    poll();
    return;
  }

  // the link that passes its inertia into range k (the first of range k + 1), and
  // range k's last link
  auto above = [&](std::size_t k) { return bound_[k + 1] * chunk; };
  const std::size_t tip = R - 1;
  ChainCarryInterval& combine = intervals_[R * static_cast<std::size_t>(G) + static_cast<std::size_t>(T)];
  // the combine, by the last thread to finish phase A: the dual carries of ranges
  // T-1..0 from the tip's Y (carry_[T - 1], set by the tip's thread)
  auto finish_phase_a = [&](int thread) {
    if (arrived_.fetch_add(1, std::memory_order_acq_rel) + 1 == T) {
      combine.thread = thread;
      combine.kind = ChainCarryInterval::Combine;
      combine.c_lo = 0;
      combine.c_hi = C;
      if (origin) combine.start_ms = ms_since(origin);
      for (std::size_t k = tip - 1; k-- > 0;) carry_[k] = agg_[k + 1].apply(carry_[k + 1]);
      if (origin) combine.end_ms = ms_since(origin);
      combined_.store(true, std::memory_order_release);
    }
  };
  auto wait_combined = [&](int thread) {
    while (!combined_.load(std::memory_order_acquire)) {
      if (thread == 0) poll();
      std::this_thread::yield();
    }
  };
  // range k's carry from its dual carry (range T - 1: the tip walk's Ia)
  auto start_of = [&](std::size_t k, ABInertia<S>& Ia, Transform<S>& X) {
    const Index e = above(k) - 1;
    Ia = k == tip - 1 ? tip_Ia_ : chunk_inertia_carry(d, e, carry_[k]);
    X = d.has_child(e) ? d.Xup(e + 1) : Transform<S>::identity();
  };

  bool ran = false;
#pragma omp parallel num_threads(T)
  {
    const int t = this_thread_number();
    if (team_size() == T) {
      if (t == 0) ran = true;
      if (t == T - 1) {
        // phase A: the tip's walk from its leaf, and its first link's dual
        ABInertia<S> IA_first{};
        tip_Ia_ = walk(tip, t, ABInertia<S>{}, Transform<S>::identity(), IA_first);
        carry_[tip - 1] = dual_from_articulated(d.body_of(above(tip - 1)), IA_first);
        finish_phase_a(t);
        wait_combined(t);
        // phase C: range 0
        ABInertia<S> Ia, unused;
        Transform<S> X;
        start_of(0, Ia, X);
        walk(0, t, Ia, X, unused);
      } else {
        // phase A: reduce range t + 1 (in pieces of a walk group, the calling thread
        // polling in between)
        const std::size_t k = static_cast<std::size_t>(t) + 1;
        ChainCarryInterval& iv = intervals_[R * static_cast<std::size_t>(G) + static_cast<std::size_t>(t)];
        iv.thread = t;
        iv.kind = ChainCarryInterval::Reduce;
        iv.c_lo = bound_[k];
        iv.c_hi = bound_[k + 1];
        if (origin) iv.start_ms = ms_since(origin);
        const Index step = step_of(k);
        const Index first = bound_[k] * chunk, last = std::min(count, bound_[k + 1] * chunk) - 1;
        const FlushDenormalsScope flush;  // the aggregate's coupling decays through the subnormals
        DualRiccati<DualScalar> agg{};
        for (Index s = first; s <= last; s += step * chunk) {
          const Index e = std::min(last, s + step * chunk - 1);
          const DualRiccati<DualScalar> piece = dual_aggregate(d, s, e);
          agg = s == first ? piece : DualRiccati<DualScalar>::compose(agg, piece);
          if (t == 0) poll();
        }
        agg_[k] = agg;
        if (origin) iv.end_ms = ms_since(origin);
        finish_phase_a(t);
        wait_combined(t);
        // phase C: range t + 1
        ABInertia<S> Ia, unused;
        Transform<S> X;
        start_of(k, Ia, X);
        walk(k, t, Ia, X, unused);
      }
    }
  }
  if (!ran) {  // the runtime gave fewer threads than asked: the serial recursion
    used_ = 1;
    bound_[0] = 0;
    bound_[1] = C;
    for (std::size_t k = 1; k <= R; ++k) bound_[k] = C;
    for (auto& iv : intervals_) iv = {0, ChainCarryInterval::Walk, 0, 0, -1.0, -1.0};
    for (std::size_t k = 0; k < R; ++k) done_[k].store(0), reported_[k] = 0;
    ABInertia<S> IA_first{};
    walk(0, 0, ABInertia<S>{}, Transform<S>::identity(), IA_first);
  }
  poll();
}

template class ChainInertiaCarries<float>;
template class ChainInertiaCarries<double>;

}  // namespace scandyn
