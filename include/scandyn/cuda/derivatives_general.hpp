// scandyn/cuda/derivatives_general.hpp: one instance's work in the general derivative
// kernels (kernels/derivatives.cu: id_derivatives_general_kernel,
// fd_derivatives_general_kernel; models with multi-DoF joints, one thread per
// instance), __host__ __device__ so that the host tests run the kernels' composition
// (tests/cuda/test_cuda_derivatives_multi_dof.cu) where no device is usable.
//
// Each copies instance b's q (nq), qd and qdd or tau into per-thread arrays and runs the
// serial reference's functions on them (scandyn/algorithm/derivatives.cpp for a model
// with multi-DoF joints): rnea_derivatives_general_instance; aba_general (over a
// GeneralWork of per-thread arrays, scandyn/instance/general_instance.hpp) then
// fd_derivatives_general_instance, whose nv DerivativeBody entries reuse the ABA's
// scratch bytes (GeneralFdScratch: the ABA's is dead once qdd is known). On a device
// the arrays are the thread's local memory.
#pragma once

#include "scandyn/build_config.hpp"

#if SCANDYN_HAS_CUDA
#include "scandyn/cuda/derivatives.hpp"
#include "scandyn/instance/dynamics_derivatives.hpp"
#include "scandyn/instance/general_instance.hpp"

namespace scandyn {
namespace cuda {

// Instance b's n entries of v into out.
template <class S>
SCANDYN_HD void gather_instance(const BatchView<const S>& v, long long b, Index n, S* out) {
  for (Index i = 0; i < n; ++i) out[i] = v.at(i, static_cast<Index>(b));
}

// aba_general's scratch for at most C bodies and C DoFs (the CRBA's Ic unused).
template <class S, int C>
struct GeneralAbaScratch {
  Transform<S> Xup[C];
  Motion<S> v[C], a[C], c[C];
  Force<S> f[C];
  ABInertia<S> IA[C];
  Force<S> U[C];
  S D[C], u[C], L[kMaxJointDofs * C];
  SCANDYN_HD GeneralWork<S> work() { return {Xup, v, a, c, f, nullptr, IA, U, D, u, L}; }
};

// The forward dynamics' scratch: the ABA's, then the derivatives' nv DerivativeBody
// entries in the same bytes.
template <class S, int C>
union GeneralFdScratch {
  GeneralAbaScratch<S, C> aba;
  DerivativeBody<S> work[C];
  SCANDYN_HD GeneralFdScratch() {}
};

// dtau/dq, dtau/dqd and M of instance b (every entry written).
template <class S, int C>
SCANDYN_HD void id_derivatives_general_thread(const GeneralDerivativeParams<S, C>& model, const IdBatchIn<S>& in,
                                              const IdDerivativesOut<S>& out, long long b) {
  const Index nv = model.nv;
  S q[GeneralDerivativeParams<S, C>::q_capacity], qd[C], qdd[C];
  gather_instance(in.q, b, model.nq, q);
  gather_instance(in.qd, b, nv, qd);
  gather_instance(in.qdd, b, nv, qdd);
  DerivativeBody<S> work[C];
  const S *const qp = q, *const qdp = qd, *const qddp = qdd;
  rnea_derivatives_general_instance(model.body, model.nb, nv, model.a0, qp, qdp, qddp,
                                    in.fext ? in.fext + b * model.nb : nullptr, work,
                                    instance_matrix(out.dtau_dq, b, nv), instance_matrix(out.dtau_dqd, b, nv),
                                    instance_matrix(out.M, b, nv), nullptr);
}

// qdd of instance b by aba_general (into out.qdd when given), then dqdd/dq, dqdd/dqd
// and M^-1 by fd_derivatives_general_instance (the factor of M over the tree of DoFs in
// the output blocks). Returns -1, or the DoF whose pivot (the ABA's, or M's) failed
// (the outputs then not meaningful).
template <class S, int C>
SCANDYN_HD Index fd_derivatives_general_thread(const GeneralDerivativeParams<S, C>& model, const FdBatchIn<S>& in,
                                               const FdDerivativesOut<S>& out, long long b) {
  const Index nv = model.nv;
  S q[GeneralDerivativeParams<S, C>::q_capacity], qd[C], tau[C], qdd[C];
  gather_instance(in.q, b, model.nq, q);
  gather_instance(in.qd, b, nv, qd);
  gather_instance(in.tau, b, nv, tau);
  const Force<S>* fext = in.fext ? in.fext + b * model.nb : nullptr;
  GeneralFdScratch<S, C> scratch;
  // plain pointers: aba_general's instantiation of the serial reference (reference_general_impl.hpp)
  const S *const qp = q, *const qdp = qd, *const taup = tau;
  S* const qddp = qdd;
  Index failed = aba_general(model.body, model.nb, model.a0, scratch.aba.work(), qp, qdp, taup, qddp, fext,
                             static_cast<const S*>(nullptr));
  if (failed >= 0) return failed;
  if (out.qdd.data)
    for (Index i = 0; i < nv; ++i) out.qdd.at(i, static_cast<Index>(b)) = qdd[i];
  return fd_derivatives_general_instance(model.body, model.nb, nv, model.a0, qp, qdp, static_cast<const S*>(qddp),
                                         fext, model.dof_parent, model.dof_last, model.dof_run, scratch.work,
                                         instance_matrix(out.dqdd_dq, b, nv), instance_matrix(out.dqdd_dqd, b, nv),
                                         instance_matrix(out.dqdd_dtau, b, nv));
}

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
