// kernels/general_dynamics.cu: the general path on the GPU (scandyn/cuda/general_dynamics.hpp):
// aba_general_kernel, crba_general_kernel and kinematics_general_kernel, one thread
// per instance over the one-instance routines of scandyn/instance/general_instance.hpp
// and kinematics_instance.hpp, and GeneralPlan (the device bodies and scratch). Each
// kernel is compiled twice: kScalars false (GeneralWorkOf of StridedArrays: the
// Instance and Structs layouts, by the plan's strides) and true (every scalar
// interleaved: Scalars).
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdlib>
#include <string>

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
                            std::size_t budget_bytes, GeneralInterleave interleave) {
  const Index nb = model.nbodies(), nv = model.nv(), nq = model.nq();
  GeneralArgs<S>& g = args_;
  g.nb = nb, g.nv = nv, g.nq = nq;
  g.a0 = base_acceleration(model.gravity);
  // q, qd, tau and the result (the largest need: aba's), and the caller's
  g.layout = GeneralLayout<S>::make(nb, nv, nq + 3 * nv + extra_scalars, extra_bytes);
  g.slots = std::max<long long>(1, std::min<long long>(std::max<Index>(max_batch, 1),
                                                       static_cast<long long>(budget_bytes / g.layout.bytes)));
  g.layout.place(g.slots);
  g.interleave = interleave;
  const std::size_t body_bytes = align16(static_cast<std::size_t>(nb) * sizeof(Body<S>));
  bytes_ = body_bytes + g.layout.end;
  memory_ = detail::device_malloc(bytes_, [&](std::size_t free_bytes, std::size_t) {
    return "backend 'cuda': the general path's scratch for model '" + model.name + "' (" + std::to_string(g.slots) +
           " instances at a time, " + std::to_string(g.layout.bytes) + " bytes each) needs " + std::to_string(bytes_) +
           " bytes of device memory; " + std::to_string(free_bytes) + " are free";
  });
  g.bodies = static_cast<const Body<S>*>(memory_);
  g.work = static_cast<char*>(memory_) + body_bytes;
  check(cudaMemcpy(memory_, model.bodies.data(), static_cast<std::size_t>(nb) * sizeof(Body<S>),
                   cudaMemcpyHostToDevice),
        "copying the bodies to the device");
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
  if (args_.interleave == GeneralInterleave::Scalars)
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
