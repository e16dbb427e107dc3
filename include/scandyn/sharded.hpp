// scandyn/sharded.hpp: one batch across several devices.
//
// A sharded engine holds one engine per device and splits every batch into
// contiguous ranges of instances, shard k computing instances
// [shard_range(B, n, k).begin, + count) with its own engine, stream and memory,
// reading and writing the caller's views in place (each shard sees a sub-view:
// the same strides, its data pointer moved to its first instance). The shards run
// at once, one host thread (a ShardPool worker) per device, so that the devices'
// copies and kernels overlap; the call returns when every shard has finished.
//
//   scandyn::BackendOptions o;
//   o.backend = scandyn::BackendKind::Cuda;
//   o.devices = scandyn::parse_devices("all");   // or {0, 1}; empty: the current device
//   o.max_batch = B;                              // the whole batch: each shard holds ~B / n
//   auto id = scandyn::make_inverse_dynamics<float>(model, o);   // a ShardedInverseDynamics
//
// The factories of scandyn/engine.hpp return these on the cuda backend when
// BackendOptions::devices names a device other than the current one, or more than one;
// a device named twice runs two shards on it (how the tests shard on one GPU).
// Errors from a shard (a construction that does not fit, a failed copy or launch)
// are a BackendError that begins "device D: ". Failures per instance (forward
// dynamics' pivots, the run-time check) come back in one BatchStatus over the whole
// batch, instances numbered as the caller's.
//
// The classes are backend-agnostic: make_sharded() builds one from any engines, e.g.
// serial ones with no device (the CPU tests shard serial engines this way and check
// bit-identity with one engine over the whole batch).
#pragma once

#include <condition_variable>
#include <cstddef>
#include <exception>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "scandyn/engine.hpp"

namespace scandyn {

// The instances [begin, begin + count) of one shard.
struct ShardRange {
  Index begin = 0;
  Index count = 0;
};

// Shard k of n over B instances: contiguous ranges in order, the first B % n shards one
// instance longer than the others (n >= 1, 0 <= k < n).
ShardRange shard_range(Index B, int n, int k);
// The most instances a shard of n over up to max_batch holds: ceil(max_batch / n).
Index shard_capacity(Index max_batch, int n);

// A view of the instances of r (data null stays null).
template <class T>
BatchView<T> slice(const BatchView<T>& v, const ShardRange& r) {
  return {v.data ? v.data + r.begin * v.batch_stride : nullptr, r.count, v.dof_stride, v.batch_stride};
}
// Body wrenches (B x nbodies, instance-major) of the instances of r; null stays null.
template <class S>
const Force<S>* slice(const Force<S>* fext, const ShardRange& r, Index nbodies) {
  return fext ? fext + r.begin * nbodies : nullptr;
}
template <class S>
IdBatchIn<S> slice(const IdBatchIn<S>& in, const ShardRange& r, Index nbodies) {
  return {slice(in.q, r), slice(in.qd, r), slice(in.qdd, r), slice(in.fext, r, nbodies)};
}
template <class S>
FdBatchIn<S> slice(const FdBatchIn<S>& in, const ShardRange& r, Index nbodies) {
  return {slice(in.q, r), slice(in.qd, r), slice(in.tau, r), slice(in.fext, r, nbodies)};
}
template <class S>
BiasBatchIn<S> slice(const BiasBatchIn<S>& in, const ShardRange& r, Index nbodies) {
  return {slice(in.q, r), slice(in.qd, r), slice(in.fext, r, nbodies)};
}
template <class S>
HybridBatchIn<S> slice(const HybridBatchIn<S>& in, const ShardRange& r, Index nbodies) {
  return {slice(in.q, r), slice(in.qd, r), slice(in.qdd, r), slice(in.tau, r), slice(in.fext, r, nbodies)};
}

// The devices of a BackendOptions::devices text:
//   "all"       every CUDA device visible to the process, in order (BackendError when
//               none is usable);
//   "current"   (or "") the empty list: the device current when an engine is made;
//   "0,1,..."   these ordinals, in this order (a repeated one runs several shards there).
// Throws BackendError naming the value for anything else (a negative or non-numeric
// entry). Ordinals are checked against the devices present when an engine is made.
std::vector<int> parse_devices(const std::string& text);
// "current" for an empty list, else the ordinals joined by commas ("0,1").
std::string devices_string(const std::vector<int>& devices);
// True when a device list asks for more than the current device: several devices, or
// one other than the calling thread's current one (what the cuda factories and the
// simulator shard on).
bool spans_devices(const std::vector<int>& devices);

// One host thread per shard. With `cuda`, worker k makes devices[k] its current CUDA
// device before its first job (a failure there fails each of its jobs with that message).
class ShardPool {
 public:
  ShardPool(std::vector<int> devices, bool cuda);
  ~ShardPool();
  ShardPool(const ShardPool&) = delete;
  ShardPool& operator=(const ShardPool&) = delete;

  int size() const { return static_cast<int>(devices_.size()); }
  const std::vector<int>& devices() const { return devices_; }
  bool cuda() const { return cuda_; }

  // Runs job(k) on worker k for every shard k and waits for all of them. When jobs
  // throw, the lowest shard's exception is rethrown as a BackendError
  // "device D: <what>" (cuda) or "shard k: <what>"; the other shards have finished
  // by then. No allocation (the job is passed by reference).
  template <class Job>
  void run(Job&& job) {
    struct Call final : Task {
      explicit Call(Job& j) : job(j) {}
      void operator()(int k) override { job(k); }
      Job& job;
    } call(job);
    dispatch(call);
  }

  // "device 1: " (cuda) or "shard 1: ": how a shard's errors begin.
  std::string label(int k) const;

 private:
  struct Task {
    virtual ~Task() = default;
    virtual void operator()(int k) = 0;
  };
  void dispatch(Task& task);
  void work(int k);

  std::vector<int> devices_;
  bool cuda_ = false;
  std::vector<std::thread> threads_;
  std::vector<std::exception_ptr> errors_;  // (n) the last run's
  std::mutex mutex_;
  std::condition_variable start_, done_;
  Task* task_ = nullptr;
  unsigned long long generation_ = 0;  // runs started
  int pending_ = 0;                    // workers still in the current run
  bool stop_ = false;
};

// What every sharded engine tells about its shards (bench's device-resident rows use it).
class ShardedEngine {
 public:
  virtual ~ShardedEngine() = default;
  virtual int shard_count() const = 0;
  virtual int shard_device(int k) const = 0;  // the device ordinal (-1 for engines without one)
  virtual Engine& shard_engine(int k) = 0;
};

namespace detail {

// Destroys `engine` on shard k's worker (its device current there), after the pool's
// last job; nothing is thrown (a destructor's).
template <class E>
void release_on_device(ShardPool& pool, int k, std::unique_ptr<E>& engine) {
  try {
    pool.run([&](int j) {
      if (j == k) engine.reset();
    });
  } catch (...) {
    engine.reset();  // the worker could not run it: release it here
  }
}

// A shard's per-instance failed DoFs copied to its range of `failed_dof` (the sharded
// engine's own, B entries; -1 where the shard's engine keeps none). Run by the shard's
// worker, right after its compute.
void keep_failed_dofs(const BatchStatus& status, const ShardRange& r, int* failed_dof);
// Statuses of the shards of one call as one over the whole batch: instances renumbered,
// failed_dof (B entries, filled by keep_failed_dofs) as its per-instance array.
BatchStatus merge_shard_statuses(const std::vector<BatchStatus>& statuses, Index B, int* failed_dof);

// The engine interface E over the engines of the shards and their pool: what every
// sharded engine holds and says of itself (its strategy: the shards' with "-x<n>").
template <class E>
class Shards : public E, public ShardedEngine {
 public:
  // max_batch: the whole batch's, for the per-instance failures of calls that report them
  Shards(std::vector<std::unique_ptr<E>> engines, std::vector<int> devices, bool cuda, Index nbodies,
         Index max_batch = 0)
      : engines_(std::move(engines)), pool_(std::move(devices), cuda), nbodies_(nbodies),
        statuses_(engines_.size()), failed_dof_(static_cast<std::size_t>(max_batch > 0 ? max_batch : 0), -1) {
    if (engines_.empty() || static_cast<int>(engines_.size()) != pool_.size())
      throw BackendError("sharded engine: " + std::to_string(engines_.size()) + " engines for " +
                         std::to_string(pool_.size()) + " devices");
  }
  ~Shards() override {
    // each engine released with its own device current (its stream and memory live there)
    for (int k = 0; k < pool_.size(); ++k) release_on_device(pool_, k, engines_[static_cast<std::size_t>(k)]);
  }
  Shards(const Shards&) = delete;
  Shards& operator=(const Shards&) = delete;

  int shard_count() const override { return pool_.size(); }
  int shard_device(int k) const override { return pool_.cuda() ? pool_.devices()[k] : -1; }
  Engine& shard_engine(int k) override { return *engines_[static_cast<std::size_t>(k)]; }
  E& shard(int k) { return *engines_[static_cast<std::size_t>(k)]; }

  std::string strategy() const override {
    return engines_.front()->strategy() + (pool_.size() > 1 ? "-x" + std::to_string(pool_.size()) : "");
  }
  BackendKind backend() const override { return engines_.front()->backend(); }
  bool exact() const override { return engines_.front()->exact(); }

 protected:
  // f(engine, range) for every shard with instances, at once; B the batch's size
  template <class F>
  void each(Index B, F&& f) {
    const int n = pool_.size();
    pool_.run([&](int k) {
      const ShardRange r = shard_range(B, n, k);
      if (r.count > 0) f(*engines_[static_cast<std::size_t>(k)], r);
    });
  }
  // The same for calls that return a BatchStatus: the shards' statuses as one, instances
  // numbered as the caller's. what: the algorithm, for the max_batch error.
  template <class F>
  BatchStatus each_status(Index B, const char* what, F&& f) {
    if (B > static_cast<Index>(failed_dof_.size()))
      throw BackendError(std::string(what) + ": batch of " + std::to_string(B) + " instances above max_batch " +
                         std::to_string(failed_dof_.size()));
    for (BatchStatus& s : statuses_) s = BatchStatus{};
    const int n = pool_.size();
    pool_.run([&](int k) {
      const ShardRange r = shard_range(B, n, k);
      if (r.count == 0) return;
      BatchStatus& s = statuses_[static_cast<std::size_t>(k)];
      s = f(*engines_[static_cast<std::size_t>(k)], r);
      keep_failed_dofs(s, r, failed_dof_.data());
    });
    return merge_shard_statuses(statuses_, B, failed_dof_.data());
  }

  std::vector<std::unique_ptr<E>> engines_;
  ShardPool pool_;
  Index nbodies_ = 0;

 private:
  std::vector<BatchStatus> statuses_;  // (n) the last call's, per shard
  std::vector<int> failed_dof_;        // (max_batch) the last call's failed DoF per instance
};

}  // namespace detail

// The engines of scandyn/engine.hpp, sharded. Constructors: (engines, devices, cuda,
// nbodies[, max_batch]) as detail::Shards; those whose calls report failures per
// instance take the whole batch's max_batch.

template <class S>
class ShardedInverseDynamics final : public detail::Shards<InverseDynamics<S>> {
 public:
  using detail::Shards<InverseDynamics<S>>::Shards;
  void compute(const IdBatchIn<S>& in, const BatchView<S>& tau) override {
    this->each(tau.batch, [&](InverseDynamics<S>& e, const ShardRange& r) {
      e.compute(slice(in, r, this->nbodies_), slice(tau, r));
    });
  }
};

template <class S>
class ShardedBiasForces final : public detail::Shards<BiasForces<S>> {
 public:
  using detail::Shards<BiasForces<S>>::Shards;
  void compute(const BiasBatchIn<S>& in, const BatchView<S>& h) override {
    this->each(h.batch, [&](BiasForces<S>& e, const ShardRange& r) {
      e.compute(slice(in, r, this->nbodies_), slice(h, r));
    });
  }
};

template <class S>
class ShardedMassMatrix final : public detail::Shards<MassMatrix<S>> {
 public:
  using detail::Shards<MassMatrix<S>>::Shards;
  void compute(const BatchView<const S>& q, const BatchView<S>& M) override {
    this->each(M.batch, [&](MassMatrix<S>& e, const ShardRange& r) { e.compute(slice(q, r), slice(M, r)); });
  }
};

template <class S>
class ShardedForwardDynamics final : public detail::Shards<ForwardDynamics<S>> {
 public:
  using detail::Shards<ForwardDynamics<S>>::Shards;
  BatchStatus compute(const FdBatchIn<S>& in, const BatchView<S>& qdd) override {
    return this->each_status(qdd.batch, "forward dynamics", [&](ForwardDynamics<S>& e, const ShardRange& r) {
      return e.compute(slice(in, r, this->nbodies_), slice(qdd, r));
    });
  }
  FdMethod method() const override { return this->engines_.front()->method(); }
};

template <class S>
class ShardedKinematics final : public detail::Shards<Kinematics<S>> {
 public:
  using detail::Shards<Kinematics<S>>::Shards;
  void compute(const BatchView<const S>& q, const BatchView<S>& poses, const BatchView<S>& J) override {
    this->each(q.batch, [&](Kinematics<S>& e, const ShardRange& r) {
      e.compute(slice(q, r), slice(poses, r), slice(J, r));
    });
  }
  const KinematicsOptions& options() const override { return this->engines_.front()->options(); }
};

template <class S>
class ShardedIdDerivatives final : public detail::Shards<IdDerivatives<S>> {
 public:
  using detail::Shards<IdDerivatives<S>>::Shards;
  void compute(const IdBatchIn<S>& in, const IdDerivativesOut<S>& out) override {
    this->each(in.q.batch, [&](IdDerivatives<S>& e, const ShardRange& r) {
      e.compute(slice(in, r, this->nbodies_), {slice(out.dtau_dq, r), slice(out.dtau_dqd, r), slice(out.M, r)});
    });
  }
};

template <class S>
class ShardedIdSecondDerivatives final : public detail::Shards<IdSecondDerivatives<S>> {
 public:
  using detail::Shards<IdSecondDerivatives<S>>::Shards;
  void compute(const IdBatchIn<S>& in, const IdSecondDerivativesOut<S>& out) override {
    this->each(in.q.batch, [&](IdSecondDerivatives<S>& e, const ShardRange& r) {
      e.compute(slice(in, r, this->nbodies_), {slice(out.d2tau_dq2, r), slice(out.d2tau_dqd2, r),
                                               slice(out.d2tau_dqdqd, r), slice(out.dM_dq, r)});
    });
  }
};

template <class S>
class ShardedFdDerivatives final : public detail::Shards<FdDerivatives<S>> {
 public:
  using detail::Shards<FdDerivatives<S>>::Shards;
  BatchStatus compute(const FdBatchIn<S>& in, const FdDerivativesOut<S>& out) override {
    return this->each_status(in.q.batch, "forward-dynamics derivatives", [&](FdDerivatives<S>& e, const ShardRange& r) {
      return e.compute(slice(in, r, this->nbodies_),
                       {slice(out.dqdd_dq, r), slice(out.dqdd_dqd, r), slice(out.dqdd_dtau, r), slice(out.qdd, r)});
    });
  }
};

template <class S>
class ShardedHybridDynamics final : public detail::Shards<HybridDynamics<S>> {
 public:
  using detail::Shards<HybridDynamics<S>>::Shards;
  BatchStatus compute(const HybridBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& tau) override {
    return this->each_status(qdd.batch, "hybrid dynamics", [&](HybridDynamics<S>& e, const ShardRange& r) {
      return e.compute(slice(in, r, this->nbodies_), slice(qdd, r), slice(tau, r));
    });
  }
  const std::vector<unsigned char>& prescribed() const override { return this->engines_.front()->prescribed(); }
};

template <class S>
class ShardedConstrainedForwardDynamics final : public detail::Shards<ConstrainedForwardDynamics<S>> {
 public:
  using detail::Shards<ConstrainedForwardDynamics<S>>::Shards;
  BatchStatus compute(const FdBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& lambda) override {
    return this->each_status(qdd.batch, "closed-loop forward dynamics",
                             [&](ConstrainedForwardDynamics<S>& e, const ShardRange& r) {
                               return e.compute(slice(in, r, this->nbodies_), slice(qdd, r), slice(lambda, r));
                             });
  }
  void residual(const BatchView<const S>& q, const BatchView<const S>& qd, const BatchView<S>& phi,
                const BatchView<S>& velocity) override {
    this->each(q.batch, [&](ConstrainedForwardDynamics<S>& e, const ShardRange& r) {
      e.residual(slice(q, r), slice(qd, r), slice(phi, r), slice(velocity, r));
    });
  }
  Index rows() const override { return this->engines_.front()->rows(); }
};

}  // namespace scandyn
