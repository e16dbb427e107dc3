// cpu_fallback/forward_dynamics.cpp: the serial and OpenMP forward dynamics.
//   aba       the reference ABA (aba) per instance, threads over instances;
//   jsi       the reference CRBA + L^T L (fd_jsi) per instance; with
//             BackendOptions::fallback_aba an instance whose factorisation fails is
//             computed again by aba;
//   parallel  the parallel chain forward dynamics (ChainForwardDynamics: scans over
//             links on the engine's threads) for unbranched chains from the base.
// hybrid runs on cuda only.
#include <vector>

#include "cpu_engines.hpp"
#include "instance_loop.hpp"
#include "scandyn/algorithm/chain_fd.hpp"
#include "scandyn/algorithm/reference.hpp"

namespace scandyn {
namespace cpu {
namespace {

template <class S>
class CpuForwardDynamics final : public ForwardDynamics<S> {
 public:
  CpuForwardDynamics(const ModelTpl<S>& model, const BackendOptions& o)
      : model_(model), kind_(o.backend), threads_(engine_threads(o)), max_batch_(o.max_batch) {
    method_ = o.fd_method == FdMethod::Auto ? choose_fd_method(kind_, model) : o.fd_method;
    if (method_ == FdMethod::Hybrid)
      throw BackendError("hybrid runs on the cuda backend only (articulated inertias on the host, the other passes "
                         "as device scans); on the CPU use parallel, aba or jsi");
    if (o.fallback_aba && method_ != FdMethod::Jsi)
      throw BackendError(std::string("the aba fallback applies to forward dynamics by jsi, not ") + to_string(method_));
    fallback_ = o.fallback_aba;
    failed_.assign(static_cast<std::size_t>(std::max<Index>(max_batch_, 1)), -1);
    if (method_ == FdMethod::Parallel) {
      chain_ = std::make_unique<ChainForwardDynamics<S>>(model, std::max<Index>(max_batch_, 1), threads_);
      return;
    }
    // the nv x nv workspace only for jsi (a 10^5-link rope would need 80 GB)
    for (int t = 0; t < threads_; ++t) data_.emplace_back(model_, method_ == FdMethod::Jsi);
    rows_ = RowScratch<S>(threads_, 4, static_cast<std::size_t>(model.nq()));
  }

  BatchStatus compute(const FdBatchIn<S>& in, const BatchView<S>& qdd) override {
    check_batch(in, qdd, max_batch_);
    const Index B = in.q.batch;
    if (chain_) {
      chain_->compute(in, qdd, failed_.data());
      return summarize_failures(failed_.data(), B, Failure::ArticulatedPivot);
    }
    const Index nv = model_.nv(), nq = model_.nq(), nb = model_.nbodies();
    Index fell_back = 0;
    for_instance_blocks(threads_, B, [&](int t, Index begin, Index end) {
      Index fell = 0;
      for (Index b = begin; b < end; ++b) {
        const S* q = gather(in.q, b, nq, rows_.row(t, 0));
        const S* qd = gather(in.qd, b, nv, rows_.row(t, 1));
        const S* tau = gather(in.tau, b, nv, rows_.row(t, 2));
        const Force<S>* fext = in.fext ? in.fext + static_cast<std::size_t>(b) * nb : nullptr;
        S* out = output_row(qdd, b, rows_.row(t, 3));
        Status st = method_ == FdMethod::Aba ? aba(model_, data_[t], q, qd, tau, out, fext)
                                             : fd_jsi(model_, data_[t], q, qd, tau, out, fext);
        if (!st.ok() && fallback_) {
          st = aba(model_, data_[t], q, qd, tau, out, fext);
          if (st.ok()) ++fell;
        }
        failed_[static_cast<std::size_t>(b)] = static_cast<int>(st.failed_dof);
        if (st.ok()) scatter(out, qdd, b, nv);
      }
#pragma omp atomic
      fell_back += fell;
    });
    const Failure what = fallback_ ? Failure::BothPivots : pivot_failure(method_);
    return summarize_failures(failed_.data(), B, what, fell_back);
  }

  FdMethod method() const override { return method_; }
  std::string strategy() const override { return fallback_ ? "jsi+aba" : to_string(method_); }
  BackendKind backend() const override { return kind_; }
  bool exact() const override { return method_ == FdMethod::Aba || (method_ == FdMethod::Jsi && !fallback_); }

 private:
  const ModelTpl<S>& model_;
  BackendKind kind_;
  int threads_;
  Index max_batch_;
  FdMethod method_ = FdMethod::Aba;
  bool fallback_ = false;                            // jsi: a failed instance again by aba
  std::vector<int> failed_;                          // (max_batch) failed DoF per instance, -1: none
  std::vector<DataTpl<S>> data_;                     // (threads) workspaces (jsi: with the nv x nv one)
  RowScratch<S> rows_;                               // per thread: q, qd, tau, qdd rows of one instance
  std::unique_ptr<ChainForwardDynamics<S>> chain_;  // parallel
};

}  // namespace

template <class S>
std::unique_ptr<ForwardDynamics<S>> make_forward_dynamics(const ModelTpl<S>& model, const BackendOptions& o) {
  return std::make_unique<CpuForwardDynamics<S>>(model, o);
}
template std::unique_ptr<ForwardDynamics<float>> make_forward_dynamics(const ModelTpl<float>&, const BackendOptions&);
template std::unique_ptr<ForwardDynamics<double>> make_forward_dynamics(const ModelTpl<double>&, const BackendOptions&);

}  // namespace cpu
}  // namespace scandyn
