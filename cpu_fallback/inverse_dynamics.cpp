// cpu_fallback/inverse_dynamics.cpp: the serial and OpenMP inverse dynamics and
// bias forces: threads over instances (the serial recursion, rnea / bias_forces), or
// for a few long chains scans over links (rnea_scan, all threads on one instance).
#include <vector>

#include "cpu_engines.hpp"
#include "instance_loop.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/algorithm/rnea_scan.hpp"
#include "simd_batch.hpp"

namespace scandyn {
namespace cpu {

int engine_threads(const BackendOptions& o) {
  if (o.backend == BackendKind::Serial) return 1;
  const std::string why = backend_unusable(o.backend);
  if (!why.empty()) throw BackendError(why);
  return backend_threads(o.backend, o.threads);
}

namespace {

// tau = RNEA(q, qd, qdd, fext), or with kBias h = RNEA(q, qd, 0, fext), for a batch.
// The bias forces are the same engine with no qdd (bias_forces per instance, or the
// scans with qdd = 0); CpuInverseDynamics and CpuBiasForces below give it each
// interface's compute().
template <class S, class Interface, bool kBias>
class CpuRnea : public Interface {
 public:
  CpuRnea(const ModelTpl<S>& model, const BackendOptions& o)
      : model_(model), kind_(o.backend), threads_(engine_threads(o)), max_batch_(o.max_batch) {
    // Auto: inverse dynamics by shape; the bias forces by the recursion (their scans
    // exist, for a caller that asks, but have not been measured against it)
    strategy_ = o.strategy != IdStrategy::Auto ? o.strategy
                : kBias                        ? IdStrategy::Recursion
                                               : choose_id_strategy(kind_, model.nv(), max_batch_, threads_);
    const Index nv = model.nv();
    const int workers = instance_threads(threads_, max_batch_);
    if (strategy_ == IdStrategy::Recursion) {
      for (int t = 0; t < workers; ++t) data_.emplace_back(model_, /*mass_matrix=*/false);
      simd_ = make_simd_batches(model_, o.simd, threads_, max_batch_);
    } else {
      // one scan workspace using all threads across links, instances in turn
      scan_.emplace_back(model_, threads_);
      zero_.assign(static_cast<std::size_t>(nv), S(0));
    }
    rows_ = RowScratch<S>(strategy_ == IdStrategy::Recursion ? workers : 1, 4, static_cast<std::size_t>(model.nq()));
  }

  std::string strategy() const override {
    return std::string(to_string(strategy_)) + (simd_.empty() ? "" : "-simd" + std::to_string(SimdBatch<S>::W));
  }
  BackendKind backend() const override { return kind_; }
  bool exact() const override { return strategy_ == IdStrategy::Recursion && (simd_.empty() || simd_exact()); }

 protected:
  void run(const BatchView<const S>& q, const BatchView<const S>& qd, const BatchView<const S>& qdd,
           const Force<S>* fext, const BatchView<S>& out) {
    const Index nv = model_.nv(), nq = model_.nq(), nb = model_.nbodies();
    const Index B = q.batch;
    const auto instance_fext = [&](Index b) { return fext ? fext + static_cast<std::size_t>(b) * nb : nullptr; };
    if (strategy_ == IdStrategy::Recursion) {
      for_instance_blocks(threads_, B, [&](int t, Index begin, Index end) {
        for_simd_groups(
            simd_.empty() ? nullptr : &simd_[t], begin, end,
            [&](Index b) {
              simd_[t].rnea(q, qd, qdd, fext, out, b);  // qdd without data: the bias forces
              return true;
            },
            [&](Index b) {
              const S* qb = gather(q, b, nq, rows_.row(t, 0));
              const S* qdb = gather(qd, b, nv, rows_.row(t, 1));
              S* o = output_row(out, b, rows_.row(t, 3));
              if constexpr (kBias) bias_forces(model_, data_[t], qb, qdb, o, instance_fext(b));
              else rnea(model_, data_[t], qb, qdb, gather(qdd, b, nv, rows_.row(t, 2)), o, instance_fext(b));
              scatter(o, out, b, nv);
            });
      });
      return;
    }
    const ScanForm form = strategy_ == IdStrategy::ScanWorld ? ScanForm::World : ScanForm::Local;
    for (Index b = 0; b < B; ++b) {
      const S* qddb = kBias ? zero_.data() : gather(qdd, b, nv, rows_.row(0, 2));
      S* o = output_row(out, b, rows_.row(0, 3));
      rnea_scan(model_, scan_[0], form, gather(q, b, nq, rows_.row(0, 0)), gather(qd, b, nv, rows_.row(0, 1)), qddb,
                o, instance_fext(b));
      scatter(o, out, b, nv);
    }
  }

  const ModelTpl<S>& model_;
  BackendKind kind_;
  IdStrategy strategy_;
  int threads_;
  Index max_batch_;
  std::vector<DataTpl<S>> data_;        // (instance_threads) recursion workspaces
  std::vector<SimdBatch<S>> simd_;      // (instance_threads, or none) the recursion's SIMD workspaces
  std::vector<ScanWorkspace<S>> scan_;  // (1) scan workspace
  std::vector<S> zero_;                 // (nv) the bias forces' qdd for the scans
  RowScratch<S> rows_;                  // per thread: q, qd, qdd, out rows of one instance
};

template <class S>
class CpuInverseDynamics final : public CpuRnea<S, InverseDynamics<S>, false> {
 public:
  using CpuRnea<S, InverseDynamics<S>, false>::CpuRnea;
  void compute(const IdBatchIn<S>& in, const BatchView<S>& tau) override {
    check_batch(in, tau, this->max_batch_);
    this->run(in.q, in.qd, in.qdd, in.fext, tau);
  }
};

template <class S>
class CpuBiasForces final : public CpuRnea<S, BiasForces<S>, true> {
 public:
  using CpuRnea<S, BiasForces<S>, true>::CpuRnea;
  void compute(const BiasBatchIn<S>& in, const BatchView<S>& h) override {
    check_batch(in, h, this->max_batch_);
    this->run(in.q, in.qd, BatchView<const S>{}, in.fext, h);
  }
};

}  // namespace

template <class S>
std::unique_ptr<InverseDynamics<S>> make_inverse_dynamics(const ModelTpl<S>& model, const BackendOptions& o) {
  return std::make_unique<CpuInverseDynamics<S>>(model, o);
}
template <class S>
std::unique_ptr<BiasForces<S>> make_bias_forces(const ModelTpl<S>& model, const BackendOptions& o) {
  return std::make_unique<CpuBiasForces<S>>(model, o);
}

template std::unique_ptr<InverseDynamics<float>> make_inverse_dynamics(const ModelTpl<float>&, const BackendOptions&);
template std::unique_ptr<InverseDynamics<double>> make_inverse_dynamics(const ModelTpl<double>&, const BackendOptions&);
template std::unique_ptr<BiasForces<float>> make_bias_forces(const ModelTpl<float>&, const BackendOptions&);
template std::unique_ptr<BiasForces<double>> make_bias_forces(const ModelTpl<double>&, const BackendOptions&);

}  // namespace cpu
}  // namespace scandyn
