// src/sim/prescribed.cpp: the trajectories of prescribed joint motion
// (scandyn/sim/prescribed.hpp).
#include "scandyn/sim/prescribed.hpp"

#include <cmath>
#include <stdexcept>

namespace scandyn {
namespace sim {

namespace {
constexpr double kTwoPi = 6.283185307179586476925286766559;
}

void JointTrajectory::eval(double time, double& q_out, double& qd_out, double& qdd_out) const {
  if (kind == Kind::Sine) {
    const double w = kTwoPi * frequency, a = w * time + phase;
    const double s = std::sin(a), c = std::cos(a);
    q_out = offset + amplitude * s;
    qd_out = amplitude * w * c;
    qdd_out = -amplitude * w * w * s;
    return;
  }
  const std::size_t n = t.size() - 1;  // intervals
  if (time <= t[0] || time >= t[n]) {  // held at the end positions
    q_out = time <= t[0] ? q[0] : q[n];
    qd_out = qdd_out = 0;
    return;
  }
  std::size_t k = 0, hi = n;  // the interval [t[k], t[k + 1]) holding time: bisection
  while (hi - k > 1) {
    const std::size_t mid = (k + hi) / 2;
    (time < t[mid] ? hi : k) = mid;
  }
  const double h = t[k + 1] - t[k], a = t[k + 1] - time, b = time - t[k];
  const double ck = q[k] / h - m[k] * h / 6, ck1 = q[k + 1] / h - m[k + 1] * h / 6;
  q_out = (m[k] * a * a * a + m[k + 1] * b * b * b) / (6 * h) + ck * a + ck1 * b;
  qd_out = (-m[k] * a * a + m[k + 1] * b * b) / (2 * h) - ck + ck1;
  qdd_out = (m[k] * a + m[k + 1] * b) / h;
}

JointTrajectory sine_trajectory(double amplitude, double frequency, double phase, double offset) {
  JointTrajectory j;
  j.kind = JointTrajectory::Kind::Sine;
  j.amplitude = amplitude, j.frequency = frequency, j.phase = phase, j.offset = offset;
  return j;
}

JointTrajectory table_trajectory(std::vector<double> t, std::vector<double> q) {
  if (t.size() != q.size()) throw std::invalid_argument("the knots' times and positions differ in number");
  if (t.size() < 2) throw std::invalid_argument("a table needs at least 2 knots");
  for (std::size_t k = 0; k < t.size(); ++k) {
    if (!std::isfinite(t[k]) || !std::isfinite(q[k])) throw std::invalid_argument("knot " + std::to_string(k) + " is not finite");
    if (k > 0 && !(t[k] > t[k - 1]))
      throw std::invalid_argument("knot " + std::to_string(k) + ": times must increase strictly");
  }
  // the clamped spline's second derivatives m: a tridiagonal system (zero slope at both
  // ends), solved by the Thomas algorithm
  const std::size_t N = t.size(), n = N - 1;
  std::vector<double> lo(N), di(N), up(N), r(N);
  auto h = [&](std::size_t k) { return t[k + 1] - t[k]; };
  auto slope = [&](std::size_t k) { return (q[k + 1] - q[k]) / h(k); };
  di[0] = 2 * h(0), up[0] = h(0), r[0] = 6 * slope(0);
  for (std::size_t k = 1; k < n; ++k) {
    lo[k] = h(k - 1), di[k] = 2 * (h(k - 1) + h(k)), up[k] = h(k);
    r[k] = 6 * (slope(k) - slope(k - 1));
  }
  lo[n] = h(n - 1), di[n] = 2 * h(n - 1), r[n] = -6 * slope(n - 1);
  for (std::size_t k = 1; k < N; ++k) {
    const double f = lo[k] / di[k - 1];
    di[k] -= f * up[k - 1];
    r[k] -= f * r[k - 1];
  }
  std::vector<double> m(N);
  m[n] = r[n] / di[n];
  for (std::size_t k = n; k-- > 0;) m[k] = (r[k] - up[k] * m[k + 1]) / di[k];
  JointTrajectory j;
  j.kind = JointTrajectory::Kind::Table;
  j.t = std::move(t), j.q = std::move(q), j.m = std::move(m);
  return j;
}

std::vector<unsigned char> PrescribedMotion::mask(Index nv) const {
  std::vector<unsigned char> out(static_cast<std::size_t>(nv), 0);
  for (Index d : dofs) out[static_cast<std::size_t>(d)] = 1;
  return out;
}

}  // namespace sim
}  // namespace scandyn
