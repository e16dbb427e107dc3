// The CPU driver of the chain forward dynamics' JVP and VJP
// (scandyn/algorithm/chain_directional.hpp): OpenMP over chunks, the chain FD's
// passes and scans (chain_scan_host.hpp), then the derivative passes' walks.
#include "scandyn/algorithm/chain_directional.hpp"

#include <algorithm>
#include <string>

#include "chain_scan_host.hpp"

namespace scandyn {

template <class S>
ChainFdDirectional<S>::ChainFdDirectional(const ModelTpl<S>& model, Index max_batch, int threads, Index chunk)
    : n_(model.nbodies()), max_batch_(std::max<Index>(max_batch, 1)) {
  bodies_ = ChainBodies<S>::from(model, max_batch_);
  if (model.floating_base())
    throw BackendError("the parallel chain JVP / VJP of forward dynamics takes chains of 1-DoF joints from a fixed "
                       "base; body 0 (joint '" + model.joint_names[0] +
                       "') is a floating base (a free rope; use aba_jvp / aba_vjp)");
  threads_ = threads > 0 ? threads : openmp_threads();
  const Index links = n_ * max_batch_;
  chunk_ = chunk > 0 ? chunk : std::clamp<Index>(links / (8 * threads_), 8, 64);  // as ChainForwardDynamics
  a0_ = base_acceleration(model.gravity);
  for (auto* m : {&v_, &a_, &dv_}) m->resize(static_cast<std::size_t>(links));
  for (auto* f : {&U_, &w_, &F_, &df_}) f->resize(static_cast<std::size_t>(links));
  IA_.resize(static_cast<std::size_t>(links));
  for (auto* x : {&D_, &u_, &x_}) x->resize(static_cast<std::size_t>(links));
  failed_.resize(static_cast<std::size_t>(max_batch_));
  const ChainChunking ck(links, chunk_, 16);
  aff_.resize(ck);
  dual_.resize(ck);
}

template <class S>
ChainDirectionalData<S> ChainFdDirectional<S>::bind(const FdBatchIn<S>& in, const BatchView<S>& qdd) {
  check_batch(in, qdd, max_batch_);
  ChainDirectionalData<S> d;
  ChainFdData<S>& f = d.fd;
  f.n = n_;
  f.bind(in, qdd);
  chain_host::bind_chain(f, bodies_, a0_, v_, U_, D_, w_, u_, failed_);
  f.a = a_.data();
  std::fill(failed_.begin(), failed_.begin() + f.batch, -1);
  // the chain at rest: v, w, fext, a null, no gravity; tau and qdd set by the caller
  ChainFdData<S>& r = d.rest;
  r = f;
  r.v = nullptr;
  r.w = nullptr;
  r.fext = nullptr;
  r.a = nullptr;
  r.a0 = Motion<S>::zero();
  f.IA_out = IA_.data();  // pass 1's IA (fd only)
  f.pA_out = F_.data();   // pass 2's pA, then F (fd only)
  d.F = F_.data();
  d.dv = dv_.data();
  d.df = df_.data();
  d.x = x_.data();
  return d;
}

template <class S>
Index ChainFdDirectional<S>::finish(Index B, int* failed) const {
  Index bad = 0;
  for (Index b = 0; b < B; ++b) bad += failed_[b] >= 0;
  if (failed) std::copy(failed_.begin(), failed_.begin() + B, failed);
  return bad;
}

using chain_host::for_chunks;
using chain_host::scan_levels;

namespace {

// The FD's passes 0-3 over d.fd (v, U, D, a, IA, pA; qdd), then on every chunk (links
// s..e) the subtree forces F locally and first(d, s, e), the chunk's level-0
// aggregate of the first derivative pass, into aff.agg[0] (not yet scanned).
template <class S, class First>
void fd_then_forces(const ChainDirectionalData<S>& d, const ChainChunking& ck, ChainLevels<Affine6<S>>& aff,
                    ChainLevels<DualRiccati<DualScalar>>& dual, int T, First first) {
  chain_host::fd_passes(d.fd, ck, aff, dual, T);
  for_chunks(ck, d.count(), T, [&](Index c, Index s, Index e) {
    subtree_force_local(d, s, e);
    aff.agg[0][c] = first(d, s, e);
  });
}

void require_rows(Index rows, Index n, Index B, Index batch, const char* what) {
  (void)rows;
  if (batch != B) throw BackendError(std::string("chain JVP / VJP: ") + what + " has " + std::to_string(batch) +
                                     " instances, the batch " + std::to_string(B) + " (" + std::to_string(n) + " rows)");
}
}  // namespace

template <class S>
Index ChainFdDirectional<S>::jvp(const FdBatchIn<S>& in, const BatchView<const S>& dq, const BatchView<const S>& dqd,
                                 const BatchView<const S>& dtau, const BatchView<S>& qdd, const BatchView<S>& dqdd,
                                 int* failed) {
  const Index B = in.q.batch;
  for (auto [v, name] : {std::pair{dq.batch, "dq"}, {dqd.batch, "dqd"}, {dtau.batch, "dtau"}, {dqdd.batch, "dqdd"}})
    require_rows(n_, n_, B, v, name);
  ChainDirectionalData<S> d = bind(in, qdd);
  if (B == 0) return 0;
  d.dq = dq;
  d.dqd = dqd;
  d.dtau = dtau;
  d.rest.tau = BatchView<const S>::aos(x_.data(), n_, B);
  d.rest.qdd = dqdd;
  const ChainChunking ck(d.count(), chunk_, 16);
  const int T = threads_;
  auto& agg = aff_.agg[0];
  auto& carry = aff_.carry[0];
  // the FD; F (locally) and dv (forward)
  fd_then_forces(d, ck, aff_, dual_, T,
                 [](const auto& x, Index s, Index e) { return jvp_velocity_aggregate(x, s, e); });
  scan_levels(ck, aff_.agg, aff_.carry, true, T);
  for_chunks(ck, d.count(), T, [&](Index c, Index s, Index e) { agg[c] = jvp_velocity_walk(d, s, e, carry[c]); });
  // da (forward), df
  scan_levels(ck, aff_.agg, aff_.carry, true, T);
  for_chunks(ck, d.count(), T, [&](Index c, Index s, Index e) { agg[c] = jvp_acceleration_walk(d, s, e, carry[c]); });
  // dF (backward), dtau - r
  scan_levels(ck, aff_.agg, aff_.carry, false, T);
  for_chunks(ck, d.count(), T, [&](Index c, Index s, Index e) { agg[c] = jvp_force_walk(d, s, e, carry[c]); });
  // dqdd = M^-1 (dtau - r): passes 2 and 3 at rest
  chain_host::finish_passes(d.rest, ck, aff_, T);
  return finish(B, failed);
}

template <class S>
Index ChainFdDirectional<S>::vjp(const FdBatchIn<S>& in, const BatchView<const S>& w, const BatchView<S>& qdd,
                                 const BatchView<S>& gq, const BatchView<S>& gqd, const BatchView<S>& gtau,
                                 int* failed) {
  const Index B = in.q.batch;
  for (auto [v, name] : {std::pair{w.batch, "w"}, {gq.batch, "gq"}, {gqd.batch, "gqd"}, {gtau.batch, "gtau"}})
    require_rows(n_, n_, B, v, name);
  ChainDirectionalData<S> d = bind(in, qdd);
  if (B == 0) return 0;
  d.gq = gq;
  d.gqd = gqd;
  d.gtau = gtau;
  d.rest.tau = w;
  d.rest.qdd = BatchView<S>::aos(x_.data(), n_, B);  // u
  d.rest.a = dv_.data();                               // Fbar
  d.rest.pA_out = df_.data();                          // pA of the rest problem
  const ChainChunking ck(d.count(), chunk_, 16);
  const int T = threads_;
  auto& agg = aff_.agg[0];
  auto& carry = aff_.carry[0];
  // the FD; F (locally) and the rest solve's pass 2 (backward)
  fd_then_forces(d, ck, aff_, dual_, T,
                 [](const auto& x, Index s, Index e) { return vjp_rest_bias_aggregate(x, s, e); });
  scan_levels(ck, aff_.agg, aff_.carry, false, T);
  for_chunks(ck, d.count(), T, [&](Index c, Index s, Index e) { agg[c] = bias_walk(d.rest, s, e, carry[c]); });
  // the rest solve's pass 3 (u = M^-1 w in x, Fbar in dv); RA, gtau, RV's aggregates
  scan_levels(ck, aff_.agg, aff_.carry, true, T);
  for_chunks(ck, d.count(), T, [&](Index c, Index s, Index e) {
    acceleration_walk(d.rest, s, e, carry[c]);
    agg[c] = vjp_adjoint_walk(d, s, e, carry[c]);
  });
  // RV (backward); gq, gqd
  scan_levels(ck, aff_.agg, aff_.carry, false, T);
  for_chunks(ck, d.count(), T, [&](Index c, Index s, Index e) { vjp_rv_walk(d, s, e, carry[c]); });
  return finish(B, failed);
}

template class ChainFdDirectional<float>;
template class ChainFdDirectional<double>;

}  // namespace scandyn
