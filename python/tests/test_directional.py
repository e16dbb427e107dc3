"""scandyn.autograd's directional derivatives of forward dynamics (FdDirectional,
fd_jvp, fd_vjp: the library's make_fd_directional_derivatives), O(nv) per instance.

Truths, each independent of the engine under test:
- the dense derivatives (fd_derivatives: dqdd/dq, dqdd/dqd, M^-1, the serial ABA
  derivatives) contracted with the direction / the weight, on rope:50 and curtain:3:20
  (double: 1e-9 of the result's largest entry; measured <= 6e-12);
- central differences of the library's serial ABA along a random direction on
  rope:2000 (step 1e-5 along a direction of entries in [-1, 1]; 1e-6 of the largest
  entry: the differences' own floor there is ~3e-8, cond(M) growing like nv^4);
- the identity <vjp(w), v> = <w, jvp(v)> (1e-10 of the sum of the terms' magnitudes
  up to rope:200, iiwa, curtain:4:30; on rope:2000, whose cond(M) ~ nv^4 ~ 1e13, 5e-8:
  measured 5e-10 (aba) and 7.5e-9 (parallel));
- serial against openmp: bit for bit for method 'aba' (threads over instances, the same
  arithmetic), 1e-9 for 'parallel' (the scans' chunks follow the threads); a batch
  against its instances one by one likewise (1e-12 for 'parallel': measured 2.4e-13);
- float32 against the double dense truth: 2e-4 of the largest entry on curtain:3:20
  and iiwa (measured <= 1.4e-5); on rope:50 at random configurations the float ABA's own
  error is larger (cond(M) ~ nv^4): dqdd 5e-3 (measured 1.3e-3), gq, gqd, gtau 1e-4
  (measured <= 1.6e-5)."""

import numpy as np
import pytest

import scandyn as sd
import scandyn.autograd as ad
from conftest import degenerate_urdf


def _random(nv, B, seed, count=6, scale=1.0):
    rng = np.random.default_rng(seed)
    return [rng.uniform(-scale, scale, (B, nv)) for _ in range(count)]


def _dense(m, q, qd, tau, dq, dqd, dtau, w):
    """(qdd, J v, w^T J blocks) from the dense derivatives."""
    qdd, A, Bm, C = ad.fd_derivatives(m, q, qd, tau)
    jv = np.einsum("bij,bj->bi", A, dq) + np.einsum("bij,bj->bi", Bm, dqd) + np.einsum("bij,bj->bi", C, dtau)
    return qdd, jv, np.einsum("bij,bi->bj", A, w), np.einsum("bij,bi->bj", Bm, w), np.einsum("bij,bi->bj", C, w)


def _rel(a, b):
    return np.max(np.abs(np.asarray(a, np.float64) - b)) / max(1.0, np.max(np.abs(b)))


@pytest.mark.parametrize("spec", ["rope:50", "curtain:3:20"])
@pytest.mark.parametrize("method", ["aba", "parallel"])
def test_jvp_and_vjp_are_the_dense_derivatives_contracted(spec, method):
    m = sd.load_model(spec)
    q, qd, tau, dq, dqd, dtau = _random(m.nv, 3, 1)
    w = _random(m.nv, 3, 2, 1)[0]
    qdd_ref, jv, wq, wqd, wtau = _dense(m, q, qd, tau, dq, dqd, dtau, w)
    e = ad.FdDirectional(m, max_batch=3, method=method)
    assert e.method == ("parallel" if method == "parallel" else "aba_jvp")
    qdd, dqdd = e.jvp(q, qd, tau, dq, dqd, dtau)
    assert qdd.shape == dqdd.shape == (3, m.nv) and dqdd.dtype == np.float64
    assert _rel(qdd, qdd_ref) <= 1e-9
    assert _rel(dqdd, jv) <= 1e-9
    qdd2, gq, gqd, gtau = e.vjp(q, qd, tau, w)
    assert _rel(qdd2, qdd_ref) <= 1e-9
    assert _rel(gq, wq) <= 1e-9 and _rel(gqd, wqd) <= 1e-9 and _rel(gtau, wtau) <= 1e-9
    # the function API (engine cached per model) gives the same numbers
    np.testing.assert_array_equal(ad.fd_jvp(m, q, qd, tau, dq, dqd, dtau, method=method)[1], dqdd)
    np.testing.assert_array_equal(ad.fd_vjp(m, q, qd, tau, w, method=method)[1], gq)


@pytest.mark.parametrize("method", ["aba", "parallel"])
def test_jvp_is_the_central_differences_of_forward_dynamics_on_rope2000(method):
    m = sd.load_model("rope:2000")
    q, qd, tau, dq, dqd, dtau = _random(m.nv, 2, 3)
    qdd, dqdd = ad.fd_jvp(m, q, qd, tau, dq, dqd, dtau, method=method)
    np.testing.assert_allclose(qdd, sd.forward_dynamics(m, q, qd, tau, method="aba", backend="serial"),
                               rtol=0, atol=1e-9 * np.max(np.abs(qdd)))

    def fd(h):
        return sd.forward_dynamics(m, q + h * dq, qd + h * dqd, tau + h * dtau, method="aba", backend="serial")

    h = 1e-5
    central = (fd(h) - fd(-h)) / (2 * h)
    assert np.max(np.abs(dqdd - central)) <= 1e-6 * np.max(np.abs(central))


@pytest.mark.parametrize("spec,method,tol", [("rope:200", "parallel", 1e-10), ("rope:200", "aba", 1e-10),
                                             ("iiwa", "aba", 1e-10), ("curtain:4:30", "parallel", 1e-10),
                                             ("rope:2000", "parallel", 5e-8), ("rope:2000", "aba", 5e-8)])
def test_adjoint_identity(spec, method, tol):
    m = sd.load_model(spec)
    q, qd, tau, dq, dqd, dtau = _random(m.nv, 2, 4)
    w = _random(m.nv, 2, 5, 1)[0]
    _, dqdd = ad.fd_jvp(m, q, qd, tau, dq, dqd, dtau, method=method)
    _, gq, gqd, gtau = ad.fd_vjp(m, q, qd, tau, w, method=method)
    for b in range(2):  # per instance
        terms = np.concatenate([gq[b] * dq[b], gqd[b] * dqd[b], gtau[b] * dtau[b]])
        assert abs(np.sum(terms) - np.dot(w[b], dqdd[b])) <= tol * np.sum(np.abs(terms))


@pytest.mark.parametrize("method", ["aba", "parallel"])
def test_serial_equals_openmp(method):
    if sd._scandyn.backend_unusable("openmp"):
        pytest.skip("openmp backend unusable here: " + sd._scandyn.backend_unusable("openmp"))
    m = sd.load_model("rope:300")
    q, qd, tau, dq, dqd, dtau = _random(m.nv, 4, 6)
    outs = {}
    for backend in ("serial", "openmp"):
        e = ad.FdDirectional(m, backend=backend, max_batch=4, method=method, threads=2)
        assert e.backend == backend
        outs[backend] = e.jvp(q, qd, tau, dq, dqd, dtau) + e.vjp(q, qd, tau, dq)
    for s, o in zip(outs["serial"], outs["openmp"]):
        if method == "aba":
            np.testing.assert_array_equal(s, o)
        else:
            assert _rel(o, s) <= 1e-9


@pytest.mark.parametrize("method", ["aba", "parallel"])
def test_a_batch_is_its_instances_one_by_one(method):
    m = sd.load_model("rope:40")
    q, qd, tau, dq, dqd, dtau = _random(m.nv, 5, 7)
    e = ad.FdDirectional(m, max_batch=5, method=method)
    batch = e.jvp(q, qd, tau, dq, dqd, dtau) + e.vjp(q, qd, tau, dq)
    for b in range(5):
        one = e.jvp(q[b], qd[b], tau[b], dq[b], dqd[b], dtau[b]) + e.vjp(q[b], qd[b], tau[b], dq[b])
        for x, y in zip(batch, one):
            assert y.shape == (m.nv,)
            if method == "aba":  # per instance, the same arithmetic
                np.testing.assert_array_equal(x[b], y)
            else:  # the scans' chunks follow the batch
                assert _rel(x[b], y) <= 1e-12
    # strided (non-contiguous) inputs read in place
    qT = np.asfortranarray(q)
    np.testing.assert_array_equal(e.jvp(qT, qd, tau, dq, dqd, dtau)[1], batch[1])


@pytest.mark.parametrize("spec,tol_jvp,tol_vjp", [("curtain:3:20", 2e-4, 2e-4), ("iiwa", 2e-4, 2e-4),
                                                  ("rope:50", 5e-3, 1e-4)])
@pytest.mark.parametrize("method", ["aba", "parallel"])
def test_float32_against_the_double_truth(spec, tol_jvp, tol_vjp, method):
    m = sd.load_model(spec)
    q, qd, tau, dq, dqd, dtau = _random(m.nv, 3, 1)
    w = _random(m.nv, 3, 2, 1)[0]
    qdd_ref, jv, wq, wqd, wtau = _dense(m, q, qd, tau, dq, dqd, dtau, w)
    f = [x.astype(np.float32) for x in (q, qd, tau, dq, dqd, dtau, w)]
    qdd, dqdd = ad.fd_jvp(m, *f[:6], method=method)
    assert dqdd.dtype == np.float32
    assert _rel(dqdd, jv) <= tol_jvp
    _, gq, gqd, gtau = ad.fd_vjp(m, *f[:3], f[6], method=method)
    assert gq.dtype == np.float32
    assert max(_rel(gq, wq), _rel(gqd, wqd), _rel(gtau, wtau)) <= tol_vjp


def test_bad_arguments_raise_the_packages_errors_naming_them():
    m = sd.load_model("rope:10")
    q, qd, tau, dq, dqd, dtau = _random(m.nv, 3, 8)
    e = ad.FdDirectional(m, max_batch=3)
    with pytest.raises(sd.ShapeError, match="dq has shape"):
        e.jvp(q, qd, tau, np.zeros((3, m.nv + 1)), dqd, dtau)
    with pytest.raises(sd.ShapeError, match="dtau has shape"):
        e.jvp(q, qd, tau, dq, dqd, dtau[:2])
    with pytest.raises(sd.ShapeError, match="w has shape"):
        e.vjp(q, qd, tau, np.zeros((4, m.nv)))
    with pytest.raises(sd.ShapeError, match="qd has shape"):
        ad.fd_vjp(m, q, qd[0], tau, dq)
    with pytest.raises(sd.DTypeError, match="dqd has dtype float32"):
        e.jvp(q, qd, tau, dq, dqd.astype(np.float32), dtau)
    with pytest.raises(sd.ShapeError, match="max_batch"):
        e.jvp(*_random(m.nv, 4, 9))
    with pytest.raises(sd.ShapeError, match="q has shape"):
        e.vjp(q[None], qd, tau, dq)
    with pytest.raises(sd.BackendError, match="jsi"):
        ad.FdDirectional(m, method="jsi")
    with pytest.raises(sd.BackendError, match="parallel"):  # a branching tree: no chain scans
        ad.FdDirectional(sd.load_model("tree:20:1"), method="parallel")


def test_failed_instances_raise_forward_dynamics_error(tmp_path):
    m = sd.load_model(str(degenerate_urdf(tmp_path)), allow_nonphysical_inertia=True)
    z = np.zeros((2, 1))
    with pytest.raises(sd.ForwardDynamicsError, match="articulated inertia pivot at DoF 0") as err:
        ad.fd_jvp(m, z, z, z, z, z, z)
    assert err.value.status.failed == 2 and list(err.value.status.failed_dof) == [0, 0]
    e = ad.FdDirectional(m, max_batch=2)
    with pytest.raises(sd.ForwardDynamicsError):
        e.vjp(z, z, z, z)
    assert e.last_status.failed == 2


# ---- torch ------------------------------------------------------------------------


def test_torch_tensors_in_and_out():
    torch = pytest.importorskip("torch")
    m = sd.load_model("rope:30")
    arrays = _random(m.nv, 2, 10)
    t = [torch.tensor(a) for a in arrays]
    qdd, dqdd = ad.fd_jvp(m, *t)
    assert isinstance(dqdd, torch.Tensor) and dqdd.dtype == torch.float64
    np.testing.assert_array_equal(dqdd.numpy(), ad.fd_jvp(m, *arrays)[1])
