// kernels/general_dynamics.cu: the general path on the GPU (scandyn/cuda/general_dynamics.hpp):
// aba_general_kernel, crba_general_kernel and kinematics_general_kernel, one thread
// per instance over the one-instance routines of scandyn/instance/general_instance.hpp
// and kinematics_instance.hpp; aba_levels_kernel, a warp per instance over a tree's
// levels (GeneralAba::Levels); and GeneralPlan (the device bodies, level schedule and
// scratch). Each thread-per-instance
// kernel is compiled twice: kScalars false (GeneralWorkOf of StridedArrays: the
// Instance and Structs layouts, by the plan's strides) and true (every scalar
// interleaved: Scalars).
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdlib>
#include <string>
#include <vector>

#include "scandyn/cuda/general_dynamics.hpp"
#include "scandyn/instance/kinematics_instance.hpp"
#include "staging.hpp"

namespace scandyn {
namespace cuda {

using detail::check;

namespace {

std::size_t align16(std::size_t n) { return (n + 15) / 16 * 16; }

// The scalars of instance b's column i < n of v into out.
template <class S, class Out>
__device__ void gather(const BatchView<const S>& v, long long b, Index n, const Out& out) {
  for (Index i = 0; i < n; ++i) out[i] = v.at(i, static_cast<Index>(b));
}

// Thread t's scratch and the instances it takes: t, t + slots, ... < B.
template <class S, bool kScalars>
__device__ auto general_work(const GeneralArgs<S>& g, long long t) {
  if constexpr (kScalars) return g.work_scalars(t);
  else return g.work_strided(t);
}
#define SCANDYN_GENERAL_INSTANCES(g, B)                                                   \
  const long long t = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;    \
  if (t >= (g).slots) return;                                                            \
  const auto w = general_work<S, kScalars>(g, t);                                        \
  const StridedArray<S> sc = (g).scalar_area(t);                                         \
  for (long long b = t; b < (B); b += (g).slots)

// Scratch scalars: q (nq), qd (nv), tau (nv), qdd (nv).
template <class S, bool kScalars>
__global__ void __launch_bounds__(kGeneralBlock)
    aba_general_kernel(const GeneralArgs<S> g, const FdBatchIn<S> in, const BatchView<S> qdd, int* failed_dof) {
  SCANDYN_GENERAL_INSTANCES(g, in.q.batch) {
    const StridedArray<S> q = sc;
    const StridedArray<S> qd = q + g.nq;
    const StridedArray<S> tau = qd + g.nv;
    const StridedArray<S> out = tau + g.nv;
    gather(in.q, b, g.nq, q);
    gather(in.qd, b, g.nv, qd);
    gather(in.tau, b, g.nv, tau);
    const Force<S>* fext = in.fext ? in.fext + b * g.nb : nullptr;
    const Index failed = aba_general(g.bodies, g.nb, g.a0, w, q, qd, tau, out, fext, static_cast<const S*>(nullptr));
    if (failed < 0)
      for (Index i = 0; i < g.nv; ++i) qdd.at(i, static_cast<Index>(b)) = out[i];
    failed_dof[b] = static_cast<int>(failed);
  }
}

// Threads per block of aba_levels_kernel (a warp per instance).
constexpr int kLevelsBlock = 128;

// One warp per instance: the lanes run a level's bodies through aba_general's
// per-body steps (general_instance.hpp), level after level, __syncwarp() between
// levels (a level reads only what the previous one wrote). Pass 2's shares reach a
// parent when its lane gathers them, children in decreasing index: the order in
// which the serial aba_general adds them. The scratch of warp slot t is contiguous
// (GeneralInterleave::Instance). Scratch scalars: q (nq), qd (nv), tau (nv), qdd (nv).
template <class S>
__global__ void __launch_bounds__(kLevelsBlock)
    aba_levels_kernel(const GeneralArgs<S> g, const LevelSchedule ls, const FdBatchIn<S> in, const BatchView<S> qdd,
                      int* failed_dof) {
  const long long t = (static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x) / 32;
  const int lane = static_cast<int>(threadIdx.x & 31);
  if (t >= g.slots) return;  // the whole warp (t is the warp's)
  const auto w = g.work_strided(t);
  const StridedArray<S> q = g.scalar_area(t);
  const StridedArray<S> qd = q + g.nq;
  const StridedArray<S> tau = qd + g.nv;
  const StridedArray<S> out = tau + g.nv;
  for (long long b = t; b < in.q.batch; b += g.slots) {
    const Index bi = static_cast<Index>(b);
    for (Index i = lane; i < g.nq; i += 32) q[i] = in.q.at(i, bi);
    for (Index i = lane; i < g.nv; i += 32) {
      qd[i] = in.qd.at(i, bi);
      tau[i] = in.tau.at(i, bi);
    }
    const Force<S>* fext = in.fext ? in.fext + b * g.nb : nullptr;
    __syncwarp();
    // pass 1, root to leaves
    for (Index l = 0; l < ls.levels; ++l) {
      for (int k = ls.level_begin[l] + lane; k < ls.level_begin[l + 1]; k += 32) {
        const Index i = ls.order[k], p = g.bodies[i].parent;
        aba_general_forward(g.bodies, i, p < 0 ? Motion<S>::zero() : Motion<S>(w.v[p]), w, q, qd, fext);
      }
      __syncwarp();
    }
    // pass 2, leaves to root: each body gathers its children's shares, then its joint terms
    int failed = -1;
    for (Index l = ls.levels - 1; l >= 0; --l) {
      for (int k = ls.level_begin[l] + lane; k < ls.level_begin[l + 1]; k += 32) {
        const Index i = ls.order[k];
        ABInertia<S> IA = w.IA[i];
        Force<S> pA = w.f[i];
        if (ls.child_begin[i] < ls.child_begin[i + 1]) {
          for (int c = ls.child_begin[i]; c < ls.child_begin[i + 1]; ++c) {
            const Index ci = ls.child[c];
            aba_general_to_parent(g.bodies, ci, ABInertia<S>(w.IA[ci]), Force<S>(w.f[ci]), w, IA, pA);
          }
          w.IA[i] = IA;  // final: the parent's lane reads it at the next level
          w.f[i] = pA;
        }
        const Index f = aba_general_joint(g.bodies, i, IA, pA, w, tau, static_cast<const S*>(nullptr));
        if (f > failed) failed = static_cast<int>(f);
      }
      __syncwarp();
    }
    // the serial ABA stops at its first failed pivot, the highest DoF that fails (a
    // failure's NaN reaches only lower DoFs, its ancestors)
    failed = __reduce_max_sync(0xffffffffu, failed);
    if (failed < 0) {
      // pass 3, root to leaves
      for (Index l = 0; l < ls.levels; ++l) {
        for (int k = ls.level_begin[l] + lane; k < ls.level_begin[l + 1]; k += 32) {
          const Index i = ls.order[k], p = g.bodies[i].parent;
          aba_general_acceleration(g.bodies, i, p < 0 ? g.a0 : Motion<S>(w.a[p]), w, out);
        }
        __syncwarp();
      }
      for (Index i = lane; i < g.nv; i += 32) qdd.at(i, bi) = out[i];
    }
    if (lane == 0) failed_dof[b] = failed;
    __syncwarp();
  }
}

// Entry (r, c) of instance b's M in an (nv nv x B) view.
template <class S>
struct MassEntries {
  BatchView<S> M;
  Index nv, b;
  SCANDYN_HD S& operator()(Index r, Index c) const { return M.at(r * nv + c, b); }
};

// Scratch scalars: q (nq). M written in place: entry r nv + c of instance b.
template <class S, bool kScalars>
__global__ void __launch_bounds__(kGeneralBlock)
    crba_general_kernel(const GeneralArgs<S> g, const BatchView<const S> q_in, const BatchView<S> M) {
  SCANDYN_GENERAL_INSTANCES(g, q_in.batch) {
    const StridedArray<S> q = sc;
    gather(q_in, b, g.nq, q);
    const Index nv = g.nv, bi = static_cast<Index>(b);
    crba_general(g.bodies, g.nb, nv, w, q, MassEntries<S>{M, nv, bi});
  }
}

// Scratch scalars: q (nq); the body placements X0 in GeneralWorkOf::Xup (nb).
template <class S, bool kScalars>
__global__ void __launch_bounds__(kGeneralBlock)
    kinematics_general_kernel(const GeneralArgs<S> g, const FramePlacement<S>* __restrict__ frames, Index F,
                              PoseFormat format, FrameReference reference, const BatchView<const S> q_in,
                              const BatchView<S> poses, const BatchView<S> J) {
  SCANDYN_GENERAL_INSTANCES(g, q_in.batch) {
    const StridedArray<S> q = sc;
    gather(q_in, b, g.nq, q);
    const Strided<S> pb{poses.data ? poses.data + b * poses.batch_stride : nullptr, poses.dof_stride};
    const Strided<S> Jb{J.data ? J.data + b * J.batch_stride : nullptr, J.dof_stride};
    kinematics_instance_at(g.bodies, g.nb, g.nv, frames, F, format, reference, q, w.Xup, pb, Jb);
  }
}

#undef SCANDYN_GENERAL_INSTANCES

}  // namespace

const char* interleave_name(GeneralInterleave i) {
  switch (i) {
    case GeneralInterleave::Instance: return "instance";
    case GeneralInterleave::Structs: return "structs";
    case GeneralInterleave::Scalars: return "scalars";
  }
  return "?";
}

GeneralInterleave general_interleave_from_env() {
  const char* v = std::getenv("SCANDYN_GENERAL_INTERLEAVE");
  if (!v || !*v) return kGeneralInterleave;
  for (GeneralInterleave i : {GeneralInterleave::Instance, GeneralInterleave::Structs, GeneralInterleave::Scalars})
    if (std::string(v) == interleave_name(i)) return i;
  throw BackendError(std::string("SCANDYN_GENERAL_INTERLEAVE='") + v +
                     "': expected instance, structs or scalars (the general path's scratch layout)");
}

const char* general_aba_name(GeneralAba a) { return a == GeneralAba::Levels ? "levels" : "thread"; }

namespace {
// Body depths (roots 0; bodies in DoF order, parents first).
template <class S>
std::vector<int> body_depths(const ModelTpl<S>& model) {
  std::vector<int> depth(static_cast<std::size_t>(model.nbodies()), 0);
  for (Index i = 0; i < model.nbodies(); ++i) {
    const Index p = model.bodies[static_cast<std::size_t>(i)].parent;
    depth[static_cast<std::size_t>(i)] = p < 0 ? 0 : depth[static_cast<std::size_t>(p)] + 1;
  }
  return depth;
}
}  // namespace

GeneralAba general_aba_from_env() {
  const char* v = std::getenv("SCANDYN_GENERAL_ABA");
  if (!v || !*v) return GeneralAba::Thread;
  for (GeneralAba a : {GeneralAba::Thread, GeneralAba::Levels})
    if (std::string(v) == general_aba_name(a)) return a;
  throw BackendError(std::string("SCANDYN_GENERAL_ABA='") + v +
                     "': expected thread or levels (how the general path's ABA runs an instance)");
}

namespace {
// The bytes of every area's share per thread, in GeneralLayout's order.
template <class S>
void area_bytes(Index nb, Index nv, Index scalars, std::size_t extra_bytes, std::size_t (&out)[13]) {
  const std::size_t B = static_cast<std::size_t>(nb), V = static_cast<std::size_t>(nv);
  const std::size_t b[13] = {B * sizeof(Transform<S>), B * sizeof(Motion<S>),    B * sizeof(Motion<S>),
                             B * sizeof(Motion<S>),    B * sizeof(Force<S>),     B * sizeof(Inertia<S>),
                             B * sizeof(ABInertia<S>), V * sizeof(Force<S>),     V * sizeof(S),
                             V * sizeof(S),            V * kMaxJointDofs * sizeof(S),
                             static_cast<std::size_t>(scalars) * sizeof(S), align16(extra_bytes)};
  for (int k = 0; k < 13; ++k) out[k] = b[k];
}
template <class S>
std::size_t* area_offsets(GeneralLayout<S>& l, int k) {
  std::size_t* const o[13] = {&l.Xup, &l.v, &l.a, &l.c, &l.f, &l.Ic, &l.IA, &l.U, &l.D, &l.u, &l.L, &l.scalars, &l.extra};
  return o[k];
}
}  // namespace

template <class S>
GeneralLayout<S> GeneralLayout<S>::make(Index nb, Index nv, Index scalars, std::size_t extra_bytes) {
  GeneralLayout<S> l{};
  l.nb = nb, l.nv = nv, l.nscalars = scalars, l.extra_bytes = align16(extra_bytes);
  std::size_t b[13];
  area_bytes<S>(nb, nv, scalars, extra_bytes, b);
  for (std::size_t x : b) l.bytes += align16(x);
  l.place(1);
  return l;
}

template <class S>
void GeneralLayout<S>::place(long long slots) {
  std::size_t b[13];
  area_bytes<S>(nb, nv, nscalars, extra_bytes, b);
  std::size_t at = 0;
  for (int k = 0; k < 13; ++k) {
    *area_offsets(*this, k) = at;
    at += align16(b[k] * static_cast<std::size_t>(slots));
  }
  end = at;
}

template <class S>
GeneralPlan<S>::GeneralPlan(const ModelTpl<S>& model, Index max_batch, std::size_t extra_bytes, Index extra_scalars,
                            std::size_t budget_bytes, GeneralInterleave interleave, GeneralAba aba)
    : aba_(aba) {
  const Index nb = model.nbodies(), nv = model.nv(), nq = model.nq();
  GeneralArgs<S>& g = args_;
  g.nb = nb, g.nv = nv, g.nq = nq;
  g.a0 = base_acceleration(model.gravity);
  // q, qd, tau and the result (the largest need: aba's), and the caller's
  g.layout = GeneralLayout<S>::make(nb, nv, nq + 3 * nv + extra_scalars, extra_bytes);
  if (budget_bytes == 0) {
    std::size_t free_bytes = 0, total_bytes = 0;
    if (cudaMemGetInfo(&free_bytes, &total_bytes) != cudaSuccess) free_bytes = 0;
    cudaGetLastError();  // a failed query leaves the minimum budget, and no sticky error
    budget_bytes = std::min(kMaxBudgetBytes, std::max(kMinBudgetBytes, free_bytes / 8));
  }
  g.slots = std::max<long long>(1, std::min<long long>(std::max<Index>(max_batch, 1),
                                                       static_cast<long long>(budget_bytes / g.layout.bytes)));
  g.layout.place(g.slots);
  g.interleave = aba == GeneralAba::Levels ? GeneralInterleave::Instance : interleave;
  // the level schedule (Levels): order, level_begin, child_begin, child
  std::vector<int> order, level_begin, child_begin, child;
  if (aba == GeneralAba::Levels) {
    const std::vector<int> depth = body_depths(model);
    const int levels = nb > 0 ? *std::max_element(depth.begin(), depth.end()) + 1 : 0;
    level_begin.assign(static_cast<std::size_t>(levels) + 1, 0);
    for (int d : depth) ++level_begin[static_cast<std::size_t>(d) + 1];
    for (int l = 0; l < levels; ++l) level_begin[l + 1] += level_begin[l];
    order.resize(static_cast<std::size_t>(nb));
    std::vector<int> at(level_begin.begin(), level_begin.end() - 1);
    for (Index i = 0; i < nb; ++i) order[static_cast<std::size_t>(at[depth[static_cast<std::size_t>(i)]]++)] = int(i);
    child_begin.assign(static_cast<std::size_t>(nb) + 1, 0);
    for (Index i = 0; i < nb; ++i)
      if (model.bodies[static_cast<std::size_t>(i)].parent >= 0)
        ++child_begin[static_cast<std::size_t>(model.bodies[static_cast<std::size_t>(i)].parent) + 1];
    for (Index i = 0; i < nb; ++i) child_begin[i + 1] += child_begin[i];
    child.resize(static_cast<std::size_t>(child_begin.back()));
    std::vector<int> fill(child_begin.begin(), child_begin.end() - 1);
    for (Index i = nb - 1; i >= 0; --i) {
      const Index p = model.bodies[static_cast<std::size_t>(i)].parent;
      if (p >= 0) child[static_cast<std::size_t>(fill[static_cast<std::size_t>(p)]++)] = int(i);
    }
    levels_.levels = levels;
  }
  const std::size_t ints = order.size() + level_begin.size() + child_begin.size() + child.size();
  const std::size_t body_bytes = align16(static_cast<std::size_t>(nb) * sizeof(Body<S>));
  const std::size_t schedule_bytes = align16(ints * sizeof(int));
  bytes_ = body_bytes + schedule_bytes + g.layout.end;
  memory_ = detail::device_malloc(bytes_, [&](std::size_t free_bytes, std::size_t) {
    return "backend 'cuda': the general path's scratch for model '" + model.name + "' (" + std::to_string(g.slots) +
           " instances at a time, " + std::to_string(g.layout.bytes) + " bytes each) needs " + std::to_string(bytes_) +
           " bytes of device memory; " + std::to_string(free_bytes) + " are free";
  });
  g.bodies = static_cast<const Body<S>*>(memory_);
  g.work = static_cast<char*>(memory_) + body_bytes + schedule_bytes;
  check(cudaMemcpy(memory_, model.bodies.data(), static_cast<std::size_t>(nb) * sizeof(Body<S>),
                   cudaMemcpyHostToDevice),
        "copying the bodies to the device");
  if (ints > 0) {
    std::vector<int> all;
    all.reserve(ints);
    for (const std::vector<int>* v : {&order, &level_begin, &child_begin, &child}) all.insert(all.end(), v->begin(), v->end());
    int* const d = reinterpret_cast<int*>(static_cast<char*>(memory_) + body_bytes);
    check(cudaMemcpy(d, all.data(), ints * sizeof(int), cudaMemcpyHostToDevice), "copying the level schedule to the device");
    levels_.order = d;
    levels_.level_begin = d + order.size();
    levels_.child_begin = levels_.level_begin + level_begin.size();
    levels_.child = levels_.child_begin + child_begin.size();
  }
}

template <class S>
GeneralPlan<S>::~GeneralPlan() {
  if (memory_) cudaFree(memory_);
}

template <class S>
cudaError_t GeneralPlan<S>::launch_aba(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed_dof,
                                       cudaStream_t stream) const {
  const Index B = in.q.batch;
  if (B < 0 || in.qd.batch != B || in.tau.batch != B || qdd.batch != B || !failed_dof) return cudaErrorInvalidValue;
  if (B == 0) return cudaSuccess;
  if (aba_ == GeneralAba::Levels) {
    const long long warps = std::min<long long>(args_.slots, B);
    const long long blocks = (warps * 32 + kLevelsBlock - 1) / kLevelsBlock;
    aba_levels_kernel<S><<<static_cast<unsigned>(blocks), kLevelsBlock, 0, stream>>>(args_, levels_, in, qdd,
                                                                                    failed_dof);
  } else if (args_.interleave == GeneralInterleave::Scalars)
    aba_general_kernel<S, true><<<args_.blocks(B), kGeneralBlock, 0, stream>>>(args_, in, qdd, failed_dof);
  else
    aba_general_kernel<S, false><<<args_.blocks(B), kGeneralBlock, 0, stream>>>(args_, in, qdd, failed_dof);
  return cudaGetLastError();
}

template <class S>
cudaError_t GeneralPlan<S>::launch_crba(const BatchView<const S>& q, const BatchView<S>& M, cudaStream_t stream) const {
  const Index B = q.batch;
  if (B < 0 || M.batch != B) return cudaErrorInvalidValue;
  if (B == 0) return cudaSuccess;
  if (args_.interleave == GeneralInterleave::Scalars)
    crba_general_kernel<S, true><<<args_.blocks(B), kGeneralBlock, 0, stream>>>(args_, q, M);
  else
    crba_general_kernel<S, false><<<args_.blocks(B), kGeneralBlock, 0, stream>>>(args_, q, M);
  return cudaGetLastError();
}

template <class S>
cudaError_t GeneralPlan<S>::launch_kinematics(const FramePlacement<S>* frames, Index F, PoseFormat format,
                                              FrameReference reference, const BatchView<const S>& q,
                                              const BatchView<S>& poses, const BatchView<S>& J,
                                              cudaStream_t stream) const {
  const Index B = q.batch;
  if (B < 0 || (poses.data && poses.batch != B) || (J.data && J.batch != B)) return cudaErrorInvalidValue;
  if (B == 0 || F == 0 || (!poses.data && !J.data)) return cudaSuccess;
  if (!frames) return cudaErrorInvalidValue;
  if (args_.interleave == GeneralInterleave::Scalars)
    kinematics_general_kernel<S, true><<<args_.blocks(B), kGeneralBlock, 0, stream>>>(args_, frames, F, format,
                                                                                       reference, q, poses, J);
  else
    kinematics_general_kernel<S, false><<<args_.blocks(B), kGeneralBlock, 0, stream>>>(args_, frames, F, format,
                                                                                        reference, q, poses, J);
  return cudaGetLastError();
}

template struct GeneralLayout<float>;
template struct GeneralLayout<double>;
template class GeneralPlan<float>;
template class GeneralPlan<double>;

}  // namespace cuda
}  // namespace scandyn
