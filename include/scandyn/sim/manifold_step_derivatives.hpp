// scandyn/sim/manifold_step_derivatives.hpp: the step Jacobian of models with
// multi-DoF joints (a floating base, spherical joints), whose positions step on the
// configuration manifold (step_instance_at, scandyn/sim/integrators.hpp).
//
// The state's tangent: q's derivative rows and columns are nv-dimensional, local
// increments q ⊕ d = joint_integrate(q, d, 1) per joint (a free joint's d = [w; v]:
// quat (x) Exp(w), p + R(quat) v; a spherical joint's d = w: quat (x) Exp(w); the
// convention of the first-order dynamics derivatives' q columns,
// rnea_derivatives_general_instance); qd and tau are plain nv vectors. The input
// tangent is at q, the output's at q'.
//
// The map differentiated per joint is joint_integrate, q' = q ⊕ h v (configuration.hpp):
//   1-DoF       dq'/dq = 1, dq'/dv = h
//   spherical   R' = R E, E = Exp(h w):
//                 dq'/dq = E^T, dq'/dw = h Jr(h w)     (Jr: SO(3)'s right Jacobian)
//   free        p' = p + h R v, R' = R E (p moved at the start orientation):
//                 dq'/dq = [E^T 0; -h E^T [v]x  E^T],  dq'/d(w, v) = [h Jr(h w) 0; 0 h E^T]
// (rows and columns [rotation; position], positions in the body frame at q and at
// q'). rk4's stages sit at q ⊕ theta_s with theta_{s+1} = c_{s+1} slope_s and slope_s
// = joint_tangent_slope(theta_s, qd_s) (Munthe-Kaas); its derivatives:
//   spherical   slope = Jr^-1(t) w:
//                 d/dw = Jr^-1(t), d/dt = -1/2 [w]x + 2 c'(|t|^2) (t x (t x w)) t^T
//                                         - c [t x w]x - c [t]x [w]x
//               (c(|t|^2) the coefficient of so3_right_jacobian_inverse)
//   free        slope_v = Exp(t) v: d/dv = Exp(t), d/dt = -Exp(t) [v]x Jr(t)
// The stage position's tangent (at q ⊕ theta_s) is dq'/dq of joint_integrate(q,
// theta_s, 1) applied to dq plus dq'/dv applied to dtheta_s; the forward dynamics'
// derivatives (fd_derivatives_general_instance) take their q columns there.
#pragma once

#include "scandyn/sim/step_derivatives.hpp"

namespace scandyn {
namespace sim {

// A joint's small dense matrix (joint_nv x joint_nv, row-major in m).
template <class S>
struct JointBlock {
  S m[kMaxJointDofs][kMaxJointDofs];
  SCANDYN_HD void zero() {
    for (int r = 0; r < kMaxJointDofs; ++r)
      for (int c = 0; c < kMaxJointDofs; ++c) m[r][c] = S(0);
  }
  SCANDYN_HD void set(int r0, int c0, const Mat3<S>& A) {
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) m[r0 + r][c0 + c] = A(r, c);
  }
};

// sin|t| / |t|, (1 - cos|t|) / |t|^2, (|t| - sin|t|) / |t|^3 (series near zero).
template <class S>
SCANDYN_HD void so3_coefficients(S t2, S& s, S& c, S& d) {
  if (t2 < S(1e-4)) {
    s = S(1) - t2 / S(6) + t2 * t2 / S(120);
    c = S(0.5) - t2 / S(24) + t2 * t2 / S(720);
    d = S(1) / S(6) - t2 / S(120) + t2 * t2 / S(5040);
  } else {
    const S a = ScalarMath<S>::sqrt(t2);
    const S sn = ScalarMath<S>::sin(a);
    s = sn / a;
    c = (S(1) - ScalarMath<S>::cos(a)) / t2;
    d = (a - sn) / (t2 * a);
  }
}

// Exp(t) = 1 + s [t]x + c [t]x^2 (Rodrigues).
template <class S>
SCANDYN_HD Mat3<S> so3_exp_matrix(const Vec3<S>& t) {
  S s, c, d;
  so3_coefficients(dot(t, t), s, c, d);
  const Mat3<S> K = skew(t), K2 = K * K;
  Mat3<S> E = Mat3<S>::identity();
  for (int k = 0; k < 9; ++k) E.m[k] += s * K.m[k] + c * K2.m[k];
  return E;
}

// SO(3)'s right Jacobian, Exp(t + e) = Exp(t) Exp(Jr(t) e + O(e^2)):
// Jr(t) = 1 - c [t]x + d [t]x^2.
template <class S>
SCANDYN_HD Mat3<S> so3_right_jacobian(const Vec3<S>& t) {
  S s, c, d;
  so3_coefficients(dot(t, t), s, c, d);
  const Mat3<S> K = skew(t), K2 = K * K;
  Mat3<S> J = Mat3<S>::identity();
  for (int k = 0; k < 9; ++k) J.m[k] += -c * K.m[k] + d * K2.m[k];
  return J;
}

// d(Jr^-1(t) w)/dt (so3_right_jacobian_inverse's derivative in t), with c(|t|^2) =
// 1/|t|^2 - (1 + cos|t|) / (2 |t| sin|t|) and its derivative c' in |t|^2 (series
// 1/12 + x/720 + x^2/30240 + x^3/1209600 + x^4/47900160 below |t|^2 = 0.1).
template <class S>
SCANDYN_HD Mat3<S> so3_right_jacobian_inverse_dt(const Vec3<S>& t, const Vec3<S>& w) {
  const S t2 = dot(t, t);
  S c, dc;
  if (t2 < S(0.1)) {
    c = S(1) / S(12) + t2 / S(720) + t2 * t2 / S(30240) + t2 * t2 * t2 / S(1209600) +
        t2 * t2 * t2 * t2 / S(47900160);
    dc = S(1) / S(720) + t2 / S(15120) + t2 * t2 / S(403200) + t2 * t2 * t2 / S(11975040);
  } else {
    const S a = ScalarMath<S>::sqrt(t2), sn = ScalarMath<S>::sin(a), cs = ScalarMath<S>::cos(a);
    const S sh = ScalarMath<S>::sin(S(0.5) * a), cot = (S(1) + cs) / sn;  // cot(a / 2)
    c = S(1) / t2 - cot / (S(2) * a);
    const S dc_da = -S(2) / (t2 * a) + S(1) / (S(4) * a * sh * sh) + cot / (S(2) * t2);
    dc = dc_da / (S(2) * a);
  }
  const Vec3<S> txw = cross(t, w), ttxw = cross(t, txw);
  const Mat3<S> Wx = skew(w), Tx = skew(t), TWx = skew(txw), TxWx = Tx * Wx;
  Mat3<S> D;
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k) {
      const S tk = k == 0 ? t.x : (k == 1 ? t.y : t.z);
      const S ur = r == 0 ? ttxw.x : (r == 1 ? ttxw.y : ttxw.z);
      D(r, k) = -S(0.5) * Wx(r, k) + S(2) * dc * ur * tk - c * TWx(r, k) - c * TxWx(r, k);
    }
  return D;
}

// The derivatives of joint_integrate(b, q, v, h) (q' = q ⊕ h v) in the tangents:
// Dq = dq'/dq (local increments at q and at q'), Dv = dq'/dv (joint_nv x joint_nv each;
// header comment). They do not depend on q.
template <class S>
SCANDYN_HD void joint_integrate_jacobians(const Body<S>& b, const S* v, S h, JointBlock<S>& Dq, JointBlock<S>& Dv) {
  Dq.zero();
  Dv.zero();
  if (b.type == JointType::Revolute || b.type == JointType::Prismatic) {
    Dq.m[0][0] = S(1);
    Dv.m[0][0] = h;
    return;
  }
  const Vec3<S> hw{h * v[0], h * v[1], h * v[2]};
  const Mat3<S> Et = transpose(so3_exp_matrix(hw));
  const Mat3<S> Jr = so3_right_jacobian(hw);
  Mat3<S> hJr, hEt;
  for (int k = 0; k < 9; ++k) hJr.m[k] = h * Jr.m[k], hEt.m[k] = h * Et.m[k];
  Dq.set(0, 0, Et);
  Dv.set(0, 0, hJr);
  if (b.type == JointType::Free) {
    Dq.set(3, 3, Et);
    const Mat3<S> C = mul_skew(hEt, Vec3<S>{v[3], v[4], v[5]});  // h E^T [v]x
    Mat3<S> nC;
    for (int k = 0; k < 9; ++k) nC.m[k] = -C.m[k];
    Dq.set(3, 0, nC);
    Dv.set(3, 3, hEt);
  }
}

// The derivatives of joint_tangent_slope(b, theta, v): St = d/dtheta, Sv = d/dv
// (header comment).
template <class S>
SCANDYN_HD void joint_tangent_slope_jacobians(const Body<S>& b, const S* theta, const S* v, JointBlock<S>& St,
                                              JointBlock<S>& Sv) {
  St.zero();
  Sv.zero();
  if (b.type == JointType::Revolute || b.type == JointType::Prismatic) {
    Sv.m[0][0] = S(1);
    return;
  }
  const Vec3<S> t{theta[0], theta[1], theta[2]};
  const Vec3<S> w{v[0], v[1], v[2]};
  St.set(0, 0, so3_right_jacobian_inverse_dt(t, w));
  Mat3<S> Ji;  // Jr^-1(t), column by column
  for (int k = 0; k < 3; ++k) {
    const Vec3<S> e{k == 0 ? S(1) : S(0), k == 1 ? S(1) : S(0), k == 2 ? S(1) : S(0)};
    const Vec3<S> col = so3_right_jacobian_inverse(t, e);
    Ji(0, k) = col.x, Ji(1, k) = col.y, Ji(2, k) = col.z;
  }
  Sv.set(0, 0, Ji);
  if (b.type == JointType::Free) {
    const Mat3<S> E = so3_exp_matrix(t);
    const Mat3<S> D = mul_skew(E, Vec3<S>{v[3], v[4], v[5]}) * so3_right_jacobian(t);  // Exp(t) [v]x Jr(t)
    Mat3<S> nD;
    for (int k = 0; k < 9; ++k) nD.m[k] = -D.m[k];
    St.set(3, 0, nD);
    Sv.set(3, 3, E);
  }
}

// Rows k .. k + nj - 1 of Y (n columns): Y = P [the joint's identity columns, if P]
// + D X (X's same rows). Y may be X. tmp: nj n scalars.
template <class S>
SCANDYN_HD void joint_rows(Index k, int nj, Index n, const JointBlock<S>* P, const JointBlock<S>& D, MatrixRef<S> X,
                           MatrixRef<S> Y, S* tmp) {
  for (int r = 0; r < nj; ++r)
    for (Index j = 0; j < n; ++j) {
      S acc = (P && j >= k && j < k + nj) ? P->m[r][j - k] : S(0);
      for (int c = 0; c < nj; ++c) acc += D.m[r][c] * X(k + c, j);
      tmp[r * n + j] = acc;
    }
  for (int r = 0; r < nj; ++r)
    for (Index j = 0; j < n; ++j) Y(k + r, j) = tmp[r * n + j];
}

// The forces of one stage of a model with multi-DoF joints (effect_forces_at, the
// simulator's) and, when eq is not null, their partials: per DoF; a multi-DoF
// joint's DoFs read q = 0 (effect_forces_at), so their force does not move with q
// (eq = 0).
template <unsigned kEffects, class S>
SCANDYN_HD void stage_forces_at(const Body<S>* bodies, Index nb, const JointCoefficients<S>* coef, const S* tau,
                                const S* q, const S* qd, S h, S* tau_out, S* eq, S* eqd) {
  if constexpr ((kEffects & kJointEffects) != 0) {
    effect_forces_at<kEffects>(bodies, nb, coef, tau, q, qd, h, tau_out);
  } else {
    Index nv = 0;
    for (Index i = 0; i < nb; ++i) nv += joint_nv(bodies[i].type);
    for (Index i = 0; i < nv; ++i) tau_out[i] = tau[i];
  }
  if (!eq) return;
  for (Index i = 0; i < nb; ++i) {
    const Body<S>& b = bodies[i];
    const Index k = b.idx_v;
    if (b.type == JointType::Revolute || b.type == JointType::Prismatic) {
      joint_effect_partials<kEffects>(coef[k], q[b.idx_q], qd[k], h, eq[k], eqd[k]);
      continue;
    }
    for (int j = 0; j < joint_nv(b.type); ++j) {
      joint_effect_partials<kEffects>(coef[k + j], S(0), qd[k + j], h, eq[k + j], eqd[k + j]);
      eq[k + j] = S(0);
    }
  }
}

// Scalars of scratch step_jacobian_at_instance needs for nq positions and nv DoFs.
inline std::size_t step_jacobian_at_scratch(Index nq, Index nv, Integrator integrator) {
  const std::size_t m = static_cast<std::size_t>(nv);
  return 16 * m + static_cast<std::size_t>(nq) + (integrator == Integrator::Rk4 ? 21 : 3) * m * m;
}

// step_jacobian_instance for a model with multi-DoF joints: q (nq) and qd (nv)
// advance in place exactly as step_instance_at advances them (the same functions in
// the same order), and J receives d(q', qd') / d(q, qd, tau) (nv x nv blocks; q's in
// the tangents of the header comment). fd reads q with nq entries; dfd(q, qd, qdd,
// armature, Fq, Fqd, Ft) -> Index writes the forward-dynamics derivatives at qdd
// (fd_derivatives_general_instance). scratch: step_jacobian_at_scratch(nq, nv,
// kIntegrator) scalars. Returns -1, or the failed DoF (q, qd then unchanged).
template <unsigned kEffects, Integrator kIntegrator, class S, class Fd, class Dfd>
SCANDYN_HD Index step_jacobian_at_instance(const Body<S>* bodies, Index nb, Index nq, Index n, S dt,
                                           const JointCoefficients<S>* coef, const S* armature, S* q, S* qd,
                                           const S* tau, S* scratch, const StepJacobian<S>& J, Fd&& fd, Dfd&& dfd) {
  const std::size_t m = static_cast<std::size_t>(n), nn = m * m;
  S *tau_s = scratch, *qdd = scratch + m, *qds = scratch + 2 * m, *aq = scratch + 3 * m, *aqd = scratch + 4 * m,
    *eq = scratch + 5 * m, *eqd = scratch + 6 * m, *theta = scratch + 7 * m, *tmp = scratch + 8 * m,
    *qs = scratch + 14 * m;
  S* const mat = scratch + 16 * m + static_cast<std::size_t>(nq);
  const MatrixRef<S> A[3] = {{mat, n, 1}, {mat + nn, n, 1}, {mat + 2 * nn, n, 1}};
  auto one = [](Index i, Index j) { return i == j ? S(1) : S(0); };
  // the stage's forward dynamics and A (tangent columns at qa) at (qa, qda)
  auto stage = [&](const S* qa, const S* qda, S h, const S* arm) -> Index {
    stage_forces_at<kEffects>(bodies, nb, coef, tau, qa, qda, h, tau_s, eq, eqd);
    Index failed = fd(qa, qda, static_cast<const S*>(tau_s), arm, qdd);
    if (failed >= 0) return failed;
    failed = dfd(qa, qda, static_cast<const S*>(qdd), arm, A[0], A[1], A[2]);
    if (failed >= 0) return failed;
    add_effect_partials<kEffects>(n, A, eq, eqd);
    return -1;
  };
  const MatrixRef<S> Jq[3] = {J.q_q, J.q_qd, J.q_tau}, Jqd[3] = {J.qd_q, J.qd_qd, J.qd_tau};
  JointBlock<S> Dq, Dv;

  if constexpr (kIntegrator == Integrator::Rk4) {
    // per column block b of z = (q, qd, tau): the tangents of theta_s (Dth), qd_s
    // (Dqds), the weighted sums (Daq, Daqd), the stage position's tangent (Dqs; then
    // the slope's) and the stage's dqdd/dz (K)
    S* const dmat = mat + 3 * nn;
    MatrixRef<S> Dth[3], Dqds[3], Daq[3], Daqd[3], Dqs[3], K[3];
    for (int b = 0; b < 3; ++b) {
      Dth[b] = {dmat + b * nn, n, 1};
      Dqds[b] = {dmat + (3 + b) * nn, n, 1};
      Daq[b] = {dmat + (6 + b) * nn, n, 1};
      Daqd[b] = {dmat + (9 + b) * nn, n, 1};
      Dqs[b] = {dmat + (12 + b) * nn, n, 1};
      K[b] = {dmat + (15 + b) * nn, n, 1};
      for (Index i = 0; i < n; ++i)
        for (Index j = 0; j < n; ++j) {
          Dth[b](i, j) = Daq[b](i, j) = Daqd[b](i, j) = S(0);
          Dqds[b](i, j) = b == 1 ? one(i, j) : S(0);
        }
    }
    for (Index i = 0; i < nq; ++i) qs[i] = q[i];
    for (Index i = 0; i < n; ++i) qds[i] = qd[i], theta[i] = S(0), aq[i] = S(0), aqd[i] = S(0);
    for (int s = 0; s < 4; ++s) {
      const Index failed = stage(qs, qds, S(0), static_cast<const S*>(nullptr));
      if (failed >= 0) return failed;
      // the stage position's tangent: Dqs_b = Rq [1 if b = q] + Rv Dth_b (joint_integrate(q, theta_s, 1))
      for (Index i = 0; i < nb; ++i) {
        const Index k = bodies[i].idx_v;
        joint_integrate_jacobians(bodies[i], theta + k, S(1), Dq, Dv);
        for (int b = 0; b < 3; ++b) joint_rows(k, joint_nv(bodies[i].type), n, b == 0 ? &Dq : nullptr, Dv, Dth[b], Dqs[b], tmp);
      }
      // K_b = A_q Dqs_b + A_qd Dqds_b (+ A_tau for b = tau)
      for (int b = 0; b < 3; ++b)
        for (Index i = 0; i < n; ++i) {
          for (Index j = 0; j < n; ++j) K[b](i, j) = b == 2 ? A[2](i, j) : S(0);
          for (Index l = 0; l < n; ++l) {
            const S a0 = A[0](i, l), a1 = A[1](i, l);
            for (Index j = 0; j < n; ++j) K[b](i, j) += a0 * Dqs[b](l, j) + a1 * Dqds[b](l, j);
          }
        }
      // the slope's tangent (into Dqs): St Dth_b + Sv Dqds_b
      for (Index i = 0; i < nb; ++i) {
        const Index k = bodies[i].idx_v;
        const int nj = joint_nv(bodies[i].type);
        joint_tangent_slope_jacobians(bodies[i], theta + k, qds + k, Dq, Dv);
        for (int b = 0; b < 3; ++b) {
          for (int r = 0; r < nj; ++r)
            for (Index j = 0; j < n; ++j) {
              S acc = S(0);
              for (int c = 0; c < nj; ++c) acc += Dq.m[r][c] * Dth[b](k + c, j) + Dv.m[r][c] * Dqds[b](k + c, j);
              tmp[r * n + j] = acc;
            }
          for (int r = 0; r < nj; ++r)
            for (Index j = 0; j < n; ++j) Dqs[b](k + r, j) = tmp[r * n + j];
        }
      }
      const S weight = (s == 0 || s == 3) ? S(1) : S(2);
      const S c = s < 2 ? S(0.5) * dt : dt;  // the next stage's offset
      for (int b = 0; b < 3; ++b)
        for (Index i = 0; i < n; ++i)
          for (Index j = 0; j < n; ++j) {
            Daq[b](i, j) += weight * Dqs[b](i, j);
            Daqd[b](i, j) += weight * K[b](i, j);
            Dth[b](i, j) = c * Dqs[b](i, j);
            Dqds[b](i, j) = (b == 1 ? one(i, j) : S(0)) + c * K[b](i, j);
          }
      // the values, as step_instance_at
      for (Index i = 0; i < nb; ++i) {
        const Index k = bodies[i].idx_v;
        S slope[kMaxJointDofs];
        joint_tangent_slope(bodies[i], theta + k, qds + k, slope);
        for (int j = 0; j < joint_nv(bodies[i].type); ++j) theta[k + j] = slope[j];
      }
      for (Index i = 0; i < n; ++i) {
        aq[i] += weight * theta[i];
        aqd[i] += weight * qdd[i];
        theta[i] *= c;
        qds[i] = qd[i] + c * qdd[i];
      }
      for (Index i = 0; i < nq; ++i) qs[i] = q[i];
      integrate_bodies(bodies, nb, qs, theta, S(1));
    }
    // q' = q ⊕ dt/6 aq, qd' = qd + dt/6 aqd
    const S sixth = dt / S(6);
    for (Index i = 0; i < nb; ++i) {
      const Index k = bodies[i].idx_v;
      joint_integrate_jacobians(bodies[i], aq + k, sixth, Dq, Dv);
      for (int b = 0; b < 3; ++b) joint_rows(k, joint_nv(bodies[i].type), n, b == 0 ? &Dq : nullptr, Dv, Daq[b], Jq[b], tmp);
    }
    for (int b = 0; b < 3; ++b)
      for (Index i = 0; i < n; ++i)
        for (Index j = 0; j < n; ++j) Jqd[b](i, j) = (b == 1 ? one(i, j) : S(0)) + sixth * Daqd[b](i, j);
    integrate_bodies(bodies, nb, q, aq, sixth);
    for (Index i = 0; i < n; ++i) qd[i] += sixth * aqd[i];
    return -1;
  } else {
    constexpr bool kImplicit = kIntegrator == Integrator::Implicit && (kEffects & kImplicitEffects) != 0;
    const Index failed = stage(q, qd, kImplicit ? dt : S(0), kImplicit ? armature : static_cast<const S*>(nullptr));
    if (failed >= 0) return failed;
    // qd' = qd + dt qdd, q' = q ⊕ dt qd'
    for (Index i = 0; i < n; ++i) qd[i] += dt * qdd[i];
    for (int b = 0; b < 3; ++b)
      for (Index i = 0; i < n; ++i)
        for (Index j = 0; j < n; ++j) Jqd[b](i, j) = (b == 1 ? one(i, j) : S(0)) + dt * A[b](i, j);
    for (Index i = 0; i < nb; ++i) {
      const Index k = bodies[i].idx_v;
      joint_integrate_jacobians(bodies[i], qd + k, dt, Dq, Dv);
      for (int b = 0; b < 3; ++b) joint_rows(k, joint_nv(bodies[i].type), n, b == 0 ? &Dq : nullptr, Dv, Jqd[b], Jq[b], tmp);
    }
    integrate_bodies(bodies, nb, q, qd, dt);
    return -1;
  }
}

// ---- directional derivatives of one step (O(nv) each) -----------------------------

// y = M x for a joint's block (nj entries; y may not be x).
template <class S>
SCANDYN_HD void joint_block_mul(const JointBlock<S>& M, int nj, const S* x, S* y) {
  for (int r = 0; r < nj; ++r) {
    S acc = S(0);
    for (int c = 0; c < nj; ++c) acc += M.m[r][c] * x[c];
    y[r] = acc;
  }
}
// y += M^T x for a joint's block (nj entries; y may not be x).
template <class S>
SCANDYN_HD void joint_block_mul_transpose_add(const JointBlock<S>& M, int nj, const S* x, S* y) {
  for (int c = 0; c < nj; ++c) {
    S acc = S(0);
    for (int r = 0; r < nj; ++r) acc += M.m[r][c] * x[r];
    y[c] += acc;
  }
}

// Scalars of scratch step_jvp_at_instance and step_vjp_at_instance use for nq
// positions and nv DoFs.
inline std::size_t step_directional_at_scratch(Index nq, Index nv) {
  return 26 * static_cast<std::size_t>(nv) + 5 * static_cast<std::size_t>(nq);
}

// One step of a model with multi-DoF joints with its tangent: (q, qd) advance as
// step_instance_at advances them, and (dq, dqd) (nv each, in place; dq in the
// tangents of the header comment, at q in and at q' out) become the tangent of the new
// state along (dq, dqd, dtau): the products of step_jacobian_at_instance's Jacobian
// with the direction, each map's tangent taken in turn (the forward dynamics' by
// fd_jvp, the joints' maps by their joint_nv blocks), O(nv). fd_jvp(q, qd, tau, dq,
// dqd, dtau, armature, dqdd, qdd) -> Index writes qdd = FD(q, qd, tau) and its tangent
// (aba_jvp; q of nq entries, dq a tangent). scratch: step_directional_at_scratch(nq,
// nv) scalars. Returns -1 or the failed DoF.
template <unsigned kEffects, Integrator kIntegrator, class S, class FdJvp>
SCANDYN_HD Index step_jvp_at_instance(const Body<S>* bodies, Index nb, Index nq, Index n, S dt,
                                      const JointCoefficients<S>* coef, const S* armature, S* q, S* qd, const S* tau,
                                      S* dq, S* dqd, const S* dtau, S* scratch, FdJvp&& fd_jvp) {
  const std::size_t m = static_cast<std::size_t>(n);
  S *tau_s = scratch, *qdd = scratch + m, *dqdd = scratch + 2 * m, *eq = scratch + 3 * m, *eqd = scratch + 4 * m,
    *dtau_s = scratch + 5 * m, *qds = scratch + 6 * m, *theta = scratch + 7 * m, *aq = scratch + 8 * m,
    *aqd = scratch + 9 * m, *dth = scratch + 10 * m, *dqds = scratch + 11 * m, *P = scratch + 12 * m,
    *daq = scratch + 13 * m, *daqd = scratch + 14 * m, *qs = scratch + 15 * m;
  // the stage's qdd and dqdd at (qa, qda) with the tangent (dqa, dqda)
  auto stage = [&](const S* qa, const S* qda, const S* dqa, const S* dqda, S h, const S* arm) -> Index {
    stage_forces_at<kEffects>(bodies, nb, coef, tau, qa, qda, h, tau_s, eq, eqd);
    for (Index i = 0; i < n; ++i) dtau_s[i] = dtau[i] + eq[i] * dqa[i] + eqd[i] * dqda[i];
    return fd_jvp(qa, qda, static_cast<const S*>(tau_s), dqa, dqda, static_cast<const S*>(dtau_s), arm, dqdd, qdd);
  };
  JointBlock<S> Dq, Dv;
  S x[kMaxJointDofs], y[kMaxJointDofs];
  if constexpr (kIntegrator == Integrator::Rk4) {
    for (Index i = 0; i < nq; ++i) qs[i] = q[i];
    for (Index i = 0; i < n; ++i) {
      qds[i] = qd[i], theta[i] = aq[i] = aqd[i] = S(0);
      dth[i] = daq[i] = daqd[i] = S(0), dqds[i] = dqd[i];
    }
    for (int s = 0; s < 4; ++s) {
      // the stage position q (+) theta_s's tangent: P = Dq(theta_s) dq + Dv(theta_s) dtheta_s
      for (Index i = 0; i < nb; ++i) {
        const Index k = bodies[i].idx_v;
        const int nj = joint_nv(bodies[i].type);
        joint_integrate_jacobians(bodies[i], theta + k, S(1), Dq, Dv);
        joint_block_mul(Dq, nj, dq + k, x);
        joint_block_mul(Dv, nj, dth + k, y);
        for (int j = 0; j < nj; ++j) P[k + j] = x[j] + y[j];
      }
      const Index failed = stage(qs, qds, P, dqds, S(0), static_cast<const S*>(nullptr));
      if (failed >= 0) return failed;
      // the slope and its tangent (into P): St dtheta_s + Sv dqd_s
      for (Index i = 0; i < nb; ++i) {
        const Index k = bodies[i].idx_v;
        const int nj = joint_nv(bodies[i].type);
        joint_tangent_slope_jacobians(bodies[i], theta + k, qds + k, Dq, Dv);
        joint_block_mul(Dq, nj, dth + k, x);
        joint_block_mul(Dv, nj, dqds + k, y);
        S slope[kMaxJointDofs];
        joint_tangent_slope(bodies[i], theta + k, qds + k, slope);
        for (int j = 0; j < nj; ++j) P[k + j] = x[j] + y[j], theta[k + j] = slope[j];
      }
      const S weight = (s == 0 || s == 3) ? S(1) : S(2);
      const S c = s < 2 ? S(0.5) * dt : dt;  // the next stage's offset
      for (Index i = 0; i < n; ++i) {
        aq[i] += weight * theta[i];
        aqd[i] += weight * qdd[i];
        theta[i] *= c;
        qds[i] = qd[i] + c * qdd[i];
        daq[i] += weight * P[i];
        daqd[i] += weight * dqdd[i];
        dth[i] = c * P[i];
        dqds[i] = dqd[i] + c * dqdd[i];
      }
      for (Index i = 0; i < nq; ++i) qs[i] = q[i];
      integrate_bodies(bodies, nb, qs, theta, S(1));
    }
    // q' = q (+) dt/6 aq, qd' = qd + dt/6 aqd
    const S sixth = dt / S(6);
    for (Index i = 0; i < nb; ++i) {
      const Index k = bodies[i].idx_v;
      const int nj = joint_nv(bodies[i].type);
      joint_integrate_jacobians(bodies[i], aq + k, sixth, Dq, Dv);
      joint_block_mul(Dq, nj, dq + k, x);
      joint_block_mul(Dv, nj, daq + k, y);
      for (int j = 0; j < nj; ++j) dq[k + j] = x[j] + y[j];
    }
    for (Index i = 0; i < n; ++i) dqd[i] += sixth * daqd[i];
    integrate_bodies(bodies, nb, q, aq, sixth);
    for (Index i = 0; i < n; ++i) qd[i] += sixth * aqd[i];
  } else {
    constexpr bool kImplicit = kIntegrator == Integrator::Implicit && (kEffects & kImplicitEffects) != 0;
    const Index failed = stage(q, qd, dq, dqd, kImplicit ? dt : S(0), kImplicit ? armature : static_cast<const S*>(nullptr));
    if (failed >= 0) return failed;
    // qd' = qd + dt qdd, q' = q (+) dt qd'
    for (Index i = 0; i < n; ++i) qd[i] += dt * qdd[i], dqd[i] += dt * dqdd[i];
    for (Index i = 0; i < nb; ++i) {
      const Index k = bodies[i].idx_v;
      const int nj = joint_nv(bodies[i].type);
      joint_integrate_jacobians(bodies[i], qd + k, dt, Dq, Dv);
      joint_block_mul(Dq, nj, dq + k, x);
      joint_block_mul(Dv, nj, dqd + k, y);
      for (int j = 0; j < nj; ++j) dq[k + j] = x[j] + y[j];
    }
    integrate_bodies(bodies, nb, q, qd, dt);
  }
  return -1;
}

// The adjoint of one step of a model with multi-DoF joints at (q, qd, tau): gq, gqd
// (nv each, in place; gq in the tangent at q' in, at q out) hold the adjoints of the
// new state and become those of (q, qd); gtau (nv) gets the torques' (written). q and
// qd are not changed. The maps of step_jvp_at_instance transposed, in reverse order
// (rk4: its four stages run forward first, their states kept); fd as
// step_instance_at's; fd_vjp(q, qd, tau, armature, w, gq, gqd, gtau) -> Index the
// adjoint of qdd = FD(q, qd, tau) for the weight w on qdd (aba_vjp). scratch:
// step_directional_at_scratch(nq, nv) scalars. Returns -1 or the failed DoF.
template <unsigned kEffects, Integrator kIntegrator, class S, class Fd, class FdVjp>
SCANDYN_HD Index step_vjp_at_instance(const Body<S>* bodies, Index nb, Index nq, Index n, S dt,
                                      const JointCoefficients<S>* coef, const S* armature, const S* q, const S* qd,
                                      const S* tau, S* gq, S* gqd, S* gtau, S* scratch, Fd&& fd, FdVjp&& fd_vjp) {
  const std::size_t m = static_cast<std::size_t>(n), mq = static_cast<std::size_t>(nq);
  S *tau_s = scratch, *qdd = scratch + m, *eq = scratch + 2 * m, *eqd = scratch + 3 * m, *w = scratch + 4 * m,
    *a = scratch + 5 * m, *b = scratch + 6 * m, *gt = scratch + 7 * m, *v = scratch + 8 * m, *gaq = scratch + 9 * m,
    *gaqd = scratch + 10 * m, *gth = scratch + 11 * m, *gqds = scratch + 12 * m, *gsig = scratch + 13 * m,
    *aq = scratch + 14 * m, *aqd = scratch + 15 * m, *stth = scratch + 16 * m, *stqd = scratch + 20 * m,
    *stq = scratch + 24 * m, *theta = scratch + 24 * m + 4 * mq, *qds = scratch + 25 * m + 4 * mq;
  JointBlock<S> Dq, Dv;
  S x[kMaxJointDofs];
  for (Index i = 0; i < n; ++i) gtau[i] = S(0);
  // the adjoint of one stage's qdd = FD(qa, qda, tau + e(qa, qda)) for the weight w:
  // a (the stage position's tangent), b (the stage velocity's), gtau
  auto stage_adjoint = [&](const S* qa, const S* qda, S h, const S* arm) -> Index {
    stage_forces_at<kEffects>(bodies, nb, coef, tau, qa, qda, h, tau_s, eq, eqd);
    const Index failed = fd_vjp(qa, qda, static_cast<const S*>(tau_s), arm, static_cast<const S*>(w), a, b, gt);
    if (failed >= 0) return failed;
    for (Index i = 0; i < n; ++i) {
      a[i] += eq[i] * gt[i];
      b[i] += eqd[i] * gt[i];
      gtau[i] += gt[i];
    }
    return -1;
  };
  if constexpr (kIntegrator == Integrator::Rk4) {
    // forward: the four stages' theta_s, qd_s and positions q (+) theta_s, as step_instance_at
    for (Index i = 0; i < nq; ++i) stq[i] = q[i];
    for (Index i = 0; i < n; ++i) qds[i] = qd[i], theta[i] = aq[i] = aqd[i] = S(0);
    for (int s = 0; s < 4; ++s) {
      S* const q_s = stq + s * mq;
      for (Index i = 0; i < n; ++i) stth[s * m + i] = theta[i], stqd[s * m + i] = qds[i];
      stage_forces_at<kEffects>(bodies, nb, coef, tau, q_s, qds, S(0), tau_s, static_cast<S*>(nullptr),
                                static_cast<S*>(nullptr));
      const Index failed = fd(static_cast<const S*>(q_s), static_cast<const S*>(qds), static_cast<const S*>(tau_s),
                              static_cast<const S*>(nullptr), qdd);
      if (failed >= 0) return failed;
      for (Index i = 0; i < nb; ++i) {
        const Index k = bodies[i].idx_v;
        S slope[kMaxJointDofs];
        joint_tangent_slope(bodies[i], theta + k, qds + k, slope);
        for (int j = 0; j < joint_nv(bodies[i].type); ++j) theta[k + j] = slope[j];
      }
      const S weight = (s == 0 || s == 3) ? S(1) : S(2);
      const S c = s < 2 ? S(0.5) * dt : dt;
      for (Index i = 0; i < n; ++i) {
        aq[i] += weight * theta[i];
        aqd[i] += weight * qdd[i];
        theta[i] *= c;
        qds[i] = qd[i] + c * qdd[i];
      }
      if (s == 3) break;
      S* const q_next = stq + (s + 1) * mq;
      for (Index i = 0; i < nq; ++i) q_next[i] = q[i];
      integrate_bodies(bodies, nb, q_next, theta, S(1));
    }
    // reverse: q' = q (+) dt/6 aq, qd' = qd + dt/6 aqd
    const S sixth = dt / S(6);
    for (Index i = 0; i < nb; ++i) {
      const Index k = bodies[i].idx_v;
      const int nj = joint_nv(bodies[i].type);
      joint_integrate_jacobians(bodies[i], aq + k, sixth, Dq, Dv);
      for (int j = 0; j < nj; ++j) x[j] = gq[k + j], gq[k + j] = gaq[k + j] = S(0);
      joint_block_mul_transpose_add(Dq, nj, x, gq + k);
      joint_block_mul_transpose_add(Dv, nj, x, gaq + k);
    }
    for (Index i = 0; i < n; ++i) gaqd[i] = sixth * gqd[i], gth[i] = gqds[i] = S(0);
    // the stages 3..0 (gth, gqds: the adjoints of the next stage's dtheta and dqd_s)
    for (int s = 3; s >= 0; --s) {
      const S weight = (s == 0 || s == 3) ? S(1) : S(2);
      const S c = s < 2 ? S(0.5) * dt : dt;
      for (Index i = 0; i < n; ++i) {
        gsig[i] = weight * gaq[i] + c * gth[i];  // the slope's tangent
        w[i] = weight * gaqd[i] + c * gqds[i];   // the stage's dqdd
        gqd[i] += gqds[i];
      }
      const S* const th_s = stth + s * m;
      const S* const qd_s = stqd + s * m;
      // the slope St dtheta_s + Sv dqd_s: gth = St^T gsig, gqds = Sv^T gsig
      for (Index i = 0; i < nb; ++i) {
        const Index k = bodies[i].idx_v;
        const int nj = joint_nv(bodies[i].type);
        joint_tangent_slope_jacobians(bodies[i], th_s + k, qd_s + k, Dq, Dv);
        for (int j = 0; j < nj; ++j) gth[k + j] = gqds[k + j] = S(0);
        joint_block_mul_transpose_add(Dq, nj, gsig + k, gth + k);
        joint_block_mul_transpose_add(Dv, nj, gsig + k, gqds + k);
      }
      const Index failed = stage_adjoint(stq + s * mq, qd_s, S(0), static_cast<const S*>(nullptr));
      if (failed >= 0) return failed;
      for (Index i = 0; i < n; ++i) gqds[i] += b[i];
      // the stage position's tangent Dq(theta_s) dq + Dv(theta_s) dtheta_s
      for (Index i = 0; i < nb; ++i) {
        const Index k = bodies[i].idx_v;
        const int nj = joint_nv(bodies[i].type);
        joint_integrate_jacobians(bodies[i], th_s + k, S(1), Dq, Dv);
        joint_block_mul_transpose_add(Dq, nj, a + k, gq + k);
        joint_block_mul_transpose_add(Dv, nj, a + k, gth + k);
      }
    }
    for (Index i = 0; i < n; ++i) gqd[i] += gqds[i];  // qd_0 = qd
  } else {
    constexpr bool kImplicit = kIntegrator == Integrator::Implicit && (kEffects & kImplicitEffects) != 0;
    const S h = kImplicit ? dt : S(0);
    const S* const arm = kImplicit ? armature : static_cast<const S*>(nullptr);
    // forward: qd' = qd + dt qdd (into v)
    stage_forces_at<kEffects>(bodies, nb, coef, tau, q, qd, h, tau_s, static_cast<S*>(nullptr),
                              static_cast<S*>(nullptr));
    Index failed = fd(q, qd, static_cast<const S*>(tau_s), arm, qdd);
    if (failed >= 0) return failed;
    for (Index i = 0; i < n; ++i) v[i] = qd[i] + dt * qdd[i];
    // reverse: q' = q (+) dt qd': gq = Dq^T gq', gqd' += Dv^T gq'
    for (Index i = 0; i < nb; ++i) {
      const Index k = bodies[i].idx_v;
      const int nj = joint_nv(bodies[i].type);
      joint_integrate_jacobians(bodies[i], v + k, dt, Dq, Dv);
      for (int j = 0; j < nj; ++j) x[j] = gq[k + j], gq[k + j] = S(0);
      joint_block_mul_transpose_add(Dq, nj, x, gq + k);
      joint_block_mul_transpose_add(Dv, nj, x, gqd + k);
    }
    // qd' = qd + dt qdd
    for (Index i = 0; i < n; ++i) w[i] = dt * gqd[i];
    failed = stage_adjoint(q, qd, h, arm);
    if (failed >= 0) return failed;
    for (Index i = 0; i < n; ++i) gq[i] += a[i], gqd[i] += b[i];
  }
  return -1;
}

}  // namespace sim
}  // namespace scandyn
