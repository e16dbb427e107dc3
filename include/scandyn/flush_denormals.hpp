// scandyn/flush_denormals.hpp: a scope in which this host thread's floating-point unit
// flushes subnormal results to zero and reads subnormal inputs as zero (x86 SSE/AVX:
// MXCSR's FTZ and DAZ bits; elsewhere nothing), restoring the previous mode at the
// scope's end.
//
// Why: a long composition of contracting maps (the dual Riccati aggregates of
// dual_aggregate, scandyn/algorithm/chain_fd.hpp: the coupling C of a range is a
// product of one contraction per link) passes through the subnormal range on its way
// to zero. On Intel x86 every operation on a subnormal takes a microcode assist (about
// a hundred cycles), so a reduction over tens of thousands of links ran 5-12x slower
// per link than over the whole chain (bench/chain_carries_cost, reduce-par rows,
// bench/results/chain_carries-scaling-h200-host.csv; a 2-core AMD EPYC: 1.6x). What
// is flushed is below 2.2e-308 (double) / 1.2e-38 (float) next to entries of order 1:
// the results change at most in their last bits, where they do at all.
// Host code only (CUDA's double arithmetic handles subnormals at full speed).
#pragma once

#if defined(__SSE2__) || defined(_M_X64)
#include <xmmintrin.h>
#define SCANDYN_HAS_MXCSR 1
#else
#define SCANDYN_HAS_MXCSR 0
#endif

namespace scandyn {

class FlushDenormalsScope {
 public:
  FlushDenormalsScope() {
#if SCANDYN_HAS_MXCSR
    saved_ = _mm_getcsr();
    _mm_setcsr(saved_ | kFlushToZero | kDenormalsAreZero);
#endif
  }
  ~FlushDenormalsScope() {
#if SCANDYN_HAS_MXCSR
    _mm_setcsr(saved_);
#endif
  }
  FlushDenormalsScope(const FlushDenormalsScope&) = delete;
  FlushDenormalsScope& operator=(const FlushDenormalsScope&) = delete;

 private:
#if SCANDYN_HAS_MXCSR
  static constexpr unsigned kFlushToZero = 0x8000;      // MXCSR.FZ
  static constexpr unsigned kDenormalsAreZero = 0x0040;  // MXCSR.DAZ
  unsigned saved_ = 0;
#endif
};

}  // namespace scandyn
