// Tests of the first-order dynamics derivatives (scandyn/algorithm/derivatives.hpp)
// against independent truths: central finite differences of the reference rnea and
// aba, the identities dqdd/dtau = M^-1 (crba) and dqdd/dq = -M^-1 dtau/dq at qdd =
// FD, on shipped robots, random trees with prismatic joints and chains, with and
// without external wrenches.
#include <gtest/gtest.h>

#include <array>
#include <cmath>
#include <random>
#include <vector>

#include "scandyn/algorithm/derivatives.hpp"
#include "scandyn/algorithm/directional_derivatives.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

using test::random_vector;

struct State {
  std::vector<double> q, qd, qdd, tau;
  std::vector<Force<double>> fext;
};

State random_state(Index n, unsigned seed, bool with_fext) {
  std::mt19937_64 rng(seed);
  State s{random_vector(rng, n, -2, 2), random_vector(rng, n, -2, 2), random_vector(rng, n, -2, 2),
          random_vector(rng, n, -5, 5), {}};
  if (with_fext) s.fext = test::random_wrenches<double>(rng, n, 2.0);
  return s;
}

MatrixRef<double> ref(std::vector<double>& m, Index n) { return {m.data(), n, 1}; }

// d f / d x (n x n, row-major) by central differences D(h) = (f(x + h e_j) - f(x -
// h e_j)) / 2h with one Richardson step, (4 D(h / 2) - D(h)) / 3: truncation O(h^4)
// and rounding O(eps |f| / h), so that a step of 1e-3 is accurate to ~1e-10 relative
// even where |f| is large next to its derivative (ropes' small inertias).
template <class F>
std::vector<double> central_jacobian(Index n, std::vector<double>& x, double h, F&& f) {
  std::vector<double> J(static_cast<std::size_t>(n) * n), fp(n), fm(n);
  auto diff = [&](Index j, double step, std::vector<double>& d) {
    const double x0 = x[j];
    x[j] = x0 + step;
    f(fp.data());
    x[j] = x0 - step;
    f(fm.data());
    x[j] = x0;
    for (Index i = 0; i < n; ++i) d[i] = (fp[i] - fm[i]) / (2 * step);
  };
  std::vector<double> d1(n), d2(n);
  for (Index j = 0; j < n; ++j) {
    diff(j, h, d1);
    diff(j, h / 2, d2);
    for (Index i = 0; i < n; ++i) J[i * n + j] = (4 * d2[i] - d1[i]) / 3;
  }
  return J;
}

// d f / d eps of f(x + eps dx, y + eps dy, z + eps dz) at eps = 0 (three input
// vectors of n entries, n outputs), by central differences with one Richardson step
// as central_jacobian.
template <class F>
std::vector<double> directional_difference(Index n, const std::array<const std::vector<double>*, 3>& x,
                                           const std::array<const std::vector<double>*, 3>& dx, double h, F&& f) {
  std::vector<double> in[3] = {std::vector<double>(n), std::vector<double>(n), std::vector<double>(n)};
  std::vector<double> fp(n), fm(n), d[2] = {std::vector<double>(n), std::vector<double>(n)};
  for (int k = 0; k < 2; ++k) {
    const double step = k == 0 ? h : h / 2;
    for (int sign : {1, -1}) {
      for (int a = 0; a < 3; ++a)
        for (Index i = 0; i < n; ++i) in[a][i] = (*x[a])[i] + sign * step * (*dx[a])[i];
      f(in[0].data(), in[1].data(), in[2].data(), sign > 0 ? fp.data() : fm.data());
    }
    for (Index i = 0; i < n; ++i) d[k][i] = (fp[i] - fm[i]) / (2 * step);
  }
  for (Index i = 0; i < n; ++i) d[0][i] = (4 * d[1][i] - d[0][i]) / 3;
  return d[0];
}

// The dense products of a Jacobian of three n x n row-major blocks J = [J0 J1 J2]: J v
// for the direction v = (v0, v1, v2), and J^T w = (J0^T w, J1^T w, J2^T w).
struct DenseProducts {
  std::vector<double> jv;
  std::array<std::vector<double>, 3> jtw;
  // a VJP (g0, g1, g2) against J^T w: max_rel_err below tol in each block
  void expect_transpose(const std::vector<double>& g0, const std::vector<double>& g1, const std::vector<double>& g2,
                        double tol) const {
    EXPECT_LT(test::max_rel_err(g0, jtw[0]), tol) << "J0^T w";
    EXPECT_LT(test::max_rel_err(g1, jtw[1]), tol) << "J1^T w";
    EXPECT_LT(test::max_rel_err(g2, jtw[2]), tol) << "J2^T w";
  }
};

DenseProducts dense_products(Index n, const std::array<const std::vector<double>*, 3>& J,
                             const std::array<const std::vector<double>*, 3>& v, const std::vector<double>& w) {
  const std::vector<double>& J0 = *J[0], &J1 = *J[1], &J2 = *J[2];
  DenseProducts p{std::vector<double>(n, 0.0), {std::vector<double>(n, 0.0), std::vector<double>(n, 0.0),
                                                std::vector<double>(n, 0.0)}};
  for (Index i = 0; i < n; ++i)
    for (Index j = 0; j < n; ++j) {
      p.jv[i] += J0[i * n + j] * (*v[0])[j] + J1[i * n + j] * (*v[1])[j] + J2[i * n + j] * (*v[2])[j];
      p.jtw[0][j] += w[i] * J0[i * n + j];
      p.jtw[1][j] += w[i] * J1[i * n + j];
      p.jtw[2][j] += w[i] * J2[i * n + j];
    }
  return p;
}

// A rope's state near rest for the differences along a direction on long ropes
// (random_state with wrenches, |q|, |qd| scaled to <= 0.01: large angles and rates on
// many links give link velocities whose rounding, not the derivative, would dominate),
// and three directions in [-1, 1] (seeded by direction_seed).
struct NearRest {
  State s;
  std::array<std::vector<double>, 3> d;
};

NearRest near_rest(Index n, unsigned state_seed, unsigned direction_seed) {
  NearRest r{random_state(n, state_seed, true), {}};
  for (Index i = 0; i < n; ++i) r.s.q[i] *= 0.005, r.s.qd[i] *= 0.005;
  std::mt19937_64 rng(direction_seed);
  for (auto& d : r.d) d = random_vector(rng, n, -1, 1);
  return r;
}

std::vector<std::pair<std::string, Model>> derivative_models() {
  std::vector<std::pair<std::string, Model>> models;
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"})
    models.emplace_back(file, test::load_robot(file));
  for (const char* spec : {"chain:1", "chain:9", "tree:20:3", "rope:30", "curtain:3:4"})
    models.emplace_back(spec, load_model(spec));
  models.emplace_back("random_model(15)", test::random_model(15, 7));
  models.emplace_back("random_model(40)", test::random_model(40, 8));
  return models;
}

// Finite-difference step and tolerance (double): central differences with one
// Richardson step at h = 1e-3 (central_jacobian); 1e-6 relative to the largest entry
// (or 1); 5e-6 for forward dynamics on ropes and curtains, whose small link inertias
// make M ill-conditioned, so that the ABA's own rounding, amplified by cond(M) and
// divided by the step, reaches ~1e-6 (the identities below hold to 1e-9 there).
constexpr double kStep = 1e-3;
constexpr double kFdTol = 1e-6;

TEST(RneaDerivatives, MatchCentralDifferences) {
  for (auto& [name, model] : derivative_models()) {
    for (bool with_fext : {false, true}) {
      SCOPED_TRACE(name + (with_fext ? " with fext" : ""));
      const Index n = model.nv();
      State s = random_state(n, 11 + n, with_fext);
      const Force<double>* fext = with_fext ? s.fext.data() : nullptr;
      DerivativeDataTpl<double> dd(model);
      Data data(model);
      std::vector<double> dq(n * n, NAN), dqd(n * n, NAN), M(n * n, NAN), tau(n, NAN), tau_ref(n);
      rnea_derivatives(model, dd, s.q.data(), s.qd.data(), s.qdd.data(), fext, ref(dq, n), ref(dqd, n), ref(M, n),
                       tau.data());
      rnea(model, data, s.q.data(), s.qd.data(), s.qdd.data(), tau_ref.data(), fext);
      EXPECT_LT(test::max_rel_err(tau, tau_ref), 1e-12);
      auto id = [&](double* out) { rnea(model, data, s.q.data(), s.qd.data(), s.qdd.data(), out, fext); };
      EXPECT_LT(test::max_rel_err(dq, central_jacobian(n, s.q, kStep, id)), kFdTol);
      EXPECT_LT(test::max_rel_err(dqd, central_jacobian(n, s.qd, kStep, id)), kFdTol);
      std::vector<double> Mref(n * n);
      crba(model, data, s.q.data(), Mref.data());
      EXPECT_LT(test::max_rel_err(M, Mref), 1e-12);
    }
  }
}

TEST(AbaDerivatives, MatchCentralDifferencesAndIdentities) {
  for (auto& [name, model] : derivative_models()) {
    for (bool with_fext : {false, true}) {
      SCOPED_TRACE(name + (with_fext ? " with fext" : ""));
      const Index n = model.nv();
      State s = random_state(n, 23 + n, with_fext);
      const Force<double>* fext = with_fext ? s.fext.data() : nullptr;
      DerivativeDataTpl<double> dd(model);
      Data data(model);
      std::vector<double> dq(n * n, NAN), dqd(n * n, NAN), Minv(n * n, NAN), qdd(n, NAN), qdd_ref(n);
      ASSERT_TRUE(aba_derivatives(model, dd, s.q.data(), s.qd.data(), s.tau.data(), fext, qdd.data(), ref(dq, n),
                                  ref(dqd, n), ref(Minv, n))
                      .ok());
      ASSERT_TRUE(aba(model, data, s.q.data(), s.qd.data(), s.tau.data(), qdd_ref.data(), fext).ok());
      EXPECT_EQ(qdd, qdd_ref);
      auto fd = [&](double* out) { aba(model, data, s.q.data(), s.qd.data(), s.tau.data(), out, fext); };
      const bool ill_conditioned = name.rfind("rope", 0) == 0 || name.rfind("curtain", 0) == 0;
      const double tol = ill_conditioned ? 5e-6 : kFdTol;
      EXPECT_LT(test::max_rel_err(dq, central_jacobian(n, s.q, kStep, fd)), tol);
      EXPECT_LT(test::max_rel_err(dqd, central_jacobian(n, s.qd, kStep, fd)), tol);
      EXPECT_LT(test::max_rel_err(Minv, central_jacobian(n, s.tau, kStep, fd)), tol);
      // identities: M Minv = 1, and dqdd/dq = -M^-1 dtau/dq at qdd = FD
      std::vector<double> M(n * n), tq(n * n), tqd(n * n), Mt(n * n);
      crba(model, data, s.q.data(), M.data());
      double eye_err = 0;
      for (Index i = 0; i < n; ++i)
        for (Index j = 0; j < n; ++j) {
          double acc = 0;
          for (Index k = 0; k < n; ++k) acc += M[i * n + k] * Minv[k * n + j];
          eye_err = std::max(eye_err, std::fabs(acc - (i == j ? 1.0 : 0.0)));
        }
      EXPECT_LT(eye_err, 1e-9);
      rnea_derivatives(model, dd, s.q.data(), s.qd.data(), qdd.data(), fext, ref(tq, n), ref(tqd, n), ref(Mt, n));
      std::vector<double> minus_Minv_tq(n * n);
      for (Index i = 0; i < n; ++i)
        for (Index j = 0; j < n; ++j) {
          double acc = 0;
          for (Index k = 0; k < n; ++k) acc -= Minv[i * n + k] * tq[k * n + j];
          minus_Minv_tq[i * n + j] = acc;
        }
      EXPECT_LT(test::max_rel_err(dq, minus_Minv_tq), 1e-9);
    }
  }
}

// fd_derivatives_instance<8> (the packed factor and column solves with L in
// registers, what the CUDA kernels run up to 8 DoF) against the default tree walks
// over the output blocks, on the same qdd: models of up to 8 DoF (chains, trees whose
// numbering is not a preorder, chains from the base, prismatic joints), with and
// without external wrenches and armature; double 1e-13 relative to each block's
// largest entry (or 1), float 1e-4; M^-1 exactly symmetric; a pivot that fails is
// the same DoF on both.
template <class S>
void packed_against_tree(const std::string& name, const Model& model_d, bool with_fext, bool with_armature) {
  SCOPED_TRACE(name + (with_fext ? " with fext" : "") + (with_armature ? " with armature" : "") +
               (sizeof(S) == 4 ? " float" : " double"));
  const ModelTpl<S> model = model_d.cast<S>();
  const Index n = model.nv();
  const State s = random_state(n, 41 + n, with_fext);
  const auto cast = [](const std::vector<double>& v) { return std::vector<S>(v.begin(), v.end()); };
  const std::vector<S> q = cast(s.q), qd = cast(s.qd), tau = cast(s.tau);
  std::vector<Force<S>> fext;
  for (const auto& f : s.fext) fext.push_back(f.template cast<S>());
  std::vector<S> armature(n);
  for (Index i = 0; i < n; ++i) armature[i] = S(0.01) * S(i + 1);
  const S* arm = with_armature ? armature.data() : nullptr;
  DerivativeDataTpl<S> dd(model);
  std::vector<S> qdd(n);
  ASSERT_TRUE(aba(model, dd.aba, q.data(), qd.data(), tau.data(), qdd.data(), with_fext ? fext.data() : nullptr, arm)
                  .ok());
  const Motion<S> a0 = base_acceleration(model.gravity);
  std::vector<S> tree[3], packed[3];
  for (auto* set : {tree, packed})
    for (int k = 0; k < 3; ++k) set[k].assign(static_cast<std::size_t>(n * n), S(NAN));
  const auto run = [&](std::vector<S>* out, bool use_packed) {
    const auto m = [&](int k) { return MatrixRef<S>{out[k].data(), n, 1}; };
    const Force<S>* f = with_fext ? fext.data() : nullptr;
    return use_packed ? fd_derivatives_instance<8>(model.bodies.data(), n, a0, q.data(), qd.data(),
                                                   static_cast<const S*>(qdd.data()), f, dd.work.data(), m(0), m(1),
                                                   m(2), arm)
                      : fd_derivatives_instance(model.bodies.data(), n, a0, q.data(), qd.data(),
                                                static_cast<const S*>(qdd.data()), f, dd.work.data(), m(0), m(1),
                                                m(2), arm);
  };
  ASSERT_EQ(run(tree, false), -1);
  ASSERT_EQ(run(packed, true), -1);
  const double tol = sizeof(S) == 4 ? 1e-4 : 1e-13;
  for (int k = 0; k < 3; ++k) {
    SCOPED_TRACE("block " + std::to_string(k));
    EXPECT_LT(test::max_rel_err(packed[k], tree[k]), tol);
  }
  for (Index i = 0; i < n; ++i)
    for (Index j = 0; j < n; ++j) EXPECT_EQ(packed[2][i * n + j], packed[2][j * n + i]);
  // a pivot that is not positive: the same DoF reported
  if (with_armature && n > 2) {
    std::vector<S> bad(armature);
    bad[n / 2] = S(-1e6);
    arm = bad.data();
    EXPECT_EQ(run(packed, true), run(tree, false));
    EXPECT_GE(run(packed, true), 0);
  }
}

TEST(AbaDerivatives, PackedSolveMatchesTheTreeWalks) {
  std::vector<std::pair<std::string, Model>> models;
  models.emplace_back("iiwa.urdf", test::load_robot("iiwa.urdf"));
  for (const char* spec : {"chain:1", "chain:2", "chain:8"}) models.emplace_back(spec, load_model(spec));
  for (unsigned seed : {1u, 2u, 3u}) models.emplace_back("random_model(8)", test::random_model(8, seed));
  models.emplace_back("random_model(5)", test::random_model(5, 4));
  models.emplace_back("random_chains_from_base(7)", test::random_chains_from_base(7, 5, {3, 5}));
  for (auto& [name, model] : models)
    for (bool with_fext : {false, true})
      for (bool with_armature : {false, true}) {
        packed_against_tree<double>(name, model, with_fext, with_armature);
        packed_against_tree<float>(name, model, with_fext, with_armature);
      }
}

// The directional derivative of inverse dynamics against the dense matrices: dtau =
// dtau/dq dq + dtau/dqd dqd + M dqdd, and the adjoint (w^T dtau/dq, w^T dtau/dqd, M
// w), 1e-11 relative to max(1, max |result|), up to rope:1000.
TEST(RneaJvp, JvpAndVjpMatchTheDenseDerivatives) {
  auto models = derivative_models();
  models.emplace_back("rope:1000", load_model("rope:1000"));
  for (auto& [name, model] : models) {
    SCOPED_TRACE(name);
    const Index n = model.nv();
    const State s = random_state(n, 5 + n, true);
    std::mt19937_64 rng(n);
    const auto dq = random_vector(rng, n, -1, 1), dqd = random_vector(rng, n, -1, 1), dqdd = random_vector(rng, n, -1, 1),
               w = random_vector(rng, n, -1, 1);
    const std::size_t nn = static_cast<std::size_t>(n) * n;
    std::vector<double> A(nn), B(nn), M(nn), jvp(n, NAN), tau(n, NAN), tau_ref(n);
    DerivativeDataTpl<double> dd(model);
    rnea_derivatives(model, dd, s.q.data(), s.qd.data(), s.qdd.data(), s.fext.data(), ref(A, n), ref(B, n), ref(M, n),
                     tau_ref.data());
    const DenseProducts dense = dense_products(n, {&A, &B, &M}, {&dq, &dqd, &dqdd}, w);
    RneaJvpData<double> jd(model);
    rnea_jvp(model, jd, s.q.data(), s.qd.data(), s.qdd.data(), s.fext.data(), dq.data(), dqd.data(), dqdd.data(),
             jvp.data(), tau.data());
    EXPECT_LT(test::max_rel_err(jvp, dense.jv), 1e-11);
    EXPECT_LT(test::max_rel_err(tau, tau_ref), 1e-12);
    // the adjoint: w^T dtau/dq, w^T dtau/dqd, M w
    std::vector<double> gq(n, NAN), gqd(n, NAN), gqdd(n, NAN);
    rnea_vjp(model, jd, s.q.data(), s.qd.data(), s.qdd.data(), s.fext.data(), w.data(), gq.data(), gqd.data(),
             gqdd.data());
    dense.expect_transpose(gq, gqd, gqdd, 1e-11);
  }
}

// On rope:100000, where the dense matrices (80 GB each) do not fit: against central
// differences along the direction (Richardson, step 1e-4): 1e-6 relative to max(1,
// max |dtau|).
TEST(RneaJvp, MatchesCentralDifferencesOnALongRope) {
  const Model model = load_model("rope:100000");
  const Index n = model.nv();
  // a hanging rope near rest, direction (dq, dqd, dqdd)
  const NearRest r = near_rest(n, 3, 9);
  const State& s = r.s;
  std::vector<double> jvp(n);
  RneaJvpData<double> jd(model);
  rnea_jvp(model, jd, s.q.data(), s.qd.data(), s.qdd.data(), s.fext.data(), r.d[0].data(), r.d[1].data(),
           r.d[2].data(), jvp.data());
  Data data(model, /*mass_matrix=*/false);
  // the direction changes every joint angle, so a step h turns the rope's shape by
  // about h sqrt(nv): 1e-4 keeps that small (3e-4 to 1e-5 all pass; 1e-3 fails by
  // truncation)
  const std::vector<double> d1 = directional_difference(
      n, {&s.q, &s.qd, &s.qdd}, {&r.d[0], &r.d[1], &r.d[2]}, 1e-4,
      [&](const double* q, const double* qd, const double* qdd, double* out) {
        rnea(model, data, q, qd, qdd, out, s.fext.data());
      });
  EXPECT_LT(test::max_rel_err(jvp, d1), 1e-6);
}

// The JVP and VJP of forward dynamics against the dense aba_derivatives: 1e-9
// relative to max(1, max |result|) (M^-1 by the ABA at rest against L^T L), up to
// rope:200.
TEST(AbaJvp, JvpAndVjpMatchTheDenseDerivatives) {
  auto models = derivative_models();
  models.emplace_back("rope:200", load_model("rope:200"));
  for (auto& [name, model] : models) {
    SCOPED_TRACE(name);
    const Index n = model.nv();
    const State s = random_state(n, 15 + n, true);
    std::mt19937_64 rng(n + 1);
    const auto dq = random_vector(rng, n, -1, 1), dqd = random_vector(rng, n, -1, 1), dtau = random_vector(rng, n, -1, 1),
               w = random_vector(rng, n, -1, 1);
    const std::size_t nn = static_cast<std::size_t>(n) * n;
    std::vector<double> A(nn), B(nn), Minv(nn), qdd(n), qdd2(n, NAN), jvp(n, NAN), gq(n, NAN), gqd(n, NAN),
        gtau(n, NAN);
    DerivativeDataTpl<double> dd(model);
    ASSERT_TRUE(aba_derivatives(model, dd, s.q.data(), s.qd.data(), s.tau.data(), s.fext.data(), qdd.data(),
                                ref(A, n), ref(B, n), ref(Minv, n))
                    .ok());
    const DenseProducts dense = dense_products(n, {&A, &B, &Minv}, {&dq, &dqd, &dtau}, w);
    AbaJvpData<double> jd(model);
    ASSERT_TRUE(aba_jvp(model, jd, s.q.data(), s.qd.data(), s.tau.data(), s.fext.data(), dq.data(), dqd.data(),
                        dtau.data(), jvp.data(), qdd2.data())
                    .ok());
    EXPECT_EQ(qdd2, qdd);
    EXPECT_LT(test::max_rel_err(jvp, dense.jv), 1e-9);
    ASSERT_TRUE(aba_vjp(model, jd, s.q.data(), s.qd.data(), s.tau.data(), s.fext.data(), w.data(), gq.data(),
                        gqd.data(), gtau.data(), qdd2.data())
                    .ok());
    dense.expect_transpose(gq, gqd, gtau, 1e-9);
  }
}

// The JVP of forward dynamics on rope:1000 against central differences of the ABA
// along the direction (Richardson, step 1e-4, the rope near rest as for RneaJvp):
// 1e-6 relative to max(1, max |dqdd|). Longer ropes are not a test of the JVP in
// double: cond(M) grows like nv^4, and the differences of the ABA itself drift
// (2e-5 at rope:10000, 0.1 at rope:100000); a check there needs the high-precision
// truth (src/truth).
TEST(AbaJvp, MatchesCentralDifferencesOnARope) {
  const Model model = load_model("rope:1000");
  const Index n = model.nv();
  // direction (dq, dqd, dtau)
  const NearRest r = near_rest(n, 4, 10);
  const State& s = r.s;
  std::vector<double> jvp(n), qdd(n);
  AbaJvpData<double> jd(model);
  ASSERT_TRUE(aba_jvp(model, jd, s.q.data(), s.qd.data(), s.tau.data(), s.fext.data(), r.d[0].data(), r.d[1].data(),
                      r.d[2].data(), jvp.data(), qdd.data())
                  .ok());
  Data data(model, /*mass_matrix=*/false);
  const std::vector<double> d1 = directional_difference(
      n, {&s.q, &s.qd, &s.tau}, {&r.d[0], &r.d[1], &r.d[2]}, 1e-4,
      [&](const double* q, const double* qd, const double* tau, double* out) {
        ASSERT_TRUE(aba(model, data, q, qd, tau, out, s.fext.data()).ok());
      });
  EXPECT_LT(test::max_rel_err(jvp, d1), 1e-6);
}

}  // namespace
}  // namespace scandyn
