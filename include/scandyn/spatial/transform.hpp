// scandyn/spatial/transform.hpp: Plücker coordinate transforms stored as (E, r).
//
// X = B_X_A maps spatial motion vectors from frame A coordinates to frame B:
//   X = [ E       0 ]      E: 3x3 rotation taking A coordinates to B coordinates
//       [ -E[r]x  E ]      r: position of B's origin, in A coordinates
// Forces map with X* = X^{-T}. For a URDF pose of B in A (rotation R, translation p),
// E = R^T and r = p.
#pragma once

#include "scandyn/spatial/motion.hpp"

namespace scandyn {

template <class S>
struct Transform {
  Mat3<S> E;  // rotation, A coordinates -> B coordinates
  Vec3<S> r;  // origin of B expressed in A (m)

  SCANDYN_HD static Transform identity() { return {Mat3<S>::identity(), Vec3<S>::zero()}; }
  // Transform whose target frame B has pose (R, p) in A.
  SCANDYN_HD static Transform from_pose(const Mat3<S>& R, const Vec3<S>& p) {
    return {transpose(R), p};
  }
  template <class T>
  SCANDYN_HD Transform<T> cast() const { return {E.template cast<T>(), r.template cast<T>()}; }

  // X m: motion from A to B.
  SCANDYN_HD Motion<S> apply(const Motion<S>& m) const {
    return {E * m.w, E * (m.v - cross(r, m.w))};
  }
  // X^{-1} m: motion from B to A.
  SCANDYN_HD Motion<S> apply_inverse(const Motion<S>& m) const {
    const Vec3<S> w = mul_transpose(E, m.w);
    return {w, mul_transpose(E, m.v) + cross(r, w)};
  }
  // X* f: force from A to B.
  SCANDYN_HD Force<S> apply(const Force<S>& f) const {
    return {E * (f.n - cross(r, f.f)), E * f.f};
  }
  // X^T f = (X*)^{-1} f: force from B to A.
  SCANDYN_HD Force<S> apply_transpose(const Force<S>& f) const {
    const Vec3<S> lin = mul_transpose(E, f.f);
    return {mul_transpose(E, f.n) + cross(r, lin), lin};
  }
  // X^{-1} = A_X_B.
  SCANDYN_HD Transform inverse() const { return {transpose(E), -(E * r)}; }
};

// Composition C_X_A = C_X_B * B_X_A.
template <class S>
SCANDYN_HD Transform<S> operator*(const Transform<S>& cXb, const Transform<S>& bXa) {
  return {cXb.E * bXa.E, bXa.r + mul_transpose(bXa.E, cXb.r)};
}

}  // namespace scandyn
