// cpu_fallback/second_derivatives.cpp: the serial and OpenMP second-order
// derivatives of inverse dynamics: per instance on the output views' tensors, threads
// over instances, what the serial rnea_second_derivatives runs: the analytical
// second-order recursion rnea_second_derivatives_analytic_instance
// (scandyn/instance/second_derivatives_analytic.hpp) for models of 1-DoF joints, the
// dual passes rnea_second_derivatives_instance
// (scandyn/instance/second_derivatives_instance.hpp) otherwise.
#include <vector>

#include "cpu_engines.hpp"
#include "instance_loop.hpp"
#include "scandyn/algorithm/second_derivatives.hpp"

namespace scandyn {
namespace cpu {
namespace {

template <class S>
class CpuIdSecondDerivatives final : public IdSecondDerivatives<S> {
 public:
  CpuIdSecondDerivatives(const ModelTpl<S>& model, const BackendOptions& o)
      : model_(model),
        kind_(o.backend),
        threads_(instance_threads(engine_threads(o), o.max_batch)),
        max_batch_(o.max_batch),
        rows_(threads_, 3, static_cast<std::size_t>(model.nv())) {
    for (int t = 0; t < threads_; ++t) data_.emplace_back(model);
  }
  std::string strategy() const override { return "rnea_second_derivatives"; }
  BackendKind backend() const override { return kind_; }
  bool exact() const override { return true; }

  void compute(const IdBatchIn<S>& in, const IdSecondDerivativesOut<S>& out) override {
    check_batch(in, out, max_batch_);
    const Index nv = model_.nv();
    const Motion<S> a0 = base_acceleration(model_.gravity);
    for_instance_blocks(threads_, in.q.batch, [&](int t, Index begin, Index end) {
      SecondDerivativeData<S>& d = data_[static_cast<std::size_t>(t)];
      if (analytic_) {
        for (Index b = begin; b < end; ++b)
          rnea_second_derivatives_analytic_instance(
              model_.bodies.data(), nv, a0, gather(in.q, b, nv, rows_.row(t, 0)), gather(in.qd, b, nv, rows_.row(t, 1)),
              gather(in.qdd, b, nv, rows_.row(t, 2)), in.fext ? in.fext + b * nv : nullptr, d.plain.data(),
              instance_tensor(out.d2tau_dq2, b, nv), instance_tensor(out.d2tau_dqd2, b, nv),
              instance_tensor(out.d2tau_dqdqd, b, nv), instance_tensor(out.dM_dq, b, nv));
        return;
      }
      for (Index b = begin; b < end; ++b)
        rnea_second_derivatives_instance(d.bodies.data(), nv, a0, gather(in.q, b, nv, rows_.row(t, 0)),
                                         gather(in.qd, b, nv, rows_.row(t, 1)), gather(in.qdd, b, nv, rows_.row(t, 2)),
                                         in.fext ? in.fext + b * nv : nullptr, d.work.data(), d.wrenches.data(),
                                         instance_tensor(out.d2tau_dq2, b, nv), instance_tensor(out.d2tau_dqd2, b, nv),
                                         instance_tensor(out.d2tau_dqdqd, b, nv), instance_tensor(out.dM_dq, b, nv));
    });
  }

 private:
  const ModelTpl<S>& model_;
  bool analytic_ = !model_.multi_dof();  // 1-DoF joints: the analytical recursion
  BackendKind kind_;
  int threads_;
  Index max_batch_;
  std::vector<SecondDerivativeData<S>> data_;  // (threads) one instance's scratch (and the dual model)
  RowScratch<S> rows_;                         // per thread: q, qd, qdd (nv each) of one instance
};

}  // namespace

template <class S>
std::unique_ptr<IdSecondDerivatives<S>> make_id_second_derivatives(const ModelTpl<S>& model, const BackendOptions& o) {
  return std::make_unique<CpuIdSecondDerivatives<S>>(model, o);
}
template std::unique_ptr<IdSecondDerivatives<float>> make_id_second_derivatives(const ModelTpl<float>&,
                                                                                const BackendOptions&);
template std::unique_ptr<IdSecondDerivatives<double>> make_id_second_derivatives(const ModelTpl<double>&,
                                                                                 const BackendOptions&);

}  // namespace cpu
}  // namespace scandyn
