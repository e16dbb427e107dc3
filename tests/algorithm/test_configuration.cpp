// The configuration manifold (scandyn/algorithm/configuration.hpp): q ⊕ v h against
// closed-form rotations and finite differences of q, and, integrated with ABA by
// the classical RK4 on (q, qd) (q in its quaternion embedding, renormalised), the
// physics of free systems in zero gravity: spatial momentum (linear and angular)
// and kinetic energy conserved, and a free asymmetric body's rotation against the
// torque-free Euler equations integrated on their own.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "scandyn/algorithm/configuration.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

Model free_model(const std::string& spec) {
  Model m = test::load_floating(spec);
  m.gravity = {0, 0, 0};
  return m;
}

// Random q with unit quaternions, random qd in [-a, a].
void random_state(const Model& m, std::mt19937_64& rng, double a, std::vector<double>& q, std::vector<double>& qd) {
  q = test::random_vector(rng, m.nq(), -1, 1);
  normalize_configuration(m, q.data());
  qd = test::random_vector(rng, m.nv(), -a, a);
}

// One classical RK4 step of (q, qd)' = (dq/dt(q, qd), ABA(q, qd, 0)), q in R^nq.
void rk4_step(const Model& m, Data& data, std::vector<double>& q, std::vector<double>& qd, double dt) {
  const std::size_t nq = q.size(), nv = qd.size();
  const std::vector<double> tau(nv, 0.0);
  std::vector<double> qs = q, qds = qd, kq(nq), kv(nv), sq(nq, 0.0), sv(nv, 0.0);
  for (int s = 0; s < 4; ++s) {
    configuration_derivative(m, qs.data(), qds.data(), kq.data());
    ASSERT_TRUE(aba(m, data, qs.data(), qds.data(), tau.data(), kv.data()).ok());
    const double w = (s == 0 || s == 3) ? 1.0 : 2.0, c = s < 2 ? 0.5 * dt : dt;
    for (std::size_t i = 0; i < nq; ++i) sq[i] += w * kq[i], qs[i] = q[i] + c * kq[i];
    for (std::size_t i = 0; i < nv; ++i) sv[i] += w * kv[i], qds[i] = qd[i] + c * kv[i];
  }
  for (std::size_t i = 0; i < nq; ++i) q[i] += dt / 6 * sq[i];
  for (std::size_t i = 0; i < nv; ++i) qd[i] += dt / 6 * sv[i];
  normalize_configuration(m, q.data());
}

// Total spatial momentum in world coordinates [angular about the world origin;
// linear] and kinetic energy, from the bodies' velocities and world transforms.
struct Conserved {
  Force<double> h;
  double energy;
};
Conserved conserved(const Model& m, Data& data, const std::vector<double>& q, const std::vector<double>& qd) {
  std::vector<double> tau(m.nv());
  const std::vector<double> zero(m.nv(), 0.0);
  rnea(m, data, q.data(), qd.data(), zero.data(), tau.data());  // fills data.Xup, data.v
  std::vector<Transform<double>> X0(m.nbodies());                // world -> body
  Conserved c{Force<double>::zero(), 0};
  for (Index i = 0; i < m.nbodies(); ++i) {
    const Index p = m.parent(i);
    X0[i] = p < 0 ? data.Xup[i] : data.Xup[i] * X0[p];
    const Force<double> hb = m.bodies[i].I * data.v[i];
    c.h += X0[i].apply_transpose(hb);
    c.energy += 0.5 * dot(data.v[i], hb);
  }
  return c;
}

double norm(const Force<double>& f) { return std::sqrt(dot(f.n, f.n) + dot(f.f, f.f)); }

}  // namespace

TEST(Configuration, SphericalIntegrationIsTheRotationExponential) {
  Model m = load_model("ballrope:1");
  std::vector<double> q = {0.1, -0.3, 0.2, 0.9};
  normalize_configuration(m, q.data());
  const Mat3<double> R0 = quat_to_matrix(q.data());
  const Vec3<double> w{0.4, -1.1, 0.7};
  const double t = 0.83, n = std::sqrt(dot(w, w));
  integrate_configuration(m, q.data(), &w.x, t);
  const Mat3<double> R1 = quat_to_matrix(q.data());
  const Mat3<double> expected = R0 * axis_angle((1 / n) * w, std::sin(n * t), std::cos(n * t));
  for (int k = 0; k < 9; ++k) EXPECT_NEAR(R1.m[k], expected.m[k], 1e-14);
  EXPECT_NEAR(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3], 1.0, 1e-15);
}

TEST(Configuration, DerivativeMatchesFiniteDifferences) {
  for (const char* spec : {"rope:5", "ballrope:4", "tree:12:3"}) {
    SCOPED_TRACE(spec);
    const Model m = free_model(spec);
    std::mt19937_64 rng(7);
    std::vector<double> q, qd;
    random_state(m, rng, 1.5, q, qd);
    std::vector<double> qdot(m.nq());
    configuration_derivative(m, q.data(), qd.data(), qdot.data());
    // (q ⊕ v h - q ⊕ v (-h)) / 2h = dq/dt + O(h^2)
    const double h = 1e-5;
    std::vector<double> qp = q, qm = q;
    integrate_configuration(m, qp.data(), qd.data(), h);
    integrate_configuration(m, qm.data(), qd.data(), -h);
    for (Index i = 0; i < m.nq(); ++i) EXPECT_NEAR((qp[i] - qm[i]) / (2 * h), qdot[i], 1e-8) << "q_" << i;
  }
}

// Zero gravity, no torques: the world-frame spatial momentum (hence the linear
// momentum and the angular momentum about the centre of mass) and the kinetic
// energy stay constant: relative drift <= 1e-9 over 10^4 RK4 steps in double.
TEST(FreeSystems, MomentumAndEnergyConservedByRk4) {
  struct Case {
    const char* spec;
    double dt, speed;
  };
  for (const Case& c : {Case{"rope:100", 1e-4, 0.5}, Case{"ballrope:100", 1e-4, 0.5}, Case{"atlas", 1e-4, 0.5}}) {
    SCOPED_TRACE(c.spec);
    const Model m = free_model(c.spec);
    Data data(m);
    std::mt19937_64 rng(11);
    std::vector<double> q, qd;
    random_state(m, rng, c.speed, q, qd);
    const Conserved c0 = conserved(m, data, q, qd);
    double drift_h = 0, drift_e = 0;
    for (int step = 1; step <= 10000; ++step) {
      rk4_step(m, data, q, qd, c.dt);
      if (step % 1000 == 0) {
        const Conserved ct = conserved(m, data, q, qd);
        drift_h = std::max(drift_h, norm(ct.h - c0.h) / norm(c0.h));
        drift_e = std::max(drift_e, std::fabs(ct.energy - c0.energy) / c0.energy);
      }
    }
    EXPECT_LE(drift_h, 1e-9) << "spatial momentum";
    EXPECT_LE(drift_e, 1e-9) << "kinetic energy";
  }
}

// A free body with principal moments 1 < 2 < 3 spinning about (near) its
// intermediate axis: its body-frame angular velocity follows Euler's equations
// I w' = (I w) x w (integrated here on their own, with 10x finer RK4 steps) and
// flips: w_y changes sign.
TEST(FreeSystems, IntermediateAxisFlip) {
  const double I[3] = {1.0, 2.0, 3.0};
  const Model m = test::free_body_model(1.5, {0.1, -0.2, 0.05}, {I[0], I[1], I[2]});
  Data data(m);

  // rotation about the centre of mass c: the origin's body-frame velocity is w x c
  const Vec3<double> com{0.1, -0.2, 0.05};
  Vec3<double> w{1e-3, 1.0, 1e-3};
  std::vector<double> q = {0, 0, 0, 0, 0, 0, 1};
  const Vec3<double> v0 = -cross(com, w);  // velocity of the origin: w x (0 - c)
  std::vector<double> qd = {w.x, w.y, w.z, v0.x, v0.y, v0.z};

  const double dt = 1e-3, T = 20.0;
  double w_euler[3] = {w.x, w.y, w.z};
  auto euler_rhs = [&](const double* x, double* d) {
    d[0] = (I[1] - I[2]) * x[1] * x[2] / I[0];
    d[1] = (I[2] - I[0]) * x[2] * x[0] / I[1];
    d[2] = (I[0] - I[1]) * x[0] * x[1] / I[2];
  };
  bool flipped = false;
  double worst = 0;
  const int steps = static_cast<int>(T / dt + 0.5);
  for (int s = 0; s < steps; ++s) {
    rk4_step(m, data, q, qd, dt);
    for (int k = 0; k < 10; ++k) {  // Euler's equations alone, dt / 10
      const double h = dt / 10;
      double k1[3], k2[3], k3[3], k4[3], x[3];
      euler_rhs(w_euler, k1);
      for (int j = 0; j < 3; ++j) x[j] = w_euler[j] + 0.5 * h * k1[j];
      euler_rhs(x, k2);
      for (int j = 0; j < 3; ++j) x[j] = w_euler[j] + 0.5 * h * k2[j];
      euler_rhs(x, k3);
      for (int j = 0; j < 3; ++j) x[j] = w_euler[j] + h * k3[j];
      euler_rhs(x, k4);
      for (int j = 0; j < 3; ++j) w_euler[j] += h / 6 * (k1[j] + 2 * k2[j] + 2 * k3[j] + k4[j]);
    }
    for (int j = 0; j < 3; ++j) worst = std::max(worst, std::fabs(qd[j] - w_euler[j]));
    if (qd[1] < -0.5) flipped = true;
  }
  EXPECT_TRUE(flipped) << "w_y never reversed in " << T << " s";
  EXPECT_LT(worst, 1e-8) << "body angular velocity against Euler's equations";
}
