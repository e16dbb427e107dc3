"""Hybrid dynamics from Python (scandyn.HybridDynamics, scandyn.hybrid_dynamics): the
identities tau = M qdd + h on every row with the given entries copied through, the
limits all-prescribed = inverse dynamics and none-prescribed = forward dynamics, the
command line's results on the same states, and the errors."""

import numpy as np
import pytest

import scandyn as sd
from conftest import DTYPES, degenerate_urdf, states

# relative tolerances of tau = M qdd + h per precision (|tau| ~ 10-100 on these models)
TOL = {np.float64: 1e-10, np.float32: 2e-3}
HYBRID_MODELS = ["iiwa", "hyq", "rope:20", "tree:15:3", "chain:9"]


def random_mask(nv, rng):
    return rng.random(nv) < 0.5


@pytest.mark.parametrize("spec", HYBRID_MODELS)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("backend", ["serial", "openmp"])
def test_hybrid_identities(spec, dtype, backend):
    if backend == "openmp" and sd.backend_unusable("openmp"):
        pytest.skip(sd.backend_unusable("openmp"))
    m = sd.load_model(spec)
    rng = np.random.default_rng(7)
    B = 6
    q, qd, qdd, tau = states(m, B, dtype, seed=3)
    mask = random_mask(m.nv, rng)
    e = sd.HybridDynamics(m, mask, backend=backend, max_batch=B, dtype=dtype)
    assert e.prescribed.tolist() == mask.tolist() and e.exact
    qo, to = e(q, qd, qdd, tau)
    assert qo.dtype == dtype and to.shape == (B, m.nv)
    # the given entries copied through exactly
    np.testing.assert_array_equal(qo[:, mask], qdd[:, mask])
    np.testing.assert_array_equal(to[:, ~mask], tau[:, ~mask])
    # tau = M qdd + h on every row, in double from the double engines
    q64, qd64, qo64 = (x.astype(np.float64) for x in (q, qd, qo))
    M = sd.mass_matrix(m, q64, backend="serial")
    h = sd.bias_forces(m, q64, qd64, backend="serial")
    r = np.einsum("bij,bj->bi", M, qo64) + h - to
    scale = max(1.0, np.abs(to).max())
    assert np.abs(r).max() <= TOL[dtype] * scale * (1 if dtype == np.float64 else 10), np.abs(r).max()


@pytest.mark.parametrize("spec", ["iiwa", "hyq", "rope:20"])
def test_hybrid_limits_are_id_and_fd(spec):
    """All DoFs prescribed is inverse dynamics; none is forward dynamics (the CPU
    engines run the reference's operations: equal to the last bit)."""
    m = sd.load_model(spec)
    q, qd, qdd, tau = states(m, 5, np.float64, seed=11)
    qo, to = sd.hybrid_dynamics(m, q, qd, np.ones(m.nv, bool), qdd, tau, backend="serial")
    np.testing.assert_array_equal(qo, qdd)
    np.testing.assert_allclose(to, sd.inverse_dynamics(m, q, qd, qdd, backend="serial"), rtol=0, atol=1e-12)
    qo, to = sd.hybrid_dynamics(m, q, qd, np.zeros(m.nv, bool), qdd, tau, backend="serial")
    np.testing.assert_array_equal(to, tau)
    np.testing.assert_allclose(qo, sd.forward_dynamics(m, q, qd, tau, method="aba", backend="serial"), rtol=0,
                               atol=1e-10 * max(1, np.abs(qo).max()))


def test_hybrid_matches_cli(cli, tmp_path):
    """The engine's results equal `scandyn eval --algo hybrid --prescribed` on the same
    states (the same engine behind both; the CSV round trip is exact: repr and %.17g)."""
    m = sd.load_model("iiwa")
    q, qd, qdd, tau = states(m, 8, np.float64, seed=5)
    dofs = [1, 4, 6]
    mask = np.zeros(m.nv, bool)
    mask[dofs] = True
    out = _run_hybrid_cli(cli, tmp_path, q, qd, qdd, tau, mask, ",".join(str(i) for i in dofs))
    qo, to = sd.hybrid_dynamics(m, q, qd, dofs, qdd, tau, backend="serial")
    for i in range(m.nv):
        np.testing.assert_allclose(out[f"qdd_hd_{i}"], qo[:, i], rtol=1e-15, atol=1e-15)
        np.testing.assert_allclose(out[f"tau_hd_{i}"], to[:, i], rtol=1e-15, atol=1e-15)
    # joint names select the same DoFs
    names = [m.joint_names[i] for i in dofs]
    qn, tn = sd.hybrid_dynamics(m, q, qd, names, qdd, tau, backend="serial")
    np.testing.assert_array_equal(qn, qo)
    np.testing.assert_array_equal(tn, to)


def _run_hybrid_cli(cli, tmp_path, q, qd, qdd, tau, mask, listing):
    import subprocess

    B, nv = q.shape
    names, cols = [], []
    for i in range(nv):
        names += [f"q_{i}", f"qd_{i}", f"qdd_{i}" if mask[i] else f"tau_{i}"]
        cols += [q[:, i], qd[:, i], qdd[:, i] if mask[i] else tau[:, i]]
    data = np.stack(cols, axis=1)
    states_csv, out_csv = tmp_path / "hybrid_states.csv", tmp_path / "hybrid_out.csv"
    with open(states_csv, "w") as f:
        f.write(",".join(names) + "\n")
        for row in data:
            f.write(",".join(repr(float(x)) for x in row) + "\n")
    subprocess.run([cli, "eval", "--model", "iiwa", "--states", str(states_csv), "--out", str(out_csv), "--algo",
                    "hybrid", "--prescribed", listing, "--backend", "serial"], check=True, capture_output=True,
                   text=True)
    with open(out_csv) as f:
        header = f.readline().strip().split(",")
        rows = np.array([[float(x) for x in line.split(",")] for line in f if line.strip()])
    return {name: rows[:, k] for k, name in enumerate(header)}


def test_hybrid_single_state_and_strided():
    m = sd.load_model("iiwa")
    q, qd, qdd, tau = states(m, 4, np.float64, seed=2)
    mask = np.zeros(m.nv, bool)
    mask[::2] = True
    e = sd.HybridDynamics(m, mask, backend="serial", max_batch=4)
    qo, to = e(q, qd, qdd, tau)
    q1, t1 = e(q[2], qd[2], qdd[2], tau[2])
    assert q1.shape == (m.nv,)
    np.testing.assert_array_equal(q1, qo[2])
    np.testing.assert_array_equal(t1, to[2])
    # Fortran-ordered inputs and outputs written through their strides
    qf, qdf, qddf, tauf = (np.asfortranarray(x) for x in (q, qd, qdd, tau))
    qo2, to2 = np.empty((4, m.nv), order="F"), np.empty((4, m.nv), order="F")
    e(qf, qdf, qddf, tauf, qdd_out=qo2, tau_out=to2)
    np.testing.assert_array_equal(qo2, qo)
    np.testing.assert_array_equal(to2, to)


def test_hybrid_errors():
    m = sd.load_model("iiwa")
    q, qd, qdd, tau = states(m, 2, np.float64)
    with pytest.raises(ValueError, match="not a joint"):
        sd.HybridDynamics(m, ["no_such_joint"])
    with pytest.raises(ValueError, match="outside 0..6"):
        sd.HybridDynamics(m, [7])
    with pytest.raises(ValueError, match="expected nv = 7"):
        sd.HybridDynamics(m, np.ones(3, bool))
    e = sd.HybridDynamics(m, [0], backend="serial", max_batch=2)
    with pytest.raises(sd.ShapeError, match="tau_out shares memory with qdd_out"):
        out = np.empty((2, m.nv))
        e(q, qd, qdd, tau, qdd_out=out, tau_out=out)
    with pytest.raises(sd.ShapeError, match="qdd_out shares memory with q"):
        e(q, qd, qdd, tau, qdd_out=q)
    with pytest.raises(sd.DTypeError):
        e(q.astype(np.float32), qd, qdd, tau)
    with pytest.raises(sd.BackendError, match="spherical|floating|free|multi"):
        b = sd.load_model("ballrope:3")
        sd.HybridDynamics(b, [0])


def test_hybrid_pivot_failure(tmp_path):
    """A DoF whose force is given and whose articulated inertia is zero: the call raises
    ForwardDynamicsError naming it; prescribing that DoF instead succeeds."""
    m = sd.load_model(str(degenerate_urdf(tmp_path)), allow_nonphysical_inertia=True)
    z = np.zeros((1, 1))
    with pytest.raises(sd.ForwardDynamicsError) as info:
        sd.hybrid_dynamics(m, z, z, [], z, z, backend="serial")
    assert info.value.status.failed == 1
    qo, to = sd.hybrid_dynamics(m, z, z, [0], z + 2.0, z, backend="serial")
    assert qo[0, 0] == 2.0 and np.isfinite(to).all()


@pytest.mark.parametrize("dtype", DTYPES)
def test_hybrid_cuda_arrays(dtype):
    """CUDA tensors go to the CUDA engine (one thread per instance) on torch's current
    stream; the results equal the serial engine's within the precision's tolerance."""
    reason = sd.backend_unusable("cuda")
    if reason:
        pytest.skip(f"backend cuda: {reason}")
    torch = pytest.importorskip("torch")
    m = sd.load_model("iiwa")
    q, qd, qdd, tau = states(m, 64, dtype, seed=9)
    mask = np.array([1, 0, 0, 1, 0, 1, 0], bool)
    qo, to = sd.hybrid_dynamics(m, q, qd, mask, qdd, tau, backend="serial")
    dev = [torch.from_numpy(x).cuda() for x in (q, qd, qdd, tau)]
    e = sd.HybridDynamics(m, mask, backend="cuda", max_batch=64, dtype=dtype)
    qg, tg = e(*dev, check=True)
    assert qg.is_cuda and e.last_status.ok
    tol = 1e-9 if dtype == np.float64 else 2e-3
    scale = max(1.0, np.abs(to).max())
    np.testing.assert_allclose(qg.cpu().numpy(), qo, rtol=0, atol=tol * max(1.0, np.abs(qo).max()))
    np.testing.assert_allclose(tg.cpu().numpy(), to, rtol=0, atol=tol * scale)


def test_hybrid_long_chain_scans():
    """On a rope of 5000 links the openmp engine takes the parallel chain scans (prescribed
    joints rigid for the articulated inertia) from 16 threads per instance on, the
    recursion with fewer; the scans' results equal the serial recursion's to 1e-9
    relative."""
    if sd.backend_unusable("openmp"):
        pytest.skip(sd.backend_unusable("openmp"))
    m = sd.load_model("rope:5000")
    rng = np.random.default_rng(4)
    q, qd, qdd, tau = (rng.uniform(-1, 1, (2, m.nv)) for _ in range(4))
    mask = rng.random(m.nv) < 0.4
    assert sd.HybridDynamics(m, mask, backend="openmp", max_batch=2, threads=31).strategy == "recursion"
    e = sd.HybridDynamics(m, mask, backend="openmp", max_batch=2, threads=32)
    assert e.strategy == "parallel" and not e.exact
    qo, to = e(q, qd, qdd, tau)
    qr, tr = sd.HybridDynamics(m, mask, backend="serial", max_batch=2)(q, qd, qdd, tau)
    np.testing.assert_array_equal(qo[:, mask], qdd[:, mask])
    np.testing.assert_array_equal(to[:, ~mask], tau[:, ~mask])
    np.testing.assert_allclose(qo, qr, rtol=0, atol=1e-9 * max(1.0, np.abs(qr).max()))
    np.testing.assert_allclose(to, tr, rtol=0, atol=1e-9 * max(1.0, np.abs(tr).max()))


def test_hybrid_long_chain_cuda_arrays():
    """CUDA tensors reach the CUDA engine of either strategy: on a rope of 300 links
    (beyond one thread's DoFs) the parallel chain hybrid runs on torch's current stream,
    with a long prescribed run; its results equal the serial recursion's (double)."""
    reason = sd.backend_unusable("cuda")
    if reason:
        pytest.skip(f"backend cuda: {reason}")
    torch = pytest.importorskip("torch")
    m = sd.load_model("rope:300")
    rng = np.random.default_rng(5)
    q, qd, qdd, tau = (rng.uniform(-1, 1, (3, m.nv)) for _ in range(4))
    mask = np.zeros(m.nv, bool)
    mask[20:260] = True  # a prescribed run of 240 links
    mask[::7] = True
    e = sd.HybridDynamics(m, mask, backend="cuda", max_batch=3)
    assert e.strategy == "parallel"
    dev = [torch.from_numpy(x).cuda() for x in (q, qd, qdd, tau)]
    qg, tg = e(*dev)
    torch.cuda.synchronize()
    assert qg.is_cuda and tg.is_cuda
    qr, tr = sd.HybridDynamics(m, mask, backend="serial", max_batch=3)(q, qd, qdd, tau)
    np.testing.assert_allclose(qg.cpu().numpy(), qr, rtol=0, atol=1e-9 * max(1.0, np.abs(qr).max()))
    np.testing.assert_allclose(tg.cpu().numpy(), tr, rtol=0, atol=1e-9 * max(1.0, np.abs(tr).max()))
