"""Kinematics from Python: sd.frame_placements, sd.frame_jacobians, sd.Kinematics.

Checked against the command line (the C++ serial engine, `scandyn eval --algo fk,jac`:
17 significant digits, so equal bit for bit), finite differences of the placements
(J qd is the frame's velocity), Pinocchio when importable (framesForwardKinematics,
getFrameJacobian), OpenMP against serial (bit-identical) and float32 against float64
(2e-5, positions in metres); plus shapes, out=, torch tensors and the errors. CUDA arrays:
test_cuda_kinematics.py."""

import csv
import os
import subprocess

import numpy as np
import pytest

import scandyn as sd
from conftest import DTYPES, MODELS
from test_errors import _FakeCudaArray, _FakeDlpackDevice


def random_q(model, B, dtype=np.float64, seed=0):
    return np.random.default_rng(seed).uniform(-2.5, 2.5, (B, model.nv)).astype(dtype)


@pytest.fixture(scope="module", params=MODELS)
def kmodel(request):
    return sd.load_model(request.param)


def test_frames_are_every_link(kmodel):
    frames = kmodel.frames
    assert len(frames) == len(set(frames)) >= kmodel.nv + 1
    assert frames[0] == kmodel.root_link
    assert set(kmodel.link_names) <= set(frames)


@pytest.mark.parametrize("dtype", DTYPES)
def test_shapes_and_out(kmodel, dtype):
    q = random_q(kmodel, 5, dtype)
    F = len(kmodel.frames)
    T = sd.frame_placements(kmodel, q)
    assert T.shape == (5, F, 4, 4) and T.dtype == dtype
    np.testing.assert_array_equal(T[..., 3, :], np.broadcast_to([0, 0, 0, 1], (5, F, 4)))
    P = sd.frame_placements(kmodel, q, frames=kmodel.frames[-1], quaternion=True)
    assert P.shape == (5, 1, 7)
    J = sd.frame_jacobians(kmodel, q, frames=[kmodel.frames[-1], kmodel.frames[0]])
    assert J.shape == (5, 2, 6, kmodel.nv)
    assert not J[:, 1].any()  # the root link does not move
    one = sd.frame_placements(kmodel, q[0])
    assert one.shape == (F, 4, 4)
    np.testing.assert_array_equal(one, T[0])
    out = np.full((5, F, 6, kmodel.nv), np.nan, dtype=dtype)
    got = sd.frame_jacobians(kmodel, q, out=out)
    assert got is out and np.isfinite(out).all()
    # a slice along the batch dimension of a C array is written in place
    big = np.full((10, F, 4, 4), np.nan, dtype=dtype)
    sd.frame_placements(kmodel, q, out=big[::2])
    np.testing.assert_array_equal(big[::2], T)
    assert np.isnan(big[1::2]).all()


def test_the_command_line_bit_for_bit(kmodel, cli, tmp_path):
    q = random_q(kmodel, 4, seed=3)
    names = kmodel.frames
    inp = tmp_path / "in.csv"
    with open(inp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([f"q_{i}" for i in range(kmodel.nv)])
        for row in q:
            w.writerow(["%.17g" % x for x in row])
    for ref in ("world", "local"):
        out = tmp_path / f"out_{ref}.csv"
        subprocess.run([cli, "eval", "--model", kmodel.source, "--states", str(inp), "--out", str(out),
                        "--algo", "fk,jac", "--reference", ref], check=True)
        with open(out) as fh:
            rows = list(csv.DictReader(fh))
        P = sd.frame_placements(kmodel, q, quaternion=True, backend="serial")
        J = sd.frame_jacobians(kmodel, q, reference=ref, backend="serial")
        for b, row in enumerate(rows):
            for k, f in enumerate(names):
                got = [float(row[f"fk_{f}_{e}"]) for e in ("px", "py", "pz", "qx", "qy", "qz", "qw")]
                np.testing.assert_array_equal(P[b, k], got)
                Jc = [[float(row[f"J_{f}_{r}_{j}"]) for j in range(kmodel.nv)] for r in range(6)]
                np.testing.assert_array_equal(J[b, k], Jc)


@pytest.mark.parametrize("reference", ["world", "local"])
def test_jacobian_is_the_derivative_of_the_placements(kmodel, reference):
    q = random_q(kmodel, 3, seed=5)
    qd = random_q(kmodel, 3, seed=6)
    h = 1e-6
    T = sd.frame_placements(kmodel, q)
    dT = (sd.frame_placements(kmodel, q + h * qd) - sd.frame_placements(kmodel, q - h * qd)) / (2 * h)
    R, dR = T[..., :3, :3], dT[..., :3, :3]
    W = dR @ np.swapaxes(R, -1, -2)  # [w]x in world axes
    w = 0.5 * np.stack([W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]], -1)
    v = dT[..., :3, 3]
    if reference == "local":
        Rt = np.swapaxes(R, -1, -2)
        w, v = (Rt @ w[..., None])[..., 0], (Rt @ v[..., None])[..., 0]
    J = sd.frame_jacobians(kmodel, q, reference=reference)
    got = np.einsum("bkrj,bj->bkr", J, qd)
    want = np.concatenate([w, v], -1)
    np.testing.assert_allclose(got, want, atol=1e-7 * max(1.0, np.abs(want).max()))


def test_backends_and_precisions(kmodel):
    q = random_q(kmodel, 40, seed=8)
    Ts, Js = sd.frame_placements(kmodel, q, backend="serial"), sd.frame_jacobians(kmodel, q, backend="serial")
    if sd.has_openmp:
        np.testing.assert_array_equal(sd.frame_placements(kmodel, q, backend="openmp"), Ts)
        np.testing.assert_array_equal(sd.frame_jacobians(kmodel, q, backend="openmp"), Js)
    qf = q.astype(np.float32)
    Tf, Jf = sd.frame_placements(kmodel, qf), sd.frame_jacobians(kmodel, qf)
    assert Tf.dtype == np.float32 and Jf.dtype == np.float32
    np.testing.assert_allclose(Tf, Ts, atol=2e-5 * max(1.0, np.abs(Ts).max()))
    np.testing.assert_allclose(Jf, Js, atol=2e-5 * max(1.0, np.abs(Js).max()))


def test_engine_both_outputs_in_one_call(kmodel):
    q = random_q(kmodel, 6, seed=9)
    e = sd.Kinematics(kmodel, frames=kmodel.frames[1:3], max_batch=6, reference="local", pose="quaternion")
    assert e.frames == kmodel.frames[1:3] and e.reference == "local" and e.pose == "quaternion"
    P, J = e(q)
    np.testing.assert_array_equal(P, sd.frame_placements(kmodel, q, frames=kmodel.frames[1:3], quaternion=True))
    np.testing.assert_array_equal(J, sd.frame_jacobians(kmodel, q, frames=kmodel.frames[1:3], reference="local"))
    assert e(q, jacobians=False)[1] is None


def test_pinocchio(kmodel):
    pin = pytest.importorskip("pinocchio")
    if not kmodel.source.endswith(".urdf"):
        pytest.skip("Pinocchio reads URDF files")
    pm = pin.buildModelFromUrdf(kmodel.source)
    pdata = pm.createData()
    q = random_q(kmodel, 3, seed=10)
    T = sd.frame_placements(kmodel, q)
    Jw = sd.frame_jacobians(kmodel, q)
    Jl = sd.frame_jacobians(kmodel, q, reference="local")
    swap = [3, 4, 5, 0, 1, 2]  # Pinocchio's rows are [linear; angular]
    for b in range(3):
        qp = np.concatenate([[np.cos(q[b, j.idx_v]), np.sin(q[b, j.idx_v])] if j.nq == 2 else [q[b, j.idx_v]]
                             for j in pm.joints[1:]])
        pin.framesForwardKinematics(pm, pdata, qp)
        pin.computeJointJacobians(pm, pdata, qp)
        for k, name in enumerate(kmodel.frames):
            fid = pm.getFrameId(name, pin.BODY)
            np.testing.assert_allclose(T[b, k], pdata.oMf[fid].homogeneous, atol=1e-12)
            for J, ref in ((Jw, pin.LOCAL_WORLD_ALIGNED), (Jl, pin.LOCAL)):
                Jp = np.asarray(pin.getFrameJacobian(pm, pdata, fid, ref)).reshape(6, kmodel.nv)[swap]
                np.testing.assert_allclose(J[b, k], Jp, atol=1e-12)


def test_torch_tensors():
    torch = pytest.importorskip("torch")
    m = sd.load_model("iiwa")
    q = torch.rand(4, m.nv, dtype=torch.float64)
    T = sd.frame_placements(m, q)
    assert isinstance(T, torch.Tensor) and T.shape == (4, len(m.frames), 4, 4)
    np.testing.assert_array_equal(T.numpy(), sd.frame_placements(m, q.numpy()))


def test_errors():
    m = sd.load_model("iiwa")
    q = np.zeros((2, m.nv))
    with pytest.raises(sd.ModelError, match="no frame 'tool'.*iiwa_link_7"):
        sd.frame_placements(m, q, frames=["tool"])
    with pytest.raises(sd.ShapeError):
        sd.frame_placements(m, np.zeros((2, m.nv + 1)))
    with pytest.raises(sd.ShapeError):
        sd.frame_jacobians(m, q, out=np.zeros((2, len(m.frames), 6, m.nv + 1)))
    with pytest.raises(sd.DTypeError):
        sd.frame_jacobians(m, q, out=np.zeros((2, len(m.frames), 6, m.nv), dtype=np.float32))
    with pytest.raises(ValueError, match="reference"):
        sd.frame_jacobians(m, q, reference="body")
    with pytest.raises(sd.ShapeError, match="max_batch"):
        sd.Kinematics(m, max_batch=1)(q)


def test_output_overlaps():
    """Outputs that share memory with q, with each other or within themselves: ShapeError
    naming them (the engines read q while writing, threads write entries independently)."""
    m = sd.load_model("iiwa")
    F = len(m.frames)
    e = sd.Kinematics(m, max_batch=2)
    buf = np.zeros(2 * F * (16 + 6 * m.nv))
    q = buf[:2 * m.nv].reshape(2, m.nv)
    with pytest.raises(sd.ShapeError, match="poses shares memory with q"):
        e(q, poses=buf[:2 * F * 16].reshape(2, F, 4, 4), jacobians=False)
    q = np.zeros((2, m.nv))
    P = buf[:2 * F * 16].reshape(2, F, 4, 4)
    with pytest.raises(sd.ShapeError, match="J shares memory with poses"):
        e(q, poses=P, jacobians=buf[2 * F * 16 - 8:2 * F * 16 - 8 + 2 * F * 6 * m.nv].reshape(2, F, 6, m.nv))
    one = np.zeros((F, 4, 4))
    both = np.lib.stride_tricks.as_strided(one, shape=(2, F, 4, 4), strides=(0,) + one.strides)
    with pytest.raises(sd.ShapeError, match="overlapping entries"):
        e(q, poses=both, jacobians=False)


def test_device_arrays_without_dlpack_refused():
    """Kinematics takes device arrays through the dynamics engines' path: an array with only
    __cuda_array_interface__ is refused (DeviceError), one of an unknown DLPack library
    raises (no result can be allocated for it; no CUDA backend in a CPU build), never read."""
    m = sd.load_model("iiwa")
    with pytest.raises(sd.DeviceError, match="__cuda_array_interface__"):
        sd.frame_placements(m, _FakeCudaArray())
    with pytest.raises(sd.Error):
        sd.frame_jacobians(m, _FakeDlpackDevice())
