// scandyn/spatial/pack.hpp: Pack<T, W>, W values of T in one SIMD register, used as
// a scalar type so that the serial reference algorithms run W instances at once.
//
// The CPU engines' SIMD path (cpu_fallback/simd_batch.hpp) instantiates the
// reference rnea / crba / aba (src/algorithm/reference_impl.hpp) over Pack: lane l
// of every value belongs to instance l of a group of W. Arithmetic is lane-wise
// IEEE (GCC/Clang vector extensions, which compile to SSE2, AVX or AVX-512 by the
// build's target flags), and sqrt, sin, cos call the scalar library per lane, so
// that each lane computes what the scalar code computes for its instance.
//
// Comparisons return a PackMask whose truth value (explicit operator bool) is
// "true in every lane". The algorithms compare only (a) model constants, which are
// the same in every lane (a joint axis against 0), and (b) pivots (pivot_ok: d > 0
// and finite), where "every lane" is the right question: a false answer makes the
// caller compute that group's instances again one at a time, which names the failing
// instance and leaves the others' results as the scalar code gives them.
#pragma once

#include <cmath>
#include <cstring>
#include <limits>

#include "scandyn/spatial/scalar.hpp"

namespace scandyn {

// Bytes of the widest vector register the build targets: 64 (AVX-512), 32 (AVX) or 16 (SSE2);
// -DSCANDYN_SIMD_BYTES=N sets it (e.g. 32 for 4 doubles per pack on an AVX-512 build).
#if defined(SCANDYN_SIMD_BYTES)
inline constexpr int kSimdBytes = SCANDYN_SIMD_BYTES;
#elif defined(__AVX512F__)
inline constexpr int kSimdBytes = 64;
#elif defined(__AVX__)
inline constexpr int kSimdBytes = 32;
#else
inline constexpr int kSimdBytes = 16;
#endif

template <class T, int W>
struct PackMask;

template <class T, int W>
struct Pack {
  static_assert(W >= 2 && (W & (W - 1)) == 0, "Pack width must be a power of two");
  static constexpr int width = W;
  using Lane = T;
  typedef T V __attribute__((vector_size(sizeof(T) * W)));
  V v;

  Pack() = default;
  Pack(T x) : v(V{} + x) {}  // broadcast (implicit: S(0), S(1) and mixed arithmetic with T)
  static Pack from_vector(V x) {
    Pack p;
    p.v = x;
    return p;
  }
  static Pack load(const T* p) {  // W contiguous values, any alignment
    Pack r;
    std::memcpy(&r.v, p, sizeof(V));
    return r;
  }
  void store(T* p) const { std::memcpy(p, &v, sizeof(V)); }
  T operator[](int l) const { return v[l]; }
  void set(int l, T x) { v[l] = x; }

  friend Pack operator+(Pack a, Pack b) { return from_vector(a.v + b.v); }
  friend Pack operator-(Pack a, Pack b) { return from_vector(a.v - b.v); }
  friend Pack operator*(Pack a, Pack b) { return from_vector(a.v * b.v); }
  friend Pack operator/(Pack a, Pack b) { return from_vector(a.v / b.v); }
  friend Pack operator-(Pack a) { return from_vector(-a.v); }
  Pack& operator+=(Pack b) { v += b.v; return *this; }
  Pack& operator-=(Pack b) { v -= b.v; return *this; }
  Pack& operator*=(Pack b) { v *= b.v; return *this; }
  Pack& operator/=(Pack b) { v /= b.v; return *this; }

  friend PackMask<T, W> operator==(Pack a, Pack b) { return {a.v == b.v}; }
  friend PackMask<T, W> operator!=(Pack a, Pack b) { return {a.v != b.v}; }
  friend PackMask<T, W> operator<(Pack a, Pack b) { return {a.v < b.v}; }
  friend PackMask<T, W> operator<=(Pack a, Pack b) { return {a.v <= b.v}; }
  friend PackMask<T, W> operator>(Pack a, Pack b) { return {a.v > b.v}; }
  friend PackMask<T, W> operator>=(Pack a, Pack b) { return {a.v >= b.v}; }
};

// A lane-wise comparison result (lanes all ones or zero); true as a bool when true in every lane.
template <class T, int W>
struct PackMask {
  using M = decltype(typename Pack<T, W>::V{} == typename Pack<T, W>::V{});
  M m;
  bool all() const {
    for (int l = 0; l < W; ++l)
      if (!m[l]) return false;
    return true;
  }
  bool lane(int l) const { return m[l] != 0; }
  explicit operator bool() const { return all(); }
  PackMask operator!() const { return {!m}; }
};

template <class T, int W>
inline constexpr bool kIsPack<Pack<T, W>> = true;

// Lane-wise library calls: the same functions the scalar code calls, lane by lane.
template <class T, int W>
struct ScalarMath<Pack<T, W>> {
  using P = Pack<T, W>;
  template <class F>
  static P map(P x, F f) {
    P r;
    for (int l = 0; l < W; ++l) r.v[l] = f(x.v[l]);
    return r;
  }
  static P sqrt(P x) { return map(x, [](T a) { return ScalarMath<T>::sqrt(a); }); }
  static P sin(P x) { return map(x, [](T a) { return ScalarMath<T>::sin(a); }); }
  static P cos(P x) { return map(x, [](T a) { return ScalarMath<T>::cos(a); }); }
  static P abs(P x) { return map(x, [](T a) { return ScalarMath<T>::abs(a); }); }
  // finite in every lane
  static bool isfinite(P x) {
    for (int l = 0; l < W; ++l)
      if (!ScalarMath<T>::isfinite(x.v[l])) return false;
    return true;
  }
  static P epsilon() { return P(std::numeric_limits<T>::epsilon()); }
};

// The pack of S that fills the build's widest register: 4 doubles / 8 floats under AVX2,
// 8 / 16 under AVX-512, 2 / 4 with SSE2 only.
template <class S>
using NativePack = Pack<S, kSimdBytes / int(sizeof(S))>;

}  // namespace scandyn
