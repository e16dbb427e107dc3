// cpu_fallback/derivatives.cpp: the serial and OpenMP derivatives of inverse and
// forward dynamics, the reference rnea_derivatives / aba_derivatives per instance
// (scandyn/algorithm/derivatives.hpp), threads over instances.
#include <algorithm>
#include <vector>

#include "cpu_engines.hpp"
#include "instance_loop.hpp"
#include "scandyn/algorithm/derivatives.hpp"

namespace scandyn {
namespace cpu {
namespace {

// What both engines hold: the model, the backend and its threads, and per thread a
// workspace and contiguous rows for one instance's inputs.
template <class S, class Interface>
class CpuDerivativeEngine : public Interface {
 public:
  CpuDerivativeEngine(const ModelTpl<S>& model, const BackendOptions& o, const char* strategy)
      : model_(model),
        kind_(o.backend),
        threads_(instance_threads(engine_threads(o), o.max_batch)),
        max_batch_(o.max_batch),
        strategy_(strategy),
        rows_(threads_, 4, static_cast<std::size_t>(model.nq())) {
    for (int t = 0; t < threads_; ++t) data_.emplace_back(model);
  }
  std::string strategy() const override { return strategy_; }
  BackendKind backend() const override { return kind_; }
  bool exact() const override { return true; }

 protected:
  // instance b's entries of v as a contiguous array (row k of thread t's rows; row 0:
  // q, nq entries, the others nv)
  const S* input(const BatchView<const S>& v, Index b, int t, int k) {
    return gather(v, b, k == 0 ? model_.nq() : model_.nv(), rows_.row(t, k));
  }
  // instance b's body wrenches (nbodies each), or null
  const Force<S>* wrenches(const Force<S>* fext, Index b) const {
    return fext ? fext + b * model_.nbodies() : nullptr;
  }
  const ModelTpl<S>& model_;
  BackendKind kind_;
  int threads_;
  Index max_batch_;
  const char* strategy_;
  std::vector<DerivativeDataTpl<S>> data_;  // (threads) workspaces
  RowScratch<S> rows_;                      // per thread: q (nq), qd, qdd or tau, qdd out (nv each)
};

template <class S>
class CpuIdDerivatives final : public CpuDerivativeEngine<S, IdDerivatives<S>> {
  using Base = CpuDerivativeEngine<S, IdDerivatives<S>>;

 public:
  CpuIdDerivatives(const ModelTpl<S>& model, const BackendOptions& o) : Base(model, o, "rnea_derivatives") {}

  void compute(const IdBatchIn<S>& in, const IdDerivativesOut<S>& out) override {
    check_batch(in, out, this->max_batch_);
    const Index nv = this->model_.nv();
    for_instance_blocks(this->threads_, in.q.batch, [&](int t, Index begin, Index end) {
      for (Index b = begin; b < end; ++b)
        rnea_derivatives(this->model_, this->data_[t], this->input(in.q, b, t, 0), this->input(in.qd, b, t, 1),
                         this->input(in.qdd, b, t, 2), this->wrenches(in.fext, b),
                         instance_matrix(out.dtau_dq, b, nv), instance_matrix(out.dtau_dqd, b, nv),
                         instance_matrix(out.M, b, nv));
    });
  }
};

template <class S>
class CpuFdDerivatives final : public CpuDerivativeEngine<S, FdDerivatives<S>> {
  using Base = CpuDerivativeEngine<S, FdDerivatives<S>>;

 public:
  CpuFdDerivatives(const ModelTpl<S>& model, const BackendOptions& o)
      : Base(model, o, "aba_derivatives"), failed_dof_(static_cast<std::size_t>(std::max<Index>(o.max_batch, 1))) {}

  BatchStatus compute(const FdBatchIn<S>& in, const FdDerivativesOut<S>& out) override {
    check_batch(in, out, this->max_batch_);
    const Index nv = this->model_.nv();
    for_instance_blocks(this->threads_, in.q.batch, [&](int t, Index begin, Index end) {
      for (Index b = begin; b < end; ++b) {
        S* const row = this->rows_.row(t, 3);
        S* qdd = out.qdd.data ? output_row(out.qdd, b, row) : row;
        const Status st = aba_derivatives(this->model_, this->data_[t], this->input(in.q, b, t, 0),
                                          this->input(in.qd, b, t, 1), this->input(in.tau, b, t, 2),
                                          this->wrenches(in.fext, b), qdd,
                                          instance_matrix(out.dqdd_dq, b, nv), instance_matrix(out.dqdd_dqd, b, nv),
                                          instance_matrix(out.dqdd_dtau, b, nv));
        if (out.qdd.data) scatter(qdd, out.qdd, b, nv);
        failed_dof_[static_cast<std::size_t>(b)] = st.failed_dof;
      }
    });
    return summarize_failures(failed_dof_.data(), in.q.batch, Failure::ArticulatedPivot);
  }

 private:
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
