// cpu_fallback/simd_batch.hpp: the CPU engines' SIMD path: the serial reference
// algorithms (rnea, bias_forces, crba, aba of scandyn/algorithm/reference.hpp) run
// over Pack<S, W> (scandyn/spatial/pack.hpp), W instances per register lane.
//
// One formula: the packs go through the very templates the scalar engines run, with
// the model broadcast into packs (SimdModel). A group of W consecutive instances is
// gathered from the batch views into packs (one vector load per DoF when the
// instances are contiguous, BatchView::soa), computed, and scattered. Each lane
// performs the scalar code's operations in the same order (lane-wise IEEE
// arithmetic, the same library sin/cos/sqrt per lane), so a lane's result is the
// serial engine's bit for bit where the compiler contracts no multiply-add
// differently in the two (simd_exact()). Instances past the last full group take the
// scalar path.
//
// Models: 1-DoF revolute and prismatic joints (simd_supported()); the engines use
// the scalar path for any other model.
#pragma once

#include <vector>

#include "instance_loop.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/batch.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/spatial/pack.hpp"

namespace scandyn {
namespace cpu {

// Can the SIMD path take this model? (every joint revolute or prismatic)
template <class S>
bool simd_supported(const ModelTpl<S>& model);

// True when the SIMD path's lanes are bit-identical to the scalar engines: built
// without FMA (contraction into fused multiply-adds may differ between the scalar
// and the vector code). The tests assert bit identity when it is true.
constexpr bool simd_exact() {
#if defined(__FMA__)
  return false;
#else
  return true;
#endif
}

// The model with every constant broadcast into packs, and one thread's workspace.
template <class S>
class SimdBatch {
 public:
  using P = NativePack<S>;
  static constexpr int W = P::width;

  // mass_matrix: the workspace of crba() (an nv x nv output), else of rnea() and aba() (nv)
  explicit SimdBatch(const ModelTpl<S>& model, bool mass_matrix = false);
  SimdBatch(const SimdBatch&) = delete;
  SimdBatch(SimdBatch&&) = default;

  // Instances [b, b + W) of the batch (all of them must exist). fext: B x nv wrenches
  // or null. rnea with qdd.data null computes the bias forces.
  void rnea(const BatchView<const S>& q, const BatchView<const S>& qd, const BatchView<const S>& qdd,
            const Force<S>* fext, const BatchView<S>& tau, Index b);
  void crba(const BatchView<const S>& q, const BatchView<S>& M, Index b);
  // false when a pivot failed in some lane: nothing written (the caller computes
  // these W instances one at a time, which names the failing ones)
  bool aba(const BatchView<const S>& q, const BatchView<const S>& qd, const BatchView<const S>& tau,
           const Force<S>* fext, const BatchView<S>& qdd, Index b);

 private:
  void load(const BatchView<const S>& v, Index b, Index n, P* out) const;
  void store(const P* in, const BatchView<S>& v, Index b, Index n) const;
  const Force<P>* load_fext(const Force<S>* fext, Index b);

  Index nv_;
  ModelTpl<P> model_;        // the model, broadcast
  DataTpl<P> data_;          // workspace of the reference algorithms
  std::vector<P> q_, qd_, x_, out_;  // (nv; out: nv x nv for a mass-matrix batch) one group's inputs, output
  std::vector<Force<P>> fext_;       // (nv) one group's external wrenches
};

// Would the engines take the SIMD path? simd On or Auto, a model it takes
// (simd_supported) and more than one lane per pack in this build. On with a model it
// cannot take is a BackendError naming the first joint it cannot take.
template <class S>
bool use_simd(const ModelTpl<S>& model, CpuSimd simd);

// The SIMD workspaces of an engine made for up to max_batch instances on `threads`
// threads: one per thread that can get instances (instance_threads), or none when the
// engine does not take the SIMD path or when no call can fill a group (max_batch < W:
// a group is W instances of one thread's block, and a block never exceeds the batch).
// mass_matrix: workspaces for crba() (nv x nv per thread; the others hold nv).
template <class S>
std::vector<SimdBatch<S>> make_simd_batches(const ModelTpl<S>& model, CpuSimd simd, int threads, Index max_batch,
                                            bool mass_matrix = false) {
  std::vector<SimdBatch<S>> v;
  if (use_simd(model, simd) && max_batch >= SimdBatch<S>::W)
    for (int t = 0, n = instance_threads(threads, max_batch); t < n; ++t) v.emplace_back(model, mass_matrix);
  return v;
}

// Instances [begin, end) of one thread: group(b) for each full group b..b+W-1 when
// simd is non-null (group returns false when the group must be computed again one at
// a time: a failed pivot in some lane), one(b) for every other instance.
template <class S, class Group, class One>
void for_simd_groups(SimdBatch<S>* simd, Index begin, Index end, Group&& group, One&& one) {
  constexpr Index W = SimdBatch<S>::W;
  Index b = begin;
  if (simd)
    for (; b + W <= end; b += W)
      if (!group(b))
        for (Index k = b; k < b + W; ++k) one(k);
  for (; b < end; ++b) one(b);
}

}  // namespace cpu
}  // namespace scandyn
