// scandyn/algorithm/fd_check_batch.hpp: forward dynamics' run-time check as the
// engines run it (BackendOptions::fd_check), with its retries.
//
// One FdBatchCheck per forward-dynamics engine. For each instance the engine
// computed (its pivots sound), settle():
//   1. runs fd_check (scandyn/algorithm/fd_check.hpp) in double on the engine's
//      inputs and result: the error estimate max|M^-1 (ID(q, qd, qdd) - tau)| /
//      max(1, max|qdd|); at most the threshold (fd_check_tol<S>): done;
//   2. flagged, with options.fallback_aba (jsi engines): qdd again by the reference
//      aba in S, checked again;
//   3. still flagged, with options.fallback_double (float engines): qdd again by the
//      reference aba in double, rounded to S, checked again;
//   4. still flagged: the instance fails with Failure::ResidualTooLarge at the DoF of
//      the largest correction; qdd keeps the last result.
// A float engine's model is checked widened to double (exact): the check in float
// would share the float engine's rounding of the joint transforms and miss most of
// its error on long chains (docs/accuracy.md). The serial and OpenMP engines call
// settle() per instance inside their loop; engines that compute a whole batch at
// once (the parallel chain forward dynamics, the cuda engines' compute()) call
// settle_batch() on host memory afterwards.
#pragma once

#include <memory>
#include <vector>

#include "scandyn/algorithm/fd_check.hpp"
#include "scandyn/engine.hpp"

namespace scandyn {

template <class S>
class FdBatchCheck {
 public:
  // For an engine running `method` (resolved) on options.backend with `threads` host
  // threads (workspaces for at most options.max_batch of them); on() tells whether
  // options.fd_check enables the check for it. The model must outlive the check.
  // Allocates its workspaces here only when on().
  FdBatchCheck(const ModelTpl<S>& model, const BackendOptions& options, FdMethod method, int threads);
  FdBatchCheck(const FdBatchCheck&) = delete;
  FdBatchCheck& operator=(const FdBatchCheck&) = delete;

  bool on() const { return on_; }
  double threshold() const { return threshold_; }

  // The outcome of settle() for one instance.
  struct Outcome {
    int failed_dof = -1;    // -1, or the DoF of the largest correction (ResidualTooLarge)
    double estimate = -1;   // the last estimate (-1 when the check did not run)
    bool retried = false;   // a retry (2 or 3 above) produced the result that passed
    bool changed = false;   // qdd was overwritten by a retry
  };
  // Steps 1-4 for one instance on workspace t < threads: q (nq), qd, tau, qdd (nv each,
  // host memory) and fext (one wrench per body, or null); qdd is overwritten by a retry.
  // by_aba: qdd came from an aba in S already (step 2 would repeat it).
  Outcome settle(int t, const S* q, const S* qd, const S* tau, const Force<S>* fext, S* qdd, bool by_aba = false);

  // settle() for every instance b < B whose failed_dof[b] is -1, on the check's
  // threads, host memory with any strides; writes failed_dof[b] and estimate[b]
  // (-1 for instances not checked) and the retried results into qdd. Returns the
  // number of instances a retry fixed.
  Index settle_batch(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed_dof, double* estimate);

 private:
  double check(int t, const S* q, const S* qd, const S* tau, const Force<S>* fext, const S* qdd, int* worst);
  // The check of a model with multi-DoF joints (a floating base, spherical joints):
  // r = ID(q, qd, qdd) - tau by the reference rnea, delta = M^-1 r by the reference
  // aba at rest (qd = 0, no gravity: rest_), the same estimate; into delta (nv).
  FdCheck<double> check_at(int t, const S* q, const S* qd, const S* tau, const Force<S>* fext, const S* qdd,
                           double* delta);

  const ModelTpl<S>& model_;
  bool on_ = false;
  bool retry_aba_ = false, retry_double_ = false;
  int threads_ = 1;
  double threshold_ = 0;
  std::unique_ptr<Model> wide_;       // S = float: the model widened to double
  const Model* check_model_ = nullptr;  // the model the check (and the double retry) runs on
  std::vector<Data> data_;            // (threads) double workspaces of the check
  std::vector<DataTpl<S>> data_s_;    // (threads) workspaces of the aba retry in S
  std::vector<double> rows_;          // (threads x 5 nq) per thread: delta, q, qd, tau, qdd in double
  std::vector<Force<double>> fext_;   // (threads x nbodies) the double retry's wrenches
  std::vector<S> rows_s_;             // (threads x 4 nq) settle_batch's gathered q, qd, tau, qdd
  std::unique_ptr<Model> rest_;       // multi-DoF models: check_model_ without gravity (M^-1 r by aba)
  std::vector<double> at_rows_;       // multi-DoF: (threads x 2 nv) per thread: ID, then r; zeros_ the rest qd
  std::vector<double> zeros_;         // multi-DoF: (nv) zero joint rates
};

}  // namespace scandyn
