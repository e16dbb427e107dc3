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
    const std::vector<double>* in[7] = {&c.q, &c.qd, &c.tau, &c.dq, &c.dqd, &c.dtau, &c.w};
    for (int k = 0; k < 7; ++k) {
      x[k].resize(n);
      for (Index i = 0; i < n; ++i) x[k][i] = (*in[k])[i * B + b];
    }
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

// The driver's results in precision S, SoA.
template <class S>
struct Result {
  std::vector<S> qdd_j, dqdd, qdd_v, gq, gqd, gtau;
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
  Result<float> r;
  for (auto* v : {&r.qdd_j, &r.dqdd, &r.qdd_v, &r.gq, &r.gqd, &r.gtau}) v->assign(c.q.size(), NAN);
  std::vector<float> x[7], out[5];
  for (auto& o : out) o.resize(n);
  for (Index b = 0; b < B; ++b) {
    const std::vector<double>* in[7] = {&c.q, &c.qd, &c.tau, &c.dq, &c.dqd, &c.dtau, &c.w};
    for (int k = 0; k < 7; ++k) {
      x[k].resize(n);
      for (Index i = 0; i < n; ++i) x[k][i] = static_cast<float>((*in[k])[i * B + b]);
    }
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

}  // namespace scandyn::test::chain_dir
