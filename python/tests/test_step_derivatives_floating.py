"""The step and rollout derivatives on models with multi-DoF joints (a floating base,
spherical joints) from Python: scandyn.autograd.StepDerivatives, torch_step,
torch_rollout, jax_rollout. Truths: central differences of the rollouts
(StepDerivatives.rollout, the simulator's step) along the retraction q ⊕ h e_j (q's
tangent) and along qd0 and tau; the tangent/ambient maps' identity E^T P^T = 1;
serial == openmp. Steps 1e-6 (q), 1e-6 (qd; 1e-3 on the ball rope) and 1e-3 x the
torques' scale (tau); tolerance 1e-6 relative to the largest entry compared. The torch and jax tests skip without torch / jax."""

import numpy as np
import pytest

import scandyn.autograd as ad

SCENES = {
    "floating hyq euler": {"model": "hyq.urdf", "base": "floating", "dt": 2e-3, "integrator": "euler",
                           "effects": {"gravity": True, "damping": 0.5}},
    "floating hyq rk4": {"model": "hyq.urdf", "base": "floating", "dt": 2e-3, "integrator": "rk4",
                         "effects": {"gravity": True, "damping": 0.5}},
    "floating ballrope:3 rk4": {"model": "ballrope:3", "base": "floating", "dt": 1e-4, "integrator": "rk4",
                                "effects": {"gravity": True}},
}
# torques' scale and the qd step of the differences per scene: the ball rope's links of
# 1e-8 kg m^2 take torques of 1e-4 N m, and at dt = 1e-4 a qd step of 1e-6 moves q' by
# 1e-10, at rounding level (the C++ tests' steps)
TAU_SCALE = {"floating ballrope:3 rk4": 1e-4}
QD_STEP = {"floating ballrope:3 rk4": 1e-3}


def quat_mul(a, b):
    """Hamilton product of (x, y, z, w) quaternions."""
    av, aw, bv, bw = a[:3], a[3], b[:3], b[3]
    return np.concatenate([aw * bv + bw * av + np.cross(av, bv), [aw * bw - av @ bv]])


def quat_matrix(p):
    return ad._quat_matrix(p[None, :3], p[None, 3:])[0]


def retract(step, q, j, h):
    """q ⊕ h e_j (one state, (nq,)): the simulator's joint_integrate with v = e_j."""
    q = np.array(q, dtype=float)
    for kind, iq, iv in step._s.joints:
        nj = {"free": 6, "spherical": 3}.get(kind, 1)
        if not iv <= j < iv + nj:
            continue
        k = j - iv
        if nj == 1:
            q[iq] += h
            return q
        at = iq + 3 if kind == "free" else iq
        if k >= 3:  # a free joint's translation, in the base frame
            q[iq:iq + 3] += h * quat_matrix(q[at:at + 4])[:, k - 3]
            return q
        e = np.zeros(4)
        e[k], e[3] = np.sin(h / 2), np.cos(h / 2)
        r = quat_mul(q[at:at + 4], e)
        q[at:at + 4] = r / np.linalg.norm(r)
        return q
    raise AssertionError(f"no joint has DoF {j}")


def state(step, seed, B=None):
    rng = np.random.default_rng(seed)
    shape = () if B is None else (B,)
    q = np.zeros(shape + (step.nq,))
    for kind, iq, iv in step._s.joints:
        if kind in ("revolute", "prismatic"):
            q[..., iq] = rng.uniform(-0.5, 0.5, shape)
            continue
        at = iq + 3 if kind == "free" else iq
        if kind == "free":
            q[..., iq:iq + 3] = rng.uniform(-1, 1, shape + (3,))
        quat = rng.normal(size=shape + (4,))
        q[..., at:at + 4] = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
    return q, rng.uniform(-1, 1, shape + (step.nv,))


@pytest.mark.parametrize("name", sorted(SCENES))
def test_step_jacobian_against_differences_along_the_retraction(name):
    step = ad.StepDerivatives(SCENES[name], backend="serial")
    n = step.nv
    assert step.nq > n
    q, qd = state(step, 1)
    tau = np.random.default_rng(2).uniform(-1, 1, n) * TAU_SCALE.get(name, 1)
    qn, qdn, J = step.jacobian(q, qd, tau)
    h = 1e-6
    for j in range(n):  # the q columns: q ⊕ (±h e_j); the outputs' tangents at q' by the inverse retraction,
        # to first order ambient_gradient's transpose: d = P(q') (q'_+ - q'_-)
        outs = [step.rollout(retract(step, q, j, s * h), qd, tau[None]) for s in (1, -1)]
        dq = (outs[0][0][0] - outs[1][0][0]) / (2 * h)
        # P(q') dq: columns of P^T are ambient_gradient of the unit tangent vectors
        P = np.stack([step.ambient_gradient(qn, np.eye(n)[r]) for r in range(n)])
        col = np.concatenate([P @ dq, (outs[0][1][0] - outs[1][1][0]) / (2 * h)])
        np.testing.assert_allclose(J[:, j], col, rtol=0, atol=1e-6 * max(np.abs(J[:, :n]).max(), 1e-300))
    h = QD_STEP.get(name, 1e-6)
    for j in range(n):  # the qd columns
        e = np.eye(n)[j] * h
        outs = [step.rollout(q, qd + s * e, tau[None]) for s in (1, -1)]
        P = np.stack([step.ambient_gradient(qn, np.eye(n)[r]) for r in range(n)])
        col = np.concatenate([P @ (outs[0][0][0] - outs[1][0][0]) / (2 * h), (outs[0][1][0] - outs[1][1][0]) / (2 * h)])
        np.testing.assert_allclose(J[:, n + j], col, rtol=0, atol=1e-6 * np.abs(J[:, n:2 * n]).max())


def test_tangent_and_ambient_maps_are_inverse_and_serial_equals_openmp():
    step = ad.StepDerivatives(SCENES["floating hyq rk4"], backend="serial")
    q, qd = state(step, 3, B=4)
    g = np.random.default_rng(4).normal(size=(4, step.nv))
    np.testing.assert_allclose(step.tangent_gradient(q, step.ambient_gradient(q, g)), g, rtol=0, atol=1e-14)
    tau = np.random.default_rng(5).uniform(-1, 1, (4, step.nv))
    a = step.jacobian(q, qd, tau)
    b = ad.StepDerivatives(SCENES["floating hyq rk4"], backend="openmp").jacobian(q, qd, tau)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def loss_and_grads_by_differences(step, q0, qd0, tau, a, c, tau_scale=1.0, qd_step=1e-6):
    """L = sum(a * q_t) + sum(c * qd_t) over a rollout, and its central differences along
    q0's tangent, qd0 and tau."""
    def L(q, qd, u):
        qs, qds = step.rollout(q, qd, u)
        return float(np.sum(a * qs) + np.sum(c * qds))
    h, ht, hd = 1e-6, 1e-3 * tau_scale, qd_step
    n = step.nv
    gq = np.array([(L(retract(step, q0, j, h), qd0, tau) - L(retract(step, q0, j, -h), qd0, tau)) / (2 * h)
                   for j in range(n)])
    gqd = np.array([(L(q0, qd0 + hd * np.eye(n)[j], tau) - L(q0, qd0 - hd * np.eye(n)[j], tau)) / (2 * hd)
                    for j in range(n)])
    gtau = np.zeros_like(tau)
    for t in range(tau.shape[0]):
        for j in range(n):
            e = np.zeros_like(tau)
            e[t, j] = ht
            gtau[t, j] = (L(q0, qd0, tau + e) - L(q0, qd0, tau - e)) / (2 * ht)
    return gq, gqd, gtau


def tangent_directions(step, q0):
    """E(q0) e_j (nq,) per tangent direction j: the retraction's derivative, by differences."""
    return np.stack([(retract(step, q0, j, 1e-7) - retract(step, q0, j, -1e-7)) / 2e-7 for j in range(step.nv)])


@pytest.mark.parametrize("name", ["floating hyq euler", "floating ballrope:3 rk4"])
def test_torch_rollout_and_step_gradients_on_a_floating_model(name):
    torch = pytest.importorskip("torch")
    step = ad.StepDerivatives(SCENES[name], backend="serial")
    n, T = step.nv, 4
    q0, qd0 = state(step, 6)
    rng = np.random.default_rng(7)
    tau = rng.uniform(-1, 1, (T, n)) * TAU_SCALE.get(name, 1)
    a, c = rng.normal(size=(T, step.nq)), rng.normal(size=(T, n))
    tq0, tqd0, ttau = (torch.tensor(x, requires_grad=True) for x in (q0, qd0, tau))
    qs, qds = ad.torch_rollout(step, tq0, tqd0, ttau)
    assert tuple(qs.shape) == (T, step.nq) and tuple(qds.shape) == (T, n)
    (torch.sum(torch.tensor(a) * qs) + torch.sum(torch.tensor(c) * qds)).backward()
    gq, gqd, gtau = loss_and_grads_by_differences(step, q0, qd0, tau, a, c, TAU_SCALE.get(name, 1),
                                                  QD_STEP.get(name, 1e-6))
    # q0's gradient (nq coordinates) along the retraction's directions = the tangent gradient
    along = tangent_directions(step, q0) @ tq0.grad.numpy()
    scale = max(np.abs(gq).max(), np.abs(gqd).max())
    np.testing.assert_allclose(along, gq, rtol=0, atol=1e-6 * scale)
    np.testing.assert_allclose(tqd0.grad.numpy(), gqd, rtol=0, atol=1e-6 * scale)
    np.testing.assert_allclose(ttau.grad.numpy(), gtau, rtol=0, atol=1e-6 * np.abs(gtau).max())
    # torch_step: one step's gradients equal the rollout's with T = 1
    s0, sd0, st0 = (torch.tensor(x, requires_grad=True) for x in (q0, qd0, tau[0]))
    q1, qd1 = ad.torch_step(step, s0, sd0, st0)
    (torch.sum(torch.tensor(a[0]) * q1) + torch.sum(torch.tensor(c[0]) * qd1)).backward()
    r0, rd0, rt0 = (torch.tensor(x, requires_grad=True) for x in (q0, qd0, tau[:1]))
    qs1, qds1 = ad.torch_rollout(step, r0, rd0, rt0)
    (torch.sum(torch.tensor(a[:1]) * qs1) + torch.sum(torch.tensor(c[:1]) * qds1)).backward()
    for x, y in ((s0, r0), (sd0, rd0)):
        np.testing.assert_allclose(x.grad.numpy(), y.grad.numpy(), rtol=0, atol=1e-10 * np.abs(y.grad.numpy()).max())
    np.testing.assert_allclose(st0.grad.numpy(), rt0.grad.numpy()[0], rtol=0, atol=1e-10 * np.abs(rt0.grad.numpy()).max())


def test_jax_rollout_gradients_on_a_floating_model():
    jax = pytest.importorskip("jax")
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    step = ad.StepDerivatives(SCENES["floating hyq rk4"], backend="serial")
    n, T = step.nv, 3
    q0, qd0 = state(step, 8)
    rng = np.random.default_rng(9)
    tau = rng.uniform(-1, 1, (T, n))
    a, c = rng.normal(size=(T, step.nq)), rng.normal(size=(T, n))

    def loss(q, qd, u):
        qs, qds = ad.jax_rollout(step, q, qd, u)
        return jnp.sum(a * qs) + jnp.sum(c * qds)

    g = jax.grad(loss, argnums=(0, 1, 2))(jnp.asarray(q0), jnp.asarray(qd0), jnp.asarray(tau))
    gq, gqd, gtau = loss_and_grads_by_differences(step, q0, qd0, tau, a, c)
    scale = max(np.abs(gq).max(), np.abs(gqd).max())
    np.testing.assert_allclose(tangent_directions(step, q0) @ np.asarray(g[0]), gq, rtol=0, atol=1e-6 * scale)
    np.testing.assert_allclose(np.asarray(g[1]), gqd, rtol=0, atol=1e-6 * scale)
    np.testing.assert_allclose(np.asarray(g[2]), gtau, rtol=0, atol=1e-6 * np.abs(gtau).max())
