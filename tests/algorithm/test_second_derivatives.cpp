// The second-order derivatives of inverse dynamics (rnea_second_derivatives,
// scandyn/algorithm/second_derivatives.hpp). Truths: central differences of the
// analytical first-order derivatives (rnea_derivatives; step 1e-5, 1e-7 relative to
// the tensor's largest entry in double), the symmetry of the second derivatives in
// their two variables, and the mixed partials both ways (1e-9 relative); and the
// analytical second-order recursion (what rnea_second_derivatives runs) against the
// dual-number passes (rnea_second_derivatives_dual), entry by entry (1e-11 relative
// in double, 2e-5 in float against the double reference); the weighted contraction
// rnea_weighted_dq2 against its dual passes (rnea_weighted_dq2_dual, 1e-12).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>
#include <vector>

#include "scandyn/algorithm/second_derivatives.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

using test::max_abs;

struct First {
  std::vector<double> dq, dqd, M;
};

First first_order(const Model& model, DerivativeDataTpl<double>& dd, const std::vector<double>& q,
                  const std::vector<double>& qd, const std::vector<double>& qdd, const Force<double>* fext) {
  const Index n = model.nv();
  First f{std::vector<double>(n * n), std::vector<double>(n * n), std::vector<double>(n * n)};
  rnea_derivatives(model, dd, q.data(), qd.data(), qdd.data(), fext, MatrixRef<double>{f.dq.data(), n, 1},
                   MatrixRef<double>{f.dqd.data(), n, 1}, MatrixRef<double>{f.M.data(), n, 1});
  return f;
}

TEST(SecondDerivatives, CentralDifferencesOfTheFirstOrderDerivativesAndSymmetry) {
  std::vector<std::pair<std::string, Model>> models;
  models.emplace_back("iiwa", test::load_robot("iiwa.urdf"));
  models.emplace_back("hyq", test::load_robot("hyq.urdf"));
  models.emplace_back("random_model(12) (prismatic joints)", test::random_model(12, 9));
  for (const auto& [name, model] : models) {
    for (bool with_wrenches : {false, true}) {
      SCOPED_TRACE(name + (with_wrenches ? " with external wrenches" : ""));
      const Index n = model.nv();
      std::mt19937_64 rng(17 + n);
      const std::vector<double> q = test::random_vector(rng, n, -1.5, 1.5), qd = test::random_vector(rng, n, -1.5, 1.5),
                                qdd = test::random_vector(rng, n, -2, 2);
      const std::vector<Force<double>> wrenches = test::random_wrenches<double>(rng, n, 1.0);
      const Force<double>* fext = with_wrenches ? wrenches.data() : nullptr;
      SecondDerivativeData<double> sd(model);
      const std::size_t nnn = static_cast<std::size_t>(n) * n * n;
      std::vector<double> Hqq(nnn), Hvv(nnn), Hqv(nnn), dM(nnn);
      rnea_second_derivatives(model, sd, q.data(), qd.data(), qdd.data(), fext, Hqq.data(), Hvv.data(), Hqv.data(),
                              dM.data());
      DerivativeDataTpl<double> dd(model);
      auto at = [&](Index i, Index j, Index k) { return (static_cast<std::size_t>(i) * n + j) * n + k; };
      // central differences along q_k and qd_k of the analytical first-order blocks
      std::vector<double> Fqq(nnn), Fqv(nnn), Fvv(nnn), FM(nnn), Fvq(nnn);
      const double h = 1e-5;
      for (Index k = 0; k < n; ++k)
        for (int var = 0; var < 2; ++var) {
          std::vector<double> qp = q, qm = q, vp = qd, vm = qd;
          (var == 0 ? qp : vp)[k] += h;
          (var == 0 ? qm : vm)[k] -= h;
          const First p = first_order(model, dd, qp, vp, qdd, fext), m = first_order(model, dd, qm, vm, qdd, fext);
          for (Index i = 0; i < n; ++i)
            for (Index j = 0; j < n; ++j) {
              const std::size_t e = static_cast<std::size_t>(i) * n + j;
              if (var == 0) {
                Fqq[at(i, j, k)] = (p.dq[e] - m.dq[e]) / (2 * h);
                FM[at(i, j, k)] = (p.M[e] - m.M[e]) / (2 * h);
                Fvq[at(i, j, k)] = (p.dqd[e] - m.dqd[e]) / (2 * h);  // d/dq_k of dtau_i/dqd_j
              } else {
                Fvv[at(i, j, k)] = (p.dqd[e] - m.dqd[e]) / (2 * h);
                Fqv[at(i, j, k)] = (p.dq[e] - m.dq[e]) / (2 * h);  // d/dqd_k of dtau_i/dq_j
              }
            }
        }
      auto expect_close = [&](const std::vector<double>& a, const std::vector<double>& b, double tol, const char* what) {
        double err = 0;
        for (std::size_t e = 0; e < a.size(); ++e) err = std::max(err, std::abs(a[e] - b[e]));
        EXPECT_LE(err, tol * std::max(1.0, max_abs(b))) << what;
      };
      EXPECT_GT(max_abs(Hqq), 1e-2);  // the tensors are not trivially zero
      EXPECT_GT(max_abs(Hqv), 1e-2);
      EXPECT_GT(max_abs(Hvv), 1e-2);
      expect_close(Hqq, Fqq, 1e-7, "d2tau/dq2 vs differences");
      expect_close(Hvv, Fvv, 1e-7, "d2tau/dqd2 vs differences");
      expect_close(Hqv, Fqv, 1e-7, "d2tau/dq dqd vs differences");
      expect_close(dM, FM, 1e-7, "dM/dq vs differences");
      // symmetry, and the mixed partials the other way round: d/dq_j (dtau_i/dqd_k)
      std::vector<double> Hqq_t(nnn), Hvv_t(nnn), Hqv_t(nnn);
      for (Index i = 0; i < n; ++i)
        for (Index j = 0; j < n; ++j)
          for (Index k = 0; k < n; ++k) {
            Hqq_t[at(i, j, k)] = Hqq[at(i, k, j)];
            Hvv_t[at(i, j, k)] = Hvv[at(i, k, j)];
            Hqv_t[at(i, j, k)] = Fvq[at(i, k, j)];
          }
      expect_close(Hqq, Hqq_t, 1e-9, "d2tau/dq2 symmetric");
      expect_close(Hvv, Hvv_t, 1e-9, "d2tau/dqd2 symmetric");
      expect_close(Hqv, Hqv_t, 1e-7, "mixed partials both ways");
      // float follows double
      SecondDerivativeData<float> sf(model.cast<float>());
      const Model& md = model;
      const ModelTpl<float> mf = md.cast<float>();
      std::vector<float> qf(q.begin(), q.end()), qdf(qd.begin(), qd.end()), qddf(qdd.begin(), qdd.end());
      std::vector<Force<float>> wf;
      for (const auto& w : wrenches) wf.push_back(w.cast<float>());
      std::vector<float> a(nnn), b(nnn), c(nnn);
      rnea_second_derivatives(mf, sf, qf.data(), qdf.data(), qddf.data(), with_wrenches ? wf.data() : nullptr, a.data(),
                              b.data(), c.data());
      expect_close(std::vector<double>(a.begin(), a.end()), Hqq, 1e-4, "float d2tau/dq2");
    }
  }
}

// The models the analytical recursion is checked on against the dual passes: the
// shipped robots, random trees (prismatic joints, arbitrary axes), a random chain and
// random chains from the base; each named with its count of prismatic joints.
std::vector<std::pair<std::string, Model>> analytic_models() {
  std::vector<std::pair<std::string, Model>> models;
  models.emplace_back("iiwa", test::load_robot("iiwa.urdf"));
  models.emplace_back("hyq", test::load_robot("hyq.urdf"));
  models.emplace_back("atlas", test::load_robot("atlas.urdf"));
  models.emplace_back("random_model(12)", test::random_model(12, 9));
  models.emplace_back("random_model(20)", test::random_model(20, 31));
  models.emplace_back("random_model(40)", test::random_model(40, 4));
  models.emplace_back("random_chain(10)", test::random_chain(10, 7));
  models.emplace_back("random_chains_from_base(14)", test::random_chains_from_base(14, 5, {0, 4, 9}));
  for (auto& [name, model] : models) {
    int prismatic = 0;
    for (const auto& b : model.bodies) prismatic += b.type == JointType::Prismatic;
    name += " (" + std::to_string(prismatic) + " prismatic)";
  }
  return models;
}

// The analytical recursion (rnea_second_derivatives) against the dual-number passes
// (rnea_second_derivatives_dual): every entry of the four tensors, relative to each
// tensor's largest entry; exact symmetry of d2tau/dq2 and d2tau/dqd2 in (j, k); the
// outputs' previous contents do not matter (NaN-filled first).
TEST(SecondDerivatives, AnalyticRecursionMatchesTheDualPasses) {
  for (const auto& [name, model] : analytic_models()) {
    for (bool with_wrenches : {false, true}) {
      SCOPED_TRACE(name + (with_wrenches ? " with external wrenches" : ""));
      const Index n = model.nv();
      const std::size_t nnn = static_cast<std::size_t>(n) * n * n;
      std::mt19937_64 rng(91 + n + with_wrenches);
      const std::vector<double> q = test::random_vector(rng, n, -2, 2), qd = test::random_vector(rng, n, -2, 2),
                                qdd = test::random_vector(rng, n, -3, 3);
      const std::vector<Force<double>> wrenches = test::random_wrenches<double>(rng, n, 2.0);
      const Force<double>* fext = with_wrenches ? wrenches.data() : nullptr;
      SecondDerivativeData<double> sd(model);
      const double nan = std::nan("");
      std::vector<double> A[4], D[4];
      for (int t = 0; t < 4; ++t) A[t].assign(nnn, nan), D[t].assign(nnn, nan);
      rnea_second_derivatives(model, sd, q.data(), qd.data(), qdd.data(), fext, A[0].data(), A[1].data(),
                              A[2].data(), A[3].data());
      rnea_second_derivatives_dual(model, sd, q.data(), qd.data(), qdd.data(), fext, D[0].data(), D[1].data(),
                                   D[2].data(), D[3].data());
      static const char* const kNames[4] = {"d2tau_dq2", "d2tau_dqd2", "d2tau_dqdqd", "dM_dq"};
      for (int t = 0; t < 4; ++t) {
        double err = 0;
        std::size_t unwritten = 0;  // NaN left from the fill (std::max would skip them)
        for (std::size_t e = 0; e < nnn; ++e) {
          unwritten += !std::isfinite(A[t][e]);
          err = std::max(err, std::abs(A[t][e] - D[t][e]));
        }
        EXPECT_EQ(unwritten, 0u) << kNames[t];
        EXPECT_GT(max_abs(D[t]), 1e-2) << kNames[t];
        EXPECT_LE(err, 1e-11 * max_abs(D[t])) << kNames[t] << ": max |analytic - dual| " << err;
        std::printf("%s%s %s: max |analytic - dual| / max |dual| = %.2e\n", name.c_str(), with_wrenches ? " +fext" : "",
                    kNames[t], err / max_abs(D[t]));
      }
      auto at = [&](Index i, Index j, Index k) { return (static_cast<std::size_t>(i) * n + j) * n + k; };
      for (Index i = 0; i < n; ++i)
        for (Index j = 0; j < n; ++j)
          for (Index k = 0; k < j; ++k) {
            ASSERT_EQ(A[0][at(i, j, k)], A[0][at(i, k, j)]) << "d2tau_dq2 " << i << " " << j << " " << k;
            ASSERT_EQ(A[1][at(i, j, k)], A[1][at(i, k, j)]) << "d2tau_dqd2 " << i << " " << j << " " << k;
          }
      // float against the double reference; without dM_dq (null: not written)
      const ModelTpl<float> mf = model.cast<float>();
      SecondDerivativeData<float> sf(mf);
      std::vector<float> qf(q.begin(), q.end()), qdf(qd.begin(), qd.end()), qddf(qdd.begin(), qdd.end());
      std::vector<Force<float>> wf;
      for (const auto& w : wrenches) wf.push_back(w.cast<float>());
      std::vector<float> F[3];
      for (int t = 0; t < 3; ++t) F[t].assign(nnn, std::nanf(""));
      rnea_second_derivatives(mf, sf, qf.data(), qdf.data(), qddf.data(), with_wrenches ? wf.data() : nullptr,
                              F[0].data(), F[1].data(), F[2].data());
      for (int t = 0; t < 3; ++t) {
        double err = 0;
        std::size_t unwritten = 0;
        for (std::size_t e = 0; e < nnn; ++e) {
          unwritten += !std::isfinite(F[t][e]);
          err = std::max(err, std::abs(double(F[t][e]) - D[t][e]));
        }
        EXPECT_EQ(unwritten, 0u) << "float " << kNames[t];
        EXPECT_LE(err, 2e-5 * max_abs(D[t])) << "float " << kNames[t] << ": max |float - dual double| " << err;
        std::printf("%s%s float %s: max |float - dual double| / max |dual| = %.2e\n", name.c_str(),
                    with_wrenches ? " +fext" : "", kNames[t], err / max_abs(D[t]));
      }
    }
  }
}

// inertia_rate(s, I), the weighted recursion's subtree sums' term, as an operator:
// (s x* I - I s x) m for random twists s, inertias I (random mass, centre of mass and
// rotational inertia) and motions m, 1e-13 relative.
TEST(SecondDerivatives, InertiaRateIsTheCrossProductCommutator) {
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> u(-1, 1);
  auto vec = [&] { return Vec3<double>{u(rng), u(rng), u(rng)}; };
  for (int t = 0; t < 20; ++t) {
    const Sym3<double> Ic{1 + u(rng) * 0.2, 1.5 + u(rng) * 0.2, 2 + u(rng) * 0.2, 0.1 * u(rng), 0.1 * u(rng),
                          0.1 * u(rng)};
    const Inertia<double> I = Inertia<double>::from_com(2 + u(rng), vec(), Ic);
    const Motion<double> sv{vec(), vec()}, m{vec(), vec()};
    const Force<double> want = cross(sv, I * m) - I * cross(sv, m), got = inertia_rate(sv, I) * m;
    const double scale = std::max({1.0, std::abs(want.n.x), std::abs(want.n.y), std::abs(want.n.z),
                                   std::abs(want.f.x), std::abs(want.f.y), std::abs(want.f.z)});
    for (int k = 0; k < 3; ++k) {
      EXPECT_NEAR(got.n[k], want.n[k], 1e-13 * scale) << t;
      EXPECT_NEAR(got.f[k], want.f[k], 1e-13 * scale) << t;
    }
  }
}

// The weighted contraction out(j, k) = sum_i w_i d2tau_i/dq_j dq_k: rnea_weighted_dq2
// (the analytical recursion's weighted variant) against the dual passes
// (rnea_weighted_dq2_dual), every entry (NaN-filled first), 1e-12 relative to the
// reference's largest entry in double; exactly symmetric; and against the analytical
// d2tau_dq2 tensor contracted with w (1e-12). Two cases per model: the variational
// integrator's (the model without gravity at (q, 0, v), w = v, no wrenches) and every
// term (gravity, qd, qdd, a random w, with and without external wrenches). Float
// within 2e-5 of the double reference.
TEST(SecondDerivatives, WeightedContractionMatchesTheDualPasses) {
  for (const auto& [name, full] : analytic_models()) {
    for (int terms = 0; terms < 3; ++terms) {  // 0: the variational integrator's; 1: every term; 2: and wrenches
      SCOPED_TRACE(name + ", " +
                   (terms == 0 ? "at rest without gravity, w = qdd" : terms == 1 ? "every term" : "every term + fext"));
      Model model = full;
      if (terms == 0) model.gravity = Vec3<double>{0, 0, 0};
      const Index n = model.nv();
      const std::size_t nn = static_cast<std::size_t>(n) * n, nnn = nn * n;
      std::mt19937_64 rng(313 + n + terms);
      const std::vector<double> q = test::random_vector(rng, n, -2, 2), qdd = test::random_vector(rng, n, -3, 3);
      const std::vector<double> qd = terms == 0 ? std::vector<double>(n, 0.0) : test::random_vector(rng, n, -2, 2);
      const std::vector<double> w = terms == 0 ? qdd : test::random_vector(rng, n, -1, 1);
      const std::vector<Force<double>> wrenches = test::random_wrenches<double>(rng, n, 2.0);
      const Force<double>* fext = terms == 2 ? wrenches.data() : nullptr;
      SecondDerivativeData<double> sd(model);
      std::vector<double> A(nn, std::nan("")), D(nn, std::nan("")), T(nnn), none(nnn);
      rnea_weighted_dq2(model, sd, q.data(), qd.data(), qdd.data(), fext, w.data(), A.data());
      rnea_weighted_dq2_dual(model, sd, q.data(), qd.data(), qdd.data(), fext, w.data(), D.data());
      rnea_second_derivatives(model, sd, q.data(), qd.data(), qdd.data(), fext, T.data(), none.data(), none.data());
      std::vector<double> C(nn, 0.0);  // the tensor contracted
      for (Index i = 0; i < n; ++i)
        for (std::size_t e = 0; e < nn; ++e) C[e] += w[i] * T[i * nn + e];
      double err = 0, err_tensor = 0;
      std::size_t unwritten = 0;
      for (std::size_t e = 0; e < nn; ++e) {
        unwritten += !std::isfinite(A[e]);
        err = std::max(err, std::abs(A[e] - D[e]));
        err_tensor = std::max(err_tensor, std::abs(A[e] - C[e]));
      }
      EXPECT_EQ(unwritten, 0u);
      EXPECT_GT(max_abs(D), 1e-2);
      EXPECT_LE(err, 1e-12 * max_abs(D)) << "max |analytic - dual| " << err;
      EXPECT_LE(err_tensor, 1e-12 * max_abs(D)) << "max |analytic - contracted tensor| " << err_tensor;
      std::printf("%s terms %d: weighted dq2 max |analytic - dual| / max |dual| = %.2e, vs the contracted tensor %.2e\n",
                  name.c_str(), terms, err / max_abs(D), err_tensor / max_abs(D));
      for (Index j = 0; j < n; ++j)
        for (Index k = 0; k < j; ++k) ASSERT_EQ(A[j * n + k], A[k * n + j]) << j << " " << k;
      // float against the double reference
      const ModelTpl<float> mf = model.cast<float>();
      SecondDerivativeData<float> sf(mf);
      std::vector<float> qf(q.begin(), q.end()), qdf(qd.begin(), qd.end()), qddf(qdd.begin(), qdd.end()),
          wf(w.begin(), w.end()), F(nn, std::nanf(""));
      std::vector<Force<float>> ff;
      for (const auto& x : wrenches) ff.push_back(x.cast<float>());
      rnea_weighted_dq2(mf, sf, qf.data(), qdf.data(), qddf.data(), fext ? ff.data() : nullptr, wf.data(), F.data());
      double ferr = 0;
      std::size_t funwritten = 0;
      for (std::size_t e = 0; e < nn; ++e) {
        funwritten += !std::isfinite(F[e]);
        ferr = std::max(ferr, std::abs(double(F[e]) - D[e]));
      }
      EXPECT_EQ(funwritten, 0u) << "float";
      EXPECT_LE(ferr, 2e-5 * max_abs(D)) << "float: max |float - dual double| " << ferr;
    }
  }
}

}  // namespace
}  // namespace scandyn
