// scandyn/spatial/motion.hpp: spatial motion and force vectors, [angular; linear].
//
// Motion m = [w; v]: angular velocity w and the linear velocity v of the body-fixed
// point at the frame origin. Force f = [n; f]: moment n about the frame origin and
// linear force f. The pairing m . f = w.n + v.f is power.
#pragma once

#include "scandyn/spatial/vec3.hpp"

namespace scandyn {

template <class S>
struct Motion {
  Vec3<S> w;  // angular part (rad/s, rad/s^2)
  Vec3<S> v;  // linear part at the frame origin (m/s, m/s^2)

  SCANDYN_HD static Motion zero() { return {Vec3<S>::zero(), Vec3<S>::zero()}; }
  // Component k of the 6-vector [w; v].
  SCANDYN_HD S operator[](int k) const { return k < 3 ? w[k] : v[k - 3]; }
  template <class T>
  SCANDYN_HD Motion<T> cast() const { return {w.template cast<T>(), v.template cast<T>()}; }
};

template <class S>
struct Force {
  Vec3<S> n;  // moment about the frame origin (N m)
  Vec3<S> f;  // linear force (N)

  SCANDYN_HD static Force zero() { return {Vec3<S>::zero(), Vec3<S>::zero()}; }
  SCANDYN_HD S operator[](int k) const { return k < 3 ? n[k] : f[k - 3]; }
  template <class T>
  SCANDYN_HD Force<T> cast() const { return {n.template cast<T>(), f.template cast<T>()}; }
};

template <class S>
SCANDYN_HD Motion<S> operator+(const Motion<S>& a, const Motion<S>& b) { return {a.w + b.w, a.v + b.v}; }
template <class S>
SCANDYN_HD Motion<S> operator-(const Motion<S>& a, const Motion<S>& b) { return {a.w - b.w, a.v - b.v}; }
template <class S>
SCANDYN_HD Motion<S> operator-(const Motion<S>& a) { return {-a.w, -a.v}; }
template <class S>
SCANDYN_HD Motion<S> operator*(S s, const Motion<S>& a) { return {s * a.w, s * a.v}; }
template <class S>
SCANDYN_HD Motion<S>& operator+=(Motion<S>& a, const Motion<S>& b) { a.w += b.w; a.v += b.v; return a; }

template <class S>
SCANDYN_HD Force<S> operator+(const Force<S>& a, const Force<S>& b) { return {a.n + b.n, a.f + b.f}; }
template <class S>
SCANDYN_HD Force<S> operator-(const Force<S>& a, const Force<S>& b) { return {a.n - b.n, a.f - b.f}; }
template <class S>
SCANDYN_HD Force<S> operator-(const Force<S>& a) { return {-a.n, -a.f}; }
template <class S>
SCANDYN_HD Force<S> operator*(S s, const Force<S>& a) { return {s * a.n, s * a.f}; }
template <class S>
SCANDYN_HD Force<S>& operator+=(Force<S>& a, const Force<S>& b) { a.n += b.n; a.f += b.f; return a; }
template <class S>
SCANDYN_HD Force<S>& operator-=(Force<S>& a, const Force<S>& b) { a.n -= b.n; a.f -= b.f; return a; }

// Power pairing m . f.
template <class S>
SCANDYN_HD S dot(const Motion<S>& m, const Force<S>& f) { return dot(m.w, f.n) + dot(m.v, f.f); }

// Motion cross product m x u (Featherstone's crm(m) u): [w x uw; w x uv + v x uw].
template <class S>
SCANDYN_HD Motion<S> cross(const Motion<S>& m, const Motion<S>& u) {
  return {cross(m.w, u.w), cross(m.w, u.v) + cross(m.v, u.w)};
}
// Force cross product m x* f (Featherstone's crf(m) f = -crm(m)^T f): [w x n + v x f; w x f].
template <class S>
SCANDYN_HD Force<S> cross(const Motion<S>& m, const Force<S>& f) {
  return {cross(m.w, f.n) + cross(m.v, f.f), cross(m.w, f.f)};
}

}  // namespace scandyn
