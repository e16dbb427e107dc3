// The CPU driver of the chain forward dynamics (scandyn/algorithm/chain_fd.hpp):
// OpenMP over chunks, the same walks and scans as the CUDA driver.
#include "scandyn/algorithm/chain_fd.hpp"

#include "chain_scan_host.hpp"

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
  aff_.resize(ck);
  dual_.resize(ck);
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
    chain_host::bind_chain(d, bodies_, a0_, v_, U_, D_, w_, u_, failed_);
    if (floating_) d.bind_base(IA_base_.data(), a_base_.data(), qdd_base_.data());

    chain_host::fd_passes(d, ChainChunking(d.count(), chunk_, 16), aff_, dual_, threads_);
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
