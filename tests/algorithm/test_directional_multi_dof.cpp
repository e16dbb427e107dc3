// The directional derivatives (JVP, VJP) of inverse and forward dynamics on models with
// multi-DoF joints (a floating base, spherical joints; rnea_jvp / rnea_vjp / aba_jvp /
// aba_vjp over scandyn/instance/directional_general_instance.hpp) against the dense
// first-order derivatives of the same models (rnea_derivatives / aba_derivatives:
// rnea_derivatives_general_instance, fd_derivatives_general_instance, themselves
// tested against central differences along each DoF's retraction in
// test_derivatives_multi_dof.cpp) contracted with the directions, in the same tangent
// convention (q (+) d = q exp(d) per joint); the adjoint identity <w, J v> = <J^T w, v>;
// the engine (make_fd_directional_derivatives, method aba: serial equal to the
// reference, OpenMP equal to serial, float against double) and what it refuses.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <string>
#include <vector>

#include "floating_models.hpp"
#include "scandyn/algorithm/derivatives.hpp"
#include "scandyn/algorithm/directional_derivatives.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

using test::random_vector;

using Case = test::NamedModel;

std::vector<Case> cases() { return test::multi_dof_models({}, 6, 7, 9, {1, 4, 11, 30}, 70); }

// One state and directions: q (nq), qd, tau, and the directions dq (a tangent, nv),
// dqd, dtau, and the weight w (nv each); fext per body or empty.
struct State {
  std::vector<double> q, qd, tau, dq, dqd, dtau, w, arm;
  std::vector<Force<double>> fext;
};

State random_state(const Model& m, unsigned seed, bool with_fext) {
  std::mt19937_64 rng(seed);
  const int nv = static_cast<int>(m.nv());
  State s;
  s.q = test::random_q(m, rng, -2, 2);
  s.qd = random_vector(rng, nv, -2, 2);
  s.tau = random_vector(rng, nv, -5, 5);
  s.dq = random_vector(rng, nv, -1, 1);
  s.dqd = random_vector(rng, nv, -1, 1);
  s.dtau = random_vector(rng, nv, -1, 1);
  s.w = random_vector(rng, nv, -1, 1);
  s.arm = random_vector(rng, nv, 0.01, 0.1);
  if (with_fext) s.fext = test::random_wrenches<double>(rng, static_cast<int>(m.nbodies()), 2.0);
  return s;
}

const Force<double>* wrenches(const State& s) { return s.fext.empty() ? nullptr : s.fext.data(); }

// y = sum_k A_k x_k (row-major nv x nv blocks; transposed: A_k^T x_k) and its scale,
// sum_k |A_k| |x_k| per entry: the size of the terms the result sums, whose rounding
// the comparison allows (a ball rope's cond(M) reaches 1e7: its dqdd cancels).
struct Product {
  std::vector<double> y, scale;
};
Product contract(Index nv, std::initializer_list<std::pair<const std::vector<double>*, const std::vector<double>*>> t,
                 bool transposed) {
  Product p{std::vector<double>(nv, 0.0), std::vector<double>(nv, 0.0)};
  for (const auto& [A, x] : t)
    for (Index i = 0; i < nv; ++i)
      for (Index j = 0; j < nv; ++j) {
        const double a = transposed ? (*A)[j * nv + i] : (*A)[i * nv + j];
        p.y[i] += a * (*x)[j];
        p.scale[i] += std::fabs(a * (*x)[j]);
      }
  return p;
}

// max_i |got_i - want_i| / max_i scale_i
double rel_err(const std::vector<double>& got, const Product& want) {
  double err = 0, scale = 0;
  for (std::size_t i = 0; i < got.size(); ++i) {
    err = std::max(err, std::fabs(got[i] - want.y[i]));
    scale = std::max(scale, want.scale[i]);
  }
  return err / scale;
}

// max_i |a_i - b_i| / max(1, max_i |b_i|)
double max_rel(const std::vector<double>& a, const std::vector<double>& b) {
  double err = 0, scale = 1;
  for (std::size_t i = 0; i < a.size(); ++i) {
    err = std::max(err, std::fabs(a[i] - b[i]));
    scale = std::max(scale, std::fabs(b[i]));
  }
  return err / scale;
}

MatrixRef<double> ref(std::vector<double>& m, Index n) { return {m.data(), n, 1}; }

// Against the dense derivatives: 1e-10 of the terms' magnitudes. The floating ball
// rope's M is ill-conditioned (6 links of 1e-8 kg m^2 on a free root): there the ABA's
// M^-1 w and the dense path's L^T L solve of the same M (gtau, which no directional
// recursion touches) already differ by 4e-10, so its bound is 2e-9 (measured: at most
// 7.6e-10, gq).
constexpr double kTol = 1e-10;
double fd_tolerance(const std::string& name) { return name == "ballrope:6 (floating)" ? 2e-9 : kTol; }

TEST(MultiDofDirectional, InverseDynamicsMatchDenseDerivatives) {
  for (const Case& c : cases()) {
    for (bool with_fext : {false, true}) {
      SCOPED_TRACE(c.name + (with_fext ? " with fext" : ""));
      const Model& m = c.m;
      ASSERT_TRUE(m.multi_dof());
      const Index nv = m.nv();
      const State s = random_state(m, 5 + static_cast<unsigned>(nv), with_fext);
      const std::vector<double> qdd = s.dtau;  // any accelerations
      DerivativeDataTpl<double> dd(m);
      std::vector<double> Dq(nv * nv), Dqd(nv * nv), M(nv * nv), tau(nv);
      rnea_derivatives(m, dd, s.q.data(), s.qd.data(), qdd.data(), wrenches(s), ref(Dq, nv), ref(Dqd, nv), ref(M, nv),
                       tau.data());
      RneaJvpData<double> data(m);
      std::vector<double> dtau(nv), tau_jvp(nv), gq(nv), gqd(nv), gqdd(nv);
      const std::vector<double> dqdd = s.w;
      rnea_jvp(m, data, s.q.data(), s.qd.data(), qdd.data(), wrenches(s), s.dq.data(), s.dqd.data(), dqdd.data(),
               dtau.data(), tau_jvp.data());
      EXPECT_LT(max_rel(tau_jvp, tau), 1e-13);  // ID (the dense path sums it in the world frame)
      EXPECT_LT(rel_err(dtau, contract(nv, {{&Dq, &s.dq}, {&Dqd, &s.dqd}, {&M, &dqdd}}, false)), kTol);
      rnea_vjp(m, data, s.q.data(), s.qd.data(), qdd.data(), wrenches(s), s.w.data(), gq.data(), gqd.data(),
               gqdd.data());
      EXPECT_LT(rel_err(gq, contract(nv, {{&Dq, &s.w}}, true)), kTol);
      EXPECT_LT(rel_err(gqd, contract(nv, {{&Dqd, &s.w}}, true)), kTol);
      EXPECT_LT(rel_err(gqdd, contract(nv, {{&M, &s.w}}, true)), kTol);
    }
  }
}

TEST(MultiDofDirectional, ForwardDynamicsMatchDenseDerivatives) {
  for (const Case& c : cases()) {
    for (int variant = 0; variant < 3; ++variant) {  // plain, fext, armature
      const bool with_fext = variant == 1, with_arm = variant == 2;
      SCOPED_TRACE(c.name + (with_fext ? " with fext" : with_arm ? " with armature" : ""));
      const Model& m = c.m;
      const Index nv = m.nv();
      const State s = random_state(m, 17 + static_cast<unsigned>(nv) + variant, with_fext);
      const double* arm = with_arm ? s.arm.data() : nullptr;
      DerivativeDataTpl<double> dd(m);
      std::vector<double> Aq(nv * nv), Aqd(nv * nv), Minv(nv * nv), qdd(nv);
      ASSERT_TRUE(aba_derivatives(m, dd, s.q.data(), s.qd.data(), s.tau.data(), wrenches(s), qdd.data(), ref(Aq, nv),
                                  ref(Aqd, nv), ref(Minv, nv), arm)
                      .ok());
      AbaJvpData<double> data(m);
      std::vector<double> dqdd(nv), qdd_j(nv), qdd_v(nv), gq(nv), gqd(nv), gtau(nv);
      ASSERT_TRUE(aba_jvp(m, data, s.q.data(), s.qd.data(), s.tau.data(), wrenches(s), s.dq.data(), s.dqd.data(),
                          s.dtau.data(), dqdd.data(), qdd_j.data(), arm)
                      .ok());
      ASSERT_TRUE(aba_vjp(m, data, s.q.data(), s.qd.data(), s.tau.data(), wrenches(s), s.w.data(), gq.data(),
                          gqd.data(), gtau.data(), qdd_v.data(), arm)
                      .ok());
      EXPECT_EQ(qdd_j, qdd);  // the reference ABA itself
      EXPECT_EQ(qdd_v, qdd);
      const double tol = fd_tolerance(c.name);
      EXPECT_LT(rel_err(dqdd, contract(nv, {{&Aq, &s.dq}, {&Aqd, &s.dqd}, {&Minv, &s.dtau}}, false)), tol);
      EXPECT_LT(rel_err(gq, contract(nv, {{&Aq, &s.w}}, true)), tol);
      EXPECT_LT(rel_err(gqd, contract(nv, {{&Aqd, &s.w}}, true)), tol);
      EXPECT_LT(rel_err(gtau, contract(nv, {{&Minv, &s.w}}, true)), tol);

      // the adjoint identity <w, J v> = <J^T w, v>, v = (dq, dqd, dtau), relative to the
      // sum of the terms' magnitudes
      double lhs = 0, rhs = 0, size = 0;
      for (Index i = 0; i < nv; ++i) {
        lhs += s.w[i] * dqdd[i];
        const double t[3] = {gq[i] * s.dq[i], gqd[i] * s.dqd[i], gtau[i] * s.dtau[i]};
        for (double x : t) rhs += x, size += std::fabs(x);
        size += std::fabs(s.w[i] * dqdd[i]);
      }
      EXPECT_LT(std::fabs(lhs - rhs), kTol * size);
    }
  }
}

// A failed pivot is reported, as aba's.
TEST(MultiDofDirectional, ReportsAFailedPivot) {
  Model m = test::load_floating("ballrope:3");
  m.bodies[2].I = Inertia<double>::zero();  // the leaf's joint pivot S^T IA S = 0
  const State s = random_state(m, 3, false);
  const Force<double>* const kNoWrenches = nullptr;
  AbaJvpData<double> data(m);
  const Index nv = m.nv();
  std::vector<double> a(nv), b(nv), c(nv), d(nv);
  EXPECT_FALSE(aba_jvp(m, data, s.q.data(), s.qd.data(), s.tau.data(), kNoWrenches, s.dq.data(), s.dqd.data(),
                       s.dtau.data(), a.data(), b.data())
                   .ok());
  EXPECT_FALSE(aba_vjp(m, data, s.q.data(), s.qd.data(), s.tau.data(), kNoWrenches, s.w.data(), a.data(), b.data(),
                       c.data(), d.data())
                   .ok());
}

// The engine: B instances (instance b at row b), every output NaN before the call.
struct Batch {
  Index nq, nv, nb, B;
  std::vector<double> q, qd, tau, dq, dqd, dtau, w;
  std::vector<Force<double>> fext;
};

Batch random_batch(const Model& m, Index B, unsigned seed) {
  Batch x{m.nq(), m.nv(), m.nbodies(), B, {}, {}, {}, {}, {}, {}, {}, {}};
  for (Index b = 0; b < B; ++b) {
    const State s = random_state(m, seed + static_cast<unsigned>(b), true);
    for (auto [dst, src] : {std::pair{&x.q, &s.q}, {&x.qd, &s.qd}, {&x.tau, &s.tau}, {&x.dq, &s.dq},
                            {&x.dqd, &s.dqd}, {&x.dtau, &s.dtau}, {&x.w, &s.w}})
      dst->insert(dst->end(), src->begin(), src->end());
    x.fext.insert(x.fext.end(), s.fext.begin(), s.fext.end());
  }
  return x;
}

// qdd (jvp), dqdd, qdd (vjp), gq, gqd, gtau: nv x B each, instance innermost per row b
template <class S>
std::vector<std::vector<S>> run_engine(const Model& model, const Batch& x, BackendKind kind, std::string* strategy) {
  BackendOptions o;
  o.backend = kind;
  o.max_batch = x.B;
  o.fd_method = FdMethod::Aba;
  o.threads = 2;
  const ModelTpl<S> m = model.cast<S>();
  auto eng = make_fd_directional_derivatives(m, o);
  if (strategy) *strategy = eng->strategy();
  auto cast = [](const std::vector<double>& v) { return std::vector<S>(v.begin(), v.end()); };
  const std::vector<S> q = cast(x.q), qd = cast(x.qd), tau = cast(x.tau), dq = cast(x.dq), dqd = cast(x.dqd),
                       dtau = cast(x.dtau), w = cast(x.w);
  std::vector<Force<S>> fext;
  for (const Force<double>& f : x.fext) fext.push_back(f.template cast<S>());
  std::vector<std::vector<S>> out(6, std::vector<S>(static_cast<std::size_t>(x.nv * x.B), S(NAN)));
  FdBatchIn<S> in;
  in.q = BatchView<const S>::aos(q.data(), x.nq, x.B);
  in.qd = BatchView<const S>::aos(qd.data(), x.nv, x.B);
  in.tau = BatchView<const S>::aos(tau.data(), x.nv, x.B);
  in.fext = fext.data();
  auto view = [&](const std::vector<S>& v) { return BatchView<const S>::aos(v.data(), x.nv, x.B); };
  auto out_view = [&](int k) { return BatchView<S>::aos(out[k].data(), x.nv, x.B); };
  EXPECT_TRUE(eng->jvp(in, view(dq), view(dqd), view(dtau), out_view(0), out_view(1)).ok());
  EXPECT_TRUE(eng->vjp(in, view(w), out_view(2), out_view(3), out_view(4), out_view(5)).ok());
  return out;
}

TEST(MultiDofDirectional, Engines) {
  for (const Case& c : cases()) {
    SCOPED_TRACE(c.name);
    const Model& m = c.m;
    const Index nv = m.nv(), B = 5;
    const Batch x = random_batch(m, B, 101);
    std::string strategy;
    const auto serial = run_engine<double>(m, x, BackendKind::Serial, &strategy);
    EXPECT_EQ(strategy, "aba_jvp");
    // serial: the reference functions, instance by instance
    AbaJvpData<double> data(m);
    for (Index b = 0; b < B; ++b) {
      std::vector<double> dqdd(nv), qdd(nv), gq(nv), gqd(nv), gtau(nv), qdd_v(nv);
      const Force<double>* f = x.fext.data() + b * m.nbodies();
      ASSERT_TRUE(aba_jvp(m, data, x.q.data() + b * m.nq(), x.qd.data() + b * nv, x.tau.data() + b * nv, f,
                          x.dq.data() + b * nv, x.dqd.data() + b * nv, x.dtau.data() + b * nv, dqdd.data(), qdd.data())
                      .ok());
      ASSERT_TRUE(aba_vjp(m, data, x.q.data() + b * m.nq(), x.qd.data() + b * nv, x.tau.data() + b * nv, f,
                          x.w.data() + b * nv, gq.data(), gqd.data(), gtau.data(), qdd_v.data())
                      .ok());
      const std::vector<double>* want[6] = {&qdd, &dqdd, &qdd_v, &gq, &gqd, &gtau};
      for (int k = 0; k < 6; ++k)
        for (Index i = 0; i < nv; ++i) ASSERT_EQ(serial[k][b * nv + i], (*want[k])[i]) << "output " << k;
    }
    if (backend_unusable(BackendKind::OpenMP).empty()) {
      EXPECT_EQ(run_engine<double>(m, x, BackendKind::OpenMP, nullptr), serial);  // bit for bit
    }
    // float against double, 1e-4 of each output's largest entry (at least 1): measured
    // at most 1.7e-5 (atlas's gqd) on the robots and the random trees (ball ropes left
    // out: their 1e-8 kg m^2 links fail float's pivots, as for the dense derivatives)
    if (c.name.find("ballrope") != std::string::npos) continue;
    const auto single = run_engine<float>(m, x, BackendKind::Serial, nullptr);
    for (int k = 0; k < 6; ++k) {
      double err = 0, scale = 1;
      for (std::size_t e = 0; e < serial[k].size(); ++e) {
        err = std::max(err, std::fabs(double(single[k][e]) - serial[k][e]));
        scale = std::max(scale, std::fabs(serial[k][e]));
      }
      EXPECT_LT(err / scale, 1e-4) << "float output " << k;
    }
  }
}

TEST(MultiDofDirectional, EngineRefusals) {
  const Model m = test::load_floating(test::model_path("hyq.urdf"));
  BackendOptions o;
  o.fd_method = FdMethod::Parallel;  // the chain scans take 1-DoF joints only
  EXPECT_THROW(make_fd_directional_derivatives(m, o), BackendError);
  EXPECT_THROW(make_fd_directional_derivatives(load_model("ballrope:8"), o), BackendError);
  o.fd_method = FdMethod::Auto;  // a spherical chain: aba, not the scans
  EXPECT_EQ(make_fd_directional_derivatives(load_model("ballrope:8"), o)->strategy(), "aba_jvp");
  if (!SCANDYN_HAS_CUDA) return;  // (a build without cuda refuses the backend itself)
  o.backend = BackendKind::Cuda;
  try {
    make_fd_directional_derivatives(m, o);
    ADD_FAILURE() << "cuda took a floating base";
  } catch (const BackendError& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("root_joint"), std::string::npos) << what;
  }
}

}  // namespace
}  // namespace scandyn
