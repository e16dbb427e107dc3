// cpu_fallback/kinematics.cpp: the serial and OpenMP kinematics engine, the
// per-instance routine kinematics_instance (scandyn/instance/kinematics_instance.hpp)
// per instance, threads over instances.
#include <vector>

#include "cpu_engines.hpp"
#include "instance_loop.hpp"
#include "scandyn/instance/kinematics_instance.hpp"

namespace scandyn {
namespace cpu {
namespace {

template <class S>
class CpuKinematics final : public Kinematics<S> {
 public:
  CpuKinematics(const ModelTpl<S>& model, const BackendOptions& o, const KinematicsOptions& k)
      : model_(model),
        kind_(o.backend),
        threads_(instance_threads(engine_threads(o), o.max_batch)),
        max_batch_(o.max_batch),
        options_(k) {
    check_kinematics_options(model, k);
    for (Index f : k.frames) frames_.push_back(model.frames[static_cast<std::size_t>(f)]);
    X0_.resize(static_cast<std::size_t>(threads_) * static_cast<std::size_t>(model.nbodies()));
    q_rows_ = RowScratch<S>(threads_, 1, static_cast<std::size_t>(model.nq()));
  }

  void compute(const BatchView<const S>& q, const BatchView<S>& poses, const BatchView<S>& J) override {
    check_batch(q, poses, J, max_batch_);
    const Index nv = model_.nv(), nq = model_.nq(), nb = model_.nbodies(), F = static_cast<Index>(frames_.size());
    const bool multi = model_.multi_dof();
    for_instance_blocks(threads_, q.batch, [&](int t, Index begin, Index end) {
      Transform<S>* X0 = X0_.data() + static_cast<std::size_t>(t) * static_cast<std::size_t>(nb);
      for (Index b = begin; b < end; ++b) {
        const S* qb = gather(q, b, nq, q_rows_.row(t, 0));
        const Strided<S> pb{poses.data ? poses.data + b * poses.batch_stride : nullptr, poses.dof_stride};
        const Strided<S> Jb{J.data ? J.data + b * J.batch_stride : nullptr, J.dof_stride};
        if (multi)
          kinematics_instance_at(model_.bodies.data(), nb, nv, frames_.data(), F, options_.pose, options_.reference,
                                 qb, X0, pb, Jb);
        else
          kinematics_instance(model_.bodies.data(), nv, frames_.data(), F, options_.pose, options_.reference, qb, X0,
                              pb, Jb);
      }
    });
  }

  const KinematicsOptions& options() const override { return options_; }
  std::string strategy() const override { return "recursion"; }
  BackendKind backend() const override { return kind_; }
  bool exact() const override { return true; }

 private:
  const ModelTpl<S>& model_;
  BackendKind kind_;
  int threads_;
  Index max_batch_;
  KinematicsOptions options_;
  std::vector<FramePlacement<S>> frames_;  // (F) the selected frames' placements
  std::vector<Transform<S>> X0_;           // (threads x nbodies) body placements per thread
  RowScratch<S> q_rows_;                   // per thread: one instance's q (nq)
};

}  // namespace

template <class S>
std::unique_ptr<Kinematics<S>> make_kinematics(const ModelTpl<S>& model, const BackendOptions& o,
                                               const KinematicsOptions& k) {
  return std::make_unique<CpuKinematics<S>>(model, o, k);
}
template std::unique_ptr<Kinematics<float>> make_kinematics(const ModelTpl<float>&, const BackendOptions&,
                                                            const KinematicsOptions&);
template std::unique_ptr<Kinematics<double>> make_kinematics(const ModelTpl<double>&, const BackendOptions&,
                                                             const KinematicsOptions&);

}  // namespace cpu
}  // namespace scandyn
