// scandyn/spatial/quaternion.hpp: unit quaternions of rotation matrices.
#pragma once

#include "scandyn/spatial/vec3.hpp"

namespace scandyn {

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
