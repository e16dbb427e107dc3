// scandyn/spatial/quaternion.hpp: unit quaternions (x, y, z, w): of rotation
// matrices, and as the positions of spherical and free joints.
//
// A joint's quaternion q rotates vectors of a child frame into its parent frame:
// v_parent = R(q) v_child. Arrays hold (x, y, z, w), as in q vectors and CSV files.
#pragma once

#include "scandyn/spatial/vec3.hpp"

namespace scandyn {

// R(q), child coordinates -> parent coordinates, of the unit quaternion
// (x, y, z, w) = p[0..3] (the caller keeps it unit: inputs are normalised on reading
// and after each integration step).
template <class S>
SCANDYN_HD Mat3<S> quat_to_matrix(const S* p) {
  const S x = p[0], y = p[1], z = p[2], w = p[3];
  const S x2 = x + x, y2 = y + y, z2 = z + z;
  const S xx = x * x2, yy = y * y2, zz = z * z2;
  const S xy = x * y2, xz = x * z2, yz = y * z2;
  const S wx = w * x2, wy = w * y2, wz = w * z2;
  return {{S(1) - (yy + zz), xy - wz, xz + wy,
           xy + wz, S(1) - (xx + zz), yz - wx,
           xz - wy, yz + wx, S(1) - (xx + yy)}};
}

// Hamilton product a b of quaternions (x, y, z, w): rotation by b, then by a.
template <class S>
SCANDYN_HD void quat_multiply(const S* a, const S* b, S* out) {
  const S x = a[3] * b[0] + a[0] * b[3] + a[1] * b[2] - a[2] * b[1];
  const S y = a[3] * b[1] - a[0] * b[2] + a[1] * b[3] + a[2] * b[0];
  const S z = a[3] * b[2] + a[0] * b[1] - a[1] * b[0] + a[2] * b[3];
  const S w = a[3] * b[3] - a[0] * b[0] - a[1] * b[1] - a[2] * b[2];
  out[0] = x, out[1] = y, out[2] = z, out[3] = w;
}

// A unit quaternion (x, y, z, w): the rotation v -> q v q*.
template <class S>
struct Quat {
  S x, y, z, w;
};

// The unit quaternion of a rotation matrix R (R v rotates v), with w >= 0 (of the
// two quaternions q and -q of R, the one Eigen and Pinocchio print when w != 0).
// Shepperd's method: the square root is taken of the largest of 1 + trace and
// 1 + 2 R_kk - trace, so it never loses precision near a half turn.
template <class S>
SCANDYN_HD Quat<S> quaternion_of(const Mat3<S>& R) {
  const S t = R(0, 0) + R(1, 1) + R(2, 2);
  Quat<S> q;
  if (t >= R(0, 0) && t >= R(1, 1) && t >= R(2, 2)) {
    const S s = ScalarMath<S>::sqrt(S(1) + t) * S(2);  // 4 w
    q = {(R(2, 1) - R(1, 2)) / s, (R(0, 2) - R(2, 0)) / s, (R(1, 0) - R(0, 1)) / s, S(0.25) * s};
  } else if (R(0, 0) >= R(1, 1) && R(0, 0) >= R(2, 2)) {
    const S s = ScalarMath<S>::sqrt(S(1) + R(0, 0) - R(1, 1) - R(2, 2)) * S(2);  // 4 x
    q = {S(0.25) * s, (R(0, 1) + R(1, 0)) / s, (R(0, 2) + R(2, 0)) / s, (R(2, 1) - R(1, 2)) / s};
  } else if (R(1, 1) >= R(2, 2)) {
    const S s = ScalarMath<S>::sqrt(S(1) + R(1, 1) - R(0, 0) - R(2, 2)) * S(2);  // 4 y
    q = {(R(0, 1) + R(1, 0)) / s, S(0.25) * s, (R(1, 2) + R(2, 1)) / s, (R(0, 2) - R(2, 0)) / s};
  } else {
    const S s = ScalarMath<S>::sqrt(S(1) + R(2, 2) - R(0, 0) - R(1, 1)) * S(2);  // 4 z
    q = {(R(0, 2) + R(2, 0)) / s, (R(1, 2) + R(2, 1)) / s, S(0.25) * s, (R(1, 0) - R(0, 1)) / s};
  }
  if (q.w < S(0)) q = {-q.x, -q.y, -q.z, -q.w};
  return q;
}

}  // namespace scandyn
