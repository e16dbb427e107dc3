// scandyn/spatial/inertia.hpp: rigid-body spatial inertia (10 parameters) and
// articulated-body inertia (a symmetric 6x6 in 3x3 blocks).
//
// In [angular; linear] order a rigid inertia about a frame origin is
//   I = [ Ibar   [h]x ]     m: mass, h = m c (c: centre of mass in this frame),
//       [ [h]x^T  m 1 ]     Ibar: rotational inertia about the frame origin.
#pragma once

#include "scandyn/spatial/transform.hpp"

namespace scandyn {

template <class S>
struct Inertia {
  S m;        // mass (kg)
  Vec3<S> h;  // first moment of mass m c (kg m)
  Sym3<S> I;  // rotational inertia about the frame origin (kg m^2)

  SCANDYN_HD static Inertia zero() { return {S(0), Vec3<S>::zero(), Sym3<S>::zero()}; }
  // From mass, centre of mass c and rotational inertia Ic about c (axes of this frame).
  SCANDYN_HD static Inertia from_com(S mass, const Vec3<S>& c, const Sym3<S>& Ic) {
    // parallel axis: Ibar = Ic + m (|c|^2 1 - c c^T)
    Sym3<S> Ib = Ic - sym_outer(c, mass);
    const S cc = mass * dot(c, c);
    Ib.xx += cc; Ib.yy += cc; Ib.zz += cc;
    return {mass, mass * c, Ib};
  }
  template <class T>
  SCANDYN_HD Inertia<T> cast() const { return {T(m), h.template cast<T>(), I.template cast<T>()}; }

  // I v: momentum of a body moving with v.
  SCANDYN_HD Force<S> operator*(const Motion<S>& v) const {
    return {I * v.w + cross(h, v.v), m * v.v - cross(h, v.w)};
  }
  // Given this inertia in frame B and X = B_X_A, returns X^T I X: the same inertia in A.
  SCANDYN_HD Inertia transform_transpose(const Transform<S>& X) const {
    const Vec3<S> y = mul_transpose(X.E, h);  // h in A axes, still about B's origin
    const Vec3<S>& r = X.r;
    // Ibar_A = E^T Ibar E - ([y]x[r]x + [r]x[y]x) - m [r]x[r]x
    Sym3<S> IA = congruence_transpose(X.E, I) - skew_sym_product2(y, r) - sym_outer(r, m);
    const S rr = m * dot(r, r);
    IA.xx += rr; IA.yy += rr; IA.zz += rr;
    return {m, y + m * r, IA};
  }
};

template <class S>
SCANDYN_HD Inertia<S> operator+(const Inertia<S>& a, const Inertia<S>& b) {
  return {a.m + b.m, a.h + b.h, a.I + b.I};
}
template <class S>
SCANDYN_HD Inertia<S>& operator+=(Inertia<S>& a, const Inertia<S>& b) {
  a = a + b;
  return a;
}

// Articulated-body inertia, a symmetric 6x6 matrix
//   IA = [ Iww    Iwv ]
//        [ Iwv^T  Ivv ]
template <class S>
struct ABInertia {
  Sym3<S> Iww;  // angular-angular block (kg m^2)
  Mat3<S> Iwv;  // angular-linear block (kg m)
  Sym3<S> Ivv;  // linear-linear block (kg)

  template <class T>
  SCANDYN_HD ABInertia<T> cast() const {
    return {Iww.template cast<T>(), Iwv.template cast<T>(), Ivv.template cast<T>()};
  }
  SCANDYN_HD static ABInertia from(const Inertia<S>& I) {
    return {I.I, skew(I.h), Sym3<S>{I.m, I.m, I.m, S(0), S(0), S(0)}};
  }
  // IA v
  SCANDYN_HD Force<S> operator*(const Motion<S>& v) const {
    return {Iww * v.w + Iwv * v.v, mul_transpose(Iwv, v.w) + Ivv * v.v};
  }
  // IA - U U^T / D, with the 6-vector U given as a force.
  SCANDYN_HD ABInertia minus_outer(const Force<S>& U, S Dinv) const {
    const Vec3<S> Un = Dinv * U.n;
    Mat3<S> H = Iwv;
    for (int r = 0; r < 3; ++r) {
      H.m[3 * r + 0] -= Un[r] * U.f.x;
      H.m[3 * r + 1] -= Un[r] * U.f.y;
      H.m[3 * r + 2] -= Un[r] * U.f.z;
    }
    return {Iww - sym_outer(U.n, Dinv), H, Ivv - sym_outer(U.f, Dinv)};
  }
  // Given this inertia in frame B and X = B_X_A, returns X^T IA X: the same inertia in A.
  SCANDYN_HD ABInertia transform_transpose(const Transform<S>& X) const {
    // rotate: blocks' = E^T blocks E
    const Sym3<S> A = congruence_transpose(X.E, Iww);
    const Sym3<S> C = congruence_transpose(X.E, Ivv);
    const Mat3<S> H = mul_transpose(X.E, Iwv * X.E);
    // shift by r: with P = [1 0; -[r]x 1], result = P^T I' P
    //   Iww'' = A - H[r]x - (H[r]x)^T - [r]x C [r]x,  Iwv'' = H + [r]x C,  Ivv'' = C
    const Mat3<S> Rx = skew(X.r);
    const Mat3<S> Cf = C.full();
    const Mat3<S> RC = Rx * Cf;             // [r]x C
    const Mat3<S> HR = mul_skew(H, X.r);    // H [r]x
    const Mat3<S> RCR = mul_skew(RC, X.r);  // [r]x C [r]x
    Sym3<S> Aw = A;
    Aw.xx -= S(2) * HR.m[0] + RCR.m[0];
    Aw.yy -= S(2) * HR.m[4] + RCR.m[4];
    Aw.zz -= S(2) * HR.m[8] + RCR.m[8];
    Aw.xy -= HR.m[1] + HR.m[3] + RCR.m[1];
    Aw.xz -= HR.m[2] + HR.m[6] + RCR.m[2];
    Aw.yz -= HR.m[5] + HR.m[7] + RCR.m[5];
    return {Aw, H + RC, C};
  }
};

template <class S>
SCANDYN_HD ABInertia<S> operator+(const ABInertia<S>& a, const ABInertia<S>& b) {
  return {a.Iww + b.Iww, a.Iwv + b.Iwv, a.Ivv + b.Ivv};
}
template <class S>
SCANDYN_HD ABInertia<S>& operator+=(ABInertia<S>& a, const ABInertia<S>& b) {
  a = a + b;
  return a;
}

}  // namespace scandyn
