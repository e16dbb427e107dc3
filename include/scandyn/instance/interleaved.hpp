// scandyn/instance/interleaved.hpp: arrays of one thread's scratch inside a buffer
// that `slots` threads share, for the general path on the GPU (GeneralWorkOf,
// scandyn/instance/general_instance.hpp; kernels/general_dynamics.cu):
//
//   StridedArray<T>      element i of T at data[i * stride]. With data = base + t and
//                        stride = slots, thread t's elements are interleaved with the
//                        other threads' a whole T at a time ("structs": a warp reading
//                        field k of element i reads 32 scalars sizeof(T) apart); with
//                        data = base + t n and stride 1 the thread's n elements are
//                        contiguous ("per instance": 32 scalars a whole slice apart).
//                        operator[] returns a T&.
//   ScalarInterleaved<T> every scalar of T interleaved ("scalars"): scalar k of element
//                        i at data[(i N + k) * stride], N = T's scalars, data = base + t,
//                        stride = slots, so that a warp reading scalar k of element i
//                        reads 32 consecutive scalars. operator[] returns a proxy:
//                        read it into a T (`const T x = a[i];`), assign a T to it,
//                        or add one (`a[i] += x`).
//
// The serial reference keeps plain pointers (GeneralWork<S>): code that works on
// all three reads an element into a local, and writes or adds a whole element.
#pragma once

#include <type_traits>

#include "scandyn/spatial.hpp"

namespace scandyn {

template <class T>
struct StridedArray {
  T* data;
  long long stride;
  SCANDYN_HD T& operator[](Index i) const { return data[i * stride]; }
  // the elements from k on
  SCANDYN_HD StridedArray operator+(Index k) const { return {data + k * stride, stride}; }
};

// The scalar type of a spatial struct (Transform<S>, Motion<S>, ...) and of a scalar.
template <class T>
struct ScalarOf {
  using type = T;
};
template <template <class> class X, class S>
struct ScalarOf<X<S>> {
  using type = S;
};

template <class T>
struct ScalarInterleaved {
  using S = typename ScalarOf<T>::type;
  static constexpr int N = static_cast<int>(sizeof(T) / sizeof(S));
  static_assert(sizeof(T) == N * sizeof(S) && std::is_trivially_copyable<T>::value,
                "ScalarInterleaved: T must be a plain struct of its scalars");

  struct Ref {
    S* p;  // scalar 0 of the element; scalar k at p[k * stride]
    long long stride;
    SCANDYN_HD operator T() const {
      T x;
      S* const s = reinterpret_cast<S*>(&x);
#ifdef __CUDA_ARCH__
#pragma unroll
#endif
      for (int k = 0; k < N; ++k) s[k] = p[k * stride];
      return x;
    }
    SCANDYN_HD const Ref& operator=(const T& x) const {
      const S* const s = reinterpret_cast<const S*>(&x);
#ifdef __CUDA_ARCH__
#pragma unroll
#endif
      for (int k = 0; k < N; ++k) p[k * stride] = s[k];
      return *this;
    }
    SCANDYN_HD const Ref& operator+=(const T& x) const {
      T y = *this;
      y += x;
      return *this = y;
    }
  };

  S* data;
  long long stride;
  SCANDYN_HD Ref operator[](Index i) const { return {data + static_cast<long long>(i) * N * stride, stride}; }
};

// The array of T of the per-scalar layout: scalars are plain strided arrays (a T&).
template <class T>
using ScalarInterleavedArray =
    typename std::conditional<std::is_floating_point<T>::value, StridedArray<T>, ScalarInterleaved<T>>::type;

// ---- a joint's run of entries as a plain pointer -----------------------------------
// The *_at steps of steps.hpp take a joint's entries (q, qd, tau, qdd; ABA's Y, L, w)
// as plain pointers. joint_run gives them: a + off for a plain pointer (the serial
// reference, nothing copied), else tmp, which load_run fills from the array before
// the step and store_run writes back after it (no-ops for plain pointers).

template <class A, class T>
SCANDYN_HD auto joint_run(const A& a, Index off, T* tmp) {
  (void)a, (void)off, (void)tmp;
  if constexpr (std::is_pointer<A>::value) return a + off;
  else return tmp;
}

template <class A, class T>
SCANDYN_HD void load_run(const A& a, Index off, int n, T* tmp) {
  (void)a, (void)off, (void)n, (void)tmp;
  if constexpr (!std::is_pointer<A>::value)
    for (int k = 0; k < n; ++k) tmp[k] = a[off + k];
}

template <class A, class T>
SCANDYN_HD void store_run(const A& a, Index off, int n, const T* tmp) {
  (void)a, (void)off, (void)n, (void)tmp;
  if constexpr (!std::is_pointer<A>::value)
    for (int k = 0; k < n; ++k) a[off + k] = tmp[k];
}

}  // namespace scandyn
