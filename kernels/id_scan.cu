// kernels/id_scan.cu: inverse dynamics as device-wide scans across links
// (scandyn/cuda/id_scan.hpp). The scan elements, their operators and the per-body
// steps are the host/device ones of scandyn/scan/elements.hpp and
// scandyn/algorithm/steps.hpp; this file only says where each element's inputs
// come from and where each result goes.
#include <cub/device/device_scan.cuh>
#include <thrust/iterator/counting_iterator.h>
#include <thrust/iterator/tabulate_output_iterator.h>
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

// ---- velocities: (Xup_i, S qd_i); heads (0, Xup_i v_parent + S qd_i) ----------------
template <class S>
struct VelocityElement {
  Level<S> L;
  __device__ MotionAffine<S> operator()(unsigned e) const {
    const auto s = L.site(e);
    const Body<S>& bd = L.body(s.i);
    const Transform<S> X = joint_transform(bd, L.in.q.at(s.i, s.b));
    const Motion<S> sq = joint_motion(bd, L.in.qd.at(s.i, s.b));
    if (!(s.role & kSegmentHead)) return {X, sq};
    const int p = L.parent[s.i];
    const Motion<S> vp = p < 0 ? Motion<S>::zero() : L.v[L.slot(s.b, p)];
    return {zero_transform<S>(), X.apply(vp) + sq};
  }
};
template <class S>
struct VelocityStore {
  Level<S> L;
  __device__ void operator()(unsigned e, const MotionAffine<S>& x) const {
    const auto s = L.site(e);
    L.v[L.slot(s.b, s.i)] = x.b;
  }
};

// ---- accelerations: (Xup_i, S qdd + v x S qd); heads fold in Xup_i a_parent ---------
template <class S>
struct AccelerationElement {
  Level<S> L;
  __device__ MotionAffine<S> operator()(unsigned e) const {
    const auto s = L.site(e);
    const Body<S>& bd = L.body(s.i);
    const Transform<S> X = joint_transform(bd, L.in.q.at(s.i, s.b));
    const Motion<S> v = L.v[L.slot(s.b, s.i)];
    const S qd = L.in.qd.at(s.i, s.b);
    const Motion<S> c = add_joint_motion(bd, cross_joint_motion(bd, v, qd), L.in.qdd.at(s.i, s.b));
    if (!(s.role & kSegmentHead)) return {X, c};
    const int p = L.parent[s.i];
    const Motion<S> ap = p < 0 ? L.a0 : L.a[L.slot(s.b, p)];
    return {zero_transform<S>(), X.apply(ap) + c};
  }
};
template <class S>
struct AccelerationStore {
  Level<S> L;
  __device__ void operator()(unsigned e, const MotionAffine<S>& x) const {
    const auto s = L.site(e);
    L.a[L.slot(s.b, s.i)] = x.b;
  }
};

// ---- forces, scanned from the level's last element back to its first ----------------
// Element of body i: G -> B + Y^T G with G = F_{i+1}, Y = Xup_{i+1} (0 at a segment's
// tail) and B = f_i plus the forces of the branch children (heads of higher levels).
template <class S>
struct ForceElement {
  Level<S> L;
  __device__ ForceAffine<S> operator()(unsigned r) const {
    const auto s = L.site(L.count - 1 - r);
    const Body<S>& bd = L.body(s.i);
    const std::size_t slot = L.slot(s.b, s.i);
    const Motion<S> v = L.v[slot], a = L.a[slot];
    Force<S> f = bd.I * a + cross(v, bd.I * v);
    if (L.in.fext) f -= L.in.fext[slot];
    for (int k = L.branch_begin[s.i]; k < L.branch_begin[s.i + 1]; ++k) {
      const int c = L.branch_child[k];
      const Transform<S> Xc = joint_transform(L.body(c), L.in.q.at(c, s.b));
      f += Xc.apply_transpose(L.F[L.slot(s.b, c)]);
    }
    if (s.role & kSegmentTail) return {zero_transform<S>(), f};
    return {joint_transform(L.body(s.i + 1), L.in.q.at(s.i + 1, s.b)), f};
  }
};
template <class S>
struct ForceStore {
  Level<S> L;
  __device__ void operator()(unsigned r, const ForceAffine<S>& x) const {
    const auto s = L.site(L.count - 1 - r);
    if (s.role & kSegmentHead) L.F[L.slot(s.b, s.i)] = x.B;
    L.tau.at(s.i, s.b) = joint_project(L.body(s.i), x.B);
  }
};
// CUB's operator sees (prefix so far, next element): here (deeper run d, outer body o).
struct ComposeForceSuffix {
  template <class S>
  __host__ __device__ ForceAffine<S> operator()(const ForceAffine<S>& d, const ForceAffine<S>& o) const {
    return compose(o, d);
  }
};

template <template <class> class Element, template <class> class Store, class Op, class S>
cudaError_t scan_level(void* temp, std::size_t& temp_bytes, const Level<S>& L, Op op, cudaStream_t stream) {
  auto in = thrust::make_transform_iterator(thrust::counting_iterator<unsigned>(0u), Element<S>{L});
  auto out = thrust::make_tabulate_output_iterator(Store<S>{L});
  return cub::DeviceScan::InclusiveScan(temp, temp_bytes, in, out, op, static_cast<int>(L.count), stream);
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

// CUB's temporary storage for the largest level scan of any pass.
template <class S>
std::size_t cub_temp_bytes(std::size_t count) {
  if (count == 0) return 0;
  Level<S> L{};
  L.n_level = 1;
  L.count = static_cast<unsigned>(count);
  std::size_t a = 0, b = 0, c = 0;
  scan_level<VelocityElement, VelocityStore>(nullptr, a, L, ComposeMotionAffine{}, nullptr);
  scan_level<AccelerationElement, AccelerationStore>(nullptr, b, L, ComposeMotionAffine{}, nullptr);
  scan_level<ForceElement, ForceStore>(nullptr, c, L, ComposeForceSuffix{}, nullptr);
  return std::max({a, b, c});
}

// Byte sizes of the parts of one allocation, in order.
template <class S>
struct Parts {
  std::size_t table, body_class, parent, order, role, branch_begin, branch_child, v, a, F, temp;
  std::size_t total() const {
    return table + body_class + parent + order + role + branch_begin + branch_child + v + a + F + temp;
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
  p.temp = aligned(cub_temp_bytes<S>(B * static_cast<std::size_t>(h.max_level)));
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
  };
  const Index nl = levels();
  for (Index l = 0; l < nl; ++l) {
    at_level(l);
    std::size_t bytes = temp_bytes_;
    cudaError_t err = scan_level<VelocityElement, VelocityStore>(temp_, bytes, L, ComposeMotionAffine{}, stream);
    if (err != cudaSuccess) return err;
    bytes = temp_bytes_;
    err = scan_level<AccelerationElement, AccelerationStore>(temp_, bytes, L, ComposeMotionAffine{}, stream);
    if (err != cudaSuccess) return err;
  }
  for (Index l = nl - 1; l >= 0; --l) {
    at_level(l);
    std::size_t bytes = temp_bytes_;
    const cudaError_t err = scan_level<ForceElement, ForceStore>(temp_, bytes, L, ComposeForceSuffix{}, stream);
    if (err != cudaSuccess) return err;
  }
  return cudaSuccess;
}

template class IdScanPlan<float>;
template class IdScanPlan<double>;

}  // namespace cuda
}  // namespace scandyn
