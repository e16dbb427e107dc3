// scandyn/cuda/id_scan.hpp: batched inverse dynamics on a CUDA device as
// device-wide scans across links (strategy "scan-local").
//
// The local-frame form of scandyn/scan/elements.hpp:
//   velocities     x_i = Xup_i x_parent + S qd                       (MotionAffine)
//   accelerations  x_i = Xup_i x_parent + S qdd + v x S qd, -g at the base
//   forces         F_i = f_i + Xup_{i+1}^T F_{i+1} + sum over branch children
//                  (ForceAffine, run leaves -> root; f_i = I a + v x* I v - fext)
//   tau_i = S^T F_i.
//
// Trees. The preorder tree is cut into chain segments (scandyn/scan/tree_plan.hpp);
// a segment's level is its depth in the segment tree. Each level is one scan per
// pass over the concatenation of all its segments, for all instances:
// element e = b * n_level + k (instance b, position k of the level's bodies).
// Segments and instances are kept apart without flags: a segment's first body
// takes the element (0, Xup x_parent + b) in the forward passes (a map with a zero
// transform ignores whatever precedes it), and its last body the element (0, f) in
// the backward pass. A head's parent lies in a lower level (its values are final
// when the level runs forward); a branch child heads a segment of a higher level
// (its force is final when the level runs backward). A chain is one level: the
// whole batch is three scans.
//
// Runs. Each instance's bodies of a level are cut into chunks of 4..64 consecutive
// bodies; a run (chunk, instance) is one thread (about 2^16 threads per pass, more
// only past 64 bodies each), instances fastest, so a warp reads consecutive
// instances' inputs and writes its scratch 32 entries at a time.
// Each pass aggregates every run serially, scans the run aggregates with CUB's
// single-pass scan (cub::DeviceScan::InclusiveScan, decoupled look-back), then
// walks every run again from its carry-in, by the recursion itself. So a value is
// a carry-in (composed maps spanning whole runs) followed by at most 63 steps of
// the recursion, the passes are fused where their data allow (velocity walk +
// acceleration aggregates, acceleration walk + force aggregates for a chain), and
// the only per-link traffic is the inputs, v, a, the force offsets and tau.
//
// Model constants are deduplicated: identical bodies (every link of a generated
// rope) share one entry of a body table, and each link reads a 4-byte index.
//
// Multi-DoF joints: one element per body (the elements' _at forms), the joint's rows
// of q, qd, qdd and tau from two index arrays (Body::idx_q / idx_v), read only for
// such models. A floating base is the root segment's head: its pose and twist (and
// its qdd with -g) are the forward scans' first element, and the backward scan
// writes its wrench to tau_0..5; spherical joints are ordinary elements.
//
// Every pointer given to launch() is a DEVICE pointer. The plan owns its device
// memory (model tables, scratch for max_batch instances, CUB's temporary storage):
// nothing is allocated per call and nothing is synchronised; one plan serves one
// stream at a time.
#pragma once

#include <cstddef>
#include <string>
#include <vector>

#include "scandyn/algorithm/rnea_scan.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/build_config.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

namespace scandyn {
namespace cuda {

// Position roles in a level's body list.
enum ScanRole : unsigned char {
  kSegmentHead = 1,  // first body of its segment: its parent is in a lower level (or the base)
  kSegmentTail = 2,  // last body of its segment: body i + 1 is not its child
};

// Threads per scan pass the plans aim at (IdScanPlan's target_runs).
inline constexpr unsigned kDefaultTargetRuns = 1u << 16;

template <class S>
class IdScanPlan {
 public:
  // Copies the model to the device and allocates the scratch for max_batch
  // instances. target_runs: about how many threads a pass runs (chunks get longer,
  // up to 64 links, before there are more). Throws BackendError when the device
  // memory does not suffice (naming the bytes needed and free) or on any CUDA error.
  IdScanPlan(const ModelTpl<S>& model, Index max_batch, unsigned target_runs = kDefaultTargetRuns);
  ~IdScanPlan();
  IdScanPlan(const IdScanPlan&) = delete;
  IdScanPlan& operator=(const IdScanPlan&) = delete;

  // tau (nv x B) = RNEA(q (nq x B), qd, qdd) - sum J^T fext for B = in.q.batch <= max_batch
  // instances (device views, any strides; fext: B x nbodies body wrenches or null), on
  // `stream`: 3 scans per level, no synchronisation. Returns cudaErrorInvalidValue
  // for disagreeing batch sizes, B > max_batch or a null pointer, else the first
  // launch error.
  cudaError_t launch(const IdBatchIn<S>& in, const BatchView<S>& tau, cudaStream_t stream);

  Index nv() const { return nv_; }
  Index max_batch() const { return max_batch_; }
  Index levels() const { return static_cast<Index>(level_begin_.size()) - 1; }
  Index body_classes() const { return classes_; }   // distinct bodies in the device table
  std::size_t device_bytes() const { return bytes_; }  // held by this plan

  // Device bytes a plan for this model and batch would hold (model tables, scratch,
  // CUB's temporary storage); what the constructor checks against free memory.
  static std::size_t bytes_needed(const ModelTpl<S>& model, Index max_batch);

 private:
  Index nv_ = 0;                        // DoFs (rows of qd, qdd, tau)
  Index nb_ = 0;                        // bodies (scan elements per instance)
  Index max_batch_ = 0;
  unsigned target_runs_ = kDefaultTargetRuns;
  Index classes_ = 0;
  Motion<S> a0_{};                      // base acceleration (-g)
  std::vector<Index> level_begin_;      // (levels + 1) offsets into order_
  std::size_t bytes_ = 0;
  void* block_ = nullptr;               // one device allocation holding all below
  // device arrays inside block_
  const Body<S>* body_table_ = nullptr;   // (classes) distinct bodies
  const int* body_class_ = nullptr;       // (nbodies) body i -> table entry
  const int* parent_ = nullptr;           // (nbodies) parent body, -1 at the base
  const int* order_ = nullptr;            // (nbodies) bodies level by level, segments contiguous
  const unsigned char* role_ = nullptr;   // (nbodies) ScanRole bits of order_[k]
  const int* branch_begin_ = nullptr;     // (nbodies + 1) CSR offsets of branch children per body
  const int* branch_child_ = nullptr;     // branch children (children other than body i + 1)
  const int* branch_point_ = nullptr;     // (nbodies) index among bodies with branch children, or -1
  const int* branch_pos_ = nullptr;       // (nbodies) a branch child's index in branch_child_, or -1
  const int* idx_q_ = nullptr;            // (nbodies) multi-DoF models: body i's first row of q, else null
  const int* idx_v_ = nullptr;            // (nbodies) multi-DoF models: its first row of qd, qdd, tau
  Motion<S>* v_ = nullptr;                // per-level scratch by (run, step): velocities
  Motion<S>* a_ = nullptr;                //   accelerations
  Force<S>* offset_ = nullptr;            //   force-pass offsets
  Motion<S>* vb_ = nullptr;               // (branch points x max_batch) v of bodies with branch children
  Motion<S>* ab_ = nullptr;               // (branch points x max_batch) a of the same
  Force<S>* Fb_ = nullptr;                // (branch children x max_batch) forces of branch children
  void* agg_ = nullptr;                   // (runs) run aggregates of the current pass
  void* pre_ = nullptr;                   // (runs) their inclusive scan (prefixes or suffixes)
  void* temp_ = nullptr;                // CUB temporary storage
  std::size_t temp_bytes_ = 0;
};

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
