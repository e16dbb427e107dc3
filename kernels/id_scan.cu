// kernels/id_scan.cu: inverse dynamics as device-wide scans across links
// (scandyn/cuda/id_scan.hpp). The scan elements, their operators and the per-body
// steps are the host/device ones of scandyn/scan/elements.hpp and
// scandyn/algorithm/steps.hpp; this file only says where each element's inputs
// come from and where each result goes.
#include <cub/device/device_scan.cuh>
#include <thrust/iterator/counting_iterator.h>
#include <thrust/iterator/transform_iterator.h>

#include <algorithm>
#include <climits>
#include <cstring>
#include <string>
#include <unordered_map>

#include "scandyn/algorithm/steps.hpp"
#include "scandyn/cuda/device.hpp"
#include "staging.hpp"
#include "scandyn/cuda/id_scan.hpp"
#include "scandyn/scan/elements.hpp"
#include "scandyn/scan/tree_plan.hpp"

namespace scandyn {
namespace cuda {

using detail::error_string;

namespace {

// ---- runs ---------------------------------------------------------------------------
// Level l holds n bodies (its segments, concatenated) for each of B instances. The
// bodies are cut into C chunks of P consecutive ones; run r = c B + b (instance
// fastest) is chunk c of instance b, one thread. Every pass aggregates each run
// serially, scans the run aggregates of each instance in chunk order with CUB
// (scan index b C + c), then walks each run again from its carry-in by the
// recursion itself: values are a carry-in (maps composed over whole runs) followed
// by at most P - 1 steps of the recursion.
//
// Memory. Per-level scratch (v, a, force offsets) is stored by (run, step) as
// [r / 32][step][r % 32]: at every step a warp's 32 threads touch 32 consecutive
// entries. Values other levels need are also stored by (body, instance): v and a
// of bodies with branch children (for the heads that hang from them), and the
// forces of those heads (for their parents' offsets).
constexpr int kRunBlock = 128;
constexpr unsigned kMinRun = 4, kMaxRun = 64;

struct RunShape {
  unsigned n, P, C, B, R;  // bodies, chunk length, chunks, instances, runs = C B
};

RunShape run_shape(unsigned n, unsigned B, unsigned target_runs) {
  const unsigned long long count = static_cast<unsigned long long>(n) * B;
  unsigned P = static_cast<unsigned>(std::min<unsigned long long>(kMaxRun, (count + target_runs - 1) / target_runs));
  P = std::min(n, std::max(kMinRun, P));
  const unsigned C = (n + P - 1) / P;
  return {n, P, C, B, C * B};
}

// entries of per-level scratch a shape uses, and a bound for every B <= max_batch
std::size_t scratch_entries(const RunShape& s) { return std::size_t((s.R + 31) / 32) * 32 * s.P; }
std::size_t scratch_bound(unsigned n, unsigned max_batch) {
  return std::size_t(max_batch) * (n + std::min(n, kMaxRun) - 1) + 31 * kMaxRun;
}

// kMulti: a model with multi-DoF joints (idx_q / idx_v set); the kernels are
// instantiated for it separately, so that a model of 1-DoF joints runs code without
// the general path (and its registers).
template <class S, bool kMulti = false>
struct Level {
  static constexpr bool kMultiDof = kMulti;
  // model (device)
  const Body<S>* __restrict__ table;         // distinct bodies
  const int* __restrict__ body_class;        // (nv) body -> table entry
  const int* __restrict__ parent;            // (nv)
  const int* __restrict__ order;             // (n) this level's bodies
  const unsigned char* __restrict__ role;    // (n) ScanRole bits
  const int* __restrict__ branch_begin;      // (nv + 1)
  const int* __restrict__ branch_child;      // branch children, by parent
  const int* __restrict__ branch_point;      // (nv) index among bodies with branch children, or -1
  const int* __restrict__ branch_pos;        // (nv) index of a branch child in branch_child, or -1
  const int* __restrict__ idx_q;             // (nbodies) first q row of body i's joint, or null: a model
  const int* __restrict__ idx_v;             // (nbodies) of 1-DoF joints, body i at row i of q, qd, qdd, tau
  // batch (device views)
  IdBatchIn<S> in;
  BatchView<S> tau;
  // scratch
  Motion<S>* v;         // per-level, by (run, step), from `base`
  Motion<S>* a;
  Force<S>* offset;
  Motion<S>* vb;        // (branch points x B) v of bodies with branch children
  Motion<S>* ab;        // (branch points x B) a of the same
  Force<S>* Fb;         // (branch children x B) forces of branch children (segment heads)
  std::size_t base;     // this level's first scratch entry
  int nb;               // bodies (fext's stride)
  RunShape shape;
  Motion<S> a0;         // base acceleration

  struct Site {
    unsigned b;           // instance
    int i;                // body
    unsigned char role;
    std::size_t st;       // scratch entry
  };
  // run r's step j; valid when chunk_begin(r) + j < n
  __device__ __forceinline__ unsigned chunk(unsigned r) const { return r / shape.B; }
  __device__ __forceinline__ unsigned steps(unsigned r) const { return min(shape.P, shape.n - chunk(r) * shape.P); }
  __device__ __forceinline__ Site site(unsigned r, unsigned j) const {
    const unsigned c = chunk(r), b = r - c * shape.B, k = c * shape.P + j;
    return {b, order[k], role[k], base + (std::size_t(r >> 5) * shape.P + j) * 32 + (r & 31)};
  }
  // scan index of run r (instances apart, chunks in order)
  __device__ __forceinline__ unsigned scan_index(unsigned r) const {
    const unsigned c = chunk(r), b = r - c * shape.B;
    return b * shape.C + c;
  }
  __device__ __forceinline__ Body<S> body(int i) const { return table[body_class[i]]; }
  // Xup of body i (bd its body) in instance b; a multi-DoF joint from its q rows
  __device__ __forceinline__ Transform<S> Xup(const Body<S>& bd, int i, unsigned b) const {
    if constexpr (!kMulti) return joint_transform(bd, in.q.at(i, b));
    if (joint_nv(bd.type) == 1) return joint_transform(bd, in.q.at(idx_q[i], b));
    S x[7];
    for (int k = 0; k < joint_nq(bd.type); ++k) x[k] = in.q.at(idx_q[i] + k, b);
    return joint_transform_at(bd, x);
  }
  __device__ __forceinline__ Transform<S> Xup(int i, unsigned b) const { return Xup(body(i), i, b); }
  // body i's joint rates from v (qd or qdd) into x (joint_nv entries; kMulti)
  __device__ __forceinline__ void rates(const BatchView<const S>& v, const Body<S>& bd, int i, unsigned b,
                                        S* x) const {
    for (int k = 0; k < joint_nv(bd.type); ++k) x[k] = v.at(idx_v[i] + k, b);
  }
};

// ---- scan elements ------------------------------------------------------------------

// The elements are scandyn/scan/elements.hpp's (id_velocity_element,
// id_acceleration_element); here only where a segment head's parent value comes
// from: the base, or the stored values of a branch point of a lower level.

// velocities: (Xup_i, S qd_i); a segment head (0, Xup_i v_parent + S qd_i)
template <class S, bool kM>
__device__ MotionAffine<S> velocity_element(const Level<S, kM>& L, const typename Level<S, kM>::Site& s, const Body<S>& bd,
                                            const Transform<S>& X) {
  MotionAffine<S> e;
  if constexpr (kM) {
    S qd[kMaxJointDofs];
    L.rates(L.in.qd, bd, s.i, s.b, qd);
    e = id_velocity_element_at(bd, X, qd);
  } else {
    e = id_velocity_element(bd, X, L.in.qd.at(s.i, s.b));
  }
  if (!(s.role & kSegmentHead)) return e;
  const int p = L.parent[s.i];
  const Motion<S> vp = p < 0 ? Motion<S>::zero() : L.vb[std::size_t(L.branch_point[p]) * L.shape.B + s.b];
  return fold_parent(e, vp);
}

// accelerations: (Xup_i, S qdd + v x S qd); a head folds in Xup_i a_parent (-g at the base)
template <class S, bool kM>
__device__ MotionAffine<S> acceleration_element(const Level<S, kM>& L, const typename Level<S, kM>::Site& s,
                                                const Body<S>& bd, const Transform<S>& X, const Motion<S>& v) {
  MotionAffine<S> e;
  if constexpr (kM) {
    S qd[kMaxJointDofs], qdd[kMaxJointDofs];
    L.rates(L.in.qd, bd, s.i, s.b, qd);
    L.rates(L.in.qdd, bd, s.i, s.b, qdd);
    e = id_acceleration_element_at(bd, X, v, qd, qdd);
  } else {
    e = id_acceleration_element(bd, X, v, L.in.qd.at(s.i, s.b), L.in.qdd.at(s.i, s.b));
  }
  if (!(s.role & kSegmentHead)) return e;
  const int p = L.parent[s.i];
  const Motion<S> ap = p < 0 ? L.a0 : L.ab[std::size_t(L.branch_point[p]) * L.shape.B + s.b];
  return fold_parent(e, ap);
}

// forces, leaves to root: G -> B + Y^T G with G = F_{i+1}, Y = Xup_{i+1} (zero at a
// segment's tail), B = f_i = I a + v x* I v - fext (body_force) plus the forces of
// the branch children (heads of higher levels, final when this level runs)
template <class S, bool kM>
__device__ ForceAffine<S> force_element(const Level<S, kM>& L, const typename Level<S, kM>::Site& s, const Body<S>& bd,
                                        const Motion<S>& v, const Motion<S>& a) {
  Force<S> f = body_force(bd, v, a);
  if (L.in.fext) f -= L.in.fext[std::size_t(s.b) * L.nb + s.i];
  for (int k = L.branch_begin[s.i]; k < L.branch_begin[s.i + 1]; ++k) {
    const int c = L.branch_child[k];
    const Transform<S> Xc = L.Xup(c, s.b);
    f += Xc.apply_transpose(L.Fb[std::size_t(k) * L.shape.B + s.b]);
  }
  if (s.role & kSegmentTail) return {zero_transform<S>(), f};
  return {L.Xup(s.i + 1, s.b), f};
}

// CUB's operator sees (prefix so far, next element): for the force aggregates,
// scanned from the last run back, that is (deeper runs d, outer run o).
struct ComposeForceSuffix {
  template <class S>
  __host__ __device__ ForceAffine<S> operator()(const ForceAffine<S>& d, const ForceAffine<S>& o) const {
    return compose(o, d);
  }
};

// ---- pass kernels: one thread per run -----------------------------------------------

// velocity aggregates
template <class S, bool kM>
__global__ void __launch_bounds__(kRunBlock) velocity_runs(const Level<S, kM> L, MotionAffine<S>* __restrict__ agg) {
  const unsigned r = blockIdx.x * blockDim.x + threadIdx.x;
  if (r >= L.shape.R) return;
  const unsigned n = L.steps(r);
  MotionAffine<S> acc;
  for (unsigned j = 0; j < n; ++j) {
    const auto s = L.site(r, j);
    const Body<S> bd = L.body(s.i);
    const MotionAffine<S> el = velocity_element(L, s, bd, L.Xup(bd, s.i, s.b));
    acc = j == 0 ? el : compose(acc, el);
  }
  agg[L.scan_index(r)] = acc;
}

// velocities from the carry-in; acceleration aggregates
template <class S, bool kM>
__global__ void __launch_bounds__(kRunBlock)
    velocity_walk(const Level<S, kM> L, const MotionAffine<S>* __restrict__ pre, MotionAffine<S>* __restrict__ agg) {
  const unsigned r = blockIdx.x * blockDim.x + threadIdx.x;
  if (r >= L.shape.R) return;
  const unsigned n = L.steps(r), si = L.scan_index(r);
  Motion<S> x = L.chunk(r) > 0 ? pre[si - 1].b : Motion<S>::zero();  // a chunk 0 starts with a head
  MotionAffine<S> acc;
  for (unsigned j = 0; j < n; ++j) {
    const auto s = L.site(r, j);
    const Body<S> bd = L.body(s.i);
    const Transform<S> X = L.Xup(bd, s.i, s.b);
    x = apply(velocity_element(L, s, bd, X), x);
    L.v[s.st] = x;
    const int bp = L.branch_point[s.i];
    if (bp >= 0) L.vb[std::size_t(bp) * L.shape.B + s.b] = x;
    const MotionAffine<S> el = acceleration_element(L, s, bd, X, x);
    acc = j == 0 ? el : compose(acc, el);
  }
  agg[si] = acc;
}

// accelerations from the carry-in; with kForces (a model of one level) also the
// force offsets and aggregates, which otherwise wait for force_runs
template <class S, bool kM, bool kForces>
__global__ void __launch_bounds__(kRunBlock)
    acceleration_walk(const Level<S, kM> L, const MotionAffine<S>* __restrict__ pre, ForceAffine<S>* __restrict__ agg) {
  const unsigned r = blockIdx.x * blockDim.x + threadIdx.x;
  if (r >= L.shape.R) return;
  const unsigned n = L.steps(r), si = L.scan_index(r);
  Motion<S> x = L.chunk(r) > 0 ? pre[si - 1].b : Motion<S>::zero();
  ForceAffine<S> acc;
  for (unsigned j = 0; j < n; ++j) {
    const auto s = L.site(r, j);
    const Body<S> bd = L.body(s.i);
    const Motion<S> v = L.v[s.st];
    x = apply(acceleration_element(L, s, bd, L.Xup(bd, s.i, s.b), v), x);
    L.a[s.st] = x;
    const int bp = L.branch_point[s.i];
    if (bp >= 0) L.ab[std::size_t(bp) * L.shape.B + s.b] = x;
    if constexpr (kForces) {
      const ForceAffine<S> el = force_element(L, s, bd, v, x);
      L.offset[s.st] = el.B;
      acc = j == 0 ? el : compose(acc, el);  // the outer run so far, then this inner element
    }
  }
  if constexpr (kForces) agg[si] = acc;
}

// force offsets and aggregates of a level whose branch children are final
template <class S, bool kM>
__global__ void __launch_bounds__(kRunBlock) force_runs(const Level<S, kM> L, ForceAffine<S>* __restrict__ agg) {
  const unsigned r = blockIdx.x * blockDim.x + threadIdx.x;
  if (r >= L.shape.R) return;
  const unsigned n = L.steps(r);
  ForceAffine<S> acc;
  for (unsigned j = 0; j < n; ++j) {
    const auto s = L.site(r, j);
    const ForceAffine<S> el = force_element(L, s, L.body(s.i), L.v[s.st], L.a[s.st]);
    L.offset[s.st] = el.B;
    acc = j == 0 ? el : compose(acc, el);
  }
  agg[L.scan_index(r)] = acc;
}

// forces from the carry-in (the force of the next run's first body), last step
// first; tau, and the forces of branch children for their parents
template <class S, bool kM>
__global__ void __launch_bounds__(kRunBlock) force_walk(const Level<S, kM> L, const ForceAffine<S>* __restrict__ suffix) {
  const unsigned r = blockIdx.x * blockDim.x + threadIdx.x;
  if (r >= L.shape.R) return;
  const unsigned n = L.steps(r), si = L.scan_index(r), count = L.shape.B * L.shape.C;
  // suffix[k] covers scan indices count - 1 - k .. the instance's last run
  Force<S> G = L.chunk(r) + 1 < L.shape.C ? suffix[count - 2 - si].B : Force<S>::zero();  // a last chunk ends in a tail
  for (unsigned j = n; j-- > 0;) {
    const auto s = L.site(r, j);
    const Body<S> bd = L.body(s.i);
    const Transform<S> Y = (s.role & kSegmentTail) ? zero_transform<S>()
                                                   : L.Xup(s.i + 1, s.b);
    G = L.offset[s.st] + Y.apply_transpose(G);
    const int pos = L.branch_pos[s.i];
    if (pos >= 0) L.Fb[std::size_t(pos) * L.shape.B + s.b] = G;
    if (!kM || joint_nv(bd.type) == 1) {
      L.tau.at(kM ? L.idx_v[s.i] : s.i, s.b) = joint_project(bd, G);
    } else {  // a floating base: its wrench, tau_0..5
      S t[kMaxJointDofs];
      joint_project_at(bd, G, t);
      for (int k = 0; k < joint_nv(bd.type); ++k) L.tau.at(L.idx_v[s.i] + k, s.b) = t[k];
    }
  }
}

// run aggregates read from the last back
template <class S>
struct Reversed {
  const ForceAffine<S>* agg;
  unsigned count;
  __host__ __device__ ForceAffine<S> operator()(unsigned k) const { return agg[count - 1 - k]; }
};

template <class S>
cudaError_t scan_motion_runs(void* temp, std::size_t& bytes, const MotionAffine<S>* agg, MotionAffine<S>* pre,
                             unsigned count, cudaStream_t stream) {
  return cub::DeviceScan::InclusiveScan(temp, bytes, agg, pre, ComposeMotionAffine{}, static_cast<int>(count),
                                        stream);
}
template <class S>
cudaError_t scan_force_runs(void* temp, std::size_t& bytes, const ForceAffine<S>* agg, ForceAffine<S>* suffix,
                            unsigned count, cudaStream_t stream) {
  auto in = thrust::make_transform_iterator(thrust::counting_iterator<unsigned>(0u), Reversed<S>{agg, count});
  return cub::DeviceScan::InclusiveScan(temp, bytes, in, suffix, ComposeForceSuffix{}, static_cast<int>(count),
                                        stream);
}

// Host-side layout of a plan: the level order, roles, branch children, body classes.
struct HostPlan {
  std::vector<int> order, parent, branch_begin, branch_child, body_class;
  std::vector<int> idx_q, idx_v;  // (nbodies) a multi-DoF model's joint rows; empty otherwise
  std::vector<int> branch_point;  // (nv) index among bodies with branch children, or -1
  std::vector<int> branch_pos;    // (nv) position of a branch child in branch_child, or -1
  int branch_points = 0;
  std::vector<unsigned char> role;
  std::vector<Index> level_begin;
  Index max_level = 0;  // bodies in the largest level
};

template <class S>
HostPlan host_plan(const ModelTpl<S>& model, std::vector<Body<S>>* table) {
  const Index n = model.nbodies();
  HostPlan h;
  std::vector<Index> parent(static_cast<std::size_t>(n));
  for (Index i = 0; i < n; ++i) {
    parent[i] = model.bodies[i].parent;
    if (parent[i] >= i || parent[i] < -1)
      throw BackendError("backend 'cuda': body " + std::to_string(i) + " has parent " + std::to_string(parent[i]) +
                         " (bodies must come after their parent)");
  }
  h.parent.assign(parent.begin(), parent.end());
  const TreeScanPlan plan = make_tree_scan_plan(parent, std::max<Index>(n, 1));  // no cutting: pieces = segments
  h.level_begin.push_back(0);
  for (Index l = 0; l < plan.num_levels(); ++l) {
    for (Index k = plan.level_begin[l]; k < plan.level_begin[l + 1]; ++k) {
      const auto& piece = plan.pieces[k];
      for (Index i = piece.begin; i < piece.end; ++i) {
        h.order.push_back(i);
        h.role.push_back(static_cast<unsigned char>((i == piece.begin ? kSegmentHead : 0) |
                                                    (i + 1 == piece.end ? kSegmentTail : 0)));
      }
    }
    h.level_begin.push_back(static_cast<Index>(h.order.size()));
    h.max_level = std::max(h.max_level, h.level_begin[l + 1] - h.level_begin[l]);
  }
  // branch children: children other than the next body
  h.branch_begin.assign(static_cast<std::size_t>(n) + 1, 0);
  for (Index c = 0; c < n; ++c)
    if (parent[c] >= 0 && parent[c] != c - 1) ++h.branch_begin[parent[c] + 1];
  for (Index i = 0; i < n; ++i) h.branch_begin[i + 1] += h.branch_begin[i];
  h.branch_child.resize(static_cast<std::size_t>(h.branch_begin[n]));
  std::vector<int> fill(h.branch_begin.begin(), h.branch_begin.end() - 1);
  h.branch_pos.assign(static_cast<std::size_t>(n), -1);
  for (Index c = 0; c < n; ++c)
    if (parent[c] >= 0 && parent[c] != c - 1) {
      h.branch_pos[c] = fill[parent[c]];
      h.branch_child[fill[parent[c]]++] = c;
    }
  h.branch_point.assign(static_cast<std::size_t>(n), -1);
  for (Index i = 0; i < n; ++i)
    if (h.branch_begin[i + 1] > h.branch_begin[i]) h.branch_point[i] = h.branch_points++;
  if (model.multi_dof())
    for (const Body<S>& b : model.bodies) {
      h.idx_q.push_back(static_cast<int>(b.idx_q));
      h.idx_v.push_back(static_cast<int>(b.idx_v));
    }
  // body classes: bodies equal in everything but the parent index and their rows in
  // q and qd share an entry (every link of a generated rope)
  if (table) {
    std::unordered_map<std::string, int> seen;
    h.body_class.resize(static_cast<std::size_t>(n));
    for (Index i = 0; i < n; ++i) {
      Body<S> b = model.bodies[i];
      b.parent = -1;
      b.idx_q = b.idx_v = 0;
      std::string key(reinterpret_cast<const char*>(&b), sizeof b);
      auto [it, fresh] = seen.emplace(std::move(key), static_cast<int>(table->size()));
      if (fresh) table->push_back(b);
      h.body_class[i] = it->second;
    }
  }
  return h;
}

constexpr std::size_t kAlign = 256;
std::size_t aligned(std::size_t x) { return (x + kAlign - 1) / kAlign * kAlign; }

// CUB's temporary storage for `runs` run aggregates.
template <class S>
std::size_t cub_temp_bytes(unsigned runs) {
  if (runs == 0) return 0;
  std::size_t a = 0, b = 0;
  scan_motion_runs<S>(nullptr, a, nullptr, nullptr, runs, nullptr);
  scan_force_runs<S>(nullptr, b, nullptr, nullptr, runs, nullptr);
  return std::max(a, b);
}

// Byte sizes of the parts of one allocation, in order.
struct Parts {
  std::size_t ints, role, table;                 // model
  std::size_t v, a, offset, vb, ab, Fb;          // scratch
  std::size_t agg, pre, temp;                    // run aggregates, their scan, CUB's storage
  std::size_t total() const { return ints + role + table + v + a + offset + vb + ab + Fb + agg + pre + temp; }
};

// ints: body_class, parent, order, branch_point, branch_pos (nb each), branch_begin (nb + 1), branch_child,
// idx_q, idx_v (nb each, multi-DoF models)
template <class S>
Parts parts(const HostPlan& h, std::size_t classes, Index nb, Index max_batch) {
  const std::size_t n = static_cast<std::size_t>(nb), B = static_cast<std::size_t>(max_batch);
  Parts p{};
  p.ints = aligned((6 * n + 1 + h.branch_child.size() + h.idx_q.size() + h.idx_v.size()) * sizeof(int));
  p.role = aligned(n);
  p.table = aligned(classes * sizeof(Body<S>));
  std::size_t scratch = 0, runs = 0;
  for (std::size_t l = 0; l + 1 < h.level_begin.size(); ++l) {
    const unsigned nl = static_cast<unsigned>(h.level_begin[l + 1] - h.level_begin[l]);
    scratch += scratch_bound(nl, static_cast<unsigned>(B));
    runs = std::max<std::size_t>(runs, B * std::max<std::size_t>(1, (nl + kMinRun - 1) / kMinRun));
  }
  p.v = aligned(scratch * sizeof(Motion<S>));
  p.a = p.v;
  p.offset = aligned(scratch * sizeof(Force<S>));
  p.vb = aligned(B * h.branch_points * sizeof(Motion<S>));
  p.ab = p.vb;
  p.Fb = aligned(B * h.branch_child.size() * sizeof(Force<S>));
  p.agg = aligned(runs * std::max(sizeof(MotionAffine<S>), sizeof(ForceAffine<S>)));
  p.pre = p.agg;
  p.temp = aligned(cub_temp_bytes<S>(static_cast<unsigned>(runs)));
  return p;
}

void check_count(Index nv, Index max_batch, Index max_level) {
  if (static_cast<long long>(max_batch) * (max_level + kMaxRun) > INT_MAX)
    throw BackendError("backend 'cuda': max_batch " + std::to_string(max_batch) + " instances of a model with " +
                       std::to_string(nv) + " bodies give scans of more than 2^31 - 1 elements");
}

}  // namespace

template <class S>
std::size_t IdScanPlan<S>::bytes_needed(const ModelTpl<S>& model, Index max_batch) {
  std::vector<Body<S>> table;
  const HostPlan h = host_plan(model, &table);
  check_count(model.nbodies(), max_batch, h.max_level);
  return parts<S>(h, table.size(), model.nbodies(), max_batch).total();
}

template <class S>
IdScanPlan<S>::IdScanPlan(const ModelTpl<S>& model, Index max_batch, unsigned target_runs)
    : nv_(model.nv()), nb_(model.nbodies()), max_batch_(max_batch), target_runs_(std::max(1u, target_runs)) {
  if (max_batch_ < 0) throw BackendError("backend 'cuda': max_batch " + std::to_string(max_batch_) + " is negative");
  std::vector<Body<S>> table;
  const HostPlan h = host_plan(model, &table);
  check_count(nb_, max_batch_, h.max_level);
  classes_ = static_cast<Index>(table.size());
  level_begin_ = h.level_begin;
  a0_ = base_acceleration(model.gravity);
  const Parts p = parts<S>(h, table.size(), nb_, max_batch_);
  bytes_ = p.total();
  temp_bytes_ = p.temp;
  if (bytes_ == 0) return;

  block_ = detail::device_malloc(bytes_, [&](std::size_t free_bytes, std::size_t total_bytes) {
    return "backend 'cuda': the link scans for max_batch " + std::to_string(max_batch_) + " instances of a " +
           std::to_string(nb_) + "-body model in " + (sizeof(S) == 4 ? "float" : "double") + " need " +
           std::to_string(bytes_) + " bytes of device memory (v, a and force offsets: " +
           std::to_string(3 * sizeof(Motion<S>)) +
           " bytes per body and instance, plus model tables and scan storage); the device has " +
           std::to_string(free_bytes) + " bytes free of " + std::to_string(total_bytes);
  });
  char* at = static_cast<char*>(block_);
  auto take = [&at](std::size_t bytes) {
    char* here = at;
    at += bytes;
    return here;
  };
  // the model's int arrays, packed
  std::vector<int> ints;
  ints.reserve(p.ints / sizeof(int));
  auto pack = [&ints](const std::vector<int>& v) {
    const std::size_t at_ = ints.size();
    ints.insert(ints.end(), v.begin(), v.end());
    return at_;
  };
  const std::size_t o_class = pack(h.body_class), o_parent = pack(h.parent), o_order = pack(h.order);
  const std::size_t o_bp = pack(h.branch_point), o_pos = pack(h.branch_pos), o_bb = pack(h.branch_begin);
  const std::size_t o_bc = pack(h.branch_child), o_iq = pack(h.idx_q), o_iv = pack(h.idx_v);
  int* ints_d = reinterpret_cast<int*>(take(p.ints));
  unsigned char* role_d = reinterpret_cast<unsigned char*>(take(p.role));
  Body<S>* table_d = reinterpret_cast<Body<S>*>(take(p.table));
  body_table_ = table_d, role_ = role_d;
  body_class_ = ints_d + o_class, parent_ = ints_d + o_parent, order_ = ints_d + o_order;
  branch_point_ = ints_d + o_bp, branch_pos_ = ints_d + o_pos;
  branch_begin_ = ints_d + o_bb, branch_child_ = ints_d + o_bc;
  if (!h.idx_q.empty()) idx_q_ = ints_d + o_iq, idx_v_ = ints_d + o_iv;
  v_ = reinterpret_cast<Motion<S>*>(take(p.v));
  a_ = reinterpret_cast<Motion<S>*>(take(p.a));
  offset_ = reinterpret_cast<Force<S>*>(take(p.offset));
  vb_ = reinterpret_cast<Motion<S>*>(take(p.vb));
  ab_ = reinterpret_cast<Motion<S>*>(take(p.ab));
  Fb_ = reinterpret_cast<Force<S>*>(take(p.Fb));
  agg_ = take(p.agg);
  pre_ = take(p.pre);
  temp_ = take(p.temp);

  auto upload = [&](void* dst, const void* src, std::size_t bytes, const char* what) {
    if (bytes == 0) return;
    const cudaError_t e = cudaMemcpy(dst, src, bytes, cudaMemcpyHostToDevice);
    if (e != cudaSuccess) {
      (void)cudaGetLastError();
      cudaFree(block_);
      block_ = nullptr;
      throw BackendError(std::string("backend 'cuda': copying the ") + what + " to the device: " + error_string(e));
    }
  };
  upload(ints_d, ints.data(), ints.size() * sizeof(int), "model's index arrays");
  upload(role_d, h.role.data(), h.role.size(), "segment roles");
  upload(table_d, table.data(), table.size() * sizeof(Body<S>), "body table");
  // A cudaMemcpy from pageable memory may return before the data reaches the device,
  // and launches on a non-blocking stream do not wait for the legacy stream: make
  // the tables final before any launch reads them.
  if (const cudaError_t err = cudaDeviceSynchronize(); err != cudaSuccess) {
    (void)cudaGetLastError();
    cudaFree(block_);
    block_ = nullptr;
    throw BackendError("backend 'cuda': copying the model tables to the device: " + error_string(err));
  }
}

template <class S>
IdScanPlan<S>::~IdScanPlan() {
  if (block_) cudaFree(block_);
}

template <class S>
cudaError_t IdScanPlan<S>::launch(const IdBatchIn<S>& in, const BatchView<S>& tau, cudaStream_t stream) {
  const Index B = in.q.batch;
  if (B < 0 || in.qd.batch != B || in.qdd.batch != B || tau.batch != B || B > max_batch_) return cudaErrorInvalidValue;
  if (B == 0 || nv_ == 0) return cudaSuccess;
  if (!in.q.data || !in.qd.data || !in.qdd.data || !tau.data) return cudaErrorInvalidValue;
  // the passes over L, a Level<S, kMulti> (the kernels of a model with multi-DoF
  // joints are other instances)
  auto passes = [&](auto L) -> cudaError_t {
    constexpr bool kM = decltype(L)::kMultiDof;
    const Index nl = levels();
    // every level's scratch region, for this batch size
    std::vector<std::size_t> base(static_cast<std::size_t>(nl) + 1, 0);
    auto at_level = [&](Index l) {
      L.order = order_ + level_begin_[l];
      L.role = role_ + level_begin_[l];
      L.shape = run_shape(static_cast<unsigned>(level_begin_[l + 1] - level_begin_[l]), static_cast<unsigned>(B),
                          target_runs_);
      L.base = base[l];
    };
    for (Index l = 0; l < nl; ++l) {
      at_level(l);
      base[l + 1] = base[l] + scratch_entries(L.shape);
    }
    auto* magg = static_cast<MotionAffine<S>*>(agg_);
    auto* mpre = static_cast<MotionAffine<S>*>(pre_);
    auto* fagg = static_cast<ForceAffine<S>*>(agg_);
    auto* fsuf = static_cast<ForceAffine<S>*>(pre_);
    auto blocks = [](const RunShape& R) { return (R.R + kRunBlock - 1) / kRunBlock; };
    cudaError_t err = cudaSuccess;
    // forward, level by level: velocities, then accelerations (and a chain's force offsets)
    for (Index l = 0; l < nl; ++l) {
      at_level(l);
      const RunShape& R = L.shape;
      std::size_t bytes = temp_bytes_;
      velocity_runs<<<blocks(R), kRunBlock, 0, stream>>>(L, magg);
      if ((err = cudaGetLastError()) != cudaSuccess) return err;
      if ((err = scan_motion_runs<S>(temp_, bytes, magg, mpre, R.R, stream)) != cudaSuccess) return err;
      velocity_walk<<<blocks(R), kRunBlock, 0, stream>>>(L, mpre, magg);
      if ((err = cudaGetLastError()) != cudaSuccess) return err;
      bytes = temp_bytes_;
      if ((err = scan_motion_runs<S>(temp_, bytes, magg, mpre, R.R, stream)) != cudaSuccess) return err;
      if (nl == 1) acceleration_walk<S, kM, true><<<blocks(R), kRunBlock, 0, stream>>>(L, mpre, fagg);
      else acceleration_walk<S, kM, false><<<blocks(R), kRunBlock, 0, stream>>>(L, mpre, fagg);
      if ((err = cudaGetLastError()) != cudaSuccess) return err;
    }
    // backward, deepest level first: forces and torques. A level's force offsets
    // need its branch children's forces, which the deeper levels produce: with more
    // than one level they are made here.
    for (Index l = nl - 1; l >= 0; --l) {
      at_level(l);
      const RunShape& R = L.shape;
      if (nl > 1) {
        force_runs<<<blocks(R), kRunBlock, 0, stream>>>(L, fagg);
        if ((err = cudaGetLastError()) != cudaSuccess) return err;
      }
      std::size_t bytes = temp_bytes_;
      if ((err = scan_force_runs<S>(temp_, bytes, fagg, fsuf, R.R, stream)) != cudaSuccess) return err;
      force_walk<<<blocks(R), kRunBlock, 0, stream>>>(L, fsuf);
      if ((err = cudaGetLastError()) != cudaSuccess) return err;
    }
    return cudaSuccess;
  };
  if (idx_q_)
    return passes(Level<S, true>{body_table_, body_class_, parent_, nullptr, nullptr, branch_begin_, branch_child_,
                                 branch_point_, branch_pos_, idx_q_, idx_v_, in, tau, v_, a_, offset_, vb_, ab_, Fb_,
                                 0, static_cast<int>(nb_), RunShape{}, a0_});
  return passes(Level<S, false>{body_table_, body_class_, parent_, nullptr, nullptr, branch_begin_, branch_child_,
                                branch_point_, branch_pos_, nullptr, nullptr, in, tau, v_, a_, offset_, vb_, ab_, Fb_,
                                0, static_cast<int>(nb_), RunShape{}, a0_});
}

template class IdScanPlan<float>;
template class IdScanPlan<double>;

}  // namespace cuda
}  // namespace scandyn
