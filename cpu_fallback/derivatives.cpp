// cpu_fallback/derivatives.cpp: the serial and OpenMP derivatives of inverse and
// forward dynamics, the reference rnea_derivatives / aba_derivatives per instance
// (scandyn/algorithm/derivatives.hpp), threads over instances.
#include <vector>

#include "cpu_engines.hpp"
#include "instance_loop.hpp"
#include "scandyn/algorithm/derivatives.hpp"

namespace scandyn {
namespace cpu {
namespace {

// Per-thread workspaces and contiguous input rows shared by both engines.
template <class S>
class DerivativeScratch {
 public:
  DerivativeScratch(const ModelTpl<S>& model, int threads) {
    for (int t = 0; t < threads; ++t) data.emplace_back(model);
    rows = RowScratch<S>(threads, 4, static_cast<std::size_t>(model.nv()));
  }
  std::vector<DerivativeDataTpl<S>> data;  // (threads) workspaces
  RowScratch<S> rows;                      // per thread: q, qd, qdd or tau (nv each), qdd out (nv)
};

template <class S>
class CpuIdDerivatives final : public IdDerivatives<S> {
 public:
  CpuIdDerivatives(const ModelTpl<S>& model, const BackendOptions& o)
      : model_(model), kind_(o.backend), threads_(engine_threads(o)), max_batch_(o.max_batch),
        scratch_(model, threads_) {}

  void compute(const IdBatchIn<S>& in, const IdDerivativesOut<S>& out) override {
    check_batch(in, out, max_batch_);
    const Index nv = model_.nv();
    for_instance_blocks(threads_, in.q.batch, [&](int t, Index begin, Index end) {
      for (Index b = begin; b < end; ++b) {
        rnea_derivatives(model_, scratch_.data[t], gather(in.q, b, nv, scratch_.rows.row(t, 0)),
                         gather(in.qd, b, nv, scratch_.rows.row(t, 1)),
                         gather(in.qdd, b, nv, scratch_.rows.row(t, 2)), in.fext ? in.fext + b * nv : nullptr,
                         instance_matrix(out.dtau_dq, b, nv), instance_matrix(out.dtau_dqd, b, nv),
                         instance_matrix(out.M, b, nv));
      }
    });
  }

  std::string strategy() const override { return "rnea_derivatives"; }
  BackendKind backend() const override { return kind_; }
  bool exact() const override { return true; }

 private:
  const ModelTpl<S>& model_;
  BackendKind kind_;
  int threads_;
  Index max_batch_;
  DerivativeScratch<S> scratch_;
};

template <class S>
class CpuFdDerivatives final : public FdDerivatives<S> {
 public:
  CpuFdDerivatives(const ModelTpl<S>& model, const BackendOptions& o)
      : model_(model), kind_(o.backend), threads_(engine_threads(o)), max_batch_(o.max_batch),
        scratch_(model, threads_), failed_dof_(static_cast<std::size_t>(o.max_batch)) {}

  BatchStatus compute(const FdBatchIn<S>& in, const FdDerivativesOut<S>& out) override {
    check_batch(in, out, max_batch_);
    const Index nv = model_.nv();
    for_instance_blocks(threads_, in.q.batch, [&](int t, Index begin, Index end) {
      for (Index b = begin; b < end; ++b) {
        S* qdd = out.qdd.data ? output_row(out.qdd, b, scratch_.rows.row(t, 3)) : scratch_.rows.row(t, 3);
        const Status st = aba_derivatives(model_, scratch_.data[t], gather(in.q, b, nv, scratch_.rows.row(t, 0)),
                                          gather(in.qd, b, nv, scratch_.rows.row(t, 1)),
                                          gather(in.tau, b, nv, scratch_.rows.row(t, 2)),
                                          in.fext ? in.fext + b * nv : nullptr, qdd,
                                          instance_matrix(out.dqdd_dq, b, nv), instance_matrix(out.dqdd_dqd, b, nv),
                                          instance_matrix(out.dqdd_dtau, b, nv));
        if (out.qdd.data) scatter(qdd, out.qdd, b, nv);
        failed_dof_[static_cast<std::size_t>(b)] = st.failed_dof;
      }
    });
    return summarize_failures(failed_dof_.data(), in.q.batch, Failure::ArticulatedPivot);
  }

  std::string strategy() const override { return "aba_derivatives"; }
  BackendKind backend() const override { return kind_; }
  bool exact() const override { return true; }

 private:
  const ModelTpl<S>& model_;
  BackendKind kind_;
  int threads_;
  Index max_batch_;
  DerivativeScratch<S> scratch_;
  std::vector<int> failed_dof_;  // (max_batch) per instance: -1 or the DoF whose pivot failed
};

}  // namespace

template <class S>
std::unique_ptr<IdDerivatives<S>> make_id_derivatives(const ModelTpl<S>& model, const BackendOptions& o) {
  return std::make_unique<CpuIdDerivatives<S>>(model, o);
}
template <class S>
std::unique_ptr<FdDerivatives<S>> make_fd_derivatives(const ModelTpl<S>& model, const BackendOptions& o) {
  return std::make_unique<CpuFdDerivatives<S>>(model, o);
}
template std::unique_ptr<IdDerivatives<float>> make_id_derivatives(const ModelTpl<float>&, const BackendOptions&);
template std::unique_ptr<IdDerivatives<double>> make_id_derivatives(const ModelTpl<double>&, const BackendOptions&);
template std::unique_ptr<FdDerivatives<float>> make_fd_derivatives(const ModelTpl<float>&, const BackendOptions&);
template std::unique_ptr<FdDerivatives<double>> make_fd_derivatives(const ModelTpl<double>&, const BackendOptions&);

}  // namespace cpu
}  // namespace scandyn
