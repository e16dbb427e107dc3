// cpu_fallback/hybrid_dynamics.cpp: the serial and OpenMP hybrid dynamics: the
// reference hybrid_dynamics (Featherstone 2008, 9.2) per instance, threads over
// instances (instance_loop.hpp), bit-identical to the reference ("recursion"); and
// for long unbranched chains the parallel chain hybrid dynamics ("parallel":
// ChainHybridDynamics, scans over links, scandyn/algorithm/chain_hybrid.hpp), chosen
// as forward dynamics' parallel method is (choose_fd_method), or by fd_method.
#include <vector>

#include "cpu_engines.hpp"
#include "instance_loop.hpp"
#include "scandyn/algorithm/chain_hybrid.hpp"
#include "scandyn/algorithm/reference.hpp"

namespace scandyn {
namespace cpu {
namespace {

template <class S>
class CpuHybridDynamics final : public HybridDynamics<S> {
 public:
  CpuHybridDynamics(const ModelTpl<S>& model, const std::vector<unsigned char>& prescribed, const BackendOptions& o)
      : model_(model),
        prescribed_(prescribed),
        kind_(o.backend),
        threads_(instance_threads(engine_threads(o), o.max_batch)),
        max_batch_(o.max_batch) {
    failed_.assign(static_cast<std::size_t>(std::max<Index>(max_batch_, 1)), -1);
    for (int t = 0; t < threads_; ++t) data_.emplace_back(model_, false);
    rows_ = RowScratch<S>(threads_, 6, static_cast<std::size_t>(model.nv()));
  }

  BatchStatus compute(const HybridBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& tau) override {
    check_batch(in, qdd, tau, max_batch_);
    const Index B = in.q.batch, nv = model_.nv();
    for_instance_blocks(threads_, B, [&](int t, Index begin, Index end) {
      for (Index b = begin; b < end; ++b) {
        const S* q = gather(in.q, b, nv, rows_.row(t, 0));
        const S* qd = gather(in.qd, b, nv, rows_.row(t, 1));
        const S* qdd_in = gather(in.qdd, b, nv, rows_.row(t, 2));
        const S* tau_in = gather(in.tau, b, nv, rows_.row(t, 3));
        const Force<S>* fext = in.fext ? in.fext + static_cast<std::size_t>(b) * nv : nullptr;
        S* qdd_out = output_row(qdd, b, rows_.row(t, 4));
        S* tau_out = output_row(tau, b, rows_.row(t, 5));
        const Status st =
            hybrid_dynamics(model_, data_[t], q, qd, prescribed_.data(), qdd_in, tau_in, qdd_out, tau_out, fext);
        failed_[static_cast<std::size_t>(b)] = static_cast<int>(st.failed_dof);
        if (st.ok()) {
          scatter(qdd_out, qdd, b, nv);
          scatter(tau_out, tau, b, nv);
        }
      }
    });
    return summarize_failures(failed_.data(), B, Failure::ArticulatedPivot);
  }

  const std::vector<unsigned char>& prescribed() const override { return prescribed_; }
  std::string strategy() const override { return "recursion"; }
  BackendKind backend() const override { return kind_; }
  bool exact() const override { return true; }

 private:
  const ModelTpl<S>& model_;
  std::vector<unsigned char> prescribed_;  // (nv) nonzero: the DoF's acceleration is given
  BackendKind kind_;
  int threads_;
  Index max_batch_;
  std::vector<int> failed_;       // (max_batch) failed DoF per instance, -1: none
  std::vector<DataTpl<S>> data_;  // (threads) workspaces
  RowScratch<S> rows_;            // per thread: q, qd, qdd in, tau in, qdd out, tau out of one instance
};

// The parallel chain hybrid dynamics on the engine API.
template <class S>
class CpuChainHybridDynamics final : public HybridDynamics<S> {
 public:
  CpuChainHybridDynamics(const ModelTpl<S>& model, const std::vector<unsigned char>& prescribed,
                         const BackendOptions& o)
      : prescribed_(prescribed), kind_(o.backend), max_batch_(o.max_batch),
        chain_(model, prescribed, std::max<Index>(o.max_batch, 1), engine_threads(o)) {
    failed_.assign(static_cast<std::size_t>(std::max<Index>(max_batch_, 1)), -1);
  }

  BatchStatus compute(const HybridBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& tau) override {
    check_batch(in, qdd, tau, max_batch_);
    chain_.compute(in, qdd, tau, failed_.data());
    return summarize_failures(failed_.data(), in.q.batch, Failure::ArticulatedPivot);
  }

  const std::vector<unsigned char>& prescribed() const override { return prescribed_; }
  std::string strategy() const override { return "parallel"; }
  BackendKind backend() const override { return kind_; }

 private:
  std::vector<unsigned char> prescribed_;
  BackendKind kind_;
  Index max_batch_;
  ChainHybridDynamics<S> chain_;
  std::vector<int> failed_;  // (max_batch) first failed link per instance, -1: none
};

}  // namespace

template <class S>
std::unique_ptr<HybridDynamics<S>> make_hybrid_dynamics(const ModelTpl<S>& model,
                                                        const std::vector<unsigned char>& prescribed,
                                                        const BackendOptions& o) {
  // fd_method: Auto (the parallel chain where forward dynamics would take it), Aba (the
  // recursion), Parallel (the chain scans; BackendError for a model that is not chains):
  // choose_hybrid_method
  if (choose_hybrid_method(o.backend, model, o.fd_method, o.max_batch, engine_threads(o)) == FdMethod::Parallel)
    return std::make_unique<CpuChainHybridDynamics<S>>(model, prescribed, o);
  return std::make_unique<CpuHybridDynamics<S>>(model, prescribed, o);
}
template std::unique_ptr<HybridDynamics<float>> make_hybrid_dynamics(const ModelTpl<float>&,
                                                                     const std::vector<unsigned char>&,
                                                                     const BackendOptions&);
template std::unique_ptr<HybridDynamics<double>> make_hybrid_dynamics(const ModelTpl<double>&,
                                                                      const std::vector<unsigned char>&,
                                                                      const BackendOptions&);

}  // namespace cpu
}  // namespace scandyn
