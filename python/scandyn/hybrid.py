"""Hybrid dynamics (Featherstone 2008, 9.2): for each DoF either its acceleration
(prescribed motion) or its force is given; the library's HybridDynamics engine computes
the rest, gravity included:

    tau_out = M(q) qdd_out + h(q, qd) (- J^T fext)   on every row,
    qdd_out[i] = qdd[i] at prescribed DoFs,  tau_out[i] = tau[i] at the others.

All DoFs prescribed is inverse dynamics, none is forward dynamics (bit-identical on the
CPU backends to the reference's rnea / aba orders of operations: docs/hybrid.md).
"""
import numpy as np

from . import _scandyn as _ext
from ._api import ForwardDynamics, _EngineBase, _cached, _check_out, _empty, _inputs, _writable, _DIRECT_OUT, _reraise


def _mask(model, prescribed):
    """The (nv,) 0/1 list of a prescribed set: a boolean mask of nv entries, or DoF
    indices (ints), or joint names (model.joint_names; 1-DoF joints)."""
    nv = model.nv
    p = list(prescribed) if not isinstance(prescribed, str) else [prescribed]
    arr = np.asarray(p)
    if arr.dtype == bool:
        if arr.shape != (nv,):
            raise ValueError(f"a boolean prescribed mask has {arr.size} entries, expected nv = {nv}")
        return [int(x) for x in arr]
    mask = [0] * nv
    names = model.joint_names
    for x in p:
        if isinstance(x, str):
            if x not in names:
                raise ValueError(f"prescribed joint {x!r} is not a joint of {model.name!r} (model.joint_names)")
            i = names.index(x)
        else:
            i = int(x)
            if not 0 <= i < nv:
                raise ValueError(f"prescribed DoF {i} is outside 0..{nv - 1}")
        mask[i] = 1
    return mask


class HybridDynamics(_EngineBase):
    """Hybrid dynamics with a fixed prescribed set (``prescribed``: DoF indices, joint
    names, or a boolean (nv,) mask) for up to max_batch instances: serial and OpenMP
    (the reference per instance), CUDA (one thread per instance, up to 64 DoF).

    ``engine(q, qd, qdd, tau)`` returns (qdd_out, tau_out), the full vectors: qdd is read
    at prescribed DoFs only, tau at the others. An instance whose articulated pivot (of a
    DoF whose force is given) is not positive and finite raises ForwardDynamicsError
    (``status`` names it). On CUDA arrays a call only queues the work; ``check()`` waits
    and raises as ForwardDynamics.check does (failed DoFs in ``failed_dof``)."""

    _ext_class = _ext.HybridDynamics
    _names = ("q", "qd", "qdd", "tau", "fext")

    def __init__(self, model, prescribed, backend="auto", max_batch=1, dtype=np.float64, threads=0, device=None):
        super().__init__(model, backend, max_batch, dtype, device, prescribed=_mask(model, prescribed),
                         threads=threads)
        self.last_status = None
        self.failed_dof = None
        self._pending = None
        self._failed_buffers = {}

    prescribed = property(lambda self: np.array(self._e.prescribed, dtype=bool), doc="(nv) the prescribed mask")
    method = "aba"  # the pivots that can fail are the articulated-body algorithm's (status messages)

    # the CUDA calls' failed-DoF buffers and their check: ForwardDynamics' own
    _what = "hybrid dynamics"
    _failed_buffer = ForwardDynamics._failed_buffer
    _failed_of = ForwardDynamics._failed_of
    _settle = ForwardDynamics._settle
    check = ForwardDynamics.check

    def __call__(self, q, qd, qdd, tau, fext=None, qdd_out=None, tau_out=None, stream=None, failed_dof=None,
                 check=False):
        where, (q, qd, qdd, tau, fext), qdd_out, wq = self._prepare((q, qd, qdd, tau, fext), qdd_out, stream)
        if tau_out is None:
            tau_out = _empty(where, tuple(where.like.shape[:-1]) + (self.nv,), self._dtype)
        else:
            _check_out(tau_out)
        hand = _DIRECT_OUT.get(type(tau_out))
        wt = hand(tau_out) if hand is not None else _writable(tau_out, where)
        failed, fd = self._failed_of(where, failed_dof)
        try:
            status = self._e.compute(q, qd, qdd, tau, wq, wt, fext, fd, where.stream or 0)
        except TypeError as e:
            _reraise(e)
        self._settle(status, where, failed, check)
        return qdd_out, tau_out


def hybrid_dynamics(model, q, qd, prescribed, qdd, tau, fext=None, backend="auto", stream=None, check=None):
    """(qdd_out, tau_out) of hybrid dynamics: qdd given at the ``prescribed`` DoFs (indices,
    joint names or a boolean (nv,) mask), tau at the others; q, qd, qdd, tau (B, nv) or
    (nv,). The engine is cached per model, backend, dtype and prescribed set. CUDA arrays:
    the check of the pivots waits for the stream unless check=False."""
    (q, qd, qdd, tau, fext), _ = _inputs([("q", q), ("qd", qd), ("qdd", qdd), ("tau", tau), ("fext", fext)])
    mask = tuple(_mask(model, prescribed))
    engine = _cached(HybridDynamics, mask, model, backend, q, prescribed=np.array(mask, dtype=bool))
    return engine(q, qd, qdd, tau, fext=fext, stream=stream, check=check is None or bool(check))
