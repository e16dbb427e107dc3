"""fd_jvp / fd_vjp (FdDirectional, method 'aba') on models with a floating base and ball
joints: q is (B, nq) with unit quaternions, the directions dq and the gradients gq are
tangents (nv) of local increments q (+) d = q exp(d) per joint, the convention of
fd_derivatives' q columns.

Truths:
- the dense derivatives (fd_derivatives) contracted with the direction / the weight, in
  double: 1e-10 of the largest sum of the terms' magnitudes, sum_j |A_ij x_j|; 2e-9 on
  the floating ball rope, whose ill-conditioned M (1e-8 kg m^2 links on a free root)
  makes the ABA's M^-1 and the dense path's L^T L solve of it differ by up to 7.6e-10
  of that measure (tests/algorithm/test_directional_multi_dof.cpp);
- serial against openmp, bit for bit (threads over instances, the same arithmetic);
- float32 against the double results on floating hyq: 1e-4 of each output's largest
  entry (at least 1);
- the method 'parallel' (the chain scans, 1-DoF joints only) raises BackendError
  naming the joint; q with nv columns raises ShapeError naming nq."""

import numpy as np
import pytest

import scandyn as sd
import scandyn.autograd as ad


def random_q(m, B, rng):
    """(B, nq) configurations: each joint's quaternion of unit length."""
    cols, k = [], 0
    for t in m.joint_types:
        n = {"free": 7, "spherical": 4}.get(t, 1)
        x = rng.uniform(-1, 1, (B, n))
        if n > 1:
            x[:, n - 4:] /= np.linalg.norm(x[:, n - 4:], axis=1, keepdims=True)
        cols.append(x)
        k += n
    assert k == m.nq
    return np.concatenate(cols, axis=1)


def state(m, B, seed):
    rng = np.random.default_rng(seed)
    q = random_q(m, B, rng)
    qd, tau, dq, dqd, dtau, w = (rng.uniform(-1, 1, (B, m.nv)) for _ in range(6))
    return q, qd, tau, dq, dqd, dtau, w


def check(got, terms, tol):
    """got against sum of A x over the (A, x, transposed) terms, tol of the largest sum
    of the terms' magnitudes."""
    want = np.zeros_like(got)
    scale = np.zeros_like(got)
    for A, x, t in terms:
        At = np.swapaxes(A, 1, 2) if t else A
        want += np.einsum("bij,bj->bi", At, x)
        scale += np.einsum("bij,bj->bi", np.abs(At), np.abs(x))
    assert np.max(np.abs(got - want)) <= tol * np.max(scale)


MODELS = [("hyq", True), ("atlas", True), ("ballrope:6", False), ("ballrope:6", True)]


@pytest.mark.parametrize("spec,floating", MODELS)
def test_jvp_and_vjp_are_the_dense_derivatives_contracted(spec, floating):
    m = sd.load_model(spec, floating_base=floating, allow_nonphysical_inertia=True)
    assert m.nq > m.nv
    q, qd, tau, dq, dqd, dtau, w = state(m, 3, 4)
    tol = 2e-9 if spec.startswith("ballrope") and floating else 1e-10
    qdd_ref, A, Bm, C = ad.fd_derivatives(m, q, qd, tau, backend="serial")
    qdd, dqdd = ad.fd_jvp(m, q, qd, tau, dq, dqd, dtau, backend="serial")
    assert qdd.shape == dqdd.shape == (3, m.nv)
    np.testing.assert_array_equal(qdd, qdd_ref)  # the same serial ABA
    check(dqdd, [(A, dq, False), (Bm, dqd, False), (C, dtau, False)], tol)
    qdd2, gq, gqd, gtau = ad.fd_vjp(m, q, qd, tau, w, backend="serial")
    np.testing.assert_array_equal(qdd2, qdd_ref)
    check(gq, [(A, w, True)], tol)
    check(gqd, [(Bm, w, True)], tol)
    check(gtau, [(C, w, True)], tol)
    # one state: (nq,) and (nv,)
    qdd1, dqdd1 = ad.fd_jvp(m, q[1], qd[1], tau[1], dq[1], dqd[1], dtau[1], backend="serial")
    assert dqdd1.shape == (m.nv,)
    np.testing.assert_array_equal(dqdd1, dqdd[1])


@pytest.mark.parametrize("spec,floating", MODELS)
def test_serial_equals_openmp(spec, floating):
    m = sd.load_model(spec, floating_base=floating, allow_nonphysical_inertia=True)
    q, qd, tau, dq, dqd, dtau, w = state(m, 5, 7)
    s = ad.FdDirectional(m, backend="serial", max_batch=5, method="aba")
    o = ad.FdDirectional(m, backend="openmp", max_batch=5, method="aba", threads=2)
    assert s.method == o.method == "aba_jvp"
    for a, b in zip(s.jvp(q, qd, tau, dq, dqd, dtau), o.jvp(q, qd, tau, dq, dqd, dtau)):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(s.vjp(q, qd, tau, w), o.vjp(q, qd, tau, w)):
        np.testing.assert_array_equal(a, b)


def test_float32_on_floating_hyq():
    m = sd.load_model("hyq", floating_base=True)
    x = state(m, 4, 9)  # measured at most 4.9e-7 (1e-4 asserted)
    e64 = ad.FdDirectional(m, backend="serial", max_batch=4, method="aba")
    e32 = ad.FdDirectional(m, backend="serial", max_batch=4, method="aba", dtype=np.float32)
    x32 = [a.astype(np.float32) for a in x]
    for a, b in zip(e32.jvp(*x32[:6]) + e32.vjp(*x32[:3], x32[6]), e64.jvp(*x[:6]) + e64.vjp(*x[:3], x[6])):
        assert a.dtype == np.float32
        assert np.max(np.abs(a - b)) <= 1e-4 * max(1.0, np.max(np.abs(b)))


def test_refusals():
    m = sd.load_model("hyq", floating_base=True)
    q, qd, tau, dq, dqd, dtau, w = state(m, 2, 1)
    with pytest.raises(sd.BackendError, match="root_joint"):
        ad.FdDirectional(m, method="parallel")
    with pytest.raises(sd.ShapeError, match="nq"):
        ad.fd_vjp(m, q[:, : m.nv], qd, tau, w)
