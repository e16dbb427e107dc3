"""Analytical derivatives and differentiable dynamics: torch.autograd.Function and
jax.custom_vjp wrappers whose backward passes run scandyn's derivatives.

    import scandyn as sd, scandyn.autograd as ad, torch
    m = sd.load_model("iiwa")
    q = torch.zeros(8, m.nv, dtype=torch.float64, requires_grad=True)
    tau = ad.torch_inverse_dynamics(m, q, qd, qdd)        # backward: dtau/dq, dtau/dqd, M
    qdd = ad.torch_forward_dynamics(m, q, qd, tau)        # backward: dqdd/dq, dqdd/dqd, M^-1
    step = ad.StepDerivatives({"model": "iiwa", "dt": 1e-3, "effects": {"gravity": True}})
    q1, qd1 = ad.torch_step(step, q, qd, tau)             # backward: the step's Jacobian
    qs, qds = ad.torch_rollout(step, q0, qd0, taus)       # (T, B, nv); backward: the rollout's adjoint
    loss(qs, qds).backward()

The derivatives (Carpentier & Mansard 2018; the step's and the rollout's adjoint) are
the library's (scandyn/engine.hpp: make_id_derivatives, make_fd_derivatives;
scandyn/sim/step_derivatives.hpp), float32 or float64, on the arrays' device: host
memory (NumPy, CPU tensors; serial or openmp) or a CUDA device (torch CUDA tensors,
CuPy, JAX on a GPU: the CUDA engines on the caller's stream, no copy; the same DLPack
hand-over as scandyn's other engines, _api.py). Results are arrays of the inputs' kind
on their device. The torch wrappers compute the values in forward and the derivatives
at the saved inputs in backward (first order: no double backward), on the tensors'
device. jax_* are the same through jax.custom_vjp and jax.pure_callback (host memory).
docs/derivatives.md.
"""

import json
import os
from collections import namedtuple

import numpy as np

from . import _scandyn as _ext
from . import _api
from ._api import (_Torch, ForwardDynamics, _EngineBase, _cached, _cuda_device, _empty, _entry_major, _finish,
                   _handover, _host_int32, _inputs, _kind, _lead_of, _reraise, _where, _writable, resolve_model_spec)
from .errors import BackendError, DeviceError, DTypeError


def _backend(backend):
    return _api._resolve_backend(backend)


def _matrices(engine, where, q, lead, count):
    """count (lead + (nv, nv)) results of an engine's call: entry-major views on a CUDA
    device (torch, CuPy: the kernels' coalesced layout, as the mass matrix's), else new
    row-major arrays of the inputs' kind."""
    nv, dtype = engine._nv, engine._dtype
    out = []
    for _ in range(count):
        m = _entry_major(q, nv, nv, dtype) if where.cuda is not None else None
        out.append(m if m is not None else _empty(where, tuple(lead) + (nv, nv), dtype))
    return out


def _tensors(engine, where, q, lead, count):
    """count (lead + (nv, nv, nv)) results of an engine's call, as _matrices: on a CUDA
    device entry-major views (T[b, i, j, k] at ((i * nv + j) * nv + k) * B + b; torch,
    CuPy with a batch dimension), else new row-major arrays of the inputs' kind."""
    nv, dtype = engine._nv, engine._dtype
    out = []
    for _ in range(count):
        t = None
        if where.cuda is not None and getattr(q, "ndim", 0) == 2:
            b = q.shape[0]
            if type(q).__module__.startswith("torch"):
                dtypes = _Torch.dtypes or _Torch.load().dtypes
                t = q.new_empty_strided((b, nv, nv, nv), (1, nv * nv * b, nv * b, b), dtype=dtypes[dtype])
            elif type(q).__module__.startswith("cupy"):
                import cupy

                with q.device:
                    t = cupy.empty((nv, nv, nv, b), dtype=dtype).transpose(3, 0, 1, 2)
        out.append(t if t is not None else _empty(where, tuple(lead) + (nv, nv, nv), dtype))
    return out


# ---- the derivative engines ---------------------------------------------------------


def _id_call(engine, inputs, stream, count, results):
    """An inverse-dynamics derivative engine's call on (q, qd, qdd): count results made
    by results (_matrices or _tensors), written by the engine's compute(); returns them."""
    where, host, _, _ = engine._prepare(inputs, None, stream)  # (its (B, nv) out unused)
    lead = tuple(where.like.shape[:-1])
    outs = results(engine, where, where.like, lead, count)
    try:
        engine._e.compute(*host, *(_writable(o, where) for o in outs), where.stream or 0)
    except TypeError as e:
        _reraise(e)
    _finish(where)
    return outs


class IdDerivatives(_EngineBase):
    """(dtau/dq, dtau/dqd, M) of tau = ID(q, qd, qdd) (gravity included) for up to
    max_batch instances: the library's make_id_derivatives. Host arrays run the
    engine's compute(); CUDA arrays (backend 'cuda', the engine's device) its
    compute_async() on the caller's stream (``stream=``, else torch's or CuPy's current
    one), no copy, no synchronisation (JAX: waited for). Results are arrays of the
    inputs' kind on their device, (B, nv, nv) each ((nv, nv) for one state); on a
    CUDA device torch and CuPy results are entry-major views (as MassMatrix's)."""

    _ext_class = _ext.IdDerivatives
    _names = ("q", "qd", "qdd")

    def __init__(self, model, backend="auto", max_batch=1, dtype=np.float64, threads=0, device=None):
        super().__init__(model, backend, max_batch, dtype, device, None, threads=threads)

    def __call__(self, q, qd, qdd, stream=None):
        return tuple(_id_call(self, (q, qd, qdd), stream, 3, _matrices))


IdSecondDerivativesResult = namedtuple("IdSecondDerivativesResult",
                                       ["d2tau_dq2", "d2tau_dqd2", "d2tau_dqdqd", "dM_dq"])
IdSecondDerivativesResult.__doc__ = (
    "The second derivatives of tau = ID(q, qd, qdd): four (B, nv, nv, nv) arrays ((nv, nv, nv) for one "
    "state), entry [..., i, j, k]: d2tau_dq2 = d^2 tau_i / dq_j dq_k, d2tau_dqd2 = d^2 tau_i / dqd_j dqd_k, "
    "d2tau_dqdqd = d^2 tau_i / dq_j dqd_k, dM_dq = d M_ij / dq_k.")


class IdSecondDerivatives(_EngineBase):
    """The second derivatives of tau = ID(q, qd, qdd) (gravity included) for up to
    max_batch instances: the library's make_id_second_derivatives (the analytical
    second-order recursion; models of 1-DoF joints, revolute or prismatic: floating
    bases and spherical joints raise BackendError; on 'cuda' up to 64 DoF).

    A call ``engine(q, qd, qdd)`` on (B, nv) arrays ((nv,) for one state) returns an
    IdSecondDerivativesResult (a named tuple) of four (B, nv, nv, nv) arrays ((nv, nv,
    nv) for one state), entry [b, i, j, k]:

    - ``d2tau_dq2``   = d^2 tau_i / dq_j dq_k   (symmetric in j, k)
    - ``d2tau_dqd2``  = d^2 tau_i / dqd_j dqd_k (symmetric in j, k; tau is quadratic in qd: a function of q only)
    - ``d2tau_dqdqd`` = d^2 tau_i / dq_j dqd_k
    - ``dM_dq``       = d M_ij / dq_k (= d^2 tau_i / dqdd_j dq_k)

    so each instance's tensor is the library's, entry (i, j, k) at (i * nv + j) * nv + k
    of a row-major block. Host arrays run the engine's compute() (serial, openmp, or
    cuda: copies in and out); CUDA arrays (backend 'cuda', the engine's device) its
    compute_async() on the caller's stream as IdDerivatives' (torch and CuPy results:
    entry-major views, T[b, i, j, k] at ((i * nv + j) * nv + k) * B + b). Results are
    arrays of the inputs' kind on their device, in the engine's dtype."""

    _ext_class = _ext.IdSecondDerivatives
    _names = ("q", "qd", "qdd")

    def __init__(self, model, backend="auto", max_batch=1, dtype=np.float64, threads=0, device=None):
        super().__init__(model, backend, max_batch, dtype, device, None, threads=threads)

    def __call__(self, q, qd, qdd, stream=None):
        return IdSecondDerivativesResult(*_id_call(self, (q, qd, qdd), stream, 4, _tensors))


class FdDerivatives(ForwardDynamics):
    """qdd and (dqdd/dq, dqdd/dqd, dqdd/dtau = M^-1) of qdd = FD(q, qd, tau) by the ABA:
    the library's make_fd_derivatives, on host or CUDA arrays as IdDerivatives. An
    instance whose pivot is not positive raises ForwardDynamicsError; on CUDA arrays
    the failed DoFs go to ``failed_dof`` and are read by ``check()`` (or ``check=True``),
    as ForwardDynamics'."""

    _ext_class = _ext.FdDerivatives
    _names = ("q", "qd", "tau")
    _what = "the forward-dynamics derivatives"

    def __init__(self, model, backend="auto", max_batch=1, dtype=np.float64, threads=0, device=None):
        _EngineBase.__init__(self, model, backend, max_batch, dtype, device, None, threads=threads)
        self.last_status = None
        self.failed_dof = None
        self._pending = None
        self._failed_buffers = {}

    def __call__(self, q, qd, tau, stream=None, failed_dof=None, check=False):
        where, (hq, hqd, htau), qdd, wqdd = _EngineBase._prepare(self, (q, qd, tau), None, stream)
        mats = _matrices(self, where, where.like, tuple(where.like.shape[:-1]), 3)
        failed, fd = self._failed_of(where, failed_dof)
        try:
            status = self._e.compute(hq, hqd, htau, wqdd, *(_writable(m, where) for m in mats), fd,
                                     where.stream or 0)
        except TypeError as e:
            _reraise(e)
        self._settle(status, where, failed, check)
        return (qdd,) + tuple(mats)


class FdDirectional(ForwardDynamics):
    """The directional derivatives of qdd = FD(q, qd, tau) (gravity included), O(nv) per
    instance, for models whose dense (nv, nv) derivatives do not fit (ropes of 10^5
    links): the library's make_fd_directional_derivatives.

    - ``jvp(q, qd, tau, dq, dqd, dtau) -> (qdd, dqdd)``, dqdd = dqdd/dq dq + dqdd/dqd dqd
      + M^-1 dtau;
    - ``vjp(q, qd, tau, w) -> (qdd, gq, gqd, gtau)``, gq = (dqdd/dq)^T w, gqd =
      (dqdd/dqd)^T w, gtau = M^-1 w.

    Every array (B, nv) (B <= max_batch instances) or (nv,) for one state, q (B, nq),
    results the same shape, of the inputs' kind (NumPy, or CPU torch tensors), in the
    engine's dtype. Host arrays only, on every backend: 'serial', 'openmp' ('auto'), or
    'cuda' (one device; the engine copies the host arrays to its device and back). CUDA
    arrays raise DeviceError. Models with a floating base or spherical joints (nq > nv)
    on serial and openmp by 'aba': dq and gq are tangents (nv) of local increments q (+)
    d = q exp(d) per joint, as fd_derivatives' q columns; cuda and 'parallel' refuse
    them (BackendError). ``method``: 'parallel' (the chunked scans, for unbranched chains
    of 1-DoF joints from a fixed base; the only one on cuda), 'aba' (aba_jvp / aba_vjp
    per instance, threads over instances; serial and openmp), 'auto' (parallel for such
    chains of 4096 links or more on the host, always on cuda; else aba); ``strategy``
    says which ran ('parallel' or 'aba_jvp'). An instance whose articulated pivot is not
    positive and finite raises ForwardDynamicsError (``status`` names it; its results
    are not meaningful); ``last_status`` is the last call's scandyn.Status."""

    _ext_class = _ext.FdDirectionalDerivatives
    _what = "the directional derivatives of forward dynamics"

    def __init__(self, model, backend="auto", max_batch=1, dtype=np.float64, threads=0, method="auto", device=None):
        _EngineBase.__init__(self, model, backend, max_batch, dtype, device, None, threads=threads, method=method)
        self.last_status = None
        self.failed_dof = None
        self._pending = None
        self._failed_buffers = {}

    method = property(lambda self: self._e.strategy, doc="'parallel' (the chain scans) or 'aba_jvp'")

    def _run(self, name, named, count):
        """The extension's call `name` on the named arrays (q, qd, tau first) with count
        new (B, nv) results; returns them."""
        arrays, _ = _inputs(named, self._dtype)
        where = _where(arrays[0])
        if where.cuda is not None:
            raise DeviceError(_on_cuda_message(where.cuda))
        handed = [_handover(a, n, where) for (n, _), a in zip(named, arrays)]
        outs = [_empty(where, _lead_of(arrays[0]) + (self._nv,), self._dtype) for _ in range(count)]
        try:
            status = getattr(self._e, name)(*handed, *(_writable(o, where) for o in outs))
        except TypeError as e:
            _reraise(e)
        self._settle(status, where, None, True)
        return tuple(outs)

    def jvp(self, q, qd, tau, dq, dqd, dtau):
        """(qdd, dqdd), (B, nv) each ((nv,) for one state): qdd = FD(q, qd, tau) and
        dqdd = dqdd/dq dq + dqdd/dqd dqd + M^-1 dtau."""
        return self._run("jvp", [("q", q), ("qd", qd), ("tau", tau), ("dq", dq), ("dqd", dqd), ("dtau", dtau)], 2)

    def vjp(self, q, qd, tau, w):
        """(qdd, gq, gqd, gtau), (B, nv) each ((nv,) for one state): qdd = FD(q, qd, tau)
        and, for the weight w on qdd, gq = (dqdd/dq)^T w, gqd = (dqdd/dqd)^T w, gtau =
        M^-1 w (M symmetric)."""
        return self._run("vjp", [("q", q), ("qd", qd), ("tau", tau), ("w", w)], 4)


def _on_cuda_message(device):
    return (f"the arrays are on CUDA device {device}, but the directional derivatives of forward dynamics take "
            "host arrays (NumPy, CPU tensors) on every backend (backend 'cuda' copies them to its device and back)")


def _directional(model, named, backend, method):
    """The cached FdDirectional engine for a call on the named arrays (q first)."""
    arrays, _ = _inputs(named)
    q = arrays[0]
    device = _cuda_device(q, _kind(q), "q")
    if device is not None:
        raise DeviceError(_on_cuda_message(device))
    return _cached(FdDirectional, method, model, backend, q, method=method), arrays


# ---- the derivatives as functions ---------------------------------------------------


def id_derivatives(model, q, qd, qdd, backend="auto", stream=None):
    """(dtau/dq, dtau/dqd, M) of tau = ID(q, qd, qdd), gravity included: (B, nv, nv)
    each for (B, nv) inputs ((nv, nv) for (nv,)); entry [..., i, j] = d tau_i / d x_j.
    Arrays of the inputs' kind on their device: host arrays (NumPy, CPU torch) on the
    host backends, CUDA arrays (torch, CuPy, JAX on a GPU; backend 'auto' follows them)
    on their device, queued on ``stream`` (default: the array library's current one).
    The engine is cached per model (IdDerivatives)."""
    (q, qd, qdd), _ = _inputs([("q", q), ("qd", qd), ("qdd", qdd)])
    return _cached(IdDerivatives, None, model, backend, q)(q, qd, qdd, stream=stream)


def id_second_derivatives(model, q, qd, qdd, backend="auto", stream=None):
    """The second derivatives of tau = ID(q, qd, qdd), gravity included: an
    IdSecondDerivativesResult (d2tau_dq2, d2tau_dqd2, d2tau_dqdqd, dM_dq), (B, nv, nv,
    nv) each for (B, nv) inputs ((nv, nv, nv) for (nv,)); entry [..., i, j, k] =
    d^2 tau_i / dx_j dy_k (x, y: q, q; qd, qd; q, qd), and dM_dq[..., i, j, k] = d M_ij
    / dq_k. Host or CUDA arrays as id_derivatives; models of 1-DoF joints. The engine is
    cached per model (IdSecondDerivatives)."""
    (q, qd, qdd), _ = _inputs([("q", q), ("qd", qd), ("qdd", qdd)])
    return _cached(IdSecondDerivatives, None, model, backend, q)(q, qd, qdd, stream=stream)


def fd_derivatives(model, q, qd, tau, backend="auto", stream=None, check=None):
    """(qdd, dqdd/dq, dqdd/dqd, dqdd/dtau = M^-1) of qdd = FD(q, qd, tau) by the ABA,
    on host or CUDA arrays as id_derivatives. ForwardDynamicsError for an instance whose
    pivot fails; on CUDA arrays that check waits for the stream (check=None: yes);
    check=False only queues the work (failures unreported: use FdDerivatives.check())."""
    (q, qd, tau), _ = _inputs([("q", q), ("qd", qd), ("tau", tau)])
    engine = _cached(FdDerivatives, None, model, backend, q)
    return engine(q, qd, tau, stream=stream, check=check is None or bool(check))


def fd_jvp(model, q, qd, tau, dq, dqd, dtau, backend="auto", method="auto"):
    """(qdd, dqdd) of qdd = FD(q, qd, tau): dqdd = dqdd/dq dq + dqdd/dqd dqd + M^-1 dtau,
    O(nv) per instance (no nv x nv matrix). Every array (B, nv) or (nv,) (q: (B, nq) or
    (nq,); dq a tangent with multi-DoF joints, FdDirectional), results (B, nv) or (nv,);
    host arrays (NumPy, CPU torch) only, float32 or float64 (q's dtype).
    ``backend``, ``method``: as FdDirectional (whose engine is cached per model).
    ForwardDynamicsError for an instance whose pivot fails."""
    engine, a = _directional(model, [("q", q), ("qd", qd), ("tau", tau), ("dq", dq), ("dqd", dqd), ("dtau", dtau)],
                             backend, method)
    return engine.jvp(*a)


def fd_vjp(model, q, qd, tau, w, backend="auto", method="auto"):
    """(qdd, gq, gqd, gtau) of qdd = FD(q, qd, tau) for the weight w on qdd: gq =
    (dqdd/dq)^T w, gqd = (dqdd/dqd)^T w, gtau = M^-1 w, O(nv) per instance. Shapes,
    arrays and errors as fd_jvp."""
    engine, a = _directional(model, [("q", q), ("qd", qd), ("tau", tau), ("w", w)], backend, method)
    return engine.vjp(*a)


_SEQUENCES = ("tau", "gq", "gqd", "dtau")  # (T, B, nv) arguments of the rollout calls


def _quat_matrix(v, w):
    """The rotation matrices (..., 3, 3) of unit quaternions (x, y, z) = v (..., 3), w
    (..., 1): base-frame vectors into the world (scandyn's quat_to_matrix)."""
    x, y, z, w = v[..., 0], v[..., 1], v[..., 2], w[..., 0]
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                     np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                     np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)


class StepDerivatives:
    """The derivatives of one scene's simulator step and of its rollouts (the scene's
    model, effects, integrator and dt; its instances and initial state are not used).
    ``scene``: a scene file's path or a dict of its keys (as scandyn.Simulator). dtype:
    float64 (default) or float32: every array of a call has it. Covered: euler, rk4,
    implicit; gravity, damping, springs, limits, external wrenches (constant); revolute
    and prismatic joints everywhere, and multi-DoF joints (a floating base, spherical
    joints: ``"base": "floating"``, ``ballrope:N``) on host arrays (serial, openmp);
    contacts, prescribed motion, loops, and multi-DoF joints on CUDA raise BackendError
    naming them.

    Multi-DoF joints: q has nq entries (quaternions), qd and tau nv. The Jacobian's q
    rows and columns, rollout_vjp's gq (in) and gq0 (out) and rollout_jvp's dq0 and dq
    are nv-dimensional tangents of local increments, q ⊕ d = q exp(d) per joint (a free
    joint's d = [w; v]: quat (x) Exp(w), p + R v; docs/derivatives.md).
    ``tangent_gradient`` and ``ambient_gradient`` map gradients between q's nq
    coordinates and the tangent (what torch_step, torch_rollout and jax_rollout do).

    Where the calls run: host arrays on ``backend`` ('auto': openmp or serial; 'cuda':
    the CUDA engines' host calls, copies in and out); CUDA arrays (torch, CuPy, JAX on a
    GPU) on their own device (backend 'auto' or 'cuda'; the device's engines are made on
    first use), queued on ``stream`` (default: the array library's current stream), no
    copy. Results are arrays of the inputs' kind on their device. A CUDA call's failed
    instances are found by waiting for the stream and reading their (B,) failed DoFs:
    ``check`` (default True; per call check=) does that and raises BackendError as a
    host call does; check=False only queues the work (a failed instance's results are
    then not meaningful and nothing reports it)."""

    def __init__(self, scene, backend="auto", dtype=np.float64, check=True):
        if isinstance(scene, dict):
            scene = dict(scene)
            if isinstance(scene.get("model"), str):
                scene["model"] = resolve_model_spec(scene["model"])
            text, source, base = json.dumps(scene, allow_nan=False), "<scene dict>", os.getcwd()
        else:
            path = os.fspath(scene)
            with open(path) as f:
                text = f.read()
            source, base = path, os.path.dirname(os.path.abspath(path))
        self.dtype = np.dtype(dtype)
        cls = {np.dtype(np.float64): _ext.StepDerivatives64, np.dtype(np.float32): _ext.StepDerivatives32}.get(self.dtype)
        if cls is None:
            raise DTypeError(f"dtype must be float32 or float64, got {self.dtype}")
        self._cls, self._scene, self._backend_asked = cls, (text, source, base), backend
        self.check = bool(check)
        self.last_status = None
        # the host calls' object, made now (a scene the derivatives do not cover is refused here)
        self._s = cls(text, source, base, "cuda" if backend == "cuda" else _backend(backend))
        self._by_device = {self._s.device: self._s} if self._s.backend == "cuda" else {}

    nv = property(lambda self: self._s.nv)
    nq = property(lambda self: self._s.nq, doc="rows of q (> nv with a floating base or spherical joints)")
    dt = property(lambda self: self._s.dt)

    def tangent_gradient(self, q, g):
        """The tangent gradient (..., nv) of a function of q whose gradient in q's nq
        coordinates is g (..., nq), at the configurations q (..., nq): E(q)^T g with E =
        d(q ⊕ d)/dd at d = 0 (a quaternion's 1/2 quat (x) (d, 0), a free joint's position
        R d_v). NumPy arrays (host)."""
        q, g = np.asarray(q), np.asarray(g)
        if self.nq == self.nv:
            return g
        out = np.zeros(q.shape[:-1] + (self.nv,), dtype=np.result_type(q, g))
        for kind, iq, iv in self._s.joints:
            if kind in ("revolute", "prismatic"):
                out[..., iv] = g[..., iq]
                continue
            k = iq + 3 if kind == "free" else iq
            pv, pw = q[..., k:k + 3], q[..., k + 3:k + 4]
            gv, gw = g[..., k:k + 3], g[..., k + 3:k + 4]
            out[..., iv:iv + 3] = 0.5 * (pw * gv - np.cross(pv, gv) - pv * gw)
            if kind == "free":
                out[..., iv + 3:iv + 6] = np.einsum("...ji,...j->...i", _quat_matrix(pv, pw), g[..., iq:iq + 3])
        return out

    def ambient_gradient(self, q, gt):
        """The gradient (..., nq) in q's coordinates of a function whose tangent gradient
        at the configurations q (..., nq, unit quaternions) is gt (..., nv): P(q)^T gt
        with P the derivative of the inverse retraction log(q^-1 q~) at q~ = q (a
        quaternion's d = 2 vec(conj(quat) (x) dquat), a free joint's R^T dp); the
        component along each quaternion is zero. NumPy arrays (host)."""
        q, gt = np.asarray(q), np.asarray(gt)
        if self.nq == self.nv:
            return gt
        out = np.zeros(q.shape[:-1] + (self.nq,), dtype=np.result_type(q, gt))
        for kind, iq, iv in self._s.joints:
            if kind in ("revolute", "prismatic"):
                out[..., iq] = gt[..., iv]
                continue
            k = iq + 3 if kind == "free" else iq
            pv, pw = q[..., k:k + 3], q[..., k + 3:k + 4]
            gr = gt[..., iv:iv + 3]
            out[..., k:k + 3] = 2 * (pw * gr + np.cross(pv, gr))
            out[..., k + 3] = -2 * np.sum(pv * gr, axis=-1)
            if kind == "free":
                out[..., iq:iq + 3] = np.einsum("...ij,...j->...i", _quat_matrix(pv, pw), gt[..., iv + 3:iv + 6])
        return out
    backend = property(lambda self: self._s.backend, doc="the backend of host calls")

    def _ext_for(self, where):
        if where.cuda is None:
            return self._s
        s = self._by_device.get(where.cuda)
        if s is None:
            if self._backend_asked not in ("auto", "cuda"):
                raise DeviceError(f"the arrays are on CUDA device {where.cuda}, but these step derivatives were made "
                                  f"with backend={self._backend_asked!r}: make them with backend='cuda' or 'auto'")
            s = self._cls(*self._scene, "cuda", where.cuda)
            self._by_device[where.cuda] = s
        return s

    def _begin(self, named, stream, sequences=_SEQUENCES):
        """(where, the arrays with a batch dimension, their hand-over, ext object, single):
        one state ((nv,) states, (T, nv) sequences: the names in sequences) runs as a batch
        of one."""
        arrays, _ = _inputs(named, self.dtype.name)
        single = len(getattr(arrays[0], "shape", ())) == 1
        if single:
            arrays = [a[:, None] if n in sequences else a[None] for (n, _), a in zip(named, arrays)]
        where = _where(arrays[0], stream)
        handed = [_handover(a, n, where) for (n, _), a in zip(named, arrays)]
        return where, arrays, handed, self._ext_for(where), single

    def _new(self, where, *shapes):
        outs = [_empty(where, s, self.dtype.name) for s in shapes]
        return outs, [_writable(o, where) for o in outs]

    def _failed(self, where, batch):
        """A CUDA call's (B,) int32 failed-DoF array on the device and its hand-over."""
        if where.cuda is None:
            return None, None
        f = _empty(where, (batch,), "int32")
        return f, _writable(f, where)

    def _settle(self, status, where, failed, check, what):
        if status.queued:
            check = self.check if check is None else bool(check)
            if check or where.kind == "jax":
                _ext.synchronize_stream(where.stream)  # JAX is handed its results once they are done
            if not check:
                return
            status = _ext.status_of_step_failures(_host_int32(failed))
        self.last_status = status
        if not status.ok:
            raise BackendError(f"the {what} failed: {status.message}")

    @staticmethod
    def _unbatch(single, outs, sequences):
        if not single:
            return tuple(outs)
        return tuple(o[:, 0] if seq else o[0] for o, seq in zip(outs, sequences))

    def jacobian(self, q, qd, tau, stream=None, check=None):
        """(q', qd', J): the step from (q, qd) under tau, and J = d(q', qd') / d(q, qd,
        tau), (B, 2 nv, 3 nv) (rows q', qd'; columns q, qd, tau; q's as tangents for
        multi-DoF joints, q' (B, nq)). On a CUDA device J is an entry-major view (torch,
        CuPy; as the mass matrix's)."""
        where, arrays, h, s, single = self._begin([("q", q), ("qd", qd), ("tau", tau)], stream, sequences=())
        n, B, dt = self.nv, arrays[0].shape[0], self.dtype.name
        (qn, qdn), (wqn, wqdn) = self._new(where, (B, self.nq), (B, n))
        blocks = wblocks = None
        transpose = False
        if where.cuda is None:
            J = _empty(where, (B, 2 * n, 3 * n), dt)
        else:
            J = _entry_major(arrays[0], 2 * n, 3 * n, dt)
            if J is None:  # no strides (JAX): the same memory as a (2 nv, 3 nv, B) array, transposed after
                J, transpose = _empty(where, (2 * n, 3 * n, B), dt), True
            blocks = _empty(where, (6 * n * n * B,), dt)
            wblocks = _writable(blocks, where)
        failed, wf = self._failed(where, B)
        try:
            status = s.jacobian(*h, wqn, wqdn, _writable(J, where), wblocks, wf, where.stream or 0)
        except TypeError as e:
            _reraise(e)
        self._settle(status, where, failed, check, "step derivatives")
        del blocks  # the stream-ordered allocators keep it until the copies ran
        if transpose:
            J = J.transpose((2, 0, 1))
        return self._unbatch(single, (qn, qdn, J), (False, False, False))

    def rollout(self, q0, qd0, tau, stream=None, check=None):
        """(q, qd), (T, B, nq) and (T, B, nv): the states after each of the T steps of tau
        (T, B, nv) from (q0 (B, nq), qd0 (B, nv)) (one state: (nq,), (nv,) and (T, nv) give
        (T, nq), (T, nv))."""
        return self._rollout_call("rollout", [("q0", q0), ("qd0", qd0), ("tau", tau)], (True, True),
                                  "rollout", stream, check, widths=(self.nq, self.nv))

    def rollout_vjp(self, q0, qd0, tau, gq, gqd, stream=None, check=None):
        """(gq0, gqd0, gtau): the gradient of a loss L with dL/dq_t = gq, dL/dqd_t = gqd
        (T, B, nv), by the adjoint recursion (checkpointed: O(sqrt(T)) states kept)."""
        return self._rollout_call("vjp", [("q0", q0), ("qd0", qd0), ("tau", tau), ("gq", gq), ("gqd", gqd)],
                                  (False, False, True), "rollout derivatives", stream, check)

    def rollout_jvp(self, q0, qd0, tau, dq0, dqd0, dtau, stream=None, check=None):
        """(dq, dqd), each (T, B, nv): the trajectory's tangent along (dq0, dqd0, dtau)."""
        return self._rollout_call(
            "jvp", [("q0", q0), ("qd0", qd0), ("tau", tau), ("dq0", dq0), ("dqd0", dqd0), ("dtau", dtau)],
            (True, True), "rollout derivatives", stream, check)

    def _rollout_call(self, method, named, per_step, what, stream, check, widths=None):
        """One of the extension's rollout calls (method: "rollout", "vjp", "jvp") on the
        named arrays (q0, qd0, tau first); per_step: for each result, True for (T, B, w),
        False for (B, w), w its entry of widths (default nv)."""
        where, arrays, h, s, single = self._begin(named, stream)
        T, B = arrays[2].shape[0], arrays[0].shape[0]
        widths = widths or (self.nv,) * len(per_step)
        outs, w = self._new(where, *[(T, B, n) if p else (B, n) for p, n in zip(per_step, widths)])
        failed, wf = self._failed(where, B)
        try:
            status = getattr(s, method)(*h, *w, wf, where.stream or 0)
        except TypeError as e:
            _reraise(e)
        self._settle(status, where, failed, check, what)
        return self._unbatch(single, outs, per_step)


# ---- torch.autograd.Function --------------------------------------------------------

_TORCH = {}


def _torch_functions():
    if _TORCH:
        return _TORCH
    import torch

    def vec_mat(g, m):  # g^T m over the leading dimensions: (..., n) x (..., n, k) -> (..., k)
        return torch.einsum("...i,...ij->...j", g, m)

    def zeros_for(t, ref):  # a tangent torch passes as None: zeros
        return torch.zeros_like(ref) if t is None else t

    def opaque(fn):
        """A Function whose forward is fn(*args) (scandyn's engines on plain tensors) and
        which is not differentiated further: what backward and jvp call, so that the
        torch.func transforms (jvp, grad, vjp) hand scandyn plain tensors, not their
        wrappers (docs: extending torch.func)."""

        class Opaque(torch.autograd.Function):
            @staticmethod
            def forward(*args):
                return fn(*args)

            @staticmethod
            def setup_context(ctx, inputs, output):
                pass

        return Opaque.apply

    fd_vjp_op = opaque(lambda model, backend, q, qd, tau, w: fd_vjp(model, q, qd, tau, w.contiguous(),
                                                                     backend=backend)[1:])
    fd_jvp_op = opaque(lambda model, backend, q, qd, tau, dq, dqd, dtau: fd_jvp(
        model, q, qd, tau, dq.contiguous(), dqd.contiguous(), dtau.contiguous(), backend=backend)[1])

    def dense_jvp(derivatives, model, backend, q, qd, x, dq, dqd, dx):
        return sum(torch.einsum("...ij,...j->...i", m, t) for m, t in zip(derivatives(model, q, qd, x, backend),
                                                                         (dq, dqd, dx)))

    def dynamics_function(values, derivatives):
        """A Function (model, backend, q, qd, x) -> y = values(...) whose backward
        contracts g with derivatives(model, q, qd, x, backend) = (dy/dq, dy/dqd, dy/dx),
        both on the tensors' device (CUDA: torch's current stream)."""

        jvp_op = opaque(lambda *a: dense_jvp(derivatives, *a))
        vjp_op = opaque(lambda model, backend, q, qd, x, g: tuple(vec_mat(g, m) for m in derivatives(model, q, qd, x,
                                                                                                       backend)))

        class DynamicsFunction(torch.autograd.Function):
            @staticmethod
            def forward(model, backend, q, qd, x):
                return values(model, q, qd, x, backend=backend)

            @staticmethod
            def setup_context(ctx, inputs, output):  # (the torch.func transforms need this form)
                ctx.model, ctx.backend, q, qd, x = inputs
                ctx.save_for_backward(q, qd, x)
                ctx.save_for_forward(q, qd, x)

            @staticmethod
            def jvp(ctx, _model, _backend, dq, dqd, dx):  # forward mode: the sum of dy/dz dz
                q, qd, x = ctx.saved_tensors
                return jvp_op(ctx.model, ctx.backend, q, qd, x, zeros_for(dq, q), zeros_for(dqd, qd), zeros_for(dx, x))

            @staticmethod
            def backward(ctx, g):
                q, qd, x = ctx.saved_tensors
                grads = vjp_op(ctx.model, ctx.backend, q, qd, x, g)
                return (None, None) + tuple(t if need else None for t, need in zip(grads, ctx.needs_input_grad[2:]))

        return DynamicsFunction

    InverseDynamicsFunction = dynamics_function(_api.inverse_dynamics, id_derivatives)
    ForwardDynamicsFunction = dynamics_function(_api.forward_dynamics, lambda *a: fd_derivatives(*a)[1:])

    class DirectionalForwardDynamicsFunction(torch.autograd.Function):
        """qdd = FD(q, qd, tau) with backward fd_vjp (reverse mode) and jvp fd_jvp
        (forward mode: torch.func.jvp, torch.autograd.forward_ad): O(nv) per instance,
        no (nv, nv) matrix. Host tensors."""

        @staticmethod
        def forward(model, backend, q, qd, tau):
            return _api.forward_dynamics(model, q, qd, tau, backend=backend)

        @staticmethod
        def setup_context(ctx, inputs, output):
            ctx.model, ctx.backend, q, qd, tau = inputs
            ctx.save_for_backward(q, qd, tau)
            ctx.save_for_forward(q, qd, tau)

        @staticmethod
        def backward(ctx, g):
            q, qd, tau = ctx.saved_tensors
            grads = fd_vjp_op(ctx.model, ctx.backend, q, qd, tau, g)
            return (None, None) + tuple(x if need else None for x, need in zip(grads, ctx.needs_input_grad[2:]))

        @staticmethod
        def jvp(ctx, _model, _backend, dq, dqd, dtau):
            q, qd, tau = ctx.saved_tensors
            return fd_jvp_op(ctx.model, ctx.backend, q, qd, tau, zeros_for(dq, q), zeros_for(dqd, qd),
                             zeros_for(dtau, tau))

    def tangent_of(step, q, g):  # q's gradient (nq coordinates) -> its tangent (nv); host tensors
        if step.nq == step.nv:
            return g
        return torch.as_tensor(step.tangent_gradient(q.detach().cpu().numpy(), g.detach().cpu().numpy()),
                               dtype=g.dtype)

    def ambient_of(step, q, g):  # a tangent gradient at q (nv) -> q's nq coordinates
        if step.nq == step.nv:
            return g
        return torch.as_tensor(step.ambient_gradient(q.detach().cpu().numpy(), g.detach().cpu().numpy()),
                               dtype=g.dtype)

    class StepFunction(torch.autograd.Function):
        @staticmethod
        def forward(ctx, step, q, qd, tau):
            qn, qdn, J = step.jacobian(q, qd, tau)
            ctx.save_for_backward(J, q, qn)
            ctx.step = step
            return qn, qdn

        @staticmethod
        def backward(ctx, gq, gqd):
            J, q, qn = ctx.saved_tensors
            step, n = ctx.step, ctx.step.nv
            gz = vec_mat(torch.cat([tangent_of(step, qn, gq), gqd], dim=-1), J)
            return None, ambient_of(step, q, gz[..., :n]), gz[..., n:2 * n], gz[..., 2 * n:]

    class RolloutFunction(torch.autograd.Function):
        @staticmethod
        def forward(ctx, step, q0, qd0, tau):
            ctx.step = step
            qs, qds = step.rollout(q0, qd0, tau)
            ctx.save_for_backward(q0, qd0, tau, qs)
            return qs, qds

        @staticmethod
        def backward(ctx, gq, gqd):
            q0, qd0, tau, qs = ctx.saved_tensors
            step = ctx.step
            gq0, gqd0, gtau = step.rollout_vjp(q0, qd0, tau, tangent_of(step, qs, gq).contiguous(), gqd)
            return None, ambient_of(step, q0, gq0), gqd0, gtau

    _TORCH.update(id=InverseDynamicsFunction, fd=ForwardDynamicsFunction, fd_directional=DirectionalForwardDynamicsFunction,
                  step=StepFunction, rollout=RolloutFunction)
    return _TORCH


def torch_inverse_dynamics(model, q, qd, qdd, backend="auto"):
    """tau = ID(q, qd, qdd) on CPU or CUDA tensors, differentiable (backward: id_derivatives,
    on the tensors' device)."""
    return _torch_functions()["id"].apply(model, backend, q, qd, qdd)


def _fd_derivatives_route(model, on_cuda, derivatives):
    """'dense' or 'directional': how the differentiable forward dynamics differentiate
    (see torch_forward_dynamics)."""
    if derivatives not in ("auto", "dense", "directional"):
        raise ValueError(f"derivatives={derivatives!r}: expected 'auto', 'dense' or 'directional'")
    if derivatives != "auto":
        return derivatives
    return "dense" if on_cuda or model.nq != model.nv else "directional"


def torch_forward_dynamics(model, q, qd, tau, backend="auto", derivatives="auto"):
    """qdd = FD(q, qd, tau) on CPU or CUDA tensors, differentiable. ``derivatives``:
    'dense': backward contracts the gradient with fd_derivatives' (nv, nv) matrices on the
    tensors' device; 'directional': backward is fd_vjp and forward mode (torch.func.jvp)
    fd_jvp, O(nv) per instance with no (nv, nv) matrix (host tensors; models of 1-DoF
    joints: a rope of 10^5 links); 'auto' (default): directional for host tensors of
    1-DoF-joint models (faster at every size measured, iiwa included: docs/derivatives.md),
    dense for CUDA tensors and multi-DoF joints."""
    route = _fd_derivatives_route(model, _cuda_device(q, _kind(q), "q") is not None, derivatives)
    return _torch_functions()["fd" if route == "dense" else "fd_directional"].apply(model, backend, q, qd, tau)


def torch_step(step, q, qd, tau):
    """(q', qd') = one simulator step of ``step`` (a StepDerivatives), differentiable
    (backward: the step's Jacobian)."""
    return _torch_functions()["step"].apply(step, q, qd, tau)


def torch_rollout(step, q0, qd0, tau):
    """(q, qd), (T, B, nq) and (T, B, nv) (or (T, nq), (T, nv)): T simulator steps under
    tau (T, B, nv), differentiable (backward: the rollout's adjoint,
    StepDerivatives.rollout_vjp; CUDA tensors: the CUDA adjoint on their device, torch's
    current stream). With multi-DoF joints (host tensors) q's gradients are mapped to
    the tangent (StepDerivatives.tangent_gradient) before the adjoint and q0's back to
    its nq coordinates after (ambient_gradient: zero along each quaternion)."""
    return _torch_functions()["rollout"].apply(step, q0, qd0, tau)


# ---- jax.custom_vjp -----------------------------------------------------------------


def _jax_dynamics(values, derivatives, out_dim):
    """A jax.custom_vjp function f(q, qd, x) -> y of shape (..., out_dim): values(q, qd,
    x) and derivatives(q, qd, x) -> (dq, dqd, dx) (..., out_dim, n) are NumPy callbacks."""
    import jax
    import jax.numpy as jnp

    def shape(q, *tail):
        return jax.ShapeDtypeStruct(q.shape[:-1] + tail, q.dtype)

    @jax.custom_vjp
    def f(q, qd, x):
        return jax.pure_callback(lambda a, b, c: np.asarray(values(a, b, c), a.dtype), shape(q, out_dim), q, qd, x)

    def fwd(q, qd, x):
        return f(q, qd, x), (q, qd, x)

    def bwd(res, g):
        q, qd, x = res
        mats = jax.pure_callback(lambda a, b, c: tuple(np.asarray(m, a.dtype) for m in derivatives(a, b, c)),
                                 (shape(q, out_dim, q.shape[-1]), shape(q, out_dim, qd.shape[-1]),
                                  shape(q, out_dim, x.shape[-1])), q, qd, x)
        return tuple(jnp.einsum("...i,...ij->...j", g, m) for m in mats)

    f.defvjp(fwd, bwd)
    return f


def jax_inverse_dynamics(model, q, qd, qdd, backend="auto"):
    """tau = ID(q, qd, qdd) for JAX arrays (CPU), differentiable by jax.grad / jax.vjp."""
    f = _jax_dynamics(lambda a, b, c: _api.inverse_dynamics(model, a, b, c, backend=_backend(backend)),
                      lambda a, b, c: id_derivatives(model, a, b, c, backend), model.nv)
    return f(q, qd, qdd)


def _jax_directional_fd(model, backend):
    """qdd = FD(q, qd, tau) as a jax.custom_vjp whose backward is fd_vjp (O(nv), no
    (nv, nv) matrix): NumPy callbacks, host memory."""
    import jax

    def shape(q):
        return jax.ShapeDtypeStruct(q.shape, q.dtype)

    @jax.custom_vjp
    def f(q, qd, tau):
        return jax.pure_callback(
            lambda a, b, c: np.asarray(_api.forward_dynamics(model, a, b, c, backend=_backend(backend)), a.dtype),
            shape(q), q, qd, tau)

    def fwd(q, qd, tau):
        return f(q, qd, tau), (q, qd, tau)

    def bwd(res, g):
        q, qd, tau = res
        return jax.pure_callback(
            lambda a, b, c, w: tuple(np.asarray(x, a.dtype) for x in fd_vjp(model, a, b, c, np.ascontiguousarray(w),
                                                                             backend=backend)[1:]),
            (shape(q), shape(qd), shape(tau)), q, qd, tau, g)

    f.defvjp(fwd, bwd)
    return f


def jax_forward_dynamics(model, q, qd, tau, backend="auto", derivatives="auto"):
    """qdd = FD(q, qd, tau) for JAX arrays (CPU), differentiable by jax.grad / jax.vjp.
    ``derivatives``: 'dense' (fd_derivatives' matrices), 'directional' (fd_vjp, O(nv),
    models of 1-DoF joints) or 'auto' (directional for 1-DoF-joint models, else dense), as
    torch_forward_dynamics."""
    if _fd_derivatives_route(model, False, derivatives) == "directional":
        return _jax_directional_fd(model, backend)(q, qd, tau)
    f = _jax_dynamics(lambda a, b, c: _api.forward_dynamics(model, a, b, c, backend=_backend(backend)),
                      lambda a, b, c: fd_derivatives(model, a, b, c, backend)[1:], model.nv)
    return f(q, qd, tau)


def jax_rollout(step, q0, qd0, tau):
    """(q, qd) (T, B, nq) and (T, B, nv) of T simulator steps for JAX arrays (CPU),
    differentiable (the rollout's adjoint; with multi-DoF joints q's gradients pass
    through StepDerivatives.tangent_gradient / ambient_gradient)."""
    import jax

    out_q = jax.ShapeDtypeStruct(tau.shape[:1] + q0.shape, q0.dtype)
    out_qd = jax.ShapeDtypeStruct(tau.shape[:1] + qd0.shape, qd0.dtype)

    @jax.custom_vjp
    def f(q0, qd0, tau):
        return jax.pure_callback(lambda a, b, c: step.rollout(a, b, c), (out_q, out_qd), q0, qd0, tau)

    def fwd(q0, qd0, tau):
        qs, qds = f(q0, qd0, tau)
        return (qs, qds), (q0, qd0, tau, qs)

    def vjp(a, b, c, qs, d, e):
        d = np.ascontiguousarray(step.tangent_gradient(qs, d), dtype=a.dtype)
        gq0, gqd0, gtau = step.rollout_vjp(a, b, c, d, e)
        return np.asarray(step.ambient_gradient(a, gq0), a.dtype), gqd0, gtau

    def bwd(res, g):
        q0, qd0, tau, qs = res
        return jax.pure_callback(vjp,
                                 (jax.ShapeDtypeStruct(q0.shape, q0.dtype), jax.ShapeDtypeStruct(qd0.shape, qd0.dtype),
                                  jax.ShapeDtypeStruct(tau.shape, tau.dtype)), q0, qd0, tau, qs, g[0], g[1])

    f.defvjp(fwd, bwd)
    return f(q0, qd0, tau)


__all__ = [
    "FdDerivatives", "FdDirectional", "IdDerivatives", "IdSecondDerivatives", "IdSecondDerivativesResult",
    "StepDerivatives", "fd_derivatives", "fd_jvp", "fd_vjp", "id_derivatives", "id_second_derivatives", "jax_forward_dynamics", "jax_inverse_dynamics",
    "jax_rollout", "torch_forward_dynamics", "torch_inverse_dynamics", "torch_rollout", "torch_step",
]
