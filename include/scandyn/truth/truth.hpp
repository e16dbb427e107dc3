// scandyn/truth/truth.hpp: the high-precision truth. The serial reference
// algorithms (RNEA, bias forces, CRBA, ABA, CRBA + L^T L) instantiated in
// long double (x87 extended, 64-bit significand, epsilon 1.1e-19) and in
// __float128 (binary128, epsilon 1.9e-34) by library scandyn_truth, for the
// tests and the accuracy tools only (the engines never link it).
//
// The same code as the float and double reference (src/algorithm/reference_impl.hpp
// instantiated for the wider scalars; math calls through ScalarMath<S>), on a model
// converted from the double one exactly (every double is a long double and a
// binary128): the truth solves the very problem the double reference solves, with
// rounding errors about 10^3 (long double) and 10^18 (binary128) times smaller.
#pragma once

#include <cmath>
#include <cstddef>
#include <limits>
#include <vector>

#include "scandyn/algorithm/configuration.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/truth/float128.hpp"

namespace scandyn::truth {

// The model in T: the double model converted exactly (ModelTpl::cast, as for float),
// then made consistent in T. A double model's rotations Xtree.E (from URDF rpy
// angles) and joint axes are orthonormal and unit only to about 1e-16, and the
// algorithms use E^T as E^-1 and |axis| = 1, so in T the converted model would be a
// slightly inconsistent one: measured, CRBA and the RNEA's columns then disagree by
// 8e-17 in binary128 on hyq, atlas and random trees (chains with axis-aligned joints
// are exact). So each E is orthonormalised (Newton-Schulz, E <- E (3 - E^T E) / 2,
// quadratic: 1e-16 -> 1e-32 -> below binary128's epsilon) and each axis normalised,
// in T. The change is within double's rounding of the model (a relative 1e-16), far
// below every error the truth measures except a correctly rounded double's.
template <class T>
ModelTpl<T> truth_model(const Model& model) {
  ModelTpl<T> m = model.template cast<T>();
  for (Body<T>& b : m.bodies) {
    Mat3<T>& E = b.Xtree.E;
    for (int it = 0; it < 4; ++it) {
      const Mat3<T> EtE = mul_transpose(E, E);  // E^T E
      Mat3<T> K = Mat3<T>::zero();
      for (int k = 0; k < 9; ++k) K.m[k] = (k % 4 == 0 ? T(3) : T(0)) - EtE.m[k];
      E = E * K;
      for (int k = 0; k < 9; ++k) E.m[k] = E.m[k] / T(2);
    }
    b.axis = (T(1) / ScalarMath<T>::sqrt(dot(b.axis, b.axis))) * b.axis;
  }
  return m;
}

// The reference algorithms in T (long double or float128) on double inputs: q has
// nq entries, qd, qdd and tau nv (nq = nv + the quaternions' extra entries for a
// floating base or spherical joints: scandyn/model/model.hpp), fext nbodies body
// wrenches or null; results in T. Models with multi-DoF joints run the reference's
// general path (rnea_at, crba_at, aba_at) in T.
//
// Quaternions: a double unit quaternion is unit only to about 1e-16, and the joint
// transform (quat_to_matrix) assumes a unit one, so (as for the model's rotations
// above) each quaternion of q is normalised again in T before use: the truth solves
// the problem at the exactly unit quaternion nearest the double one, which differs
// from the double input by its rounding (a relative 1e-16).
template <class T>
class Truth {
 public:
  // mass_matrix = false: no nv x nv workspace (mass and fd_jsi then throw)
  explicit Truth(const Model& model, bool mass_matrix = true)
      : model_(truth_model<T>(model)), data_(model_, mass_matrix) {
    const std::size_t n = static_cast<std::size_t>(model_.nv());
    q_.resize(static_cast<std::size_t>(model_.nq()));
    b_.resize(n);
    c_.resize(n);
  }
  const ModelTpl<T>& model() const { return model_; }
  Index nv() const { return model_.nv(); }
  Index nq() const { return model_.nq(); }
  // q (nq) in T as the last call used it: the double q widened, quaternions
  // normalised in T (what the truth's results are the exact dynamics of)
  const std::vector<T>& q() const { return q_; }

  // tau = RNEA(q, qd, qdd)
  void id(const double* q, const double* qd, const double* qdd, T* tau, const Force<double>* fext = nullptr) {
    widen(q, qd, qdd, fext);
    rnea(model_, data_, q_.data(), b_.data(), c_.data(), tau, fext ? f_.data() : nullptr);
  }
  // h = RNEA(q, qd, 0)
  void bias(const double* q, const double* qd, T* h, const Force<double>* fext = nullptr) {
    widen(q, qd, nullptr, fext);
    bias_forces(model_, data_, q_.data(), b_.data(), h, fext ? f_.data() : nullptr);
  }
  // M(q), nv x nv row-major
  void mass(const double* q, T* M) {
    widen(q, nullptr, nullptr, nullptr);
    crba(model_, data_, q_.data(), M);
  }
  // qdd = FD(q, qd, tau) by ABA (the truth of every forward dynamics)
  Status fd(const double* q, const double* qd, const double* tau, T* qdd, const Force<double>* fext = nullptr) {
    widen(q, qd, tau, fext);
    return aba(model_, data_, q_.data(), b_.data(), c_.data(), qdd, fext ? f_.data() : nullptr);
  }
  // qdd = FD(q, qd, tau) by CRBA + L^T L (a second route, for the tests)
  Status fd_jsi(const double* q, const double* qd, const double* tau, T* qdd, const Force<double>* fext = nullptr) {
    widen(q, qd, tau, fext);
    return scandyn::fd_jsi(model_, data_, q_.data(), b_.data(), c_.data(), qdd, fext ? f_.data() : nullptr);
  }

 private:
  void widen(const double* q, const double* y, const double* z, const Force<double>* fext) {
    for (std::size_t i = 0; i < q_.size(); ++i) q_[i] = T(q[i]);
    normalize_configuration(model_, q_.data());  // quaternions unit in T
    for (std::size_t i = 0; i < b_.size(); ++i) {
      if (y) b_[i] = T(y[i]);
      if (z) c_[i] = T(z[i]);
    }
    if (fext) {
      const std::size_t nb = static_cast<std::size_t>(model_.nbodies());
      f_.resize(nb);
      for (std::size_t i = 0; i < nb; ++i) f_[i] = fext[i].template cast<T>();
    }
  }

  ModelTpl<T> model_;
  DataTpl<T> data_;
  std::vector<T> q_;           // (nq) positions in T
  std::vector<T> b_, c_;       // (nv) the other inputs in T
  std::vector<Force<T>> f_;    // (nbodies) external wrenches in T
};

// scandyn::rel_err against a truth in T: max_i |x_i - ref_i| / max(1, max_i |ref_i|),
// the difference taken in T (a double x is compared with the truth itself, not with
// the truth rounded to double, so a correctly rounded double shows its half ulp).
// NaN when any x_i or ref_i is NaN.
template <class T, class A>
double rel_err(const A* x, const T* ref, std::size_t n) {
  using M = ScalarMath<T>;
  T scale = T(1), err = T(0);
  for (std::size_t i = 0; i < n; ++i) {
    const T e = M::abs(T(x[i]) - ref[i]);
    if (!(e == e)) return std::numeric_limits<double>::quiet_NaN();
    if (e > err) err = e;
    const T r = M::abs(ref[i]);
    if (r > scale) scale = r;
  }
  return double(err / scale);
}

}  // namespace scandyn::truth
