// The simulator's step derivatives and rollout derivatives on models with multi-DoF
// joints (a floating base, spherical joints): scandyn/sim/manifold_step_derivatives.hpp.
// Truths: central differences of the Simulator's own step (serial, double) along
// each tangent direction, q ⊕ (±eps e_j) = joint_integrate(q, e_j, ±eps), with the
// outputs mapped back to the tangent at the unperturbed output by the inverse
// retraction (free: log(R_ref^T R), R_ref^T (p - p_ref); spherical: log(quat_ref^-1
// quat)); qd and tau perturbed as plain vectors. Steps 1e-6 (q), 1e-6 for qd (1e-3
// on the ball ropes, whose dt = 1e-4 makes dq'/dqd ~ 1e-4: a smaller step leaves
// the difference of q' at rounding level) and 2e-3 tau_scale (tau); tolerance 1e-6
// relative to each block's largest entry. The
// rollout gradient against central differences of a rollout loss, 1e-6 relative;
// <vjp(g), v> = <g, jvp(v)> to 1e-10; OpenMP equal to serial bit for bit; float
// within 1e-3 of double (relative to each block's largest entry).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>
#include <string>
#include <vector>

#include "floating_models.hpp"
#include "scandyn/algorithm/configuration.hpp"
#include "scandyn/sim/manifold_step_derivatives.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"
#include "scandyn/sim/step_derivatives.hpp"
#include "scene_util.hpp"
#include "step_derivatives_util.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

using sim::Scene;
using sim::Simulator;
using sim::StepSequence;

struct Case {
  std::string name;
  Scene scene;
  double tau_scale = 5;  // torques in [-tau_scale, tau_scale]
  double qd_step = 1e-6;  // the central differences' step for qd
};

Scene with_integrator(Scene s, const char* integrator) {
  sim::Integrator in;
  EXPECT_TRUE(sim::parse_integrator(integrator, in));
  s.integrator = in;
  return s;
}

std::vector<Case> cases() {
  std::vector<Case> c;
  for (const char* integrator : {"euler", "rk4", "implicit"}) {
    const std::string in = integrator;
    c.push_back({"floating hyq " + in,
                 test::scene_from(R"({"model": "hyq.urdf", "base": "floating", "dt": 2e-3, "integrator": ")" + in +
                                  R"(", "effects": {"gravity": true, "damping": 0.5, "springs": {"stiffness": 3},
                                  "external": {"wrenches": [{"link": "lf_lowerleg", "wrench": [0.1, 0.2, 0.3, 1, 2, 3]},
                                                            {"link": "base_link_0", "wrench": [1, -2, 0.5, 3, 0, -1]}]}}})"),
                 5});
    c.push_back({"ballrope:4 " + in,
                 test::scene_from(R"({"model": "ballrope:4", "dt": 1e-4, "integrator": ")" + in +
                                  R"(", "effects": {"gravity": true, "damping": 1e-6}})"),
                 1e-4, 1e-3});
    c.push_back({"floating ballrope:4 " + in,
                 test::scene_from(R"({"model": "ballrope:4", "base": "floating", "dt": 1e-4, "integrator": ")" + in +
                                  R"(", "effects": {"gravity": true, "damping": 1e-6}})"),
                 1e-4, 1e-3});
  }
  // a random tree on a free root with ~40% spherical joints, gravity
  for (const char* integrator : {"euler", "rk4"}) {
    Scene s = test::scene_from(R"({"model": "ballrope:2", "base": "floating", "dt": 1e-3,
                                   "effects": {"gravity": true}})");
    s.model = test::random_floating_model(9, 5, 0.4);
    s.initial.q.assign(static_cast<std::size_t>(s.model.nq()), 0.0);
    neutral_bodies(s.model.bodies.data(), s.model.nbodies(), s.initial.q.data());
    s.initial.qd.assign(static_cast<std::size_t>(s.model.nv()), 0.0);
    s.joints.assign(static_cast<std::size_t>(s.model.nv()), s.joints[0]);  // the base's: no joint effect
    c.push_back({std::string("random free tree ") + integrator, with_integrator(s, integrator), 2});
  }
  return c;
}

Scene batch_of(Scene s, Index B) {
  s.instances = B;
  return s;
}

struct State {
  std::vector<double> q, qd, tau;  // (nq), (nv), (nv)
};

State random_state(const Model& m, unsigned seed, double tau_scale) {
  std::mt19937_64 rng(seed);
  State s;
  s.q = test::random_q(m, rng, -1, 1);
  s.qd = test::random_vector(rng, static_cast<int>(m.nv()), -1, 1);
  s.tau = test::random_vector(rng, static_cast<int>(m.nv()), -tau_scale, tau_scale);
  return s;
}

// q ⊕ h e_j (the retraction along tangent direction j).
std::vector<double> retract(const Model& m, std::vector<double> q, Index j, double h) {
  std::vector<double> e(static_cast<std::size_t>(m.nv()), 0.0);
  e[static_cast<std::size_t>(j)] = 1;
  integrate_configuration(m, q.data(), e.data(), h);
  return q;
}

// log of a unit quaternion (x, y, z, w) as a rotation vector.
Vec3<double> quat_log(const double* p) {
  double x = p[0], y = p[1], z = p[2], w = p[3];
  if (w < 0) x = -x, y = -y, z = -z, w = -w;
  const double s = std::sqrt(x * x + y * y + z * z);
  const double k = s < 1e-12 ? 2 / w : 2 * std::atan2(s, w) / s;
  return {k * x, k * y, k * z};
}

// The inverse retraction: d with q_ref ⊕ d = q, joint by joint (nv entries).
std::vector<double> tangent_of(const Model& m, const double* q_ref, const double* q) {
  std::vector<double> d(static_cast<std::size_t>(m.nv()));
  for (const Body<double>& b : m.bodies) {
    const double *a = q_ref + b.idx_q, *c = q + b.idx_q;
    double* o = d.data() + b.idx_v;
    if (b.type == JointType::Revolute || b.type == JointType::Prismatic) {
      o[0] = c[0] - a[0];
      continue;
    }
    const double* qa = b.type == JointType::Free ? a + 3 : a;
    const double* qc = b.type == JointType::Free ? c + 3 : c;
    const double inv[4] = {-qa[0], -qa[1], -qa[2], qa[3]};
    double r[4];
    quat_multiply(inv, qc, r);
    const Vec3<double> w = quat_log(r);
    o[0] = w.x, o[1] = w.y, o[2] = w.z;
    if (b.type == JointType::Free) {
      const Vec3<double> dp = mul_transpose(quat_to_matrix(qa), Vec3<double>{c[0] - a[0], c[1] - a[1], c[2] - a[2]});
      o[3] = dp.x, o[4] = dp.y, o[5] = dp.z;
    }
  }
  return d;
}

// Central differences of the simulator's step at s: J (2n x 3n, row-major; rows the
// tangent of q', qd'; columns q's tangent, qd, tau), and the unperturbed new state.
std::vector<double> step_by_differences(const Case& c, const State& s, std::vector<double>& q_next) {
  const Model& m = c.scene.model;
  const Index n = m.nv(), nq = m.nq(), P = 3 * n, B = 2 * P + 1;
  auto h_of = [&](Index k) { return k < n ? 1e-6 : k < 2 * n ? c.qd_step : 2e-3 * c.tau_scale; };
  std::vector<double> q, qd, tau;
  for (Index k = 0; k < B; ++k) {
    const Index col = k / 2;
    const double h = k == B - 1 ? 0.0 : (k % 2 == 0 ? h_of(col) : -h_of(col));
    std::vector<double> qk = s.q, qdk = s.qd, tk = s.tau;
    if (k < B - 1) {
      if (col < n) qk = retract(m, s.q, col, h);
      else if (col < 2 * n) qdk[static_cast<std::size_t>(col - n)] += h;
      else tk[static_cast<std::size_t>(col - 2 * n)] += h;
    }
    q.insert(q.end(), qk.begin(), qk.end());
    qd.insert(qd.end(), qdk.begin(), qdk.end());
    tau.insert(tau.end(), tk.begin(), tk.end());
  }
  test::simulate_rows(batch_of(c.scene, B), q, qd, {tau});
  const double* ref = q.data() + (B - 1) * nq;
  q_next.assign(ref, ref + nq);
  std::vector<double> J(static_cast<std::size_t>(2 * n * P));
  for (Index k = 0; k < P; ++k) {
    const std::vector<double> dp = tangent_of(m, ref, q.data() + 2 * k * nq);
    const std::vector<double> dm = tangent_of(m, ref, q.data() + (2 * k + 1) * nq);
    for (Index r = 0; r < n; ++r) {
      J[r * P + k] = (dp[r] - dm[r]) / (2 * h_of(k));
      J[(n + r) * P + k] = (qd[2 * k * n + r] - qd[(2 * k + 1) * n + r]) / (2 * h_of(k));
    }
  }
  return J;
}

using Jacobians = test::StepJacobians;

Jacobians step_jacobians(const Case& c, const std::vector<double>& q, const std::vector<double>& qd,
                         const std::vector<double>& tau, BackendKind kind, int threads = 1) {
  return test::step_jacobians_of(batch_of(c.scene, 1), q, qd, tau, kind, threads);
}

TEST(StepDerivativesMultiDof, JacobianMatchesCentralDifferencesOfTheSimulatorsStep) {
  for (const Case& c : cases()) {
    SCOPED_TRACE(c.name);
    const Model& m = c.scene.model;
    ASSERT_TRUE(m.multi_dof());
    const Index n = m.nv(), P = 3 * n;
    const State s = random_state(m, 11, c.tau_scale);
    std::vector<double> q_next;
    const std::vector<double> ref = step_by_differences(c, s, q_next);
    const Jacobians J = step_jacobians(c, s.q, s.qd, s.tau, BackendKind::Serial);
    // the new state: the simulator's bit for bit
    for (Index i = 0; i < m.nq(); ++i) EXPECT_EQ(J.q[i], q_next[i]) << "q' " << i;
    for (int rb = 0; rb < 2; ++rb)
      for (int cb = 0; cb < 3; ++cb) {
        double scale = 0, err = 0;
        for (Index r = 0; r < n; ++r)
          for (Index k = 0; k < n; ++k) scale = std::max(scale, std::abs(ref[(rb * n + r) * P + cb * n + k]));
        for (Index r = 0; r < n; ++r)
          for (Index k = 0; k < n; ++k)
            err = std::max(err, std::abs(J.at(0, rb * n + r, cb * n + k) - ref[(rb * n + r) * P + cb * n + k]));
        EXPECT_LE(err, 1e-6 * std::max(scale, 1e-300)) << "block " << rb << cb << " scale " << scale;
      }
  }
}

// The rollouts' JVP and VJP of one step (step_jvp_at_instance / step_vjp_at_instance
// over aba_jvp / aba_vjp, O(nv)) are the dense step Jacobian contracted: J v and J^T g
// to 1e-10 of the largest sum of the terms' magnitudes, sum_k |J_ik v_k|, on every case
// (euler, rk4, implicit; damping, springs, external wrenches); 1e-9 on the floating ball
// rope, whose ill-conditioned M (1e-8 kg m^2 links on a free root) makes the ABA's
// M^-1 and the dense path's L^T L solve differ by up to 7.6e-10 of the same measure
// (tests/algorithm/test_directional_multi_dof.cpp; measured here 1.6e-10).
TEST(StepDerivativesMultiDof, OneStepJvpAndVjpAreTheJacobianContracted) {
  for (const Case& c : cases()) {
    SCOPED_TRACE(c.name);
    const Model& m = c.scene.model;
    const Index n = m.nv(), nq = m.nq(), P = 3 * n;
    const State s = random_state(m, 23, c.tau_scale);
    const double tol = c.name.find("floating ballrope") == 0 ? 1e-9 : 1e-10;
    const Jacobians J = step_jacobians(c, s.q, s.qd, s.tau, BackendKind::Serial);
    std::mt19937_64 rng(29);
    const std::vector<double> v = test::random_vector(rng, static_cast<int>(P), -1, 1),
                              g = test::random_vector(rng, static_cast<int>(2 * n), -1, 1);
    Simulator<double> base(batch_of(c.scene, 1), BackendKind::Serial);
    sim::RolloutDerivatives<double> rd(base.setup(), BackendOptions{}, 1);
    const BatchView<const double> q0 = BatchView<const double>::aos(s.q.data(), nq, 1),
                                  qd0 = BatchView<const double>::aos(s.qd.data(), n, 1);
    const StepSequence<const double> tau{BatchView<const double>::aos(s.tau.data(), n, 1), n, 1};
    std::vector<double> dq(n, NAN), dqd(n, NAN), gq0(n, NAN), gqd0(n, NAN), gtau(n, NAN);
    ASSERT_TRUE(rd.jvp(q0, qd0, tau, BatchView<const double>::aos(v.data(), n, 1),
                       BatchView<const double>::aos(v.data() + n, n, 1),
                       {BatchView<const double>::aos(v.data() + 2 * n, n, 1), n, 1},
                       {BatchView<double>::aos(dq.data(), n, 1), n, 1}, {BatchView<double>::aos(dqd.data(), n, 1), n, 1})
                    .ok());
    ASSERT_TRUE(rd.vjp(q0, qd0, tau, {BatchView<const double>::aos(g.data(), n, 1), n, 1},
                       {BatchView<const double>::aos(g.data() + n, n, 1), n, 1},
                       BatchView<double>::aos(gq0.data(), n, 1), BatchView<double>::aos(gqd0.data(), n, 1),
                       {BatchView<double>::aos(gtau.data(), n, 1), n, 1})
                    .ok());
    // J v
    double err = 0, scale = 0;
    for (Index r = 0; r < 2 * n; ++r) {
      double y = 0, mag = 0;
      for (Index k = 0; k < P; ++k) y += J.at(0, r, k) * v[k], mag += std::abs(J.at(0, r, k) * v[k]);
      err = std::max(err, std::abs((r < n ? dq[r] : dqd[r - n]) - y));
      scale = std::max(scale, mag);
    }
    EXPECT_LE(err, tol * scale) << "jvp";
    // J^T g
    err = scale = 0;
    for (Index k = 0; k < P; ++k) {
      double y = 0, mag = 0;
      for (Index r = 0; r < 2 * n; ++r) y += J.at(0, r, k) * g[r], mag += std::abs(J.at(0, r, k) * g[r]);
      err = std::max(err, std::abs((k < n ? gq0[k] : k < 2 * n ? gqd0[k - n] : gtau[k - 2 * n]) - y));
      scale = std::max(scale, mag);
    }
    EXPECT_LE(err, tol * scale) << "vjp";
  }
}

TEST(StepDerivativesMultiDof, OpenmpEqualsSerialBitForBit) {
  for (const Case& c : cases()) {
    SCOPED_TRACE(c.name);
    const Model& m = c.scene.model;
    const Index B = 5;
    std::vector<double> q, qd, tau;
    for (Index b = 0; b < B; ++b) {
      const State s = random_state(m, 100 + static_cast<unsigned>(b), c.tau_scale);
      q.insert(q.end(), s.q.begin(), s.q.end());
      qd.insert(qd.end(), s.qd.begin(), s.qd.end());
      tau.insert(tau.end(), s.tau.begin(), s.tau.end());
    }
    const Jacobians a = step_jacobians(c, q, qd, tau, BackendKind::Serial);
    const Jacobians b = step_jacobians(c, q, qd, tau, BackendKind::OpenMP, 2);
    for (int k = 0; k < 6; ++k) EXPECT_EQ(a.blocks[k], b.blocks[k]) << "block " << k;
    EXPECT_EQ(a.q, b.q);
    EXPECT_EQ(a.qd, b.qd);
  }
}

// float follows double (floating hyq, every block within 1e-3 of its largest double entry)
TEST(StepDerivativesMultiDof, FloatFollowsDouble) {
  for (const Case& c : cases()) {
    if (c.name.find("hyq") == std::string::npos) continue;
    SCOPED_TRACE(c.name);
    const Model& m = c.scene.model;
    const Index n = m.nv(), nq = m.nq();
    const State s = random_state(m, 21, c.tau_scale);
    const Jacobians d = step_jacobians(c, s.q, s.qd, s.tau, BackendKind::Serial);
    Simulator<float> base(batch_of(c.scene, 1), BackendKind::Serial);
    auto engine = sim::make_step_derivatives(base.setup(), BackendOptions{});
    std::vector<float> q(s.q.begin(), s.q.end()), qd(s.qd.begin(), s.qd.end()), tau(s.tau.begin(), s.tau.end());
    std::vector<std::vector<float>> blocks(6, std::vector<float>(n * n, NAN));
    std::vector<float> qn(nq, NAN), qdn(n, NAN);
    auto v = [&](int k) { return BatchView<float>::aos(blocks[k].data(), n * n, 1); };
    const FdBatchIn<float> in{BatchView<const float>::aos(q.data(), nq, 1), BatchView<const float>::aos(qd.data(), n, 1),
                              BatchView<const float>::aos(tau.data(), n, 1), nullptr};
    ASSERT_TRUE(engine->compute(in, {v(0), v(1), v(2), v(3), v(4), v(5), BatchView<float>::aos(qn.data(), nq, 1),
                                     BatchView<float>::aos(qdn.data(), n, 1)})
                    .ok());
    for (int k = 0; k < 6; ++k) {
      double scale = 0, err = 0;
      for (Index e = 0; e < n * n; ++e) scale = std::max(scale, std::abs(d.blocks[k][e]));
      for (Index e = 0; e < n * n; ++e) err = std::max(err, std::abs(double(blocks[k][e]) - d.blocks[k][e]));
      EXPECT_LE(err, 1e-3 * scale) << "block " << k;
    }
    for (Index i = 0; i < nq; ++i) EXPECT_NEAR(qn[i], d.q[i], 1e-4) << "q' " << i;
  }
}

// The joint maps' derivatives at large offsets too (the exact branches, |t| up to 2.5)
TEST(StepDerivativesMultiDof, JointMapJacobiansMatchCentralDifferences) {
  Model m = test::random_floating_model(3, 2, 1.0);  // free root, spherical joints
  std::mt19937_64 rng(4);
  for (double scale : {1e-3, 0.2, 1.4}) {
    for (const Body<double>& b : m.bodies) {
      const int nj = joint_nv(b.type);
      std::vector<double> v = test::random_vector(rng, nj, -scale, scale), t = test::random_vector(rng, nj, -scale, scale);
      sim::JointBlock<double> St, Sv, Dq, Dv;
      sim::joint_tangent_slope_jacobians(b, t.data(), v.data(), St, Sv);
      const double eps = 1e-6;
      for (int k = 0; k < nj; ++k)
        for (int which = 0; which < 2; ++which) {
          std::vector<double> tp = t, tm = t, vp = v, vm = v;
          (which == 0 ? tp : vp)[k] += eps;
          (which == 0 ? tm : vm)[k] -= eps;
          double sp[6], sm[6];
          joint_tangent_slope(b, tp.data(), vp.data(), sp);
          joint_tangent_slope(b, tm.data(), vm.data(), sm);
          for (int r = 0; r < nj; ++r)
            EXPECT_NEAR((which == 0 ? St : Sv).m[r][k], (sp[r] - sm[r]) / (2 * eps), 1e-8)
                << "slope, joint type " << int(b.type) << " scale " << scale;
        }
      // joint_integrate(q, v, h): tangent at q' of perturbations of q and v
      const double h = 0.7;
      sim::joint_integrate_jacobians(b, v.data(), h, Dq, Dv);
      std::vector<double> q = test::random_q(m, rng, -1, 1);
      std::vector<double> full_v(static_cast<std::size_t>(m.nv()), 0.0);
      for (int k = 0; k < nj; ++k) full_v[static_cast<std::size_t>(b.idx_v + k)] = v[static_cast<std::size_t>(k)];
      std::vector<double> qn = q;
      integrate_configuration(m, qn.data(), full_v.data(), h);
      for (int k = 0; k < nj; ++k)
        for (int which = 0; which < 2; ++which) {
          std::vector<double> qp = q, qm = q, vp = full_v, vm = full_v;
          if (which == 0) qp = retract(m, q, b.idx_v + k, eps), qm = retract(m, q, b.idx_v + k, -eps);
          else vp[b.idx_v + k] += eps, vm[b.idx_v + k] -= eps;
          integrate_configuration(m, qp.data(), vp.data(), h);
          integrate_configuration(m, qm.data(), vm.data(), h);
          const std::vector<double> dp = tangent_of(m, qn.data(), qp.data()), dm = tangent_of(m, qn.data(), qm.data());
          for (int r = 0; r < nj; ++r)
            EXPECT_NEAR((which == 0 ? Dq : Dv).m[r][k], (dp[b.idx_v + r] - dm[b.idx_v + r]) / (2 * eps), 1e-8)
                << "integrate, joint type " << int(b.type) << " scale " << scale;
        }
    }
  }
}

// L = sum_t <a_t, log(qbar_t^-1 q_t)> + <c_t, qd_t>, qbar_t the unperturbed trajectory:
// dL/dq_t (tangent at q_t = qbar_t) = a_t, dL/dqd_t = c_t.
TEST(StepDerivativesMultiDof, RolloutAdjointMatchesCentralDifferencesOfARolloutLoss) {
  for (const Case& c : cases()) {
    if (c.name.find("implicit") != std::string::npos && c.name.find("hyq") == std::string::npos) continue;
    SCOPED_TRACE(c.name);
    const Model& m = c.scene.model;
    const Index n = m.nv(), nq = m.nq(), T = 12;
    const State s = random_state(m, 7, c.tau_scale);
    std::mt19937_64 rng(9);
    std::vector<std::vector<double>> taus(T), a(T), cw(T);
    for (Index t = 0; t < T; ++t) {
      taus[t] = test::random_vector(rng, static_cast<int>(n), -c.tau_scale, c.tau_scale);
      a[t] = test::random_vector(rng, static_cast<int>(n), -1, 1);
      cw[t] = test::random_vector(rng, static_cast<int>(n), -1, 1);
    }
    Simulator<double> base(batch_of(c.scene, 1), BackendKind::Serial);
    // the reference trajectory
    std::vector<double> tau_flat, qs(T * nq), qds(T * n);
    for (const auto& u : taus) tau_flat.insert(tau_flat.end(), u.begin(), u.end());
    const StepSequence<const double> tau_seq{BatchView<const double>::aos(tau_flat.data(), n, 1), n, T};
    for (const BackendKind kind : {BackendKind::Serial, BackendKind::OpenMP}) {
      BackendOptions o;
      o.backend = kind;
      o.threads = 2;
      sim::RolloutDerivatives<double> rd(base.setup(), o, 4);
      const BatchView<const double> q0 = BatchView<const double>::aos(s.q.data(), nq, 1),
                                    qd0 = BatchView<const double>::aos(s.qd.data(), n, 1);
      ASSERT_TRUE(rd.rollout(q0, qd0, tau_seq, {BatchView<double>::aos(qs.data(), nq, 1), nq, T},
                             {BatchView<double>::aos(qds.data(), n, 1), n, T})
                      .ok());
      // the rollout: the simulator's states
      std::vector<double> sq = s.q, sqd = s.qd;
      std::vector<std::vector<double>> one_step(1);
      for (Index t = 0; t < T; ++t) {
        one_step[0] = taus[t];
        test::simulate_rows(batch_of(c.scene, 1), sq, sqd, one_step);
        for (Index i = 0; i < nq; ++i) ASSERT_EQ(qs[t * nq + i], sq[i]) << "step " << t;
      }
      std::vector<double> ga, gc, gq0(n), gqd0(n), gtau(T * n);
      for (Index t = 0; t < T; ++t) ga.insert(ga.end(), a[t].begin(), a[t].end()), gc.insert(gc.end(), cw[t].begin(), cw[t].end());
      ASSERT_TRUE(rd.vjp(q0, qd0, tau_seq, {BatchView<const double>::aos(ga.data(), n, 1), n, T},
                         {BatchView<const double>::aos(gc.data(), n, 1), n, T}, BatchView<double>::aos(gq0.data(), n, 1),
                         BatchView<double>::aos(gqd0.data(), n, 1), {BatchView<double>::aos(gtau.data(), n, 1), n, T})
                      .ok());
      // the loss at perturbed inputs (rows of the batch), by the simulator
      auto losses = [&](const std::vector<std::vector<double>>& q0s, const std::vector<std::vector<double>>& qd0s,
                        const std::vector<std::vector<std::vector<double>>>& tau_s) {
        const Index B = static_cast<Index>(q0s.size());
        std::vector<double> q, qd;
        for (Index b = 0; b < B; ++b) q.insert(q.end(), q0s[b].begin(), q0s[b].end()), qd.insert(qd.end(), qd0s[b].begin(), qd0s[b].end());
        std::vector<double> L(B, 0.0);
        for (Index t = 0; t < T; ++t) {
          std::vector<double> u;
          for (Index b = 0; b < B; ++b) u.insert(u.end(), tau_s[b][t].begin(), tau_s[b][t].end());
          test::simulate_rows(batch_of(c.scene, B), q, qd, {u});
          for (Index b = 0; b < B; ++b) {
            const std::vector<double> d = tangent_of(m, qs.data() + t * nq, q.data() + b * nq);
            for (Index i = 0; i < n; ++i) L[b] += a[t][i] * d[i] + cw[t][i] * qd[b * n + i];
          }
        }
        return L;
      };
      // columns: every q0 tangent, every qd0, the torques of steps 0, 5, T-1
      std::vector<std::vector<double>> q0s, qd0s;
      std::vector<std::vector<std::vector<double>>> tau_s;
      std::vector<double> grad, hs;
      const double hq = 1e-6, ht = 2e-3 * c.tau_scale;
      for (Index k = 0; k < n; ++k)
        for (double sg : {1.0, -1.0}) q0s.push_back(retract(m, s.q, k, sg * hq)), qd0s.push_back(s.qd), tau_s.push_back(taus);
      for (Index k = 0; k < n; ++k) grad.push_back(gq0[k]), hs.push_back(hq);
      for (Index k = 0; k < n; ++k)
        for (double sg : {1.0, -1.0}) {
          std::vector<double> v = s.qd;
          v[k] += sg * c.qd_step;
          q0s.push_back(s.q), qd0s.push_back(v), tau_s.push_back(taus);
        }
      for (Index k = 0; k < n; ++k) grad.push_back(gqd0[k]), hs.push_back(c.qd_step);
      for (Index t : {Index(0), Index(5), T - 1})
        for (Index k = 0; k < n; ++k) {
          for (double sg : {1.0, -1.0}) {
            auto u = taus;
            u[t][k] += sg * ht;
            q0s.push_back(s.q), qd0s.push_back(s.qd), tau_s.push_back(u);
          }
          grad.push_back(gtau[t * n + k]), hs.push_back(ht);
        }
      const std::vector<double> L = losses(q0s, qd0s, tau_s);
      double scale = 0, err = 0;
      for (std::size_t k = 0; k < grad.size(); ++k) {
        const double fd = (L[2 * k] - L[2 * k + 1]) / (2 * hs[k]);
        scale = std::max(scale, std::abs(fd));
      }
      for (std::size_t k = 0; k < grad.size(); ++k) {
        const double fd = (L[2 * k] - L[2 * k + 1]) / (2 * hs[k]);
        err = std::max(err, std::abs(grad[k] - fd));
        EXPECT_NEAR(grad[k], fd, 1e-6 * scale) << "entry " << k << " of " << grad.size() << ", " << to_string(kind);
      }
      // the JVP: <vjp(g), v> = <g, jvp(v)>
      const std::vector<double> dq0 = test::random_vector(rng, static_cast<int>(n), -1, 1),
                                dqd0 = test::random_vector(rng, static_cast<int>(n), -1, 1),
                                dtau = test::random_vector(rng, static_cast<int>(T * n), -1, 1);
      std::vector<double> dq(T * n), dqd(T * n);
      ASSERT_TRUE(rd.jvp(q0, qd0, tau_seq, BatchView<const double>::aos(dq0.data(), n, 1),
                         BatchView<const double>::aos(dqd0.data(), n, 1),
                         {BatchView<const double>::aos(dtau.data(), n, 1), n, T},
                         {BatchView<double>::aos(dq.data(), n, 1), n, T}, {BatchView<double>::aos(dqd.data(), n, 1), n, T})
                      .ok());
      double lhs = 0, rhs = 0, mag = 0;
      for (Index i = 0; i < n; ++i) lhs += gq0[i] * dq0[i] + gqd0[i] * dqd0[i];
      for (Index i = 0; i < T * n; ++i) lhs += gtau[i] * dtau[i], rhs += ga[i] * dq[i] + gc[i] * dqd[i];
      for (Index i = 0; i < T * n; ++i) mag += std::abs(ga[i] * dq[i]) + std::abs(gc[i] * dqd[i]);
      EXPECT_NEAR(lhs, rhs, 1e-10 * std::max(mag, 1.0));
    }
  }
}

TEST(StepDerivativesMultiDof, CudaRefusesMultiDofJointsByName) {
  Simulator<double> base(test::scene_from(R"({"model": "hyq.urdf", "base": "floating", "dt": 1e-3})"),
                         BackendKind::Serial);
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  for (int which = 0; which < 2; ++which) {
    try {
      if (which == 0) (void)sim::make_step_derivatives(base.setup(), o);
      else sim::RolloutDerivatives<double> rd(base.setup(), o);
      ADD_FAILURE() << "cuda accepted a floating base";
    } catch (const BackendError& e) {
      const std::string msg = e.what();
      EXPECT_NE(msg.find("root_joint"), std::string::npos) << msg;
      EXPECT_NE(msg.find("floating base"), std::string::npos) << msg;
      EXPECT_NE(msg.find("serial or openmp"), std::string::npos) << msg;
    }
  }
}

}  // namespace
}  // namespace scandyn
