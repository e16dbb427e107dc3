// src/algorithm/fd_check_batch.cpp: FdBatchCheck (scandyn/algorithm/fd_check_batch.hpp).
#include "scandyn/algorithm/fd_check_batch.hpp"

#include <cmath>
#include <limits>
#include <type_traits>

#include "../../cpu_fallback/instance_loop.hpp"

namespace scandyn {

template <class S>
FdBatchCheck<S>::FdBatchCheck(const ModelTpl<S>& model, const BackendOptions& o, FdMethod method, int threads)
    // no more workspaces than instances (a 10^6-link rope's is ~1 GB)
    : model_(model),
      threads_(cpu::instance_threads(threads, o.max_batch)),
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
  retry_aba_ = o.fallback_aba && method == FdMethod::Jsi;
  retry_double_ = o.fallback_double;
  if (!on_) return;
  if constexpr (std::is_same_v<S, double>) {
    check_model_ = &model;
  } else {
    wide_ = std::make_unique<Model>(model.template cast<double>());
    check_model_ = wide_.get();
  }
  // rows of nq entries (q's; nq = nv for 1-DoF joints)
  const std::size_t n = static_cast<std::size_t>(model.nq()), nv = static_cast<std::size_t>(model.nv());
  for (int t = 0; t < threads_; ++t) data_.emplace_back(*check_model_, false);
  if (retry_aba_)
    for (int t = 0; t < threads_; ++t) data_s_.emplace_back(model_, false);
  rows_.assign(static_cast<std::size_t>(threads_) * 5 * n, 0.0);
  if (retry_double_)
    fext_.assign(static_cast<std::size_t>(threads_) * static_cast<std::size_t>(model.nbodies()), Force<double>::zero());
  rows_s_.assign(static_cast<std::size_t>(threads_) * 4 * n, S(0));
  if (model.multi_dof()) {
    rest_ = std::make_unique<Model>(*check_model_);
    rest_->gravity = Vec3<double>::zero();
    at_rows_.assign(static_cast<std::size_t>(threads_) * 2 * nv, 0.0);
    zeros_.assign(nv, 0.0);
  }
}

template <class S>
double FdBatchCheck<S>::check(int t, const S* q, const S* qd, const S* tau, const Force<S>* fext, const S* qdd,
                              int* worst) {
  const Index n = model_.nv();
  double* delta = rows_.data() + static_cast<std::size_t>(t) * 5 * model_.nq();
  const FdCheck<double> c = model_.multi_dof() ? check_at(t, q, qd, tau, fext, qdd, delta)
                                               : fd_check(*check_model_, data_[t], q, qd, tau, qdd, fext,
                                                          static_cast<const S*>(nullptr), delta);
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
FdCheck<double> FdBatchCheck<S>::check_at(int t, const S* q, const S* qd, const S* tau, const Force<S>* fext,
                                          const S* qdd, double* delta) {
  const Index nv = model_.nv(), nq = model_.nq(), nb = model_.nbodies();
  // inputs in double: q, qd, qdd after delta in this thread's row (5 nq entries)
  double* dq = delta + nq;
  double *dqd = dq + nq, *dqdd = dqd + nq;
  for (Index i = 0; i < nq; ++i) dq[i] = q[i];
  for (Index i = 0; i < nv; ++i) dqd[i] = qd[i], dqdd[i] = qdd[i];
  double* id = at_rows_.data() + static_cast<std::size_t>(t) * 2 * nv;
  double* r = id + nv;
  const Force<double>* dfext = nullptr;
  std::vector<Force<double>> wide;  // float engines with wrenches: widened here (rare)
  if (fext) {
    if constexpr (std::is_same_v<S, double>) {
      dfext = fext;
    } else {
      wide.resize(static_cast<std::size_t>(nb));
      for (Index i = 0; i < nb; ++i) wide[i] = fext[i].template cast<double>();
      dfext = wide.data();
    }
  }
  rnea(*check_model_, data_[t], dq, dqd, dqdd, id, dfext);
  FdCheckNorms<double> norms;
  for (Index i = 0; i < nv; ++i) r[i] = fd_check_residual(norms, id[i], double(tau[i]), 0.0);
  FdCheck<double> out;
  out.residual = norms.residual;
  out.relative_residual = fd_relative_residual(norms);
  const Status st = aba(*rest_, data_[t], dq, zeros_.data(), r, delta);  // M^-1 r
  if (!st.ok()) {
    out.failed_dof = st.failed_dof;
    out.error_estimate = std::numeric_limits<double>::infinity();
    return out;
  }
  for (Index i = 0; i < nv; ++i) fd_check_delta(norms, delta[i], double(qdd[i]));
  out.error_estimate = fd_error_estimate(norms);
  return out;
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
    const Index n = model_.nv(), w = model_.nq(), nb = model_.nbodies();
    double* row = rows_.data() + static_cast<std::size_t>(t) * 5 * w;
    double *dq = row + w, *dqd = row + 2 * w, *dtau = row + 3 * w, *dqdd = row + 4 * w;
    Force<double>* dfext = fext ? fext_.data() + static_cast<std::size_t>(t) * nb : nullptr;
    for (Index i = 0; i < w; ++i) dq[i] = q[i];
    for (Index i = 0; i < n; ++i) {
      dqd[i] = qd[i];
      dtau[i] = tau[i];
    }
    if (fext)
      for (Index i = 0; i < nb; ++i) dfext[i] = fext[i].template cast<double>();
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
  const Index B = in.q.batch, n = model_.nv(), w = model_.nq(), nb = model_.nbodies();
  Index fixed = 0;
  cpu::for_instance_blocks(threads_, B, [&](int t, Index begin, Index end) {
    S* row = rows_s_.data() + static_cast<std::size_t>(t) * 4 * w;
    Index fix = 0;
    for (Index b = begin; b < end; ++b) {
      estimate[b] = -1;
      if (failed_dof[b] >= 0) continue;
      const S* q = cpu::gather(in.q, b, w, row);
      const S* qd = cpu::gather(in.qd, b, n, row + w);
      const S* tau = cpu::gather(in.tau, b, n, row + 2 * w);
      S* out = qdd.dof_stride == 1 ? qdd.data + b * qdd.batch_stride : row + 3 * w;
      if (qdd.dof_stride != 1)
        for (Index i = 0; i < n; ++i) out[i] = qdd.at(i, b);
      const Outcome o = settle(t, q, qd, tau, in.fext ? in.fext + static_cast<std::size_t>(b) * nb : nullptr, out);
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
