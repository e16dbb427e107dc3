// src/sim/sharded_sim.cpp: the simulator across several devices (scandyn/sim/simulator.hpp,
// "Devices"): one backend per shard of the batch, each with its own state, stream and
// memory, every call run on all shards at once by a ShardPool (scandyn/sharded.hpp),
// instances renumbered between the caller's batch and each shard's.
#include <algorithm>
#include <string>
#include <utility>
#include <vector>

#include "scandyn/cuda/device.hpp"
#include "scandyn/sharded.hpp"
#include "scandyn/sim/simulator.hpp"

namespace scandyn {
namespace sim {
namespace detail {

BatchStatus merge_shard_statuses(const std::vector<BatchStatus>& statuses, Index B) {
  const int n = static_cast<int>(statuses.size());
  BatchStatus total;
  for (int k = 0; k < n; ++k) {
    BatchStatus s = statuses[static_cast<std::size_t>(k)];
    if (s.first_instance >= 0) s.first_instance += shard_range(B, n, k).begin;
    add_step_failures(total, s);
  }
  return total;
}

namespace {

template <class S>
class ShardedSimBackend final : public SimBackend<S> {
 public:
  ShardedSimBackend(const SimSetup<S>& setup, std::vector<int> devices, bool cuda, const MakeSimBackend<S>& make)
      : setup_(setup), pool_(std::move(devices), cuda) {
    const int n = pool_.size();
    const std::size_t nn = static_cast<std::size_t>(n);
    setups_.resize(nn);
    backends_.resize(nn);
    routes_.resize(nn);
    q_rows_.resize(nn);
    qd_rows_.resize(nn);
    statuses_.resize(nn);
    for (int k = 0; k < n; ++k) {
      setups_[static_cast<std::size_t>(k)] = std::make_unique<SimSetup<S>>(setup);
      setups_[static_cast<std::size_t>(k)]->batch = range(k).count;
    }
    try {
      // each shard made by its worker: with its device current, its errors "device D: "
      pool_.run([&](int k) {
        if (range(k).count > 0) backends_[static_cast<std::size_t>(k)] = make(*setups_[static_cast<std::size_t>(k)]);
      });
    } catch (...) {
      release();
      throw;
    }
  }
  ~ShardedSimBackend() override { release(); }

  void step(const BatchView<const S>& tau) override {
    if (tau.data && tau.batch != setup_.batch)
      throw BackendError("Simulator::step: torques for " + std::to_string(tau.batch) + " instances, the simulator has " +
                         std::to_string(setup_.batch));
    for (auto& s : setups_) s->time = setup_.time;
    each([&](int, SimBackend<S>& b, const ShardRange& r) { b.step_host(slice(tau, r)); });
  }
  void step_host(const BatchView<const S>& tau) override { step(tau); }
  bool tau_on_device() const override { return false; }

  BatchView<S> q() override { throw no_single_view("q", "read_state() copies it to the host; q(k) views shard k"); }
  BatchView<S> qd() override { throw no_single_view("qd", "read_state() copies it to the host; qd(k) views shard k"); }
  Force<S>* wrenches() override {
    if (!setup_.wrenches_per_step) return nullptr;
    throw no_single_view("wrenches", "wrenches(k) are shard k's (shard_range(k) its instances)");
  }
  ContactReading<S>* contact_forces() override {
    if (!(setup_.effects & kContacts)) return nullptr;
    throw no_single_view("contact_forces", "read_contact_forces() copies them to the host; contact_forces(k) are shard k's");
  }

  void read_contact_forces(ContactReading<S>* host) override {
    if (!(setup_.effects & kContacts)) return;
    const Index P = setup_.contact_count();
    each([&](int, SimBackend<S>& b, const ShardRange& r) { b.read_contact_forces(host + r.begin * P); });
  }

  // each instance's rows to its shard, the instance renumbered from the shard's first
  void write_instances(const Index* instances, Index count, const S* q_rows, const S* qd_rows) override {
    const Index B = setup_.batch, nq = setup_.model.nq(), nv = setup_.model.nv();
    const int n = pool_.size();
    for (int k = 0; k < n; ++k) {
      const std::size_t kk = static_cast<std::size_t>(k);
      routes_[kk].clear(), q_rows_[kk].clear(), qd_rows_[kk].clear();
    }
    for (Index j = 0; j < count; ++j) {
      const int k = shard_of(B, n, instances[j]);
      const std::size_t kk = static_cast<std::size_t>(k);
      routes_[kk].push_back(instances[j] - range(k).begin);
      q_rows_[kk].insert(q_rows_[kk].end(), q_rows + j * nq, q_rows + (j + 1) * nq);
      qd_rows_[kk].insert(qd_rows_[kk].end(), qd_rows + j * nv, qd_rows + (j + 1) * nv);
    }
    each([&](int k, SimBackend<S>& b, const ShardRange&) {
      const std::size_t kk = static_cast<std::size_t>(k);
      if (!routes_[kk].empty())
        b.write_instances(routes_[kk].data(), static_cast<Index>(routes_[kk].size()), q_rows_[kk].data(),
                          qd_rows_[kk].data());
    });
  }

  // each shard's (nq x count) and (nv x count) into its columns of the caller's (nq x B), (nv x B)
  void read_state(S* q_host, S* qd_host) override {
    const Index B = setup_.batch, nq = setup_.model.nq(), nv = setup_.model.nv();
    each([&](int k, SimBackend<S>& b, const ShardRange& r) {
      std::vector<S>& q = q_rows_[static_cast<std::size_t>(k)];
      std::vector<S>& qd = qd_rows_[static_cast<std::size_t>(k)];
      q.resize(static_cast<std::size_t>(nq) * r.count);
      qd.resize(static_cast<std::size_t>(nv) * r.count);
      b.read_state(q.data(), qd.data());
      for (Index i = 0; i < nq; ++i) std::copy_n(q.data() + i * r.count, r.count, q_host + i * B + r.begin);
      for (Index i = 0; i < nv; ++i) std::copy_n(qd.data() + i * r.count, r.count, qd_host + i * B + r.begin);
    });
  }

  BatchStatus status() override {
    for (BatchStatus& s : statuses_) s = BatchStatus{};
    each([&](int k, SimBackend<S>& b, const ShardRange&) { statuses_[static_cast<std::size_t>(k)] = b.status(); });
    return merge_shard_statuses(statuses_, setup_.batch);
  }
  void clear_status() override {
    each([](int, SimBackend<S>& b, const ShardRange&) { b.clear_status(); });
  }
  void synchronize() override {
    each([](int, SimBackend<S>& b, const ShardRange&) { b.synchronize(); });
  }
  // shard 0 holds instances whenever the batch has any
  bool on_device() const override { return backends_.front() ? backends_.front()->on_device() : pool_.cuda(); }
  std::string strategy() const override {
    return (backends_.front() ? backends_.front()->strategy() : std::string("empty")) +
           (pool_.size() > 1 ? "-x" + std::to_string(pool_.size()) : "");
  }
  void* stream() const override { return nullptr; }  // one per shard: stream(k)

  int shard_count() const override { return pool_.size(); }
  int shard_device(int k) const override { return pool_.cuda() ? pool_.devices()[static_cast<std::size_t>(k)] : -1; }
  SimBackend<S>* shard(int k) override { return backends_[static_cast<std::size_t>(k)].get(); }

 private:
  ShardRange range(int k) const { return shard_range(setup_.batch, pool_.size(), k); }

  // f(k, shard k's backend, its range) on every shard with instances, at once
  template <class F>
  void each(F&& f) {
    pool_.run([&](int k) {
      if (SimBackend<S>* b = backends_[static_cast<std::size_t>(k)].get()) f(k, *b, range(k));
    });
  }

  // the shards' backends destroyed by their workers (device memory and streams freed
  // with their device current)
  void release() {
    try {
      pool_.run([&](int k) { backends_[static_cast<std::size_t>(k)].reset(); });
    } catch (...) {  // a worker without its device: its backend was never made
    }
  }

  BackendError no_single_view(const char* what, const char* instead) const {
    return BackendError(std::string("Simulator::") + what + "(): the simulator is sharded across " +
                        (pool_.cuda() ? "devices " + devices_string(pool_.devices())
                                      : std::to_string(pool_.size()) + " shards") +
                        ", with no single view of its memory: " + instead);
  }

  const SimSetup<S>& setup_;                          // the Simulator's (batch B, time)
  ShardPool pool_;                                    // worker k: shard k, devices[k] current when cuda
  std::vector<std::unique_ptr<SimSetup<S>>> setups_;  // (n) shard k's: batch its count (its backend keeps a reference)
  std::vector<std::unique_ptr<SimBackend<S>>> backends_;  // (n) null for a shard without instances
  std::vector<std::vector<Index>> routes_;            // (n) write_instances: shard k's instances, renumbered
  std::vector<std::vector<S>> q_rows_, qd_rows_;      // (n) write_instances' rows, read_state's shard state
  std::vector<BatchStatus> statuses_;                 // (n) status(): the shards'
};

}  // namespace

template <class S>
std::unique_ptr<SimBackend<S>> make_sharded_sim_backend(const SimSetup<S>& setup, std::vector<int> devices, bool cuda,
                                                        const MakeSimBackend<S>& make) {
  return std::make_unique<ShardedSimBackend<S>>(setup, std::move(devices), cuda, make);
}

template std::unique_ptr<SimBackend<float>> make_sharded_sim_backend(const SimSetup<float>&, std::vector<int>, bool,
                                                                     const MakeSimBackend<float>&);
template std::unique_ptr<SimBackend<double>> make_sharded_sim_backend(const SimSetup<double>&, std::vector<int>, bool,
                                                                      const MakeSimBackend<double>&);

}  // namespace detail
}  // namespace sim
}  // namespace scandyn
