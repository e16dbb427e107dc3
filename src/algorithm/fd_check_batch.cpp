// src/algorithm/fd_check_batch.cpp: FdBatchCheck (scandyn/algorithm/fd_check_batch.hpp).
#include "scandyn/algorithm/fd_check_batch.hpp"

#include <cmath>

#include "../../cpu_fallback/instance_loop.hpp"

namespace scandyn {

template <class S>
FdBatchCheck<S>::FdBatchCheck(const ModelTpl<S>& model, const BackendOptions& o, FdMethod method, int threads)
    // no more workspaces than instances (a 10^6-link rope's is ~1 GB)
    : model_(model),
      threads_(static_cast<int>(std::max<Index>(1, std::min<Index>(threads, std::max<Index>(o.max_batch, 1))))),
      threshold_(fd_check_tol<S>(o)) {
  // the double fallback asks for the check: Auto turns it on
  on_ = o.fallback_double && o.fd_check == FdCheckMode::Auto
            ? true
            : fd_check_enabled(o.fd_check, o.backend, method, model.nv());
  if (!(threshold_ > 0)) throw BackendError("the forward-dynamics check's threshold must be positive, not " +
                                            std::to_string(threshold_));
  if (o.fallback_double && sizeof(S) > sizeof(float))
    throw BackendError("the double fallback applies to float forward dynamics (this engine computes in double)");
  if (o.fallback_double && !on_)
    throw BackendError("the double fallback recomputes the instances the forward-dynamics check flags, and the check "
                       "is off");
  if (on_ && model.multi_dof()) {
    // the check's residual and M^-1 r take 1-DoF joints (nv positions): Auto leaves it off
    if (o.fd_check == FdCheckMode::On || o.fallback_double)
      throw BackendError("the forward-dynamics check: model '" + model.name + "' has the multi-DoF joint '" +
                         first_multi_dof_joint(model) + "'; the check takes revolute and prismatic joints only "
                         "(use --fd-check off / fd_check='off')");
    on_ = false;
  }
  retry_aba_ = o.fallback_aba && method == FdMethod::Jsi;
  retry_double_ = o.fallback_double;
  if (!on_) return;
  if constexpr (std::is_same_v<S, double>) {
    check_model_ = &model;
  } else {
    wide_ = std::make_unique<Model>(model.template cast<double>());
    check_model_ = wide_.get();
  }
  const std::size_t n = static_cast<std::size_t>(model.nv());
  for (int t = 0; t < threads_; ++t) data_.emplace_back(*check_model_, false);
  if (retry_aba_)
    for (int t = 0; t < threads_; ++t) data_s_.emplace_back(model_, false);
  rows_.assign(static_cast<std::size_t>(threads_) * 5 * n, 0.0);
  if (retry_double_) fext_.assign(static_cast<std::size_t>(threads_) * n, Force<double>::zero());
  rows_s_.assign(static_cast<std::size_t>(threads_) * 4 * n, S(0));
}

template <class S>
double FdBatchCheck<S>::check(int t, const S* q, const S* qd, const S* tau, const Force<S>* fext, const S* qdd,
                              int* worst) {
  const Index n = model_.nv();
  double* delta = rows_.data() + static_cast<std::size_t>(t) * 5 * n;
  const FdCheck<double> c = fd_check(*check_model_, data_[t], q, qd, tau, qdd, fext, static_cast<const S*>(nullptr),
                                     delta);
  if (c.failed_dof >= 0) {
    *worst = static_cast<int>(c.failed_dof);
    return c.error_estimate;
  }
  Index w = 0;
  for (Index i = 1; i < n; ++i)
    if (!(std::abs(delta[i]) <= std::abs(delta[w]))) w = i;
  *worst = static_cast<int>(w);
  return c.error_estimate;
}

template <class S>
typename FdBatchCheck<S>::Outcome FdBatchCheck<S>::settle(int t, const S* q, const S* qd, const S* tau,
                                                         const Force<S>* fext, S* qdd, bool by_aba) {
  Outcome out;
  int worst = 0;
  out.estimate = check(t, q, qd, tau, fext, qdd, &worst);
  auto passed = [&] { return out.estimate <= threshold_; };
  if (passed()) return out;
  if (retry_aba_ && !by_aba && aba(model_, data_s_[t], q, qd, tau, qdd, fext).ok()) {
    out.changed = true;
    out.estimate = check(t, q, qd, tau, fext, qdd, &worst);
  }
  if (!passed() && retry_double_) {
    const Index n = model_.nv();
    double* row = rows_.data() + static_cast<std::size_t>(t) * 5 * n;
    double *dq = row + n, *dqd = row + 2 * n, *dtau = row + 3 * n, *dqdd = row + 4 * n;
    Force<double>* dfext = fext ? fext_.data() + static_cast<std::size_t>(t) * n : nullptr;
    for (Index i = 0; i < n; ++i) {
      dq[i] = q[i];
      dqd[i] = qd[i];
      dtau[i] = tau[i];
      if (fext) dfext[i] = fext[i].template cast<double>();
    }
    if (aba(*check_model_, data_[t], dq, dqd, dtau, dqdd, dfext).ok()) {
      for (Index i = 0; i < n; ++i) qdd[i] = static_cast<S>(dqdd[i]);
      out.changed = true;
      out.estimate = check(t, q, qd, tau, fext, qdd, &worst);
    }
  }
  if (passed()) out.retried = true;
  else out.failed_dof = worst;
  return out;
}

template <class S>
Index FdBatchCheck<S>::settle_batch(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed_dof,
                                    double* estimate) {
  const Index B = in.q.batch, n = model_.nv();
  Index fixed = 0;
  cpu::for_instance_blocks(threads_, B, [&](int t, Index begin, Index end) {
    S* row = rows_s_.data() + static_cast<std::size_t>(t) * 4 * n;
    Index fix = 0;
    for (Index b = begin; b < end; ++b) {
      estimate[b] = -1;
      if (failed_dof[b] >= 0) continue;
      const S* q = cpu::gather(in.q, b, n, row);
      const S* qd = cpu::gather(in.qd, b, n, row + n);
      const S* tau = cpu::gather(in.tau, b, n, row + 2 * n);
      S* out = qdd.dof_stride == 1 ? qdd.data + b * qdd.batch_stride : row + 3 * n;
      if (qdd.dof_stride != 1)
        for (Index i = 0; i < n; ++i) out[i] = qdd.at(i, b);
      const Outcome o = settle(t, q, qd, tau, in.fext ? in.fext + static_cast<std::size_t>(b) * n : nullptr, out);
      if (o.changed) cpu::scatter(out, qdd, b, n);
      failed_dof[b] = o.failed_dof;
      estimate[b] = o.estimate;
      fix += o.retried;
    }
#pragma omp atomic
    fixed += fix;
  });
  return fixed;
}

template class FdBatchCheck<float>;
template class FdBatchCheck<double>;

}  // namespace scandyn
