// scandyn/instance/hybrid_instance.hpp: the hybrid dynamics of one instance in one thread
// (Featherstone 2008, 9.2): aba_instance's passes with the prescribed joints' steps
// (aba_instance's kHybrid), the serial scandyn::hybrid_dynamics's arithmetic.
#pragma once

#include "scandyn/instance/aba_instance.hpp"

#if SCANDYN_HAS_CUDA
namespace scandyn {
namespace cuda {

#if defined(__CUDACC__)
// qdd_out and hd.tau_out of one instance: DoFs whose bit is set in hd.prescribed take
// their acceleration from hd.qdd_in and get their force; the others take their force
// from tau_in and get their acceleration. Returns -1, or the DoF (with its force
// given) whose articulated pivot was not positive and finite, nothing written. The
// template arguments are aba_instance's; models of up to 64 DoF. Also a host
// function under nvcc.
template <class S, int C, bool kKeepXup = false, bool kUnrolled = (C <= 8), Trig kTrig = Trig::Library,
          int kSlots = C, class Bd = Body<S>>
__host__ __device__ __forceinline__ Index hybrid_instance(const ThreadModelParams<S, C, Bd>& model, DofColumn<const S> q,
                                                          DofColumn<const S> qd, DofColumn<const S> tau_in,
                                                          const Force<S>* fext, DofColumn<S> qdd_out,
                                                          const HybridColumns<S>& hd) {
  return aba_instance<S, C, kKeepXup, kUnrolled, kTrig, kSlots, true>(model, q, qd, tau_in, fext, qdd_out, nullptr,
                                                                      hd);
}
#endif  // __CUDACC__

}  // namespace cuda
}  // namespace scandyn

#endif  // SCANDYN_HAS_CUDA
