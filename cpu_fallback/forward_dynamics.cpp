// cpu_fallback/forward_dynamics.cpp: the serial and OpenMP forward dynamics.
//   aba       the reference ABA (aba) per instance, threads over instances;
//   jsi       the reference CRBA + L^T L (fd_jsi) per instance; with
//             BackendOptions::fallback_aba an instance whose factorisation fails is
//             computed again by aba;
//   parallel  the parallel chain forward dynamics (ChainForwardDynamics: scans over
//             links on the engine's threads) for unbranched chains from the base.
// hybrid runs on cuda only. With the run-time check on (BackendOptions::fd_check), each
// instance's result is checked, and retried, by FdBatchCheck (in the instance loop for
// aba and jsi, after the batch for parallel).
#include <vector>

#include "cpu_engines.hpp"
#include "instance_loop.hpp"
#include "scandyn/algorithm/chain_fd.hpp"
#include "scandyn/algorithm/fd_check_batch.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "simd_batch.hpp"

namespace scandyn {
namespace cpu {
namespace {

template <class S>
class CpuForwardDynamics final : public ForwardDynamics<S> {
 public:
  CpuForwardDynamics(const ModelTpl<S>& model, const BackendOptions& o)
      : model_(model), kind_(o.backend), threads_(engine_threads(o)), max_batch_(o.max_batch) {
    method_ = o.fd_method == FdMethod::Auto ? choose_fd_method(kind_, model, max_batch_, threads_) : o.fd_method;
    if (method_ == FdMethod::Hybrid)
      throw BackendError("hybrid runs on the cuda backend only (articulated inertias on the host, the other passes "
                         "as device scans); on the CPU use parallel, aba or jsi");
    if (o.fallback_aba && method_ != FdMethod::Jsi)
      throw BackendError(std::string("the aba fallback applies to forward dynamics by jsi, not ") + to_string(method_));
    fallback_ = o.fallback_aba;
    failed_.assign(static_cast<std::size_t>(std::max<Index>(max_batch_, 1)), -1);
    check_ = std::make_unique<FdBatchCheck<S>>(model, o, method_, threads_);
    if (check_->on()) estimate_.assign(failed_.size(), -1.0);
    if (method_ == FdMethod::Parallel) {
      chain_ = std::make_unique<ChainForwardDynamics<S>>(model, std::max<Index>(max_batch_, 1), threads_);
      return;
    }
    // the nv x nv workspace only for jsi (a 10^5-link rope would need 80 GB)
    const int workers = instance_threads(threads_, max_batch_);
    for (int t = 0; t < workers; ++t) data_.emplace_back(model_, method_ == FdMethod::Jsi);
    rows_ = RowScratch<S>(workers, 4, static_cast<std::size_t>(model.nq()));
    // aba in SIMD groups (the check, when on, then runs on each result of a group)
    if (method_ == FdMethod::Aba) simd_ = make_simd_batches(model_, o.simd, threads_, max_batch_);
  }

  BatchStatus compute(const FdBatchIn<S>& in, const BatchView<S>& qdd) override {
    check_batch(in, qdd, max_batch_);
    const Index B = in.q.batch;
    if (chain_) {
      chain_->compute(in, qdd, failed_.data());
      if (!check_->on()) return summarize_failures(failed_.data(), B, Failure::ArticulatedPivot);
      const Index fixed = check_->settle_batch(in, qdd, failed_.data(), estimate_.data());
      return summarize_checked(failed_.data(), estimate_.data(), B, Failure::ArticulatedPivot, check_->threshold(), 0,
                               fixed);
    }
    const Index nv = model_.nv(), nq = model_.nq(), nb = model_.nbodies();
    Index fell_back = 0, retried = 0;
    for_instance_blocks(threads_, B, [&](int t, Index begin, Index end) {
      Index fell = 0, retry = 0;
      // the check of instance b's computed qdd (out: its nv entries, contiguous), which
      // may compute it again (the fallbacks); the result written to qdd, flagged or not
      const auto settle = [&](Index b, const S* q, const S* qd, const S* tau, const Force<S>* fext, S* out,
                              bool by_aba) {
        const auto o = check_->settle(t, q, qd, tau, fext, out, by_aba);
        failed_[static_cast<std::size_t>(b)] = o.failed_dof;
        estimate_[static_cast<std::size_t>(b)] = o.estimate;
        retry += o.retried;
        scatter(out, qdd, b, nv);
      };
      const auto one = [&](Index b) {
        const S* q = gather(in.q, b, nq, rows_.row(t, 0));
        const S* qd = gather(in.qd, b, nv, rows_.row(t, 1));
        const S* tau = gather(in.tau, b, nv, rows_.row(t, 2));
        const Force<S>* fext = in.fext ? in.fext + static_cast<std::size_t>(b) * nb : nullptr;
        S* out = output_row(qdd, b, rows_.row(t, 3));
        Status st = method_ == FdMethod::Aba ? aba(model_, data_[t], q, qd, tau, out, fext)
                                             : fd_jsi(model_, data_[t], q, qd, tau, out, fext);
        bool by_aba = method_ == FdMethod::Aba;
        if (!st.ok() && fallback_) {
          st = aba(model_, data_[t], q, qd, tau, out, fext);
          by_aba = true;
          if (st.ok()) ++fell;
        }
        failed_[static_cast<std::size_t>(b)] = static_cast<int>(st.failed_dof);
        if (check_->on()) {
          estimate_[static_cast<std::size_t>(b)] = -1;
          if (st.ok()) return settle(b, q, qd, tau, fext, out, by_aba);
        }
        if (st.ok()) scatter(out, qdd, b, nv);
      };
      // a group with a failed pivot in some lane is computed again by `one`, instance by instance;
      // with the check on, each result of a group is then checked (and settled) as `one`'s are
      for_simd_groups(
          simd_.empty() ? nullptr : &simd_[t], begin, end,
          [&](Index b) {
            if (!simd_[t].aba(in.q, in.qd, in.tau, in.fext, qdd, b)) return false;
            std::fill(failed_.begin() + b, failed_.begin() + b + SimdBatch<S>::W, -1);
            if (check_->on())
              for (Index k = b; k < b + SimdBatch<S>::W; ++k)
                settle(k, gather(in.q, k, nq, rows_.row(t, 0)), gather(in.qd, k, nv, rows_.row(t, 1)),
                       gather(in.tau, k, nv, rows_.row(t, 2)),
                       in.fext ? in.fext + static_cast<std::size_t>(k) * nb : nullptr,
                       result_row(qdd, k, nv, rows_.row(t, 3)), /*by_aba=*/true);
            return true;
          },
          one);
#pragma omp atomic
      fell_back += fell;
#pragma omp atomic
      retried += retry;
    });
    const Failure what = fallback_ ? Failure::BothPivots : pivot_failure(method_);
    if (check_->on())
      return summarize_checked(failed_.data(), estimate_.data(), B, what, check_->threshold(), fell_back,
                               retried);
    return summarize_failures(failed_.data(), B, what, fell_back);
  }

  FdMethod method() const override { return method_; }
  std::string strategy() const override {
    const std::string base = !simd_.empty() ? "aba-simd" + std::to_string(SimdBatch<S>::W)
                             : fallback_        ? std::string("jsi+aba")
                                                : std::string(to_string(method_));
    return base + (check_->on() ? "+check" : "");
  }
  BackendKind backend() const override { return kind_; }
  bool exact() const override {
    return !check_->on() &&
           ((method_ == FdMethod::Aba && (simd_.empty() || simd_exact())) || (method_ == FdMethod::Jsi && !fallback_));
  }

 private:
  const ModelTpl<S>& model_;
  BackendKind kind_;
  int threads_;
  Index max_batch_;
  FdMethod method_ = FdMethod::Aba;
  bool fallback_ = false;                            // jsi: a failed instance again by aba
  std::vector<int> failed_;                          // (max_batch) failed DoF per instance, -1: none
  std::vector<DataTpl<S>> data_;                     // (instance_threads) workspaces (jsi: with the nv x nv one)
  RowScratch<S> rows_;                               // per thread: q, qd, tau, qdd rows of one instance
  std::vector<SimdBatch<S>> simd_;                   // (instance_threads, or none) aba's SIMD workspaces
  std::unique_ptr<ChainForwardDynamics<S>> chain_;  // parallel
  std::unique_ptr<FdBatchCheck<S>> check_;           // the run-time check (on() or not)
  std::vector<double> estimate_;                     // (max_batch) the check's estimates, -1: unchecked
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
