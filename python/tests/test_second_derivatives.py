"""scandyn.autograd.IdSecondDerivatives / id_second_derivatives: the second-order
derivatives of inverse dynamics (make_id_second_derivatives) from Python.

Truths (float64): central differences, step 1e-6, of the first-order derivatives
(id_derivatives' dtau/dq and dtau/dqd, themselves checked against differences of
inverse dynamics in test_autograd.py) and of the mass matrix (scandyn.mass_matrix):
1e-6 relative to max(1, the reference's largest entry); symmetry in (j, k) of
d2tau_dq2 and d2tau_dqd2 to 1e-12 relative; serial == openmp and a batch == its
instances, bit for bit (the same per-instance recursion); float32 against float64
2e-4 relative. Models: iiwa (7 revolute DoF) and tree:12:2 (a random branching tree
of 12 bodies, 4 of them on prismatic joints). The CUDA tests skip with their reason
where the CUDA build, a GPU or torch is missing."""

import numpy as np
import pytest

import scandyn as sd
import scandyn.autograd as ad
from conftest import uniform_states, assert_close

H = 1e-6  # the central differences' step
REL = 1e-6  # their tolerance, relative to max(1, max |reference|)
MODELS = ["iiwa", "tree:12:2"]


def _central(f, x, h=H):
    """d f / d x_k for f: (B, nv) -> (B, nv, nv): (B, nv, nv, nv), k last, by central differences."""
    B, n = x.shape
    out = np.zeros((B, n, n, n))
    for k in range(n):
        e = np.zeros_like(x)
        e[:, k] = h
        out[..., k] = (f(x + e) - f(x - e)) / (2 * h)
    return out


def test_the_tree_model_has_prismatic_joints_and_branches():
    m = sd.load_model("tree:12:2")
    assert m.joint_types.count("prismatic") == 4
    assert len(m.parents) != len(set(m.parents))  # a parent with two children


@pytest.mark.parametrize("name", MODELS)
def test_second_derivatives_are_central_differences_of_the_first(name):
    m = sd.load_model(name)
    q, qd, qdd = uniform_states(m.nv, 3, 1)
    r = ad.id_second_derivatives(m, q, qd, qdd, backend="serial")
    assert isinstance(r, ad.IdSecondDerivativesResult)
    for t in r:
        assert isinstance(t, np.ndarray) and t.shape == (3, m.nv, m.nv, m.nv) and t.dtype == np.float64

    def dtau_dq(a, b):
        return ad.id_derivatives(m, a, b, qdd, backend="serial")[0]

    def dtau_dqd(a, b):
        return ad.id_derivatives(m, a, b, qdd, backend="serial")[1]

    # entry (i, j, k): d/dx_k of the first-order entry (i, j)
    assert_close(r.d2tau_dq2, _central(lambda v: dtau_dq(v, qd), q), REL)
    assert_close(r.d2tau_dqd2, _central(lambda v: dtau_dqd(q, v), qd), REL)
    # d^2 tau_i / dq_j dqd_k both ways: d/dqd_k (dtau_i/dq_j) and d/dq_j (dtau_i/dqd_k)
    assert_close(r.d2tau_dqdqd, _central(lambda v: dtau_dq(q, v), qd), REL)
    assert_close(r.d2tau_dqdqd, _central(lambda v: dtau_dqd(v, qd), q).transpose(0, 1, 3, 2), REL)
    # dM_dq[i, j, k] = d M_ij / dq_k
    assert_close(r.dM_dq, _central(lambda v: sd.mass_matrix(m, v, backend="serial"), q), REL)
    # not all zero (a test of something)
    for t in r:
        assert np.max(np.abs(t)) > 1e-3


@pytest.mark.parametrize("name", MODELS)
def test_second_derivatives_are_symmetric_in_the_last_two_indices(name):
    m = sd.load_model(name)
    r = ad.id_second_derivatives(m, *uniform_states(m.nv, 4, 2))
    for t in (r.d2tau_dq2, r.d2tau_dqd2):
        assert_close(t, t.transpose(0, 1, 3, 2), 1e-12)
    # M is symmetric, so is its derivative in (i, j)
    assert_close(r.dM_dq, r.dM_dq.transpose(0, 2, 1, 3), 1e-12)


@pytest.mark.parametrize("name", MODELS)
def test_serial_equals_openmp_and_a_batch_equals_its_instances(name):
    m = sd.load_model(name)
    q, qd, qdd = uniform_states(m.nv, 5, 3)
    serial = ad.IdSecondDerivatives(m, backend="serial", max_batch=5)
    openmp = ad.IdSecondDerivatives(m, backend="openmp", max_batch=5, threads=2)
    assert serial.backend == "serial" and openmp.backend == "openmp"
    a, b = serial(q, qd, qdd), openmp(q, qd, qdd)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    for i in range(5):
        one = serial(q[i], qd[i], qdd[i])  # one state: (nv, nv, nv)
        for x, y in zip(a, one):
            assert y.shape == (m.nv,) * 3
            np.testing.assert_array_equal(x[i], y)
    # a batch slice with its own strides (every other instance) reads as given
    for x, y in zip(serial(q[::2], qd[::2], qdd[::2]), a):
        np.testing.assert_array_equal(x, y[::2])


@pytest.mark.parametrize("name", MODELS)
def test_float32_is_float64_within_its_rounding(name):
    m = sd.load_model(name)
    q, qd, qdd = uniform_states(m.nv, 3, 4)
    want = ad.id_second_derivatives(m, q, qd, qdd)
    got = ad.id_second_derivatives(m, *(a.astype(np.float32) for a in (q, qd, qdd)))
    for g, w in zip(got, want):
        assert g.dtype == np.float32
        assert_close(g, w, 2e-4)
    e = ad.IdSecondDerivatives(m, dtype=np.float32)
    assert e.dtype == np.float32 and e.nv == m.nv


def test_bad_shapes_and_arguments_raise_naming_them():
    m = sd.load_model("iiwa")
    n = m.nv
    q, qd, qdd = uniform_states(n, 2)
    e = ad.IdSecondDerivatives(m, max_batch=2)
    with pytest.raises(sd.ShapeError, match="q has shape"):
        e(q[:, :-1], qd[:, :-1], qdd[:, :-1])
    with pytest.raises(sd.ShapeError, match="qd has shape"):
        e(q, qd[:1], qdd)
    with pytest.raises(sd.ShapeError, match="qdd has shape"):
        e(q, qd, np.zeros((2, n + 1)))
    with pytest.raises(sd.ShapeError, match="max_batch"):
        e(*uniform_states(n, 3))
    with pytest.raises(sd.DTypeError):
        e(q, qd.astype(np.float32), qdd)
    # the extension's outputs: shape, layout and aliasing, named
    outs = [np.zeros((2, n, n, n)) for _ in range(4)]
    bad = np.zeros((2, n, n, n + 1))
    with pytest.raises(sd.ShapeError, match="dM_dq has shape"):
        e._e.compute(q, qd, qdd, *outs[:3], bad, 0)
    with pytest.raises(sd.ShapeError, match="d2tau_dqd2: each instance's"):
        e._e.compute(q, qd, qdd, outs[0], np.zeros((2, n, n, n)).transpose(0, 2, 1, 3), *outs[2:], 0)
    with pytest.raises(sd.ShapeError, match="d2tau_dq2 shares memory with d2tau_dqdqd"):
        e._e.compute(q, qd, qdd, outs[0], outs[1], outs[0], outs[3], 0)
    # multi-DoF joints are refused (make_id_second_derivatives: 1-DoF joints only)
    with pytest.raises(sd.BackendError):
        ad.IdSecondDerivatives(sd.load_model("iiwa", floating_base=True))


cuda_reason = sd.backend_unusable("cuda")


@pytest.mark.skipif(bool(cuda_reason), reason=f"backend cuda: {cuda_reason}")
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_cuda_equals_the_host_path(dtype):
    """backend cuda on host arrays, and on torch CUDA tensors (the caller's stream,
    entry-major results): against serial, 1e-9 (double) / 2e-4 (float32) relative."""
    m = sd.load_model("tree:12:2")
    q, qd, qdd = uniform_states(m.nv, 33, 5)
    want = ad.id_second_derivatives(m, q, qd, qdd, backend="serial")
    rel = 1e-9 if dtype == np.float64 else 2e-4
    host = ad.IdSecondDerivatives(m, backend="cuda", max_batch=33, dtype=dtype)(
        *(a.astype(dtype) for a in (q, qd, qdd)))
    for g, w in zip(host, want):
        assert_close(g, w, rel)
    torch = pytest.importorskip("torch", reason="torch is not installed")
    if not torch.cuda.is_available():
        pytest.skip("torch has no CUDA device here")
    got = ad.id_second_derivatives(m, *(torch.from_numpy(a.astype(dtype)).cuda() for a in (q, qd, qdd)))
    for g, w in zip(got, want):
        assert isinstance(g, torch.Tensor) and g.is_cuda and g.shape == (33, m.nv, m.nv, m.nv)
        assert_close(g, w, rel)
