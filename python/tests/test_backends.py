"""Backends and devices: the CUDA backend with host arrays (the engines' staged
compute(), as `scandyn eval --backend cuda`) against the serial reference, and arrays
on a GPU refused with DeviceError (the device path is not implemented yet) for every
GPU array library that is importable. Each skips with its reason where the GPU, the
CUDA build or the library is missing (CI)."""

import numpy as np
import pytest

import scandyn as sd
from conftest import DTYPES, states

cuda_reason = sd.backend_unusable("cuda")


def test_backend_unusable():
    assert sd.backend_unusable("serial") == ""
    assert (sd.backend_unusable("openmp") == "") == sd.has_openmp
    assert (sd.backend_unusable("cuda") == "") <= sd.has_cuda
    with pytest.raises(sd.BackendError):
        sd.backend_unusable("tpu")


@pytest.mark.skipif(bool(cuda_reason), reason=f"backend cuda: {cuda_reason}")
@pytest.mark.parametrize("dtype", DTYPES)
def test_cuda_backend_with_host_arrays(model, dtype):
    q, qd, qdd, tau = states(model, 33, dtype, seed=11)
    tol = 1e-9 if dtype == np.float64 else 2e-3
    for fn, args in [(sd.inverse_dynamics, (q, qd, qdd)), (sd.bias_forces, (q, qd)),
                     (sd.mass_matrix, (q,)), (sd.forward_dynamics, (q, qd, tau))]:
        ref = fn(model, *args, backend="serial")
        out = np.full_like(ref, np.nan)
        got = fn(model, *args, backend="cuda", out=out)
        assert got is out
        scale = 1.0 + np.abs(ref).max()
        np.testing.assert_allclose(got, ref, rtol=tol, atol=tol * scale, err_msg=fn.__name__)
    e = sd.InverseDynamics(model, backend="cuda", max_batch=33, dtype=dtype)
    assert e.backend == "cuda"


def _gpu_arrays():
    """(library, maker) for each importable GPU array library with a usable GPU."""
    out = []
    try:
        import torch

        if torch.cuda.is_available():
            out.append(("torch", lambda a: torch.from_numpy(a).cuda()))
    except ImportError:
        pass
    try:
        import cupy

        if cupy.cuda.runtime.getDeviceCount() > 0:
            out.append(("cupy", lambda a: cupy.asarray(a)))
    except Exception:  # ImportError, or CUDA errors without a GPU
        pass
    try:
        import jax

        gpus = [d for d in jax.devices() if d.platform == "gpu"]
        if gpus:
            out.append(("jax", lambda a: jax.device_put(a, gpus[0])))
    except Exception:
        pass
    return out


GPU_ARRAYS = _gpu_arrays()


@pytest.mark.skipif(not GPU_ARRAYS, reason="no GPU array library (torch, cupy, jax) with a GPU here")
@pytest.mark.parametrize("lib,make", GPU_ARRAYS, ids=[g[0] for g in GPU_ARRAYS])
def test_gpu_arrays_refused(lib, make):
    m = sd.load_model("iiwa")
    q, qd, qdd, _ = states(m, 4, np.float32)
    g = make(q)
    for backend in ("auto", "cuda", "openmp"):
        with pytest.raises(sd.DeviceError, match="backend 'cuda' from Python is not implemented yet"):
            sd.inverse_dynamics(m, g, make(qd), make(qdd), backend=backend)
    # mixed: host q, device qd
    with pytest.raises(sd.DeviceError):
        sd.inverse_dynamics(m, q, make(qd), qdd)
