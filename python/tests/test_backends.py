"""Backends and devices: the CUDA backend with host arrays (the engines' staged
compute(), as `scandyn eval --backend cuda`) against the serial reference. The device
path (CUDA arrays) is test_cuda_arrays.py's. Each skips with its reason where the GPU
or the CUDA build is missing (CI)."""

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
