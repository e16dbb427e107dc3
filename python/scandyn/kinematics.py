"""Kinematics: frame poses and frame Jacobians (the library's Kinematics engine).

Frames are the model's URDF links, fixed links included (``Model.frames`` lists their
names). Poses are in the world (base) frame; a Jacobian J (6 x nv) maps qd to the
frame's [angular; linear] velocity, the linear part that of the frame's origin, in
world axes (``reference="world"``, Pinocchio's LOCAL_WORLD_ALIGNED) or the frame's
own axes (``reference="local"``, Pinocchio's LOCAL). Pinocchio's rows are [linear;
angular]: ``J[..., [3, 4, 5, 0, 1, 2], :]`` is Pinocchio's Jacobian.
"""
import numpy as np

from . import _scandyn as _ext
from ._api import _EngineBase, _call, _cached, _check_out, _empty, _inputs, _lead_of, _where, _writable
from .errors import DeviceError

_HOST_ONLY = ("kinematics from Python takes host arrays (NumPy, torch CPU, JAX CPU); its CUDA-array path is "
              "not written yet: nothing is copied between devices")

_POSES = {"matrix": (4, 4), "quaternion": (7,)}


class Kinematics(_EngineBase):
    """Poses and Jacobians of the frames named in ``frames`` (None: every frame, in
    ``Model.frames`` order) for up to max_batch instances. ``pose``: "matrix" (4 x 4
    homogeneous [R p; 0 0 0 1]) or "quaternion" (px, py, pz, qx, qy, qz, qw; w >= 0);
    ``reference``: "world" or "local" (the Jacobians' axes)."""

    _ext_class = _ext.Kinematics

    def __init__(self, model, frames=None, backend="auto", max_batch=1, dtype=np.float64, reference="world",
                 pose="matrix", threads=0, device=None):
        if device is not None:
            raise DeviceError(f"device={device}: " + _HOST_ONLY)
        if isinstance(frames, str):
            frames = [frames]
        super().__init__(model, backend, max_batch, dtype, frames=None if frames is None else list(frames),
                         reference=reference, pose=pose, threads=threads)

    frames = property(lambda self: self._e.frames, doc="(F) the frames' names, in output order")
    reference = property(lambda self: self._e.reference)
    pose = property(lambda self: self._e.pose)

    def _out(self, q, out, tail):
        if out is None:
            return _empty(_where(q), _lead_of(q) + (len(self.frames),) + tail, self._dtype)
        _check_out(out)
        return out

    def __call__(self, q, poses=True, jacobians=True):
        """(poses, J) of q ((B, nq) or (nq,)): poses (B, F, 4, 4) or (B, F, 7), J (B, F, 6,
        nv). Each of poses and jacobians is True (allocate), an array to write (out), or
        False / None (skip: None returned in its place)."""
        (q,), _ = _inputs([("q", q)], self._dtype)
        where = _where(q)
        if where.cuda is not None:
            raise DeviceError("q is a CUDA array: " + _HOST_ONLY)
        P = self._out(q, None if poses is True else poses, _POSES[self.pose]) if poses is not False and poses is not None else None
        J = self._out(q, None if jacobians is True else jacobians, (6, self.nv)) \
            if jacobians is not False and jacobians is not None else None
        _call(self._e.compute, q, None if P is None else _writable(P, where),
              None if J is None else _writable(J, where))
        return P, J

    def placements(self, q, out=None):
        """Poses of q: (B, F, 4, 4) or (B, F, 7)."""
        return self(q, poses=True if out is None else out, jacobians=None)[0]

    def jacobians(self, q, out=None):
        """Jacobians of q: (B, F, 6, nv)."""
        return self(q, poses=None, jacobians=True if out is None else out)[1]


def _names(frames):
    if frames is None:
        return None
    return (frames,) if isinstance(frames, str) else tuple(frames)


def frame_placements(model, q, frames=None, quaternion=False, backend="auto", out=None):
    """World poses of the frames (names; None: every frame, ``model.frames``): (B, F, 4,
    4) homogeneous matrices, or with quaternion=True (B, F, 7) rows px, py, pz, qx, qy,
    qz, qw. q: (B, nq) or (nq,) (then (F, 4, 4) / (F, 7)); nq = nv unless the model has a
    floating base or ball joints (their quaternions)."""
    (q,), _ = _inputs([("q", q)])
    names = _names(frames)
    pose = "quaternion" if quaternion else "matrix"
    engine = _cached(Kinematics, (names, pose), model, backend, q, frames=names, pose=pose)
    return engine.placements(q, out=out)


def frame_jacobians(model, q, frames=None, reference="world", backend="auto", out=None):
    """Frame Jacobians (B, F, 6, nv), rows [angular; linear], in world axes at each
    frame's origin (reference="world") or in the frame's axes ("local")."""
    (q,), _ = _inputs([("q", q)])
    names = _names(frames)
    engine = _cached(Kinematics, (names, reference), model, backend, q, frames=names, reference=reference)
    return engine.jacobians(q, out=out)
