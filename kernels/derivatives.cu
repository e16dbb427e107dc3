// kernels/derivatives.cu: the batched first-order derivatives of inverse and forward
// dynamics, one thread per instance (scandyn/cuda/derivatives.hpp): the per-instance
// functions of scandyn/instance/dynamics_derivatives.hpp (the serial reference's),
// after aba_instance for the forward dynamics' qdd.
//
// What runs (launch_id_derivatives, launch_fd_derivatives):
//   inverse dynamics: unbranched chains of up to kPackedLtlCapacity (8) DoF
//     id_derivatives_lean_kernel (the lean chain recursion); every other model
//     id_derivatives_kernel (rnea_derivatives_instance);
//   forward dynamics: chains of up to 8 DoF fd_aba_kernel, then
//     fd_derivatives_at_kernel<kLean> (the lean recursion, then packed_fd_solve with L
//     in registers); other trees of up to 8 DoF the same two kernels with
//     rnea_derivatives_instance (the packed path); beyond 8 DoF fd_derivatives_kernel
//     (ABA, derivatives, the factor and solves by the tree walks in the output blocks).
// Two environment switches, read at every launch, keep the replaced kernels for A/B
// (bench, tests): SCANDYN_DFD_KERNEL=packed (the packed path on chains too) or tree
// (fd_derivatives_kernel at every capacity), SCANDYN_DID_KERNEL=recursion
// (id_derivatives_kernel on chains too). Measured on an H200 (iiwa, float, 10^6
// instances, device-resident): dfd lean 3.93e8/s, packed 3.37e8, tree 1.62e8; did lean
// 9.94e8/s, recursion 6.86e8.
//
// Models with multi-DoF joints (a floating base, spherical joints) of up to
// kMaxThreadDofs DoF: id_derivatives_general_kernel (rnea_derivatives_general_instance)
// and fd_derivatives_general_kernel (aba_general, then fd_derivatives_general_instance),
// one thread per instance over GeneralDerivativeParams (launch_id_derivatives /
// launch_fd_derivatives of a GeneralDerivativeModel). The functions are the serial
// reference's (scandyn/algorithm/derivatives.cpp: aba, then the same two), on
// per-thread copies of the instance's q, qd, qdd / tau and per-thread scratch.
#include <cuda_runtime.h>

#include <atomic>
#include <cstdlib>
#include <cstring>
#include <string>
#include <type_traits>

#include "scandyn/cuda/derivatives.hpp"
#include "scandyn/cuda/derivatives_general.hpp"
#include "scandyn/instance/aba_instance.hpp"
#include "scandyn/instance/dof_column.hpp"
#include "scandyn/instance/dynamics_derivatives.hpp"
#include "staging.hpp"

namespace scandyn {
namespace cuda {

using detail::check;
using detail::copy;
using detail::plan;
using detail::Staging;

// ---- kernels and launches ----------------------------------------------------------

// One thread per instance b < B: dtau/dq, dtau/dqd and M of instance b.
template <class S, int C>
__global__ void __launch_bounds__(kDerivativesBlock)
    id_derivatives_kernel(const __grid_constant__ ThreadModelParams<S, C> model, const IdBatchIn<S> in,
                          const IdDerivativesOut<S> out) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= in.q.batch) return;
  const Index nv = model.nv;
  DerivativeBody<S> work[C];  // per-thread local memory
  rnea_derivatives_instance(model.body, nv, model.a0, instance_column(in.q, b), instance_column(in.qd, b),
                            instance_column(in.qdd, b), in.fext ? in.fext + b * nv : nullptr, work,
                            instance_matrix(out.dtau_dq, b, nv), instance_matrix(out.dtau_dqd, b, nv),
                            instance_matrix(out.M, b, nv), nullptr);
}

// ---- the lean chain recursion (the default on chains of up to 8 DoF) ----------------
// rnea_derivatives_instance for an unbranched chain (body i's parent i - 1) of at most
// C DoF, with 24 scalars of per-thread scratch per body instead of DerivativeBody's 72
// (the slots in local memory: 768 B per thread in float at C = 8 against
// DerivativeBody's 2304). The same formulas, evaluated in three passes:
//   1. forward: X_i, v_i, a_i (world frame) running in registers, stored in slot i;
//   2. backward: from slot j (and slot j - 1's v, a) body j's J, dV, dA, its own Ic,
//      F, B added to the running composites (registers), then psi_j = Ic_j S_j,
//      rho_j = Bc_j^T S_j, Phi_j and Psi_j replace slot j's contents;
//   3. forward again: X_i, v_i, a_i recomputed running (the same operations as pass
//      1), J_i, dV_i, dA_i, and for every j >= i the entries (j, i) and (i, j) from
//      slot j, each output entry written once.
// The composites are summed in the serial order (own body first, then the child's
// composite), every entry is the same dot products as rnea_derivatives_instance's.
template <class S>
struct LeanKinematics {
  Transform<S> X;
  Motion<S> v, a;
};
template <class S>
struct LeanCoupling {
  Force<S> psi, rho, Phi, Psi;
};
template <class S>
union LeanSlot {
  LeanKinematics<S> k;
  LeanCoupling<S> c;
  __device__ LeanSlot() {}
};

// Body i's world-frame kinematics from its parent's (i == 0: the base, at rest with
// acceleration a0), as derivative_forward_step.
template <class S>
__device__ __forceinline__ void lean_kinematics(const Body<S>& b, S q, S qd, S qdd, bool root,
                                                const LeanKinematics<S>& parent, const Motion<S>& a0,
                                                LeanKinematics<S>& o, Motion<S>& J) {
  const Transform<S> Xup = joint_transform(b, q);
  o.X = root ? Xup : Xup * parent.X;
  const Motion<S> vp = root ? Motion<S>::zero() : parent.v;
  const Motion<S> ap = root ? a0 : parent.a;
  J = o.X.apply_inverse(joint_motion(b, S(1)));
  o.v = vp + qd * J;
  o.a = ap + qdd * J + qd * cross(o.v, J);
}

template <class S, int C, class V, class Mat>
__device__ __forceinline__ void lean_chain_rnea_derivatives(const Body<S>* body, Index nv, const Motion<S>& a0, V q,
                                                            V qd, V qdd, const Force<S>* fext, Mat dtau_dq,
                                                            Mat dtau_dqd, Mat M) {
  LeanSlot<S> slot[C];
  {  // 1. forward
    LeanKinematics<S> k;
#pragma unroll
    for (int i = 0; i < nv; ++i) {
      if (i < nv) {
        Motion<S> J;
        LeanKinematics<S> o;
        lean_kinematics(body[i], S(q[i]), S(qd[i]), S(qdd[i]), i == 0, k, a0, o, J);
        k = o;
        slot[i].k = o;
      }
    }
  }
  {  // 2. backward
    Force<S> Fc;
    Inertia<S> Ic;
    VelocityDerivative<S> Bc;
#pragma unroll
    for (int j = nv - 1; j >= 0; --j) {
      if (j < nv) {
        const LeanKinematics<S> w = slot[j].k;
        const Motion<S> vp = j == 0 ? Motion<S>::zero() : slot[j > 0 ? j - 1 : 0].k.v;
        const Motion<S> ap = j == 0 ? a0 : slot[j > 0 ? j - 1 : 0].k.a;
        const Body<S>& b = body[j];
        const Motion<S> J = w.X.apply_inverse(joint_motion(b, S(1)));
        const Motion<S> dV = cross(vp, J);
        const Motion<S> dA = cross(ap, J) + cross(vp, dV);
        const Inertia<S> Io = b.I.transform_transpose(w.X);
        Force<S> Fo = Io * w.a + cross(w.v, Io * w.v);
        if (fext) Fo -= w.X.apply_transpose(fext[j]);
        const VelocityDerivative<S> Bo = VelocityDerivative<S>::of(Io, w.v);
        if (j == nv - 1) {
          Fc = Fo;
          Ic = Io;
          Bc = Bo;
        } else {  // the serial order: work[p] (own) += work[j] (the child's composite)
          Force<S> F2 = Fo;
          F2 += Fc;
          Inertia<S> I2 = Io;
          I2 += Ic;
          VelocityDerivative<S> B2 = Bo;
          B2 += Bc;
          Fc = F2;
          Ic = I2;
          Bc = B2;
        }
        LeanCoupling<S> c;
        c.psi = Ic * J;
        c.rho = Bc.apply_transpose(J);
        c.Phi = cross(J, Fc) + Ic * dA + Bc.apply(dV);
        c.Psi = Ic * (S(2) * dV) + Bc.apply(J);
        slot[j].c = c;
      }
    }
  }
  {  // 3. forward again: the entries
    LeanKinematics<S> k;
#pragma unroll
    for (int i = 0; i < nv; ++i) {
      if (i < nv) {
        const Motion<S> vp = i == 0 ? Motion<S>::zero() : k.v;
        const Motion<S> ap = i == 0 ? a0 : k.a;
        Motion<S> J;
        LeanKinematics<S> o;
        lean_kinematics(body[i], S(q[i]), S(qd[i]), S(qdd[i]), i == 0, k, a0, o, J);
        k = o;
        const Motion<S> dV = cross(vp, J);
        const Motion<S> dA = cross(ap, J) + cross(vp, dV);
#pragma unroll
        for (int j = i; j < nv; ++j) {
          if (j < nv) {
            const LeanCoupling<S> c = slot[j].c;
            dtau_dq(j, i) = dot(dA, c.psi) + dot(dV, c.rho);
            dtau_dqd(j, i) = S(2) * dot(dV, c.psi) + dot(J, c.rho);
            const S Mji = dot(J, c.psi);
            M(j, i) = Mji;
            if (i != j) {
              dtau_dq(i, j) = dot(J, c.Phi);
              dtau_dqd(i, j) = dot(J, c.Psi);
              M(i, j) = Mji;
            }
          }
        }
      }
    }
  }
}

// Whether a model's bodies form an unbranched chain (the lean kernels' models).
template <class Params>
bool is_chain(const Params& p) {
  for (Index i = 0; i < p.nv; ++i)
    if (p.body[i].parent != i - 1) return false;
  return true;
}

// Blocks per SM of the lean kernels and fd_derivatives_at_kernel (__launch_bounds__'
// minimum): float 10 (fd_derivatives_at_kernel: at most 102 registers, 96 at capacity
// 8, no spills, 640 threads per SM instead of 512 at its natural 114); double 1
// (held to 102 it spills ~1 KB per thread).
template <class S>
constexpr int at_min_blocks() {
  return sizeof(S) == 4 ? 10 : 1;
}

// id_derivatives_kernel by the lean chain recursion (chains of up to kPackedLtlCapacity DoF).
template <class S, int C>
__global__ void __launch_bounds__(kDerivativesBlock, at_min_blocks<S>())
    id_derivatives_lean_kernel(const __grid_constant__ ThreadModelParams<S, C> model, const IdBatchIn<S> in,
                               const IdDerivativesOut<S> out) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= in.q.batch) return;
  const Index nv = model.nv;
  lean_chain_rnea_derivatives<S, C>(model.body, nv, model.a0, instance_column(in.q, b), instance_column(in.qd, b),
                                    instance_column(in.qdd, b), in.fext ? in.fext + b * nv : nullptr,
                                    instance_matrix(out.dtau_dq, b, nv), instance_matrix(out.dtau_dqd, b, nv),
                                    instance_matrix(out.M, b, nv));
}

namespace {

// Whether the environment variable name is set to value (read at every launch, so
// that a test may switch it; bench A/B).
bool env_is(const char* name, const char* value) {
  const char* e = std::getenv(name);
  return e && std::strcmp(e, value) == 0;
}

// The derivative kernels keep their DerivativeBody arrays in local memory, cached in
// L1, and use no shared memory: ask for the largest L1 (carveout 0% shared memory),
// once per kernel and device. SCANDYN_DFD_CARVEOUT=default leaves the driver's choice
// (bench A/B).
bool carveout_wanted() {
  static const bool wanted = [] {
    const char* e = std::getenv("SCANDYN_DFD_CARVEOUT");
    return !(e && std::string(e) == "default");
  }();
  return wanted;
}

template <auto Kernel>
void prefer_l1() {
  static std::atomic<unsigned long long> devices{0};  // bit d: set on device d
  if (!carveout_wanted()) return;
  int d = 0;
  if (cudaGetDevice(&d) != cudaSuccess || d < 0 || d >= 64) return;
  const unsigned long long bit = 1ull << d;
  if (devices.load(std::memory_order_relaxed) & bit) return;
  if (cudaFuncSetAttribute(reinterpret_cast<const void*>(Kernel), cudaFuncAttributePreferredSharedMemoryCarveout,
                           int(cudaSharedmemCarveoutMaxL1)) != cudaSuccess)
    (void)cudaGetLastError();  // a hint: its error is not the launch's
  devices.fetch_or(bit, std::memory_order_relaxed);
}

}  // namespace

// Where fd_aba_kernel leaves qdd of instance b for fd_derivatives_at_kernel: out.qdd,
// or row 0 of instance b's dqdd/dtau block (nv of its nv x nv entries).
template <class S>
__device__ __forceinline__ DofColumn<S> qdd_scratch(const FdDerivativesOut<S>& out, long long b) {
  return out.qdd.data ? instance_column(out.qdd, b) : instance_column(out.dqdd_dtau, b);
}

// One thread per instance b < B: qdd by the ABA, then dqdd/dq, dqdd/dqd, M^-1 by
// fd_derivatives_instance<0> (the factor and solves by the tree walks over the output
// blocks: every capacity above kPackedLtlCapacity, and SCANDYN_DFD_KERNEL=tree).
template <class S, int C>
__global__ void __launch_bounds__(kDerivativesBlock)
    fd_derivatives_kernel(const __grid_constant__ ThreadModelParams<S, C> model, const FdBatchIn<S> in,
                          const FdDerivativesOut<S> out, int* failed_dof) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= in.q.batch) return;
  const Index nv = model.nv;
  const Force<S>* fext = in.fext ? in.fext + b * nv : nullptr;
  S qdd_local[C];
  const DofColumn<S> qdd = out.qdd.data ? instance_column(out.qdd, b) : DofColumn<S>{qdd_local, 1};
  const DofColumn<const S> q = instance_column(in.q, b), qd = instance_column(in.qd, b);
  Index failed = aba_instance<S, C>(model, q, qd, instance_column(in.tau, b), fext, qdd);
  if (failed < 0) {
    DerivativeBody<S> work[C];  // per-thread local memory
    failed = fd_derivatives_instance<0>(model.body, nv, model.a0, q, qd, DofColumn<const S>{qdd.data, qdd.stride},
                                        fext, work, instance_matrix(out.dqdd_dq, b, nv),
                                        instance_matrix(out.dqdd_dqd, b, nv), instance_matrix(out.dqdd_dtau, b, nv));
  }
  if (failed_dof) failed_dof[b] = failed;
}

// One thread per instance b < B: qdd by the ABA into qdd_scratch. The first of the
// two kernels up to kPackedLtlCapacity DoF: the ABA of a capacity-8 model takes ~220
// registers per thread (it keeps the bodies in registers), the derivatives and the
// packed solve ~100; in one kernel the ABA's count would cap the whole recursion at
// 12.5% occupancy.
template <class S, int C>
__global__ void __launch_bounds__(kDerivativesBlock)
    fd_aba_kernel(const __grid_constant__ ThreadModelParams<S, C> model, const FdBatchIn<S> in,
                  const FdDerivativesOut<S> out, int* failed_dof) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= in.q.batch) return;
  const Force<S>* fext = in.fext ? in.fext + b * model.nv : nullptr;
  const Index failed = aba_instance<S, C>(model, instance_column(in.q, b), instance_column(in.qd, b),
                                          instance_column(in.tau, b), fext, qdd_scratch(out, b));
  if (failed_dof) failed_dof[b] = failed;
}

// One thread per instance b < B whose ABA succeeded (failed_dof[b] < 0, or no
// failed_dof): the inverse-dynamics derivatives at fd_aba_kernel's qdd into the
// blocks, then packed_fd_solve on them: dqdd/dq, dqdd/dqd, M^-1. kLean: the
// inverse-dynamics derivatives by lean_chain_rnea_derivatives (chains only); else by
// rnea_derivatives_instance.
template <class S, int C, bool kLean>
__global__ void __launch_bounds__(kDerivativesBlock, at_min_blocks<S>())
    fd_derivatives_at_kernel(const __grid_constant__ ThreadModelParams<S, C> model, const FdBatchIn<S> in,
                             const FdDerivativesOut<S> out, int* failed_dof) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= in.q.batch) return;
  if (failed_dof && failed_dof[b] >= 0) return;
  const Index nv = model.nv;
  S qdd[C];  // copied out first: the scratch may be the dqdd/dtau block
  const DofColumn<S> scratch = qdd_scratch(out, b);
  for (Index i = 0; i < nv; ++i) qdd[i] = scratch[i];
  const Force<S>* fext = in.fext ? in.fext + b * nv : nullptr;
  const MatrixRef<S> dq = instance_matrix(out.dqdd_dq, b, nv), dqd = instance_matrix(out.dqdd_dqd, b, nv),
                     dtau = instance_matrix(out.dqdd_dtau, b, nv);
  if constexpr (kLean) {
    lean_chain_rnea_derivatives<S, C>(model.body, nv, model.a0, instance_column(in.q, b), instance_column(in.qd, b),
                                      DofColumn<const S>{qdd, 1}, fext, dq, dqd, dtau);
  } else {
    DerivativeBody<S> work[C];  // per-thread local memory
    rnea_derivatives_instance(model.body, nv, model.a0, instance_column(in.q, b), instance_column(in.qd, b),
                              DofColumn<const S>{qdd, 1}, fext, work, dq, dqd, dtau, nullptr);
  }
  const Index failed = packed_fd_solve<C>(dq, dqd, dtau, static_cast<const S*>(nullptr));
  if (failed_dof) failed_dof[b] = failed;
}

// ---- models with multi-DoF joints: the general kernels ------------------------------
// One thread per instance b < B over scandyn/cuda/derivatives_general.hpp's
// per-instance functions (per-thread arrays in local memory).

// dtau/dq, dtau/dqd and M of instance b (rnea_derivatives_general_instance).
template <class S, int C>
__global__ void __launch_bounds__(kDerivativesBlock)
    id_derivatives_general_kernel(const __grid_constant__ GeneralDerivativeParams<S, C> model, const IdBatchIn<S> in,
                                  const IdDerivativesOut<S> out) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= in.q.batch) return;
  id_derivatives_general_thread(model, in, out, b);
}

// qdd by aba_general (into out.qdd when given), then dqdd/dq, dqdd/dqd, M^-1 by
// fd_derivatives_general_instance; failed_dof[b] (when given): -1, or the DoF whose
// pivot (the ABA's, or M's) failed.
template <class S, int C>
__global__ void __launch_bounds__(kDerivativesBlock)
    fd_derivatives_general_kernel(const __grid_constant__ GeneralDerivativeParams<S, C> model, const FdBatchIn<S> in,
                                  const FdDerivativesOut<S> out, int* failed_dof) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= in.q.batch) return;
  const Index failed = fd_derivatives_general_thread(model, in, out, b);
  if (failed_dof) failed_dof[b] = static_cast<int>(failed);
}

namespace {

unsigned blocks_for(Index B) {
  return static_cast<unsigned>((static_cast<long long>(B) + kDerivativesBlock - 1) / kDerivativesBlock);
}

// The launches' argument checks (every model kind): cudaErrorInvalidValue for views of
// different batches or a missing array; otherwise cudaSuccess, and `run` false when
// there is nothing to do (no instance, or a model without DoFs).
template <class S>
cudaError_t check_id_arguments(const IdBatchIn<S>& in, const IdDerivativesOut<S>& out, Index nv, bool& run) {
  run = false;
  const Index B = in.q.batch;
  if (B < 0 || in.qd.batch != B || in.qdd.batch != B || out.dtau_dq.batch != B || out.dtau_dqd.batch != B ||
      out.M.batch != B)
    return cudaErrorInvalidValue;
  if (B == 0 || nv == 0) return cudaSuccess;
  if (!in.q.data || !in.qd.data || !in.qdd.data || !out.dtau_dq.data || !out.dtau_dqd.data || !out.M.data)
    return cudaErrorInvalidValue;
  run = true;
  return cudaSuccess;
}

template <class S>
cudaError_t check_fd_arguments(const FdBatchIn<S>& in, const FdDerivativesOut<S>& out, Index nv, bool& run) {
  run = false;
  const Index B = in.q.batch;
  if (B < 0 || in.qd.batch != B || in.tau.batch != B || out.dqdd_dq.batch != B || out.dqdd_dqd.batch != B ||
      out.dqdd_dtau.batch != B || (out.qdd.data && out.qdd.batch != B))
    return cudaErrorInvalidValue;
  if (B == 0 || nv == 0) return cudaSuccess;
  if (!in.q.data || !in.qd.data || !in.tau.data || !out.dqdd_dq.data || !out.dqdd_dqd.data || !out.dqdd_dtau.data)
    return cudaErrorInvalidValue;
  run = true;
  return cudaSuccess;
}

}  // namespace

template <class S>
cudaError_t launch_id_derivatives(const ThreadModel<S>& model, const IdBatchIn<S>& in, const IdDerivativesOut<S>& out,
                                  cudaStream_t stream) {
  bool run = false;
  if (const cudaError_t e = check_id_arguments(in, out, model.nv(), run); e != cudaSuccess || !run) return e;
  const Index B = in.q.batch;
  const bool recursion = env_is("SCANDYN_DID_KERNEL", "recursion");
  visit_compiled_capacity(model.params(), [&](const auto& params) {
    using P = std::decay_t<decltype(params)>;
    constexpr int C = P::capacity;
    if constexpr (C <= kPackedLtlCapacity) {
      if (!recursion && is_chain(params)) {
        id_derivatives_lean_kernel<S, C><<<blocks_for(B), kDerivativesBlock, 0, stream>>>(params, in, out);
        return;
      }
    }
    id_derivatives_kernel<S, C><<<blocks_for(B), kDerivativesBlock, 0, stream>>>(params, in, out);
  });
  return cudaGetLastError();
}

template <class S>
cudaError_t launch_fd_derivatives(const ThreadModel<S>& model, const FdBatchIn<S>& in, const FdDerivativesOut<S>& out,
                                  int* failed_dof, cudaStream_t stream) {
  bool run = false;
  if (const cudaError_t e = check_fd_arguments(in, out, model.nv(), run); e != cudaSuccess || !run) return e;
  const Index B = in.q.batch;
  const bool tree = env_is("SCANDYN_DFD_KERNEL", "tree"), packed = env_is("SCANDYN_DFD_KERNEL", "packed");
  const unsigned grid = blocks_for(B);
  visit_compiled_capacity(model.params(), [&](const auto& params) {
    using P = std::decay_t<decltype(params)>;
    constexpr int C = P::capacity;
    if constexpr (C <= kPackedLtlCapacity) {
      if (!tree) {
        prefer_l1<fd_aba_kernel<S, C>>();
        fd_aba_kernel<S, C><<<grid, kDerivativesBlock, 0, stream>>>(params, in, out, failed_dof);
        if (!packed && is_chain(params)) {
          prefer_l1<fd_derivatives_at_kernel<S, C, true>>();
          fd_derivatives_at_kernel<S, C, true><<<grid, kDerivativesBlock, 0, stream>>>(params, in, out, failed_dof);
        } else {
          prefer_l1<fd_derivatives_at_kernel<S, C, false>>();
          fd_derivatives_at_kernel<S, C, false><<<grid, kDerivativesBlock, 0, stream>>>(params, in, out, failed_dof);
        }
        return;
      }
    }
    prefer_l1<fd_derivatives_kernel<S, C>>();
    fd_derivatives_kernel<S, C><<<grid, kDerivativesBlock, 0, stream>>>(params, in, out, failed_dof);
  });
  return cudaGetLastError();
}

template <class S>
GeneralDerivativeModel<S>::GeneralDerivativeModel(const ModelTpl<S>& model)
    : nv_(model.nv()), nq_(model.nq()), nb_(model.nbodies()) {
  if (nv_ > kMaxThreadDofs)
    throw BackendError("backend 'cuda': model '" + model.name + "' has " + std::to_string(nv_) +
                       " DoF; the derivatives run a thread per instance, which takes at most " +
                       std::to_string(kMaxThreadDofs));
  capacity_ = nv_ <= 8 ? 8 : nv_ <= 16 ? 16 : nv_ <= 32 ? 32 : 64;
  const auto fill = [&](auto& p) {
    using P = std::decay_t<decltype(p)>;
    if (nq_ > P::q_capacity)  // (cannot happen: nq <= 4 nv / 3)
      throw BackendError("backend 'cuda': model '" + model.name + "' has " + std::to_string(nq_) +
                         " position entries, more than the derivative kernels' " + std::to_string(P::q_capacity));
    p = P{};
    for (Index i = 0; i < nb_; ++i) p.body[i] = model.bodies[static_cast<std::size_t>(i)];
    dof_parents(model.bodies.data(), nb_, p.dof_parent);
    dof_subtree_last(p.dof_parent, nv_, p.dof_last);
    dof_runs(p.dof_parent, nv_, p.dof_run);
    p.a0 = base_acceleration(model.gravity);
    p.nb = nb_, p.nv = nv_, p.nq = nq_;
  };
  switch (capacity_) {
    case 8: fill(params_.template emplace<GeneralDerivativeParams<S, 8>>()); break;
    case 16: fill(params_.template emplace<GeneralDerivativeParams<S, 16>>()); break;
    case 32: fill(params_.template emplace<GeneralDerivativeParams<S, 32>>()); break;
    default: fill(params_.template emplace<GeneralDerivativeParams<S, 64>>()); break;
  }
}

template <class S>
cudaError_t launch_id_derivatives(const GeneralDerivativeModel<S>& model, const IdBatchIn<S>& in,
                                  const IdDerivativesOut<S>& out, cudaStream_t stream) {
  bool run = false;
  if (const cudaError_t e = check_id_arguments(in, out, model.nv(), run); e != cudaSuccess || !run) return e;
  const Index B = in.q.batch;
  visit_compiled_capacity(model.params(), [&](const auto& params) {
    constexpr int C = std::decay_t<decltype(params)>::capacity;
    id_derivatives_general_kernel<S, C><<<blocks_for(B), kDerivativesBlock, 0, stream>>>(params, in, out);
  });
  return cudaGetLastError();
}

template <class S>
cudaError_t launch_fd_derivatives(const GeneralDerivativeModel<S>& model, const FdBatchIn<S>& in,
                                  const FdDerivativesOut<S>& out, int* failed_dof, cudaStream_t stream) {
  bool run = false;
  if (const cudaError_t e = check_fd_arguments(in, out, model.nv(), run); e != cudaSuccess || !run) return e;
  const Index B = in.q.batch;
  visit_compiled_capacity(model.params(), [&](const auto& params) {
    constexpr int C = std::decay_t<decltype(params)>::capacity;
    prefer_l1<fd_derivatives_general_kernel<S, C>>();
    fd_derivatives_general_kernel<S, C><<<blocks_for(B), kDerivativesBlock, 0, stream>>>(params, in, out,
                                                                                        failed_dof);
  });
  return cudaGetLastError();
}

// ---- the engines --------------------------------------------------------------------
//
// Staging buffer per engine, for max_batch instances (cap = nq x max_batch scalars:
// nv x max_batch for models of 1-DoF joints): the three inputs in slots 0..2, qdd in
// slot 3 (forward dynamics), the wrenches (6 slots, detail::stage_inputs' layout: nb <=
// nv wrenches per instance), then the three nv x nv outputs (nv^2 x max_batch scalars
// each), then (forward dynamics) max_batch ints of failed DoFs.

namespace {

constexpr std::size_t kInputSlots = 10;  // q, qd, qdd / tau, qdd out, fext (6)

template <class S>
std::unique_ptr<detail::StagingBuffer> derivative_staging(const ModelTpl<S>& model, Index max_batch, bool fd) {
  if (model.nv() > kMaxThreadDofs)
    throw BackendError("backend 'cuda': model '" + model.name + "' has " + std::to_string(model.nv()) +
                       " DoF; the derivatives run a thread per instance, which takes at most " +
                       std::to_string(kMaxThreadDofs));
  if (max_batch < 0) throw BackendError("backend 'cuda': max_batch " + std::to_string(max_batch) + " is negative");
  const std::size_t n = static_cast<std::size_t>(model.nv()), nq = static_cast<std::size_t>(model.nq());
  return std::make_unique<detail::StagingBuffer>(
      max_batch, model.nv(), sizeof(S) == 4 ? "float" : "double",
      fd ? "q, qd, tau, qdd, fext and three nv x nv derivatives" : "q, qd, qdd, fext and three nv x nv derivatives",
      (kInputSlots * nq + 3 * n * n) * sizeof(S) + (fd ? sizeof(int) : 0));
}

// Stages the three nv x nv outputs (device views in `dev`), returns their plans.
template <class S, std::size_t N>
void plan_outputs(const BatchView<S> (&host)[N], const char* const (&names)[N], Index nv, std::size_t cap, S* base,
                  Staging (&st)[N], BatchView<S> (&dev)[N]) {
  const std::size_t mcap = static_cast<std::size_t>(nv) * cap;
  for (std::size_t k = 0; k < N; ++k) {
    st[k] = plan(host[k], nv * nv, mcap, true, names[k]);
    dev[k] = st[k].device_view(base + k * mcap, host[k].batch);
  }
}

template <class S, std::size_t N>
void copy_outputs(const Staging (&st)[N], const BatchView<S> (&host)[N], const char* const (&names)[N], Index nv,
                  std::size_t cap, S* base, cudaStream_t stream) {
  const std::size_t mcap = static_cast<std::size_t>(nv) * cap;
  for (std::size_t k = 0; k < N; ++k)
    check(copy(st[k], host[k], nv * nv, base + k * mcap, cudaMemcpyDeviceToHost, stream),
          (std::string("copying ") + names[k] + " to the host").c_str());
}

}  // namespace

template <class S>
CudaIdDerivatives<S>::CudaIdDerivatives(const ModelTpl<S>& model, const BackendOptions& options)
    : nv_(model.nv()), nq_(model.nq()), nb_(model.nbodies()), max_batch_(options.max_batch) {
  staging_ = derivative_staging(model, max_batch_, false);
  if (model.multi_dof()) {
    general_ = std::make_unique<GeneralDerivativeModel<S>>(model);
    require_compiled_capacity(general_->capacity(), "the derivatives of models with multi-DoF joints", model.name);
  } else {
    thread_ = std::make_unique<ThreadModel<S>>(model);
  }
}
template <class S>
CudaIdDerivatives<S>::~CudaIdDerivatives() = default;

template <class S>
cudaError_t CudaIdDerivatives<S>::compute_async(const IdBatchIn<S>& in, const IdDerivativesOut<S>& out,
                                                cudaStream_t stream) {
  return general_ ? launch_id_derivatives(*general_, in, out, stream) : launch_id_derivatives(*thread_, in, out, stream);
}

template <class S>
void CudaIdDerivatives<S>::compute(const IdBatchIn<S>& in, const IdDerivativesOut<S>& out) {
  check_batch(in, out, max_batch_);
  const Index B = in.q.batch, nv = nv_;
  if (B == 0 || nv == 0) return;
  const std::size_t cap = static_cast<std::size_t>(nv) * max_batch_;   // an output's nv slots of cap
  const std::size_t icap = static_cast<std::size_t>(nq_) * max_batch_;  // an input slot (nq = nv: 1-DoF joints)
  S* const buffer = static_cast<S*>(staging_->data());
  const cudaStream_t stream = staging_->stream();
  static const char* const kNames[3] = {"dtau_dq", "dtau_dqd", "M"};
  const BatchView<S> host[3] = {out.dtau_dq, out.dtau_dqd, out.M};
  Staging st[3];
  BatchView<S> dev[3];
  plan_outputs(host, kNames, nv, cap, buffer + kInputSlots * icap, st, dev);
  const detail::StagedInputs<S> d = detail::stage_inputs<S>({in.q, in.qd, in.qdd}, {"q", "qd", "qdd"}, in.fext,
                                                            {nq_, nv, nv}, nb_, icap, buffer, stream);
  check(compute_async(IdBatchIn<S>{d.in[0], d.in[1], d.in[2], d.fext}, IdDerivativesOut<S>{dev[0], dev[1], dev[2]},
                      stream),
        "launching id_derivatives_kernel");
  copy_outputs(st, host, kNames, nv, cap, buffer + kInputSlots * icap, stream);
  check(cudaStreamSynchronize(stream), "running id_derivatives_kernel");
}

template <class S>
CudaFdDerivatives<S>::CudaFdDerivatives(const ModelTpl<S>& model, const BackendOptions& options)
    : nv_(model.nv()),
      nq_(model.nq()),
      nb_(model.nbodies()),
      max_batch_(options.max_batch),
      failed_host_(static_cast<std::size_t>(options.max_batch)) {
  staging_ = derivative_staging(model, max_batch_, true);
  if (model.multi_dof()) {
    general_ = std::make_unique<GeneralDerivativeModel<S>>(model);
    require_compiled_capacity(general_->capacity(), "the derivatives of models with multi-DoF joints", model.name);
  } else {
    thread_ = std::make_unique<ThreadModel<S>>(model);
  }
}
template <class S>
CudaFdDerivatives<S>::~CudaFdDerivatives() = default;

template <class S>
cudaError_t CudaFdDerivatives<S>::compute_async(const FdBatchIn<S>& in, const FdDerivativesOut<S>& out,
                                                int* failed_dof, cudaStream_t stream) {
  return general_ ? launch_fd_derivatives(*general_, in, out, failed_dof, stream)
                  : launch_fd_derivatives(*thread_, in, out, failed_dof, stream);
}

template <class S>
BatchStatus CudaFdDerivatives<S>::compute(const FdBatchIn<S>& in, const FdDerivativesOut<S>& out) {
  check_batch(in, out, max_batch_);
  const Index B = in.q.batch, nv = nv_;
  if (B == 0 || nv == 0) return BatchStatus{};
  const std::size_t cap = static_cast<std::size_t>(nv) * max_batch_;   // an output's nv slots of cap
  const std::size_t icap = static_cast<std::size_t>(nq_) * max_batch_;  // an input slot (nq = nv: 1-DoF joints)
  S* const buffer = static_cast<S*>(staging_->data());
  const cudaStream_t stream = staging_->stream();
  static const char* const kNames[3] = {"dqdd_dq", "dqdd_dqd", "dqdd_dtau"};
  const BatchView<S> host[3] = {out.dqdd_dq, out.dqdd_dqd, out.dqdd_dtau};
  Staging st[3];
  BatchView<S> dev[3];
  S* const mats = buffer + kInputSlots * icap;
  plan_outputs(host, kNames, nv, cap, mats, st, dev);
  int* const dfailed = reinterpret_cast<int*>(mats + 3 * static_cast<std::size_t>(nv) * cap);
  Staging sqdd;
  BatchView<S> dqdd{};
  if (out.qdd.data) {
    sqdd = plan(out.qdd, nv, icap, true, "qdd");
    dqdd = sqdd.device_view(buffer + 3 * icap, B);
  }
  const detail::StagedInputs<S> d = detail::stage_inputs<S>({in.q, in.qd, in.tau}, {"q", "qd", "tau"}, in.fext,
                                                            {nq_, nv, nv}, nb_, icap, buffer, stream);
  check(compute_async(FdBatchIn<S>{d.in[0], d.in[1], d.in[2], d.fext},
                      FdDerivativesOut<S>{dev[0], dev[1], dev[2], dqdd}, dfailed, stream),
        "launching fd_derivatives_kernel");
  copy_outputs(st, host, kNames, nv, cap, mats, stream);
  if (out.qdd.data)
    check(copy(sqdd, out.qdd, nv, buffer + 3 * icap, cudaMemcpyDeviceToHost, stream), "copying qdd to the host");
  check(cudaMemcpyAsync(failed_host_.data(), dfailed, static_cast<std::size_t>(B) * sizeof(int), cudaMemcpyDeviceToHost,
                        stream),
        "copying the failed DoFs to the host");
  check(cudaStreamSynchronize(stream), "running fd_derivatives_kernel");
  return summarize_failures(failed_host_.data(), B, Failure::ArticulatedPivot);
}

template <class S>
std::unique_ptr<IdDerivatives<S>> make_cuda_id_derivatives(const ModelTpl<S>& model, const BackendOptions& options) {
  return std::make_unique<CudaIdDerivatives<S>>(model, options);
}
template <class S>
std::unique_ptr<FdDerivatives<S>> make_cuda_fd_derivatives(const ModelTpl<S>& model, const BackendOptions& options) {
  return std::make_unique<CudaFdDerivatives<S>>(model, options);
}

#define SCANDYN_INSTANTIATE(S)                                                                                      \
  template class CudaIdDerivatives<S>;                                                                             \
  template class CudaFdDerivatives<S>;                                                                             \
  template cudaError_t launch_id_derivatives(const ThreadModel<S>&, const IdBatchIn<S>&, const IdDerivativesOut<S>&, \
                                             cudaStream_t);                                                        \
  template cudaError_t launch_fd_derivatives(const ThreadModel<S>&, const FdBatchIn<S>&, const FdDerivativesOut<S>&, \
                                             int*, cudaStream_t);                                                  \
  template class GeneralDerivativeModel<S>;                                                                        \
  template cudaError_t launch_id_derivatives(const GeneralDerivativeModel<S>&, const IdBatchIn<S>&,                \
                                             const IdDerivativesOut<S>&, cudaStream_t);                            \
  template cudaError_t launch_fd_derivatives(const GeneralDerivativeModel<S>&, const FdBatchIn<S>&,                \
                                             const FdDerivativesOut<S>&, int*, cudaStream_t);                      \
  template std::unique_ptr<IdDerivatives<S>> make_cuda_id_derivatives(const ModelTpl<S>&, const BackendOptions&);    \
  template std::unique_ptr<FdDerivatives<S>> make_cuda_fd_derivatives(const ModelTpl<S>&, const BackendOptions&);
SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)
#undef SCANDYN_INSTANTIATE

}  // namespace cuda
}  // namespace scandyn
