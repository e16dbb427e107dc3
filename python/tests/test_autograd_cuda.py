"""scandyn.autograd on CUDA arrays: the derivative engines (make_id_derivatives,
make_fd_derivatives on backend cuda), the step Jacobian (cuda::CudaStepDerivatives)
and the rollouts' adjoint / JVP (cuda::CudaRolloutDerivatives) through Python, on
torch CUDA tensors (and CuPy, JAX on a GPU where importable), on the caller's stream.

Truths: the host path of the same functions (docs/python.md; itself checked against
central differences in test_autograd.py): double 1e-9 relative to the result's scale,
float32 on the GPU against the double host path 2e-3 (id) and 1e-2 (fd, whose M^-1
amplifies rounding; the step and rollouts: 1e-2 on 10 steps); torch.autograd.gradcheck
in double on CUDA tensors (its default tolerances). Each test skips with its reason
where the CUDA build, a GPU or torch is missing."""

import numpy as np
import pytest

import scandyn as sd
import scandyn.autograd as ad
from conftest import uniform_states, assert_close

cuda_reason = sd.backend_unusable("cuda")
pytestmark = pytest.mark.skipif(bool(cuda_reason), reason=f"backend cuda: {cuda_reason}")

SCENE = {"model": "iiwa", "dt": 2e-3, "integrator": "rk4",
         "effects": {"gravity": True, "damping": 0.5, "springs": {"stiffness": 2.0}}}


@pytest.fixture(scope="module")
def torch():
    torch = pytest.importorskip("torch", reason="torch is not installed")
    if not torch.cuda.is_available():
        pytest.skip("torch has no CUDA device here")
    return torch


def _cuda(torch, a, dtype=np.float64):
    return torch.from_numpy(np.ascontiguousarray(a, dtype=dtype)).cuda()


@pytest.mark.parametrize("name", ["iiwa", "hyq"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_id_and_fd_derivatives_on_cuda_tensors_equal_the_host_path(torch, name, dtype):
    m = sd.load_model(name)
    q, qd, x = uniform_states(m.nv, 33, 1)
    host_id = ad.id_derivatives(m, q, qd, x)
    host_fd = ad.fd_derivatives(m, q, qd, x)
    got_id = ad.id_derivatives(m, *(_cuda(torch, a, dtype) for a in (q, qd, x)))
    got_fd = ad.fd_derivatives(m, *(_cuda(torch, a, dtype) for a in (q, qd, x)))
    double = dtype == np.float64
    for got, want in zip(got_id, host_id):
        assert isinstance(got, torch.Tensor) and got.is_cuda and got.shape == (33, m.nv, m.nv)
        assert got.dtype == (torch.float64 if double else torch.float32)
        assert_close(got, want, 1e-9 if double else 2e-3)
    for got, want in zip(got_fd, host_fd):
        assert got.is_cuda and got.shape == want.shape
        assert_close(got, want, 1e-9 if double else 1e-2)
    # one state: (nv, nv) on the device
    one = ad.id_derivatives(m, *(_cuda(torch, a[0], dtype) for a in (q, qd, x)))
    assert one[0].shape == (m.nv, m.nv) and one[0].is_cuda
    assert_close(one[2], host_id[2][0], 1e-9 if double else 2e-3)


def test_torch_gradcheck_dynamics_on_cuda(torch):
    m = sd.load_model("iiwa")
    q, qd, x = (_cuda(torch, a).requires_grad_(True) for a in uniform_states(m.nv, 3, 5))
    assert torch.autograd.gradcheck(lambda a, b, c: ad.torch_inverse_dynamics(m, a, b, c), (q, qd, x))
    assert torch.autograd.gradcheck(lambda a, b, c: ad.torch_forward_dynamics(m, a, b, c), (q, qd, x))
    # backward runs on the device: the gradients are CUDA tensors equal to the host path's
    qh, qdh, xh = (t.detach().cpu().requires_grad_(True) for t in (q, qd, x))
    ad.torch_forward_dynamics(m, q, qd, x).square().sum().backward()
    ad.torch_forward_dynamics(m, qh, qdh, xh).square().sum().backward()
    assert q.grad.is_cuda
    for a, b in ((q, qh), (qd, qdh), (x, xh)):
        assert_close(a.grad, b.grad.numpy(), 1e-9)


def test_step_derivatives_on_cuda_tensors_equal_the_host_path(torch):
    host = ad.StepDerivatives(SCENE)
    gpu = ad.StepDerivatives(SCENE)  # backend 'auto': host arrays on the CPU, CUDA arrays on their device
    n, T, B = host.nv, 10, 40
    rng = np.random.default_rng(3)
    q0, qd0 = rng.uniform(-0.5, 0.5, (2, B, n))
    tau = rng.uniform(-2, 2, (T, B, n))
    gq, gqd = rng.uniform(-1, 1, (2, T, B, n))
    v0, vd0 = rng.uniform(-1, 1, (2, B, n))
    vt = rng.uniform(-1, 1, (T, B, n))
    d = lambda a: _cuda(torch, a)  # noqa: E731
    for got, want in zip(gpu.jacobian(d(q0), d(qd0), d(tau[0])), host.jacobian(q0, qd0, tau[0])):
        assert got.is_cuda and got.shape == want.shape
        assert_close(got, want, 1e-9)
    for got, want in zip(gpu.rollout(d(q0), d(qd0), d(tau)), host.rollout(q0, qd0, tau)):
        assert got.is_cuda and got.shape == (T, B, n)
        assert_close(got, want, 1e-9)
    for got, want in zip(gpu.rollout_vjp(d(q0), d(qd0), d(tau), d(gq), d(gqd)), host.rollout_vjp(q0, qd0, tau, gq, gqd)):
        assert got.is_cuda and got.shape == want.shape
        assert_close(got, want, 1e-9)
    for got, want in zip(gpu.rollout_jvp(d(q0), d(qd0), d(tau), d(v0), d(vd0), d(vt)),
                         host.rollout_jvp(q0, qd0, tau, v0, vd0, vt)):
        assert_close(got, want, 1e-9)
    # one state ((nv,), (T, nv)) and float32 on the device
    q1, qd1 = gpu.rollout(d(q0[0]), d(qd0[0]), d(tau[:, 0]))
    assert q1.shape == (T, n)
    assert_close(q1, host.rollout(q0, qd0, tau)[0][:, 0], 1e-9)
    f32 = ad.StepDerivatives(SCENE, backend="cuda", dtype=np.float32)
    f = lambda a: _cuda(torch, a, np.float32)  # noqa: E731
    assert_close(f32.jacobian(f(q0), f(qd0), f(tau[0]))[2], host.jacobian(q0, qd0, tau[0])[2], 1e-2)
    assert_close(f32.rollout_vjp(f(q0), f(qd0), f(tau), f(gq), f(gqd))[2], host.rollout_vjp(q0, qd0, tau, gq, gqd)[2], 1e-2)
    # a host backend refuses CUDA arrays by name
    with pytest.raises(sd.DeviceError, match="backend='cuda'"):
        ad.StepDerivatives(SCENE, backend="serial").rollout(d(q0), d(qd0), d(tau))


def test_torch_gradcheck_step_and_rollout_on_cuda(torch):
    step = ad.StepDerivatives(SCENE, backend="cuda")
    n = step.nv
    rng = np.random.default_rng(6)
    q, qd = (_cuda(torch, rng.uniform(-0.5, 0.5, (2, n))).requires_grad_(True) for _ in range(2))
    tau = _cuda(torch, rng.uniform(-2, 2, (2, n))).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b, c: ad.torch_step(step, a, b, c), (q, qd, tau))
    taus = _cuda(torch, rng.uniform(-2, 2, (6, 2, n))).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b, c: ad.torch_rollout(step, a, b, c), (q, qd, taus))
    # loss.backward() runs the CUDA adjoint: equal to the host path's gradients
    qs, qds = ad.torch_rollout(step, q, qd, taus)
    (qs.square().sum() + qds.sum()).backward()
    host = ad.StepDerivatives(SCENE, backend="serial")
    qh, qdh, th = (t.detach().cpu().requires_grad_(True) for t in (q, qd, taus))
    qs, qds = ad.torch_rollout(host, qh, qdh, th)
    (qs.square().sum() + qds.sum()).backward()
    assert taus.grad.is_cuda
    for a, b in ((q, qh), (qd, qdh), (taus, th)):
        assert_close(a.grad, b.grad.numpy(), 1e-9)


def test_a_non_default_torch_stream_carries_the_work(torch):
    m = sd.load_model("iiwa")
    q, qd, x = uniform_states(m.nv, 64, 7)
    want = ad.id_derivatives(m, q, qd, x)
    step = ad.StepDerivatives(SCENE)
    rng = np.random.default_rng(8)
    taus = rng.uniform(-2, 2, (5, 64, m.nv))
    host_grad = ad.StepDerivatives(SCENE, backend="serial").rollout_vjp(q, qd, taus, np.ones_like(taus),
                                                                        np.zeros_like(taus))
    side = torch.cuda.Stream()
    dq, dqd, dx, dt = (_cuda(torch, a) for a in (q, qd, x, taus))
    ad.id_derivatives(m, dq, dqd, dx)  # the engine made (and its memory allocated) before the timed part
    torch.cuda.synchronize()
    with torch.cuda.stream(side):
        torch.cuda._sleep(200_000_000)  # GPU time queued ahead on the side stream
        got = ad.id_derivatives(m, dq, dqd, dx)  # queued behind it, no synchronisation
        assert not side.query(), "the call waited for the side stream (or ran elsewhere)"
        assert torch.cuda.default_stream().query(), "the default stream was made to wait for the side stream"
        t = dt.clone().requires_grad_(True)
        qs, _ = ad.torch_rollout(step, dq, dqd, t)
        qs.sum().backward()  # the adjoint on the side stream (check=True waits for it)
    side.synchronize()
    for g, w in zip(got, want):
        assert_close(g, w, 1e-9)
    assert_close(t.grad, host_grad[2], 1e-9)


def test_cupy_arrays_run_on_their_device():
    cupy = pytest.importorskip("cupy", reason="CuPy is not installed")
    try:
        if cupy.cuda.runtime.getDeviceCount() == 0:
            pytest.skip("CuPy sees no CUDA device")
    except cupy.cuda.runtime.CUDARuntimeError as e:
        pytest.skip(f"CuPy has no CUDA device: {e}")
    m = sd.load_model("iiwa")
    q, qd, x = uniform_states(m.nv, 9, 2)
    got = ad.fd_derivatives(m, *(cupy.asarray(a) for a in (q, qd, x)))
    assert all(isinstance(g, cupy.ndarray) for g in got)
    for g, w in zip(got, ad.fd_derivatives(m, q, qd, x)):
        assert_close(cupy.asnumpy(g), w, 1e-9)
    step = ad.StepDerivatives(SCENE)
    J = step.jacobian(*(cupy.asarray(a) for a in (q, qd, x)))[2]
    assert_close(cupy.asnumpy(J), step.jacobian(q, qd, x)[2], 1e-9)


def test_jax_gpu_arrays_run_on_their_device():
    jax = pytest.importorskip("jax", reason="jax is not installed")
    try:
        gpu = jax.devices("gpu")[0]
    except RuntimeError as e:
        pytest.skip(f"jax has no GPU: {e}")
    m = sd.load_model("iiwa")
    q, qd, x = uniform_states(m.nv, 5, 4)
    put = lambda a: jax.device_put(a.astype(np.float32), gpu)  # noqa: E731  (float32: x64 left as it is)
    got = ad.id_derivatives(m, put(q), put(qd), put(x))
    assert all(next(iter(g.devices())).platform == "gpu" for g in got)
    for g, w in zip(got, ad.id_derivatives(m, q, qd, x)):
        assert_close(np.asarray(g), w, 2e-3)
    step = ad.StepDerivatives(SCENE, dtype=np.float32)
    J = step.jacobian(put(q), put(qd), put(x))[2]
    assert J.shape == (5, 2 * m.nv, 3 * m.nv)
    assert_close(np.asarray(J), ad.StepDerivatives(SCENE).jacobian(q, qd, x)[2], 1e-2)
