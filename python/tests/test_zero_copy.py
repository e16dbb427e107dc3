"""Zero copy: results are written into out= (the returned array is out and shares its
memory), arrays reach the engines with their own strides (views give the same bits as
contiguous copies, and strided outs are written only where they point), and no input is
converted behind the caller's back (a dtype that differs is an error, not a cast)."""

import numpy as np
import pytest

import scandyn as sd
from conftest import DTYPES, states


@pytest.fixture(scope="module")
def iiwa():
    return sd.load_model("iiwa")


@pytest.mark.parametrize("dtype", DTYPES)
def test_out_is_written_in_place(iiwa, dtype):
    q, qd, qdd, tau = states(iiwa, 10, dtype)
    nv = iiwa.nv
    for fn, args, shape in [
        (sd.inverse_dynamics, (q, qd, qdd), (10, nv)),
        (sd.bias_forces, (q, qd), (10, nv)),
        (sd.forward_dynamics, (q, qd, tau), (10, nv)),
        (sd.mass_matrix, (q,), (10, nv, nv)),
    ]:
        out = np.full(shape, np.nan, dtype=dtype)
        r = fn(iiwa, *args, out=out)
        assert r is out and np.shares_memory(r, out)
        np.testing.assert_array_equal(out, fn(iiwa, *args))


def test_engine_call_writes_out(iiwa):
    q, qd, qdd, tau = states(iiwa, 4, np.float32)
    e = sd.ForwardDynamics(iiwa, max_batch=4, dtype=np.float32)
    out = np.full((4, iiwa.nv), np.nan, np.float32)
    addr = out.__array_interface__["data"][0]
    for _ in range(3):
        r = e(q, qd, tau, out=out)
        assert r is out and r.__array_interface__["data"][0] == addr
    assert np.isfinite(out).all()


@pytest.mark.parametrize("dtype", DTYPES)
def test_strided_inputs(iiwa, dtype):
    """Every-other-row views, Fortran-order arrays, transposed (nv, B) storage,
    negative strides, broadcast rows: the same bits as C-contiguous copies."""
    q, qd, qdd, tau = states(iiwa, 12, dtype)
    ref = sd.inverse_dynamics(iiwa, q, qd, qdd, backend="serial")
    big = np.zeros((24, iiwa.nv + 3), dtype)
    big[::2, 1:iiwa.nv + 1] = q
    q_rows = big[::2, 1:iiwa.nv + 1]  # strides (2 * (nv+3), 1) elements
    assert not q_rows.flags.c_contiguous
    np.testing.assert_array_equal(sd.inverse_dynamics(iiwa, q_rows, qd, qdd, backend="serial"), ref)
    qf = np.asfortranarray(q)
    np.testing.assert_array_equal(sd.inverse_dynamics(iiwa, qf, qd, qdd, backend="serial"), ref)
    q_soa = np.ascontiguousarray(q.T).T  # scandyn's native layout: the instance innermost
    np.testing.assert_array_equal(sd.inverse_dynamics(iiwa, q_soa, qd, qdd, backend="serial"), ref)
    qrev = q[::-1].copy()[::-1]  # negative batch stride
    np.testing.assert_array_equal(sd.inverse_dynamics(iiwa, qrev, qd, qdd, backend="serial"), ref)
    # a broadcast (stride 0) row: every instance reads the same memory
    b = np.broadcast_to(q[3], q.shape)
    assert b.strides[0] == 0 and not b.flags.writeable
    r = sd.inverse_dynamics(iiwa, b, np.broadcast_to(qd[3], q.shape), np.broadcast_to(qdd[3], q.shape),
                            backend="serial")
    np.testing.assert_array_equal(r, np.broadcast_to(ref[3], q.shape))
    # read-only inputs
    q_ro = q.copy()
    q_ro.flags.writeable = False
    np.testing.assert_array_equal(sd.inverse_dynamics(iiwa, q_ro, qd, qdd, backend="serial"), ref)


@pytest.mark.parametrize("dtype", DTYPES)
def test_strided_out(iiwa, dtype):
    q, qd, qdd, tau = states(iiwa, 6, dtype)
    nv = iiwa.nv
    ref = sd.forward_dynamics(iiwa, q, qd, tau, backend="serial")
    big = np.full((12, nv + 2), np.nan, dtype)
    view = big[1::2, 2:]  # every other row, offset columns
    r = sd.forward_dynamics(iiwa, q, qd, tau, out=view, backend="serial")
    assert r is view and np.shares_memory(r, big)
    np.testing.assert_array_equal(view, ref)
    # nothing else was touched
    mask = np.ones(big.shape, bool)
    mask[1::2, 2:] = False
    assert np.isnan(big[mask]).all()
    # a transposed out: (nv, B) storage seen as (B, nv)
    t = np.full((nv, 6), np.nan, dtype)
    sd.forward_dynamics(iiwa, q, qd, tau, out=t.T, backend="serial")
    np.testing.assert_array_equal(t.T, ref)


def test_mass_matrix_out_slice(iiwa):
    q, *_ = states(iiwa, 5, np.float64)
    nv = iiwa.nv
    big = np.full((10, nv, nv), np.nan)
    r = sd.mass_matrix(iiwa, q, out=big[::2])
    assert np.shares_memory(r, big)
    np.testing.assert_array_equal(big[::2], sd.mass_matrix(iiwa, q))
    assert np.isnan(big[1::2]).all()
    # one state: (nv, nv)
    one = np.full((nv, nv), np.nan)
    sd.mass_matrix(iiwa, q[2], out=one)
    np.testing.assert_array_equal(one, big[4])


def test_no_implicit_conversion(iiwa):
    """A float64 engine given float32 (or int) data raises instead of casting: the
    binding never asks for a converted copy."""
    q, qd, qdd, _ = states(iiwa, 3, np.float64)
    e = sd.InverseDynamics(iiwa, max_batch=3, dtype=np.float64)
    with pytest.raises(sd.DTypeError):
        e(q.astype(np.float32), qd, qdd)
    with pytest.raises(sd.DTypeError):
        e(q.astype(np.int64), qd, qdd)


def test_torch_cpu_tensors(iiwa):
    torch = pytest.importorskip("torch", reason="torch is not installed (not needed in CI)")
    q, qd, qdd, _ = states(iiwa, 4, np.float32)
    tq, tqd, tqdd = (torch.from_numpy(a) for a in (q, qd, qdd))
    r = sd.inverse_dynamics(iiwa, tq, tqd, tqdd)
    assert isinstance(r, torch.Tensor) and r.dtype == torch.float32
    np.testing.assert_array_equal(r.numpy(), sd.inverse_dynamics(iiwa, q, qd, qdd))
    out = torch.empty(4, iiwa.nv)
    assert sd.inverse_dynamics(iiwa, tq, tqd, tqdd, out=out) is out


def test_engine_calls_short_path(iiwa):
    """The engines' short path (arrays and out= all torch tensors, or all NumPy arrays):
    the same bits as the general path (lists, out=None), tensors that require grad read
    as they are, torch subclasses (Parameter), mixed torch / NumPy host arrays, and its
    errors (read-only out, wrong shapes) as the general path's."""
    torch = pytest.importorskip("torch", reason="torch is not installed (not needed in CI)")
    q, qd, qdd, tau = states(iiwa, 5, np.float32)
    ref = {
        "id": sd.InverseDynamics(iiwa, backend="serial", max_batch=5, dtype=np.float32)(q.tolist(), qd, qdd),
        "bias": sd.BiasForces(iiwa, backend="serial", max_batch=5, dtype=np.float32)(q.tolist(), qd),
        "mass": sd.MassMatrix(iiwa, backend="serial", max_batch=5, dtype=np.float32)(q.tolist()),
        "fd": sd.ForwardDynamics(iiwa, backend="serial", max_batch=5, dtype=np.float32)(q.tolist(), qd, tau),
    }
    engines = {
        "id": (sd.InverseDynamics, (q, qd, qdd)),
        "bias": (sd.BiasForces, (q, qd)),
        "mass": (sd.MassMatrix, (q,)),
        "fd": (sd.ForwardDynamics, (q, qd, tau)),
    }
    for name, (cls, ins) in engines.items():
        e = cls(iiwa, backend="serial", max_batch=5, dtype=np.float32)
        shape = ref[name].shape
        out = np.full(shape, np.nan, np.float32)
        assert e(*ins, out=out) is out
        np.testing.assert_array_equal(out, ref[name])
        t_ins = [torch.from_numpy(a).clone().requires_grad_(True) for a in ins]
        t_ins[0] = torch.nn.Parameter(t_ins[0].detach().clone())
        t_out = torch.full(shape, float("nan"))
        assert e(*t_ins, out=t_out) is t_out
        np.testing.assert_array_equal(t_out.numpy(), ref[name])
        mixed = [torch.from_numpy(a) if k % 2 else a for k, a in enumerate(ins)]
        t_out.fill_(float("nan"))
        e(*mixed, out=t_out)
        np.testing.assert_array_equal(t_out.numpy(), ref[name])
        ro = np.empty(shape, np.float32)
        ro.flags.writeable = False
        with pytest.raises(sd.ShapeError, match="read-only"):
            e(*ins, out=ro)
        with pytest.raises(sd.ShapeError, match="out has shape"):
            e(*ins, out=torch.empty((4,) + shape[1:]))
        with pytest.raises(sd.DTypeError, match="dtype"):
            e(*ins, out=torch.empty(shape, dtype=torch.float64))
