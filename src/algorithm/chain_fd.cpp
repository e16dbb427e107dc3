// The CPU driver of the chain forward dynamics (scandyn/algorithm/chain_fd.hpp):
// OpenMP over chunks, the same walks and scans as the CUDA driver.
#include "scandyn/algorithm/chain_fd.hpp"

#include <stdexcept>

#include <algorithm>
#include <climits>
#include <string>
#include <unordered_map>

#if defined(_OPENMP)
#include <omp.h>
#endif

namespace scandyn {

ChainChunking::ChainChunking(Index links_, Index chunk_, Index fan_in_)
    : links(links_), chunk(std::max<Index>(chunk_, 1)), fan_in(std::max<Index>(fan_in_, 2)) {
  if (links <= 0) return;
  Index size = (links + chunk - 1) / chunk;
  level_size.push_back(size);
  while (size > fan_in) {
    size = (size + fan_in - 1) / fan_in;
    level_size.push_back(size);
  }
}

template <class S>
void require_chain(const ModelTpl<S>& model, const char* what) {
  if (model.nbodies() == 0) throw BackendError(std::string(what) + ": the model has no moving bodies");
  const Index i = first_branching_body(model);
  if (i >= 0)
    throw BackendError(std::string(what) + " needs unbranched chains hanging from the base (every body's parent " +
                       "the previous body or the base); body " + std::to_string(i) + " (joint '" +
                       model.joint_names[i] + "') has parent " + std::to_string(model.parent(i)));
  const Index j = first_unsupported_chain_joint(model);
  if (j >= 0)
    throw BackendError(std::string(what) + " takes revolute and prismatic joints and a floating base (a free rope); " +
                       "body " + std::to_string(j) + " (joint '" + model.joint_names[j] + "') is " +
                       (model.bodies[j].type == JointType::Spherical ? "a spherical joint" : "a free joint") +
                       " (use aba or jsi)");
}

template <class S>
ChainBodies<S> ChainBodies<S>::from(const ModelTpl<S>& model, Index max_batch) {
  require_chain(model, "the parallel chain forward dynamics");
  const Index n = model.nbodies();
  if (static_cast<long long>(n) * max_batch > INT_MAX / 2)
    throw BackendError("the parallel chain forward dynamics: " + std::to_string(n) + " links x " +
                       std::to_string(max_batch) + " instances exceed 2^30 links per call");
  ChainBodies o;
  o.body_class.resize(static_cast<std::size_t>(n));
  std::unordered_map<std::string, int> seen;  // a body's bytes -> its entry
  for (Index i = 0; i < n; ++i) {
    Body<S> b = model.bodies[i];
    b.parent = model.parent(i) == -1 ? -1 : kChainPrevious;
    b.idx_q = b.idx_v = 0;  // the drivers place link i by ChainFdData::q_row / v_row
    auto [it, fresh] = seen.emplace(std::string(reinterpret_cast<const char*>(&b), sizeof b),
                                    static_cast<int>(o.body.size()));
    if (fresh) {
      o.body.push_back(b);
      o.Phi.push_back(InverseInertia<DualScalar>::from(b.I.template cast<DualScalar>()));
    }
    o.body_class[i] = it->second;
  }
  return o;
}

namespace {

// The aggregates above level 0 and the carries of every level, for one pass whose
// level-0 aggregates are in agg[0]; `in` enters the whole sequence.
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

}  // namespace

template <class S>
ChainForwardDynamics<S>::ChainForwardDynamics(const ModelTpl<S>& model, Index max_batch, int threads, Index chunk)
    : n_(model.nbodies()), max_batch_(std::max<Index>(max_batch, 1)) {
  bodies_ = ChainBodies<S>::from(model, max_batch_);
  floating_ = model.floating_base();
  threads_ = threads > 0 ? threads : openmp_threads();
  const Index links = n_ * max_batch_;
  // chunks: at least 8 per thread, at most 64 links each, at least 8 links each
  chunk_ = chunk > 0 ? chunk : std::clamp<Index>(links / (8 * threads_), 8, 64);
  a0_ = base_acceleration(model.gravity);
  v_.resize(links);
  U_.resize(links);
  w_.resize(links);
  D_.resize(links);
  u_.resize(links);
  failed_.resize(static_cast<std::size_t>(max_batch_));
  if (floating_) {
    IA_base_.resize(static_cast<std::size_t>(max_batch_));
    a_base_.resize(static_cast<std::size_t>(max_batch_));
    qdd_base_.resize(static_cast<std::size_t>(max_batch_));
  }
  const ChainChunking ck(links, chunk_, 16);
  for (Index size : ck.level_size) {
    aff_.emplace_back(static_cast<std::size_t>(size));
    aff_carry_.emplace_back(static_cast<std::size_t>(size));
    dual_.emplace_back(static_cast<std::size_t>(size));
    dual_carry_.emplace_back(static_cast<std::size_t>(size));
  }
}

template <class S>
Index ChainForwardDynamics<S>::compute(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed) {
  check_batch(in, qdd, max_batch_);
  const Index B = in.q.batch;
  if (B == 0) return 0;
  std::fill(failed_.begin(), failed_.begin() + B, -1);
  // the passes over d, a ChainFdData<S> or, for a free rope, a ChainFdData<S, true>
  auto passes = [&](auto& d) {
    d.n = n_;
    d.bind(in, qdd);
    d.body = bodies_.body.data();
    d.Phi = bodies_.Phi.data();
    d.body_class = bodies_.body_class.data();
    d.a0 = a0_;
    d.v = v_.data();
    d.U = U_.data();
    d.D = D_.data();
    d.w = w_.data();
    d.u = u_.data();
    d.failed = failed_.data();
    if (floating_) d.bind_base(IA_base_.data(), a_base_.data(), qdd_base_.data());

    const ChainChunking ck(d.count(), chunk_, 16);
    const Index chunks = ck.chunks(), L = ck.chunk, count = d.count();
    const int T = threads_;
    auto first = [&](Index c) { return c * L; };
    auto last = [&](Index c) { return std::min(count, (c + 1) * L) - 1; };

    // pass 0: velocities (and pass 1's aggregates)
#pragma omp parallel for num_threads(T) schedule(static)
    for (Index c = 0; c < chunks; ++c) aff_[0][c] = velocity_aggregate(d, first(c), last(c));
    scan_levels(ck, aff_, aff_carry_, true, T);
#pragma omp parallel for num_threads(T) schedule(static)
    for (Index c = 0; c < chunks; ++c) dual_[0][c] = velocity_walk(d, first(c), last(c), aff_carry_[0][c]);
    // pass 1: articulated inertias (and pass 2's aggregates)
    scan_levels(ck, dual_, dual_carry_, false, T);
#pragma omp parallel for num_threads(T) schedule(static)
    for (Index c = 0; c < chunks; ++c)
      aff_[0][c] = inertia_walk(d, first(c), last(c), chunk_inertia_carry(d, last(c), dual_carry_[0][c]));
    // pass 2: bias forces (and pass 3's aggregates)
    scan_levels(ck, aff_, aff_carry_, false, T);
#pragma omp parallel for num_threads(T) schedule(static)
    for (Index c = 0; c < chunks; ++c) aff_[0][c] = bias_walk(d, first(c), last(c), aff_carry_[0][c]);
    // pass 3: accelerations
    scan_levels(ck, aff_, aff_carry_, true, T);
#pragma omp parallel for num_threads(T) schedule(static)
    for (Index c = 0; c < chunks; ++c) acceleration_walk(d, first(c), last(c), aff_carry_[0][c]);
  };
  if (floating_) {
    ChainFdData<S, true> d;
    passes(d);
  } else {
    ChainFdData<S> d;
    passes(d);
  }

  Index bad = 0;
  for (Index b = 0; b < B; ++b) bad += failed_[b] >= 0;
  if (failed) std::copy(failed_.begin(), failed_.begin() + B, failed);
  return bad;
}

template void require_chain(const ModelTpl<float>&, const char*);
template void require_chain(const ModelTpl<double>&, const char*);
template struct ChainBodies<float>;
template struct ChainBodies<double>;
template class ChainForwardDynamics<float>;
template class ChainForwardDynamics<double>;

}  // namespace scandyn
