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
from ._api import (_EngineBase, _cached, _call, _check_out, _empty, _finish, _handover, _inputs, _lead_of, _where,
                   _writable)

_POSES = {"matrix": (4, 4), "quaternion": (7,)}


class Kinematics(_EngineBase):
    """Poses and Jacobians of the frames named in ``frames`` (None: every frame, in
    ``Model.frames`` order) for up to max_batch instances. ``pose``: "matrix" (4 x 4
    homogeneous [R p; 0 0 0 1]) or "quaternion" (px, py, pz, qx, qy, qz, qw; w >= 0);
    ``reference``: "world" or "local" (the Jacobians' axes). As the dynamics engines: host
    arrays run compute() and return when done; CUDA arrays (backend="cuda", ``device``:
    the engine's CUDA device, default the current one) queue compute_async() on the
    caller's stream (``stream=``, else torch's or CuPy's current stream) and return at
    once, results in the same array library on the same device."""

    _ext_class = _ext.Kinematics
    cuda_max_dofs = _ext.Kinematics.cuda_max_dofs  # backend "cuda" takes models of up to this many DoF

    def __init__(self, model, frames=None, backend="auto", max_batch=1, dtype=np.float64, reference="world",
                 pose="matrix", threads=0, device=None):
        if isinstance(frames, str):
            frames = [frames]
        super().__init__(model, backend, max_batch, dtype, device, frames=None if frames is None else list(frames),
                         reference=reference, pose=pose, threads=threads)

    frames = property(lambda self: self._e.frames, doc="(F) the frames' names, in output order")
    reference = property(lambda self: self._e.reference)
    pose = property(lambda self: self._e.pose)

    def _out(self, where, lead, given, tail):
        """The output to write: given (True: a new array of q's kind on q's device, lead +
        (F,) + tail), or None when given is False or None (not computed)."""
        if given is False or given is None:
            return None
        if given is True:
            return _empty(where, lead + (len(self.frames),) + tail, self._dtype)
        _check_out(given)
        return given

    def __call__(self, q, poses=True, jacobians=True, stream=None):
        """(poses, J) of q ((B, nq) or (nq,)): poses (B, F, 4, 4) or (B, F, 7), J (B, F, 6,
        nv). Each of poses and jacobians is True (allocate), an array to write (out), or
        False / None (skip: None returned in its place). CUDA arrays: queued on ``stream``
        (default: the array library's current stream), no synchronisation (JAX results
        are handed back once computed, as for the dynamics engines)."""
        (q,), _ = _inputs([("q", q)], self._dtype)
        where = _where(q, stream)
        lead = _lead_of(q)
        P = self._out(where, lead, poses, _POSES[self.pose])
        J = self._out(where, lead, jacobians, (6, self.nv))
        _call(self._e.compute, _handover(q, "q", where), None if P is None else _writable(P, where),
              None if J is None else _writable(J, where), stream=where.stream or 0)
        _finish(where)
        return P, J

    def placements(self, q, out=None, stream=None):
        """Poses of q: (B, F, 4, 4) or (B, F, 7)."""
        return self(q, poses=True if out is None else out, jacobians=None, stream=stream)[0]

    def jacobians(self, q, out=None, stream=None):
        """Jacobians of q: (B, F, 6, nv)."""
        return self(q, poses=None, jacobians=True if out is None else out, stream=stream)[1]


def _names(frames):
    if frames is None:
        return None
    return (frames,) if isinstance(frames, str) else tuple(frames)


def frame_placements(model, q, frames=None, quaternion=False, backend="auto", out=None, stream=None):
    """World poses of the frames (names; None: every frame, ``model.frames``): (B, F, 4,
    4) homogeneous matrices, or with quaternion=True (B, F, 7) rows px, py, pz, qx, qy,
    qz, qw. q: (B, nq) or (nq,) (then (F, 4, 4) / (F, 7); nq = nv unless the model has a
    floating base or ball joints, their quaternions). backend="auto" follows q: CUDA
    arrays run on their device (queued on ``stream``, default the array library's current
    one), host arrays on OpenMP; the result is an array of q's library on q's device."""
    (q,), _ = _inputs([("q", q)])
    names = _names(frames)
    pose = "quaternion" if quaternion else "matrix"
    engine = _cached(Kinematics, (names, pose), model, backend, q, frames=names, pose=pose)
    return engine.placements(q, out=out, stream=stream)


def frame_jacobians(model, q, frames=None, reference="world", backend="auto", out=None, stream=None):
    """Frame Jacobians (B, F, 6, nv), rows [angular; linear], in world axes at each
    frame's origin (reference="world") or in the frame's axes ("local"). Devices and
    streams as frame_placements."""
    (q,), _ = _inputs([("q", q)])
    names = _names(frames)
    engine = _cached(Kinematics, (names, reference), model, backend, q, frames=names, reference=reference)
    return engine.jacobians(q, out=out, stream=stream)
