// scandyn/spatial/small_matrix.hpp: fixed-size dense matrices for the chain
// forward dynamics' scan elements (6x6 affine maps, 5x5 constraint-space blocks).
//
// Row-major, trivially copyable, SCANDYN_HD operations only: the same code runs in
// the serial, OpenMP and CUDA paths. Sizes are compile-time, so every loop unrolls
// and a matrix stays in registers on the device.
#pragma once

#include <cmath>

#include "scandyn/spatial/inertia.hpp"
#include "scandyn/spatial/motion.hpp"
#include "scandyn/spatial/transform.hpp"

namespace scandyn {

template <class S, int R, int C>
struct SmallMat {
  S m[R * C];  // row-major: entry (r, c) at m[r * C + c]

  SCANDYN_HD S operator()(int r, int c) const { return m[r * C + c]; }
  SCANDYN_HD S& operator()(int r, int c) { return m[r * C + c]; }
  SCANDYN_HD static SmallMat zero() {
    SmallMat o;
    for (int k = 0; k < R * C; ++k) o.m[k] = S(0);
    return o;
  }
  SCANDYN_HD static SmallMat identity() {
    SmallMat o = zero();
    for (int k = 0; k < (R < C ? R : C); ++k) o(k, k) = S(1);
    return o;
  }
};

template <class S, int N>
using SmallVec = SmallMat<S, N, 1>;
template <class S>
using Mat6 = SmallMat<S, 6, 6>;
template <class S>
using Vec6 = SmallVec<S, 6>;

template <class S, int R, int K, int C>
SCANDYN_HD SmallMat<S, R, C> operator*(const SmallMat<S, R, K>& A, const SmallMat<S, K, C>& B) {
  SmallMat<S, R, C> o;
  for (int r = 0; r < R; ++r)
    for (int c = 0; c < C; ++c) {
      S s = S(0);
      for (int k = 0; k < K; ++k) s += A(r, k) * B(k, c);
      o(r, c) = s;
    }
  return o;
}

// A^T B
template <class S, int K, int R, int C>
SCANDYN_HD SmallMat<S, R, C> mul_transpose(const SmallMat<S, K, R>& A, const SmallMat<S, K, C>& B) {
  SmallMat<S, R, C> o;
  for (int r = 0; r < R; ++r)
    for (int c = 0; c < C; ++c) {
      S s = S(0);
      for (int k = 0; k < K; ++k) s += A(k, r) * B(k, c);
      o(r, c) = s;
    }
  return o;
}

template <class S, int R, int C>
SCANDYN_HD SmallMat<S, C, R> transpose(const SmallMat<S, R, C>& A) {
  SmallMat<S, C, R> o;
  for (int r = 0; r < R; ++r)
    for (int c = 0; c < C; ++c) o(c, r) = A(r, c);
  return o;
}

template <class S, int R, int C>
SCANDYN_HD SmallMat<S, R, C> operator+(SmallMat<S, R, C> A, const SmallMat<S, R, C>& B) {
  for (int k = 0; k < R * C; ++k) A.m[k] += B.m[k];
  return A;
}

template <class S, int R, int C>
SCANDYN_HD SmallMat<S, R, C> operator-(SmallMat<S, R, C> A, const SmallMat<S, R, C>& B) {
  for (int k = 0; k < R * C; ++k) A.m[k] -= B.m[k];
  return A;
}

// (A + A^T) / 2: removes the rounding asymmetry of a product that is symmetric in
// exact arithmetic, so that Cholesky sees a symmetric matrix.
template <class S, int N>
SCANDYN_HD SmallMat<S, N, N> symmetrize(SmallMat<S, N, N> A) {
  for (int r = 0; r < N; ++r)
    for (int c = r + 1; c < N; ++c) {
      const S s = S(0.5) * (A(r, c) + A(c, r));
      A(r, c) = s;
      A(c, r) = s;
    }
  return A;
}

// In place A = L L^T (lower triangle of A holds L on return). Returns false when a
// pivot is not positive and finite (A not numerically positive definite).
template <class S, int N>
SCANDYN_HD bool cholesky(SmallMat<S, N, N>& A) {
  for (int j = 0; j < N; ++j) {
    S d = A(j, j);
    for (int k = 0; k < j; ++k) d -= A(j, k) * A(j, k);
    if (!(d > S(0)) || !ScalarMath<S>::isfinite(d)) return false;  // d <= 0, NaN or +inf
    const S l = ScalarMath<S>::sqrt(d);
    A(j, j) = l;
    for (int i = j + 1; i < N; ++i) {
      S s = A(i, j);
      for (int k = 0; k < j; ++k) s -= A(i, k) * A(j, k);
      A(i, j) = s / l;
    }
  }
  return true;
}

// Solves (L L^T) X = B in place (X = B on entry) with L from cholesky().
template <class S, int N, int C>
SCANDYN_HD void cholesky_solve(const SmallMat<S, N, N>& L, SmallMat<S, N, C>& X) {
  for (int c = 0; c < C; ++c) {
    for (int i = 0; i < N; ++i) {  // L y = b
      S s = X(i, c);
      for (int k = 0; k < i; ++k) s -= L(i, k) * X(k, c);
      X(i, c) = s / L(i, i);
    }
    for (int i = N - 1; i >= 0; --i) {  // L^T x = y
      S s = X(i, c);
      for (int k = i + 1; k < N; ++k) s -= L(k, i) * X(k, c);
      X(i, c) = s / L(i, i);
    }
  }
}

// ---- conversions from the spatial types ([angular; linear] order) ------------

template <class S>
SCANDYN_HD Vec6<S> to_vec6(const Motion<S>& v) {
  return {{v.w.x, v.w.y, v.w.z, v.v.x, v.v.y, v.v.z}};
}
template <class S>
SCANDYN_HD Vec6<S> to_vec6(const Force<S>& f) {
  return {{f.n.x, f.n.y, f.n.z, f.f.x, f.f.y, f.f.z}};
}
template <class S>
SCANDYN_HD Motion<S> to_motion(const Vec6<S>& x) {
  return {{x.m[0], x.m[1], x.m[2]}, {x.m[3], x.m[4], x.m[5]}};
}
template <class S>
SCANDYN_HD Force<S> to_force(const Vec6<S>& x) {
  return {{x.m[0], x.m[1], x.m[2]}, {x.m[3], x.m[4], x.m[5]}};
}

template <class S>
SCANDYN_HD Mat6<S> to_mat6(const ABInertia<S>& I) {
  Mat6<S> o;
  const Mat3<S> A = I.Iww.full(), C = I.Ivv.full();
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) {
      o(r, c) = A(r, c);
      o(r, c + 3) = I.Iwv(r, c);
      o(r + 3, c) = I.Iwv(c, r);
      o(r + 3, c + 3) = C(r, c);
    }
  return o;
}

// The symmetric part of a 6x6 as an articulated inertia.
template <class S>
SCANDYN_HD ABInertia<S> to_abinertia(const Mat6<S>& M) {
  auto h = [&](int r, int c) { return S(0.5) * (M(r, c) + M(c, r)); };
  ABInertia<S> o;
  o.Iww = {M(0, 0), M(1, 1), M(2, 2), h(0, 1), h(0, 2), h(1, 2)};
  o.Ivv = {M(3, 3), M(4, 4), M(5, 5), h(3, 4), h(3, 5), h(4, 5)};
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) o.Iwv(r, c) = S(0.5) * (M(r, c + 3) + M(c + 3, r));
  return o;
}

// The motion transform X = B_X_A as a 6x6: [E 0; -E [r]x E].
template <class S>
SCANDYN_HD Mat6<S> to_mat6(const Transform<S>& X) {
  Mat6<S> o = Mat6<S>::zero();
  const Mat3<S> ErX = X.E * skew(X.r);
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) {
      o(r, c) = X.E(r, c);
      o(r + 3, c + 3) = X.E(r, c);
      o(r + 3, c) = -ErX(r, c);
    }
  return o;
}

}  // namespace scandyn
