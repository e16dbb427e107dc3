"""Host arrays of other array libraries (JAX on the CPU, torch CPU tensors): the result
is an array of the same library, equal to the NumPy call's bits (the same engine)."""

import numpy as np
import pytest

import scandyn as sd
from conftest import states


def test_jax_cpu_arrays():
    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    m = sd.load_model("iiwa")
    q, qd, qdd, tau = states(m, 9, np.float32, seed=1)
    cpu = jax.devices("cpu")[0]
    j = [jax.device_put(a, cpu) for a in (q, qd, qdd, tau)]
    for fn, jargs, args in [(sd.inverse_dynamics, j[:3], (q, qd, qdd)), (sd.bias_forces, j[:2], (q, qd)),
                            (sd.mass_matrix, j[:1], (q,)), (sd.forward_dynamics, [j[0], j[1], j[3]], (q, qd, tau))]:
        got = fn(m, *jargs)
        assert isinstance(got, jax.Array), fn.__name__
        np.testing.assert_array_equal(np.asarray(got), fn(m, *args), err_msg=fn.__name__)
    with pytest.raises(sd.ShapeError, match="immutable"):
        sd.inverse_dynamics(m, *j[:3], out=jnp.zeros((9, 7), jnp.float32))


def test_torch_cpu_tensors():
    torch = pytest.importorskip("torch")
    m = sd.load_model("hyq")
    q, qd, qdd, _ = states(m, 9, np.float64, seed=1)
    got = sd.inverse_dynamics(m, *(torch.from_numpy(a) for a in (q, qd, qdd)))
    assert isinstance(got, torch.Tensor) and got.dtype == torch.float64
    np.testing.assert_array_equal(got.numpy(), sd.inverse_dynamics(m, q, qd, qdd))
    out = torch.empty(9, m.nv, dtype=torch.float64)
    assert sd.inverse_dynamics(m, *(torch.from_numpy(a) for a in (q, qd, qdd)), out=out) is out
