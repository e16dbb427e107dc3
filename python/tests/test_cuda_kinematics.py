"""Kinematics on CUDA arrays (torch CUDA tensors, CuPy, JAX on a GPU): sd.frame_placements,
sd.frame_jacobians and sd.Kinematics run the CUDA kinematics engine's compute_async() on
the caller's stream, with no copy and no synchronisation, and return arrays of the same
library on the same device (out= written in place).

Every result is checked against the serial engine on host copies of the same q (within
test_cuda_arrays.TOL: the device's FMA and sin/cos differ from the host's), which is
itself checked against the command line, finite differences and Pinocchio
(test_kinematics.py). Each test skips with its reason where the CUDA build, a GPU or the
array library is missing (CI); on the GPU machine every test runs."""

import numpy as np
import pytest

import scandyn as sd
from conftest import DTYPES, MODELS
from test_cuda_arrays import TOL, Lib, _close, _torch, lib  # noqa: F401 (lib: the array-library fixture)

cuda_reason = sd.backend_unusable("cuda")
pytestmark = pytest.mark.skipif(bool(cuda_reason), reason=f"backend cuda: {cuda_reason}")


@pytest.fixture(scope="module", params=MODELS)
def kmodel(request):
    return sd.load_model(request.param)


def random_q(model, B, dtype, seed=0):
    return np.random.default_rng(seed).uniform(-2.5, 2.5, (B, model.nv)).astype(dtype)


def _same_sign_quaternions(got, ref):
    """got's quaternions (the last 4 of each 7) with the sign of ref's: q and -q are one
    rotation, and where w is about 0 the device and the host may pick either (w >= 0
    decided on values that differ by rounding)."""
    got = got.copy()
    flip = np.sum(got[..., 3:] * ref[..., 3:], -1) < 0
    got[..., 3:][flip] *= -1
    return got


@pytest.mark.parametrize("dtype", DTYPES)
def test_function_api_on_device(kmodel, lib, dtype):
    q = random_q(kmodel, 37, dtype, seed=3)
    dq = lib.dev(q)
    F = len(kmodel.frames)
    for quaternion, tail in ((False, (4, 4)), (True, (7,))):
        ref = sd.frame_placements(kmodel, q, quaternion=quaternion, backend="serial")
        got = sd.frame_placements(kmodel, dq, quaternion=quaternion)  # backend="auto" follows the array
        assert lib.is_kind(got), f"frame_placements returned {type(got)} for {lib.name} inputs"
        assert got.shape == (37, F) + tail and np.dtype(str(got.dtype).replace("torch.", "")) == dtype
        h = lib.host(got)
        _close(_same_sign_quaternions(h, ref) if quaternion else h, ref, dtype, f"{lib.name} placements")
    for reference in ("world", "local"):
        ref = sd.frame_jacobians(kmodel, q, reference=reference, backend="serial")
        got = sd.frame_jacobians(kmodel, dq, reference=reference)
        assert lib.is_kind(got) and got.shape == (37, F, 6, kmodel.nv)
        _close(lib.host(got), ref, dtype, f"{lib.name} jacobians {reference}")
    # named frames, and one state: (nv,) in, (F', 4, 4) out
    names = [kmodel.frames[-1], kmodel.frames[0]]
    one = sd.frame_placements(kmodel, lib.dev(q[5]), frames=names)
    assert one.shape == (2, 4, 4)
    _close(lib.host(one), sd.frame_placements(kmodel, q[5], frames=names, backend="serial"), dtype, "one state")


@pytest.mark.parametrize("dtype", DTYPES)
def test_engine_out_aliases_caller_memory(lib, dtype):
    """Both outputs written in place, at the same device addresses call after call; an
    output may be a slice along the batch dimension (every other instance)."""
    if lib.empty is None:
        pytest.skip("JAX arrays are immutable: out= is refused (a new array is returned)")
    m = sd.load_model("iiwa")
    B = 300
    frames = ["iiwa_link_7", "iiwa_link_3"]
    e = sd.Kinematics(m, frames=frames, backend="cuda", max_batch=B, dtype=dtype, pose="quaternion")
    assert e.backend == "cuda" and e.device >= 0
    P = lib.empty((B, 2, 7), dtype)
    J = lib.empty((B, 2, 6, m.nv), dtype)
    paddr, jaddr = lib.ptr(P), lib.ptr(J)
    for seed in range(3):
        q = random_q(m, B, dtype, seed)
        got_P, got_J = e(lib.dev(q), poses=P, jacobians=J)
        assert got_P is P and got_J is J and lib.ptr(P) == paddr and lib.ptr(J) == jaddr
        ref_P = sd.frame_placements(m, q, frames=frames, quaternion=True, backend="serial")
        _close(_same_sign_quaternions(lib.host(P), ref_P), ref_P, dtype, "poses out=")
        _close(lib.host(J), sd.frame_jacobians(m, q, frames=frames, backend="serial"), dtype, "J out=")
    # only one output: the other is None and nothing else is written
    assert e(lib.dev(q), poses=False, jacobians=J)[0] is None
    if lib.name == "torch":
        import torch

        big = torch.full((2 * B, 2, 6, m.nv), float("nan"), dtype=getattr(torch, np.dtype(dtype).name), device="cuda")
        view = big[::2]
        assert e.jacobians(lib.dev(q), out=view) is view
        h = big.cpu().numpy()
        _close(h[::2], sd.frame_jacobians(m, q, frames=frames, backend="serial"), dtype, "strided out")
        assert np.isnan(h[1::2]).all()


def test_strided_device_q(lib):
    """A transposed (nv, B) device array and a row slice reach the kernel through their strides."""
    if lib.name == "jax":
        pytest.skip("JAX exports its arrays contiguous")
    m = sd.load_model("hyq")
    q = random_q(m, 64, np.float64, seed=9)
    ref = sd.frame_jacobians(m, q, backend="serial")
    qT = lib.dev(np.ascontiguousarray(q.T)).T
    q2 = lib.dev(np.repeat(q, 2, axis=0))[::2]
    _close(lib.host(sd.frame_jacobians(m, qT)), ref, np.float64, "transposed q")
    _close(lib.host(sd.frame_jacobians(m, q2)), ref, np.float64, "sliced q")


def test_torch_side_stream_no_sync():
    """Queued on torch's current stream (a side stream) without waiting: a long kernel queued
    ahead on that stream is still running when the call returns, the default stream was not
    made to wait, and the result is right once the stream is done; stream= names a stream."""
    torch = _torch()
    if torch is None:
        pytest.skip("torch with CUDA is not importable here")
    m = sd.load_model("iiwa")
    B = 4096
    q = random_q(m, B, np.float32, seed=2)
    ref = sd.frame_placements(m, q, backend="serial")
    e = sd.Kinematics(m, backend="cuda", max_batch=B, dtype=np.float32)
    dq = torch.from_numpy(q).cuda()
    e.placements(dq)  # first launch (module loading) outside the measured call
    torch.cuda.synchronize()
    side = torch.cuda.Stream()
    with torch.cuda.stream(side):
        torch.cuda._sleep(200_000_000)  # ~0.1 s of GPU time queued ahead on the side stream
        P, J = e(dq)
        done = torch.cuda.Event()
        done.record(side)
    assert not done.query(), "the call waited for the side stream's work"
    assert torch.cuda.default_stream().query(), "the default stream was made to wait for the side stream"
    side.synchronize()
    _close(P.cpu().numpy(), ref, np.float32, "side stream poses")
    _close(J.cpu().numpy(), sd.frame_jacobians(m, q, backend="serial"), np.float32, "side stream J")
    s2 = torch.cuda.Stream()
    out = torch.empty_like(P)
    assert sd.frame_placements(m, dq, out=out, stream=s2) is out
    s2.synchronize()
    _close(out.cpu().numpy(), ref, np.float32, "stream=")


def test_cupy_stream():
    l = Lib("cupy")
    if not l.ok:
        pytest.skip("CuPy with a CUDA GPU is not importable here")
    import cupy

    m = sd.load_model("iiwa")
    q = random_q(m, 500, np.float64, seed=4)
    s = cupy.cuda.Stream(non_blocking=True)
    with s:
        J = sd.frame_jacobians(m, cupy.asarray(q))
    s.synchronize()
    _close(cupy.asnumpy(J), sd.frame_jacobians(m, q, backend="serial"), np.float64, "cupy stream")


def test_device_errors(lib):
    m = sd.load_model("iiwa")
    F = len(m.frames)
    q = random_q(m, 4, np.float32)
    g = lib.dev(q)
    with pytest.raises(sd.DeviceError, match="backend 'openmp'|backend 'serial'"):
        sd.frame_placements(m, g, backend="openmp")
    with pytest.raises(sd.ShapeError, match="nv = 7"):
        sd.frame_jacobians(m, lib.dev(q[:, :6]))
    e = sd.Kinematics(m, backend="cuda", max_batch=2, dtype=np.float32)
    with pytest.raises(sd.ShapeError, match="max_batch = 2"):
        e(g)
    with pytest.raises(sd.DTypeError, match="float32"):
        e(lib.dev(q[:2].astype(np.float64)))
    if lib.empty is None:
        with pytest.raises(sd.ShapeError, match="immutable"):
            e.placements(g[:2], out=lib.dev(np.zeros((2, F, 4, 4), np.float32)))
        return
    with pytest.raises(sd.DeviceError, match="every array of a call is on one device"):
        sd.frame_placements(m, g, out=np.zeros((4, F, 4, 4), np.float32))  # device q, host out
    with pytest.raises(sd.DeviceError, match="every array of a call is on one device"):
        sd.frame_placements(m, q, out=lib.empty((4, F, 4, 4), np.float32))  # host q, device out
    with pytest.raises(sd.ShapeError, match=r"expected \(4, %d, 6, 7\)" % F):
        sd.frame_jacobians(m, g, out=lib.empty((4, F, 6, 6), np.float32))
    with pytest.raises(sd.DTypeError, match="float32"):
        sd.frame_jacobians(m, g, out=lib.empty((4, F, 6, 7), np.float64))
