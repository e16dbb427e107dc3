// cpu_fallback/constrained_dynamics.cpp: the serial and OpenMP forward dynamics of
// trees closed by loops (ConstrainedForwardDynamics, scandyn/engine.hpp): per
// instance the reference's crba and bias_forces, then the loops' rows and the dense
// rank-revealing solve of scandyn/algorithm/loop_solver.hpp (the routines the CUDA
// engine runs per thread); threads over instances (instance_loop.hpp).
#include <algorithm>
#include <vector>

#include "cpu_engines.hpp"
#include "instance_loop.hpp"
#include "scandyn/algorithm/loops.hpp"
#include "scandyn/algorithm/reference.hpp"

namespace scandyn {
namespace cpu {
namespace {

template <class S>
class CpuConstrainedForwardDynamics final : public ConstrainedForwardDynamics<S> {
 public:
  CpuConstrainedForwardDynamics(const ModelTpl<S>& model, const LoopSet& loops, const BackendOptions& o)
      : model_(model), loops_(loop_rows_of<S>(loops)), m_(loops.rows()), kind_(o.backend),
        threads_(instance_threads(engine_threads(o), o.max_batch)), max_batch_(o.max_batch) {
    const Index n = model.nv();
    failed_.assign(static_cast<std::size_t>(std::max<Index>(max_batch_, 1)), -1);
    for (int t = 0; t < threads_; ++t) {
      data_.emplace_back(model_, false);
      scratch_.emplace_back(n, m_);
    }
    rows_ = RowScratch<S>(threads_, 5, static_cast<std::size_t>(std::max(n, m_)));
  }

  BatchStatus compute(const FdBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& lambda) override {
    check_batch(in, qdd, lambda, max_batch_);
    const Index B = in.q.batch, n = model_.nv();
    for_instance_blocks(threads_, B, [&](int t, Index begin, Index end) {
      Scratch& w = scratch_[t];
      for (Index b = begin; b < end; ++b) {
        const S* q = gather(in.q, b, n, rows_.row(t, 0));
        const S* qd = gather(in.qd, b, n, rows_.row(t, 1));
        const S* tau = gather(in.tau, b, n, rows_.row(t, 2));
        const Force<S>* fext = in.fext ? in.fext + static_cast<std::size_t>(b) * n : nullptr;
        S* qdd_out = output_row(qdd, b, rows_.row(t, 3));
        S* lambda_out = output_row(lambda, b, rows_.row(t, 4));
        crba(model_, data_[t], q, w.M.data());
        bias_forces(model_, data_[t], q, qd, w.h.data(), fext);
        rows_of(w, q, qd, nullptr, w.J.data(), w.gamma.data());
        // the solve writes its outputs only when M factors: a failed instance's stay unwritten
        const LoopSolveStatus st = constrained_fd_solve(n, m_, w.M.data(), w.h.data(), tau, w.J.data(),
                                                        w.gamma.data(), w.qdd.data(), w.lambda.data(),
                                                        w.work.data(), w.perm.data());
        failed_[static_cast<std::size_t>(b)] = static_cast<int>(st.failed_dof);
        if (st.failed_dof >= 0) continue;
        std::copy(w.qdd.begin(), w.qdd.end(), qdd_out);
        std::copy(w.lambda.begin(), w.lambda.end(), lambda_out);
        scatter(qdd_out, qdd, b, n);
        scatter(lambda_out, lambda, b, m_);
      }
    });
    return summarize_failures(failed_.data(), B, Failure::MassMatrixPivot);
  }

  void residual(const BatchView<const S>& q, const BatchView<const S>& qd, const BatchView<S>& phi,
                const BatchView<S>& velocity) override {
    const Index B = q.batch, n = model_.nv();
    if (qd.batch != B || (phi.data && phi.batch != B) || (velocity.data && velocity.batch != B) || B > max_batch_ ||
        (B > 0 && (!q.data || !qd.data)))
      throw BackendError("loop residual: batch sizes disagree (q " + std::to_string(B) + ", qd " +
                         std::to_string(qd.batch) + ") or exceed max_batch " + std::to_string(max_batch_));
    for_instance_blocks(threads_, B, [&](int t, Index begin, Index end) {
      Scratch& w = scratch_[t];
      for (Index b = begin; b < end; ++b) {
        const S* qb = gather(q, b, n, rows_.row(t, 0));
        const S* qdb = gather(qd, b, n, rows_.row(t, 1));
        if (phi.data) {
          S* out = output_row(phi, b, rows_.row(t, 3));
          rows_of(w, qb, qdb, out, velocity.data ? w.J.data() : nullptr, nullptr);
          scatter(out, phi, b, m_);
        } else {
          rows_of(w, qb, qdb, nullptr, w.J.data(), nullptr);
        }
        if (velocity.data) {  // J qd
          S* out = output_row(velocity, b, rows_.row(t, 4));
          for (Index r = 0; r < m_; ++r) {
            S s = S(0);
            for (Index j = 0; j < n; ++j) s += w.J[static_cast<std::size_t>(r) * n + j] * qdb[j];
            out[r] = s;
          }
          scatter(out, velocity, b, m_);
        }
      }
    });
  }

  Index rows() const override { return m_; }
  std::string strategy() const override { return "dense"; }
  BackendKind backend() const override { return kind_; }

 private:
  struct Scratch {  // one thread's
    std::vector<S> M, h, J, gamma, qdd, lambda, work;  // (nv^2, nv, m nv, m, nv, m, the solve's)
    std::vector<Index> perm;                            // (m)
    std::vector<Transform<S>> X0;                       // (nv)
    std::vector<Motion<S>> v, a;                        // (nv)
    Scratch(Index n, Index m)
        : M(static_cast<std::size_t>(n) * n), h(n), J(static_cast<std::size_t>(m) * n), gamma(m), qdd(n),
          lambda(m), work(constrained_fd_scratch(n, m)), perm(m), X0(n), v(n), a(n) {}
  };

  void rows_of(Scratch& w, const S* q, const S* qd, S* phi, S* J, S* gamma) const {
    const Index n = model_.nv();
    loop_body_motion(model_.bodies.data(), n, q, qd, w.X0.data(), w.v.data(), w.a.data());
    loop_rows(model_.bodies.data(), n, loops_.data(), static_cast<Index>(loops_.size()), w.X0.data(), w.v.data(),
              w.a.data(), phi, J, gamma);
  }

  const ModelTpl<S>& model_;
  std::vector<LoopRow<S>> loops_;
  Index m_;
  BackendKind kind_;
  int threads_;
  Index max_batch_;
  std::vector<int> failed_;       // (max_batch) failed DoF per instance, -1: none
  std::vector<DataTpl<S>> data_;  // (threads) the reference's workspaces
  std::vector<Scratch> scratch_;  // (threads)
  RowScratch<S> rows_;            // per thread: q, qd, tau, and the outputs of one instance
};

}  // namespace

template <class S>
std::unique_ptr<ConstrainedForwardDynamics<S>> make_constrained_forward_dynamics(const ModelTpl<S>& model,
                                                                                 const LoopSet& loops,
                                                                                 const BackendOptions& o) {
  return std::make_unique<CpuConstrainedForwardDynamics<S>>(model, loops, o);
}
template std::unique_ptr<ConstrainedForwardDynamics<float>> make_constrained_forward_dynamics(
    const ModelTpl<float>&, const LoopSet&, const BackendOptions&);
template std::unique_ptr<ConstrainedForwardDynamics<double>> make_constrained_forward_dynamics(
    const ModelTpl<double>&, const LoopSet&, const BackendOptions&);

}  // namespace cpu
}  // namespace scandyn
