"""Floating bases and ball joints on CUDA arrays (torch CUDA tensors, CuPy, JAX on a GPU):
the engines (the floating-base thread kernels for hyq and atlas; the general path for
ball joints), frame placements and Jacobians, and the simulator's CUDA step with q of nq
columns, each against the serial backend on host copies of the same inputs (within
test_cuda_arrays.TOL). Each test skips with its reason where the CUDA build, a GPU or the
array library is missing (CI); on the GPU machine every test runs."""

import numpy as np
import pytest

import scandyn as sd
from conftest import DTYPES
from test_cuda_arrays import _close, _torch, lib  # noqa: F401 (lib: the array-library fixture)
from test_cuda_kinematics import _same_sign_quaternions

cuda_reason = sd.backend_unusable("cuda")
pytestmark = pytest.mark.skipif(bool(cuda_reason), reason=f"backend cuda: {cuda_reason}")

# (spec, floating_base): the floating-base thread kernels (hyq, atlas) and the general
# path (ball joints on a fixed and on a floating root)
MODELS = [("hyq", True), ("atlas", True), ("ballrope:5", False), ("ballrope:4", True)]


@pytest.fixture(scope="module", params=MODELS, ids=[f"{s}{'-floating' if f else ''}" for s, f in MODELS])
def fmodel(request):
    spec, floating = request.param
    return sd.load_model(spec, floating_base=floating, allow_nonphysical_inertia=spec == "atlas")


def random_state(m, B, dtype, seed):
    """q (B, nq) with unit quaternions (the base's q[3:7], each ball joint's 4), qd, u (B, nv)."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-1, 1, (B, m.nq))
    at = 0
    for t in m.joint_types:
        if t == "free":
            q[:, at + 3:at + 7] /= np.linalg.norm(q[:, at + 3:at + 7], axis=1, keepdims=True)
            at += 7
        elif t == "spherical":
            q[:, at:at + 4] /= np.linalg.norm(q[:, at:at + 4], axis=1, keepdims=True)
            at += 4
        else:
            at += 1
    assert at == m.nq
    return (q.astype(dtype), rng.uniform(-1, 1, (B, m.nv)).astype(dtype),
            rng.uniform(-1, 1, (B, m.nv)).astype(dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_engines_on_device(fmodel, lib, dtype):
    q, qd, u = random_state(fmodel, 29, dtype, seed=4)
    dq, dqd, du = lib.dev(q), lib.dev(qd), lib.dev(u)
    calls = [
        ("inverse_dynamics", (dq, dqd, du), (q, qd, u)),
        ("forward_dynamics", (dq, dqd, du), (q, qd, u)),
        ("bias_forces", (dq, dqd), (q, qd)),
        ("mass_matrix", (dq,), (q,)),
    ]
    for name, dev_args, host_args in calls:
        got = getattr(sd, name)(fmodel, *dev_args)  # backend="auto" follows the arrays
        assert lib.is_kind(got), f"{name} returned {type(got)} for {lib.name} inputs"
        ref = getattr(sd, name)(fmodel, *host_args, backend="serial")
        assert got.shape == ref.shape
        _close(lib.host(got), ref, dtype, f"{lib.name} {name}")


@pytest.mark.parametrize("dtype", DTYPES)
def test_derivatives_on_device(fmodel, lib, dtype):
    """id_derivatives / fd_derivatives on CUDA arrays: the cuda engines' general kernels
    (multi-DoF joints) against the serial backend on host copies: did and qdd within
    TOL, dfd's blocks within 1e-8 (double) or 1e-2 (float) of each block's largest entry
    (M^-1's rounding times cond(M)); float leaves the ball ropes out (their 1e-8 kg m^2
    links fail float's pivots)."""
    import scandyn.autograd as ad

    if dtype == np.float32 and any(t == "spherical" for t in fmodel.joint_types):
        pytest.skip("ball ropes in float: their tiny link inertias fail float's pivots")
    q, qd, u = random_state(fmodel, 19, dtype, seed=8)
    dq, dqd, du = lib.dev(q), lib.dev(qd), lib.dev(u)
    got = ad.id_derivatives(fmodel, dq, dqd, du)
    ref = ad.id_derivatives(fmodel, q, qd, u, backend="serial")
    for k, (g, r) in enumerate(zip(got, ref)):
        assert lib.is_kind(g) and g.shape == r.shape == (19, fmodel.nv, fmodel.nv)
        _close(lib.host(g), r, dtype, f"{lib.name} id_derivatives block {k}")
    got = ad.fd_derivatives(fmodel, dq, dqd, du)
    ref = ad.fd_derivatives(fmodel, q, qd, u, backend="serial")
    for k, (g, r) in enumerate(zip(got, ref)):
        g = lib.host(g)
        if k > 0:  # the blocks, through M^-1 (the ball ropes' cond(M) reaches 1e7)
            tol = 1e-2 if dtype == np.float32 else 1e-8
            np.testing.assert_allclose(g, r, rtol=0, atol=tol * (1.0 + np.abs(r).max()),
                                       err_msg=f"{lib.name} fd_derivatives block {k}")
        else:
            _close(g, r, dtype, f"{lib.name} fd_derivatives output {k}")


@pytest.mark.parametrize("dtype", DTYPES)
def test_kinematics_on_device(fmodel, lib, dtype):
    q, _, _ = random_state(fmodel, 23, dtype, seed=5)
    dq = lib.dev(q)
    got = sd.frame_placements(fmodel, dq, quaternion=True)
    assert lib.is_kind(got)
    ref = sd.frame_placements(fmodel, q, quaternion=True, backend="serial")
    _close(_same_sign_quaternions(lib.host(got), ref), ref, dtype, f"{lib.name} placements")
    for reference in ("world", "local"):
        got = sd.frame_jacobians(fmodel, dq, reference=reference)
        ref = sd.frame_jacobians(fmodel, q, reference=reference, backend="serial")
        assert got.shape == (23, len(fmodel.frames), 6, fmodel.nv)
        _close(lib.host(got), ref, dtype, f"{lib.name} jacobians {reference}")


@pytest.mark.parametrize("spec,strategy", [("hyq", "fused-aba"), ("ballrope:5", "general-aba")])
def test_simulator_on_device_matches_serial(spec, strategy):
    """The CUDA step of a floating hyq (the fused floating-base kernel) and of a floating
    ball-joint rope (the general step): q (B, nq) on the device, equal to the serial
    step's after 20 steps (double: the same steps, FMA contraction apart)."""
    torch = _torch()
    if torch is None:
        pytest.skip("torch with CUDA is not importable here")
    # (dt 1e-4 and torques of 1e-6: the ball rope's 1 cm links have inertias ~3e-7 kg m^2)
    s = {"model": spec, "base": "floating", "dt": 1e-4, "integrator": "rk4", "instances": 16,
         "effects": {"gravity": True}, "initial": {"random": {"seed": 2, "q": 0.2, "qd": 0.3}}}
    gpu = sd.Simulator(dict(s, backend="cuda"))
    cpu = sd.Simulator(dict(s, backend="serial"))
    assert gpu.strategy == strategy
    assert isinstance(gpu.q, torch.Tensor) and gpu.q.is_cuda and gpu.q.shape == (16, cpu.nq)
    rng = np.random.default_rng(6)
    tau = rng.uniform(-1e-6, 1e-6, (16, cpu.nv))
    for _ in range(20):
        gpu.step(torch.from_numpy(tau).cuda())
        cpu.step(tau)
    torch.cuda.synchronize()
    ref = cpu.q
    np.testing.assert_allclose(gpu.q.cpu().numpy(), ref, rtol=0, atol=1e-9 * max(1.0, np.abs(ref).max()))
    np.testing.assert_allclose(gpu.qd.cpu().numpy(), cpu.qd, rtol=0, atol=1e-9 * max(1.0, np.abs(cpu.qd).max()))
