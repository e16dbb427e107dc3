"""Closed kinematic loops: loop closures declared beside a tree model and the forward
dynamics of the closed system (the library's ConstrainedForwardDynamics engine).

A loop file is JSON, ``{"loops": [{"type": "point" | "weld", "link_a": NAME, "point_a":
[x, y, z], "link_b": NAME, "point_b": [x, y, z]}, ...]}`` (points in each link's frame;
``point``: 3 equations, ``weld``: 6, 3 angular first); the generators ``fivebar``,
``fourbar`` and ``cloth:K:N`` carry their loops (:func:`generator_loops`). With the
loops' Jacobian J (m x nv) and gamma = Jdot qd, forward dynamics solves

    M qdd + h = tau + J^T lambda,   J qdd + gamma = 0

exactly (no stabilisation), with redundant rows handled (a planar loop closed by a 3D
point has a zero row): qdd is unique, lambda the minimum-norm solution (docs/loops.md).
"""
import json as _json
import os

import numpy as np

from . import _scandyn as _ext
from ._api import (ForwardDynamics, Model, _EngineBase, _cached, _call, _check_out, _empty, _finish, _handover,
                   _inputs, _lead_of, _where, _writable, _DIRECT_OUT, _reraise)


class Loops:
    """A loop set for one model (made by :func:`load_loops`, :func:`parse_loops` or
    :func:`generator_loops`): ``rows`` constraint equations (m), ``json`` its loop-file
    text, ``len()`` its loops."""

    __slots__ = ("model", "_l")

    def __init__(self, model, ext_loops):
        self.model, self._l = model, ext_loops

    rows = property(lambda self: self._l.rows, doc="m: 3 per point loop, 6 per weld")
    json = property(lambda self: self._l.json, doc="the loop file's text (JSON)")

    def __len__(self):
        return len(self._l)

    def __repr__(self):
        return f"scandyn.Loops(model={self.model.name!r}, loops={len(self)}, rows={self.rows})"


def _check_model(model):
    if not isinstance(model, Model):
        raise TypeError(f"model must be a scandyn.Model (scandyn.load_model), got {type(model).__name__}")


def load_loops(model, path):
    """The loops of a loop file (JSON, the schema above) for ``model``. Raises LoopError
    naming the file, the loop and the key (unknown link, a loop between a link and
    itself, malformed JSON)."""
    _check_model(model)
    return Loops(model, _ext.load_loops(model._m, os.fspath(path)))


def parse_loops(model, loops, source="<text>"):
    """The loops of a loop file's text, or of the same structure as a dict / list
    (``{"loops": [...]}`` or the list alone)."""
    _check_model(model)
    if not isinstance(loops, str):
        loops = _json.dumps(loops if isinstance(loops, dict) else {"loops": list(loops)})
        source = source if source != "<text>" else "<dict>"
    return Loops(model, _ext.parse_loops(model._m, loops, source))


def generator_loops(model):
    """The loops a generated model carries (``fivebar``, ``fourbar``, ``cloth:K:N``);
    empty for other models."""
    _check_model(model)
    return Loops(model, _ext.generator_loops(model._m))


class ConstrainedForwardDynamics(_EngineBase):
    """Forward dynamics of ``model`` closed by ``loops`` for up to max_batch instances:
    serial and OpenMP (dense per instance), CUDA (one thread per instance, models of up
    to 16 DoF with up to 12 constraint rows: the five-bar, the four-bar).

    ``engine(q, qd, tau)`` returns (qdd, lambda): (B, nv) and (B, m). An instance whose
    mass matrix is not positive definite raises ForwardDynamicsError (its outputs left
    unwritten). ``engine.residual(q, qd)`` returns (phi, J qd), (B, m) each: the loops'
    position residual and velocity residual. On CUDA arrays a call only queues the work;
    ``check()`` waits and raises as ForwardDynamics.check does."""

    _ext_class = _ext.ConstrainedForwardDynamics
    _names = ("q", "qd", "tau", "fext")

    def __init__(self, model, loops, backend="auto", max_batch=1, dtype=np.float64, threads=0, device=None):
        if not isinstance(loops, Loops):
            raise TypeError(f"loops must be a scandyn.Loops (scandyn.load_loops), got {type(loops).__name__}")
        super().__init__(model, backend, max_batch, dtype, device, loops=loops._l, threads=threads)
        self.loops = loops
        self.last_status = None
        self.failed_dof = None
        self._pending = None
        self._failed_buffers = {}

    rows = property(lambda self: self._e.rows, doc="m: the loops' constraint rows")
    method = "jsi"  # what fails is a pivot of the mass matrix's factor (status messages)

    # the CUDA calls' failed-DoF buffers and their check: ForwardDynamics' own
    _what = "closed-loop forward dynamics"
    _failed_buffer = ForwardDynamics._failed_buffer
    _failed_of = ForwardDynamics._failed_of
    _settle = ForwardDynamics._settle
    check = ForwardDynamics.check

    def _out(self, where, given, width):
        if given is None:
            return _empty(where, tuple(where.like.shape[:-1]) + (width,), self._dtype)
        _check_out(given)
        return given

    def __call__(self, q, qd, tau, fext=None, qdd_out=None, lambda_out=None, stream=None, failed_dof=None,
                 check=False):
        where, (q, qd, tau, fext), qdd_out, wq = self._prepare((q, qd, tau, fext), qdd_out, stream)
        lambda_out = self._out(where, lambda_out, self.rows)
        hand = _DIRECT_OUT.get(type(lambda_out))
        wl = hand(lambda_out) if hand is not None else _writable(lambda_out, where)
        failed, fd = self._failed_of(where, failed_dof)
        try:
            status = self._e.compute(q, qd, tau, wq, wl, fext, fd, where.stream or 0)
        except TypeError as e:
            _reraise(e)
        self._settle(status, where, failed, check)
        return qdd_out, lambda_out

    def residual(self, q, qd, phi=True, velocity=True, stream=None):
        """(phi, J qd) of (q, qd), (B, m) each (m,) for one state): the position and the
        velocity residual of the loops. Each of phi and velocity: True (allocate), an array
        to write, or False / None (skip: None in its place)."""
        (q, qd), _ = _inputs([("q", q), ("qd", qd)], self._dtype)
        where = _where(q, stream)
        lead = _lead_of(q)
        outs = []
        for given in (phi, velocity):
            if given is False or given is None:
                outs.append(None)
            elif given is True:
                outs.append(_empty(where, lead + (self.rows,), self._dtype))
            else:
                _check_out(given)
                outs.append(given)
        _call(self._e.residual, _handover(q, "q", where), _handover(qd, "qd", where),
              *[None if o is None else _writable(o, where) for o in outs], stream=where.stream or 0)
        _finish(where)
        return tuple(outs)


def _engine(model, loops, q, backend):
    if not isinstance(loops, Loops):
        raise TypeError(f"loops must be a scandyn.Loops (scandyn.load_loops), got {type(loops).__name__}")
    return _cached(ConstrainedForwardDynamics, id(loops._l), model, backend, q, loops=loops)


def constrained_forward_dynamics(model, loops, q, qd, tau, fext=None, backend="auto", stream=None, check=None):
    """(qdd, lambda) of the model closed by ``loops``: M qdd + h = tau + J^T lambda,
    J qdd + Jdot qd = 0, gravity included; q, qd, tau (B, nv) or (nv,). The engine is
    cached per model, loop set, backend and dtype. CUDA arrays: the check of the
    factorisations waits for the stream unless check=False."""
    (q, qd, tau, fext), _ = _inputs([("q", q), ("qd", qd), ("tau", tau), ("fext", fext)])
    engine = _engine(model, loops, q, backend)
    return engine(q, qd, tau, fext=fext, stream=stream, check=check is None or bool(check))


def loop_residual(model, loops, q, qd, backend="auto", stream=None):
    """(phi, J qd) of the loops at (q, qd): (B, m) each, or (m,) for one state."""
    (q, qd), _ = _inputs([("q", q), ("qd", qd)])
    return _engine(model, loops, q, backend).residual(q, qd, stream=stream)
