// scandyn/spatial/vec3.hpp: 3-vectors, 3x3 matrices and symmetric 3x3 matrices.
//
// Plain, trivially copyable structs with SCANDYN_HD operations: the same code
// runs in the serial reference, the OpenMP backend and CUDA kernels.
#pragma once

#include <cmath>

#include "scandyn/config.hpp"
#include "scandyn/spatial/scalar.hpp"

namespace scandyn {

template <class S>
struct Vec3 {
  S x, y, z;

  SCANDYN_HD static Vec3 zero() { return {S(0), S(0), S(0)}; }
  SCANDYN_HD S operator[](int i) const { return i == 0 ? x : (i == 1 ? y : z); }
  template <class T>
  SCANDYN_HD Vec3<T> cast() const { return {T(x), T(y), T(z)}; }
};

template <class S>
SCANDYN_HD Vec3<S> operator+(const Vec3<S>& a, const Vec3<S>& b) {
  return {a.x + b.x, a.y + b.y, a.z + b.z};
}
template <class S>
SCANDYN_HD Vec3<S> operator-(const Vec3<S>& a, const Vec3<S>& b) {
  return {a.x - b.x, a.y - b.y, a.z - b.z};
}
template <class S>
SCANDYN_HD Vec3<S> operator-(const Vec3<S>& a) {
  return {-a.x, -a.y, -a.z};
}
template <class S>
SCANDYN_HD Vec3<S> operator*(S s, const Vec3<S>& a) {
  return {s * a.x, s * a.y, s * a.z};
}
template <class S>
SCANDYN_HD Vec3<S>& operator+=(Vec3<S>& a, const Vec3<S>& b) {
  a.x += b.x; a.y += b.y; a.z += b.z;
  return a;
}
template <class S>
SCANDYN_HD Vec3<S>& operator-=(Vec3<S>& a, const Vec3<S>& b) {
  a.x -= b.x; a.y -= b.y; a.z -= b.z;
  return a;
}
template <class S>
SCANDYN_HD S dot(const Vec3<S>& a, const Vec3<S>& b) {
  return a.x * b.x + a.y * b.y + a.z * b.z;
}
template <class S>
SCANDYN_HD Vec3<S> cross(const Vec3<S>& a, const Vec3<S>& b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}

// 3x3 matrix, row-major: m[3*row + col].
template <class S>
struct Mat3 {
  S m[9];

  SCANDYN_HD static Mat3 identity() {
    return {{S(1), S(0), S(0), S(0), S(1), S(0), S(0), S(0), S(1)}};
  }
  SCANDYN_HD static Mat3 zero() {
    return {{S(0), S(0), S(0), S(0), S(0), S(0), S(0), S(0), S(0)}};
  }
  SCANDYN_HD S operator()(int r, int c) const { return m[3 * r + c]; }
  SCANDYN_HD S& operator()(int r, int c) { return m[3 * r + c]; }
  template <class T>
  SCANDYN_HD Mat3<T> cast() const {
    Mat3<T> o;
    for (int k = 0; k < 9; ++k) o.m[k] = T(m[k]);
    return o;
  }
};

// A b
template <class S>
SCANDYN_HD Vec3<S> operator*(const Mat3<S>& A, const Vec3<S>& b) {
  return {A.m[0] * b.x + A.m[1] * b.y + A.m[2] * b.z,
          A.m[3] * b.x + A.m[4] * b.y + A.m[5] * b.z,
          A.m[6] * b.x + A.m[7] * b.y + A.m[8] * b.z};
}
// A^T b
template <class S>
SCANDYN_HD Vec3<S> mul_transpose(const Mat3<S>& A, const Vec3<S>& b) {
  return {A.m[0] * b.x + A.m[3] * b.y + A.m[6] * b.z,
          A.m[1] * b.x + A.m[4] * b.y + A.m[7] * b.z,
          A.m[2] * b.x + A.m[5] * b.y + A.m[8] * b.z};
}
// A B
template <class S>
SCANDYN_HD Mat3<S> operator*(const Mat3<S>& A, const Mat3<S>& B) {
  Mat3<S> C;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c)
      C.m[3 * r + c] = A.m[3 * r] * B.m[c] + A.m[3 * r + 1] * B.m[3 + c] + A.m[3 * r + 2] * B.m[6 + c];
  return C;
}
// A^T B
template <class S>
SCANDYN_HD Mat3<S> mul_transpose(const Mat3<S>& A, const Mat3<S>& B) {
  Mat3<S> C;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c)
      C.m[3 * r + c] = A.m[r] * B.m[c] + A.m[3 + r] * B.m[3 + c] + A.m[6 + r] * B.m[6 + c];
  return C;
}
template <class S>
SCANDYN_HD Mat3<S> transpose(const Mat3<S>& A) {
  return {{A.m[0], A.m[3], A.m[6], A.m[1], A.m[4], A.m[7], A.m[2], A.m[5], A.m[8]}};
}
template <class S>
SCANDYN_HD Mat3<S> operator+(const Mat3<S>& A, const Mat3<S>& B) {
  Mat3<S> C;
  for (int k = 0; k < 9; ++k) C.m[k] = A.m[k] + B.m[k];
  return C;
}
template <class S>
SCANDYN_HD Mat3<S> operator-(const Mat3<S>& A, const Mat3<S>& B) {
  Mat3<S> C;
  for (int k = 0; k < 9; ++k) C.m[k] = A.m[k] - B.m[k];
  return C;
}
// [v]x, the matrix of v x (.)
template <class S>
SCANDYN_HD Mat3<S> skew(const Vec3<S>& v) {
  return {{S(0), -v.z, v.y, v.z, S(0), -v.x, -v.y, v.x, S(0)}};
}
// A [v]x, computed without forming the skew matrix.
template <class S>
SCANDYN_HD Mat3<S> mul_skew(const Mat3<S>& A, const Vec3<S>& v) {
  Mat3<S> C;
  for (int r = 0; r < 3; ++r) {
    const S a0 = A.m[3 * r], a1 = A.m[3 * r + 1], a2 = A.m[3 * r + 2];
    // [a0 a1 a2] * [[0,-z,y],[z,0,-x],[-y,x,0]]
    C.m[3 * r + 0] = a1 * v.z - a2 * v.y;
    C.m[3 * r + 1] = a2 * v.x - a0 * v.z;
    C.m[3 * r + 2] = a0 * v.y - a1 * v.x;
  }
  return C;
}

// Rotation matrix of angle t about the unit axis a (Rodrigues):
// R = I + sin t [a]x + (1 - cos t) [a]x^2. R maps child coordinates to parent ones.
template <class S>
SCANDYN_HD Mat3<S> axis_angle(const Vec3<S>& a, S s, S c) {
  const S t = S(1) - c;
  const S xs = a.x * s, ys = a.y * s, zs = a.z * s;
  const S xt = a.x * t, yt = a.y * t, zt = a.z * t;
  return {{xt * a.x + c, xt * a.y - zs, xt * a.z + ys,
           yt * a.x + zs, yt * a.y + c, yt * a.z - xs,
           zt * a.x - ys, zt * a.y + xs, zt * a.z + c}};
}

// Rotation matrix from roll-pitch-yaw (URDF convention): R = Rz(yaw) Ry(pitch) Rx(roll).
template <class S>
SCANDYN_HD Mat3<S> rpy_matrix(S roll, S pitch, S yaw) {
  using M = ScalarMath<S>;
  const S cr = M::cos(roll), sr = M::sin(roll), cp = M::cos(pitch), sp = M::sin(pitch);
  const S cy = M::cos(yaw), sy = M::sin(yaw);
  return {{cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr,
           sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr,
           -sp, cp * sr, cp * cr}};
}

// Symmetric 3x3 matrix stored as its 6 distinct entries.
template <class S>
struct Sym3 {
  S xx, yy, zz, xy, xz, yz;

  SCANDYN_HD static Sym3 zero() { return {S(0), S(0), S(0), S(0), S(0), S(0)}; }
  SCANDYN_HD Mat3<S> full() const { return {{xx, xy, xz, xy, yy, yz, xz, yz, zz}}; }
  // Symmetric part of a general matrix ((A + A^T) / 2).
  SCANDYN_HD static Sym3 from(const Mat3<S>& A) {
    const S h = S(0.5);
    return {A.m[0], A.m[4], A.m[8], h * (A.m[1] + A.m[3]), h * (A.m[2] + A.m[6]),
            h * (A.m[5] + A.m[7])};
  }
  template <class T>
  SCANDYN_HD Sym3<T> cast() const { return {T(xx), T(yy), T(zz), T(xy), T(xz), T(yz)}; }
};

template <class S>
SCANDYN_HD Vec3<S> operator*(const Sym3<S>& A, const Vec3<S>& b) {
  return {A.xx * b.x + A.xy * b.y + A.xz * b.z, A.xy * b.x + A.yy * b.y + A.yz * b.z,
          A.xz * b.x + A.yz * b.y + A.zz * b.z};
}
template <class S>
SCANDYN_HD Sym3<S> operator+(const Sym3<S>& A, const Sym3<S>& B) {
  return {A.xx + B.xx, A.yy + B.yy, A.zz + B.zz, A.xy + B.xy, A.xz + B.xz, A.yz + B.yz};
}
template <class S>
SCANDYN_HD Sym3<S> operator-(const Sym3<S>& A, const Sym3<S>& B) {
  return {A.xx - B.xx, A.yy - B.yy, A.zz - B.zz, A.xy - B.xy, A.xz - B.xz, A.yz - B.yz};
}
template <class S>
SCANDYN_HD Sym3<S>& operator+=(Sym3<S>& A, const Sym3<S>& B) {
  A = A + B;
  return A;
}
// a b^T + b a^T, symmetric
template <class S>
SCANDYN_HD Sym3<S> sym_outer2(const Vec3<S>& a, const Vec3<S>& b) {
  return {S(2) * a.x * b.x, S(2) * a.y * b.y, S(2) * a.z * b.z, a.x * b.y + a.y * b.x,
          a.x * b.z + a.z * b.x, a.y * b.z + a.z * b.y};
}
// s a a^T
template <class S>
SCANDYN_HD Sym3<S> sym_outer(const Vec3<S>& a, S s) {
  const Vec3<S> sa = s * a;
  return {sa.x * a.x, sa.y * a.y, sa.z * a.z, sa.x * a.y, sa.x * a.z, sa.y * a.z};
}
// E^T A E for a general E: the congruence that re-expresses A in the frame E maps from.
template <class S>
SCANDYN_HD Sym3<S> congruence_transpose(const Mat3<S>& E, const Sym3<S>& A) {
  // AE = A E (3x3), result = E^T (A E), only the 6 upper entries.
  const Mat3<S> Af = A.full();
  const Mat3<S> AE = Af * E;
  const S* e = E.m;
  const S* b = AE.m;
  auto entry = [&](int r, int c) {
    return e[r] * b[c] + e[3 + r] * b[3 + c] + e[6 + r] * b[6 + c];
  };
  return {entry(0, 0), entry(1, 1), entry(2, 2), entry(0, 1), entry(0, 2), entry(1, 2)};
}
// [a]x [b]x + [b]x [a]x = a b^T + b a^T - 2 (a.b) I, symmetric.
template <class S>
SCANDYN_HD Sym3<S> skew_sym_product2(const Vec3<S>& a, const Vec3<S>& b) {
  Sym3<S> o = sym_outer2(a, b);
  const S d = S(2) * dot(a, b);
  o.xx -= d; o.yy -= d; o.zz -= d;
  return o;
}

}  // namespace scandyn
