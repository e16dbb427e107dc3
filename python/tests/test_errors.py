"""Every bad input raises a scandyn.Error subclass (also a ValueError / TypeError /
RuntimeError) with the library's message; nothing is computed, copied or crashed."""

import numpy as np
import pytest

import scandyn as sd
from conftest import states, degenerate_urdf


@pytest.fixture(scope="module")
def iiwa():
    return sd.load_model("iiwa")


def test_wrong_nv(iiwa):
    q, qd, qdd, _ = states(iiwa, 3, np.float64)
    with pytest.raises(sd.ShapeError, match=r"q has shape \(3, 6\).*nv = 7") as e:
        sd.inverse_dynamics(iiwa, q[:, :6], qd, qdd)
    assert isinstance(e.value, ValueError)
    with pytest.raises(sd.ShapeError, match="qdd"):
        sd.inverse_dynamics(iiwa, q, qd, qdd[:, :5])


def test_wrong_rank(iiwa):
    q = np.zeros((2, 3, 7))
    with pytest.raises(sd.ShapeError):
        sd.inverse_dynamics(iiwa, q, q, q)
    with pytest.raises(sd.ShapeError):
        sd.mass_matrix(iiwa, np.float64(1.0))


def test_leading_shapes_differ(iiwa):
    q, qd, qdd, _ = states(iiwa, 4, np.float64)
    with pytest.raises(sd.ShapeError, match="leading shape"):
        sd.inverse_dynamics(iiwa, q, qd[:3], qdd)
    with pytest.raises(sd.ShapeError, match="leading shape"):
        sd.bias_forces(iiwa, q, qd[0])


def test_wrong_dtype(iiwa):
    q = np.zeros((2, 7), np.int64)
    with pytest.raises(sd.DTypeError, match="int64") as e:
        sd.inverse_dynamics(iiwa, q, q, q)
    assert isinstance(e.value, TypeError)
    h = np.zeros((2, 7), np.float16)
    with pytest.raises(sd.DTypeError, match="float16"):
        sd.mass_matrix(iiwa, h)


def test_mixed_dtypes(iiwa):
    q, qd, qdd, tau = states(iiwa, 2, np.float64)
    with pytest.raises(sd.DTypeError, match="qd has dtype float32, expected float64"):
        sd.inverse_dynamics(iiwa, q, qd.astype(np.float32), qdd)
    with pytest.raises(sd.DTypeError, match="out"):
        sd.forward_dynamics(iiwa, q, qd, tau, out=np.empty((2, 7), np.float32))
    with pytest.raises(sd.DTypeError, match="fext"):
        sd.inverse_dynamics(iiwa, q, qd, qdd, fext=np.zeros((2, 7, 6), np.float32))


def test_bad_out(iiwa):
    q, qd, qdd, _ = states(iiwa, 4, np.float64)
    with pytest.raises(sd.ShapeError):
        sd.inverse_dynamics(iiwa, q, qd, qdd, out=np.empty((3, 7)))
    with pytest.raises(sd.ShapeError, match="overlapping"):  # broadcast: entries share memory
        sd.inverse_dynamics(iiwa, q, qd, qdd, out=np.lib.stride_tricks.as_strided(np.empty(7), (4, 7), (0, 8)))
    with pytest.raises(sd.ShapeError, match="shares memory with qdd"):
        sd.inverse_dynamics(iiwa, q, qd, qdd, out=qdd)
    ro = np.empty((4, 7))
    ro.flags.writeable = False
    with pytest.raises(sd.ShapeError, match="read-only"):
        sd.inverse_dynamics(iiwa, q, qd, qdd, out=ro)
    with pytest.raises(sd.DTypeError, match="out must be an array"):
        sd.inverse_dynamics(iiwa, q, qd, qdd, out=[0.0] * 7)
    with pytest.raises(sd.ShapeError, match="row-major"):
        sd.mass_matrix(iiwa, q, out=np.empty((4, 7, 8))[:, :, :7])  # padded rows
    with pytest.raises(sd.ShapeError, match=r"\(4, 7, 7\)"):
        sd.mass_matrix(iiwa, q, out=np.empty((4, 7)))


def test_bad_fext(iiwa):
    q, qd, qdd, _ = states(iiwa, 2, np.float64)
    with pytest.raises(sd.ShapeError, match=r"\(2, 7, 6\)"):
        sd.inverse_dynamics(iiwa, q, qd, qdd, fext=np.zeros((2, 7, 3)))
    with pytest.raises(sd.ShapeError, match="C-contiguous"):
        sd.inverse_dynamics(iiwa, q, qd, qdd, fext=np.zeros((2, 7, 12))[:, :, ::2])


def test_engine_max_batch(iiwa):
    q, qd, qdd, _ = states(iiwa, 5, np.float64)
    e = sd.InverseDynamics(iiwa, max_batch=4)
    with pytest.raises(sd.ShapeError, match="max_batch = 4"):
        e(q, qd, qdd)
    with pytest.raises(sd.ShapeError, match="max_batch"):
        sd.InverseDynamics(iiwa, max_batch=0)


def test_backend_names(iiwa):
    q, qd, qdd, _ = states(iiwa, 2, np.float64)
    with pytest.raises(sd.BackendError, match="gpu") as e:
        sd.inverse_dynamics(iiwa, q, qd, qdd, backend="gpu")
    assert isinstance(e.value, RuntimeError)
    with pytest.raises(sd.BackendError):
        sd.forward_dynamics(iiwa, q, qd, qdd, method="magic")
    with pytest.raises(sd.BackendError):
        sd.InverseDynamics(iiwa, strategy="sideways")
    with pytest.raises(sd.DTypeError):
        sd.InverseDynamics(iiwa, dtype=np.int32)
    with pytest.raises(TypeError):
        sd.inverse_dynamics("iiwa", q, qd, qdd)


@pytest.mark.skipif(sd.has_cuda, reason="this build has the CUDA backend")
def test_cuda_backend_not_built(iiwa):
    q, qd, qdd, _ = states(iiwa, 2, np.float64)
    with pytest.raises(sd.BackendError, match="cuda"):
        sd.inverse_dynamics(iiwa, q, qd, qdd, backend="cuda")


class _FakeCudaArray:
    """Stands in for a CuPy array / torch CUDA tensor: only the device protocols."""

    shape = (2, 7)
    dtype = np.dtype(np.float32)

    @property
    def __cuda_array_interface__(self):
        return {"shape": self.shape, "typestr": "<f4", "data": (0, False), "version": 3}


class _FakeDlpackDevice:
    shape = (2, 7)
    dtype = np.dtype(np.float32)

    def __dlpack_device__(self):
        return (2, 0)  # kDLCUDA, device 0

    def __dlpack__(self, stream=None):
        raise AssertionError("must not be imported")


def test_cuda_array_interface_only_refused(iiwa):
    """__cuda_array_interface__ names no device: such arrays are refused, never copied."""
    x = _FakeCudaArray()
    with pytest.raises(sd.DeviceError, match="__cuda_array_interface__"):
        sd.inverse_dynamics(iiwa, x, x, x)


def test_unallocatable_cuda_result_refused(iiwa):
    """A CUDA DLPack array of an unknown library: no result can be allocated for it (and in
    a build without CUDA the backend is missing); an error, and the array is never read."""
    x = _FakeDlpackDevice()
    with pytest.raises(sd.Error):
        sd.inverse_dynamics(iiwa, x, x, x)


def test_forward_dynamics_failure(tmp_path):
    """A link whose inertia about its joint axis is zero: the articulated-inertia pivot is
    0, and forward dynamics raises with the library's BatchStatus message."""
    urdf = degenerate_urdf(tmp_path)
    with pytest.raises(sd.ModelError):
        sd.load_model(str(urdf))
    m = sd.load_model(str(urdf), allow_nonphysical_inertia=True)
    q = np.zeros((3, 1))
    out = np.full((3, 1), 123.0)
    with pytest.raises(sd.ForwardDynamicsError) as e:
        sd.forward_dynamics(m, q, q, q, out=out)
    st = e.value.status
    assert isinstance(e.value, RuntimeError)
    assert not st.ok and st.failed == 3 and st.first_instance == 0 and st.first_dof == 0
    assert "instance 0: articulated inertia pivot at DoF 0 is not positive" in str(e.value)
    assert st.message in str(e.value)
    assert list(st.failed_dof) == [0, 0, 0]
    assert (out == 123.0).all()  # failed instances are left unwritten, never NaN
    fd = sd.ForwardDynamics(m, max_batch=3)
    with pytest.raises(sd.ForwardDynamicsError):
        fd(q, q, q)
    assert fd.last_status.failed == 3


def test_forward_dynamics_check():
    """The run-time check (fd_check): float32 jsi on chain:64 is 0.02..0.3 off on random
    states; with the check on it raises ForwardDynamicsError naming the estimate, with
    fallback_double every instance is recomputed in double (status.retried), with it off
    the unchecked result comes back."""
    m = sd.load_model("chain:64")
    rng = np.random.default_rng(3)
    q, qd, tau = (rng.uniform(-1, 1, (4, 64)).astype(np.float32) for _ in range(3))
    fd = sd.ForwardDynamics(m, max_batch=4, dtype=np.float32, method="jsi", fd_check="on")
    with pytest.raises(sd.ForwardDynamicsError) as e:
        fd(q, qd, tau)
    assert e.value.status.failed == 4
    assert "forward dynamics check: estimated error of qdd" in str(e.value)
    assert "above the threshold 0.0001" in str(e.value)
    fixed = sd.ForwardDynamics(m, max_batch=4, dtype=np.float32, method="jsi", fd_check="on",
                               fallback_double=True)
    a = fixed(q, qd, tau)
    assert fixed.last_status.ok and fixed.last_status.retried == 4
    ref = sd.ForwardDynamics(m, max_batch=4, method="aba", fd_check="off")(
        q.astype(np.float64), qd.astype(np.float64), tau.astype(np.float64))
    assert np.abs(a - ref).max() / max(1.0, np.abs(ref).max()) < 1e-6
    loose = sd.ForwardDynamics(m, max_batch=4, dtype=np.float32, method="jsi", fd_check="on", fd_check_tol=10)
    off = sd.ForwardDynamics(m, max_batch=4, dtype=np.float32, method="jsi", fd_check="off")
    assert (loose(q, qd, tau) == off(q, qd, tau)).all()
    with pytest.raises(sd.Error):
        sd.ForwardDynamics(m, max_batch=4, dtype=np.float32, fd_check="maybe")


def test_max_batch_range(iiwa):
    for bad in (0, -3, 2**31):
        with pytest.raises(sd.ShapeError, match="max_batch must be from 1 to 2147483647"):
            sd.InverseDynamics(iiwa, backend="serial", max_batch=bad)
