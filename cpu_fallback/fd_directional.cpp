// cpu_fallback/fd_directional.cpp: the serial and OpenMP directional derivatives
// (JVP, VJP) of forward dynamics (make_fd_directional_derivatives,
// scandyn/engine.hpp): for unbranched chains from a fixed base the chunked scans of
// ChainFdDirectional (scandyn/algorithm/chain_directional.hpp, "parallel"), else the
// serial aba_jvp / aba_vjp per instance, threads over instances ("aba_jvp"; models with
// multi-DoF joints too: q of nq entries, fext one wrench per body).
#include <algorithm>
#include <memory>
#include <vector>

#include "cpu_engines.hpp"
#include "instance_loop.hpp"
#include "scandyn/algorithm/chain_directional.hpp"
#include "scandyn/algorithm/directional_derivatives.hpp"

namespace scandyn {
namespace cpu {
namespace {

template <class S>
class CpuFdDirectional final : public FdDirectionalDerivatives<S> {
 public:
  CpuFdDirectional(const ModelTpl<S>& model, const BackendOptions& o, bool chain)
      : model_(model),
        kind_(o.backend),
        max_batch_(std::max<Index>(o.max_batch, 1)),
        failed_(static_cast<std::size_t>(max_batch_), -1) {
    const int threads = engine_threads(o);
    if (chain) {
      chain_ = std::make_unique<ChainFdDirectional<S>>(model, max_batch_, threads);
    } else {
      threads_ = instance_threads(threads, max_batch_);
      rows_ = RowScratch<S>(threads_, 10, static_cast<std::size_t>(model.nq()));  // q: nq, the others nv
      for (int t = 0; t < threads_; ++t) data_.push_back(std::make_unique<AbaJvpData<S>>(model));
    }
  }
  std::string strategy() const override { return chain_ ? "parallel" : "aba_jvp"; }
  BackendKind backend() const override { return kind_; }
  bool exact() const override { return !chain_; }

  BatchStatus jvp(const FdBatchIn<S>& in, const BatchView<const S>& dq, const BatchView<const S>& dqd,
                  const BatchView<const S>& dtau, const BatchView<S>& qdd, const BatchView<S>& dqdd) override {
    check(in, qdd, {&dq, &dqd, &dtau}, {&dqdd});
    const Index B = in.q.batch, nv = model_.nv();
    if (chain_) {
      chain_->jvp(in, dq, dqd, dtau, qdd, dqdd, failed_.data());
    } else {
      each_instance(B, [&](int t, Index b) {
        S* o_qdd = output_row(qdd, b, rows_.row(t, 6));
        S* o_dqdd = output_row(dqdd, b, rows_.row(t, 7));
        const Status st = aba_jvp(model_, *data_[t], in_row(in.q, b, t, 0), in_row(in.qd, b, t, 1),
                                  in_row(in.tau, b, t, 2), in.fext ? in.fext + b * model_.nbodies() : nullptr, in_row(dq, b, t, 3),
                                  in_row(dqd, b, t, 4), in_row(dtau, b, t, 5), o_dqdd, o_qdd);
        scatter(o_qdd, qdd, b, nv);
        scatter(o_dqdd, dqdd, b, nv);
        return st;
      });
    }
    return summarize_failures(failed_.data(), B, Failure::ArticulatedPivot);
  }

  BatchStatus vjp(const FdBatchIn<S>& in, const BatchView<const S>& w, const BatchView<S>& qdd,
                  const BatchView<S>& gq, const BatchView<S>& gqd, const BatchView<S>& gtau) override {
    check(in, qdd, {&w}, {&gq, &gqd, &gtau});
    const Index B = in.q.batch, nv = model_.nv();
    if (chain_) {
      chain_->vjp(in, w, qdd, gq, gqd, gtau, failed_.data());
    } else {
      each_instance(B, [&](int t, Index b) {
        S* o_qdd = output_row(qdd, b, rows_.row(t, 6));
        S* o_gq = output_row(gq, b, rows_.row(t, 7));
        S* o_gqd = output_row(gqd, b, rows_.row(t, 8));
        S* o_gtau = output_row(gtau, b, rows_.row(t, 9));
        const Status st = aba_vjp(model_, *data_[t], in_row(in.q, b, t, 0), in_row(in.qd, b, t, 1),
                                  in_row(in.tau, b, t, 2), in.fext ? in.fext + b * model_.nbodies() : nullptr, in_row(w, b, t, 3),
                                  o_gq, o_gqd, o_gtau, o_qdd);
        scatter(o_qdd, qdd, b, nv);
        scatter(o_gq, gq, b, nv);
        scatter(o_gqd, gqd, b, nv);
        scatter(o_gtau, gtau, b, nv);
        return st;
      });
    }
    return summarize_failures(failed_.data(), B, Failure::ArticulatedPivot);
  }

 private:
  // the serial path: f(t, b), instance b on thread t (its rows_ and data_), returns
  // aba_jvp's or aba_vjp's Status, whose failed DoF goes to failed_[b]
  template <class F>
  void each_instance(Index B, F&& f) {
    for_instance_blocks(threads_, B, [&](int t, Index begin, Index end) {
      for (Index b = begin; b < end; ++b) failed_[static_cast<std::size_t>(b)] = f(t, b).failed_dof;
    });
  }
  // row k of instance b on thread t (k = 0: q, nq entries; the others nv)
  const S* in_row(const BatchView<const S>& v, Index b, int t, int k) {
    return gather(v, b, k == 0 ? model_.nq() : model_.nv(), rows_.row(t, k));
  }
  // the FD's views (check_batch), then every direction and output: in.q's batch
  void check(const FdBatchIn<S>& in, const BatchView<S>& qdd, std::initializer_list<const BatchView<const S>*> x,
             std::initializer_list<const BatchView<S>*> y) const {
    check_batch(in, qdd, max_batch_);
    for (const auto* v : x)
      if (v->batch != in.q.batch || !v->data)
        throw BackendError("the directional derivatives: a direction has " + std::to_string(v->batch) +
                           " instances (or no data), q " + std::to_string(in.q.batch));
    for (const auto* v : y)
      if (v->batch != in.q.batch || !v->data)
        throw BackendError("the directional derivatives: an output has " + std::to_string(v->batch) +
                           " instances (or no data), q " + std::to_string(in.q.batch));
  }

  const ModelTpl<S>& model_;
  BackendKind kind_;
  Index max_batch_;
  int threads_ = 1;
  std::vector<int> failed_;                          // (max_batch) -1 or the failed DoF
  std::unique_ptr<ChainFdDirectional<S>> chain_;     // the scans, or null
  std::vector<std::unique_ptr<AbaJvpData<S>>> data_;  // (threads) aba_jvp's workspaces
  RowScratch<S> rows_;                               // per thread: 6 inputs, 4 outputs
};

}  // namespace

template <class S>
std::unique_ptr<FdDirectionalDerivatives<S>> make_fd_directional_derivatives(const ModelTpl<S>& model,
                                                                             const BackendOptions& o, bool chain) {
  return std::make_unique<CpuFdDirectional<S>>(model, o, chain);
}
template std::unique_ptr<FdDirectionalDerivatives<float>> make_fd_directional_derivatives(const ModelTpl<float>&,
                                                                                         const BackendOptions&, bool);
template std::unique_ptr<FdDirectionalDerivatives<double>> make_fd_directional_derivatives(const ModelTpl<double>&,
                                                                                          const BackendOptions&, bool);

}  // namespace cpu
}  // namespace scandyn
