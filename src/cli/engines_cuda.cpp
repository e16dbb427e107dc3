// src/cli/engines_cuda.cpp: bench's device-resident batch for the CUDA engines: the
// batch copied once to device memory (cuda::DeviceBatch), the engine's
// compute_async() on its stream per call; fd's failed DoFs stay on the device until
// status() reads them, after the timing. Every engine has one except fd by the
// hybrid method, jsi with the aba fallback and fd with the run-time check on
// (compute() only: the host must see q, or which instances failed or were flagged).
#include "engines.hpp"

#if SCANDYN_HAS_CUDA

#include <functional>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "cli.hpp"
#include "scandyn/cuda/constrained_dynamics.hpp"
#include "scandyn/cuda/derivatives.hpp"
#include "scandyn/cuda/second_derivatives.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/cuda/device_batch.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"
#include "scandyn/cuda/kinematics.hpp"
#include "scandyn/cuda/mass_matrix.hpp"
#include "scandyn/sharded.hpp"

namespace scandyn::cli {
namespace {

template <class S>
class CudaResidentBatch final : public ResidentBatch<S> {
 public:
  // queue: the engine's compute_async() on the batch; failure: what a failed DoF means
  using Queue = std::function<cudaError_t(const cuda::DeviceBatch<S>&)>;
  // nq: the row length of inputs[0] when it is q (0: nv)
  CudaResidentBatch(std::string strategy, std::string what, Index nv, const std::vector<const S*>& inputs,
                    std::size_t count, std::size_t out_width, std::size_t engine_bytes, Queue queue,
                    Failure failure = Failure::None, Index nq = 0)
      : strategy_(std::move(strategy)), what_(std::move(what)), queue_(std::move(queue)), failure_(failure) {
    try {
      batch_ = std::make_unique<cuda::DeviceBatch<S>>(nv, static_cast<Index>(count), inputs, out_width,
                                                      failure != Failure::None, engine_bytes, nq);
    } catch (const BackendError& e) {
      throw UsageError(e.what(), false);  // beyond device memory: before any timing
    }
  }

  void launch() override {
    if (const cudaError_t err = queue_(*batch_); err != cudaSuccess)
      throw DataError("backend 'cuda': launching " + what_ + ": " + cudaGetErrorString(err));
  }
  void wait() override { call([&] { batch_->synchronize(what_.c_str()); }); }
  void read(S* out) override { call([&] { batch_->read_output(out); }); }
  BatchStatus status() override {
    if (failure_ == Failure::None) return {};
    failed_.resize(static_cast<std::size_t>(batch_->output().batch));
    call([&] { batch_->read_failed(failed_.data()); });
    return summarize_failures(failed_.data(), static_cast<Index>(failed_.size()), failure_);
  }
  std::string strategy() const override { return strategy_; }

 private:
  template <class F>
  void call(F&& f) {  // a CUDA error during a computation is a failed computation (exit 1)
    try {
      f();
    } catch (const BackendError& e) {
      throw DataError(e.what());
    }
  }
  std::string strategy_, what_;
  Queue queue_;
  Failure failure_;
  std::vector<int> failed_;  // (B) after status()
  std::unique_ptr<cuda::DeviceBatch<S>> batch_;
};

// A sharded engine's device-resident batch (scandyn/sharded.hpp): shard k's instances
// copied once to its device, each shard's compute_async() queued on its own device
// and stream (one host thread queues all of them, so the devices run at once); read()
// and status() put the shards' results back in the caller's instance order.
template <class S>
class ShardedResidentBatch final : public ResidentBatch<S> {
 public:
  // shards[k]: shard k's resident batch, made with device devices[k] current
  ShardedResidentBatch(std::vector<std::unique_ptr<ResidentBatch<S>>> shards, std::vector<int> devices,
                       std::vector<ShardRange> ranges, std::size_t out_width, Index count)
      : shards_(std::move(shards)), devices_(std::move(devices)), ranges_(std::move(ranges)),
        out_width_(out_width), count_(count) {}

  void launch() override {
    each([](ResidentBatch<S>& r) { r.launch(); });
  }
  void wait() override {
    each([](ResidentBatch<S>& r) { r.wait(); });
  }
  void read(S* out) override {
    for (std::size_t k = 0; k < shards_.size(); ++k)
      on_device(k, [&] { shards_[k]->read(out + static_cast<std::size_t>(ranges_[k].begin) * out_width_); });
  }
  BatchStatus status() override {
    std::vector<BatchStatus> statuses(shards_.size());
    failed_.assign(static_cast<std::size_t>(count_), -1);
    for (std::size_t k = 0; k < shards_.size(); ++k)
      on_device(k, [&] {
        statuses[k] = shards_[k]->status();
        detail::keep_failed_dofs(statuses[k], ranges_[k], failed_.data());
      });
    return detail::merge_shard_statuses(statuses, count_, failed_.data());
  }
  std::string strategy() const override {
    return shards_.front()->strategy() + "-x" + std::to_string(shards_.size());
  }

 private:
  // f() with shard k's device current; errors name the device
  template <class F>
  void on_device(std::size_t k, F&& f) {
    const std::string label = "device " + std::to_string(devices_[k]) + ": ";
    cuda::DeviceScope scope(devices_[k]);
    if (!scope.ok()) throw DataError(label + scope.error());
    try {
      f();
    } catch (const DataError& e) {
      throw DataError(label + e.what());
    }
  }
  template <class F>
  void each(F&& f) {
    for (std::size_t k = 0; k < shards_.size(); ++k) on_device(k, [&] { f(*shards_[k]); });
  }

  std::vector<std::unique_ptr<ResidentBatch<S>>> shards_;
  std::vector<int> devices_;
  std::vector<ShardRange> ranges_;
  std::size_t out_width_;
  Index count_;
  std::vector<int> failed_;  // (count) after status()
};

}  // namespace

template <class S>
std::unique_ptr<ResidentBatch<S>> make_resident_batch(Algo algo, Engine& engine, Index nv, Index nq,
                                                     const BatchIn<S>& in) {
  using D = cuda::DeviceBatch<S>;
  if (auto* sharded = dynamic_cast<ShardedEngine*>(&engine)) {
    // one resident batch per shard, each of its instances' rows, made on its device
    const int n = sharded->shard_count();
    const auto rows = [&](const S* p, Index b, Index w) { return p ? p + static_cast<std::size_t>(b) * w : nullptr; };
    std::vector<std::unique_ptr<ResidentBatch<S>>> shards;
    std::vector<int> devices;
    std::vector<ShardRange> ranges;
    for (int k = 0; k < n; ++k) {
      const ShardRange r = shard_range(static_cast<Index>(in.count), n, k);
      const int device = sharded->shard_device(k);
      cuda::DeviceScope scope(device);
      if (!scope.ok()) throw UsageError("device " + std::to_string(device) + ": " + scope.error(), false);
      const BatchIn<S> part{static_cast<std::size_t>(r.count), rows(in.q, r.begin, nq), rows(in.qd, r.begin, nv),
                            rows(in.qdd, r.begin, nv), rows(in.tau, r.begin, nv)};
      std::unique_ptr<ResidentBatch<S>> shard;
      try {
        shard = make_resident_batch(algo, sharded->shard_engine(k), nv, nq, part);
      } catch (const UsageError& e) {
        throw UsageError("device " + std::to_string(device) + ": " + e.what(), false);
      }
      if (!shard) return nullptr;  // an engine without a device-resident batch
      shards.push_back(std::move(shard));
      devices.push_back(device);
      ranges.push_back(r);
    }
    return std::make_unique<ShardedResidentBatch<S>>(std::move(shards), std::move(devices), std::move(ranges),
                                                     output_width(algo, nv), static_cast<Index>(in.count));
  }
  const std::size_t width = output_width(algo, nv);
  if (algo == Algo::Fd) {
    auto& e = dynamic_cast<cuda::CudaForwardDynamics<S>&>(engine);
    // hybrid: compute() only; the aba fallback and the run-time check's retries and
    // report need the host to see each instance (the check's device cost:
    // bench_cuda_fd's +check rows)
    if (e.method() == FdMethod::Hybrid || e.fallback_aba() || e.strategy().find("+check") != std::string::npos)
      return nullptr;
    return std::make_unique<CudaResidentBatch<S>>(
        e.strategy(), "the forward dynamics", nv, std::vector<const S*>{in.q, in.qd, in.tau}, in.count, width,
        e.device_bytes(),
        [&e](const D& d) {
          return e.compute_async({d.input(0), d.input(1), d.input(2)}, d.output(), d.failed_dof(), d.stream());
        },
        pivot_failure(e.method()), nq);
  }
  if (algo == Algo::DId || algo == Algo::DFd || algo == Algo::D2Id) {
    // the output's three blocks (nv x nv, or nv^3 for d2id), instance innermost: block k
    // from entry k width / 3
    const auto block = [n = static_cast<std::ptrdiff_t>(width / 3)](const D& d, int k) {
      const BatchView<S> o = d.output();
      return BatchView<S>{o.data + k * n * o.dof_stride, o.batch, o.dof_stride, o.batch_stride};
    };
    if (algo == Algo::D2Id) {
      auto& e = dynamic_cast<cuda::CudaIdSecondDerivatives<S>&>(engine);
      return std::make_unique<CudaResidentBatch<S>>(
          e.strategy(), "the second-order inverse-dynamics derivatives", nv,
          std::vector<const S*>{in.q, in.qd, in.qdd}, in.count, width, std::size_t(0), [&e, block](const D& d) {
            return e.compute_async({d.input(0), d.input(1), d.input(2)},
                                   {block(d, 0), block(d, 1), block(d, 2), {}}, d.stream());
          });
    }
    if (algo == Algo::DFd) {
      auto& e = dynamic_cast<cuda::CudaFdDerivatives<S>&>(engine);
      return std::make_unique<CudaResidentBatch<S>>(
          e.strategy(), "the forward-dynamics derivatives", nv, std::vector<const S*>{in.q, in.qd, in.tau}, in.count,
          width, std::size_t(0),
          [&e, block](const D& d) {
            return e.compute_async({d.input(0), d.input(1), d.input(2)},
                                   {block(d, 0), block(d, 1), block(d, 2), {}}, d.failed_dof(), d.stream());
          },
          Failure::ArticulatedPivot, nq);
    }
    auto& e = dynamic_cast<cuda::CudaIdDerivatives<S>&>(engine);
    return std::make_unique<CudaResidentBatch<S>>(
        e.strategy(), "the inverse-dynamics derivatives", nv, std::vector<const S*>{in.q, in.qd, in.qdd}, in.count,
        width, std::size_t(0), [&e, block](const D& d) {
          return e.compute_async({d.input(0), d.input(1), d.input(2)}, {block(d, 0), block(d, 1), block(d, 2)},
                                 d.stream());
        },
        Failure::None, nq);
  }
  if (algo == Algo::Mass) {
    auto& e = dynamic_cast<cuda::CudaMassMatrix<S>&>(engine);
    return std::make_unique<CudaResidentBatch<S>>(
        e.strategy(), "the mass matrix", nv, std::vector<const S*>{in.q}, in.count, width, e.device_bytes(),
        [&e](const D& d) { return e.compute_async(d.input(0), d.output(), d.stream()); }, Failure::None, nq);
  }
  if (algo == Algo::Bias) {
    auto& e = dynamic_cast<cuda::CudaBiasForces<S>&>(engine);
    return std::make_unique<CudaResidentBatch<S>>(
        e.strategy(), "the bias forces", nv, std::vector<const S*>{in.q, in.qd}, in.count, width,
        e.device_bytes(), [&e](const D& d) { return e.compute_async({d.input(0), d.input(1)}, d.output(), d.stream()); },
        Failure::None, nq);
  }
  auto& e = dynamic_cast<cuda::CudaInverseDynamics<S>&>(engine);
  return std::make_unique<CudaResidentBatch<S>>(
      e.strategy(), "the inverse dynamics", nv, std::vector<const S*>{in.q, in.qd, in.qdd}, in.count, width,
      e.device_bytes(),
      [&e](const D& d) { return e.compute_async({d.input(0), d.input(1), d.input(2)}, d.output(), d.stream()); },
      Failure::None, nq);
}
template <class S>
std::unique_ptr<ResidentBatch<S>> make_resident_kinematics(Kinematics<S>& engine, Index nv, const S* q,
                                                           std::size_t count, std::size_t fk_width,
                                                           std::size_t jac_width) {
  auto& e = dynamic_cast<cuda::CudaKinematics<S>&>(engine);
  return std::make_unique<CudaResidentBatch<S>>(
      e.strategy(), "the kinematics", nv, std::vector<const S*>{q}, count, fk_width + jac_width, 0,
      [&e, fk_width, jac_width](const cuda::DeviceBatch<S>& d) {
        // the output (width x B, structure-of-arrays): the poses' rows, then J's
        const BatchView<S> out = d.output();
        const BatchView<S> poses{fk_width ? out.data : nullptr, out.batch, out.dof_stride, out.batch_stride};
        const BatchView<S> J{jac_width ? out.data + fk_width * out.dof_stride : nullptr, out.batch, out.dof_stride,
                             out.batch_stride};
        return e.compute_async(d.input(0), poses, J, d.stream());
      });
}
template <class S>
std::unique_ptr<ResidentBatch<S>> make_resident_loops(ConstrainedForwardDynamics<S>& engine, Index nv, const S* q,
                                                      const S* qd, const S* tau, std::size_t count) {
  auto& e = dynamic_cast<cuda::CudaConstrainedForwardDynamics<S>&>(engine);
  return std::make_unique<CudaResidentBatch<S>>(
      e.strategy(), "the closed-loop forward dynamics", nv, std::vector<const S*>{q, qd, tau}, count,
      static_cast<std::size_t>(nv + e.rows()), std::size_t(0),
      [&e, nv](const cuda::DeviceBatch<S>& d) {
        // the output (nv + m x B, structure-of-arrays): qdd's rows, then lambda's
        const BatchView<S> out = d.output();
        const BatchView<S> qdd{out.data, out.batch, out.dof_stride, out.batch_stride};
        const BatchView<S> lambda{out.data + nv * out.dof_stride, out.batch, out.dof_stride, out.batch_stride};
        return e.compute_async({d.input(0), d.input(1), d.input(2), nullptr}, qdd, lambda, d.failed_dof(),
                               d.stream());
      },
      Failure::MassMatrixPivot);
}
template std::unique_ptr<ResidentBatch<float>> make_resident_loops(ConstrainedForwardDynamics<float>&, Index,
                                                                   const float*, const float*, const float*,
                                                                   std::size_t);
template std::unique_ptr<ResidentBatch<double>> make_resident_loops(ConstrainedForwardDynamics<double>&, Index,
                                                                    const double*, const double*, const double*,
                                                                    std::size_t);
template std::unique_ptr<ResidentBatch<float>> make_resident_kinematics(Kinematics<float>&, Index, const float*,
                                                                        std::size_t, std::size_t, std::size_t);
template std::unique_ptr<ResidentBatch<double>> make_resident_kinematics(Kinematics<double>&, Index, const double*,
                                                                         std::size_t, std::size_t, std::size_t);

template std::unique_ptr<ResidentBatch<float>> make_resident_batch(Algo, Engine&, Index, Index, const BatchIn<float>&);
template std::unique_ptr<ResidentBatch<double>> make_resident_batch(Algo, Engine&, Index, Index, const BatchIn<double>&);

}  // namespace scandyn::cli

#endif  // SCANDYN_HAS_CUDA
