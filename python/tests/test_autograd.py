"""scandyn.autograd: the analytical derivatives from Python, and the
torch.autograd.Function / jax.custom_vjp wrappers whose backward runs them.

Truths: central differences of the library's own inverse dynamics, forward dynamics,
simulator step and rollout (float64, steps 1e-6; 1e-6 relative), torch.autograd.gradcheck
(float64: its default tolerances, against its own finite differences), the identity
<vjp(g), v> = <g, jvp(v)> (1e-10). The JAX tests skip visibly when jax is missing."""

import numpy as np
import pytest

import scandyn as sd
import scandyn.autograd as ad
from conftest import uniform_states

IIWA_SCENE = {"model": "iiwa", "dt": 2e-3, "integrator": "rk4",
              "effects": {"gravity": True, "damping": 0.5, "springs": {"stiffness": 2.0}}}


def _central(f, x, h=1e-6):
    """d f / d x (f: (B, nv) -> (B, nv)), (B, nv, nv) by central differences."""
    B, n = x.shape
    J = np.zeros((B, n, n))
    for j in range(n):
        e = np.zeros_like(x)
        e[:, j] = h
        J[:, :, j] = (f(x + e) - f(x - e)) / (2 * h)
    return J


def _close(a, b, rel=1e-6):
    assert np.max(np.abs(a - b)) <= rel * max(1.0, np.max(np.abs(b))), np.max(np.abs(a - b))


@pytest.mark.parametrize("name", ["iiwa", "hyq"])
def test_id_and_fd_derivatives_are_the_central_differences(name):
    m = sd.load_model(name)
    q, qd, x = uniform_states(m.nv, 3)
    dq, dqd, M = ad.id_derivatives(m, q, qd, x)
    _close(dq, _central(lambda v: sd.inverse_dynamics(m, v, qd, x), q))
    _close(dqd, _central(lambda v: sd.inverse_dynamics(m, q, v, x), qd))
    _close(M, sd.mass_matrix(m, q), 1e-12)
    qdd, fq, fqd, ft = ad.fd_derivatives(m, q, qd, x)
    _close(qdd, sd.forward_dynamics(m, q, qd, x), 1e-12)
    _close(fq, _central(lambda v: sd.forward_dynamics(m, v, qd, x), q))
    _close(fqd, _central(lambda v: sd.forward_dynamics(m, q, v, x), qd))
    _close(ft @ M, np.broadcast_to(np.eye(m.nv), M.shape), 1e-9)
    # one state: (nv, nv)
    assert ad.id_derivatives(m, q[0], qd[0], x[0])[0].shape == (m.nv, m.nv)


def test_step_jacobian_is_the_central_differences_of_the_simulators_step():
    step = ad.StepDerivatives(IIWA_SCENE)
    n = step.nv
    q, qd, tau = uniform_states(n, 2, 3)
    qn, qdn, J = step.jacobian(q, qd, tau)
    # the simulator's own step
    sim = sd.Simulator(dict(IIWA_SCENE, instances=2, backend="serial"))
    sim.q[:] = q
    sim.qd[:] = qd
    sim.step(tau)
    np.testing.assert_array_equal(qn, sim.q)
    np.testing.assert_array_equal(qdn, sim.qd)

    def next_state(z):
        a, b, _ = step.jacobian(z[:, :n], z[:, n:2 * n], z[:, 2 * n:])
        return np.concatenate([a, b], axis=1)

    z = np.concatenate([q, qd, tau], axis=1)
    h = np.concatenate([np.full(2 * n, 1e-6), np.full(n, 1e-2)])
    fd = np.zeros_like(J)
    for j in range(3 * n):
        e = np.zeros_like(z)
        e[:, j] = h[j]
        fd[:, :, j] = (next_state(z + e) - next_state(z - e)) / (2 * h[j])
    for r in range(2):  # each block relative to its own scale (the tau blocks are ~dt^2)
        for c in range(3):
            blk = (slice(None), slice(r * n, (r + 1) * n), slice(c * n, (c + 1) * n))
            assert np.max(np.abs(J[blk] - fd[blk])) <= 1e-6 * np.max(np.abs(fd[blk])), (r, c)


def test_rollout_vjp_is_the_transpose_of_the_jvp_and_the_central_differences():
    step = ad.StepDerivatives(IIWA_SCENE)
    n, T, B = step.nv, 20, 2
    rng = np.random.default_rng(4)
    q0, qd0 = rng.uniform(-0.5, 0.5, (2, B, n))
    tau = rng.uniform(-2, 2, (T, B, n))
    gq, gqd = rng.uniform(-1, 1, (2, T, B, n))
    g0, gd0, gt = step.rollout_vjp(q0, qd0, tau, gq, gqd)
    v0, vd0 = rng.uniform(-1, 1, (2, B, n))
    vt = rng.uniform(-1, 1, (T, B, n))
    dq, dqd = step.rollout_jvp(q0, qd0, tau, v0, vd0, vt)
    lhs = np.sum(g0 * v0) + np.sum(gd0 * vd0) + np.sum(gt * vt)
    rhs = np.sum(gq * dq) + np.sum(gqd * dqd)
    assert abs(lhs - rhs) <= 1e-10 * (np.sum(np.abs(gq * dq)) + np.sum(np.abs(gqd * dqd)))

    def loss(q0_):
        q, qd = step.rollout(q0_, qd0, tau)
        return np.sum(gq * q) + np.sum(gqd * qd)

    h = 1e-6
    for j in range(n):
        e = np.zeros_like(q0)
        e[0, j] = h
        assert abs((loss(q0 + e) - loss(q0 - e)) / (2 * h) - g0[0, j]) <= 1e-6 * max(1.0, np.max(np.abs(g0)))


def test_step_refuses_contacts_by_name():
    scene = {"model": "rope:3", "dt": 1e-3, "effects": {"gravity": True, "contacts": {
        "stiffness": 1000, "points": [{"link": "link_1", "position": [0, 0, 0]}],
        "planes": [{"normal": [0, 0, 1], "offset": -5}]}}}
    with pytest.raises(sd.BackendError, match="contacts"):
        ad.StepDerivatives(scene)


# ---- torch ------------------------------------------------------------------------


@pytest.fixture
def torch():
    return pytest.importorskip("torch")


def test_torch_gradcheck_inverse_and_forward_dynamics(torch):
    m = sd.load_model("iiwa")
    q, qd, x = (torch.tensor(a, requires_grad=True) for a in uniform_states(m.nv, 2, 5))
    assert torch.autograd.gradcheck(lambda a, b, c: ad.torch_inverse_dynamics(m, a, b, c), (q, qd, x))
    assert torch.autograd.gradcheck(lambda a, b, c: ad.torch_forward_dynamics(m, a, b, c), (q, qd, x))
    # one state, and loss.backward() through both
    q1 = q[0].detach().clone().requires_grad_(True)
    tau = ad.torch_inverse_dynamics(m, q1, qd[0].detach(), x[0].detach())
    ad.torch_forward_dynamics(m, q1, qd[0].detach(), tau).sum().backward()
    # FD(ID(qdd)) = qdd for every q: the composite's gradient in q is 0
    assert torch.max(torch.abs(q1.grad)) < 1e-8


def test_torch_gradcheck_step_and_rollout(torch):
    step = ad.StepDerivatives(IIWA_SCENE)
    n = step.nv
    rng = np.random.default_rng(6)
    q, qd = (torch.tensor(rng.uniform(-0.5, 0.5, (2, n)), requires_grad=True) for _ in range(2))
    tau = torch.tensor(rng.uniform(-2, 2, (2, n)), requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b, c: ad.torch_step(step, a, b, c), (q, qd, tau))
    taus = torch.tensor(rng.uniform(-2, 2, (6, 2, n)), requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b, c: ad.torch_rollout(step, a, b, c), (q, qd, taus))
    qs, qds = ad.torch_rollout(step, q, qd, taus)
    (qs.pow(2).sum() + qds.sum()).backward()
    assert taus.grad.shape == taus.shape and torch.all(torch.isfinite(taus.grad))


def test_torch_forward_dynamics_directional_equals_dense(torch):
    """derivatives='directional' (backward fd_vjp, forward mode fd_jvp, O(nv)) against
    'dense' (fd_derivatives' matrices) and gradcheck; forward mode (torch.func.jvp) on
    both against the dense matrices. float64: 1e-10 relative (both are the same
    derivative by different recursions). rope:12 near rest with small torques (its 1 cm
    links under torques of 1 N m reach qdd ~1e6, beyond gradcheck's differences)."""
    for spec, scale in (("iiwa", (1.0, 1.0, 1.0)), ("rope:12", (0.3, 0.3, 1e-3))):
        m = sd.load_model(spec)
        q, qd, x = (torch.tensor(s * a, requires_grad=True) for s, a in zip(scale, uniform_states(m.nv, 3, 11)))
        assert torch.autograd.gradcheck(
            lambda a, b, c: ad.torch_forward_dynamics(m, a, b, c, derivatives="directional"), (q, qd, x))
        w = torch.tensor(np.random.default_rng(12).uniform(-1, 1, (3, m.nv)))
        grads = {}
        for route in ("dense", "directional"):
            g = torch.autograd.grad((ad.torch_forward_dynamics(m, q, qd, x, derivatives=route) * w).sum(), (q, qd, x))
            grads[route] = [t.numpy() for t in g]
        for a, b in zip(grads["directional"], grads["dense"]):
            _close(a, b, 1e-10)
        # forward mode
        _, fq, fqd, ft = ad.fd_derivatives(m, q.detach().numpy(), qd.detach().numpy(), x.detach().numpy())
        v = [torch.tensor(a) for a in uniform_states(m.nv, 3, 13)]
        expect = sum(np.einsum("bij,bj->bi", mat, t.numpy()) for mat, t in zip((fq, fqd, ft), v))
        for route in ("dense", "directional"):
            _, tangent = torch.func.jvp(lambda a, b, c: ad.torch_forward_dynamics(m, a, b, c, derivatives=route),
                                        (q.detach(), qd.detach(), x.detach()), tuple(v))
            _close(tangent.numpy(), expect, 1e-10)
    with pytest.raises(ValueError, match="derivatives="):
        ad.torch_forward_dynamics(m, q, qd, x, derivatives="sparse")


def test_torch_forward_dynamics_backward_on_a_long_rope(torch):
    """rope:3000 (dense derivatives would be 3 x 72 MB per instance): loss.backward()
    through the default route (directional), against central differences of the loss
    along a random direction of (q, qd, tau) (h = 1e-6, float64; 1e-6 relative)."""
    m = sd.load_model("rope:3000")
    rng = np.random.default_rng(14)
    base = [rng.uniform(-0.3, 0.3, (1, m.nv)) for _ in range(3)]
    dirs = [rng.uniform(-1, 1, (1, m.nv)) for _ in range(3)]
    weight = rng.uniform(-1, 1, (1, m.nv))

    def loss(a, b, c):
        return float(np.sum(weight * sd.forward_dynamics(m, a, b, c)))

    ts = [torch.tensor(a, requires_grad=True) for a in base]
    (ad.torch_forward_dynamics(m, *ts) * torch.tensor(weight)).sum().backward()
    predicted = sum(float(np.sum(t.grad.numpy() * d)) for t, d in zip(ts, dirs))
    h = 1e-6
    plus = loss(*(a + h * d for a, d in zip(base, dirs)))
    minus = loss(*(a - h * d for a, d in zip(base, dirs)))
    central = (plus - minus) / (2 * h)
    assert abs(predicted - central) <= 1e-6 * max(1.0, abs(central)), (predicted, central)


# ---- jax --------------------------------------------------------------------------


def test_jax_custom_vjp_matches_the_derivatives():
    jax = pytest.importorskip("jax", reason="jax is not installed: the jax.custom_vjp wrappers are not tested here")
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    m = sd.load_model("iiwa")
    q, qd, x = uniform_states(m.nv, 2, 7)
    g = np.ones((2, m.nv))
    _, vjp = jax.vjp(lambda a, b, c: ad.jax_inverse_dynamics(m, a, b, c), jnp.asarray(q), jnp.asarray(qd), jnp.asarray(x))
    dq, dqd, M = ad.id_derivatives(m, q, qd, x)
    gq, gqd, gx = vjp(jnp.asarray(g))
    _close(np.asarray(gq), np.einsum("bi,bij->bj", g, dq), 1e-12)
    _close(np.asarray(gx), np.einsum("bi,bij->bj", g, M), 1e-12)
    _, vjp = jax.vjp(lambda a, b, c: ad.jax_forward_dynamics(m, a, b, c), jnp.asarray(q), jnp.asarray(qd), jnp.asarray(x))
    _, fq, _, ft = ad.fd_derivatives(m, q, qd, x)
    gq, _, gt = vjp(jnp.asarray(g))
    _close(np.asarray(gq), np.einsum("bi,bij->bj", g, fq), 1e-12)
    _close(np.asarray(gt), np.einsum("bi,bij->bj", g, ft), 1e-12)
    step = ad.StepDerivatives(IIWA_SCENE)
    taus = np.random.default_rng(8).uniform(-1, 1, (5, 2, m.nv))
    grad = jax.grad(lambda a: jnp.sum(ad.jax_rollout(step, a, jnp.asarray(qd), jnp.asarray(taus))[0]))(jnp.asarray(q))
    _close(np.asarray(grad), step.rollout_vjp(q, qd, taus, np.ones_like(taus), np.zeros_like(taus))[0], 1e-12)


def test_jax_forward_dynamics_directional_equals_dense():
    """jax_forward_dynamics with derivatives='directional' (fd_vjp) equals 'dense' (1e-10
    relative, float64) on iiwa and rope:12, and jax.grad through the default route on
    rope:2000 equals central differences along a random direction (h = 1e-6, 1e-6)."""
    jax = pytest.importorskip("jax", reason="jax is not installed: the jax.custom_vjp wrappers are not tested here")
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    for spec in ("iiwa", "rope:12"):
        m = sd.load_model(spec)
        q, qd, x = (jnp.asarray(a) for a in uniform_states(m.nv, 2, 15))
        g = jnp.asarray(np.random.default_rng(16).uniform(-1, 1, (2, m.nv)))
        out = {}
        for route in ("dense", "directional"):
            _, vjp = jax.vjp(lambda a, b, c: ad.jax_forward_dynamics(m, a, b, c, derivatives=route), q, qd, x)
            out[route] = [np.asarray(t) for t in vjp(g)]
        for a, b in zip(out["directional"], out["dense"]):
            _close(a, b, 1e-10)
    m = sd.load_model("rope:2000")
    rng = np.random.default_rng(17)
    q, qd, x, d, w = (rng.uniform(-0.3, 0.3, (1, m.nv)) for _ in range(5))
    grad = jax.grad(lambda a: jnp.sum(jnp.asarray(w) * ad.jax_forward_dynamics(m, a, jnp.asarray(qd), jnp.asarray(x))))(
        jnp.asarray(q))
    h = 1e-6
    central = (np.sum(w * sd.forward_dynamics(m, q + h * d, qd, x)) - np.sum(w * sd.forward_dynamics(m, q - h * d, qd, x))) / (2 * h)
    predicted = float(np.sum(np.asarray(grad) * d))
    assert abs(predicted - central) <= 1e-6 * max(1.0, abs(central)), (predicted, central)
