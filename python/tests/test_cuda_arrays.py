"""The device path: CUDA arrays (torch CUDA tensors, CuPy, JAX on a GPU) go to the CUDA
engines' compute_async() on the caller's stream, with no copy and no synchronisation,
and the result is an array of the same library on the same device.

Every result is checked against the serial reference on host copies of the same inputs
(within the float tolerance: the device's FMA and sin/cos differ from the host's).
Each test skips with its reason where the CUDA build, a GPU or the library is missing
(CI); on the GPU machine torch, CuPy and JAX are installed and every test runs."""

import numpy as np
import pytest

import scandyn as sd
from conftest import DTYPES, states, degenerate_urdf

cuda_reason = sd.backend_unusable("cuda")
pytestmark = pytest.mark.skipif(bool(cuda_reason), reason=f"backend cuda: {cuda_reason}")

TOL = {np.float64: 1e-9, np.float32: 2e-3}


def _torch():
    try:
        import torch
    except ImportError:
        return None
    return torch if torch.cuda.is_available() else None


def _cupy():
    try:
        import cupy

        return cupy if cupy.cuda.runtime.getDeviceCount() > 0 else None
    except Exception:  # ImportError, or CUDA errors without a GPU
        return None


def _jax_gpu():
    try:
        import jax

        jax.config.update("jax_enable_x64", True)  # float64 arrays stay float64 (JAX's default makes them float32)
        gpus = [d for d in jax.devices() if d.platform == "gpu"]
    except Exception:
        return None
    return gpus[0] if gpus else None


class Lib:
    """One GPU array library: to device, to host, and how to read an array's address."""

    def __init__(self, name):
        self.name = name
        if name == "torch":
            torch = _torch()
            self.ok = torch is not None
            if self.ok:
                self.dev = lambda a: torch.from_numpy(np.ascontiguousarray(a)).cuda()
                self.host = lambda x: x.cpu().numpy()
                self.ptr = lambda x: x.data_ptr()
                self.empty = lambda shape, dtype: torch.empty(shape, dtype=getattr(torch, np.dtype(dtype).name),
                                                              device="cuda")
                self.is_kind = lambda x: isinstance(x, torch.Tensor) and x.is_cuda
        elif name == "cupy":
            cupy = _cupy()
            self.ok = cupy is not None
            if self.ok:
                self.dev = cupy.asarray
                self.host = cupy.asnumpy
                self.ptr = lambda x: x.data.ptr
                self.empty = lambda shape, dtype: cupy.empty(shape, dtype)
                self.is_kind = lambda x: isinstance(x, cupy.ndarray)
        else:
            gpu = _jax_gpu()
            self.ok = gpu is not None
            if self.ok:
                import jax

                self.dev = lambda a: jax.device_put(np.ascontiguousarray(a), gpu)
                self.host = np.asarray
                self.ptr = lambda x: x.unsafe_buffer_pointer()
                self.empty = None  # immutable: no out=
                self.is_kind = lambda x: isinstance(x, jax.Array) and next(iter(x.devices())).platform == "gpu"


LIBS = ["torch", "cupy", "jax"]


@pytest.fixture(params=LIBS)
def lib(request):
    l = Lib(request.param)
    if not l.ok:
        pytest.skip(f"{request.param} with a CUDA GPU is not importable here")
    return l


def _close(got, ref, dtype, what):
    tol = TOL[dtype]
    np.testing.assert_allclose(got, ref, rtol=tol, atol=tol * (1.0 + np.abs(ref).max()), err_msg=what)


CALLS = [
    ("inverse_dynamics", lambda q, qd, qdd, tau: (q, qd, qdd)),
    ("bias_forces", lambda q, qd, qdd, tau: (q, qd)),
    ("mass_matrix", lambda q, qd, qdd, tau: (q,)),
    ("forward_dynamics", lambda q, qd, qdd, tau: (q, qd, tau)),
]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("name,pick", CALLS, ids=[c[0] for c in CALLS])
def test_function_api_on_device(model, lib, dtype, name, pick):
    fn = getattr(sd, name)
    host = pick(*states(model, 37, dtype, seed=3))
    ref = fn(model, *host, backend="serial")
    got = fn(model, *[lib.dev(a) for a in host])  # backend="auto" follows the arrays
    assert lib.is_kind(got), f"{name} returned {type(got)} for {lib.name} inputs"
    assert got.shape == ref.shape and np.dtype(str(got.dtype).replace("torch.", "")) == dtype
    _close(lib.host(got), ref, dtype, f"{lib.name} {name}")
    # one state: (nv,) in, (nv,) / (nv, nv) out
    one = fn(model, *[lib.dev(a[5]) for a in host])
    _close(lib.host(one), ref[5], dtype, f"{lib.name} {name} single state")


@pytest.mark.parametrize("dtype", DTYPES)
def test_engines_out_aliases_caller_memory(lib, dtype):
    """out= is written in place: the returned object is out, at the same device address,
    call after call (no result copied anywhere)."""
    if lib.empty is None:
        pytest.skip("JAX arrays are immutable: out= is refused (a new array is returned)")
    m = sd.load_model("iiwa")
    B = 300
    q, qd, qdd, tau = states(m, B, dtype, seed=5)
    dq, dqd, dqdd, dtau = (lib.dev(a) for a in (q, qd, qdd, tau))
    id_ = sd.InverseDynamics(m, backend="cuda", max_batch=B, dtype=dtype)
    fd = sd.ForwardDynamics(m, backend="cuda", max_batch=B, dtype=dtype)
    mm = sd.MassMatrix(m, backend="cuda", max_batch=B, dtype=dtype)
    out = lib.empty((B, m.nv), dtype)
    M = lib.empty((B, m.nv, m.nv), dtype)
    addr, maddr = lib.ptr(out), lib.ptr(M)
    for _ in range(3):
        assert id_(dq, dqd, dqdd, out=out) is out and lib.ptr(out) == addr
        _close(lib.host(out), sd.inverse_dynamics(m, q, qd, qdd, backend="serial"), dtype, "id out=")
        assert fd(dq, dqd, dtau, out=out) is out and lib.ptr(out) == addr
        assert fd.check().ok
        _close(lib.host(out), sd.forward_dynamics(m, q, qd, tau, backend="serial"), dtype, "fd out=")
        assert mm(dq, out=M) is M and lib.ptr(M) == maddr
        _close(lib.host(M), sd.mass_matrix(m, q, backend="serial"), dtype, "mass out=")
    # a strided out: every other row of a (2B, nv) array; the rows between stay NaN
    if lib.name == "torch":
        import torch

        big = torch.full((2 * B, m.nv), float("nan"), dtype=getattr(torch, np.dtype(dtype).name), device="cuda")
        view = big[::2]
        assert id_(dq, dqd, dqdd, out=view) is view
        h = big.cpu().numpy()
        _close(h[::2], sd.inverse_dynamics(m, q, qd, qdd, backend="serial"), dtype, "strided out")
        assert np.isnan(h[1::2]).all()


@pytest.mark.parametrize("dtype", DTYPES)
def test_mass_matrix_default_result_is_entry_major(lib, dtype):
    """Without out=, M of a batch of torch / CuPy arrays is a (B, nv, nv) view of
    entry-major memory (the kernel's coalesced layout); it reads as any array, and
    its row-major copy equals the serial reference."""
    if lib.name == "jax":
        pytest.skip("JAX arrays have no strides: M comes back row-major")
    m = sd.load_model("iiwa")
    B, nv = 129, m.nv
    (q,) = states(m, B, dtype, seed=11)[:1]
    M = sd.mass_matrix(m, lib.dev(q))
    item = np.dtype(dtype).itemsize
    strides = tuple(s * item for s in M.stride()) if lib.name == "torch" else M.strides
    assert M.shape == (B, nv, nv) and strides == (item, nv * B * item, B * item)
    ref = sd.mass_matrix(m, q, backend="serial")
    _close(lib.host(M), ref, dtype, "entry-major M")
    Mc = M.contiguous() if lib.name == "torch" else lib.dev(lib.host(M))
    _close(lib.host(Mc @ Mc[:, :, :1]), ref @ ref[:, :, :1], dtype, "matmul of entry-major M")


def test_strided_device_inputs(lib):
    """Transposed (soa) and sliced device inputs reach the kernels through their strides."""
    if lib.name == "jax":
        pytest.skip("JAX exports its arrays contiguous")
    m = sd.load_model("hyq")
    q, qd, qdd, _ = states(m, 64, np.float64, seed=9)
    ref = sd.inverse_dynamics(m, q, qd, qdd, backend="serial")
    qT = lib.dev(np.ascontiguousarray(q.T)).T  # (B, nv) view of an (nv, B) array: BatchView::soa
    qd2 = lib.dev(np.repeat(qd, 2, axis=0))[::2]  # every other row
    got = sd.inverse_dynamics(m, qT, qd2, lib.dev(qdd))
    _close(lib.host(got), ref, np.float64, "strided device inputs")


def test_torch_side_stream_no_sync():
    """Work queued on a torch side stream: the call returns before the GPU has run it
    (no synchronisation: a long kernel queued first on the side stream is still running
    when the call returns), the result is right once the stream is waited for, and the
    default stream was not made to wait (torch's own event on it stays unrecorded)."""
    torch = _torch()
    if torch is None:
        pytest.skip("torch with CUDA is not importable here")
    m = sd.load_model("iiwa")
    B = 4096
    q, qd, qdd, _ = states(m, B, np.float32, seed=2)
    ref = sd.inverse_dynamics(m, q, qd, qdd, backend="serial")
    side = torch.cuda.Stream()
    e = sd.InverseDynamics(m, backend="cuda", max_batch=B, dtype=np.float32)
    dq, dqd, dqdd = (torch.from_numpy(a).cuda() for a in (q, qd, qdd))
    e(dq, dqd, dqdd)  # first launch (module loading) outside the measured call
    torch.cuda.synchronize()
    out3 = torch.full_like(dq, float("nan"))
    torch.cuda.synchronize()
    with torch.cuda.stream(side):
        torch.cuda._sleep(200_000_000)  # ~0.1 s of GPU time queued ahead on the side stream
        out = e(dq, dqd, dqdd)  # torch's current stream: side
        e(dq, dqd, dqdd, out=out3)  # the engines' short path (all torch, out=): side too
        done_event = torch.cuda.Event()
        done_event.record(side)
    assert not done_event.query(), "the call waited for the side stream's work"
    assert torch.cuda.default_stream().query(), "the default stream was made to wait for the side stream"
    side.synchronize()
    _close(out.cpu().numpy(), ref, np.float32, "side stream")
    _close(out3.cpu().numpy(), ref, np.float32, "side stream, out=")
    # stream= names the stream explicitly, from outside a stream context
    out2 = torch.empty_like(dq)
    s2 = torch.cuda.Stream()
    e(dq, dqd, dqdd, out=out2, stream=s2)
    s2.synchronize()
    _close(out2.cpu().numpy(), ref, np.float32, "stream=")


def test_cupy_stream():
    cupy = _cupy()
    if cupy is None:
        pytest.skip("CuPy with a CUDA GPU is not importable here")
    m = sd.load_model("iiwa")
    q, qd, qdd, _ = states(m, 500, np.float64, seed=4)
    s = cupy.cuda.Stream(non_blocking=True)
    with s:
        out = sd.inverse_dynamics(m, cupy.asarray(q), cupy.asarray(qd), cupy.asarray(qdd))
    s.synchronize()
    _close(cupy.asnumpy(out), sd.inverse_dynamics(m, q, qd, qdd, backend="serial"), np.float64, "cupy stream")


def test_device_errors(lib):
    m = sd.load_model("iiwa")
    q, qd, qdd, _ = states(m, 4, np.float32)
    g = lib.dev(q)
    with pytest.raises(sd.DeviceError, match="every array of a call is on one device"):
        sd.inverse_dynamics(m, g, qd, lib.dev(qdd))  # mixed host and device
    with pytest.raises(sd.DeviceError, match="backend 'openmp'|backend 'serial'"):
        sd.inverse_dynamics(m, g, lib.dev(qd), lib.dev(qdd), backend="openmp")
    with pytest.raises(sd.ShapeError, match="nv = 7"):
        sd.inverse_dynamics(m, lib.dev(q[:, :6]), lib.dev(qd[:, :6]), lib.dev(qdd[:, :6]))
    with pytest.raises(sd.DTypeError, match="float64"):
        sd.inverse_dynamics(m, g, lib.dev(qd.astype(np.float64)), lib.dev(qdd))
    e = sd.InverseDynamics(m, backend="cuda", max_batch=2, dtype=np.float32)
    with pytest.raises(sd.ShapeError, match="max_batch = 2"):
        e(g, lib.dev(qd), lib.dev(qdd))
    if lib.empty is None:
        with pytest.raises(sd.ShapeError, match="immutable"):
            e(g[:2], lib.dev(qd[:2]), lib.dev(qdd[:2]), out=lib.dev(q[:2]))


def test_batch_beyond_device_memory():
    """An engine whose buffers cannot fit in device memory: BackendError naming the bytes."""
    m = sd.load_model("iiwa")
    with pytest.raises(sd.BackendError, match="bytes|GiB|memory"):
        sd.InverseDynamics(m, backend="cuda", max_batch=10**9, dtype=np.float64)  # 10**9 x 7 DoF x 10 x 8 B: 560 GB


def test_forward_dynamics_failure_on_device(lib, tmp_path):
    """A zero pivot on the device: not raised at call time (that would need a wait), read
    by check() (the function API checks by default), the failed instances unwritten."""
    urdf = degenerate_urdf(tmp_path)
    m = sd.load_model(str(urdf), allow_nonphysical_inertia=True)
    q = np.zeros((3, 1))
    with pytest.raises(sd.ForwardDynamicsError, match="instance 0: articulated inertia pivot at DoF 0"):
        sd.forward_dynamics(m, lib.dev(q), lib.dev(q), lib.dev(q))
    if lib.name == "jax":
        return
    fd = sd.ForwardDynamics(m, backend="cuda", max_batch=3)
    fd(lib.dev(q), lib.dev(q), lib.dev(q))  # queued, nothing raised yet
    with pytest.raises(sd.ForwardDynamicsError) as e:
        fd.check()
    assert e.value.status.failed == 3
    assert list(lib.host(fd.failed_dof)) == [0, 0, 0]
