// cpu_fallback/mass_matrix.cpp: the serial and OpenMP mass matrix, the reference
// CRBA (crba) per instance, threads over instances.
#include <vector>

#include "cpu_engines.hpp"
#include "instance_loop.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "simd_batch.hpp"

namespace scandyn {
namespace cpu {
namespace {

template <class S>
class CpuMassMatrix final : public MassMatrix<S> {
 public:
  CpuMassMatrix(const ModelTpl<S>& model, const BackendOptions& o)
      : model_(model),
        kind_(o.backend),
        threads_(instance_threads(engine_threads(o), o.max_batch)),
        max_batch_(o.max_batch) {
    const std::size_t nv = static_cast<std::size_t>(model.nv());
    for (int t = 0; t < threads_; ++t) data_.emplace_back(model_, /*mass_matrix=*/false);
    q_rows_ = RowScratch<S>(threads_, 1, static_cast<std::size_t>(model.nq()));
    M_rows_ = RowScratch<S>(threads_, 1, nv * nv);
    simd_ = make_simd_batches(model_, o.simd, threads_, max_batch_, /*mass_matrix=*/true);
  }

  void compute(const BatchView<const S>& q, const BatchView<S>& M) override {
    check_batch(q, M, max_batch_);
    const Index nv = model_.nv();
    for_instance_blocks(threads_, q.batch, [&](int t, Index begin, Index end) {
      for_simd_groups(
          simd_.empty() ? nullptr : &simd_[t], begin, end,
          [&](Index b) {
            simd_[t].crba(q, M, b);
            return true;
          },
          [&](Index b) {
            S* m = output_row(M, b, M_rows_.row(t, 0));
            crba(model_, data_[t], gather(q, b, model_.nq(), q_rows_.row(t, 0)), m);
            scatter(m, M, b, nv * nv);
          });
    });
  }

  std::string strategy() const override {
    return simd_.empty() ? "crba" : "crba-simd" + std::to_string(SimdBatch<S>::W);
  }
  BackendKind backend() const override { return kind_; }
  bool exact() const override { return simd_.empty() || simd_exact(); }

 private:
  const ModelTpl<S>& model_;
  BackendKind kind_;
  int threads_;
  Index max_batch_;
  std::vector<DataTpl<S>> data_;  // (threads) workspaces
  std::vector<SimdBatch<S>> simd_;  // (threads, or none) SIMD workspaces
  RowScratch<S> q_rows_, M_rows_; // per thread: one instance's q (nv) and M (nv x nv)
};

}  // namespace

template <class S>
std::unique_ptr<MassMatrix<S>> make_mass_matrix(const ModelTpl<S>& model, const BackendOptions& o) {
  return std::make_unique<CpuMassMatrix<S>>(model, o);
}
template std::unique_ptr<MassMatrix<float>> make_mass_matrix(const ModelTpl<float>&, const BackendOptions&);
template std::unique_ptr<MassMatrix<double>> make_mass_matrix(const ModelTpl<double>&, const BackendOptions&);

}  // namespace cpu
}  // namespace scandyn
