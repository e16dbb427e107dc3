// The CPU driver of the hybrid chain dynamics (scandyn/algorithm/chain_hybrid.hpp):
// OpenMP over chunks, the chain forward dynamics' chunking and level scans with the
// hybrid's walks.
#include "scandyn/algorithm/chain_hybrid.hpp"

#include <algorithm>
#include <string>

#include "chain_scan_host.hpp"

namespace scandyn {

template <class S>
ChainHybridDynamics<S>::ChainHybridDynamics(const ModelTpl<S>& model, const std::vector<unsigned char>& prescribed,
                                            Index max_batch, int threads, Index chunk, HybridRunScan runs)
    : n_(model.nv()), max_batch_(std::max<Index>(max_batch, 1)), prescribed_(prescribed) {
  require_one_dof_joints(model, "the parallel chain hybrid dynamics");
  if (static_cast<Index>(prescribed.size()) != n_)
    throw BackendError("the parallel chain hybrid dynamics: the prescribed mask has " +
                       std::to_string(prescribed.size()) + " entries for a model of " + std::to_string(n_) + " DoF");
  bodies_ = ChainBodies<S>::from(model, max_batch_);
  threads_ = threads > 0 ? threads : openmp_threads();
  const Index links = n_ * max_batch_;
  chunk_ = chunk > 0 ? chunk : std::clamp<Index>(links / (8 * threads_), 8, 64);
  scan_runs_ = hybrid_scans_runs(prescribed_, chunk_, runs);
  a0_ = base_acceleration(model.gravity);
  v_.resize(links);
  U_.resize(links);
  w_.resize(links);
  D_.resize(links);
  u_.resize(links);
  failed_.resize(static_cast<std::size_t>(max_batch_));
  const ChainChunking ck(links, chunk_, 16);
  for (Index size : ck.level_size) {
    aff_.emplace_back(static_cast<std::size_t>(size));
    aff_carry_.emplace_back(static_cast<std::size_t>(size));
    dual_.emplace_back(static_cast<std::size_t>(size));
    dual_carry_.emplace_back(static_cast<std::size_t>(size));
  }
  if (scan_runs_) run_.resize(ck);
  else run_.carry.assign(1, std::vector<HybridRun<S>>(static_cast<std::size_t>(ck.chunks())));  // walked
}

template <class S>
Index ChainHybridDynamics<S>::compute(const HybridBatchIn<S>& in, const BatchView<S>& qdd_out,
                                      const BatchView<S>& tau_out, int* failed) {
  check_batch(in, qdd_out, tau_out, max_batch_);
  const Index B = in.q.batch;
  if (B == 0) return 0;
  ChainHybridData<S> d;
  d.n = n_;
  d.batch = B;
  chain_host::bind_chain(d, bodies_, a0_, v_, U_, D_, w_, u_, failed_);
  d.q = in.q;
  d.qd = in.qd;
  d.tau = in.tau;
  d.fext = in.fext;
  d.qdd = qdd_out;
  d.prescribed = prescribed_.data();
  d.qdd_in = in.qdd;
  d.tau_out = tau_out;
  std::fill(failed_.begin(), failed_.begin() + B, -1);

  const ChainChunking ck(d.count(), chunk_, 16);
  const Index count = d.count();
  const int T = threads_;
  using chain_host::for_chunks;
  using chain_host::scan_levels;

  // pass 0: velocities and the runs' composites S_{e+1} at the chunk boundaries
  // (scanned, or walked by each chunk); pass 1's aggregates
  auto& run_after = run_.carry[0];
  for_chunks(ck, count, T, [&](Index c, Index s, Index e) {
    aff_[0][c] = velocity_aggregate<S>(d, s, e);
    if (scan_runs_) run_.agg[0][c] = hybrid_composite_aggregate(d, s, e);
  });
  scan_levels(ck, aff_, aff_carry_, true, T);
  if (scan_runs_) scan_levels(ck, run_.agg, run_.carry, false, T);
  for_chunks(ck, count, T, [&](Index c, Index s, Index e) {
    dual_[0][c] = hybrid_velocity_walk(d, s, e, aff_carry_[0][c], run_after[c], scan_runs_);
  });
  // pass 1: articulated inertias, prescribed joints rigid (and pass 2's aggregates)
  scan_levels(ck, dual_, dual_carry_, false, T);
  for_chunks(ck, count, T, [&](Index c, Index s, Index e) {
    aff_[0][c] = hybrid_inertia_walk(d, s, e, hybrid_inertia_carry(d, e, dual_carry_[0][c], run_after[c]));
  });
  // pass 2: bias forces, prescribed accelerations included (and pass 3's aggregates)
  scan_levels(ck, aff_, aff_carry_, false, T);
  for_chunks(ck, count, T,
             [&](Index c, Index s, Index e) { aff_[0][c] = hybrid_bias_walk(d, s, e, aff_carry_[0][c]); });
  // pass 3: accelerations and the prescribed joints' forces
  scan_levels(ck, aff_, aff_carry_, true, T);
  for_chunks(ck, count, T, [&](Index c, Index s, Index e) { hybrid_acceleration_walk(d, s, e, aff_carry_[0][c]); });

  Index bad = 0;
  for (Index b = 0; b < B; ++b) bad += failed_[b] >= 0;
  if (failed) std::copy(failed_.begin(), failed_.begin() + B, failed);
  return bad;
}

template class ChainHybridDynamics<float>;
template class ChainHybridDynamics<double>;

}  // namespace scandyn
