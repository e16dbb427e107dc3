// kernels/sim_variational.cuh (internal): the simulator's variational step on the
// GPU, one thread per instance running variational_dense_step
// (scandyn/sim/variational_instance.hpp, the host step's routine: Newton with the
// exact Jacobian, LU with partial pivoting) for models of up to kMaxThreadDofs DoFs
// (and kVariationalExactMaxDofs); kernels/simulator_step.cu owns one plan per
// simulator with "integrator": "variational".
//
// Scratch: the six nv x nv matrices of an instance (D, K, M, J, the unused blocks,
// H) in one device buffer, instance-innermost (entry (i, j) of matrix m of instance
// b at matrices[(m nv^2 + i nv + j) B + b]): the threads of a warp walk the same
// (i, j) in the same instruction (one model, one loop structure), so each access is
// one coalesced transaction, where per-instance contiguous matrices would put the
// 32 accesses 8 nv^2 bytes apart. The vectors and per-body values (the derivative
// passes' bodies, the ABA's) are C-sized arrays in the thread's local memory, which
// the hardware interleaves by thread the same way.
#pragma once

#include <cuda_runtime.h>

#include "scandyn/sim/simulator.hpp"
#include "scandyn/sim/variational_instance.hpp"
#include "sim_fused.cuh"

namespace scandyn {
namespace sim {
namespace detail {

// A recorded DoF with this bit set: the variational step's Newton iteration did
// not converge there (Failure::NotConverged), rather than a failed pivot.
inline constexpr Index kNotConvergedDof = Index(1) << 29;

// The variational kernel's constants (device pointers).
template <class S>
struct VariationalArgs {
  VariationalModel<S> model;         // bodies in device memory, a0 (-g, or zero), a0_rest, H on
  const JointCoefficients<S>* coef;  // (nv) joint coefficients (neutral for undeclared effects)
  S* matrices;                       // (6 nv^2 x B) the Newton matrices, instance-innermost
  S dt;
  bool external;                     // the scene declares external wrenches (FusedArgs::wrenches read)
};

// One thread's vectors and per-body values for variational_dense_step, capacity C
// (C >= nv): local arrays in the kernel (the host tests build the same).
template <class S, int C>
struct VariationalThreadScratch {
  S zero[C], q1[C], qm[C], v[C], p0[C], tau_m[C], tau_g[C], f[C], eq[C], eqd[C], r[C], work[C], dtv[C];  // (nv)
  Index piv[C];                          // (nv) LU's row exchanges
  DerivativeBody<S> deriv[C];            // (nv) the first- and second-order passes' bodies
  WeightedDq2Body<S> hsums[C];           // (nv) H's per-body sums
  // (nv) rnea_general / aba_general: transforms, velocities, accelerations, velocity
  // products, forces, articulated inertias, U = IA S, D = S^T U, u
  Transform<S> Xup[C];
  Motion<S> vb[C], ab[C], cb[C];
  Force<S> fb[C], U[C];
  ABInertia<S> IA[C];
  S D[C], u[C];

  // The scratch of instance b of B: these arrays (zero cleared) and its six nv x nv
  // matrices in `matrices` (6 nv^2 x B, instance-innermost: entry (i, j) of matrix m
  // at matrices[(m nv^2 + i nv + j) B + b]).
  __host__ __device__ VariationalScratch<S> view(Index n, S* matrices, long long b, long long B) {
    for (Index i = 0; i < n; ++i) zero[i] = S(0);
    const std::ptrdiff_t one = static_cast<std::ptrdiff_t>(n) * n * B;  // one matrix of every instance
    S* const m = matrices + b;
    auto mat = [&](int k) { return MatrixRef<S>{m + k * one, n, static_cast<std::ptrdiff_t>(B)}; };
    return {zero, q1, qm, v, p0, tau_m, tau_g, f, eq, eqd, r, work, dtv, mat(0), mat(1), mat(2), mat(3), mat(4), mat(5),
            piv, deriv, hsums, GeneralWork<S>{Xup, vb, ab, cb, fb, nullptr, IA, U, D, u, nullptr}};
  }
};

// One simulator's variational step on the device: the model's bodies, the
// coefficients, the matrices' buffer.
template <class S>
class VariationalSimPlan {
 public:
  // Throws BackendError for a model of more than kMaxThreadDofs (or
  // kVariationalExactMaxDofs) DoFs, naming the limit; CUDA errors as BackendError.
  explicit VariationalSimPlan(const SimSetup<S>& setup);
  // The same refusal, before anything is allocated.
  static void require_capacity(const SimSetup<S>& setup);
  ~VariationalSimPlan();
  VariationalSimPlan(const VariationalSimPlan&) = delete;
  VariationalSimPlan& operator=(const VariationalSimPlan&) = delete;
  // One step of every instance (a.batch) on the stream; failures into a.status.
  cudaError_t launch(const FusedArgs<S>& a, cudaStream_t stream) const;

 private:
  VariationalArgs<S> args_{};
  Index capacity_ = 0;    // the kernel's C: 8, 16, 32 or 64
  void* raw_ = nullptr;   // bodies, coefficients, matrices
};

}  // namespace detail
}  // namespace sim
}  // namespace scandyn
