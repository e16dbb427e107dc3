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
#include "scandyn/cuda/id_scan.hpp"
#include "scandyn/scan/elements.hpp"
#include "scandyn/scan/tree_plan.hpp"

namespace scandyn {
namespace cuda {
namespace {

// A map that ignores its argument: x -> 0 x + b (segment heads and tails).
template <class S>
__device__ __forceinline__ Transform<S> zero_transform() {
  return {Mat3<S>::zero(), Vec3<S>::zero()};
}

// What the element and store functors of one level read and write.
template <class S>
struct Level {
  const Body<S>* table;        // distinct bodies
  const int* body_class;       // (nv) body -> table entry
  const int* parent;           // (nv)
  const int* order;            // (n_level) this level's bodies
  const unsigned char* role;   // (n_level) ScanRole bits
  const int* branch_begin;     // (nv + 1)
  const int* branch_child;
  unsigned n_level;            // bodies in this level
  unsigned count;              // elements in the scan: B * n_level
  int nv;
  IdBatchIn<S> in;             // device views
  BatchView<S> tau;
  Motion<S>* v;                // (B x nv)
  Motion<S>* a;                // (B x nv)
  Force<S>* F;                 // (B x nv), written at segment heads
  Motion<S> a0;                // base acceleration

  // element e of the level -> instance b, body i, role
  struct Site {
    unsigned b;
    int i;
    unsigned char role;
  };
  __device__ __forceinline__ Site site(unsigned e) const {
    const unsigned b = e / n_level, k = e - b * n_level;
    return {b, order[k], role[k]};
  }
  __device__ __forceinline__ std::size_t slot(unsigned b, int i) const {
    return static_cast<std::size_t>(b) * nv + i;
  }
  __device__ __forceinline__ const Body<S>& body(int i) const { return table[body_class[i]]; }
};

// ---- scan elements ------------------------------------------------------------------

// velocities: (Xup_i, S qd_i); a segment head (0, Xup_i v_parent + S qd_i)
template <class S>
__device__ MotionAffine<S> velocity_element(const Level<S>& L, const typename Level<S>::Site& s) {
  const Body<S>& bd = L.body(s.i);
  const Transform<S> X = joint_transform(bd, L.in.q.at(s.i, s.b));
  const Motion<S> sq = joint_motion(bd, L.in.qd.at(s.i, s.b));
  if (!(s.role & kSegmentHead)) return {X, sq};
  const int p = L.parent[s.i];
  const Motion<S> vp = p < 0 ? Motion<S>::zero() : L.v[L.slot(s.b, p)];
  return {zero_transform<S>(), X.apply(vp) + sq};
}

// accelerations: (Xup_i, S qdd + v x S qd); a head folds in Xup_i a_parent (-g at the base)
template <class S>
__device__ MotionAffine<S> acceleration_element(const Level<S>& L, const typename Level<S>::Site& s,
                                                const Motion<S>& v) {
  const Body<S>& bd = L.body(s.i);
  const Transform<S> X = joint_transform(bd, L.in.q.at(s.i, s.b));
  const S qd = L.in.qd.at(s.i, s.b);
  const Motion<S> c = add_joint_motion(bd, cross_joint_motion(bd, v, qd), L.in.qdd.at(s.i, s.b));
  if (!(s.role & kSegmentHead)) return {X, c};
  const int p = L.parent[s.i];
  const Motion<S> ap = p < 0 ? L.a0 : L.a[L.slot(s.b, p)];
  return {zero_transform<S>(), X.apply(ap) + c};
}

// forces, leaves to root: G -> B + Y^T G with G = F_{i+1}. The offset B is the net
// body force f_i = I a + v x* I v - fext plus the forces of the branch children
// (heads of higher levels, final when this level runs) ...
template <class S>
__device__ Force<S> force_offset(const Level<S>& L, const typename Level<S>::Site& s, const Motion<S>& v,
                                 const Motion<S>& a) {
  const Body<S>& bd = L.body(s.i);
  Force<S> f = bd.I * a + cross(v, bd.I * v);
  if (L.in.fext) f -= L.in.fext[L.slot(s.b, s.i)];
  for (int k = L.branch_begin[s.i]; k < L.branch_begin[s.i + 1]; ++k) {
    const int c = L.branch_child[k];
    const Transform<S> Xc = joint_transform(L.body(c), L.in.q.at(c, s.b));
    f += Xc.apply_transpose(L.F[L.slot(s.b, c)]);
  }
  return f;
}
// ... and the map Y = Xup_{i+1}, zero at a segment's tail.
template <class S>
__device__ Transform<S> force_map(const Level<S>& L, const typename Level<S>::Site& s) {
  if (s.role & kSegmentTail) return zero_transform<S>();
  return joint_transform(L.body(s.i + 1), L.in.q.at(s.i + 1, s.b));
}

// CUB's operator sees (prefix so far, next element): for the run aggregates of the
// force pass, scanned from the last run back, that is (deeper runs d, outer run o).
struct ComposeForceSuffix {
  template <class S>
  __host__ __device__ ForceAffine<S> operator()(const ForceAffine<S>& d, const ForceAffine<S>& o) const {
    return compose(o, d);
  }
};

// ---- runs ------------------------------------------------------------------------------
// A level's `count` elements are cut into runs of `run` consecutive elements, one
// thread each. Every pass is: aggregate each run serially (kernels below), scan the
// run aggregates with CUB, then walk each run serially from its carry-in. Inside a
// run the values come from the recursion itself (apply, not compose), so the only
// composed maps span one run.
struct Runs {
  unsigned count;  // elements
  unsigned run;    // elements per run
  unsigned runs;   // ceil(count / run)
  __device__ __forceinline__ unsigned begin(unsigned r) const { return r * run; }
  __device__ __forceinline__ unsigned end(unsigned r) const { return min(count, (r + 1) * run); }
};

constexpr int kRunBlock = 128;
constexpr unsigned kTargetRuns = 1u << 16;  // threads per level pass, when there are elements for them
constexpr unsigned kMinRun = 4, kMaxRun = 64;

Runs make_runs(unsigned count) {
  unsigned run = (count + kTargetRuns - 1) / kTargetRuns;
  run = std::min(kMaxRun, std::max(kMinRun, run));
  return {count, run, (count + run - 1) / run};
}

// velocity aggregates
template <class S>
__global__ void __launch_bounds__(kRunBlock) velocity_runs(const Level<S> L, const Runs R, MotionAffine<S>* agg) {
  const unsigned r = blockIdx.x * blockDim.x + threadIdx.x;
  if (r >= R.runs) return;
  const unsigned e0 = R.begin(r), e1 = R.end(r);
  MotionAffine<S> acc = velocity_element(L, L.site(e0));
  for (unsigned e = e0 + 1; e < e1; ++e) acc = compose(acc, velocity_element(L, L.site(e)));
  agg[r] = acc;
}

// velocities from the carry-in; acceleration aggregates
template <class S>
__global__ void __launch_bounds__(kRunBlock)
    velocity_walk(const Level<S> L, const Runs R, const MotionAffine<S>* pre, MotionAffine<S>* agg) {
  const unsigned r = blockIdx.x * blockDim.x + threadIdx.x;
  if (r >= R.runs) return;
  const unsigned e0 = R.begin(r), e1 = R.end(r);
  Motion<S> x = r > 0 ? pre[r - 1].b : Motion<S>::zero();  // the first element is a head
  MotionAffine<S> acc;
  for (unsigned e = e0; e < e1; ++e) {
    const auto s = L.site(e);
    x = apply(velocity_element(L, s), x);
    L.v[L.slot(s.b, s.i)] = x;
    const MotionAffine<S> el = acceleration_element(L, s, x);
    acc = e == e0 ? el : compose(acc, el);
  }
  agg[r] = acc;
}

// One element of the force pass: its offset is kept for force_walk, the element
// joins the run's aggregate (the outer run so far, then this inner element).
template <class S>
__device__ __forceinline__ void force_element(const Level<S>& L, const typename Level<S>::Site& s, std::size_t slot,
                                              const Motion<S>& v, const Motion<S>& a, bool first, Force<S>* offset,
                                              ForceAffine<S>& acc) {
  const ForceAffine<S> el{force_map(L, s), force_offset(L, s, v, a)};
  offset[slot] = el.B;
  acc = first ? el : compose(acc, el);
}

// accelerations from the carry-in; with kForces (a model of one level) also the
// force offsets and aggregates, which otherwise wait for force_runs
template <class S, bool kForces>
__global__ void __launch_bounds__(kRunBlock) acceleration_walk(const Level<S> L, const Runs R,
                                                               const MotionAffine<S>* pre, Force<S>* offset,
                                                               ForceAffine<S>* agg) {
  const unsigned r = blockIdx.x * blockDim.x + threadIdx.x;
  if (r >= R.runs) return;
  const unsigned e0 = R.begin(r), e1 = R.end(r);
  Motion<S> x = r > 0 ? pre[r - 1].b : Motion<S>::zero();
  ForceAffine<S> acc;
  for (unsigned e = e0; e < e1; ++e) {
    const auto s = L.site(e);
    const std::size_t slot = L.slot(s.b, s.i);
    const Motion<S> v = L.v[slot];
    x = apply(acceleration_element(L, s, v), x);
    L.a[slot] = x;
    if constexpr (kForces) force_element(L, s, slot, v, x, e == e0, offset, acc);
  }
  if constexpr (kForces) agg[r] = acc;
}

// force offsets and aggregates of a level whose branch children are final
template <class S>
__global__ void __launch_bounds__(kRunBlock)
    force_runs(const Level<S> L, const Runs R, Force<S>* offset, ForceAffine<S>* agg) {
  const unsigned r = blockIdx.x * blockDim.x + threadIdx.x;
  if (r >= R.runs) return;
  const unsigned e0 = R.begin(r), e1 = R.end(r);
  ForceAffine<S> acc;
  for (unsigned e = e0; e < e1; ++e) {
    const auto s = L.site(e);
    const std::size_t slot = L.slot(s.b, s.i);
    force_element(L, s, slot, L.v[slot], L.a[slot], e == e0, offset, acc);
  }
  agg[r] = acc;
}

// forces from the carry-in (the force of the next run's first body), last element
// first; tau, and the forces of segment heads for the levels below
template <class S>
__global__ void __launch_bounds__(kRunBlock)
    force_walk(const Level<S> L, const Runs R, const Force<S>* offset, const ForceAffine<S>* suffix) {
  const unsigned r = blockIdx.x * blockDim.x + threadIdx.x;
  if (r >= R.runs) return;
  const unsigned e0 = R.begin(r), e1 = R.end(r);
  // suffix[k] covers runs R.runs - 1 - k .. end; run r + 1's is suffix[R.runs - 2 - r]
  Force<S> G = r + 1 < R.runs ? suffix[R.runs - 2 - r].B : Force<S>::zero();  // the last element is a tail
  for (unsigned e = e1; e-- > e0;) {
    const auto s = L.site(e);
    const std::size_t slot = L.slot(s.b, s.i);
    G = offset[slot] + force_map(L, s).apply_transpose(G);
    if (s.role & kSegmentHead) L.F[slot] = G;
    L.tau.at(s.i, s.b) = joint_project(L.body(s.i), G);
  }
}

// run aggregates read from the last run back
template <class S>
struct Reversed {
  const ForceAffine<S>* agg;
  unsigned runs;
  __host__ __device__ ForceAffine<S> operator()(unsigned k) const { return agg[runs - 1 - k]; }
};

template <class S>
cudaError_t scan_motion_runs(void* temp, std::size_t& bytes, const MotionAffine<S>* agg, MotionAffine<S>* pre,
                             unsigned runs, cudaStream_t stream) {
  return cub::DeviceScan::InclusiveScan(temp, bytes, agg, pre, ComposeMotionAffine{}, static_cast<int>(runs), stream);
}
template <class S>
cudaError_t scan_force_runs(void* temp, std::size_t& bytes, const ForceAffine<S>* agg, ForceAffine<S>* suffix,
                            unsigned runs, cudaStream_t stream) {
  auto in = thrust::make_transform_iterator(thrust::counting_iterator<unsigned>(0u), Reversed<S>{agg, runs});
  return cub::DeviceScan::InclusiveScan(temp, bytes, in, suffix, ComposeForceSuffix{}, static_cast<int>(runs), stream);
}

std::string error_string(cudaError_t err) {
  const char* s = cudaGetErrorString(err);
  return std::string(s ? s : "unknown CUDA error") + " (" + std::to_string(static_cast<int>(err)) + ")";
}

// Host-side layout of a plan: the level order, roles, branch children, body classes.
struct HostPlan {
  std::vector<int> order, parent, branch_begin, branch_child, body_class;
  std::vector<unsigned char> role;
  std::vector<Index> level_begin;
  Index max_level = 0;  // bodies in the largest level
};

template <class S>
HostPlan host_plan(const ModelTpl<S>& model, std::vector<Body<S>>* table) {
  const Index n = model.nv();
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
  for (Index c = 0; c < n; ++c)
    if (parent[c] >= 0 && parent[c] != c - 1) h.branch_child[fill[parent[c]]++] = c;
  // body classes: bodies equal in everything but the parent index share an entry
  if (table) {
    std::unordered_map<std::string, int> seen;
    h.body_class.resize(static_cast<std::size_t>(n));
    for (Index i = 0; i < n; ++i) {
      Body<S> b = model.bodies[i];
      b.parent = -1;
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

// CUB's temporary storage for the run-aggregate scans of the largest level.
template <class S>
std::size_t cub_temp_bytes(unsigned runs) {
  if (runs == 0) return 0;
  std::size_t a = 0, b = 0;
  scan_motion_runs<S>(nullptr, a, nullptr, nullptr, runs, nullptr);
  scan_force_runs<S>(nullptr, b, nullptr, nullptr, runs, nullptr);
  return std::max(a, b);
}

// Byte sizes of the parts of one allocation, in order.
template <class S>
struct Parts {
  std::size_t table, body_class, parent, order, role, branch_begin, branch_child, v, a, F, offset;
  std::size_t agg, pre, temp;  // per run: motion or force aggregates, their scan; CUB's storage
  std::size_t total() const {
    return table + body_class + parent + order + role + branch_begin + branch_child + v + a + F + offset + agg + pre +
           temp;
  }
};

template <class S>
Parts<S> parts(const HostPlan& h, std::size_t classes, Index nv, Index max_batch) {
  const std::size_t n = static_cast<std::size_t>(nv), B = static_cast<std::size_t>(max_batch);
  Parts<S> p{};
  p.table = aligned(classes * sizeof(Body<S>));
  p.body_class = aligned(n * sizeof(int));
  p.parent = aligned(n * sizeof(int));
  p.order = aligned(n * sizeof(int));
  p.role = aligned(n);
  p.branch_begin = aligned((n + 1) * sizeof(int));
  p.branch_child = aligned(h.branch_child.size() * sizeof(int));
  p.v = aligned(B * n * sizeof(Motion<S>));
  p.a = aligned(B * n * sizeof(Motion<S>));
  p.F = aligned(B * n * sizeof(Force<S>));
  p.offset = aligned(B * n * sizeof(Force<S>));
  const unsigned runs = make_runs(static_cast<unsigned>(B * static_cast<std::size_t>(h.max_level))).runs;
  p.agg = aligned(runs * std::max(sizeof(MotionAffine<S>), sizeof(ForceAffine<S>)));
  p.pre = p.agg;
  p.temp = aligned(cub_temp_bytes<S>(runs));
  return p;
}

void check_count(Index nv, Index max_batch, Index max_level) {
  if (static_cast<long long>(max_batch) * max_level > INT_MAX)
    throw BackendError("backend 'cuda': max_batch " + std::to_string(max_batch) + " instances of a model with " +
                       std::to_string(nv) + " bodies give scans of more than 2^31 - 1 elements");
}

}  // namespace

template <class S>
std::size_t IdScanPlan<S>::bytes_needed(const ModelTpl<S>& model, Index max_batch) {
  std::vector<Body<S>> table;
  const HostPlan h = host_plan(model, &table);
  check_count(model.nv(), max_batch, h.max_level);
  return parts<S>(h, table.size(), model.nv(), max_batch).total();
}

template <class S>
IdScanPlan<S>::IdScanPlan(const ModelTpl<S>& model, Index max_batch) : nv_(model.nv()), max_batch_(max_batch) {
  if (max_batch_ < 0) throw BackendError("backend 'cuda': max_batch " + std::to_string(max_batch_) + " is negative");
  std::vector<Body<S>> table;
  const HostPlan h = host_plan(model, &table);
  check_count(nv_, max_batch_, h.max_level);
  classes_ = static_cast<Index>(table.size());
  level_begin_ = h.level_begin;
  a0_ = base_acceleration(model.gravity);
  const Parts<S> p = parts<S>(h, table.size(), nv_, max_batch_);
  bytes_ = p.total();
  temp_bytes_ = p.temp;
  if (bytes_ == 0) return;

  std::size_t free_bytes = 0, total_bytes = 0;
  cudaError_t err = cudaMemGetInfo(&free_bytes, &total_bytes);
  if (err != cudaSuccess) {
    (void)cudaGetLastError();
    throw BackendError("backend 'cuda': cudaMemGetInfo: " + error_string(err));
  }
  auto too_large = [&](const std::string& why) {
    return BackendError("backend 'cuda': the link scans for max_batch " + std::to_string(max_batch_) +
                        " instances of a " + std::to_string(nv_) + "-body model in " +
                        (sizeof(S) == 4 ? "float" : "double") + " need " + std::to_string(bytes_) +
                        " bytes of device memory (v, a, F: " + std::to_string(3 * sizeof(Motion<S>)) +
                        " bytes per body and instance, plus model tables and scan storage); the device has " +
                        std::to_string(free_bytes) + " bytes free of " + std::to_string(total_bytes) + why);
  };
  if (bytes_ > free_bytes) throw too_large("");
  if ((err = cudaMalloc(&block_, bytes_)) != cudaSuccess) {
    (void)cudaGetLastError();
    block_ = nullptr;
    throw too_large(": cudaMalloc failed with " + error_string(err));
  }
  char* at = static_cast<char*>(block_);
  auto take = [&at](std::size_t bytes) {
    char* here = at;
    at += bytes;
    return here;
  };
  Body<S>* table_d = reinterpret_cast<Body<S>*>(take(p.table));
  int* class_d = reinterpret_cast<int*>(take(p.body_class));
  int* parent_d = reinterpret_cast<int*>(take(p.parent));
  int* order_d = reinterpret_cast<int*>(take(p.order));
  unsigned char* role_d = reinterpret_cast<unsigned char*>(take(p.role));
  int* bb_d = reinterpret_cast<int*>(take(p.branch_begin));
  int* bc_d = reinterpret_cast<int*>(take(p.branch_child));
  v_ = reinterpret_cast<Motion<S>*>(take(p.v));
  a_ = reinterpret_cast<Motion<S>*>(take(p.a));
  F_ = reinterpret_cast<Force<S>*>(take(p.F));
  offset_ = reinterpret_cast<Force<S>*>(take(p.offset));
  agg_ = take(p.agg);
  pre_ = take(p.pre);
  temp_ = take(p.temp);
  body_table_ = table_d, body_class_ = class_d, parent_ = parent_d, order_ = order_d, role_ = role_d;
  branch_begin_ = bb_d, branch_child_ = bc_d;

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
  upload(table_d, table.data(), table.size() * sizeof(Body<S>), "body table");
  upload(class_d, h.body_class.data(), h.body_class.size() * sizeof(int), "body classes");
  upload(parent_d, h.parent.data(), h.parent.size() * sizeof(int), "parent array");
  upload(order_d, h.order.data(), h.order.size() * sizeof(int), "level order");
  upload(role_d, h.role.data(), h.role.size(), "segment roles");
  upload(bb_d, h.branch_begin.data(), h.branch_begin.size() * sizeof(int), "branch offsets");
  upload(bc_d, h.branch_child.data(), h.branch_child.size() * sizeof(int), "branch children");
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
  Level<S> L{body_table_, body_class_, parent_, nullptr, nullptr, branch_begin_, branch_child_, 0, 0, nv_, in, tau,
             v_, a_, F_, a0_};
  auto at_level = [&](Index l) {
    L.order = order_ + level_begin_[l];
    L.role = role_ + level_begin_[l];
    L.n_level = static_cast<unsigned>(level_begin_[l + 1] - level_begin_[l]);
    L.count = L.n_level * static_cast<unsigned>(B);
    return make_runs(L.count);
  };
  auto* magg = static_cast<MotionAffine<S>*>(agg_);
  auto* mpre = static_cast<MotionAffine<S>*>(pre_);
  auto* fagg = static_cast<ForceAffine<S>*>(agg_);
  auto* fsuf = static_cast<ForceAffine<S>*>(pre_);
  auto blocks = [](const Runs& R) { return (R.runs + kRunBlock - 1) / kRunBlock; };
  cudaError_t err = cudaSuccess;
  const Index nl = levels();
  // forward, level by level: velocities, then accelerations (and the force offsets)
  for (Index l = 0; l < nl; ++l) {
    const Runs R = at_level(l);
    std::size_t bytes = temp_bytes_;
    velocity_runs<<<blocks(R), kRunBlock, 0, stream>>>(L, R, magg);
    if ((err = cudaGetLastError()) != cudaSuccess) return err;
    if ((err = scan_motion_runs<S>(temp_, bytes, magg, mpre, R.runs, stream)) != cudaSuccess) return err;
    velocity_walk<<<blocks(R), kRunBlock, 0, stream>>>(L, R, mpre, magg);
    if ((err = cudaGetLastError()) != cudaSuccess) return err;
    bytes = temp_bytes_;
    if ((err = scan_motion_runs<S>(temp_, bytes, magg, mpre, R.runs, stream)) != cudaSuccess) return err;
    if (nl == 1) acceleration_walk<S, true><<<blocks(R), kRunBlock, 0, stream>>>(L, R, mpre, offset_, fagg);
    else acceleration_walk<S, false><<<blocks(R), kRunBlock, 0, stream>>>(L, R, mpre, offset_, fagg);
    if ((err = cudaGetLastError()) != cudaSuccess) return err;
  }
  // backward, deepest level first: forces and torques. A level's force offsets
  // need its branch children's forces, which the deeper levels produce: with more
  // than one level they are made here.
  for (Index l = nl - 1; l >= 0; --l) {
    const Runs R = at_level(l);
    if (nl > 1) {
      force_runs<<<blocks(R), kRunBlock, 0, stream>>>(L, R, offset_, fagg);
      if ((err = cudaGetLastError()) != cudaSuccess) return err;
    }
    std::size_t bytes = temp_bytes_;
    if ((err = scan_force_runs<S>(temp_, bytes, fagg, fsuf, R.runs, stream)) != cudaSuccess) return err;
    force_walk<<<blocks(R), kRunBlock, 0, stream>>>(L, R, offset_, fsuf);
    if ((err = cudaGetLastError()) != cudaSuccess) return err;
  }
  return cudaSuccess;
}

template class IdScanPlan<float>;
template class IdScanPlan<double>;

}  // namespace cuda
}  // namespace scandyn
