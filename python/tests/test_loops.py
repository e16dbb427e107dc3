"""Closed kinematic loops from Python (scandyn.Loops, ConstrainedForwardDynamics,
constrained_forward_dynamics, loop_residual): loop sets from generators, files, text
and dicts; the constrained forward dynamics against `scandyn eval` on the same closed
states (the Eigen reference there) and against Pinocchio's constraintDynamics, the equations M qdd + h = tau + J^T lambda and
J qdd + Jdot qd = 0 (J and Jdot qd from the residual: its velocity at unit rates and
its central difference along qd), float32 within float tolerance, CUDA arrays against
the host engine, and the errors.

Closed states: random q near 0 moved onto the loops by Gauss-Newton on the residual
(test code), qd projected onto J's null space. Tolerances: double, relative to
max(1, max |x|)."""

import subprocess

import numpy as np
import pytest

import scandyn as sd

LOOPY = ["fourbar", "fivebar", "cloth:3:4"]


def jacobian(engine, q):
    """J (B, m, nv) at q (B, nv): the residual's velocity at unit joint rates."""
    B, nv = q.shape
    qs = np.repeat(q, nv, axis=0)
    qd = np.tile(np.eye(nv), (B, 1))
    _, v = engine.residual(qs, qd, phi=False)
    return v.reshape(B, nv, -1).transpose(0, 2, 1)


def closed_states(model, loops, B, seed):
    rng = np.random.default_rng(seed)
    e = sd.ConstrainedForwardDynamics(model, loops, backend="serial", max_batch=B * model.nv)
    q = rng.uniform(-0.2, 0.2, (B, model.nv))
    for _ in range(60):
        phi, _ = e.residual(q, np.zeros_like(q), velocity=False)
        if np.abs(phi).max() < 1e-13:
            break
        J = jacobian(e, q)
        q = q - np.stack([np.linalg.lstsq(J[b], phi[b], rcond=1e-12)[0] for b in range(B)])
    assert np.abs(e.residual(q, np.zeros_like(q), velocity=False)[0]).max() < 1e-12
    J = jacobian(e, q)
    qd = rng.uniform(-1, 1, (B, model.nv))
    qd = np.stack([qd[b] - np.linalg.pinv(J[b], rcond=1e-10) @ (J[b] @ qd[b]) for b in range(B)])
    tau = rng.uniform(-1, 1, (B, model.nv))
    return e, q, qd, tau, J


def test_loop_sets(tmp_path):
    m = sd.load_model("fivebar")
    L = sd.generator_loops(m)
    assert (len(L), L.rows) == (1, 3)
    assert len(sd.generator_loops(sd.load_model("cloth:3:4"))) == 8
    assert len(sd.generator_loops(sd.load_model("iiwa"))) == 0
    # the file text round trip, and the dict form
    f = tmp_path / "fivebar_loops.json"
    f.write_text(L.json)
    assert sd.load_loops(m, f).json == L.json
    import json

    assert sd.parse_loops(m, json.loads(L.json)).json == L.json
    assert sd.parse_loops(m, json.loads(L.json)["loops"]).rows == 3


def test_loop_errors(tmp_path):
    m = sd.load_model("fivebar")
    loop = {"type": "point", "link_a": "left_distal", "point_a": [0, 0, 0], "link_b": "nowhere", "point_b": [0, 0, 0]}
    with pytest.raises(sd.LoopError, match="unknown link 'nowhere'"):
        sd.parse_loops(m, [loop])
    loop["link_b"] = "left_distal"
    with pytest.raises(sd.LoopError, match="itself"):
        sd.parse_loops(m, [loop])
    with pytest.raises(sd.LoopError):
        sd.load_loops(m, tmp_path / "missing.json")
    other = sd.load_model("fivebar")
    with pytest.raises(sd.LoopError, match="made for model"):
        sd.ConstrainedForwardDynamics(other, sd.generator_loops(m))
    with pytest.raises(TypeError):
        sd.constrained_forward_dynamics(m, "loops.json", np.zeros(4), np.zeros(4), np.zeros(4))
    e = sd.ConstrainedForwardDynamics(m, sd.generator_loops(m), backend="serial", max_batch=2)
    z = np.zeros((2, 4))
    with pytest.raises(sd.ShapeError, match="lambda_out"):
        e(z, z, z, lambda_out=np.zeros((2, 4)))
    with pytest.raises(sd.ShapeError, match="shares memory"):
        e(z, z, z, qdd_out=z)


@pytest.mark.parametrize("spec", LOOPY)
@pytest.mark.parametrize("backend", ["serial", "openmp"])
def test_constrained_equations(spec, backend):
    if sd.backend_unusable(backend):
        pytest.skip(sd.backend_unusable(backend))
    m = sd.load_model(spec)
    L = sd.generator_loops(m)
    B = 5
    e_ref, q, qd, tau, J = closed_states(m, L, B, seed=1)
    e = sd.ConstrainedForwardDynamics(m, L, backend=backend, max_batch=B)
    qdd, lam = e(q, qd, tau)
    assert qdd.shape == (B, m.nv) and lam.shape == (B, L.rows)
    scale = max(1.0, np.abs(qdd).max())
    # M qdd + h - tau = J^T lambda
    lhs = sd.inverse_dynamics(m, q, qd, qdd, backend="serial") - tau
    np.testing.assert_allclose(lhs, np.einsum("bmi,bm->bi", J, lam), rtol=0, atol=1e-9 * scale)
    # J qdd + Jdot qd = 0, Jdot qd by central differences of J(q + t qd) qd
    h = 1e-6
    _, vp = e_ref.residual(q + h * qd, qd, phi=False)
    _, vm = e_ref.residual(q - h * qd, qd, phi=False)
    gamma = (vp - vm) / (2 * h)
    assert np.abs(np.einsum("bmi,bi->bm", J, qdd) + gamma).max() <= 1e-6 * scale
    # the velocity residual of the closed states is zero
    phi, v = sd.loop_residual(m, L, q, qd, backend=backend)
    assert np.abs(phi).max() < 1e-12 and np.abs(v).max() < 1e-12


@pytest.mark.parametrize("spec", LOOPY)
def test_constrained_matches_cli(spec, cli, tmp_path):
    """The engine's qdd and lambda against `scandyn eval` (the Eigen reference: complete
    orthogonal decomposition, minimum-norm lambda) on the same closed states."""
    m = sd.load_model(spec)
    L = sd.generator_loops(m)
    _, q, qd, tau, _ = closed_states(m, L, 6, seed=2)
    names, cols = [], []
    for prefix, a in (("q", q), ("qd", qd), ("tau", tau)):
        for i in range(m.nv):
            names.append(f"{prefix}_{i}")
            cols.append(a[:, i])
    states, out = tmp_path / "s.csv", tmp_path / "o.csv"
    with open(states, "w") as f:
        f.write(",".join(names) + "\n")
        for row in np.stack(cols, axis=1):
            f.write(",".join(repr(float(x)) for x in row) + "\n")
    subprocess.run([cli, "eval", "--model", spec, "--states", str(states), "--out", str(out)], check=True,
                   capture_output=True, text=True)
    with open(out) as f:
        header = f.readline().strip().split(",")
        table = np.array([[float(x) for x in line.split(",")] for line in f if line.strip()])
    col = {n: table[:, k] for k, n in enumerate(header)}
    qdd, lam = sd.constrained_forward_dynamics(m, L, q, qd, tau, backend="serial")
    sq, sl = max(1.0, np.abs(qdd).max()), max(1.0, np.abs(lam).max())
    for i in range(m.nv):
        np.testing.assert_allclose(qdd[:, i], col[f"qdd_fd_{i}"], rtol=0, atol=1e-10 * sq)
    for k in range(L.rows):
        np.testing.assert_allclose(lam[:, k], col[f"lambda_{k}"], rtol=0, atol=1e-8 * sl)


def test_constrained_float32_and_single_state():
    m = sd.load_model("fivebar")
    L = sd.generator_loops(m)
    _, q, qd, tau, _ = closed_states(m, L, 8, seed=3)
    qdd, lam = sd.constrained_forward_dynamics(m, L, q, qd, tau, backend="serial")
    q32, l32 = sd.constrained_forward_dynamics(m, L, *(x.astype(np.float32) for x in (q, qd, tau)), backend="serial")
    assert q32.dtype == np.float32
    np.testing.assert_allclose(q32, qdd, rtol=0, atol=2e-3 * max(1.0, np.abs(qdd).max()))
    np.testing.assert_allclose(l32, lam, rtol=0, atol=2e-3 * max(1.0, np.abs(lam).max()))
    q1, l1 = sd.constrained_forward_dynamics(m, L, q[3], qd[3], tau[3], backend="serial")
    assert q1.shape == (m.nv,) and l1.shape == (L.rows,)
    np.testing.assert_array_equal(q1, qdd[3])
    np.testing.assert_array_equal(l1, lam[3])


@pytest.mark.parametrize("spec", ["fivebar", "fourbar"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_constrained_cuda_arrays(spec, dtype):
    """CUDA tensors go to the CUDA engine (one thread per instance, the same solve as the
    CPU engines); results equal the serial engine's within the precision's tolerance."""
    reason = sd.backend_unusable("cuda")
    if reason:
        pytest.skip(f"backend cuda: {reason}")
    torch = pytest.importorskip("torch")
    m = sd.load_model(spec)
    L = sd.generator_loops(m)
    _, q, qd, tau, _ = closed_states(m, L, 32, seed=4)
    q, qd, tau = (x.astype(dtype) for x in (q, qd, tau))
    qdd, lam = sd.constrained_forward_dynamics(m, L, q, qd, tau, backend="serial")
    e = sd.ConstrainedForwardDynamics(m, L, backend="cuda", max_batch=32, dtype=dtype)
    qg, lg = e(*(torch.from_numpy(x).cuda() for x in (q, qd, tau)), check=True)
    assert qg.is_cuda and e.last_status.ok
    tol = 1e-9 if dtype == np.float64 else 2e-3
    np.testing.assert_allclose(qg.cpu().numpy(), qdd, rtol=0, atol=tol * max(1.0, np.abs(qdd).max()))
    np.testing.assert_allclose(lg.cpu().numpy(), lam, rtol=0, atol=tol * max(1.0, np.abs(lam).max()))
    phi, v = e.residual(torch.from_numpy(q).cuda(), torch.from_numpy(qd).cuda())
    torch.cuda.synchronize()
    assert float(phi.abs().max()) < (1e-12 if dtype == np.float64 else 1e-5)


@pytest.mark.parametrize("spec", ["fivebar", "fourbar"])
@pytest.mark.parametrize("backend", ["serial", "openmp"])
def test_constrained_against_pinocchio(spec, backend):
    """qdd against Pinocchio's constraintDynamics (CONTACT_3D between the loop's two points)
    on the models re-described in Pinocchio by scripts/check_loops_pinocchio.py, on its
    random closed states: an independent library, 1e-9 relative."""
    pytest.importorskip("pinocchio")
    if sd.backend_unusable(backend):
        pytest.skip(sd.backend_unusable(backend))
    import importlib.util
    import os

    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    where = os.path.join(root, "scripts", "check_loops_pinocchio.py")
    mod_spec = importlib.util.spec_from_file_location("check_loops_pinocchio", where)
    clp = importlib.util.module_from_spec(mod_spec)
    mod_spec.loader.exec_module(clp)
    pm, loop = clp.build(spec)
    rng = np.random.default_rng(5)
    rows = [clp.closed_state(spec, pm, loop, rng) for _ in range(8)]
    q = np.stack([r[0] for r in rows])
    qd = np.stack([r[1] for r in rows])
    tau = rng.uniform(-1, 1, q.shape)
    ref = np.stack([clp.pinocchio_fd(pm, loop, q[b], qd[b], tau[b]) for b in range(len(rows))])
    m = sd.load_model(spec)
    qdd, _ = sd.constrained_forward_dynamics(m, sd.generator_loops(m), q, qd, tau, backend=backend)
    np.testing.assert_allclose(qdd, ref, rtol=0, atol=1e-9 * max(1.0, np.abs(ref).max()))


def test_simulator_sparse_loop_solver_equals_dense():
    """The simulator's sparse loop path (scene "loop_solver": "sparse": the factor graph's
    CHOLMOD solver, registered at import when the module is built with it;
    sd.has_sparse_loops) against the dense one on the same closed state of cloth:6:6, 40 rk4
    steps under gravity: q within 1e-12 and qd within 1e-11 relative to max(1, max |x|)
    (tests/factor_graph/test_sparse_loop_step.cpp measures ~1e-13 a step), and the loops
    closed after. Without CHOLMOD: the simulator's error, then skipped."""
    m = sd.load_model("cloth:6:6")
    e, q0, qd0, _, _ = closed_states(m, sd.generator_loops(m), 1, 7)

    def scene(solver):
        return {"model": "cloth:6:6", "backend": "serial", "effects": {"gravity": True}, "integrator": "rk4",
                "dt": 2e-4, "loop_solver": solver, "initial": {"q": q0[0].tolist(), "qd": qd0[0].tolist()}}

    if not sd.has_sparse_loops:
        with pytest.raises(sd.BackendError, match="no sparse loop solver"):
            sd.Simulator(scene("sparse"))
        pytest.skip("scandyn._scandyn was built without SuiteSparse CHOLMOD: no sparse loop solver")
    sparse, dense = sd.Simulator(scene("sparse")), sd.Simulator(scene("dense"))
    sparse.step_many(40)
    dense.step_many(40)
    q, qd, q_ref, qd_ref = sparse.q.copy(), sparse.qd.copy(), dense.q.copy(), dense.qd.copy()
    assert np.abs(q_ref - q0).max() > 1e-4  # the cloth moved
    np.testing.assert_allclose(q, q_ref, rtol=0, atol=1e-12 * max(1.0, np.abs(q_ref).max()))
    np.testing.assert_allclose(qd, qd_ref, rtol=0, atol=1e-11 * max(1.0, np.abs(qd_ref).max()))
    phi, v = e.residual(q, qd)
    assert np.abs(phi).max() < 1e-10 and np.abs(v).max() < 1e-10


def test_simulator_iterative_loop_solver_equals_dense():
    """The simulator's iterative loop path (scene "loop_solver": "iterative": the core
    library's matrix-free conjugate gradients, in every build) against the dense one on
    the same closed state of cloth:6:6, 40 rk4 steps under gravity: q within 1e-9 and qd
    within 1e-8 relative to max(1, max |x|) (the solver's tolerance is a relative
    residual of 1e-10; tests/sim/test_iterative_loops.cpp), and the loops closed after."""
    m = sd.load_model("cloth:6:6")
    e, q0, qd0, _, _ = closed_states(m, sd.generator_loops(m), 1, 7)

    def scene(solver):
        return {"model": "cloth:6:6", "backend": "serial", "effects": {"gravity": True}, "integrator": "rk4",
                "dt": 2e-4, "loop_solver": solver, "initial": {"q": q0[0].tolist(), "qd": qd0[0].tolist()}}

    iterative, dense = sd.Simulator(scene("iterative")), sd.Simulator(scene("dense"))
    iterative.step_many(40)
    dense.step_many(40)
    q, qd, q_ref, qd_ref = iterative.q.copy(), iterative.qd.copy(), dense.q.copy(), dense.qd.copy()
    assert np.abs(q_ref - q0).max() > 1e-4  # the cloth moved
    np.testing.assert_allclose(q, q_ref, rtol=0, atol=1e-9 * max(1.0, np.abs(q_ref).max()))
    np.testing.assert_allclose(qd, qd_ref, rtol=0, atol=1e-8 * max(1.0, np.abs(qd_ref).max()))
    phi, v = e.residual(q, qd)
    assert np.abs(phi).max() < 1e-10 and np.abs(v).max() < 1e-10
