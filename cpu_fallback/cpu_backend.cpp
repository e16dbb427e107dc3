// The CPU backends: serial (one thread) and OpenMP (threads over instances, or
// scans over links for a few long chains). Both run the shared step functions.
#include <algorithm>
#include <vector>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/backend.hpp"
#include "scandyn/build_config.hpp"
#if SCANDYN_HAS_CUDA
#include "scandyn/cuda/inverse_dynamics.hpp"
#endif

#ifdef _OPENMP
#include <omp.h>
#endif

namespace scandyn {

const char* to_string(BackendKind b) {
  switch (b) {
    case BackendKind::Serial: return "serial";
    case BackendKind::OpenMP: return "openmp";
    case BackendKind::Cuda: return "cuda";
  }
  return "?";
}

const char* to_string(IdStrategy s) {
  switch (s) {
    case IdStrategy::Auto: return "auto";
    case IdStrategy::Recursion: return "recursion";
    case IdStrategy::ScanLocal: return "scan-local";
    case IdStrategy::ScanWorld: return "scan-world";
  }
  return "?";
}

BackendKind parse_backend(const std::string& name) {
  if (name == "serial") return BackendKind::Serial;
  if (name == "openmp") return BackendKind::OpenMP;
  if (name == "cuda") return BackendKind::Cuda;
  throw BackendError("unknown backend '" + name + "' (expected serial, openmp or cuda)");
}

IdStrategy parse_strategy(const std::string& name) {
  if (name == "auto") return IdStrategy::Auto;
  if (name == "recursion") return IdStrategy::Recursion;
  if (name == "scan-local") return IdStrategy::ScanLocal;
  if (name == "scan-world") return IdStrategy::ScanWorld;
  throw BackendError("unknown strategy '" + name + "' (expected auto, recursion, scan-local or scan-world)");
}

IdStrategy choose_strategy(Index nv, Index batch, int threads) {
  // Instances are independent: splitting them costs nothing. Scans over links pay
  // 1.5-3x the arithmetic of the recursion, so they only win when there are fewer
  // instances than threads and enough links to give every thread long runs: from
  // about 10^4 links on 16 threads for ropes, curtains and random trees alike
  // (docs/accuracy-id-scan.md).
  if (threads <= 1 || batch >= threads || nv < 4096) return IdStrategy::Recursion;
  return IdStrategy::ScanLocal;
}

template <class S>
void check_batch(const IdBatchIn<S>& in, const BatchView<S>& tau, Index max_batch) {
  const Index B = in.q.batch;
  if (in.qd.batch != B || in.qdd.batch != B || tau.batch != B)
    throw BackendError("batch sizes disagree: q " + std::to_string(B) + ", qd " + std::to_string(in.qd.batch) +
                       ", qdd " + std::to_string(in.qdd.batch) + ", tau " + std::to_string(tau.batch));
  if (B < 0) throw BackendError("negative batch size " + std::to_string(B));
  if (B > max_batch)
    throw BackendError("batch of " + std::to_string(B) + " instances exceeds the engine's max_batch " +
                       std::to_string(max_batch));
  if (B > 0 && (!in.q.data || !in.qd.data || !in.qdd.data || !tau.data))
    throw BackendError("null data pointer in a batch of " + std::to_string(B) + " instances");
}
template void check_batch(const IdBatchIn<float>&, const BatchView<float>&, Index);
template void check_batch(const IdBatchIn<double>&, const BatchView<double>&, Index);

template <class S>
void check_batch(const FdBatchIn<S>& in, const BatchView<S>& qdd, Index max_batch) {
  const Index B = in.q.batch;
  if (in.qd.batch != B || in.tau.batch != B || qdd.batch != B)
    throw BackendError("batch sizes disagree: q " + std::to_string(B) + ", qd " + std::to_string(in.qd.batch) +
                       ", tau " + std::to_string(in.tau.batch) + ", qdd " + std::to_string(qdd.batch));
  if (B < 0) throw BackendError("negative batch size " + std::to_string(B));
  if (B > max_batch)
    throw BackendError("batch of " + std::to_string(B) + " instances exceeds the engine's max_batch " +
                       std::to_string(max_batch));
  if (B > 0 && (!in.q.data || !in.qd.data || !in.tau.data || !qdd.data))
    throw BackendError("null data pointer in a batch of " + std::to_string(B) + " instances");
}
template void check_batch(const FdBatchIn<float>&, const BatchView<float>&, Index);
template void check_batch(const FdBatchIn<double>&, const BatchView<double>&, Index);

int openmp_threads() {
#ifdef _OPENMP
  return omp_get_max_threads();
#else
  return 1;
#endif
}

namespace {

template <class S>
class CpuInverseDynamics final : public InverseDynamics<S> {
 public:
  CpuInverseDynamics(const ModelTpl<S>& model, BackendKind kind, IdStrategy strategy, int threads, Index max_batch)
      : model_(model), kind_(kind), threads_(threads), max_batch_(max_batch) {
    strategy_ = strategy == IdStrategy::Auto ? choose_strategy(model.nv(), max_batch, threads) : strategy;
    const Index nv = model.nv();
    if (strategy_ == IdStrategy::Recursion) {
      // one reference workspace and contiguous state per thread
      for (int t = 0; t < threads_; ++t) data_.emplace_back(model_, /*mass_matrix=*/false);
    } else {
      // one scan workspace using all threads across links, instances in turn
      scan_.emplace_back(model_, threads_);
    }
    state_.resize(static_cast<std::size_t>(threads_) * 4 * nv);
  }

  void compute(const IdBatchIn<S>& in, const BatchView<S>& tau) override {
    check_batch(in, tau, max_batch_);
    const Index B = in.q.batch;
    if (strategy_ == IdStrategy::Recursion) compute_instances(in, tau, B);
    else compute_scans(in, tau, B);
  }

  std::string strategy() const override { return to_string(strategy_); }
  std::string backend() const override { return to_string(kind_); }

 private:
  // the per-thread contiguous copies of one instance's q, qd, qdd, tau
  S* state(int t, int k) { return state_.data() + (static_cast<std::size_t>(t) * 4 + k) * model_.nv(); }

  void gather(const IdBatchIn<S>& in, Index b, S* q, S* qd, S* qdd) const {
    const Index nv = model_.nv();
    for (Index i = 0; i < nv; ++i) {
      q[i] = in.q.at(i, b);
      qd[i] = in.qd.at(i, b);
      qdd[i] = in.qdd.at(i, b);
    }
  }

  void compute_instances(const IdBatchIn<S>& in, const BatchView<S>& tau, Index B) {
    if (threads_ == 1 || B == 1) {
      // no parallel region: entering one costs more than a small robot's whole RNEA
      instances(in, tau, 0, 0, B);
      return;
    }
#pragma omp parallel num_threads(threads_)
    {
#ifdef _OPENMP
      const int t = omp_get_thread_num();
      const int nt = omp_get_num_threads();
#else
      const int t = 0, nt = 1;
#endif
      // contiguous blocks of instances, one per thread (static schedule)
      const Index per = B / nt, extra = B % nt;
      const Index begin = t * per + std::min<Index>(t, extra);
      instances(in, tau, t, begin, begin + per + (t < extra ? 1 : 0));
    }
  }

  // instances [begin, end) on thread t's workspace
  void instances(const IdBatchIn<S>& in, const BatchView<S>& tau, int t, Index begin, Index end) {
    const Index nv = model_.nv();
    S *q = state(t, 0), *qd = state(t, 1), *qdd = state(t, 2), *out = state(t, 3);
    for (Index b = begin; b < end; ++b) {
      gather(in, b, q, qd, qdd);
      rnea(model_, data_[t], q, qd, qdd, out, in.fext ? in.fext + static_cast<std::size_t>(b) * nv : nullptr);
      for (Index i = 0; i < nv; ++i) tau.at(i, b) = out[i];
    }
  }

  void compute_scans(const IdBatchIn<S>& in, const BatchView<S>& tau, Index B) {
    const Index nv = model_.nv();
    S *q = state(0, 0), *qd = state(0, 1), *qdd = state(0, 2), *out = state(0, 3);
    const ScanForm form = strategy_ == IdStrategy::ScanWorld ? ScanForm::World : ScanForm::Local;
    for (Index b = 0; b < B; ++b) {
      gather(in, b, q, qd, qdd);
      rnea_scan(model_, scan_[0], form, q, qd, qdd, out, in.fext ? in.fext + static_cast<std::size_t>(b) * nv : nullptr);
      for (Index i = 0; i < nv; ++i) tau.at(i, b) = out[i];
    }
  }

  const ModelTpl<S>& model_;
  BackendKind kind_;
  IdStrategy strategy_;
  int threads_;
  Index max_batch_;
  std::vector<DataTpl<S>> data_;        // (threads) recursion workspaces
  std::vector<ScanWorkspace<S>> scan_;  // (1) scan workspace
  std::vector<S> state_;                // (threads x 4 x nv) contiguous per-thread state
};

}  // namespace

template <class S>
std::unique_ptr<InverseDynamics<S>> make_inverse_dynamics(const ModelTpl<S>& model, const BackendOptions& o) {
  switch (o.backend) {
    case BackendKind::Serial:
      return std::make_unique<CpuInverseDynamics<S>>(model, o.backend, o.strategy, 1, o.max_batch);
    case BackendKind::OpenMP: {
#if SCANDYN_HAS_OPENMP && defined(_OPENMP)
      const int threads = o.threads > 0 ? o.threads : openmp_threads();
      return std::make_unique<CpuInverseDynamics<S>>(model, o.backend, o.strategy, threads, o.max_batch);
#else
      throw BackendError("backend 'openmp' is not available in this build (configured with SCANDYN_OPENMP=OFF)");
#endif
    }
    case BackendKind::Cuda:
#if SCANDYN_HAS_CUDA
      return cuda::make_cuda_inverse_dynamics<S>(model, o);
#else
      throw BackendError("backend 'cuda' is not available in this build (configured without CUDA)");
#endif
  }
  throw BackendError("unknown backend");
}

template std::unique_ptr<InverseDynamics<float>> make_inverse_dynamics(const ModelTpl<float>&, const BackendOptions&);
template std::unique_ptr<InverseDynamics<double>> make_inverse_dynamics(const ModelTpl<double>&, const BackendOptions&);

}  // namespace scandyn
