// Cases of the chain JVP / VJP tests (tests/algorithm/test_chain_directional.cpp on
// the host, tests/cuda/test_cuda_chain_directional.cu on the device): random states
// and directions of B instances, the serial aba_jvp / aba_vjp of each as the
// reference, and the serial float's error on the same inputs (the case's
// conditioning, from which the tolerances follow).
#pragma once

#include <cmath>
#include <cstdio>
#include <random>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "scandyn/algorithm/directional_derivatives.hpp"
#include "test_util.hpp"

namespace scandyn::test::chain_dir {

// B instances (SoA, n x B) of random states and directions, and the serial double
// aba_jvp / aba_vjp of each.
struct Case {
  Index n = 0, B = 0;
  std::vector<double> q, qd, tau, dq, dqd, dtau, w;
  std::vector<Force<double>> fext;  // (B x n) or empty
  std::vector<double> qdd, dqdd, gq, gqd, gtau;  // the serial references
};

// Instance b's inputs q, qd, tau, dq, dqd, dtau, w of c (n each), in precision T, into x.
template <class T>
void instance_inputs(const Case& c, Index b, std::vector<T> (&x)[7]) {
  const std::vector<double>* in[7] = {&c.q, &c.qd, &c.tau, &c.dq, &c.dqd, &c.dtau, &c.w};
  for (int k = 0; k < 7; ++k) {
    x[k].resize(c.n);
    for (Index i = 0; i < c.n; ++i) x[k][i] = static_cast<T>((*in[k])[i * c.B + b]);
  }
}

inline Case make_case(const Model& model, Index B, unsigned seed, bool with_fext, double q_scale = 1) {
  std::mt19937_64 rng(seed);
  const Index n = model.nv();
  Case c;
  c.n = n;
  c.B = B;
  const int nb = static_cast<int>(n * B);
  c.q = test::random_vector(rng, nb, -3 * q_scale, 3 * q_scale);
  c.qd = test::random_vector(rng, nb, -1, 1);
  c.tau = test::random_vector(rng, nb, -2, 2);
  c.dq = test::random_vector(rng, nb, -1, 1);
  c.dqd = test::random_vector(rng, nb, -1, 1);
  c.dtau = test::random_vector(rng, nb, -1, 1);
  c.w = test::random_vector(rng, nb, -1, 1);
  if (with_fext) c.fext = test::random_wrenches<double>(rng, nb, 1.0);
  for (auto* v : {&c.qdd, &c.dqdd, &c.gq, &c.gqd, &c.gtau}) v->assign(c.q.size(), NAN);
  AbaJvpData<double> jd(model);
  std::vector<double> x[7], out[5];
  for (auto& o : out) o.resize(n);
  for (Index b = 0; b < B; ++b) {
    instance_inputs(c, b, x);
    const Force<double>* f = with_fext ? c.fext.data() + b * n : nullptr;
    EXPECT_TRUE(aba_jvp(model, jd, x[0].data(), x[1].data(), x[2].data(), f, x[3].data(), x[4].data(), x[5].data(),
                        out[1].data(), out[0].data())
                    .ok());
    EXPECT_TRUE(aba_vjp(model, jd, x[0].data(), x[1].data(), x[2].data(), f, x[6].data(), out[2].data(),
                        out[3].data(), out[4].data(), out[0].data())
                    .ok());
    std::vector<double>* ref[5] = {&c.qdd, &c.dqdd, &c.gq, &c.gqd, &c.gtau};
    for (int k = 0; k < 5; ++k)
      for (Index i = 0; i < n; ++i) (*ref[k])[i * B + b] = out[k][i];
  }
  return c;
}

// The case's inputs in precision S (SoA, n x B; fext B x n, or empty).
template <class S>
struct Inputs {
  std::vector<S> q, qd, tau, dq, dqd, dtau, w;
  std::vector<Force<S>> fext;
  explicit Inputs(const Case& c)
      : q(test::cast_vector<S>(c.q)),
        qd(test::cast_vector<S>(c.qd)),
        tau(test::cast_vector<S>(c.tau)),
        dq(test::cast_vector<S>(c.dq)),
        dqd(test::cast_vector<S>(c.dqd)),
        dtau(test::cast_vector<S>(c.dtau)),
        w(test::cast_vector<S>(c.w)) {
    for (const auto& f : c.fext) fext.push_back(f.template cast<S>());
  }
};

// The driver's results in precision S, SoA.
template <class S>
struct Result {
  std::vector<S> qdd_j, dqdd, qdd_v, gq, gqd, gtau;

  // every output `size` NaNs (n B: unwritten entries show)
  static Result nan(std::size_t size) {
    Result r;
    for (auto* v : {&r.qdd_j, &r.dqdd, &r.qdd_v, &r.gq, &r.gqd, &r.gtau}) v->assign(size, S(NAN));
    return r;
  }
};

struct Errors {
  double qdd, dqdd, gq, gqd, gtau;
  double operator[](int k) const { return k == 0 ? qdd : k == 1 ? dqdd : k == 2 ? gq : k == 3 ? gqd : gtau; }
};
const char* const kField[5] = {"qdd", "dqdd", "gq", "gqd", "gtau"};

template <class S>
Errors errors(const Result<S>& r, const Case& c) {
  return {std::fmax(test::max_rel_err(r.qdd_j, c.qdd), test::max_rel_err(r.qdd_v, c.qdd)),
          test::max_rel_err(r.dqdd, c.dqdd), test::max_rel_err(r.gq, c.gq), test::max_rel_err(r.gqd, c.gqd),
          test::max_rel_err(r.gtau, c.gtau)};
}

inline std::string str(const Errors& e) {
  char buf[160];
  std::snprintf(buf, sizeof buf, "qdd %.2e dqdd %.2e gq %.2e gqd %.2e gtau %.2e", e.qdd, e.dqdd, e.gq, e.gqd, e.gtau);
  return buf;
}

// The serial aba_jvp / aba_vjp in float on the same inputs against the double
// references: the error float itself makes, whatever the algorithm.
inline Errors serial_float_errors(const Model& model, const Case& c) {
  const ModelTpl<float> m = model.cast<float>();
  const Index n = c.n, B = c.B;
  AbaJvpData<float> jd(m);
  Result<float> r = Result<float>::nan(c.q.size());
  std::vector<float> x[7], out[5];
  for (auto& o : out) o.resize(n);
  for (Index b = 0; b < B; ++b) {
    instance_inputs(c, b, x);
    std::vector<Force<float>> f;
    for (Index i = 0; i < n && !c.fext.empty(); ++i) f.push_back(c.fext[b * n + i].cast<float>());
    const Force<float>* fp = f.empty() ? nullptr : f.data();
    (void)aba_jvp(m, jd, x[0].data(), x[1].data(), x[2].data(), fp, x[3].data(), x[4].data(), x[5].data(),
                  out[1].data(), out[0].data());
    (void)aba_vjp(m, jd, x[0].data(), x[1].data(), x[2].data(), fp, x[6].data(), out[2].data(), out[3].data(),
                  out[4].data(), out[0].data());
    std::vector<float>* res[5] = {&r.qdd_j, &r.dqdd, &r.gq, &r.gqd, &r.gtau};
    for (int k = 0; k < 5; ++k)
      for (Index i = 0; i < n; ++i) (*res[k])[i * B + b] = out[k][i];
  }
  r.qdd_v = r.qdd_j;
  return errors(r, c);
}

// The tolerance of every output, from the case's conditioning: es, the serial float's
// error on the same inputs, says how much the case amplifies a rounding error
// (dqdd = M^-1 (dtau - r) on a rope of 1000 links: es ~ 0.5 at random
// configurations, ~5 near rest, where cond(M) grows like n^4). Double: 1e-9, or 30x
// the serial double's own error so estimated (es x 2^-29, the ratio of the two
// precisions' epsilons), whichever is larger; float (the inputs rounded to float):
// 1e-5, or 30x es. (Measured on the host: at most 3.5x in double, 8.6x in float, on
// rope:1000 near rest; the device's fused multiply-adds round differently.)
inline double tolerance(double es, bool is_float) {
  return is_float ? std::fmax(1e-5, 30 * es) : std::fmax(1e-9, 30 * es * std::ldexp(1.0, -29));
}

inline void expect_within(const Errors& e, const Errors& es, bool is_float, const std::string& what) {
  for (int k = 0; k < 5; ++k)
    EXPECT_LT(e[k], tolerance(es[k], is_float))
        << kField[k] << ", " << what << ": " << str(e) << "; serial float " << str(es);
}

// check_model's cases: for fext off and on, f(c, es, with_fext) on the case of `model`
// (B instances, q in +-3 q_scale, the seed from nv) with es its serial float errors,
// under a trace naming spec.
template <class F>
void for_each_case(const Model& model, const std::string& spec, Index B, double q_scale, F&& f) {
  for (bool with_fext : {false, true}) {
    SCOPED_TRACE(spec + (with_fext ? " with fext" : "") + ", q in +-" + std::to_string(3 * q_scale));
    const Case c = make_case(model, B, 3 + static_cast<unsigned>(model.nv()) + with_fext, with_fext, q_scale);
    const Errors es = serial_float_errors(model, c);
    f(c, es, with_fext);
  }
}

// The adjoint identity's two sides, lhs = <w, dqdd(v)> and rhs = <(gq, gqd, gtau)(w),
// (dq, dqd, dtau)> of r, and scale, the sum of the products' magnitudes.
struct AdjointSums {
  double lhs = 0, rhs = 0, scale = 0;
};

inline AdjointSums adjoint_sums(const Case& c, const Result<double>& r) {
  AdjointSums a;
  for (std::size_t k = 0; k < c.q.size(); ++k) {
    a.lhs += c.w[k] * r.dqdd[k];
    a.scale += std::fabs(c.w[k] * r.dqdd[k]);
    const double t[3] = {r.gq[k] * c.dq[k], r.gqd[k] * c.dqd[k], r.gtau[k] * c.dtau[k]};
    for (double x : t) a.rhs += x, a.scale += std::fabs(x);
  }
  return a;
}

}  // namespace scandyn::test::chain_dir
